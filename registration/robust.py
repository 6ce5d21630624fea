"""The ``register`` default in numpy and scipy: multi-start CD-W, Welsch IRLS, fixed-scale selection.

No torch on this path (nor Open3D, numba or matplotlib): ``linereg.register`` and the
``linereg-register`` command start in about the time numpy and scipy take to import.

The first round and the polish are majorise-minimise (MM) steps of a Welsch objective: match
points to their nearest neighbours, weight each match by ``exp(-d^2 / 2 nu^2)`` and solve the
weighted Procrustes problem in closed form. A step cannot increase the objective at a fixed
``nu`` (the Welsch function is concave in ``d^2``, and new nearest neighbours only shorten the
distances), so a few dozen steps replace hundreds of gradient steps.

1. Both clouds centred (:func:`~linereg.registration.methods.run_centered`) and scaled together
   into the unit ball; FPS subsets of ``num_points`` for the polish and the selection.
2. Round 1, coarse: IRLS on CD-W (:func:`cdw_irls`; ``nu = nu0 * median`` of the nearest
   distances, recomputed every step) from every start on small FPS subsets, once with both
   directions and once with the source-to-target term alone (a partial view inside a whole
   target). All candidates of a round form one batch; merged ones are dropped.
3. Polish: Welsch IRLS of the source-to-target distances with falling fixed scales
   (:func:`welsch_irls`, :func:`polish_scales`).
4. Select the candidate with the lowest :func:`fixed_scale_cost`. When the choice is doubtful
   (a distinct rival nearly as good, a high cost, a low fitness), round 2 runs Adam on CD-W
   (:func:`cdw_adam`) from the same starts; still doubtful, round 3 searches every pose of a
   grid (:func:`pose_search`: hundreds of rotations, and for each the best translation of a
   lattice, by a one-sided Welsch cost read from a table) and runs the one-sided IRLS from the
   best distinct poses. Each round ends with the polish, and the doubt test runs over every
   candidate so far. After a doubtful first round the final choice among all candidates is the
   lowest value of the polish's own objective (Welsch at its last scale, ``polish_end`` point
   spacings; ``doubtful_select``): every candidate is a local minimum of that objective, while
   the coarser selection scale rewards a wrong pose that brings more of a partly overlapping
   view near the target (docs/registration.md).
5. Fine polish of the chosen pose when the source lies on the target (fitness at least
   ``fine_fitness``): the IRLS goes on to ``fine_end`` times the point spacing
   (:func:`fine_scales`); partly overlapping scans keep the polish's pose. Then, when the two
   clouds are independent samplings of the surface (almost no source point coincides with a
   target point), a few plane-to-plane steps (:func:`plane_to_plane_irls`, Generalized-ICP)
   remove the point-to-point fit's sampling offset.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from linereg.checks import check_points, check_transform
from linereg.fps import farthest_point_subset as fps
from linereg.registration.methods import METHODS, MethodResult, run_centered

Poses = tuple[np.ndarray, np.ndarray]
"""``(R (K, 3, 3), t (K, 3))``: ``K`` rigid transforms ``x -> R x + t``."""


def as_matrices(poses: Poses) -> np.ndarray:
    """``(K, 4, 4)`` homogeneous matrices of ``poses``."""
    rotations, translations = poses
    out = np.tile(np.eye(4), (len(rotations), 1, 1))
    out[:, :3, :3] = rotations
    out[:, :3, 3] = translations
    return out


def apply(poses: Poses, points: np.ndarray) -> np.ndarray:
    """``(K, N, 3)``: ``points (N, 3)`` moved by each of the ``K`` poses."""
    rotations, translations = poses
    return points @ rotations.transpose(0, 2, 1) + translations[:, None, :]


def weighted_procrustes(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> tuple[Poses, np.ndarray]:
    """The rigid ``(R, t)`` minimising ``sum_n w_n |R p_n + t - q_n|^2`` for each of ``K`` problems.

    Args:
        p, q: ``(K, N, 3)`` corresponding points.
        w: ``(K, N)`` non-negative weights.

    Returns:
        ``((R (K, 3, 3), t (K, 3)), valid (K,))``; ``valid`` is false where the weights sum to
        (almost) zero, and ``R, t`` are then the identity.
    """
    total = w.sum(axis=1)
    valid = total > 1e-12
    w = (w / np.where(valid, total, 1.0)[:, None])[:, None, :]
    p_mean = (w @ p)[:, 0]
    q_mean = (w @ q)[:, 0]
    cov = ((p - p_mean[:, None]) * w.transpose(0, 2, 1)).transpose(0, 2, 1) @ (q - q_mean[:, None])
    u, _, vt = np.linalg.svd(cov)
    v_ut = vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)
    sign = np.where(np.linalg.det(v_ut) < 0, -1.0, 1.0)
    vt[:, 2] *= sign[:, None]
    rotations = vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)
    rotations[~valid] = np.eye(3)
    translations = q_mean - (rotations @ p_mean[:, :, None])[:, :, 0]
    translations[~valid] = 0.0
    return (rotations, translations), valid


_REACH = 6.0
"""Nearest-neighbour searches for a Welsch weight stop at ``_REACH * nu`` (weight below ``exp(-18)``: 0)."""


def _welsch_weights(distances: np.ndarray, nu: np.ndarray | float) -> np.ndarray:
    return np.exp(-np.square(distances) / (2.0 * np.square(nu)))


def welsch_cost(distances: np.ndarray, nu: np.ndarray | float) -> np.ndarray:
    """``mean 1 - exp(-d^2 / 2 nu^2)`` over the last axis: 0 when every distance is 0, 1 when all are far."""
    return (1.0 - _welsch_weights(distances, nu)).mean(axis=-1)


def lower_median(values: np.ndarray) -> np.ndarray:
    """Median over the last axis, the lower middle value for an even count (``torch.median``'s, as CD-W's scale)."""
    middle = (values.shape[-1] - 1) // 2
    return np.partition(values, middle, axis=-1)[..., middle]


def cdw(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    src_tree: cKDTree,
    tgt_tree: cKDTree,
    two_sided: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest neighbours of CD-W at each pose, both directions, from trees built once.

    The target-to-source matches query the target moved back by the inverse pose in the tree of
    the unmoved source, so no tree is built per pose.

    Returns:
        ``d_xy (K, N)``, ``j (K, N)`` (nearest target of each moved source point), ``d_yx (K, M)``,
        ``i (K, M)`` (nearest source point of each target point), ``median (K,)`` (of both
        directions where ``two_sided``, of ``d_xy`` alone elsewhere).
    """
    rotations, translations = poses
    d_xy, j = tgt_tree.query(apply(poses, src), workers=1)
    back = (tgt[None] - translations[:, None, :]) @ rotations
    d_yx, i = src_tree.query(back, workers=1)
    median = np.where(two_sided, lower_median(np.concatenate([d_xy, d_yx], axis=1)), lower_median(d_xy))
    return d_xy, j, d_yx, i, median


