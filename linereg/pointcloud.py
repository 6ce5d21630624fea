"""Point-cloud operations: neighbour spacing, Chamfer distances, fit, sampling, normals, visibility.

Batched tensors are ``(B, P, 3)``; the unbatched ``(P, 3)`` form is accepted wherever the
docstring says so and gives unbatched outputs. Distances returned here are Euclidean, never
squared, unless a docstring says otherwise.
"""

from __future__ import annotations

import numpy as np
import torch

from linereg.checks import check_points, check_same_batch
from linereg.fps import farthest_point_indices
from linereg.knn import knn_distances


def mean_neighbor_distance(points: torch.Tensor | np.ndarray, k: int = 2) -> torch.Tensor:
    """Mean distance of a point to its ``k`` nearest neighbours, averaged over the cloud.

    This is the paper's point spacing ``d_nei``: for every point take the mean Euclidean (not
    squared) distance to its ``k`` nearest other points, then average over all points.

    Args:
        points: tensor or array of shape ``(B, N, 3)`` or ``(N, 3)``; numpy input is converted.
        k: number of neighbours, ``1 <= k < N``.

    Returns:
        Tensor of shape ``(B,)`` or a scalar tensor; 0 for a cloud whose points all coincide.

    Raises:
        ValueError: ``N <= k`` or ``k < 1``.
    """
    if isinstance(points, np.ndarray):
        points = torch.from_numpy(points)
    check_points(points, "points")
    num_points = points.shape[-2]
    if k < 1 or num_points <= k:
        raise ValueError(f"mean_neighbor_distance needs 1 <= k < N, got k={k} for N={num_points} points")
    return knn_distances(points, points, k, exclude_self=True).mean(dim=(-2, -1))


def trimmed_chamfer_distance(
    x: torch.Tensor, y: torch.Tensor, keep_fraction: float | torch.Tensor = 1.0
) -> torch.Tensor:
    """How far apart two clouds lie, without labels: a symmetric Chamfer distance over each
    direction's closest points.

    Every point's Euclidean distance to its nearest point of the other cloud is taken; per
    direction, the ``ceil(keep_fraction * P)`` smallest are averaged, and the two means are
    added. ``keep_fraction=1`` is the plain Chamfer distance; below 1 it ignores the points
    of a partial view that have no counterpart in the other cloud (trimmed ICP's criterion).

    Args:
        x: tensor of shape ``(B, N, 3)`` or ``(N, 3)``.
        y: tensor of shape ``(B, M, 3)`` or ``(M, 3)``, batched like ``x``.
        keep_fraction: share of each direction's distances kept, in ``(0, 1]``: one number, or
            a tensor of shape ``(B,)`` giving each pair its own share (batched clouds only).

    Returns:
        Tensor of shape ``(B,)``, or a scalar tensor for unbatched clouds.

    Raises:
        ValueError: bad shapes, one cloud batched and the other not, NaN/Inf coordinates,
            different batch sizes, a ``keep_fraction`` outside ``(0, 1]`` or of the wrong shape.
    """
    _check_cloud_pair(x, y)
    # float64, so that ceil(0.9 * 100) is 90 as with Python numbers
    fraction = torch.as_tensor(keep_fraction, dtype=torch.float64, device=x.device)
    if fraction.dim() > 0 and (x.dim() != 3 or fraction.shape != x.shape[:1]):
        shapes = f"clouds {tuple(x.shape)}, keep_fraction {tuple(fraction.shape)}"
        raise ValueError(f"a keep_fraction tensor needs batched clouds and shape (B,), got {shapes}")
    if not bool(((fraction > 0) & (fraction <= 1)).all()):
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    total = 0.0
    for query, reference in ((x, y), (y, x)):
        nearest = knn_distances(query, reference)[..., 0]
        count = nearest.shape[-1]
        kept = torch.ceil(fraction * count).clamp(1, count)
        closest_first = nearest.sort(dim=-1).values
        mask = torch.arange(count, device=x.device) < kept[..., None]
        total = total + (closest_first * mask).sum(-1) / kept.to(nearest.dtype)
    return total


