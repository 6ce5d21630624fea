"""Random straight lines for the line-intersection metric (paper §3.2 and its ablations).

A line is ``origin + s * direction`` with a unit ``direction``. Every sampler takes the
(detached) source and target of one sample and a CPU ``torch.Generator`` and returns
``(origins (L, 3), directions (L, 3))`` as float64 numpy arrays.

Samplers (the ``sampling`` option of the loss):

``sphere``
    The paper's: two independent points ``S_r(u, alpha)`` with ``u ~ U[-1, 1]``,
    ``alpha ~ U[0, 2 pi)`` on a sphere covering both clouds, joined by a line.
``box_point_direction``
    Ablation Sample1: a point uniform in the joint bounding box and a uniform direction.
``cloud_points``
    Ablation Sample2: a random source point and a random target point, each moved by a
    uniform perturbation in ``[-e, e]^3`` (``e = perturbation * sphere radius``), joined.
``authors``
    The paper code's sampler: the sphere is centred on the target centroid with radius equal to
    the target's bounding-box diagonal, and only lines that cross both clouds' bounding boxes
    are kept (up to 10 rounds of resampling; fewer lines are returned if they do not fill up).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from linereg.pointcloud import bounding_sphere

SAMPLERS = ("sphere", "box_point_direction", "cloud_points", "authors")
_AUTHORS_ROUNDS = 10


def _rand(shape: tuple[int, ...], generator: torch.Generator) -> np.ndarray:
    return torch.rand(shape, generator=generator, dtype=torch.float64).numpy()


def _unit_sphere_points(n: int, generator: torch.Generator) -> np.ndarray:
    """``(n, 3)`` points uniform on the unit sphere via the paper's ``(u, alpha)`` parametrisation."""
    u = 2.0 * _rand((n,), generator) - 1.0
    alpha = 2.0 * math.pi * _rand((n,), generator)
    rho = np.sqrt(np.clip(1.0 - u * u, 0.0, None))
    return np.stack([rho * np.cos(alpha), rho * np.sin(alpha), u], axis=1)


def _join(start: np.ndarray, end: np.ndarray, generator: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Lines through two point sets; coincident pairs get a random direction."""
    direction = end - start
    norm = np.linalg.norm(direction, axis=1, keepdims=True)
    degenerate = norm[:, 0] < 1e-12
    if degenerate.any():
        direction[degenerate] = _unit_sphere_points(int(degenerate.sum()), generator)
        norm[degenerate] = 1.0
    return start, direction / norm


def _sphere(center: np.ndarray, radius: float, n: int, generator: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    first = center + radius * _unit_sphere_points(n, generator)
    second = center + radius * _unit_sphere_points(n, generator)
    return _join(first, second, generator)


def _hits_box(origins: np.ndarray, dirs: np.ndarray, box_min: np.ndarray, box_max: np.ndarray) -> np.ndarray:
    """``(L,)`` bool: does each infinite line cross the axis-aligned box (slab test)?"""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (box_min - origins) / dirs
        tb = (box_max - origins) / dirs
    parallel = np.abs(dirs) < 1e-15
    inside = (origins >= box_min) & (origins <= box_max)
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return lo.max(axis=1) <= hi.min(axis=1)


def sample_lines(
    src: torch.Tensor,
    tgt: torch.Tensor,
    num_lines: int,
    generator: torch.Generator,
    *,
    sampling: str = "sphere",
    radius_factor: float = 1.0,
    perturbation: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``num_lines`` lines for one pair.

    Args:
        src: tensor of shape ``(N, 3)`` giving the (transformed) source points.
        tgt: tensor of shape ``(M, 3)`` giving the target points.
        num_lines: number of lines ``L``.
        generator: CPU ``torch.Generator`` (reproducible sampling).
        sampling: one of :data:`SAMPLERS` (see the module docstring).
        radius_factor: multiplies the sphere radius (``sphere`` and ``authors``; the paper
            repo uses 1.0 for RPM-Net and 0.5 for DCP/FMR).
        perturbation: ``cloud_points`` perturbation as a fraction of the covering radius.

    Returns:
        ``origins (L', 3)`` and unit ``directions (L', 3)``, float64; ``L' = L`` except for
        ``authors`` when too few lines cross both boxes.
    """
    src_np = src.detach().cpu().double().numpy()
    tgt_np = tgt.detach().cpu().double().numpy()
    if sampling == "sphere":
        center, radius = bounding_sphere(src.detach().double().cpu(), tgt.detach().double().cpu())
        return _sphere(center.numpy(), float(radius) * radius_factor, num_lines, generator)
    if sampling == "box_point_direction":
        both = np.concatenate([src_np, tgt_np])
        lo, hi = both.min(axis=0), both.max(axis=0)
        points = lo + (hi - lo) * _rand((num_lines, 3), generator)
        return points, _unit_sphere_points(num_lines, generator)
    if sampling == "cloud_points":
        _, radius = bounding_sphere(src.detach().double().cpu(), tgt.detach().double().cpu())
        spread = perturbation * float(radius)
        pick_src = (_rand((num_lines,), generator) * len(src_np)).astype(np.int64).clip(0, len(src_np) - 1)
        pick_tgt = (_rand((num_lines,), generator) * len(tgt_np)).astype(np.int64).clip(0, len(tgt_np) - 1)
        start = src_np[pick_src] + spread * (2.0 * _rand((num_lines, 3), generator) - 1.0)
        end = tgt_np[pick_tgt] + spread * (2.0 * _rand((num_lines, 3), generator) - 1.0)
        return _join(start, end, generator)
    if sampling == "authors":
        tgt_min, tgt_max = tgt_np.min(axis=0), tgt_np.max(axis=0)
        src_min, src_max = src_np.min(axis=0), src_np.max(axis=0)
        radius = float(np.linalg.norm(tgt_max - tgt_min)) * radius_factor
        center = tgt_np.mean(axis=0)
        kept_o, kept_d, total = [], [], 0
        for _ in range(_AUTHORS_ROUNDS):
            origins, dirs = _sphere(center, radius, num_lines, generator)
            keep = _hits_box(origins, dirs, src_min, src_max) & _hits_box(origins, dirs, tgt_min, tgt_max)
            kept_o.append(origins[keep])
            kept_d.append(dirs[keep])
            total += int(keep.sum())
            if total >= num_lines:
                break
        return np.concatenate(kept_o)[:num_lines], np.concatenate(kept_d)[:num_lines]
    raise ValueError(f"unknown line sampling {sampling!r}; choose one of {', '.join(SAMPLERS)}")
