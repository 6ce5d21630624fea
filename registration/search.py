"""The global pose search of the ``register`` default's third round (numpy).

Hundreds of rotations spread over SO(3) (:func:`~linereg.registration.poses.spread_rotations`),
and for each the best translation of a lattice by a one-sided Welsch cost read from a table, so
that every pose costs one look-up per source point. The best distinct poses
(:func:`~linereg.registration.poses.distinct_best`) then start the one-sided coarse IRLS.
"""

from __future__ import annotations

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.registration.welsch import REACH, welsch_weights


def pose_search(
    rotations: np.ndarray, src: np.ndarray, tgt: np.ndarray, *, radius: float, spacing: float, nu: float, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """For every rotation, the translation of a lattice with the lowest one-sided Welsch cost.

    The cost ``mean_i 1 - exp(-d_i^2 / 2 nu^2)`` of the moved source points' distances ``d_i`` to
    the target is read from a table of its value at the centres of cubic cells of side ``cell``
    (each point counts in its nearest cell), so that every pose costs one look-up per point.

    Args:
        rotations: ``(R, 3, 3)``.
        src: ``(N, 3)`` source points inside the unit ball; tgt: ``(M, 3)`` target points.
        radius: largest translation; spacing: step of the translation lattice (rounded to whole cells).
        nu: Welsch scale of the cost; cell: side of the table's cells.

    Returns:
        ``translations (R, 3)`` and their costs ``(R,)``.

    Raises:
        ValueError: a source point outside the unit ball (the table covers the unit ball plus ``radius``).
    """
    if np.linalg.norm(src, axis=1).max() > 1.0 + 1e-9:
        raise ValueError("pose_search: the source points must lie inside the unit ball")
    half = int(np.ceil((1.0 + radius) / cell)) + 1
    side = 2 * half + 1
    axis = cell * np.arange(-half, half + 1)
    centres = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    distances, _ = NearestNeighbors(tgt).query(centres, distance_upper_bound=REACH * nu)
    table = 1.0 - welsch_weights(distances, nu)
    step = max(round(spacing / cell), 1)
    reach = int(radius / (step * cell) + 1e-9)
    lattice = step * np.stack(np.meshgrid(*[np.arange(-reach, reach + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    lattice = lattice[np.linalg.norm(lattice * cell, axis=1) <= radius + 1e-9]
    shift = (lattice[:, 0] * side + lattice[:, 1]) * side + lattice[:, 2]
    translations, costs = np.empty((len(rotations), 3)), np.empty(len(rotations))
    for chunk in np.array_split(np.arange(len(rotations)), max(len(rotations) // 32, 1)):
        cells = np.rint(src @ rotations[chunk].transpose(0, 2, 1) / cell).astype(np.int64) + half
        index = (cells[..., 0] * side + cells[..., 1]) * side + cells[..., 2]
        cost = table[index[:, None, :] + shift[None, :, None]].mean(axis=2)
        best = cost.argmin(axis=1)
        translations[chunk] = lattice[best] * cell
        costs[chunk] = cost[np.arange(len(chunk)), best]
    return translations, costs
