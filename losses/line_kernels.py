"""Compiled (numba) index kernels of the line-intersection metric.

The kernels decide *which* points form each intersection and *which* intersections are matched
(indices and detached convex weights). :func:`welsch_lines` then computes the value of the
paper's per-line reduction and, since the weights are constants, its gradient w.r.t. every point
in closed form; the loss wraps it in a ``torch.autograd.Function``. For the other settings the
loss gathers the points with torch and autograd differentiates the value. The k nearest
neighbours of the points come from :func:`nearest_neighbors` (a uniform grid, searched ring by
ring).

Candidate search, without ever testing all point-line pairs:

* every point ``p`` with radius ``r_p`` is inserted into each cell of a uniform grid that its
  ball ``B(p, r_p)`` overlaps (a "dilated" grid, built once per call in ``O(N)``);
* each line walks the cells it crosses (3D-DDA, Amanatides & Woo 1987) and tests the points
  stored there. If ``dist(p, line) < r_p``, the foot of the perpendicular ``q`` lies in
  ``B(p, r_p)``, so the cell that the walk visits at ``q``'s line parameter holds a copy of
  ``p``. A point is therefore accepted only in the cell whose parameter interval contains its
  own parameter ``t_p``, which finds every candidate exactly once.

Work is ``O(N + L * (cells crossed + points met))``; memory ``O(N + L + hits)``. Each line is
scanned in two phases: a branch-free pass over the points of the cells it crosses collects the
candidates (a data-dependent branch per tested point costs more than the test itself), then the
neighbour test and the weights run on those few.

Threads: :func:`line_intersections` takes all clouds of a batch (sources and targets) at once
and runs work items of a few hundred lines in parallel (``numba.prange``; the number of threads
is numba's, ``NUMBA_NUM_THREADS`` or ``numba.set_num_threads``). Results do not depend on it. On
a machine shared with other processes, OpenMP threads that spin while they wait (the default of
the GNU runtime, used by torch too) multiply the time of every parallel region: run with
``OMP_WAIT_POLICY=PASSIVE`` set before torch is imported, or with one thread
(``scripts/bench_loss.py --batch 8`` measures both).
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np

if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # Try OpenMP first: numba's default tries TBB first and warns when a library loaded earlier
    # (Open3D ships one) is too old for it.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

MODE_CANDIDATES = 0  # Insec1: every candidate point is an intersection
MODE_CONVEX = 1  # paper Eq. (7): candidates whose k nearest neighbours are candidates too
MODE_TRIPLET = 2  # authors' code: the point and its k neighbours all within the anchor's radius
MODE_PIERCE = 3  # as MODE_CONVEX, but the weights locate where the line pierces the triangle

_GRID_CELL_CAP_PER_POINT = 8
_MIN_GRID_CELLS = 4096


def grid_cell_size(points: np.ndarray, radius: np.ndarray, cell_factor: float) -> float:
    """Cell edge for the dilated grid: ``cell_factor * (N / 1024)^(1/6)`` times the median radius,
    bounded so the grid has at most ``max(4096, 8 N)`` cells (memory linear in ``N``).

    The growth with ``N`` balances the two costs of a line: cells crossed (``~ 1 / cell``) and
    points tested (``~ N * cell^2`` on a surface), whose optimum is ``cell ~ N^(-1/3)``, while
    the radius shrinks as ``N^(-1/2)`` (``scripts/bench_loss.py`` shows the effect).
    """
    extent = points.max(axis=0) - points.min(axis=0) + 2.0 * radius.max()
    cap = max(_MIN_GRID_CELLS, _GRID_CELL_CAP_PER_POINT * len(points))
    floor = float((np.prod(np.maximum(extent, 1e-300)) / cap) ** (1.0 / 3.0))
    floor = max(floor, float(extent.max()) / 1024.0)
    factor = cell_factor * (len(points) / 1024.0) ** (1.0 / 6.0)
    return max(factor * float(np.median(radius)), floor, float(np.finfo(np.float64).tiny))


@numba.njit(cache=True)
def build_dilated_grid(points, radius, cell):
    """CSR grid: cell ``c`` holds ``cell_points[cell_start[c]:cell_start[c+1]]``.

    Returns ``(grid_min (3,), dims (3,) int64, cell_start (C+1,), cell_points (S,),
    cell_xyzr (4, S))``; ``cell_xyzr`` repeats each stored point's coordinates and radius in
    cell order so that the line walk reads memory sequentially.
    """
    n = points.shape[0]
    grid_min = np.empty(3)
    grid_max = np.empty(3)
    r_max = radius.max()
    for a in range(3):
        grid_min[a] = points[:, a].min() - r_max
        grid_max[a] = points[:, a].max() + r_max
    dims = np.empty(3, dtype=np.int64)
    for a in range(3):
        dims[a] = max(1, math.ceil((grid_max[a] - grid_min[a]) / cell))
    n_cells = dims[0] * dims[1] * dims[2]
    lo = np.empty((n, 3), dtype=np.int64)
    hi = np.empty((n, 3), dtype=np.int64)
    counts = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        for a in range(3):
            lo[i, a] = min(dims[a] - 1, max(0, int((points[i, a] - radius[i] - grid_min[a]) / cell)))
            hi[i, a] = min(dims[a] - 1, max(0, int((points[i, a] + radius[i] - grid_min[a]) / cell)))
        for x in range(lo[i, 0], hi[i, 0] + 1):
            for y in range(lo[i, 1], hi[i, 1] + 1):
                for z in range(lo[i, 2], hi[i, 2] + 1):
                    counts[(x * dims[1] + y) * dims[2] + z + 1] += 1
    cell_start = np.cumsum(counts)
    fill = cell_start[:-1].copy()
    cell_points = np.empty(cell_start[-1], dtype=np.int64)
    for i in range(n):
        for x in range(lo[i, 0], hi[i, 0] + 1):
            for y in range(lo[i, 1], hi[i, 1] + 1):
                for z in range(lo[i, 2], hi[i, 2] + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    cell_points[fill[c]] = i
                    fill[c] += 1
    cell_xyzr = np.empty((4, cell_points.shape[0]))
    for s in range(cell_points.shape[0]):
        i = cell_points[s]
        cell_xyzr[0, s] = points[i, 0]
        cell_xyzr[1, s] = points[i, 1]
        cell_xyzr[2, s] = points[i, 2]
        cell_xyzr[3, s] = radius[i]
    return grid_min, dims, cell_start, cell_points, cell_xyzr


@numba.njit(cache=True, inline="always")
def _line_distance(points, i, ox, oy, oz, ux, uy, uz, eps2):
    """Distance from point ``i`` to the line ``o + t u`` (``u`` unit), with ``eps2`` added
    under the square root (the authors' code adds 2e-4)."""
    dx = points[i, 0] - ox
    dy = points[i, 1] - oy
    dz = points[i, 2] - oz
    t = dx * ux + dy * uy + dz * uz
    d2 = dx * dx + dy * dy + dz * dz - t * t
    return math.sqrt(max(d2, 0.0) + eps2)


@numba.njit(cache=True, inline="always")
def _axis_setup(o, u, lo, cell, dim, t_start):
    """DDA set-up on one axis: ``(cell index, step, t of the next boundary, t per cell)``."""
    i = min(dim - 1, max(0, int((o + t_start * u - lo) / cell)))
    if u > 1e-15:
        return i, 1, (lo + (i + 1) * cell - o) / u, cell / u
    if u < -1e-15:
        return i, -1, (lo + i * cell - o) / u, -cell / u
    return i, 0, np.inf, np.inf


@numba.njit(cache=True, inline="always")
def _slab(o, u, lo, hi, t0, t1):
    """Intersect the running parameter interval ``[t0, t1]`` with one slab of the grid box."""
    if abs(u) < 1e-15:
        if o < lo or o > hi:
            return 1.0, 0.0
        return t0, t1
    ta = (lo - o) / u
    tb = (hi - o) / u
    return max(t0, min(ta, tb)), min(t1, max(ta, tb))


@numba.njit(cache=True)
def _pierce_weights(points, a, b, c, ox, oy, oz, ux, uy, uz, out):
    """Barycentric weights of the point where the line pierces the plane of triangle ``abc``.

    Writes ``out[0:3]`` and returns True, or returns False (leaving ``out`` alone) when the
    triangle is degenerate or nearly parallel to the line.
    """
    e1x = points[b, 0] - points[a, 0]
    e1y = points[b, 1] - points[a, 1]
    e1z = points[b, 2] - points[a, 2]
    e2x = points[c, 0] - points[a, 0]
    e2y = points[c, 1] - points[a, 1]
    e2z = points[c, 2] - points[a, 2]
    # Moller-Trumbore: solve o + t u = a + w1 e1 + w2 e2.
    px = uy * e2z - uz * e2y
    py = uz * e2x - ux * e2z
    pz = ux * e2y - uy * e2x
    det = e1x * px + e1y * py + e1z * pz
    scale = math.sqrt((e1x * e1x + e1y * e1y + e1z * e1z) * (e2x * e2x + e2y * e2y + e2z * e2z))
    if abs(det) <= 1e-3 * scale:
        return False
    sx = ox - points[a, 0]
    sy = oy - points[a, 1]
    sz = oz - points[a, 2]
    w1 = (sx * px + sy * py + sz * pz) / det
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    w2 = (ux * qx + uy * qy + uz * qz) / det
    out[0] = 1.0 - w1 - w2
    out[1] = w1
    out[2] = w2
    return True


@numba.njit(cache=True, inline="always")
def _scan_line(
    line,
    origins,
    dirs,
    points,
    radius,
    neighbors,
    mode,
    eps2,
    grid_min,
    dims,
    cell,
    cell_start,
    cell_points,
    cell_xyzr,
    scratch_entry,
    scratch_d2,
    scratch_near,
    out_anchor,
    out_weight,
    out_start,
    out_stop,
):
    """Walk one line through the grid of one cloud and return its number of intersections.

    Intersection ``j`` of the line is written to row ``out_start + j`` of ``out_anchor`` and
    ``out_weight`` when that row is below ``out_stop``; the ones beyond are only counted.
    ``scratch_entry`` and ``scratch_d2`` hold at least as many rows as the grid has entries,
    ``scratch_near`` ``k``.
    """
    ox, oy, oz = origins[line, 0], origins[line, 1], origins[line, 2]
    ux, uy, uz = dirs[line, 0], dirs[line, 1], dirs[line, 2]
    nx, ny, nz = dims[0], dims[1], dims[2]
    k = neighbors.shape[1]
    t0, t1 = _slab(ox, ux, grid_min[0], grid_min[0] + nx * cell, -np.inf, np.inf)
    t0, t1 = _slab(oy, uy, grid_min[1], grid_min[1] + ny * cell, t0, t1)
    t0, t1 = _slab(oz, uz, grid_min[2], grid_min[2] + nz * cell, t0, t1)
    if t0 >= t1:
        return 0
    t_start = t0 + 1e-9 * (t1 - t0)
    ix, sx, tmx, tdx = _axis_setup(ox, ux, grid_min[0], cell, nx, t_start)
    iy, sy, tmy, tdy = _axis_setup(oy, uy, grid_min[1], cell, ny, t_start)
    iz, sz, tmz, tdz = _axis_setup(oz, uz, grid_min[2], cell, nz, t_start)
    # Phase 1: collect the candidates in walk order with a branch-free test. Each stored point is
    # kept only in the cell whose parameter interval holds its foot point (dedup).
    found = 0
    t_enter = -np.inf
    while True:
        # Next boundary crossed, and whether this is the last cell on the line.
        if tmx <= tmy and tmx <= tmz:
            t_exit = tmx
            last = ix + sx < 0 or ix + sx >= nx
        elif tmy <= tmz:
            t_exit = tmy
            last = iy + sy < 0 or iy + sy >= ny
        else:
            t_exit = tmz
            last = iz + sz < 0 or iz + sz >= nz
        if t_exit >= t1:
            last = True
        if last:
            t_exit = np.inf
        c = (ix * ny + iy) * nz + iz
        for s in range(cell_start[c], cell_start[c + 1]):
            dx = cell_xyzr[0, s] - ox
            dy = cell_xyzr[1, s] - oy
            dz = cell_xyzr[2, s] - oz
            t = dx * ux + dy * uy + dz * uz
            r = cell_xyzr[3, s]
            d2 = max(dx * dx + dy * dy + dz * dz - t * t, 0.0)
            scratch_entry[found] = s
            scratch_d2[found] = d2
            found += (d2 + eps2 < r * r) & (t >= t_enter) & (t < t_exit)
        if last:
            break
        t_enter = t_exit
        if tmx <= tmy and tmx <= tmz:
            ix += sx
            tmx += tdx
        elif tmy <= tmz:
            iy += sy
            tmy += tdy
        else:
            iz += sz
            tmz += tdz
    # Phase 2: the neighbour test and the weights of each candidate.
    count = 0
    for j in range(found):
        s = scratch_entry[j]
        i = cell_points[s]
        r = cell_xyzr[3, s]
        d = math.sqrt(scratch_d2[j] + eps2)
        row = out_start + count
        write = row < out_stop
        if mode == MODE_CANDIDATES:
            if write:
                out_anchor[row] = i
                out_weight[row, 0] = 1.0
            count += 1
            continue
        # MODE_CONVEX: neighbours must be candidates under their own radius;
        # MODE_TRIPLET: neighbours must be within the anchor's radius.
        ok = True
        total = d
        for m in range(k):
            nb = neighbors[i, m]
            dn = _line_distance(points, nb, ox, oy, oz, ux, uy, uz, eps2)
            limit = r if mode == MODE_TRIPLET else radius[nb]
            if dn >= limit:
                ok = False
                break
            scratch_near[m] = dn
            total += dn
        if not ok:
            continue
        count += 1
        if not write:
            continue
        out_anchor[row] = i
        if mode == MODE_PIERCE and _pierce_weights(
            points, i, neighbors[i, 0], neighbors[i, 1], ox, oy, oz, ux, uy, uz, out_weight[row]
        ):
            continue
        if total > 0.0:
            out_weight[row, 0] = d / total
            for m in range(k):
                out_weight[row, m + 1] = scratch_near[m] / total
        else:
            for m in range(k + 1):
                out_weight[row, m] = 1.0 / (k + 1)
    return count


@numba.njit(cache=True)
def _concatenated_grids(points, point_offsets, radius, cells):
    """One dilated grid per cloud, stored back to back.

    Returns ``grid_min (C, 3)``, ``dims (C, 3)``, ``cell_offsets (C+1,)`` (the CSR array of
    cloud ``c`` is ``cell_start[cell_offsets[c]:cell_offsets[c+1]]``), and the concatenated
    ``cell_start`` (indices into the concatenated entries), ``cell_points`` (cloud-local
    indices) and ``cell_xyzr``.
    """
    n_clouds = cells.shape[0]
    grid_min = np.empty((n_clouds, 3))
    dims = np.empty((n_clouds, 3), dtype=np.int64)
    cell_offsets = np.zeros(n_clouds + 1, dtype=np.int64)
    entry_offsets = np.zeros(n_clouds + 1, dtype=np.int64)
    grids = []
    for c in range(n_clouds):
        p0, p1 = point_offsets[c], point_offsets[c + 1]
        grid = build_dilated_grid(points[p0:p1], radius[p0:p1], cells[c])
        grid_min[c] = grid[0]
        dims[c] = grid[1]
        cell_offsets[c + 1] = cell_offsets[c] + grid[2].shape[0]
        entry_offsets[c + 1] = entry_offsets[c] + grid[3].shape[0]
        grids.append(grid)
    cell_start = np.empty(cell_offsets[-1], dtype=np.int64)
    cell_points = np.empty(entry_offsets[-1], dtype=np.int64)
    cell_xyzr = np.empty((4, entry_offsets[-1]))
    for c in range(n_clouds):
        _, _, start, stored, xyzr = grids[c]
        cell_start[cell_offsets[c] : cell_offsets[c + 1]] = start + entry_offsets[c]
        cell_points[entry_offsets[c] : entry_offsets[c + 1]] = stored
        cell_xyzr[:, entry_offsets[c] : entry_offsets[c + 1]] = xyzr
    return grid_min, dims, cell_offsets, cell_start, cell_points, cell_xyzr


@numba.njit(cache=True)
def _scan_lines(
    cloud,
    first,
    stop,
    origins,
    dirs,
    points,
    point_offsets,
    radius,
    neighbors,
    mode,
    eps2,
    cells,
    grids,
    counts,
    out_anchor,
    out_weight,
    out_start,
    out_stop,
):
    """Scan lines ``first:stop`` against cloud ``cloud``, writing their intersections back to back
    from row ``out_start`` (only rows below ``out_stop``); fills ``counts`` and returns the total."""
    grid_min, dims, cell_offsets, cell_start, cell_points, cell_xyzr = grids
    p0, p1 = point_offsets[cloud], point_offsets[cloud + 1]
    c0, c1 = cell_offsets[cloud], cell_offsets[cloud + 1]
    cloud_points, cloud_radius, cloud_neighbors = points[p0:p1], radius[p0:p1], neighbors[p0:p1]
    entries = cell_start[c1 - 1] - cell_start[c0]
    scratch_entry = np.empty(entries + 1, dtype=np.int64)
    scratch_d2 = np.empty(entries + 1)
    scratch_near = np.empty(cloud_neighbors.shape[1])
    cloud_min, cloud_dims, cloud_cell, cloud_start = grid_min[cloud], dims[cloud], cells[cloud], cell_start[c0:c1]
    row = out_start
    for line in range(first, stop):
        n = _scan_line(
            line,
            origins,
            dirs,
            cloud_points,
            cloud_radius,
            cloud_neighbors,
            mode,
            eps2,
            cloud_min,
            cloud_dims,
            cloud_cell,
            cloud_start,
            cell_points,
            cell_xyzr,
            scratch_entry,
            scratch_d2,
            scratch_near,
            out_anchor,
            out_weight,
            row,
            out_stop,
        )
        counts[line] = n
        row += n
    return row - out_start


@numba.njit(cache=True, parallel=True)
def line_intersections(origins, dirs, line_offsets, points, point_offsets, radius, neighbors, mode, eps2, cells, chunk):
    """All intersections of lines with clouds, for a whole batch at once.

    Cloud ``c`` is ``points[point_offsets[c]:point_offsets[c+1]]``; its lines are rows
    ``line_offsets[c]:line_offsets[c+1]`` of ``origins`` and ``dirs``. Work items of at most
    ``chunk`` lines of one cloud run in parallel (numba threads, across clouds and lines); each
    writes into its own slice of a buffer, and a final pass copies the slices out in line order,
    so the result does not depend on the number of threads. An item whose lines have more
    intersections than its slice holds is scanned again, straight into the output.

    Args:
        origins, dirs: ``(L, 3)`` float64 line points and unit directions.
        line_offsets: ``(C+1,)`` int64 line range of each cloud.
        points: ``(N, 3)`` float64, the clouds back to back.
        point_offsets: ``(C+1,)`` int64 point range of each cloud.
        radius: ``(N,)`` float64 per-point cylinder radius (``delta`` in the paper).
        neighbors: ``(N, k)`` int64 cloud-local indices of the k nearest neighbours of each point
            (self excluded); ``(N, 0)`` for ``MODE_CANDIDATES``.
        mode: ``MODE_CANDIDATES``, ``MODE_CONVEX``, ``MODE_TRIPLET`` or ``MODE_PIERCE``.
        eps2: added under the square root of every point-line distance.
        cells: ``(C,)`` float64 grid cell edge of each cloud (see :func:`grid_cell_size`).
        chunk: most lines per work item.

    Returns:
        ``offsets (L+1,)`` int64 (intersections of line ``l`` are ``offsets[l]:offsets[l+1]``),
        ``anchors (H,)`` int64 cloud-local anchor point of each intersection, ``weights (H, k+1)``
        float64 convex weights of the anchor and its neighbours (detached; Eq. 7's
        ``d_p / sum d``, or barycentric for ``MODE_PIERCE``).
    """
    n_clouds = cells.shape[0]
    n_lines = origins.shape[0]
    k = neighbors.shape[1]
    grids = _concatenated_grids(points, point_offsets, radius, cells)
    items_per_cloud = np.empty(n_clouds, dtype=np.int64)
    for c in range(n_clouds):
        items_per_cloud[c] = (line_offsets[c + 1] - line_offsets[c] + chunk - 1) // chunk
    n_items = items_per_cloud.sum()
    item_cloud = np.empty(n_items, dtype=np.int64)
    item_first = np.empty(n_items, dtype=np.int64)
    item_stop = np.empty(n_items, dtype=np.int64)
    buffer_start = np.zeros(n_items + 1, dtype=np.int64)
    item = 0
    for c in range(n_clouds):
        for j in range(items_per_cloud[c]):
            item_cloud[item] = c
            item_first[item] = line_offsets[c] + j * chunk
            item_stop[item] = min(line_offsets[c + 1], item_first[item] + chunk)
            # Room for a few intersections per line; busier items are scanned twice.
            buffer_start[item + 1] = buffer_start[item] + 4 * (item_stop[item] - item_first[item]) + 16
            item += 1
    buffer_anchor = np.empty(buffer_start[-1], dtype=np.int64)
    buffer_weight = np.empty((buffer_start[-1], k + 1))
    counts = np.zeros(n_lines, dtype=np.int64)
    item_total = np.empty(n_items, dtype=np.int64)
    for item in numba.prange(n_items):
        item_total[item] = _scan_lines(
            item_cloud[item],
            item_first[item],
            item_stop[item],
            origins,
            dirs,
            points,
            point_offsets,
            radius,
            neighbors,
            mode,
            eps2,
            cells,
            grids,
            counts,
            buffer_anchor,
            buffer_weight,
            buffer_start[item],
            buffer_start[item + 1],
        )
    offsets = np.zeros(n_lines + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(counts)
    anchors = np.empty(offsets[-1], dtype=np.int64)
    weights = np.empty((offsets[-1], k + 1))
    for item in numba.prange(n_items):
        first, stop, total = item_first[item], item_stop[item], item_total[item]
        out = offsets[first]
        if total <= buffer_start[item + 1] - buffer_start[item]:
            begin = buffer_start[item]
            anchors[out : out + total] = buffer_anchor[begin : begin + total]
            weights[out : out + total] = buffer_weight[begin : begin + total]
        else:
            _scan_lines(
                item_cloud[item],
                first,
                stop,
                origins,
                dirs,
                points,
                point_offsets,
                radius,
                neighbors,
                mode,
                eps2,
                cells,
                grids,
                counts,
                anchors,
                weights,
                out,
                offsets[stop],
            )
    return offsets, anchors, weights


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
    hit_points = np.zeros((n_hits, 3))
    members = np.empty((n_hits, k + 1), dtype=np.int64)
    for c in numba.prange(point_offsets.shape[0] - 1):
        p0 = point_offsets[c]
        for h in range(offsets[line_offsets[c]], offsets[line_offsets[c + 1]]):
            anchor = p0 + anchors[h]
            members[h, 0] = anchor
            for m in range(k):
                members[h, m + 1] = p0 + neighbors[anchor, m]
            for m in range(k + 1):
                for a in range(3):
                    hit_points[h, a] += weights[h, m] * points[members[h, m], a]
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


@numba.njit(cache=True)
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
    value = np.zeros(n_samples)
    scale = np.zeros(n_samples)
    counts = np.zeros((n_samples, 5), dtype=np.int64)
    hit_grad = np.zeros((anchors.shape[0], 3))
    for b in range(n_samples):
        l0, l1 = line_offsets[b], line_offsets[b + 1]
        for line in range(l0, l1):
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
        two_c = max(2.0 * (scale[b] if squared_input else scale[b] * scale[b]), tiny)
        per_line = 1.0 / max(counts[b, 0], 1)
        total = 0.0
        for line in range(l0, l1):
            w = math.exp(-abs(ns[line] - nt[line]) / 2.0) if line_weight else 1.0
            for p in range(pair_offsets[line], pair_offsets[line + 1]):
                near = math.exp(-dist_sq[p] / two_c)
                total += w * (1.0 - near)
                slope = per_line * w * near * 2.0 / two_c
                s, g = src_hit[p], tgt_hit[p]
                for a in range(3):
                    step = slope * (hit_points[s, a] - hit_points[g, a])
                    hit_grad[s, a] += step
                    hit_grad[g, a] -= step
        value[b] = total * per_line
    grad = np.zeros(points.shape)
    for h in range(anchors.shape[0]):
        for m in range(members.shape[1]):
            for a in range(3):
                grad[members[h, m], a] += weights[h, m] * hit_grad[h, a]
    return value, grad, scale, counts


@numba.njit(cache=True)
def _cloud_knn(points, k, out_index, out_dist):
    """The ``k`` nearest other points of every point of one cloud, sorted by distance, found
    in a uniform grid of about two points per cell by searching rings of cells outwards until
    no closer point can remain."""
    n = points.shape[0]
    lo = np.empty(3)
    extent = np.empty(3)
    for a in range(3):
        lo[a] = points[:, a].min()
        extent[a] = points[:, a].max() - lo[a]
    floor = 1e-9 * max(extent.max(), 1e-300)
    volume = max(extent[0], floor) * max(extent[1], floor) * max(extent[2], floor)
    cell = max((volume / max(n / 2, 1)) ** (1.0 / 3.0), 1e-300)
    dims = np.empty(3, dtype=np.int64)
    while True:
        for a in range(3):
            dims[a] = min(int(extent[a] / cell) + 1, 1 << 20)
        if dims[0] * dims[1] * dims[2] <= 4 * n + 64:
            break
        cell *= 1.26
    cell_of = np.empty(n, dtype=np.int64)
    counts = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    for i in range(n):
        c = 0
        for a in range(3):
            c = c * dims[a] + min(dims[a] - 1, int((points[i, a] - lo[a]) / cell))
        cell_of[i] = c
        counts[c + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[cell_of[i]]] = i
        fill[cell_of[i]] += 1
    sorted_points = np.empty((n, 3))
    for s in range(n):
        for a in range(3):
            sorted_points[s, a] = points[order[s], a]
    best = np.empty(k)
    home = np.empty(3, dtype=np.int64)
    for query in range(n):  # in cell order, so that neighbouring queries read the same cells
        i = order[query]
        c = cell_of[i]
        margin = np.inf
        for a in range(2, -1, -1):
            home[a] = c % dims[a]
            c //= dims[a]
            offset = points[i, a] - lo[a] - home[a] * cell
            margin = min(margin, offset, cell - offset)
        margin = max(margin, 0.0)
        for m in range(k):
            best[m] = np.inf
            out_index[i, m] = -1
        ring = 0
        while True:
            for x in range(max(home[0] - ring, 0), min(home[0] + ring, dims[0] - 1) + 1):
                for y in range(max(home[1] - ring, 0), min(home[1] + ring, dims[1] - 1) + 1):
                    on_shell = abs(x - home[0]) == ring or abs(y - home[1]) == ring
                    for z in range(max(home[2] - ring, 0), min(home[2] + ring, dims[2] - 1) + 1):
                        if not (on_shell or abs(z - home[2]) == ring):
                            continue
                        # Skip a cell that cannot hold a point closer than the k-th found so far.
                        gap = 0.0
                        for a, index in ((0, x), (1, y), (2, z)):
                            below = lo[a] + index * cell - points[i, a]
                            above = points[i, a] - lo[a] - (index + 1) * cell
                            step = max(below, above, 0.0)
                            gap += step * step
                        if gap > best[k - 1]:
                            continue
                        c = (x * dims[1] + y) * dims[2] + z
                        for s in range(start[c], start[c + 1]):
                            d = 0.0
                            for a in range(3):
                                diff = sorted_points[s, a] - points[i, a]
                                d += diff * diff
                            j = order[s]
                            if d < best[k - 1] and j != i:
                                m = k - 1
                                while m > 0 and best[m - 1] > d:
                                    best[m] = best[m - 1]
                                    out_index[i, m] = out_index[i, m - 1]
                                    m -= 1
                                best[m] = d
                                out_index[i, m] = j
            covered = ring >= dims[0] and ring >= dims[1] and ring >= dims[2]
            reach = ring * cell + margin
            if covered or (out_index[i, k - 1] >= 0 and best[k - 1] <= reach * reach):
                break
            ring += 1
        for m in range(k):
            out_dist[i, m] = math.sqrt(best[m])


@numba.njit(cache=True, parallel=True)
def nearest_neighbors(points, point_offsets, k):
    """The ``k`` nearest other points of every point, cloud by cloud (clouds in parallel).

    Args:
        points: ``(N, 3)`` float64, the clouds back to back.
        point_offsets: ``(C+1,)`` int64 point range of each cloud (each with more than ``k`` points).
        k: neighbours per point.

    Returns:
        ``index (N, k)`` int64 cloud-local indices and ``dist (N, k)`` float64 Euclidean
        distances, ascending; a point's own index is never among its neighbours, its duplicates are.
    """
    index = np.empty((points.shape[0], k), dtype=np.int64)
    dist = np.empty((points.shape[0], k))
    for c in numba.prange(point_offsets.shape[0] - 1):
        p0, p1 = point_offsets[c], point_offsets[c + 1]
        _cloud_knn(points[p0:p1], k, index[p0:p1], dist[p0:p1])
    return index, dist
