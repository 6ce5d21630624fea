"""Random rotations and rigid transforms for the synthetic benchmarks.

Every function takes ``generator`` as a ``torch.Generator``, a ``numpy.random.Generator``, an
``int`` seed (a fresh torch generator seeded with it) or ``None`` (torch's global generator, so
``torch.manual_seed`` applies). Samples are drawn in float64 on the CPU and then cast, so a seed
gives the same poses whatever ``dtype`` and ``device`` are requested. Conventions follow
:mod:`linereg.se3`: column vectors, ``tgt ≈ R @ src + t``, Euler ``"xyz"`` means
``R = Rx(a0) @ Ry(a1) @ Rz(a2)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import roma
import torch

from linereg.se3 import euler_to_rotmat, rt_to_matrix

GeneratorLike = torch.Generator | np.random.Generator | int | None
UniformSampler = Callable[[tuple[int, ...]], torch.Tensor]


def _uniform_sampler(generator: GeneratorLike) -> UniformSampler:
    """A function drawing float64 CPU samples from U[0, 1) of a given shape with ``generator``."""
    if isinstance(generator, np.random.Generator):
        return lambda shape: torch.from_numpy(generator.random(shape))
    if isinstance(generator, torch.Generator):
        return lambda shape: torch.rand(shape, generator=generator, dtype=torch.float64, device=generator.device).cpu()
    if generator is None:
        return lambda shape: torch.rand(shape, dtype=torch.float64)
    if isinstance(generator, int | np.integer) and not isinstance(generator, bool):
        seeded = torch.Generator().manual_seed(int(generator))
        return lambda shape: torch.rand(shape, generator=seeded, dtype=torch.float64)
    raise TypeError(
        f"generator must be a torch.Generator, numpy.random.Generator, int seed or None, got {type(generator).__name__}"
    )


def _check_batch_size(batch_size: int) -> None:
    """Raise unless ``batch_size`` is a non-negative integer."""
    if not isinstance(batch_size, int | np.integer) or isinstance(batch_size, bool):
        raise TypeError(f"batch_size must be an int, got {type(batch_size).__name__}")
    if batch_size < 0:
        raise ValueError(f"batch_size must be >= 0, got {batch_size}")


def _euler_translation_transform(
    batch_size: int,
    generator: GeneratorLike,
    max_angle_deg: float,
    max_translation: float,
    dtype: torch.dtype,
    device: torch.device | str,
) -> torch.Tensor:
    """``(B, 4, 4)`` transforms with Euler angles U[0, max] ("xyz") and t U[-max, max]^3."""
    _check_batch_size(batch_size)
    if max_angle_deg < 0 or max_translation < 0:
        raise ValueError(
            f"ranges must be non-negative, got max angle {max_angle_deg} deg and max translation {max_translation}"
        )
    uniform = _uniform_sampler(generator)((batch_size, 6))
    angles = uniform[:, :3] * math.radians(max_angle_deg)
    translation = (2.0 * uniform[:, 3:] - 1.0) * max_translation
    transform = rt_to_matrix(euler_to_rotmat(angles, "xyz"), translation)
    return transform.to(dtype=dtype, device=device)


def random_transform_paper(
    batch_size: int,
    generator: GeneratorLike = None,
    *,
    max_angle_deg: float = 45.0,
    max_translation: float = 0.2,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Source-to-target transforms of the paper's synthetic pairs (§4.1, following DCP).

    Three Euler angles each U[0, max_angle_deg], ``R = Rx Ry Rz``; translation components each
    U[-max_translation, max_translation].

    Args:
        batch_size: number of transforms ``B``.
        generator: random source (see the module docstring).
        max_angle_deg: upper bound of each Euler angle, in degrees.
        max_translation: bound of each translation component (length units of the data).
        dtype: dtype of the result.
        device: device of the result.

    Returns:
        Tensor of shape ``(B, 4, 4)`` giving ``T_tgt_src``.
    """
    return _euler_translation_transform(batch_size, generator, max_angle_deg, max_translation, dtype, device)


