"""Tests for linereg.se3: round trips, conventions, gradients, broadcasting."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from linereg import se3

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 2e-5, torch.float64: 1e-12}


def _random_axes(n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    axes = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    return torch.nn.functional.normalize(axes, dim=-1).to(dtype)


def _twists(angle: float, dtype: torch.dtype, n: int = 8, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed + 1)
    v = torch.randn(n, 3, generator=generator, dtype=torch.float64).to(dtype)
    return torch.cat((_random_axes(n, dtype, seed) * angle, v), dim=-1)


def _rx(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)


def _ry(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def _rz(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _assert_rotation(R: torch.Tensor, atol: float) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0)


class TestSo3:
    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-4, 0.5, 2.0, math.pi - 1e-3])
    def test_round_trip(self, dtype, angle):
        omega = _random_axes(16, dtype) * angle
        R = se3.so3_exp(omega)
        _assert_rotation(R, atol=10 * TOL[dtype])
        torch.testing.assert_close(se3.so3_log(R), omega, atol=10 * TOL[dtype], rtol=0)

    def test_matches_scipy(self):
        omega = _random_axes(10, torch.float64) * torch.linspace(0.1, 3.0, 10, dtype=torch.float64)[:, None]
        expected = torch.from_numpy(Rotation.from_rotvec(omega.numpy()).as_matrix())
        torch.testing.assert_close(se3.so3_exp(omega), expected, atol=1e-12, rtol=0)

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_log_near_pi_recovers_rotation(self, dtype):
        omega = _random_axes(16, dtype) * (math.pi - 1e-6)
        R = se3.so3_exp(omega)
        log = se3.so3_log(R)
        assert torch.isfinite(log).all()
        torch.testing.assert_close(se3.so3_exp(log), R, atol=10 * TOL[dtype], rtol=0)
        torch.testing.assert_close(log.norm(dim=-1), omega.norm(dim=-1), atol=1e-5, rtol=0)

    def test_cardinality(self):
        omega = torch.randn(2, 5, 3)
        assert se3.so3_exp(omega).shape == (2, 5, 3, 3)
        assert se3.so3_log(se3.so3_exp(omega)).shape == (2, 5, 3)
        assert se3.so3_exp(torch.randn(3)).shape == (3, 3)

    def test_gradcheck_log(self):
        omega = _random_axes(4, torch.float64) * torch.tensor([[0.3], [1.0], [2.0], [2.9]], dtype=torch.float64)
        R = se3.so3_exp(omega).requires_grad_()
        assert torch.autograd.gradcheck(se3.so3_log, (R,))

    def test_gradcheck_exp(self):
        omega = (_random_axes(4, torch.float64) * 0.7).requires_grad_()
        assert torch.autograd.gradcheck(se3.so3_exp, (omega,))

    def test_exception(self):
        with pytest.raises(ValueError, match=r"omega must have shape \(\.\.\., 3\), got \(4, 2\)"):
            se3.so3_exp(torch.zeros(4, 2))
        with pytest.raises(TypeError, match=r"omega must be a torch\.Tensor"):
            se3.so3_exp(np.zeros(3))
        with pytest.raises(TypeError, match="floating-point"):
            se3.so3_exp(torch.zeros(3, dtype=torch.long))


class TestSe3ExpLog:
    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.0316, 0.0317, 1.0, 3.0, math.pi - 1e-4])
    def test_log_of_exp(self, dtype, angle):
        xi = _twists(angle, dtype)
        torch.testing.assert_close(se3.se3_log(se3.se3_exp(xi)), xi, atol=20 * TOL[dtype], rtol=0)

    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("angle", [1e-8, 0.5, math.pi - 1e-6])
    def test_exp_of_log(self, dtype, angle):
        T = se3.se3_exp(_twists(angle, torch.float64)).to(dtype)
        torch.testing.assert_close(se3.se3_exp(se3.se3_log(T)), T, atol=20 * TOL[dtype], rtol=0)

    def test_translation_uses_left_jacobian(self):
        # Quarter turn about z, v along x: t = V v with
        # V = I + (1 - cos)/th^2 W + (th - sin)/th^3 W^2.
        theta = math.pi / 2
        xi = torch.tensor([0.0, 0.0, theta, 1.0, 0.0, 0.0], dtype=torch.float64)
        T = se3.se3_exp(xi)
        expected_t = torch.tensor([math.sin(theta) / theta, (1 - math.cos(theta)) / theta, 0.0], dtype=torch.float64)
        torch.testing.assert_close(T[:3, 3], expected_t, atol=1e-14, rtol=0)
        torch.testing.assert_close(T[:3, :3], _rz(theta), atol=1e-14, rtol=0)
        torch.testing.assert_close(T[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))

    def test_pure_translation(self):
        xi = torch.tensor([0.0, 0.0, 0.0, 0.1, -0.2, 0.3])
        T = se3.se3_exp(xi)
        torch.testing.assert_close(T[:3, :3], torch.eye(3))
        torch.testing.assert_close(T[:3, 3], xi[3:])

    def test_series_and_closed_form_agree_at_threshold(self):
        # Both sides of the Taylor switch (theta^2 = 1e-3) give the same exponential.
        angles = torch.tensor([math.sqrt(1e-3) * (1 - 1e-9), math.sqrt(1e-3) * (1 + 1e-9)], dtype=torch.float64)
        xi = torch.cat(
            (
                angles[:, None] * torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64),
                torch.ones(2, 3, dtype=torch.float64),
            ),
            -1,
        )
        T = se3.se3_exp(xi)
        torch.testing.assert_close(T[0], T[1], atol=1e-10, rtol=0)

    def test_cardinality(self):
        xi = torch.randn(2, 3, 6)
        assert se3.se3_exp(xi).shape == (2, 3, 4, 4)
        assert se3.se3_log(se3.se3_exp(xi)).shape == (2, 3, 6)
        assert se3.se3_exp(torch.randn(6)).shape == (4, 4)

    def test_gradcheck_exp(self):
        xi = _twists(0.8, torch.float64, n=3).requires_grad_()
        assert torch.autograd.gradcheck(se3.se3_exp, (xi,))

    def test_gradcheck_exp_small_angle(self):
        xi = _twists(1e-3, torch.float64, n=3).requires_grad_()
        assert torch.autograd.gradcheck(se3.se3_exp, (xi,))

    def test_gradcheck_log(self):
        T = se3.se3_exp(_twists(1.2, torch.float64, n=3)).requires_grad_()
        assert torch.autograd.gradcheck(se3.se3_log, (T,))

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_finite_gradient_at_zero(self, dtype):
        xi = torch.zeros(2, 6, dtype=dtype, requires_grad=True)
        se3.se3_exp(xi).square().sum().backward()
        assert torch.isfinite(xi.grad).all()
        T = torch.eye(4, dtype=dtype).repeat(2, 1, 1).requires_grad_()
        se3.se3_log(T).sum().backward()
        assert torch.isfinite(T.grad).all()

    def test_gradient_at_zero_is_the_generator(self):
        # d exp(xi) / d xi at 0 is hat(omega) plus v in the last column.
        xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        jacobian = torch.autograd.functional.jacobian(se3.se3_exp, xi)
        expected_z = torch.zeros(4, 4, dtype=torch.float64)
        expected_z[0, 1], expected_z[1, 0] = -1.0, 1.0
        torch.testing.assert_close(jacobian[..., 2], expected_z)
        expected_vx = torch.zeros(4, 4, dtype=torch.float64)
        expected_vx[0, 3] = 1.0
        torch.testing.assert_close(jacobian[..., 3], expected_vx)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"xi must have shape \(\.\.\., 6\), got \(3,\)"):
            se3.se3_exp(torch.zeros(3))
        with pytest.raises(ValueError, match=r"T must have shape \(\.\.\., 4, 4\), got \(3, 3\)"):
            se3.se3_log(torch.eye(3))


class TestMatrixHelpers:
    def test_rt_round_trip(self):
        R = se3.so3_exp(torch.randn(5, 3))
        t = torch.randn(5, 3)
        T = se3.rt_to_matrix(R, t)
        assert T.shape == (5, 4, 4)
        torch.testing.assert_close(T[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(5, 4))
        R_back, t_back = se3.matrix_to_rt(T)
        torch.testing.assert_close(R_back, R)
        torch.testing.assert_close(t_back, t)

    def test_rt_to_matrix_broadcasts(self):
        T = se3.rt_to_matrix(torch.eye(3), torch.randn(4, 3))
        assert T.shape == (4, 4, 4)
        torch.testing.assert_close(T[:, :3, :3], torch.eye(3).expand(4, 3, 3))

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_inverse_and_compose(self, dtype):
        T_ab = se3.se3_exp(_twists(1.0, dtype, n=4, seed=1))
        T_bc = se3.se3_exp(_twists(2.0, dtype, n=4, seed=2))
        eye = torch.eye(4, dtype=dtype).expand(4, 4, 4)
        torch.testing.assert_close(se3.compose(T_ab, se3.inverse(T_ab)), eye, atol=10 * TOL[dtype], rtol=0)
        torch.testing.assert_close(se3.compose(se3.inverse(T_ab), T_ab), eye, atol=10 * TOL[dtype], rtol=0)
        torch.testing.assert_close(se3.inverse(T_ab), torch.linalg.inv(T_ab), atol=10 * TOL[dtype], rtol=0)
        T_ac = se3.compose(T_ab, T_bc)
        torch.testing.assert_close(
            se3.inverse(T_ac),
            se3.compose(se3.inverse(T_bc), se3.inverse(T_ab)),
            atol=10 * TOL[dtype],
            rtol=0,
        )

    def test_convention_compose_applies_right_first(self):
        points_c = torch.randn(7, 3, dtype=torch.float64)
        T_ab = se3.se3_exp(_twists(1.0, torch.float64, n=1, seed=3))[0]
        T_bc = se3.se3_exp(_twists(0.4, torch.float64, n=1, seed=4))[0]
        points_b = se3.transform_points(T_bc, points_c)
        torch.testing.assert_close(
            se3.transform_points(se3.compose(T_ab, T_bc), points_c),
            se3.transform_points(T_ab, points_b),
        )


class TestTransformPoints:
    def test_matches_homogeneous_product(self):
        T = se3.se3_exp(_twists(1.0, torch.float64, n=3))
        points = torch.randn(3, 10, 3, dtype=torch.float64)
        homogeneous = torch.cat((points, torch.ones(3, 10, 1, dtype=torch.float64)), -1)
        expected = (homogeneous @ T.transpose(-1, -2))[..., :3]
        torch.testing.assert_close(se3.transform_points(T, points), expected)

    def test_convention_column_vectors(self):
        T = se3.rt_to_matrix(_rz(math.pi / 2), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
        out = se3.transform_points(T, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
        torch.testing.assert_close(out, torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64))

    def test_broadcasting(self):
        T = se3.se3_exp(_twists(1.0, torch.float32, n=2))
        single_cloud = torch.randn(5, 3)
        assert se3.transform_points(T, single_cloud).shape == (2, 5, 3)
        assert se3.transform_points(T[0], torch.randn(4, 5, 3)).shape == (4, 5, 3)
        batched = se3.transform_points(T[:, None], torch.randn(2, 3, 5, 3))
        assert batched.shape == (2, 3, 5, 3)
        torch.testing.assert_close(se3.transform_points(T, single_cloud)[1], se3.transform_points(T[1], single_cloud))

    def test_empty_point_set(self):
        points = torch.zeros(2, 0, 3)
        out = se3.transform_points(torch.eye(4).expand(2, 4, 4), points)
        assert out.shape == (2, 0, 3)

    def test_normals_ignore_translation(self):
        T = se3.rt_to_matrix(_rz(math.pi / 2), torch.tensor([5.0, 5.0, 5.0], dtype=torch.float64))
        normals = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
        torch.testing.assert_close(
            se3.transform_normals(T, normals), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
        )

    def test_gradcheck(self):
        T = se3.se3_exp(_twists(0.5, torch.float64, n=2)).requires_grad_()
        points = torch.randn(2, 4, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(se3.transform_points, (T, points))

    def test_exception(self):
        with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 3\), got \(5, 2\)"):
            se3.transform_points(torch.eye(4), torch.zeros(5, 2))
        with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., N, 3\), got \(3,\)"):
            se3.transform_points(torch.eye(4), torch.zeros(3))
        with pytest.raises(ValueError, match=r"T must have shape \(\.\.\., 4, 4\), got \(3, 4\)"):
            se3.transform_points(torch.zeros(3, 4), torch.zeros(5, 3))


class TestEuler:
    @pytest.mark.parametrize("angles", [(0.3, -0.5, 1.1), (0.0, 0.0, 0.0), (0.7, 0.2, -2.5)])
    def test_convention_xyz_is_rx_ry_rz(self, angles):
        expected = _rx(angles[0]) @ _ry(angles[1]) @ _rz(angles[2])
        R = se3.euler_to_rotmat(torch.tensor(angles, dtype=torch.float64))
        torch.testing.assert_close(R, expected, atol=1e-14, rtol=0)

    def test_convention_zyx(self):
        angles = (0.3, -0.5, 1.1)
        expected = _rz(angles[0]) @ _ry(angles[1]) @ _rx(angles[2])
        R = se3.euler_to_rotmat(torch.tensor(angles, dtype=torch.float64), "zyx")
        torch.testing.assert_close(R, expected, atol=1e-14, rtol=0)

    def test_cardinality_and_dtype(self):
        R = se3.euler_to_rotmat(torch.rand(4, 2, 3, dtype=torch.float32))
        assert R.shape == (4, 2, 3, 3) and R.dtype == torch.float32
        _assert_rotation(R, atol=1e-5)

    @pytest.mark.parametrize("convention", ["xy", "xxy", "abc", "XYZ"])
    def test_exception(self, convention):
        with pytest.raises(ValueError, match="convention must be three axis letters"):
            se3.euler_to_rotmat(torch.zeros(3), convention)


class TestRotationAngle:
    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("angle", [0.0, 1e-7, 1e-3, 0.5, math.pi / 2, 3.0, math.pi - 1e-5, math.pi])
    def test_values(self, dtype, angle):
        omega = _random_axes(8, torch.float64) * angle
        R = se3.so3_exp(omega).to(dtype)
        expected = torch.full((8,), angle, dtype=dtype)
        torch.testing.assert_close(se3.rotation_angle(R), expected, atol=10 * TOL[dtype], rtol=0)

    def test_more_accurate_than_arccos_near_zero(self):
        R = se3.so3_exp(torch.tensor([1e-5, 0.0, 0.0]))
        naive = torch.arccos(torch.clamp((R.diagonal().sum() - 1) / 2, -1, 1))
        assert naive == 0.0
        torch.testing.assert_close(se3.rotation_angle(R), torch.tensor(1e-5), atol=1e-11, rtol=0)

    def test_gradients(self):
        omega = (_random_axes(3, torch.float64) * 1.3).requires_grad_()
        assert torch.autograd.gradcheck(lambda w: se3.rotation_angle(se3.so3_exp(w)), (omega,))
        for matrix in (torch.eye(3, dtype=torch.float64), _rx(math.pi)):
            R = matrix.clone().requires_grad_()
            se3.rotation_angle(R).backward()
            assert torch.isfinite(R.grad).all()

    def test_never_nan_on_non_orthonormal_input(self):
        R = torch.eye(3) * 1.5
        assert torch.isfinite(se3.rotation_angle(R))


DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]


@pytest.mark.parametrize("device", DEVICES)
def test_device_and_dtype_follow_input(device):
    xi = torch.randn(3, 6, dtype=torch.float64, device=device)
    T = se3.se3_exp(xi)
    outputs = [
        T,
        se3.se3_log(T),
        se3.inverse(T),
        se3.transform_points(T, torch.randn(3, 5, 3, dtype=torch.float64, device=device)),
        se3.rotation_angle(T[:, :3, :3]),
        se3.euler_to_rotmat(xi[:, :3]),
    ]
    for output in outputs:
        assert output.device.type == device
        assert output.dtype == torch.float64
