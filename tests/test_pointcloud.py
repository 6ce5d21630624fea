"""Tests for linereg.pointcloud against slow references and hand-made clouds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from linereg.pointcloud import (
    bounding_sphere,
    estimate_normals,
    farthest_point_sampling,
    fit_into_cube,
    hidden_point_removal,
    mean_neighbor_distance,
    resample_indices,
    trimmed_chamfer_distance,
    weighted_chamfer_distance,
)


def _unit_sphere(num_points: int, seed: int = 0) -> np.ndarray:
    points = np.random.default_rng(seed).normal(size=(num_points, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _lattice(size: int) -> np.ndarray:
    axis = np.arange(size, dtype=np.float64)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def test_mean_neighbor_distance_unit_lattice() -> None:
    lattice = _lattice(4)
    torch.testing.assert_close(mean_neighbor_distance(lattice, k=2), torch.tensor(1.0, dtype=torch.float64))
    batched = torch.from_numpy(np.stack([lattice, 2.5 * lattice]))
    torch.testing.assert_close(mean_neighbor_distance(batched, k=1), torch.tensor([1.0, 2.5], dtype=torch.float64))


def test_mean_neighbor_distance_edge_cases() -> None:
    assert mean_neighbor_distance(torch.zeros(7, 3), k=2).item() == 0.0
    with pytest.raises(ValueError, match="k < N"):
        mean_neighbor_distance(torch.rand(2, 3), k=2)


def test_fps_unique_and_spread() -> None:
    points = np.random.default_rng(6).random((3000, 3)).astype(np.float32)
    for start_index in (None, 17):
        idx = farthest_point_sampling(points, 64, start_index=start_index)
        assert idx.shape == (64,) and idx.dtype == np.int64
        assert len(np.unique(idx)) == 64
        sampled = points[idx]
        random = points[np.random.default_rng(7).choice(3000, 64, replace=False)]
        assert _min_pairwise(sampled) > 3 * _min_pairwise(random)
    assert farthest_point_sampling(points, 5, start_index=17)[0] == 17


def test_fps_torch_batched_and_duplicates() -> None:
    points = torch.rand(2, 500, 3, generator=torch.Generator().manual_seed(8))
    idx = farthest_point_sampling(points, 32)
    assert idx.shape == (2, 32) and idx.dtype == torch.long
    for row in idx:
        assert len(torch.unique(row)) == 32
    duplicated = np.repeat(np.random.default_rng(9).random((4, 3)), 25, axis=0)
    idx = farthest_point_sampling(duplicated, 10)
    assert len(np.unique(idx)) == 10
    assert len(np.unique(duplicated[idx[:4]], axis=0)) == 4


def test_fps_errors() -> None:
    points = np.random.default_rng(0).random((10, 3))
    with pytest.raises(ValueError, match="n_samples must be between 1 and N=10"):
        farthest_point_sampling(points, 11)
    with pytest.raises(ValueError, match="n_samples must be between"):
        farthest_point_sampling(points, 0)
    with pytest.raises(ValueError, match="start_index must be in"):
        farthest_point_sampling(points, 3, start_index=10)


def _min_pairwise(points: np.ndarray) -> float:
    diff = np.linalg.norm(points[:, None] - points[None], axis=-1)
    return float(diff[~np.eye(len(points), dtype=bool)].min())


def test_resample_indices_without_replacement() -> None:
    idx = resample_indices(100, 40, 0)
    assert idx.shape == (40,) and idx.dtype == np.int64
    assert len(np.unique(idx)) == 40 and idx.min() >= 0 and idx.max() < 100
    np.testing.assert_array_equal(idx, resample_indices(100, 40, np.random.default_rng(0)))
    assert sorted(resample_indices(30, 30, 1)) == list(range(30))


def test_resample_indices_with_replacement_keeps_every_point() -> None:
    idx = resample_indices(10, 25, 3)
    assert idx.shape == (25,)
    counts = np.bincount(idx, minlength=10)
    assert counts.min() >= 1 and counts.sum() == 25
    with pytest.raises(ValueError, match="num_points >= 1"):
        resample_indices(0, 5, 0)


def test_estimate_normals_sphere_consistent_outward() -> None:
    points = _unit_sphere(2000)
    normals = estimate_normals(points, k=20)
    assert normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert np.sum(normals * points, axis=1).min() > 0.98


def test_estimate_normals_plane_and_camera() -> None:
    rng = np.random.default_rng(10)
    plane = np.column_stack([rng.random((400, 2)), np.zeros(400)])
    normals = estimate_normals(plane, k=15)
    np.testing.assert_allclose(np.abs(normals[:, 2]), 1.0, atol=1e-5)
    assert len(np.unique(np.sign(normals[:, 2]))) == 1
    for camera_z in (5.0, -5.0):
        towards = estimate_normals(plane, k=15, orient_towards=np.array([0.5, 0.5, camera_z]))
        np.testing.assert_allclose(towards[:, 2], np.sign(camera_z), atol=1e-5)
    inward = estimate_normals(_unit_sphere(500), radius=0.5, orient_towards=np.zeros(3))
    assert np.sum(inward * _unit_sphere(500), axis=1).max() < -0.9


def test_bounding_sphere_covers_all_points() -> None:
    generator = torch.Generator().manual_seed(11)
    a = torch.randn(4, 100, 3, generator=generator)
    b = torch.randn(4, 50, 3, generator=generator) * 3 + 2
    center, radius = bounding_sphere(a, b)
    assert center.shape == (4, 3) and radius.shape == (4,)
    for cloud in (a, b):
        assert ((cloud - center[:, None]).norm(dim=-1) <= radius[:, None] + 1e-5).all()
    center, radius = bounding_sphere(a[0])
    assert center.shape == (3,) and radius.shape == ()
    torch.testing.assert_close((a[0] - center).norm(dim=-1).max(), radius)
    with pytest.raises(ValueError, match="all batched"):
        bounding_sphere(a, b[0])


def test_fit_into_cube_bounds() -> None:
    rng = np.random.default_rng(12)
    a = (rng.random((200, 3)) * [10.0, 2.0, 3.0] + 40.0).astype(np.float32)
    b = (rng.random((100, 3)) * 4.0 + 45.0).astype(np.float32)
    (sa, sb), center, scale = fit_into_cube(a, b, half_extent=1.0)
    joint = np.vstack([sa, sb])
    assert sa.dtype == np.float32
    assert np.abs(joint).max() <= 1.0 + 1e-6
    np.testing.assert_allclose(joint.max(axis=0)[np.argmax(np.ptp(joint, axis=0))], 1.0, atol=1e-6)
    np.testing.assert_allclose(sa, (a - center) * scale, atol=1e-5)
    with pytest.raises(ValueError, match="zero extent"):
        fit_into_cube(np.ones((5, 3)))


def test_hidden_point_removal_keeps_front_half() -> None:
    points = _unit_sphere(4000, seed=13)
    visible = hidden_point_removal(points, np.array([0.0, 0.0, 10.0]))
    assert visible.dtype == np.int64 and np.all(np.diff(visible) > 0)
    assert 0.35 < len(visible) / len(points) < 0.55
    assert (points[visible, 2] > -0.05).mean() > 0.99


def _trimmed_chamfer_naive(x: torch.Tensor, y: torch.Tensor, keep_fraction: float) -> torch.Tensor:
    """Brute force: all distances, each direction's nearest ones sorted and the first share averaged."""
    dists = ((x[..., :, None, :] - y[..., None, :, :]) ** 2).sum(-1).sqrt()
    total = 0.0
    for nearest in (dists.min(-1).values, dists.min(-2).values):
        kept = int(np.ceil(keep_fraction * nearest.shape[-1]))
        total = total + nearest.sort(-1).values[..., :kept].mean(-1)
    return total


