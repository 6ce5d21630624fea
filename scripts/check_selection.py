"""Does the register default's selection cost rank poses right? Check it on a benchmark's results.

    python scripts/check_selection.py outputs/benchmark/partial_vs_whole/<run>/results.json

For every pair of the run (rebuilt from its settings) and every method whose pose ended more than
``--wrong-deg`` off, compare :func:`linereg.registration.robust.fixed_scale_cost` (the cost that picks the best
start, computed as the solver does: both clouds centred and scaled into the unit ball) at the
ground truth and at that wrong pose. The selection can only go wrong where a wrong pose costs less.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from linereg.datasets.benchmark_pairs import select_pairs
from linereg.registration.methods import translation
from linereg.registration.robust import RobustOptions, fixed_scale_cost


def _solver_frame(transform: np.ndarray, src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, float]:
    """``transform`` between the centred clouds, and their common unit-ball radius."""
    c_src, c_tgt = src.mean(axis=0), tgt.mean(axis=0)
    radius = max(np.linalg.norm(src - c_src, axis=1).max(), np.linalg.norm(tgt - c_tgt, axis=1).max())
    centred = translation(-c_tgt) @ transform @ translation(c_src)
    centred[:3, 3] /= radius
    return centred, radius


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.json of python -m train.benchmark")
    parser.add_argument("--wrong-deg", type=float, default=5.0)
    args = parser.parse_args(argv)
    content = json.loads(args.results.read_text())
    settings = content["settings"]
    pairs = select_pairs(settings["benchmark"], pairs=settings.get("pairs"), seed=int(settings.get("seed", 0)))
    wrong, ranked_right = 0, 0
    margins = []
    for record in content["records"]:
        if record["err_r_deg"] <= args.wrong_deg:
            continue
        pair = pairs[record["pair"]]
        src, tgt = pair.src_xyz.astype(np.float64), pair.tgt_xyz.astype(np.float64)
        truth, radius = _solver_frame(pair.gt_transform.astype(np.float64), src, tgt)
        found, _ = _solver_frame(np.asarray(record["transform"]), src, tgt)
        poses = np.stack([truth, found])
        costs = fixed_scale_cost(
            (poses[:, :3, :3], poses[:, :3, 3]),
            (src - src.mean(axis=0)) / radius,
            cKDTree((tgt - tgt.mean(axis=0)) / radius),
            RobustOptions().select_nu,
        )
        wrong += 1
        ranked_right += int(costs[0] < costs[1])
        margins.append(float(costs[1] - costs[0]))
    if not wrong:
        print(f"no pose more than {args.wrong_deg} deg off in {args.results}")
        return 0
    print(
        f"{args.results}: {wrong} poses more than {args.wrong_deg:g} deg off (all methods); the selection cost is "
        f"lower at the ground truth for {ranked_right} of them ({ranked_right / wrong:.1%}); "
        f"cost(wrong) - cost(truth): median {np.median(margins):.3f}, min {min(margins):.3f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
