"""The ``register`` default's stage for doubtful pairs: global candidates and a dense judgement.

When the first round of :class:`~linereg.registration.robust.RobustRegistration` is doubtful
(partly overlapping scans, symmetric shapes), FPFH + RANSAC and FGR candidates
(:func:`~linereg.registration.features.global_candidates`) join the local ones, and every
candidate is judged against a *dense* target: up to ``GlobalOptions.dense_points`` FPS points of
the whole target instead of the solver's subset. On a room scanned at 1 cm, a subset of 2048
points is 6 cm apart; a wrong pose that slides the overlap along walls and floors then fits the
subset as well as the right one. Against the dense target each candidate gets a Welsch IRLS polish
down to ``dense_end`` dense spacings (:func:`dense_polish`) and the lowest fixed-scale Welsch
cost at ``select_spacings`` dense spacings (:func:`dense_costs`) chooses: one rule for every
candidate, whatever produced it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.registration.evaluation import assess_registration, point_spacing
from linereg.registration.poses import Poses, as_matrices
from linereg.registration.welsch import fixed_scale_cost, welsch_irls

if TYPE_CHECKING:
    from linereg.registration.robust_options import GlobalOptions


@dataclass(frozen=True)
class DenseTarget:
    """The target as the dense judgement sees it (in the solver's unit ball).

    Attributes:
        points: ``(M, 3)`` FPS points of the whole target.
        index: their nearest-neighbour index.
        spacing: their median nearest-neighbour distance.
    """

    points: np.ndarray
    index: NearestNeighbors
    spacing: float


def dense_target(tgt: np.ndarray, count: int) -> DenseTarget:
    """:class:`DenseTarget` of ``count`` FPS points of ``tgt (M, 3)`` (all of them when ``M <= count``)."""
    points = fps(tgt, count)
    index = NearestNeighbors(points)
    return DenseTarget(points, index, point_spacing(points, index))


def dense_polish(poses: Poses, src: np.ndarray, dense: DenseTarget, options: GlobalOptions) -> Poses:
    """Welsch IRLS of every pose of ``poses`` (``K``) with source points ``src (N, 3)`` against the
    dense target: ``dense_steps`` scales falling geometrically from ``dense_start`` to ``dense_end``
    dense spacings, then up to ``dense_settle`` steps at the last one."""
    scales = np.geomspace(options.dense_start, options.dense_end, options.dense_steps) * dense.spacing
    return welsch_irls(poses, src, dense.index, scales, options.dense_settle)


def dense_costs(poses: Poses, src: np.ndarray, dense: DenseTarget, options: GlobalOptions) -> np.ndarray:
    """``(K,)`` fixed-scale Welsch costs at ``select_spacings`` dense spacings: the selection rule."""
    return fixed_scale_cost(poses, src, dense.index, options.select_spacings * dense.spacing)


def dense_confident(poses: Poses, best: int, src: np.ndarray, dense: DenseTarget) -> bool:
    """Whether candidate ``best`` passes the confidence test of :func:`linereg.register`
    (:func:`~linereg.registration.evaluation.assess_registration`) against the dense target."""
    transform = as_matrices((poses[0][best : best + 1], poses[1][best : best + 1]))[0]
    return assess_registration(src, dense.points, transform).confident
