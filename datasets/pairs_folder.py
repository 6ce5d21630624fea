"""The user's own scan pairs: ``<name>_src.<ext>``, ``<name>_tgt.<ext>``, optional ``<name>_gt.txt``.

Any point-cloud format of :func:`linereg.io.read_point_cloud` works (PLY, PCD, OBJ, XYZ/TXT,
NPY/NPZ). ``<name>_gt.txt`` holds the 4x4 (or 3x4) source-to-target transform
(``tgt ≈ R @ src + t``); either every pair has one or none does (unlabeled data). Normals
are read when the files have them and estimated otherwise (RPM-Net needs them).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from linereg.datasets.base import DATASETS, PairDataset, existing_folder, item_rng
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.io import POINT_CLOUD_SUFFIXES, read_point_cloud, read_transform
from linereg.structures import PairSample

_STREAM = 41


def _by_stem(root: Path, suffix: str) -> dict[str, Path]:
    """``{name: path}`` of files ``<name><suffix>.<point-cloud extension>``."""
    found: dict[str, Path] = {}
    for path in sorted(root.iterdir()):
        if path.suffix.lower() in POINT_CLOUD_SUFFIXES and path.stem.endswith(suffix):
            name = path.stem[: -len(suffix)]
            if name in found:
                raise ValueError(f"two files for pair {name!r}{suffix}: {found[name]} and {path}")
            found[name] = path
    return found


class FolderPairs(PairDataset):
    """Scan pairs from a folder (see the module docstring).

    Args:
        root: the folder.
        num_points: points per cloud after FPS (``None`` keeps every point).
        dense_points: random cap before normal estimation (``None``: no cap).
        half_extent: scale pairs jointly into ``[-half_extent, half_extent]^3``; ``None``
            keeps the file units (the default: your data, your units).
        seed: base seed.
    """

    registry_name = "pairs_folder"

    def __init__(
        self,
        root: str | Path,
        *,
        num_points: int | None = None,
        dense_points: int | None = None,
        half_extent: float | None = None,
        seed: int = 0,
    ) -> None:
        self.root = existing_folder(root, "pairs folder")
        sources, targets = _by_stem(self.root, "_src"), _by_stem(self.root, "_tgt")
        if not sources:
            raise FileNotFoundError(
                f"no '<name>_src.<ext>' point-cloud files in {self.root} "
                f"(extensions: {', '.join(POINT_CLOUD_SUFFIXES)})"
            )
        unmatched = sorted(set(sources) ^ set(targets))
        if unmatched:
            raise ValueError(f"{self.root}: pairs without both _src and _tgt files: {unmatched}")
        self.names = sorted(sources)
        self.files = {name: (sources[name], targets[name]) for name in self.names}
        labelled = [n for n in self.names if (self.root / f"{n}_gt.txt").is_file()]
        if labelled and len(labelled) != len(self.names):
            unlabelled = sorted(set(self.names) - set(labelled))
            raise ValueError(f"{self.root}: give a <name>_gt.txt for every pair or for none; missing for {unlabelled}")
        self.labelled = bool(labelled)
        self.scan = ScanSettings(num_points=num_points, dense_points=dense_points, half_extent=half_extent)
        self.seed = seed

    def __len__(self) -> int:
        return len(self.names)

    def make_pair(self, index: int) -> PairSample:
        name = self.names[index]
        src_file, tgt_file = self.files[name]
        source = read_point_cloud(src_file, min_points=4)
        target = read_point_cloud(tgt_file, min_points=4)
        gt = read_transform(self.root / f"{name}_gt.txt") if self.labelled else None
        return finish_scan_pair(
            source.xyz,
            target.xyz,
            gt,
            self.scan,
            item_rng(self.seed, _STREAM, index),
            src_normals=source.normals,
            tgt_normals=target.normals,
            meta={
                "dataset": self.registry_name,
                "index": index,
                "name": name,
                "file": str(src_file),
                "target_file": str(tgt_file),
            },
        )

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "root": str(self.root),
            "files": [
                [path.name, path.stat().st_size, path.stat().st_mtime_ns]
                for name in self.names
                for path in self.files[name]
            ],
            "labelled": self.labelled,
            "scan": vars(self.scan),
            "seed": self.seed,
        }


@DATASETS.register("pairs_folder")
def build_pairs_folder(
    *,
    root: str,
    num_points: int | None = None,
    dense_points: int | None = None,
    half_extent: float | None = None,
    seed: int = 0,
) -> FolderPairs:
    """The user's scan pairs (see :class:`FolderPairs`)."""
    return FolderPairs(
        root,
        num_points=num_points,
        dense_points=dense_points,
        half_extent=half_extent,
        seed=seed,
    )