def weighted_chamfer_distance(
    x: torch.Tensor, y: torch.Tensor, x_weights: torch.Tensor, y_weights: torch.Tensor
) -> torch.Tensor:
    """A symmetric Chamfer distance in which each point counts by its weight.

    Per direction, the weighted mean of every point's Euclidean distance to its nearest point
    of the other cloud; the two means are added. Uniform weights give the plain Chamfer
    distance. With RPM-Net's soft assignment masses as weights, points the assignment leaves
    unmatched (no counterpart in a partial view) count little.

    Args:
        x: tensor of shape ``(B, N, 3)`` or ``(N, 3)``.
        y: tensor of shape ``(B, M, 3)`` or ``(M, 3)``, batched like ``x``.
        x_weights: tensor of shape ``(B, N)`` or ``(N,)``: non-negative, a positive sum per cloud.
        y_weights: tensor of shape ``(B, M)`` or ``(M,)``, likewise.

    Returns:
        Tensor of shape ``(B,)``, or a scalar tensor for unbatched clouds.

    Raises:
        ValueError: bad shapes, one cloud batched and the other not, NaN/Inf coordinates or
            weights, different batch sizes, negative weights or a cloud whose weights sum to 0.
    """
    _check_cloud_pair(x, y)
    total = 0.0
    for query, reference, weights, name in ((x, y, x_weights, "x_weights"), (y, x, y_weights, "y_weights")):
        if tuple(weights.shape) != tuple(query.shape[:-1]):
            raise ValueError(f"{name} must have shape {tuple(query.shape[:-1])}, got {tuple(weights.shape)}")
        if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
            raise ValueError(f"{name} must be finite and non-negative")
        mass = weights.sum(-1)
        if bool((mass <= 0).any()):
            raise ValueError(f"{name} must have a positive sum for every cloud")
        nearest = knn_distances(query, reference)[..., 0]
        total = total + (nearest * weights.to(nearest.dtype)).sum(-1) / mass.to(nearest.dtype)
    return total


def _check_cloud_pair(x: torch.Tensor, y: torch.Tensor) -> None:
    """Both clouds finite, ``(B, P, 3)`` with one batch size or both ``(P, 3)``."""
    check_points(x, "x")
    check_points(y, "y")
    if x.dim() != y.dim():
        shapes = f"{tuple(x.shape)} and {tuple(y.shape)}"
        raise ValueError(f"x and y must both be batched or both unbatched, got shapes {shapes}")
    if x.dim() == 3:
        check_same_batch(x, y, "x", "y")


def farthest_point_sampling(
    points: np.ndarray | torch.Tensor,
    n_samples: int,
    *,
    start_index: int | None = None,
) -> np.ndarray | torch.Tensor:
    """Indices of ``n_samples`` points chosen by exact farthest-point sampling (``fpsample``).

    Each new sample is the point farthest (Euclidean) from all samples chosen so far. Indices
    are always distinct: once every remaining point coincides with a sample (duplicated
    points), the remaining slots take unused indices in ascending order.
    With ``start_index=None`` the bucket/KD-line variant ("QuickFPS",
    ``fpsample.bucket_fps_kdline_sampling``, 3-30x faster than vanilla FPS on 1k-300k points,
    see ``scripts/bench_fps.py``) runs from a start point it picks itself (deterministic
    for a given cloud); an explicit ``start_index`` runs vanilla FPS from that point, since
    fpsample 1.0's bucket variants do not honour the start index they are given.

    Args:
        points: array or tensor of shape ``(N, 3)`` or ``(B, N, 3)`` (each cloud sampled on
            the CPU).
        n_samples: number of samples, ``1 <= n_samples <= N``.
        start_index: index of the first sample (of every cloud), or ``None`` (see above).

    Returns:
        Same kind as ``points``: int64 array or long tensor (on the input's device) of shape
        ``(n_samples,)`` or ``(B, n_samples)`` giving indices into each cloud.

    Raises:
        ValueError: ``n_samples`` outside ``[1, N]`` or ``start_index`` outside ``[0, N)``.
    """
    check_points(points, "points")
    num_points = points.shape[-2]
    if not 1 <= n_samples <= num_points:
        raise ValueError(f"n_samples must be between 1 and N={num_points}, got {n_samples}")
    if start_index is not None and not 0 <= start_index < num_points:
        raise ValueError(f"start_index must be in [0, {num_points}), got {start_index}")
    array = points if isinstance(points, np.ndarray) else points.detach().cpu().numpy()
    clouds = array.reshape(-1, num_points, 3)
    idx = np.stack([farthest_point_indices(cloud, n_samples, start_index) for cloud in clouds])
    idx = idx.reshape(*points.shape[:-2], n_samples)
    return idx if isinstance(points, np.ndarray) else torch.from_numpy(idx).to(points.device)


