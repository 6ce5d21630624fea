"""``scale=true``: a similarity transform (rotation, translation and one scale) between clouds in different units.

:func:`linereg.register` with ``scale=True`` solves ``tgt ≈ s R src + t`` in three steps:

1. :func:`scale_guesses`: the scale from the ratio of the clouds' point spacings (exact for one
   sensor in two units) and from the ratio of their RMS radii (whole objects), one guess when they agree;
2. the rigid method on the source scaled by each guess (its global stage and finish included);
3. :func:`similarity_polish`: Welsch IRLS of ``(s, R, t)`` with Umeyama's weighted similarity
   solve (*Least-squares estimation of transformation parameters between two point patterns*,
   TPAMI 1991) from each answer, the scale free at every step.

The guess whose polished answer :func:`~linereg.registration.evaluation.assess_registration`
trusts (else fits best) is the answer; its scale is ``RegistrationResult.scale``. A fit that leaves
its scale free (:func:`~linereg.registration.trust.free_scale`: a room pair's planes slide, and a
fit of partly overlapping rooms shrinks the source by a few per cent) yields to the rigid answer at
the spacings' ratio when that ratio lies within the free range and the rigid answer is trusted:
``info["scale_from"]`` says ``"point spacings"`` rather than ``"fit"``.
"""

from __future__ import annotations

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.procrustes import weighted_procrustes_numpy
from linereg.registration.poses import rodrigues
from linereg.registration.trust import spacing_of
from linereg.registration.welsch import welsch_weights

AGREEMENT = 1.02
"""Two guesses within this ratio of each other are one (the spacing ratio's)."""
POLISH_POINTS = 2048
"""FPS points of the source the polish moves."""
POLISH_SCALES = np.geomspace(4.0, 1.0, 20).tolist() + [1.0] * 20
"""Welsch scales of the polish, in point spacings of the target."""
PLANE_STEPS = 10
"""Point-to-plane similarity steps that end the polish."""


def scale_guesses(src: np.ndarray, tgt: np.ndarray) -> list[float]:
    """Scales ``s`` with ``tgt ≈ s R src + t``: the ratio of point spacings, then the ratio of RMS
    radii when it differs from the first by more than :data:`AGREEMENT`."""
    by_spacing = spacing_of(tgt) / max(spacing_of(src), 1e-300)
    by_extent = _rms_radius(tgt) / max(_rms_radius(src), 1e-300)
    agree = max(by_spacing / by_extent, by_extent / by_spacing) <= AGREEMENT
    return [by_spacing] if agree else [by_spacing, by_extent]


def _rms_radius(points: np.ndarray) -> float:
    """RMS distance of ``points (N, 3)`` from their centroid."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def scale_of(transform: np.ndarray) -> float:
    """The scale ``s`` of a similarity ``(4, 4)`` ``[s R | t]`` (the cube root of its block's determinant)."""
    return float(np.cbrt(np.linalg.det(transform[:3, :3])))


def with_scale(transform: np.ndarray, scale: float) -> np.ndarray:
    """The similarity ``transform @ diag(scale, scale, scale, 1)``: ``transform`` applied to the scaled source."""
    return transform @ np.diag([scale, scale, scale, 1.0])


def weighted_similarity(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """Umeyama's weighted similarity ``(4, 4)`` mapping ``src (N, 3)`` onto ``tgt (N, 3)``, or ``None``
    when the weights vanish."""
    rotations, _, valid = weighted_procrustes_numpy(src[None], tgt[None], weights[None])
    if not valid[0]:
        return None
    w = weights / weights.sum()
    src_mean, tgt_mean = w @ src, w @ tgt
    rotated = (src - src_mean) @ rotations[0].T
    spread = np.sum(w * np.sum((src - src_mean) ** 2, axis=1))
    scale = float(np.sum(w * np.sum(rotated * (tgt - tgt_mean), axis=1)) / spread)
    transform = np.eye(4)
    transform[:3, :3] = scale * rotations[0]
    transform[:3, 3] = tgt_mean - scale * rotations[0] @ src_mean
    return transform


def similarity_polish(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Welsch IRLS of the similarity ``transform (4, 4)`` mapping ``src (N, 3)`` onto ``tgt (M, 3)``:
    one weighted similarity solve per scale of :data:`POLISH_SCALES` (nearest target points), then
    :data:`PLANE_STEPS` point-to-plane steps (:func:`plane_similarity_step`: points that slide
    along the surface no longer pull the scale)."""
    source = fps(np.asarray(src, dtype=np.float64), POLISH_POINTS)
    index = NearestNeighbors(tgt)
    spacing = spacing_of(tgt)
    for nu in POLISH_SCALES:
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        distances, idx = index.query(moved)
        step = weighted_similarity(source, index.points[idx], welsch_weights(distances, nu * spacing))
        if step is None or scale_of(step) <= 0:
            break
        transform = step
    for _ in range(PLANE_STEPS):
        transform = plane_similarity_step(source, index, transform, spacing)
    return transform


def plane_similarity_step(
    source: np.ndarray, index: NearestNeighbors, transform: np.ndarray, spacing: float
) -> np.ndarray:
    """One Gauss-Newton step of the Welsch-weighted point-to-plane distances (scale ``spacing``)
    over a similarity: ``x' = c + (1 + sigma) (I + [w]x) (x - c) + tau`` about the moved points'
    centroid ``c``, each moved point ``x`` of ``source (N, 3)`` against the plane of its nearest
    target points (:func:`~linereg.registration.trust.target_normals`)."""
    from linereg.registration.trust import target_normals

    moved = source @ transform[:3, :3].T + transform[:3, 3]
    distances, idx = index.query(moved)
    normals = target_normals(moved, index)
    center = moved.mean(axis=0)
    arm = moved - center
    residual = np.sum(normals * (moved - index.points[idx]), axis=1)
    jacobian = np.column_stack([np.cross(arm, normals), np.sum(normals * arm, axis=1), normals])
    weights = welsch_weights(distances, spacing)
    normal_matrix = jacobian.T @ (weights[:, None] * jacobian)
    if np.linalg.cond(normal_matrix) > 1e12:
        return transform
    omega, sigma, tau = np.split(np.linalg.solve(normal_matrix, -jacobian.T @ (weights * residual)), [3, 4])
    rotation = rodrigues(omega[None])[0]
    step = np.eye(4)
    step[:3, :3] = (1.0 + float(sigma[0])) * rotation
    step[:3, 3] = center - step[:3, :3] @ center + tau
    return step @ transform
