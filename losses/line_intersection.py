"""The line-intersection metric of Deng et al., "A Robust Loss for Point Cloud Registration"
(ICCV 2021), §3.2 — sparse, batched, differentiable w.r.t. the source points.

For ``L`` random lines ``l`` (see :mod:`linereg.losses.lines`):

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

Steps 1 and 2 only choose indices and detached weights, so memory is linear in ``N + L``. Two
backends choose them (``backend`` option): ``numba`` (:mod:`linereg.losses.line_kernels`, a compiled grid
walk that only examines point-line pairs that can interact, on the CPU, threads across samples
and lines) and ``torch`` (:mod:`linereg.losses.line_torch`, an all-pairs test in chunks on the tensors'
device, batched, no per-sample host round trip). ``auto`` (default) takes ``torch`` for tensors
on an accelerator and ``numba`` on the CPU. With ``numba`` and the settings of
:func:`fused_path` (the paper's and ``linereg``'s among them), the kernels also match the
intersections and compute the value with its gradient (:class:`FusedLineValue`), and the
backward pass only scales that gradient; otherwise torch gathers the points and autograd
differentiates steps 2-3 (a sparse scatter). For the same
lines both give the same value and gradient up to float rounding. Half-precision inputs are
evaluated in float32.

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
``backend``       ``auto``                                    ``numba``, ``torch``
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
import numbers
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import numpy as np
import torch

from linereg.checks import check_lengths, check_points, check_same_batch

from . import line_kernels, line_torch
from .base import LOSSES, AlignmentLoss
from .chamfer import check_nu0
from .line_torch import Hits
from .lines import SAMPLERS, sample_line_batch

INTERSECTIONS = {
    "candidates": line_kernels.MODE_CANDIDATES,
    "convex": line_kernels.MODE_CONVEX,
    "triplet": line_kernels.MODE_TRIPLET,
    "pierce": line_kernels.MODE_PIERCE,
}
REDUCTIONS = ("lines", "groups")
WELSCH_INPUTS = ("distance", "squared")
BACKENDS = ("auto", "numba", "torch")
STAT_KEYS = (
    "lines",
    "lines_hit_both",
    "lines_hit_src",
    "lines_hit_tgt",
    "intersections_src",
    "intersections_tgt",
    "nu",
)

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
    "backend": "auto",
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
    backend: str = PAPER_DEFAULTS["backend"]

    def __post_init__(self) -> None:
        choices = {
            "sampling": SAMPLERS,
            "intersection": tuple(INTERSECTIONS),
            "reduction": REDUCTIONS,
            "welsch_input": WELSCH_INPUTS,
            "backend": BACKENDS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        for name in ("num_lines", "k"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        positive = {
            "delta_factor": self.delta_factor,
            "nu0": self.nu0,
            "radius_factor": self.radius_factor,
            "cell_factor": self.cell_factor,
        }
        for name, value in positive.items():
            if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if self.max_hits is not None and self.max_hits < 1:
            raise ValueError(f"max_hits must be >= 1 or None, got {self.max_hits}")
        if self.intersection == "pierce" and self.k != 2:
            raise ValueError(f"intersection 'pierce' intersects triangles and needs k=2, got k={self.k}")
        if self.nu is not None and not (math.isfinite(self.nu) and self.nu > 0):
            raise ValueError(f"nu must be a finite number > 0 or None, got {self.nu}")
        if not (math.isfinite(self.distance_eps) and self.distance_eps >= 0):
            raise ValueError(f"distance_eps must be a finite number >= 0, got {self.distance_eps}")

    @classmethod
    def for_variant(cls, variant: str = "paper", **overrides: Any) -> LineMetricOptions:
        """Options of ``variant`` (``paper``, ``authors`` or ``linereg``) with ``overrides`` on top."""
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
        return cls(**{**VARIANTS[variant], **overrides})

    def resolved_backend(self, device: torch.device) -> str:
        """``numba`` or ``torch``: ``auto`` takes ``torch`` for tensors that are not on the CPU."""
        if self.backend != "auto":
            return self.backend
        return "numba" if device.type == "cpu" else "torch"


@dataclass
class LineMetricResult:
    """Per-sample values ``(B,)`` and hit statistics (floats averaged over the batch)."""

    value: torch.Tensor
    stats: dict[str, float] = field(default_factory=dict)


@dataclass
class LineBatch:
    """The lines of a batch: ``origins``, ``dirs`` ``(B, L, 3)`` float64 (unit directions) on the
    clouds' device; sample ``b`` uses its first ``counts[b]`` lines (``(B,)`` int64 numpy)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    counts: np.ndarray

    def valid(self) -> torch.Tensor:
        """``(B, L)`` bool, False for padding lines."""
        n_lines = self.origins.shape[1]
        counts = torch.from_numpy(self.counts).to(self.origins.device)
        return torch.arange(n_lines, device=self.origins.device)[None] < counts[:, None]


