"""3DMatch / 3DLoMatch fragment pairs with the benchmark's ``gt.log``.

Layout (the geometric-registration benchmark): a scene folder of fragments
``cloud_bin_<i>.ply`` and a ``gt.log`` whose blocks ``i j n`` + 4x4 ``T`` satisfy
``p_in_fragment_i = T @ p_in_fragment_j``. Each block becomes one pair with **source =
fragment j, target = fragment i, gt_transform = T** (source to target). ``gt.log`` is looked
up in the scene folder, then in a sibling ``<scene>-evaluation/`` folder (the official
download), unless ``gt_log`` names it. ``gt_overlap.log`` (``i,j,ratio``) next to it enables
the overlap filter (the paper keeps pairs with overlap > 0.7; 3DLoMatch is 0.1-0.3) and gives each
pair's ``meta["overlap"]``; with ``compute_overlap`` a pair it does not list gets the share of
its source points within 3.75 cm of a target point after the ground truth
(:func:`linereg.datasets.fragments.overlap_ratio`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from linereg.datasets.base import DATASETS, PairDataset, existing_folder, item_rng
from linereg.datasets.formats import read_log, read_overlap_log
from linereg.datasets.fragments import overlap_ratio
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.io import read_point_cloud
from linereg.structures import PairSample

_STREAM = 21


class NoPairsError(ValueError):
    """A scene whose ``gt.log`` pairs were all filtered out or miss a fragment file."""


def find_gt_log(scene: Path) -> Path | None:
    """``gt.log`` of a scene folder (in it, or in ``<scene>-evaluation/``), or ``None``."""
    for candidate in (scene / "gt.log", scene.parent / f"{scene.name}-evaluation" / "gt.log"):
        if candidate.is_file():
            return candidate
    return None


def _find_gt_log(scene: Path) -> Path:
    """:func:`find_gt_log`, or FileNotFoundError."""
    found = find_gt_log(scene)
    if found is not None:
        return found
    raise FileNotFoundError(
        f"no gt.log for the 3DMatch scene {scene} (looked in the folder and in "
        f"{scene.name}-evaluation/); pass gt_log=<path>"
    )


@DATASETS.register("threedmatch")
class ThreeDMatchPairs(PairDataset):
    """Fragment pairs of one 3DMatch scene.

    Args:
        root: scene folder with ``cloud_bin_<i>.ply`` fragments.
        gt_log: the scene's ``gt.log`` (default: found next to the fragments).
        overlap_log: ``gt_overlap.log`` (default: next to ``gt_log`` when present).
        min_overlap: keep pairs with overlap ratio ``>= min_overlap`` (needs overlaps).
        max_overlap: keep pairs with overlap ratio ``<= max_overlap`` (3DLoMatch: 0.3).
        skip_missing: drop pairs whose fragment files are absent instead of failing.
        compute_overlap: measure the overlap of pairs without a ``gt_overlap.log`` ratio.
        num_points, dense_points, half_extent: how each fragment pair is sampled and scaled
            (:class:`~linereg.datasets.scan_pairs.ScanSettings`; ``half_extent=None`` keeps metres).
        seed: base seed.
    """

    registry_name = "threedmatch"

    def __init__(
        self,
        root: str | Path,
        *,
        gt_log: str | Path | None = None,
        overlap_log: str | Path | None = None,
        min_overlap: float | None = None,
        max_overlap: float | None = None,
        skip_missing: bool = False,
        compute_overlap: bool = False,
        num_points: int | None = ScanSettings.num_points,
        dense_points: int | None = ScanSettings.dense_points,
        half_extent: float | None = ScanSettings.half_extent,
        seed: int = 0,
    ) -> None:
        self.root = existing_folder(root, "3DMatch scene folder")
        self.gt_log = Path(gt_log).resolve() if gt_log is not None else _find_gt_log(self.root)
        entries = read_log(self.gt_log)
        if overlap_log is None and (self.gt_log.parent / "gt_overlap.log").is_file():
            overlap_log = self.gt_log.parent / "gt_overlap.log"
        overlaps = read_overlap_log(overlap_log) if overlap_log is not None else None
        if (min_overlap is not None or max_overlap is not None) and overlaps is None:
            raise ValueError(
                f"min_overlap/max_overlap need overlap ratios, but there is no gt_overlap.log "
                f"next to {self.gt_log}; pass overlap_log=<path>"
            )
        if overlaps is not None:
            low = -np.inf if min_overlap is None else min_overlap
            high = np.inf if max_overlap is None else max_overlap
            entries = [e for e in entries if low <= overlaps.get((e.i, e.j), -1.0) <= high]
        missing = [e for e in entries if not (self._fragment(e.i).is_file() and self._fragment(e.j).is_file())]
        if missing and not skip_missing:
            example = missing[0]
            raise FileNotFoundError(
                f"{len(missing)} of {len(entries)} pairs of {self.gt_log} reference fragments "
                f"missing from {self.root} (e.g. cloud_bin_{example.i}.ply / "
                f"cloud_bin_{example.j}.ply); pass skip_missing=True to use the "
                f"{len(entries) - len(missing)} complete pairs"
            )
        missing_ids = {id(e) for e in missing}
        self.entries = [e for e in entries if id(e) not in missing_ids]
        if not self.entries:
            raise NoPairsError(
                f"no 3DMatch pairs left in {self.root} (gt.log {self.gt_log}, "
                f"min_overlap={min_overlap}, max_overlap={max_overlap})"
            )
        self.overlaps = overlaps or {}
        self.scan = ScanSettings(num_points=num_points, dense_points=dense_points, half_extent=half_extent)
        self.seed = seed
        self.compute_overlap = compute_overlap
        self.filters = {"min_overlap": min_overlap, "max_overlap": max_overlap}

    def _fragment(self, index: int) -> Path:
        """Path of fragment ``index``."""
        return self.root / f"cloud_bin_{index}.ply"

    def __len__(self) -> int:
        return len(self.entries)

    def make_pair(self, index: int) -> PairSample:
        entry = self.entries[index]
        source = read_point_cloud(self._fragment(entry.j), min_points=4)
        target = read_point_cloud(self._fragment(entry.i), min_points=4)
        meta: dict[str, Any] = {
            "dataset": self.registry_name,
            "index": index,
            "scene": self.root.name,
            "source": f"cloud_bin_{entry.j}",
            "target": f"cloud_bin_{entry.i}",
            "file": str(self._fragment(entry.j)),
        }
        if (entry.i, entry.j) in self.overlaps:
            meta["overlap"] = self.overlaps[(entry.i, entry.j)]
        elif self.compute_overlap:
            meta["overlap"] = overlap_ratio(source.xyz, target.xyz, entry.transform)
        return finish_scan_pair(
            source.xyz,
            target.xyz,
            entry.transform,
            self.scan,
            item_rng(self.seed, _STREAM, index),
            src_normals=source.normals,
            tgt_normals=target.normals,
            src_viewpoint=np.zeros(3),
            tgt_viewpoint=np.zeros(3),
            meta=meta,
        )

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "root": str(self.root),
            "gt_log": str(self.gt_log),
            "pairs": [[e.i, e.j] for e in self.entries],
            **self.filters,
            "compute_overlap": self.compute_overlap,
            "scan": vars(self.scan),
            "seed": self.seed,
        }
