"""Compiled (numba) candidate search of the line-intersection metric.

The kernels decide *which* points form each intersection (indices and detached convex
weights). On the numba path, :func:`linereg.losses.line_welsch_kernels.welsch_lines` then
matches the intersections and computes the value of the paper's per-line reduction with its
gradient in closed form; for the other settings the loss gathers the points with torch and
autograd differentiates the value. The k nearest neighbours of the points and their radii come
from :func:`linereg.losses.line_neighbors.cloud_neighborhoods`.

Candidate search, without ever testing all point-line pairs:

* every point ``p`` with radius ``r_p`` is inserted into each cell of a uniform grid that its
  ball ``B(p, r_p)`` overlaps (a "dilated" grid, built once per call in ``O(N)``:
  :mod:`linereg.losses.line_grid`); one grid holds both clouds of a sample (source and target
  share their lines), so each line is walked once;
* each line walks the cells it crosses (3D-DDA, Amanatides & Woo 1987; each axis steps exactly
  the cells between the line's entry and exit cells) and tests the points stored there. If
  ``dist(p, line) < r_p``, the foot of the perpendicular ``q`` lies in ``B(p, r_p)``, so the cell
  that the walk visits at ``q``'s line parameter holds a copy of ``p``. A point is therefore
  accepted only in the cell whose parameter interval contains its own parameter ``t_p``, which
  finds every candidate exactly once.

Work is ``O(N + L * (cells crossed + points met))``; memory ``O(N + L + hits)``. Each line is
scanned in two phases: a branch-free pass over the points of the cells it crosses collects the
candidates (a data-dependent branch per tested point costs more than the test itself), then the
neighbour test and the weights run on those few, each written to its own cloud's output.

Threads: :func:`line_intersections` takes all samples of a batch (sources and targets) at once
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

from .line_grid import sample_grids

if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # Try OpenMP first: numba's default tries TBB first and warns when a library loaded earlier
    # (Open3D ships one) is too old for it.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

MODE_CANDIDATES = 0  # Insec1: every candidate point is an intersection
MODE_CONVEX = 1  # paper Eq. (7): candidates whose k nearest neighbours are candidates too
MODE_TRIPLET = 2  # authors' code: the point and its k neighbours all within the anchor's radius
MODE_PIERCE = 3  # as MODE_CONVEX, but the weights locate where the line pierces the triangle


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
def _axis_walk(o, u, lo, cell, dim, t_in, t_out):
    """DDA set-up on one axis between the parameters ``t_in`` and ``t_out`` of a line inside the
    grid box: ``(first cell index, cells to step, t of the first boundary, t per cell)``."""
    first = min(dim - 1, max(0, int((o + t_in * u - lo) / cell)))
    last = min(dim - 1, max(0, int((o + t_out * u - lo) / cell)))
    if u > 1e-15:
        return first, max(last - first, 0), (lo + (first + 1) * cell - o) / u, cell / u
    if u < -1e-15:
        return first, max(first - last, 0), (lo + first * cell - o) / u, -cell / u
    return first, 0, np.inf, np.inf


@numba.njit(cache=True, inline="always")
def _collect_candidates(ox, oy, oz, ux, uy, uz, eps2, grid_min, dims, cell, cell_start, entry_xyzr, flags, found):
    """Walk the line ``o + t u`` through a dilated grid (3D-DDA) and write to ``found`` the
    entries within their radius of it, in walk order; return their number.

    A point is stored in every cell its ball overlaps, so it is kept only in the cell whose
    parameter interval holds its foot point's ``t`` (each point at most once). The test has no
    branch: a cell's entries (coordinates and squared radii stored as rows, ``entry_xyzr (4, S)``)
    are tested in one loop into ``flags`` (``(S,)`` bool scratch), which the compiler vectorises,
    then compacted into ``found``.
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    t0, t1 = _slab(ox, ux, grid_min[0], grid_min[0] + nx * cell, -np.inf, np.inf)
    t0, t1 = _slab(oy, uy, grid_min[1], grid_min[1] + ny * cell, t0, t1)
    t0, t1 = _slab(oz, uz, grid_min[2], grid_min[2] + nz * cell, t0, t1)
    if not t0 < t1:
        return 0
    margin = 1e-9 * (t1 - t0)
    ix, steps_x, tmx, tdx = _axis_walk(ox, ux, grid_min[0], cell, nx, t0 + margin, t1 - margin)
    iy, steps_y, tmy, tdy = _axis_walk(oy, uy, grid_min[1], cell, ny, t0 + margin, t1 - margin)
    iz, steps_z, tmz, tdz = _axis_walk(oz, uz, grid_min[2], cell, nz, t0 + margin, t1 - margin)
    # Each axis steps exactly the cells between the entry and exit cells, so the walk stays in
    # the grid whatever the rounding of the boundary parameters.
    if steps_x == 0:
        tmx = np.inf
    if steps_y == 0:
        tmy = np.inf
    if steps_z == 0:
        tmz = np.inf
    stride_x = ny * nz if ux > 0 else -ny * nz
    stride_y = nz if uy > 0 else -nz
    stride_z = 1 if uz > 0 else -1
    c = (ix * ny + iy) * nz + iz
    count = 0
    t_enter = -np.inf
    for _ in range(steps_x + steps_y + steps_z + 1):
        t_exit = min(tmx, min(tmy, tmz))
        start = cell_start[c]
        size = cell_start[c + 1] - start
        xs = entry_xyzr[0, start : start + size]
        ys = entry_xyzr[1, start : start + size]
        zs = entry_xyzr[2, start : start + size]
        r2s = entry_xyzr[3, start : start + size]
        for j in range(size):
            dx = xs[j] - ox
            dy = ys[j] - oy
            dz = zs[j] - oz
            t = dx * ux + dy * uy + dz * uz
            d2 = max(dx * dx + dy * dy + dz * dz - t * t, 0.0)
            flags[j] = (d2 + eps2 < r2s[j]) & (t >= t_enter) & (t < t_exit)
        for j in range(size):
            found[count] = start + j
            count += flags[j]
        t_enter = t_exit
        if tmx == t_exit:
            c += stride_x
            steps_x -= 1
            tmx = tmx + tdx if steps_x > 0 else np.inf
        elif tmy == t_exit:
            c += stride_y
            steps_y -= 1
            tmy = tmy + tdy if steps_y > 0 else np.inf
        else:
            c += stride_z
            steps_z -= 1
            tmz = tmz + tdz if steps_z > 0 else np.inf
    return count


