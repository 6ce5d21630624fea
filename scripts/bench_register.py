"""Time the registration of one pair: the register default against the paper's solver.

    python scripts/bench_register.py                  # the README row (5 Human pairs, 1024 points)
    python scripts/bench_register.py --pairs 10 --threads 2

Every method runs on the same Human-protocol pairs (needs the shared data); each pair is
registered once after a warm-up pair. The table gives the median wall-clock time per pair, the
number of Adam iterations, the time per iteration (coarse multi-start iterations count once per
iteration, all starts together), the median Err_R, and the time relative to the paper's solver
(one start, 500 iterations of the paper's line metric with 15000 lines) measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from linereg.metrics import rotation_error_deg
from train.benchmark import build_pairs
from train.methods import build_method

METHODS = {
    "register default (4 starts)": {"name": "adam_loss", "stages": "default"},
    "register default, 1 start": {"name": "adam_loss", "stages": "default", "starts": 1},
    "paper solver": {"name": "adam_loss", "stages": "paper", "starts": 1},
    "icp_point (Open3D)": {"name": "icp_point"},
}
REFERENCE = "paper solver"


def _iterations(method) -> int | None:
    """Adam iterations of a solver (``None`` for the classical methods)."""
    stages = getattr(method, "stages", None)
    return None if stages is None else sum(stage.iterations for stage in stages)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    pairs = build_pairs({"name": "human", "num_points": args.points}, pairs=args.pairs + 1, seed=0)
    warmup, pairs = pairs[0], pairs[1:]
    rows = []
    for label, config in METHODS.items():
        method = build_method(config)
        method(warmup.src_xyz, warmup.tgt_xyz, warmup.src_normals, warmup.tgt_normals)
        seconds, errors = [], []
        for pair in pairs:
            result = method(pair.src_xyz, pair.tgt_xyz, pair.src_normals, pair.tgt_normals)
            seconds.append(result.seconds)
            R_pred = torch.as_tensor(result.transform[:3, :3], dtype=torch.float64)
            R_gt = torch.as_tensor(pair.gt_transform[:3, :3], dtype=torch.float64)
            errors.append(float(rotation_error_deg(R_pred, R_gt)))
        iterations = _iterations(method)
        median = statistics.median(seconds)
        rows.append(
            {
                "method": label,
                "seconds_median": median,
                "seconds_max": max(seconds),
                "iterations": iterations,
                "ms_per_iteration": None if iterations is None else 1000 * median / iterations,
                "err_r_deg_median": float(np.median(errors)),
            }
        )
    reference = next(row["seconds_median"] for row in rows if row["method"] == REFERENCE)
    for row in rows:
        row["time_vs_paper_solver"] = row["seconds_median"] / reference
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"{len(pairs)} Human pairs, {args.points} points, torch threads {torch.get_num_threads()}\n")
    print(
        "| method | time/pair median (s) | max (s) | iterations | ms/iteration | median Err_R (deg) "
        "| time vs paper solver |"
    )
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        per_iteration = "" if row["ms_per_iteration"] is None else f"{row['ms_per_iteration']:.1f}"
        print(
            f"| {row['method']} | {row['seconds_median']:.2f} | {row['seconds_max']:.2f} | {row['iterations'] or ''} | "
            f"{per_iteration} | {row['err_r_deg_median']:.3f} | {row['time_vs_paper_solver']:.3f}x |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
