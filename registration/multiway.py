"""``linereg.register_scans``: many scans into one frame, through a pose graph.

::

    import linereg

    result = linereg.register_scans(["scan_0.ply", "scan_1.ply", ...], mode="sequence")
    result.poses[k]          # (4, 4) scan k -> the first scan's frame, or None where not placed
    result.placed[k], result.verdicts[k]
    result.edges             # every pair registered: its transform, fitness, confident, kept
    result.merged            # (M, 3) the placed scans together, on the voxel grid

Edges. ``mode="sequence"``: each scan against its next ``neighbours`` scans (odometry), then loop
closures among the others, proposed where the poses so far predict an overlap. ``mode="unordered"``:
every pair ranked by a cheap overlap estimate (the fitness of a short FPFH + RANSAC on a coarse
grid), and each scan's best ``candidates`` pairs registered. Every edge is registered with
:func:`linereg.register_many` (any ``method`` of :func:`linereg.register`, a network included) on the
scans' voxel grids (about ``grid_points`` points each; depth images' row-and-column sampling would
otherwise skew the confidence test), and only confident ones enter the graph, so the work grows
with the pairs registered.

Graph. Open3D's pose graph (``pipelines.registration.global_optimization``, Levenberg-Marquardt
with a line process): each edge's information matrix comes from the pair's correspondences on the
voxel grid (``get_information_matrix_from_point_clouds``); odometry edges are certain, loop
closures and unordered edges uncertain, and the line process drops those that disagree with the rest.
The starting poses follow a spanning tree of the edges that agree with the most triangles of edges,
then hold the most correspondences, so that one wrong edge does not set them; an edge the graph keeps
but does not follow (too few correspondences to matter) is not counted as kept.

Verdicts. A scan is placed when kept edges connect it to the first scan, and ``verdicts`` names
them; otherwise it is left out with the reason. A scan no confident edge reaches is never placed.
"""

from __future__ import annotations

import heapq
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.registration.api import DEFAULT_METHOD, as_cloud
from linereg.registration.features import FeatureOptions, feature_voxel, fpfh
from linereg.registration.many import register_many
from linereg.registration.pose_graph import information, optimise_graph

MODES = ("sequence", "unordered")
OVERLAP_POINTS = 1000
"""Most grid points of a scan :func:`predicted_overlap` moves."""
ODOMETRY, LOOP, CANDIDATE = "odometry", "loop closure", "candidate"


