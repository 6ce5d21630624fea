"""Welsch's robust function and the point-to-point polish of the ``register`` default (numpy).

The polish is majorise-minimise (MM) on a Welsch objective: match every moved source point to its
nearest target point, weight the match by ``exp(-d^2 / 2 nu^2)`` and solve the weighted
Procrustes problem in closed form. A step cannot increase the objective at a fixed ``nu`` (the
Welsch function is concave in ``d^2``, and new nearest neighbours only shorten the distances).
The same Welsch cost at a fixed scale compares candidate poses (:func:`fixed_scale_cost`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.procrustes import weighted_procrustes_numpy
from linereg.registration.poses import Poses, apply

if TYPE_CHECKING:
    from linereg.registration.robust_options import PolishOptions

REACH = 6.0
"""Nearest-neighbour searches for a Welsch weight stop at ``REACH * nu`` (weight below ``exp(-18)``: 0)."""


def welsch_weights(distances: np.ndarray, nu: np.ndarray | float) -> np.ndarray:
    """Welsch's IRLS weights ``exp(-d^2 / 2 nu^2)`` of ``distances`` (``inf``: 0)."""
    return np.exp(-np.square(distances) / (2.0 * np.square(nu)))


def welsch_cost(distances: np.ndarray, nu: np.ndarray | float) -> np.ndarray:
    """``mean 1 - exp(-d^2 / 2 nu^2)`` over the last axis: 0 when every distance is 0, 1 when all are far."""
    return (1.0 - welsch_weights(distances, nu)).mean(axis=-1)


def lower_median(values: np.ndarray) -> np.ndarray:
    """Median over the last axis, the lower middle value for an even count (``torch.median``'s, as CD-W's scale)."""
    middle = (values.shape[-1] - 1) // 2
    return np.partition(values, middle, axis=-1)[..., middle]


def padded_points(index: NearestNeighbors) -> np.ndarray:
    """``(M + 1, 3)``: the indexed points and a last row of zeros, the point of the index ``M`` that
    :meth:`~linereg.knn.NearestNeighbors.query` returns for "none in range" (its weight is 0)."""
    return np.concatenate([index.points, np.zeros((1, 3))])


def welsch_irls(
    poses: Poses,
    src: np.ndarray,
    tgt_index: NearestNeighbors,
    nus: np.ndarray,
    settle: int = 0,
    tolerance: float = 1e-6,
) -> Poses:
    """Robust point-to-point ICP: one Welsch-weighted Procrustes step per scale in ``nus``,
    matching every source point ``(N, 3)`` to its nearest target point; ``K`` poses at once.
    Then up to ``settle`` more steps at the last scale, each pose until it moves less than
    ``tolerance`` (ICP crawls along directions in which the surfaces slide on each other)."""
    tgt = padded_points(tgt_index)
    rotations, translations = (array.copy() for array in poses)
    active = np.ones(len(rotations), dtype=bool)
    schedule = list(nus) + [nus[-1]] * settle if len(nus) else []
    for step, nu in enumerate(schedule):
        current = (rotations[active], translations[active])
        distances, idx = tgt_index.query(apply(current, src), distance_upper_bound=REACH * nu)
        weights = welsch_weights(distances, nu)
        new_r, new_t, valid = weighted_procrustes_numpy(np.broadcast_to(src, (len(idx), *src.shape)), tgt[idx], weights)
        new_r[~valid], new_t[~valid] = current[0][~valid], current[1][~valid]
        rotations[active], translations[active] = new_r, new_t
        if step >= len(nus) - 1:
            moved = np.abs(new_r - current[0]).max(axis=(1, 2)) + np.abs(new_t - current[1]).max(axis=1)
            active[np.flatnonzero(active)[moved < tolerance]] = False
            if not active.any():
                break
    return rotations, translations


def fixed_scale_cost(poses: Poses, src: np.ndarray, tgt_index: NearestNeighbors, nu: float) -> np.ndarray:
    """Welsch cost of every source point's nearest target distance with a FIXED scale ``nu``.

    ``mean_i 1 - exp(-d_i^2 / 2 nu^2)``: 0 when every source point lies on the target, 1 when
    none is near it. Unlike the paper's median-scaled metrics its value compares poses.

    Returns:
        ``(K,)`` costs in ``[0, 1]``.
    """
    distances, _ = tgt_index.query(apply(poses, src), distance_upper_bound=REACH * nu)
    return welsch_cost(distances, nu)


def polish_scales(polish: PolishOptions, spacing: float) -> np.ndarray:
    """Welsch scales of the IRLS polish: ``steps`` values falling geometrically from ``nu`` to
    ``end`` times the target's point ``spacing`` over the first half, then held (the last steps
    settle at the fine scale)."""
    if polish.steps == 0:
        return np.zeros(0)
    fine = min(polish.end * spacing, polish.nu)
    falling = np.geomspace(polish.nu, fine, max((polish.steps + 1) // 2, 1))
    return np.concatenate([falling, np.full(polish.steps - len(falling), fine)])[: polish.steps]


def fine_scales(polish: PolishOptions, spacing: float) -> np.ndarray:
    """Welsch scales of the fine polish of a pose whose source lies on the target: the geometric
    sequence of ``(steps + 1) // 2`` values from ``end`` to ``fine_end`` times the target's point
    ``spacing``, less its first (the polish ended there); empty when ``fine_end >= end`` or
    ``steps`` is 0."""
    if polish.steps == 0 or polish.fine_end >= polish.end:
        return np.zeros(0)
    count = max((polish.steps + 1) // 2, 2)
    start = min(polish.end * spacing, polish.nu)
    return np.geomspace(start, min(polish.fine_end * spacing, start), count)[1:]
