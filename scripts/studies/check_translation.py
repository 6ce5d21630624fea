"""Where RPM-Net's translation error on partial-view pairs comes from.

    python scripts/studies/check_translation.py <run>                    # an RPM-Net run's test pairs
    python scripts/studies/check_translation.py <run> --split val --refine-iterations 1 3 10

On every pair of the run's split (:func:`linereg.datasets.benchmark_pairs.run_pairs`) it prints
Err_R and Err_t (l1, x10^-1 as docs/results.md) of:

1. **The frame, without the network**: RPM-Net's own transform head
   (:func:`linereg.models.blocks.soft_correspondence_transform`) fed exact correspondences (the
   source moved by the ground truth, shuffled; must give 0), the nearest target point of every
   source point at the ground-truth pose (the sampling floor), and geometric soft assignments
   through RPM-Net's Sinkhorn with slack.
2. **The trained network** (its last iterate), and its rotation (or the ground truth's) with the
   translation that aligns the two clouds' centroids. On a partial view against a whole shape the
   centroids differ by where the view lies on the shape, so centroid alignment has a fixed
   translation error; ``error along centroid offset`` is the share of the network's translation
   error along that offset. Also the assignment's row mass near the true match against a uniform
   assignment's, and RPM-Net's outlier penalty of the network's, a uniform and a correct assignment.
3. **Remedies on the same checkpoint**: nearest-neighbour translation refinement
   (:func:`linereg.models.blocks.refine_translation`, the network's rotation kept), and Open3D's
   point-to-point ICP from the identity on the same pairs. The time column is the median over
   repeats of one batch, as a ratio to the network's forward pass measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.checkpoint import find_checkpoint
from linereg.datasets import collate_pairs
from linereg.datasets.benchmark_pairs import run_pairs
from linereg.losses.supervised import outlier_penalty
from linereg.metrics import registration_errors
from linereg.models import load_model
from linereg.models.blocks import refine_translation, soft_correspondence_transform
from linereg.models.rpmnet import log_sinkhorn
from linereg.registration.methods import METHODS
from linereg.se3 import matrix_to_rt, rt_to_matrix, transform_points
from linereg.structures import PairBatch

SINKHORN_BETAS = (200.0, 1000.0)  # geometric affinity -beta * |x - y|^2, units of the cloud
NEAR_RADIUS = 0.1  # "near the true match", in the units of the clouds (Human: about a point spacing)


def _row(name: str, T: torch.Tensor, gt: torch.Tensor, src: torch.Tensor, extra: str = "") -> str:
    errors = registration_errors(T.double(), gt, src)
    return (
        f"| {name} | {errors['err_r_deg'].mean():.3f} | {10 * errors['err_t_l1'].mean():.3f} | "
        f"{10 * errors['err_t_l1'].median():.3f} | {extra} |"
    )


def _centroid_alignment(rotation: torch.Tensor, src: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """``(B, 4, 4)``: ``rotation (B, 3, 3)`` with the translation mapping the source centroid onto the target's."""
    translation = tgt.mean(1) - (rotation @ src.mean(1)[..., None])[..., 0]
    return rt_to_matrix(rotation, translation)


