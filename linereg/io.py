"""Point-cloud, mesh and transform files.

Readers return float32 ``(N, 3)`` coordinates (and normals when the file has them) and raise
with the file name in every message. Formats:

* ``.ply`` (ascii or binary; ``nx ny nz`` vertex properties become normals), parsed by
  :mod:`linereg.ply`: the header is checked line by line and the data against the counts it
  declares, so truncated, padded or malformed files are rejected with the reason (Open3D 0.20
  warns on stdout and returns zero-filled points; trimesh accepts a short ascii body);
* ``.pcd`` through Open3D (imported lazily, it takes seconds to import);
* ``.obj`` ``v`` lines (``vn`` lines become normals when there is one per vertex);
* ``.xyz`` / ``.txt`` / ``.pts`` text with 3 or 6 columns separated by whitespace or commas
  (ModelNet's ``x,y,z,nx,ny,nz``);
* ``.npy`` arrays ``(N, 3)`` or ``(N, 6)`` and ``.npz`` archives with a key ``xyz``,
  ``points`` or ``pos`` (and optionally ``normals``).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from linereg.checks import RIGID_TOLERANCE, check_points, check_transform
from linereg.ply import read_ply, write_binary, write_ply

POINT_CLOUD_SUFFIXES = (".ply", ".pcd", ".obj", ".xyz", ".txt", ".pts", ".npy", ".npz")
MESH_SUFFIXES = (".off", ".obj", ".ply", ".stl")
_TEXT_SUFFIXES = (".xyz", ".txt", ".pts")
_NPZ_POINT_KEYS = ("xyz", "points", "pos")


class PointCloud(NamedTuple):
    """A point cloud read from a file.

    Attributes:
        xyz: float32 array of shape ``(N, 3)`` giving the coordinates.
        normals: float32 array of shape ``(N, 3)`` giving per-point normals, or ``None`` when
            the file has none.
    """

    xyz: np.ndarray
    normals: np.ndarray | None


def read_point_cloud(path: str | Path, *, min_points: int = 1) -> PointCloud:
    """Read a point cloud (see the module docstring for the formats).

    Args:
        path: file to read.
        min_points: fewest points accepted.

    Returns:
        :class:`PointCloud` with float32 ``xyz`` and ``normals`` (or ``None``).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unsupported extension, unreadable or malformed content, no points, fewer
            than ``min_points`` points, or NaN/Inf values; the message names the file.
    """
    path = _existing_file(path)
    suffix = path.suffix.lower()
    readers = {
        ".ply": read_ply,
        ".pcd": _read_pcd,
        ".obj": _read_obj,
        ".npy": _read_npy,
        ".npz": _read_npz,
    }
    reader = _read_text if suffix in _TEXT_SUFFIXES else readers.get(suffix)
    if reader is None:
        raise ValueError(
            f"{path}: unsupported point-cloud extension {path.suffix!r}; supported: {', '.join(POINT_CLOUD_SUFFIXES)}"
        )
    try:
        xyz, normals = reader(path)
        xyz = np.asarray(xyz, dtype=np.float32)
        normals = None if normals is None else np.asarray(normals, dtype=np.float32)
    except (OSError, ValueError, TypeError, KeyError, IndexError, EOFError) as error:
        raise ValueError(f"{path}: cannot read point cloud: {error}") from error
    return _validated(path, xyz, normals, min_points)


def _existing_file(path: str | Path) -> Path:
    """``path`` as a Path, or FileNotFoundError (IsADirectoryError for a folder) naming it."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a folder, not a file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return path


def _validated(path: Path, xyz: np.ndarray, normals: np.ndarray | None, min_points: int) -> PointCloud:
    """Check shapes, size and finiteness of what a reader returned."""
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"{path}: expected (N, 3) coordinates, got shape {xyz.shape}")
    if xyz.shape[0] == 0:
        raise ValueError(f"{path}: the file contains no points")
    if xyz.shape[0] < min_points:
        raise ValueError(f"{path}: expected at least {min_points} points, got {xyz.shape[0]}")
    if not np.isfinite(xyz).all():
        raise ValueError(f"{path}: coordinates contain NaN or Inf")
    if normals is not None:
        if normals.shape != xyz.shape:
            raise ValueError(f"{path}: normals have shape {normals.shape}, points {xyz.shape}")
        if not np.isfinite(normals).all():
            raise ValueError(f"{path}: normals contain NaN or Inf")
    return PointCloud(xyz, normals)


