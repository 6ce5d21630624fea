"""RGB-D sequences: depth images + intrinsics + (optional) camera poses -> frame pairs.

Pairs are frames ``a`` and ``b = a + frame_gap`` (the paper: 20 frames apart). The source is
frame ``a``, the target frame ``b``, both back-projected into their own camera coordinates;
with camera-to-world poses ``T_a``, ``T_b`` the ground truth is ``T_b^-1 @ T_a`` (maps source
camera coordinates to target camera coordinates). Without poses (or ``use_poses=False``) the
pairs are unlabeled. Pairs are then finished like the paper's Real dataset: normals oriented
towards the sensor, FPS to 2048 points, joint scaling into ``[-5, 5]^3``.

Layouts (``layout="auto"`` picks by the files present):

* ``"7scenes"``: ``frame-XXXXXX.depth.png`` (mm), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world),
  optional ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240).
* ``"tum"``: ``depth.txt`` (``timestamp depth/xxx.png``), depth scaled by 5000, optional
  ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, associated to the nearest depth
  timestamp within 20 ms; depth frames without a pose are dropped when poses are used),
  intrinsics from the ``freiburg1/2/3`` name (TUM's calibrated values) or 525 / 319.5 / 239.5.
* ``"folder"``: ``depth/`` images (PNG/PGM, sorted, numbered by the digits of their names),
  optional ``trajectory.log`` (Redwood camera-to-world log) or ``pose.txt`` / ``poses.txt``
  (``tx ty tz qx qy qz qw`` per frame), intrinsics from ``intrinsics=`` or a
  ``camera_intrinsics.json`` / ``intrinsic.json`` / ``camera-intrinsics.txt`` in the folder.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from linereg.datasets.base import DATASETS, PairDataset, existing_folder, item_rng
from linereg.datasets.formats import (
    Intrinsics,
    read_association_list,
    read_depth_image,
    read_intrinsics,
    read_log,
    read_pose_list,
    read_pose_matrix,
)
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.se3 import compose, inverse
from linereg.structures import PairSample

LAYOUTS = ("auto", "7scenes", "tum", "folder")
SEVEN_SCENES_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0)
TUM_INTRINSICS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6),
}
DEFAULT_INTRINSICS = Intrinsics(525.0, 525.0, 319.5, 239.5)
DEFAULT_DEPTH_SCALE = {"7scenes": 1000.0, "tum": 5000.0, "folder": 1000.0}
TUM_MAX_TIME_DIFFERENCE = 0.02
_INTRINSICS_FILES = ("camera_intrinsics.json", "intrinsic.json", "camera-intrinsics.txt")
_STREAM = 31


@dataclass(frozen=True)
class Frame:
    """One depth frame: its number, image path and camera-to-world pose (or ``None``)."""

    number: int
    depth: Path
    pose: np.ndarray | None


def depth_to_points(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    *,
    depth_scale: float,
    pixel_stride: int = 1,
    max_depth: float | None = None,
) -> np.ndarray:
    """Back-project a raw depth image into camera coordinates (x right, y down, z forward).

    Args:
        depth: ``(H, W)`` raw integer depth (0 and 65535 are invalid).
        intrinsics: pinhole intrinsics in pixels.
        depth_scale: raw units per metre (1000 for millimetres, 5000 for TUM).
        pixel_stride: use every ``pixel_stride``-th row and column.
        max_depth: drop points farther than this (metres), ``None`` keeps all.

    Returns:
        ``(P, 3)`` float64 points in metres.
    """
    if depth_scale <= 0:
        raise ValueError(f"depth_scale must be positive, got {depth_scale}")
    rows, cols = np.mgrid[0 : depth.shape[0] : pixel_stride, 0 : depth.shape[1] : pixel_stride]
    raw = depth[rows, cols]
    valid = (raw > 0) & (raw < 65535)
    z = raw[valid].astype(np.float64) / depth_scale
    if max_depth is not None:
        keep = z <= max_depth
        z, rows, cols = z[keep], rows[valid][keep], cols[valid][keep]
    else:
        rows, cols = rows[valid], cols[valid]
    x = (cols - intrinsics.cx) * z / intrinsics.fx
    y = (rows - intrinsics.cy) * z / intrinsics.fy
    return np.stack([x, y, z], axis=1)


def _number(path: Path, position: int) -> int:
    """The last group of digits in a file name, else ``position``."""
    digits = re.findall(r"\d+", path.name)
    return int(digits[-1]) if digits else position


def _detect_layout(root: Path) -> str:
    """The layout of a sequence folder (see the module docstring)."""
    if any(root.glob("frame-*.depth.png")):
        return "7scenes"
    if (root / "depth.txt").is_file():
        return "tum"
    if (root / "depth").is_dir():
        return "folder"
    raise FileNotFoundError(
        f"{root} is not a recognised RGB-D sequence: expected frame-XXXXXX.depth.png "
        "(7-Scenes), depth.txt (TUM) or a depth/ folder"
    )


def _seven_scenes_frames(root: Path, use_poses: bool) -> list[Frame]:
    """Frames of a 7-Scenes sequence folder."""
    frames = []
    for path in sorted(root.glob("frame-*.depth.png")):
        number = _number(path.with_name(path.name.replace(".depth.png", "")), 0)
        pose_file = path.with_name(path.name.replace(".depth.png", ".pose.txt"))
        pose = read_pose_matrix(pose_file) if use_poses and pose_file.is_file() else None
        if use_poses and pose is None:
            raise FileNotFoundError(f"pose file missing for {path.name}: {pose_file}")
        frames.append(Frame(number, path, pose))
    return frames


def _tum_frames(root: Path, use_poses: bool) -> list[Frame]:
    """Frames of a TUM RGB-D sequence (poses associated by timestamp)."""
    depth_list = read_association_list(root / "depth.txt")
    ground_truth = root / "groundtruth.txt"
    if not use_poses or not ground_truth.is_file():
        return [Frame(i, root / name, None) for i, (_, name) in enumerate(depth_list)]
    stamps, poses = read_pose_list(ground_truth, timestamps=True)
    frames = []
    for i, (stamp, name) in enumerate(depth_list):
        nearest = int(np.argmin(np.abs(stamps - stamp)))
        if abs(stamps[nearest] - stamp) <= TUM_MAX_TIME_DIFFERENCE:
            frames.append(Frame(i, root / name, poses[nearest]))
    return frames


def _folder_frames(root: Path, use_poses: bool) -> list[Frame]:
    """Frames of a ``depth/`` folder, with ``trajectory.log`` or ``pose(s).txt`` poses."""
    images = sorted(
        (p for p in (root / "depth").iterdir() if p.suffix.lower() in (".png", ".pgm")),
        key=lambda p: (_number(p, 0), p.name),
    )
    if not images:
        raise FileNotFoundError(f"no .png/.pgm depth images in {root / 'depth'}")
    poses: np.ndarray | None = None
    if use_poses:
        if (root / "trajectory.log").is_file():
            poses = np.stack([e.transform for e in read_log(root / "trajectory.log")])
        for name in ("pose.txt", "poses.txt"):
            if poses is None and (root / name).is_file():
                poses = read_pose_list(root / name, timestamps=False)[1]
        if poses is not None and len(poses) != len(images):
            raise ValueError(f"{root}: {len(poses)} poses for {len(images)} depth images")
    return [Frame(_number(p, i), p, None if poses is None else poses[i]) for i, p in enumerate(images)]


def _default_intrinsics(root: Path, layout: str) -> Intrinsics:
    """Intrinsics from a file in the folder, else the layout's default."""
    for name in _INTRINSICS_FILES:
        if (root / name).is_file():
            return read_intrinsics(root / name)
    if layout == "7scenes":
        return SEVEN_SCENES_INTRINSICS
    if layout == "tum":
        for key, value in TUM_INTRINSICS.items():
            if key in root.name:
                return value
    return DEFAULT_INTRINSICS


