"""Generate and cache the paper's datasets (Airplane, Human, Real) or the procedural default.

Usage::

    python scripts/prepare_dataset.py airplane --root data/modelnet40/modelnet40_normal_resampled
    python scripts/prepare_dataset.py human --root data/human_meshes
    python scripts/prepare_dataset.py real --threedmatch data/3dmatch --rgbd data/rgbd
    python scripts/prepare_dataset.py procedural --num-shapes 100

Each split is generated once into ``--out`` (compressed shards + a manifest of the settings,
see ``datasets/cache.py``) with ``--workers`` processes, and the script prints the folder,
the pair count, the time taken and the config that loads it (``{name: cached, path: ...}``).

* airplane: 625 ModelNet40 airplanes (text or HDF5 via ``modelnet40``; ``.off`` meshes via
  ``mesh_folder``), random 500/125 split, 18 views each: 9000 train / 2250 test pairs.
* human: every mesh under ``--root`` (the paper: 110 Axyz bodies), random 100/10 split,
  50 views each, target = the whole body: 5000 / 500 pairs for 110 meshes.
* real: every 3DMatch scene under ``--threedmatch`` (pairs with overlap >= 0.7) and every
  7-Scenes / TUM sequence under ``--rgbd`` (pairs 20 frames apart), 2048 points in
  ``[-5, 5]^3``, split 80 / 20 at random (the paper: 8000 / 2000).
* procedural: the embedded default (no files), ``--num-shapes`` train and a fifth as many test.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from linereg.datasets import build_dataset, materialize  # noqa: E402

PAPER_AIRPLANE_SHAPES = 625
PAPER_AIRPLANE_TRAIN_FRACTION = 500 / 625
PAPER_HUMAN_TRAIN_FRACTION = 100 / 110
PAPER_REAL_MIN_OVERLAP = 0.7


def airplane_configs(root: Path, seed: int) -> dict[str, dict[str, Any]]:
    """Train/test configs of the Airplane dataset from a ModelNet40 folder."""
    common: dict[str, Any] = {
        "root": str(root),
        "categories": "airplane",
        "split_rule": "random",
        "max_shapes": PAPER_AIRPLANE_SHAPES,
        "train_fraction": PAPER_AIRPLANE_TRAIN_FRACTION,
        "split_seed": seed,
        "seed": seed,
    }
    if any(root.glob("airplane/**/*.off")):
        common.update(name="mesh_folder", protocol={"name": "airplane", "view_axis": [0, 0, 1]})
    else:
        common.update(name="modelnet40", protocol="airplane")
    return {split: {**common, "split": split} for split in ("train", "test")}


def human_configs(root: Path, seed: int) -> dict[str, dict[str, Any]]:
    """Train/test configs of the Human dataset from a folder of body meshes (y-up)."""
    common = {
        "name": "mesh_folder",
        "root": str(root),
        "protocol": "human",
        "split_rule": "random",
        "train_fraction": PAPER_HUMAN_TRAIN_FRACTION,
        "split_seed": seed,
        "seed": seed,
    }
    return {split: {**common, "split": split} for split in ("train", "test")}


def _threedmatch_scenes(root: Path) -> list[Path]:
    """Scene folders (holding ``cloud_bin_0.ply``) under ``root``."""
    return sorted(p.parent for p in root.glob("**/cloud_bin_0.ply"))


def _rgbd_sequences(root: Path) -> list[Path]:
    """Sequence folders (7-Scenes frames or a TUM ``depth.txt``) under ``root``."""
    seven_scenes = {p.parent for p in root.glob("**/frame-000000.depth.png")}
    tum = {p.parent for p in root.glob("**/depth.txt")}
    return sorted(seven_scenes | tum)


def real_configs(threedmatch: Path | None, rgbd: Path | None, seed: int) -> dict[str, dict[str, Any]]:
    """Train/test configs of the Real dataset (3DMatch + RGB-D sequences, mixed and split)."""
    parts: list[dict[str, Any]] = []
    if threedmatch is not None:
        parts += [
            {"name": "threedmatch", "root": str(scene), "min_overlap": PAPER_REAL_MIN_OVERLAP, "seed": seed}
            for scene in _threedmatch_scenes(threedmatch)
        ]
    if rgbd is not None:
        parts += [
            {"name": "rgbd_sequence", "root": str(sequence), "frame_gap": 20, "seed": seed}
            for sequence in _rgbd_sequences(rgbd)
        ]
    if not parts:
        raise SystemExit(
            "error: no 3DMatch scene (cloud_bin_0.ply) or RGB-D sequence (frame-000000.depth.png, "
            "depth.txt) found under --threedmatch / --rgbd"
        )
    common = {"name": "concat", "datasets": parts, "split_seed": seed}
    return {split: {**common, "split": split} for split in ("train", "test")}


def procedural_configs(num_shapes: int, seed: int) -> dict[str, dict[str, Any]]:
    """Train/test configs of the procedural default dataset."""
    sizes = {"train": num_shapes, "test": max(1, num_shapes // 5)}
    return {
        split: {"name": "procedural", "split": split, "num_shapes": size, "seed": seed} for split, size in sizes.items()
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", choices=("airplane", "human", "real", "procedural"))
    parser.add_argument("--root", type=Path, help="ModelNet40 folder (airplane) or mesh folder (human)")
    parser.add_argument("--threedmatch", type=Path, help="folder of 3DMatch scenes (real)")
    parser.add_argument("--rgbd", type=Path, help="folder of 7-Scenes / TUM sequences (real)")
    parser.add_argument("--num-shapes", type=int, default=100, help="procedural train shapes")
    parser.add_argument("--out", type=Path, default=Path("data/cache"), help="cache folder")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--splits", nargs="+", choices=("train", "test"), default=["train", "test"])
    args = parser.parse_args(argv)
    if args.dataset in ("airplane", "human") and args.root is None:
        parser.error(f"{args.dataset} needs --root")
    if args.dataset == "airplane":
        configs = airplane_configs(args.root, args.seed)
    elif args.dataset == "human":
        configs = human_configs(args.root, args.seed)
    elif args.dataset == "real":
        configs = real_configs(args.threedmatch, args.rgbd, args.seed)
    else:
        configs = procedural_configs(args.num_shapes, args.seed)
    for split in args.splits:
        started = time.perf_counter()
        cached = materialize(build_dataset(configs[split]), args.out, workers=args.workers)
        elapsed = time.perf_counter() - started
        print(
            f"{args.dataset} {split}: {len(cached)} pairs in {cached.path} "
            f"({elapsed:.1f} s; generated {cached.manifest['generated_pairs']} with "
            f"{cached.manifest['workers']} worker(s))"
        )
        print(f"  load with: {{name: cached, path: {cached.path}}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
