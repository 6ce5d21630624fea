"""Optimiser and per-stage scheduler registries of the training loop (``configs/optimizer``, ``configs/scheduler``).

``OPTIMIZERS.build({name: adam|adamw|sgd, lr: ..., **torch arguments}, parameters)``;
``SCHEDULERS.build({name: constant|cosine|step, ...}, optimizer, epochs=<epochs of the stage>)``
(``None`` for ``constant``).
"""

from __future__ import annotations

from typing import Any

import torch

from linereg.registry import Registry

OPTIMIZERS: Registry[torch.optim.Optimizer] = Registry("optimizer")
OPTIMIZERS.register("adam")(torch.optim.Adam)
OPTIMIZERS.register("adamw")(torch.optim.AdamW)
OPTIMIZERS.register("sgd")(torch.optim.SGD)

SCHEDULERS: Registry[Any] = Registry("scheduler")


@SCHEDULERS.register("constant")
def _constant(optimizer: torch.optim.Optimizer, *, epochs: int) -> None:
    """No schedule: the stage's learning rate throughout."""
    return None


@SCHEDULERS.register("cosine")
def _cosine(optimizer: torch.optim.Optimizer, *, epochs: int, min_lr_scale: float = 0.01):
    """Cosine decay over the stage's epochs down to ``min_lr_scale`` x its learning rate."""
    lr = optimizer.param_groups[0]["lr"]
    return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(epochs, 1), eta_min=lr * min_lr_scale)


@SCHEDULERS.register("step")
def _step(optimizer: torch.optim.Optimizer, *, epochs: int, step_size: int = 10, gamma: float = 0.5):
    """Multiply the learning rate by ``gamma`` every ``step_size`` epochs of the stage."""
    return torch.optim.lr_scheduler.StepLR(optimizer, step_size=step_size, gamma=gamma)
