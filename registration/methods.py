"""Registration methods for one pair of clouds: one interface, one registry.

Every method (the optimisation-based registration with any loss, and the classical
baselines) is a callable ``method(src, tgt, src_normals=None, tgt_normals=None)`` on numpy
``(N, 3)`` / ``(M, 3)`` clouds returning a :class:`MethodResult` whose ``transform`` maps the
source onto the target (``tgt ≈ R @ src + t``). Build one with
``METHODS.build({"name": ..., **kwargs})``.

Fairness: by default every method sees both clouds translated to their centroids
(:func:`run_centered`), and the translation is folded back into the returned transform, so
methods that do not centre internally are not handicapped by the initial offset. An initial
guess is applied to the source in one place, :func:`run_with_init`, and is part of the result.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from linereg.checks import check_points
from linereg.registration.robust_result import RobustResult
from linereg.registry import Registry


@dataclass
class MethodResult:
    """Outcome of one registration.

    Attributes:
        transform: ``(4, 4)`` float64 source-to-target transform.
        seconds: wall-clock time of the registration.
        info: method-specific extras that no typed record holds (loss curve, iterations,
            ``warnings``, ...).
        solution: the method's typed record, when it has one: the
            :class:`~linereg.registration.robust_result.RobustResult` of ``robust``.
    """

    transform: np.ndarray
    seconds: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    solution: RobustResult | None = None


Method = Callable[..., MethodResult]


class MethodRegistry(Registry[Method]):
    """The methods' registry; the torch solvers and the Open3D baselines register on first need.

    ``robust`` (numpy, :mod:`linereg.registration.robust`) is registered when the package is
    imported; a name not yet registered, or a listing, imports ``lazy_modules`` first, so that
    ``linereg.register`` with the default method does not import torch or Open3D.
    """

    lazy_modules = ("linereg.registration.solvers", "linereg.registration.baselines")

    def __init__(self, kind: str) -> None:
        super().__init__(kind)
        self._loaded = False

    def load_all(self) -> None:
        """Import every module that registers methods."""
        if not self._loaded:
            self._loaded = True
            for module in self.lazy_modules:
                importlib.import_module(module)

    def get(self, name: str) -> Method:
        if name not in self._builders:
            self.load_all()
        return super().get(name)

    def names(self, pattern: str = "*") -> list[str]:
        self.load_all()
        return super().names(pattern)

    def __contains__(self, name: str) -> bool:
        if name not in self._builders:
            self.load_all()
        return super().__contains__(name)


METHODS = MethodRegistry("registration method")


def translation(offset: np.ndarray) -> np.ndarray:
    """``(4, 4)`` float64 pure translation by ``offset (3,)``."""
    T = np.eye(4)
    T[:3, 3] = offset
    return T


def run_centered(
    solve: Callable[[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None], MethodResult],
    src: np.ndarray,
    tgt: np.ndarray,
    src_normals: np.ndarray | None = None,
    tgt_normals: np.ndarray | None = None,
    *,
    center: bool = True,
) -> MethodResult:
    """Validate the inputs, optionally centre both clouds, run ``solve`` and time it.

    ``solve`` receives the (centred) clouds and returns the transform between them; the result
    is mapped back to the original frames: ``T = T(c_tgt) @ T_centred @ T(-c_src)``.
    """
    check_points(src, "source", batched=False)
    check_points(tgt, "target", batched=False)
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    c_src = src.mean(axis=0) if center else np.zeros(3)
    c_tgt = tgt.mean(axis=0) if center else np.zeros(3)
    start = time.perf_counter()
    result = solve(src - c_src, tgt - c_tgt, src_normals, tgt_normals)
    seconds = time.perf_counter() - start
    transform = translation(c_tgt) @ np.asarray(result.transform, dtype=np.float64) @ translation(-c_src)
    return MethodResult(transform=transform, seconds=seconds, info=result.info, solution=result.solution)


def run_with_init(
    method: Method,
    src: np.ndarray,
    tgt: np.ndarray,
    src_normals: np.ndarray | None = None,
    tgt_normals: np.ndarray | None = None,
    init: np.ndarray | None = None,
) -> MethodResult:
    """Run ``method`` on the source moved by the initial guess ``init (4, 4)``.

    The one place where an initial guess is applied: the method sees ``init @ src`` (and the
    rotated normals) and the returned transform includes the guess, ``T = T_method @ init``.
    """
    if init is None:
        return method(src, tgt, src_normals, tgt_normals)
    moved = src @ init[:3, :3].T + init[:3, 3]
    normals = None if src_normals is None else src_normals @ init[:3, :3].T
    result = method(moved, tgt, normals, tgt_normals)
    transform = np.asarray(result.transform, dtype=np.float64) @ init
    return MethodResult(transform=transform, seconds=result.seconds, info=result.info, solution=result.solution)
