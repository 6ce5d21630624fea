"""Does the doubt test send the wrong first-round answers of ``register``, and only those, on?

    python scripts/studies/check_doubt.py --split choose --out doubt_choose.json   # seed-7 pairs: the thresholds
    python scripts/studies/check_doubt.py --split test --out doubt_test.json       # the benchmarks' pairs
    python scripts/studies/check_doubt.py --load doubt_choose.json                 # the tables again

The ``register`` default (:class:`~linereg.registration.robust.RobustRegistration`) runs once on
every pair. Its first round's answer is right when Err_R <= 2 deg and its translation error <= 2 %
of the target's bounding-box diagonal. On a target no larger than the solver's subset (the object
sources) the answer is the first-round candidate of lowest selection cost and the doubt test is
the subset test (:func:`~linereg.registration.robust.doubt`); a doubtful answer goes to rounds 2
and 3. On a scan the subset test is followed by the dense check, which judges the answer against
the dense target (``RobustResult.checked``) and alone sends it to the global stage; the subset
test alone is the rule without the check. A *false alarm* is a right answer sent on, a *miss* a
wrong answer kept.

``--split choose`` runs room-fragment pairs outside the ``fragments`` benchmark's draw: pairs
drawn with seed 7 from its overlap bins (the benchmarks draw with seed 0; the pairs of the
seed-0 draw are left out) and every pair of the shared sequence above its bins (overlap 0.8-1,
``fragments_high``: the room fragments are the only scan source with pairs outside its
benchmark's draw), and prints the false alarms and misses of the dense check for a
range of its two thresholds: the inlier RMSE limit in sampling distances (the confidence test of
:func:`~linereg.registration.evaluation.assess_registration` against the dense target) and the
rival ratio (``doubt_ratio``: a distinct candidate scoring more than ``1 / ratio`` of the best's
score). ``--split test`` runs every benchmark's own pairs (seed 0: the object sources, ``dragon``,
``fragments``, ``3dmatch``) and the shared statue scan pair, whose label is the transform FRICP
estimated (``scans/fricp_statue/m3trans.txt``: no ground truth ships with it), and prints the
false alarms and misses of both rules per source.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.checks import nearest_rotation
from linereg.datasets.benchmark_pairs import select_pairs
from linereg.fps import farthest_point_subset as fps
from linereg.io import read_point_cloud, read_transform
from linereg.paths import shared_data_dir
from linereg.registration import evaluation
from linereg.registration.baselines import diameter
from linereg.registration.benchmark_results import CORRECT_ROTATION_DEG, CORRECT_TRANSLATION_FRACTION
from linereg.registration.poses import rotation_gap_deg
from linereg.registration.robust import RobustRegistration
from linereg.registration.robust_options import RobustOptions
from linereg.registration.robust_result import CHECK, RobustResult

OBJECTS = ("airplane", "human", "pvw_airplane", "pvw_human", "pvw_stanford", "dragon")
"""The object benchmarks (``configs/benchmark/<name>.yaml``), 40 pairs each as registration.md runs them."""
SCANS = ("fragments", "3dmatch")
"""The scan benchmarks, with their own pair counts."""
HIGH_OVERLAP, HIGH_PAIRS = (0.8, 1.0), 18
"""Every room-fragment pair of the shared sequence above the benchmark's overlap bins (all 18 of them)."""
STATUE = "scans/fricp_statue"
RMSE_LIMITS = (1.1, 1.2, 1.3, 1.4, 1.5)
RATIOS = (1.0, 1.25, 2.0, 3.0)


def benchmark_source(name: str) -> dict:
    """The pair source of ``configs/benchmark/<name>.yaml``, as ``linereg-benchmark`` composes it."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from linereg.train import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        config = compose("benchmark", overrides=[f"benchmark={name}"])
    return OmegaConf.to_container(config.benchmark, resolve=True)


def labelled(name: str, split: str, pairs: int | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(source, target, label)`` of every pair of source ``name`` in ``split``."""
    if name == "statue":
        folder = shared_data_dir() / STATUE
        clouds = (read_point_cloud(folder / f"{side}.ply").xyz for side in ("source", "target"))
        return [(*clouds, read_transform(folder / "m3trans.txt"))]
    if name == "fragments_high":
        high = {**benchmark_source("fragments"), "bins": [list(HIGH_OVERLAP)]}
        return [(p.src_xyz, p.tgt_xyz, p.gt_transform) for p in select_pairs(high, pairs=HIGH_PAIRS, seed=7)]
    source = benchmark_source(name)
    pairs = pairs if name in OBJECTS else None
    if split == "test":
        drawn = select_pairs(source, pairs=pairs, seed=0)
    else:
        benchmark = {(p.meta["src_fragment"], p.meta["tgt_fragment"]) for p in select_pairs(source, seed=0)}
        drawn = [
            p
            for p in select_pairs(source, pairs=pairs, seed=7)
            if (p.meta["src_fragment"], p.meta["tgt_fragment"]) not in benchmark
        ]
    return [(p.src_xyz, p.tgt_xyz, p.gt_transform) for p in drawn]


def errors(transform: np.ndarray, label: np.ndarray, target: np.ndarray) -> tuple[float, float, bool]:
    """Err_R (deg), the translation error as a share of the target's bounding-box diagonal, and
    whether the pose is right (Err_R <= 2 deg and that share <= 2 %)."""
    err_r = float(rotation_gap_deg(transform[None, :3, :3], label[:3, :3])[0])
    err_t = float(np.linalg.norm(transform[:3, 3] - label[:3, 3])) / diameter(target)
    return err_r, err_t, err_r <= CORRECT_ROTATION_DEG and err_t <= CORRECT_TRANSLATION_FRACTION


