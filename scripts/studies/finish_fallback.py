"""When neither the polished network pose nor the solver's answer is trusted, which should the finish keep?

    python scripts/studies/finish_fallback.py [--pairs 30]

For each network on its own protocol's pairs and on another protocol's (``rpm_ours_airplane`` and
``rpm_ours_human`` on both, ``rpm_ours_real`` on its own), seed 0, the finish's polish of the network's
pose and the whole solver's answer, on the validation pairs (where the rule is chosen) and on the test
pairs. On the pairs where ``register``'s check trusts neither answer, each rule keeps one: the larger
inlier share within 3 point spacings, the larger share within 1.5, the larger Gaussian score at one
point spacing (:func:`~linereg.registration.trust.soft_fitness`), always the solver's, always the
network's. The table gives the mean Err_R of the kept answers per split and set.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

SETS = (
    ("rpm_ours_airplane", "rpm_ours_airplane"),
    ("rpm_ours_human", "rpm_ours_human"),
    ("rpm_ours_real", "rpm_ours_real"),
    ("rpm_ours_airplane", "rpm_ours_human"),
    ("rpm_ours_human", "rpm_ours_airplane"),
)
RULES = {
    "inlier share (3 spacings)": lambda net, sol: net["fitness"] > sol["fitness"],
    "tight share (1.5 spacings)": lambda net, sol: net["tight"] > sol["tight"],
    "Gaussian score (1 spacing; the finish's)": lambda net, sol: net["soft"] > sol["soft"],
    "the solver's always": lambda net, sol: False,
    "the network's always": lambda net, sol: True,
}


def untrusted_pairs(network: str, owner: str, split: str, count: int) -> list[dict]:
    """The pairs of ``owner``'s protocol (``split``) where the check trusts neither ``network``'s
    polished pose nor the solver's answer: each answer's Err_R and scores."""
    from linereg import pretrained
    from linereg.checks import nearest_rotation
    from linereg.datasets.benchmark_pairs import run_pairs
    from linereg.knn import NearestNeighbors
    from linereg.registration.evaluation import assess_registration
    from linereg.registration.learned import Finish, LearnedRegistration
    from linereg.registration.poses import rotation_gap_deg
    from linereg.registration.trust import soft_fitness, spacing_of, tight_fitness

    pairs = run_pairs(run=str(pretrained.path(owner)), split=split, pairs=count, seed=0)
    clouds = [(p.src_xyz.astype(np.float64), p.tgt_xyz.astype(np.float64)) for p in pairs]
    finish, rows = Finish(), []
    starts = LearnedRegistration(network, refine=True).predict_many(clouds)  # the finish's forward
    for (src, tgt), start, pair in zip(clouds, starts, pairs, strict=True):
        polished = finish.polish(src, tgt, start).transform
        if assess_registration(src, tgt, polished).confident:
            continue
        solved = finish.solver(src, tgt).transform
        if assess_registration(src, tgt, solved).confident:
            continue
        truth, index, spacing = (
            nearest_rotation(pair.gt_transform[:3, :3].astype(np.float64)),
            NearestNeighbors(tgt),
            spacing_of(tgt),
        )
        row = {}
        for name, transform in (("network", polished), ("solver", solved)):
            judged = assess_registration(src, tgt, transform)
            row[name] = {
                "err": float(rotation_gap_deg(transform[None, :3, :3], truth)[0]),
                "fitness": judged.fitness,
                "tight": float(tight_fitness(src, index, transform[None], 1.5 * spacing)[0]),
                "soft": float(soft_fitness(src, index, transform[None], spacing)[0]),
            }
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=30, help="pairs per set and split")
    args = parser.parse_args(argv)
    found = {
        (split, f"{network} on {owner}'s pairs"): untrusted_pairs(network, owner, split, args.pairs)
        for split in ("val", "test")
        for network, owner in SETS
    }
    print("| split | set | pairs neither trusted | " + " | ".join(RULES) + " |")
    print("|---|---|---:|" + "---:|" * len(RULES))
    for (split, name), rows in found.items():
        cells = []
        for keep_network in RULES.values():
            kept = [
                r["network"]["err"] if keep_network(r["network"], r["solver"]) else r["solver"]["err"] for r in rows
            ]
            cells.append(f"{np.mean(kept):.2f}" if kept else "-")
        print(f"| {split} | {name} | {len(rows)} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":  # the validation splits are built in worker processes
    main()
