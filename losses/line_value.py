"""Step 3 of the line-intersection metric: the Welsch value of the matched intersections.

:func:`line_values` computes it with torch (autograd differentiates it); on the numba path of
:func:`fused_path` the kernels compute the value and its gradient themselves
(:class:`FusedLineValue`, :func:`linereg.losses.line_welsch_kernels.welsch_lines`).
"""

from __future__ import annotations

import torch

from .line_options import LineMetricOptions
from .line_pairs import KernelPlan, LinePairs, numba_plan, resolve_lines, stacked_points
from .line_welsch_kernels import welsch_lines


def _segment_lower_median(values: torch.Tensor, segment: torch.Tensor, n_segments: int) -> torch.Tensor:
    """``(n_segments,)`` lower median of ``values`` within each segment (``torch.median``'s
    convention), 0 for an empty segment."""
    counts = torch.bincount(segment, minlength=n_segments)
    if len(values) == 0:
        return values.new_zeros(n_segments)
    order = torch.argsort(values)
    order = order[torch.argsort(segment[order], stable=True)]
    starts = torch.cumsum(counts, 0) - counts
    pick = (starts + (counts - 1).clamp_min(0) // 2).clamp_max(len(values) - 1)
    return torch.where(counts > 0, values[order][pick], 0.0)


def welsch_terms(
    pairs: LinePairs, options: LineMetricOptions
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per match: the line weight ``w_l``, the squared distance and the Welsch denominator
    ``2 nu^2`` (``2 c`` for squared input); and the per-sample scale ``nu (B,)`` (detached; 0 for
    a sample without matches)."""
    batch, n_lines = pairs.lines.origins.shape[:2]
    diff = pairs.src_points[pairs.src_index] - pairs.tgt_points[pairs.tgt_index]
    dist_sq = diff.square().sum(dim=1)
    sample = pairs.line // n_lines
    if options.nu is not None:
        scale = dist_sq.new_full((batch,), options.nu)
    elif options.welsch_input == "distance":
        scale = options.nu0 * _segment_lower_median(dist_sq.detach().sqrt(), sample, batch)
    else:
        scale = options.nu0 * _segment_lower_median(dist_sq.detach(), sample, batch)
    two_c = (2.0 * (scale.square() if options.welsch_input == "distance" else scale)).clamp_min(
        torch.finfo(dist_sq.dtype).tiny
    )
    if options.line_weight:
        line_w = torch.exp(-(pairs.src_count - pairs.tgt_count).abs().to(dist_sq.dtype) / 2.0)[pairs.line]
    else:
        line_w = torch.ones_like(dist_sq)
    return line_w, dist_sq, two_c[sample], scale


def line_values(
    pairs: LinePairs, options: LineMetricOptions, anchor: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 3: ``(B,)`` values and ``(B, 7)`` statistics (:data:`linereg.losses.line_options.STAT_KEYS`)."""
    batch, n_lines = pairs.lines.origins.shape[:2]
    line_w, dist_sq, two_c, scale = welsch_terms(pairs, options)
    weighted = line_w * (1.0 - torch.exp(-dist_sq / two_c))
    sample = pairs.line // n_lines
    kept = pairs.keep.view(batch, n_lines).sum(dim=1)
    # A sample without a kept line is a defined zero with a zero gradient, still on the graph.
    zero = anchor.sum() * 0.0
    if options.reduction == "lines":
        sums = weighted.new_zeros(batch).index_add(0, sample, weighted)
        value = zero + sums / kept.clamp_min(1).to(weighted.dtype)
    else:
        # The authors' per-(|S_l|, |T_l|) averaging, rows (source->target) and columns apart.
        src_size, tgt_size = len(pairs.src_points) + 1, len(pairs.tgt_points) + 1
        group = (sample * src_size + pairs.src_count[pairs.line]) * tgt_size + pairs.tgt_count[pairs.line]
        buckets, bucket = torch.unique(group * 2 + (~pairs.is_row).long(), return_inverse=True)
        sums = weighted.new_zeros(len(buckets)).index_add(0, bucket, weighted)
        means = sums / torch.bincount(bucket, minlength=len(buckets)).to(weighted.dtype)
        bucket_sample = buckets // 2 // (src_size * tgt_size)
        group_sample = torch.unique(group) // (src_size * tgt_size)
        n_groups = torch.bincount(group_sample, minlength=batch).clamp_min(1)
        value = zero + weighted.new_zeros(batch).index_add(0, bucket_sample, means) / n_groups.to(weighted.dtype)
    ns = pairs.src_count.view(batch, n_lines)
    nt = pairs.tgt_count.view(batch, n_lines)
    stats = torch.stack(
        [
            torch.from_numpy(pairs.lines.counts).to(ns.device),
            kept,
            (ns > 0).sum(dim=1),
            (nt > 0).sum(dim=1),
            ns.sum(dim=1),
            nt.sum(dim=1),
        ],
        dim=1,
    ).double()
    return value, torch.cat([stats, scale.detach().double()[:, None]], dim=1)


def fused_path(options: LineMetricOptions, device: torch.device) -> bool:
    """Whether the numba kernels compute the value and its gradient themselves
    (:class:`FusedLineValue`): the numba backend with constant intersection weights and the
    per-line reduction; other settings take the torch formula of :func:`line_values`."""
    constant_weights = options.detach_weights or options.intersection in ("candidates", "pierce")
    return options.resolved_backend(device) == "numba" and constant_weights and options.reduction == "lines"


class FusedLineValue(torch.autograd.Function):
    """Step 3 for a fixed :class:`KernelPlan`: ``(B,)`` values, ``(B,)`` scales ``nu`` and
    ``(B, 5)`` hit counts (see :func:`linereg.losses.line_welsch_kernels.welsch_lines`) from ``src (B, N, 3)``
    and ``tgt (B, M, 3)``; the kernel writes the gradient w.r.t. the points during the forward
    pass, and the backward pass only scales it by the incoming ``(B,)`` gradient."""

    @staticmethod
    def forward(ctx, src, tgt, plan: KernelPlan, options: LineMetricOptions):
        batch = src.shape[0]
        points = stacked_points([src, tgt], plan.point_lengths)
        value, grad, scale, counts = welsch_lines(
            plan.offsets,
            plan.anchors,
            plan.weights,
            plan.line_offsets,
            points,
            plan.point_offsets,
            plan.neighbors,
            batch,
            -1 if options.max_hits is None else options.max_hits,
            options.line_weight,
            options.welsch_input == "squared",
            options.nu0,
            0.0 if options.nu is None else options.nu,
            float(torch.finfo(src.dtype).tiny),
        )
        grad_rows = torch.from_numpy(grad)
        grads = []
        for side, cloud in enumerate((src, tgt)):
            first = side * batch
            rows = grad_rows[plan.point_offsets[first] : plan.point_offsets[first + batch]]
            if (plan.point_lengths[first : first + batch] == cloud.shape[1]).all():
                padded = rows.view(cloud.shape)
            else:
                padded = rows.new_zeros(cloud.shape)
                for b in range(batch):
                    c = first + b
                    padded[b, : plan.point_lengths[c]] = grad_rows[plan.point_offsets[c] : plan.point_offsets[c + 1]]
            grads.append(padded.to(cloud.device, cloud.dtype))
        ctx.save_for_backward(*grads)
        scale_t, counts_t = torch.from_numpy(scale), torch.from_numpy(counts)
        ctx.mark_non_differentiable(scale_t, counts_t)
        return torch.from_numpy(value).to(src.device, src.dtype), scale_t, counts_t

    @staticmethod
    def backward(ctx, grad_value, _grad_scale, _grad_counts):
        grad_src, grad_tgt = ctx.saved_tensors
        weight = grad_value[:, None, None]
        return weight * grad_src, weight * grad_tgt, None, None


def fused_values(src, tgt, src_lengths, tgt_lengths, options, generator, lines):
    """Steps 1-3 on the numba path (:func:`fused_path`): ``(B,)`` values and ``(B, 7)`` statistics."""
    line_batch = resolve_lines(src, tgt, src_lengths, tgt_lengths, options, generator, lines)
    plan = numba_plan(src, tgt, src_lengths, tgt_lengths, line_batch, options)
    value, scale, counts = FusedLineValue.apply(src, tgt, plan, options)
    stats = torch.cat([torch.from_numpy(line_batch.counts)[:, None], counts], dim=1).double()
    return value, torch.cat([stats, scale[:, None]], dim=1)
