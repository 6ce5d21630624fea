"""Where does a label-free loss put a pair's pose? Each loss minimised from the ground truth.

    python scripts/studies/loss_minimum.py outputs/schedule_airplane_full/airplane/dcp_cd_s0   # a run's test pairs
    python scripts/studies/loss_minimum.py <run> --lines 20000 --iterations 200 --pairs 60

For every pair of the run's split (:func:`linereg.datasets.benchmark_pairs.run_pairs`) and every
loss below, Adam on the source's pose (:func:`linereg.registration.solvers.adam_stage`) starts at
the ground truth and descends the loss; the table gives how far from the ground truth it ends.
A network trained with a loss is pulled toward that loss's minimum, so the distance is a floor the
loss sets on what training with it can reach on these pairs (a bias, not a bound: a network can
stop short of it). The losses are the training losses of ``scripts/reproduce_schedule.sh``'s
cells: Chamfer (the ``*_cd`` cells) and the paper's line metric (``*_ours``) at the given lines
and Welsch scale factors.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.benchmark_pairs import run_pairs
from linereg.losses import AlignmentLoss, build_loss
from linereg.metrics import rotation_error_deg, translation_error
from linereg.registration.solvers import Stage, adam_stage


def training_losses(lines: int, nu0s: list[float]) -> dict[str, dict]:
    """Configs of the cells' alignment losses, by the name of their table row."""
    losses = {"chamfer (CD)": {"name": "chamfer"}}
    for nu0 in nu0s:
        losses[f"line metric, {lines} lines, nu0 = {nu0:g}"] = {
            "name": "line_intersection",
            "num_lines": lines,
            "nu0": nu0,
            "seed": 0,
        }
    return losses


def distance_to_minimum(
    loss: AlignmentLoss,
    src: torch.Tensor,
    tgt: torch.Tensor,
    gt: torch.Tensor,
    stage: Stage,
    start: torch.Tensor | None = None,
) -> tuple[float, float]:
    """Err_R (deg) and Err_t (l1) from ``gt (4, 4)`` of the pose Adam reaches on ``loss`` from ``start``.

    Args:
        loss: alignment loss between the moved ``src (N, 3)`` and ``tgt (M, 3)``.
        gt: ground-truth transform of ``src`` onto ``tgt``.
        stage: Adam's iterations and peak learning rate.
        start: ``(4, 4)`` initial pose (default: ``gt``).
    """
    found = adam_stage(stage, loss, src, tgt, (gt if start is None else start)[None])
    err_r = rotation_error_deg(found[:, :3, :3], gt[None, :3, :3])
    err_t = translation_error(found[:, :3, 3], gt[None, :3, 3], norm="l1")
    return err_r.item(), err_t.item()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="training run folder or checkpoint")
    parser.add_argument("--split", default="test")
    parser.add_argument("--pairs", type=int, default=None, help="a seeded draw of this many pairs (default: all)")
    parser.add_argument("--lines", type=int, default=5000)
    parser.add_argument("--nu0", type=float, nargs="+", default=[0.5], help="Welsch scale factors of the line rows")
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--lr", type=float, default=0.005, help="Adam's peak rate on the twist (cosine decay)")
    args = parser.parse_args(argv)
    pairs = run_pairs(run=args.run, split=args.split, pairs=args.pairs)
    stage = Stage(loss={}, iterations=args.iterations, lr=args.lr)
    print(
        f"{len(pairs)} {args.split} pairs of {args.run}; Adam from the ground truth, {args.iterations} iterations\n",
        flush=True,
    )
    print("| loss | Err_R at its minimum, deg (mean / median) | beyond 1 deg | Err_t l1 (x10^-1) (mean / median) |")
    print("|---|---|---|---|")
    for label, config in training_losses(args.lines, args.nu0).items():
        loss = build_loss(config)
        rotation, translation = [], []
        for pair in tqdm(pairs, desc=label, leave=False):
            src = torch.as_tensor(pair.src_xyz, dtype=torch.float64)
            tgt = torch.as_tensor(pair.tgt_xyz, dtype=torch.float64)
            gt = torch.as_tensor(pair.gt_transform, dtype=torch.float64)
            err_r, err_t = distance_to_minimum(loss, src, tgt, gt, stage)
            rotation.append(err_r)
            translation.append(10 * err_t)
        print(
            f"| {label} | {statistics.mean(rotation):.3f} / {statistics.median(rotation):.3f} "
            f"| {sum(error > 1.0 for error in rotation)} of {len(rotation)} pairs "
            f"| {statistics.mean(translation):.3f} / {statistics.median(translation):.3f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
