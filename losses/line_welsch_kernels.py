"""Compiled (numba) matching and value of the line-intersection metric, with its gradient.

From the intersections found by :func:`linereg.losses.line_kernels.line_intersections`, the
kernels match the intersections of each line both ways (closest point, paper Eq. 3's
``sigma_l`` and ``rho_l``) and compute the per-line Welsch reduction and, since the
intersection weights are constants, its gradient w.r.t. every point in closed form.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .line_kernels import float_zeros, int_zeros


@numba.njit(cache=True, inline="always")
def _nearest(points, row, others, start, stop):
    """Index in ``[start, stop)`` of the row of ``others`` closest to ``points[row]``."""
    best = np.inf
    arg = start
    for j in range(start, stop):
        d = 0.0
        for a in range(3):
            diff = points[row, a] - others[j, a]
            d += diff * diff
        if d < best:
            best = d
            arg = j
    return arg


@numba.njit(cache=True)
def match_along_lines(src_offsets, tgt_offsets, src_points, tgt_points, pair_offsets):
    """Closest-point matching both ways between the intersections of each line.

    Args:
        src_offsets, tgt_offsets: ``(L+1,)`` CSR offsets of the source/target intersections.
        src_points, tgt_points: ``(Hs, 3)``, ``(Ht, 3)`` float64 intersection points.
        pair_offsets: ``(L+1,)`` where line ``l`` owns ``|S_l| + |T_l|`` pair slots if it is
            kept, zero otherwise.

    Returns:
        ``src_index (P,)``, ``tgt_index (P,)`` int64 (into the intersection arrays), and
        ``line (P,)`` int64. Slots ``[0, |S_l|)`` of a line match each source intersection to
        its closest target intersection (sigma_l); the rest match each target intersection to
        its closest source intersection (rho_l).
    """
    n_lines = src_offsets.shape[0] - 1
    n_pairs = pair_offsets[-1]
    src_index = np.empty(n_pairs, dtype=np.int64)
    tgt_index = np.empty(n_pairs, dtype=np.int64)
    line_of = np.empty(n_pairs, dtype=np.int64)
    for line in range(n_lines):
        p = pair_offsets[line]
        if pair_offsets[line + 1] == p:
            continue
        s0, s1 = src_offsets[line], src_offsets[line + 1]
        g0, g1 = tgt_offsets[line], tgt_offsets[line + 1]
        for s in range(s0, s1):
            src_index[p] = s
            tgt_index[p] = _nearest(src_points, s, tgt_points, g0, g1)
            line_of[p] = line
            p += 1
        for g in range(g0, g1):
            src_index[p] = _nearest(tgt_points, g, src_points, s0, s1)
            tgt_index[p] = g
            line_of[p] = line
            p += 1
    return src_index, tgt_index, line_of


@numba.njit(cache=True, parallel=True)
def _hit_points(offsets, anchors, weights, line_offsets, points, point_offsets, neighbors):
    """``(H, 3)`` intersection points ``sum_m weights[h, m] * member_m`` (anchor first, then its
    neighbours), and ``(H, k+1)`` the rows of ``points`` of the members; clouds in parallel."""
    n_hits = anchors.shape[0]
    k = neighbors.shape[1]
    hit_points = np.empty((n_hits, 3))
    members = np.empty((n_hits, k + 1), dtype=np.int64)
    for c in numba.prange(point_offsets.shape[0] - 1):
        p0 = point_offsets[c]
        for h in range(offsets[line_offsets[c]], offsets[line_offsets[c + 1]]):
            anchor = p0 + anchors[h]
            members[h, 0] = anchor
            for m in range(k):
                members[h, m + 1] = p0 + neighbors[anchor, m]
            for a in range(3):
                total = 0.0
                for m in range(k + 1):
                    total += weights[h, m] * points[members[h, m], a]
                hit_points[h, a] = total
    return hit_points, members


@numba.njit(cache=True)
def _pair_slots(offsets, line_offsets, n_samples, max_hits):
    """Per line of the source side (``(Ls,)``, sample-major): intersections on each side, whether
    the line is kept, and ``(Ls+1,)`` offsets of its ``|S_l| + |T_l|`` pair slots (0 if dropped)."""
    n_lines = line_offsets[n_samples]
    ns = np.empty(n_lines, dtype=np.int64)
    nt = np.empty(n_lines, dtype=np.int64)
    keep = np.empty(n_lines, dtype=np.bool_)
    pair_offsets = np.zeros(n_lines + 1, dtype=np.int64)
    for line in range(n_lines):
        ns[line] = offsets[line + 1] - offsets[line]
        other = line + line_offsets[n_samples]
        nt[line] = offsets[other + 1] - offsets[other]
        within = max_hits < 0 or (ns[line] <= max_hits and nt[line] <= max_hits)
        keep[line] = ns[line] >= 1 and nt[line] >= 1 and within
        pair_offsets[line + 1] = pair_offsets[line] + (ns[line] + nt[line] if keep[line] else 0)
    return ns, nt, keep, pair_offsets


@numba.njit(cache=True, parallel=True)
def _closest_pairs(offsets, line_offsets, n_samples, hit_points, keep, pair_offsets):
    """Both-way closest-point matches on every kept line: ``(P,)`` source hit, target hit and
    squared distance; slots ``[0, |S_l|)`` of a line are ``sigma_l``, the rest ``rho_l``."""
    n_pairs = pair_offsets[-1]
    src_hit = np.empty(n_pairs, dtype=np.int64)
    tgt_hit = np.empty(n_pairs, dtype=np.int64)
    dist_sq = np.empty(n_pairs)
    for line in numba.prange(line_offsets[n_samples]):
        if not keep[line]:
            continue
        p = pair_offsets[line]
        s0, s1 = offsets[line], offsets[line + 1]
        other = line + line_offsets[n_samples]
        g0, g1 = offsets[other], offsets[other + 1]
        for s in range(s0, s1):
            src_hit[p] = s
            tgt_hit[p] = _nearest(hit_points, s, hit_points, g0, g1)
            p += 1
        for g in range(g0, g1):
            src_hit[p] = _nearest(hit_points, g, hit_points, s0, s1)
            tgt_hit[p] = g
            p += 1
    for p in numba.prange(n_pairs):
        d = 0.0
        for a in range(3):
            diff = hit_points[src_hit[p], a] - hit_points[tgt_hit[p], a]
            d += diff * diff
        dist_sq[p] = d
    return src_hit, tgt_hit, dist_sq


@numba.njit(cache=True, parallel=True)
def welsch_lines(
    offsets,
    anchors,
    weights,
    line_offsets,
    points,
    point_offsets,
    neighbors,
    n_samples,
    max_hits,
    line_weight,
    squared_input,
    nu0,
    fixed_nu,
    tiny,
):
    """Steps 2 and 3 of the metric with reduction ``lines``, and its gradient, from the output of
    :func:`line_intersections` (clouds ordered ``src_0 .. src_{B-1}, tgt_0 .. tgt_{B-1}``, the
    lines of ``tgt_b`` being those of ``src_b``).

    The value of sample ``b`` is ``sum_pairs w_l psi(|x - y|) / kept_b`` over the closest-point
    pairs of its kept lines, ``psi = 1 - exp(-d^2 / two_c)`` with ``two_c = 2 nu^2``
    (``2 nu`` for ``squared_input``), ``nu = fixed_nu`` if ``fixed_nu > 0`` else ``nu0`` times
    the lower median of ``d`` (``d^2`` for ``squared_input``) over the sample's pairs, detached;
    ``tiny`` bounds ``two_c`` from below. The convex weights are constants, so the gradient of
    ``value_b`` w.r.t. a point is the weighted sum of the gradients w.r.t. the intersections it
    belongs to.

    Args:
        offsets, anchors, weights: the output of :func:`line_intersections`.
        line_offsets, points, point_offsets, neighbors: its inputs (``2 B`` clouds).
        n_samples: ``B``.
        max_hits: lines with more intersections on a side are dropped (-1: no limit).
        line_weight: weight each line by ``w_l = exp(-| |S_l| - |T_l| | / 2)`` (else 1).

    Returns:
        ``value (B,)``, ``grad (N, 3)`` (``d value_b / d points``, rows as ``points``),
        ``scale (B,)`` (``nu``; 0 for a sample without pairs) and ``counts (B, 5)`` int64: kept
        lines, lines hit on the source and on the target side, source and target intersections.
    """
    hit_points, members = _hit_points(offsets, anchors, weights, line_offsets, points, point_offsets, neighbors)
    ns, nt, keep, pair_offsets = _pair_slots(offsets, line_offsets, n_samples, max_hits)
    src_hit, tgt_hit, dist_sq = _closest_pairs(offsets, line_offsets, n_samples, hit_points, keep, pair_offsets)
    value = float_zeros(n_samples)
    scale = float_zeros(n_samples)
    counts = int_zeros((n_samples, 5))
    two_c = float_zeros(n_samples)
    per_line = float_zeros(n_samples)
    line_sample = np.empty(line_offsets[n_samples], dtype=np.int64)
    for b in range(n_samples):
        l0, l1 = line_offsets[b], line_offsets[b + 1]
        for line in range(l0, l1):
            line_sample[line] = b
            counts[b, 0] += keep[line]
            counts[b, 1] += ns[line] > 0
            counts[b, 2] += nt[line] > 0
            counts[b, 3] += ns[line]
            counts[b, 4] += nt[line]
        q0, q1 = pair_offsets[l0], pair_offsets[l1]
        if q1 == q0:
            continue
        if fixed_nu > 0.0:
            scale[b] = fixed_nu
        else:
            middle = (q1 - q0 - 1) // 2
            lower_median = np.partition(dist_sq[q0:q1], middle)[middle]
            scale[b] = nu0 * (lower_median if squared_input else math.sqrt(lower_median))
        two_c[b] = max(2.0 * (scale[b] if squared_input else scale[b] * scale[b]), tiny)
        per_line[b] = 1.0 / max(counts[b, 0], 1)
    # Lines in parallel: each intersection belongs to one line, so each gradient row has one writer.
    line_total = np.empty(line_offsets[n_samples])
    hit_grad = float_zeros((anchors.shape[0], 3))
    for line in numba.prange(line_offsets[n_samples]):
        b = line_sample[line]
        w = math.exp(-abs(ns[line] - nt[line]) / 2.0) if line_weight else 1.0
        total = 0.0
        for p in range(pair_offsets[line], pair_offsets[line + 1]):
            near = math.exp(-dist_sq[p] / two_c[b])
            total += w * (1.0 - near)
            slope = per_line[b] * w * near * 2.0 / two_c[b]
            s, g = src_hit[p], tgt_hit[p]
            for a in range(3):
                step = slope * (hit_points[s, a] - hit_points[g, a])
                hit_grad[s, a] += step
                hit_grad[g, a] -= step
        line_total[line] = total
    for b in range(n_samples):
        total = 0.0  # a plain loop: an array sum here would become a parallel reduction
        for line in range(line_offsets[b], line_offsets[b + 1]):
            total += line_total[line]
        value[b] = total * per_line[b]
    # Clouds in parallel: the members of an intersection are points of its own cloud.
    grad = float_zeros(points.shape)
    for c in numba.prange(point_offsets.shape[0] - 1):
        for h in range(offsets[line_offsets[c]], offsets[line_offsets[c + 1]]):
            for m in range(members.shape[1]):
                for a in range(3):
                    grad[members[h, m], a] += weights[h, m] * hit_grad[h, a]
    return value, grad, scale, counts
