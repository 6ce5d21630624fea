"""How far are the shared 3DMatch pairs' published poses from where their whole fragments align?

    python scripts/studies/check_3dmatch_ground_truth.py [--results <3dmatch run>/results.json]

The shared data hold redkitchen's fragments 0 and 4 whole (about 300k points each) and the
GeoTransformer demo pair, whose target is fragment 0 subsampled and whose source is fragment 6
subsampled (the script checks both: ``ref.npy`` lies on fragment 0, ``gt.npy`` is the ``0 6``
block of redkitchen's ``gt.log``). Each published pose (``gt.log``, exactly rigid as the
``3dmatch`` benchmark reads it) is refined by Open3D point-to-plane ICP on the densest clouds at
hand, as the ``fragments`` benchmark refines its tracking poses
(:func:`~linereg.datasets.fragments.refine_pose`, 1 cm voxels): ``0 <- 4`` and ``0 <- 6`` onto
the whole fragment 0, ``4 <- 6`` onto the whole fragment 4. The chain ``(0 <- 4)(4 <- 6)``
checks the direct ``0 <- 6`` through two other refinements. Fitness is the share of source
points within 1.5 cm of the whole target, inlier RMS their RMS distance. With ``--results``
(``linereg-benchmark benchmark=3dmatch``), every method's pose is also scored against the
refined poses; its errors against the published poses are the benchmark's own.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from linereg.datasets.formats import read_log
from linereg.datasets.fragments import refine_pose
from linereg.io import read_point_cloud
from linereg.knn import NearestNeighbors
from linereg.paths import shared_data_dir
from linereg.pointcloud import estimate_normals
from linereg.registration.evaluation import evaluate_registration
from scripts.studies.check_fragment_ground_truth import pose_gap

VOXEL = 0.01
"""Voxel of the refinement (metres): the ``fragments`` benchmark's fusion voxel."""
FITNESS_DISTANCE = 0.015
"""Inlier distance of the fitness (metres): 1.5 voxels, the refinement's last round."""
GT_LOG = "3dmatch/geotransformer_demo/benchmarks/3DMatch/7-scenes-redkitchen/gt.log"
LINKS = {
    "0 <- 4": ("fragment 4", "fragment 0", (0, 4)),
    "4 <- 6": ("demo source", "fragment 4", (4, 6)),
    "0 <- 6": ("demo source", "fragment 0", (0, 6)),
}
"""The refined poses: name -> (source cloud, target cloud, ``gt.log`` block (target, source))."""


def load(shared: Path) -> dict:
    """The whole fragments 0 and 4, the demo clouds, and the published poses by ``(target, source)``."""
    demo = shared / "3dmatch/geotransformer_demo/demo"
    clouds = {
        "fragment 0": read_point_cloud(shared / "3dmatch/redkitchen_0_4/cloud_bin_0.ply").xyz.astype(np.float64),
        "fragment 4": read_point_cloud(shared / "3dmatch/redkitchen_0_4/cloud_bin_4.ply").xyz.astype(np.float64),
        "demo source": np.load(demo / "src.npy").astype(np.float64),
        "demo target": np.load(demo / "ref.npy").astype(np.float64),
    }
    published = {(entry.i, entry.j): entry.transform for entry in read_log(shared / GT_LOG)}
    demo_gap = np.abs(np.load(demo / "gt.npy") - published[(0, 6)]).max()
    on_fragment, _ = NearestNeighbors(clouds["fragment 0"]).query(clouds["demo target"])
    if demo_gap > 1e-3 or on_fragment.max() > 1e-5:
        raise SystemExit("the demo pair is not redkitchen 0 <- 6 (gt.npy or ref.npy differ)")
    return {"clouds": clouds, "published": published}


