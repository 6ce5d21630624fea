"""Options of the line-intersection metric: every setting, the paper's defaults and the
``authors`` and ``linereg`` variants (see :mod:`linereg.losses.line_intersection` for their
meaning)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import torch

from . import line_kernels
from .lines import SAMPLERS

INTERSECTIONS = {
    "candidates": line_kernels.MODE_CANDIDATES,
    "convex": line_kernels.MODE_CONVEX,
    "triplet": line_kernels.MODE_TRIPLET,
    "pierce": line_kernels.MODE_PIERCE,
}
REDUCTIONS = ("lines", "groups")
WELSCH_INPUTS = ("distance", "squared")
BACKENDS = ("auto", "numba", "torch")
STAT_KEYS = (
    "lines",
    "lines_hit_both",
    "lines_hit_src",
    "lines_hit_tgt",
    "intersections_src",
    "intersections_tgt",
    "nu",
)

PAPER_DEFAULTS: dict[str, Any] = {
    "num_lines": 15000,
    "sampling": "sphere",
    "intersection": "convex",
    "k": 2,
    "delta_factor": math.sqrt(3.0) / 2.0,
    "nu0": 0.5,
    "line_weight": True,
    "welsch_input": "distance",
    "max_hits": None,
    "reduction": "lines",
    "radius_factor": 1.0,
    "distance_eps": 0.0,
    "cell_factor": 4.0,
    "nu": None,
    "detach_weights": True,
    "backend": "auto",
}
AUTHORS_OVERRIDES: dict[str, Any] = {
    "sampling": "authors",
    "intersection": "triplet",
    "welsch_input": "squared",
    "nu0": 1.0,
    "max_hits": 4,
    "reduction": "groups",
    "distance_eps": 2e-4,
}
LINEREG_OVERRIDES: dict[str, Any] = {"intersection": "pierce"}
VARIANTS = {"paper": {}, "authors": AUTHORS_OVERRIDES, "linereg": LINEREG_OVERRIDES}


@dataclass(frozen=True)
class LineMetricOptions:
    """Every setting of the metric (see the module docstring for their meaning)."""

    num_lines: int = PAPER_DEFAULTS["num_lines"]
    sampling: str = PAPER_DEFAULTS["sampling"]
    intersection: str = PAPER_DEFAULTS["intersection"]
    k: int = PAPER_DEFAULTS["k"]
    delta_factor: float = PAPER_DEFAULTS["delta_factor"]
    nu0: float = PAPER_DEFAULTS["nu0"]
    line_weight: bool = PAPER_DEFAULTS["line_weight"]
    welsch_input: str = PAPER_DEFAULTS["welsch_input"]
    max_hits: int | None = PAPER_DEFAULTS["max_hits"]
    reduction: str = PAPER_DEFAULTS["reduction"]
    radius_factor: float = PAPER_DEFAULTS["radius_factor"]
    distance_eps: float = PAPER_DEFAULTS["distance_eps"]
    cell_factor: float = PAPER_DEFAULTS["cell_factor"]
    nu: float | None = PAPER_DEFAULTS["nu"]
    detach_weights: bool = PAPER_DEFAULTS["detach_weights"]
    backend: str = PAPER_DEFAULTS["backend"]

    def __post_init__(self) -> None:
        choices = {
            "sampling": SAMPLERS,
            "intersection": tuple(INTERSECTIONS),
            "reduction": REDUCTIONS,
            "welsch_input": WELSCH_INPUTS,
            "backend": BACKENDS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        for name in ("num_lines", "k"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        positive = {
            "delta_factor": self.delta_factor,
            "nu0": self.nu0,
            "radius_factor": self.radius_factor,
            "cell_factor": self.cell_factor,
        }
        for name, value in positive.items():
            if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if self.max_hits is not None and self.max_hits < 1:
            raise ValueError(f"max_hits must be >= 1 or None, got {self.max_hits}")
        if self.intersection == "pierce" and self.k != 2:
            raise ValueError(f"intersection 'pierce' intersects triangles and needs k=2, got k={self.k}")
        if self.nu is not None and not (math.isfinite(self.nu) and self.nu > 0):
            raise ValueError(f"nu must be a finite number > 0 or None, got {self.nu}")
        if not (math.isfinite(self.distance_eps) and self.distance_eps >= 0):
            raise ValueError(f"distance_eps must be a finite number >= 0, got {self.distance_eps}")

    @classmethod
    def for_variant(cls, variant: str = "paper", **overrides: Any) -> LineMetricOptions:
        """Options of ``variant`` (``paper``, ``authors`` or ``linereg``) with ``overrides`` on top."""
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
        return cls(**{**VARIANTS[variant], **overrides})

    def resolved_backend(self, device: torch.device) -> str:
        """``numba`` or ``torch``: ``auto`` takes ``torch`` for tensors that are not on the CPU."""
        if self.backend != "auto":
            return self.backend
        return "numba" if device.type == "cpu" else "torch"
