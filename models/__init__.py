"""Registration models and their registry.

Every model maps a :class:`linereg.structures.PairBatch` to a
:class:`linereg.structures.RegistrationOutput`. Importing this package registers ``dcp_v1``,
``dcp_v2``, ``rpmnet`` and ``fmr`` in :data:`MODELS`; ``MODELS.build({name: ..., **kwargs})``
creates one, :func:`load_model` restores a trained one from a checkpoint of ``python -m train``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from linereg.checkpoint import load_checkpoint
from linereg.models import dcp, fmr, rpmnet
from linereg.models.base import MODELS

__all__ = ["MODELS", "dcp", "fmr", "load_model", "rpmnet"]


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[nn.Module, dict[str, Any]]:
    """The model of a checkpoint, rebuilt from its stored config, in evaluation mode.

    Args:
        path: checkpoint file or run folder (``best.pt`` preferred).
        device: where to put the model.

    Returns:
        ``(model, checkpoint)``; ``checkpoint["config"]`` is the run's resolved config.
    """
    state = load_checkpoint(path)
    model = MODELS.build(state["config"]["model"])
    model.load_state_dict(state["model"])
    return model.to(device).eval(), state
