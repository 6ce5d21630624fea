"""The ``register`` default's stage for doubtful scans: the dense check, global candidates and a dense judgement.

When the first round of :class:`~linereg.registration.robust.RobustRegistration` is doubtful on a
target with more points than the solver's subset (partly overlapping scans), its candidates are
judged against a *dense* target: up to ``GlobalOptions.dense_points`` FPS points of the whole
target instead of the solver's subset. On a room scanned at 1 cm, a subset of 2048 points is 6 cm
apart; a wrong pose that slides the overlap along walls and floors then fits the subset as well as
the right one. Against the dense target each candidate gets a Welsch IRLS polish down to
``dense_end`` dense spacings (:func:`dense_polish`) and the lowest fixed-scale Welsch cost at that
last scale (:func:`dense_costs`) chooses: one rule for every candidate, whatever produced it.

That judgement of the first round's candidates alone is the *dense check*: its choice is
doubtful (:func:`dense_doubt`) when it fails the confidence test of :func:`linereg.register`
against the dense target or a distinct rival scores nearly as well. A partly overlapping scan
always fails the subset's fitness test; the dense check keeps the right answers and sends the
wrong ones on (``docs/studies/doubt-test.md`` measures how often each rule errs), and only a
doubtful check brings FPFH + RANSAC and FGR candidates
(:class:`~linereg.registration.features.FeatureMatcher`), one at a time, until the choice passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.registration.evaluation import inlier_test, passes_inlier_test, point_spacing
from linereg.registration.poses import Poses, as_matrices, rotation_gap_deg
from linereg.registration.welsch import fixed_scale_cost, welsch_irls

if TYPE_CHECKING:
    from linereg.registration.robust_options import GlobalOptions, SelectOptions


@dataclass(frozen=True)
class DenseTarget:
    """The target as the dense judgement sees it (in the solver's unit ball).

    Attributes:
        points: ``(M, 3)`` FPS points of the whole target.
        index: their nearest-neighbour index.
        spacing: their median nearest-neighbour distance.
        scale: the last Welsch scale of the dense polish and the scale of the selection cost.
    """

    points: np.ndarray
    index: NearestNeighbors
    spacing: float
    scale: float


def dense_target(tgt: np.ndarray, options: GlobalOptions, finest: float) -> DenseTarget:
    """:class:`DenseTarget` of ``dense_points`` FPS points of ``tgt (M, 3)`` (all of them when fewer);
    its scale is ``dense_end`` dense spacings, or ``finest`` (the polish's last scale) if smaller:
    a target no denser than the solver's subset keeps the precision of the polish."""
    points = fps(tgt, options.dense_points)
    index = NearestNeighbors(points)
    spacing = point_spacing(points, index)
    return DenseTarget(points, index, spacing, min(options.dense_end * spacing, finest))


def dense_polish(poses: Poses, src: np.ndarray, dense: DenseTarget, options: GlobalOptions) -> Poses:
    """Welsch IRLS of every pose of ``poses`` (``K``) with source points ``src (N, 3)`` against the
    dense target: ``dense_steps`` scales falling geometrically from ``dense_start`` dense spacings
    to the target's ``scale``, then up to ``dense_settle`` steps at the last one."""
    scales = np.geomspace(options.dense_start * dense.spacing, dense.scale, options.dense_steps)
    return welsch_irls(poses, src, dense.index, scales, options.dense_settle)


def dense_costs(poses: Poses, src: np.ndarray, dense: DenseTarget) -> np.ndarray:
    """``(K,)`` fixed-scale Welsch costs at the dense polish's last scale: the selection rule
    (every polished candidate is a local minimum of it)."""
    return fixed_scale_cost(poses, src, dense.index, dense.scale)


def dense_confident(poses: Poses, best: int, src: np.ndarray, dense: DenseTarget) -> bool:
    """Whether candidate ``best`` passes the inlier test of :func:`linereg.register`
    (:func:`~linereg.registration.evaluation.inlier_test`) against the dense target."""
    transform = as_matrices((poses[0][best : best + 1], poses[1][best : best + 1]))[0]
    quality, spacing, _, _ = inlier_test(src, dense.points, transform)
    return passes_inlier_test(quality, spacing)


def dense_doubt(
    select: SelectOptions, poses: Poses, costs: np.ndarray, src: np.ndarray, dense: DenseTarget
) -> tuple[bool, float]:
    """``(doubtful, margin)`` of the lowest dense cost. The score ``1 - cost`` is the soft share of
    inliers; the choice is doubtful when it fails the confidence test of :func:`linereg.register`
    or a candidate more than ``distinct_deg`` away scores more than ``1 / doubt_ratio`` of its score;
    ``margin`` is ``1 - rival score / best score`` (1 without a rival)."""
    scores = 1.0 - costs
    best = int(scores.argmax())
    confident = dense_confident(poses, best, src, dense)
    rivals = rotation_gap_deg(poses[0], poses[0][best]) > select.distinct_deg
    if not rivals.any():
        return not confident, 1.0
    rival, best_score = float(scores[rivals].max()), float(scores[best])
    return not confident or rival * select.doubt_ratio > best_score, 1.0 - rival / max(best_score, 1e-12)
