"""Tests for linereg.checks: error types and messages."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

from linereg.checks import (
    as_rigid_transform,
    check_lengths,
    check_points,
    check_same_batch,
    check_transform,
    nearest_rotation,
)
from linereg.se3 import se3_exp


class TestCheckPoints:
    @pytest.mark.parametrize(
        "points",
        [
            torch.zeros(5, 3),
            torch.zeros(2, 5, 3),
            np.zeros((5, 3), dtype=np.float32),
            torch.zeros(2, 5, 3, dtype=torch.float64),
        ],
    )
    def test_accepts(self, points):
        check_points(points)

    def test_not_an_array(self):
        with pytest.raises(TypeError, match=r"src must be a torch\.Tensor or numpy array, got list"):
            check_points([[0.0, 0.0, 0.0]], "src")

    @pytest.mark.parametrize("points", [torch.zeros(5, 3, dtype=torch.long), np.zeros((5, 3), dtype=np.int32)])
    def test_non_float(self, points):
        with pytest.raises(TypeError, match="src must have a floating-point dtype, got"):
            check_points(points, "src")

    def test_wrong_last_axis(self):
        with pytest.raises(ValueError, match=r"src must have shape \(N, 3\) or \(B, N, 3\), got \(5, 2\)"):
            check_points(torch.zeros(5, 2), "src")

    def test_wrong_rank(self):
        with pytest.raises(ValueError, match=r"got \(1, 2, 5, 3\)"):
            check_points(torch.zeros(1, 2, 5, 3), "src")

    def test_batched_flag(self):
        with pytest.raises(ValueError, match=r"tgt must have shape \(B, N, 3\), got \(5, 3\)"):
            check_points(torch.zeros(5, 3), "tgt", batched=True)
        with pytest.raises(ValueError, match=r"tgt must have shape \(N, 3\), got \(1, 5, 3\)"):
            check_points(torch.zeros(1, 5, 3), "tgt", batched=False)

    def test_other_dimension(self):
        check_points(torch.zeros(5, 6), dim=6)
        with pytest.raises(ValueError, match=r"must have shape \(N, 6\) or \(B, N, 6\), got \(5, 3\)"):
            check_points(torch.zeros(5, 3), dim=6)

    def test_empty(self):
        with pytest.raises(ValueError, match=r"src must hold at least 1 point\(s\), got 0"):
            check_points(torch.zeros(2, 0, 3), "src")
        with pytest.raises(ValueError, match=r"at least 3 point\(s\), got 2"):
            check_points(torch.zeros(2, 3), "src", min_points=3)

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite(self, bad):
        points = torch.zeros(2, 5, 3)
        points[1, 2, 0] = bad
        with pytest.raises(ValueError, match="src contains NaN or Inf coordinates"):
            check_points(points, "src")
        with pytest.raises(ValueError, match="src contains NaN or Inf coordinates"):
            check_points(points.numpy(), "src")


class TestCheckTransform:
    def test_accepts(self):
        check_transform(torch.eye(4))
        check_transform(se3_exp(torch.randn(2, 3, 6, dtype=torch.float64)), rigid_atol=1e-9)
        check_transform(np.eye(4), rigid_atol=1e-9)

    def test_not_an_array(self):
        with pytest.raises(TypeError, match=r"T_pred must be a torch\.Tensor or numpy array, got tuple"):
            check_transform((1, 2), "T_pred")

    @pytest.mark.parametrize("shape", [(3, 4), (4,), (2, 4, 3)])
    def test_wrong_shape(self, shape):
        with pytest.raises(
            ValueError,
            match=re.escape(f"T_pred must have shape (..., 4, 4), got {shape}"),
        ):
            check_transform(torch.zeros(shape), "T_pred")

    def test_non_finite(self):
        transform = torch.eye(4).repeat(2, 1, 1)
        transform[1, 0, 3] = float("nan")
        with pytest.raises(ValueError, match="T_pred contains NaN or Inf entries"):
            check_transform(transform, "T_pred")

    def test_non_rigid(self):
        scaled = torch.eye(4)
        scaled[:3, :3] *= 2.0
        with pytest.raises(ValueError, match=r"T_pred is not a rigid transform: max \|R\^T R - I\| = 3\.00e\+00"):
            check_transform(scaled, "T_pred", rigid_atol=1e-6)
        reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))
        with pytest.raises(ValueError, match=r"det R = \[-1\.\]"):
            check_transform(reflection, "T_pred", rigid_atol=1e-6)
        bad_last_row = torch.eye(4)
        bad_last_row[3, 0] = 0.5
        with pytest.raises(ValueError, match=r"last-row error 5\.00e-01 \(tolerance 1e-06\)"):
            check_transform(bad_last_row, "T_pred", rigid_atol=1e-6)

    def test_non_rigid_accepted_without_tolerance(self):
        check_transform(torch.eye(4) * 2.0)


def _pose(angle: float = 0.4) -> np.ndarray:
    transform = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    transform[:3, :3] = [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    transform[:3, 3] = [0.5, -1.0, 2.0]
    return transform


class TestAsRigidTransform:
    def test_a_rigid_matrix_is_returned_unchanged_without_a_warning(self):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            np.testing.assert_array_equal(as_rigid_transform(_pose(), "gt"), _pose())
            out = as_rigid_transform(torch.from_numpy(_pose()), "gt")
        assert isinstance(out, np.ndarray) and out.dtype == np.float64

    def test_a_nearly_rigid_matrix_is_orthonormalised_with_a_warning(self):
        near = _pose()
        near[:3, :3] += 5e-4 * np.random.default_rng(0).standard_normal((3, 3))
        near[3, 0] = 5e-4
        with pytest.warns(
            UserWarning, match=r"^init: not exactly rigid, orthonormalised \(max \|R\^T R - I\| = "
        ) as caught:
            rigid = as_rigid_transform(near, "init")
        assert len(caught) == 1 and "\n" not in str(caught[0].message)
        rotation = rigid[:3, :3]
        assert abs(np.linalg.det(rotation) - 1.0) < 1e-12
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        np.testing.assert_array_equal(rigid[3], [0.0, 0.0, 0.0, 1.0])
        np.testing.assert_array_equal(rigid[:3, 3], near[:3, 3])
        np.testing.assert_allclose(rigid, _pose(), atol=2e-3)

    def test_a_float32_matrix_is_accepted(self):
        with pytest.warns(UserWarning, match="gt: not exactly rigid"):
            rigid = as_rigid_transform(_pose().astype(np.float32), "gt")
        assert rigid.dtype == np.float64

    def test_a_matrix_far_from_rigid_is_an_error_naming_the_argument(self):
        far = _pose()
        far[:3, :3] += 1e-2 * np.random.default_rng(1).standard_normal((3, 3))
        with pytest.raises(
            ValueError, match=r"^gt is not a rigid transform: max \|R\^T R - I\| = .*\(tolerance 0\.001\)"
        ):
            as_rigid_transform(far, "gt")

    def test_a_reflection_is_an_error(self):
        reflection = np.diag([1.0, 1.0, -1.0, 1.0])
        with pytest.raises(ValueError, match=r"^init is not a rigid transform: .*det R = \[-1\.\].*a reflection"):
            as_rigid_transform(reflection, "init")

    @pytest.mark.parametrize(
        ("matrix", "error", "message"),
        [
            (np.eye(4)[None], ValueError, r"init must have shape \(4, 4\), got \(1, 4, 4\)"),
            (np.eye(4, dtype=int), TypeError, "init must have a floating-point dtype"),
            (np.full((4, 4), np.nan), ValueError, "init contains NaN or Inf entries"),
        ],
    )
    def test_rejects(self, matrix, error, message):
        with pytest.raises(error, match=message):
            as_rigid_transform(matrix, "init")

    def test_nearest_rotation_is_a_rotation(self):
        rotation = nearest_rotation(np.random.default_rng(2).standard_normal((3, 3)))
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)


def test_check_same_batch():
    check_same_batch(torch.zeros(2, 5, 3), torch.zeros(2, 4, 4), "src", "T")
    with pytest.raises(ValueError, match="src and T must share the batch size, got 2 and 3"):
        check_same_batch(torch.zeros(2, 5, 3), torch.zeros(3, 4, 4), "src", "T")


class TestCheckLengths:
    def test_none_passes_through(self):
        assert check_lengths(None, "lengths", 2, 10) is None

    @pytest.mark.parametrize("lengths", [torch.tensor([3, 10]), np.array([3, 10], dtype=np.int32)])
    def test_accepts_integers_and_returns_a_cpu_tensor(self, lengths):
        out = check_lengths(lengths, "lengths", 2, 10, min_length=3)
        assert out.dtype == torch.int64 and out.tolist() == [3, 10]

    @pytest.mark.parametrize(
        ("lengths", "error", "message"),
        [
            ([3, 4], TypeError, "lengths must be a torch.Tensor or numpy array of integers, got list"),
            (torch.tensor([3.0, 4.0]), TypeError, "lengths must have an integer dtype, got torch.float32"),
            (torch.tensor([True, False]), TypeError, "lengths must have an integer dtype"),
            (torch.tensor([[3, 4]]), ValueError, r"lengths must have shape \(2,\) \(one length per sample\)"),
            (torch.tensor([3, -1]), ValueError, r"lengths\[1\] = -1 is outside \[1, 10\]"),
            (torch.tensor([11, 4]), ValueError, r"lengths\[0\] = 11 is outside \[1, 10\]"),
        ],
    )
    def test_rejects(self, lengths, error, message):
        with pytest.raises(error, match=message):
            check_lengths(lengths, "lengths", 2, 10)
