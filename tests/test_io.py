"""Tests for linereg.io on files generated under tmp_path."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from linereg.io import (
    POINT_CLOUD_SUFFIXES,
    PointCloud,
    read_mesh,
    read_point_cloud,
    read_transform,
    write_point_cloud,
    write_transform,
)


@pytest.fixture
def cloud() -> PointCloud:
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return PointCloud(rng.normal(size=(50, 3)).astype(np.float32), normals.astype(np.float32))


def _rigid(angle: float = 0.3) -> np.ndarray:
    transform = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    transform[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    transform[:3, 3] = [0.1, -2.0, 3.5]
    return transform


@pytest.mark.parametrize("suffix", POINT_CLOUD_SUFFIXES)
@pytest.mark.parametrize("with_normals", [True, False])
def test_round_trip_every_format(tmp_path: Path, cloud: PointCloud, suffix: str, with_normals: bool) -> None:
    path = tmp_path / "nested" / "folder" / f"cloud{suffix}"
    write_point_cloud(path, cloud.xyz, cloud.normals if with_normals else None)
    loaded = read_point_cloud(path)
    assert loaded.xyz.dtype == np.float32
    np.testing.assert_array_equal(loaded.xyz, cloud.xyz)
    if with_normals:
        np.testing.assert_array_equal(loaded.normals, cloud.normals)
    else:
        assert loaded.normals is None


def test_ply_is_binary_little_endian(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "cloud.ply"
    write_point_cloud(path, cloud.xyz, cloud.normals)
    header = path.read_bytes()[:200].decode("ascii", errors="replace")
    assert "format binary_little_endian 1.0" in header and "property float nx" in header


def test_npy_layout(tmp_path: Path, cloud: PointCloud) -> None:
    write_point_cloud(tmp_path / "a.npy", cloud.xyz, cloud.normals)
    assert np.load(tmp_path / "a.npy").shape == (50, 6)
    write_point_cloud(tmp_path / "b.npy", cloud.xyz)
    assert np.load(tmp_path / "b.npy").shape == (50, 3)


def test_read_modelnet_comma_text(tmp_path: Path) -> None:
    path = tmp_path / "airplane_0001.txt"
    path.write_text(
        "-0.098790,-0.182300,0.163800,0.829000,-0.557200,-0.048180\n"
        "0.994600,0.074420,0.010250,0.331800,-0.939500,0.085320\n"
    )
    loaded = read_point_cloud(path)
    np.testing.assert_allclose(loaded.xyz[1], [0.9946, 0.07442, 0.01025], rtol=1e-6)
    np.testing.assert_allclose(loaded.normals[0], [0.829, -0.5572, -0.04818], rtol=1e-6)


def test_read_ascii_ply_with_faces_and_normals(tmp_path: Path) -> None:
    path = tmp_path / "scan.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n3 0 1 2\n"
    )
    loaded = read_point_cloud(path)
    np.testing.assert_array_equal(loaded.xyz, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(loaded.normals, [[0, 0, 1]] * 3)


def test_obj_normals_only_when_counts_match(tmp_path: Path) -> None:
    path = tmp_path / "mesh.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1 2 3\n")
    loaded = read_point_cloud(path)
    assert loaded.xyz.shape == (3, 3) and loaded.normals is None


def test_npz_alternative_key(tmp_path: Path, cloud: PointCloud) -> None:
    np.savez(tmp_path / "a.npz", points=cloud.xyz)
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "a.npz").xyz, cloud.xyz)


def test_read_errors(tmp_path: Path, cloud: PointCloud) -> None:
    with pytest.raises(FileNotFoundError, match=r"missing\.ply: no such file"):
        read_point_cloud(tmp_path / "missing.ply")
    (tmp_path / "cloud.las").write_text("x")
    with pytest.raises(ValueError, match=r"cloud\.las: unsupported .*supported: \.ply, \.pcd"):
        read_point_cloud(tmp_path / "cloud.las")
    (tmp_path / "ragged.xyz").write_text("1 2 3\n4 5\n")
    with pytest.raises(ValueError, match=r"ragged\.xyz: cannot read point cloud"):
        read_point_cloud(tmp_path / "ragged.xyz")
    (tmp_path / "four.xyz").write_text("1 2 3 4\n")
    with pytest.raises(ValueError, match=r"four\.xyz: .*expected 3 or 6 columns"):
        read_point_cloud(tmp_path / "four.xyz")
    (tmp_path / "empty.xyz").write_text("# only a comment\n")
    with pytest.raises(ValueError, match=r"empty\.xyz: the file contains no points"):
        read_point_cloud(tmp_path / "empty.xyz")
    (tmp_path / "nan.txt").write_text("1,2,3\nnan,0,0\n")
    with pytest.raises(ValueError, match=r"nan\.txt: coordinates contain NaN or Inf"):
        read_point_cloud(tmp_path / "nan.txt")
    write_point_cloud(tmp_path / "small.ply", cloud.xyz[:5])
    with pytest.raises(ValueError, match=r"small\.ply: expected at least 10 points, got 5"):
        read_point_cloud(tmp_path / "small.ply", min_points=10)
    np.save(tmp_path / "flat.npy", np.zeros(9))
    with pytest.raises(ValueError, match=r"flat\.npy: .*expected 3 or 6 columns"):
        read_point_cloud(tmp_path / "flat.npy")
    np.savez(tmp_path / "keys.npz", other=cloud.xyz)
    with pytest.raises(ValueError, match=r"keys\.npz: .*no point array"):
        read_point_cloud(tmp_path / "keys.npz")


def test_malformed_binary_files(tmp_path: Path, cloud: PointCloud) -> None:
    write_point_cloud(tmp_path / "full.ply", cloud.xyz)
    (tmp_path / "truncated.ply").write_bytes((tmp_path / "full.ply").read_bytes()[:-7])
    with pytest.raises(ValueError, match=r"truncated\.ply: cannot read point cloud"):
        read_point_cloud(tmp_path / "truncated.ply")
    (tmp_path / "garbage.ply").write_text("not a ply file\n")
    with pytest.raises(ValueError, match=r"garbage\.ply: cannot read point cloud"):
        read_point_cloud(tmp_path / "garbage.ply")
    (tmp_path / "garbage.pcd").write_text("not a pcd file\n")
    with pytest.raises(ValueError, match=r"garbage\.pcd: cannot read point cloud"):
        read_point_cloud(tmp_path / "garbage.pcd")


_XYZ_HEADER = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
MALFORMED_PLY = {
    "empty": ("", r"the file is empty"),
    "no_vertices": (_XYZ_HEADER.replace("vertex 2", "vertex 0") + "end_header\n", r"the file contains no points"),
    "missing_z": (
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n1 2\n3 4\n",
        r"the vertex element lacks the property \['z'\] \(it has \['x', 'y'\]\)",
    ),
    "missing_end_header": (_XYZ_HEADER + "1 2 3\n4 5 6\n", r"header line 7: '1 2 3' is not a PLY header line"),
    "unknown_format": (
        _XYZ_HEADER.replace("ascii", "utf8") + "end_header\n1 2 3\n4 5 6\n",
        r"header line 2: unknown PLY format 'utf8 1\.0'",
    ),
    "no_format": (_XYZ_HEADER.replace("format ascii 1.0\n", "") + "end_header\n", r"no 'format' line"),
    "bad_type": (_XYZ_HEADER.replace("float z", "float128 z") + "end_header\n", r"header line 6: bad property"),
    "short_ascii_body": (
        _XYZ_HEADER.replace("vertex 2", "vertex 10") + "end_header\n1 2 3\n4 5 6\n",
        r"the header declares vertex: 10 \(10 data lines\) but the file holds 2: truncated",
    ),
    "long_ascii_body": (
        _XYZ_HEADER + "end_header\n1 2 3\n4 5 6\n7 8 9\n",
        r"holds 3: more data than the header declares",
    ),
    "short_ascii_row": (_XYZ_HEADER + "end_header\n1 2 3\n4 5\n", r"vertex 1 has 2 values, the header declares 3"),
    "no_vertex_element": ("ply\nformat ascii 1.0\nelement face 0\nend_header\n", r"no 'vertex' element"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED_PLY))
def test_malformed_ply_is_explained(tmp_path: Path, case: str) -> None:
    content, message = MALFORMED_PLY[case]
    path = tmp_path / f"{case}.ply"
    path.write_text(content)
    with pytest.raises(ValueError, match=rf"{case}\.ply: .*{message}"):
        read_point_cloud(path)


def test_truncated_binary_ply_is_explained(tmp_path: Path, cloud: PointCloud) -> None:
    write_point_cloud(tmp_path / "full.ply", cloud.xyz)
    (tmp_path / "cut.ply").write_bytes((tmp_path / "full.ply").read_bytes()[:-7])
    with pytest.raises(ValueError, match=r"cut\.ply: .*truncated: the header declares 50 vertices of 12 bytes"):
        read_point_cloud(tmp_path / "cut.ply")


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_with_faces_matches_trimesh(tmp_path: Path, cloud: PointCloud, encoding: str) -> None:
    mesh = trimesh.Trimesh(cloud.xyz.astype(np.float64), [[0, 1, 2], [2, 3, 4]], process=False)
    path = tmp_path / "mesh.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding=encoding))
    expected = trimesh.load(path, process=False).vertices.astype(np.float32)
    np.testing.assert_array_equal(read_point_cloud(path).xyz, expected)


def test_big_endian_ply_with_a_list_element_before_the_vertices(tmp_path: Path, cloud: PointCloud) -> None:
    header = (
        "ply\nformat binary_big_endian 1.0\nelement face 2\nproperty list uchar int vertex_indices\n"
        "element vertex 50\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    faces = b"".join(np.uint8(3).tobytes() + np.array(face, ">i4").tobytes() for face in ([0, 1, 2], [2, 3, 4]))
    path = tmp_path / "big.ply"
    path.write_bytes(header.encode() + faces + cloud.xyz.astype(">f4").tobytes())
    np.testing.assert_array_equal(read_point_cloud(path).xyz, cloud.xyz)
    path.write_bytes(header.encode() + faces[:7])
    with pytest.raises(ValueError, match=r"big\.ply: .*truncated inside the 'face' element"):
        read_point_cloud(path)


def test_malformed_obj_and_pcd_are_explained(tmp_path: Path, cloud: PointCloud) -> None:
    (tmp_path / "short.obj").write_text("v 1 2 3\nv 1 2\n")
    with pytest.raises(ValueError, match=r"short\.obj: .*line 2: 'v' needs 3 numbers, got 'v 1 2'"):
        read_point_cloud(tmp_path / "short.obj")
    write_point_cloud(tmp_path / "full.pcd", cloud.xyz)
    (tmp_path / "cut.pcd").write_bytes((tmp_path / "full.pcd").read_bytes()[:-5])
    with pytest.raises(ValueError, match=r"cut\.pcd: .*POINTS 50 of 12 bytes \(600 bytes\) but the file holds 595"):
        read_point_cloud(tmp_path / "cut.pcd")
    header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
    (tmp_path / "short.pcd").write_text(header + "1 2 3\n")
    with pytest.raises(ValueError, match=r"short\.pcd: .*declares POINTS 3 but the file holds 1 data lines"):
        read_point_cloud(tmp_path / "short.pcd")


def test_a_folder_is_not_a_file(tmp_path: Path) -> None:
    (tmp_path / "scan.ply").mkdir()
    with pytest.raises(IsADirectoryError, match=r"scan\.ply: is a folder, not a file"):
        read_point_cloud(tmp_path / "scan.ply")


def test_write_errors(tmp_path: Path, cloud: PointCloud) -> None:
    with pytest.raises(ValueError, match=r"unsupported point-cloud extension '\.las'"):
        write_point_cloud(tmp_path / "a.las", cloud.xyz)
    with pytest.raises(ValueError, match="normals must have the shape of xyz"):
        write_point_cloud(tmp_path / "a.ply", cloud.xyz, cloud.normals[:10])
    with pytest.raises(ValueError, match="xyz must have shape"):
        write_point_cloud(tmp_path / "a.ply", cloud.xyz[None])


def test_transform_round_trip_and_formats(tmp_path: Path) -> None:
    transform = _rigid()
    write_transform(tmp_path / "sub" / "T.txt", transform)
    np.testing.assert_array_equal(read_transform(tmp_path / "sub" / "T.txt"), transform)
    (tmp_path / "T34.txt").write_text(
        "# 3x4, commas\n" + "\n".join(",".join(repr(float(value)) for value in row) for row in transform[:3])
    )
    loaded = read_transform(tmp_path / "T34.txt")
    assert loaded.dtype == np.float64
    np.testing.assert_array_equal(loaded, transform)


def test_transform_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nothere\.txt: no such file"):
        read_transform(tmp_path / "nothere.txt")
    (tmp_path / "short.txt").write_text("1 0 0 0 1 0")
    with pytest.raises(ValueError, match=r"short\.txt: expected 16 \(4x4\) or 12 \(3x4\)"):
        read_transform(tmp_path / "short.txt")
    scaled = _rigid()
    scaled[:3, :3] *= 1.01
    np.savetxt(tmp_path / "scaled.txt", scaled)
    with pytest.raises(ValueError, match=r"scaled\.txt: transform is not a rigid transform"):
        read_transform(tmp_path / "scaled.txt")
    (tmp_path / "words.txt").write_text("one two")
    with pytest.raises(ValueError, match=r"words\.txt: cannot read transform"):
        read_transform(tmp_path / "words.txt")


def _save_matrix(path: Path, matrix: np.ndarray) -> None:
    """``matrix`` in the format of ``path``'s suffix (text, ``.npy`` or a one-array ``.npz``)."""
    if path.suffix == ".npy":
        np.save(path, matrix)
    elif path.suffix == ".npz":
        np.savez(path, transform=matrix)
    else:
        np.savetxt(path, matrix, fmt="%.17g")


