"""A deliberately simple dense reference of the line-intersection metric.

Every point-line distance is materialised (``L x N``) and lines are processed one by one in
Python, straight from the paper's definitions. Only for small cases: tests compare the sparse
implementation against it, and ``scripts/bench_loss.py`` times it where it fits.
"""

from __future__ import annotations

import numpy as np
import torch

from losses.line_intersection import LineMetricOptions


def _intersections(
    points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, options: LineMetricOptions
) -> list[torch.Tensor]:
    """Per line, the ``(h, 3)`` intersection points of one cloud."""
    k = options.k
    pairwise = torch.cdist(points.detach(), points.detach())
    pairwise.fill_diagonal_(float("inf"))
    nbr_dist, nbr_idx = pairwise.topk(k, dim=1, largest=False)
    rel = points.detach()[None, :, :] - origins[:, None, :]
    t = (rel * dirs[:, None, :]).sum(-1)
    dist = (rel.square().sum(-1) - t.square()).clamp_min(0.0).add(options.distance_eps).sqrt()
    if options.intersection == "triplet":
        members = torch.cat([torch.arange(len(points))[:, None], nbr_idx], dim=1)
        coords = points.detach()[members]
        spacing = torch.cdist(coords, coords).sum(dim=(1, 2)) / 2 / (k * (k + 1) / 2)
        radius = options.delta_factor * spacing
    else:
        radius = torch.full((len(points),), options.delta_factor * float(nbr_dist.mean()), dtype=points.dtype)
    out = []
    for line in range(len(origins)):
        rows = []
        for anchor in range(len(points)):
            d0 = dist[line, anchor]
            if not d0 < radius[anchor]:
                continue
            if options.intersection == "candidates":
                rows.append(points[anchor])
                continue
            members = [anchor, *nbr_idx[anchor].tolist()]
            limits = radius[members] if options.intersection == "convex" else radius[anchor].expand(len(members))
            d = dist[line, members]
            if not bool((d < limits).all()):
                continue
            if not options.detach_weights:
                rel = points[members] - origins[line]
                d = ((rel.square().sum(-1) - (rel @ dirs[line]).square()).clamp_min(0.0) + options.distance_eps).sqrt()
            w = d / d.sum() if float(d.sum()) > 0 else torch.full_like(d, 1.0 / len(members))
            rows.append((w[:, None] * points[members]).sum(0))
        out.append(torch.stack(rows) if rows else points.new_zeros((0, 3)))
    return out


def dense_line_metric(
    src: torch.Tensor, tgt: torch.Tensor, origins: np.ndarray, dirs: np.ndarray, options: LineMetricOptions
) -> torch.Tensor:
    """The metric for one pair ``src (N, 3)``, ``tgt (M, 3)`` and explicit lines (0-dim tensor)."""
    o = torch.as_tensor(origins, dtype=src.dtype)
    u = torch.as_tensor(dirs, dtype=src.dtype)
    s_lines = _intersections(src, o, u, options)
    t_lines = _intersections(tgt, o, u, options)
    pairs = []  # (line, is_row, |S_l|, |T_l|, squared distance)
    for line, (s, t) in enumerate(zip(s_lines, t_lines, strict=True)):
        ns, nt = len(s), len(t)
        if ns == 0 or nt == 0:
            continue
        if options.max_hits is not None and (ns > options.max_hits or nt > options.max_hits):
            continue
        d2 = (s[:, None, :] - t[None, :, :]).square().sum(-1)
        rows = d2.detach().argmin(dim=1)
        cols = d2.detach().argmin(dim=0)
        pairs += [(line, True, ns, nt, d2[i, rows[i]]) for i in range(ns)]
        pairs += [(line, False, ns, nt, d2[cols[j], j]) for j in range(nt)]
    if not pairs:
        return src.sum() * 0.0
    d2 = torch.stack([p[4] for p in pairs])
    if options.nu is not None:
        scale = d2.new_tensor(options.nu)
    elif options.welsch_input == "distance":
        scale = options.nu0 * d2.detach().sqrt().median()
    else:
        scale = options.nu0 * d2.detach().median()
    two_c = 2.0 * (scale**2 if options.welsch_input == "distance" else scale)
    psi = 1.0 - torch.exp(-d2 / two_c.clamp_min(torch.finfo(d2.dtype).tiny))
    weight = torch.tensor(
        [np.exp(-abs(p[2] - p[3]) / 2.0) if options.line_weight else 1.0 for p in pairs], dtype=psi.dtype
    )
    if options.reduction == "lines":
        return (weight * psi).sum() / len({p[0] for p in pairs})
    groups: dict[tuple[int, int], dict[bool, list[torch.Tensor]]] = {}
    for p, value in zip(pairs, weight * psi, strict=True):
        groups.setdefault((p[2], p[3]), {True: [], False: []})[p[1]].append(value)
    total = sum(torch.stack(g[True]).mean() + torch.stack(g[False]).mean() for g in groups.values())
    return total / len(groups)