@dataclass(frozen=True)
class MultiwayOptions:
    """Settings of :func:`register_scans` (lengths in voxels of the scans' grid).

    Attributes:
        neighbours: sequence mode: each scan is registered to its next ``neighbours`` scans.
        loop_closures: sequence mode: most loop closures proposed per scan, spread over the earlier
            scans the poses so far predict to overlap it by ``min_overlap`` (the farthest first).
        min_overlap: the predicted overlap of a proposed loop closure.
        candidates: unordered mode: pairs registered per scan, best overlap estimate first; a scan
            left unreached gets its next ``candidates`` pairs once more.
        voxel: the grid of the information matrices, the graph and the merged cloud, in input units
            (``None``: the point spacing of ``grid_points`` FPS points of the first scan).
        grid_points: see ``voxel``.
        rank_points: the coarse grid of the overlap estimate holds about this many points per scan.
        rank_iterations: RANSAC iterations of the overlap estimate.
        correspondence_distance: inlier distance of the information matrices and the graph (Open3D's
            ``max_correspondence_distance``), in voxels.
        edge_prune_threshold: line-process weight below which the graph drops an uncertain edge.
        preference_loop_closure: weight of the uncertain edges against the odometry (Open3D's).
        polish: point-to-plane ICP of each placed scan against the others merged, after the graph.
    """

    neighbours: int = 1
    loop_closures: int = 2
    min_overlap: float = 0.3
    candidates: int = 3
    voxel: float | None = None
    grid_points: int = 30000
    rank_points: int = 1000
    rank_iterations: int = 2000
    correspondence_distance: float = 1.5
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 1.0
    polish: bool = False

    def __post_init__(self) -> None:
        for name in ("neighbours", "candidates", "grid_points", "rank_points", "rank_iterations"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.loop_closures < 0 or not 0 <= self.min_overlap <= 1:
            raise ValueError("loop_closures must be >= 0 and min_overlap in [0, 1]")
        if self.voxel is not None and not self.voxel > 0:
            raise ValueError(f"voxel must be > 0, got {self.voxel}")


@dataclass
class Edge:
    """One registered pair: ``transformation`` maps scan ``source`` into scan ``target``'s frame.

    Attributes:
        source, target: scan indices.
        transformation: ``(4, 4)`` source-to-target transform.
        fitness, inlier_rmse, confident, seconds, warnings: of :class:`~linereg.registration.api.RegistrationResult`.
        kind: ``"odometry"`` (sequence neighbours), ``"loop closure"`` or ``"candidate"`` (unordered).
        kept: confident and kept by the pose graph.
    """

    source: int
    target: int
    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    confident: bool
    seconds: float
    kind: str
    kept: bool = False
    warnings: tuple[str, ...] = ()

    @property
    def uncertain(self) -> bool:
        """Every edge but odometry may be wrong: the pose graph's line process may drop it."""
        return self.kind != ODOMETRY


@dataclass
class MultiwayResult:
    """The outcome of :func:`register_scans`.

    Attributes:
        names: each scan's name (a file's stem, else ``scan_<k>``).
        poses: per scan a ``(4, 4)`` transform into the first scan's frame, or ``None`` (not placed).
        placed: per scan, whether it was placed.
        verdicts: per scan, the edges that placed it or why it was left out.
        edges: every registered pair, in the order registered.
        merged: ``(M, 3)`` the placed scans in the first scan's frame, one point per voxel.
        voxel: the grid's voxel, in input units.
        seconds: wall-clock time of the whole run.
    """

    names: list[str]
    poses: list[np.ndarray | None]
    placed: list[bool]
    verdicts: list[str]
    edges: list[Edge]
    merged: np.ndarray
    voxel: float
    seconds: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


class Scans:
    """The scans, their voxel grids (Open3D clouds with normals) and the grids' indexes.

    Args:
        scans: files, arrays, tensors or Open3D clouds (what :func:`linereg.register` takes).
        options: :class:`MultiwayOptions` (``voxel``, ``grid_points``).
    """

    def __init__(self, scans: Sequence[Any], options: MultiwayOptions) -> None:
        if len(scans) < 2:
            raise ValueError(f"register_scans needs at least 2 scans, got {len(scans)}")
        self.clouds = [as_cloud(scan, f"scans[{k}]") for k, scan in enumerate(scans)]
        self.names = [_name(scan, k) for k, scan in enumerate(scans)]
        self.voxel = options.voxel or feature_voxel(self.clouds[0][0], options.grid_points)
        self.grids = [_grid(points, self.voxel) for points, _ in self.clouds]
        self.indexes = [NearestNeighbors(np.asarray(grid.points)) for grid in self.grids]

    def __len__(self) -> int:
        return len(self.clouds)

    def moved(self, k: int, transform: np.ndarray | None) -> np.ndarray:
        """``(N, 3)`` scan ``k``'s grid points moved by ``transform (4, 4)`` (as they are for ``None``)."""
        points = np.asarray(self.grids[k].points)
        return points if transform is None else points @ transform[:3, :3].T + transform[:3, 3]


def _name(scan: Any, index: int) -> str:
    """A file's stem, else ``scan_<index>``."""
    return Path(scan).stem if isinstance(scan, str | os.PathLike) else f"scan_{index}"


def _grid(points: np.ndarray, voxel: float):
    """``points (N, 3)`` on a ``voxel`` grid, as an Open3D cloud with normals."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel, max_nn=30))
    return cloud


def register_scans(
    scans: Sequence[Any],
    method: str | os.PathLike | Mapping[str, Any] = DEFAULT_METHOD,
    mode: str = "sequence",
    device: str | None = None,
    *,
    options: MultiwayOptions | None = None,
    registered: Mapping[tuple[int, int], Edge] | None = None,
    on_edge: Callable[[Edge], None] | None = None,
    progress: bool = True,
    **method_options: Any,
) -> MultiwayResult:
    """Place every scan in the first scan's frame (see the module docstring).

    Args:
        scans: two or more files, ``(N, 3)`` arrays, tensors or Open3D clouds.
        method, device, **method_options: as :func:`linereg.register` (``refine=True`` with a network).
        mode: ``"sequence"`` (scans in order, each near the next) or ``"unordered"``.
        options: :class:`MultiwayOptions`.
        registered: edges already registered, by ``(source, target)``: not registered again.
        on_edge: called with each edge as soon as it is registered (``registered`` ones excluded).
        progress: progress bars on stderr.

    Returns:
        A :class:`MultiwayResult`.

    Raises:
        ValueError: fewer than 2 scans, an unknown mode, or what :func:`linereg.register` raises.
    """
    began = time.perf_counter()
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    options = options or MultiwayOptions()
    scans = Scans(scans, options)
    settings = {"method": method, "device": device, "progress": progress, **method_options}
    register = _EdgeRegistration(scans, settings, dict(registered or {}), on_edge)
    edges = (_sequence_edges if mode == "sequence" else _unordered_edges)(scans, register, options)
    result = place(scans, edges, options)
    result.seconds = time.perf_counter() - began
    result.info = {"mode": mode, "registered": register.count, "resumed": register.resumed}
    return result


class _EdgeRegistration:
    """Registers requested pairs with :func:`linereg.register_many`, reusing ``registered`` ones."""

    def __init__(self, scans: Scans, settings: dict[str, Any], registered: dict, on_edge) -> None:
        self.scans, self.settings, self.registered, self.on_edge = scans, settings, registered, on_edge
        self.count = self.resumed = 0

    def __call__(self, requests: list[tuple[int, int, np.ndarray | None, str]]) -> list[Edge]:
        """Edges of ``(source, target, initial guess or None, kind)`` requests, in their order."""
        found = {}
        for source, target, _, kind in requests:
            if (source, target) in self.registered:
                found[source, target] = replace(self.registered[source, target], kind=kind, kept=False)
                self.resumed += 1
        todo = [request for request in requests if request[:2] not in found]
        pairs = [(self.scans.moved(source, init), self.scans.moved(target, None)) for source, target, init, _ in todo]
        for (source, target, init, kind), result in zip(todo, register_many(pairs, **self.settings), strict=True):
            transform = result.transformation if init is None else result.transformation @ init
            edge = Edge(
                source,
                target,
                transform,
                result.fitness,
                result.inlier_rmse,
                result.confident,
                result.seconds,
                kind,
                warnings=tuple(result.info.get("warnings", ())),
            )
            found[source, target] = edge
            self.count += 1
            if self.on_edge is not None:
                self.on_edge(edge)
        return [found[request[:2]] for request in requests]


def _sequence_edges(scans: Scans, register: _EdgeRegistration, options: MultiwayOptions) -> list[Edge]:
    """Odometry to the next ``neighbours`` scans, then the loop closures the odometry's poses predict."""
    from linereg.datasets.scan_folder import neighbour_pairs

    edges = register([(i, j, None, ODOMETRY) for i, j in neighbour_pairs(len(scans), options.neighbours)])
    poses = spanning_poses(len(scans), [edge for edge in edges if edge.confident])
    return edges + register(loop_closures(scans, poses, options))


def loop_closures(
    scans: Scans, poses: list[np.ndarray | None], options: MultiwayOptions
) -> list[tuple[int, int, np.ndarray, str]]:
    """Loop-closure requests ``(i, j, guess, kind)``: for each placed scan ``j``, the earlier placed
    scans ``i`` more than ``neighbours`` apart that ``poses`` predict to overlap it by ``min_overlap``
    (:func:`predicted_overlap`): ``loop_closures`` of them spread over the sequence, the farthest first."""
    centres = [np.asarray(grid.get_center()) for grid in scans.grids]
    radii = [np.linalg.norm(np.asarray(grid.get_max_bound()) - grid.get_min_bound()) / 2 for grid in scans.grids]
    requests = []
    for j, pose_j in enumerate(poses):
        eligible = []
        for i in range(j - options.neighbours if pose_j is not None else 0):
            if poses[i] is None:
                continue
            guess = np.linalg.inv(pose_j) @ poses[i]
            apart = np.linalg.norm(guess[:3, :3] @ centres[i] + guess[:3, 3] - centres[j])
            if apart <= radii[i] + radii[j] and predicted_overlap(scans, i, j, guess, options) >= options.min_overlap:
                eligible.append((i, j, guess, LOOP))
        if eligible and options.loop_closures:
            spread = np.linspace(0, len(eligible) - 1, min(options.loop_closures, len(eligible))).round()
            requests += [eligible[int(n)] for n in dict.fromkeys(spread)]
    return requests


def predicted_overlap(scans: Scans, source: int, target: int, guess: np.ndarray, options: MultiwayOptions) -> float:
    """Share of the source's grid within ``correspondence_distance`` voxels of the target's grid once moved by
    ``guess (4, 4)`` (at most :data:`OVERLAP_POINTS` of its points, evenly taken)."""
    points = np.asarray(scans.grids[source].points)
    points = points[:: max(1, len(points) // OVERLAP_POINTS)]
    radius = options.correspondence_distance * scans.voxel
    distances, _ = scans.indexes[target].query(points @ guess[:3, :3].T + guess[:3, 3], distance_upper_bound=radius)
    return float(np.mean(distances <= radius))


def _unordered_edges(scans: Scans, register: _EdgeRegistration, options: MultiwayOptions) -> list[Edge]:
    """Each scan's best ``candidates`` pairs by :func:`overlap_ranking`; the next ones for scans not reached."""
    ranking = overlap_ranking(scans, options)
    edges: list[Edge] = []
    for round_number in range(2):
        reached = spanning_poses(len(scans), [edge for edge in edges if edge.confident])
        waiting = [k for k in range(len(scans)) if reached[k] is None or round_number == 0]
        requests = _best_pairs(ranking, waiting, options.candidates, {(e.source, e.target) for e in edges})
        edges += register([(i, j, guess, CANDIDATE) for i, j, guess in requests])
    return edges


def _best_pairs(ranking, scans: list[int], count: int, done: set[tuple[int, int]]) -> list:
    """The best ``count`` pairs of ``ranking`` not in ``done`` for each of ``scans``, without repeats,
    in ranking order, as ``(i, j, guess)``."""
    taken: set[int] = set()
    for k in scans:
        mine = [n for n, (_, i, j, _) in enumerate(ranking) if k in (i, j) and (i, j) not in done]
        taken.update(mine[:count])
    return [ranking[n][1:] for n in sorted(taken)]


def overlap_ranking(scans: Scans, options: MultiwayOptions) -> list[tuple[float, int, int, np.ndarray]]:
    """Every pair ``(score, i, j, guess)``, best first: ``guess (4, 4)`` maps scan ``i`` onto scan ``j`` and
    ``score`` is its fitness, both from FPFH + RANSAC (``rank_iterations``) on a grid of about
    ``rank_points`` points per scan (the cheap overlap estimate)."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    voxel = feature_voxel(scans.clouds[0][0], options.rank_points)
    features = [fpfh(points, voxel, FeatureOptions()) for points, _ in scans.clouds]
    distance = FeatureOptions().distance * voxel
    checkers = [
        registration.CorrespondenceCheckerBasedOnEdgeLength(FeatureOptions().edge_similarity),
        registration.CorrespondenceCheckerBasedOnDistance(distance),
    ]
    ranking = []
    for i in range(len(scans)):
        for j in range(i + 1, len(scans)):
            o3d.utility.random.seed(0)
            found = registration.registration_ransac_based_on_feature_matching(
                features[i][0],
                features[j][0],
                features[i][1],
                features[j][1],
                True,
                distance,
                registration.TransformationEstimationPointToPoint(False),
                3,
                checkers,
                registration.RANSACConvergenceCriteria(options.rank_iterations, 0.999),
            )
            ranking.append((found.fitness, i, j, np.asarray(found.transformation)))
    return sorted(ranking, key=lambda entry: -entry[0])


def triangle_support(scans: Scans, edges: list[Edge], options: MultiwayOptions) -> list[int]:
    """Per edge, how many triangles of ``edges`` agree with it minus how many do not: the third scan's two
    edges compose to the same transform within twice the graph's inlier distance (:func:`displacement`)."""
    between = {}
    for edge in edges:
        between[edge.source, edge.target] = edge.transformation
        between[edge.target, edge.source] = np.linalg.inv(edge.transformation)
    around: dict[int, set[int]] = {}
    for source, target in between:
        around.setdefault(source, set()).add(target)
    limit = 2.0 * options.correspondence_distance * scans.voxel
    support = []
    for edge in edges:
        thirds = around[edge.source] & around[edge.target]
        votes = [
            displacement(scans, edge.source, edge.transformation, between[k, edge.target] @ between[edge.source, k])
            <= limit
            for k in thirds
        ]
        support.append(2 * sum(votes) - len(votes))
    return support


def displacement(scans: Scans, source: int, first: np.ndarray, second: np.ndarray) -> float:
    """RMS distance between scan ``source``'s grid moved by ``first`` and by ``second`` (both ``(4, 4)``)."""
    points = np.asarray(scans.grids[source].points)
    difference = first - second
    shift = points @ difference[:3, :3].T + difference[:3, 3]
    return float(np.sqrt(np.mean(np.sum(shift**2, axis=1))))


def spanning_poses(count: int, edges: list[Edge], rank: list[tuple] | None = None) -> list[np.ndarray | None]:
    """Per scan its ``(4, 4)`` pose in scan 0's frame along a spanning tree of ``edges`` grown from scan 0
    (odometry first, then the highest ``rank``, by default the fittest edge), or ``None`` where no edge
    reaches it."""
    rank = rank or [(edge.fitness,) for edge in edges]
    poses: list[np.ndarray | None] = [None] * count
    poses[0] = np.eye(4)
    touching: dict[int, list[int]] = {}
    for n, edge in enumerate(edges):
        touching.setdefault(edge.source, []).append(n)
        touching.setdefault(edge.target, []).append(n)
    heap = [(edges[n].uncertain, *(-value for value in rank[n]), n) for n in touching.get(0, [])]
    heapq.heapify(heap)
    while heap:
        edge = edges[heapq.heappop(heap)[-1]]
        if (poses[edge.source] is None) == (poses[edge.target] is None):
            continue
        if poses[edge.source] is None:
            poses[edge.source], new = poses[edge.target] @ edge.transformation, edge.source
        else:
            poses[edge.target], new = poses[edge.source] @ np.linalg.inv(edge.transformation), edge.target
        for n in touching[new]:
            heapq.heappush(heap, (edges[n].uncertain, *(-value for value in rank[n]), n))
    return poses


def place_scans(scans: Sequence[Any], edges: Sequence[Edge], options: MultiwayOptions | None = None) -> MultiwayResult:
    """The pose graph of :func:`register_scans` on given ``edges`` (e.g. a result's edges with more added).

    Args:
        scans: the scans the edges index (what :func:`register_scans` takes).
        edges: the registered pairs; the confident ones enter the graph.
        options: :class:`MultiwayOptions` (the grid, the graph's settings, ``polish``).
    """
    began = time.perf_counter()
    options = options or MultiwayOptions()
    result = place(Scans(scans, options), list(edges), options)
    result.seconds = time.perf_counter() - began
    return result


def place(scans: Scans, edges: list[Edge], options: MultiwayOptions) -> MultiwayResult:
    """Optimise the pose graph of the confident ``edges``, keep what it keeps and place what they reach."""
    confident = [edge for edge in edges if edge.confident]
    distance = options.correspondence_distance * scans.voxel
    informations = {
        id(edge): information(scans.grids[edge.source], scans.grids[edge.target], distance, edge.transformation)
        for edge in confident
    }
    support = triangle_support(scans, confident, options)
    rank = [(votes, informations[id(edge)][5, 5]) for edge, votes in zip(confident, support, strict=True)]
    initial = spanning_poses(len(scans), confident, rank)
    connected = [pose is not None for pose in initial]
    linked = [edge for edge in confident if initial[edge.source] is not None and initial[edge.target] is not None]
    for _ in range(2):
        optimised, survived = optimise_graph(initial, linked, informations, distance, options)
        kept = [edge for edge in survived if agrees(scans, edge, optimised, options)]
        if len(kept) == len(linked):
            break
        linked = kept
        initial = spanning_poses(len(scans), kept, [(informations[id(edge)][5, 5],) for edge in kept])
    kept_ids = {id(edge) for edge in kept}
    edges = [replace(edge, kept=id(edge) in kept_ids) for edge in edges]
    reached = spanning_poses(len(scans), [edge for edge in edges if edge.kept])
    poses = [optimised[k] if reached[k] is not None else None for k in range(len(scans))]
    if options.polish:
        poses = polish(scans, poses, options)
    return MultiwayResult(
        names=scans.names,
        poses=poses,
        placed=[pose is not None for pose in poses],
        verdicts=[_verdict(scans.names, k, edges, poses[k] is not None, connected[k]) for k in range(len(scans))],
        edges=edges,
        merged=merge(scans, poses),
        voxel=scans.voxel,
    )


def agrees(scans: Scans, edge: Edge, poses: list[np.ndarray], options: MultiwayOptions) -> bool:
    """Whether the optimised ``poses`` put the source's grid within ``correspondence_distance`` voxels (RMS) of
    where ``edge`` puts it: an edge the graph kept with too little information to matter does not."""
    relative = np.linalg.inv(poses[edge.target]) @ poses[edge.source]
    return (
        displacement(scans, edge.source, relative, edge.transformation) <= options.correspondence_distance * scans.voxel
    )


def _verdict(names: list[str], k: int, edges: list[Edge], placed: bool, connected: bool) -> str:
    """Scan ``k``'s verdict: the kept edges that placed it, or why it was left out (``connected``: confident
    edges connect it to the first scan)."""
    mine = [edge for edge in edges if k in (edge.source, edge.target)]

    def others(chosen: list[Edge]) -> str:
        return ", ".join(dict.fromkeys(names[edge.target if edge.source == k else edge.source] for edge in chosen))

    kept = [edge for edge in mine if edge.kept]
    if placed:
        return "first scan: the frame of the others" if k == 0 else f"placed by its edges to {others(kept)}"
    if not mine:
        return "left out: no pair with it was registered"
    confident = [edge for edge in mine if edge.confident]
    if not confident:
        return f"left out: no confident edge reaches it (registered against {others(mine)})"
    if not connected:
        return f"left out: its confident edges (to {others(confident)}) do not connect it to {names[0]}"
    if not kept:
        return f"left out: the pose graph dropped its confident edges (to {others(confident)}) as inconsistent"
    return f"left out: once the pose graph dropped edges, its kept ones (to {others(kept)}) no longer reach {names[0]}"


def polish(scans: Scans, poses: list[np.ndarray | None], options: MultiwayOptions) -> list[np.ndarray | None]:
    """Each placed scan but the first moved by point-to-plane ICP onto the other placed scans merged."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    distance = options.correspondence_distance * scans.voxel
    placed = [k for k, pose in enumerate(poses) if pose is not None]
    moved = {k: o3d.geometry.PointCloud(scans.grids[k]).transform(poses[k]) for k in placed}
    polished = list(poses)
    for k in placed[1:]:
        others = o3d.geometry.PointCloud()
        for other in placed:
            if other != k:
                others += moved[other]
        fitted = registration.registration_icp(
            scans.grids[k], others, distance, poses[k], registration.TransformationEstimationPointToPlane()
        )
        polished[k] = np.asarray(fitted.transformation)
    return polished


def merge(scans: Scans, poses: list[np.ndarray | None]) -> np.ndarray:
    """``(M, 3)`` the placed scans' grids in the first scan's frame, one point per voxel."""
    import open3d as o3d

    merged = o3d.geometry.PointCloud()
    for grid, pose in zip(scans.grids, poses, strict=True):
        if pose is not None:
            merged += o3d.geometry.PointCloud(grid).transform(pose)
    return np.asarray(merged.voxel_down_sample(scans.voxel).points)