@pytest.mark.parametrize("rows", [4, 3], ids=["4x4", "3x4"])
@pytest.mark.parametrize("suffix", [".txt", ".npy", ".npz"])
def test_read_transform_formats(tmp_path: Path, suffix: str, rows: int) -> None:
    transform = _rigid()
    _save_matrix(tmp_path / f"T{suffix}", transform[:rows])
    loaded = read_transform(tmp_path / f"T{suffix}")
    assert loaded.dtype == np.float64
    np.testing.assert_array_equal(loaded, transform)


def test_read_transform_keeps_a_nearly_rigid_float32_matrix_as_stored(tmp_path: Path) -> None:
    near = _rigid()
    near[:3, :3] *= 1.0002
    np.save(tmp_path / "gt.npy", near.astype(np.float32))
    np.testing.assert_array_equal(read_transform(tmp_path / "gt.npy"), near.astype(np.float32))


@pytest.mark.parametrize(
    ("name", "write", "message"),
    [
        (
            "two.npz",
            lambda p: np.savez(p, R=np.eye(3), t=np.zeros(3)),
            r"holds 2 arrays \(R, t\), expected exactly one",
        ),
        ("empty.npz", lambda p: np.savez(p), r"holds 0 arrays"),
        ("corrupt.npz", lambda p: p.write_bytes(b"PK not a zip"), r"cannot read transform: not a zip archive"),
        ("corrupt.npy", lambda p: p.write_bytes(b"not an array"), r"cannot read transform: the magic string"),
        ("objects.npy", lambda p: np.save(p, np.full((4, 4), None)), r"cannot read transform: Object arrays"),
        ("square.npy", lambda p: np.save(p, np.eye(3)), r"expected a 4x4 or 3x4 matrix, got shape \(3, 3\)"),
        ("words.npy", lambda p: np.save(p, np.full((4, 4), "a")), r"expected real numbers, got dtype <U1"),
        ("nan.npy", lambda p: np.save(p, np.full((4, 4), np.nan)), r"transform contains NaN or Inf entries"),
        ("inf.txt", lambda p: p.write_text("inf " * 16), r"transform contains NaN or Inf entries"),
        ("far.npz", lambda p: np.savez(p, np.diag([1.0, 1.0, 1.01, 1.0])), r"is not a rigid transform"),
    ],
)
def test_read_transform_file_errors(tmp_path: Path, name: str, write, message: str) -> None:
    write(tmp_path / name)
    with pytest.raises(ValueError, match=re.escape(name) + ": .*" + message):
        read_transform(tmp_path / name)


