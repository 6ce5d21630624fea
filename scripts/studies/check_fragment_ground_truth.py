"""How far are the fragments' tracking poses from where their geometry aligns, and which pose do methods find?

    python scripts/studies/check_fragment_ground_truth.py [--pairs 48] [--seed 0] \\
        [--results tracking=<results.json> refined=<results.json>]

For the pairs of the ``fragments`` benchmark (same draw), the script compares the tracking pose
of each pair (the camera poses' ``T_target^-1 T_source``) with the refined ground truth
(:func:`linereg.datasets.fragments.refine_pose`) on the *whole* fragments: the share of source
points within 1.5 fusion voxels of a target point (fitness) and their RMS distance, the overlap
(3.75 cm) under each, and the rotation and translation between the two poses. With
``--results``, it also prints the median errors of each method of benchmark runs scored against
either ground truth (``linereg-benchmark benchmark=fragments benchmark.ground_truth=...``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.fragments import (
    DEFAULT_BINS,
    FragmentSettings,
    bin_label,
    cached_fragments,
    draw_pairs,
    overlap_ratio,
    refined_cache_path,
    refined_ground_truths,
)
from linereg.paths import shared_data_dir
from linereg.registration.evaluation import evaluate_registration
from linereg.registration.poses import rotation_gap_deg


def pose_gap(first: np.ndarray, second: np.ndarray) -> tuple[float, float]:
    """Rotation angle (deg) and translation distance (cm) between two ``(4, 4)`` rigid poses."""
    angle = float(rotation_gap_deg(first[None, :3, :3], second[:3, :3])[0])
    return angle, 100.0 * float(np.linalg.norm(first[:3, 3] - second[:3, 3]))


def pose_rows(pairs: int, seed: int) -> list[dict]:
    """Per drawn pair: its bin, the correction and the alignment at both poses."""
    shared = shared_data_dir()
    if shared is None:
        raise SystemExit("the shared data folder was not found (set $LINEREG_SHARED_DATA)")
    root = (shared / "rgbd/7scenes_first_half/data").resolve()
    settings = FragmentSettings()
    fragments = cached_fragments(root, settings)
    drawn = draw_pairs(fragments.overlaps, DEFAULT_BINS, pairs, seed)
    ends = [tuple(int(v) for v in fragments.pairs[candidate]) for candidate, _ in drawn]
    refined = refined_ground_truths(fragments, ends, settings, refined_cache_path(root, settings))
    rows = []
    for (_, bin_number), (target, source) in zip(drawn, ends, strict=True):
        tracking, truth = fragments.ground_truth(target, source), refined[(target, source)]
        distance = 1.5 * settings.voxel_size
        source_points, target_points = fragments.xyz[source], fragments.xyz[target]
        rows.append(
            {
                "bin": bin_label(*DEFAULT_BINS[bin_number], bin_number == len(DEFAULT_BINS) - 1),
                **dict(zip(("correction_deg", "correction_cm"), pose_gap(truth, tracking), strict=True)),
                "tracking": evaluate_registration(source_points, target_points, distance, tracking)[:2],
                "refined": evaluate_registration(source_points, target_points, distance, truth)[:2],
                "overlap": [
                    overlap_ratio(source_points, target_points, pose, max_points=20000) for pose in (tracking, truth)
                ],
            }
        )
    return rows


def pose_table(rows: list[dict]) -> list[str]:
    """Markdown table of :func:`pose_rows` per overlap bin and over all pairs."""
    lines = [
        "| pairs | correction median / max (deg) | correction median / max (cm) "
        "| fitness tracking -> refined (median) | inlier RMS tracking -> refined (median, mm) "
        "| refined fits more points | overlap tracking -> refined (min-max) |",
        "|---|---|---|---|---|---|---|",
    ]
    groups = {label: [row for row in rows if row["bin"] == label] for label in dict.fromkeys(r["bin"] for r in rows)}
    for label, group in {**groups, "all": rows}.items():
        degrees = np.array([row["correction_deg"] for row in group])
        centimetres = np.array([row["correction_cm"] for row in group])
        fitness = np.array([[row["tracking"][0], row["refined"][0]] for row in group])
        rms = 1000 * np.array([[row["tracking"][1], row["refined"][1]] for row in group])
        overlap = np.array([row["overlap"] for row in group])
        lines.append(
            f"| {label} ({len(group)}) | {np.median(degrees):.2f} / {degrees.max():.2f} "
            f"| {np.median(centimetres):.1f} / {centimetres.max():.1f} "
            f"| {np.median(fitness[:, 0]):.3f} -> {np.median(fitness[:, 1]):.3f} "
            f"| {np.median(rms[:, 0]):.1f} -> {np.median(rms[:, 1]):.1f} "
            f"| {int((fitness[:, 1] > fitness[:, 0]).sum())} of {len(group)} "
            f"| {overlap[:, 0].min():.2f}-{overlap[:, 0].max():.2f} "
            f"-> {overlap[:, 1].min():.2f}-{overlap[:, 1].max():.2f} |"
        )
    return lines


def method_table(results: dict[str, Path]) -> list[str]:
    """Median rotation / translation error of each method against each ground truth."""
    runs = {name: json.loads(Path(path).read_text())["records"] for name, path in results.items()}
    methods = list(dict.fromkeys(record["method"] for records in runs.values() for record in records))
    header = " | ".join(f"{name}: RRE median (deg) | {name}: RTE median (cm)" for name in runs)
    lines = [f"| method | {header} |", "|---|" + "---|" * (2 * len(runs))]
    for method in methods:
        cells = []
        for records in runs.values():
            mine = [record for record in records if record["method"] == method]
            cells.append(f"{np.median([r['err_r_deg'] for r in mine]):.2f}")
            cells.append(f"{100 * np.median([r['err_t_l2'] for r in mine]):.1f}")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=48)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--results", nargs="*", default=[], metavar="NAME=RESULTS_JSON")
    args = parser.parse_args(argv)
    results = dict(item.split("=", 1) for item in args.results)
    print("\n".join(pose_table(pose_rows(args.pairs, args.seed))))
    if results:
        print()
        print("\n".join(method_table(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
