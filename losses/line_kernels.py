"""Compiled (numba) index kernels of the line-intersection metric.

The kernels decide *which* points form each intersection and *which* intersections are matched
(indices and detached convex weights). :func:`welsch_lines` then computes the value of the
paper's per-line reduction and, since the weights are constants, its gradient w.r.t. every point
in closed form; the loss wraps it in a ``torch.autograd.Function``. For the other settings the
loss gathers the points with torch and autograd differentiates the value. The k nearest
neighbours of the points and their radii come from :func:`cloud_neighborhoods` (a uniform grid,
searched ring by ring).

Candidate search, without ever testing all point-line pairs:

* every point ``p`` with radius ``r_p`` is inserted into each cell of a uniform grid that its
  ball ``B(p, r_p)`` overlaps (a "dilated" grid, built once per call in ``O(N)``); one grid holds
  both clouds of a sample (source and target share their lines), so each line is walked once;
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


@numba.njit(cache=True)
def grid_cell_size(points, radius, cell_factor, n_points):
    """Cell edge of the dilated grid over ``points (P, 3)`` (one sample's clouds together):
    ``cell_factor * (n_points / 1024)^(1/6)`` times the median radius, bounded so the grid has at
    most ``max(4096, 8 P)`` cells (memory linear in ``P``); ``n_points`` is the size of one cloud.

    The growth with ``n_points`` balances the two costs of a line: cells crossed (``~ 1 / cell``)
    and points tested (``~ N * cell^2`` on a surface), whose optimum is ``cell ~ N^(-1/3)``, while
    the radius shrinks as ``N^(-1/2)`` (``scripts/bench_loss.py`` shows the effect).
    """
    volume = 1.0
    longest = 0.0
    for a in range(3):
        extent = points[:, a].max() - points[:, a].min() + 2.0 * radius.max()
        volume *= max(extent, 1e-300)
        longest = max(longest, extent)
    cap = max(_MIN_GRID_CELLS, _GRID_CELL_CAP_PER_POINT * points.shape[0])
    floor = max((volume / cap) ** (1.0 / 3.0), longest / 1024.0)
    factor = cell_factor * (n_points / 1024.0) ** (1.0 / 6.0)
    return max(factor * np.median(radius), floor, np.finfo(np.float64).tiny)


@numba.njit(cache=True)
def sample_cell_sizes(points, point_offsets, radius, n_samples, cell_factor):
    """``(B,)`` :func:`grid_cell_size` of every sample, its clouds (``G`` sides, side-major as in
    :func:`line_intersections`) together; ``n_points`` is the mean size of its clouds."""
    n_sides = (point_offsets.shape[0] - 1) // n_samples
    cells = np.empty(n_samples)
    for b in range(n_samples):
        size = 0
        for g in range(n_sides):
            size += point_offsets[g * n_samples + b + 1] - point_offsets[g * n_samples + b]
        sample_points = np.empty((size, 3))
        sample_radius = np.empty(size)
        row = 0
        for g in range(n_sides):
            for i in range(point_offsets[g * n_samples + b], point_offsets[g * n_samples + b + 1]):
                sample_points[row] = points[i]
                sample_radius[row] = radius[i]
                row += 1
        cells[b] = grid_cell_size(sample_points, sample_radius, cell_factor, size / n_sides)
    return cells


@numba.njit(cache=True, inline="always")
def _ball_cells(points, radius, i, grid_min, dims, cell):
    """Cell index range ``lo_x, hi_x, lo_y, hi_y, lo_z, hi_z`` (inclusive) overlapped by the
    bounding box of ``B(points[i], radius[i])``."""
    r = radius[i]
    lx = min(dims[0] - 1, max(0, int((points[i, 0] - r - grid_min[0]) / cell)))
    hx = min(dims[0] - 1, max(0, int((points[i, 0] + r - grid_min[0]) / cell)))
    ly = min(dims[1] - 1, max(0, int((points[i, 1] - r - grid_min[1]) / cell)))
    hy = min(dims[1] - 1, max(0, int((points[i, 1] + r - grid_min[1]) / cell)))
    lz = min(dims[2] - 1, max(0, int((points[i, 2] - r - grid_min[2]) / cell)))
    hz = min(dims[2] - 1, max(0, int((points[i, 2] + r - grid_min[2]) / cell)))
    return lx, hx, ly, hy, lz, hz


@numba.njit(cache=True)
def build_dilated_grid(points, radius, starts, stops, cell):
    """CSR grid over the rows ``starts[g]:stops[g]`` of ``points`` (the clouds of one sample):
    cell ``c`` holds entries ``cell_start[c]:cell_start[c+1]``, each a copy of a point whose
    ``radius``-ball overlaps the cell, in cloud order then row order.

    Returns ``(grid_min (3,), dims (3,) int64, cell_start (C+1,), entry_rows (S,) int64,
    entry_xyzr (4, S))``: the row of each entry in ``points`` and its coordinates and squared
    radius (one row each), stored in cell order so that a line walk reads memory sequentially.
    """
    grid_min = np.full(3, np.inf)
    grid_max = np.full(3, -np.inf)
    r_max = 0.0
    for g in range(starts.shape[0]):
        for i in range(starts[g], stops[g]):
            r_max = max(r_max, radius[i])
            for a in range(3):
                grid_min[a] = min(grid_min[a], points[i, a])
                grid_max[a] = max(grid_max[a], points[i, a])
    dims = np.empty(3, dtype=np.int64)
    for a in range(3):
        grid_min[a] -= r_max
        dims[a] = max(1, math.ceil((grid_max[a] + r_max - grid_min[a]) / cell))
    counts = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    for g in range(starts.shape[0]):
        for i in range(starts[g], stops[g]):
            lx, hx, ly, hy, lz, hz = _ball_cells(points, radius, i, grid_min, dims, cell)
            for x in range(lx, hx + 1):
                for y in range(ly, hy + 1):
                    for z in range(lz, hz + 1):
                        counts[(x * dims[1] + y) * dims[2] + z + 1] += 1
    cell_start = np.cumsum(counts)
    fill = cell_start[:-1].copy()
    entry_rows = np.empty(cell_start[-1], dtype=np.int64)
    entry_xyzr = np.empty((4, cell_start[-1]))
    for g in range(starts.shape[0]):
        for i in range(starts[g], stops[g]):
            lx, hx, ly, hy, lz, hz = _ball_cells(points, radius, i, grid_min, dims, cell)
            for x in range(lx, hx + 1):
                for y in range(ly, hy + 1):
                    for z in range(lz, hz + 1):
                        c = (x * dims[1] + y) * dims[2] + z
                        s = fill[c]
                        fill[c] = s + 1
                        entry_rows[s] = i
                        entry_xyzr[0, s] = points[i, 0]
                        entry_xyzr[1, s] = points[i, 1]
                        entry_xyzr[2, s] = points[i, 2]
                        entry_xyzr[3, s] = radius[i] * radius[i]
    return grid_min, dims, cell_start, entry_rows, entry_xyzr


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
def _scan_lines(
    sample,
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
    cell,
    grid,
    counts,
    count_lines,
    out_anchor,
    out_weight,
    out_row,
    out_stop,
):
    """Intersections of lines ``first:stop`` of sample ``sample`` with each of its clouds.

    Each line walks the sample's grid once (all its clouds together); the intersections of line
    ``l`` with side ``g`` are written from ``out_row[g]`` on (rows below ``out_stop[g]`` only; the
    others are only counted) and, if ``count_lines``, counted in ``counts[g * L + l]``. Returns
    the ``(G,)`` totals.
    """
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
def _float_zeros(shape):
    """``np.zeros(shape)``, compiled apart: written inside a ``parallel=True`` kernel, an
    allocation (or any array expression) becomes a parallel region of its own, and each region
    wakes the threads; the kernels keep parallel regions to their ``prange`` loops."""
    return np.zeros(shape)


@numba.njit(cache=True)
def _int_zeros(shape):
    """``np.zeros(shape, int64)``, compiled apart (see :func:`_float_zeros`)."""
    return np.zeros(shape, dtype=np.int64)


@numba.njit(cache=True)
def _sample_grids(points, point_offsets, radius, cells):
    """The dilated grid of every sample (its clouds together), as a list."""
    n_samples = cells.shape[0]
    n_sides = (point_offsets.shape[0] - 1) // n_samples
    grids = []
    for b in range(n_samples):
        starts = np.empty(n_sides, dtype=np.int64)
        stops = np.empty(n_sides, dtype=np.int64)
        for g in range(n_sides):
            starts[g] = point_offsets[g * n_samples + b]
            stops[g] = point_offsets[g * n_samples + b + 1]
        grids.append(build_dilated_grid(points, radius, starts, stops, cells[b]))
    return grids


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
    grids = _sample_grids(points, point_offsets, radius, cells)
    items_per_sample = np.empty(n_samples, dtype=np.int64)
    for b in range(n_samples):
        items_per_sample[b] = (line_offsets[b + 1] - line_offsets[b] + chunk - 1) // chunk
    n_items = 0
    for b in range(n_samples):
        n_items += items_per_sample[b]
    item_sample = np.empty(n_items, dtype=np.int64)
    item_first = np.empty(n_items, dtype=np.int64)
    item_stop = np.empty(n_items, dtype=np.int64)
    buffer_start = _int_zeros(n_items + 1)
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
    counts = _int_zeros(n_sides * n_lines)
    item_total = np.empty((n_items, n_sides), dtype=np.int64)
    for item in numba.prange(n_items):
        rows = np.empty(n_sides, dtype=np.int64)
        stops = np.empty(n_sides, dtype=np.int64)
        for g in range(n_sides):
            rows[g] = g * room + buffer_start[item]
            stops[g] = g * room + buffer_start[item + 1]
        b = item_sample[item]
        item_total[item] = _scan_lines(
            b,
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
            cells[b],
            grids[b],
            counts,
            True,
            buffer_anchor,
            buffer_weight,
            rows,
            stops,
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
            _scan_lines(
                b,
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
                cells[b],
                grids[b],
                counts,
                False,
                anchors,
                weights,
                rows,
                rows + item_total[item],
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
    value = _float_zeros(n_samples)
    scale = _float_zeros(n_samples)
    counts = _int_zeros((n_samples, 5))
    two_c = _float_zeros(n_samples)
    per_line = _float_zeros(n_samples)
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
    hit_grad = _float_zeros((anchors.shape[0], 3))
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
    grad = _float_zeros(points.shape)
    for c in numba.prange(point_offsets.shape[0] - 1):
        for h in range(offsets[line_offsets[c]], offsets[line_offsets[c + 1]]):
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


@numba.njit(cache=True)
def _cloud_radius(points, index, dist, triplet, delta_factor, out):
    """Cylinder radius ``delta`` of every point of one cloud from its ``k`` nearest neighbours:
    ``delta_factor`` times the cloud's mean neighbour distance ``d_nei`` (one value for the
    cloud), or for ``triplet`` the locally adaptive ``delta_factor`` times the mean pairwise
    spacing of the point and its neighbours."""
    n, k = index.shape
    if not triplet:
        total = 0.0
        for i in range(n):
            total += dist[i].sum() / k
        out[:] = delta_factor * (total / n)
        return
    pairs = k * (k + 1) / 2
    for i in range(n):
        spacing = dist[i].sum()
        for a in range(k):
            for b in range(a + 1, k):
                d = 0.0
                for axis in range(3):
                    diff = points[index[i, a], axis] - points[index[i, b], axis]
                    d += diff * diff
                spacing += math.sqrt(d)
        out[i] = delta_factor * spacing / pairs


@numba.njit(cache=True, parallel=True)
def cloud_neighborhoods(points, point_offsets, k, triplet, delta_factor):
    """The ``k`` nearest other points of every point and its cylinder radius, cloud by cloud
    (clouds in parallel).

    Args:
        points: ``(N, 3)`` float64, the clouds back to back.
        point_offsets: ``(C+1,)`` int64 point range of each cloud (each with more than ``k`` points).
        k: neighbours per point.
        triplet: radius of ``MODE_TRIPLET`` (per point) instead of the per-cloud ``delta``.
        delta_factor: ``delta = delta_factor * d_nei`` (see :func:`_cloud_radius`).

    Returns:
        ``index (N, k)`` int64 cloud-local indices and ``dist (N, k)`` float64 Euclidean
        distances, ascending (a point's own index is never among its neighbours, its duplicates
        are), and ``radius (N,)`` float64.
    """
    index = np.empty((points.shape[0], k), dtype=np.int64)
    dist = np.empty((points.shape[0], k))
    radius = np.empty(points.shape[0])
    for c in numba.prange(point_offsets.shape[0] - 1):
        p0, p1 = point_offsets[c], point_offsets[c + 1]
        _cloud_knn(points[p0:p1], k, index[p0:p1], dist[p0:p1])
        _cloud_radius(points[p0:p1], index[p0:p1], dist[p0:p1], triplet, delta_factor, radius[p0:p1])
    return index, dist, radius
