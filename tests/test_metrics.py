"""Tests for linereg.metrics on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from linereg import metrics, random_poses, se3


def _rz(angle_deg: float) -> torch.Tensor:
    a = math.radians(angle_deg)
    return torch.tensor(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )


def _transform(R: torch.Tensor, t) -> torch.Tensor:
    return se3.rt_to_matrix(R, torch.as_tensor(t, dtype=torch.float64))


class TestRotationError:
    @pytest.mark.parametrize("angle", [0.0, 1.0, 45.0, 90.0, 179.0, 180.0])
    def test_about_z(self, angle):
        error = metrics.rotation_error_deg(_rz(angle), torch.eye(3, dtype=torch.float64))
        torch.testing.assert_close(error, torch.tensor(angle, dtype=torch.float64), atol=1e-9, rtol=0)

    def test_relative_to_ground_truth(self):
        R_gt = random_poses.random_rotation(5, 0, dtype=torch.float64)
        R_pred = R_gt @ _rz(30.0)
        torch.testing.assert_close(
            metrics.rotation_error_deg(R_pred, R_gt), torch.full((5,), 30.0, dtype=torch.float64)
        )
        torch.testing.assert_close(
            metrics.rotation_error_deg(R_gt, R_pred), torch.full((5,), 30.0, dtype=torch.float64)
        )

    def test_small_error_in_float32(self):
        error = metrics.rotation_error_deg(_rz(0.01).float(), torch.eye(3))
        torch.testing.assert_close(error, torch.tensor(0.01), atol=1e-5, rtol=0)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"R_gt must have shape \(\.\.\., 3, 3\), got \(4, 4\)"):
            metrics.rotation_error_deg(torch.eye(3), torch.eye(4))


class TestTranslationError:
    def test_norms(self):
        t_pred = torch.tensor([1.0, -2.0, 0.5])
        t_gt = torch.tensor([0.0, 0.0, 2.5])
        torch.testing.assert_close(metrics.translation_error(t_pred, t_gt, "l1"), torch.tensor(5.0))
        torch.testing.assert_close(metrics.translation_error(t_pred, t_gt, "l2"), torch.tensor(3.0))

    def test_batched(self):
        t = torch.zeros(2, 3, 3)
        t_gt = torch.ones(2, 3, 3)
        assert metrics.translation_error(t, t_gt, "l1").shape == (2, 3)
        torch.testing.assert_close(metrics.translation_error(t, t_gt, "l1"), torch.full((2, 3), 3.0))

    def test_unknown_norm(self):
        with pytest.raises(ValueError, match=r"norm must be one of \('l1', 'l2'\), got 'linf'"):
            metrics.translation_error(torch.zeros(3), torch.zeros(3), "linf")


class TestPointwiseError:
    def test_known_offset(self):
        T_gt = _transform(torch.eye(3, dtype=torch.float64), [0.0, 0.0, 0.0])[None]
        T_pred = _transform(torch.eye(3, dtype=torch.float64), [0.3, 0.0, -0.4])[None]
        points = torch.randn(1, 10, 3, dtype=torch.float64)
        torch.testing.assert_close(
            metrics.pointwise_error(T_pred, T_gt, points, "l1"),
            torch.tensor([0.7], dtype=torch.float64),
        )
        torch.testing.assert_close(
            metrics.pointwise_error(T_pred, T_gt, points, "l2"),
            torch.tensor([0.5], dtype=torch.float64),
        )

    def test_rotation_about_origin(self):
        # Points on the unit circle in the xy plane, rotated by 90 deg: every displacement has
        # length sqrt(2) (l2) and |cos a - (-sin a)| + |sin a - cos a| (l1).
        angles = torch.linspace(0, 2 * math.pi, 9, dtype=torch.float64)[:-1]
        points = torch.stack((angles.cos(), angles.sin(), torch.zeros_like(angles)), -1)[None]
        T_pred = _transform(_rz(90.0), [0.0, 0.0, 0.0])[None]
        T_gt = torch.eye(4, dtype=torch.float64)[None]
        torch.testing.assert_close(
            metrics.pointwise_error(T_pred, T_gt, points, "l2"),
            torch.tensor([math.sqrt(2)], dtype=torch.float64),
        )
        expected_l1 = ((angles.cos() + angles.sin()).abs() + (angles.sin() - angles.cos()).abs()).mean()
        torch.testing.assert_close(metrics.pointwise_error(T_pred, T_gt, points, "l1"), expected_l1[None])

    def test_lengths_ignore_padding(self):
        T_gt = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
        T_pred = _transform(_rz(90.0), [0.0, 0.0, 0.0]).expand(2, 4, 4)
        points = torch.zeros(2, 4, 3, dtype=torch.float64)
        points[:, :2] = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64)
        points[0, 2:] = 100.0
        points[1, 2:] = float("nan")
        error = metrics.pointwise_error(T_pred, T_gt, points, "l2", lengths=torch.tensor([2, 2]))
        expected = (math.sqrt(2) + 2 * math.sqrt(2)) / 2
        torch.testing.assert_close(error, torch.full((2,), expected, dtype=torch.float64))

    def test_bad_lengths(self):
        T = torch.eye(4).expand(2, 4, 4)
        with pytest.raises(ValueError, match=r"lengths must lie in \[1, 3\], got \[0, 3\]"):
            metrics.pointwise_error(T, T, torch.zeros(2, 3, 3), lengths=torch.tensor([0, 3]))
        with pytest.raises(ValueError, match=r"lengths must have shape \(2,\), got \(3,\)"):
            metrics.pointwise_error(T, T, torch.zeros(2, 3, 3), lengths=torch.tensor([1, 1, 1]))


class TestRegistrationErrors:
    def test_keys_values_and_dtype(self):
        T_gt = _transform(torch.eye(3, dtype=torch.float64), [0.1, 0.2, 0.3])[None].float()
        T_pred = _transform(_rz(90.0), [0.1, 0.2, 0.0])[None].float()
        src = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
        errors = metrics.registration_errors(T_pred, T_gt, src)
        assert set(errors) == set(metrics.ERROR_KEYS)
        assert all(value.dtype == torch.float64 and value.shape == (1,) for value in errors.values())
        torch.testing.assert_close(errors["err_r_deg"], torch.tensor([90.0], dtype=torch.float64), atol=1e-5, rtol=0)
        torch.testing.assert_close(errors["err_t_l1"], torch.tensor([0.3], dtype=torch.float64), atol=1e-7, rtol=0)
        torch.testing.assert_close(errors["err_t_l2"], torch.tensor([0.3], dtype=torch.float64), atol=1e-7, rtol=0)
        # Points on the z axis are fixed by the rotation: only the translation difference remains.
        torch.testing.assert_close(errors["err_pw_l2"], torch.tensor([0.3], dtype=torch.float64), atol=1e-7, rtol=0)

    def test_perfect_prediction(self):
        T = random_poses.random_transform_paper(3, 0)
        errors = metrics.registration_errors(T, T, torch.randn(3, 20, 3))
        for value in errors.values():
            assert value.abs().max() < 1e-3

    def test_validation(self):
        T = torch.eye(4).expand(2, 4, 4)
        with pytest.raises(ValueError, match="T_pred contains NaN or Inf"):
            metrics.registration_errors(torch.full((2, 4, 4), float("nan")), T, torch.zeros(2, 5, 3))
        with pytest.raises(ValueError, match="T_pred and src must share the batch size"):
            metrics.registration_errors(T, T, torch.zeros(3, 5, 3))
        with pytest.raises(ValueError, match=r"src must have shape \(B, N, 3\)"):
            metrics.registration_errors(T, T, torch.zeros(5, 3))
        with pytest.raises(ValueError, match=r"T_pred and T_gt must both have shape \(B, 4, 4\)"):
            metrics.registration_errors(torch.eye(4), torch.eye(4), torch.zeros(1, 5, 3))


class TestSummaries:
    def test_alpha_recall(self):
        errors = torch.tensor([0.01, 0.02, 0.05, 0.2])
        recall = metrics.alpha_recall(errors, torch.tensor([0.0, 0.015, 0.05, 0.1, 1.0]))
        torch.testing.assert_close(recall, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=torch.float64))

    def test_alpha_recall_numpy(self):
        recall = metrics.alpha_recall(np.array([0.1, 0.3]), np.array([0.2]))
        torch.testing.assert_close(recall, torch.tensor([0.5], dtype=torch.float64))

    def test_alpha_recall_exception(self):
        with pytest.raises(ValueError, match=r"err_pw_l2 must have shape \(P,\) with P >= 1, got \(0,\)"):
            metrics.alpha_recall(torch.zeros(0), torch.ones(2))

    def test_summarize(self):
        summary = metrics.summarize(
            {"err_r_deg": torch.tensor([1.0, 2.0, 6.0, 7.0]), "err_t_l2": np.array([0.1, 0.2, 0.9])}
        )
        assert summary == pytest.approx(
            {
                "err_r_deg_mean": 4.0,
                "err_r_deg_median": 4.0,
                "err_t_l2_mean": 0.4,
                "err_t_l2_median": 0.2,
            }
        )
        assert all(isinstance(value, float) for value in summary.values())

    def test_summarize_exception(self):
        with pytest.raises(ValueError, match=r"errors\['err_r_deg'\] must have shape \(P,\)"):
            metrics.summarize({"err_r_deg": np.zeros((2, 2))})

    def test_paper_table(self):
        summary = {
            "err_r_deg_mean": 0.576,
            "err_t_l1_mean": 0.0017,
            "err_t_l2_mean": 0.0013,
            "err_pw_l1_mean": 0.0018,
            "err_pw_l2_mean": 0.0015,
        }
        table = metrics.paper_table({"Ours": summary, "ICP": {**summary, "err_r_deg_mean": 10.015}})
        lines = table.splitlines()
        assert lines[0] == "| Method | Err_R (deg) | Err_t (x10^-1) (l1, l2) | Err_pw (x10^-1) (l1, l2) |"
        assert lines[2] == "| Ours | 0.576 | 0.017, 0.013 | 0.018, 0.015 |"
        assert lines[3].startswith("| ICP | 10.015 |")
        assert len(lines) == 4

    def test_paper_table_missing_key(self):
        with pytest.raises(KeyError, match="summary of 'Ours' lacks err_pw_l1_mean"):
            metrics.paper_table(
                {
                    "Ours": {
                        "err_r_deg_mean": 1.0,
                        "err_t_l1_mean": 0.1,
                        "err_t_l2_mean": 0.1,
                        "err_pw_l2_mean": 0.1,
                    }
                }
            )

    def test_end_to_end(self):
        T_gt = random_poses.random_transform_paper(6, 0, dtype=torch.float64)
        T_pred = se3.compose(se3.se3_exp(0.01 * torch.randn(6, 6, dtype=torch.float64)), T_gt)
        summary = metrics.summarize(metrics.registration_errors(T_pred, T_gt, torch.randn(6, 50, 3)))
        assert set(summary) == {f"{key}_{stat}" for key in metrics.ERROR_KEYS for stat in ("mean", "median")}
        assert "| run |" in metrics.paper_table({"run": summary})