def random_transform_rpmnet(
    batch_size: int,
    generator: GeneratorLike = None,
    *,
    rot_mag_deg: float = 45.0,
    trans_mag: float = 0.5,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """The RPM-Net / ModelNet40 "crop" perturbation (RPM-Net's repository, src/data_loader/transforms.py).

    Three Euler angles each U[0, rot_mag_deg], ``R = Rx Ry Rz``; translation U[-trans_mag,
    trans_mag]^3. This is the perturbation *applied to the source* cloud
    (``src_perturbed = R @ src + t``); the ground truth mapping the perturbed source to the
    reference is its inverse, ``linereg.se3.inverse(result)``.

    Args:
        batch_size: number of transforms ``B``.
        generator: random source (see the module docstring).
        rot_mag_deg: upper bound of each Euler angle, in degrees.
        trans_mag: bound of each translation component.
        dtype: dtype of the result.
        device: device of the result.

    Returns:
        Tensor of shape ``(B, 4, 4)`` giving the source perturbation.
    """
    return _euler_translation_transform(batch_size, generator, rot_mag_deg, trans_mag, dtype, device)


def _unit_vectors(uniform: torch.Tensor) -> torch.Tensor:
    """Unit vectors ``(B, 3)`` uniform on the sphere from U[0, 1) samples ``(B, 2)``."""
    z = 2.0 * uniform[:, 0] - 1.0
    azimuth = 2.0 * math.pi * uniform[:, 1]
    radius = torch.sqrt(torch.clamp_min(1.0 - z * z, 0.0))
    return torch.stack((radius * torch.cos(azimuth), radius * torch.sin(azimuth), z), dim=-1)


def random_rotation(
    batch_size: int,
    generator: GeneratorLike = None,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Rotations uniform on SO(3) (Haar measure), by Shoemake's uniform unit quaternions.

    Args:
        batch_size: number of rotations ``B``.
        generator: random source (see the module docstring).
        dtype: dtype of the result.
        device: device of the result.

    Returns:
        Tensor of shape ``(B, 3, 3)``.
    """
    _check_batch_size(batch_size)
    u1, u2, u3 = _uniform_sampler(generator)((batch_size, 3)).unbind(-1)
    low, high = torch.sqrt(1.0 - u1), torch.sqrt(u1)
    quat_xyzw = torch.stack(
        (
            low * torch.sin(2.0 * math.pi * u2),
            low * torch.cos(2.0 * math.pi * u2),
            high * torch.sin(2.0 * math.pi * u3),
            high * torch.cos(2.0 * math.pi * u3),
        ),
        dim=-1,
    )
    return roma.unitquat_to_rotmat(quat_xyzw).to(dtype=dtype, device=device)


def random_axis_angle_rotation(
    batch_size: int,
    generator: GeneratorLike = None,
    *,
    min_angle_deg: float,
    max_angle_deg: float,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Rotations about a uniformly random unit axis by an angle U[min_angle_deg, max_angle_deg].

    Used for the Airplane protocol's second camera (angle in [-75, 75] degrees); a negative
    angle is a rotation about the opposite axis.

    Args:
        batch_size: number of rotations ``B``.
        generator: random source (see the module docstring).
        min_angle_deg: lower bound of the angle, in degrees.
        max_angle_deg: upper bound of the angle, in degrees (``>= min_angle_deg``).
        dtype: dtype of the result.
        device: device of the result.

    Returns:
        Tensor of shape ``(B, 3, 3)``.
    """
    _check_batch_size(batch_size)
    if max_angle_deg < min_angle_deg:
        raise ValueError(f"max_angle_deg must be >= min_angle_deg, got {max_angle_deg} < {min_angle_deg}")
    uniform = _uniform_sampler(generator)((batch_size, 3))
    axis = _unit_vectors(uniform[:, :2])
    angle_range = math.radians(max_angle_deg - min_angle_deg)
    angle = math.radians(min_angle_deg) + uniform[:, 2] * angle_range
    return roma.rotvec_to_rotmat(axis * angle[:, None]).to(dtype=dtype, device=device)
