"""The quality of a registration without ground truth, and whether it can be trusted.

:func:`evaluate_registration` is Open3D's ``pipelines.registration.evaluate_registration``:
``fitness`` is the fraction of source points with a target point within
``max_correspondence_distance``, ``inlier_rmse`` the RMS distance of those points.

:func:`assess_registration` scores the result of every method that :func:`linereg.register` runs
(the solvers, the baselines and trained networks alike) with distances measured in the target's
own *sampling distance* (:func:`sampling_distance`): the RMS distance between two independent
samplings of the target's surface at its density, sensor noise included. A right pose puts the
overlapping source points at about that distance from the target; a wrong one scatters them over
the whole inlier range. The pose is ``confident`` when at least :data:`MIN_FITNESS` of the source
points lie within :data:`INLIER_DISTANCES` sampling distances and their RMS distance is at most
:data:`MAX_INLIER_RMSE` sampling distances. The thresholds were chosen on the candidates and
results of pairs drawn with seed 7 (``scripts/studies/check_confidence.py``); the benchmarks report seed 0.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.registration import trust

INLIER_DISTANCES = 3.0
"""The fitness threshold of :func:`assess_registration`, in sampling distances."""
MIN_FITNESS = 0.1
"""Fewest share of source inliers for a confident pose (a correct pair at 20 % overlap scores about 0.2)."""
MAX_INLIER_RMSE = 1.2
"""Largest inlier RMS distance of a confident pose, in sampling distances."""
ASSESS_SOURCE_POINTS = 2048
"""FPS points of the source :func:`assess_registration` moves."""
ASSESS_TARGET_POINTS = 4096
"""FPS points of the target it measures against (all of them when fewer)."""


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
    return _inlier_quality(distances, max_correspondence_distance)


def _inlier_quality(distances: np.ndarray, threshold: float) -> RegistrationQuality:
    """:class:`RegistrationQuality` of nearest-target ``distances (N,)`` with inliers within ``threshold``."""
    inliers = distances <= threshold
    rmse = float(np.sqrt(np.square(distances[inliers]).mean())) if inliers.any() else 0.0
    return RegistrationQuality(float(inliers.mean()), rmse, int(inliers.sum()))


def point_spacing(points: np.ndarray, index: NearestNeighbors | None = None) -> float:
    """Median distance of a point of ``points (N, 3)`` to its nearest other point (``index``: of
    ``points``); a point repeated up to 3 times counts once (its nearest point elsewhere)."""
    distances, _ = (index or NearestNeighbors(points)).query(points, k=min(len(points), 5))
    elsewhere = np.where(distances[:, 1:] > 0, distances[:, 1:], np.inf).min(axis=1)
    return float(np.median(elsewhere[np.isfinite(elsewhere)])) if np.isfinite(elsewhere).any() else 0.0


def sampling_distance(points: np.ndarray, seed: int = 0) -> float:
    """The distance two independent samplings of the surface of ``points (N, 3)`` lie apart.

    The cloud is split at random into halves; each point of one half is matched to the nearest
    point of the other (distances beyond 5 times their median, holes and edges, are clipped);
    the RMS of those distances, divided by ``sqrt(2)`` (a half is half as dense), is the distance
    at the full density, noise included.
    """
    order = np.random.default_rng(seed).permutation(len(points))
    first, second = points[order[::2]], points[order[1::2]]
    distances, _ = NearestNeighbors(second).query(first)
    clipped = np.minimum(distances, 5.0 * np.median(distances))
    return float(np.sqrt(np.mean(np.square(clipped))) / np.sqrt(2.0))


class Assessment(NamedTuple):
    """Result of :func:`assess_registration` (lengths in the clouds' units).

    Attributes:
        fitness: share of source points within ``fitness_threshold`` of the target.
        inlier_rmse: RMS distance of those points.
        fitness_threshold: :data:`INLIER_DISTANCES` sampling distances, unless given.
        sampling_distance: the target's :func:`sampling_distance`.
        confident: the pose passes every test of the module docstring.
        tight_fitness: share of source points within :data:`TIGHT_DISTANCES` point spacings of the
            whole target (``nan`` when the inlier test failed first).
        chance_fitness: the same share at random placements of the source
            (:func:`~linereg.registration.trust.chance_fitness`; ``nan`` when not measured).
        warnings: why the pose is not trusted, or what is odd about the clouds, one line each.
    """

    fitness: float
    inlier_rmse: float
    fitness_threshold: float
    sampling_distance: float
    confident: bool
    tight_fitness: float = float("nan")
    chance_fitness: float = float("nan")
    warnings: tuple[str, ...] = ()


def inlier_test(
    source: np.ndarray, target: np.ndarray, transformation: np.ndarray | None = None
) -> tuple[RegistrationQuality, float, np.ndarray, np.ndarray]:
    """The inlier test of ``transformation (4, 4)`` on :data:`ASSESS_SOURCE_POINTS` and
    :data:`ASSESS_TARGET_POINTS` FPS points: the quality within :data:`INLIER_DISTANCES` sampling
    distances, the target's sampling distance, the nearest-target distances of the moved source
    subset ``(n,)`` and that subset ``(n, 3)`` (not moved)."""
    source = fps(np.asarray(source, dtype=np.float64), ASSESS_SOURCE_POINTS)
    target = fps(np.asarray(target, dtype=np.float64), ASSESS_TARGET_POINTS)
    spacing = sampling_distance(target)
    moved = source if transformation is None else source @ transformation[:3, :3].T + transformation[:3, 3]
    distances, _ = NearestNeighbors(target).query(moved)
    return _inlier_quality(distances, INLIER_DISTANCES * spacing), spacing, distances, source


def passes_inlier_test(quality: RegistrationQuality, spacing: float) -> bool:
    """At least :data:`MIN_FITNESS` inliers at an RMS distance of at most :data:`MAX_INLIER_RMSE` sampling distances."""
    return quality.fitness >= MIN_FITNESS and quality.inlier_rmse <= MAX_INLIER_RMSE * spacing


def assess_registration(
    source: np.ndarray,
    target: np.ndarray,
    transformation: np.ndarray | None = None,
    fitness_threshold: float | None = None,
    on_surface: np.ndarray | bool | None = True,
    target_index: NearestNeighbors | None = None,
) -> Assessment:
    """Fitness, inlier RMSE and every test of the module docstring of ``transformation (4, 4)``
    mapping ``source (N, 3)`` onto ``target (M, 3)``.

    Args:
        fitness_threshold: inlier distance of the reported ``fitness`` and ``inlier_rmse``
            (``None``: :data:`INLIER_DISTANCES` sampling distances); the tests keep their own.
        on_surface: the target's clutter-free points as ``(M,)`` bool, ``None`` for all of them,
            ``True`` to find them (:func:`~linereg.registration.trust.surface_points`).
        target_index: the KD-tree of ``target``, when already built.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    transform = np.eye(4) if transformation is None else np.asarray(transformation, dtype=np.float64)
    if on_surface is True:
        on_surface = trust.surface_points(target, source, target_index=target_index)
    surface = None if on_surface is None else target[on_surface]
    test, spacing, distances, subset = inlier_test(source, target if surface is None else surface, transform)
    passed = passes_inlier_test(test, spacing)
    verdict = trust.verdict(source, subset, target, surface, transform, passed, target_index)
    warnings = _inlier_warnings(test, spacing) + verdict.warnings
    reported = test if fitness_threshold is None else _inlier_quality(distances, fitness_threshold)
    threshold = INLIER_DISTANCES * spacing if fitness_threshold is None else fitness_threshold
    return Assessment(
        reported.fitness,
        reported.inlier_rmse,
        threshold,
        spacing,
        verdict.confident,
        verdict.tight_fitness,
        verdict.chance_fitness,
        warnings,
    )


def _inlier_warnings(test: RegistrationQuality, spacing: float) -> tuple[str, ...]:
    """Why the inlier test fails, if it does."""
    if test.fitness < MIN_FITNESS:
        return (
            f"only {100 * test.fitness:.1f} % of the source lies within {INLIER_DISTANCES:g} sampling distances of the "
            "target: no overlap found (too little overlap, another object, or clouds in different units)",
        )
    if test.inlier_rmse > MAX_INLIER_RMSE * spacing:
        return (
            f"the inliers lie {test.inlier_rmse / spacing:.2f} sampling distances from the target (at most "
            f"{MAX_INLIER_RMSE:g} when right): the surfaces do not coincide (a wrong pose, another object, a mirror "
            "image or heavy noise)",
        )
    return ()
