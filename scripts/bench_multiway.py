"""Multiway registration (:func:`linereg.register_scans`) against Open3D's multiway pipeline, on real scans.

    python scripts/bench_multiway.py                      # both data sets, the tables of docs/studies/multiway.md
    python scripts/bench_multiway.py --only bunny --figure docs/figures/multiway_bunny.png

Data (the shared data, ``$LINEREG_SHARED_DATA`` or ``../shared/data``):

* the 7 Stanford Bunny range scans, ``mode="unordered"``; errors of each scan's pose against
  ``bun.conf`` relative to ``bun000``;
* the 7-Scenes sequence of the Real protocol, frames 0-490 every 10th (50 depth frames back-projected
  at every 2nd pixel, as :class:`~linereg.datasets.rgbd.RgbdSequencePairs` does), ``mode="sequence"``;
  the absolute trajectory error (RMSE over the placed frames) against the camera poses relative to
  frame 0, as they are (``anchored``) and after the best rigid alignment of the two trajectories
  (``aligned``, Horn's method as TUM's ATE).

Below each table: the mean fitness (share of the source grid within one voxel of the target grid) of
the kept pairs at our poses and at the reference poses: which of the two the scans' geometry prefers.

Rows per data set: ours (the ``register`` default on every edge); ours on the same edges with one wrong
confident edge added (a true pair turned by 30 degrees about the vertical, fitness 0.99); ours on the
same edges with the final polish; and the anchor, Open3D's multiway tutorial: FPFH + RANSAC and
point-to-plane ICP (coarse, then fine) on every pair (Bunny) or every pair at most
:data:`ANCHOR_WINDOW` frames apart (7-Scenes), odometry edges certain, ``global_optimization`` with the
tutorial's settings on the same voxel grid as ours.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from linereg.paths import shared_data_dir
from linereg.registration.multiway import Edge, MultiwayOptions, Scans, place_scans, register_scans
from linereg.train.register_scans import pose_errors, read_gt_poses

ANCHOR_WINDOW = 4
"""The 7-Scenes anchor registers every pair of frames at most this many scans apart."""
WRONG_TURN_DEG = 30.0
FRAMES = range(0, 500, 10)


def bunny() -> tuple[list, list[np.ndarray], str]:
    """The Bunny scans (files), their poses relative to bun000 and the mode."""
    root = shared_data_dir() / "scans" / "stanford_bunny_range"
    files = sorted(root.glob("*.ply"))
    return files, read_gt_poses(root / "bun.conf", files), "unordered"


def seven_scenes() -> tuple[list, list[np.ndarray], str]:
    """The 7-Scenes frames as ``(N, 3)`` clouds in metres, their camera poses relative to frame 0 and the mode."""
    from linereg.datasets.fragments import sequence_frames
    from linereg.datasets.rgbd import depth_to_points, read_depth_image

    frames, intrinsics, depth_scale = sequence_frames(shared_data_dir() / "rgbd" / "7scenes_first_half" / "data")
    chosen = [frame for frame in frames if frame.number in FRAMES]
    clouds = [
        depth_to_points(read_depth_image(frame.depth), intrinsics, depth_scale=depth_scale, pixel_stride=2)
        for frame in chosen
    ]
    first = np.linalg.inv(chosen[0].pose)
    return clouds, [first @ frame.pose for frame in chosen], "sequence"


def scores(poses: list[np.ndarray | None], truths: list[np.ndarray]) -> dict[str, float]:
    """Placed count, worst and RMS errors (anchored at the first scan) and the aligned ATE of the placed scans."""
    from linereg.procrustes import weighted_procrustes_numpy

    placed = [k for k, pose in enumerate(poses) if pose is not None]
    errors = np.array([pose_errors(poses[k], truths[k]) for k in placed])
    ours, theirs = np.stack([poses[k][:3, 3] for k in placed]), np.stack([truths[k][:3, 3] for k in placed])
    rotation, translation, _ = weighted_procrustes_numpy(ours[None], theirs[None], np.ones((1, len(placed))))
    align = np.eye(4)
    align[:3, :3], align[:3, 3] = rotation[0], translation[0]
    aligned = np.array([pose_errors(align @ poses[k], truths[k]) for k in placed])
    return {
        "placed": len(placed),
        "worst_r": errors[:, 0].max(),
        "worst_t": errors[:, 1].max(),
        "rms_r": np.sqrt(np.mean(errors[:, 0] ** 2)),
        "rms_t": np.sqrt(np.mean(errors[:, 1] ** 2)),
        "ate_r": np.sqrt(np.mean(aligned[:, 0] ** 2)),
        "ate_t": np.sqrt(np.mean(aligned[:, 1] ** 2)),
    }


def wrong_edge(truths: list[np.ndarray], source: int, target: int) -> Edge:
    """A confident edge ``source -> target``: the true transform turned by :data:`WRONG_TURN_DEG` about the y axis."""
    from scipy.spatial.transform import Rotation

    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("y", WRONG_TURN_DEG, degrees=True).as_matrix()
    return Edge(
        source, target, turn @ np.linalg.inv(truths[target]) @ truths[source], 0.99, 0.0, True, 0.0, "loop closure"
    )


def anchor(scans: Scans, mode: str) -> tuple[list[np.ndarray], int, float]:
    """Open3D's multiway tutorial on ``scans``' grids: the poses, the edge count and the seconds."""
    import open3d as o3d

    from linereg.registration.features import FeatureOptions, global_candidates

    registration = o3d.pipelines.registration
    began, voxel, count = time.perf_counter(), scans.voxel, len(scans)
    window = count if mode == "unordered" else ANCHOR_WINDOW
    graph = registration.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(registration.PoseGraphNode(odometry))
    pairs = [(i, j) for i in range(count) for j in range(i + 1, min(count, i + window + 1))]
    for i, j in pairs:
        points = [np.asarray(scans.grids[k].points) for k in (i, j)]
        found, _ = global_candidates(*points, FeatureOptions(mutual=(True,), fgr=False))
        transform = found[0]
        for distance in (15.0 * voxel, 1.5 * voxel):
            transform = registration.registration_icp(
                scans.grids[i], scans.grids[j], distance, transform, registration.TransformationEstimationPointToPlane()
            ).transformation
        information = registration.get_information_matrix_from_point_clouds(
            scans.grids[i], scans.grids[j], 1.5 * voxel, transform
        )
        if j == i + 1:
            odometry = transform @ odometry
            graph.nodes.append(registration.PoseGraphNode(np.linalg.inv(odometry)))
        graph.edges.append(registration.PoseGraphEdge(i, j, transform, information, uncertain=j != i + 1))
    option = registration.GlobalOptimizationOption(
        max_correspondence_distance=1.5 * voxel, edge_prune_threshold=0.25, reference_node=0
    )
    registration.global_optimization(
        graph,
        registration.GlobalOptimizationLevenbergMarquardt(),
        registration.GlobalOptimizationConvergenceCriteria(),
        option,
    )
    return [np.asarray(node.pose) for node in graph.nodes], len(pairs), time.perf_counter() - began


def pair_fitness(scans: Scans, edges: list[Edge], poses: list, truths: list[np.ndarray]) -> tuple[float, float]:
    """Mean share of each edge's source grid within one voxel of its target grid, at ``poses`` and at ``truths``."""
    from linereg.registration.evaluation import evaluate_registration

    def mean(chosen: list) -> float:
        return float(
            np.mean(
                [
                    evaluate_registration(
                        np.asarray(scans.grids[e.source].points),
                        np.asarray(scans.grids[e.target].points),
                        scans.voxel,
                        np.linalg.inv(chosen[e.target]) @ chosen[e.source],
                    ).fitness
                    for e in edges
                ]
            )
        )

    return mean(poses), mean(truths)


