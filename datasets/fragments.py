"""Partial-overlap pairs of real rooms, fused from an RGB-D sequence the way 3DMatch builds fragments.

A *fragment* is a run of ``frames_per_fragment`` consecutive depth frames back-projected
(:func:`linereg.datasets.rgbd.depth_to_points`), moved by their camera poses into the camera
frame of the run's first frame and fused by Open3D voxel down-sampling (``voxel_size``, 1 cm by
default; 3DMatch fuses 50 frames with a TSDF). Fragments start every ``fragment_stride`` depth
frames. With camera-to-world poses ``T_a`` and ``T_b`` of the first frames of fragments
``a < b``, the pair *source = fragment b, target = fragment a* has ground truth
``T_a^-1 @ T_b`` (``p_target = gt @ p_source``, the 3DMatch ``gt.log`` convention). Only
fragments without a common frame are paired, so source and target are independent samplings of
the room.

Ground truth: the tracking poses of a sequence drift (7-Scenes' KinectFusion poses put two
fragments up to ~3 deg and ~15 cm apart from where their geometry aligns), so by default each
drawn pair's ground truth is the tracking pose refined by point-to-plane ICP on the *whole*
fragments (:func:`refine_pose`), as registration benchmarks built on drifting poses do (FCGF's
KITTI pairs, Choy et al., ICCV 2019). The refinement starts from the tracking pose only, never
from a method's estimate, and uses every fragment point, while the methods see 30 000 random
points. ``ground_truth="tracking"`` keeps the tracking pose (made exactly rigid). The refined
poses are cached beside the fragments.

Overlap (the 3DMatch / Predator convention): the share of source points that lie within
:data:`OVERLAP_RADIUS` (3.75 cm) of a target point once moved by the ground truth; for fragments it
is measured on ``overlap_points`` source points drawn at random (a standard error below 0.004 for
20 000 points). Pairs are drawn independently and uniformly from overlap bins (half-open
``[low, high)``, the last one closed), the requested count split evenly across the bins; each
cloud of a pair keeps 30 000 random points of its fragment by default (``dense_points``).

Building the fragments, their normals (local PCA oriented towards the first camera) and the
overlaps of every candidate pair takes about half a minute for the shared 7-Scenes sequence; the
result is cached in one ``.npz`` under ``cache_dir`` (default ``$XDG_CACHE_HOME/linereg`` or
``~/.cache/linereg``), named by a hash of the sequence and the fragment settings.
"""

from __future__ import annotations

import json
import os
import secrets
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch

from linereg.checks import nearest_rotation
from linereg.datasets.cache import settings_key
from linereg.datasets.formats import Intrinsics, read_depth_image
from linereg.datasets.rgbd import (
    DEFAULT_DEPTH_SCALE,
    Frame,
    _default_intrinsics,
    _detect_layout,
    _folder_frames,
    _seven_scenes_frames,
    _tum_frames,
    depth_to_points,
)
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.knn import NearestNeighbors
from linereg.metrics import rotation_error_deg
from linereg.pointcloud import estimate_normals, open3d_cloud
from linereg.structures import PairSample

OVERLAP_RADIUS = 0.0375
"""Distance (metres) within which a source point counts as overlapping (3DMatch, Predator)."""
DEFAULT_BINS = ((0.2, 0.3), (0.3, 0.5), (0.5, 0.8))
GROUND_TRUTHS = ("refined", "tracking")
REFINE_DISTANCES = (5.0, 3.0, 1.5)
"""Correspondence distances of the ground-truth refinement, in fusion voxels: the first two rounds
run on a grid of two voxels, the last one on every point."""
REFINE_ITERATIONS = 30
CACHE_VERSION = 1


