"""Benchmark the registration models: time per pair, peak memory and parameter counts.

    python scripts/bench_models.py                          # CPU, 1024 points, batch 1 and 4
    python scripts/bench_models.py --device cuda --batch-sizes 1 8 32
    python scripts/bench_models.py --models rpmnet --points 2048 --repeats 5

Every registered model is built with its paper defaults (``--set name.key=value`` overrides
one, e.g. ``--set rpmnet.num_neighbors=32``). Per model and batch size, on random clouds of
``--points`` points (uniform in the unit cube, random unit normals; the target is a moved
copy):

* ``forward``: evaluation mode under ``torch.no_grad()`` (RPM-Net runs its 5 test
  iterations and its chunked feature network);
* ``train step``: training mode, forward + backward of the model's supervised loss (RPM-Net
  runs its 2 training iterations).

Times are the median over ``--repeats`` runs after one warm-up, divided by the batch size.
Peak memory is the rise of ``torch.cuda.max_memory_allocated`` (CUDA) or of the resident set
size (CPU, sampled every millisecond) during one more run after the timed ones. For that run
glibc returns its free heap memory (``malloc_trim``) and serves every allocation above 1 MiB
with its own mapping (``mallopt``), so freed tensors leave the resident set at once and the
run's peak is its own; the timed runs use glibc's usual threshold (32 MiB at most).
"""

from __future__ import annotations

import argparse
import ctypes
import os
import statistics
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import linereg.losses.supervised  # noqa: F401  (registers the supervised losses)
from linereg.losses.base import build_loss
from linereg.models import MODELS
from linereg.random_poses import random_transform_paper
from linereg.se3 import transform_normals, transform_points
from linereg.structures import PairBatch

SUPERVISED_LOSS = {"dcp_v1": "gt_dcp", "dcp_v2": "gt_dcp", "rpmnet": "gt_rpmnet", "fmr": "gt_fmr"}
PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20
# glibc's mallopt parameter number for the mmap threshold (malloc.h), the threshold used while
# measuring memory and glibc's largest automatic threshold, restored for timing.
M_MMAP_THRESHOLD = -3
MEASURING_THRESHOLD = 2**20
TIMING_THRESHOLD = 32 * 2**20


def set_mmap_threshold(size: int) -> None:
    """Make glibc mmap (and unmap on free) every allocation above ``size`` bytes, if glibc.

    Free heap memory is returned to the system first (``malloc_trim``), so that it cannot serve
    the next allocations.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    libc.malloc_trim(0)
    libc.mallopt(M_MMAP_THRESHOLD, size)


def _rss_mb() -> float:
    """Current resident set size in MB."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * PAGE_MB


class PeakMemory:
    """Context manager measuring the peak memory rise (MB) of the code it wraps."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.peak_mb = 0.0

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device) / 2**20
            return self
        self._base = self._peak = _rss_mb()
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()
        return self

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._peak = max(self._peak, _rss_mb())
            time.sleep(0.001)

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak_mb = torch.cuda.max_memory_allocated(self.device) / 2**20 - self._base
            return
        self._stop.set()
        self._sampler.join()
        self.peak_mb = max(self._peak, _rss_mb()) - self._base


def make_batch(batch_size: int, num_points: int, device: torch.device) -> PairBatch:
    """Random pairs: uniform points, random normals, target = moved and shuffled source."""
    generator = torch.Generator().manual_seed(0)
    src = torch.rand(batch_size, num_points, 3, generator=generator) - 0.5
    normals = F.normalize(torch.randn(batch_size, num_points, 3, generator=generator), dim=-1)
    T = random_transform_paper(batch_size, 1)
    order = torch.randperm(num_points, generator=generator)
    batch = PairBatch(
        src,
        transform_points(T, src)[:, order],
        normals,
        transform_normals(T, normals)[:, order],
        gt_transform=T,
    )
    return batch.to(device)


def measure(fn: Callable[[], object], repeats: int, device: torch.device) -> tuple[float, float]:
    """Median wall time (ms) over ``repeats`` calls after a warm-up, and peak memory (MB)."""
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(1000 * (time.perf_counter() - start))
    set_mmap_threshold(MEASURING_THRESHOLD)
    with PeakMemory(device) as memory:
        fn()
    set_mmap_threshold(TIMING_THRESHOLD)
    return statistics.median(times), memory.peak_mb


def parse_overrides(items: list[str]) -> dict[str, dict[str, object]]:
    """``["rpmnet.num_neighbors=32"]`` -> ``{"rpmnet": {"num_neighbors": 32}}``."""
    overrides: dict[str, dict[str, object]] = {}
    for item in items:
        key, _, value = item.partition("=")
        model, _, argument = key.partition(".")
        if not (model and argument and value):
            raise SystemExit(f"--set expects model.argument=value, got {item!r}")
        try:
            parsed: object = int(value)
        except ValueError:
            try:
                parsed = float(value)
            except ValueError:
                parsed = value
        overrides.setdefault(model, {})[argument] = parsed
    return overrides


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:index]")
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--models", nargs="+", default=MODELS.names(), choices=MODELS.names())
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    parser.add_argument("--set", nargs="*", default=[], dest="overrides", metavar="M.ARG=V")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    overrides = parse_overrides(args.overrides)

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(
        f"{where}, {torch.get_num_threads()} threads, torch {torch.__version__}, "
        f"{args.points} points, median of {args.repeats}\n"
    )
    print(
        "| model | batch | parameters | forward ms/pair | train step ms/pair | peak MB forward | peak MB train step |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in args.models:
        torch.manual_seed(0)
        model = MODELS.build({"name": name, **overrides.get(name, {})}).to(device)
        loss = build_loss({"name": SUPERVISED_LOSS[name]})
        parameters = sum(p.numel() for p in model.parameters())
        for batch_size in args.batch_sizes:
            batch = make_batch(batch_size, args.points, device)

            def forward(model=model, batch=batch) -> None:
                model.eval()
                with torch.no_grad():
                    model(batch)

            def train_step(model=model, batch=batch, loss=loss) -> None:
                model.train()
                model.zero_grad(set_to_none=True)
                loss(model(batch), batch).total.backward()

            forward_ms, forward_mb = measure(forward, args.repeats, device)
            train_ms, train_mb = measure(train_step, args.repeats, device)
            print(
                f"| {name} | {batch_size} | {parameters / 1e6:.2f} M "
                f"| {forward_ms / batch_size:.1f} | {train_ms / batch_size:.1f} "
                f"| {forward_mb:.0f} | {train_mb:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