def _explicit_lines(lines: Any, batch: int, device: torch.device) -> LineBatch:
    """Validate ``lines=[(origins (L_b, 3), dirs (L_b, 3)), ...]`` and pad them into a batch;
    directions are normalised (a line does not depend on their length)."""
    if not isinstance(lines, list | tuple) or len(lines) != batch:
        got = f"{len(lines)} entries" if isinstance(lines, list | tuple) else type(lines).__name__
        raise ValueError(f"lines must be a list of {batch} (origins, dirs) pairs, one per sample, got {got}")
    origins, dirs = [], []
    for b, entry in enumerate(lines):
        if not isinstance(entry, list | tuple) or len(entry) != 2:
            raise ValueError(f"lines[{b}] must be a pair (origins, dirs)")
        o, d = (torch.as_tensor(x).detach().to("cpu", torch.float64) for x in entry)
        if o.ndim != 2 or o.shape[1] != 3 or o.shape != d.shape or len(o) == 0:
            raise ValueError(
                f"lines[{b}] must hold origins and dirs of one shape (L, 3) with L >= 1, "
                f"got {tuple(o.shape)} and {tuple(d.shape)}"
            )
        if not (torch.isfinite(o).all() and torch.isfinite(d).all()):
            raise ValueError(f"lines[{b}] contains NaN or Inf")
        norm = d.norm(dim=1, keepdim=True)
        if not (norm > 0).all():
            raise ValueError(f"lines[{b}] has a zero direction (row {int((norm[:, 0] <= 0).nonzero()[0])})")
        origins.append(o)
        dirs.append(d / norm)
    counts = np.array([len(o) for o in origins], dtype=np.int64)
    width = int(counts.max())
    padded_o = torch.stack([torch.cat([o, o[:1].expand(width - len(o), 3)]) for o in origins])
    padded_d = torch.stack([torch.cat([d, d[:1].expand(width - len(d), 3)]) for d in dirs])
    return LineBatch(padded_o.to(device), padded_d.to(device), counts)


def _cylinder_radius(
    points: torch.Tensor, valid: torch.Tensor, neighbors: torch.Tensor, distances: torch.Tensor, options
) -> torch.Tensor:
    """``(B, N)`` float64 radius ``delta`` of every point: ``delta_factor * d_nei`` per cloud
    (``d_nei`` the mean distance to the k nearest neighbours over the valid points), or for
    ``triplet`` the locally adaptive ``delta_factor * mean pairwise spacing`` of each point and
    its neighbours."""
    k = options.k
    if options.intersection == "triplet":
        rows = torch.arange(points.shape[0], device=points.device)[:, None, None]
        near = points[rows, neighbors]
        spacing = distances.sum(dim=2)
        for a in range(k):
            for b in range(a + 1, k):
                spacing = spacing + (near[:, :, a] - near[:, :, b]).norm(dim=-1)
        return options.delta_factor * spacing / (k * (k + 1) / 2)
    mean = (distances.mean(dim=2) * valid).sum(dim=1) / valid.sum(dim=1)
    return (options.delta_factor * mean)[:, None].expand(valid.shape)


