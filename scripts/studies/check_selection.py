"""Does the register default's selection cost rank poses right? Check it on a benchmark's results.

    python scripts/studies/check_selection.py outputs/benchmark/<source>/<run>/results.json
    python scripts/studies/check_selection.py <run>/results.json --candidates [--pairs 8 10] [--line]

For every pair of the run (rebuilt from its settings) and every method whose pose ended more than
``--wrong-deg`` off, compare :func:`linereg.registration.welsch.fixed_scale_cost` (the cost that
picks the best start, computed as the solver does: both clouds centred and scaled into the unit
ball) at the ground truth and at that wrong pose. The selection can only go wrong where a wrong pose costs less.

``--candidates`` asks the same of other criteria, on the solver's own candidates: every polished
candidate of the three rounds (all three run on every pair) and the ground truth polished by the
same IRLS. A criterion ranks a pair right when the best candidate within ``--right-deg`` of the
truth scores lower than every candidate farther off (:func:`selection_criteria` lists them;
``--line`` adds the line-intersection metric at a fixed scale, which imports torch).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.benchmark_pairs import select_pairs
from linereg.knn import NearestNeighbors
from linereg.registration.methods import translation
from linereg.registration.planes import pca_normals
from linereg.registration.poses import apply, rotation_gap_deg
from linereg.registration.robust import RobustOptions, RobustRegistration
from linereg.registration.welsch import fixed_scale_cost, welsch_cost, welsch_irls


def _solver_frame(transform: np.ndarray, src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, float]:
    """``transform`` between the centred clouds, and their common unit-ball radius."""
    c_src, c_tgt = src.mean(axis=0), tgt.mean(axis=0)
    radius = max(np.linalg.norm(src - c_src, axis=1).max(), np.linalg.norm(tgt - c_tgt, axis=1).max())
    centred = translation(-c_tgt) @ transform @ translation(c_src)
    centred[:3, 3] /= radius
    return centred, radius


def trimmed_cost(distances: np.ndarray, power: float) -> np.ndarray:
    """Trimmed-ICP's overlap-free cost ``min_f rmse(f) / f^power`` over the last axis, ``rmse(f)`` of
    the fraction ``f`` in [0.3, 1] of smallest distances (Chetverikov et al., 2005)."""
    squares = np.cumsum(np.sort(np.square(distances), axis=-1), axis=-1)
    count = distances.shape[-1]
    values = []
    for fraction in np.linspace(0.3, 1.0, 15):
        kept = max(round(fraction * count), 1)
        values.append(np.sqrt(squares[..., kept - 1] / kept) / fraction**power)
    return np.min(values, axis=0)


def selection_criteria(poses, src: np.ndarray, tgt: np.ndarray, spacing: float) -> dict[str, np.ndarray]:
    """Candidate selection costs ``(K,)`` (lower is better) of ``K`` poses of ``src (N, 3)`` onto ``tgt (M, 3)``.

    ``one@k``: :func:`fixed_scale_cost` (source-to-target Welsch) at ``k`` target point
    ``spacing``s; ``two@k``: plus the target-to-source term; ``select_nu``: the default's
    selection cost; ``misfit both ways``: 2 - the fitness (within 3 spacings) of each direction;
    ``mutual rmse/f^2``: RMS distance of the mutual overlap (points whose nearest partner is within
    3 spacings and has them within 3 spacings) over its share squared; ``trimmed``: Trimmed-ICP's
    cost of each direction, summed; ``normals@k``: one-sided Welsch weight times the agreement
    of PCA normals.
    """
    rotations, translations = poses
    d_xy, j = NearestNeighbors(tgt).query(apply(poses, src))
    d_yx, i = NearestNeighbors(src).query((tgt[None] - translations[:, None, :]) @ rotations)
    inlier = 3.0 * spacing
    out = {}
    for k in (0.3, 0.5, 1.0, 2.0):
        out[f"one@{k:g}"] = welsch_cost(d_xy, k * spacing)
    for k in (0.3, 1.0):
        out[f"two@{k:g}"] = welsch_cost(d_xy, k * spacing) + welsch_cost(d_yx, k * spacing)
    out["select_nu"] = welsch_cost(d_xy, RobustOptions().select.nu)
    out["misfit both ways"] = 2.0 - (d_xy < inlier).mean(axis=1) - (d_yx < inlier).mean(axis=1)
    rows = np.arange(len(rotations))[:, None]
    mutual_src = (d_xy < inlier) & (d_yx[rows, j] < inlier)
    mutual_tgt = (d_yx < inlier) & (d_xy[rows, i] < inlier)
    share = (mutual_src.mean(axis=1) + mutual_tgt.mean(axis=1)) / 2.0
    squares = np.where(mutual_src, d_xy**2, 0.0).sum(axis=1) + np.where(mutual_tgt, d_yx**2, 0.0).sum(axis=1)
    rmse = np.sqrt(squares / np.maximum(mutual_src.sum(axis=1) + mutual_tgt.sum(axis=1), 1))
    out["mutual rmse/f^2"] = rmse / np.maximum(share, 1e-6) ** 2
    out["trimmed"] = trimmed_cost(d_xy, 2.0) + trimmed_cost(d_yx, 2.0)
    agreement = np.abs(((pca_normals(src)[None] @ rotations.transpose(0, 2, 1)) * pca_normals(tgt)[j]).sum(axis=-1))
    for k in (1.0, 2.0):
        out[f"normals@{k:g}"] = (1.0 - np.exp(-(d_xy**2) / (2 * (k * spacing) ** 2)) * agreement).mean(axis=1)
    return out


def line_criterion(poses, src: np.ndarray, tgt: np.ndarray, spacing: float) -> np.ndarray:
    """The line-intersection metric (``linereg`` variant, 10 000 lines of one seed, fixed ``nu`` = 1
    target point spacing) of each pose ``(K,)``; imports torch."""
    import torch

    from linereg.losses.line_intersection import LineMetricOptions, line_intersection_metric

    options = LineMetricOptions.for_variant("linereg", nu=spacing, num_lines=10000)
    target = torch.as_tensor(tgt)[None]
    values = []
    for moved in apply(poses, src):
        generator = torch.Generator().manual_seed(0)
        result = line_intersection_metric(torch.as_tensor(moved)[None], target, options=options, generator=generator)
        values.append(float(result.value[0]))
    return np.array(values)


def candidates(pair, solver: RobustRegistration):
    """Every polished candidate of rounds 1-3 and the polished ground truth (first), in the solver's
    frame: ``(poses, rounds (K,), truth (4, 4), src, tgt, spacing)``."""
    src, tgt = pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)
    scaled, radius = solver._pair(src - src.mean(axis=0), tgt - tgt.mean(axis=0))
    truth = translation(-tgt.mean(axis=0)) @ pair.gt_transform.astype(np.float64) @ translation(src.mean(axis=0))
    truth[:3, 3] /= radius
    start = (truth[None, :3, :3], truth[None, :3, 3])
    polished = welsch_irls(start, scaled.src, scaled.tgt_index, scaled.nus, solver.options.polish.settle)
    rotations, translations, rounds = [polished[0]], [polished[1]], [0]
    for number in (1, 2, 3):
        (r, t), _, _ = solver._round(number, scaled)
        rotations.append(r)
        translations.append(t)
        rounds += [number] * len(r)
    poses = (np.concatenate(rotations), np.concatenate(translations))
    return poses, np.array(rounds), truth, scaled.src, scaled.tgt, scaled.spacing


def check_candidates(pairs, indices: list[int], right_deg: float, line: bool) -> None:
    """Print, per criterion, on how many pairs the truth's basin ranks first, and the worst margin."""
    solver = RobustRegistration()
    margins: dict[str, list[tuple[int, float]]] = {}
    for index in indices:
        poses, _, truth, src, tgt, spacing = candidates(pairs[index], solver)
        right = rotation_gap_deg(poses[0], truth[:3, :3]) < right_deg
        criteria = selection_criteria(poses, src, tgt, spacing)
        if line:
            criteria["line@1"] = line_criterion(poses, src, tgt, spacing)
        for name, costs in criteria.items():
            best_right = costs[right].min()
            margin = (costs[~right].min() - best_right) / max(abs(best_right), 1e-12) if (~right).any() else np.inf
            margins.setdefault(name, []).append((index, float(margin)))
    print(f"{len(indices)} pairs; right: within {right_deg:g} deg of the truth (the polished truth is a candidate)")
    print("criterion | truth's basin first | worst (cost(best wrong) - cost(best right)) / cost(best right) [pair]")
    for name, rows in margins.items():
        worst = min(rows, key=lambda row: row[1])
        lost = [index for index, margin in rows if margin <= 0]
        print(f"{name} | {len(rows) - len(lost)}/{len(rows)} | {worst[1]:+.3f} [{worst[0]}] lost: {lost}")


