"""Where does the finished network's time go, and what bounds its throughput against the solver's?

    python scripts/studies/finish_costs.py [--pairs 30] [--json]
    python scripts/studies/finish_costs.py --acceptance     # the accuracy side: stricter acceptance
    python scripts/studies/finish_costs.py --iterations     # RPM-Net's iterations before the polish

For each network on its own protocol's test pairs and on another protocol's (the sets of
``bench_register.py --throughput``), seed 0, in one process on the machine as it is: the seconds per
pair of ``register`` with the solver (what ``register_many`` does for the solver way: the noise and
clutter tests, the solver, the check), and of each part of the finished network (``refine=true``):

* the network's forward (:meth:`~linereg.registration.learned.LearnedRegistration.predict_many`, all
  pairs in one batch: subsampling, normals, the model), its share per pair;
* the polish of its pose (:meth:`~linereg.registration.learned.Finish.polish`);
* the finish's check of the polished pose (the clutter test and
  :func:`~linereg.registration.evaluation.assess_registration` on one KD-tree of the target);
* the whole solver with its check, on the pairs whose polished pose the check does not trust (the
  fallback), as a mean over all pairs;
* ``register``'s own work around any method (the noise and clutter tests and the final check): the
  solver way's time less the solver's.

The model adds the parts; the throughput ratio is the solver way's time over it. "Bound" is the ratio
if the forward, the polish and every check cost nothing: only the fallback's solver runs. The 3x of
the learned-path targets needs the parts' sum under a third of the solver way's time. "Truth trusted"
is the share of pairs whose ground-truth pose, polished as the finish polishes a network's, the check
trusts, and "perfect network" the ratio of a network that always answered the truth: it still falls
back on every other pair.

With ``--acceptance``, the other side of the trade: the finished network's mean Err_R and how often
the solver runs when the finish keeps a polished pose only if the check trusts it *and* it passes a
stricter rule (:data:`RULES`), on the airplane and room networks' validation pairs (where a rule
would be chosen) and test pairs, beside the solver's own mean Err_R on the same pairs.

With ``--iterations``, on the same pairs: per count of RPM-Net's iterations (:data:`ITERATIONS`), the
forward's seconds per pair (the median of 3 forwards of all the pairs, after one more), the bare
network's mean Err_R, how many polished poses the check trusts and their mean and largest Err_R
(:data:`~linereg.registration.learned.FINISH_ITERATIONS` is chosen on the validation pairs).
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from scripts.studies.finish_fallback import SETS  # the same networks and pairs

TARGET = 3.0
"""The throughput ratio the learned-path targets ask of the finished network in its domain."""
RULES = {
    "the check (the finish's)": lambda judged: True,
    "and inlier RMSE <= 1.0 sampling distances": lambda judged: judged.inlier_rmse <= judged.sampling_distance,
    "and inlier share >= 0.9": lambda judged: judged.fitness >= 0.9,
}
"""Acceptance rules of a polished pose the check trusts, for ``--acceptance``."""
ACCEPTANCE_SETS = (("rpm_ours_airplane", "val", 40), ("rpm_ours_airplane", "test", 30))
ACCEPTANCE_SETS += (("rpm_ours_real", "val", 30), ("rpm_ours_real", "test", 30))
ITERATIONS = (5, 3, 2, 1)
"""RPM-Net's iterations tried by ``--iterations`` (the shipped networks' own: 5)."""


def _timed(function, *args):
    """``(seconds, function(*args))``."""
    start = time.perf_counter()
    value = function(*args)
    return time.perf_counter() - start, value


def _judged_once(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray):
    """The finish's check of one pose, its target's KD-tree and clutter test included."""
    from linereg.registration.learned import pose_check

    return pose_check(src, tgt)(transform)


def _labelled_pairs(owner: str, split: str, count: int) -> tuple[list, list[np.ndarray]]:
    """``count`` pairs of ``owner``'s protocol (``split``, seed 0) as float64 ``(src, tgt)`` clouds, and
    their ``(4, 4)`` ground truths made rigid (stored in float32, the Real protocol's rotations scaled
    by about 1e-4, which the arccos of :func:`_err_r` would read as a degree or more)."""
    from linereg import pretrained
    from linereg.checks import nearest_rotation
    from linereg.datasets.benchmark_pairs import run_pairs

    pairs = run_pairs(run=str(pretrained.path(owner)), split=split, pairs=count, seed=0)
    clouds = [(p.src_xyz.astype(np.float64), p.tgt_xyz.astype(np.float64)) for p in pairs]
    truths = []
    for pair in pairs:
        truth = pair.gt_transform.astype(np.float64)
        truth[:3, :3] = nearest_rotation(truth[:3, :3])
        truths.append(truth)
    return clouds, truths


def _err_r(transform: np.ndarray, truth: np.ndarray) -> float:
    """Err_R (degrees) of ``transform (4, 4)`` against ``truth (4, 4)``."""
    from linereg.registration.poses import rotation_gap_deg

    return float(rotation_gap_deg(transform[None, :3, :3], truth[:3, :3])[0])


def costs(network: str, owner: str, count: int) -> dict[str, float]:
    """Seconds per pair of each part (module docstring) on ``count`` test pairs of ``owner``'s
    protocol, the fallback share, the modelled ratio, its bound, the largest fallback share that
    would leave 3x with the other parts as they are, and the share of pairs whose ground-truth pose,
    polished as the finish polishes, the check trusts, with the ratio of a network that always answered
    the truth (it falls back elsewhere)."""
    from linereg import register
    from linereg.registration.learned import LearnedRegistration

    clouds, truths = _labelled_pairs(owner, "test", count)
    learned = LearnedRegistration(network, refine=True)  # the finish's forward
    finish = learned.finish
    learned.predict_many(clouds[:1])  # warm-up: the model loaded, the kernels compiled
    register(*clouds[0])
    forward, poses = _timed(learned.predict_many, clouds)
    parts = {name: [] for name in ("solver_way", "solver", "polish", "check", "fallback")}
    truth_trusted = []
    for (src, tgt), start, truth in zip(clouds, poses, truths, strict=True):
        truth_trusted.append(_judged_once(src, tgt, finish.polish(src, tgt, truth).transform).confident)
        parts["solver_way"].append(_timed(register, src, tgt)[0])
        parts["solver"].append(_timed(finish.solver, src, tgt)[0])
        seconds, polished = _timed(finish.polish, src, tgt, start)
        parts["polish"].append(seconds)
        seconds, judged = _timed(_judged_once, src, tgt, polished.transform)
        parts["check"].append(seconds)
        parts["fallback"].append(0.0 if judged.confident else parts["solver"][-1] + seconds)
    row = {name: statistics.fmean(values) for name, values in parts.items()}
    row["forward"] = forward / len(clouds)
    row["wrap"] = row["solver_way"] - row["solver"]
    row["fallback_share"] = float(np.mean([value > 0 for value in parts["fallback"]]))
    finished = row["forward"] + row["polish"] + row["check"] + row["fallback"] + row["wrap"]
    row["finished"] = finished
    row["ratio"] = row["solver_way"] / finished
    row["bound"] = row["solver_way"] / row["fallback"] if row["fallback"] > 0 else float("inf")
    fixed = row["forward"] + row["polish"] + row["check"] + row["wrap"]
    per_fallback = row["solver"] + row["check"]
    row["share_for_target"] = max(row["solver_way"] / TARGET - fixed, 0.0) / per_fallback
    row["truth_trusted"] = float(np.mean(truth_trusted))
    row["perfect_ratio"] = row["solver_way"] / (fixed + (1.0 - row["truth_trusted"]) * per_fallback)
    return row


def acceptance(network: str, split: str, count: int) -> dict[str, dict[str, float]]:
    """Per rule of :data:`RULES` (and the solver alone): the mean Err_R of the finished network on
    ``count`` pairs of ``network``'s protocol (``split``, seed 0) and the share of pairs the solver ran
    on. The finish's fallback as it is: the solver's answer replaces the polished pose when the check
    trusts it or it fits better (:func:`~linereg.registration.learned.fits_better`)."""
    from linereg.registration.learned import Finish, LearnedRegistration, fits_better, pose_check

    clouds, truths = _labelled_pairs(network, split, count)
    finish, found = Finish(), {name: [] for name in (*RULES, "the solver alone")}
    starts = LearnedRegistration(network, refine=True).predict_many(clouds)  # the finish's forward
    for (src, tgt), start, truth in zip(clouds, starts, truths, strict=True):
        error = functools.partial(_err_r, truth=truth)
        polished, check = finish.polish(src, tgt, start).transform, pose_check(src, tgt)
        judged = check(polished)
        solved = finish.solver(src, tgt).transform
        solver_wins = check(solved).confident or fits_better(src, tgt, solved, polished)
        fallback = solved if solver_wins else polished
        for name, rule in RULES.items():
            kept = judged.confident and rule(judged)
            found[name].append((error(polished if kept else fallback), not kept))
        found["the solver alone"].append((error(solved), True))
    return {
        name: {
            "pairs": len(rows),
            "err_r_deg_mean": statistics.fmean(e for e, _ in rows),
            "solver_ran": statistics.fmean(r for _, r in rows),
        }
        for name, rows in found.items()
    }


def iterations(network: str, split: str, count: int) -> dict[int, dict[str, float]]:
    """Per count of :data:`ITERATIONS`, on ``count`` pairs of ``network``'s protocol (``split``, seed 0):
    the forward's seconds per pair, the bare network's mean Err_R, the polished poses the check trusts
    and their mean and largest Err_R."""
    from linereg.registration.learned import Finish, LearnedRegistration, pose_check

    clouds, truths = _labelled_pairs(network, split, count)

    def errors(poses):
        return np.array([_err_r(pose, truth) for pose, truth in zip(poses, truths, strict=True)])

    finish, rows = Finish(), {}
    for count_of_iterations in ITERATIONS:
        learned = LearnedRegistration(network, iterations=count_of_iterations)
        learned.predict_many(clouds)  # warm-up: the batch's shapes
        timed = [_timed(learned.predict_many, clouds) for _ in range(3)]
        seconds, starts = statistics.median(seconds for seconds, _ in timed), timed[0][1]
        polished = [finish.polish(src, tgt, start).transform for (src, tgt), start in zip(clouds, starts, strict=True)]
        trusted = [pose_check(src, tgt)(pose).confident for (src, tgt), pose in zip(clouds, polished, strict=True)]
        kept = errors(polished)[np.array(trusted)]
        rows[count_of_iterations] = {
            "pairs": len(clouds),
            "forward_s": seconds / len(clouds),
            "network_err_r_deg": float(errors(starts).mean()),
            "trusted": int(sum(trusted)),
            "trusted_err_r_deg_mean": float(kept.mean()) if len(kept) else float("nan"),
            "trusted_err_r_deg_max": float(kept.max()) if len(kept) else float("nan"),
        }
    return rows


def print_iterations(rows: dict[str, dict[int, dict[str, float]]]) -> None:
    """The ``--iterations`` rows as a markdown table."""
    print("| network, pairs | iterations | forward (s / pair) | network Err_R | trusted polished | their Err_R (max) |")
    print("|---|---:|---:|---:|---:|---|")
    for pairs, counts in rows.items():
        for count, r in counts.items():
            print(
                f"| {pairs} | {count} | {r['forward_s']:.3f} | {r['network_err_r_deg']:.2f} "
                f"| {r['trusted']} / {r['pairs']} "
                f"| {r['trusted_err_r_deg_mean']:.3f} ({r['trusted_err_r_deg_max']:.2f}) |"
            )


def print_acceptance(rows: dict[str, dict[str, dict[str, float]]]) -> None:
    """The ``--acceptance`` rows as a markdown table."""
    print("| network, pairs | acceptance of a polished pose | pairs | Err_R mean (deg) | the solver ran |")
    print("|---|---|---:|---:|---:|")
    for pairs, rules in rows.items():
        for name, row in rules.items():
            print(f"| {pairs} | {name} | {row['pairs']} | {row['err_r_deg_mean']:.3f} | {row['solver_ran']:.2f} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=30, help="test pairs of each set (seed 0)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    parser.add_argument("--acceptance", action="store_true", help="Err_R and solver runs of stricter acceptance rules")
    parser.add_argument("--iterations", action="store_true", help="RPM-Net's iterations before the finish's polish")
    args = parser.parse_args(argv)
    if args.iterations or args.acceptance:
        study, show = (iterations, print_iterations) if args.iterations else (acceptance, print_acceptance)
        found = {f"{net}, {split}": study(net, split, count) for net, split, count in ACCEPTANCE_SETS}
        if args.json:
            print(json.dumps(found))
        else:
            show(found)
        return 0
    rows = {}
    for network, owner in SETS:
        name = f"{network} on {owner}'s test pairs"
        rows[name] = costs(network, owner, args.pairs)
        print(f"{name}: {rows[name]}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows))
        return 0
    print(
        "| network, pairs | solver way (s) | forward | polish | check | fallback share | fallback solver "
        "| register's own | finished (s) | ratio | bound | fallback share for 3x | truth trusted | perfect network |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in rows.items():
        print(
            f"| {name} | {r['solver_way']:.3f} | {r['forward']:.3f} | {r['polish']:.3f} | {r['check']:.3f} "
            f"| {r['fallback_share']:.2f} | {r['fallback']:.3f} | {r['wrap']:.3f} | {r['finished']:.3f} "
            f"| {r['ratio']:.2f}x | {r['bound']:.2f}x | {r['share_for_target']:.2f} | {r['truth_trusted']:.2f} "
            f"| {r['perfect_ratio']:.2f}x |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