@numba.njit(cache=True)
def _scan_lines(batch, sample, first, stop, cell, grid, counts, count_lines, out_anchor, out_weight, out_row, out_stop):
    """Intersections of lines ``first:stop`` of sample ``sample`` with each of its clouds.

    ``batch`` is ``(origins, dirs, points, point_offsets, radius, neighbors, mode, eps2)``, the
    arguments of :func:`line_intersections`. Each line walks the sample's grid once (all its clouds
    together); the intersections of line ``l`` with side ``g`` are written from ``out_row[g]`` on
    (rows below ``out_stop[g]`` only; the others are only counted) and, if ``count_lines``,
    counted in ``counts[g * L + l]``. Returns the ``(G,)`` totals.
    """
    origins, dirs, points, point_offsets, radius, neighbors, mode, eps2 = batch
    grid_min, dims, cell_start, entry_rows, entry_xyzr = grid
    n_sides = out_row.shape[0]
    n_samples = (point_offsets.shape[0] - 1) // n_sides
    n_lines = origins.shape[0]
    k = neighbors.shape[1]
    found = np.empty(entry_rows.shape[0] + 1, dtype=np.int64)
    flags = np.empty(entry_rows.shape[0], dtype=np.bool_)
    near = np.empty(k)
    row = out_row.copy()
    cloud_start = np.empty(n_sides, dtype=np.int64)
    cloud_stop = np.empty(n_sides, dtype=np.int64)
    for g in range(n_sides):
        cloud_start[g] = point_offsets[g * n_samples + sample]
        cloud_stop[g] = point_offsets[g * n_samples + sample + 1]
    for line in range(first, stop):
        ox, oy, oz = origins[line, 0], origins[line, 1], origins[line, 2]
        ux, uy, uz = dirs[line, 0], dirs[line, 1], dirs[line, 2]
        n_found = _collect_candidates(
            ox, oy, oz, ux, uy, uz, eps2, grid_min, dims, cell, cell_start, entry_xyzr, flags, found
        )
        # The neighbour test and the weights of each candidate.
        for j in range(n_found):
            s = found[j]
            i = entry_rows[s]
            side = 0
            while i >= cloud_stop[side]:
                side += 1
            p0 = cloud_start[side]
            r = radius[i]
            d = math.sqrt(_clamped_d2(points, i, ox, oy, oz, ux, uy, uz) + eps2)
            ok = True
            total = d
            for m in range(k):
                nb = p0 + neighbors[i, m]
                dn = _line_distance(points, nb, ox, oy, oz, ux, uy, uz, eps2)
                # MODE_CONVEX, MODE_PIERCE: neighbours must be candidates under their own
                # radius; MODE_TRIPLET: within the anchor's radius.
                limit = r if mode == MODE_TRIPLET else radius[nb]
                if dn >= limit:
                    ok = False
                    break
                near[m] = dn
                total += dn
            if not ok:
                continue
            if count_lines:
                counts[side * n_lines + line] += 1
            out = row[side]
            row[side] = out + 1
            if out >= out_stop[side]:
                continue
            out_anchor[out] = i - p0
            if mode == MODE_CANDIDATES:
                out_weight[out, 0] = 1.0
                continue
            if mode == MODE_PIERCE and _pierce_weights(
                points, i, p0 + neighbors[i, 0], p0 + neighbors[i, 1], ox, oy, oz, ux, uy, uz, out_weight[out]
            ):
                continue
            if total > 0.0:
                out_weight[out, 0] = d / total
                for m in range(k):
                    out_weight[out, m + 1] = near[m] / total
            else:
                for m in range(k + 1):
                    out_weight[out, m] = 1.0 / (k + 1)
    return row - out_row


