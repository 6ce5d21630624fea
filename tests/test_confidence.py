"""The confidence test every method's result gets (registration/evaluation.py assess_registration)."""

import numpy as np
import pytest

import linereg
from linereg.registration.evaluation import (
    INLIER_DISTANCES,
    MAX_INLIER_RMSE,
    MIN_FITNESS,
    assess_registration,
    sampling_distance,
)


def _surface(count: int, seed: int) -> np.ndarray:
    """``count`` random points of an ellipsoid's upper half on a rectangle, off its centre (a
    scene-like surface with a unique pose)."""
    rng = np.random.default_rng(seed)
    dome = rng.normal(size=(count // 2, 3))
    dome /= np.linalg.norm(dome, axis=1, keepdims=True)
    dome[:, 2] = np.abs(dome[:, 2])
    dome = dome * [1.0, 0.6, 0.8] + [0.7, 0.3, 0.0]
    floor = np.column_stack([rng.uniform([-2, -1], [3, 2], (count - len(dome), 2)), np.zeros(count - len(dome))])
    return np.concatenate([dome, floor])


def _moved(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _naive_confident(source: np.ndarray, target: np.ndarray, spacing: float) -> bool:
    """The test written out point by point."""
    distances = np.array([np.min(np.linalg.norm(target - point, axis=1)) for point in source])
    inliers = distances[distances <= INLIER_DISTANCES * spacing]
    return bool(len(inliers) >= MIN_FITNESS * len(source) and np.sqrt(np.mean(inliers**2)) <= MAX_INLIER_RMSE * spacing)


def test_sampling_distance_is_the_distance_between_independent_samplings():
    """Two independent samplings of a plane at one density lie about the sampling distance apart."""
    rng = np.random.default_rng(0)
    first = np.column_stack([rng.uniform(0, 1, (4000, 2)), np.zeros(4000)])
    second = np.column_stack([rng.uniform(0, 1, (4000, 2)), np.zeros(4000)])
    distances = np.array([np.min(np.linalg.norm(second - point, axis=1)) for point in first[:300]])
    assert sampling_distance(first) == pytest.approx(np.sqrt(np.mean(distances**2)), rel=0.15)


def test_a_right_pose_is_confident_and_wrong_ones_are_not():
    """Independent samplings of one surface: the true pose passes, a shift and a rotation fail,
    and the test agrees with its naive twin."""
    target, source = _surface(4000, 0), _surface(2000, 1)
    spacing = sampling_distance(target)
    shifted, turned = np.eye(4), np.eye(4)
    shifted[:3, 3] = [0.3, 0.0, 0.0]
    angle = np.radians(25.0)
    turned[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    turned[0, 3] = 0.2
    for transform, expected in ((np.eye(4), True), (shifted, False), (turned, False)):
        assessed = assess_registration(source, target, transform)
        assert assessed.confident is expected
        assert _naive_confident(_moved(transform, source), target, spacing) is expected
        assert assessed.fitness_threshold == pytest.approx(INLIER_DISTANCES * spacing)


def test_the_flag_does_not_depend_on_units_and_the_reported_threshold_can_be_set():
    target, source = _surface(3000, 2), _surface(1500, 3)
    metres = assess_registration(source, target)
    millimetres = assess_registration(1000 * source, 1000 * target)
    assert metres.confident and millimetres.confident
    assert millimetres.fitness == pytest.approx(metres.fitness)
    assert millimetres.sampling_distance == pytest.approx(1000 * metres.sampling_distance)
    given = assess_registration(source, target, fitness_threshold=1e-9)
    assert given.fitness == 0.0 and given.fitness_threshold == 1e-9 and given.confident


def test_every_method_gets_the_flag_from_the_same_test():
    """``register`` flags the result of a baseline as it flags the default's."""
    target, source = _surface(3000, 4), _surface(1500, 5)
    angle = np.radians(20.0)
    truth = np.eye(4)
    truth[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    truth[:3, 3] = [0.1, -0.05, 0.02]
    moved = _moved(truth, target)
    for method in ("robust", "icp_point"):
        result = linereg.register(source, moved, method=method)
        expected = assess_registration(source, moved, result.transformation)
        assert result.confident is expected.confident
        assert result.fitness == pytest.approx(expected.fitness)
