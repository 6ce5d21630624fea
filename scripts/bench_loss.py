"""Benchmark the line-intersection metric: forward and backward time and peak memory.

    python scripts/bench_loss.py                      # the README table (numba backend on the CPU)
    python scripts/bench_loss.py --json               # one JSON object per row
    python scripts/bench_loss.py --points 1024 --lines 20000 --repeats 10
    python scripts/bench_loss.py --backend torch      # the device-native backend (here on the CPU)
    python scripts/bench_loss.py --device cuda        # on a GPU (backend auto = torch)
    python scripts/bench_loss.py --batch 8 --points 1024 --lines 15000   # threads x load table
    python scripts/bench_loss.py --profile --points 1024 --lines 20000   # where the time goes

Each row is one pair (source and target with ``N`` points each, ``L`` lines), timed as the
median over ``--repeats`` runs after a warm-up. Every row also times, in the same process, the
all-pairs compiled reference: a numba loop over all lines (``prange``, all threads) testing
every point of *one* cloud against every line, with no spatial index; the column
``ours / all-pairs`` is our forward+backward over *both* clouds divided by it (wall clock, the
configured threads). The columns ``1-thread CPU ms`` time both again on one thread in CPU time of
the process, alternately, and give their ratio: other jobs on the machine inflate wall times
and make the first ratio swing, while CPU time on one thread stays nearly steady. Peak memory is
measured in a fresh subprocess: the largest resident-set size seen during one forward+backward
(sampled every millisecond from ``/proc/self/statm``) above the resident size just before it,
after a small warm-up call (on CUDA: the rise of ``torch.cuda.max_memory_allocated``). The
dense reference of ``tests/line_reference.py`` (every point-line distance materialised) runs
where ``N * L`` is at most ``--dense-limit``; ``dense / ours`` is its time divided by ours.

``--batch B`` instead times a batch of ``B`` pairs with 1 and 2 threads (torch and numba alike),
on a quiet machine and with another process spinning on one core (started and stopped here).

``--profile`` instead profiles ``--repeats`` forward+backward calls per row with ``cProfile`` on one
thread, timed in CPU time of the process (steady on a machine busy with other jobs, where wall
times are not), and prints the functions that take the most time of their own, then the time of
the metric's pieces (candidate search, line sampler, kNN and radii, matching and value, the rest).

OpenMP threads that spin while they wait make every parallel region wait for a descheduled
thread on a busy machine; the script sets ``OMP_WAIT_POLICY=PASSIVE`` before importing torch
unless the variable is already set (the header prints it).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import math
import os
import pstats
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from linereg.losses.line_intersection import LineMetricOptions, line_intersection_metric
from linereg.losses.lines import sample_lines
from linereg.se3 import euler_to_rotmat, rt_to_matrix, transform_points
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


def time_sparse(src, tgt, options, repeats, device, clock=time.perf_counter):
    """Median forward and backward milliseconds of ``src``, ``tgt`` (``(N, 3)`` or ``(B, N, 3)``),
    wall-clock time by default (``clock=time.process_time``: CPU time of the process)."""
    batched = src if src.ndim == 3 else src[None]
    target = tgt if tgt.ndim == 3 else tgt[None]
    fwd, bwd = [], []
    for rep in range(repeats + 1):
        leaf = batched.clone().requires_grad_(True)
        gen = torch.Generator().manual_seed(rep)
        _sync(device)
        t0 = clock()
        value = line_intersection_metric(leaf, target, options=options, generator=gen).value.sum()
        _sync(device)
        t1 = clock()
        value.backward()
        _sync(device)
        t2 = clock()
        if rep > 0:  # the first run is a warm-up
            fwd.append(1000 * (t1 - t0))
            bwd.append(1000 * (t2 - t1))
    return statistics.median(fwd), statistics.median(bwd)


@numba.njit(parallel=True, cache=True)
def _all_pairs_candidates(origins, dirs, points, radius):
    """Number of points within ``radius`` of each line, testing every point-line pair."""
    counts = np.zeros(origins.shape[0], dtype=np.int64)
    r2 = radius * radius
    for line in numba.prange(origins.shape[0]):
        ox, oy, oz = origins[line, 0], origins[line, 1], origins[line, 2]
        ux, uy, uz = dirs[line, 0], dirs[line, 1], dirs[line, 2]
        found = 0
        for i in range(points.shape[0]):
            dx = points[i, 0] - ox
            dy = points[i, 1] - oy
            dz = points[i, 2] - oz
            t = dx * ux + dy * uy + dz * uz
            if dx * dx + dy * dy + dz * dz - t * t < r2:
                found += 1
        counts[line] = found
    return counts


def time_all_pairs(src, tgt, n_lines, repeats, clock=time.perf_counter):
    """Median milliseconds of the all-pairs compiled candidate search for one cloud (CPU), wall
    clock by default."""
    src_cpu, tgt_cpu = src.cpu(), tgt.cpu()
    origins, dirs = sample_lines(src_cpu, tgt_cpu, n_lines, torch.Generator().manual_seed(0))
    points = src_cpu.double().numpy()
    radius = 0.866 * float(torch.cdist(src_cpu[:512], src_cpu).topk(3, largest=False).values[:, 1:].mean())
    _all_pairs_candidates(origins[:2], dirs[:2], points[:8], radius)  # compile outside the timing
    times = []
    for _ in range(repeats):
        t0 = clock()
        _all_pairs_candidates(origins, dirs, points, radius)
        times.append(1000 * (clock() - t0))
    return statistics.median(times)


def peak_memory_mb(n: int, n_lines: int, variant: str, backend: str) -> float:
    """Peak MB above baseline of one forward+backward, measured in a fresh process."""
    probe = [sys.executable, __file__, "--memory-probe", str(n), str(n_lines), "--variant", variant]
    probe += ["--backend", backend]
    return float(subprocess.run(probe, check=True, capture_output=True, text=True).stdout.strip())


def _memory_probe(n: int, n_lines: int, variant: str, backend: str) -> None:
    small_src, small_tgt = make_pair(256, "cpu")
    options = LineMetricOptions.for_variant(variant, num_lines=n_lines, backend=backend)
    line_intersection_metric(
        small_src[None].requires_grad_(True), small_tgt[None], options=options
    ).value.sum().backward()
    src, tgt = make_pair(n, "cpu")
    leaf = src.clone().requires_grad_(True)
    with PeakMemory() as mem:
        line_intersection_metric(leaf[None], tgt[None], options=options).value.sum().backward()
    print(f"{mem.peak_mb:.1f}")


def cuda_peak_memory_mb(src, tgt, options) -> float:
    """Peak MB of CUDA memory allocated during one forward+backward, above the allocation before it."""
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    leaf = src.clone().requires_grad_(True)
    line_intersection_metric(leaf[None], tgt[None], options=options).value.sum().backward()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2**20


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


def one_thread_cpu_ms(src, tgt, options, repeats) -> tuple[float, float]:
    """Median CPU milliseconds on one thread of our forward+backward and of the all-pairs search
    (one cloud), measured alternately in this process: a figure that stays steady when other
    jobs share the cores, where wall times do not."""
    threads = torch.get_num_threads(), numba.get_num_threads()
    set_threads(1)
    try:
        ours, ref = [], []
        for _ in range(repeats):
            fwd, bwd = time_sparse(src, tgt, options, 1, "cpu", clock=time.process_time)
            ours.append(fwd + bwd)
            ref.append(time_all_pairs(src, tgt, options.num_lines, 1, clock=time.process_time))
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])
    return statistics.median(ours), statistics.median(ref)


def set_threads(threads: int) -> None:
    """Use ``threads`` threads in torch and in the numba kernels."""
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def batch_table(args) -> None:
    """Batch of ``--batch`` pairs with 1 and 2 threads, quiet and with one core taken."""
    n, n_lines = args.points[0], args.lines[0]
    options = LineMetricOptions.for_variant(args.variant, num_lines=n_lines, backend=args.backend)
    pairs = [make_pair(n, args.device) for _ in range(args.batch)]
    src = torch.stack([p[0] for p in pairs])
    tgt = torch.stack([p[1] for p in pairs])
    print(
        f"torch {torch.__version__}, numba {numba.__version__}, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, device {args.device}, backend {args.backend}, "
        f"variant {args.variant}, {n} points, {n_lines} lines"
    )
    print(
        "| batch | threads | other process on one core | fwd+bwd ms | ms per pair | all-pairs ms | ours / all-pairs |"
    )
    print("|---:|---:|---|---:|---:|---:|---:|")
    for loaded in (False, True):
        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if loaded else None
        try:
            for threads in (1, 2):
                set_threads(threads)
                fwd, bwd = time_sparse(src, tgt, options, args.repeats, args.device)
                ref = time_all_pairs(src[0], tgt[0], n_lines, min(3, args.repeats))
                total = fwd + bwd
                print(
                    f"| {args.batch} | {threads} | {'yes' if loaded else 'no'} | {total:.1f} | "
                    f"{total / args.batch:.1f} | {ref:.1f} | {total / args.batch / ref:.2f} |",
                    flush=True,
                )
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()


PROFILE_PIECES = {
    "line_intersections": "candidate search (line_kernels.line_intersections)",
    "sample_line_batch": "line sampler (lines.sample_line_batch)",
    "cloud_neighborhoods": "kNN and radii (line_kernels.cloud_neighborhoods)",
    "welsch_lines": "matching, value and gradient (line_kernels.welsch_lines)",
}


def profile_table(args) -> None:
    """CPU milliseconds per forward+backward call, in total and per function (own time), one thread."""
    set_threads(1)
    print(
        f"torch {torch.__version__}, numba {numba.__version__}, 1 thread, CPU time (cProfile, process_time), "
        f"device {args.device}, backend {args.backend}, variant {args.variant}, {args.repeats} calls per row"
    )
    for n in args.points:
        src, tgt = make_pair(n, args.device)
        for n_lines in args.lines:
            options = LineMetricOptions.for_variant(args.variant, num_lines=n_lines, backend=args.backend)
            time_sparse(src, tgt, options, 1, args.device)  # compile and warm up outside the profile
            profiler = cProfile.Profile(time.process_time)
            profiler.enable()
            time_sparse(src, tgt, options, args.repeats - 1, args.device)
            profiler.disable()
            stats = pstats.Stats(profiler)
            calls = args.repeats
            total = stats.total_tt * 1000 / calls
            print(f"\n{n} points, {n_lines} lines: {total:.1f} ms per call")
            print("| function (own time) | ms per call | share |")
            print("|---|---:|---:|")
            rows = sorted(stats.stats.items(), key=lambda item: item[1][2], reverse=True)
            for (filename, line, name), (_, _, own, _, _) in rows[:12]:
                where = f"{Path(filename).name}:{line}({name})" if line else name
                print(f"| {where} | {own * 1000 / calls:.2f} | {own * 1000 / calls / total:.0%} |")
            pieces = {name: 0.0 for name in PROFILE_PIECES.values()}
            for (_, _, function), (_, _, _, cumulative, _) in stats.stats.items():
                if function in PROFILE_PIECES:
                    pieces[PROFILE_PIECES[function]] += cumulative * 1000 / calls
            pieces["the rest"] = total - sum(pieces.values())
            print("\n| piece (cumulative) | ms per call |\n|---|---:|")
            for piece, ms in pieces.items():
                print(f"| {piece} | {ms:.2f} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[1024, 5000, 10000, 100000])
    parser.add_argument("--lines", type=int, nargs="+", default=[5000, 15000, 20000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dense-limit", type=float, default=5.2e7, help="largest N * L given to the dense reference")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", default="auto", choices=["auto", "numba", "torch"])
    parser.add_argument("--variant", default="paper", choices=["paper", "authors", "linereg"])
    parser.add_argument("--threads", type=int, help="torch and numba threads (default: as configured)")
    parser.add_argument("--batch", type=int, help="time a batch of this many pairs with 1 and 2 threads instead")
    parser.add_argument("--profile", action="store_true", help="profile the calls of each row instead (one thread)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per row instead of a table")
    parser.add_argument("--memory-probe", type=int, nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.memory_probe:
        _memory_probe(*args.memory_probe, args.variant, args.backend)
        return
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: this torch build ({torch.__version__}) sees no CUDA device")
    if args.threads is not None:
        set_threads(args.threads)
    if args.batch is not None:
        batch_table(args)
        return
    if args.profile:
        profile_table(args)
        return

    rows = []
    if not args.json:
        print(
            f"torch {torch.__version__}, {torch.get_num_threads()} torch threads, numba {numba.__version__} "
            f"({numba.get_num_threads()} threads), OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, "
            f"device {args.device}, backend {args.backend}, variant {args.variant}"
        )
        print(
            "| N | L | forward ms | backward ms | total ms | peak MB | all-pairs ms (one cloud) "
            "| ours / all-pairs | 1-thread CPU ms: ours | all-pairs | ratio | dense ms | dense / ours |"
        )
        print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.points:
        src, tgt = make_pair(n, args.device)
        for n_lines in args.lines:
            options = LineMetricOptions.for_variant(args.variant, num_lines=n_lines, backend=args.backend)
            fwd, bwd = time_sparse(src, tgt, options, args.repeats, args.device)
            if args.device == "cpu":
                peak = peak_memory_mb(n, n_lines, args.variant, args.backend)
            else:
                peak = cuda_peak_memory_mb(src, tgt, options)
            ref = time_all_pairs(src, tgt, n_lines, min(3, args.repeats))
            cpu_ours, cpu_ref = (
                one_thread_cpu_ms(src, tgt, options, args.repeats) if args.device == "cpu" else (math.nan, math.nan)
            )
            dense = time_dense(src, tgt, options, args.device) if n * n_lines <= args.dense_limit else math.nan
            row = {
                "n_points": n,
                "n_lines": n_lines,
                "fwd_ms": round(fwd, 2),
                "bwd_ms": round(bwd, 2),
                "peak_mb": round(peak, 1),
                "all_pairs_ms": round(ref, 2),
                "ratio_all_pairs": round((fwd + bwd) / ref, 2),
                "cpu1_ms": None if math.isnan(cpu_ours) else round(cpu_ours, 2),
                "all_pairs_cpu1_ms": None if math.isnan(cpu_ref) else round(cpu_ref, 2),
                "ratio_cpu1": None if math.isnan(cpu_ours) else round(cpu_ours / cpu_ref, 2),
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
                    f"| {n} | {n_lines} | {fwd:.1f} | {bwd:.1f} | {fwd + bwd:.1f} | {peak:.0f} | {ref:.1f} "
                    f"| {row['ratio_all_pairs']:.2f} | {cpu_ours:.1f} | {cpu_ref:.1f} | {cpu_ours / cpu_ref:.2f} "
                    f"| {dense_txt} | {ratio_txt} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
