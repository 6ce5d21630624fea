"""Input validation shared by every layer (one home for the error wording).

Public entry points check type first (``TypeError``), then shape and values (``ValueError``);
every message names the argument and gives the expected and the actual value.
"""

from __future__ import annotations

import sys
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

ArrayLike = "torch.Tensor | np.ndarray"

RIGID_TOLERANCE = 1e-3
"""Largest deviation from a rotation that :func:`as_rigid_transform` repairs (float32 or rounded files)."""

_REPAIR_NOTICE = 1e-9
"""A repair that changes an entry by more than this is reported with a warning."""


def is_tensor(value: Any) -> bool:
    """Whether ``value`` is a ``torch.Tensor``, without importing torch (numpy-only callers
    such as the ``register`` default stay free of it: a tensor exists only once torch is loaded)."""
    torch_module = sys.modules.get("torch")
    return torch_module is not None and isinstance(value, torch_module.Tensor)


def check_points(
    points: ArrayLike,
    name: str = "points",
    *,
    min_points: int = 1,
    batched: bool | None = None,
    dim: int = 3,
) -> None:
    """Check that ``points`` is a finite point cloud of shape ``(N, dim)`` or ``(B, N, dim)``.

    Args:
        points: tensor or array of shape ``(N, dim)`` or ``(B, N, dim)``.
        name: argument name used in error messages.
        min_points: smallest acceptable ``N``.
        batched: ``True`` requires ``(B, N, dim)``, ``False`` requires ``(N, dim)``,
            ``None`` accepts both.
        dim: size of the last axis.

    Raises:
        TypeError: not a tensor/array, or not a floating-point dtype.
        ValueError: wrong shape, fewer than ``min_points`` points, or NaN/Inf coordinates.
    """
    tensor = is_tensor(points)
    if not (tensor or isinstance(points, np.ndarray)):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(points).__name__}")
    is_float = points.is_floating_point() if tensor else np.issubdtype(points.dtype, np.floating)
    if not is_float:
        raise TypeError(f"{name} must have a floating-point dtype, got {points.dtype}")
    allowed = {True: (3,), False: (2,), None: (2, 3)}[batched]
    shape = tuple(points.shape)
    if points.ndim not in allowed or shape[-1] != dim:
        expected = " or ".join({2: f"(N, {dim})", 3: f"(B, N, {dim})"}[n] for n in allowed)
        raise ValueError(f"{name} must have shape {expected}, got {shape}")
    if shape[-2] < min_points:
        raise ValueError(f"{name} must hold at least {min_points} point(s), got {shape[-2]}")
    finite = points.isfinite().all() if tensor else np.isfinite(points).all()
    if not bool(finite):
        raise ValueError(f"{name} contains NaN or Inf coordinates")


def check_shape(value: torch.Tensor, name: str, trailing: tuple[int, ...]) -> None:
    """Check that ``value`` is a floating-point tensor whose shape ends in ``trailing``.

    Raises:
        TypeError: not a tensor, or not a floating-point dtype.
        ValueError: the trailing dimensions differ from ``trailing``.
    """
    if not is_tensor(value):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if not value.is_floating_point():
        raise TypeError(f"{name} must have a floating-point dtype, got {value.dtype}")
    if value.ndim < len(trailing) or tuple(value.shape[value.ndim - len(trailing) :]) != trailing:
        expected = "(..., " + ", ".join(str(size) for size in trailing) + ")"
        raise ValueError(f"{name} must have shape {expected}, got {tuple(value.shape)}")


