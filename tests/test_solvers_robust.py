"""``robust_adam``, :class:`linereg.registration.solvers.AdamRobustRegistration` (the torch twin of the
``register`` default), and its building blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from linereg.losses.chamfer import chamfer_welsch_distance
from linereg.registration import METHODS
from linereg.registration.solvers import (
    AdamRobustOptions as RobustOptions,
)
from linereg.registration.solvers import (
    NearestTarget,
    chamfer_welsch_batched,
    fixed_scale_fit,
    torch_threads,
    welsch_irls,
)
from linereg.se3 import euler_to_rotmat, rotation_angle, rt_to_matrix


def surface(n: int, seed: int) -> np.ndarray:
    """Samples of an asymmetric bumpy ellipsoid (float64, unit scale)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    bump = 1.0 + 0.25 * np.sin(3.0 * x[:, 0]) * np.cos(2.0 * x[:, 1])
    return x * bump[:, None] * np.array([1.4, 1.0, 0.7])


def pose(angles_deg, t) -> np.ndarray:
    R = euler_to_rotmat(torch.tensor(angles_deg, dtype=torch.float64) * math.pi / 180)
    return rt_to_matrix(R, torch.tensor(t, dtype=torch.float64)).numpy()


def apply(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ T[:3, :3].T + T[:3, 3]


def rotation_error_deg(T: np.ndarray, truth: np.ndarray) -> float:
    return math.degrees(float(rotation_angle(torch.from_numpy(T[:3, :3] @ truth[:3, :3].T))))


def test_batched_chamfer_welsch_matches_the_loss_value_and_gradient():
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.normal(size=(3, 60, 3))).requires_grad_()
    y = torch.from_numpy(rng.normal(size=(3, 90, 3)))
    ours = chamfer_welsch_batched(x, y, 2.0)
    (grad_ours,) = torch.autograd.grad(ours.sum(), x)
    reference = chamfer_welsch_distance(x, y, nu0=2.0)
    (grad_reference,) = torch.autograd.grad(reference.sum(), x)
    torch.testing.assert_close(ours, reference)
    torch.testing.assert_close(grad_ours, grad_reference)


def test_one_sided_entries_keep_only_the_source_to_target_term():
    rng = np.random.default_rng(4)
    x = torch.from_numpy(rng.normal(size=(2, 50, 3)))
    y = torch.from_numpy(rng.normal(size=(2, 80, 3)) * 1.5)
    ours = chamfer_welsch_batched(x, y, 2.0, two_sided=torch.tensor([True, False]))
    torch.testing.assert_close(ours[0], chamfer_welsch_distance(x[:1], y[:1], nu0=2.0)[0])
    distances = torch.cdist(x[1], y[1]).min(dim=1).values  # naive twin: brute force, one direction
    nu = 2.0 * distances.median()
    torch.testing.assert_close(ours[1], (1 - torch.exp(-distances.square() / (2 * nu * nu))).mean())


def test_nearest_target_matches_brute_force():
    rng = np.random.default_rng(1)
    tgt = torch.from_numpy(rng.normal(size=(200, 3)))
    query = torch.from_numpy(rng.normal(size=(2, 50, 3)))
    distances, idx = NearestTarget(tgt)(query)
    brute = torch.cdist(query, tgt[None].expand(2, -1, -1))
    torch.testing.assert_close(distances, brute.min(dim=2).values)
    assert idx.shape == (2, 50)


def test_welsch_irls_recovers_a_pose_from_exact_correspondences():
    src = torch.from_numpy(surface(400, 2))
    truth = torch.from_numpy(pose([8, -5, 4], [0.05, 0.02, -0.03]))
    tgt = src @ truth[:3, :3].T + truth[:3, 3]
    start = torch.eye(4, dtype=torch.float64)[None]
    found = welsch_irls(start, src, NearestTarget(tgt), [0.3] * 5 + [0.05] * 15)[0]
    assert rotation_error_deg(found.numpy(), truth.numpy()) < 1e-3
    np.testing.assert_allclose(found[:3, 3].numpy(), truth[:3, 3].numpy(), atol=1e-5)


def test_fixed_scale_fit_is_lowest_at_the_true_pose_and_matches_its_definition():
    src = torch.from_numpy(surface(300, 3))
    truth = pose([30, 10, -20], [0.1, 0.0, 0.0])
    tgt = torch.from_numpy(apply(truth, surface(300, 3)))
    poses = torch.from_numpy(np.stack([truth, np.eye(4), pose([0, 180, 0], [0, 0, 0]) @ truth]))
    costs = fixed_scale_fit(poses, src, NearestTarget(tgt), 0.05)
    assert int(costs.argmin()) == 0 and float(costs[0]) < 1e-6
    moved = src @ poses[1, :3, :3].T + poses[1, :3, 3]
    nearest = torch.cdist(moved, tgt).min(dim=1).values
    torch.testing.assert_close(costs[1], (1 - torch.exp(-nearest.square() / (2 * 0.05**2))).mean())