@dataclass(frozen=True)
class FragmentSettings:
    """How fragments are fused from a sequence and how their overlaps are measured.

    Attributes:
        frames_per_fragment: consecutive depth frames fused into one fragment.
        fragment_stride: depth frames between the first frames of consecutive fragments.
        voxel_size: fusion voxel (metres); one point per occupied voxel.
        pixel_stride: back-project every ``pixel_stride``-th row and column of each depth image.
        max_depth: drop depths beyond this (metres); ``None`` keeps all.
        normal_k: neighbours of the normal estimate.
        overlap_radius: see :data:`OVERLAP_RADIUS` (metres).
        overlap_points: source points the overlap is measured on (``None``: all).
        frame_range: ``[first, stop)`` frame numbers the fragments are taken from (``None``: all).
    """

    frames_per_fragment: int = 20
    fragment_stride: int = 10
    voxel_size: float = 0.01
    pixel_stride: int = 2
    max_depth: float | None = None
    normal_k: int = 30
    overlap_radius: float = OVERLAP_RADIUS
    overlap_points: int | None = 20000
    frame_range: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        for name in ("frames_per_fragment", "fragment_stride", "pixel_stride", "normal_k"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("voxel_size", "overlap_radius", "max_depth", "overlap_points"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"{name} must be positive, got {value}")
        if self.frame_range is not None:
            first, stop = self.frame_range
            if first >= stop:
                raise ValueError(f"frame_range must be [first, stop) with first < stop, got {list(self.frame_range)}")
            object.__setattr__(self, "frame_range", (int(first), int(stop)))


@dataclass
class Fragments:
    """Fused fragments of one sequence and the overlaps of every frame-disjoint pair.

    Attributes:
        xyz: per fragment, ``(P_k, 3)`` float32 points in metres, camera frame of its first frame.
        normals: per fragment, ``(P_k, 3)`` float32 unit normals.
        frames: ``(K, 2)`` frame numbers of the first and last frame of each fragment.
        poses: ``(K, 4, 4)`` camera-to-world poses of the first frames.
        pairs: ``(C, 2)`` candidate pairs ``(target a, source b)``, ``a < b``, no common frame.
        overlaps: ``(C,)`` overlap of each candidate (source points near the target).
    """

    xyz: list[np.ndarray]
    normals: list[np.ndarray]
    frames: np.ndarray
    poses: np.ndarray
    pairs: np.ndarray
    overlaps: np.ndarray

    def ground_truth(self, target: int, source: int) -> np.ndarray:
        """``(4, 4)`` tracking pose of fragment ``source`` in fragment ``target``, exactly rigid.

        The stored poses are rigid to about 1e-5 only; the rotation is replaced by its nearest
        rotation.
        """
        relative = np.linalg.inv(self.poses[target]) @ self.poses[source]
        relative[:3, :3] = nearest_rotation(relative[:3, :3])
        relative[3] = [0.0, 0.0, 0.0, 1.0]
        return relative


def sequence_frames(root: Path) -> tuple[list[Frame], Intrinsics, float]:
    """Posed depth frames of an RGB-D sequence folder (any layout of :mod:`linereg.datasets.rgbd`).

    Returns:
        ``(frames, intrinsics, depth_scale)``; frames in file order.

    Raises:
        ValueError: a frame has no camera pose.
    """
    layout = _detect_layout(root)
    readers = {"7scenes": _seven_scenes_frames, "tum": _tum_frames, "folder": _folder_frames}
    frames = readers[layout](root, True)
    unposed = [frame.depth.name for frame in frames if frame.pose is None]
    if unposed:
        raise ValueError(f"{root}: fragments need camera poses; {len(unposed)} frames have none (e.g. {unposed[0]})")
    return frames, _default_intrinsics(root, layout), DEFAULT_DEPTH_SCALE[layout]


def fuse_fragment(
    frames: Sequence[Frame],
    intrinsics: Intrinsics,
    *,
    depth_scale: float,
    voxel_size: float,
    pixel_stride: int = 1,
    max_depth: float | None = None,
) -> np.ndarray:
    """Depth frames fused into one cloud in the camera frame of ``frames[0]``.

    Args:
        frames: posed frames (camera-to-world ``pose``).
        intrinsics: pinhole intrinsics of the depth images.
        depth_scale: raw depth units per metre.
        voxel_size: Open3D voxel down-sampling size (metres).
        pixel_stride: back-project every ``pixel_stride``-th row and column.
        max_depth: drop depths beyond this (metres).

    Returns:
        ``(P, 3)`` float64 points in metres.
    """
    world_to_first = np.linalg.inv(frames[0].pose)
    clouds = []
    for frame in frames:
        camera = depth_to_points(
            read_depth_image(frame.depth),
            intrinsics,
            depth_scale=depth_scale,
            pixel_stride=pixel_stride,
            max_depth=max_depth,
        )
        to_first = world_to_first @ frame.pose
        clouds.append(camera @ to_first[:3, :3].T + to_first[:3, 3])
    return np.asarray(open3d_cloud(np.concatenate(clouds)).voxel_down_sample(voxel_size).points)


def refine_pose(
    source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, pose: np.ndarray, voxel_size: float
) -> np.ndarray:
    """A source-to-target pose refined by Open3D point-to-plane ICP, coarse to fine.

    Rounds of :data:`REFINE_ITERATIONS` iterations at the correspondence distances
    :data:`REFINE_DISTANCES` (in ``voxel_size``); all but the last run on a grid of two voxels.

    Args:
        source: ``(N, 3)`` source points.
        target: ``(M, 3)`` target points.
        target_normals: ``(M, 3)`` target unit normals.
        pose: ``(4, 4)`` starting source-to-target transform.
        voxel_size: the clouds' sampling voxel (metres).

    Returns:
        ``(4, 4)`` float64 refined transform.
    """
    import open3d as o3d

    registration = o3d.pipelines.registration
    fine = open3d_cloud(source), open3d_cloud(target, target_normals)
    coarse = tuple(cloud.voxel_down_sample(2.0 * voxel_size) for cloud in fine)
    refined = np.asarray(pose, dtype=np.float64)
    for round_number, distance in enumerate(REFINE_DISTANCES):
        clouds = fine if round_number == len(REFINE_DISTANCES) - 1 else coarse
        refined = registration.registration_icp(
            *clouds,
            distance * voxel_size,
            refined,
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=REFINE_ITERATIONS),
        ).transformation
    return np.array(refined)