def cdw_value(poses: Poses, src: np.ndarray, tgt: np.ndarray, nu: np.ndarray, two_sided: np.ndarray) -> np.ndarray:
    """CD-W at each pose with a given scale ``nu (K,)``: ``mean psi(d_xy) + [two_sided] mean psi(d_yx)``."""
    d_xy, _, d_yx, _, _ = cdw(poses, src, tgt, cKDTree(src), cKDTree(tgt), two_sided)
    return welsch_cost(d_xy, nu[:, None]) + two_sided * welsch_cost(d_yx, nu[:, None])


def merged_into_earlier(poses: Poses, two_sided: np.ndarray, merged: np.ndarray, distance: float) -> np.ndarray:
    """Which poses lie within ``distance`` of an earlier, unmerged pose with the same ``two_sided``.

    The gap of two poses is the larger of their rotations' and translations' max-entry
    differences (a chord, not an angle).

    Args:
        poses: ``K`` poses; two_sided: ``(K,)`` booleans; merged: ``(K,)`` poses already merged.

    Returns:
        ``(K,)`` booleans.
    """
    rotations, translations = poses
    gap = np.maximum(
        np.abs(rotations[:, None] - rotations[None]).max(axis=(2, 3)),
        np.abs(translations[:, None] - translations[None]).max(axis=2),
    )
    same_side = two_sided[:, None] == two_sided[None, :]
    earlier = np.tri(len(rotations), k=-1, dtype=bool)
    return ((gap < distance) & same_side & earlier & ~merged[None, :]).any(axis=1)


def cdw_irls(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    two_sided: np.ndarray,
    nu0: float,
    steps: int,
    *,
    fixed_nu: np.ndarray | None = None,
    tolerance: float = 1e-6,
    merge_distance: float = 0.0,
) -> tuple[Poses, np.ndarray]:
    """IRLS (MM) on CD-W from every pose at once: the coarse stage.

    Each step matches both ways (:func:`cdw`), weights each match by Welsch's
    ``exp(-d^2 / 2 nu^2)`` divided by its direction's point count (the objective is a mean per
    direction) and solves one weighted Procrustes problem over the union of the matches. Where
    ``two_sided`` is false only the source-to-target matches count: the model of a partial source
    inside a whole target, which is not pulled towards covering the whole shape.

    Args:
        poses: ``K`` starting poses.
        src: ``(N, 3)`` source points; tgt: ``(M, 3)`` target points.
        two_sided: ``(K,)`` booleans.
        nu0: ``nu = nu0 * median`` nearest distance of the current pose (CD-W's scale).
        steps: most IRLS steps; a pose that moves less than ``tolerance`` stops early.
        fixed_nu: ``(K,)`` scales held constant instead (then every step decreases CD-W at that scale).
        merge_distance: a pose whose rotation (as a chord: ``|R_a - R_b|`` max entry) and
            translation both lie within this of an earlier pose with the same ``two_sided``
            has merged into its basin: it stops and is flagged (0: never).

    Returns:
        ``(poses, merged (K,))``: the ``K`` final poses, and which of them merged into an earlier one.
    """
    src_tree, tgt_tree = cKDTree(src), cKDTree(tgt)
    rotations, translations = (array.copy() for array in poses)
    active = np.ones(len(rotations), dtype=bool)
    merged = np.zeros(len(rotations), dtype=bool)
    scale = np.concatenate([np.full(len(src), 1.0 / len(src)), np.full(len(tgt), 1.0 / len(tgt))])
    for _ in range(steps):
        if not active.any():
            break
        current = (rotations[active], translations[active])
        sides = two_sided[active]
        d_xy, j, d_yx, i, median = cdw(current, src, tgt, src_tree, tgt_tree, sides)
        nu = np.maximum(nu0 * median if fixed_nu is None else fixed_nu[active], 1e-12)[:, None]
        weights = np.concatenate([_welsch_weights(d_xy, nu), _welsch_weights(d_yx, nu) * sides[:, None]], axis=1)
        p = np.concatenate([np.broadcast_to(src, (len(j), *src.shape)), src[i]], axis=1)
        q = np.concatenate([tgt[j], np.broadcast_to(tgt, (len(i), *tgt.shape))], axis=1)
        (new_r, new_t), valid = weighted_procrustes(p, q, weights * scale)
        new_r[~valid], new_t[~valid] = current[0][~valid], current[1][~valid]
        moved = np.abs(new_r - current[0]).max(axis=(1, 2)) + np.abs(new_t - current[1]).max(axis=1)
        rotations[active], translations[active] = new_r, new_t
        active[np.flatnonzero(active)[moved < tolerance]] = False
        if merge_distance > 0:
            duplicate = merged_into_earlier((rotations, translations), two_sided, merged, merge_distance)
            merged |= duplicate
            active &= ~duplicate
    return (rotations, translations), merged


def cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` matrices ``[v]_x`` of vectors ``(..., 3)``: ``[v]_x u = v x u``."""
    matrices = np.zeros((*vectors.shape, 3))
    matrices[..., 0, 1], matrices[..., 0, 2], matrices[..., 1, 2] = -vectors[..., 2], vectors[..., 1], -vectors[..., 0]
    return matrices - np.swapaxes(matrices, -1, -2)


def rodrigues(rotvecs: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` rotation matrices of rotation vectors ``(K, 3)`` (axis times angle)."""
    angle = np.linalg.norm(rotvecs, axis=1)[:, None, None]
    k = cross_matrices(rotvecs)
    small = angle < 1e-8
    sin = np.where(small, 1.0, np.sin(angle) / np.where(small, 1.0, angle))
    cos = np.where(small, 0.5, (1.0 - np.cos(angle)) / np.where(small, 1.0, angle) ** 2)
    return np.eye(3) + sin * k + cos * (k @ k)


def cdw_gradient(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    src_tree: cKDTree,
    tgt_tree: cKDTree,
    two_sided: np.ndarray,
    nu0: float,
) -> np.ndarray:
    """Gradient ``(K, 6)`` (rotation, then translation) of CD-W under a left perturbation
    ``T <- exp(xi) T`` at ``xi = 0``, with ``nu = nu0 * median`` held constant (as the loss detaches it)."""
    d_xy, j, d_yx, i, median = cdw(poses, src, tgt, src_tree, tgt_tree, two_sided)
    nu_sq = np.square(np.maximum(nu0 * median, 1e-12))[:, None, None]
    moved = apply(poses, src)
    force_xy = (moved - tgt[j]) * _welsch_weights(d_xy, np.sqrt(nu_sq[:, :, 0]))[..., None] / (nu_sq * len(src))
    matched = np.take_along_axis(moved, i[..., None], axis=1)
    weights_yx = _welsch_weights(d_yx, np.sqrt(nu_sq[:, :, 0])) * two_sided[:, None]
    force_yx = (matched - tgt) * weights_yx[..., None] / (nu_sq * len(tgt))
    rotation = np.cross(moved, force_xy).sum(axis=1) + np.cross(matched, force_yx).sum(axis=1)
    return np.concatenate([rotation, force_xy.sum(axis=1) + force_yx.sum(axis=1)], axis=1)


def cdw_adam(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    two_sided: np.ndarray,
    nu0: float,
    steps: int,
    lr: float,
    *,
    merge_distance: float = 0.0,
) -> tuple[Poses, np.ndarray]:
    """Adam on CD-W from every pose at once, in the tangent space of the current pose
    (``T <- exp(-step) T``, moments kept per pose), with a cosine-decaying learning rate.

    Its fixed-length steps slide across shallow barriers that stop IRLS (an MM method descends
    into the nearest basin): the coarse stage that finds the basin (docs/registration.md).
    Arguments and ``merge_distance`` as :func:`cdw_irls`.

    Returns:
        ``(poses, merged (K,))``.
    """
    src_tree, tgt_tree = cKDTree(src), cKDTree(tgt)
    rotations, translations = (array.copy() for array in poses)
    count = len(rotations)
    first, second = np.zeros((count, 6)), np.zeros((count, 6))
    active = np.ones(count, dtype=bool)
    merged = np.zeros(count, dtype=bool)
    for step in range(steps):
        if not active.any():
            break
        rate = lr * 0.5 * (1.0 + np.cos(np.pi * step / steps))
        current = (rotations[active], translations[active])
        grad = cdw_gradient(current, src, tgt, src_tree, tgt_tree, two_sided[active], nu0)
        first[active] = 0.9 * first[active] + 0.1 * grad
        second[active] = 0.999 * second[active] + 0.001 * np.square(grad)
        update = (
            -rate
            * (first[active] / (1 - 0.9 ** (step + 1)))
            / (np.sqrt(second[active] / (1 - 0.999 ** (step + 1))) + 1e-8)
        )
        turn = rodrigues(update[:, :3])
        rotations[active] = turn @ current[0]
        translations[active] = (turn @ current[1][:, :, None])[:, :, 0] + update[:, 3:]
        if merge_distance > 0:
            duplicate = merged_into_earlier((rotations, translations), two_sided, merged, merge_distance)
            merged |= duplicate
            active &= ~duplicate
    return (rotations, translations), merged


def welsch_irls(
    poses: Poses, src: np.ndarray, tgt_tree: cKDTree, nus: np.ndarray, settle: int = 0, tolerance: float = 1e-6
) -> Poses:
    """Robust point-to-point ICP: one Welsch-weighted Procrustes step per scale in ``nus``,
    matching every source point ``(N, 3)`` to its nearest target point; ``K`` poses at once.
    Then up to ``settle`` more steps at the last scale, each pose until it moves less than
    ``tolerance`` (ICP crawls along directions in which the surfaces slide on each other)."""
    tgt = np.concatenate([tgt_tree.data, np.zeros((1, 3))])  # scipy's index of "none in range": weight 0
    rotations, translations = (array.copy() for array in poses)
    active = np.ones(len(rotations), dtype=bool)
    schedule = list(nus) + [nus[-1]] * settle if len(nus) else []
    for step, nu in enumerate(schedule):
        current = (rotations[active], translations[active])
        distances, idx = tgt_tree.query(apply(current, src), distance_upper_bound=_REACH * nu, workers=1)
        weights = _welsch_weights(distances, nu)
        (new_r, new_t), valid = weighted_procrustes(np.broadcast_to(src, (len(idx), *src.shape)), tgt[idx], weights)
        new_r[~valid], new_t[~valid] = current[0][~valid], current[1][~valid]
        rotations[active], translations[active] = new_r, new_t
        if step >= len(nus) - 1:
            moved = np.abs(new_r - current[0]).max(axis=(1, 2)) + np.abs(new_t - current[1]).max(axis=1)
            active[np.flatnonzero(active)[moved < tolerance]] = False
            if not active.any():
                break
    return rotations, translations


def pca_frames(points: np.ndarray, k: int = 10) -> np.ndarray:
    """Local principal axes ``(N, 3, 3)`` of ``points (N, 3)``: column ``a`` of entry ``i`` is the
    axis of the ``a``-th smallest variance of point ``i``'s ``k`` nearest points (itself included)."""
    _, index = cKDTree(points).query(points, k=min(k, len(points)), workers=1)
    neighbours = points[index] - points[index].mean(axis=1, keepdims=True)
    return np.linalg.eigh(neighbours.transpose(0, 2, 1) @ neighbours)[1]


