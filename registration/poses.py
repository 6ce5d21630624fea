"""Sets of rigid poses in numpy, for the solvers that move many candidate poses at once.

A set of ``K`` poses is a pair ``(R (K, 3, 3), t (K, 3))`` (:data:`Poses`), each mapping
``x -> R x + t``. The rotations of the starts (:func:`axis_rotations`, :func:`cube_rotations`,
:func:`spread_rotations`) and the tests that tell two candidates apart
(:func:`rotation_gap_deg`, :func:`merged_into_earlier`, :func:`distinct_best`) live here.
"""

from __future__ import annotations

import itertools

import numpy as np

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


def rotation_gap_deg(rotations: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Angles (degrees) between each of ``rotations (K, 3, 3)`` and ``reference (3, 3)``."""
    cos = (np.einsum("kij,ij->k", rotations, reference) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


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


def distinct_best(rotations: np.ndarray, costs: np.ndarray, count: int, gap_deg: float) -> np.ndarray:
    """Indices of up to ``count`` lowest-cost rotations, each more than ``gap_deg`` from every one before it."""
    chosen: list[int] = []
    for index in np.argsort(costs, kind="stable"):
        if not chosen or (rotation_gap_deg(rotations[chosen], rotations[index]) > gap_deg).all():
            chosen.append(int(index))
            if len(chosen) == count:
                break
    return np.array(chosen, dtype=np.int64)
