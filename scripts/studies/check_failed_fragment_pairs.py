"""Fragment pairs that methods fail: is the ground truth wrong, or do the fragments fit better elsewhere?

    python scripts/studies/check_failed_fragment_pairs.py --results <run>/results.json \\
        [--methods ours fpfh_ransac]

For every pair of a ``fragments`` benchmark run (``linereg-benchmark benchmark=fragments``, refined
ground truth) on which one of ``--methods`` ends outside 5 deg / 10 cm, on the *whole* fragments:

* **the ground truth against a chain.** The pair's refined pose is compared with the composition
  of two refined poses through a third fragment ``k`` (``T_tk T_ks``, each link
  :func:`~linereg.datasets.fragments.refine_pose` from its tracking pose), ``k`` sharing no frame
  with either end and chosen to maximise the smaller of the two links' overlaps (the links are
  cached beside the benchmark's refined ground truth);
* **which pose the fragments prefer.** The share of source points within 1.5 cm of the target
  (fitness) and the fixed-scale Welsch cost ``mean 1 - exp(-d^2 / 2 nu^2)`` of their nearest
  distances at several scales ``nu``, at the ground truth and at each method's pose. A failed
  pose that scores worse than the truth on both fine scores (fitness, Welsch at 2 cm: the scale
  at which ``register`` selects) is a *search* failure (the truth was there to be found); one
  that scores better on both is an *ambiguity* that these scores cannot resolve.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.fragments import (
    FragmentSettings,
    cached_fragments,
    refined_cache_path,
    refined_ground_truths,
)
from linereg.knn import NearestNeighbors
from linereg.paths import shared_data_dir
from linereg.registration.benchmark_results import RECALL_THRESHOLDS
from linereg.registration.welsch import welsch_cost
from scripts.studies.check_fragment_ground_truth import pose_gap

FITNESS_DISTANCE = 0.015
"""Inlier distance of the fitness (metres): 1.5 fusion voxels, as the refinement's last round."""
WELSCH_SCALES = (0.02, 0.05, 0.10)
"""Scales ``nu`` (metres) of the fixed-scale Welsch costs."""


def failed_pairs(records: list[dict], methods: list[str]) -> dict[int, dict[str, dict]]:
    """``{pair: {method: record}}`` of the pairs on which one of ``methods`` misses 5 deg / 10 cm."""
    max_deg, max_translation = RECALL_THRESHOLDS[1]
    by_pair: dict[int, dict[str, dict]] = {}
    for record in records:
        if record["method"] in methods:
            by_pair.setdefault(record["pair"], {})[record["method"]] = record
    return {
        pair: found
        for pair, found in sorted(by_pair.items())
        if any(r["err_r_deg"] > max_deg or r["err_t_l2"] > max_translation for r in found.values())
    }


def chain_fragment(fragments, target: int, source: int) -> tuple[int, float, float]:
    """The fragment ``k`` with no frame in common with ``target`` or ``source`` maximising the
    smaller of the candidate overlaps of ``(target, k)`` and ``(k, source)``; with both overlaps."""
    overlaps = {
        tuple(int(v) for v in pair): float(o) for pair, o in zip(fragments.pairs, fragments.overlaps, strict=True)
    }

    def overlap(a: int, b: int) -> float | None:
        return overlaps.get((min(a, b), max(a, b)))

    best = None
    for k in range(len(fragments.xyz)):
        first, second = overlap(target, k), overlap(k, source)
        if k in (target, source) or first is None or second is None:
            continue
        if best is None or min(first, second) > min(best[1], best[2]):
            best = (k, first, second)
    if best is None:
        raise SystemExit(f"no fragment shares no frame with both {target} and {source}")
    return best


def fit_scores(source: np.ndarray, index: NearestNeighbors, pose: np.ndarray) -> list[float]:
    """Fitness at :data:`FITNESS_DISTANCE`, then the Welsch cost at each of :data:`WELSCH_SCALES`."""
    distances, _ = index.query(source @ pose[:3, :3].T + pose[:3, 3])
    return [float(np.mean(distances <= FITNESS_DISTANCE))] + [float(welsch_cost(distances, nu)) for nu in WELSCH_SCALES]


