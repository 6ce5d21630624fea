"""Weighted rigid Procrustes (Kabsch / Umeyama): a torch solver with safe fallbacks and gradients,
and its numpy twin for the numpy solvers.

Solves, per batch element,

    min_{R in SO(3), t}  sum_i w_i || R @ src_i + t - tgt_i ||^2

(column vectors, ``tgt ≈ R @ src + t``, as everywhere in linereg). With normalised weights
``p_i = w_i / sum_j w_j``, centroids ``c_src = sum_i p_i src_i`` and ``c_tgt``, and the
cross-covariance ``M = sum_i p_i (tgt_i - c_tgt)(src_i - c_src)^T``, the rotation is the
rotation nearest to ``M`` (``argmax_R tr(R^T M)``, reflection excluded) and
``t = c_tgt - R @ c_src``.

:func:`weighted_procrustes` (torch, differentiable) and :func:`weighted_procrustes_numpy` (numpy,
many problems at once, no gradient) solve the same problem; torch is imported on first use of
the torch solver, so that numpy callers such as the ``register`` default do not load it.

References:
    W. Kabsch, "A solution for the best rotation to relate two sets of vectors",
    Acta Crystallographica A32, 1976.
    S. Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from linereg.checks import check_shape

if TYPE_CHECKING:
    import torch

# Relative size of the second singular value of M below which the rotation is not unique
# (a single direction of spread: collinear points).
_RANK_RTOL = 1e-6
# Relative size of M (against the squared coordinate scale) below which M counts as zero
# (a single point, or all points coincident).
_ZERO_COVARIANCE_RTOL = 1e-10


class ProcrustesResult(NamedTuple):
    """Result of :func:`weighted_procrustes`.

    Attributes:
        transform: tensor of shape ``(B, 4, 4)`` giving ``T_tgt_src`` (dtype of ``src``).
        valid: bool tensor of shape ``(B,)``; ``False`` where the problem was degenerate (see
            :func:`weighted_procrustes`).
    """

    transform: torch.Tensor
    valid: torch.Tensor


def _check_inputs(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None) -> None:
    """Shape and type checks shared by both torch solvers."""
    import torch

    check_shape(src, "src", (3,))
    check_shape(tgt, "tgt", (3,))
    if src.ndim != 3:
        raise ValueError(f"src must have shape (B, N, 3), got {tuple(src.shape)}")
    if tgt.shape != src.shape:
        raise ValueError(f"tgt must have the shape of src {tuple(src.shape)}, got {tuple(tgt.shape)}")
    if weights is None:
        return
    if not isinstance(weights, torch.Tensor):
        raise TypeError(f"weights must be a torch.Tensor or None, got {type(weights).__name__}")
    if weights.shape != src.shape[:2]:
        raise ValueError(f"weights must have shape (B, N) = {tuple(src.shape[:2])}, got {tuple(weights.shape)}")


def _nearest_rotation(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotations nearest to ``M (B, 3, 3)`` and a ``(B,)`` mask of samples the solver handled."""
    import roma
    import torch

    try:
        rotation = roma.special_procrustes(M)
    except (RuntimeError, ValueError):
        rotations, solved = [], []
        eye = torch.eye(3, dtype=M.dtype, device=M.device)
        for sample in M:
            try:
                rotations.append(roma.special_procrustes(sample))
                solved.append(True)
            except (RuntimeError, ValueError):
                rotations.append(eye)
                solved.append(False)
        rotation = torch.stack(rotations)
        return rotation, torch.tensor(solved, device=M.device)
    return rotation, torch.isfinite(rotation).flatten(1).all(dim=1)


def weighted_procrustes(
    src: torch.Tensor,
    tgt: torch.Tensor,
    weights: torch.Tensor | None = None,
    *,
    eps: float = 1e-5,
) -> ProcrustesResult:
    """Best rigid transform mapping ``src`` onto corresponding ``tgt`` in weighted least squares.

    Centroids and the 3x3 covariance are computed in float64; the rotation comes from
    ``roma.special_procrustes`` (proper rotation, det +1, with damped derivatives), so the
    result is differentiable in ``src``, ``tgt`` and ``weights`` and never NaN, gradients
    included. Degenerate samples are flagged ``valid = False``:

    * weights with a sum below ``eps``, a negative or a non-finite entry, a non-finite
      coordinate, a zero covariance (one point, coincident points) or a solver failure: the
      rotation falls back to the identity and the translation to the difference of the
      (unweighted if the weights are unusable) centroids, zero if a coordinate is non-finite;
    * a rank-deficient covariance (collinear points): the rotation about the line is not
      unique; an optimal proper rotation is still returned.

    A ``UserWarning`` says how many samples were affected.

    Args:
        src: tensor of shape ``(B, N, 3)`` giving source points.
        tgt: tensor of shape ``(B, N, 3)`` giving the corresponding target points.
        weights: tensor of shape ``(B, N)`` giving non-negative weights, or ``None`` (uniform).
        eps: smallest acceptable sum of weights per sample.

    Returns:
        :class:`ProcrustesResult` with ``transform (B, 4, 4)`` (dtype of ``src``) and
        ``valid (B,)``.
    """
    import torch

    from linereg.se3 import rt_to_matrix

    _check_inputs(src, tgt, weights)
    src64, tgt64 = src.double(), tgt.double()
    weights64 = torch.ones_like(src64[..., 0]) if weights is None else weights.double()

    finite_points = torch.isfinite(src64).all(2).all(1) & torch.isfinite(tgt64).all(2).all(1)
    usable_weights = torch.isfinite(weights64).all(1) & (weights64 >= 0).all(1) & (weights64.sum(1) >= eps)
    src64 = torch.where(finite_points[:, None, None], src64, torch.zeros_like(src64))
    tgt64 = torch.where(finite_points[:, None, None], tgt64, torch.zeros_like(tgt64))
    weights64 = torch.where(usable_weights[:, None], weights64, torch.ones_like(weights64))

    probabilities = weights64 / weights64.sum(1, keepdim=True)
    src_centroid = (probabilities[..., None] * src64).sum(1)
    tgt_centroid = (probabilities[..., None] * tgt64).sum(1)
    src_centered = src64 - src_centroid[:, None]
    tgt_centered = tgt64 - tgt_centroid[:, None]
    covariance = (probabilities[..., None] * tgt_centered).transpose(1, 2) @ src_centered

    with torch.no_grad():
        singular_values = torch.linalg.svdvals(covariance)
        coordinate_scale = torch.sqrt(
            (probabilities * src64.square().sum(-1)).sum(1) * (probabilities * tgt64.square().sum(-1)).sum(1)
        )
        zero_covariance = singular_values[:, 0] <= _ZERO_COVARIANCE_RTOL * coordinate_scale
        rank_deficient = singular_values[:, 1] <= _RANK_RTOL * singular_values[:, 0]
    fallback = ~(finite_points & usable_weights) | zero_covariance

    eye = torch.eye(3, dtype=torch.float64, device=src.device).expand_as(covariance)
    solver_input = torch.where(fallback[:, None, None], eye, covariance)
    # special_procrustes is scale invariant; normalising makes its gradient damping relative.
    solver_input = solver_input / torch.linalg.matrix_norm(solver_input)[:, None, None]
    rotation, solved = _nearest_rotation(solver_input)
    fallback = fallback | ~solved
    rotation = torch.where(fallback[:, None, None], eye, rotation)

    translation = tgt_centroid - (rotation @ src_centroid[..., None])[..., 0]
    valid = ~fallback & ~rank_deficient
    _warn_degenerate(int(fallback.sum()), int((rank_deficient & ~fallback).sum()), len(valid))
    return ProcrustesResult(rt_to_matrix(rotation, translation).to(src.dtype), valid)


