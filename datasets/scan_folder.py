"""A folder of scans, paired without labels: ``dataset=scan_folder dataset.root=<folder>``.

The scans are the folder's point-cloud files (any format of :func:`linereg.io.read_point_cloud`),
in natural name order (``scan_2`` before ``scan_10``). The candidate pairs are each scan with the
ones up to ``frame_gap`` places after it (source the earlier scan, target the later), or the pairs
listed in ``pairs_file`` (``<scan> <scan>`` per line, names with or without extension, ``#``
comments). A seeded share of them is held out: ``part=val`` (``val_share``) and ``part=test``
(``test_share``; without one, the validation pairs) are disjoint from ``part=train``.

No pose is read unless ``poses`` names a file of them (a Stanford ``.conf``, every scan placed in
one frame); the configs pass it to the test split alone, so Err_R is reported where labels exist
and training and the label-free choice of the checkpoint never see one.

Training pairs can be repeated ``copies`` times, each copy's source turned by a random rotation of
up to ``source_motion_deg`` about its centre (more pairs, no label needed).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from linereg.datasets.base import DATASETS, PairDataset, existing_folder, item_rng
from linereg.datasets.formats import read_conf
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.io import POINT_CLOUD_SUFFIXES, read_point_cloud
from linereg.structures import PairSample

PARTS = ("train", "val", "test", "all")
_STREAM = 43
_SPLIT_STREAM = 44


def natural_key(name: str) -> list[Any]:
    """Sort key of a file name with its digit runs compared as numbers (``scan_2`` < ``scan_10``)."""
    return [int(chunk) if chunk.isdigit() else chunk.lower() for chunk in re.split(r"(\d+)", name)]


def list_scans(root: Path, exclude: tuple[Path, ...] = ()) -> list[Path]:
    """The point-cloud files of ``root`` in natural name order, without the ``exclude`` files."""
    excluded = {path.resolve() for path in exclude}
    scans = [
        path
        for path in root.iterdir()
        if path.is_file() and path.suffix.lower() in POINT_CLOUD_SUFFIXES and path.resolve() not in excluded
    ]
    return sorted(scans, key=lambda path: natural_key(path.name))


def neighbour_pairs(count: int, frame_gap: int) -> list[tuple[int, int]]:
    """``(i, j)`` with ``0 < j - i <= frame_gap`` over ``count`` scans, by ``i`` then ``j``."""
    return [(i, j) for i in range(count) for j in range(i + 1, min(i + frame_gap, count - 1) + 1)]


def read_pairs_file(path: Path, scans: list[Path]) -> list[tuple[int, int]]:
    """The pairs of a pairs file as scan indices (see the module docstring)."""
    index = {scan.name: i for i, scan in enumerate(scans)} | {scan.stem: i for i, scan in enumerate(scans)}
    pairs = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        unknown = [name for name in fields if name not in index]
        if len(fields) != 2 or unknown:
            raise ValueError(f"{path}: line {line_no}: expected two scans of the folder, got {line.strip()!r}")
        pairs.append((index[fields[0]], index[fields[1]]))
    return pairs


def held_out_parts(count: int, val_share: float, test_share: float, seed: int) -> dict[str, list[int]]:
    """Disjoint pair indices ``{"train", "val", "test"}`` of ``count`` pairs: a seeded permutation
    cut into ``test_share``, ``val_share`` (each at least one pair when positive) and the rest."""
    for name, share in (("val_share", val_share), ("test_share", test_share)):
        if not 0 <= share < 1:
            raise ValueError(f"{name} must be in [0, 1), got {share}")
    sizes = [max(1, round(share * count)) if share > 0 else 0 for share in (test_share, val_share)]
    if count - sum(sizes) < 1:
        raise ValueError(
            f"{count} pair(s) cannot give {sizes[1]} validation, {sizes[0]} test and at least one training pair; "
            "add scans, raise frame_gap or lower val_share / test_share"
        )
    order = np.random.default_rng([seed, _SPLIT_STREAM]).permutation(count).tolist()
    test, val, train = order[: sizes[0]], order[sizes[0] : sum(sizes)], order[sum(sizes) :]
    return {"train": sorted(train), "val": sorted(val), "test": sorted(test or val)}


def turn_about_centre(points: np.ndarray, max_angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """``points (N, 3)`` rotated about their centroid by a random axis and an angle up to ``max_angle_deg``."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(0.0, max_angle_deg))
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    centre = points.mean(axis=0)
    return (points - centre) @ rotation.T + centre


