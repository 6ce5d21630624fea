"""linereg.io on the real files in the shared data folder (sizes from each folder's SOURCE.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from linereg.io import read_mesh, read_point_cloud, read_transform

pytestmark = pytest.mark.shared_data


def _file(shared_data: Path, relative: str) -> Path:
    path = shared_data / relative
    if not path.is_file():
        pytest.skip(f"shared data file absent: {relative}")
    return path


def _assert_mostly_unit(normals: np.ndarray) -> None:
    """Nearly all normals have unit length (the FRICP scan holds two that do not)."""
    assert np.isfinite(normals).all()
    assert np.mean(np.abs(np.linalg.norm(normals, axis=1) - 1.0) < 1e-2) > 0.999


@pytest.mark.parametrize(
    ("relative", "num_points", "has_normals"),
    [
        ("modelnet40_normal_resampled/airplane/airplane_0001.txt", 10_000, True),
        ("modelnet40_normal_resampled/chair/chair_0391.txt", 10_000, True),
        ("3dmatch/redkitchen_0_4/cloud_bin_0.ply", 258_342, False),
        ("3dmatch/redkitchen_0_4/cloud_bin_4.ply", 313_395, False),
        ("3dmatch/geotransformer_demo/demo/src.npy", 15_953, False),
        ("3dmatch/geotransformer_demo/demo/ref.npy", 18_977, False),
        ("scans/fricp_statue/source.ply", 14_806, True),
        ("scans/fricp_statue/target.ply", 15_446, True),
        ("meshes/stanford_lowres/dragon.ply", 22_982, False),
        ("meshes/odedstein/bunny/bunny.obj", 3_301, False),
    ],
)
def test_read_point_cloud_real_files(shared_data: Path, relative: str, num_points: int, has_normals: bool) -> None:
    cloud = read_point_cloud(_file(shared_data, relative))
    assert cloud.xyz.shape == (num_points, 3) and cloud.xyz.dtype == np.float32
    assert np.isfinite(cloud.xyz).all()
    assert np.ptp(cloud.xyz, axis=0).min() > 0
    assert (cloud.normals is not None) == has_normals
    if has_normals:
        _assert_mostly_unit(cloud.normals)


def test_modelnet_text_is_in_unit_sphere(shared_data: Path) -> None:
    cloud = read_point_cloud(_file(shared_data, "modelnet40_normal_resampled/airplane/airplane_0001.txt"))
    assert np.linalg.norm(cloud.xyz, axis=1).max() <= 1.0 + 1e-4


@pytest.mark.parametrize(
    ("relative", "num_vertices", "num_faces"),
    [
        ("meshes/modelnet_airplane_off/airplane_0001.off", None, None),
        ("meshes/fmr_bed/bed.off", None, 35_299),
        ("meshes/odedstein/human/human_man.obj", 6_890, 13_776),
        ("meshes/odedstein/plane/plane.obj", 8_730, 17_456),
        ("meshes/odedstein/bunny/bunny.obj", 3_301, 6_598),
        ("meshes/stanford_lowres/dragon.ply", None, 45_550),
        ("meshes/stanford_lowres/bunny.ply", None, 16_262),
        ("meshes/stanford_bunny_full/stanford-bunny.obj", 34_834, 69_451),
    ],
)
def test_read_mesh_real_files(
    shared_data: Path, relative: str, num_vertices: int | None, num_faces: int | None
) -> None:
    mesh = read_mesh(_file(shared_data, relative))
    assert len(mesh.vertices) > 0 and len(mesh.faces) > 0
    assert np.isfinite(mesh.vertices).all()
    assert mesh.faces.max() < len(mesh.vertices)
    if num_vertices is not None:
        assert len(mesh.vertices) == num_vertices
    if num_faces is not None:
        assert len(mesh.faces) == num_faces
    assert mesh.area > 0


def test_read_transform_real_file(shared_data: Path) -> None:
    transform = read_transform(_file(shared_data, "scans/fricp_statue/m3trans.txt"))
    assert transform.shape == (4, 4)
    np.testing.assert_allclose(transform[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(transform[0], [0.804419, 0.359467, -0.472963, -0.15688])