def pca_normals(points: np.ndarray, k: int = 10) -> np.ndarray:
    """Unoriented unit normals ``(N, 3)`` of ``points (N, 3)``: the least principal axis of each
    point's ``k`` nearest points (itself included). Numpy twin of Open3D's estimate, without orientation."""
    return pca_frames(points, k)[:, :, 0]


def surface_covariances(points: np.ndarray, k: int = 10, epsilon: float = 1e-2) -> np.ndarray:
    """Plane covariances ``(N, 3, 3)`` of ``points (N, 3)`` for :func:`plane_to_plane_irls`: each
    point's local frame (:func:`pca_frames`) with variances ``(epsilon, 1, 1)``, a disc of unit
    spread along the surface and ``epsilon`` across it (Segal et al., Generalized-ICP, 2009)."""
    frames = pca_frames(points, k)
    return np.einsum("nij,j,nkj->nik", frames, np.array([epsilon, 1.0, 1.0]), frames)


def plane_to_plane_irls(
    poses: Poses,
    src: np.ndarray,
    src_covariances: np.ndarray,
    tgt_tree: cKDTree,
    tgt_covariances: np.ndarray,
    nu: float,
    steps: int,
) -> Poses:
    """Robust plane-to-plane ICP (Generalized-ICP): ``steps`` Gauss-Newton steps on
    ``sum_i w_i r_i^T (C_j + R C_i R^T)^-1 r_i``, ``r_i = R p_i + t - q_j``, for ``K`` poses at once.

    ``q_j`` is the nearest target point of the moved source point ``p_i`` (``src (N, 3)``),
    ``C_i``/``C_j`` their :func:`surface_covariances` (``(N, 3, 3)``, ``(M, 3, 3)``), ``w_i``
    Welsch's weight of the point distance at scale ``nu``. The model of two independent samplings
    of one surface: each point lies somewhere on its local plane, on both sides, so the residual
    carries neither the point-to-point fit's sampling offset nor point-to-plane's one-sided bias.
    """
    tgt = np.concatenate([tgt_tree.data, np.zeros((1, 3))])  # scipy's index of "none in range": weight 0
    tgt_covariances = np.concatenate([tgt_covariances, np.eye(3)[None]])
    rotations, translations = (array.copy() for array in poses)
    for _ in range(steps):
        moved = apply((rotations, translations), src)
        distances, idx = tgt_tree.query(moved, distance_upper_bound=_REACH * nu, workers=1)
        rotated = np.einsum("kab,nbc,kdc->knad", rotations, src_covariances, rotations)
        information = np.linalg.inv(tgt_covariances[idx] + rotated)
        residual = moved - tgt[idx]
        weights = _welsch_weights(distances, nu)
        jacobian = np.concatenate([-cross_matrices(moved), np.broadcast_to(np.eye(3), (*moved.shape, 3))], axis=-1)
        weighted = np.einsum("kn,knab,knbj->knaj", weights, information, jacobian)
        hessian = np.einsum("knai,knaj->kij", jacobian, weighted) + 1e-12 * np.eye(6)
        step = -np.linalg.solve(hessian, np.einsum("knaj,kna->kj", weighted, residual)[..., None])[..., 0]
        turn = rodrigues(step[:, :3])
        rotations = turn @ rotations
        translations = (turn @ translations[:, :, None])[:, :, 0] + step[:, 3:]
    return rotations, translations


def fixed_scale_cost(poses: Poses, src: np.ndarray, tgt_tree: cKDTree, nu: float) -> np.ndarray:
    """Welsch cost of every source point's nearest target distance with a FIXED scale ``nu``.

    ``mean_i 1 - exp(-d_i^2 / 2 nu^2)``: 0 when every source point lies on the target, 1 when
    none is near it. Unlike the paper's median-scaled metrics its value compares poses.

    Returns:
        ``(K,)`` costs in ``[0, 1]``.
    """
    distances, _ = tgt_tree.query(apply(poses, src), distance_upper_bound=_REACH * nu, workers=1)
    return welsch_cost(distances, nu)


def cube_rotations() -> np.ndarray:
    """The 24 rotations of the cube (signed axis permutations with determinant +1), the
    identity first, as ``(24, 3, 3)`` float64 matrices."""
    rotations = [np.eye(3)]
    for permutation in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), permutation] = signs
            if np.linalg.det(matrix) > 0 and not np.allclose(matrix, np.eye(3)):
                rotations.append(matrix)
    return np.stack(rotations)


