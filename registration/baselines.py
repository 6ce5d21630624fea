"""Classical registration baselines: ICP, point-to-plane ICP, FGR, FRICP (the paper's Table 1) and FPFH + RANSAC.

Each is registered in :data:`linereg.registration.methods.METHODS` and built with
``METHODS.build({"name": ..., **kwargs})``; the result is a callable
``method(src, tgt, src_normals=None, tgt_normals=None) -> MethodResult`` on numpy clouds.
Every method runs through :func:`linereg.registration.methods.run_centered`: both clouds are translated to
their centroids first (``center=True``, as every method) and the returned transform maps the
original source onto the original target (``tgt ≈ R @ src + t``).

Distances are given relative to the target's *diameter* ``d``, the diagonal of its
axis-aligned bounding box, so the defaults work for any unit: the paper's synthetic pairs
(in ``[-1, 1]^3``, ``d`` about 2.5-3.5) as well as scans in metres.

``icp_point``
    Open3D point-to-point ICP (Besl & McKay), correspondences up to
    ``max_correspondence_ratio * d``.
``icp_plane``
    Open3D point-to-plane ICP; target normals are the given ones, else estimated by
    :func:`linereg.pointcloud.estimate_normals`.
``fgr``
    Open3D Fast Global Registration (Zhou et al. 2016) on FPFH features, no ICP refinement:
    optional voxel down-sampling, normals (given or estimated), FPFH within
    ``feature_radius_ratio * d``.
``fpfh_ransac``
    Open3D's global-registration pipeline: FPFH features on a voxel grid, RANSAC on their
    mutual matches, then point-to-plane ICP on the grids
    (:func:`linereg.registration.features.global_candidates`; the grid is derived from the
    target's spacing, as for the ``register`` default's global candidates).
``fricp``
    Fast and Robust ICP (Zhang et al., TPAMI 2022) through ``fricp_cpp.native``, the pybind11
    bindings of the authors' C++ code, run as their command-line ``main.cpp`` does (method 3:
    Welsch kernel, ``nu`` annealed from ``nu_begin_k`` times the median initial residual down
    to ``nu_end_k`` times the median point spacing, Anderson acceleration), with the paper's
    defaults (``nu_begin_k = 3``, ``nu_end_k = 1 / (3 sqrt 3)``, ``nu_alpha = 0.5``).

Open3D and ``fricp_cpp`` are imported inside the functions (importing Open3D takes seconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from linereg.pointcloud import estimate_normals, open3d_cloud
from linereg.registration.features import FeatureOptions, global_candidates
from linereg.registration.methods import METHODS, MethodResult, run_centered

FRICP_VARIANTS = ("ICP", "AA_ICP", "FICP", "RICP", "PPL", "RPPL")
"""``fricp_cpp.native.Method`` names usable by ``fricp``: plain ICP, Anderson-accelerated ICP,
Fast ICP, Robust ICP (the paper's FRICP, default), point-to-plane and robust point-to-plane."""


def diameter(points: np.ndarray) -> float:
    """Diagonal of the axis-aligned bounding box of ``points (N, 3)`` (at least 1e-12)."""
    return max(float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))), 1e-12)


def _normals_or_estimate(points: np.ndarray, normals: np.ndarray | None, k: int) -> np.ndarray:
    """``normals`` when given (checked against ``points``), else PCA normals from ``k`` neighbours."""
    if normals is None:
        return estimate_normals(points, k=min(k, len(points) - 1))
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != points.shape:
        raise ValueError(f"normals must have the shape of their points {points.shape}, got {normals.shape}")
    if not np.isfinite(normals).all():
        raise ValueError("normals contain NaN or Inf")
    return normals


def _require_positive(**values: float) -> None:
    """ValueError naming the first argument that is not strictly positive."""
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}")


