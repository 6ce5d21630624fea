"""The two backends of the line-intersection metric agree, and the numba kernel's parallel
schedule never changes its result."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest
import torch

from linereg.losses import line_kernels
from linereg.losses.line_intersection import LineMetricOptions, line_intersection_metric
from linereg.se3 import transform_points
from tests.test_line_intersection import blob, lines_for, rigid

OPTIONS = {
    "convex": LineMetricOptions(),
    "candidates": LineMetricOptions(intersection="candidates"),
    "triplet": LineMetricOptions(intersection="triplet", distance_eps=2e-4),
    "pierce": LineMetricOptions.for_variant("linereg"),
    "authors": LineMetricOptions.for_variant("authors"),
    "live_weights": LineMetricOptions(detach_weights=False),
    "k3_no_weight": LineMetricOptions(k=3, line_weight=False, nu0=1.0),
    "box_sampling": LineMetricOptions(sampling="box_point_direction"),
    "cloud_points": LineMetricOptions(sampling="cloud_points", intersection="triplet"),
}


def padded_pair() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two samples, the second padded on both sides."""
    src = torch.stack([blob(220, 40), torch.cat([blob(180, 41), torch.full((40, 3), 5.0, dtype=torch.float64)])])
    tgt_b = transform_points(rigid([3, -4, 5], [0.04, 0.0, -0.02]), blob(200, 42))
    tgt = torch.stack([blob(230, 43), torch.cat([tgt_b, torch.zeros(30, 3, dtype=torch.float64)])])
    return src, tgt, torch.tensor([220, 180]), torch.tensor([230, 200])


def evaluate(options, backend, src, tgt, src_lengths=None, tgt_lengths=None, lines=None):
    leaf = src.clone().requires_grad_(True)
    result = line_intersection_metric(
        leaf,
        tgt,
        src_lengths,
        tgt_lengths,
        options=dataclasses.replace(options, backend=backend, num_lines=1500),
        generator=torch.Generator().manual_seed(11),
        lines=lines,
    )
    result.value.sum().backward()
    return result, leaf.grad


@pytest.mark.parametrize("name", list(OPTIONS))
def test_torch_backend_matches_numba(name):
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    numba_result, numba_grad = evaluate(OPTIONS[name], "numba", src, tgt, src_lengths, tgt_lengths)
    torch_result, torch_grad = evaluate(OPTIONS[name], "torch", src, tgt, src_lengths, tgt_lengths)
    assert numba_result.stats["lines_hit_both"] > 20
    torch.testing.assert_close(torch_result.value, numba_result.value, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(torch_grad, numba_grad, rtol=1e-8, atol=1e-12)
    assert numba_grad[1, 180:].abs().sum() == 0
    for key, value in numba_result.stats.items():
        assert torch_result.stats[key] == pytest.approx(value, rel=1e-12), key


def test_backends_agree_on_explicit_lines_of_different_counts():
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    lines = [lines_for(src[0], tgt[0], 700, seed=1), lines_for(src[1, :180], tgt[1, :200], 450, seed=2)]
    numba_result, numba_grad = evaluate(LineMetricOptions(), "numba", src, tgt, src_lengths, tgt_lengths, lines)
    torch_result, torch_grad = evaluate(LineMetricOptions(), "torch", src, tgt, src_lengths, tgt_lengths, lines)
    torch.testing.assert_close(torch_result.value, numba_result.value, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(torch_grad, numba_grad, rtol=1e-8, atol=1e-12)
    assert numba_result.stats["lines"] == pytest.approx((700 + 450) / 2)


def test_auto_backend_follows_the_device():
    options = LineMetricOptions()
    assert options.resolved_backend(torch.device("cpu")) == "numba"
    assert options.resolved_backend(torch.device("cuda", 0)) == "torch"
    assert LineMetricOptions(backend="numba").resolved_backend(torch.device("cuda")) == "numba"
    with pytest.raises(ValueError, match="backend must be one of auto, numba, torch"):
        LineMetricOptions(backend="cuda")


def kernel_inputs(mode: int):
    """One sample (two clouds sharing 900 lines) in the kernel's flat layout."""
    src, tgt = blob(300, 44), blob(260, 45)
    origins, dirs = lines_for(src, tgt, 900, seed=3)
    points = np.concatenate([src.numpy(), tgt.numpy()])
    neighbors = []
    radius = []
    for cloud in (src, tgt):
        dist = torch.cdist(cloud, cloud).fill_diagonal_(float("inf"))
        d, idx = dist.topk(2, largest=False)
        neighbors.append(idx.numpy())
        radius.append(np.full(len(cloud), 2.0 * float(d.mean())))  # wide: many hits per line
    nbr = np.concatenate(neighbors)
    if mode == line_kernels.MODE_CANDIDATES:
        nbr = np.ascontiguousarray(nbr[:, :0])
    return (
        origins,
        dirs,
        np.array([0, 900]),
        points,
        np.array([0, 300, 560]),
        np.concatenate(radius),
        nbr,
        mode,
        0.0,
        np.array([0.2]),
    )


@pytest.mark.parametrize("mode", [line_kernels.MODE_CANDIDATES, line_kernels.MODE_CONVEX, line_kernels.MODE_PIERCE])
def test_kernel_result_is_independent_of_chunks_and_threads(mode):
    inputs = kernel_inputs(mode)
    # One line per item overflows the per-item buffers of busy lines and takes the rescan path.
    reference = line_kernels.line_intersections(*inputs, 1)
    assert np.diff(reference[0]).max() > 4 + 16
    previous = numba.get_num_threads()
    try:
        for threads in {1, numba.config.NUMBA_NUM_THREADS}:
            numba.set_num_threads(threads)
            for chunk in (7, 64, 5000):
                offsets, anchors, weights = line_kernels.line_intersections(*inputs, chunk)
                np.testing.assert_array_equal(offsets, reference[0])
                np.testing.assert_array_equal(anchors, reference[1])
                np.testing.assert_array_equal(weights, reference[2])
    finally:
        numba.set_num_threads(previous)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_torch_backend_on_cuda_matches_numba_on_cpu():
    src, tgt, src_lengths, tgt_lengths = padded_pair()
    numba_result, numba_grad = evaluate(LineMetricOptions(), "numba", src, tgt, src_lengths, tgt_lengths)
    cuda_result, cuda_grad = evaluate(
        LineMetricOptions(), "auto", src.cuda(), tgt.cuda(), src_lengths.cuda(), tgt_lengths.cuda()
    )
    torch.testing.assert_close(cuda_result.value.cpu(), numba_result.value, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(cuda_grad.cpu(), numba_grad, rtol=1e-7, atol=1e-12)