def _median_seconds(function: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def frame_rows(src: torch.Tensor, tgt: torch.Tensor, gt: torch.Tensor) -> list[str]:
    """Section 1: RPM-Net's transform head with known correspondences."""
    rows = []
    generator = torch.Generator().manual_seed(0)
    order = torch.stack([torch.randperm(src.shape[1], generator=generator) for _ in range(src.shape[0])])
    exact_tgt = torch.gather(transform_points(gt, src), 1, order[..., None].expand(-1, -1, 3))
    exact = torch.zeros(src.shape[0], src.shape[1], src.shape[1], dtype=src.dtype)
    exact.scatter_(2, torch.argsort(order, dim=1)[..., None], 1.0)
    head = soft_correspondence_transform(src, exact_tgt, exact, weighted=True, model_name="check")
    rows.append(_row("exact correspondences (shuffled), RPM-Net's head", head, gt, src))
    squared = torch.cdist(transform_points(gt, src), tgt).square()
    nearest = torch.nn.functional.one_hot(squared.argmin(-1), tgt.shape[1]).to(src.dtype)
    head = soft_correspondence_transform(src, tgt, nearest, weighted=True, model_name="check")
    rows.append(_row("nearest target point at the GT pose", head, gt, src))
    for beta in SINKHORN_BETAS:
        assignment = torch.exp(log_sinkhorn(-beta * squared, 5, slack=True))
        head = soft_correspondence_transform(src, tgt, assignment, weighted=True, model_name="check")
        rows.append(_row(f"geometric soft assignment at GT, beta {beta:g}, Sinkhorn + slack", head, gt, src))
    Rg, _ = matrix_to_rt(gt)
    rows.append(_row("GT rotation + centroid alignment", _centroid_alignment(Rg, src, tgt), gt, src))
    return rows


def network_rows(model: torch.nn.Module, batch: PairBatch, gt: torch.Tensor, refine: list[int], repeats: int):
    """Sections 2 and 3: the network, its translation against centroid alignment, refinements."""
    src, tgt = batch.src_xyz.double(), batch.tgt_xyz.double()
    with torch.no_grad():
        output = model(batch)
        forward_seconds = _median_seconds(lambda: model(batch), repeats)
    T = output.transforms[-1].double()
    assignment = output.extras["perm_matrices"][-1].double()
    mass = assignment.sum(-1)
    rotation, translation = matrix_to_rt(T)
    _, tg = matrix_to_rt(gt)
    # Offset of the target centroid from the source centroid moved by the ground truth: the
    # translation error of centroid alignment with the true rotation.
    centroid_offset = tgt.mean(1) - transform_points(gt, src.mean(1, keepdim=True))[:, 0]
    error = translation - tg
    along = (error * torch.nn.functional.normalize(centroid_offset, dim=-1)).sum(-1)
    near = torch.cdist(transform_points(gt, src), tgt) < NEAR_RADIUS
    near_mass = float(((assignment * near).sum(-1) / mass.clamp_min(1e-12)).mean())
    uniform_near = float(near.double().mean())
    betas = ", ".join(f"{float(beta.mean()):.2f}" for beta in output.extras["beta"])
    # An assignment that puts mass only on target points near a moved source point, at most 1 per
    # target point (as Sinkhorn's columns), has at most this total mass per pair:
    matchable = near.any(dim=1).sum(-1).double()
    correct_penalty = (1 - matchable / tgt.shape[1]) + (1 - matchable / src.shape[1])
    uniform = torch.full_like(assignment, 1.0 / tgt.shape[1])
    rows = [
        _row("network", T, gt, src, f"{forward_seconds:.3f} s/batch (1x)"),
        _row("network rotation + centroid alignment", _centroid_alignment(rotation, src, tgt), gt, src),
    ]
    notes = [
        f"- network's translation error (l2) {float(error.norm(dim=-1).mean()):.4f}, of which along the "
        f"centroid offset {float(along.mean()):.4f}; the centroid offset itself (l2) "
        f"{float(centroid_offset.norm(dim=-1).mean()):.4f}",
        f"- assignment row mass within {NEAR_RADIUS:g} of the true match: {near_mass:.3f} "
        f"(a uniform assignment: {uniform_near:.3f}); beta per iteration: {betas}",
        f"- RPM-Net's outlier penalty (the unsupervised cells' regulariser, before its weight): network "
        f"{float(outlier_penalty(assignment)):.3f}, uniform assignment {float(outlier_penalty(uniform)):.3f}, "
        f"at least {float(correct_penalty.mean()):.3f} for any assignment with mass only within {NEAR_RADIUS:g} "
        f"of the true match and at most 1 per target point ({float(matchable.mean()):.0f} of "
        f"{tgt.shape[1]} target points lie that close to the moved source)",
    ]
    for iterations in refine:
        refined = refine_translation(src, tgt, T, mass, iterations)
        seconds = _median_seconds(lambda it=iterations: refine_translation(src, tgt, T, mass, it), repeats)
        rows.append(
            _row(
                f"network + {iterations} NN translation step(s) (mass-weighted)",
                refined,
                gt,
                src,
                f"+{seconds:.4f} s/batch ({seconds / forward_seconds:.3f}x)",
            )
        )
    icp = METHODS.build({"name": "icp_point"})
    icp_transforms, icp_seconds = [], 0.0
    for s, t in zip(src.numpy(), tgt.numpy(), strict=True):
        result = icp(s, t)
        icp_transforms.append(torch.as_tensor(result.transform))
        icp_seconds += result.seconds
    rows.append(
        _row(
            "Open3D point-to-point ICP (identity start, centred)",
            torch.stack(icp_transforms),
            gt,
            src,
            f"{icp_seconds:.3f} s/batch ({icp_seconds / forward_seconds:.3f}x)",
        )
    )
    return rows, notes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="an RPM-Net training run folder or checkpoint")
    parser.add_argument("--split", default="test")
    parser.add_argument("--refine-iterations", type=int, nargs="+", default=[1, 3, 10])
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, state = load_model(find_checkpoint(args.run))
    if state["config"]["model"]["name"] != "rpmnet":
        raise SystemExit(f"{args.run}: an RPM-Net run is needed, got model {state['config']['model']['name']!r}")
    pairs = run_pairs(run=args.run, split=args.split)
    batch = collate_pairs(pairs)
    src, tgt, gt = batch.src_xyz.double(), batch.tgt_xyz.double(), batch.gt_transform.double()
    print(f"{len(pairs)} {args.split} pairs of {args.run} ({src.shape[1]} vs {tgt.shape[1]} points)\n")
    header = (
        "| estimate | Err_R mean (deg) | Err_t l1 mean (x10^-1) | Err_t l1 median | time |\n|---|---:|---:|---:|---|"
    )
    print("**1. The frame (no network)**\n")
    print(header)
    print("\n".join(frame_rows(src, tgt, gt)))
    rows, notes = network_rows(model, batch, gt, args.refine_iterations, args.repeats)
    print("\n**2-3. The network, and remedies on the same checkpoint**\n")
    print(header)
    print("\n".join(rows))
    print()
    print("\n".join(notes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