def _torch_neighbors(
    clouds: list[torch.Tensor], lengths: list[torch.Tensor], k: int
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per side, ``valid (B, N)``, ``neighbors (B, N, k)`` (sample-local) and their
    ``distances (B, N, k)`` of ``clouds[side] (B, N, 3)`` with ``lengths[side] (B,)`` valid points,
    by a masked brute-force search on the clouds' device (the torch backend; the numba backend's
    twin is :func:`linereg.losses.line_kernels.cloud_neighborhoods`)."""
    valids = [
        torch.arange(cloud.shape[1], device=cloud.device)[None] < side_lengths.to(cloud.device)[:, None]
        for cloud, side_lengths in zip(clouds, lengths, strict=True)
    ]
    return [(valid, *line_torch.masked_knn(cloud, valid, k)) for cloud, valid in zip(clouds, valids, strict=True)]


@dataclass
class KernelPlan:
    """The index decisions of the numba kernel for a batch: the output of
    :func:`linereg.losses.line_kernels.line_intersections` and its inputs, per cloud (clouds
    ordered ``src_0 .. src_{B-1}, tgt_0 .. tgt_{B-1}``, cloud ``c`` holding the first
    ``point_lengths[c]`` points of its sample and the lines ``line_offsets[c]:line_offsets[c+1]``
    of ``offsets``; sample ``b`` on both sides uses the same lines)."""

    offsets: np.ndarray
    anchors: np.ndarray
    weights: np.ndarray
    line_offsets: np.ndarray
    line_ids: np.ndarray
    point_offsets: np.ndarray
    neighbors: np.ndarray

    @property
    def point_lengths(self) -> np.ndarray:
        return np.diff(self.point_offsets)


def _stacked_points(clouds: list[torch.Tensor], lengths: np.ndarray) -> np.ndarray:
    """``(sum lengths, 3)`` float64 numpy: the valid rows of every sample of ``clouds``
    (``[src (B, N, 3), tgt (B, M, 3)]``, ``lengths (2 B,)``), in the plan's cloud order."""
    batch = clouds[0].shape[0]
    rows = []
    for side, cloud in enumerate(clouds):
        side_lengths = lengths[side * batch : (side + 1) * batch]
        if (side_lengths == cloud.shape[1]).all():
            rows.append(cloud.reshape(-1, 3))
        else:
            rows.extend(cloud[b, : side_lengths[b]] for b in range(batch))
    return torch.cat(rows).detach().to("cpu", torch.float64).numpy()


