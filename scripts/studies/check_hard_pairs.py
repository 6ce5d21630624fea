"""Why a trained RPM-Net fails on some held-out pairs.

    python scripts/studies/check_hard_pairs.py <run> [<run> ...]               # the runs' test pairs
    python scripts/studies/check_hard_pairs.py <run> --worst 4 --iterations 10

For the pairs of the first run's split (the runs must share it) it prints:

0. **Overlap of the first run's data**: the share of source points within ``--radius`` of a
   target point at the ground-truth pose, summarised over its training pairs (each variant its
   curriculum trains on), validation and test pairs.
1. **Err_R by overlap**: each run's mean / median Err_R over the pairs binned by their overlap.
2. **Iterations**: each run's mean Err_R after every RPM-Net iteration up to ``--iterations``
   (the iterate at its own ``test_iters`` is the answer of ``iterate.rule=last``, bracketed).
3. **The worst pairs** of the first run: ground-truth rotation angle, overlap, each run's Err_R
   per iteration, and, for the first run's answer, whether the shape explains it: the whole
   shape's Chamfer to itself under the *alias* (the ground truth undone after the network's
   pose; near the point spacing only for a symmetric shape), the clouds' Chamfer at the network's
   pose against the ground truth's, and the error of :func:`linereg.register` (the classical
   solver) on the same clouds.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import linereg
from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.datasets import collate_pairs
from linereg.datasets.benchmark_pairs import run_pairs
from linereg.datasets.shape_pairs import ShapePairDataset
from linereg.datasets.splits import build_dataset, build_split, dataset_config
from linereg.metrics import rotation_error_deg
from linereg.models import MODELS, upgrade_run_config
from linereg.structures import PairSample

OVERLAP_BINS = (0.0, 0.5, 0.6, 0.7, 0.8, 1.01)


def overlap(pair: PairSample, radius: float) -> float:
    """Share of source points within ``radius`` of a target point at the ground-truth pose."""
    moved = pair.src_xyz @ pair.gt_transform[:3, :3].T + pair.gt_transform[:3, 3]
    return float((cKDTree(pair.tgt_xyz).query(moved)[0] < radius).mean())


def one_sided_chamfer(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean nearest-neighbour distance ``a -> b`` and ``b -> a``."""
    return float(cKDTree(b).query(a)[0].mean()), float(cKDTree(a).query(b)[0].mean())


