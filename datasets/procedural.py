"""The embedded default data: random asymmetric unions of primitives (no download needed).

Each shape glues 3-6 primitives (boxes, ellipsoids, cylinders, cones, tori, capsules) of
random size and orientation, every new part centred on the surface of an earlier one, so the
union is connected and, with probability one, has no rotational symmetry: registration is
well posed. Shapes are plain ``trimesh`` meshes, so they go through the same ray-casting
partial-view path as real meshes (:mod:`linereg.datasets.protocol`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
import trimesh

from linereg.datasets.base import DATASETS, item_rng
from linereg.datasets.protocol import Shape, build_protocol
from linereg.datasets.shape_pairs import ShapePairDataset
from linereg.random_poses import random_rotation

PRIMITIVE_KINDS = ("box", "ellipsoid", "cylinder", "cone", "torus", "capsule")
SPLIT_STREAMS = {"train": 0, "val": 1, "test": 2}
_SHAPE_STREAM = 7


def _child_seed(rng: np.random.Generator) -> int:
    """An integer seed drawn from ``rng`` (for libraries that take a seed, not a Generator)."""
    return int(rng.integers(2**31))


def random_primitive(kind: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """One primitive of random proportions centred at the origin (sizes in ``[0.15, 0.7]``).

    Args:
        kind: one of :data:`PRIMITIVE_KINDS`.
        rng: random generator.

    Returns:
        A watertight triangle mesh.
    """
    size = rng.uniform(0.15, 0.7, size=3)
    if kind == "box":
        return trimesh.creation.box(extents=size)
    if kind == "ellipsoid":
        sphere = trimesh.creation.icosphere(subdivisions=3)
        sphere.apply_scale(size / 2)
        return sphere
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=size[0] / 2, height=size[1] * 1.5, sections=48)
    if kind == "cone":
        return trimesh.creation.cone(radius=size[0] / 2, height=size[1] * 1.5, sections=48)
    if kind == "torus":
        major = size[0] / 2 + 0.05
        return trimesh.creation.torus(
            major_radius=major, minor_radius=major * rng.uniform(0.15, 0.4), major_sections=48
        )
    if kind == "capsule":
        return trimesh.creation.capsule(height=size[1] * 1.5, radius=size[0] / 3, count=[24, 24])
    raise ValueError(f"unknown primitive kind {kind!r}; choose from {PRIMITIVE_KINDS}")


def procedural_shape(rng: np.random.Generator, *, min_parts: int = 3, max_parts: int = 6) -> trimesh.Trimesh:
    """A random connected union of primitives, centred and scaled into the unit sphere.

    Args:
        rng: random generator (the shape is a pure function of its state).
        min_parts: fewest primitives, ``>= 2``.
        max_parts: most primitives, ``>= min_parts``.

    Returns:
        A triangle mesh (parts overlap; they are concatenated, not merged by booleans).
    """
    if not 2 <= min_parts <= max_parts:
        raise ValueError(f"need 2 <= min_parts <= max_parts, got {min_parts} and {max_parts}")
    num_parts = int(rng.integers(min_parts, max_parts + 1))
    parts: list[trimesh.Trimesh] = []
    for _ in range(num_parts):
        part = random_primitive(PRIMITIVE_KINDS[rng.integers(len(PRIMITIVE_KINDS))], rng)
        pose = np.eye(4)
        pose[:3, :3] = random_rotation(1, rng, dtype=torch.float64)[0].numpy()
        if parts:
            anchor = parts[rng.integers(len(parts))]
            surface_points, _ = trimesh.sample.sample_surface(anchor, 1, seed=_child_seed(rng))
            pose[:3, 3] = surface_points[0]
        part.apply_transform(pose)
        parts.append(part)
    shape = trimesh.util.concatenate(parts)
    center = (shape.bounds[0] + shape.bounds[1]) / 2
    shape.apply_translation(-center)
    shape.apply_scale(1.0 / np.linalg.norm(shape.vertices, axis=1).max())
    return shape


class ProceduralShapes:
    """A deterministic collection of procedural shapes (a shape source for pair datasets).

    Args:
        num_shapes: number of shapes.
        split: ``"train"``, ``"val"`` or ``"test"``; splits draw disjoint random streams.
        seed: base seed.
        min_parts: fewest primitives per shape.
        max_parts: most primitives per shape.
    """

    def __init__(
        self,
        num_shapes: int,
        *,
        split: str = "train",
        seed: int = 0,
        min_parts: int = 3,
        max_parts: int = 6,
    ) -> None:
        if split not in SPLIT_STREAMS:
            raise ValueError(f"split must be one of {sorted(SPLIT_STREAMS)}, got {split!r}")
        if num_shapes < 1:
            raise ValueError(f"num_shapes must be >= 1, got {num_shapes}")
        if not 2 <= min_parts <= max_parts:
            raise ValueError(f"need 2 <= min_parts <= max_parts, got {min_parts} and {max_parts}")
        self.num_shapes = num_shapes
        self.split = split
        self.seed = seed
        self.min_parts = min_parts
        self.max_parts = max_parts

    def __len__(self) -> int:
        return self.num_shapes

    def load(self, index: int) -> Shape:
        """Shape ``index`` as a mesh."""
        rng = item_rng(self.seed, _SHAPE_STREAM, SPLIT_STREAMS[self.split], index)
        mesh = procedural_shape(rng, min_parts=self.min_parts, max_parts=self.max_parts)
        return Shape(name=f"procedural_{self.split}_{index:05d}", mesh=mesh)

    def describe(self) -> dict[str, Any]:
        """Settings that determine the shapes (for cache keys and manifests)."""
        return {
            "source": "procedural",
            "num_shapes": self.num_shapes,
            "split": self.split,
            "seed": self.seed,
            "min_parts": self.min_parts,
            "max_parts": self.max_parts,
        }


DEFAULT_NUM_SHAPES = {"train": 100, "val": 20, "test": 20}


@DATASETS.register("procedural")
def build_procedural(
    *,
    split: str = "train",
    num_shapes: int | None = None,
    protocol: str | Mapping[str, Any] = "airplane",
    seed: int = 0,
    min_parts: int = 3,
    max_parts: int = 6,
) -> ShapePairDataset:
    """Pairs from procedural shapes (the default dataset: no files needed).

    Args:
        split: ``"train"``, ``"val"`` or ``"test"`` (disjoint shapes).
        num_shapes: shapes in the split (default 100 train, 20 val/test).
        protocol: pair protocol preset or mapping (see :func:`linereg.datasets.protocol.build_protocol`).
        seed: base seed of shapes and pairs.
        min_parts: fewest primitives per shape.
        max_parts: most primitives per shape.
    """
    if split not in DEFAULT_NUM_SHAPES:
        raise ValueError(f"split must be one of {sorted(DEFAULT_NUM_SHAPES)}, got {split!r}")
    shapes = ProceduralShapes(
        DEFAULT_NUM_SHAPES[split] if num_shapes is None else num_shapes,
        split=split,
        seed=seed,
        min_parts=min_parts,
        max_parts=max_parts,
    )
    return ShapePairDataset(shapes, build_protocol(protocol), seed=seed, name="procedural")
