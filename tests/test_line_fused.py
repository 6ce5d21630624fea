"""The numba path's fused value and gradient (FusedLineValue) against the torch formula, the
numba grid kNN against brute force and its radii against the torch backend's."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest
import torch

from linereg.knn import knn_distances, knn_points
from linereg.losses import line_grid
from linereg.losses.line_intersection import LineMetricOptions, _checked_inputs
from linereg.losses.line_neighbors import cloud_neighborhoods
from linereg.losses.line_pairs import line_pairs, numba_plan, resolve_lines, stacked_points, torch_setups
from linereg.losses.line_value import FusedLineValue, fused_path, fused_values, line_values
from linereg.se3 import transform_points
from tests.test_line_backends import padded_pair
from tests.test_line_intersection import blob, rigid

FUSED_OPTIONS = {
    "paper": LineMetricOptions(),
    "candidates": LineMetricOptions(intersection="candidates"),
    "triplet": LineMetricOptions(intersection="triplet", distance_eps=2e-4),
    "pierce": LineMetricOptions.for_variant("linereg"),
    "squared_max_hits": LineMetricOptions(welsch_input="squared", nu0=1.0, max_hits=4),
    "k3_no_weight_fixed_nu": LineMetricOptions(k=3, line_weight=False, nu=0.05),
}


def both_paths(options, src, tgt, src_lengths=None, tgt_lengths=None):
    """``(value, stats, grad)`` of the fused path and of the torch formula on the same lines."""
    results = []
    for fused in (True, False):
        leaf = src.clone().requires_grad_(True)
        work = _checked_inputs(leaf, tgt, src_lengths, tgt_lengths, options)
        generator = torch.Generator().manual_seed(5)
        if fused:
            value, stats = fused_values(*work, options, generator, None)
        else:
            value, stats = line_values(line_pairs(*work, options, generator, None), options, work[0])
        value.sum().backward()
        results.append((value, stats, leaf.grad))
    return results


@pytest.mark.parametrize("name", list(FUSED_OPTIONS))
def test_fused_path_matches_the_torch_formula(name):
    options = dataclasses.replace(FUSED_OPTIONS[name], num_lines=1500, backend="numba")
    assert fused_path(options, torch.device("cpu"))
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    (value, stats, grad), (ref_value, ref_stats, ref_grad) = both_paths(options, src, tgt, src_lengths, tgt_lengths)
    assert ref_stats[:, 1].min() > 20
    torch.testing.assert_close(value, ref_value, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(stats, ref_stats, rtol=1e-12, atol=0.0)
    assert grad[1, 180:].abs().sum() == 0 and grad.abs().sum() > 0


def test_fused_path_in_float32_matches_the_torch_formula_to_float32_rounding():
    src = transform_points(rigid([5, -3, 2], [0.04, 0.0, 0.02]), blob(400, 3)).float()
    tgt = blob(380, 4).float()
    options = LineMetricOptions(num_lines=2000, backend="numba")
    (value, _, grad), (ref_value, _, ref_grad) = both_paths(options, src[None], tgt[None])
    assert value.dtype == grad.dtype == torch.float32
    torch.testing.assert_close(value, ref_value, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-3, atol=1e-6 * float(ref_grad.abs().max()))


def test_settings_outside_the_fused_path_take_the_torch_formula():
    cpu = torch.device("cpu")
    assert not fused_path(LineMetricOptions(detach_weights=False), cpu)
    assert not fused_path(LineMetricOptions.for_variant("authors"), cpu)
    assert not fused_path(LineMetricOptions(backend="torch"), cpu)
    assert fused_path(LineMetricOptions(intersection="pierce", detach_weights=False), cpu)


@pytest.mark.parametrize("intersection", ["convex", "pierce", "candidates"])
def test_fused_gradient_passes_gradcheck_for_a_fixed_plan(intersection):
    # With the plan (intersections, weights) and nu fixed the value is a smooth function of the
    # points, so finite differences must agree with the gradient the kernel writes.
    options = LineMetricOptions(num_lines=300, intersection=intersection, nu=0.3, backend="numba")
    src = transform_points(rigid([6, -4, 3], [0.05, 0.0, -0.03]), blob(60, 8))[None]
    tgt = torch.stack([blob(70, 9)])
    work = _checked_inputs(src, tgt, None, None, options)
    lines = resolve_lines(*work, options, torch.Generator().manual_seed(1), None)
    plan = numba_plan(*work, lines, options)
    assert len(plan.anchors) > 40

    def value(s, t):
        return FusedLineValue.apply(s, t, plan, options)[0]

    inputs = (src.clone().requires_grad_(True), tgt.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(value, inputs, eps=1e-7, atol=1e-7, rtol=1e-5)


def test_a_sample_without_kept_lines_is_zero_with_zero_gradient_on_the_fused_path():
    src = blob(100, 10)[None].requires_grad_(True)
    tgt = (blob(100, 11) + 50.0)[None]
    options = LineMetricOptions(num_lines=500, sampling="box_point_direction", backend="numba")
    work = _checked_inputs(src, tgt, None, None, options)
    value, stats = fused_values(*work, options, torch.Generator().manual_seed(0), None)
    value.sum().backward()
    assert stats[0, 1] == 0 and value.item() == 0.0 and src.grad.abs().sum() == 0


def brute_force_knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distances and indices of the ``k`` nearest other points, and whether each row's first
    ``k + 1`` distances are all distinct (no tie can reorder it)."""
    dist = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    ordered = np.sort(dist, axis=1)[:, : k + 1]
    distinct = (np.diff(ordered, axis=1) > 0).all(axis=1)
    return ordered[:, :k], np.argsort(dist, axis=1, kind="stable")[:, :k], distinct


