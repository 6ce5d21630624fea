"""How much does one step of each alignment loss know about the right pose?

    python scripts/studies/loss_signal.py                                   # Airplane test pairs, 256 points
    python scripts/studies/loss_signal.py --protocol human --angles 5 15 --pairs 40
    python scripts/studies/loss_signal.py --losses paper cloud_points cd --json

For held-out pairs of a training protocol (``configs/protocol/<protocol>.yaml``), the source is
put at a pose ``P`` that is ``angle`` degrees (about a random axis) and ``angle / 100`` pair units
(along a random direction) away from the ground truth, the pose a network typically predicts
while it trains. One evaluation of each loss at ``P`` (fresh lines for the line metric, as in a
training step) gives the gradient ``g`` with respect to a left twist ``xi = (omega, v)`` applied
to the posed source. The true correction is ``xi* = log(T_gt P^-1)``. Printed per loss and angle,
as the mean over pairs:

* ``cos_R``: cosine between the descent direction ``-g_omega`` and ``omega*``;
* ``cos_t``: cosine between ``-g_v`` and ``v*``;
* ``agree``: fraction of pairs with ``cos_R > 0`` (the step turns the right way);
* ``lines``: lines that meet both clouds (line metric only).

A loss whose single-step gradient points towards the ground truth on most pairs is a loss a
network can learn from; this is the cheap check that precedes a training grid.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.losses import build_loss
from linereg.se3 import compose, inverse, se3_exp, se3_log, transform_points

ROOT = Path(__file__).resolve().parents[2]

# The losses compared (alignment terms only; the same settings the training configs use).
LOSSES: dict[str, dict[str, Any]] = {
    "paper": {"name": "line_intersection", "variant": "paper"},
    "authors": {"name": "line_intersection", "variant": "authors"},
    "cloud_points": {"name": "line_intersection", "sampling": "cloud_points"},
    "cloud_points_fixed_nu": {"name": "line_intersection", "sampling": "cloud_points", "nu": 0.05},
    "cloud_points_candidates": {"name": "line_intersection", "sampling": "cloud_points", "intersection": "candidates"},
    "cloud_points_nu0_1": {"name": "line_intersection", "sampling": "cloud_points", "nu0": 1.0},
    "cloud_points_nu0_2": {"name": "line_intersection", "sampling": "cloud_points", "nu0": 2.0},
    "cloud_points_nu0_2_unweighted": {
        "name": "line_intersection",
        "sampling": "cloud_points",
        "nu0": 2.0,
        "line_weight": False,
    },
    "authors_cloud_points": {"name": "line_intersection", "variant": "authors", "sampling": "cloud_points"},
    "paper_nu0_2": {"name": "line_intersection", "nu0": 2.0},
    "cd": {"name": "chamfer"},
    "cdw_0.5": {"name": "chamfer_welsch", "nu0": 0.5},
    "cdw_2": {"name": "chamfer_welsch", "nu0": 2.0},
}


def protocol_pairs(protocol: str, split: str, num_points: int, pairs: int, seed: int) -> list:
    """``pairs`` pairs of ``split`` of ``configs/protocol/<protocol>.yaml`` at ``num_points``."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    from linereg.datasets.benchmark_pairs import select_indices
    from linereg.datasets.splits import build_split

    overrides = [
        "experiment=rpm_gt",
        f"protocol={protocol}",
        f"trainer.num_points={num_points}",
        f"paths.root_dir={ROOT}",
    ]
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = hydra_compose("train", overrides=overrides, return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
    dataset = OmegaConf.to_container(cfg.dataset, resolve=True)
    built = build_split(dataset, split, progress=False)
    return [built[i] for i in select_indices(len(built), pairs, seed)]


def perturbed_pose(gt: torch.Tensor, angle_deg: float, generator: torch.Generator) -> torch.Tensor:
    """A pose ``angle_deg`` degrees and ``angle_deg / 100`` units from ``gt (4, 4)`` (float64)."""
    axis = torch.randn(3, generator=generator, dtype=torch.float64)
    shift = torch.randn(3, generator=generator, dtype=torch.float64)
    xi = torch.cat([axis / axis.norm() * math.radians(angle_deg), shift / shift.norm() * angle_deg / 100.0])
    return compose(se3_exp(xi), gt)


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    denominator = float(a.norm() * b.norm())
    return float(a @ b) / denominator if denominator > 0 else 0.0


def step_signal(loss, src: torch.Tensor, tgt: torch.Tensor, pose: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    """Cosines between one loss evaluation's descent direction and the true correction."""
    posed = transform_points(pose, src)
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    value, stats = loss.metric(transform_points(se3_exp(xi), posed)[None], tgt[None])
    (grad,) = torch.autograd.grad(value.sum(), xi, allow_unused=True)
    grad = torch.zeros(6, dtype=torch.float64) if grad is None else grad
    target = se3_log(compose(gt, inverse(pose)))
    return {
        "cos_R": _cosine(-grad[:3], target[:3]),
        "cos_t": _cosine(-grad[3:], target[3:]),
        "lines": float(stats.get("lines_hit_both", math.nan)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--protocol", default="airplane", choices=("airplane", "human", "real", "procedural"))
    parser.add_argument("--split", default="test")
    parser.add_argument("--pairs", type=int, default=40)
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--lines", type=int, default=5000, help="lines per evaluation of the line metric")
    parser.add_argument("--angles", type=float, nargs="+", default=[2.0, 5.0, 15.0])
    parser.add_argument("--losses", nargs="+", default=list(LOSSES), choices=list(LOSSES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="one JSON object per row")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    pairs = protocol_pairs(args.protocol, args.split, args.points, args.pairs, args.seed)
    print(f"{len(pairs)} {args.split} pairs of the {args.protocol} protocol, {args.points} points\n")
    if not args.json:
        print("| loss | angle (deg) | cos_R | cos_t | agree | lines meeting both |\n|---|---:|---:|---:|---:|---:|")
    for label in args.losses:
        config = dict(LOSSES[label])
        if config["name"] == "line_intersection":
            config.update(num_lines=args.lines, seed=args.seed)
        loss = build_loss(config)
        for angle in args.angles:
            generator = torch.Generator().manual_seed(args.seed)
            rows = []
            for pair in pairs:
                src = torch.as_tensor(pair.src_xyz, dtype=torch.float64)
                tgt = torch.as_tensor(pair.tgt_xyz, dtype=torch.float64)
                gt = torch.as_tensor(pair.gt_transform, dtype=torch.float64)
                rows.append(step_signal(loss, src, tgt, perturbed_pose(gt, angle, generator), gt))
            summary = {
                "loss": label,
                "angle_deg": angle,
                "cos_R": float(np.mean([r["cos_R"] for r in rows])),
                "cos_t": float(np.mean([r["cos_t"] for r in rows])),
                "agree": float(np.mean([r["cos_R"] > 0 for r in rows])),
                "lines": float(np.mean([r["lines"] for r in rows])),
            }
            if args.json:
                print(json.dumps(summary))
            else:
                lines = "" if math.isnan(summary["lines"]) else f"{summary['lines']:.0f}"
                print(
                    f"| {label} | {angle:g} | {summary['cos_R']:.3f} | {summary['cos_t']:.3f} | "
                    f"{summary['agree']:.2f} | {lines} |",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
