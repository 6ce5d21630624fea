"""Plane-to-plane steps (Generalized-ICP) that end the ``register`` default on independent samplings (numpy).

A point-to-point fit of two independent samplings of one surface stalls at a sampling offset:
each source point is pulled to a target sample, not to the surface. Modelling each point as a
thin disc along its local plane (Segal, Haehnel and Thrun, "Generalized-ICP", RSS 2009) removes
it, without point-to-plane ICP's one-sided bias.
"""

from __future__ import annotations

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.registration.poses import Poses, apply, cross_matrices, rodrigues
from linereg.registration.welsch import REACH, padded_points, welsch_weights


def pca_frames(points: np.ndarray, k: int = 10) -> np.ndarray:
    """Local principal axes ``(N, 3, 3)`` of ``points (N, 3)``: column ``a`` of entry ``i`` is the
    axis of the ``a``-th smallest variance of point ``i``'s ``k`` nearest points (itself included)."""
    _, index = NearestNeighbors(points).query(points, k=min(k, len(points)))
    neighbours = points[index] - points[index].mean(axis=1, keepdims=True)
    return np.linalg.eigh(neighbours.transpose(0, 2, 1) @ neighbours)[1]


def pca_normals(points: np.ndarray, k: int = 10) -> np.ndarray:
    """Unoriented unit normals ``(N, 3)`` of ``points (N, 3)``: the least principal axis of each
    point's ``k`` nearest points (itself included). Numpy twin of Open3D's estimate, without orientation."""
    return pca_frames(points, k)[:, :, 0]


def surface_covariances(points: np.ndarray, k: int = 10, epsilon: float = 1e-2) -> np.ndarray:
    """Plane covariances ``(N, 3, 3)`` of ``points (N, 3)`` for :func:`plane_to_plane_irls`: each
    point's local frame (:func:`pca_frames`) with variances ``(epsilon, 1, 1)``, a disc of unit
    spread along the surface and ``epsilon`` across it (Generalized-ICP, Segal et al. 2009)."""
    frames = pca_frames(points, k)
    return np.einsum("nij,j,nkj->nik", frames, np.array([epsilon, 1.0, 1.0]), frames)


def plane_to_plane_irls(
    poses: Poses,
    src: np.ndarray,
    src_covariances: np.ndarray,
    tgt_index: NearestNeighbors,
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
    tgt = padded_points(tgt_index)
    tgt_covariances = np.concatenate([tgt_covariances, np.eye(3)[None]])
    rotations, translations = (array.copy() for array in poses)
    for _ in range(steps):
        moved = apply((rotations, translations), src)
        distances, idx = tgt_index.query(moved, distance_upper_bound=REACH * nu)
        rotated = np.einsum("kab,nbc,kdc->knad", rotations, src_covariances, rotations)
        information = np.linalg.inv(tgt_covariances[idx] + rotated)
        residual = moved - tgt[idx]
        weights = welsch_weights(distances, nu)
        jacobian = np.concatenate([-cross_matrices(moved), np.broadcast_to(np.eye(3), (*moved.shape, 3))], axis=-1)
        weighted = np.einsum("kn,knab,knbj->knaj", weights, information, jacobian)
        hessian = np.einsum("knai,knaj->kij", jacobian, weighted) + 1e-12 * np.eye(6)
        step = -np.linalg.solve(hessian, np.einsum("knaj,kna->kj", weighted, residual)[..., None])[..., 0]
        turn = rodrigues(step[:, :3])
        rotations = turn @ rotations
        translations = (turn @ translations[:, :, None])[:, :, 0] + step[:, 3:]
    return rotations, translations
