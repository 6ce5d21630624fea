"""Classical baselines (registration/baselines.py): recovery, identity, centring, input errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from linereg.datasets.procedural import procedural_shape
from linereg.metrics import registration_errors
from linereg.registration import METHODS
from linereg.registration.baselines import FRICP_VARIANTS, diameter
from linereg.se3 import rt_to_matrix, so3_exp

BASELINES = ("icp_point", "icp_plane", "fgr", "fricp")


@pytest.fixture(scope="module")
def shape_points() -> np.ndarray:
    """``(~600, 3)`` float32 points spread evenly on a procedural asymmetric shape."""
    mesh = procedural_shape(np.random.default_rng(5))
    points, _ = trimesh.sample.sample_surface_even(mesh, 600, seed=0)
    return points.astype(np.float32)


def _transform(angle_deg: float, axis, translation) -> np.ndarray:
    """``(4, 4)`` float64 rotation about ``axis`` by ``angle_deg`` followed by ``translation``."""
    axis = torch.tensor(axis, dtype=torch.float64)
    rotation = so3_exp(np.radians(angle_deg) * axis / axis.norm())
    return rt_to_matrix(rotation, torch.tensor(translation, dtype=torch.float64)).numpy()


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return (points @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32)


def _errors(estimate: np.ndarray, truth: np.ndarray, src: np.ndarray) -> dict[str, float]:
    errors = registration_errors(
        torch.from_numpy(estimate)[None], torch.from_numpy(truth)[None], torch.from_numpy(src).double()[None]
    )
    return {key: float(value[0]) for key, value in errors.items()}


def test_every_baseline_is_registered():
    assert set(BASELINES) <= set(METHODS.names())


@pytest.mark.parametrize("name", BASELINES)
def test_recovers_a_small_transform(name, shape_points):
    truth = _transform(12.0, [1.0, 2.0, -1.0], [0.3, -0.1, 0.2])
    target = _apply(truth, shape_points)

    result = METHODS.build({"name": name})(shape_points, target)

    errors = _errors(result.transform, truth, shape_points)
    assert errors["err_r_deg"] < 1.0
    assert errors["err_pw_l2"] < 1e-2 * diameter(shape_points)
    assert result.transform.shape == (4, 4)
    assert result.seconds > 0


@pytest.mark.parametrize("name", BASELINES)
def test_identical_clouds_give_the_identity(name, shape_points):
    result = METHODS.build({"name": name})(shape_points, shape_points.copy())

    np.testing.assert_allclose(result.transform, np.eye(4), atol=1e-6)


def test_icp_plane_uses_given_target_normals(shape_points):
    truth = _transform(8.0, [0.0, 1.0, 1.0], [0.05, 0.0, -0.05])
    target = _apply(truth, shape_points)
    bad_normals = np.ones((len(shape_points) + 1, 3), dtype=np.float32)

    with pytest.raises(ValueError, match="normals must have the shape"):
        METHODS.build({"name": "icp_plane"})(shape_points, target, tgt_normals=bad_normals)


def test_centering_removes_the_initial_offset(shape_points):
    offset = 3.0 * diameter(shape_points)
    truth = _transform(5.0, [0.0, 0.0, 1.0], [offset, 0.0, 0.0])
    target = _apply(truth, shape_points)

    centred = METHODS.build({"name": "icp_point"})(shape_points, target)
    uncentred = METHODS.build({"name": "icp_point", "center": False})(shape_points, target)

    assert _errors(centred.transform, truth, shape_points)["err_r_deg"] < 1.0
    assert _errors(uncentred.transform, truth, shape_points)["err_t_l2"] > 0.5 * offset


@pytest.mark.parametrize("name", BASELINES)
def test_empty_cloud_is_rejected(name, shape_points):
    with pytest.raises(ValueError, match="source must hold at least 1 point"):
        METHODS.build({"name": name})(np.zeros((0, 3), dtype=np.float32), shape_points)


@pytest.mark.parametrize("name", BASELINES)
def test_nan_coordinates_are_rejected(name, shape_points):
    target = shape_points.copy()
    target[3, 1] = np.nan

    with pytest.raises(ValueError, match="target contains NaN or Inf"):
        METHODS.build({"name": name})(shape_points, target)


@pytest.mark.parametrize(
    ("config", "error", "message"),
    [
        ({"name": "fricp", "variant": "SparseICP"}, ValueError, "variant must be one of"),
        ({"name": "fricp", "nu_alpha": 1.5}, ValueError, "nu_alpha"),
        ({"name": "icp_point", "max_correspondence_ratio": 0.0}, ValueError, "max_correspondence_ratio"),
        ({"name": "fgr", "voxel_ratio": -1.0}, ValueError, "voxel_ratio"),
        ({"name": "icp_plane", "normal_k": 2}, ValueError, "normal_k"),
        ({"name": "fgr", "radius": 1.0}, TypeError, "registration method 'fgr'"),
    ],
)
def test_bad_options_are_rejected(config, error, message):
    with pytest.raises(error, match=message):
        METHODS.build(config)


@pytest.mark.parametrize("variant", [v for v in FRICP_VARIANTS if v != "RICP"])
def test_fricp_variants_run(variant, shape_points):
    truth = _transform(6.0, [1.0, 0.0, 1.0], [0.02, 0.01, 0.0])

    result = METHODS.build({"name": "fricp", "variant": variant})(shape_points, _apply(truth, shape_points))

    assert _errors(result.transform, truth, shape_points)["err_r_deg"] < 1.0
