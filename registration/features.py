"""Feature-based global registration with Open3D: FPFH features on a voxel grid, RANSAC and FGR.

The global candidates of the ``register`` default for partly overlapping scans
(:mod:`linereg.registration.global_stage`) and the ``fpfh_ransac`` baseline both come from here.
The grid is derived from the clouds themselves, so one setting serves an object in the unit
sphere and a room in metres: the voxel is the point spacing of an FPS subset of
``FeatureOptions.points`` points of the target (:func:`feature_voxel`), so that the grid holds
about that many points whatever the units. Normals and FPFH use Open3D's usual radii of 2 and
5 voxels (Rusu et al., ICRA 2009; Open3D's global-registration pipeline).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.pointcloud import open3d_cloud
from linereg.registration.evaluation import point_spacing


@dataclass(frozen=True)
class FeatureOptions:
    """Settings of the FPFH grid, RANSAC and FGR (lengths in voxels).

    Attributes:
        points: the voxel is the spacing of this many FPS points of the target (:func:`feature_voxel`).
        normal_radius, feature_radius: radii of the normals and of FPFH.
        max_neighbours: most neighbours of a normal or a feature.
        distance: RANSAC's inlier distance and correspondence check.
        edge_similarity: RANSAC's edge-length check (Open3D's ``CorrespondenceCheckerBasedOnEdgeLength``).
        iterations, confidence: RANSAC's most iterations and its stopping confidence.
        mutual: one RANSAC run per entry, with (``True``) or without mutual nearest-neighbour
            filtering of the feature matches.
        seeds: RANSAC runs per ``mutual`` entry, each with its own seed.
        fgr: also a Fast Global Registration candidate (Zhou et al., ECCV 2016).
    """

    points: int = 3000
    normal_radius: float = 2.0
    feature_radius: float = 5.0
    max_neighbours: int = 100
    distance: float = 1.5
    edge_similarity: float = 0.9
    iterations: int = 100_000
    confidence: float = 0.999
    mutual: tuple[bool, ...] = (True, False)
    seeds: int = 1
    fgr: bool = True

    def __post_init__(self) -> None:
        for name in ("points", "normal_radius", "feature_radius", "max_neighbours", "distance", "iterations", "seeds"):
            if not getattr(self, name) > 0:
                raise ValueError(f"features.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.edge_similarity < 1 or not 0 < self.confidence < 1:
            raise ValueError("features.edge_similarity and features.confidence must be in (0, 1)")
        object.__setattr__(self, "mutual", tuple(bool(value) for value in self.mutual))


def feature_voxel(points: np.ndarray, count: int) -> float:
    """Voxel side for features: the median nearest-neighbour distance of ``count`` FPS points of ``points (N, 3)``
    (the spacing of the cloud itself when it has fewer points)."""
    return point_spacing(fps(np.asarray(points, dtype=np.float64), count))


def fpfh(points: np.ndarray, voxel: float, options: FeatureOptions) -> tuple[Any, Any]:
    """The voxel grid of ``points (N, 3)`` (an Open3D cloud with normals) and its FPFH features."""
    import open3d as o3d

    search = o3d.geometry.KDTreeSearchParamHybrid
    cloud = open3d_cloud(points).voxel_down_sample(voxel)
    cloud.estimate_normals(search(radius=options.normal_radius * voxel, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, search(radius=options.feature_radius * voxel, max_nn=options.max_neighbours)
    )
    return cloud, features


def global_candidates(
    src: np.ndarray, tgt: np.ndarray, options: FeatureOptions | None = None, seed: int = 0
) -> tuple[np.ndarray, dict[str, Any]]:
    """Source-to-target candidates ``(K, 4, 4)`` of FPFH + RANSAC (one per ``mutual`` entry and seed)
    and FGR, on the voxel grid of :func:`feature_voxel`; and ``{"voxel", "src_cloud", "tgt_cloud"}``
    (the grids: Open3D clouds with normals).

    Args:
        src, tgt: ``(N, 3)`` and ``(M, 3)`` clouds (any units).
        options: :class:`FeatureOptions`.
        seed: seed of the first RANSAC run (Open3D's global random generator).
    """
    import open3d as o3d

    options = options or FeatureOptions()
    registration = o3d.pipelines.registration
    voxel = feature_voxel(tgt, options.points)
    (src_cloud, src_features), (tgt_cloud, tgt_features) = (fpfh(points, voxel, options) for points in (src, tgt))
    distance = options.distance * voxel
    checkers = [
        registration.CorrespondenceCheckerBasedOnEdgeLength(options.edge_similarity),
        registration.CorrespondenceCheckerBasedOnDistance(distance),
    ]
    candidates = []
    for mutual in options.mutual:
        for run in range(options.seeds):
            o3d.utility.random.seed(seed + run)
            found = registration.registration_ransac_based_on_feature_matching(
                src_cloud,
                tgt_cloud,
                src_features,
                tgt_features,
                mutual,
                distance,
                registration.TransformationEstimationPointToPoint(False),
                3,
                checkers,
                registration.RANSACConvergenceCriteria(options.iterations, options.confidence),
            )
            candidates.append(np.asarray(found.transformation))
    if options.fgr:
        found = registration.registration_fgr_based_on_feature_matching(
            src_cloud,
            tgt_cloud,
            src_features,
            tgt_features,
            registration.FastGlobalRegistrationOption(maximum_correspondence_distance=distance),
        )
        candidates.append(np.asarray(found.transformation))
    grids = {"voxel": voxel, "src_cloud": src_cloud, "tgt_cloud": tgt_cloud}
    return np.stack(candidates), grids