def study_rows(results: Path, methods: list[str]) -> list[dict]:
    """Per failed pair: its meta, the chain check and the scores of the truth and of each method's pose."""
    run = json.loads(results.read_text())
    benchmark = run["settings"]["benchmark"]
    if benchmark["name"] != "fragments" or benchmark.get("ground_truth", "refined") != "refined":
        raise SystemExit(f"{results}: not a fragments run against the refined ground truth")
    shared = shared_data_dir()
    if shared is None:
        raise SystemExit("the shared data folder was not found (set $LINEREG_SHARED_DATA)")
    root = (shared / "rgbd/7scenes_first_half/data").resolve()
    names = ("frames_per_fragment", "fragment_stride", "voxel_size", "pixel_stride", "max_depth")
    settings = FragmentSettings(**{name: benchmark[name] for name in names if name in benchmark})
    fragments = cached_fragments(root, settings)
    failed = failed_pairs(run["records"], methods)
    ends = {
        pair: (found[methods[0]]["meta"]["tgt_fragment"], found[methods[0]]["meta"]["src_fragment"])
        for pair, found in failed.items()
    }
    cache = refined_cache_path(root, settings)
    truths = refined_ground_truths(fragments, list(ends.values()), settings, cache)
    rows = []
    for pair, found in failed.items():
        target, source = ends[pair]
        truth = truths[(target, source)]
        middle, first, second = chain_fragment(fragments, target, source)
        links = refined_ground_truths(fragments, [(target, middle), (middle, source)], settings, cache)
        chain = links[(target, middle)] @ links[(middle, source)]
        index = NearestNeighbors(fragments.xyz[target].astype(np.float64))
        points = fragments.xyz[source].astype(np.float64)
        poses = {"truth": truth} | {m: np.array(found[m]["transform"], dtype=np.float64) for m in methods}
        rows.append(
            {
                "pair": pair,
                "bin": found[methods[0]]["meta"]["overlap_bin"],
                "overlap": found[methods[0]]["meta"]["overlap"],
                "ends": (target, source),
                "chain": (middle, first, second, *pose_gap(chain, truth)),
                "errors": {m: (found[m]["err_r_deg"], 100 * found[m]["err_t_l2"]) for m in methods},
                "scores": {name: fit_scores(points, index, pose) for name, pose in poses.items()},
            }
        )
        print(f"pair {pair} done", file=sys.stderr, flush=True)
    return rows


def chain_table(rows: list[dict], methods: list[str]) -> list[str]:
    """Markdown: per failed pair, the methods' errors and the chain's gap to the ground truth."""
    errors = " | ".join(f"{m}: RRE (deg), RTE (cm)" for m in methods)
    lines = [
        f"| pair (overlap) | target, source | {errors} | chain through (link overlaps) "
        "| chain vs ground truth (deg, cm) |",
        "|---|---|" + "---|" * (len(methods) + 2),
    ]
    for row in rows:
        middle, first, second, angle, distance = row["chain"]
        cells = " | ".join(f"{r:.1f}, {t:.1f}" for r, t in row["errors"].values())
        lines.append(
            f"| {row['pair']} ({row['overlap']:.2f}) | {row['ends'][0]}, {row['ends'][1]} | {cells} "
            f"| {middle} ({first:.2f}, {second:.2f}) | {angle:.2f}, {distance:.1f} |"
        )
    return lines


VERDICTS = ("search", "mixed", "ambiguity")
"""Failure kinds by how many of the two fine scores favour the failed pose over the truth."""


def failures(rows: list[dict], methods: list[str]) -> list[tuple[int, str, str]]:
    """``(pair, method, verdict)`` of every result outside 5 deg / 10 cm."""
    max_deg, max_translation = RECALL_THRESHOLDS[1]
    found = []
    for row in rows:
        truth = row["scores"]["truth"]
        for method in methods:
            rotation, centimetres = row["errors"][method]
            if rotation <= max_deg and centimetres <= 100 * max_translation:
                continue
            scores = row["scores"][method]
            found.append((row["pair"], method, VERDICTS[int(scores[0] > truth[0]) + int(scores[1] < truth[1])]))
    return found


def score_table(rows: list[dict], methods: list[str]) -> list[str]:
    """Markdown: fitness and Welsch costs at the truth and at each failed pose, and the verdict."""
    verdicts = {(pair, method): verdict for pair, method, verdict in failures(rows, methods)}
    scales = " | ".join(f"Welsch {100 * nu:g} cm" for nu in WELSCH_SCALES)
    lines = [
        f"| pair | pose | fitness 1.5 cm | {scales} | failure |",
        "|---|---|---|" + "---|" * (len(WELSCH_SCALES) + 1),
    ]
    for row in rows:
        lines.append(
            f"| {row['pair']} | ground truth | " + " | ".join(f"{v:.3f}" for v in row["scores"]["truth"]) + " | |"
        )
        for method in methods:
            if (row["pair"], method) in verdicts:
                scores = " | ".join(f"{v:.3f}" for v in row["scores"][method])
                lines.append(f"| {row['pair']} | {method} | {scores} | {verdicts[(row['pair'], method)]} |")
    return lines


def verdict_table(rows: list[dict], methods: list[str]) -> list[str]:
    """Markdown: per method, its failures by kind and by overlap bin."""
    bins = {row["pair"]: row["bin"] for row in rows}
    found = failures(rows, methods)
    lines = ["| method | overlap | failures | " + " | ".join(VERDICTS) + " |", "|---|---|---|" + "---|" * len(VERDICTS)]
    for method in methods:
        for label in dict.fromkeys(bins.values()):
            mine = [verdict for pair, name, verdict in found if name == method and bins[pair] == label]
            counts = " | ".join(str(mine.count(verdict)) for verdict in VERDICTS)
            lines.append(f"| {method} | {label} | {len(mine)} | {counts} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, required=True, help="results.json of a fragments benchmark run")
    parser.add_argument("--methods", nargs="+", default=["ours", "fpfh_ransac"])
    args = parser.parse_args(argv)
    rows = study_rows(args.results, args.methods)
    print("\n".join(chain_table(rows, args.methods)))
    print()
    print("\n".join(score_table(rows, args.methods)))
    print()
    print("\n".join(verdict_table(rows, args.methods)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
