"""Loss registry: the line-intersection metric, Chamfer (CD), Welsch-Chamfer (CD-W) and the
backbones' supervised losses. ``build_loss({"name": ..., **kwargs})`` builds any of them."""

from . import chamfer, line_intersection, supervised
from .base import LOSSES, AlignmentLoss, Loss, WeightedSum, build_loss, iteration_weights, set_training_progress

__all__ = [
    "LOSSES",
    "AlignmentLoss",
    "Loss",
    "WeightedSum",
    "build_loss",
    "chamfer",
    "iteration_weights",
    "line_intersection",
    "set_training_progress",
    "supervised",
]
