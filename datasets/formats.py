"""Parsers for the file formats of public registration datasets (no geometry here).

* ``.log`` files (3DMatch ``gt.log``, Redwood ``trajectory.log``): blocks of a header line
  ``i j n`` followed by four rows of a 4x4 matrix.
* ``gt_overlap.log``: lines ``i,j,ratio`` (comma or white-space separated).
* plain 4x4 / 3x3 matrix text files (7-Scenes ``frame-XXXXXX.pose.txt``,
  ``camera-intrinsics.txt``).
* pose lists ``[timestamp] tx ty tz qx qy qz qw`` (TUM ``groundtruth.txt``, slambook
  ``pose.txt``) and TUM association lists ``timestamp path``.
* Open3D ``PinholeCameraIntrinsic`` JSON (column-major ``intrinsic_matrix``).
* 16-bit depth images (PNG, PGM) read with Pillow.

Every parser raises ``ValueError`` naming the file and the line for malformed content and
``FileNotFoundError`` for a missing file.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch
from PIL import Image

from linereg.checks import check_transform, nearest_rotation

RIGID_ATOL = 1e-3


@dataclass(frozen=True)
class LogEntry:
    """One block of a ``.log`` file.

    Attributes:
        i: first index of the header (3DMatch: the target fragment).
        j: second index of the header (3DMatch: the source fragment).
        count: third header number (3DMatch: number of fragments in the scene).
        transform: ``(4, 4)`` float64 matrix; in 3DMatch ``p_i = transform @ p_j``.
    """

    i: int
    j: int
    count: int
    transform: np.ndarray


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float

    def as_list(self) -> list[float]:
        """``[fx, fy, cx, cy]``."""
        return [self.fx, self.fy, self.cx, self.cy]


def _require_file(path: str | Path, what: str) -> Path:
    """``path`` as a Path; FileNotFoundError naming ``what`` when it is not a file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    return path


def _floats(text: str, path: Path, line_no: int, count: int) -> list[float]:
    """Exactly ``count`` floats from one line, or a ValueError naming file and line."""
    parts = text.replace(",", " ").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != count:
        raise ValueError(f"{path}: line {line_no}: expected {count} numbers, got {text.strip()!r}")
    return values


def read_log(path: str | Path, *, rigid: bool = True) -> list[LogEntry]:
    """Read a 3DMatch ``gt.log`` / Redwood ``trajectory.log`` file.

    Args:
        path: the ``.log`` file.
        rigid: require every matrix to be a rigid transform (tolerance ``1e-3``) and return it
            exactly rigid (its nearest rotation; published logs are rigid to about 1e-4 only).

    Returns:
        The blocks in file order.

    Raises:
        FileNotFoundError: missing file.
        ValueError: malformed header or matrix row, truncated block, non-rigid matrix.
    """
    path = _require_file(path, "log file")
    lines = [(n, line) for n, line in enumerate(path.read_text().splitlines(), 1) if line.strip()]
    if not lines:
        raise ValueError(f"{path}: empty log file (expected blocks of 'i j n' + 4 matrix rows)")
    if len(lines) % 5:
        raise ValueError(
            f"{path}: malformed log file: {len(lines)} non-empty lines is not a multiple of 5 "
            "(each block is a header 'i j n' and 4 matrix rows)"
        )
    entries = []
    for start in range(0, len(lines), 5):
        line_no, header = lines[start]
        fields = header.split()
        if len(fields) != 3 or not all(f.lstrip("-").isdigit() for f in fields):
            raise ValueError(
                f"{path}: line {line_no}: expected a block header of 3 integers 'i j n', got {header.strip()!r}"
            )
        rows = [_floats(text, path, n, 4) for n, text in lines[start + 1 : start + 5]]
        matrix = np.array(rows, dtype=np.float64)
        if rigid:
            try:
                check_transform(matrix, f"{path}: block at line {line_no}", rigid_atol=RIGID_ATOL)
            except ValueError as error:
                raise ValueError(str(error)) from None
            matrix[:3, :3] = nearest_rotation(matrix[:3, :3])
            matrix[3] = (0.0, 0.0, 0.0, 1.0)
        i, j, count = (int(f) for f in fields)
        entries.append(LogEntry(i, j, count, matrix))
    return entries