def _warn_degenerate(fallbacks: int, rank_deficient: int, batch_size: int) -> None:
    """Warn about samples that fell back to the identity or had a non-unique rotation."""
    if fallbacks:
        warnings.warn(
            f"weighted_procrustes: {fallbacks} of {batch_size} sample(s) fell back to the "
            "identity rotation (weights summing below eps, negative or non-finite weights, "
            "non-finite points, zero covariance or solver failure)",
            stacklevel=3,
        )
    if rank_deficient:
        warnings.warn(
            f"weighted_procrustes: {rank_deficient} of {batch_size} sample(s) have a "
            "rank-deficient covariance (collinear points); the rotation is not unique",
            stacklevel=3,
        )


def procrustes_naive(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Reference weighted Kabsch with a plain ``torch.linalg.svd`` (no safeguards; for tests).

    Args:
        src: tensor of shape ``(B, N, 3)`` giving source points.
        tgt: tensor of shape ``(B, N, 3)`` giving the corresponding target points.
        weights: tensor of shape ``(B, N)`` of non-negative weights, or ``None`` (uniform).

    Returns:
        Tensor of shape ``(B, 4, 4)`` giving ``T_tgt_src`` (dtype of ``src``).
    """
    import torch

    from linereg.se3 import rt_to_matrix

    _check_inputs(src, tgt, weights)
    if weights is None:
        weights = torch.ones_like(src[..., 0])
    probabilities = (weights / weights.sum(1, keepdim=True))[..., None]
    src_centroid = (probabilities * src).sum(1)
    tgt_centroid = (probabilities * tgt).sum(1)
    covariance = (probabilities * (tgt - tgt_centroid[:, None])).transpose(1, 2) @ (src - src_centroid[:, None])
    U, _, Vh = torch.linalg.svd(covariance)
    reflection = torch.ones_like(src_centroid)
    reflection[:, 2] = torch.linalg.det(U @ Vh)
    rotation = U @ torch.diag_embed(reflection) @ Vh
    translation = tgt_centroid - (rotation @ src_centroid[..., None])[..., 0]
    return rt_to_matrix(rotation, translation)


def weighted_procrustes_numpy(
    src: np.ndarray, tgt: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy twin of :func:`weighted_procrustes` for ``K`` problems at once (no gradient).

    The rotation comes from the SVD of the weighted cross-covariance with the reflection
    excluded; the inputs are not checked (the numpy solvers call it on their own arrays).

    Args:
        src: array of shape ``(K, N, 3)`` giving source points.
        tgt: array of shape ``(K, N, 3)`` giving the corresponding target points.
        weights: array of shape ``(K, N)`` giving non-negative weights.

    Returns:
        ``(rotations (K, 3, 3), translations (K, 3), valid (K,))``; ``valid`` is false where the
        weights sum to (almost) zero, and the transform is then the identity.
    """
    total = weights.sum(axis=1)
    valid = total > 1e-12
    w = (weights / np.where(valid, total, 1.0)[:, None])[:, None, :]
    src_mean = (w @ src)[:, 0]
    tgt_mean = (w @ tgt)[:, 0]
    cov = ((src - src_mean[:, None]) * w.transpose(0, 2, 1)).transpose(0, 2, 1) @ (tgt - tgt_mean[:, None])
    u, _, vt = np.linalg.svd(cov)
    v_ut = vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)
    sign = np.where(np.linalg.det(v_ut) < 0, -1.0, 1.0)
    vt[:, 2] *= sign[:, None]
    rotations = vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)
    rotations[~valid] = np.eye(3)
    translations = tgt_mean - (rotations @ src_mean[:, :, None])[:, :, 0]
    translations[~valid] = 0.0
    return rotations, translations, valid
