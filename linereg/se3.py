"""Rigid-body maths on SO(3) and SE(3): exponential/log maps, 4x4 helpers, Euler angles.

Conventions (the same everywhere in linereg):

* column vectors; a 4x4 transform ``T_tgt_src = [[R, t], [0, 1]]`` maps source coordinates to
  target coordinates, ``tgt ≈ R @ src + t``; composing ``T_ab`` with ``T_bc`` gives ``T_ac``;
* angles in radians;
* a twist ``xi`` in se(3) is the 6-vector ``(omega, v)``: rotation vector first (axis times
  angle), then the translational part ``v``. ``se3_exp`` is the true group exponential, so
  ``t = V(omega) @ v`` with the left Jacobian ``V`` of SO(3), not ``t = v``;
* rotation vectors returned by a log map have norm in ``[0, pi]``.

Every function accepts any number of leading batch dimensions ``(...)``, float32 and float64,
and keeps the device and dtype of its input. Closed-form coefficients switch to Taylor series
near a zero angle, so values and gradients stay finite at exactly zero rotation. Rotation
vector <-> matrix conversions and Euler angles come from roma (Brégier, 2021).
"""

from __future__ import annotations

import itertools

import roma
import torch

from linereg.checks import check_shape

# Below this squared angle (rad^2) the closed-form coefficients switch to Taylor series. The
# series are kept up to theta^6, so their truncation error at the threshold is below 1e-17.
_TAYLOR_THETA_SQ = 1e-3
_EULER_AXES = frozenset("xyz")


