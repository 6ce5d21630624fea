"""Benchmark the line-intersection metric: forward and backward time and peak memory.

    python scripts/bench_loss.py                      # the README table
    python scripts/bench_loss.py --json               # one JSON object per row
    python scripts/bench_loss.py --points 1024 --lines 20000 --repeats 10

Each row is one pair (source and target with ``N`` points each, ``L`` lines), timed as the
median over ``--repeats`` runs after a warm-up. Peak memory is measured in a fresh subprocess:
the largest resident-set size seen during one forward+backward (sampled every millisecond from
``/proc/self/statm``) above the resident size just before it, after a small warm-up call. The dense reference of
``tests/line_reference.py``
(every point-line distance materialised) runs in the same process where ``N * L`` is at most
``--dense-limit``; the last column is its time divided by ours.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from linereg.se3 import euler_to_rotmat, rt_to_matrix, transform_points
from losses.line_intersection import LineMetricOptions, line_intersection_metric
from losses.lines import sample_lines
from tests.line_reference import dense_line_metric

PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE_MB


class PeakMemory:
    """Context manager sampling the resident set size; ``.peak_mb`` is the rise above entry."""

    def __enter__(self) -> PeakMemory:
        self.base = _rss_mb()
        self.peak = self.base
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_mb())
            time.sleep(0.001)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_mb())

    @property
    def peak_mb(self) -> float:
        return self.peak - self.base


def surface(n: int, seed: int) -> torch.Tensor:
    """``(n, 3)`` float32 samples of a bumpy, asymmetric ellipsoid in the unit ball."""
    g = torch.Generator().manual_seed(seed)
    x = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    bump = 1.0 + 0.2 * torch.sin(3.0 * x[:, 0]) * torch.cos(2.0 * x[:, 1])
    return x * bump[:, None] * torch.tensor([0.7, 0.5, 0.35])


def make_pair(n: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    tgt = surface(n, 1)
    pose = rt_to_matrix(euler_to_rotmat(torch.tensor([0.1, -0.05, 0.08])), torch.tensor([0.03, 0.0, -0.02]))
    return transform_points(pose, surface(n, 0)).to(device), tgt.to(device)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_sparse(src, tgt, options, repeats, device):
    """Median forward and backward milliseconds."""
    fwd, bwd = [], []
    for rep in range(repeats + 1):
        leaf = src.clone().requires_grad_(True)
        gen = torch.Generator().manual_seed(rep)
        _sync(device)
        t0 = time.perf_counter()
        value = line_intersection_metric(leaf[None], tgt[None], options=options, generator=gen).value.sum()
        _sync(device)
        t1 = time.perf_counter()
        value.backward()
        _sync(device)
        t2 = time.perf_counter()
        if rep > 0:  # the first run is a warm-up
            fwd.append(1000 * (t1 - t0))
            bwd.append(1000 * (t2 - t1))
    return statistics.median(fwd), statistics.median(bwd)


def peak_memory_mb(n: int, n_lines: int, variant: str) -> float:
    """Peak MB above baseline of one forward+backward, measured in a fresh process."""
    probe = [sys.executable, __file__, "--memory-probe", str(n), str(n_lines), "--variant", variant]
    return float(subprocess.run(probe, check=True, capture_output=True, text=True).stdout.strip())


def _memory_probe(n: int, n_lines: int, variant: str) -> None:
    small_src, small_tgt = make_pair(256, "cpu")
    options = LineMetricOptions.for_variant(variant, num_lines=n_lines)
    line_intersection_metric(
        small_src[None].requires_grad_(True), small_tgt[None], options=options
    ).value.sum().backward()
    src, tgt = make_pair(n, "cpu")
    leaf = src.clone().requires_grad_(True)
    with PeakMemory() as mem:
        line_intersection_metric(leaf[None], tgt[None], options=options).value.sum().backward()
    print(f"{mem.peak_mb:.1f}")


def time_dense(src, tgt, options, device):
    """Milliseconds of one dense forward+backward on the same kind of lines."""
    origins, dirs = sample_lines(
        src, tgt, options.num_lines, torch.Generator().manual_seed(0), sampling=options.sampling
    )
    leaf = src.clone().requires_grad_(True)
    _sync(device)
    t0 = time.perf_counter()
    dense_line_metric(leaf, tgt, origins, dirs, options).backward()
    _sync(device)
    return 1000 * (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[1024, 5000, 10000, 100000])
    parser.add_argument("--lines", type=int, nargs="+", default=[5000, 15000, 20000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dense-limit", type=float, default=5.2e7, help="largest N * L given to the dense reference")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--variant", default="paper", choices=["paper", "authors"])
    parser.add_argument("--json", action="store_true", help="print one JSON object per row instead of a table")
    parser.add_argument("--memory-probe", type=int, nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_probe:
        _memory_probe(*args.memory_probe, args.variant)
        return

    rows = []
    if not args.json:
        print(
            f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
            f"device {args.device}, variant {args.variant}"
        )
        print("| N | L | forward ms | backward ms | total ms | peak MB | dense ms | dense / ours |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.points:
        src, tgt = make_pair(n, args.device)
        for n_lines in args.lines:
            options = LineMetricOptions.for_variant(args.variant, num_lines=n_lines)
            fwd, bwd = time_sparse(src, tgt, options, args.repeats, args.device)
            peak = peak_memory_mb(n, n_lines, args.variant) if args.device == "cpu" else math.nan
            dense = time_dense(src, tgt, options, args.device) if n * n_lines <= args.dense_limit else math.nan
            row = {
                "n_points": n,
                "n_lines": n_lines,
                "fwd_ms": round(fwd, 2),
                "bwd_ms": round(bwd, 2),
                "peak_mb": round(peak, 1),
                "dense_ms": None if math.isnan(dense) else round(dense, 1),
                "ratio": None if math.isnan(dense) else round(dense / (fwd + bwd), 1),
            }
            rows.append(row)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                dense_txt = "—" if row["dense_ms"] is None else f"{row['dense_ms']:.0f}"
                ratio_txt = "—" if row["ratio"] is None else f"{row['ratio']:.0f}x"
                print(
                    f"| {n} | {n_lines} | {fwd:.1f} | {bwd:.1f} | {fwd + bwd:.1f} | {peak:.0f} "
                    f"| {dense_txt} | {ratio_txt} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