@numba.njit(cache=True, inline="always")
def _clamped_d2(points, i, ox, oy, oz, ux, uy, uz):
    """Squared distance from point ``i`` to the line ``o + t u``, as the walk computes it."""
    dx = points[i, 0] - ox
    dy = points[i, 1] - oy
    dz = points[i, 2] - oz
    t = dx * ux + dy * uy + dz * uz
    return max(dx * dx + dy * dy + dz * dz - t * t, 0.0)


@numba.njit(cache=True)
def float_zeros(shape):
    """``np.zeros(shape)``, compiled apart: written inside a ``parallel=True`` kernel, an
    allocation (or any array expression) becomes a parallel region of its own, and each region
    wakes the threads; the kernels keep parallel regions to their ``prange`` loops."""
    return np.zeros(shape)


@numba.njit(cache=True)
def int_zeros(shape):
    """``np.zeros(shape, int64)``, compiled apart (see :func:`float_zeros`)."""
    return np.zeros(shape, dtype=np.int64)


@numba.njit(cache=True, parallel=True)
def line_intersections(origins, dirs, line_offsets, points, point_offsets, radius, neighbors, mode, eps2, cells, chunk):
    """All intersections of lines with clouds, for a whole batch at once.

    Sample ``b`` has the lines ``line_offsets[b]:line_offsets[b+1]`` of ``origins`` and ``dirs``
    and ``G`` clouds (sides), cloud ``g`` being ``points[point_offsets[g*B+b]:point_offsets[g*B+b+1]]``.
    Each sample's clouds share one dilated grid and each line walks it once. Work items of at most
    ``chunk`` lines of one sample run in parallel (numba threads, across samples and lines); each
    writes into its own slice of a buffer per side, and a final pass copies the slices out in line
    order, so the result does not depend on the number of threads. An item whose lines have more
    intersections than its slice holds is scanned again, straight into the output.

    Args:
        origins, dirs: ``(L, 3)`` float64 line points and unit directions.
        line_offsets: ``(B+1,)`` int64 line range of each sample.
        points: ``(N, 3)`` float64, the clouds back to back (``G * B`` of them, side-major).
        point_offsets: ``(G*B+1,)`` int64 point range of each cloud.
        radius: ``(N,)`` float64 per-point cylinder radius (``delta`` in the paper).
        neighbors: ``(N, k)`` int64 cloud-local indices of the k nearest neighbours of each point
            (self excluded); ``(N, 0)`` for ``MODE_CANDIDATES``.
        mode: ``MODE_CANDIDATES``, ``MODE_CONVEX``, ``MODE_TRIPLET`` or ``MODE_PIERCE``.
        eps2: added under the square root of every point-line distance.
        cells: ``(B,)`` float64 grid cell edge of each sample (see :func:`grid_cell_size`).
        chunk: most lines per work item.

    Returns:
        ``offsets (G*L+1,)`` int64 (intersections of line ``l`` with side ``g`` are
        ``offsets[g*L+l]:offsets[g*L+l+1]``), ``anchors (H,)`` int64 cloud-local anchor point of
        each intersection, ``weights (H, k+1)`` float64 convex weights of the anchor and its
        neighbours (detached; Eq. 7's ``d_p / sum d``, or barycentric for ``MODE_PIERCE``).
    """
    n_samples = cells.shape[0]
    n_sides = (point_offsets.shape[0] - 1) // n_samples
    n_lines = origins.shape[0]
    k = neighbors.shape[1]
    grids = sample_grids(points, point_offsets, radius, cells)
    batch = (origins, dirs, points, point_offsets, radius, neighbors, mode, eps2)
    items_per_sample = np.empty(n_samples, dtype=np.int64)
    for b in range(n_samples):
        items_per_sample[b] = (line_offsets[b + 1] - line_offsets[b] + chunk - 1) // chunk
    n_items = 0
    for b in range(n_samples):
        n_items += items_per_sample[b]
    item_sample = np.empty(n_items, dtype=np.int64)
    item_first = np.empty(n_items, dtype=np.int64)
    item_stop = np.empty(n_items, dtype=np.int64)
    buffer_start = int_zeros(n_items + 1)
    item = 0
    for b in range(n_samples):
        for j in range(items_per_sample[b]):
            item_sample[item] = b
            item_first[item] = line_offsets[b] + j * chunk
            item_stop[item] = min(line_offsets[b + 1], item_first[item] + chunk)
            # Room for a few intersections per line and side; busier items are scanned twice.
            buffer_start[item + 1] = buffer_start[item] + 4 * (item_stop[item] - item_first[item]) + 16
            item += 1
    room = buffer_start[-1]
    buffer_anchor = np.empty(n_sides * room, dtype=np.int64)
    buffer_weight = np.empty((n_sides * room, k + 1))
    counts = int_zeros(n_sides * n_lines)
    item_total = np.empty((n_items, n_sides), dtype=np.int64)
    for item in numba.prange(n_items):
        rows = np.empty(n_sides, dtype=np.int64)
        stops = np.empty(n_sides, dtype=np.int64)
        for g in range(n_sides):
            rows[g] = g * room + buffer_start[item]
            stops[g] = g * room + buffer_start[item + 1]
        b = item_sample[item]
        first, stop = item_first[item], item_stop[item]
        item_total[item] = _scan_lines(
            batch, b, first, stop, cells[b], grids[b], counts, True, buffer_anchor, buffer_weight, rows, stops
        )
    offsets = np.empty(n_sides * n_lines + 1, dtype=np.int64)
    offsets[0] = 0
    for line in range(n_sides * n_lines):
        offsets[line + 1] = offsets[line] + counts[line]
    anchors = np.empty(offsets[-1], dtype=np.int64)
    weights = np.empty((offsets[-1], k + 1))
    for item in numba.prange(n_items):
        first, stop = item_first[item], item_stop[item]
        fits = True
        for g in range(n_sides):
            fits &= item_total[item, g] <= buffer_start[item + 1] - buffer_start[item]
        if fits:
            for g in range(n_sides):
                out, total = offsets[g * n_lines + first], item_total[item, g]
                begin = g * room + buffer_start[item]
                anchors[out : out + total] = buffer_anchor[begin : begin + total]
                weights[out : out + total] = buffer_weight[begin : begin + total]
        else:
            rows = np.empty(n_sides, dtype=np.int64)
            for g in range(n_sides):
                rows[g] = offsets[g * n_lines + first]
            b = item_sample[item]
            stops = rows + item_total[item]
            _scan_lines(batch, b, first, stop, cells[b], grids[b], counts, False, anchors, weights, rows, stops)
    return offsets, anchors, weights