def _open3d_icp(
    src: np.ndarray,
    tgt: np.ndarray,
    estimation,
    max_distance: float,
    max_iterations: int,
    tolerance: float,
    tgt_normals: np.ndarray | None = None,
) -> MethodResult:
    """Open3D ``registration_icp`` from the identity (:func:`linereg.register` scores the result)."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    result = registration.registration_icp(
        open3d_cloud(src),
        open3d_cloud(tgt, tgt_normals),
        max_distance,
        np.eye(4),
        estimation,
        registration.ICPConvergenceCriteria(
            relative_fitness=tolerance, relative_rmse=tolerance, max_iteration=max_iterations
        ),
    )
    return MethodResult(transform=np.asarray(result.transformation, dtype=np.float64))


@METHODS.register("icp_point")
@dataclass(frozen=True)
class PointToPointICP:
    """Open3D point-to-point ICP.

    Args:
        max_correspondence_ratio: pairs farther apart than this fraction of the target
            diameter are ignored (1.0 keeps nearly every pair, as Besl-McKay ICP).
        max_iterations: ICP iterations at most.
        tolerance: stop when fitness and inlier RMSE change by less than this (relative).
        center: centre both clouds first (see :func:`linereg.registration.methods.run_centered`).
    """

    max_correspondence_ratio: float = 0.25
    max_iterations: int = 100
    tolerance: float = 1e-7
    center: bool = True

    def __post_init__(self) -> None:
        _require_positive(max_correspondence_ratio=self.max_correspondence_ratio, max_iterations=self.max_iterations)

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        import open3d as o3d

        estimation = o3d.pipelines.registration.TransformationEstimationPointToPoint()
        max_distance = self.max_correspondence_ratio * diameter(tgt)
        return _open3d_icp(src, tgt, estimation, max_distance, self.max_iterations, self.tolerance)


@METHODS.register("icp_plane")
@dataclass(frozen=True)
class PointToPlaneICP:
    """Open3D point-to-plane ICP (target normals given, or estimated).

    Args:
        max_correspondence_ratio: pairs farther apart than this fraction of the target
            diameter are ignored.
        max_iterations: ICP iterations at most.
        tolerance: stop when fitness and inlier RMSE change by less than this (relative).
        normal_k: neighbours for the target normals when none are given.
        center: centre both clouds first (see :func:`linereg.registration.methods.run_centered`).
    """

    max_correspondence_ratio: float = 0.25
    max_iterations: int = 100
    tolerance: float = 1e-7
    normal_k: int = 30
    center: bool = True

    def __post_init__(self) -> None:
        _require_positive(max_correspondence_ratio=self.max_correspondence_ratio, max_iterations=self.max_iterations)
        if self.normal_k < 3:
            raise ValueError(f"normal_k must be at least 3, got {self.normal_k}")

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        import open3d as o3d

        normals = _normals_or_estimate(tgt, tgt_normals, self.normal_k)
        estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()
        max_distance = self.max_correspondence_ratio * diameter(tgt)
        return _open3d_icp(src, tgt, estimation, max_distance, self.max_iterations, self.tolerance, normals)


@METHODS.register("fgr")
@dataclass(frozen=True)
class FastGlobalRegistration:
    """Open3D Fast Global Registration on FPFH features (no ICP refinement).

    Args:
        voxel_ratio: voxel down-sampling size as a fraction of the target diameter
            (0 keeps every point; the paper's clouds have 1024 points).
        feature_radius_ratio: FPFH search radius as a fraction of the target diameter.
        feature_max_nn: FPFH neighbours at most.
        max_correspondence_ratio: FGR's maximum correspondence distance (the final scale of its
            Geman-McClure graduated non-convexity) as a fraction of the target diameter.
        iterations: FGR iterations.
        tuple_test: FGR's tuple-consistency test of the feature matches.
        normal_k: neighbours for normals when none are given.
        center: centre both clouds first (see :func:`linereg.registration.methods.run_centered`).
    """

    voxel_ratio: float = 0.0
    feature_radius_ratio: float = 0.05
    feature_max_nn: int = 100
    max_correspondence_ratio: float = 0.03
    iterations: int = 64
    tuple_test: bool = True
    normal_k: int = 30
    center: bool = True

    def __post_init__(self) -> None:
        if self.voxel_ratio < 0:
            raise ValueError(f"voxel_ratio must be >= 0, got {self.voxel_ratio}")
        _require_positive(
            feature_radius_ratio=self.feature_radius_ratio,
            feature_max_nn=self.feature_max_nn,
            max_correspondence_ratio=self.max_correspondence_ratio,
            iterations=self.iterations,
        )
        if self.normal_k < 3:
            raise ValueError(f"normal_k must be at least 3, got {self.normal_k}")

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _features(self, points: np.ndarray, normals: np.ndarray | None, scale: float):
        """Down-sampled Open3D cloud (with normals) and its FPFH features."""
        import open3d as o3d

        cloud = open3d_cloud(points, _normals_or_estimate(points, normals, self.normal_k))
        if self.voxel_ratio > 0:
            cloud = cloud.voxel_down_sample(self.voxel_ratio * scale)
        search = o3d.geometry.KDTreeSearchParamHybrid(
            radius=self.feature_radius_ratio * scale, max_nn=self.feature_max_nn
        )
        return cloud, o3d.pipelines.registration.compute_fpfh_feature(cloud, search)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        import open3d as o3d

        registration = o3d.pipelines.registration
        scale = diameter(tgt)
        src_cloud, src_features = self._features(src, src_normals, scale)
        tgt_cloud, tgt_features = self._features(tgt, tgt_normals, scale)
        option = registration.FastGlobalRegistrationOption(
            maximum_correspondence_distance=self.max_correspondence_ratio * scale,
            iteration_number=self.iterations,
            tuple_test=self.tuple_test,
        )
        result = registration.registration_fgr_based_on_feature_matching(
            src_cloud, tgt_cloud, src_features, tgt_features, option
        )
        return MethodResult(transform=np.asarray(result.transformation, dtype=np.float64))


@METHODS.register("fpfh_ransac")
@dataclass(frozen=True)
class FeatureRANSAC:
    """Open3D FPFH + RANSAC (mutual matches), then point-to-plane ICP on the voxel grids.

    Args:
        points: the voxel is the point spacing of this many FPS target points
            (:func:`~linereg.registration.features.feature_voxel`).
        refine_distance: ICP's correspondence distance, in voxels (0: no ICP).
        seed: RANSAC's seed.
        center: centre both clouds first (see :func:`linereg.registration.methods.run_centered`).
    """

    points: int = 3000
    refine_distance: float = 0.4
    seed: int = 0
    center: bool = True

    def __post_init__(self) -> None:
        _require_positive(points=self.points)
        if self.refine_distance < 0:
            raise ValueError(f"refine_distance must be >= 0, got {self.refine_distance}")

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        import open3d as o3d

        options = FeatureOptions(points=self.points, mutual=(True,), fgr=False)
        found, grids = global_candidates(src, tgt, options, seed=self.seed)
        transform = found[0]
        if self.refine_distance > 0:
            registration = o3d.pipelines.registration
            refined = registration.registration_icp(
                grids["src_cloud"],
                grids["tgt_cloud"],
                self.refine_distance * grids["voxel"],
                transform,
                registration.TransformationEstimationPointToPlane(),
            )
            transform = np.asarray(refined.transformation)
        return MethodResult(transform=np.asarray(transform, dtype=np.float64), info={"voxel": grids["voxel"]})


@METHODS.register("fricp")
@dataclass(frozen=True)
class FastRobustICP:
    """Fast and Robust ICP (the authors' C++ through ``fricp_cpp.native``), paper defaults.

    The native call scales both clouds by their largest bounding-box diagonal and, unless
    ``center=False``, centres them (as FRICP's ``main.cpp``); the transform is returned in the
    input units.

    Args:
        variant: ``fricp_cpp.native.Method`` name, one of :data:`FRICP_VARIANTS`; ``"RICP"``
            (Welsch kernel, annealed ``nu``, Anderson acceleration) is the paper's FRICP.
        nu_begin_k: initial ``nu`` = ``nu_begin_k`` x median initial residual.
        nu_end_k: final ``nu`` = ``nu_end_k`` x median target point spacing.
        nu_alpha: ``nu`` shrinks by this factor between annealing stages.
        max_iterations: ICP iterations per ``nu`` stage at most.
        tolerance: stop a stage when the transform changes by less than this.
        anderson_m: Anderson acceleration history length.
        center: centre both clouds first (see :func:`linereg.registration.methods.run_centered`).
    """

    variant: str = "RICP"
    nu_begin_k: float = 3.0
    nu_end_k: float = 1.0 / (3.0 * math.sqrt(3.0))
    nu_alpha: float = 0.5
    max_iterations: int = 100
    tolerance: float = 1e-5
    anderson_m: int = 5
    center: bool = True

    def __post_init__(self) -> None:
        if self.variant not in FRICP_VARIANTS:
            raise ValueError(f"variant must be one of {FRICP_VARIANTS}, got {self.variant!r}")
        _require_positive(
            nu_begin_k=self.nu_begin_k,
            nu_end_k=self.nu_end_k,
            max_iterations=self.max_iterations,
            tolerance=self.tolerance,
            anderson_m=self.anderson_m,
        )
        if not 0 < self.nu_alpha < 1:
            raise ValueError(f"nu_alpha must be in (0, 1), got {self.nu_alpha}")

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        from fricp_cpp import native

        parameters = native.Parameters()
        parameters.nu_begin_k = self.nu_begin_k
        parameters.nu_end_k = self.nu_end_k
        parameters.nu_alpha = self.nu_alpha
        parameters.max_icp = self.max_iterations
        parameters.stop = self.tolerance
        parameters.anderson_m = self.anderson_m
        needs_normals = self.variant in ("PPL", "RPPL")
        result = native.register_(
            np.ascontiguousarray(src),
            np.ascontiguousarray(tgt),
            getattr(native.Method, self.variant),
            source_normals=_normals_or_estimate(src, src_normals, 30) if needs_normals else None,
            target_normals=_normals_or_estimate(tgt, tgt_normals, 30) if needs_normals else None,
            parameters=parameters,
            demean=self.center,
        )
        return MethodResult(transform=np.asarray(result.transformation, dtype=np.float64))
