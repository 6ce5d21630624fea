"""Which polish should finish a network's pose: the Welsch polish from a narrow or a wide scale, or coarse steps first?

    python scripts/studies/finish_polish.py

From ``rpm_ours_airplane``'s pose on its protocol's 40 validation views (where the polish is chosen)
and 30 test views (256 points), and on 20 of ``linereg-benchmark``'s Airplane pairs (1024 points;
seed 0 draws all three), the finish's polish (:meth:`~linereg.registration.learned.Finish.polish`):
the Welsch polish from a scale of 0.2 over 40 steps (the default), from the solver's own 0.05 over 20,
or 80 coarse IRLS steps on the one-sided or two-sided Welsch-Chamfer loss first. Per variant: the mean
Err_R, the poses within 1 degree, those ``register``'s check trusts and those it trusts that are
more than 2 and 5 degrees off (the solver then does not run).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

VARIANTS = {
    "Welsch polish from 0.2, 40 steps (default)": {},
    "Welsch polish from 0.05, 20 steps (the solver's)": {"polish_nu": 0.05, "polish_steps": 20},
    "80 coarse steps, one-sided": {"coarse_steps": 80, "coarse_sides": ["source"]},
    "80 coarse steps, two-sided": {"coarse_steps": 80, "coarse_sides": ["both"]},
}


def main(argv: list[str] | None = None) -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    from linereg import pretrained
    from linereg.checks import nearest_rotation
    from linereg.datasets.benchmark_pairs import run_pairs, select_pairs
    from linereg.registration.evaluation import assess_registration
    from linereg.registration.learned import Finish, LearnedRegistration
    from linereg.registration.poses import rotation_gap_deg

    run = str(pretrained.path("rpm_ours_airplane"))
    sets = {
        "Airplane validation views (40)": run_pairs(run=run, split="val", pairs=40, seed=0),
        "Airplane test views (30)": run_pairs(run=run, split="test", pairs=30, seed=0),
        "Airplane benchmark pairs (20)": select_pairs({"name": "airplane"}, pairs=20, seed=0),
    }
    network = LearnedRegistration("rpm_ours_airplane", refine=True)  # the finish's forward
    print("| pairs | polish | Err_R mean (deg) | within 1 deg | trusted | trusted, > 2 deg | trusted, > 5 deg |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name, pairs in sets.items():
        clouds = [(p.src_xyz.astype(np.float64), p.tgt_xyz.astype(np.float64)) for p in pairs]
        starts = network.predict_many(clouds)
        truths = [nearest_rotation(p.gt_transform[:3, :3].astype(np.float64)) for p in pairs]
        for variant, options in VARIANTS.items():
            finish = Finish(options)
            errors, trusted = [], []
            for (src, tgt), start, truth in zip(clouds, starts, truths, strict=True):
                polished = finish.polish(src, tgt, start)
                errors.append(float(rotation_gap_deg(polished.transform[None, :3, :3], truth)[0]))
                trusted.append(assess_registration(src, tgt, polished.transform).confident)
            errors, trusted = np.array(errors), np.array(trusted)
            print(
                f"| {name} | {variant} | {errors.mean():.2f} | {(errors < 1).sum()} | {trusted.sum()} | "
                f"{(trusted & (errors > 2)).sum()} | {(trusted & (errors > 5)).sum()} |",
                flush=True,
            )


if __name__ == "__main__":  # the validation split is built in worker processes
    main()
