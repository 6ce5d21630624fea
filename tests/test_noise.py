"""A cloud far noisier than its partner is smoothed for the solver and judged as given
(registration/noise.py)."""

from __future__ import annotations

import numpy as np
import pytest

import linereg
from linereg.knn import NearestNeighbors
from linereg.registration import noise
from linereg.registration.trust import spacing_of
from tests.test_trust import TRUTH, bumpy, moved, rotation_error


def naive_surface_noise(points: np.ndarray, sample: int, seed: int = 0) -> float:
    """:func:`noise.surface_noise` one neighbourhood at a time, with ``np.linalg.lstsq``."""
    rng = np.random.default_rng(seed)
    probe = points if len(points) <= sample else points[rng.choice(len(points), sample, replace=False)]
    tree, residuals, nearest = NearestNeighbors(points), [], []
    for point in probe:
        distances, index = tree.query(point[None], k=noise.QUADRIC_NEIGHBOURS)
        nearest.append(distances[0][distances[0] > 0].min())
        local = points[index[0]] - points[index[0]].mean(axis=0)
        _, _, axes = np.linalg.svd(local)
        x, y, height = (local @ axes.T).T  # the normal is the last singular vector
        design = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        _, (squares,), *_ = np.linalg.lstsq(design, height, rcond=None)
        residuals.append(np.sqrt(squares / (noise.QUADRIC_NEIGHBOURS - 6)))
    return float(np.median(residuals)) / float(np.median(nearest))


def test_surface_noise_matches_its_naive_twin_and_ignores_curvature():
    rng = np.random.default_rng(0)
    clean = bumpy(6000, 1)
    noisy = clean + rng.normal(0.0, 4.0 * spacing_of(clean), clean.shape)
    for points in (clean, noisy):
        expected = naive_surface_noise(points, sample=300)
        assert noise.surface_noise(points, sample=300) == pytest.approx(expected, rel=1e-6)
    assert noise.surface_noise(clean) < 0.1 < noise.NOISY < noise.surface_noise(noisy)


def test_only_a_cloud_far_noisier_than_the_other_is_smoothed():
    assert noise.noisy_sides(0.1, 1.0) == (False, True)
    assert noise.noisy_sides(1.0, 0.1) == (True, False)
    assert noise.noisy_sides(1.0, 1.0) == (False, False)  # two fused room fragments
    assert noise.noisy_sides(0.1, 0.7) == (False, False)  # a sparse curved view, not noise
    points = np.random.default_rng(1).normal(size=(200, 3))
    _, neighbours = NearestNeighbors(points).query(points[:1], k=noise.SMOOTH_NEIGHBOURS)
    assert np.allclose(noise.smoothed(points)[0], points[neighbours[0]].mean(axis=0))


def test_a_noisy_target_is_smoothed_for_the_solver_and_judged_as_given():
    rng = np.random.default_rng(3)
    source, target = bumpy(8000, 1), moved(bumpy(12000, 2), TRUTH)
    noisy = target + rng.normal(0.0, 4.0 * spacing_of(target), target.shape)
    result = linereg.register(source, noisy)
    assert result.info["smoothed"] == ["target"] and result.info["surface_noise"]["target"] > noise.NOISY
    assert result.confident and rotation_error(result, TRUTH) < 0.5
    judged = linereg.registration.api.quality(source, noisy, result.transformation, on_surface=None)
    assert result.inlier_rmse == pytest.approx(judged["inlier_rmse"])  # the check saw the noisy target
    assert linereg.register(source, target).info["smoothed"] == []


def test_a_real_scan_under_heavy_noise_is_right_or_not_trusted(shared_data):
    """The statue pair (FRICP's estimate as the reference) with noise of 3 point spacings on its
    target: smoothed, it is answered within 2 degrees and trusted (5 degrees off without smoothing)."""
    from linereg.io import read_point_cloud, read_transform

    folder = shared_data / "scans/fricp_statue"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    truth = read_transform(folder / "m3trans.txt")
    source, target = read_point_cloud(folder / "source.ply").xyz, read_point_cloud(folder / "target.ply").xyz
    noisy = target + np.random.default_rng(0).normal(0.0, 3.0 * spacing_of(target), target.shape)
    result = linereg.register(source, noisy)
    assert result.info["smoothed"] == ["target"]
    assert result.confident and rotation_error(result, truth) < 2.0
