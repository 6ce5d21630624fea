"""How an iterative network's error moves over its iterations, and whether a label-free score picks a better one.

    python scripts/studies/check_iterations.py <run>                  # an RPM-Net or FMR run's test pairs
    python scripts/studies/check_iterations.py <run> --iterations 10 --draws 0 1 2 3

RPM-Net refines its estimate ``test_iters`` times (5, the original's setting), FMR up to
``test_iters`` times (10; a solver that stops earlier keeps its last estimate for the remaining
rows). The models return every iterate (``RegistrationOutput.transforms``); this script reads them
all. On the pairs of the run's split, for each of ``--draws`` (``dataset.seed``: other point
samples of the same pairs; default: the run's own draw), it prints the mean Err_R after each
iteration, then the mean Err_R when every pair keeps the iterate with the lowest value of a
label-free score: the losses of ``scripts/studies/loss_at_gt.py`` (the paper's line metric, the
line metric with a fixed Welsch scale, Chamfer and Welsch-Chamfer); the trimmed Chamfer distances
of ``--keep-fractions``, the choice of ``iterate.rule=best_fit iterate.keep_fraction=<f>``
(:func:`linereg.registration.iterates.select_iterate`); for RPM-Net, two fits that read each
iterate's soft assignment (the Chamfer distance with every point weighted by the assignment mass
it receives, and the Chamfer distance trimmed to the share of mass the assignment matches); and,
as a bound that needs the labels, the iterate with the lowest Err_R.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.datasets import collate_pairs
from linereg.datasets.benchmark_pairs import run_pairs
from linereg.losses import build_loss
from linereg.metrics import registration_errors
from linereg.models import MODELS, upgrade_run_config
from linereg.pointcloud import trimmed_chamfer_distance, weighted_chamfer_distance
from linereg.registration.iterates import select_iterate
from linereg.se3 import transform_points
from scripts.studies.loss_at_gt import label_free_losses


def iterate_choices(
    model: torch.nn.Module, run: str, split: str, draw: int | None, scores: dict, keep_fractions: list[float]
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """On one draw of the split's pairs: Err_R ``(I, B)`` after each iteration, and by score name
    the ``(B,)`` iterate each label-free score keeps (the lowest Err_R's last)."""
    batch = collate_pairs(run_pairs(run=run, split=split, dataset_seed=draw))
    with torch.no_grad():
        output = model(batch)
    transforms = [T.double() for T in output.transforms]
    src, tgt, gt = batch.src_xyz.double(), batch.tgt_xyz.double(), batch.gt_transform.double()
    moved = [transform_points(T, src) for T in transforms]
    errors = torch.stack([registration_errors(T, gt, src)["err_r_deg"] for T in transforms])
    choices = {
        name: torch.stack([loss.metric(x, tgt)[0].reshape(-1) for x in moved]).argmin(0)
        for name, loss in scores.items()
    }
    for fraction in keep_fractions:
        choices[f"trimmed Chamfer (keep {fraction:g})"] = select_iterate(transforms, src, tgt, "best_fit", fraction)[1]
    if "perm_matrices" in output.extras:  # RPM-Net: (B, J, K) assignments, slack removed
        masses = [(perm.sum(-1).double(), perm.sum(-2).double()) for perm in output.extras["perm_matrices"]]
        weighted = [weighted_chamfer_distance(x, tgt, *mass) for x, mass in zip(moved, masses, strict=True)]
        choices["assignment-weighted Chamfer"] = torch.stack(weighted).argmin(0)
        matched = [rows.mean(-1).clamp(1e-6, 1) for rows, _ in masses]  # (B,) share of the source matched
        trimmed = [trimmed_chamfer_distance(x, tgt, share) for x, share in zip(moved, matched, strict=True)]
        choices["Chamfer trimmed to the assignment's mass"] = torch.stack(trimmed).argmin(0)
    choices["Err_R"] = errors.argmin(0)
    return errors, choices


def _repeat_last(rows: torch.Tensor, count: int) -> torch.Tensor:
    """``(count, B)``: ``rows (I, B)`` followed by copies of its last row (a solver that stopped early)."""
    return torch.cat([rows, rows[-1:].expand(count - rows.shape[0], -1)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="an RPM-Net or FMR training run folder or checkpoint")
    parser.add_argument("--split", default="test")
    parser.add_argument("--iterations", type=int, default=None, help="test iterations (default: the run's)")
    parser.add_argument("--draws", type=int, nargs="+", default=[None], help="dataset.seed values (default: the run's)")
    parser.add_argument("--lines", type=int, default=5000)
    parser.add_argument("--fixed-nu", type=float, default=0.25, help="Welsch scale of the fixed-scale row")
    parser.add_argument(
        "--keep-fractions", type=float, nargs="*", default=[0.9, 0.7], help="trimmed Chamfer rows (1 is Chamfer)"
    )
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    state = load_checkpoint(find_checkpoint(args.run))
    model_config = upgrade_run_config(state["config"])["model"]
    if model_config["name"] not in ("rpmnet", "fmr"):
        raise SystemExit(f"{args.run}: an RPM-Net or FMR run is needed, got model {model_config['name']!r}")
    if args.iterations is not None:
        model_config["test_iters"] = args.iterations
    model = MODELS.build(model_config)
    model.load_state_dict(state["model"])
    model.eval()
    scores = {name: build_loss(loss) for name, loss in label_free_losses(args.lines, args.fixed_nu).items()}
    draws = [iterate_choices(model, args.run, args.split, draw, scores, args.keep_fractions) for draw in args.draws]
    iterations = max(errors.shape[0] for errors, _ in draws)
    errors = torch.cat([_repeat_last(rows, iterations) for rows, _ in draws], dim=1)  # (I, pairs over all draws)
    print(f"{errors.shape[1]} {args.split} pairs of {args.run} over draws {args.draws}\n")
    print("| estimate | Err_R mean (deg) | mean iteration kept |\n|---|---:|---:|")
    for k in range(errors.shape[0]):
        print(f"| iteration {k + 1}, every pair | {errors[k].mean():.3f} | {k + 1} |")
    for name in draws[0][1]:
        kept = torch.cat([choices[name] for _, choices in draws])
        label = "lowest Err_R per pair (uses the labels: a bound)" if name == "Err_R" else f"lowest {name} per pair"
        chosen = errors.gather(0, kept[None])[0]
        print(f"| {label} | {chosen.mean():.3f} | {kept.double().mean() + 1:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
