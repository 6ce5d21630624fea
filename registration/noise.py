"""A cloud far noisier than its partner, found and smoothed before the solver sees it.

Noise of a few point spacings on one cloud (a cheaper sensor, a far range, a fused depth map)
tilts the fit: each point pairs with whichever noisy neighbour lies closest, and the answer drifts
by degrees while the inliers still look right. :func:`surface_noise` measures a cloud's noise
apart from its curvature (the residual of a quadric fitted to each neighbourhood, in point
spacings); :func:`noisy_sides` names the cloud that is both noisy (:data:`NOISY`) and much noisier
than the other (:data:`NOISIER`); :func:`smoothed` replaces each of its points by the mean of its
:data:`SMOOTH_NEIGHBOURS` nearest points, for the solver only: ``register``'s check still judges
the answer on the clouds as given.

Two clouds equally noisy (two fused room fragments) stay as they are: smoothing both changes
the features the global stage matches.
"""

from __future__ import annotations

import numpy as np

from linereg.knn import NearestNeighbors

QUADRIC_NEIGHBOURS = 24
"""Points of the quadric fitted about each sampled point."""
NOISY = 1.0
"""Median quadric residual, in point spacings, from which a cloud is noisy: the benchmark's object
clouds reach 0.96 (a sparse whole airplane, whose wings are thinner than its neighbourhoods), range
scans with noise of 3 point spacings measure 1.07 to 1.10 (``scripts/bench_trust.py``)."""
NOISIER = 1.5
"""... and how many times the other cloud's it must be (the two room fragments of a benchmark pair,
each about 1.0, differ by a factor of 1.11 at most)."""
SMOOTH_NEIGHBOURS = 48
"""Nearest points averaged by :func:`smoothed`."""


def surface_noise(
    points: np.ndarray, sample: int = 1000, seed: int = 0, index: NearestNeighbors | None = None
) -> float:
    """The noise of ``points (N, 3)`` off their surface, in point spacings: the median RMS residual of
    the quadric ``z = a x^2 + b xy + c y^2 + d x + e y + f`` fitted, in the frame of its principal
    axes, to each of ``sample`` random points' :data:`QUADRIC_NEIGHBOURS` nearest points (a smooth
    surface leaves a residual far below one spacing, whatever its curvature), over the median
    distance from those points to their nearest other point (repeated points count once).
    ``index``: the :class:`~linereg.knn.NearestNeighbors` of ``points``, when already built."""
    count = QUADRIC_NEIGHBOURS
    if len(points) <= count:
        return 0.0
    rng = np.random.default_rng(seed)
    probe = points if len(points) <= sample else points[rng.choice(len(points), sample, replace=False)]
    distances, neighbours = (index or NearestNeighbors(points)).query(probe, k=count)
    apart = distances > 0.0
    nearest = distances[np.arange(len(probe)), np.argmax(apart, axis=1)][apart.any(axis=1)]
    local = points[neighbours]
    local = local - local.mean(axis=1, keepdims=True)
    _, axes = np.linalg.eigh(local.transpose(0, 2, 1) @ local)
    height, x, y = np.moveaxis(local @ axes, -1, 0)  # normal first
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)
    transposed = design.transpose(0, 2, 1)
    coefficients = np.linalg.solve(transposed @ design + 1e-12 * np.eye(6), transposed @ height[..., None])
    residual = height - (design @ coefficients)[..., 0]
    rms = np.sqrt(np.sum(residual**2, axis=1) / (count - 6))
    return float(np.median(rms)) / max(float(np.median(nearest)) if len(nearest) else 0.0, 1e-300)


def noisy_sides(source_noise: float, target_noise: float) -> tuple[bool, bool]:
    """``(source, target)``: which cloud is noisy (:data:`NOISY`) and :data:`NOISIER` than the other."""
    return (
        source_noise >= NOISY and source_noise >= NOISIER * target_noise,
        target_noise >= NOISY and target_noise >= NOISIER * source_noise,
    )


def smoothed(points: np.ndarray, index: NearestNeighbors | None = None) -> np.ndarray:
    """``(N, 3)``: each of ``points (N, 3)`` replaced by the mean of its :data:`SMOOTH_NEIGHBOURS`
    nearest points (itself included); ``index``: the KD-tree of ``points``, when already built."""
    _, neighbours = (index or NearestNeighbors(points)).query(points, k=min(SMOOTH_NEIGHBOURS, len(points)))
    return points[neighbours].mean(axis=1)
