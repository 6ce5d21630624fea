"""Feature-based global registration with Open3D: FPFH features on a voxel grid, RANSAC and FGR.

The global candidates of the ``register`` default for partly overlapping scans
(:mod:`linereg.registration.global_stage`) and the ``fpfh_ransac`` baseline both come from here.
The grid is derived from the clouds themselves, so one setting serves an object in the unit
sphere and a room in metres: the voxel is the point spacing of an FPS subset of
``FeatureOptions.points`` points of the target (:func:`feature_voxel`), so that the grid holds
about that many points whatever the units. Normals and FPFH use Open3D's usual radii of 2 and
5 voxels (Rusu et al., ICRA 2009; Open3D's global-registration pipeline).

The module imports neither torch nor the torch-based :mod:`linereg.pointcloud` (it builds its
Open3D clouds itself): the ``register`` command's global stage loads Open3D, and torch's import
would cost it more than the features do.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from linereg.fps import farthest_point_subset as fps
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
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud = cloud.voxel_down_sample(voxel)
    cloud.estimate_normals(search(radius=options.normal_radius * voxel, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, search(radius=options.feature_radius * voxel, max_nn=options.max_neighbours)
    )
    return cloud, features


class FeatureMatcher:
    """FPFH features of a source and a target, computed once, and the candidates matched from them.

    :meth:`candidates` yields one source-to-target candidate at a time (each RANSAC run, then FGR),
    so that a caller can stop as soon as one settles its question; every candidate reuses the same
    grids and features.

    Args:
        src, tgt: ``(N, 3)`` and ``(M, 3)`` clouds (any units).
        options: :class:`FeatureOptions`.

    Attributes:
        voxel: the grid's voxel (:func:`feature_voxel` of the target).
        src_cloud, tgt_cloud: the grids (Open3D clouds with normals).
    """

    def __init__(self, src: np.ndarray, tgt: np.ndarray, options: FeatureOptions | None = None) -> None:
        self.options = options or FeatureOptions()
        self.voxel = feature_voxel(tgt, self.options.points)
        (self.src_cloud, self._src_features), (self.tgt_cloud, self._tgt_features) = (
            fpfh(points, self.voxel, self.options) for points in (src, tgt)
        )

    def count(self) -> int:
        """How many candidates :meth:`candidates` yields."""
        return len(self.options.mutual) * self.options.seeds + int(self.options.fgr)

    def ransac(self, mutual: bool, seed: int) -> np.ndarray:
        """The ``(4, 4)`` candidate of one RANSAC run on the (``mutual``) feature matches, seeded with ``seed``."""
        import open3d as o3d

        registration = o3d.pipelines.registration
        options = self.options
        distance = options.distance * self.voxel
        checkers = [
            registration.CorrespondenceCheckerBasedOnEdgeLength(options.edge_similarity),
            registration.CorrespondenceCheckerBasedOnDistance(distance),
        ]
        o3d.utility.random.seed(seed)
        found = registration.registration_ransac_based_on_feature_matching(
            self.src_cloud,
            self.tgt_cloud,
            self._src_features,
            self._tgt_features,
            mutual,
            distance,
            registration.TransformationEstimationPointToPoint(False),
            3,
            checkers,
            registration.RANSACConvergenceCriteria(options.iterations, options.confidence),
        )
        return np.asarray(found.transformation)

    def fgr(self) -> np.ndarray:
        """The ``(4, 4)`` Fast Global Registration candidate (Zhou et al., ECCV 2016) of the same features."""
        import open3d as o3d

        registration = o3d.pipelines.registration
        found = registration.registration_fgr_based_on_feature_matching(
            self.src_cloud,
            self.tgt_cloud,
            self._src_features,
            self._tgt_features,
            registration.FastGlobalRegistrationOption(
                maximum_correspondence_distance=self.options.distance * self.voxel
            ),
        )
        return np.asarray(found.transformation)

    def candidates(self, seed: int = 0) -> Iterator[np.ndarray]:
        """The ``(4, 4)`` candidates one at a time: RANSAC per ``mutual`` entry and seed (run ``k``
        of an entry seeded with ``seed + k``), then FGR when ``fgr``."""
        for mutual in self.options.mutual:
            for run in range(self.options.seeds):
                yield self.ransac(mutual, seed + run)
        if self.options.fgr:
            yield self.fgr()


def global_candidates(
    src: np.ndarray, tgt: np.ndarray, options: FeatureOptions | None = None, seed: int = 0
) -> tuple[np.ndarray, dict[str, Any]]:
    """Every candidate of :meth:`FeatureMatcher.candidates` as ``(K, 4, 4)``, and
    ``{"voxel", "src_cloud", "tgt_cloud"}`` (the grids: Open3D clouds with normals).

    Args:
        src, tgt: ``(N, 3)`` and ``(M, 3)`` clouds (any units).
        options: :class:`FeatureOptions`.
        seed: seed of the first RANSAC run (Open3D's global random generator).
    """
    matcher = FeatureMatcher(src, tgt, options)
    grids = {"voxel": matcher.voxel, "src_cloud": matcher.src_cloud, "tgt_cloud": matcher.tgt_cloud}
    return np.stack(list(matcher.candidates(seed))), grids
