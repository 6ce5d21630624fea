"""A deliberately simple dense reference of the line-intersection metric.

Every point-line distance is materialised (an ``L x N`` matrix, processed in chunks of lines),
straight from the paper's definitions, with no spatial index. Tests compare the sparse
implementation against it (values and gradients), and ``scripts/bench_loss.py`` times it where
it fits in memory.
"""

from __future__ import annotations

import numpy as np
import torch

from linereg.losses.line_intersection import LineMetricOptions


def _cloud_setup(points: torch.Tensor, options: LineMetricOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """``members (N, k+1)`` (each point and its k nearest neighbours) and ``radius (N,)``."""
    k = options.k
    detached = points.detach()
    pairwise = torch.cdist(detached, detached)
    pairwise.fill_diagonal_(float("inf"))
    nbr_dist, nbr_idx = pairwise.topk(k, dim=1, largest=False)
    members = torch.cat([torch.arange(len(points), device=points.device)[:, None], nbr_idx], dim=1)
    if options.intersection == "triplet":
        coords = detached[members]
        radius = options.delta_factor * torch.cdist(coords, coords).sum(dim=(1, 2)) / 2 / (k * (k + 1) / 2)
    else:
        radius = torch.full((len(points),), options.delta_factor * float(nbr_dist.mean()), dtype=points.dtype)
    return members, radius.to(points.device)


def _line_distance(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, eps: float) -> torch.Tensor:
    """``(C, N)`` distances from every point to every line of the chunk."""
    rel = points[None] - origins[:, None]
    t = (rel * dirs[:, None]).sum(-1)
    return ((rel.square().sum(-1) - t.square()).clamp_min(0.0) + eps).sqrt()


def _pierce_weights(triangles: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor):
    """Barycentric weights ``(C, N, 3)`` of where each line pierces each triangle ``(N, 3, 3)``,
    and ``(C, N, 1)`` validity (not degenerate, not parallel)."""
    a, b, c = triangles.unbind(1)
    e1, e2 = (b - a)[None], (c - a)[None]
    s = origins[:, None] - a[None]
    u = dirs[:, None].expand_as(s)
    det = (e1 * torch.cross(u, e2, dim=-1)).sum(-1)
    w1 = (s * torch.cross(u, e2, dim=-1)).sum(-1) / det
    w2 = (u * torch.cross(s, e1, dim=-1)).sum(-1) / det
    ok = det.abs() > 1e-3 * (e1.norm(dim=-1) * e2.norm(dim=-1))
    return ok[..., None], torch.stack([1.0 - w1 - w2, w1, w2], dim=-1)


def _chunk_intersections(points, members, radius, origins, dirs, options):
    """Padded intersections of a chunk of lines: ``(C, H, 3)`` points and ``(C, H)`` validity."""
    dist = _line_distance(points.detach(), origins, dirs, options.distance_eps)
    if options.intersection == "candidates":
        mask = dist < radius[None]
        inter = points[None].expand(len(origins), -1, -1)
    else:
        member_dist = dist[:, members]
        limits = radius[members] if options.intersection == "convex" else radius[:, None].expand_as(members)
        mask = (member_dist < limits[None]).all(-1)
        if not options.detach_weights:
            member_dist = _line_distance(points, origins, dirs, options.distance_eps)[:, members]
        total = member_dist.sum(-1, keepdim=True)
        w = torch.where(total > 0, member_dist / total.clamp_min(1e-300), 1.0 / members.shape[1])
        if options.intersection == "pierce":
            w = torch.where(*_pierce_weights(points.detach()[members], origins, dirs), w)
        inter = (w[..., None] * points[members][None]).sum(-2)
    counts = mask.sum(1)
    width = max(int(counts.max()), 1)
    order = torch.sort((~mask).to(torch.int8), dim=1, stable=True).indices[:, :width]
    valid = torch.arange(width, device=points.device)[None] < counts[:, None]
    return inter.gather(1, order[..., None].expand(-1, -1, 3)), valid


def dense_line_metric(
    src: torch.Tensor,
    tgt: torch.Tensor,
    origins: np.ndarray,
    dirs: np.ndarray,
    options: LineMetricOptions,
    chunk: int = 256,
) -> torch.Tensor:
    """The metric for one pair ``src (N, 3)``, ``tgt (M, 3)`` and explicit lines (0-dim tensor)."""
    o_all = torch.as_tensor(origins, dtype=src.dtype, device=src.device)
    u_all = torch.as_tensor(dirs, dtype=src.dtype, device=src.device)
    src_setup, tgt_setup = _cloud_setup(src, options), _cloud_setup(tgt, options)
    d2_parts, weight_parts, group_parts, row_parts, line_count = [], [], [], [], 0
    for start in range(0, len(o_all), chunk):
        o, u = o_all[start : start + chunk], u_all[start : start + chunk]
        s, s_valid = _chunk_intersections(src, *src_setup, o, u, options)
        t, t_valid = _chunk_intersections(tgt, *tgt_setup, o, u, options)
        ns, nt = s_valid.sum(1), t_valid.sum(1)
        keep = (ns > 0) & (nt > 0)
        if options.max_hits is not None:
            keep &= (ns <= options.max_hits) & (nt <= options.max_hits)
        d2 = (s[:, :, None] - t[:, None, :]).square().sum(-1)
        both = s_valid[:, :, None] & t_valid[:, None, :]
        blocked = d2.detach().masked_fill(~both, float("inf"))
        rows = d2.gather(2, blocked.argmin(2, keepdim=True))[..., 0]
        cols = d2.gather(1, blocked.argmin(1, keepdim=True))[:, 0]
        row_sel = s_valid & keep[:, None]
        col_sel = t_valid & keep[:, None]
        line_w = torch.exp(-(ns - nt).abs().to(src.dtype) / 2.0)
        if not options.line_weight:
            line_w = torch.ones_like(line_w)
        group = (ns - 1) * 1000 + (nt - 1)
        for values, sel, is_row in ((rows, row_sel, True), (cols, col_sel, False)):
            d2_parts.append(values[sel])
            weight_parts.append(line_w[:, None].expand_as(sel)[sel])
            group_parts.append(group[:, None].expand_as(sel)[sel])
            row_parts.append(torch.full((int(sel.sum()),), is_row))
        line_count += int(keep.sum())
    d2 = torch.cat(d2_parts)
    if line_count == 0:
        return src.sum() * 0.0
    if options.nu is not None:
        scale = d2.new_tensor(options.nu)
    elif options.welsch_input == "distance":
        scale = options.nu0 * d2.detach().sqrt().median()
    else:
        scale = options.nu0 * d2.detach().median()
    two_c = 2.0 * (scale**2 if options.welsch_input == "distance" else scale)
    weighted = torch.cat(weight_parts) * (1.0 - torch.exp(-d2 / two_c.clamp_min(torch.finfo(d2.dtype).tiny)))
    if options.reduction == "lines":
        return weighted.sum() / line_count
    groups, is_row = torch.cat(group_parts), torch.cat(row_parts)
    total = sum(
        weighted[(groups == g) & is_row].mean() + weighted[(groups == g) & ~is_row].mean() for g in torch.unique(groups)
    )
    return total / len(torch.unique(groups))