def first_answer(result: RobustResult) -> np.ndarray:
    """The first round's answer: the one the dense check judged, or the round-1 candidate of lowest cost."""
    if result.checked is not None:
        return result.checked.transform
    first = [candidate for candidate in result.candidates if candidate.round == 1 and candidate.origin == "start"]
    return min(first, key=lambda candidate: candidate.cost).transform


def measure(name: str, src: np.ndarray, tgt: np.ndarray, label: np.ndarray) -> dict:
    """One row: the verdicts, the first answer's rightness and what the dense check measured."""
    src, tgt = np.asarray(src, dtype=np.float64), np.asarray(tgt, dtype=np.float64)
    label = np.array(label, dtype=np.float64)
    label[:3, :3] = nearest_rotation(label[:3, :3])  # ground truths stored in float32
    result = RobustRegistration().solve(src, tgt)
    check = next((step for step in result.history if step.stage == CHECK), None)
    answer = first_answer(result)
    (err_r, err_t, first_right), (final_r, final_t, final_right) = (
        errors(transform, label, tgt) for transform in (answer, result.transform)
    )
    row = {
        "source": name,
        "points": [len(src), len(tgt)],
        "right": first_right,
        "err_r": err_r,
        "err_t": err_t,
        "subset_doubtful": result.history[0].doubtful,
        "doubtful": result.history[0].doubtful if check is None else check.doubtful,
        "checked": check is not None,
        "final_right": final_right,
        "final_err_r": final_r,
        "final_err_t": final_t,
        "seconds": result.seconds,
        "stages": [step.stage for step in result.history],
        "global_candidates": result.global_candidates,
    }
    if check is not None:
        dense = fps(tgt, RobustOptions().global_stage.dense_points)
        found = evaluation.assess_registration(fps(src, 2048), dense, answer)
        row["fitness"] = found.fitness
        row["rmse"] = found.inlier_rmse / found.sampling_distance if found.fitness > 0 else float("inf")
        row["margin"] = check.margin
    return row


def sent_on(row: dict, rmse_limit: float, ratio: float) -> bool:
    """The dense check's verdict on ``row`` with these thresholds (the subset test first)."""
    if not row["checked"]:
        return row["doubtful"]
    confident = row["fitness"] >= evaluation.MIN_FITNESS and row["rmse"] <= rmse_limit
    return not confident or row["margin"] < 1.0 - 1.0 / ratio


def counts(rows: list[dict], verdict) -> str:
    """``false alarms / right answers, misses / wrong answers`` of ``verdict(row)``."""
    right = [row for row in rows if row["right"]]
    wrong = [row for row in rows if not row["right"]]
    alarms = sum(verdict(row) for row in right)
    misses = sum(not verdict(row) for row in wrong)
    return f"{alarms} / {len(right)} | {misses} / {len(wrong)}"


def sweep(rows: list[dict]) -> str:
    """False alarms and misses of the dense check over its thresholds, scan pairs pooled."""
    scans = [row for row in rows if row["source"] in (*SCANS, "fragments_high", "statue")]
    lines = [
        f"scan pairs: {len(scans)}, right first answers: {sum(row['right'] for row in scans)}\n",
        "| RMSE limit | rival ratio | false alarms / right | misses / wrong |",
        "|---|---|---|---|",
    ]
    for limit in RMSE_LIMITS:
        for ratio in RATIOS:
            verdict = functools.partial(sent_on, rmse_limit=limit, ratio=ratio)
            lines.append(f"| {limit} | {ratio} | {counts(scans, verdict)} |")
    return "\n".join(lines)


def per_source(rows: list[dict]) -> str:
    """False alarms and misses of the subset test alone and of the rule as it runs, per source."""
    lines = [
        "| source | pairs | right first answers | subset test: false alarms / right, misses / wrong "
        "| with the dense check | final answer right |",
        "|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(row["source"] for row in rows):
        chosen = [row for row in rows if row["source"] == name]
        old = counts(chosen, lambda row: row["subset_doubtful"])
        new = counts(chosen, lambda row: row["doubtful"])
        right, final = sum(row["right"] for row in chosen), sum(row["final_right"] for row in chosen)
        lines.append(f"| {name} | {len(chosen)} | {right} | {old} | {new} | {final} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=("choose", "test"), default="choose")
    parser.add_argument("--pairs", type=int, default=40, help="pairs per object source (scans: the benchmark's)")
    parser.add_argument("--sources", nargs="+", default=None, help="sources to run (default: all of the split)")
    parser.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    parser.add_argument("--load", type=Path, default=None, help="print the tables of rows written by --out")
    args = parser.parse_args(argv)
    if args.load is not None:
        rows = json.loads(args.load.read_text())
    else:
        names = ["fragments", "fragments_high"] if args.split == "choose" else [*OBJECTS, *SCANS, "statue"]
        rows = []
        for name in args.sources or names:
            for src, tgt, label in labelled(name, args.split, args.pairs):
                rows.append(measure(name, src, tgt, label))
                print(f"{name} pair {len(rows) - 1}: {rows[-1]}", file=sys.stderr, flush=True)
        if args.out is not None:
            args.out.write_text(json.dumps(rows))
    print(per_source(rows) + "\n\n" + sweep(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
