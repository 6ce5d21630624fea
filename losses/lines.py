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

import numba
import numpy as np
import torch

SAMPLERS = ("sphere", "box_point_direction", "cloud_points", "authors")
_AUTHORS_ROUNDS = 10


def _rand(shape: tuple[int, ...], generator: torch.Generator) -> np.ndarray:
    return torch.rand(shape, generator=generator, dtype=torch.float64).numpy()


@numba.njit(cache=True, parallel=True)
def _unit_sphere_rows(u_draws: np.ndarray, alpha_draws: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points ``S(u, alpha)`` of the unit sphere from ``(n,)`` uniform draws in
    ``[0, 1)``: ``u = 2 u_draw - 1``, ``alpha = 2 pi alpha_draw``."""
    n = u_draws.shape[0]
    out = np.empty((n, 3))
    for i in numba.prange(n):
        u = 2.0 * u_draws[i] - 1.0
        alpha = 2.0 * math.pi * alpha_draws[i]
        rho = math.sqrt(max(1.0 - u * u, 0.0))
        out[i, 0] = rho * math.cos(alpha)
        out[i, 1] = rho * math.sin(alpha)
        out[i, 2] = u
    return out


@numba.njit(cache=True, parallel=True)
def _chord_lines(first: np.ndarray, second: np.ndarray, center: np.ndarray, radius: float):
    """Lines through ``center + radius * first`` towards ``center + radius * second`` (rows of
    ``(n, 3)`` unit-sphere points): ``origins (n, 3)``, unit ``directions (n, 3)`` and ``(n,)``
    bool, True where the two points (nearly) coincide and the direction is left undefined."""
    n = first.shape[0]
    origins = np.empty((n, 3))
    dirs = np.empty((n, 3))
    degenerate = np.empty(n, dtype=np.bool_)
    for i in numba.prange(n):
        dx = second[i, 0] - first[i, 0]
        dy = second[i, 1] - first[i, 1]
        dz = second[i, 2] - first[i, 2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        degenerate[i] = norm < 1e-12
        if degenerate[i]:
            norm = 1.0
        for a, d in ((0, dx), (1, dy), (2, dz)):
            origins[i, a] = center[a] + radius * first[i, a]
            dirs[i, a] = d / norm
    return origins, dirs, degenerate


def _unit_sphere_points(n: int, generator: torch.Generator) -> np.ndarray:
    """``(n, 3)`` points uniform on the unit sphere via the paper's ``(u, alpha)`` parametrisation."""
    u_draws = _rand((n,), generator)
    return _unit_sphere_rows(u_draws, _rand((n,), generator))


def _sphere(center: np.ndarray, radius: float, n: int, generator: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Lines through two independent points of a sphere; the direction comes from the unit
    sphere points, so it stays defined for any radius (a random one for coincident points)."""
    first = _unit_sphere_points(n, generator)
    second = _unit_sphere_points(n, generator)
    origins, dirs, degenerate = _chord_lines(first, second, np.asarray(center, dtype=np.float64), float(radius))
    if degenerate.any():
        dirs[degenerate] = _unit_sphere_points(int(degenerate.sum()), generator)
    return origins, dirs


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


def _cloud_summaries(cloud: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """``(B, 10)`` per sample: bounding-box min (3), max (3), centroid (3), point count (1) of
    the valid points of ``cloud (B, N, 3)``, float64, computed on the cloud's device."""
    valid = torch.arange(cloud.shape[1], device=cloud.device)[None] < lengths[:, None]
    points = cloud.detach().double()
    lo = points.masked_fill(~valid[..., None], math.inf).amin(dim=1)
    hi = points.masked_fill(~valid[..., None], -math.inf).amax(dim=1)
    count = valid.sum(dim=1, keepdim=True).double()
    centroid = (points * valid[..., None]).sum(dim=1) / count
    return torch.cat([lo, hi, centroid, count], dim=1)


def _farthest_from(cloud: torch.Tensor, lengths: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """``(B,)`` largest distance from ``center (B, 3)`` to a valid point of ``cloud (B, N, 3)``."""
    valid = torch.arange(cloud.shape[1], device=cloud.device)[None] < lengths[:, None]
    dist = (cloud.detach().double() - center[:, None]).norm(dim=-1)
    return dist.masked_fill(~valid, 0.0).amax(dim=1)


def sample_line_batch(
    src: torch.Tensor,
    tgt: torch.Tensor,
    src_lengths: torch.Tensor,
    tgt_lengths: torch.Tensor,
    num_lines: int,
    generator: torch.Generator,
    *,
    sampling: str = "sphere",
    radius_factor: float = 1.0,
    perturbation: float = 0.02,
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Sample ``num_lines`` lines for every pair of a batch.

    The random numbers are drawn on the CPU from ``generator`` (sample after sample, so a batch
    gets the lines its samples would get one at a time); the few per-sample statistics the
    samplers need (bounding boxes, centroids, covering radius) are computed on the clouds'
    device and copied to the CPU once per batch, and the lines are copied to the device once.

    Args:
        src: tensor of shape ``(B, N, 3)`` giving the (transformed, possibly padded) sources.
        tgt: tensor of shape ``(B, M, 3)`` giving the targets.
        src_lengths, tgt_lengths: ``(B,)`` int64 tensors on the clouds' device, valid points.
        num_lines: number of lines ``L`` per sample.
        generator: CPU ``torch.Generator`` (reproducible sampling).
        sampling: one of :data:`SAMPLERS` (see the module docstring).
        radius_factor: multiplies the sphere radius (``sphere`` and ``authors``; the paper
            repo uses 1.0 for RPM-Net and 0.5 for DCP/FMR).
        perturbation: ``cloud_points`` perturbation as a fraction of the covering radius.

    Returns:
        ``origins (B, L, 3)`` and unit ``directions (B, L, 3)``, float64 on the clouds' device,
        and ``counts (B,)`` int64 numpy: sample ``b`` has ``counts[b]`` lines (``L`` except for
        ``authors`` when too few lines cross both boxes); rows beyond are copies of its first line.
    """
    if sampling not in SAMPLERS:
        raise ValueError(f"unknown line sampling {sampling!r}; choose one of {', '.join(SAMPLERS)}")
    device = src.device
    src_summary, tgt_summary = _cloud_summaries(src, src_lengths), _cloud_summaries(tgt, tgt_lengths)
    joint_lo = torch.minimum(src_summary[:, 0:3], tgt_summary[:, 0:3])
    joint_hi = torch.maximum(src_summary[:, 3:6], tgt_summary[:, 3:6])
    center = (joint_lo + joint_hi) / 2
    cover = torch.maximum(_farthest_from(src, src_lengths, center), _farthest_from(tgt, tgt_lengths, center))
    # The only host transfer of the sampler: (B, 30) numbers.
    stats = torch.cat([src_summary, tgt_summary, center, cover[:, None], joint_lo, joint_hi], dim=1).cpu().numpy()
    batch = src.shape[0]
    origins = np.empty((batch, num_lines, 3))
    dirs = np.empty((batch, num_lines, 3))
    counts = np.full(batch, num_lines, dtype=np.int64)
    picks = np.zeros((batch, 2, num_lines), dtype=np.int64)
    for b in range(batch):
        s_lo, s_hi, t_lo, t_hi = stats[b, 0:3], stats[b, 3:6], stats[b, 10:13], stats[b, 13:16]
        t_centroid, center_b, cover_b = stats[b, 16:19], stats[b, 20:23], stats[b, 23]
        lo, hi = stats[b, 24:27], stats[b, 27:30]
        if sampling == "sphere":
            origins[b], dirs[b] = _sphere(center_b, cover_b * radius_factor, num_lines, generator)
        elif sampling == "box_point_direction":
            origins[b] = lo + (hi - lo) * _rand((num_lines, 3), generator)
            dirs[b] = _unit_sphere_points(num_lines, generator)
        elif sampling == "cloud_points":
            for side, n_points in ((0, stats[b, 9]), (1, stats[b, 19])):
                n_points = int(n_points)
                picks[b, side] = (_rand((num_lines,), generator) * n_points).astype(np.int64).clip(0, n_points - 1)
                # origins/dirs hold the two perturbations until the picked points are added.
                (origins if side == 0 else dirs)[b] = (
                    perturbation * cover_b * (2.0 * _rand((num_lines, 3), generator) - 1.0)
                )
        else:
            radius = float(np.linalg.norm(t_hi - t_lo)) * radius_factor
            kept_o, kept_d, total = [], [], 0
            for _ in range(_AUTHORS_ROUNDS):
                o, d = _sphere(t_centroid, radius, num_lines, generator)
                keep = _hits_box(o, d, s_lo, s_hi) & _hits_box(o, d, t_lo, t_hi)
                kept_o.append(o[keep])
                kept_d.append(d[keep])
                total += int(keep.sum())
                if total >= num_lines:
                    break
            counts[b] = min(total, num_lines)
            if counts[b] == 0:
                raise ValueError(
                    f"sampling 'authors': no line of {_AUTHORS_ROUNDS} rounds crossed both bounding boxes of sample {b}"
                )
            origins[b, : counts[b]] = np.concatenate(kept_o)[: counts[b]]
            dirs[b, : counts[b]] = np.concatenate(kept_d)[: counts[b]]
            origins[b, counts[b] :] = origins[b, 0]
            dirs[b, counts[b] :] = dirs[b, 0]
    origins_t = torch.from_numpy(origins).to(device)
    dirs_t = torch.from_numpy(dirs).to(device)
    if sampling == "cloud_points":
        rows = torch.arange(batch, device=device)[:, None]
        picks_t = torch.from_numpy(picks).to(device)
        start = src.detach().double()[rows, picks_t[:, 0]] + origins_t
        end = tgt.detach().double()[rows, picks_t[:, 1]] + dirs_t
        fallback = torch.from_numpy(np.stack([_unit_sphere_points(num_lines, generator) for _ in range(batch)]))
        direction = end - start
        norm = direction.norm(dim=-1, keepdim=True)
        degenerate = norm <= 1e-12 * cover[:, None, None]
        origins_t = start
        dirs_t = torch.where(degenerate, fallback.to(device), direction / norm.clamp_min(torch.finfo(norm.dtype).tiny))
    return origins_t, dirs_t, counts


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
    """Sample ``num_lines`` lines for one pair (see :func:`sample_line_batch`).

    Args:
        src: tensor of shape ``(N, 3)`` giving the (transformed) source points.
        tgt: tensor of shape ``(M, 3)`` giving the target points.

    Returns:
        ``origins (L', 3)`` and unit ``directions (L', 3)``, float64 numpy; ``L' = L`` except
        for ``authors`` when too few lines cross both boxes.
    """
    origins, dirs, counts = sample_line_batch(
        src[None],
        tgt[None],
        torch.tensor([src.shape[0]], device=src.device),
        torch.tensor([tgt.shape[0]], device=tgt.device),
        num_lines,
        generator,
        sampling=sampling,
        radius_factor=radius_factor,
        perturbation=perturbation,
    )
    return origins[0, : counts[0]].cpu().numpy(), dirs[0, : counts[0]].cpu().numpy()