def refined_poses(data: dict, links: dict = LINKS) -> dict[str, np.ndarray]:
    """The poses of ``links`` (``0 <- 4``, ``4 <- 6``, ``0 <- 6``) refined from the published poses,
    and, when all three are refined, the chain ``0 <- 4 <- 6``."""
    clouds, published = data["clouds"], data["published"]
    # point-to-plane ICP ignores the normals' sign: orienting them to a point skips the slow consistent pass
    origin = np.zeros(3)
    targets = dict.fromkeys(target for _, target, _ in links.values())
    normals = {name: estimate_normals(clouds[name], k=30, orient_towards=origin) for name in targets}
    refined = {
        name: refine_pose(clouds[source], clouds[target], normals[target], published[key], VOXEL)
        for name, (source, target, key) in links.items()
    }
    if links.keys() == LINKS.keys():
        refined["0 <- 4 <- 6"] = refined["0 <- 4"] @ refined["4 <- 6"]
    return refined


def refined_demo_pose(shared: Path) -> np.ndarray:
    """``(4, 4)``: the GeoTransformer demo pair's published pose refined onto the whole fragment 0."""
    return refined_poses(load(shared), {"0 <- 6": LINKS["0 <- 6"]})["0 <- 6"]


def pose_table(data: dict, refined: dict[str, np.ndarray]) -> list[str]:
    """Markdown: per pose, its gap to the published pose and the fit of both on the whole target."""
    clouds, published = data["clouds"], data["published"]
    rows = LINKS | {"0 <- 4 <- 6": LINKS["0 <- 6"]}
    lines = [
        "| pose | refined vs published (deg, cm) | fitness published -> refined "
        "| inlier RMS published -> refined (mm) |",
        "|---|---|---|---|",
    ]
    for name, (source, target, key) in rows.items():
        before = evaluate_registration(clouds[source], clouds[target], FITNESS_DISTANCE, published[key])
        after = evaluate_registration(clouds[source], clouds[target], FITNESS_DISTANCE, refined[name])
        angle, distance = pose_gap(refined[name], published[key])
        lines.append(
            f"| {name} | {angle:.2f}, {distance:.1f} | {before.fitness:.3f} -> {after.fitness:.3f} "
            f"| {1000 * before.inlier_rmse:.1f} -> {1000 * after.inlier_rmse:.1f} |"
        )
    angle, distance = pose_gap(refined["0 <- 4 <- 6"], refined["0 <- 6"])
    lines += ["", f"Chain vs direct 0 <- 6: {angle:.2f} deg, {distance:.1f} cm."]
    return lines


def method_table(results: Path, refined: dict[str, np.ndarray]) -> list[str]:
    """Markdown: each method's pose on both pairs against the published and the refined poses."""
    records = json.loads(results.read_text())["records"]
    references = {"redkitchen 0/4": ["0 <- 4"], "demo (0 <- 6)": ["0 <- 6", "0 <- 4 <- 6"]}
    header = (
        "| method | redkitchen 0/4: vs published, vs refined (deg, cm) | demo: vs published, vs refined, vs chain |"
    )
    lines = [header, "|---|---|---|"]
    for method in dict.fromkeys(record["method"] for record in records):
        cells = []
        for pair, names in references.items():
            demo = pair != "redkitchen 0/4"
            (record,) = [
                r
                for r in records
                if r["method"] == method and (r["meta"].get("dataset") == "geotransformer_demo") == demo
            ]
            transform = np.array(record["transform"], dtype=np.float64)
            gaps = [(record["err_r_deg"], 100.0 * record["err_t_l2"])]
            gaps += [pose_gap(transform, refined[name]) for name in names]
            cells.append("; ".join(f"{angle:.2f}, {distance:.1f}" for angle, distance in gaps))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, help="results.json of linereg-benchmark benchmark=3dmatch")
    args = parser.parse_args(argv)
    shared = shared_data_dir()
    if shared is None:
        raise SystemExit("the shared data folder was not found (set $LINEREG_SHARED_DATA)")
    data = load(shared)
    refined = refined_poses(data)
    print("\n".join(pose_table(data, refined)))
    if args.results:
        print()
        print("\n".join(method_table(args.results, refined)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
