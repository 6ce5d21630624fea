"""Does ``confident`` keep every benchmark pair it trusts when it also asks for chance, uniqueness and units?

    python scripts/studies/check_trust.py [--pairs 40] [--out outputs/studies/trust.jsonl]
    python scripts/studies/check_trust.py --method rpm_ours_objects --refine   # the finished general model

On the benchmark pairs of every source (seed 0, as ``linereg-benchmark`` draws them), ``register``'s
answer is judged twice: by the inlier test alone
(:func:`~linereg.registration.evaluation.inlier_test`, at least 10 % inliers at an RMS of at most
1.2 sampling distances) and by the whole :func:`~linereg.registration.evaluation.assess_registration`
(the inlier test, a tight fitness above chance, no free motion, no symmetric rival). A pose is right
when Err_R <= 2 deg and its translation error <= 2 % of the target's bounding-box diagonal. One
JSON line per pair is appended to ``--out`` as it is measured; a rerun skips the pairs it holds.
``--method`` answers with another method of ``register`` (a network by name or run folder), and
``--refine`` finishes a network's poses with the solver (``refine=true``); the default ``--out`` then
names the method.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import linereg
from linereg.checks import nearest_rotation
from linereg.datasets.benchmark_pairs import select_pairs
from linereg.registration.baselines import diameter
from linereg.registration.benchmark_results import CORRECT_ROTATION_DEG, CORRECT_TRANSLATION_FRACTION
from linereg.registration.evaluation import inlier_test, passes_inlier_test
from linereg.registration.poses import rotation_gap_deg

SOURCES = {
    "airplane": {"name": "airplane"},
    "human": {"name": "human"},
    "pvw_airplane": {"name": "partial_vs_whole", "root": "modelnet40_normal_resampled", "patterns": ["airplane/*.txt"]},
    "pvw_human": {"name": "partial_vs_whole", "root": "meshes/odedstein/human"},
    "pvw_stanford": {"name": "partial_vs_whole", "root": "meshes/stanford_lowres"},
    "dragon": {"name": "dragon"},
    "fragments": {"name": "fragments"},
    "3dmatch": {"name": "3dmatch"},
}


def measure(name: str, index: int, pair, method: str = "robust", refine: bool = False) -> dict:
    """``register``'s answer (``method``, finished with ``refine``) on ``pair`` with both verdicts."""
    src, tgt = pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)
    truth = pair.gt_transform.astype(np.float64)
    truth[:3, :3] = nearest_rotation(truth[:3, :3])
    result = linereg.register(src, tgt, method=method, **({"refine": True} if refine else {}))
    transform = result.transformation
    quality, spacing, _, _ = inlier_test(src, tgt, transform)
    err_r = float(rotation_gap_deg(transform[None, :3, :3], truth[:3, :3])[0])
    err_t = float(np.linalg.norm(transform[:3, 3] - truth[:3, 3])) / diameter(tgt)
    return {
        "source": name,
        "pair": index,
        "err_r": err_r,
        "err_t": err_t,
        "right": err_r <= CORRECT_ROTATION_DEG and err_t <= CORRECT_TRANSLATION_FRACTION,
        "inlier_test": passes_inlier_test(quality, spacing),
        "confident": result.confident,
        "tight_fitness": result.info["tight_fitness"],
        "chance_fitness": result.info["chance_fitness"],
        "warnings": result.info["warnings"],
        "seconds": result.seconds,
    }


def table(rows: list[dict]) -> str:
    """Precision / recall of both verdicts per source and pooled."""
    lines = [
        "| source | pairs | right | inlier test P / R | confident P / R | trusted by the inlier test only |",
        "|---|---:|---:|---|---|---|",
    ]
    for name in [*SOURCES, "pooled"]:
        chosen = [r for r in rows if name == "pooled" or r["source"] == name]
        if not chosen:
            continue
        cells = []
        for key in ("inlier_test", "confident"):
            tp = sum(r[key] and r["right"] for r in chosen)
            cells.append(
                f"{tp / max(sum(r[key] for r in chosen), 1):.3f} / {tp / max(sum(r['right'] for r in chosen), 1):.3f}"
            )
        dropped = [
            f"{r['pair']} ({'right' if r['right'] else 'wrong'})"
            for r in chosen
            if r["inlier_test"] and not r["confident"]
        ]
        right = sum(r["right"] for r in chosen)
        lines.append(f"| {name} | {len(chosen)} | {right} | {cells[0]} | {cells[1]} | {', '.join(dropped) or '-'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=40, help="pairs per object source (fragments: 48, 3dmatch: all)")
    parser.add_argument("--sources", nargs="*", default=list(SOURCES), choices=list(SOURCES))
    parser.add_argument("--out", type=Path, help="the JSON lines (default: outputs/studies/trust[_<method>].jsonl)")
    parser.add_argument("--method", default="robust", help="register's method: a name, a network or a run folder")
    parser.add_argument("--refine", action="store_true", help="finish a network's poses with the solver")
    args = parser.parse_args(argv)
    if args.out is None:
        suffix = "" if args.method == "robust" else f"_{Path(args.method).name}{'_finished' if args.refine else ''}"
        args.out = Path(f"outputs/studies/trust{suffix}.jsonl")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows = [json.loads(line) for line in args.out.read_text().splitlines()] if args.out.exists() else []
    done = {(r["source"], r["pair"]) for r in rows}
    for name in args.sources:
        count = None if name in ("fragments", "3dmatch") else args.pairs
        for index, pair in enumerate(select_pairs(SOURCES[name], pairs=count, seed=0)):
            if (name, index) in done:
                continue
            row = measure(name, index, pair, args.method, args.refine)
            rows.append(row)
            with args.out.open("a") as stream:
                stream.write(json.dumps(row) + "\n")
            print(
                f"{name} {index}: right {row['right']} confident {row['confident']} {row['seconds']:.2f} s",
                file=sys.stderr,
            )
    print(table(rows))


if __name__ == "__main__":
    main()
