"""Device-native (pure torch) index search of the line-intersection metric.

The twin of :mod:`linereg.losses.line_kernels` for any device: the same candidate test, neighbour test,
convex or barycentric weights and closest-point matching, batched over ``B`` samples with
padding masks, and never a per-sample host round trip (a few syncs per batch remain where a
result size is data dependent: ``nonzero``, ``repeat_interleave``).

There is no spatial index: every point is tested against every line with two batched matrix
products per chunk of lines (``(B, chunk, N)`` temporaries under a fixed number of elements),
a prefilter with a safety margin; the few pairs that pass are then decided with the kernels'
exact formula. The selection runs in float64 whatever the input dtype, so the candidate sets
agree with the numba kernels. On a CPU the numba kernels are much faster
(``scripts/bench_loss.py --backend torch``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import line_kernels

_CHUNK_ELEMENTS = {"cpu": 2**20}
_CHUNK_ELEMENTS_OTHER = 2**24


@dataclass
class Hits:
    """Intersections of the lines of a batch with one side (all sources or all targets).

    Attributes:
        line: ``(H,)`` int64 global line id ``b * L + l`` of each intersection, ascending.
        members: ``(H, k+1)`` int64 rows of the flattened clouds ``(B * N, 3)`` combined into
            each intersection (anchor first; ``(H, 1)`` for ``candidates``).
        weights: ``(H, k+1)`` float64 detached convex (or barycentric) weights.
    """

    line: torch.Tensor
    members: torch.Tensor
    weights: torch.Tensor


def chunk_elements(device: torch.device) -> int:
    """Largest ``chunk * N`` of one all-pairs block on ``device``."""
    return _CHUNK_ELEMENTS.get(device.type, _CHUNK_ELEMENTS_OTHER)


def _line_distance(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, eps2: float) -> torch.Tensor:
    """``sqrt(max(|p - o|^2 - ((p - o) . u)^2, 0) + eps2)`` in the kernels' operation order."""
    rel = points - origins
    t = (rel * dirs).sum(-1)
    return ((rel.square().sum(-1) - t.square()).clamp_min(0.0) + eps2).sqrt()


