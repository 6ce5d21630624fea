"""Partial view against the whole shape: the pair a new user registers first.

For every pair ``i`` of a folder of shapes (meshes or point files), shape ``i mod S``:

1. A dense cloud of the whole shape: the file's points (point files), or ``dense_points``
   points sampled uniformly on the surface (meshes, seeded).
2. Source: the points visible from a camera at ``camera_distance`` bounding radii in a random
   direction (hidden-point removal), ``source_points`` of them drawn at random.
3. Target: ``target_points`` points drawn at random from the whole dense cloud (independent of
   the source's draw).
4. Both scaled together into ``[-half_extent, half_extent]^3``, then the target moved by the
   paper's composite transform (Euler angles U[0, ``max_angle_deg``], translation
   U[-``max_translation``, ``max_translation``]^3); ``gt_transform`` maps source to target.

Every pair is a pure function of the shape, ``seed`` and ``i`` (``numpy.random.default_rng([seed, i])``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from linereg.io import MESH_SUFFIXES, POINT_CLOUD_SUFFIXES, read_mesh, read_point_cloud
from linereg.pointcloud import bounding_sphere, fit_into_cube, hidden_point_removal
from linereg.random_poses import random_transform_paper
from linereg.se3 import transform_points
from linereg.structures import PairSample

MIN_VISIBLE_FRACTION = 0.5
"""A view must show at least this fraction of ``source_points``; other cameras are tried."""
CAMERA_TRIES = 20


@dataclass(frozen=True)
class PartialVsWholeSettings:
    """Sizes and pose range of :func:`partial_vs_whole_pair` (module docstring)."""

    source_points: int = 1024
    target_points: int = 2048
    dense_points: int = 20000
    camera_distance: float = 2.5
    half_extent: float = 1.0
    max_angle_deg: float = 45.0
    max_translation: float = 0.2

    def __post_init__(self) -> None:
        for name in ("source_points", "target_points", "dense_points"):
            if getattr(self, name) < 4:
                raise ValueError(f"{name} must be >= 4, got {getattr(self, name)}")
        if self.camera_distance <= 1.0:
            raise ValueError(f"camera_distance must exceed 1 bounding radius, got {self.camera_distance}")
        if self.half_extent <= 0:
            raise ValueError(f"half_extent must be positive, got {self.half_extent}")


def shape_files(root: str | Path, patterns: Sequence[str] | None = None) -> list[Path]:
    """Mesh and point files under ``root`` (recursive, sorted); ``patterns`` filter by glob.

    Raises:
        FileNotFoundError: ``root`` is not a folder, or holds no shape file.
    """
    folder = Path(root).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder of shapes")
    suffixes = set(MESH_SUFFIXES) | set(POINT_CLOUD_SUFFIXES)
    globs = list(patterns) if patterns else ["**/*"]
    found = sorted({p for pattern in globs for p in folder.glob(pattern) if p.is_file()})
    files = [p for p in found if p.suffix.lower() in suffixes]
    if not files:
        raise FileNotFoundError(f"{folder}: no mesh or point file matching {globs}")
    return files


def dense_cloud(path: str | Path, count: int, seed: int = 0) -> np.ndarray:
    """``(P, 3)`` float64 points of a shape file: ``count`` points sampled uniformly on a
    mesh's surface (seeded), or a point file's points (a PLY/OBJ without faces is one)."""
    path = Path(path)
    if path.suffix.lower() in MESH_SUFFIXES:
        try:
            mesh = read_mesh(path)
        except ValueError as error:
            if "no faces" not in str(error):
                raise
        else:
            import trimesh

            points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
            return np.asarray(points, dtype=np.float64)
    return read_point_cloud(path, min_points=4).xyz.astype(np.float64)


def partial_vs_whole_pair(
    whole: np.ndarray, rng: np.random.Generator, settings: PartialVsWholeSettings = PartialVsWholeSettings()
) -> PairSample:
    """One labelled pair from the dense cloud ``whole (P, 3)`` of a shape (module docstring).

    Raises:
        ValueError: no camera of ``CAMERA_TRIES`` sees enough points.
    """
    if len(whole) < settings.target_points:
        raise ValueError(f"the shape has {len(whole)} points, fewer than target_points={settings.target_points}")
    center, radius = bounding_sphere(torch.from_numpy(whole))
    for _ in range(CAMERA_TRIES):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        camera = center.numpy() + settings.camera_distance * float(radius) * direction
        visible = hidden_point_removal(whole, camera)
        if len(visible) >= MIN_VISIBLE_FRACTION * settings.source_points:
            break
    else:
        raise ValueError(
            f"no camera of {CAMERA_TRIES} sees {MIN_VISIBLE_FRACTION:.0%} of {settings.source_points} points"
        )
    source = whole[rng.choice(visible, settings.source_points, replace=len(visible) < settings.source_points)]
    target = whole[rng.choice(len(whole), settings.target_points, replace=False)]
    (source, target), _, _ = fit_into_cube(source, target, half_extent=settings.half_extent)
    pose = random_transform_paper(
        1, rng, max_angle_deg=settings.max_angle_deg, max_translation=settings.max_translation, dtype=torch.float64
    )[0]
    target = transform_points(pose, torch.from_numpy(target)).numpy()
    return PairSample(
        src_xyz=np.ascontiguousarray(source, dtype=np.float32),
        tgt_xyz=np.ascontiguousarray(target, dtype=np.float32),
        gt_transform=pose.numpy().astype(np.float32),
        meta={"camera": camera.tolist(), "visible": len(visible)},
    )


def partial_vs_whole_pairs(
    root: str | Path,
    *,
    pairs: int = 40,
    seed: int = 0,
    patterns: Sequence[str] | None = None,
    settings: PartialVsWholeSettings = PartialVsWholeSettings(),
) -> list[PairSample]:
    """``pairs`` pairs of the shapes under ``root``: pair ``i`` from shape ``i mod S``.

    Args:
        root: folder of meshes (OFF/OBJ/PLY/STL) or point files (any format of
            :func:`linereg.io.read_point_cloud`).
        pairs: number of pairs (>= 1).
        seed: seed of every draw.
        patterns: glob patterns under ``root`` (default: every file).
        settings: sizes and pose range.

    Returns:
        Labelled :class:`PairSample` list; ``meta`` names the file and the pair index.
    """
    if pairs < 1:
        raise ValueError(f"pairs must be >= 1, got {pairs}")
    files = shape_files(root, patterns)
    clouds: dict[int, np.ndarray] = {}
    out = []
    for index in range(pairs):
        shape = index % len(files)
        if shape not in clouds:
            clouds[shape] = dense_cloud(files[shape], settings.dense_points, seed=seed)
        try:
            pair = partial_vs_whole_pair(clouds[shape], np.random.default_rng([seed, index]), settings)
        except ValueError as error:
            raise ValueError(f"{files[shape]}: pair {index}: {error}") from error
        pair.meta.update({"dataset": "partial_vs_whole", "file": str(files[shape]), "index": index})
        out.append(pair)
    return out
