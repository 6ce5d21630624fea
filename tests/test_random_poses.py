"""Tests for linereg.random_poses: ranges, distributions, reproducibility, dtype/device."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from linereg import random_poses, se3


def _euler_xyz_angles(R: torch.Tensor) -> torch.Tensor:
    """Angles (a0, a1, a2) of R = Rx(a0) Ry(a1) Rz(a2), valid for |a1| < pi/2."""
    a1 = torch.asin(torch.clamp(R[:, 0, 2], -1.0, 1.0))
    a0 = torch.atan2(-R[:, 1, 2], R[:, 2, 2])
    a2 = torch.atan2(-R[:, 0, 1], R[:, 0, 0])
    return torch.stack((a0, a1, a2), dim=-1)


def _assert_rotations(R: torch.Tensor, atol: float) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    det = torch.linalg.det(R)
    torch.testing.assert_close(det, torch.ones_like(det), atol=atol, rtol=0)


EULER_SAMPLERS = [
    (random_poses.random_transform_paper, {"max_angle_deg": 30.0, "max_translation": 0.2}),
    (random_poses.random_transform_rpmnet, {"rot_mag_deg": 30.0, "trans_mag": 0.5}),
]


class TestEulerTransforms:
    @pytest.mark.parametrize(("sampler", "ranges"), EULER_SAMPLERS)
    def test_ranges_respected(self, sampler, ranges):
        T = sampler(2000, 0, dtype=torch.float64, **ranges)
        max_angle, max_translation = ranges.values()
        assert T.shape == (2000, 4, 4)
        _assert_rotations(T[:, :3, :3], atol=1e-12)
        torch.testing.assert_close(T[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(2000, 4))
        angles = torch.rad2deg(_euler_xyz_angles(T[:, :3, :3]))
        assert angles.min() >= -1e-9 and angles.max() <= max_angle + 1e-9
        # Each range is covered (not a constant or a narrower interval).
        assert angles.min() < 0.05 * max_angle and angles.max() > 0.95 * max_angle
        t = T[:, :3, 3]
        assert t.abs().max() <= max_translation
        assert t.min() < -0.9 * max_translation and t.max() > 0.9 * max_translation

    def test_paper_defaults(self):
        T = random_poses.random_transform_paper(1000, 3, dtype=torch.float64)
        assert torch.rad2deg(_euler_xyz_angles(T[:, :3, :3])).max() <= 45.0 + 1e-9
        assert T[:, :3, 3].abs().max() <= 0.2
        assert T[:, :3, 3].abs().max() > 0.19

    def test_rpmnet_defaults(self):
        T = random_poses.random_transform_rpmnet(1000, 3, dtype=torch.float64)
        assert T[:, :3, 3].abs().max() <= 0.5
        assert T[:, :3, 3].abs().max() > 0.45

    def test_rpmnet_ground_truth_is_the_inverse(self):
        perturbation = random_poses.random_transform_rpmnet(4, 1, dtype=torch.float64)
        reference = torch.randn(4, 20, 3, dtype=torch.float64)
        source = se3.transform_points(perturbation, reference)
        T_ref_src = se3.inverse(perturbation)
        torch.testing.assert_close(se3.transform_points(T_ref_src, source), reference)


ALL_SAMPLERS = [
    lambda n, g, **kw: random_poses.random_transform_paper(n, g, **kw),
    lambda n, g, **kw: random_poses.random_transform_rpmnet(n, g, **kw),
    lambda n, g, **kw: random_poses.random_rotation(n, g, **kw),
    lambda n, g, **kw: random_poses.random_axis_angle_rotation(n, g, min_angle_deg=-75.0, max_angle_deg=75.0, **kw),
]


class TestReproducibility:
    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_int_seed(self, sampler):
        torch.testing.assert_close(sampler(5, 7), sampler(5, 7), rtol=0, atol=0)
        assert not torch.allclose(sampler(5, 7), sampler(5, 8))

    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_torch_generator(self, sampler):
        first = sampler(5, torch.Generator().manual_seed(11))
        second = sampler(5, torch.Generator().manual_seed(11))
        torch.testing.assert_close(first, second, rtol=0, atol=0)
        assert not torch.allclose(first, sampler(5, torch.Generator().manual_seed(12)))

    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_numpy_generator(self, sampler):
        first = sampler(5, np.random.default_rng(11))
        second = sampler(5, np.random.default_rng(11))
        torch.testing.assert_close(first, second, rtol=0, atol=0)
        assert not torch.allclose(first, sampler(5, np.random.default_rng(12)))

    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_none_uses_global_torch_seed(self, sampler):
        torch.manual_seed(3)
        first = sampler(4, None)
        torch.manual_seed(3)
        torch.testing.assert_close(sampler(4, None), first, rtol=0, atol=0)

    def test_generator_advances(self):
        generator = torch.Generator().manual_seed(0)
        first = random_poses.random_rotation(3, generator)
        assert not torch.allclose(first, random_poses.random_rotation(3, generator))

    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_same_seed_same_values_across_dtypes(self, sampler):
        single = sampler(5, 2, dtype=torch.float32)
        double = sampler(5, 2, dtype=torch.float64)
        assert single.dtype == torch.float32 and double.dtype == torch.float64
        torch.testing.assert_close(single, double.float())

    @pytest.mark.parametrize("sampler", ALL_SAMPLERS)
    def test_empty_batch(self, sampler):
        assert sampler(0, 0).shape[0] == 0

    @pytest.mark.parametrize("bad", ["seed", 1.5, True])
    def test_bad_generator(self, bad):
        with pytest.raises(TypeError, match=r"generator must be a torch\.Generator"):
            random_poses.random_rotation(2, bad)

    def test_bad_batch_size(self):
        with pytest.raises(ValueError, match="batch_size must be >= 0, got -1"):
            random_poses.random_transform_paper(-1)
        with pytest.raises(TypeError, match="batch_size must be an int, got float"):
            random_poses.random_rotation(2.0)


class TestRandomRotation:
    def test_valid_rotations(self):
        _assert_rotations(random_poses.random_rotation(500, 0, dtype=torch.float64), atol=1e-12)

    def test_uniform_on_so3(self):
        # Haar measure: E[R] = 0, and the angle has density (1 - cos a) / pi, so
        # E[angle] = pi/2 + 2/pi and P(angle < pi/2) = (pi/2 - 1)/pi.
        R = random_poses.random_rotation(20000, 0, dtype=torch.float64)
        assert R.mean(0).abs().max() < 0.03
        angles = se3.rotation_angle(R)
        assert abs(angles.mean().item() - (math.pi / 2 + 2 / math.pi)) < 0.02
        assert abs((angles < math.pi / 2).double().mean().item() - (math.pi / 2 - 1) / math.pi) < 0.01


class TestAxisAngleRotation:
    def test_angle_range(self):
        R = random_poses.random_axis_angle_rotation(
            3000, 0, min_angle_deg=-75.0, max_angle_deg=75.0, dtype=torch.float64
        )
        _assert_rotations(R, atol=1e-12)
        angles = torch.rad2deg(se3.rotation_angle(R))
        assert angles.max() <= 75.0 + 1e-9
        assert angles.max() > 74.0 and angles.min() < 1.0

    def test_positive_range_and_axis_spread(self):
        R = random_poses.random_axis_angle_rotation(
            3000, 1, min_angle_deg=20.0, max_angle_deg=30.0, dtype=torch.float64
        )
        angles = torch.rad2deg(se3.rotation_angle(R))
        assert angles.min() >= 20.0 - 1e-9 and angles.max() <= 30.0 + 1e-9
        axes = torch.nn.functional.normalize(se3.so3_log(R), dim=-1)
        assert axes.mean(0).abs().max() < 0.06
        torch.testing.assert_close(
            axes.square().mean(0), torch.full((3,), 1 / 3, dtype=torch.float64), atol=0.03, rtol=0
        )

    def test_fixed_angle(self):
        R = random_poses.random_axis_angle_rotation(10, 0, min_angle_deg=40.0, max_angle_deg=40.0)
        torch.testing.assert_close(torch.rad2deg(se3.rotation_angle(R)), torch.full((10,), 40.0))

    def test_exception(self):
        with pytest.raises(ValueError, match="max_angle_deg must be >= min_angle_deg"):
            random_poses.random_axis_angle_rotation(2, 0, min_angle_deg=10.0, max_angle_deg=5.0)


@pytest.mark.parametrize("device", ["cpu", *(["cuda"] if torch.cuda.is_available() else [])])
def test_device(device):
    assert random_poses.random_transform_paper(2, 0, device=device).device.type == device
    assert random_poses.random_rotation(2, 0, device=device).device.type == device