def spread_rotations(count: int) -> np.ndarray:
    """``count`` rotations spread evenly over SO(3) (the super-Fibonacci spiral of Alexa, CVPR
    2022: deterministic, no clusters), as ``(count, 3, 3)`` matrices."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    s = np.arange(count) + 0.5
    small, large = np.sqrt(s / count), np.sqrt(1.0 - s / count)
    alpha, beta = 2.0 * np.pi * s / np.sqrt(2.0), 2.0 * np.pi * s / 1.533751168755204288118041
    x, y, z, w = small * np.sin(alpha), small * np.cos(alpha), large * np.sin(beta), large * np.cos(beta)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def pose_search(
    rotations: np.ndarray, src: np.ndarray, tgt: np.ndarray, *, radius: float, spacing: float, nu: float, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """For every rotation, the translation of a lattice with the lowest one-sided Welsch cost.

    The cost ``mean_i 1 - exp(-d_i^2 / 2 nu^2)`` of the moved source points' distances ``d_i`` to
    the target is read from a table of its value at the centres of cubic cells of side ``cell``
    (each point counts in its nearest cell), so that every pose costs one look-up per point.

    Args:
        rotations: ``(R, 3, 3)``.
        src: ``(N, 3)`` source points inside the unit ball; tgt: ``(M, 3)`` target points.
        radius: largest translation; spacing: step of the translation lattice (rounded to whole cells).
        nu: Welsch scale of the cost; cell: side of the table's cells.

    Returns:
        ``translations (R, 3)`` and their costs ``(R,)``.

    Raises:
        ValueError: a source point outside the unit ball (the table covers the unit ball plus ``radius``).
    """
    if np.linalg.norm(src, axis=1).max() > 1.0 + 1e-9:
        raise ValueError("pose_search: the source points must lie inside the unit ball")
    half = int(np.ceil((1.0 + radius) / cell)) + 1
    side = 2 * half + 1
    axis = cell * np.arange(-half, half + 1)
    centres = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    distances, _ = cKDTree(tgt).query(centres, distance_upper_bound=_REACH * nu, workers=1)
    table = 1.0 - _welsch_weights(distances, nu)
    step = max(round(spacing / cell), 1)
    reach = int(radius / (step * cell) + 1e-9)
    lattice = step * np.stack(np.meshgrid(*[np.arange(-reach, reach + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    lattice = lattice[np.linalg.norm(lattice * cell, axis=1) <= radius + 1e-9]
    shift = (lattice[:, 0] * side + lattice[:, 1]) * side + lattice[:, 2]
    translations, costs = np.empty((len(rotations), 3)), np.empty(len(rotations))
    for chunk in np.array_split(np.arange(len(rotations)), max(len(rotations) // 32, 1)):
        cells = np.rint(src @ rotations[chunk].transpose(0, 2, 1) / cell).astype(np.int64) + half
        index = (cells[..., 0] * side + cells[..., 1]) * side + cells[..., 2]
        cost = table[index[:, None, :] + shift[None, :, None]].mean(axis=2)
        best = cost.argmin(axis=1)
        translations[chunk] = lattice[best] * cell
        costs[chunk] = cost[np.arange(len(chunk)), best]
    return translations, costs


def distinct_best(rotations: np.ndarray, costs: np.ndarray, count: int, gap_deg: float) -> np.ndarray:
    """Indices of up to ``count`` lowest-cost rotations, each more than ``gap_deg`` from every one before it."""
    chosen: list[int] = []
    for index in np.argsort(costs, kind="stable"):
        if not chosen or (rotation_gap_deg(rotations[chosen], rotations[index]) > gap_deg).all():
            chosen.append(int(index))
            if len(chosen) == count:
                break
    return np.array(chosen, dtype=np.int64)


def axis_rotations(count: int, angle_deg: float = 90.0) -> np.ndarray:
    """The identity, then rotations by ``angle_deg`` about +x, +y, +z, -x, -y, -z (the first
    ``count``, 1..7): the first-round starts, as ``(count, 3, 3)`` matrices."""
    if not 1 <= count <= 7:
        raise ValueError(f"starts must be in 1..7 (identity and +-angle about 3 axes), got {count}")
    angle = np.deg2rad(angle_deg)
    out = [np.eye(3)]
    for sign, axis in itertools.product((1.0, -1.0), range(3)):
        k = np.zeros((3, 3))
        a, b = (axis + 1) % 3, (axis + 2) % 3
        k[b, a], k[a, b] = sign, -sign
        out.append(np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k))
    return np.stack(out[:count])


def rotation_gap_deg(rotations: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Angles (degrees) between each of ``rotations (K, 3, 3)`` and ``reference (3, 3)``."""
    cos = (np.einsum("kij,ij->k", rotations, reference) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def point_spacing(points: np.ndarray, tree: cKDTree | None = None) -> float:
    """Median distance of a point of ``points (N, 3)`` to its nearest other point."""
    distances, _ = (tree or cKDTree(points)).query(points, k=2, workers=1)
    return float(np.median(distances[:, 1]))


def alignment_quality(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray, threshold: float) -> dict[str, float]:
    """Open3D's registration quality of ``transform (4, 4)`` mapping ``src (N, 3)`` onto ``tgt (M, 3)``.

    Returns:
        ``fitness`` (fraction of source points with a target point within ``threshold``) and
        ``inlier_rmse`` (RMS distance of those points; 0 when there are none).
    """
    moved = np.asarray(src, dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
    distances, _ = cKDTree(np.asarray(tgt, dtype=np.float64)).query(moved, workers=1)
    inliers = distances <= threshold
    rmse = float(np.sqrt(np.square(distances[inliers]).mean())) if inliers.any() else 0.0
    return {"fitness": float(inliers.mean()), "inlier_rmse": rmse}


def degeneracy(points: np.ndarray, name: str) -> str | None:
    """``None`` for a cloud spread in 2 or 3 directions; a warning for a collinear one.

    Raises:
        ValueError: all points coincide (no direction at all), naming the cloud.
    """
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    scale = max(float(np.abs(points).max()), 1e-300)
    if singular[0] <= 1e-9 * scale * np.sqrt(len(points)):
        raise ValueError(f"{name}: all {len(points)} points coincide; no rotation can be determined")
    if singular[1] <= 1e-6 * singular[0]:
        return f"{name}: the {len(points)} points are collinear; the rotation about their line is arbitrary"
    return None


@dataclass(frozen=True)
class RobustOptions:
    """Settings of :class:`RobustRegistration` (lengths in the unit ball of the centred pair).

    Attributes:
        starts: initial rotations of the first two rounds (:func:`axis_rotations`).
        coarse_points: FPS size of the source in the coarse stage (the target gets twice).
        coarse_sides: every start runs once per entry: ``"both"`` (CD-W, both directions) and/or
            ``"source"`` (the source-to-target term alone: a partial view inside a whole target).
        coarse_nu0: CD-W's ``nu0`` (a wide window: robust to partial overlap).
        coarse_steps: most IRLS steps of CD-W from every start in the first round (:func:`cdw_irls`).
        explore_steps: Adam steps of CD-W from every start in the later rounds (:func:`cdw_adam`).
        explore_lr: peak learning rate (cosine decay) of those Adam steps.
        merge_distance: coarse candidates this close (rotation entries and translation) to an
            earlier one with the same coarse loss stop and are not polished.
        polish_steps: Welsch IRLS steps from every coarse result with :func:`polish_scales`.
        polish_nu: first IRLS scale.
        polish_end: last IRLS scale, times the target's median point spacing.
        polish_settle: most further IRLS steps at the last scale, each candidate until it stops moving.
        fine_end: when the chosen pose has a fitness of at least ``fine_fitness`` (the source lies
            on the target: a view inside the whole), its polish goes on with scales falling from
            ``polish_end`` to this, times the spacing (:func:`fine_scales`). A partial overlap
            (real scans: fitness 0.70-0.73 on 3DMatch) stays at ``polish_end``.
        fine_fitness: that fitness, within ``fitness_spacings`` target point spacings.
        plane_steps: plane-to-plane steps (:func:`plane_to_plane_irls`) after the fine polish when the
            clouds are independent samplings of the surface: fewer than ``coincident_share`` of
            the source points lie within ``coincident_distance`` target point spacings of a target
            point (clouds cut from one sampling share points; a point-to-point fit is exact there).
            0: never.
        plane_nu: Welsch scale of those steps, in target point spacings.
        plane_neighbours, plane_epsilon: the points of each cloud's local planes and their
            thickness (:func:`surface_covariances`).
        coincident_distance, coincident_share: that test.
        select_nu: scale of the selection cost :func:`fixed_scale_cost`.
        doubtful_select: the final choice after a doubtful first round: ``"polish"``, the
            lowest polish objective (:func:`fixed_scale_cost` at the polish's last scale,
            ``polish_end`` target point spacings), or ``"fixed"``, the lowest cost at ``select_nu``.
        doubt_ratio: the pose is doubtful when another candidate more than ``distinct_deg``
            away costs less than this factor times the best cost, or the best cost exceeds
            ``max_cost``, or fewer than ``min_fitness`` of the source points lie within
            ``fitness_spacings`` target point spacings of the target. A doubtful pose sends the
            solver to the next round: 2, Adam from the same starts; 3, the pose search
            (``rounds`` caps them).
        distinct_deg: rotation gap between two candidates that count as different basins.
        max_cost: selection cost above which the fit itself is doubtful.
        min_fitness: fitness below which the fit is doubtful (a right pose of a view inside the
            whole target scores 0.99-1, a wrong basin 0.7-0.87: docs/registration.md).
        fitness_spacings: inlier distance of that fitness, in target point spacings.
        search_rotations: rotations of the third round's pose search (:func:`spread_rotations`).
        search_radius: largest translation of that search; search_spacing: its translation step.
        search_points: FPS size of the source in the search.
        search_nu: Welsch scale of the search's cost; search_cell: cell side of its cost table.
        search_keep: best distinct poses of the search (``distinct_deg`` apart) from which the
            one-sided coarse IRLS runs.
        rounds: most rounds (1..3).
    """

    starts: int = 4
    coarse_points: int = 256
    coarse_sides: tuple[str, ...] = ("both", "source")
    coarse_nu0: float = 2.0
    coarse_steps: int = 80
    explore_steps: int = 100
    explore_lr: float = 0.03
    merge_distance: float = 0.01
    polish_steps: int = 20
    polish_nu: float = 0.05
    polish_end: float = 0.3
    polish_settle: int = 60
    fine_end: float = 0.1
    fine_fitness: float = 0.95
    plane_steps: int = 10
    plane_nu: float = 1.0
    plane_neighbours: int = 10
    plane_epsilon: float = 0.01
    coincident_distance: float = 0.02
    coincident_share: float = 0.01
    select_nu: float = 0.03
    doubtful_select: str = "polish"
    doubt_ratio: float = 1.25
    distinct_deg: float = 10.0
    max_cost: float = 0.5
    min_fitness: float = 0.985
    fitness_spacings: float = 3.0
    search_rotations: int = 600
    search_radius: float = 0.5
    search_spacing: float = 0.1
    search_points: int = 64
    search_nu: float = 0.07
    search_cell: float = 0.05
    search_keep: int = 24
    rounds: int = 3

    def __post_init__(self) -> None:
        positive = (
            "coarse_points",
            "coarse_nu0",
            "explore_lr",
            "polish_nu",
            "polish_end",
            "fine_end",
            "plane_nu",
            "plane_epsilon",
            "coincident_distance",
            "select_nu",
            "distinct_deg",
            "max_cost",
            "fitness_spacings",
            "search_radius",
            "search_rotations",
            "search_spacing",
            "search_points",
            "search_nu",
            "search_cell",
            "search_keep",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("coarse_steps", "explore_steps", "polish_steps", "polish_settle", "merge_distance", "plane_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("min_fitness", "fine_fitness", "coincident_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.plane_neighbours < 3:
            raise ValueError(f"plane_neighbours must be >= 3 (a plane needs 3 points), got {self.plane_neighbours}")
        if self.doubt_ratio < 1:
            raise ValueError(f"doubt_ratio must be >= 1, got {self.doubt_ratio}")
        if self.doubtful_select not in ("polish", "fixed"):
            raise ValueError(f"doubtful_select must be 'polish' or 'fixed', got {self.doubtful_select!r}")
        if self.rounds not in (1, 2, 3):
            raise ValueError(f"rounds must be 1, 2 or 3, got {self.rounds}")
        sides = tuple(self.coarse_sides)
        if not sides or set(sides) - {"both", "source"} or len(set(sides)) < len(sides):
            raise ValueError(f"coarse_sides must be distinct entries of 'both' and 'source', got {self.coarse_sides!r}")
        object.__setattr__(self, "coarse_sides", sides)
        axis_rotations(self.starts)


def options_from(options: RobustOptions | Mapping[str, Any] | None, kind: type = RobustOptions):
    """``options`` as a ``kind`` dataclass; a mapping with an unknown field is a ``TypeError`` naming it."""
    if options is None:
        return kind()
    if isinstance(options, kind):
        return options
    known = {f.name for f in fields(kind)}
    unknown = set(options) - known
    if unknown:
        raise TypeError(f"unknown option(s) {sorted(unknown)}; known: {sorted(known)}")
    return kind(**options)


def polish_scales(options: Any, spacing: float) -> np.ndarray:
    """Welsch scales of the IRLS polish: ``polish_steps`` values falling geometrically from
    ``polish_nu`` to ``polish_end`` times the target's point ``spacing`` over the first half,
    then held (the last steps settle at the fine scale)."""
    if options.polish_steps == 0:
        return np.zeros(0)
    fine = min(options.polish_end * spacing, options.polish_nu)
    falling = np.geomspace(options.polish_nu, fine, max((options.polish_steps + 1) // 2, 1))
    return np.concatenate([falling, np.full(options.polish_steps - len(falling), fine)])[: options.polish_steps]


def fine_scales(options: Any, spacing: float) -> np.ndarray:
    """Welsch scales of the fine polish of a pose whose source lies on the target: the geometric
    sequence of ``(polish_steps + 1) // 2`` values from ``polish_end`` to ``fine_end`` times the
    target's point ``spacing``, less its first (the polish ended there); empty when
    ``fine_end >= polish_end`` or ``polish_steps`` is 0."""
    if options.polish_steps == 0 or options.fine_end >= options.polish_end:
        return np.zeros(0)
    count = max((options.polish_steps + 1) // 2, 2)
    start = min(options.polish_end * spacing, options.polish_nu)
    return np.geomspace(start, min(options.fine_end * spacing, start), count)[1:]


class RobustRegistration:
    """The ``register`` default (numpy/scipy): multi-start IRLS on CD-W, Welsch IRLS polish,
    fixed-scale selection; when doubtful, Adam on CD-W, then a pose search (module docstring).

    The result's ``info`` holds ``fitness`` and ``inlier_rmse`` (Open3D's definitions, within
    ``fitness_threshold`` in input units; default 3 times the target's median point spacing),
    ``converged`` (the final choice is not doubtful), ``confidence`` (``1 - best cost / cost of
    the best distinct basin``, by the cost that chose it; 1 without a rival), ``rounds``, ``starts``
    (coarse candidates of all rounds: starts x coarse sides), ``candidates`` (those polished: not
    merged), the chosen pose's ``cost`` at ``select_nu``, ``selection`` (``"fixed"``, or
    ``"polish"`` after a doubtful first round: ``doubtful_select``), ``fine`` (the chosen pose got
    the fine polish), ``coincident`` (after it: the share of source points on a target point;
    ``None`` without it), ``plane`` (the plane-to-plane steps ran) and ``warnings``
    (collinear clouds).

    Args:
        options: :class:`RobustOptions` or a mapping of its fields.
        num_points: FPS size of each cloud for the polish and the selection.
        device: ``"cpu"`` only (this solver is numpy); ``robust_adam`` runs on torch devices.
        fitness_threshold: inlier distance of ``fitness`` / ``inlier_rmse`` in input units.
        center: register centred clouds.
    """

    def __init__(
        self,
        options: RobustOptions | Mapping[str, Any] | None = None,
        num_points: int | None = 2048,
        device: str = "cpu",
        fitness_threshold: float | None = None,
        center: bool = True,
    ) -> None:
        if str(device) != "cpu":
            raise ValueError(
                f"device={device!r}: the robust solver runs on the CPU (numpy); "
                "method=robust_adam runs the torch version on any device"
            )
        if num_points is not None and num_points < 3:
            raise ValueError(f"num_points must be >= 3 or None, got {num_points}")
        if fitness_threshold is not None and not fitness_threshold > 0:
            raise ValueError(f"fitness_threshold must be > 0 or None, got {fitness_threshold}")
        self.options = options_from(options)
        self.num_points = num_points
        self.fitness_threshold = fitness_threshold
        self.center = center

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None, *, init: np.ndarray | None = None) -> MethodResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)``; ``init (4, 4)`` is an initial guess applied
        to the source first (the multi-start then explores around it)."""
        check_points(src, "source", batched=False)
        check_points(tgt, "target", batched=False)
        notes = [note for note in (degeneracy(src, "source"), degeneracy(tgt, "target")) if note is not None]
        for note in notes:
            warnings.warn(note, stacklevel=2)
        src = np.asarray(src, dtype=np.float64)
        tgt = np.asarray(tgt, dtype=np.float64)
        if init is not None:
            init = np.asarray(init, dtype=np.float64)
            check_transform(init, "init")
            src = src @ init[:3, :3].T + init[:3, 3]
        result = run_centered(self._solve, src, tgt, center=self.center)
        tgt_fit = fps(tgt, self.num_points)
        threshold = self.fitness_threshold or 3.0 * point_spacing(tgt_fit)
        quality = alignment_quality(fps(src, self.num_points), tgt_fit, result.transform, threshold)
        transform = result.transform if init is None else result.transform @ init
        info = {**result.info, **quality, "fitness_threshold": threshold, "warnings": notes}
        return MethodResult(transform=transform, seconds=result.seconds, info=info)

    def _round(self, number: int, src, tgt_tree, src_coarse, tgt_coarse, nus):
        """Round ``number`` (1, 2, 3): coarse stage from its starts, then the polish: candidates,
        their costs ``(K,)`` and the number of coarse candidates."""
        options = self.options
        if number == 3:
            initial, sides = self._searched_poses(src_coarse, tgt_coarse)
        else:
            starts = axis_rotations(options.starts)
            sides = np.repeat([side == "both" for side in options.coarse_sides], len(starts))
            initial = (np.tile(starts, (len(options.coarse_sides), 1, 1)), np.zeros((len(sides), 3)))
        if number == 2:
            poses, merged = cdw_adam(
                initial,
                src_coarse,
                tgt_coarse,
                sides,
                options.coarse_nu0,
                options.explore_steps,
                options.explore_lr,
                merge_distance=options.merge_distance,
            )
        else:
            poses, merged = cdw_irls(
                initial,
                src_coarse,
                tgt_coarse,
                sides,
                options.coarse_nu0,
                options.coarse_steps,
                merge_distance=options.merge_distance,
            )
        poses = welsch_irls((poses[0][~merged], poses[1][~merged]), src, tgt_tree, nus, options.polish_settle)
        return poses, fixed_scale_cost(poses, src, tgt_tree, options.select_nu), len(sides)

    def _searched_poses(self, src_coarse, tgt_coarse) -> tuple[Poses, np.ndarray]:
        """The third round's starts: the best distinct poses of :func:`pose_search`, each with the
        one-sided coarse loss (the search places the view; the two-sided loss would pull it to cover the target)."""
        options = self.options
        rotations = spread_rotations(options.search_rotations)
        translations, costs = pose_search(
            rotations,
            fps(src_coarse, options.search_points),
            tgt_coarse,
            radius=options.search_radius,
            spacing=options.search_spacing,
            nu=options.search_nu,
            cell=options.search_cell,
        )
        best = distinct_best(rotations, costs, options.search_keep, options.distinct_deg)
        return (rotations[best], translations[best]), np.zeros(len(best), dtype=bool)

    def _doubt(
        self, poses: Poses, costs: np.ndarray, src, tgt_tree, inlier_distance, best: int | None = None, ranking=None
    ) -> tuple[bool, float, float]:
        """``(doubtful, confidence, fitness)`` of candidate ``best`` (default: the lowest cost), judged
        by the selection ``costs (K,)`` (see :class:`RobustOptions`); ``confidence`` compares the
        values of ``ranking (K,)``, the cost that chose it (default: ``costs``)."""
        options = self.options
        best = int(costs.argmin()) if best is None else best
        ranking = costs if ranking is None else ranking
        distances, _ = tgt_tree.query(apply((poses[0][best : best + 1], poses[1][best : best + 1]), src)[0], workers=1)
        fitness = float((distances <= inlier_distance).mean())
        poor = float(costs[best]) > options.max_cost or fitness < options.min_fitness
        rivals = rotation_gap_deg(poses[0], poses[0][best]) > options.distinct_deg
        if not rivals.any():
            return poor, 1.0, fitness
        doubtful = poor or float(costs[rivals].min()) < options.doubt_ratio * float(costs[best])
        return doubtful, 1.0 - float(ranking[best]) / max(float(ranking[rivals].min()), 1e-12), fitness

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        options = self.options
        src_s, tgt_s = fps(src, self.num_points), fps(tgt, self.num_points)
        radius = float(max(np.linalg.norm(src_s, axis=1).max(), np.linalg.norm(tgt_s, axis=1).max(), 1e-12))
        src_s, tgt_s = src_s / radius, tgt_s / radius
        src_coarse, tgt_coarse = fps(src_s, options.coarse_points), fps(tgt_s, 2 * options.coarse_points)
        tgt_tree = cKDTree(tgt_s)
        spacing = point_spacing(tgt_s, tgt_tree)
        nus = polish_scales(options, spacing)
        inlier_distance = options.fitness_spacings * spacing
        poses, costs, starts = self._round(1, src_s, tgt_tree, src_coarse, tgt_coarse, nus)
        doubtful, confidence, fitness = self._doubt(poses, costs, src_s, tgt_tree, inlier_distance)
        rounds = 1
        while doubtful and rounds < options.rounds:
            rounds += 1
            more, more_costs, more_starts = self._round(rounds, src_s, tgt_tree, src_coarse, tgt_coarse, nus)
            poses = tuple(np.concatenate([a, b]) for a, b in zip(poses, more, strict=True))
            costs, starts = np.concatenate([costs, more_costs]), starts + more_starts
            doubtful, confidence, fitness = self._doubt(poses, costs, src_s, tgt_tree, inlier_distance)
        best = int(costs.argmin())
        selection = "fixed"
        if rounds > 1 and options.doubtful_select == "polish" and len(nus):
            ranking = fixed_scale_cost(poses, src_s, tgt_tree, float(nus[-1]))
            best, selection = int(ranking.argmin()), "polish"
            doubtful, confidence, fitness = self._doubt(
                poses, costs, src_s, tgt_tree, inlier_distance, best=best, ranking=ranking
            )
        chosen = (poses[0][best : best + 1], poses[1][best : best + 1])
        fine_nus = fine_scales(options, spacing)
        fine = fitness >= options.fine_fitness and len(fine_nus) > 0
        if fine:
            chosen = welsch_irls(chosen, src_s, tgt_tree, fine_nus, options.polish_settle)
        coincident, plane = None, False
        if fine and options.plane_steps > 0:
            distances, _ = tgt_tree.query(apply(chosen, src_s)[0], workers=1)
            coincident = float((distances <= options.coincident_distance * spacing).mean())
            plane = coincident < options.coincident_share
            if plane:
                k, epsilon = options.plane_neighbours, options.plane_epsilon
                chosen = plane_to_plane_irls(
                    chosen,
                    src_s,
                    surface_covariances(src_s, k, epsilon),
                    tgt_tree,
                    surface_covariances(tgt_s, k, epsilon),
                    options.plane_nu * spacing,
                    options.plane_steps,
                )
        transform = as_matrices(chosen)[0]
        transform[:3, 3] *= radius
        info = {
            "converged": not doubtful,
            "confidence": confidence,
            "cost": float(costs[best]),
            "rounds": rounds,
            "starts": starts,
            "candidates": len(costs),
            "selection": selection,
            "fine": fine,
            "coincident": coincident,
            "plane": plane,
        }
        return MethodResult(transform=transform, info=info)


METHODS.register("robust")(RobustRegistration)