def resample_indices(
    num_points: int,
    num_samples: int,
    generator: np.random.Generator | int | None = None,
) -> np.ndarray:
    """Random indices that resample a cloud of ``num_points`` points to ``num_samples`` points.

    RPM-Net semantics: when ``num_points >= num_samples`` the indices are drawn without
    replacement (a random subset, in random order); otherwise every point appears once (in
    random order) followed by ``num_samples - num_points`` indices drawn with replacement.

    Args:
        num_points: size of the cloud, ``>= 1``.
        num_samples: number of indices wanted, ``>= 0``.
        generator: numpy Generator, seed, or ``None`` for fresh entropy.

    Returns:
        int64 array of shape ``(num_samples,)`` with values in ``[0, num_points)``.
    """
    if num_points < 1 or num_samples < 0:
        raise ValueError(f"need num_points >= 1 and num_samples >= 0, got {num_points} and {num_samples}")
    rng = np.random.default_rng(generator)
    if num_points >= num_samples:
        return rng.permutation(num_points)[:num_samples].astype(np.int64)
    extra = rng.integers(0, num_points, size=num_samples - num_points)
    return np.concatenate([rng.permutation(num_points), extra]).astype(np.int64)


def open3d_cloud(points: np.ndarray, normals: np.ndarray | None = None):
    """An Open3D ``PointCloud`` of ``points (N, 3)`` (and unit ``normals (N, 3)``), float64."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return cloud


def estimate_normals(
    points: np.ndarray,
    *,
    k: int = 30,
    radius: float | None = None,
    orient_towards: np.ndarray | None = None,
) -> np.ndarray:
    """Unit normals from local PCA (Open3D ``estimate_normals``).

    Orientation: with ``orient_towards`` every normal points towards that location (a
    camera). Otherwise normals are made consistent with Open3D's
    ``orient_normals_consistent_tangent_plane`` (a minimum spanning tree over the kNN graph,
    ~0.3 s for 10k points) and the global sign is chosen so that most normals point away from
    the centroid. When that step fails (e.g. Qhull rejects coplanar clouds), each normal
    points away from the centroid, ties (normals orthogonal to it, as on a plane) broken
    towards the cloud's least-variance axis.

    Args:
        points: array of shape ``(N, 3)``, ``N >= 3``.
        k: neighbours used for each normal (at most ``k`` within ``radius`` when given).
        radius: optional search radius (hybrid search).
        orient_towards: optional array ``(3,)`` giving the camera location.

    Returns:
        float32 array of shape ``(N, 3)`` giving unit normals.
    """
    check_points(points, "points", min_points=3, batched=False)
    if k < 3:
        raise ValueError(f"k must be at least 3 to fit a plane, got {k}")
    import open3d as o3d

    cloud = open3d_cloud(points)
    search = (
        o3d.geometry.KDTreeSearchParamKNN(k)
        if radius is None
        else o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=k)
    )
    cloud.estimate_normals(search)
    if orient_towards is not None:
        camera = np.asarray(orient_towards, dtype=np.float64).reshape(3)
        cloud.orient_normals_towards_camera_location(camera)
        normals = np.asarray(cloud.normals)
    else:
        normals = _orient_consistently(cloud, points, k)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return normals.astype(np.float32)


def _orient_consistently(cloud, points: np.ndarray, k: int) -> np.ndarray:
    """Consistently oriented normals of an Open3D cloud, pointing mostly away from the centroid."""
    outward = np.asarray(points, np.float64) - np.mean(points, axis=0)
    try:
        cloud.orient_normals_consistent_tangent_plane(k)
    except RuntimeError:
        normals = np.asarray(cloud.normals).copy()
        _, axes = np.linalg.eigh(outward.T @ outward)
        scale = np.linalg.norm(outward, axis=1, keepdims=True)
        score = np.sum(normals * outward, axis=1)
        tie = np.abs(score) <= 1e-6 * np.maximum(scale[:, 0], 1e-12)
        score[tie] = normals[tie] @ axes[:, 0]
        return np.where(score[:, None] < 0, -normals, normals)
    normals = np.asarray(cloud.normals)
    return -normals if np.sum(normals * outward) < 0 else normals


def bounding_sphere(*clouds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A sphere containing every point of every cloud.

    The centre is the centre of the joint axis-aligned bounding box; the radius is the largest
    distance from it to any point (not the minimal enclosing sphere, but at most ``sqrt(3)/2``
    of the box diagonal).

    Args:
        *clouds: one or more tensors, all of shape ``(B, N_i, 3)`` or all ``(N_i, 3)``.

    Returns:
        ``(center, radius)``: tensors of shape ``(B, 3)`` and ``(B,)`` (or ``(3,)`` and ``()``).
    """
    if not clouds:
        raise ValueError("bounding_sphere needs at least one cloud")
    for i, cloud in enumerate(clouds):
        check_points(cloud, f"clouds[{i}]")
    if len({cloud.ndim for cloud in clouds}) > 1:
        raise ValueError("clouds must be all batched (B, N, 3) or all unbatched (N, 3)")
    for i, cloud in enumerate(clouds[1:], start=1):
        if cloud.ndim == 3:
            check_same_batch(clouds[0], cloud, "clouds[0]", f"clouds[{i}]")
    lower = torch.stack([cloud.amin(dim=-2) for cloud in clouds]).amin(dim=0)
    upper = torch.stack([cloud.amax(dim=-2) for cloud in clouds]).amax(dim=0)
    center = (lower + upper) / 2
    radius = torch.stack([(cloud - center.unsqueeze(-2)).norm(dim=-1).amax(dim=-1) for cloud in clouds]).amax(dim=0)
    return center, radius


