"""Compiled (numba) neighbourhoods of the line-intersection metric: the ``k`` nearest other
points of every point and its cylinder radius ``delta``, all clouds of a batch in one call.

The search is a uniform grid of about two points per cell, searched ring by ring outwards, run
cloud by cloud in numba's threads. It lives here rather than in :mod:`linereg.knn` because it
runs inside one compiled parallel kernel together with the radii (a KD-tree per cloud through
:func:`linereg.knn.knn_points` takes several times as long on the metric's clouds); the tests
compare it with :func:`linereg.knn.knn_points`.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