def moved(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points (N, 3)`` under a ``(4, 4)`` transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def angle_deg(transform: np.ndarray) -> float:
    """Rotation angle of a ``(4, 4)`` transform."""
    return float(np.degrees(np.arccos(np.clip((np.trace(transform[:3, :3]) - 1) / 2, -1.0, 1.0))))


def errors_by_iteration(run: str, pairs: list[PairSample], iterations: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Err_R ``(P, iterations)`` of a run's evaluated checkpoint after every iteration.

    Returns:
        The errors, the run's ``test_iters`` and its ``(P, 4, 4)`` evaluated poses.
    """
    state = load_checkpoint(find_checkpoint(run))
    config = upgrade_run_config(state["config"])["model"]
    if config["name"] != "rpmnet":
        raise SystemExit(f"{run}: an RPM-Net run is needed, got model {config['name']!r}")
    model = MODELS.build({**config, "test_iters": max(iterations, config["test_iters"])})
    model.load_state_dict(state["model"])
    model.eval()
    batch = collate_pairs(pairs)
    with torch.no_grad():
        output = model(batch)
    gt = batch.gt_transform.double()[:, :3, :3]
    errors = torch.stack([rotation_error_deg(T.double()[:, :3, :3], gt) for T in output.transforms], dim=1)
    final = output.transforms[config["test_iters"] - 1].double().numpy()
    return errors.numpy(), config["test_iters"], final


def overlap_summary(run: str, radius: float) -> list[str]:
    """One line per split (and training variant) of a run's data: mean overlap, share below 0.5, quartiles."""
    config = load_checkpoint(find_checkpoint(run))["config"]
    stages = config.get("curriculum", {}).get("stages", {}).values()
    variants = sorted({stage["variant"] for stage in stages if stage["epochs"] > 0}, key=str)
    lines = []
    for split, variant in [*(("train", v) for v in variants), ("val", None), ("test", None)]:
        dataset = build_split(config["dataset"], split, variant=variant, progress=False)
        if dataset is None:
            continue
        values = np.array([overlap(dataset[i], radius) for i in range(len(dataset))])
        quartiles = ", ".join(f"{q:.2f}" for q in np.percentile(values, [25, 50, 75]))
        lines.append(
            f"- {split} (variant {variant}): {len(values)} pairs, mean {values.mean():.2f}, "
            f"{(values < 0.5).mean():.0%} below 0.5, quartiles {quartiles}"
        )
    return lines


def whole_shape(run: str, pair: PairSample) -> np.ndarray | None:
    """The pair's whole shape surface in the pair's frame (before the target's transform), or None."""
    config = load_checkpoint(find_checkpoint(run))["config"]["dataset"]
    builder = dataset_config(config, "test")
    for key in ("cache_dir", "cache_workers"):
        builder.pop(key, None)
    dataset = build_dataset(builder)
    if not isinstance(dataset, ShapePairDataset):
        return None
    shape_index = pair.meta["index"] // len(dataset.views)
    points, _ = dataset._renderer(shape_index).whole()
    return (points - np.asarray(pair.meta["center"])) * pair.meta["scale"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="RPM-Net training run folders (the first picks the worst pairs)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--worst", type=int, default=2, help="pairs examined in section 3")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--radius", type=float, default=0.05, help="overlap distance (pair units)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    pairs = run_pairs(run=args.runs[0], split=args.split)
    names = [f"{p.meta['shape']}_{p.meta['view']}" for p in pairs]
    overlaps = np.array([overlap(p, args.radius) for p in pairs])
    results = {run: errors_by_iteration(run, pairs, args.iterations) for run in args.runs}
    print(f"**0. Overlap of the data of {args.runs[0]}** (radius {args.radius:g})\n")
    print("\n".join(overlap_summary(args.runs[0], args.radius)))
    print(f"\n**1. Err_R by overlap** ({len(pairs)} {args.split} pairs)\n")
    print("| overlap | pairs | " + " | ".join(f"{run} mean / median" for run in args.runs) + " |")
    print("|---|---:|" + "---:|" * len(args.runs))
    for low, high in itertools.pairwise(OVERLAP_BINS):
        inside = (overlaps >= low) & (overlaps < high)
        cells = [
            f"{errors[inside, iters - 1].mean():.2f} / {np.median(errors[inside, iters - 1]):.2f}"
            for errors, iters, _ in results.values()
        ]
        print(f"| [{low:g}, {min(high, 1):g}) | {int(inside.sum())} | " + " | ".join(cells) + " |")
    print("\n**2. Mean Err_R after each iteration** (the evaluated one in brackets)\n")
    for run, (errors, iters, _) in results.items():
        means = [f"[{m:.2f}]" if i == iters - 1 else f"{m:.2f}" for i, m in enumerate(errors.mean(0))]
        print(f"- {run}: " + " ".join(means))
    errors, iters, poses = results[args.runs[0]]
    print(f"\n**3. The {args.worst} worst pairs of {args.runs[0]}**")
    for index in np.argsort(-errors[:, iters - 1])[: args.worst]:
        pair = pairs[index]
        src, tgt, gt = (np.asarray(a, dtype=np.float64) for a in (pair.src_xyz, pair.tgt_xyz, pair.gt_transform))
        print(f"\n{names[index]}: ground truth {angle_deg(gt):.1f} deg, overlap {overlaps[index]:.2f}")
        for run, (run_errors, _, _) in results.items():
            print(f"- {run}: Err_R by iteration " + " ".join(f"{e:.1f}" for e in run_errors[index]))
        alias = np.linalg.inv(gt) @ poses[index]
        at_network = np.round(one_sided_chamfer(moved(poses[index], src), tgt), 4)
        at_truth = np.round(one_sided_chamfer(moved(gt, src), tgt), 4)
        print(f"- Chamfer (one-sided means) of the clouds at the network's pose {at_network}, at the truth {at_truth}")
        shape = whole_shape(args.runs[0], pair)
        if shape is not None:
            spacing = float(cKDTree(shape).query(shape, k=2)[0][:, 1].mean())
            print(
                f"- alias {angle_deg(alias):.1f} deg: the whole shape's Chamfer to itself under it "
                f"{np.round(one_sided_chamfer(moved(alias, shape), shape), 4)} (point spacing {spacing:.4f})"
            )
        result = linereg.register(src, tgt)
        rotations = torch.from_numpy(np.stack([result.transformation[:3, :3], gt[:3, :3]]))
        error = float(rotation_error_deg(rotations[:1], rotations[1:])[0])
        print(f"- linereg.register: Err_R {error:.1f} deg (fitness {result.fitness:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