def _pierce_weights(tri: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Barycentric weights ``(H, 3)`` where each line pierces its triangle ``tri (H, 3, 3)``
    (Moller-Trumbore, as :func:`linereg.losses.line_kernels._pierce_weights`) and ``(H,)`` validity."""
    a, b, c = tri.unbind(1)
    e1, e2 = b - a, c - a
    p = torch.cross(dirs, e2, dim=-1)
    det = (e1 * p).sum(-1)
    scale = (e1.square().sum(-1) * e2.square().sum(-1)).sqrt()
    ok = det.abs() > 1e-3 * scale
    safe = torch.where(ok, det, torch.ones_like(det))
    s = origins - a
    w1 = (s * p).sum(-1) / safe
    w2 = (dirs * torch.cross(s, e1, dim=-1)).sum(-1) / safe
    return torch.stack([1.0 - w1 - w2, w1, w2], dim=-1), ok


def torch_hits(
    points: torch.Tensor,
    valid: torch.Tensor,
    radius: torch.Tensor,
    neighbors: torch.Tensor,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    line_valid: torch.Tensor,
    mode: int,
    eps2: float,
) -> Hits:
    """Intersections of every line with its sample's cloud, all samples at once.

    Args:
        points: ``(B, N, 3)`` float64 detached points.
        valid: ``(B, N)`` bool, False for padding.
        radius: ``(B, N)`` float64 cylinder radius of each point.
        neighbors: ``(B, N, k)`` int64 k nearest neighbours (sample-local indices).
        origins, dirs: ``(B, L, 3)`` float64 lines.
        line_valid: ``(B, L)`` bool, False for padding lines.
        mode: one of the ``line_kernels.MODE_*`` constants.
        eps2: added under the square root of every point-line distance.
    """
    batch, n = points.shape[:2]
    n_lines = origins.shape[1]
    k = neighbors.shape[2]
    flat_o, flat_u = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    r2 = torch.where(valid, radius.square(), -1.0)
    line_ok = line_valid.reshape(-1)
    # Prefilter with matrix products on coordinates centred per sample (so that the rounding of
    # the expanded squares stays far below r^2), then decide exactly as the numba kernel does.
    center = (points * valid[..., None]).sum(dim=1, keepdim=True) / valid.sum(dim=1)[:, None, None]
    p_c = points - center
    o_c = origins - center
    p_sq = p_c.square().sum(-1)
    o_sq = o_c.square().sum(-1)
    o_dot_u = (o_c * dirs).sum(-1)
    scale = p_sq.masked_fill(~valid, 0.0).amax(dim=1) + o_sq.amax(dim=1)
    limit = torch.where(valid, r2 + 1e-9 * scale[:, None], -torch.inf)
    chunk = max(1, chunk_elements(points.device) // (batch * n))
    found_line, found_point = [], []
    for l0 in range(0, n_lines, chunk):
        l1 = min(n_lines, l0 + chunk)
        po = torch.bmm(o_c[:, l0:l1], p_c.transpose(1, 2))
        t = torch.bmm(dirs[:, l0:l1], p_c.transpose(1, 2)) - o_dot_u[:, l0:l1, None]
        d2 = p_sq[:, None] - 2.0 * po + o_sq[:, l0:l1, None] - t.square()
        maybe = d2 + eps2 < limit[:, None]
        b, l, i = maybe.nonzero(as_tuple=True)
        found_line.append(b * n_lines + l + l0)
        found_point.append(i)
    line, anchor = torch.cat(found_line), torch.cat(found_point)
    line, order = torch.sort(line, stable=True)
    anchor = anchor[order]
    sample = line // n_lines
    rel = points[sample, anchor] - flat_o[line]
    t = (rel * flat_u[line]).sum(-1)
    d2 = (rel.square().sum(-1) - t.square()).clamp_min(0.0)
    exact = (d2 + eps2 < r2[sample, anchor]) & line_ok[line]
    line, anchor, d2 = line[exact], anchor[exact], d2[exact]
    d_anchor = (d2 + eps2).sqrt()
    sample = line // n_lines
    if mode == line_kernels.MODE_CANDIDATES:
        members = (anchor + sample * n)[:, None]
        return Hits(line, members, torch.ones(len(line), 1, dtype=points.dtype, device=points.device))
    nb = neighbors[sample, anchor]
    o, u = flat_o[line], flat_u[line]
    dn = _line_distance(points[sample[:, None], nb], o[:, None], u[:, None], eps2)
    limit = radius[sample, anchor][:, None] if mode == line_kernels.MODE_TRIPLET else radius[sample[:, None], nb]
    keep = (dn < limit).all(dim=1)
    line, anchor, sample, nb, dn, d_anchor, o, u = (x[keep] for x in (line, anchor, sample, nb, dn, d_anchor, o, u))
    total = d_anchor.clone()
    for j in range(k):
        total = total + dn[:, j]
    distances = torch.cat([d_anchor[:, None], dn], dim=1)
    weights = torch.where(total[:, None] > 0, distances / torch.where(total > 0, total, 1.0)[:, None], 1.0 / (k + 1))
    if mode == line_kernels.MODE_PIERCE:
        tri = points[sample[:, None], torch.cat([anchor[:, None], nb[:, :2]], dim=1)]
        bary, ok = _pierce_weights(tri, o, u)
        weights = torch.where(ok[:, None], bary, weights)
    members = torch.cat([anchor[:, None], nb], dim=1) + (sample * n)[:, None]
    return Hits(line, members, weights)


def _nearest_on_line(
    a_line: torch.Tensor, a: torch.Tensor, b_count: torch.Tensor, b: torch.Tensor, keep: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """For every row of ``a`` on a kept line, the row of ``b`` on the same line closest to it
    (the first in ``b``'s order on ties). ``b`` is sorted by line; ``b_count (G,)`` rows per line."""
    b_start = torch.cumsum(b_count, 0) - b_count
    rows = keep[a_line].nonzero().squeeze(1)
    reps = b_count[a_line[rows]]
    pair_a = torch.repeat_interleave(rows, reps)
    first = torch.repeat_interleave(torch.cumsum(reps, 0) - reps, reps)
    pair_b = b_start[a_line[pair_a]] + torch.arange(len(pair_a), device=a.device) - first
    d2 = (a[pair_a] - b[pair_b]).square().sum(-1)
    best = torch.full((len(a),), torch.inf, dtype=d2.dtype, device=a.device).scatter_reduce(
        0, pair_a, d2, "amin", include_self=True
    )
    last = torch.iinfo(torch.int64).max
    candidate = torch.where(d2 == best[pair_a], pair_b, last)
    choice = torch.full((len(a),), last, dtype=torch.int64, device=a.device).scatter_reduce(
        0, pair_a, candidate, "amin", include_self=True
    )
    return rows, choice[rows]


def match_along_lines(
    src_line: torch.Tensor,
    tgt_line: torch.Tensor,
    src_points: torch.Tensor,
    tgt_points: torch.Tensor,
    src_count: torch.Tensor,
    tgt_count: torch.Tensor,
    keep: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest-point matching both ways on each kept line (the twin of
    :func:`linereg.losses.line_kernels.match_along_lines`).

    Returns:
        ``src_index (P,)``, ``tgt_index (P,)``, ``line (P,)`` and ``is_row (P,)`` (True for
        source->target matches, ``sigma_l``; False for target->source ones, ``rho_l``).
    """
    s_rows, s_match = _nearest_on_line(src_line, src_points, tgt_count, tgt_points, keep)
    t_rows, t_match = _nearest_on_line(tgt_line, tgt_points, src_count, src_points, keep)
    is_row = torch.cat([torch.ones_like(s_rows, dtype=torch.bool), torch.zeros_like(t_rows, dtype=torch.bool)])
    return (
        torch.cat([s_rows, t_match]),
        torch.cat([s_match, t_rows]),
        torch.cat([src_line[s_rows], tgt_line[t_rows]]),
        is_row,
    )