@DATASETS.register("scan_folder")
class ScanFolderPairs(PairDataset):
    """Pairs of a folder of scans (see the module docstring).

    Args:
        root: the folder.
        part: ``"train"``, ``"val"``, ``"test"`` or ``"all"`` of the candidate pairs.
        frame_gap: pair each scan with the next ``frame_gap`` ones (ignored with ``pairs_file``).
        pairs_file: a file of pairs (relative to ``root`` or absolute), or ``None``.
        val_share: share of the pairs held out for validation.
        test_share: share held out for testing (0: the test part is the validation pairs).
        poses: a ``.conf`` file of scan poses (relative to ``root`` or absolute) labelling the pairs, or ``None``.
        copies: times each pair is repeated (each copy its own source motion).
        source_motion_deg: largest random rotation of a copy's source about its centre (0: none).
        num_points: points per cloud after FPS (``None`` keeps every point).
        dense_points: random cap before normal estimation (``None``: no cap).
        half_extent: scale pairs jointly into ``[-half_extent, half_extent]^3`` (``None``: file units).
        seed: base seed (the held-out pairs and every pair's sampling).
    """

    registry_name = "scan_folder"

    def __init__(
        self,
        root: str | Path,
        *,
        part: str = "all",
        frame_gap: int = 1,
        pairs_file: str | Path | None = None,
        val_share: float = 0.25,
        test_share: float = 0.0,
        poses: str | Path | None = None,
        copies: int = 1,
        source_motion_deg: float = 0.0,
        num_points: int | None = 2048,
        dense_points: int | None = 20000,
        half_extent: float | None = 1.0,
        seed: int = 0,
    ) -> None:
        self.root = existing_folder(root, "scan folder")
        if part not in PARTS:
            raise ValueError(f"part must be one of {PARTS}, got {part!r}")
        if frame_gap < 1 or copies < 1 or source_motion_deg < 0:
            raise ValueError("frame_gap and copies must be >= 1 and source_motion_deg >= 0")
        self.pairs_file = None if pairs_file is None else self.root / Path(pairs_file).expanduser()
        self.poses_file = None if poses is None else self.root / Path(poses).expanduser()
        self.scans = list_scans(self.root, exclude=tuple(p for p in (self.pairs_file, self.poses_file) if p))
        if len(self.scans) < 2:
            raise ValueError(
                f"{self.root} holds {len(self.scans)} scan(s); pairing needs at least 2 point-cloud files "
                f"({', '.join(POINT_CLOUD_SUFFIXES)})"
            )
        candidates = (
            read_pairs_file(self.pairs_file, self.scans)
            if self.pairs_file is not None
            else neighbour_pairs(len(self.scans), frame_gap)
        )
        chosen = range(len(candidates))
        if part != "all":
            chosen = held_out_parts(len(candidates), val_share, test_share, seed)[part]
        self.part = part
        self.pairs = [candidates[i] for i in chosen]
        self.copies = copies
        self.source_motion_deg = float(source_motion_deg)
        self.scan_poses = None if self.poses_file is None else self._read_poses()
        self.scan = ScanSettings(num_points=num_points, dense_points=dense_points, half_extent=half_extent)
        self.seed = seed

    def _read_poses(self) -> list[np.ndarray]:
        """Each scan's pose in the common frame of :attr:`poses_file` (scan to common, ``(4, 4)``)."""
        poses = read_conf(self.poses_file)
        missing = [scan.name for scan in self.scans if scan.name not in poses]
        if missing:
            raise ValueError(f"{self.poses_file} has no pose for {missing}")
        return [poses[scan.name] for scan in self.scans]

    def __len__(self) -> int:
        return len(self.pairs) * self.copies

    def make_pair(self, index: int) -> PairSample:
        source, target = self.pairs[index % len(self.pairs)]
        rng = item_rng(self.seed, _STREAM, index)
        src_xyz = read_point_cloud(self.scans[source], min_points=4).xyz.astype(np.float64)
        tgt_xyz = read_point_cloud(self.scans[target], min_points=4).xyz.astype(np.float64)
        if self.source_motion_deg > 0:
            src_xyz = turn_about_centre(src_xyz, self.source_motion_deg, rng)
        gt = None
        if self.scan_poses is not None:
            gt = np.linalg.inv(self.scan_poses[target]) @ self.scan_poses[source]
        meta = {
            "dataset": self.registry_name,
            "index": index,
            "name": f"{self.scans[source].stem}-{self.scans[target].stem}",
        }
        if self.source_motion_deg == 0:  # the files are the pair: register's check reads them
            meta.update(file=str(self.scans[source]), target_file=str(self.scans[target]))
        return finish_scan_pair(src_xyz, tgt_xyz, gt, self.scan, rng, meta=meta)

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "root": str(self.root),
            "files": [[scan.name, scan.stat().st_size, scan.stat().st_mtime_ns] for scan in self.scans],
            "pairs": [list(pair) for pair in self.pairs],
            "poses": None if self.poses_file is None else str(self.poses_file),
            "copies": self.copies,
            "source_motion_deg": self.source_motion_deg,
            "scan": vars(self.scan),
            "seed": self.seed,
        }
