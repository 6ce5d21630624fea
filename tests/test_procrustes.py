"""Tests for linereg.procrustes: exact recovery, weights, degenerate inputs, gradients."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import roma
import torch

from linereg import procrustes, random_poses, se3
from linereg.procrustes import procrustes_naive, weighted_procrustes, weighted_procrustes_numpy

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _problem(batch_size: int = 4, num_points: int = 64, dtype=torch.float64, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    T = random_poses.random_transform_paper(batch_size, seed, max_angle_deg=90.0, dtype=torch.float64)
    src = torch.randn(batch_size, num_points, 3, generator=generator, dtype=torch.float64)
    tgt = se3.transform_points(T, src)
    return src.to(dtype), tgt.to(dtype), T.to(dtype)


def _assert_proper_rotations(T: torch.Tensor, atol: float) -> None:
    R = T[..., :3, :3]
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    det = torch.linalg.det(R)
    torch.testing.assert_close(det, torch.ones_like(det), atol=atol, rtol=0)


def _solve_quietly(*args, **kwargs) -> procrustes.ProcrustesResult:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return weighted_procrustes(*args, **kwargs)


class TestRecovery:
    @pytest.mark.parametrize("dtype", DTYPES)
    def test_exact_without_noise(self, dtype):
        src, tgt, T = _problem(dtype=dtype)
        result = _solve_quietly(src, tgt)
        assert result.transform.dtype == dtype and result.transform.shape == (4, 4, 4)
        assert result.valid.dtype == torch.bool and result.valid.all()
        torch.testing.assert_close(result.transform, T, atol=20 * TOL[dtype], rtol=0)

    def test_large_rotation(self):
        T = se3.rt_to_matrix(
            random_poses.random_axis_angle_rotation(
                8, 0, min_angle_deg=170.0, max_angle_deg=180.0, dtype=torch.float64
            ),
            torch.randn(8, 3, dtype=torch.float64),
        )
        src = torch.randn(8, 30, 3, dtype=torch.float64)
        result = _solve_quietly(src, se3.transform_points(T, src))
        torch.testing.assert_close(result.transform, T, atol=1e-10, rtol=0)

    def test_approximate_with_noise(self):
        src, tgt, T = _problem(num_points=500)
        noisy = tgt + 0.01 * torch.randn(tgt.shape, generator=torch.Generator().manual_seed(1), dtype=tgt.dtype)
        result = _solve_quietly(src, noisy)
        rotation_error = torch.rad2deg(se3.rotation_angle(T[:, :3, :3].transpose(1, 2) @ result.transform[:, :3, :3]))
        assert rotation_error.max() < 0.5
        assert (result.transform[:, :3, 3] - T[:, :3, 3]).norm(dim=-1).max() < 0.01

    def test_zero_weight_outliers_are_ignored(self):
        src, tgt, T = _problem()
        weights = torch.ones(src.shape[:2], dtype=src.dtype)
        weights[:, ::3] = 0.0
        corrupted = tgt.clone()
        corrupted[:, ::3] += 10.0 * torch.randn_like(corrupted[:, ::3])
        result = _solve_quietly(src, corrupted, weights)
        torch.testing.assert_close(result.transform, T, atol=1e-12, rtol=0)
        assert not torch.allclose(_solve_quietly(src, corrupted).transform, T, atol=1e-3)

    def test_weights_are_scale_invariant(self):
        src, tgt, _ = _problem()
        tgt = tgt + 0.05 * torch.randn_like(tgt)
        weights = torch.rand(src.shape[:2], dtype=src.dtype)
        first = _solve_quietly(src, tgt, weights).transform
        torch.testing.assert_close(_solve_quietly(src, tgt, 1e3 * weights).transform, first)

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_matches_naive(self, dtype):
        src, tgt, _ = _problem(dtype=dtype, seed=3)
        tgt = tgt + 0.1 * torch.randn_like(tgt)
        weights = torch.rand(src.shape[:2], dtype=dtype)
        torch.testing.assert_close(
            _solve_quietly(src, tgt, weights).transform,
            procrustes_naive(src, tgt, weights),
            atol=50 * TOL[dtype],
            rtol=0,
        )

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_numpy_twin_matches_the_torch_solver_and_the_naive_one(self, seed):
        """The numpy solver of the register default and the torch solver are twins: the same
        transform on random weighted problems, and the identity where the weights sum to zero."""
        src, tgt, _ = _problem(batch_size=5, num_points=40, seed=seed)
        tgt = tgt + 0.05 * torch.randn(tgt.shape, generator=torch.Generator().manual_seed(seed), dtype=tgt.dtype)
        weights = torch.rand(src.shape[:2], generator=torch.Generator().manual_seed(seed + 10), dtype=src.dtype)
        weights[4] = 0.0
        rotations, translations, valid = weighted_procrustes_numpy(src.numpy(), tgt.numpy(), weights.numpy())
        expected = _solve_quietly(src[:4], tgt[:4], weights[:4]).transform
        torch.testing.assert_close(torch.from_numpy(rotations[:4]), expected[:, :3, :3], atol=1e-9, rtol=0)
        torch.testing.assert_close(torch.from_numpy(translations[:4]), expected[:, :3, 3], atol=1e-9, rtol=0)
        torch.testing.assert_close(expected, procrustes_naive(src[:4], tgt[:4], weights[:4]), atol=1e-9, rtol=0)
        assert valid.tolist() == [True] * 4 + [False]
        assert (rotations[4] == np.eye(3)).all() and (translations[4] == 0).all()

    def test_coplanar_points_give_exact_proper_rotation(self):
        src, _, T = _problem()
        src[..., 2] = 0.0
        result = _solve_quietly(src, se3.transform_points(T, src))
        assert result.valid.all()
        _assert_proper_rotations(result.transform, atol=1e-12)
        torch.testing.assert_close(result.transform, T, atol=1e-12, rtol=0)

    def test_reflection_is_never_returned(self):
        src, _, _ = _problem()
        mirrored = src * torch.tensor([1.0, 1.0, -1.0], dtype=src.dtype)
        result = _solve_quietly(src, mirrored)
        _assert_proper_rotations(result.transform, atol=1e-12)
        assert (procrustes_naive(src, mirrored)[:, :3, :3].det() > 0).all()


class TestDegenerate:
    def _check_no_nan_with_gradients(self, src, tgt, weights=None):
        src = src.clone().requires_grad_()
        tgt = tgt.clone().requires_grad_()
        if weights is not None:
            weights = weights.clone().requires_grad_()
        with pytest.warns(UserWarning, match="weighted_procrustes") as record:
            result = weighted_procrustes(src, tgt, weights)
        assert torch.isfinite(result.transform).all()
        (result.transform.square().sum()).backward()
        for tensor in (src, tgt, weights):
            if tensor is not None:
                assert torch.isfinite(tensor.grad).all()
        return result, " ".join(str(w.message) for w in record)

    def test_all_zero_weights(self):
        src, tgt, T = _problem(batch_size=3)
        weights = torch.ones(src.shape[:2], dtype=src.dtype)
        weights[1] = 0.0
        result, message = self._check_no_nan_with_gradients(src, tgt, weights)
        assert result.valid.tolist() == [True, False, True]
        assert "1 of 3 sample(s) fell back" in message
        torch.testing.assert_close(result.transform[1, :3, :3], torch.eye(3, dtype=src.dtype))
        expected_t = tgt[1].mean(0) - src[1].mean(0)
        torch.testing.assert_close(result.transform[1, :3, 3], expected_t)
        torch.testing.assert_close(result.transform[[0, 2]], T[[0, 2]], atol=1e-12, rtol=0)

    @pytest.mark.parametrize("bad_weight", [float("nan"), -1.0, float("inf")])
    def test_unusable_weights(self, bad_weight):
        src, tgt, _ = _problem(batch_size=2)
        weights = torch.ones(src.shape[:2], dtype=src.dtype)
        weights[0, 5] = bad_weight
        result, message = self._check_no_nan_with_gradients(src, tgt, weights)
        assert result.valid.tolist() == [False, True]
        assert "1 of 2 sample(s) fell back" in message

    def test_tiny_weight_sum_below_eps(self):
        src, tgt, _ = _problem(batch_size=2)
        weights = torch.full(src.shape[:2], 1e-9, dtype=src.dtype)
        result, _ = self._check_no_nan_with_gradients(src, tgt, weights)
        assert not result.valid.any()
        assert _solve_quietly(src, tgt, weights, eps=1e-12).valid.all()

    def test_nan_points(self):
        src, tgt, _ = _problem(batch_size=2)
        src[1, 3, 0] = float("nan")
        result, _ = self._check_no_nan_with_gradients(src, tgt)
        assert result.valid.tolist() == [True, False]
        torch.testing.assert_close(result.transform[1], torch.eye(4, dtype=src.dtype))

    def test_single_point(self):
        src = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
        tgt = torch.tensor([[[0.5, -1.0, 2.0]]], dtype=torch.float64)
        result, _ = self._check_no_nan_with_gradients(src, tgt)
        assert not result.valid.any()
        expected = se3.rt_to_matrix(torch.eye(3, dtype=torch.float64), tgt[0, 0] - src[0, 0])
        torch.testing.assert_close(result.transform[0], expected)

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_collinear_points(self, dtype):
        direction = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
        src = (torch.linspace(-1.0, 1.0, 20, dtype=torch.float64)[:, None] * direction)[None]
        T = random_poses.random_transform_paper(1, 0, dtype=torch.float64)
        tgt = se3.transform_points(T, src)
        result, message = self._check_no_nan_with_gradients(src.to(dtype), tgt.to(dtype))
        assert "rank-deficient" in message
        assert not result.valid.any()
        _assert_proper_rotations(result.transform.double(), atol=1e-5)
        # Not unique, but still optimal: the line maps onto its image.
        torch.testing.assert_close(se3.transform_points(result.transform.double(), src), tgt, atol=1e-4, rtol=0)

    def test_solver_failure_falls_back_per_sample(self, monkeypatch):
        solve = roma.special_procrustes
        calls = []

        def flaky(M, *args, **kwargs):
            calls.append(M.shape)
            if M.ndim == 3 or len(calls) == 3:
                raise torch.linalg.LinAlgError("simulated failure")
            return solve(M, *args, **kwargs)

        monkeypatch.setattr(roma, "special_procrustes", flaky)
        src, tgt, T = _problem(batch_size=3)
        with pytest.warns(UserWarning, match="1 of 3 sample"):
            result = weighted_procrustes(src, tgt)
        assert result.valid.tolist() == [True, False, True]
        torch.testing.assert_close(result.transform[[0, 2]], T[[0, 2]], atol=1e-12, rtol=0)
        torch.testing.assert_close(result.transform[1, :3, :3], torch.eye(3, dtype=src.dtype))


class TestGradients:
    def test_gradcheck(self):
        src, tgt, _ = _problem(batch_size=2, num_points=6)
        tgt = tgt + 0.1 * torch.randn_like(tgt)
        weights = torch.rand(2, 6, dtype=torch.float64) + 0.1
        inputs = tuple(x.clone().requires_grad_() for x in (src, tgt, weights))
        assert torch.autograd.gradcheck(lambda *xs: weighted_procrustes(*xs).transform, inputs)

    def test_gradients_match_naive(self):
        src, tgt, _ = _problem(batch_size=3, num_points=20, seed=5)
        tgt = tgt + 0.1 * torch.randn_like(tgt)
        weights = torch.rand(3, 20, dtype=torch.float64)
        probe = torch.randn(3, 4, 4, dtype=torch.float64)
        gradients = []
        for solver in (lambda *xs: weighted_procrustes(*xs).transform, procrustes_naive):
            inputs = [x.clone().requires_grad_() for x in (src, tgt, weights)]
            (solver(*inputs) * probe).sum().backward()
            gradients.append([x.grad for x in inputs])
        for ours, naive in zip(*gradients, strict=True):
            torch.testing.assert_close(ours, naive, atol=1e-9, rtol=1e-7)

    def test_float32_input_float32_gradient(self):
        src, tgt, _ = _problem(dtype=torch.float32)
        src.requires_grad_()
        _solve_quietly(src, tgt).transform.sum().backward()
        assert src.grad.dtype == torch.float32 and torch.isfinite(src.grad).all()


class TestValidation:
    def test_shape_mismatch(self):
        with pytest.raises(ValueError, match=r"tgt must have the shape of src \(2, 5, 3\), got \(2, 4, 3\)"):
            weighted_procrustes(torch.zeros(2, 5, 3), torch.zeros(2, 4, 3))

    def test_unbatched(self):
        with pytest.raises(ValueError, match=r"src must have shape \(B, N, 3\), got \(5, 3\)"):
            weighted_procrustes(torch.zeros(5, 3), torch.zeros(5, 3))

    def test_weights_shape(self):
        with pytest.raises(ValueError, match=r"weights must have shape \(B, N\) = \(2, 5\), got \(2, 4\)"):
            weighted_procrustes(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3), torch.ones(2, 4))

    def test_types(self):
        with pytest.raises(TypeError, match="src must have a floating-point dtype"):
            weighted_procrustes(torch.zeros(2, 5, 3, dtype=torch.long), torch.zeros(2, 5, 3))
        with pytest.raises(TypeError, match="weights must be a torch"):
            weighted_procrustes(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3), [1.0] * 5)