def test_grid_knn_matches_brute_force_on_awkward_clouds():
    rng = np.random.default_rng(0)
    clouds = [
        blob(500, 12).numpy(),
        rng.normal(size=(300, 3)) * [100.0, 1.0, 0.01],  # very flat and long
        np.c_[rng.normal(size=(200, 2)), np.zeros(200)],  # exactly planar
        np.repeat(rng.normal(size=(40, 3)), 3, axis=0),  # every point three times
        np.concatenate([rng.normal(size=(50, 3)) * 1e-6, rng.normal(size=(50, 3)) * 1e3]),  # two scales
        np.zeros((6, 3)),  # one point, six times
    ]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])])
    for k in (1, 2, 3):
        index, dist, _ = cloud_neighborhoods(np.concatenate(clouds), offsets, k, False, 1.0)
        for c, cloud in enumerate(clouds):
            ref_dist, ref_index, distinct = brute_force_knn(cloud, k)
            rows = slice(offsets[c], offsets[c + 1])
            np.testing.assert_allclose(dist[rows], ref_dist, rtol=1e-12, atol=0.0)
            assert (index[rows] != np.arange(len(cloud))[:, None]).all()
            # Indices agree wherever the distances do not tie.
            found = np.linalg.norm(cloud[index[rows]] - cloud[:, None], axis=-1)
            np.testing.assert_allclose(found, ref_dist, rtol=1e-12, atol=0.0)
            if c < 3:
                assert distinct.mean() > 0.9
            np.testing.assert_array_equal(index[rows][distinct], ref_index[distinct])


def test_grid_knn_matches_the_shared_knn():
    clouds = [blob(3000, 13).numpy(), blob(40, 14).numpy()]  # the KD-tree and the dense path
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])])
    index, dist, _ = cloud_neighborhoods(np.concatenate(clouds), offsets, 3, False, 1.0)
    for c, cloud in enumerate(clouds):
        points = torch.from_numpy(cloud)
        rows = slice(offsets[c], offsets[c + 1])
        np.testing.assert_array_equal(index[rows], knn_points(points, points, 3, exclude_self=True).idx.numpy())
        np.testing.assert_allclose(dist[rows], knn_distances(points, points, 3, exclude_self=True).numpy(), rtol=1e-12)


@pytest.mark.parametrize("intersection", ["convex", "triplet"])
def test_compiled_radii_match_the_torch_backends(intersection):
    options = LineMetricOptions(intersection=intersection, k=3, delta_factor=0.7)
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    _, valids, radii, neighbors = torch_setups(src, tgt, src_lengths, tgt_lengths, options)
    lengths = np.concatenate([src_lengths.numpy(), tgt_lengths.numpy()])
    points = stacked_points([src, tgt], lengths)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    index, _, radius = cloud_neighborhoods(points, offsets, 3, intersection == "triplet", 0.7)
    for side, valid in enumerate(valids):
        for b in range(2):
            rows = slice(offsets[2 * side + b], offsets[2 * side + b + 1])
            np.testing.assert_allclose(radius[rows], radii[side][b][valid[b]].numpy(), rtol=1e-13, atol=0.0)
            np.testing.assert_array_equal(index[rows], neighbors[side][b][valid[b]].numpy())
    if intersection == "convex":
        assert len(np.unique(radius[offsets[0] : offsets[1]])) == 1
    else:
        assert len(np.unique(radius[offsets[0] : offsets[1]])) > 100


def test_cell_sizes_of_a_batch_are_those_of_each_sample_alone():
    rng = np.random.default_rng(3)
    clouds = [rng.normal(size=(n, 3)) * scale for n, scale in ((50, 1.0), (80, 3.0), (60, 1.0), (40, 3.0))]
    radius = [rng.uniform(0.05, 0.2, len(c)) for c in clouds]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])])
    cells = line_grid.sample_cell_sizes(np.concatenate(clouds), offsets, np.concatenate(radius), 2, 4.0)
    for b in range(2):  # sample b: clouds b (source) and 2 + b (target)
        alone = line_grid.grid_cell_size(
            np.concatenate([clouds[b], clouds[2 + b]]),
            np.concatenate([radius[b], radius[2 + b]]),
            4.0,
            (len(clouds[b]) + len(clouds[2 + b])) / 2,
        )
        assert cells[b] == alone
    assert cells[1] > 2 * cells[0]


def test_fused_value_and_gradient_do_not_depend_on_the_number_of_threads():
    options = LineMetricOptions(num_lines=1500, backend="numba")
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    previous = numba.get_num_threads()
    results = []
    try:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            results.append(both_paths(options, src, tgt, src_lengths, tgt_lengths)[0])
    finally:
        numba.set_num_threads(previous)
    for value, stats, grad in results[1:]:
        assert torch.equal(value, results[0][0]) and torch.equal(grad, results[0][2])
        assert torch.equal(stats, results[0][1])