def fit_into_cube(*clouds: np.ndarray, half_extent: float = 1.0) -> tuple[list[np.ndarray], np.ndarray, float]:
    """Translate and scale clouds together so that all fit in ``[-half_extent, half_extent]^3``.

    One common map ``x' = (x - center) * scale`` is applied to every cloud (the paper scales each
    pair into ``[-1, 1]^3``): ``center`` is the centre of the joint bounding box and ``scale``
    makes its longest side exactly ``2 * half_extent``. A rigid transform ``(R, t)`` between
    the originals becomes ``(R, (t + R @ center - center) * scale)`` between the scaled clouds.

    Args:
        *clouds: one or more arrays of shape ``(N_i, 3)``.
        half_extent: half the side of the target cube, ``> 0``.

    Returns:
        ``(scaled, center, scale)``: list of scaled arrays (input dtype), float64 array
        ``(3,)``, and the float scale factor.

    Raises:
        ValueError: no clouds, ``half_extent <= 0``, or all points coincide.
    """
    if not clouds:
        raise ValueError("fit_into_cube needs at least one cloud")
    if half_extent <= 0:
        raise ValueError(f"half_extent must be positive, got {half_extent}")
    for i, cloud in enumerate(clouds):
        check_points(cloud, f"clouds[{i}]", batched=False)
    lower = np.min([cloud.min(axis=0) for cloud in clouds], axis=0).astype(np.float64)
    upper = np.max([cloud.max(axis=0) for cloud in clouds], axis=0).astype(np.float64)
    half_side = float(np.max(upper - lower)) / 2
    if half_side == 0:
        raise ValueError("cannot fit clouds whose points all coincide into a cube (zero extent)")
    center = (lower + upper) / 2
    scale = half_extent / half_side
    scaled = [((cloud - center) * scale).astype(cloud.dtype) for cloud in clouds]
    return scaled, center, scale


def scale_transform(transform: np.ndarray, center: np.ndarray, scale: float) -> np.ndarray:
    """A ``(4, 4)`` source-to-target transform expressed between clouds mapped by ``x' = (x - c) * s``
    (``center (3,)``, ``scale``): ``(R, t)`` becomes ``(R, (t + R c - c) s)`` (:func:`fit_into_cube`'s map)."""
    scaled = np.array(transform, dtype=np.float64)
    rotation = scaled[:3, :3]
    scaled[:3, 3] = (scaled[:3, 3] + rotation @ center - center) * scale
    return scaled


def hidden_point_removal(points: np.ndarray, camera: np.ndarray, *, radius_factor: float = 100.0) -> np.ndarray:
    """Indices of the points visible from ``camera`` (Katz et al. 2007, via Open3D).

    Args:
        points: array of shape ``(N, 3)``, ``N >= 4`` and not coplanar.
        camera: array of shape ``(3,)`` giving the viewpoint.
        radius_factor: spherical-flipping radius as a multiple of the cloud diameter (its
            bounding-box diagonal); larger keeps fewer, more certainly visible points.

    Returns:
        Sorted int64 array of visible point indices.
    """
    check_points(points, "points", min_points=4, batched=False)
    camera = np.asarray(camera, dtype=np.float64).reshape(3)
    cloud = open3d_cloud(points)
    diameter = float(np.linalg.norm(cloud.get_max_bound() - cloud.get_min_bound()))
    try:
        _, visible = cloud.hidden_point_removal(camera, radius_factor * diameter)
    except RuntimeError as error:
        raise ValueError(f"hidden point removal failed (degenerate cloud?): {error}") from error
    return np.sort(np.asarray(visible, dtype=np.int64))
