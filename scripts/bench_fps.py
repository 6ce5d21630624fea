"""Time farthest-point sampling: the fpsample variants against a plain batched-torch FPS.

Usage: ``.venv/bin/python scripts/bench_fps.py [--points 100000] [--repeats 3]``

Each row samples ``n`` of ``--points`` uniformly random points, asking for start index 0, and
reports the best wall time of ``--repeats`` runs, the ratio to the torch reference timed in the
same run (below 1 is faster), the start index actually used (fpsample's bucket variants pick
their own), ``prefix``: how many leading indices equal exact FPS from that same start (the
torch reference for start 0, ``fpsample.fps_sampling`` otherwise; exact methods part only at
float32 distance ties), and ``cover``: the largest distance from any point to its nearest
sample, relative to the torch reference's (above 1 means a worse spread).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import fpsample
import numpy as np
import torch
from scipy.spatial import cKDTree

from linereg.pointcloud import farthest_point_sampling


def torch_fps(points: torch.Tensor, n_samples: int) -> torch.Tensor:
    """Reference FPS on a ``(B, N, 3)`` tensor, starting at index 0; returns ``(B, n)`` long."""
    batch, num_points, _ = points.shape
    idx = torch.zeros(batch, n_samples, dtype=torch.long, device=points.device)
    nearest = torch.full((batch, num_points), float("inf"), device=points.device)
    rows = torch.arange(batch, device=points.device)
    current = torch.zeros(batch, dtype=torch.long, device=points.device)
    for i in range(n_samples):
        idx[:, i] = current
        step = ((points - points[rows, current][:, None, :]) ** 2).sum(-1)
        nearest = torch.minimum(nearest, step)
        current = nearest.argmax(dim=1)
    return idx


def best_time(fn: Callable[[], np.ndarray], repeats: int) -> tuple[float, np.ndarray]:
    """Best wall time over ``repeats`` calls and the last result (as an int64 array)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return min(times), np.asarray(result, dtype=np.int64)


def variants(points: np.ndarray, n: int) -> dict[str, Callable[[], np.ndarray]]:
    """The CPU samplers compared, by name."""
    candidates = {
        "fpsample.fps_sampling": lambda: fpsample.fps_sampling(points, n, 0),
        "fpsample.fps_npdu_sampling": lambda: fpsample.fps_npdu_sampling(points, n, start_idx=0),
        "fpsample.fps_npdu_kdtree_sampling": lambda: fpsample.fps_npdu_kdtree_sampling(points, n, start_idx=0),
        "fpsample.bucket_fps_kdtree_sampling": lambda: fpsample.bucket_fps_kdtree_sampling(points, n, 0),
    }
    for height in (3, 5, 7, 9):
        candidates[f"fpsample.bucket_fps_kdline_sampling h={height}"] = lambda h=height: (
            fpsample.bucket_fps_kdline_sampling(points, n, h, 0)
        )
    candidates["linereg fps (start_index=None)"] = lambda: farthest_point_sampling(points, n)
    candidates["linereg fps (start_index=0)"] = lambda: farthest_point_sampling(points, n, start_index=0)
    return candidates


def coverage_radius(points: np.ndarray, idx: np.ndarray) -> float:
    """Largest distance from a point of ``points`` to its nearest sample ``points[idx]``."""
    return float(cKDTree(points[idx]).query(points)[0].max())


def common_prefix(a: np.ndarray, b: np.ndarray) -> int:
    """Number of leading entries on which two index arrays agree."""
    differ = np.flatnonzero(a != b)
    return int(differ[0]) if differ.size else len(a)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    points = np.random.default_rng(0).random((args.points, 3), dtype=np.float32)
    points_torch = torch.from_numpy(points)[None]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, N = {args.points}")
    print(f"{'method':<44} {'n':>6} {'seconds':>8} {'vs torch':>8} {'start':>6} {'prefix':>6} {'cover':>6}")
    for n_samples in (1024, 10_000):
        reference_seconds, reference_idx = best_time(lambda n=n_samples: torch_fps(points_torch, n)[0], args.repeats)
        reference_cover = coverage_radius(points, reference_idx)
        print(
            f"{'torch reference (batched, B=1)':<44} {n_samples:>6} {reference_seconds:>8.4f} "
            f"{1.0:>8.3f} {0:>6} {n_samples:>6} {1.0:>6.3f}"
        )
        for name, sampler in variants(points, n_samples).items():
            seconds, idx = best_time(sampler, args.repeats)
            exact = reference_idx if idx[0] == 0 else fpsample.fps_sampling(points, n_samples, int(idx[0]))
            cover = coverage_radius(points, idx) / reference_cover
            print(
                f"{name:<44} {n_samples:>6} {seconds:>8.4f} "
                f"{seconds / reference_seconds:>8.3f} {idx[0]:>6} "
                f"{common_prefix(idx, exact):>6} {cover:>6.3f}"
            )


if __name__ == "__main__":
    main()
