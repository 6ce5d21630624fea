"""The quality of a registration without ground truth, as Open3D's ``evaluate_registration`` defines it.

:func:`evaluate_registration` scores the result of every method that :func:`linereg.register`
runs (the solvers, the baselines and trained networks alike): ``fitness`` is the fraction of
source points with a target point within ``max_correspondence_distance``, ``inlier_rmse`` the RMS
distance of those points (Open3D's ``pipelines.registration.evaluate_registration``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from linereg.knn import NearestNeighbors


class RegistrationQuality(NamedTuple):
    """Result of :func:`evaluate_registration`.

    Attributes:
        fitness: fraction of source points with a target point within the distance.
        inlier_rmse: RMS distance of those inlier points to their nearest target point (0 without inliers).
        correspondences: number of inlier points.
    """

    fitness: float
    inlier_rmse: float
    correspondences: int


def evaluate_registration(
    source: np.ndarray,
    target: np.ndarray,
    max_correspondence_distance: float,
    transformation: np.ndarray | None = None,
) -> RegistrationQuality:
    """Fitness and inlier RMSE of ``transformation`` mapping ``source`` onto ``target``.

    Args:
        source: array of shape ``(N, 3)``.
        target: array of shape ``(M, 3)``.
        max_correspondence_distance: a source point is an inlier when its nearest target point
            lies within this distance (inclusive), in the clouds' units.
        transformation: ``(4, 4)`` source-to-target transform (``None``: the identity).

    Returns:
        :class:`RegistrationQuality`.
    """
    moved = np.asarray(source, dtype=np.float64)
    if transformation is not None:
        moved = moved @ transformation[:3, :3].T + transformation[:3, 3]
    distances, _ = NearestNeighbors(np.asarray(target, dtype=np.float64)).query(moved)
    inliers = distances <= max_correspondence_distance
    rmse = float(np.sqrt(np.square(distances[inliers]).mean())) if inliers.any() else 0.0
    return RegistrationQuality(float(inliers.mean()), rmse, int(inliers.sum()))


def point_spacing(points: np.ndarray, index: NearestNeighbors | None = None) -> float:
    """Median distance of a point of ``points (N, 3)`` to its nearest other point (``index``: of ``points``)."""
    distances, _ = (index or NearestNeighbors(points)).query(points, k=2)
    return float(np.median(distances[:, 1]))