def _read_pcd(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (and normals) of a PCD file, through Open3D, after checking the data length."""
    import open3d as o3d

    _check_pcd_length(path)
    cloud = o3d.io.read_point_cloud(str(path), format="pcd")
    if not cloud.has_points():
        raise ValueError("Open3D read no points (empty or malformed PCD)")
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    return np.asarray(cloud.points), normals


def _check_pcd_length(path: Path) -> None:
    """Raise ``ValueError`` when an ascii PCD body holds another number of rows than its header's
    ``POINTS``, or a binary body fewer bytes (Open3D fills missing points with NaN or zeros);
    compressed bodies are left to Open3D."""
    header: dict[str, list[str]] = {}
    with path.open("rb") as stream:
        while True:
            raw = stream.readline()
            if not raw:
                raise ValueError("the PCD header has no DATA line")
            words = raw.decode("ascii", errors="replace").split()
            if words and not words[0].startswith("#"):
                header[words[0].upper()] = words[1:]
            if words and words[0].upper() == "DATA":
                break
        body = stream.read()
    try:
        points = int(header["POINTS"][0])
        point_bytes = sum(int(size) * int(count) for size, count in zip(header["SIZE"], header["COUNT"], strict=True))
    except (KeyError, IndexError, ValueError) as error:
        raise ValueError(f"malformed PCD header (POINTS, SIZE and COUNT lines needed): {error}") from error
    encoding = header["DATA"][0].lower() if header["DATA"] else ""
    if encoding == "ascii":
        rows = sum(1 for line in body.splitlines() if line.strip())
        if rows != points:
            raise ValueError(f"the header declares POINTS {points} but the file holds {rows} data lines")
    elif encoding == "binary" and len(body) < points * point_bytes:
        raise ValueError(
            f"the header declares POINTS {points} of {point_bytes} bytes ({points * point_bytes} bytes) but the "
            f"file holds {len(body)} bytes of data"
        )


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``v`` (and matching ``vn``) lines of a Wavefront OBJ file."""
    rows: dict[str, list[list[str]]] = {"v": [], "vn": []}
    with path.open("r", encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            words = line.split()
            if not words or words[0] not in rows:
                continue
            if len(words) < 4:
                raise ValueError(f"line {number}: {words[0]!r} needs 3 numbers, got {' '.join(words)!r}")
            rows[words[0]].append(words[1:4])
    xyz = np.array(rows["v"], dtype=np.float32).reshape(-1, 3)
    if rows["vn"] and len(rows["vn"]) == len(rows["v"]):
        return xyz, np.array(rows["vn"], dtype=np.float32).reshape(-1, 3)
    return xyz, None


def _read_text(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Rows of 3 (xyz) or 6 (xyz + normals) numbers separated by whitespace or commas."""
    with path.open("r", encoding="utf-8") as stream:
        lines = [line.replace(",", " ") for line in stream if line.split("#", 1)[0].strip()]
    if not lines:
        return np.empty((0, 3)), None
    return _split_columns(np.loadtxt(lines, dtype=np.float64, ndmin=2))


def _split_columns(values: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Split an ``(N, 3)`` or ``(N, 6)`` array into coordinates and normals."""
    if values.ndim != 2 or values.shape[1] not in (3, 6):
        raise ValueError(f"expected 3 or 6 columns (x y z [nx ny nz]), got shape {values.shape}")
    return values[:, :3], (values[:, 3:] if values.shape[1] == 6 else None)


def _read_npy(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """An ``(N, 3)`` or ``(N, 6)`` numpy array."""
    return _split_columns(np.load(path, allow_pickle=False))


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A numpy archive with a point key (``xyz``, ``points`` or ``pos``) and maybe ``normals``."""
    with np.load(path, allow_pickle=False) as archive:
        key = next((name for name in _NPZ_POINT_KEYS if name in archive.files), None)
        if key is None:
            raise ValueError(f"no point array: expected one of the keys {_NPZ_POINT_KEYS}, found {archive.files}")
        normals = archive["normals"] if "normals" in archive.files else None
        return archive[key], normals


def write_point_cloud(path: str | Path, xyz: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Write a point cloud, creating parent folders; the format follows the extension.

    ``.ply`` is binary little-endian float32; ``.npy`` holds ``(N, 3)`` or ``(N, 6)``
    (normals appended); ``.txt`` is comma-separated (ModelNet style), ``.xyz``/``.pts``
    space-separated; ``.pcd`` is binary; ``.obj`` has ``v`` (and ``vn``) lines; ``.npz`` has the
    keys ``xyz`` (and ``normals``). Everything written reads back with :func:`read_point_cloud`.

    Args:
        path: destination file.
        xyz: array of shape ``(N, 3)`` giving the coordinates.
        normals: optional array of shape ``(N, 3)``.
    """
    path = Path(path)
    check_points(xyz, "xyz", batched=False)
    xyz = np.asarray(xyz, dtype=np.float32)
    if normals is not None:
        check_points(normals, "normals", batched=False)
        if normals.shape != xyz.shape:
            raise ValueError(f"normals must have the shape of xyz {xyz.shape}, got {tuple(normals.shape)}")
        normals = np.asarray(normals, dtype=np.float32)
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise ValueError(
            f"{path}: unsupported point-cloud extension {path.suffix!r}; supported: {', '.join(POINT_CLOUD_SUFFIXES)}"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = xyz if normals is None else np.hstack([xyz, normals])
    if suffix == ".ply":
        write_ply(path, columns)
    elif suffix == ".pcd":
        _write_pcd(path, columns)
    elif suffix == ".obj":
        _write_obj(path, xyz, normals)
    elif suffix == ".npy":
        np.save(path, columns)
    elif suffix == ".npz":
        arrays = {"xyz": xyz} if normals is None else {"xyz": xyz, "normals": normals}
        np.savez(path, **arrays)
    else:
        np.savetxt(path, columns, fmt="%.9g", delimiter="," if suffix == ".txt" else " ")


def _write_pcd(path: Path, columns: np.ndarray) -> None:
    """Binary PCD v0.7 with float32 ``x y z [normal_x normal_y normal_z]`` fields."""
    names = ("x", "y", "z", "normal_x", "normal_y", "normal_z")[: columns.shape[1]]
    count = len(names)
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        f"FIELDS {' '.join(names)}",
        f"SIZE {' '.join(['4'] * count)}",
        f"TYPE {' '.join(['F'] * count)}",
        f"COUNT {' '.join(['1'] * count)}",
        f"WIDTH {columns.shape[0]}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {columns.shape[0]}",
        "DATA binary",
    ]
    write_binary(path, header, columns)


def _write_obj(path: Path, xyz: np.ndarray, normals: np.ndarray | None) -> None:
    """Wavefront OBJ with ``v`` lines and, when given, ``vn`` lines."""
    with path.open("w", encoding="ascii") as stream:
        np.savetxt(stream, xyz, fmt="v %.9g %.9g %.9g")
        if normals is not None:
            np.savetxt(stream, normals, fmt="vn %.9g %.9g %.9g")


def read_transform(path: str | Path, *, rigid: bool = True) -> np.ndarray:
    """Read a rigid transform (``rigid=False``: any finite one, a similarity): a 4x4 or 3x4 matrix
    (the last row ``[0, 0, 0, 1]`` implied).

    Formats: ``.npy`` (a 4x4 or 3x4 array), ``.npz`` (exactly one such array), anything else text
    of 16 or 12 numbers separated by whitespace, commas or newlines (``#`` starts a comment).
    The matrix is returned as stored; :func:`linereg.checks.as_rigid_transform` makes it exactly rigid.

    Returns:
        float64 array of shape ``(4, 4)``.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unreadable, not 12/16 numbers or a 4x4/3x4 array, NaN/Inf, or further than
            :data:`~linereg.checks.RIGID_TOLERANCE` from a rigid transform; the message names the file.
    """
    path = _existing_file(path)
    try:
        stored = _stored_matrix(path)
    except (OSError, EOFError, ValueError, UnicodeDecodeError, zipfile.BadZipFile) as error:
        raise ValueError(f"{path}: cannot read transform: {error}") from error
    try:
        transform = homogeneous_matrix(stored)
        check_transform(transform, "transform", rigid_atol=RIGID_TOLERANCE if rigid else None)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from error
    return transform


def _stored_matrix(path: Path) -> np.ndarray:
    """The array of a ``.npy``, the one array of a ``.npz``, else the numbers of a text file (flat)."""
    suffix = path.suffix.lower()
    if suffix == ".npy":
        with path.open("rb") as stream:
            return np.lib.format.read_array(stream, allow_pickle=False)
    if suffix == ".npz":
        if not zipfile.is_zipfile(path):
            raise ValueError("not a zip archive")
        with np.load(path, allow_pickle=False) as archive:
            if len(archive.files) != 1:
                raise ValueError(
                    f"the archive holds {len(archive.files)} arrays ({', '.join(archive.files) or 'none'}), "
                    "expected exactly one"
                )
            return archive[archive.files[0]]
    with path.open("r", encoding="utf-8") as stream:
        lines = [line.split("#", 1)[0].replace(",", " ") for line in stream]
    return np.array(" ".join(lines).split(), dtype=np.float64)


def homogeneous_matrix(stored: np.ndarray) -> np.ndarray:
    """``stored`` (16 or 12 numbers, or a 4x4 or 3x4 array) as a float64 4x4 matrix, the last row
    ``[0, 0, 0, 1]`` added to a 3x4 one (no rigidity check).

    Raises:
        ValueError: not real numbers, or neither 16 / 12 numbers nor a 4x4 / 3x4 array.
    """
    if not (np.issubdtype(stored.dtype, np.floating) or np.issubdtype(stored.dtype, np.integer)):
        raise ValueError(f"expected real numbers, got dtype {stored.dtype}")
    if stored.ndim == 1:
        if stored.size not in (12, 16):
            raise ValueError(f"expected 16 (4x4) or 12 (3x4) numbers, got {stored.size}")
        stored = stored.reshape(-1, 4)
    if stored.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"expected a 4x4 or 3x4 matrix, got shape {stored.shape}")
    matrix = stored.astype(np.float64)
    return matrix if len(matrix) == 4 else np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])


def write_transform(path: str | Path, transform: np.ndarray) -> None:
    """Write a ``(4, 4)`` transform as 4 lines of 4 numbers, creating parent folders.

    Values are written with 17 significant digits, so :func:`read_transform` returns them
    exactly.
    """
    check_transform(transform, "transform")
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape != (4, 4):
        raise ValueError(f"transform must have shape (4, 4), got {transform.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, transform, fmt="%.17g")


def read_mesh(path: str | Path):
    """Read a triangle mesh (``.off``, ``.obj``, ``.ply``, ``.stl``) with trimesh.

    Vertices that share a position are merged (trimesh's OBJ loader splits them at texture and
    normal seams; some OFF/PLY files repeat them), so the mesh has one vertex per distinct
    position and the file's faces; multi-part files (a trimesh ``Scene``) are concatenated.

    Returns:
        ``trimesh.Trimesh``.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unsupported extension, unreadable file, no vertices or no faces, or
            non-finite vertices; the message names the file.
    """
    import trimesh

    path = _existing_file(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh extension {path.suffix!r}; supported: {', '.join(MESH_SUFFIXES)}")
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as error:
        raise ValueError(f"{path}: cannot read mesh: {error}") from error
    if isinstance(loaded, trimesh.PointCloud):
        raise ValueError(f"{path}: the mesh has no faces (a point cloud? use read_point_cloud)")
    mesh = loaded.to_mesh() if isinstance(loaded, trimesh.Scene) else loaded
    if len(mesh.vertices) == 0:
        raise ValueError(f"{path}: the mesh has no vertices")
    if len(mesh.faces) == 0:
        raise ValueError(f"{path}: the mesh has no faces (a point cloud? use read_point_cloud)")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"{path}: mesh vertices contain NaN or Inf")
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return mesh
