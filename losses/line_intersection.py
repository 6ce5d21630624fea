"""The line-intersection metric of Deng et al., "A Robust Loss for Point Cloud Registration"
(ICCV 2021), §3.2 — sparse, batched, differentiable w.r.t. the source points.

For ``L`` random lines ``l`` (see :mod:`losses.lines`):

1. **Intersections.** Points within ``delta = delta_factor * d_nei`` of the line are candidates
   (``d_nei``: mean distance to the ``k`` nearest neighbours, per cloud). A candidate ``p0``
   whose ``k`` nearest neighbours are candidates too yields the intersection
   ``p0' = sum_p d_p p / sum_p d_p`` over ``p0`` and its neighbours, ``d_p`` the distance of
   ``p`` to the line (Eq. 7; weights detached).
2. **Matching.** On each line that meets both clouds, every source intersection is matched to
   its closest target intersection and vice versa (Eq. 3's ``sigma_l``, ``rho_l``).
3. **Value.** ``F_l = w_l * sum_pairs psi_nu(||x - y||)`` with Welsch's
   ``psi_nu(d) = 1 - exp(-d^2 / (2 nu^2))``, ``nu = nu0 * median pair distance`` (detached,
   recomputed every call) and ``w_l = exp(-| |S_l| - |T_l| | / 2)``. The metric is the mean of
   ``F_l`` over the lines that meet both clouds.

Only point-line pairs that can interact are ever examined: a compiled grid walk
(:mod:`losses.line_kernels`) returns indices and convex weights, and torch gathers the points,
so memory is linear in ``N + L`` and the backward pass is a sparse scatter.

Options reproduce every ablation of the paper (Table 2) and the authors' released code:

================  ==========================================  ================================
option            paper (default)                             alternatives
================  ==========================================  ================================
``sampling``      ``sphere``                                  ``box_point_direction`` (Sample1),
                                                              ``cloud_points`` (Sample2),
                                                              ``authors``
``intersection``  ``convex`` (Eq. 7)                          ``candidates`` (Insec1),
                                                              ``triplet`` (authors),
                                                              ``pierce`` (linereg)
``nu0``           0.5                                         any > 0
``k``             2                                           any >= 1
``delta_factor``  sqrt(3)/2                                   any > 0
``line_weight``   True                                        False
``nu``            None (``nu0`` x median, detached)           a fixed absolute scale
``detach_weights`` True (Eq. 7 weights are constants)         False: differentiate them too
================  ==========================================  ================================

``variant="linereg"`` is the paper's metric with one change, ``intersection="pierce"``: the
intersection of a line with a candidate ``p0`` and its 2 neighbours is the point where the line
pierces their triangle, written with its barycentric weights (detached) as a combination of the
three points. Eq. (7)'s weights ``d_p / sum d`` give a point whose offset from the true crossing
is of the order of ``delta`` whatever the alignment, which limits how precisely the metric can
register two different samplings of one surface (see the README's registration benchmark).

``variant="authors"`` switches every default to what ``code/loss.py`` of the paper repository
does (reference-notes §1.5), each still overridable:

* lines from a sphere of radius = target bounding-box diagonal around the target centroid,
  kept only if they cross both bounding boxes (``sampling="authors"``);
* the hit test is stricter: a point and its 2 neighbours must *all* lie within
  ``sqrt(3)/2 * s`` of the line, ``s`` the mean pairwise spacing of that triplet (locally
  adaptive ``delta``), with ``2e-4`` added under every distance's square root
  (``intersection="triplet"``, ``distance_eps=2e-4``);
* Welsch on *squared* distances, ``psi = 1 - exp(-d^2 / (2 c))`` with ``c = median(d^2)``
  (``welsch_input="squared"``, ``nu0=1``);
* only lines with 1 to 4 intersections on each cloud count (``max_hits=4``);
* the value is averaged per (|S_l|, |T_l|) group: ``sum_g w_g (mean_rows + mean_cols) / #groups``
  (``reduction="groups"``);
* the authors' intersection point is ``mean_i(w_i p_i)``, i.e. a third of the convex
  combination. Both clouds are scaled alike and the Welsch scale is the median, so the value
  is unchanged by that factor; we keep the true convex combination.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from linereg.checks import check_points, check_same_batch
from linereg.pointcloud import knn

from . import line_kernels
from .base import LOSSES, AlignmentLoss
from .lines import SAMPLERS, sample_lines

INTERSECTIONS = {
    "candidates": line_kernels.MODE_CANDIDATES,
    "convex": line_kernels.MODE_CONVEX,
    "triplet": line_kernels.MODE_TRIPLET,
    "pierce": line_kernels.MODE_PIERCE,
}
REDUCTIONS = ("lines", "groups")
WELSCH_INPUTS = ("distance", "squared")

PAPER_DEFAULTS: dict[str, Any] = {
    "num_lines": 15000,
    "sampling": "sphere",
    "intersection": "convex",
    "k": 2,
    "delta_factor": math.sqrt(3.0) / 2.0,
    "nu0": 0.5,
    "line_weight": True,
    "welsch_input": "distance",
    "max_hits": None,
    "reduction": "lines",
    "radius_factor": 1.0,
    "distance_eps": 0.0,
    "cell_factor": 4.0,
    "nu": None,
    "detach_weights": True,
}
AUTHORS_OVERRIDES: dict[str, Any] = {
    "sampling": "authors",
    "intersection": "triplet",
    "welsch_input": "squared",
    "nu0": 1.0,
    "max_hits": 4,
    "reduction": "groups",
    "distance_eps": 2e-4,
}
LINEREG_OVERRIDES: dict[str, Any] = {"intersection": "pierce"}
VARIANTS = {"paper": {}, "authors": AUTHORS_OVERRIDES, "linereg": LINEREG_OVERRIDES}


@dataclass(frozen=True)
class LineMetricOptions:
    """Every setting of the metric (see the module docstring for their meaning)."""

    num_lines: int = PAPER_DEFAULTS["num_lines"]
    sampling: str = PAPER_DEFAULTS["sampling"]
    intersection: str = PAPER_DEFAULTS["intersection"]
    k: int = PAPER_DEFAULTS["k"]
    delta_factor: float = PAPER_DEFAULTS["delta_factor"]
    nu0: float = PAPER_DEFAULTS["nu0"]
    line_weight: bool = PAPER_DEFAULTS["line_weight"]
    welsch_input: str = PAPER_DEFAULTS["welsch_input"]
    max_hits: int | None = PAPER_DEFAULTS["max_hits"]
    reduction: str = PAPER_DEFAULTS["reduction"]
    radius_factor: float = PAPER_DEFAULTS["radius_factor"]
    distance_eps: float = PAPER_DEFAULTS["distance_eps"]
    cell_factor: float = PAPER_DEFAULTS["cell_factor"]
    nu: float | None = PAPER_DEFAULTS["nu"]
    detach_weights: bool = PAPER_DEFAULTS["detach_weights"]

    def __post_init__(self) -> None:
        choices = {
            "sampling": SAMPLERS,
            "intersection": tuple(INTERSECTIONS),
            "reduction": REDUCTIONS,
            "welsch_input": WELSCH_INPUTS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        positive = {
            "num_lines": self.num_lines,
            "k": self.k,
            "delta_factor": self.delta_factor,
            "nu0": self.nu0,
            "radius_factor": self.radius_factor,
            "cell_factor": self.cell_factor,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        if self.max_hits is not None and self.max_hits < 1:
            raise ValueError(f"max_hits must be >= 1 or None, got {self.max_hits}")
        if self.intersection == "pierce" and self.k != 2:
            raise ValueError(f"intersection 'pierce' intersects triangles and needs k=2, got k={self.k}")
        if self.nu is not None and not self.nu > 0:
            raise ValueError(f"nu must be > 0 or None, got {self.nu}")
        if self.distance_eps < 0:
            raise ValueError(f"distance_eps must be >= 0, got {self.distance_eps}")

    @classmethod
    def for_variant(cls, variant: str = "paper", **overrides: Any) -> LineMetricOptions:
        """Options of ``variant`` (``paper`` or ``authors``) with explicit ``overrides`` on top."""
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
        return cls(**{**VARIANTS[variant], **overrides})


@dataclass
class Intersections:
    """Intersections of ``L`` lines with one cloud.

    Attributes:
        offsets: ``(L+1,)`` int64 numpy; line ``l`` owns rows ``offsets[l]:offsets[l+1]``.
        points: tensor of shape ``(H, 3)`` giving the intersection points (differentiable
            w.r.t. the cloud's points).
        members: ``(H, k+1)`` int64 numpy indices of the points combined into each one.
        weights: ``(H, k+1)`` float64 numpy convex weights as computed by the kernel.
    """

    offsets: np.ndarray
    points: torch.Tensor
    members: np.ndarray
    weights: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """``(L,)`` number of intersections per line."""
        return np.diff(self.offsets)


@dataclass
class LineMetricResult:
    """Per-sample values ``(B,)`` and hit statistics (floats averaged over the batch)."""

    value: torch.Tensor
    stats: dict[str, float] = field(default_factory=dict)


def intersect_lines(
    points: torch.Tensor, origins: np.ndarray, dirs: np.ndarray, options: LineMetricOptions
) -> Intersections:
    """Intersections of lines with one cloud (step 1 of the module docstring).

    Args:
        points: tensor of shape ``(N, 3)``, ``N > k``.
        origins: ``(L, 3)`` float64 line points.
        dirs: ``(L, 3)`` float64 unit directions.
        options: metric options (``intersection``, ``k``, ``delta_factor``, ``distance_eps``).
    """
    k = options.k
    if points.shape[0] <= k:
        raise ValueError(f"the line-intersection metric needs more than k={k} points per cloud, got {points.shape[0]}")
    detached = points.detach()
    neighbors = knn(detached, detached, k, exclude_self=True)
    nbr_idx = neighbors.idx.cpu().numpy().astype(np.int64)
    nbr_dist = neighbors.dists.double().cpu().numpy()
    coords = detached.double().cpu().numpy()
    if options.intersection == "triplet":
        spacing = nbr_dist.sum(axis=1)
        for a in range(k):
            for b in range(a + 1, k):
                spacing += np.linalg.norm(coords[nbr_idx[:, a]] - coords[nbr_idx[:, b]], axis=1)
        radius = options.delta_factor * spacing / (k * (k + 1) / 2)
    else:
        radius = np.full(points.shape[0], options.delta_factor * nbr_dist.mean())
    mode = INTERSECTIONS[options.intersection]
    kernel_neighbors = (
        np.zeros((points.shape[0], 0), dtype=np.int64) if mode == line_kernels.MODE_CANDIDATES else nbr_idx
    )
    cell = line_kernels.grid_cell_size(coords, radius, options.cell_factor)
    offsets, anchors, weights = line_kernels.line_intersections(
        np.ascontiguousarray(origins),
        np.ascontiguousarray(dirs),
        coords,
        radius,
        np.ascontiguousarray(kernel_neighbors),
        mode,
        options.distance_eps,
        cell,
    )
    members = np.concatenate([anchors[:, None], kernel_neighbors[anchors]], axis=1)
    gathered = points[torch.from_numpy(members).to(points.device)]
    if options.detach_weights or mode in (line_kernels.MODE_CANDIDATES, line_kernels.MODE_PIERCE):
        w = torch.from_numpy(weights).to(device=points.device, dtype=points.dtype)
    else:
        line_of = torch.from_numpy(np.repeat(np.arange(len(origins)), np.diff(offsets))).to(points.device)
        o = torch.from_numpy(origins).to(points)[line_of].unsqueeze(1)
        u = torch.from_numpy(dirs).to(points)[line_of].unsqueeze(1)
        rel = gathered - o
        dist = (
            ((rel.square().sum(-1) - (rel * u).sum(-1).square()).clamp_min(0.0) + options.distance_eps)
            .clamp_min(1e-30)
            .sqrt()
        )
        w = dist / dist.sum(dim=1, keepdim=True)
    inter = (gathered * w.unsqueeze(-1)).sum(dim=1)
    return Intersections(offsets=offsets, points=inter, members=members, weights=weights)


@dataclass
class LineMatches:
    """Closest-point matches along the lines that meet both clouds (step 2).

    Attributes:
        src_index: ``(P,)`` int64 rows of the source intersections.
        tgt_index: ``(P,)`` int64 rows of the target intersections.
        line: ``(P,)`` int64 line of each match.
        is_row: ``(P,)`` bool, True for source->target matches (``sigma_l``), False for
            target->source ones (``rho_l``).
        line_weight: ``(P,)`` float64 ``w_l`` of each match's line (ones when disabled).
        group: ``(P,)`` int64 id of the line's ``(|S_l|, |T_l|)`` pair.
        lines_kept: number of lines that meet both clouds (within ``max_hits``).
    """

    src_index: np.ndarray
    tgt_index: np.ndarray
    line: np.ndarray
    is_row: np.ndarray
    line_weight: np.ndarray
    group: np.ndarray
    lines_kept: int


def match_intersections(src: Intersections, tgt: Intersections, options: LineMetricOptions) -> LineMatches:
    """Match the intersections of each line both ways (Eq. 3's ``sigma_l`` and ``rho_l``)."""
    ns, nt = src.counts, tgt.counts
    keep = (ns >= 1) & (nt >= 1)
    if options.max_hits is not None:
        keep &= (ns <= options.max_hits) & (nt <= options.max_hits)
    pair_offsets = np.concatenate([[0], np.cumsum(np.where(keep, ns + nt, 0))])
    s_idx, t_idx, line_of = line_kernels.match_along_lines(
        src.offsets,
        tgt.offsets,
        src.points.detach().double().cpu().numpy(),
        tgt.points.detach().double().cpu().numpy(),
        pair_offsets,
    )
    is_row = (np.arange(len(line_of)) - pair_offsets[line_of]) < ns[line_of]
    line_w = np.exp(-np.abs(ns - nt) / 2.0)[line_of] if options.line_weight else np.ones(len(line_of))
    group = ns[line_of] * (int(nt.max(initial=0)) + 1) + nt[line_of]
    return LineMatches(s_idx, t_idx, line_of, is_row, line_w, group, int(keep.sum()))


def welsch_two_c(dist_sq: torch.Tensor, options: LineMetricOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """The detached Welsch scale ``nu`` and the denominator ``2 nu^2`` (or ``2 c`` for squared
    input) so that ``psi = 1 - exp(-d^2 / two_c)``."""
    if options.nu is not None:
        scale = dist_sq.new_tensor(options.nu)
    elif options.welsch_input == "distance":
        scale = options.nu0 * dist_sq.detach().sqrt().median()
    else:
        scale = options.nu0 * dist_sq.detach().median()
    two_c = 2.0 * (scale.square() if options.welsch_input == "distance" else scale)
    return scale, two_c.clamp_min(torch.finfo(dist_sq.dtype).tiny)


def _hit_stats(src: Intersections, tgt: Intersections, matches: LineMatches) -> dict[str, float]:
    ns, nt = src.counts, tgt.counts
    return {
        "lines": float(len(ns)),
        "lines_hit_both": float(matches.lines_kept),
        "lines_hit_src": float((ns > 0).sum()),
        "lines_hit_tgt": float((nt > 0).sum()),
        "intersections_src": float(ns.sum()),
        "intersections_tgt": float(nt.sum()),
    }


def _pair_value(
    src: Intersections, tgt: Intersections, options: LineMetricOptions, anchor: torch.Tensor
) -> tuple[torch.Tensor, dict[str, float]]:
    """Steps 2-3 for one sample: the metric value (0-dim tensor) and its statistics."""
    matches = match_intersections(src, tgt, options)
    stats = _hit_stats(src, tgt, matches)
    if matches.lines_kept == 0:
        # No line meets both clouds: a defined zero with a zero gradient, still on the graph.
        return anchor.sum() * 0.0, {**stats, "nu": 0.0}
    device = src.points.device
    diff = (
        src.points[torch.from_numpy(matches.src_index).to(device)]
        - tgt.points[torch.from_numpy(matches.tgt_index).to(device)]
    )
    dist_sq = diff.square().sum(dim=1)
    scale, two_c = welsch_two_c(dist_sq, options)
    weighted = torch.from_numpy(matches.line_weight).to(dist_sq) * (1.0 - torch.exp(-dist_sq / two_c))
    stats["nu"] = float(scale)
    if options.reduction == "lines":
        return weighted.sum() / float(matches.lines_kept), stats
    # "groups": the authors' per-(|S_l|, |T_l|) averaging, rows (source->target) and columns apart.
    _, bucket = np.unique(matches.group * 2 + (~matches.is_row), return_inverse=True)
    bucket_t = torch.from_numpy(bucket.reshape(-1)).to(device)
    n_buckets = int(bucket.max()) + 1
    sums = torch.zeros(n_buckets, dtype=weighted.dtype, device=device).index_add(0, bucket_t, weighted)
    counts = torch.zeros(n_buckets, dtype=weighted.dtype, device=device).index_add(
        0, bucket_t, torch.ones_like(weighted)
    )
    n_groups = len(np.unique(matches.group))
    return (sums / counts).sum() / n_groups, stats


@dataclass
class Correspondences:
    """Weighted point pairs from the line intersections, for IRLS/Procrustes solvers.

    Attributes:
        src: ``(P, 3)`` source-side intersection points (detached).
        tgt: ``(P, 3)`` matched target-side intersection points.
        weights: ``(P,)`` ``w_l * exp(-d^2 / (2 nu^2))``, Welsch's IRLS weights.
        stats: hit statistics of the evaluation.
    """

    src: torch.Tensor
    tgt: torch.Tensor
    weights: torch.Tensor
    stats: dict[str, float]


def line_correspondences(
    src: torch.Tensor,
    tgt: torch.Tensor,
    *,
    options: LineMetricOptions | None = None,
    generator: torch.Generator | None = None,
) -> Correspondences:
    """Correspondences implied by the metric for one pair ``src (N, 3)``, ``tgt (M, 3)``.

    Replacing Welsch's function by its quadratic surrogate at the current pose gives the
    weighted least-squares problem of the supplementary's SVD solver: minimise
    ``sum w (R x + t - y)^2`` over these pairs.
    """
    options = options or LineMetricOptions()
    check_points(src, "src", batched=False, min_points=options.k + 1)
    check_points(tgt, "tgt", batched=False, min_points=options.k + 1)
    generator = generator or torch.Generator().manual_seed(int(torch.randint(0, 2**62, ()).item()))
    origins, dirs = sample_lines(
        src, tgt, options.num_lines, generator, sampling=options.sampling, radius_factor=options.radius_factor
    )
    src_inter = intersect_lines(src.detach(), origins, dirs, options)
    tgt_inter = intersect_lines(tgt.detach(), origins, dirs, options)
    matches = match_intersections(src_inter, tgt_inter, options)
    x = src_inter.points[torch.from_numpy(matches.src_index).to(src.device)]
    y = tgt_inter.points[torch.from_numpy(matches.tgt_index).to(src.device)]
    dist_sq = (x - y).square().sum(dim=1)
    stats = _hit_stats(src_inter, tgt_inter, matches)
    if matches.lines_kept == 0:
        return Correspondences(x, y, dist_sq, {**stats, "nu": 0.0})
    scale, two_c = welsch_two_c(dist_sq, options)
    weights = torch.from_numpy(matches.line_weight).to(dist_sq) * torch.exp(-dist_sq / two_c)
    return Correspondences(x, y, weights, {**stats, "nu": float(scale)})


def line_intersection_metric(
    src: torch.Tensor,
    tgt: torch.Tensor,
    src_lengths: torch.Tensor | None = None,
    tgt_lengths: torch.Tensor | None = None,
    *,
    options: LineMetricOptions | None = None,
    generator: torch.Generator | None = None,
    lines: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> LineMetricResult:
    """The line-intersection metric between batched clouds.

    Args:
        src: tensor of shape ``(B, N, 3)`` giving the (transformed) source points; gradients
            flow to it.
        tgt: tensor of shape ``(B, M, 3)`` giving the target points.
        src_lengths: optional ``(B,)`` number of valid source points (padded batches).
        tgt_lengths: optional ``(B,)`` number of valid target points.
        options: metric options; the paper's defaults when ``None``.
        generator: CPU ``torch.Generator`` for the lines (fresh randomness when ``None``).
        lines: optional explicit lines per sample ``[(origins (L, 3), dirs (L, 3)), ...]``
            (float64, unit directions), overriding the sampler.

    Returns:
        :class:`LineMetricResult` with ``value`` of shape ``(B,)`` (zero, with zero gradient,
        for a sample where no line meets both clouds) and batch-averaged hit statistics.

    Raises:
        ValueError: wrong shapes, NaN/Inf coordinates, or a cloud with ``k`` points or fewer.
    """
    options = options or LineMetricOptions()
    check_points(src, "src", batched=True, min_points=options.k + 1)
    check_points(tgt, "tgt", batched=True, min_points=options.k + 1)
    check_same_batch(src, tgt, "src", "tgt")
    if generator is None:
        generator = torch.Generator().manual_seed(int(torch.randint(0, 2**62, ()).item()))
    values, all_stats = [], []
    for b in range(src.shape[0]):
        src_b = src[b, : int(src_lengths[b])] if src_lengths is not None else src[b]
        tgt_b = tgt[b, : int(tgt_lengths[b])] if tgt_lengths is not None else tgt[b]
        if lines is not None:
            origins, dirs = lines[b]
        else:
            origins, dirs = sample_lines(
                src_b,
                tgt_b,
                options.num_lines,
                generator,
                sampling=options.sampling,
                radius_factor=options.radius_factor,
            )
        value, stats = _pair_value(
            intersect_lines(src_b, origins, dirs, options),
            intersect_lines(tgt_b, origins, dirs, options),
            options,
            src_b,
        )
        values.append(value)
        all_stats.append(stats)
    mean_stats = {key: float(np.mean([s[key] for s in all_stats])) for key in all_stats[0]}
    return LineMetricResult(value=torch.stack(values), stats=mean_stats)


@LOSSES.register("line_intersection", needs_gt=False)
class LineIntersectionLoss(AlignmentLoss):
    """The line-intersection metric as a loss on each iteration's transformed source.

    Args:
        variant: ``paper`` (default) or ``authors`` (see the module docstring).
        seed: seeds the line generator (reproducible runs); fresh randomness when ``None``.
        discount, last_k, normalize_iterations: iteration weighting (:class:`AlignmentLoss`).
        **options: any :class:`LineMetricOptions` field, overriding the variant's default.
    """

    def __init__(
        self,
        variant: str = "paper",
        seed: int | None = None,
        discount: float = 0.5,
        last_k: int | None = None,
        normalize_iterations: bool = False,
        **options: Any,
    ) -> None:
        super().__init__(discount=discount, last_k=last_k, normalize_iterations=normalize_iterations)
        known = set(LineMetricOptions.__dataclass_fields__)
        unknown = set(options) - known
        if unknown:
            raise TypeError(f"unknown line_intersection option(s) {sorted(unknown)}; known: {sorted(known)}")
        self.options = LineMetricOptions.for_variant(variant, **options)
        self.generator = torch.Generator()
        self.generator.manual_seed(seed if seed is not None else int(torch.randint(0, 2**62, ()).item()))

    def metric(self, src, tgt, src_lengths=None, tgt_lengths=None):
        result = line_intersection_metric(
            src, tgt, src_lengths, tgt_lengths, options=self.options, generator=self.generator
        )
        return result.value, result.stats