def _overlap_with_index(index: NearestNeighbors, source: np.ndarray, transform: np.ndarray, radius: float) -> float:
    """Share of ``source (N, 3)`` points within ``radius`` of the indexed points after ``transform``."""
    moved = np.asarray(source, dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
    distances, _ = index.query(moved, distance_upper_bound=radius)
    return float(np.mean(distances <= radius))


def overlap_ratio(
    source: np.ndarray,
    target: np.ndarray,
    transform: np.ndarray,
    *,
    radius: float = OVERLAP_RADIUS,
    max_points: int | None = None,
    seed: int = 0,
) -> float:
    """Share of source points with a target point within ``radius`` once moved by ``transform``.

    Args:
        source: ``(N, 3)`` source points.
        target: ``(M, 3)`` target points, same units.
        transform: ``(4, 4)`` source-to-target transform.
        radius: neighbourhood radius (3.75 cm for metric 3DMatch-like scans).
        max_points: measure on this many source points drawn at random (``None``: all).
        seed: seed of that draw.

    Returns:
        The overlap in ``[0, 1]``.
    """
    source = np.asarray(source, dtype=np.float64)
    if max_points is not None and len(source) > max_points:
        source = source[np.random.default_rng(seed).choice(len(source), max_points, replace=False)]
    return _overlap_with_index(
        NearestNeighbors(np.asarray(target, dtype=np.float64)), source, np.asarray(transform), radius
    )


def build_fragments(root: Path, settings: FragmentSettings) -> Fragments:
    """Fuse the fragments of a sequence, estimate their normals and measure every candidate overlap."""
    frames, intrinsics, depth_scale = sequence_frames(root)
    if settings.frame_range is not None:
        first, stop = settings.frame_range
        frames = [frame for frame in frames if first <= frame.number < stop]
    length = settings.frames_per_fragment
    starts = list(range(0, len(frames) - length + 1, settings.fragment_stride))
    if len(starts) < 2:
        raise ValueError(f"{root}: {len(frames)} posed depth frames hold fewer than two fragments of {length} frames")
    xyz, normals = [], []
    for start in starts:
        points = fuse_fragment(
            frames[start : start + length],
            intrinsics,
            depth_scale=depth_scale,
            voxel_size=settings.voxel_size,
            pixel_stride=settings.pixel_stride,
            max_depth=settings.max_depth,
        )
        xyz.append(points.astype(np.float32))
        normals.append(estimate_normals(points, k=min(settings.normal_k, len(points) - 1), orient_towards=np.zeros(3)))
    poses = np.stack([frames[s].pose for s in starts])
    pairs = [(a, b) for b in range(len(starts)) for a in range(b) if starts[b] - starts[a] >= length]
    indexes = [NearestNeighbors(points) for points in xyz]
    overlaps = []
    for a, b in pairs:
        source = xyz[b]
        if settings.overlap_points is not None and len(source) > settings.overlap_points:
            source = source[np.random.default_rng([a, b]).choice(len(source), settings.overlap_points, replace=False)]
        gt = np.linalg.inv(poses[a]) @ poses[b]
        overlaps.append(_overlap_with_index(indexes[a], source, gt, settings.overlap_radius))
    return Fragments(
        xyz=xyz,
        normals=normals,
        frames=np.array([[frames[s].number, frames[s + length - 1].number] for s in starts], dtype=np.int64),
        poses=poses,
        pairs=np.array(pairs, dtype=np.int64).reshape(-1, 2),
        overlaps=np.array(overlaps, dtype=np.float64),
    )


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/linereg``, else ``~/.cache/linereg``."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser() / "linereg"


def _write_atomically(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Call ``write`` on a temporary file beside ``path``, then move it to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(temporary, "wb") as handle:
            write(handle)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def _save(fragments: Fragments, path: Path, settings: dict[str, Any]) -> None:
    """Write ``fragments`` to ``path`` (``.npz``) atomically."""
    _write_atomically(
        path,
        lambda handle: np.savez(
            handle,
            xyz=np.concatenate(fragments.xyz),
            normals=np.concatenate(fragments.normals).astype(np.float32),
            offsets=np.cumsum([0] + [len(points) for points in fragments.xyz]),
            frames=fragments.frames,
            poses=fragments.poses,
            pairs=fragments.pairs,
            overlaps=fragments.overlaps,
            settings=np.array(json.dumps(settings, sort_keys=True)),
        ),
    )


def _load(path: Path) -> Fragments:
    """Fragments written by :func:`_save`."""
    with np.load(path) as stored:
        arrays = {name: stored[name] for name in ("xyz", "normals", "offsets", "frames", "poses", "pairs", "overlaps")}
    offsets = arrays.pop("offsets")
    return Fragments(
        **{name: np.split(arrays.pop(name), offsets[1:-1]) for name in ("xyz", "normals")},
        **arrays,
    )


def _cache_description(root: Path, settings: FragmentSettings) -> dict[str, Any]:
    """What the fragment cache of ``root`` and ``settings`` is named by and stores."""
    return {
        "version": CACHE_VERSION,
        "root": str(root),
        "depth_images": len(sequence_frames(root)[0]),
        **asdict(settings),
    }


def fragment_cache_path(root: Path, settings: FragmentSettings, cache_dir: str | Path | None = None) -> Path:
    """The ``.npz`` that caches the fragments of ``root`` built with ``settings``."""
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    return folder / f"fragments-{settings_key(_cache_description(root, settings))}.npz"


def refined_cache_path(root: Path, settings: FragmentSettings, cache_dir: str | Path | None = None) -> Path:
    """The JSON that caches the refined ground truths (:func:`refined_ground_truths`) beside the fragments."""
    path = fragment_cache_path(root, settings, cache_dir)
    return path.with_name(f"{path.stem}-refined.json")


def cached_fragments(root: Path, settings: FragmentSettings, cache_dir: str | Path | None = None) -> Fragments:
    """:func:`build_fragments`, read from ``cache_dir`` when built before with the same settings."""
    path = fragment_cache_path(root, settings, cache_dir)
    if path.is_file():
        try:
            return _load(path)
        except (OSError, KeyError, ValueError) as error:
            warnings.warn(f"rebuilding the unreadable fragment cache {path}: {error}", stacklevel=2)
    fragments = build_fragments(root, settings)
    _save(fragments, path, _cache_description(root, settings))
    return fragments


def refined_ground_truths(
    fragments: Fragments, pairs: Sequence[tuple[int, int]], settings: FragmentSettings, path: Path
) -> dict[tuple[int, int], np.ndarray]:
    """:func:`refine_pose` of the tracking pose of each ``(target, source)`` pair, cached in ``path``.

    ``path`` is a JSON object ``{"<target>-<source>": 4x4 list}``, rewritten atomically after each
    new pair, so an interrupted run keeps what it refined.
    """
    cached = {}
    if path.is_file():
        try:
            cached = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            warnings.warn(f"refining again: the unreadable ground-truth cache {path}: {error}", stacklevel=2)
    refined = {}
    for target, source in pairs:
        key = f"{target}-{source}"
        if key not in cached:
            cached[key] = refine_pose(
                fragments.xyz[source],
                fragments.xyz[target],
                fragments.normals[target],
                fragments.ground_truth(target, source),
                settings.voxel_size,
            ).tolist()
            _write_atomically(path, lambda handle: handle.write(json.dumps(cached, sort_keys=True).encode()))
        refined[(target, source)] = np.array(cached[key], dtype=np.float64)
    return refined


def bin_index(value: float, bins: Sequence[Sequence[float]]) -> int | None:
    """Index of the bin ``[low, high)`` holding ``value`` (the last bin is closed), or ``None``."""
    for index, (low, high) in enumerate(bins):
        if low <= value < high or (index == len(bins) - 1 and value == high):
            return index
    return None


def bin_label(low: float, high: float, last: bool) -> str:
    """``"[0.2, 0.3)"``, or ``"[0.5, 0.8]"`` for the last bin."""
    return f"[{low:g}, {high:g}{']' if last else ')'}"


def draw_pairs(overlaps: np.ndarray, bins: Sequence[Sequence[float]], pairs: int, seed: int) -> list[tuple[int, int]]:
    """Candidates drawn uniformly without replacement from each overlap bin.

    Args:
        overlaps: ``(C,)`` overlap of every candidate.
        bins: ``[[low, high], ...]``.
        pairs: total count, split evenly (the first bins get the remainder).
        seed: seed of the draws.

    Returns:
        ``(candidate, bin)`` indices, bin by bin, candidates in increasing order within a bin.
        A bin with fewer candidates than its share gives all it has (with a warning).
    """
    if pairs < 1 or not bins:
        raise ValueError(f"need pairs >= 1 and at least one bin, got {pairs} and {list(bins)}")
    for low, high in bins:
        if not 0.0 <= low < high <= 1.0:
            raise ValueError(f"overlap bin [{low}, {high}]: expected 0 <= low < high <= 1")
    membership = np.array([-1 if (b := bin_index(value, bins)) is None else b for value in overlaps])
    rng = np.random.default_rng(seed)
    chosen = []
    for index, (low, high) in enumerate(bins):
        share = pairs // len(bins) + (index < pairs % len(bins))
        members = np.flatnonzero(membership == index)
        if len(members) < share:
            warnings.warn(
                f"overlap bin {bin_label(low, high, index == len(bins) - 1)} holds {len(members)} candidate "
                f"pairs, fewer than the {share} asked for",
                stacklevel=2,
            )
        drawn = np.sort(rng.choice(members, min(share, len(members)), replace=False))
        chosen += [(int(candidate), index) for candidate in drawn]
    return chosen


def fragment_pairs(
    root: str | Path,
    *,
    pairs: int = 48,
    seed: int = 0,
    bins: Sequence[Sequence[float]] = DEFAULT_BINS,
    dense_points: int | None = 30000,
    num_points: int | None = None,
    cache_dir: str | Path | None = None,
    settings: FragmentSettings | None = None,
    ground_truth: str = "refined",
) -> list[PairSample]:
    """Fragment pairs of a sequence drawn from overlap bins (module docstring).

    Args:
        root: a posed RGB-D sequence folder (e.g. 7-Scenes ``frame-XXXXXX.depth.png`` + ``.pose.txt``).
        pairs: number of pairs, split evenly across ``bins``.
        seed: seed of the draw and of each pair's random cap.
        bins: overlap bins ``[[low, high], ...]``.
        dense_points: random cap of each cloud (``None``: the whole fragment, ~200k points at
            1 cm; the classical baselines do not subsample, and FGR takes minutes per pair at 60k).
        num_points: FPS size of each cloud after the cap (``None``: keep them all).
        cache_dir: fragment cache folder (``None``: :func:`default_cache_dir`).
        settings: fragment settings (``None``: :class:`FragmentSettings` defaults).
        ground_truth: ``"refined"`` (the tracking pose refined on the whole fragments,
            :func:`refine_pose`) or ``"tracking"`` (module docstring).

    Returns:
        Pairs in metres, bin by bin, with ``meta``: ``source`` (``"fragments"``), ``scene``,
        ``overlap`` (of the whole fragments), ``overlap_bin``, ``src_fragment`` / ``tgt_fragment``
        (indices), ``src_frames`` / ``tgt_frames`` (first and last frame numbers),
        ``ground_truth`` and ``gt_correction_deg`` / ``gt_correction_m`` (how far the ground truth
        lies from the tracking pose; 0 for ``"tracking"``). Overlaps and bins are those of the
        tracking pose.
    """
    if ground_truth not in GROUND_TRUTHS:
        raise ValueError(f"ground_truth must be one of {GROUND_TRUTHS}, got {ground_truth!r}")
    root = Path(root).expanduser().resolve()
    settings = settings or FragmentSettings()
    fragments = cached_fragments(root, settings, cache_dir)
    scan = ScanSettings(num_points=num_points, dense_points=dense_points, half_extent=None)
    drawn = draw_pairs(fragments.overlaps, bins, pairs, seed)
    ends = [tuple(int(v) for v in fragments.pairs[candidate]) for candidate, _ in drawn]
    if ground_truth == "refined":
        truths = refined_ground_truths(fragments, ends, settings, refined_cache_path(root, settings, cache_dir))
    else:
        truths = {end: fragments.ground_truth(*end) for end in ends}
    found = []
    for index, ((candidate, bin_number), (target, source)) in enumerate(zip(drawn, ends, strict=True)):
        tracking, truth = fragments.ground_truth(target, source), truths[(target, source)]
        meta = {
            "dataset": "fragments",
            "source": "fragments",
            "scene": f"{root.parent.name}/{root.name}",
            "index": index,
            "overlap": float(fragments.overlaps[candidate]),
            "overlap_bin": bin_label(*bins[bin_number], bin_number == len(bins) - 1),
            "src_fragment": source,
            "tgt_fragment": target,
            "src_frames": fragments.frames[source].tolist(),
            "tgt_frames": fragments.frames[target].tolist(),
            "ground_truth": ground_truth,
            "gt_correction_deg": float(rotation_error_deg(*(torch.from_numpy(t[:3, :3]) for t in (truth, tracking)))),
            "gt_correction_m": float(np.linalg.norm(truth[:3, 3] - tracking[:3, 3])),
        }
        found.append(
            finish_scan_pair(
                fragments.xyz[source],
                fragments.xyz[target],
                truth,
                scan,
                np.random.default_rng([seed, index]),
                src_normals=fragments.normals[source],
                tgt_normals=fragments.normals[target],
                meta=meta,
            )
        )
    return found