def _hat(omega: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``(..., 3, 3)`` of ``omega (..., 3)``: ``hat(w) @ x = w x x``."""
    wx, wy, wz = omega.unbind(-1)
    zero = torch.zeros_like(wx)
    rows = (
        torch.stack((zero, -wz, wy), dim=-1),
        torch.stack((wz, zero, -wx), dim=-1),
        torch.stack((-wy, wx, zero), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def _split_small_angle(theta_sq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mask of small angles and a gradient-safe angle (1 where the mask is set)."""
    small = theta_sq < _TAYLOR_THETA_SQ
    theta_safe = torch.sqrt(torch.where(small, torch.ones_like(theta_sq), theta_sq))
    return small, theta_safe


def _left_jacobian_coefficient(theta_sq: torch.Tensor) -> torch.Tensor:
    """``(theta - sin theta) / theta^3``, the ``hat(w)^2`` weight of the SO(3) left Jacobian."""
    small, theta = _split_small_angle(theta_sq)
    closed_form = (theta - torch.sin(theta)) / theta**3
    series = 1.0 / 6.0 - theta_sq / 120.0 + theta_sq**2 / 5040.0 - theta_sq**3 / 362880.0
    return torch.where(small, series, closed_form)


def _inverse_left_jacobian_coefficient(theta_sq: torch.Tensor) -> torch.Tensor:
    """``(1 - (theta / 2) cot(theta / 2)) / theta^2``, the ``hat(w)^2`` weight of ``V^-1``."""
    small, theta = _split_small_angle(theta_sq)
    half = 0.5 * theta
    closed_form = (1.0 - half * torch.cos(half) / torch.sin(half)) / theta**2
    series = 1.0 / 12.0 + theta_sq / 720.0 + theta_sq**2 / 30240.0 + theta_sq**3 / 1209600.0
    return torch.where(small, series, closed_form)


def _half_angle_coefficient(theta_sq: torch.Tensor) -> torch.Tensor:
    """``(1 - cos theta) / theta^2`` as ``2 sin^2(theta/2) / theta^2`` (no cancellation)."""
    small, theta = _split_small_angle(theta_sq)
    closed_form = 2.0 * torch.sin(0.5 * theta) ** 2 / theta**2
    series = 0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0 - theta_sq**3 / 40320.0
    return torch.where(small, series, closed_form)


def _left_jacobian(omega: torch.Tensor) -> torch.Tensor:
    """SO(3) left Jacobian ``V = I + B hat(w) + C hat(w)^2`` of shape ``(..., 3, 3)``."""
    theta_sq = (omega * omega).sum(-1)[..., None, None]
    hat = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    first_order = _half_angle_coefficient(theta_sq) * hat
    return eye + first_order + _left_jacobian_coefficient(theta_sq) * (hat @ hat)


def _inverse_left_jacobian(omega: torch.Tensor) -> torch.Tensor:
    """Inverse left Jacobian ``V^-1 = I - hat(w) / 2 + D hat(w)^2`` of shape ``(..., 3, 3)``."""
    theta_sq = (omega * omega).sum(-1)[..., None, None]
    hat = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye - 0.5 * hat + _inverse_left_jacobian_coefficient(theta_sq) * (hat @ hat)


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from rotation vectors (Rodrigues' formula).

    Args:
        omega: tensor of shape ``(..., 3)`` giving axis times angle, in radians.

    Returns:
        Tensor of shape ``(..., 3, 3)`` giving rotation matrices.
    """
    check_shape(omega, "omega", (3,))
    return roma.rotvec_to_rotmat(omega)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vectors from rotation matrices (through unit quaternions, stable near 0 and pi).

    Args:
        R: tensor of shape ``(..., 3, 3)`` giving rotation matrices.

    Returns:
        Tensor of shape ``(..., 3)`` giving axis times angle, with norm in ``[0, pi]``.
    """
    check_shape(R, "R", (3, 3))
    return roma.rotmat_to_rotvec(R)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """The SE(3) exponential of twists ``xi = (omega, v)``.

    ``R = exp(hat(omega))`` and ``t = V(omega) @ v`` with the SO(3) left Jacobian ``V``.

    Args:
        xi: tensor of shape ``(..., 6)``: rotation vector ``omega`` first, then ``v``.

    Returns:
        Tensor of shape ``(..., 4, 4)`` giving rigid transforms.
    """
    check_shape(xi, "xi", (6,))
    omega, v = xi[..., :3], xi[..., 3:]
    t = (_left_jacobian(omega) @ v[..., None])[..., 0]
    return rt_to_matrix(roma.rotvec_to_rotmat(omega), t)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """The SE(3) logarithm, inverse of :func:`se3_exp` (rotation angle in ``[0, pi]``).

    Args:
        T: tensor of shape ``(..., 4, 4)`` giving rigid transforms.

    Returns:
        Tensor of shape ``(..., 6)`` giving twists ``(omega, v)`` with ``v = V(omega)^-1 @ t``.
    """
    check_shape(T, "T", (4, 4))
    R, t = matrix_to_rt(T)
    omega = roma.rotmat_to_rotvec(R)
    v = (_inverse_left_jacobian(omega) @ t[..., None])[..., 0]
    return torch.cat((omega, v), dim=-1)


def rt_to_matrix(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous 4x4 matrices ``[[R, t], [0, 1]]``.

    Args:
        R: tensor of shape ``(..., 3, 3)`` giving rotations.
        t: tensor of shape ``(..., 3)`` giving translations; leading dims broadcast with ``R``.

    Returns:
        Tensor of shape ``(..., 4, 4)``.
    """
    check_shape(R, "R", (3, 3))
    check_shape(t, "t", (3,))
    batch_shape = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    top = torch.cat((R.expand(*batch_shape, 3, 3), t.expand(*batch_shape, 3)[..., None]), dim=-1)
    bottom = torch.zeros(*batch_shape, 1, 4, dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def matrix_to_rt(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split 4x4 transforms into rotation and translation.

    Args:
        T: tensor of shape ``(..., 4, 4)``.

    Returns:
        ``(R, t)`` of shapes ``(..., 3, 3)`` and ``(..., 3)`` (views of ``T``).
    """
    check_shape(T, "T", (4, 4))
    return T[..., :3, :3], T[..., :3, 3]


def compose(T_ab: torch.Tensor, T_bc: torch.Tensor) -> torch.Tensor:
    """Compose transforms: ``T_ac = T_ab @ T_bc`` (apply ``T_bc`` first).

    Args:
        T_ab: tensor of shape ``(..., 4, 4)`` mapping frame b to frame a.
        T_bc: tensor of shape ``(..., 4, 4)`` mapping frame c to frame b.

    Returns:
        Tensor of shape ``(..., 4, 4)`` mapping frame c to frame a.
    """
    check_shape(T_ab, "T_ab", (4, 4))
    check_shape(T_bc, "T_bc", (4, 4))
    return T_ab @ T_bc


def inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse rigid transforms in closed form, ``[[R^T, -R^T t], [0, 1]]``.

    Args:
        T: tensor of shape ``(..., 4, 4)`` giving rigid transforms ``T_ab``.

    Returns:
        Tensor of shape ``(..., 4, 4)`` giving ``T_ba``.
    """
    R, t = matrix_to_rt(T)
    R_inv = R.transpose(-1, -2)
    return rt_to_matrix(R_inv, -(R_inv @ t[..., None])[..., 0])


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply rigid transforms to point sets: ``R @ p + t`` for every point.

    Args:
        T: tensor of shape ``(..., 4, 4)``; its leading dims broadcast with those of ``points``
            (a single ``(4, 4)`` applies to every cloud, ``(B, 4, 4)`` with ``(N, 3)`` gives
            ``(B, N, 3)``).
        points: tensor of shape ``(..., N, 3)``; ``N = 0`` is allowed.

    Returns:
        Tensor of shape ``(..., N, 3)`` (broadcast leading dims).
    """
    check_shape(points, "points", (3,))
    if points.ndim < 2:
        raise ValueError(f"points must have shape (..., N, 3), got {tuple(points.shape)}")
    R, t = matrix_to_rt(T)
    return points @ R.transpose(-1, -2) + t[..., None, :]


def transform_normals(T: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Rotate normals (or any direction vectors) by the rotation part of ``T``.

    Args:
        T: tensor of shape ``(..., 4, 4)``; leading dims broadcast as in :func:`transform_points`.
        normals: tensor of shape ``(..., N, 3)``.

    Returns:
        Tensor of shape ``(..., N, 3)`` giving ``R @ n`` (translation ignored).
    """
    check_shape(normals, "normals", (3,))
    if normals.ndim < 2:
        raise ValueError(f"normals must have shape (..., N, 3), got {tuple(normals.shape)}")
    R, _ = matrix_to_rt(T)
    return normals @ R.transpose(-1, -2)


def euler_to_rotmat(angles: torch.Tensor, convention: str = "xyz") -> torch.Tensor:
    """Rotation matrices from three Euler angles, composed left to right.

    For ``convention="xyz"``: ``R = Rx(a0) @ Ry(a1) @ Rz(a2)`` (the DCP / RPM-Net data
    convention; equivalently, intrinsic rotations about x, then y, then z).

    Args:
        angles: tensor of shape ``(..., 3)`` in radians.
        convention: three lower-case axis letters from ``{"x", "y", "z"}``, e.g. ``"xyz"``,
            ``"zyx"``, ``"zxz"``.

    Returns:
        Tensor of shape ``(..., 3, 3)``.
    """
    check_shape(angles, "angles", (3,))
    if (
        len(convention) != 3
        or not set(convention) <= _EULER_AXES
        or any(a == b for a, b in itertools.pairwise(convention))
    ):
        raise ValueError(
            f"convention must be three axis letters from 'xyz' without consecutive repeats, got {convention!r}"
        )
    # roma (like SciPy) reads upper-case conventions as intrinsic rotations, i.e. R = R0 R1 R2.
    return roma.euler_to_rotmat(convention.upper(), angles)


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle of rotation matrices, in radians in ``[0, pi]``.

    Computed as ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``: equal to the textbook
    ``arccos((tr R - 1) / 2)`` for rotations but accurate near 0 and pi (where ``arccos`` loses
    half the digits) and never NaN. The gradient is finite everywhere except at exactly 0 and
    exactly pi, where the angle is not differentiable; there it is returned as 0.

    Args:
        R: tensor of shape ``(..., 3, 3)``.

    Returns:
        Tensor of shape ``(...)``.
    """
    check_shape(R, "R", (3, 3))
    skew = R - R.transpose(-1, -2)
    axis_times_two_sin = torch.stack((skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]), dim=-1)
    sin_angle = 0.5 * torch.linalg.vector_norm(axis_times_two_sin, dim=-1)
    cos_angle = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(sin_angle, cos_angle)
