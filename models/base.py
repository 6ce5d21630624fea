"""The model registry, filled by the model modules (``dcp``, ``fmr``, ``rpmnet``) when imported."""

from __future__ import annotations

from torch import nn

from linereg.registry import Registry

MODELS: Registry[nn.Module] = Registry("model")
