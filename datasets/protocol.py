"""Pair generation from complete shapes: the paper's RGB-D-like protocol and RPM-Net's crop.

Paper protocol (§4.1), :class:`ViewProtocol`:

1. A virtual camera orbits the shape about ``view_axis`` and stops at ``num_views`` regularly
   spaced positions (50 for Human, 18 for Airplane), looking at the shape's centre from
   ``camera_distance`` bounding-sphere radii, ``elevation_deg`` above the orbit plane.
   The visible part from stop ``i`` is the source: ray casting (Open3D ``RaycastingScene``,
   a pinhole camera whose field of view just holds the bounding sphere) for meshes, hidden
   point removal for point clouds.
2. Target: ``"view"`` (Airplane) = the visible part after rotating the camera about the shape
   centre by an angle U[-75, 75] deg about a random axis; ``"whole"`` (Human) = the whole
   outer surface (meshes: union of ray casts from 26 directions; clouds: the cloud).
3. Normals (``"estimate"``: local PCA oriented towards the camera, as the paper's PCL step;
   ``"surface"``: the mesh's own normals), FPS to ``num_points`` (1024).
4. The pair is scaled jointly into ``[-half_extent, half_extent]^3`` and the target is moved by
   a random composite transform (Euler angles U[0, 45] deg, translation U[-0.2, 0.2]^3, as DCP);
   ``gt_transform`` is that transform (source -> target).

RPM-Net crop protocol (RPM-Net's repository, src/data_loader/transforms.py), :class:`CropProtocol`:
independent 70% half-space crops of one complete cloud, source perturbed (Euler U[0, 45] deg,
t U[-0.5, 0.5]^3), resampling to 717 points, clipped Gaussian jitter.

Everything is a pure function of the shape, the view index and the generator passed in.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
import torch
import trimesh

from linereg.pointcloud import (
    bounding_sphere,
    estimate_normals,
    farthest_point_sampling,
    fit_into_cube,
    hidden_point_removal,
    resample_indices,
)
from linereg.random_poses import (
    random_axis_angle_rotation,
    random_transform_paper,
    random_transform_rpmnet,
)
from linereg.se3 import inverse, transform_normals, transform_points
from linereg.structures import PairSample

TARGETS = ("view", "whole", "mixed")
MIN_VIEW_POINTS = 32
WHOLE_MODEL_DIRECTIONS = 26
WHOLE_MODEL_IMAGE_SIZE = 128


@dataclass
class Shape:
    """A complete shape: a triangle mesh, or a dense point cloud (optionally with normals).

    Attributes:
        name: identifier (file stem, procedural id).
        mesh: triangle mesh, or ``None`` for a point cloud.
        points: ``(K, 3)`` dense points when ``mesh`` is ``None``.
        normals: ``(K, 3)`` unit normals of ``points``, or ``None``.
        meta: extra metadata copied into every pair (file, category, ...).
    """

    name: str
    mesh: trimesh.Trimesh | None = None
    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if (self.mesh is None) == (self.points is None):
            raise ValueError(f"shape {self.name!r}: give exactly one of mesh and points")
        if self.mesh is not None and (len(self.mesh.faces) == 0 or len(self.mesh.vertices) < 3):
            raise ValueError(
                f"shape {self.name!r}: the mesh is empty ({len(self.mesh.vertices)} vertices, "
                f"{len(self.mesh.faces)} faces){_source_hint(self.meta)}"
            )
        if self.points is not None and len(self.points) < 4 * MIN_VIEW_POINTS:
            raise ValueError(
                f"shape {self.name!r}: a complete point cloud needs at least "
                f"{4 * MIN_VIEW_POINTS} points, got {len(self.points)}{_source_hint(self.meta)}"
            )
        if self.normals is not None and (self.points is None or self.normals.shape != self.points.shape):
            raise ValueError(f"shape {self.name!r}: normals must match points in shape")


def _source_hint(meta: Mapping[str, Any]) -> str:
    """`` (file ...)`` when the metadata names a file."""
    return f" (file {meta['file']})" if "file" in meta else ""


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``axis`` to a right-handed orthonormal basis."""
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    first = np.cross(axis, helper)
    first /= np.linalg.norm(first)
    return first, np.cross(axis, first)