@DATASETS.register("rgbd_sequence")
class RgbdSequencePairs(PairDataset):
    """Pairs of depth frames ``frame_gap`` apart from one RGB-D sequence.

    Args:
        root: the sequence folder.
        layout: ``"auto"``, ``"7scenes"``, ``"tum"`` or ``"folder"``.
        frame_gap: frame-number difference between source and target (paper: 20).
        pair_stride: use every ``pair_stride``-th possible source frame.
        frame_range: ``[first, stop)`` frame numbers both frames of a pair must lie in (a
            temporal train/test split of one sequence); ``None`` uses every frame.
        use_poses: label pairs from the camera poses (``False``: unlabeled pairs).
        intrinsics: ``[fx, fy, cx, cy]`` or an intrinsics file (JSON / 3x3 text); default from
            the folder or the layout.
        depth_scale: raw depth units per metre (default: 1000, TUM 5000).
        pixel_stride: back-project every ``pixel_stride``-th pixel.
        max_depth: drop points beyond this depth in metres.
        num_points, dense_points, half_extent: how each frame pair is sampled and scaled, as the
            paper's Real pairs by default (:class:`~linereg.datasets.scan_pairs.ScanSettings`;
            ``half_extent=None`` keeps metres).
        seed: base seed.
    """

    registry_name = "rgbd_sequence"

    def __init__(
        self,
        root: str | Path,
        *,
        layout: str = "auto",
        frame_gap: int = 20,
        pair_stride: int = 1,
        frame_range: Sequence[int] | None = None,
        use_poses: bool = True,
        intrinsics: Sequence[float] | str | Path | None = None,
        depth_scale: float | None = None,
        pixel_stride: int = 2,
        max_depth: float | None = None,
        num_points: int | None = ScanSettings.num_points,
        dense_points: int | None = ScanSettings.dense_points,
        half_extent: float | None = ScanSettings.half_extent,
        seed: int = 0,
    ) -> None:
        self.root = existing_folder(root, "RGB-D sequence folder")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if frame_gap < 1 or pair_stride < 1 or pixel_stride < 1:
            raise ValueError("frame_gap, pair_stride and pixel_stride must be >= 1")
        self.layout = _detect_layout(self.root) if layout == "auto" else layout
        readers = {"7scenes": _seven_scenes_frames, "tum": _tum_frames, "folder": _folder_frames}
        frames = readers[self.layout](self.root, use_poses)
        if frame_range is not None:
            if len(frame_range) != 2 or frame_range[0] >= frame_range[1]:
                raise ValueError(f"frame_range must be [first, stop) with first < stop, got {list(frame_range)}")
            frames = [f for f in frames if frame_range[0] <= f.number < frame_range[1]]
        self.frame_range = None if frame_range is None else [int(v) for v in frame_range]
        by_number = {frame.number: frame for frame in frames}
        starts = [f for f in frames if f.number + frame_gap in by_number][::pair_stride]
        self.pairs = [(f, by_number[f.number + frame_gap]) for f in starts]
        if not self.pairs:
            raise ValueError(
                f"no frame pairs {frame_gap} frames apart in {self.root} ({len(frames)} frames, "
                f"numbers {[f.number for f in frames[:5]]}...)"
            )
        if isinstance(intrinsics, str | Path):
            self.intrinsics = read_intrinsics(intrinsics)
        elif intrinsics is not None:
            if len(intrinsics) != 4:
                raise ValueError(f"intrinsics must be [fx, fy, cx, cy], got {list(intrinsics)}")
            self.intrinsics = Intrinsics(*(float(v) for v in intrinsics))
        else:
            self.intrinsics = _default_intrinsics(self.root, self.layout)
        self.depth_scale = DEFAULT_DEPTH_SCALE[self.layout] if depth_scale is None else depth_scale
        self.use_poses = use_poses
        self.frame_gap = frame_gap
        self.pixel_stride = pixel_stride
        self.max_depth = max_depth
        self.scan = ScanSettings(num_points=num_points, dense_points=dense_points, half_extent=half_extent)
        self.seed = seed

    def __len__(self) -> int:
        return len(self.pairs)

    def frame_points(self, frame: Frame) -> np.ndarray:
        """Back-projected points of one frame, camera coordinates in metres."""
        points = depth_to_points(
            read_depth_image(frame.depth),
            self.intrinsics,
            depth_scale=self.depth_scale,
            pixel_stride=self.pixel_stride,
            max_depth=self.max_depth,
        )
        if len(points) < 16:
            raise ValueError(f"{frame.depth}: only {len(points)} valid depth pixels")
        return points

    def make_pair(self, index: int) -> PairSample:
        source, target = self.pairs[index]
        gt = None
        if source.pose is not None and target.pose is not None:
            poses = torch.from_numpy(np.stack([source.pose, target.pose]))
            gt = compose(inverse(poses[1]), poses[0]).numpy()
        origin = np.zeros(3)
        return finish_scan_pair(
            self.frame_points(source),
            self.frame_points(target),
            gt,
            self.scan,
            item_rng(self.seed, _STREAM, index),
            src_viewpoint=origin,
            tgt_viewpoint=origin,
            meta={
                "dataset": self.registry_name,
                "index": index,
                "sequence": self.root.name,
                "source": source.number,
                "target": target.number,
                "file": str(source.depth),
            },
        )

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "root": str(self.root),
            "layout": self.layout,
            "pairs": [[s.number, t.number] for s, t in self.pairs],
            "frame_range": self.frame_range,
            "use_poses": self.use_poses,
            "intrinsics": self.intrinsics.as_list(),
            "depth_scale": self.depth_scale,
            "pixel_stride": self.pixel_stride,
            "max_depth": self.max_depth,
            "scan": vars(self.scan),
            "seed": self.seed,
        }