@pytest.mark.parametrize("keep_fraction", [1.0, 0.9, 0.5, 0.01])
def test_trimmed_chamfer_distance_matches_brute_force(keep_fraction: float) -> None:
    generator = torch.Generator().manual_seed(0)
    x, y = torch.rand(3, 40, 3, generator=generator), torch.rand(3, 31, 3, generator=generator)
    expected = _trimmed_chamfer_naive(x, y, keep_fraction)
    torch.testing.assert_close(trimmed_chamfer_distance(x, y, keep_fraction), expected)
    torch.testing.assert_close(trimmed_chamfer_distance(x[1], y[1], keep_fraction), expected[1])


def test_trimmed_chamfer_distance_ignores_points_without_counterpart() -> None:
    """A partial view: the points one cloud lacks weigh in the plain distance, not the trimmed one."""
    shared = torch.rand(90, 3, generator=torch.Generator().manual_seed(1))
    whole = torch.cat([shared, shared[:10] + torch.tensor([5.0, 0.0, 0.0])])
    assert trimmed_chamfer_distance(shared, whole, 0.9) == 0
    assert trimmed_chamfer_distance(shared, whole) > 0.4  # 10 of 100 points 5 away: 0.5 in one direction


def test_trimmed_chamfer_distance_errors() -> None:
    x = torch.rand(2, 10, 3)
    for fraction in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="keep_fraction must be in"):
            trimmed_chamfer_distance(x, x, fraction)
    with pytest.raises(ValueError, match="both be batched or both unbatched"):
        trimmed_chamfer_distance(x, x[0])
    with pytest.raises(ValueError, match="batch size"):
        trimmed_chamfer_distance(x, torch.rand(3, 10, 3))
    with pytest.raises(ValueError, match="NaN"):
        trimmed_chamfer_distance(x, torch.full((2, 10, 3), float("nan")))
    with pytest.raises(ValueError, match=r"keep_fraction tensor needs batched clouds and shape \(B,\)"):
        trimmed_chamfer_distance(x, x, torch.full((3,), 0.5))
    with pytest.raises(ValueError, match="keep_fraction must be in"):
        trimmed_chamfer_distance(x, x, torch.tensor([0.5, 0.0]))
    with pytest.raises(ValueError, match="needs batched clouds"):
        trimmed_chamfer_distance(x[0], x[0], torch.tensor([0.5]))


