"""Does a loss prefer the ground-truth pose? Its value at the GT pose against the identity.

    python scripts/studies/loss_at_gt.py outputs/reproduce/real/rpm_ours_s1     # a training run's test pairs
    python scripts/studies/loss_at_gt.py <run> --split val --lines 5000

For every pair of the run's split (:func:`linereg.datasets.benchmark_pairs.run_pairs`) and every loss below, counts
the pairs on which the loss is lower with the source moved by the ground truth than left where it
is. A loss that is not lower at the ground truth cannot teach a network the right pose.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.benchmark_pairs import run_pairs
from linereg.losses import build_loss
from linereg.se3 import transform_points


def label_free_losses(lines: int, fixed_nu: float) -> dict[str, dict]:
    """Configs of the losses that score a pose without labels, by the name of their table row."""
    return {
        "line metric (paper: nu = nu0 * median)": {"name": "line_intersection", "num_lines": lines, "seed": 0},
        f"line metric, fixed nu = {fixed_nu:g}": {
            "name": "line_intersection",
            "num_lines": lines,
            "nu": fixed_nu,
            "seed": 0,
        },
        "chamfer (CD)": {"name": "chamfer"},
        "chamfer-welsch (CD-W, nu0 0.5)": {"name": "chamfer_welsch", "nu0": 0.5},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="training run folder or checkpoint")
    parser.add_argument("--split", default="test")
    parser.add_argument("--lines", type=int, default=5000)
    parser.add_argument("--fixed-nu", type=float, default=0.25, help="Welsch scale of the fixed-scale row")
    args = parser.parse_args(argv)
    losses = label_free_losses(args.lines, args.fixed_nu)
    pairs = run_pairs(run=args.run, split=args.split)
    print(f"{len(pairs)} {args.split} pairs of {args.run}\n")
    print("| loss | lower at GT than at identity |\n|---|---|")
    for label, config in losses.items():
        loss = build_loss(config)
        wins = 0
        for pair in pairs:
            src = torch.as_tensor(pair.src_xyz, dtype=torch.float64)[None]
            tgt = torch.as_tensor(pair.tgt_xyz, dtype=torch.float64)[None]
            gt = torch.as_tensor(pair.gt_transform, dtype=torch.float64)
            at_gt = loss.metric(transform_points(gt, src), tgt)[0][0]
            at_identity = loss.metric(src, tgt)[0][0]
            wins += int(at_gt < at_identity)
        print(f"| {label} | {wins} of {len(pairs)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
