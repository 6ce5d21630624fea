"""The dilated grid of the line-intersection search (numba): every point ``p`` with radius ``r_p`` is
inserted into each cell of a uniform grid that its ball ``B(p, r_p)`` overlaps, built once per
call in ``O(N)``; one grid holds all clouds of a sample (:mod:`linereg.losses.line_kernels` walks
the lines through it).
"""

from __future__ import annotations

import math

import numba
import numpy as np

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


@numba.njit(cache=True)
def sample_grids(points, point_offsets, radius, cells):
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