def check_transform(transform: ArrayLike, name: str = "transform", *, rigid_atol: float | None = None) -> None:
    """Check that ``transform`` holds homogeneous 4x4 matrices of shape ``(..., 4, 4)``.

    Args:
        transform: tensor or array of shape ``(..., 4, 4)``.
        name: argument name used in error messages.
        rigid_atol: when given, also require ``R^T R = I``, ``det R = +1`` and a last row of
            ``[0, 0, 0, 1]`` within this absolute tolerance.

    Raises:
        TypeError: not a tensor/array, or not a floating-point dtype.
        ValueError: wrong shape, non-finite entries, or (with ``rigid_atol``) not rigid.
    """
    tensor = is_tensor(transform)
    if not (tensor or isinstance(transform, np.ndarray)):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(transform).__name__}")
    is_float = transform.is_floating_point() if tensor else np.issubdtype(transform.dtype, np.floating)
    if not is_float:
        raise TypeError(f"{name} must have a floating-point dtype, got {transform.dtype}")
    if transform.ndim < 2 or tuple(transform.shape[-2:]) != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {tuple(transform.shape)}")
    matrix = transform.detach().cpu().double().numpy() if tensor else np.asarray(transform, dtype=np.float64)
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name} contains NaN or Inf entries")
    if rigid_atol is None:
        return
    rot = matrix[..., :3, :3]
    orth_err = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max()
    det = np.linalg.det(rot)
    last_row_err = np.abs(matrix[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max()
    if orth_err > rigid_atol or np.abs(det - 1.0).max() > rigid_atol or last_row_err > rigid_atol:
        reflection = "; det R < 0: a reflection" if (det < 0).any() else ""
        raise ValueError(
            f"{name} is not a rigid transform: max |R^T R - I| = {orth_err:.2e}, "
            f"det R = {np.ravel(det)[:4]}, last-row error {last_row_err:.2e} (tolerance {rigid_atol}){reflection}"
        )


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to a ``(3, 3)`` matrix in the Frobenius norm: ``U V^T`` of its SVD,
    the last column of ``U`` flipped when that would be a reflection."""
    u, _, vt = np.linalg.svd(matrix)
    u[:, -1] *= np.sign(np.linalg.det(u @ vt))
    return u @ vt


def as_rigid_transform(matrix: ArrayLike, name: str = "transform", tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """``matrix`` as an exactly rigid float64 ``(4, 4)`` transform, repairing small deviations.

    A rotation block within ``tolerance`` of a rotation (``max |R^T R - I|``, ``|det R - 1|``) and a
    last row within ``tolerance`` of ``[0, 0, 0, 1]`` are replaced by the nearest rotation and
    ``[0, 0, 0, 1]``, with a ``UserWarning`` naming ``name`` when an entry changes by more than
    1e-9; a matrix rigid to within 1e-9 is returned unchanged (as float64).

    Raises:
        TypeError: not a tensor/array, or not a floating-point dtype.
        ValueError: not ``(4, 4)``, non-finite entries, or further than ``tolerance`` from a rigid
            transform (a reflection included); the message names ``name``.
    """
    check_transform(matrix, name, rigid_atol=tolerance)
    if tuple(matrix.shape) != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {tuple(matrix.shape)}")
    given = np.array(matrix.detach().cpu().numpy() if is_tensor(matrix) else matrix, dtype=np.float64)
    rigid = given.copy()
    rigid[:3, :3] = nearest_rotation(given[:3, :3])
    rigid[3] = [0.0, 0.0, 0.0, 1.0]
    if np.abs(rigid - given).max() <= _REPAIR_NOTICE:
        return given
    rotation = given[:3, :3]
    warnings.warn(
        f"{name}: not exactly rigid, orthonormalised (max |R^T R - I| = "
        f"{np.abs(rotation.T @ rotation - np.eye(3)).max():.2e}, det R = {np.linalg.det(rotation):.6f})",
        UserWarning,
        stacklevel=2,
    )
    return rigid


def check_same_batch(a: ArrayLike, b: ArrayLike, name_a: str, name_b: str) -> None:
    """Raise ``ValueError`` unless two batched tensors share their leading batch size."""
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{name_a} and {name_b} must share the batch size, got {a.shape[0]} and {b.shape[0]}")


def check_lengths(
    lengths: ArrayLike | None, name: str, batch: int, max_length: int, *, min_length: int = 1
) -> torch.Tensor | None:
    """Check the padding lengths of a batch and return them as an int64 CPU tensor.

    Args:
        lengths: ``None`` (no padding) or an integer tensor/array of shape ``(batch,)``.
        name: argument name used in error messages.
        batch: batch size ``B`` of the padded tensor.
        max_length: padded size ``N`` of the tensor (no length may exceed it).
        min_length: smallest valid length (e.g. ``k + 1`` for a metric that needs neighbours).

    Returns:
        ``None`` when ``lengths`` is ``None``, else the lengths as an int64 CPU tensor ``(B,)``.

    Raises:
        TypeError: not a tensor/array, or not an integer dtype (a float length is never truncated).
        ValueError: wrong shape, or a length outside ``[min_length, max_length]``.
    """
    if lengths is None:
        return None
    import torch

    if not isinstance(lengths, torch.Tensor | np.ndarray):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array of integers, got {type(lengths).__name__}")
    is_integer = (
        not lengths.is_floating_point() and not lengths.is_complex() and lengths.dtype != torch.bool
        if isinstance(lengths, torch.Tensor)
        else np.issubdtype(lengths.dtype, np.integer)
    )
    if not is_integer:
        raise TypeError(f"{name} must have an integer dtype, got {lengths.dtype}")
    if tuple(lengths.shape) != (batch,):
        raise ValueError(f"{name} must have shape ({batch},) (one length per sample), got {tuple(lengths.shape)}")
    values = torch.as_tensor(lengths).detach().to("cpu", torch.int64)
    for sample, length in enumerate(values.tolist()):
        if not min_length <= length <= max_length:
            raise ValueError(
                f"{name}[{sample}] = {length} is outside [{min_length}, {max_length}] "
                f"(at least {min_length} valid point(s), at most the padded size {max_length})"
            )
    return values
