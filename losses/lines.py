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


@numba.njit(cache=True, inline="always")
def _sphere_point(u_draw: float, alpha_draw: float) -> tuple[float, float, float]:
    """The unit-sphere point ``S(u, alpha)`` of uniform draws in ``[0, 1)``: ``u = 2 u_draw - 1``,
    ``alpha = 2 pi alpha_draw``."""
    u = 2.0 * u_draw - 1.0
    alpha = 2.0 * math.pi * alpha_draw
    rho = math.sqrt(max(1.0 - u * u, 0.0))
    return rho * math.cos(alpha), rho * math.sin(alpha), u


@numba.njit(cache=True, parallel=True)
def _unit_sphere_rows(u_draws: np.ndarray, alpha_draws: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points :func:`_sphere_point` of ``(n,)`` draws."""
    n = u_draws.shape[0]
    out = np.empty((n, 3))
    for i in numba.prange(n):
        out[i, 0], out[i, 1], out[i, 2] = _sphere_point(u_draws[i], alpha_draws[i])
    return out


@numba.njit(cache=True, parallel=True)
def _sphere_chords(draws: np.ndarray, center: np.ndarray, radius: float):
    """Lines through ``center + radius * a`` towards ``center + radius * b``, ``a`` and ``b`` the
    unit-sphere points (:func:`_sphere_point`) of the draws ``(4, n)`` (rows: ``u`` and ``alpha``
    of ``a``, then of ``b``): ``origins (n, 3)``, unit ``directions (n, 3)`` and ``(n,)`` bool,
    True where ``a`` and ``b`` (nearly) coincide and the direction is left undefined."""
    n = draws.shape[1]
    origins = np.empty((n, 3))
    dirs = np.empty((n, 3))
    degenerate = np.empty(n, dtype=np.bool_)
    for i in numba.prange(n):
        ax, ay, az = _sphere_point(draws[0, i], draws[1, i])
        bx, by, bz = _sphere_point(draws[2, i], draws[3, i])
        dx, dy, dz = bx - ax, by - ay, bz - az
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        degenerate[i] = norm < 1e-12
        if degenerate[i]:
            norm = 1.0
        for axis, a, d in ((0, ax, dx), (1, ay, dy), (2, az, dz)):
            origins[i, axis] = center[axis] + radius * a
            dirs[i, axis] = d / norm
    return origins, dirs, degenerate


def _unit_sphere_points(n: int, generator: torch.Generator) -> np.ndarray:
    """``(n, 3)`` points uniform on the unit sphere via the paper's ``(u, alpha)`` parametrisation."""
    u_draws = _rand((n,), generator)
    return _unit_sphere_rows(u_draws, _rand((n,), generator))


def _sphere(center: np.ndarray, radius: float, n: int, generator: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Lines through two independent points of a sphere (the draws of two
    :func:`_unit_sphere_points` calls, taken at once); the direction comes from the unit sphere
    points, so it stays defined for any radius (a random one for coincident points)."""
    draws = _rand((4, n), generator)
    origins, dirs, degenerate = _sphere_chords(draws, np.asarray(center, dtype=np.float64), float(radius))
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


def _box_and_centroid(cloud: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """``(B, 9)`` per sample: bounding-box min (3), max (3) and centroid (3) of the valid points
    of ``cloud (B, N, 3)``, float64, computed on the cloud's device."""
    valid = (torch.arange(cloud.shape[1], device=cloud.device)[None] < lengths[:, None])[..., None]
    points = cloud.detach().double()
    lo = points.masked_fill(~valid, math.inf).amin(dim=1)
    hi = points.masked_fill(~valid, -math.inf).amax(dim=1)
    centroid = (points * valid).sum(dim=1) / lengths[:, None]
    return torch.cat([lo, hi, centroid], dim=1)


def _joint_cover(src: torch.Tensor, tgt: torch.Tensor, src_lengths: torch.Tensor, tgt_lengths: torch.Tensor):
    """``(B, 10)`` per sample: the joint bounding box's min (3), max (3) and centre (3) over the
    valid points of both clouds, and the covering radius (1), the largest distance from that
    centre to a valid point; float64, computed on the clouds' device."""
    points = torch.cat([src, tgt], dim=1).detach().double()
    index = torch.arange(points.shape[1], device=points.device)[None]
    n_src = src.shape[1]
    valid = (index < src_lengths[:, None]) | ((index >= n_src) & (index < n_src + tgt_lengths[:, None]))
    lo = points.masked_fill(~valid[..., None], math.inf).amin(dim=1)
    hi = points.masked_fill(~valid[..., None], -math.inf).amax(dim=1)
    center = (lo + hi) / 2
    cover = (points - center[:, None]).norm(dim=-1).masked_fill(~valid, 0.0).amax(dim=1)
    return torch.cat([lo, hi, center, cover[:, None]], dim=1)


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
    # The only host transfer of the sampler: (B, 12) numbers, (B, 30) for ``authors``.
    parts = [_joint_cover(src, tgt, src_lengths, tgt_lengths), src_lengths[:, None], tgt_lengths[:, None]]
    if sampling == "authors":
        parts += [_box_and_centroid(src, src_lengths), _box_and_centroid(tgt, tgt_lengths)]
    stats = torch.cat([part.double() for part in parts], dim=1).cpu().numpy()
    batch = src.shape[0]
    origins = np.empty((batch, num_lines, 3))
    dirs = np.empty((batch, num_lines, 3))
    counts = np.full(batch, num_lines, dtype=np.int64)
    picks = np.zeros((batch, 2, num_lines), dtype=np.int64)
    for b in range(batch):
        lo, hi, center_b, cover_b = stats[b, 0:3], stats[b, 3:6], stats[b, 6:9], stats[b, 9]
        if sampling == "sphere":
            origins[b], dirs[b] = _sphere(center_b, cover_b * radius_factor, num_lines, generator)
        elif sampling == "box_point_direction":
            origins[b] = lo + (hi - lo) * _rand((num_lines, 3), generator)
            dirs[b] = _unit_sphere_points(num_lines, generator)
        elif sampling == "cloud_points":
            for side, n_points in ((0, stats[b, 10]), (1, stats[b, 11])):
                n_points = int(n_points)
                picks[b, side] = (_rand((num_lines,), generator) * n_points).astype(np.int64).clip(0, n_points - 1)
                # origins/dirs hold the two perturbations until the picked points are added.
                (origins if side == 0 else dirs)[b] = (
                    perturbation * cover_b * (2.0 * _rand((num_lines, 3), generator) - 1.0)
                )
        else:
            s_lo, s_hi = stats[b, 12:15], stats[b, 15:18]
            t_lo, t_hi, t_centroid = stats[b, 21:24], stats[b, 24:27], stats[b, 27:30]
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
        cover = torch.from_numpy(stats[:, 9]).to(device)
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