def check_records(content: dict, pairs, wrong_deg: float, results: Path) -> None:
    """The fixed-scale cost at the truth and at every pose more than ``wrong_deg`` off (all methods)."""
    wrong, ranked_right = 0, 0
    margins = []
    for record in content["records"]:
        if record["err_r_deg"] <= wrong_deg:
            continue
        pair = pairs[record["pair"]]
        src, tgt = pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)
        truth, radius = _solver_frame(pair.gt_transform.astype(np.float64), src, tgt)
        found, _ = _solver_frame(np.asarray(record["transform"]), src, tgt)
        poses = np.stack([truth, found])
        costs = fixed_scale_cost(
            (poses[:, :3, :3], poses[:, :3, 3]),
            (src - src.mean(axis=0)) / radius,
            NearestNeighbors((tgt - tgt.mean(axis=0)) / radius),
            RobustOptions().select.nu,
        )
        wrong += 1
        ranked_right += int(costs[0] < costs[1])
        margins.append(float(costs[1] - costs[0]))
    if not wrong:
        print(f"no pose more than {wrong_deg} deg off in {results}")
        return
    print(
        f"{results}: {wrong} poses more than {wrong_deg:g} deg off (all methods); the selection cost is "
        f"lower at the ground truth for {ranked_right} of them ({ranked_right / wrong:.1%}); "
        f"cost(wrong) - cost(truth): median {np.median(margins):.3f}, min {min(margins):.3f}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.json of python -m train.benchmark")
    parser.add_argument("--wrong-deg", type=float, default=5.0)
    parser.add_argument("--candidates", action="store_true", help="rank the solver's candidates by each criterion")
    parser.add_argument("--pairs", type=int, nargs="+", help="pair indices for --candidates (default: all)")
    parser.add_argument("--right-deg", type=float, default=5.0, help="a candidate this close to the truth is right")
    parser.add_argument("--line", action="store_true", help="add the line-intersection metric (imports torch)")
    args = parser.parse_args(argv)
    content = json.loads(args.results.read_text())
    settings = content["settings"]
    pairs = select_pairs(settings["benchmark"], pairs=settings.get("pairs"), seed=int(settings.get("seed", 0)))
    if args.candidates:
        indices = args.pairs if args.pairs is not None else list(range(len(pairs)))
        bad = [index for index in indices if not 0 <= index < len(pairs)]
        if bad:
            parser.error(f"--pairs: {bad} outside the run's {len(pairs)} pairs")
        check_candidates(pairs, indices, args.right_deg, args.line)
    else:
        check_records(content, pairs, args.wrong_deg, args.results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