def read_overlap_log(path: str | Path) -> dict[tuple[int, int], float]:
    """Read a ``gt_overlap.log``: ``{(i, j): overlap ratio}`` from lines ``i,j,ratio``."""
    path = _require_file(path, "overlap log")
    overlaps = {}
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        i, j, ratio = _floats(line, path, line_no, 3)
        overlaps[(int(i), int(j))] = ratio
    return overlaps


def read_matrix(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a white-space separated matrix of the given ``shape`` (float64)."""
    path = _require_file(path, "matrix file")
    rows = [line for line in path.read_text().splitlines() if line.strip()]
    if len(rows) != shape[0]:
        raise ValueError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got {len(rows)} rows")
    return np.array([_floats(r, path, n, shape[1]) for n, r in enumerate(rows, 1)])


def read_pose_matrix(path: str | Path) -> np.ndarray:
    """Read a rigid 4x4 pose (7-Scenes ``frame-XXXXXX.pose.txt``)."""
    matrix = read_matrix(path, (4, 4))
    check_transform(matrix, str(path), rigid_atol=RIGID_ATOL)
    return matrix


def pose_from_translation_quaternion(values: np.ndarray) -> np.ndarray:
    """``(K, 4, 4)`` rigid transforms from rows ``tx ty tz qx qy qz qw`` (quaternion normalised)."""
    values = torch.as_tensor(np.asarray(values, dtype=np.float64)).reshape(-1, 7)
    quaternion = roma.quat_normalize(values[:, 3:])
    rotation = roma.unitquat_to_rotmat(quaternion)
    poses = torch.eye(4, dtype=torch.float64).repeat(len(values), 1, 1)
    poses[:, :3, :3] = rotation
    poses[:, :3, 3] = values[:, :3]
    return poses.numpy()


def read_pose_list(path: str | Path, *, timestamps: bool) -> tuple[np.ndarray | None, np.ndarray]:
    """Read poses ``[timestamp] tx ty tz qx qy qz qw``, one per line (``#`` comments skipped).

    Args:
        path: TUM ``groundtruth.txt`` (``timestamps=True``) or a slambook-style ``pose.txt``.
        timestamps: whether each line starts with a timestamp.

    Returns:
        ``(stamps (K,) or None, poses (K, 4, 4))``; poses map camera to world coordinates.
    """
    path = _require_file(path, "pose list")
    width = 8 if timestamps else 7
    rows = [
        _floats(line, path, n, width)
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ValueError(f"{path}: no poses found (expected lines of {width} numbers)")
    table = np.array(rows)
    stamps = table[:, 0] if timestamps else None
    return stamps, pose_from_translation_quaternion(table[:, -7:])


def read_association_list(path: str | Path) -> list[tuple[float, str]]:
    """Read a TUM list (``depth.txt``): ``timestamp relative/path`` per line, ``#`` comments."""
    path = _require_file(path, "TUM file list")
    entries = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split()
        try:
            entries.append((float(fields[0]), fields[1]))
        except (ValueError, IndexError):
            raise ValueError(f"{path}: line {line_no}: expected 'timestamp path', got {line.strip()!r}") from None
    return entries


def read_intrinsics(path: str | Path) -> Intrinsics:
    """Read pinhole intrinsics from an Open3D JSON file or a 3x3 matrix text file."""
    path = _require_file(path, "intrinsics file")
    if path.suffix.lower() == ".json":
        try:
            values = json.loads(path.read_text())["intrinsic_matrix"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise ValueError(f"{path}: expected Open3D intrinsics JSON with an 'intrinsic_matrix' entry") from None
        if len(values) != 9:
            raise ValueError(f"{path}: 'intrinsic_matrix' must hold 9 numbers, got {len(values)}")
        matrix = np.asarray(values, dtype=np.float64).reshape(3, 3).T
    else:
        matrix = read_matrix(path, (3, 3))
    return Intrinsics(fx=matrix[0, 0], fy=matrix[1, 1], cx=matrix[0, 2], cy=matrix[1, 2])


def read_depth_image(path: str | Path) -> np.ndarray:
    """Read a single-channel integer depth image (16-bit PNG, 16-bit PGM) as raw units.

    Returns:
        ``(H, W)`` uint16/int32 array of raw depth values (divide by the depth scale).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not an image, or not a single-channel 16/32-bit integer image (e.g. an
            8-bit or colour image given as depth).
    """
    path = _require_file(path, "depth image")
    try:
        with Image.open(path) as image:
            mode = image.mode
            depth = np.asarray(image)
    except OSError as error:
        raise ValueError(f"{path}: cannot read depth image ({error})") from None
    if not (mode.startswith("I;16") or mode == "I") or depth.ndim != 2:
        raise ValueError(
            f"{path}: depth image must be single-channel 16-bit (or 32-bit integer), got "
            f"Pillow mode {mode!r} with shape {depth.shape}; is this a colour image?"
        )
    return depth


def read_conf(path: str | Path) -> dict[str, np.ndarray]:
    """Read a Stanford 3D Scanning Repository alignment file (``bun.conf``): each scan's pose.

    Each ``bmesh <file> tx ty tz qx qy qz qw`` line places a scan in the common frame: with ``R(q)``
    the rotation of the unit quaternion (scalar last), a scan point ``x`` lands at ``R(q)^T x + t``
    (checked on the Bunny's range scans: the scans then overlap to about 0.4 mm). ``camera`` lines
    are skipped.

    Returns:
        ``{file name: (4, 4) scan-to-common transform}`` in file order.

    Raises:
        FileNotFoundError: missing file.
        ValueError: a ``bmesh`` line without 7 numbers, or no ``bmesh`` line at all.
    """
    path = _require_file(path, "conf file")
    poses = {}
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        try:
            values = np.array([float(value) for value in fields[2:]], dtype=np.float64)
        except ValueError as error:
            raise ValueError(f"{path}: line {line_no}: {error}") from error
        if len(fields) < 2 or len(values) != 7:
            raise ValueError(
                f"{path}: line {line_no}: expected 'bmesh <file> tx ty tz qx qy qz qw', got {line.strip()!r}"
            )
        quaternion = values[3:] / np.linalg.norm(values[3:])
        pose = np.eye(4)
        pose[:3, :3] = roma.unitquat_to_rotmat(torch.from_numpy(quaternion)).numpy().T
        pose[:3, 3] = values[:3]
        poses[fields[1]] = pose
    if not poses:
        raise ValueError(f"{path}: no 'bmesh <file> tx ty tz qx qy qz qw' line")
    return poses


def write_conf(path: str | Path, poses: Mapping[str, np.ndarray]) -> None:
    """Write ``{file name: (4, 4) scan-to-common transform}`` as a Stanford alignment file, one
    ``bmesh <file> tx ty tz qx qy qz qw`` line each (:func:`read_conf` reads it back)."""
    lines = []
    for name, pose in poses.items():
        pose = np.asarray(pose, dtype=np.float64)
        quaternion = roma.rotmat_to_unitquat(torch.from_numpy(np.ascontiguousarray(pose[:3, :3].T))).numpy()
        values = " ".join(f"{value:.9g}" for value in (*pose[:3, 3], *quaternion))
        lines.append(f"bmesh {name} {values}")
    Path(path).write_text("\n".join(lines) + "\n")