def _fibonacci_directions(count: int) -> np.ndarray:
    """``(count, 3)`` nearly uniform unit directions (Fibonacci sphere)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    azimuth = np.pi * (1 + 5**0.5) * k
    radius = np.sqrt(1 - z * z)
    return np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), z], axis=1)


class ShapeViews:
    """Renders visible parts of one shape from virtual cameras (keeps the ray-casting scene).

    Args:
        shape: the complete shape.
    """

    def __init__(self, shape: Shape) -> None:
        self.shape = shape
        vertices = shape.mesh.vertices if shape.mesh is not None else shape.points
        center, radius = bounding_sphere(torch.as_tensor(np.asarray(vertices, dtype=np.float64)))
        self.center = center.numpy()
        self.radius = float(radius)
        self._scene = None
        self._whole: tuple[np.ndarray, np.ndarray] | None = None

    def _raycasting_scene(self):
        """The Open3D scene of the mesh, built on first use."""
        if self._scene is None:
            import open3d as o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(np.asarray(self.shape.mesh.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.asarray(self.shape.mesh.faces, dtype=np.uint32)),
            )
            self._scene = scene
        return self._scene

    def camera(self, direction: np.ndarray, distance: float) -> np.ndarray:
        """Camera location ``distance`` bounding radii from the centre along ``direction``."""
        return self.center + distance * self.radius * direction

    def render(
        self, eye: np.ndarray, up: np.ndarray, image_size: int, *, min_points: int = MIN_VIEW_POINTS
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Points visible from ``eye`` (and surface normals facing the camera, when known).

        Meshes are ray cast with a square pinhole image of ``image_size`` pixels per side whose
        field of view just holds the bounding sphere; the resolution doubles (twice at most)
        while fewer than ``min_points`` points are hit. Point clouds use hidden point removal.

        Returns:
            ``(points (P, 3) float64, normals (P, 3) or None)``.
        """
        if self.shape.mesh is None:
            visible = hidden_point_removal(self.shape.points, eye)
            normals = None if self.shape.normals is None else self.shape.normals[visible]
            points = np.asarray(self.shape.points[visible], dtype=np.float64)
        else:
            points, normals = self._cast(eye, up, image_size)
            for _ in range(2):
                if len(points) >= min_points:
                    break
                image_size *= 2
                points, normals = self._cast(eye, up, image_size)
        if len(points) < MIN_VIEW_POINTS:
            raise ValueError(
                f"shape {self.shape.name!r}: only {len(points)} points visible from camera "
                f"{np.round(eye, 3).tolist()}{_source_hint(self.shape.meta)}"
            )
        return points, normals

    def _cast(self, eye: np.ndarray, up: np.ndarray, image_size: int) -> tuple[np.ndarray, np.ndarray]:
        """Ray cast the mesh from ``eye``; hit points and normals flipped towards the camera."""
        import open3d as o3d

        distance = float(np.linalg.norm(eye - self.center))
        fov_deg = 2 * math.degrees(math.asin(min(1.0, self.radius / distance))) * 1.05
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=fov_deg,
            center=self.center.tolist(),
            eye=np.asarray(eye, dtype=np.float64).tolist(),
            up=np.asarray(up, dtype=np.float64).tolist(),
            width_px=image_size,
            height_px=image_size,
        )
        hits = self._raycasting_scene().cast_rays(rays)
        t_hit = hits["t_hit"].numpy().reshape(-1)
        found = np.isfinite(t_hit)
        rays_np = rays.numpy().reshape(-1, 6)[found].astype(np.float64)
        points = rays_np[:, :3] + t_hit[found, None] * rays_np[:, 3:]
        normals = hits["primitive_normals"].numpy().reshape(-1, 3)[found].astype(np.float64)
        facing = np.sum(normals * rays_np[:, 3:], axis=1) > 0
        normals[facing] *= -1
        return points, normals

    def whole(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole outer surface with outward normals (cached).

        Meshes: union of 128x128-pixel ray casts from 26 directions (interior faces, hidden
        behind the outer surface, are never hit). Clouds: the cloud, normals estimated when
        absent.
        """
        if self._whole is None:
            if self.shape.mesh is None:
                points = np.asarray(self.shape.points, dtype=np.float64)
                normals = self.shape.normals
                if normals is None:
                    normals = estimate_normals(points)
            else:
                views = []
                for direction in _fibonacci_directions(WHOLE_MODEL_DIRECTIONS):
                    up, _ = _perpendicular_basis(direction)
                    views.append(self._cast(self.camera(direction, 2.5), up, WHOLE_MODEL_IMAGE_SIZE))
                points = np.concatenate([v[0] for v in views])
                normals = np.concatenate([v[1] for v in views])
            self._whole = (points, np.asarray(normals, dtype=np.float64))
        return self._whole


def subsample(points: np.ndarray, num_points: int | None, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``num_points`` points: FPS when there are enough, else all plus repeats.

    ``None`` keeps every point (identity indices).
    """
    if num_points is None:
        return np.arange(len(points))
    if len(points) >= num_points:
        return farthest_point_sampling(np.ascontiguousarray(points, dtype=np.float32), num_points)
    return resample_indices(len(points), num_points, rng)


def _stretch(factors: np.ndarray, center: np.ndarray, points: np.ndarray, normals: np.ndarray):
    """``(N, 3)`` points scaled by ``factors`` per axis about ``center``, and their normals
    (scaled by the inverse factors, renormalised)."""
    normals = normals / factors
    return center + (points - center) * factors, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _apply(transform: torch.Tensor, points: np.ndarray, normals: np.ndarray | None):
    """``(T points, R normals)`` as float64 numpy arrays (normals may be ``None``)."""
    moved = transform_points(transform, torch.from_numpy(np.asarray(points, np.float64))).numpy()
    if normals is None:
        return moved, None
    rotated = transform_normals(transform, torch.from_numpy(np.asarray(normals, np.float64)))
    return moved, rotated.numpy()


def float32_or_none(array: np.ndarray | None) -> np.ndarray | None:
    """C-contiguous float32 copy (``None`` passes through)."""
    return None if array is None else np.ascontiguousarray(array, dtype=np.float32)


@dataclass(frozen=True)
class ViewProtocol:
    """The paper's partial-view pair protocol (see the module docstring).

    Attributes:
        name: preset name recorded in the metadata (``"airplane"``, ``"human"``).
        target: ``"view"`` (second camera, Airplane), ``"whole"`` (whole model, Human) or
            ``"mixed"`` (both pair types in one split: a second view at even camera stops, the
            whole model at odd ones).
        num_views: camera stops per shape (pairs per shape).
        view_axis: orbit axis in shape coordinates (ModelNet resampled and SMPL are y-up).
        elevation_deg: camera elevation above the orbit plane.
        target_view_angle_deg: the second camera turns by U[-angle, angle] about a random axis.
        camera_distance: camera distance from the centre, in bounding-sphere radii.
        image_size: virtual depth image side in pixels (meshes).
        num_points: points per cloud after FPS; ``None`` keeps every visible point.
        half_extent: pairs are scaled into ``[-half_extent, half_extent]^3``.
        max_angle_deg: Euler angle bound of the composite transform.
        max_translation: translation bound of the composite transform.
        normals: ``"estimate"`` (PCA, oriented to the camera) or ``"surface"`` (mesh normals,
            or the cloud's own when it has them).
        normal_k: neighbours for normal estimation.
        anisotropic_scale: training augmentation: both clouds of a pair are stretched by one factor
            per axis of the shape frame, drawn from ``[1 - a, 1 + a]`` (0: the shape as it is).
    """

    name: str = "airplane"
    target: str = "view"
    num_views: int = 18
    view_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    elevation_deg: float = 20.0
    target_view_angle_deg: float = 75.0
    camera_distance: float = 2.5
    image_size: int = 192
    num_points: int | None = 1024
    half_extent: float = 1.0
    max_angle_deg: float = 45.0
    max_translation: float = 0.2
    normals: str = "estimate"
    normal_k: int = 30
    anisotropic_scale: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.anisotropic_scale < 1:
            raise ValueError(f"anisotropic_scale must be in [0, 1), got {self.anisotropic_scale}")
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        if self.normals not in ("estimate", "surface"):
            raise ValueError(f"normals must be 'estimate' or 'surface', got {self.normals!r}")
        if self.num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {self.num_views}")
        if self.camera_distance <= 1.0:
            raise ValueError(f"camera_distance must exceed 1 bounding radius, got {self.camera_distance}")
        if self.num_points is not None and self.num_points < 1:
            raise ValueError(f"num_points must be >= 1 or None, got {self.num_points}")
        axis = np.asarray(self.view_axis, dtype=np.float64)
        if axis.shape != (3,) or np.linalg.norm(axis) == 0:
            raise ValueError(f"view_axis must be a non-zero 3-vector, got {self.view_axis}")
        object.__setattr__(self, "view_axis", tuple(float(a) for a in axis))

    @property
    def pairs_per_shape(self) -> int:
        return self.num_views

    def target_of(self, view_index: int) -> str:
        """``"view"`` or ``"whole"``: the target of pair ``view_index`` (``"mixed"`` alternates)."""
        if self.target != "mixed":
            return self.target
        return "view" if view_index % 2 == 0 else "whole"

    def camera_pose(self, views: ShapeViews, view_index: int) -> tuple[np.ndarray, np.ndarray]:
        """``(eye, up)`` of camera stop ``view_index`` on the orbit."""
        axis = np.asarray(self.view_axis) / np.linalg.norm(self.view_axis)
        first, second = _perpendicular_basis(axis)
        azimuth = 2 * math.pi * view_index / self.num_views
        elevation = math.radians(self.elevation_deg)
        direction = (
            math.cos(elevation) * (math.cos(azimuth) * first + math.sin(azimuth) * second) + math.sin(elevation) * axis
        )
        up = axis if abs(direction @ axis) < 0.99 else first
        return views.camera(direction, self.camera_distance), up

    def _view(self, views: ShapeViews, eye: np.ndarray, up: np.ndarray, rng: np.random.Generator):
        """FPS-sampled visible points and normals from one camera."""
        points, surface_normals = views.render(eye, up, self.image_size)
        idx = subsample(points, self.num_points, rng)
        if self.normals == "surface" and surface_normals is not None:
            return points[idx], surface_normals[idx]
        normals = estimate_normals(points, k=min(self.normal_k, len(points) - 1), orient_towards=eye)
        return points[idx], normals[idx]

    def make_pair(self, views: ShapeViews, view_index: int, rng: np.random.Generator) -> PairSample:
        """Pair ``view_index`` of a shape.

        Args:
            views: renderer of the shape.
            view_index: camera stop, ``0 <= view_index < num_views``.
            rng: generator of this pair (second camera, composite transform).

        Returns:
            A labelled pair; ``meta`` holds the view index, scale and centre.
        """
        if not 0 <= view_index < self.num_views:
            raise ValueError(f"view_index must be in [0, {self.num_views}), got {view_index}")
        eye, up = self.camera_pose(views, view_index)
        src_xyz, src_normals = self._view(views, eye, up, rng)
        target = self.target_of(view_index)
        if target == "view":
            turn = random_axis_angle_rotation(
                1,
                rng,
                min_angle_deg=-self.target_view_angle_deg,
                max_angle_deg=self.target_view_angle_deg,
                dtype=torch.float64,
            )[0].numpy()
            tgt_eye = views.center + turn @ (eye - views.center)
            tgt_xyz, tgt_normals = self._view(views, tgt_eye, turn @ up, rng)
        else:
            whole_xyz, whole_normals = views.whole()
            idx = subsample(whole_xyz, self.num_points, rng)
            tgt_xyz, tgt_normals = whole_xyz[idx], whole_normals[idx]
        if self.anisotropic_scale > 0:
            stretch = rng.uniform(1 - self.anisotropic_scale, 1 + self.anisotropic_scale, size=3)
            src_xyz, src_normals = _stretch(stretch, views.center, src_xyz, src_normals)
            tgt_xyz, tgt_normals = _stretch(stretch, views.center, tgt_xyz, tgt_normals)
        (src_xyz, tgt_xyz), center, scale = fit_into_cube(src_xyz, tgt_xyz, half_extent=self.half_extent)
        transform = random_transform_paper(
            1,
            rng,
            max_angle_deg=self.max_angle_deg,
            max_translation=self.max_translation,
            dtype=torch.float64,
        )[0]
        tgt_xyz, tgt_normals = _apply(transform, tgt_xyz, tgt_normals)
        return PairSample(
            src_xyz=float32_or_none(src_xyz),
            tgt_xyz=float32_or_none(tgt_xyz),
            src_normals=float32_or_none(src_normals),
            tgt_normals=float32_or_none(tgt_normals),
            gt_transform=float32_or_none(transform.numpy()),
            meta={
                "protocol": self.name,
                "view": view_index,
                "scale": float(scale),
                "center": [float(c) for c in center],
            },
        )


@dataclass(frozen=True)
class CropProtocol:
    """RPM-Net's ModelNet40 partial-visibility ("crop") protocol (RPM-Net's repository,
    src/data_loader/transforms.py).

    Attributes:
        name: preset name recorded in the metadata.
        pairs_per_shape: pairs drawn from each shape (RPM-Net: 1, redrawn every epoch).
        base_points: points of the complete cloud before cropping (``modelnet40_ply_hdf5_2048``).
        keep_ratio: fraction kept by each half-space crop.
        num_points: points per cropped cloud after resampling (ceil(0.7 * 1024) = 717).
        rot_mag_deg: Euler angle bound of the source perturbation.
        trans_mag: translation bound of the source perturbation.
        noise_std: standard deviation of the Gaussian jitter (0 disables it).
        noise_clip: jitter clipping bound.
    """

    name: str = "rpmnet_crop"
    pairs_per_shape: int = 1
    base_points: int = 2048
    keep_ratio: float = 0.7
    num_points: int = 717
    rot_mag_deg: float = 45.0
    trans_mag: float = 0.5
    noise_std: float = 0.01
    noise_clip: float = 0.05

    def __post_init__(self) -> None:
        if not 0 < self.keep_ratio <= 1:
            raise ValueError(f"keep_ratio must be in (0, 1], got {self.keep_ratio}")
        if self.pairs_per_shape < 1 or self.num_points < 1 or self.base_points < 1:
            raise ValueError("pairs_per_shape, num_points and base_points must be >= 1")

    def _crop(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Indices kept by a random half-space crop of ``keep_ratio`` of the points."""
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        height = points @ direction
        return np.flatnonzero(height > np.percentile(height, (1.0 - self.keep_ratio) * 100))

    def _finish(self, points, normals, rng):
        """Resample to ``num_points`` and jitter the coordinates."""
        idx = resample_indices(len(points), self.num_points, rng)
        points, normals = points[idx], normals[idx]
        if self.noise_std > 0:
            noise = rng.normal(scale=self.noise_std, size=points.shape)
            points = points + np.clip(noise, -self.noise_clip, self.noise_clip)
        return points, normals

    def make_pair(self, views: ShapeViews, view_index: int, rng: np.random.Generator) -> PairSample:
        """One cropped pair of a shape (``view_index`` only names the draw)."""
        whole_xyz, whole_normals = views.whole()
        base = resample_indices(len(whole_xyz), self.base_points, rng)
        points = (whole_xyz[base] - views.center) / views.radius
        normals = whole_normals[base]
        src_idx, tgt_idx = self._crop(points, rng), self._crop(points, rng)
        perturbation = random_transform_rpmnet(
            1, rng, rot_mag_deg=self.rot_mag_deg, trans_mag=self.trans_mag, dtype=torch.float64
        )[0]
        src_xyz, src_normals = _apply(perturbation, points[src_idx], normals[src_idx])
        src_xyz, src_normals = self._finish(src_xyz, src_normals, rng)
        tgt_xyz, tgt_normals = self._finish(points[tgt_idx], normals[tgt_idx], rng)
        return PairSample(
            src_xyz=float32_or_none(src_xyz),
            tgt_xyz=float32_or_none(tgt_xyz),
            src_normals=float32_or_none(src_normals),
            tgt_normals=float32_or_none(tgt_normals),
            gt_transform=float32_or_none(inverse(perturbation).numpy()),
            meta={
                "protocol": self.name,
                "view": view_index,
                "scale": 1.0 / views.radius,
                "center": [float(c) for c in views.center],
            },
        )


PROTOCOL_PRESETS: dict[str, dict[str, Any]] = {
    "airplane": {"target": "view", "num_views": 18},
    "human": {"target": "whole", "num_views": 50},
    "rpmnet_crop": {},
}


def build_protocol(spec: str | Mapping[str, Any] | ViewProtocol | CropProtocol):
    """A protocol from a preset name or a mapping ``{name: <preset>, **overrides}``.

    Presets: ``airplane`` (18 views, target = second view), ``human`` (50 views, target =
    whole model), ``rpmnet_crop``.

    Raises:
        ValueError: unknown preset or unknown override keys (the message lists valid ones).
    """
    if isinstance(spec, ViewProtocol | CropProtocol):
        return spec
    if isinstance(spec, str):
        spec = {"name": spec}
    spec = dict(spec)
    name = spec.pop("name", None)
    if name not in PROTOCOL_PRESETS:
        raise ValueError(f"unknown protocol {name!r}; choose from {sorted(PROTOCOL_PRESETS)}")
    cls = CropProtocol if name == "rpmnet_crop" else ViewProtocol
    valid = {f.name for f in fields(cls)} - {"name"}
    unknown = sorted(set(spec) - valid)
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} for protocol {name!r}; valid keys: {sorted(valid)}")
    if "view_axis" in spec:
        spec["view_axis"] = tuple(spec["view_axis"])
    return cls(name=name, **{**PROTOCOL_PRESETS[name], **spec})


def protocol_settings(protocol: ViewProtocol | CropProtocol) -> dict[str, Any]:
    """JSON-ready settings of a protocol (for cache manifests)."""
    settings = asdict(protocol)
    settings["kind"] = type(protocol).__name__
    return settings