def _numba_plan(src, tgt, src_lengths, tgt_lengths, lines: LineBatch, options) -> KernelPlan:
    """Intersections of the lines with every cloud of both sides in two kernel calls: the
    neighbours and radii of all points, then the intersections (each sample's lines walk one
    grid holding both of its clouds).

    Args:
        src, tgt: ``(B, N, 3)``, ``(B, M, 3)`` clouds (copied to the CPU in float64);
            src_lengths, tgt_lengths: ``(B,)`` int64 CPU valid points.
    """
    batch, n_lines = lines.origins.shape[:2]
    mode = INTERSECTIONS[options.intersection]
    point_lengths = torch.cat([src_lengths, tgt_lengths]).numpy()
    point_offsets = np.concatenate([[0], np.cumsum(point_lengths)])
    points = _stacked_points([src, tgt], point_lengths)
    neighbors, _, radius = line_kernels.cloud_neighborhoods(
        points, point_offsets, options.k, mode == line_kernels.MODE_TRIPLET, options.delta_factor
    )
    if mode == line_kernels.MODE_CANDIDATES:
        neighbors = np.empty((len(points), 0), dtype=np.int64)
    cells = line_kernels.sample_cell_sizes(points, point_offsets, radius, batch, options.cell_factor)
    counts = lines.counts
    origins, dirs = lines.origins.cpu().numpy(), lines.dirs.cpu().numpy()
    if (counts == n_lines).all():
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        line_ids = np.arange(batch * n_lines)
    else:
        origins = np.concatenate([origins[b, : counts[b]] for b in range(batch)])
        dirs = np.concatenate([dirs[b, : counts[b]] for b in range(batch)])
        line_ids = np.concatenate([b * n_lines + np.arange(counts[b]) for b in range(batch)])
    sample_line_offsets = np.concatenate([[0], np.cumsum(counts)])
    chunk = int(np.clip(sample_line_offsets[-1] // (4 * numba.get_num_threads()), 64, 1024))
    offsets, anchors, weights = line_kernels.line_intersections(
        origins,
        dirs,
        sample_line_offsets,
        points,
        point_offsets,
        radius,
        neighbors,
        mode,
        options.distance_eps,
        cells,
        chunk,
    )
    return KernelPlan(
        offsets,
        anchors,
        weights,
        np.concatenate([[0], np.cumsum(np.concatenate([counts, counts]))]),
        np.concatenate([line_ids, line_ids]),
        point_offsets,
        neighbors,
    )


def _plan_hits(plan: KernelPlan, sizes: tuple[int, int], mode: int) -> list[Hits]:
    """The plan as one :class:`Hits` per side (rows of the flattened padded clouds, whose padded
    sizes are ``sizes``)."""
    batch = (len(plan.point_offsets) - 1) // 2
    per_line = np.diff(plan.offsets)
    hit_line = np.repeat(plan.line_ids, per_line)
    cloud_of_line = np.repeat(np.arange(2 * batch), np.diff(plan.line_offsets))
    hit_cloud = np.repeat(cloud_of_line, per_line)
    line_offsets, offsets = plan.line_offsets, plan.offsets
    result = []
    for side, n in enumerate(sizes):
        rows = slice(offsets[line_offsets[side * batch]], offsets[line_offsets[(side + 1) * batch]])
        cloud = hit_cloud[rows]
        anchor = plan.anchors[rows]
        members = anchor[:, None]
        if mode != line_kernels.MODE_CANDIDATES:
            members = np.concatenate([members, plan.neighbors[plan.point_offsets[cloud] + anchor]], axis=1)
        sample = cloud - side * batch
        result.append(
            Hits(
                torch.from_numpy(hit_line[rows]),
                torch.from_numpy(members + (sample * n)[:, None]),
                torch.from_numpy(plan.weights[rows]),
            )
        )
    return result


def _intersection_points(cloud: torch.Tensor, hits: Hits, lines: LineBatch, options: LineMetricOptions) -> torch.Tensor:
    """``(H, 3)`` intersection points, differentiable w.r.t. ``cloud (B, N, 3)``."""
    gathered = cloud.reshape(-1, 3)[hits.members]
    if options.detach_weights or options.intersection in ("candidates", "pierce"):
        weights = hits.weights.to(cloud.dtype)
    else:
        o = lines.origins.reshape(-1, 3).to(cloud.dtype)[hits.line].unsqueeze(1)
        u = lines.dirs.reshape(-1, 3).to(cloud.dtype)[hits.line].unsqueeze(1)
        rel = gathered - o
        dist = (
            ((rel.square().sum(-1) - (rel * u).sum(-1).square()).clamp_min(0.0) + options.distance_eps)
            .clamp_min(torch.finfo(cloud.dtype).tiny)
            .sqrt()
        )
        weights = dist / dist.sum(dim=1, keepdim=True)
    return (gathered * weights.unsqueeze(-1)).sum(dim=1)


@dataclass
class LinePairs:
    """Everything the value needs: intersections and their matches along the lines.

    Attributes:
        src_points, tgt_points: ``(Hs, 3)``, ``(Ht, 3)`` intersection points (on the graph).
        src_index, tgt_index: ``(P,)`` int64 matched rows; ``line (P,)`` global line id;
            ``is_row (P,)`` True for source->target matches (``sigma_l``).
        src_count, tgt_count: ``(B * L,)`` int64 intersections per line.
        keep: ``(B * L,)`` bool, lines that meet both clouds (within ``max_hits``).
        lines: the lines.
    """

    src_points: torch.Tensor
    tgt_points: torch.Tensor
    src_index: torch.Tensor
    tgt_index: torch.Tensor
    line: torch.Tensor
    is_row: torch.Tensor
    src_count: torch.Tensor
    tgt_count: torch.Tensor
    keep: torch.Tensor
    lines: LineBatch


def _line_batch(src, tgt, src_lengths, tgt_lengths, options, generator, lines) -> LineBatch:
    """The explicit ``lines`` or the sampler's, on the clouds' device."""
    device = src.device
    if lines is not None:
        return _explicit_lines(lines, src.shape[0], device)
    origins, dirs, counts = sample_line_batch(
        src,
        tgt,
        src_lengths.to(device),
        tgt_lengths.to(device),
        options.num_lines,
        generator,
        sampling=options.sampling,
        radius_factor=options.radius_factor,
    )
    return LineBatch(origins, dirs, counts)


def _torch_setups(src, tgt, src_lengths, tgt_lengths, options):
    """Per side (source, target), on the clouds' device for the torch backend: detached float64
    points, ``valid`` masks, cylinder radii and neighbours."""
    clouds = [cloud.detach().double() for cloud in (src, tgt)]
    setups = _torch_neighbors(clouds, [src_lengths, tgt_lengths], options.k)
    valids = [valid for valid, _, _ in setups]
    neighbors = [nbr for _, nbr, _ in setups]
    radii = [
        _cylinder_radius(cloud, valid, nbr, dist, options)
        for cloud, (valid, nbr, dist) in zip(clouds, setups, strict=True)
    ]
    return clouds, valids, radii, neighbors


def _line_pairs(src, tgt, src_lengths, tgt_lengths, options, generator, lines) -> LinePairs:
    """Steps 1 and 2 for a batch (inputs already validated, float32 or wider)."""
    device = src.device
    backend = options.resolved_backend(device)
    batch = src.shape[0]
    line_batch = _line_batch(src, tgt, src_lengths, tgt_lengths, options, generator, lines)
    n_lines = line_batch.origins.shape[1]
    mode = INTERSECTIONS[options.intersection]
    if backend == "numba":
        plan = _numba_plan(src, tgt, src_lengths, tgt_lengths, line_batch, options)
        hits = [
            Hits(h.line.to(device), h.members.to(device), h.weights.to(device))
            for h in _plan_hits(plan, (src.shape[1], tgt.shape[1]), mode)
        ]
    else:
        clouds, valids, radii, neighbors = _torch_setups(src, tgt, src_lengths, tgt_lengths, options)
        line_valid, eps2 = line_batch.valid(), options.distance_eps
        hits = [
            line_torch.torch_hits(c, v, r, n, line_batch.origins, line_batch.dirs, line_valid, mode, eps2)
            for c, v, r, n in zip(clouds, valids, radii, neighbors, strict=True)
        ]
    src_hits, tgt_hits = hits
    src_points = _intersection_points(src, src_hits, line_batch, options)
    tgt_points = _intersection_points(tgt, tgt_hits, line_batch, options)
    n_total = batch * n_lines
    ns = torch.bincount(src_hits.line, minlength=n_total)
    nt = torch.bincount(tgt_hits.line, minlength=n_total)
    keep = (ns >= 1) & (nt >= 1)
    if options.max_hits is not None:
        keep &= (ns <= options.max_hits) & (nt <= options.max_hits)
    if backend == "numba":
        ns_np, nt_np, keep_np = ns.cpu().numpy(), nt.cpu().numpy(), keep.cpu().numpy()
        pair_offsets = np.concatenate([[0], np.cumsum(np.where(keep_np, ns_np + nt_np, 0))])
        s_idx, t_idx, line_of = line_kernels.match_along_lines(
            np.concatenate([[0], np.cumsum(ns_np)]),
            np.concatenate([[0], np.cumsum(nt_np)]),
            src_points.detach().double().cpu().numpy(),
            tgt_points.detach().double().cpu().numpy(),
            pair_offsets,
        )
        is_row = (np.arange(len(line_of)) - pair_offsets[line_of]) < ns_np[line_of]
        src_index, tgt_index, line, is_row_t = (torch.from_numpy(x).to(device) for x in (s_idx, t_idx, line_of, is_row))
    else:
        src_index, tgt_index, line, is_row_t = line_torch.match_along_lines(
            src_hits.line, tgt_hits.line, src_points.detach().double(), tgt_points.detach().double(), ns, nt, keep
        )
    return LinePairs(src_points, tgt_points, src_index, tgt_index, line, is_row_t, ns, nt, keep, line_batch)


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


def _welsch_terms(
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


def _values(pairs: LinePairs, options: LineMetricOptions, anchor: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 3: ``(B,)`` values and ``(B, 7)`` statistics (:data:`STAT_KEYS`)."""
    batch, n_lines = pairs.lines.origins.shape[:2]
    line_w, dist_sq, two_c, scale = _welsch_terms(pairs, options)
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
    per-line reduction; other settings take the torch formula of :func:`_values`."""
    constant_weights = options.detach_weights or options.intersection in ("candidates", "pierce")
    return options.resolved_backend(device) == "numba" and constant_weights and options.reduction == "lines"


class FusedLineValue(torch.autograd.Function):
    """Step 3 for a fixed :class:`KernelPlan`: ``(B,)`` values, ``(B,)`` scales ``nu`` and
    ``(B, 5)`` hit counts (see :func:`linereg.losses.line_kernels.welsch_lines`) from ``src (B, N, 3)``
    and ``tgt (B, M, 3)``; the kernel writes the gradient w.r.t. the points during the forward
    pass, and the backward pass only scales it by the incoming ``(B,)`` gradient."""

    @staticmethod
    def forward(ctx, src, tgt, plan: KernelPlan, options: LineMetricOptions):
        batch = src.shape[0]
        points = _stacked_points([src, tgt], plan.point_lengths)
        value, grad, scale, counts = line_kernels.welsch_lines(
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


def _fused_values(src, tgt, src_lengths, tgt_lengths, options, generator, lines):
    """Steps 1-3 on the numba path (:func:`fused_path`): ``(B,)`` values and ``(B, 7)`` statistics."""
    line_batch = _line_batch(src, tgt, src_lengths, tgt_lengths, options, generator, lines)
    plan = _numba_plan(src, tgt, src_lengths, tgt_lengths, line_batch, options)
    value, scale, counts = FusedLineValue.apply(src, tgt, plan, options)
    stats = torch.cat([torch.from_numpy(line_batch.counts)[:, None], counts], dim=1).double()
    return value, torch.cat([stats, scale[:, None]], dim=1)


def _checked_inputs(src, tgt, src_lengths, tgt_lengths, options):
    """Validate the batch; return both clouds in float32 or wider and the lengths (CPU int64)."""
    check_points(src, "src", batched=True, min_points=options.k + 1)
    check_points(tgt, "tgt", batched=True, min_points=options.k + 1)
    check_same_batch(src, tgt, "src", "tgt")
    if src.device != tgt.device:
        raise ValueError(f"src and tgt must be on the same device, got {src.device} and {tgt.device}")
    batch = src.shape[0]
    need = options.k + 1
    src_lengths = check_lengths(src_lengths, "src_lengths", batch, src.shape[1], min_length=need)
    tgt_lengths = check_lengths(tgt_lengths, "tgt_lengths", batch, tgt.shape[1], min_length=need)
    if src_lengths is None:
        src_lengths = torch.full((batch,), src.shape[1], dtype=torch.int64)
    if tgt_lengths is None:
        tgt_lengths = torch.full((batch,), tgt.shape[1], dtype=torch.int64)
    work = torch.promote_types(torch.promote_types(src.dtype, tgt.dtype), torch.float32)
    return src.to(work), tgt.to(work), src_lengths, tgt_lengths


def _fresh_generator() -> torch.Generator:
    return torch.Generator().manual_seed(int(torch.randint(0, 2**62, ()).item()))


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
        src_lengths: optional ``(B,)`` integer number of valid source points (padded batches),
            each in ``[k + 1, N]``.
        tgt_lengths: optional ``(B,)`` integer number of valid target points, in ``[k + 1, M]``.
        options: metric options; the paper's defaults when ``None``.
        generator: CPU ``torch.Generator`` for the lines (fresh randomness when ``None``).
        lines: optional explicit lines per sample ``[(origins (L_b, 3), dirs (L_b, 3)), ...]``
            (arrays or tensors; non-zero directions, normalised here), overriding the sampler.

    Returns:
        :class:`LineMetricResult` with ``value`` of shape ``(B,)`` in the dtype of ``src``
        (zero, with zero gradient, for a sample where no line meets both clouds) and
        batch-averaged hit statistics.

    Raises:
        TypeError: non-float clouds or non-integer lengths.
        ValueError: wrong shapes, NaN/Inf coordinates, a cloud with ``k`` points or fewer, a
            length outside its range, or malformed ``lines``.
    """
    options = options or LineMetricOptions()
    work_src, work_tgt, src_lengths, tgt_lengths = _checked_inputs(src, tgt, src_lengths, tgt_lengths, options)
    generator = generator or _fresh_generator()
    if fused_path(options, work_src.device):
        value, stats = _fused_values(work_src, work_tgt, src_lengths, tgt_lengths, options, generator, lines)
    else:
        pairs = _line_pairs(work_src, work_tgt, src_lengths, tgt_lengths, options, generator, lines)
        value, stats = _values(pairs, options, work_src)
    mean_stats = dict(zip(STAT_KEYS, stats.mean(dim=0).tolist(), strict=True))
    return LineMetricResult(value=value.to(src.dtype), stats=mean_stats)


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
    work_src, work_tgt, src_lengths, tgt_lengths = _checked_inputs(
        src.detach()[None], tgt.detach()[None], None, None, options
    )
    pairs = _line_pairs(work_src, work_tgt, src_lengths, tgt_lengths, options, generator or _fresh_generator(), None)
    _, stats = _values(pairs, options, work_src)
    line_w, dist_sq, two_c, _ = _welsch_terms(pairs, options)
    x = pairs.src_points[pairs.src_index]
    y = pairs.tgt_points[pairs.tgt_index]
    weights = line_w * torch.exp(-dist_sq / two_c)
    return Correspondences(
        x.to(src.dtype), y.to(src.dtype), weights.to(src.dtype), dict(zip(STAT_KEYS, stats[0].tolist(), strict=True))
    )


@LOSSES.register("line_intersection", needs_gt=False)
class LineIntersectionLoss(AlignmentLoss):
    """The line-intersection metric as a loss on each iteration's transformed source.

    Args:
        variant: ``paper`` (default), ``authors`` or ``linereg`` (see the module docstring).
        seed: seeds the line generator (reproducible runs); fresh randomness when ``None``.
        discount, last_k, normalize_iterations: iteration weighting (:class:`AlignmentLoss`).
        nu0_final: anneal the Welsch scale factor during training, geometrically from ``nu0``
            at the first epoch to ``nu0_final`` at the last (:meth:`set_progress`; the training
            loop calls it before each epoch); ``None`` keeps ``nu0`` throughout.
        **options: any :class:`LineMetricOptions` field, overriding the variant's default.
    """

    def __init__(
        self,
        variant: str = "paper",
        seed: int | None = None,
        discount: float = 0.5,
        last_k: int | None = None,
        normalize_iterations: bool = False,
        nu0_final: float | None = None,
        **options: Any,
    ) -> None:
        super().__init__(discount=discount, last_k=last_k, normalize_iterations=normalize_iterations)
        known = set(LineMetricOptions.__dataclass_fields__)
        unknown = set(options) - known
        if unknown:
            raise TypeError(f"unknown line_intersection option(s) {sorted(unknown)}; known: {sorted(known)}")
        self.options = LineMetricOptions.for_variant(variant, **options)
        if nu0_final is not None:
            if self.options.nu is not None:
                raise ValueError("nu0_final anneals nu0, which a fixed absolute scale nu overrides: set one of them")
            check_nu0(nu0_final, "nu0_final")
            nu0_final = float(nu0_final)
        self.nu0_start = self.options.nu0
        self.nu0_final = nu0_final
        self.generator = torch.Generator()
        self.generator.manual_seed(seed if seed is not None else int(torch.randint(0, 2**62, ()).item()))

    def set_progress(self, fraction: float) -> dict[str, float]:
        """Set ``nu0 = nu0_start * (nu0_final / nu0_start) ** fraction``; ``{"nu0": value}``, or ``{}`` unscheduled."""
        if self.nu0_final is None:
            return {}
        self.options = replace(self.options, nu0=self.nu0_start * (self.nu0_final / self.nu0_start) ** fraction)
        return {"nu0": self.options.nu0}

    def metric(self, src, tgt, src_lengths=None, tgt_lengths=None):
        result = line_intersection_metric(
            src, tgt, src_lengths, tgt_lengths, options=self.options, generator=self.generator
        )
        return result.value, result.stats