@pytest.mark.parametrize("suffix", [".off", ".obj", ".ply", ".stl"])
def test_read_mesh_formats(tmp_path: Path, suffix: str) -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / f"box{suffix}"
    box.export(path)
    mesh = read_mesh(path)
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.vertices) == 8 and len(mesh.faces) == 12
    np.testing.assert_allclose(mesh.extents, [1.0, 2.0, 3.0])


def test_read_mesh_errors(tmp_path: Path, cloud: PointCloud) -> None:
    with pytest.raises(FileNotFoundError, match=r"gone\.off: no such file"):
        read_mesh(tmp_path / "gone.off")
    (tmp_path / "mesh.glb").write_bytes(b"")
    with pytest.raises(ValueError, match=r"mesh\.glb: unsupported mesh extension .*\.off"):
        read_mesh(tmp_path / "mesh.glb")
    write_point_cloud(tmp_path / "points.ply", cloud.xyz)
    with pytest.raises(ValueError, match=r"points\.ply: the mesh has no faces"):
        read_mesh(tmp_path / "points.ply")
    (tmp_path / "empty.off").write_text("OFF\n0 0 0\n")
    with pytest.raises(ValueError, match=r"empty\.off: the mesh has no vertices"):
        read_mesh(tmp_path / "empty.off")
    (tmp_path / "broken.off").write_text("")
    with pytest.raises(ValueError, match=r"broken\.off: cannot read mesh"):
        read_mesh(tmp_path / "broken.off")
