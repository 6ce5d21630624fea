"""Time pair generation (Airplane protocol) and DataLoader throughput over the pair cache.

Usage::

    python scripts/bench_datasets.py [--source procedural|modelnet40] [--root DIR]
                                     [--pairs 1000] [--workers 2] [--loader-workers 0 2]

1. Generates ``--pairs`` Airplane-protocol pairs (18 views per shape, 1024 points, normals)
   into a fresh cache with ``--workers`` processes and reports pairs/s and the CPU time per
   pair (robust to other load on the machine). Shapes are loaded once per worker and reused
   for their 18 views ("cached shapes").
2. Iterates the cache with a shuffling DataLoader (batch ``--batch-size``, ``collate_pairs``)
   for ``--epochs`` epochs per worker count and reports samples/s.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from linereg.datasets import build_dataset, collate_pairs, materialize  # noqa: E402
from linereg.paths import shared_data_dir  # noqa: E402

VIEWS = 18


def generator_config(source: str, root: Path | None, pairs: int) -> dict:
    """Config of an Airplane-protocol dataset with at least ``pairs`` pairs."""
    shapes = math.ceil(pairs / VIEWS)
    if source == "procedural":
        return {"name": "procedural", "num_shapes": shapes, "protocol": "airplane"}
    if root is None:
        shared = shared_data_dir()
        if shared is None:
            raise SystemExit("error: --root is required for modelnet40 (no shared data found)")
        root = shared / "modelnet40_normal_resampled"
    return {
        "name": "modelnet40",
        "root": str(root),
        "categories": "airplane",
        "split": "all",
        "max_shapes": shapes,
        "protocol": "airplane",
    }


def _cpu_seconds() -> float:
    """User + system CPU time of this process and its finished children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def time_loader(dataset, *, batch_size: int, workers: int, epochs: int) -> float:
    """Samples per second of shuffled epochs over ``dataset``."""
    loader = DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=True,
        num_workers=workers,
        collate_fn=collate_pairs,
        persistent_workers=workers > 0,
        generator=torch.Generator().manual_seed(0),
    )
    seen = 0
    started = time.perf_counter()
    for _ in range(epochs):
        for batch in loader:
            seen += batch.batch_size
    return seen / (time.perf_counter() - started)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("procedural", "modelnet40"), default="modelnet40")
    parser.add_argument("--root", type=Path, help="modelnet40_normal_resampled folder")
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=2, help="generation processes")
    parser.add_argument("--loader-workers", type=int, nargs="+", default=[0, 2])
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--epochs", type=int, default=3)
    args = parser.parse_args(argv)

    config = generator_config(args.source, args.root, args.pairs)
    generator = build_dataset(config)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; source {args.source}")
    with tempfile.TemporaryDirectory() as out:
        cpu_before = _cpu_seconds()
        started = time.perf_counter()
        cached = materialize(generator, out, workers=args.workers, progress=False)
        elapsed = time.perf_counter() - started
        cpu = _cpu_seconds() - cpu_before
        print(
            f"generate: {len(cached)} Airplane pairs with {args.workers} worker(s) in "
            f"{elapsed:.1f} s = {len(cached) / elapsed:.1f} pairs/s; CPU {1000 * cpu / len(cached):.0f} "
            f"ms/pair (load average before: {os.getloadavg()[0]:.1f})"
        )
        size_mb = sum(p.stat().st_size for p in cached.path.iterdir()) / 2**20
        started = time.perf_counter()
        reloaded = build_dataset({"name": "cached", "path": str(cached.path)})
        print(f"cache: {size_mb:.1f} MB on disk, loaded in {time.perf_counter() - started:.2f} s")
        for workers in args.loader_workers:
            rate = time_loader(reloaded, batch_size=args.batch_size, workers=workers, epochs=args.epochs)
            print(f"loader: batch {args.batch_size}, {workers} worker(s): {rate:.0f} samples/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
