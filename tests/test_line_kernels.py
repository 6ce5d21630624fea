"""The numba kernels of the line metric against naive twins: the grid walk finds exactly the
intersections of an all-pairs test, and the compiled line sampler computes the paper's formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from linereg.losses import line_grid, line_kernels, lines
from tests.test_line_intersection import blob, lines_for


def naive_intersections(origins, dirs, points, radius, neighbors, mode, eps2):
    """Per line, the sorted anchors and their weights, testing every point (one cloud)."""
    rel = points[None] - origins[:, None]
    t = (rel * dirs[:, None]).sum(-1)
    d2 = np.maximum((rel * rel).sum(-1) - t * t, 0.0)
    dist = np.sqrt(d2 + eps2)
    result = []
    for line in range(len(origins)):
        hits = []
        for i in np.flatnonzero(d2[line] + eps2 < radius * radius):
            nbrs = neighbors[i]
            limit = np.full(len(nbrs), radius[i]) if mode == line_kernels.MODE_TRIPLET else radius[nbrs]
            if np.any(dist[line, nbrs] >= limit):
                continue
            members = dist[line, np.concatenate([[i], nbrs])]
            hits.append((i, members / members.sum()))
        result.append(hits)
    return result


def two_samples(mode):
    """Two samples with two clouds each, different sizes, line counts and per-point radii."""
    clouds = [blob(160, 60), blob(120, 61), blob(140, 62), blob(100, 63)]  # src_0, src_1, tgt_0, tgt_1
    line_sets = [lines_for(clouds[0], clouds[2], 300, seed=4), lines_for(clouds[1], clouds[3], 200, seed=5)]
    rng = np.random.default_rng(0)
    points, radius, neighbors = [], [], []
    for cloud in clouds:
        dist = torch.cdist(cloud, cloud).fill_diagonal_(float("inf"))
        d, idx = dist.topk(2, largest=False)
        points.append(cloud.numpy())
        radius.append(float(d.mean()) * rng.uniform(0.8, 2.5, len(cloud)))
        neighbors.append(idx.numpy() if mode != line_kernels.MODE_CANDIDATES else idx.numpy()[:, :0])
    return clouds, line_sets, points, radius, neighbors


@pytest.mark.parametrize("mode", [line_kernels.MODE_CANDIDATES, line_kernels.MODE_CONVEX, line_kernels.MODE_TRIPLET])
@pytest.mark.parametrize("cell_factor", [0.5, 4.0, 40.0])
def test_grid_walk_finds_exactly_the_all_pairs_intersections(mode, cell_factor):
    _, line_sets, points, radius, neighbors = two_samples(mode)
    eps2 = 1e-6 if mode == line_kernels.MODE_TRIPLET else 0.0
    cells = []
    for b in range(2):
        sample_points = np.concatenate([points[b], points[2 + b]])
        sample_radius = np.concatenate([radius[b], radius[2 + b]])
        cells.append(line_grid.grid_cell_size(sample_points, sample_radius, cell_factor, len(sample_points) / 2))
    offsets, anchors, weights = line_kernels.line_intersections(
        np.concatenate([o for o, _ in line_sets]),
        np.concatenate([d for _, d in line_sets]),
        np.array([0, 300, 500]),
        np.concatenate(points),
        np.concatenate([[0], np.cumsum([len(p) for p in points])]),
        np.concatenate(radius),
        np.ascontiguousarray(np.concatenate(neighbors)),
        mode,
        eps2,
        np.array(cells),
        64,
    )
    n_lines, found = 500, 0
    for side in range(2):
        for b in range(2):
            origins, dirs = line_sets[b]
            cloud = side * 2 + b
            expected = naive_intersections(origins, dirs, points[cloud], radius[cloud], neighbors[cloud], mode, eps2)
            first_line = side * n_lines + (0 if b == 0 else 300)
            for j, hits in enumerate(expected):
                rows = slice(offsets[first_line + j], offsets[first_line + j + 1])
                order = np.argsort(anchors[rows])
                np.testing.assert_array_equal(anchors[rows][order], [i for i, _ in hits])
                if hits:
                    np.testing.assert_allclose(weights[rows][order], [w for _, w in hits], rtol=1e-12, atol=0)
                found += len(hits)
    assert found > 200


def test_compiled_sphere_sampler_computes_the_papers_formula_on_the_same_draws():
    center, radius, n = np.array([0.3, -0.1, 0.2]), 1.7, 5000
    origins, dirs = lines._sphere(center, radius, n, torch.Generator().manual_seed(8))
    draws = torch.rand((4, n), generator=torch.Generator().manual_seed(8), dtype=torch.float64).numpy()
    ends = []
    for u_draw, alpha_draw in (draws[0:2], draws[2:4]):
        u, alpha = 2.0 * u_draw - 1.0, 2.0 * math.pi * alpha_draw
        rho = np.sqrt(np.clip(1.0 - u * u, 0.0, None))
        ends.append(np.stack([rho * np.cos(alpha), rho * np.sin(alpha), u], axis=1))
    chord = ends[1] - ends[0]
    np.testing.assert_allclose(origins, center + radius * ends[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(dirs, chord / np.linalg.norm(chord, axis=1, keepdims=True), rtol=0, atol=1e-15)


def test_compiled_sphere_sampler_gives_a_direction_for_coincident_points():
    draws = np.array([[0.5, 0.5, 1.0], [0.0, 0.0, 0.25], [0.5, 1.0, 0.0], [0.0, 0.25, 0.5]])
    origins, dirs, degenerate = lines._sphere_chords(draws, np.zeros(3), 2.0)
    np.testing.assert_array_equal(degenerate, [True, False, False])
    np.testing.assert_allclose(np.linalg.norm(dirs[1:], axis=1), 1.0)
    np.testing.assert_allclose(origins, 2.0 * np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), atol=1e-15)