def test_options_are_checked():
    with pytest.raises(ValueError, match="coarse_points must be > 0"):
        RobustOptions(coarse_points=0)
    with pytest.raises(ValueError, match="doubt_ratio must be >= 1"):
        RobustOptions(doubt_ratio=0.5)
    with pytest.raises(ValueError, match="min_fitness must be in"):
        RobustOptions(min_fitness=1.5)
    with pytest.raises(ValueError, match="coarse_sides must be"):
        RobustOptions(coarse_sides=("both", "target"))
    with pytest.raises(ValueError, match="coarse_sides must be"):
        RobustOptions(coarse_sides=())
    assert RobustOptions(coarse_sides=["source"]).coarse_sides == ("source",)
    with pytest.raises(TypeError, match="unknown option"):
        METHODS.build({"name": "robust_adam", "options": {"startz": 3}})


@pytest.fixture(scope="module")
def partial_pair():
    """A partial source (700 points with x > -0.3) against the whole, moved surface (3000 points)."""
    whole = surface(3000, 7)
    truth = pose([40, -30, 25], [0.2, -0.1, 0.15])
    return whole[whole[:, 0] > -0.3][:700], apply(truth, whole), truth


def test_robust_registration_recovers_a_partial_view_and_reports_its_quality(partial_pair):
    src, tgt, truth = partial_pair
    result = METHODS.build({"name": "robust_adam", "num_points": 1024})(src, tgt)
    assert rotation_error_deg(result.transform, truth) < 0.5
    info = result.info
    assert info["fitness"] > 0.95 and 0 < info["inlier_rmse"] < info["fitness_threshold"]
    assert info["converged"] is True and info["confidence"] > 0.2 and info["rounds"] == 1
    assert info["starts"] == 4 * 2 and info["warnings"] == []  # 4 starts, each with both coarse losses


def test_a_doubtful_pose_gets_a_second_round_from_more_starts(partial_pair):
    src, tgt, truth = partial_pair
    result = METHODS.build({"name": "robust_adam", "num_points": 512, "options": {"max_cost": 1e-6}})(src, tgt)
    assert result.info["rounds"] == 2 and result.info["starts"] == 2 * (4 + 24)
    assert result.info["converged"] is False
    assert rotation_error_deg(result.transform, truth) < 1.0


def test_a_near_symmetric_pose_that_the_first_round_misses_is_found_by_the_second():
    """The bumpy ellipsoid is nearly symmetric under half-turns: from the 4 first-round starts
    the best candidate is the flipped pose, and only the doubt (a rival basin that costs
    about as much) sends the solver on to the 24 cube rotations that reach the truth."""
    whole = surface(3000, 7)
    src = whole[whole[:, 0] > -0.3][:700]
    truth = pose([120, -100, 45], [0.2, -0.1, 0.15])
    tgt = apply(truth, whole)
    never_doubt = {"doubt_ratio": 1.0, "min_fitness": 0.0, "max_cost": 1.0}
    first_round = METHODS.build({"name": "robust_adam", "num_points": 512, "options": never_doubt})(src, tgt)
    assert first_round.info["rounds"] == 1 and rotation_error_deg(first_round.transform, truth) > 90
    result = METHODS.build({"name": "robust_adam", "num_points": 512})(src, tgt)
    assert result.info["rounds"] == 2 and rotation_error_deg(result.transform, truth) < 1.0
    assert result.info["converged"] is False  # the flipped basin still scores within doubt_ratio


def test_init_is_applied_to_the_source_first(partial_pair):
    src, tgt, truth = partial_pair
    flip = pose([180, 0, 0], [0, 0, 0])
    single = {"name": "robust_adam", "num_points": 512, "options": {"starts": 1, "max_cost": 1.0}}
    result = METHODS.build(single)(apply(np.linalg.inv(flip), src), tgt, init=flip)
    assert rotation_error_deg(result.transform @ np.linalg.inv(flip), truth) < 0.5


def test_threads_are_restored_and_results_are_deterministic(partial_pair):
    src, tgt, _ = partial_pair
    before = torch.get_num_threads()
    method = METHODS.build({"name": "robust_adam", "num_points": 512, "threads": 1})
    first, second = method(src, tgt), method(src, tgt)
    assert torch.get_num_threads() == before
    np.testing.assert_array_equal(first.transform, second.transform)
    with torch_threads(None):
        assert torch.get_num_threads() == before


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_robust_registration_on_cuda_matches_cpu(partial_pair):
    src, tgt, _ = partial_pair
    on_cpu = METHODS.build({"name": "robust_adam", "num_points": 512})(src, tgt)
    on_gpu = METHODS.build({"name": "robust_adam", "num_points": 512, "device": "cuda"})(src, tgt)
    np.testing.assert_allclose(on_gpu.transform, on_cpu.transform, atol=1e-4)


def test_the_device_argument_is_checked():
    with pytest.raises(RuntimeError):
        METHODS.build({"name": "robust_adam", "device": "nonsense"})
