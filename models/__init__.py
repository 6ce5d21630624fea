"""Registration models and their registry.

Every model maps a :class:`linereg.structures.PairBatch` to a
:class:`linereg.structures.RegistrationOutput`. Importing this package registers ``dcp_v1``,
``dcp_v2``, ``rpmnet`` and ``fmr`` in :data:`MODELS`; ``MODELS.build({name: ..., **kwargs})``
creates one, :func:`load_model` restores a trained one from a checkpoint of ``python -m train``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from linereg.checkpoint import load_checkpoint
from linereg.models import dcp, fmr, rpmnet
from linereg.models.base import MODELS

__all__ = ["MODELS", "dcp", "fmr", "load_model", "rpmnet", "upgrade_run_config"]

# Model keys of older checkpoints that chose the iterate inside RPM-Net and FMR, and the keys of
# the run's ``iterate`` block that hold the same choice.
_ITERATE_MODEL_KEYS = ("keep_best_iterate", "fit_keep_fraction")


def upgrade_run_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """A stored run config in today's layout: iterate choices held by the model move to ``iterate``.

    Checkpoints of older linereg versions hold ``model.keep_best_iterate`` and
    ``model.fit_keep_fraction``; they become ``iterate: {rule: best_fit | last, keep_fraction}``
    (:mod:`linereg.registration.iterates`). A config without them is returned unchanged (a copy).

    Args:
        config: the ``config`` entry of a checkpoint.

    Returns:
        The config with a model section every model builds from.
    """
    upgraded = dict(config)
    model = dict(config.get("model") or {})
    if not any(key in model for key in _ITERATE_MODEL_KEYS):
        return upgraded
    keep_best, keep_fraction = (model.pop(key, None) for key in _ITERATE_MODEL_KEYS)
    upgraded["model"] = model
    if "iterate" not in upgraded:
        upgraded["iterate"] = {
            "rule": "best_fit" if keep_best else "last",
            "keep_fraction": 1.0 if keep_fraction is None else float(keep_fraction),
        }
    return upgraded


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[nn.Module, dict[str, Any]]:
    """The model of a checkpoint, rebuilt from its stored config, in evaluation mode.

    Args:
        path: checkpoint file or run folder (``best.pt`` preferred).
        device: where to put the model.

    Returns:
        ``(model, checkpoint)``; ``checkpoint["config"]`` is the run's resolved config
        (:func:`upgrade_run_config`: its ``iterate`` block says which iterate answers).
    """
    state = load_checkpoint(path)
    state["config"] = upgrade_run_config(state["config"])
    model = MODELS.build(state["config"]["model"])
    model.load_state_dict(state["model"])
    return model.to(device).eval(), state