def test_trimmed_chamfer_distance_takes_a_share_per_pair() -> None:
    generator = torch.Generator().manual_seed(2)
    x, y = torch.rand(3, 40, 3, generator=generator), torch.rand(3, 31, 3, generator=generator)
    shares = torch.tensor([1.0, 0.9, 0.3])
    expected = torch.stack([_trimmed_chamfer_naive(x[b], y[b], float(shares[b])) for b in range(3)])
    torch.testing.assert_close(trimmed_chamfer_distance(x, y, shares), expected)


def test_weighted_chamfer_distance_matches_brute_force() -> None:
    generator = torch.Generator().manual_seed(3)
    x, y = torch.rand(2, 40, 3, generator=generator), torch.rand(2, 31, 3, generator=generator)
    x_weights, y_weights = torch.rand(2, 40, generator=generator), torch.rand(2, 31, generator=generator)
    dists = ((x[..., :, None, :] - y[..., None, :, :]) ** 2).sum(-1).sqrt()
    expected = (dists.min(-1).values * x_weights).sum(-1) / x_weights.sum(-1)
    expected = expected + (dists.min(-2).values * y_weights).sum(-1) / y_weights.sum(-1)
    torch.testing.assert_close(weighted_chamfer_distance(x, y, x_weights, y_weights), expected)
    torch.testing.assert_close(weighted_chamfer_distance(x[0], y[0], x_weights[0], y_weights[0]), expected[0])
    uniform = weighted_chamfer_distance(x, y, torch.ones(2, 40), torch.full((2, 31), 3.0))
    torch.testing.assert_close(uniform, trimmed_chamfer_distance(x, y))


def test_weighted_chamfer_distance_ignores_points_of_zero_weight() -> None:
    shared = torch.rand(90, 3, generator=torch.Generator().manual_seed(1))
    whole = torch.cat([shared, shared[:10] + torch.tensor([5.0, 0.0, 0.0])])
    unmatched = torch.cat([torch.ones(90), torch.zeros(10)])
    assert weighted_chamfer_distance(shared, whole, torch.ones(90), unmatched) == 0


def test_weighted_chamfer_distance_errors() -> None:
    x = torch.rand(2, 10, 3)
    ones = torch.ones(2, 10)
    with pytest.raises(ValueError, match=r"x_weights must have shape \(2, 10\)"):
        weighted_chamfer_distance(x, x, torch.ones(10), ones)
    with pytest.raises(ValueError, match="y_weights must be finite and non-negative"):
        weighted_chamfer_distance(x, x, ones, -ones)
    with pytest.raises(ValueError, match="x_weights must be finite"):
        weighted_chamfer_distance(x, x, torch.full((2, 10), float("nan")), ones)
    with pytest.raises(ValueError, match="positive sum"):
        weighted_chamfer_distance(x, x, ones, torch.zeros(2, 10))
    with pytest.raises(ValueError, match="both be batched or both unbatched"):
        weighted_chamfer_distance(x, x[0], ones, ones[0])
