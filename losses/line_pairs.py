"""Steps 1 and 2 of the line-intersection metric: the lines of a batch, the intersections
of every line with both clouds, and their closest-point matches along each line.

Only indices and detached weights are chosen here; the intersection points are gathered with
torch so that they stay on the graph. The ``numba`` backend runs the compiled kernels
(:mod:`linereg.losses.line_neighbors`, :mod:`linereg.losses.line_kernels`,
:mod:`linereg.losses.line_welsch_kernels`) on the CPU; the ``torch`` backend runs their twins
(:mod:`linereg.losses.line_torch`) on the clouds' device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import torch

from linereg.knn import knn_points

from . import line_grid, line_kernels, line_torch, line_welsch_kernels
from .line_neighbors import cloud_neighborhoods
from .line_options import INTERSECTIONS, LineMetricOptions
from .line_torch import Hits
from .lines import sample_line_batch


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
    """Per side, ``valid (B, N)``, ``neighbors (B, N, k)`` (sample-local; ``-1`` in rows of
    padding) and their Euclidean ``distances (B, N, k)`` of ``clouds[side] (B, N, 3)`` with
    ``lengths[side] (B,)`` valid points, from :func:`linereg.knn.knn_points` on the clouds'
    device (the torch backend; the numba backend's twin is
    :func:`linereg.losses.line_neighbors.cloud_neighborhoods`)."""
    setups = []
    for cloud, side_lengths in zip(clouds, lengths, strict=True):
        valid = torch.arange(cloud.shape[1], device=cloud.device)[None] < side_lengths.to(cloud.device)[:, None]
        found = knn_points(cloud, cloud, k, side_lengths, side_lengths, return_nn=True, exclude_self=True)
        setups.append((valid, found.idx, (cloud[:, :, None] - found.knn).norm(dim=-1)))
    return setups


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


def stacked_points(clouds: list[torch.Tensor], lengths: np.ndarray) -> np.ndarray:
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


def numba_plan(src, tgt, src_lengths, tgt_lengths, lines: LineBatch, options) -> KernelPlan:
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
    points = stacked_points([src, tgt], point_lengths)
    neighbors, _, radius = cloud_neighborhoods(
        points, point_offsets, options.k, mode == line_kernels.MODE_TRIPLET, options.delta_factor
    )
    if mode == line_kernels.MODE_CANDIDATES:
        neighbors = np.empty((len(points), 0), dtype=np.int64)
    cells = line_grid.sample_cell_sizes(points, point_offsets, radius, batch, options.cell_factor)
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


def resolve_lines(src, tgt, src_lengths, tgt_lengths, options, generator, lines) -> LineBatch:
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


def torch_setups(src, tgt, src_lengths, tgt_lengths, options):
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


def line_pairs(src, tgt, src_lengths, tgt_lengths, options, generator, lines) -> LinePairs:
    """Steps 1 and 2 for a batch (inputs already validated, float32 or wider)."""
    device = src.device
    backend = options.resolved_backend(device)
    batch = src.shape[0]
    line_batch = resolve_lines(src, tgt, src_lengths, tgt_lengths, options, generator, lines)
    n_lines = line_batch.origins.shape[1]
    mode = INTERSECTIONS[options.intersection]
    if backend == "numba":
        plan = numba_plan(src, tgt, src_lengths, tgt_lengths, line_batch, options)
        hits = [
            Hits(h.line.to(device), h.members.to(device), h.weights.to(device))
            for h in _plan_hits(plan, (src.shape[1], tgt.shape[1]), mode)
        ]
    else:
        clouds, valids, radii, neighbors = torch_setups(src, tgt, src_lengths, tgt_lengths, options)
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
        s_idx, t_idx, line_of = line_welsch_kernels.match_along_lines(
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