def row(name: str, found: dict[str, float], edges: int, per_edge: float, total: float, scale: float) -> str:
    """One Markdown table row."""
    return (
        f"| {name} | {found['placed']} | {found['worst_r']:.3f} | {scale * found['worst_t']:.2f} "
        f"| {found['rms_r']:.3f} | {scale * found['rms_t']:.2f} | {found['ate_r']:.3f} | {scale * found['ate_t']:.2f} "
        f"| {edges} | {per_edge:.2f} | {total:.0f} |"
    )


def bench(name: str, load, wrong: tuple[int, int], scale: float, unit: str, figure: Path | None) -> None:
    """Print the table of one data set."""
    scans, truths, mode = load()
    options = MultiwayOptions()
    result = register_scans(scans, mode=mode, options=options, progress=False)
    edges = result.edges
    per_edge = float(np.mean([edge.seconds for edge in edges]))
    print(f"\n{name}: {len(scans)} scans, mode={mode}, voxel {scale * result.voxel:.2f} {unit}")
    print(
        f"| run | placed | worst Err_R (°) | worst Err_t ({unit}) | RMS Err_R (°) | RMS Err_t ({unit}) "
        f"| ATE aligned (°) | ATE aligned ({unit}) | edges | s / edge | total (s) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(row("ours", scores(result.poses, truths), len(edges), per_edge, result.seconds, scale))
    injected = place_scans(scans, [*edges, wrong_edge(truths, *wrong)], options)
    verdict = "kept" if injected.edges[-1].kept else "dropped"
    label = f"ours + a wrong edge {result.names[wrong[0]]}-{result.names[wrong[1]]} ({verdict})"
    print(row(label, scores(injected.poses, truths), len(edges) + 1, per_edge, result.seconds, scale))
    polished = place_scans(scans, edges, replace(options, polish=True))
    print(row("ours + final polish", scores(polished.poses, truths), len(edges), per_edge, result.seconds, scale))
    poses, count, seconds = anchor(Scans(scans, options), mode)
    print(row("Open3D multiway (anchor)", scores(poses, truths), count, seconds / count, seconds, scale))
    ours, theirs = pair_fitness(Scans(scans, options), [e for e in edges if e.kept], result.poses, truths)
    print(f"kept pairs' fitness within one voxel: {ours:.3f} at our poses, {theirs:.3f} at the reference poses")
    left_out = [f"{result.names[k]}: {result.verdicts[k]}" for k in range(len(scans)) if not result.placed[k]]
    print("left out:", "; ".join(left_out) or "none")
    print(f"edges: {sum(e.confident for e in edges)} confident, {sum(e.kept for e in edges)} kept of {len(edges)}")
    if figure is not None:
        picture(result.merged, figure, f"{name}: {sum(result.placed)} scans merged")


def picture(points: np.ndarray, path: Path, title: str) -> None:
    """A small scatter of at most 6000 points of ``points (N, 3)`` seen from the front."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = points[np.random.default_rng(0).permutation(len(points))[:6000]]
    figure, axis = plt.subplots(figsize=(4, 4), dpi=100)
    axis.scatter(shown[:, 0], shown[:, 1], s=0.5, c=shown[:, 2], cmap="viridis")
    axis.set_aspect("equal")
    axis.set_axis_off()
    axis.set_title(title, fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, bbox_inches="tight")
    plt.close(figure)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("bunny", "7scenes"), help="one data set")
    parser.add_argument("--figure", type=Path, help="a PNG of the merged Bunny")
    arguments = parser.parse_args(argv)
    if shared_data_dir() is None:
        raise SystemExit("shared data not found: set $LINEREG_SHARED_DATA or place it at ../shared/data")
    if arguments.only in (None, "bunny"):
        bench("Stanford Bunny", bunny, (0, 2), 1000.0, "mm", arguments.figure)
    if arguments.only in (None, "7scenes"):
        bench("7-Scenes frames 0-490, every 10th", seven_scenes, (0, 12), 100.0, "cm", None)


if __name__ == "__main__":
    main()
