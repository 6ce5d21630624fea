"""Tests of the sparse line-intersection metric against the dense reference and its properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from linereg.losses import build_loss
from linereg.losses.line_intersection import LineIntersectionLoss, LineMetricOptions, line_intersection_metric
from linereg.losses.lines import SAMPLERS, sample_lines
from linereg.se3 import euler_to_rotmat, rt_to_matrix, transform_points
from linereg.structures import PairBatch, RegistrationOutput
from tests.line_reference import dense_line_metric


def blob(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """An asymmetric closed surface: a bumpy ellipsoid sampled with ``n`` points."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=g, dtype=dtype)
    x = x / x.norm(dim=1, keepdim=True)
    bump = 1.0 + 0.25 * torch.sin(3.0 * x[:, 0]) * torch.cos(2.0 * x[:, 1])
    return x * bump[:, None] * torch.tensor([1.4, 1.0, 0.7], dtype=dtype)


def rigid(angles_deg, t, dtype=torch.float64) -> torch.Tensor:
    R = euler_to_rotmat(torch.tensor(angles_deg, dtype=dtype) * math.pi / 180.0)
    return rt_to_matrix(R, torch.tensor(t, dtype=dtype))


def lines_for(src, tgt, n, seed, sampling="sphere"):
    return sample_lines(src, tgt, n, torch.Generator().manual_seed(seed), sampling=sampling)


CASES = [
    LineMetricOptions(),
    LineMetricOptions(intersection="candidates"),
    LineMetricOptions(line_weight=False, nu0=1.0),
    LineMetricOptions(k=3, delta_factor=1.2),
    LineMetricOptions.for_variant("authors"),
    LineMetricOptions(detach_weights=False),
    LineMetricOptions.for_variant("linereg"),
]


@pytest.mark.parametrize(
    "options", CASES, ids=["paper", "insec1", "no_weight", "k3", "authors", "live_weights", "linereg"]
)
def test_sparse_matches_dense_values_and_gradients(options):
    src0 = blob(150, 0)
    tgt = transform_points(rigid([4, -3, 6], [0.05, 0.0, -0.03]), blob(180, 1))
    origins, dirs = lines_for(src0, tgt, 300, seed=7, sampling=options.sampling)
    src_sparse = src0.clone().requires_grad_(True)
    src_dense = src0.clone().requires_grad_(True)
    sparse = line_intersection_metric(src_sparse[None], tgt[None], options=options, lines=[(origins, dirs)])
    dense = dense_line_metric(src_dense, tgt, origins, dirs, options)
    assert sparse.stats["lines_hit_both"] > 10
    torch.testing.assert_close(sparse.value[0], dense, rtol=1e-10, atol=1e-12)
    sparse.value.sum().backward()
    dense.backward()
    torch.testing.assert_close(src_sparse.grad, src_dense.grad, rtol=1e-8, atol=1e-12)
    assert src_sparse.grad.abs().sum() > 0


def test_zero_at_alignment():
    cloud = blob(400, 2)
    src = cloud.clone().requires_grad_(True)
    result = line_intersection_metric(src[None], cloud[None], generator=torch.Generator().manual_seed(0))
    assert result.stats["lines_hit_both"] > 100
    assert result.value.item() == 0.0
    result.value.sum().backward()
    assert torch.all(src.grad == 0)


def test_grows_with_misalignment():
    cloud = blob(600, 3)
    means = []
    for angle in (2.0, 8.0, 25.0):
        values = []
        for seed in range(4):
            moved = transform_points(rigid([angle, 0.5 * angle, 0.0], [0.0, 0.0, 0.0]), cloud)
            options = LineMetricOptions(num_lines=3000, nu=0.05)
            values.append(
                line_intersection_metric(
                    moved[None], cloud[None], options=options, generator=torch.Generator().manual_seed(seed)
                ).value.item()
            )
        means.append(np.mean(values))
    assert means[0] < means[1] < means[2], means


def test_invariant_to_a_common_rigid_motion():
    src = blob(300, 4)
    tgt = transform_points(rigid([5, 2, -4], [0.1, 0.0, 0.05]), blob(300, 5))
    origins, dirs = lines_for(src, tgt, 2000, seed=1)
    motion = rigid([30, -20, 50], [0.3, -0.2, 0.7])
    R, t = motion[:3, :3].numpy(), motion[:3, 3].numpy()
    before = line_intersection_metric(src[None], tgt[None], lines=[(origins, dirs)])
    after = line_intersection_metric(
        transform_points(motion, src)[None],
        transform_points(motion, tgt)[None],
        lines=[(origins @ R.T + t, dirs @ R.T)],
    )
    torch.testing.assert_close(before.value, after.value, rtol=1e-9, atol=1e-12)
    assert before.stats["lines_hit_both"] == after.stats["lines_hit_both"] > 50


@pytest.mark.parametrize("intersection", ["candidates", "convex"])
def test_finite_difference_gradient_of_a_translation(intersection):
    """d(metric)/d(translation) against central differences (fixed lines, fixed nu, and the
    convex weights differentiated so that the analytic gradient is the full one)."""
    src = blob(200, 6)
    tgt = transform_points(rigid([3, 1, -2], [0.02, -0.01, 0.03]), blob(220, 7))
    origins, dirs = lines_for(src, tgt, 1500, seed=3)
    options = LineMetricOptions(nu=0.05, intersection=intersection, detach_weights=False)

    def value(shift: torch.Tensor) -> torch.Tensor:
        return line_intersection_metric((src + shift)[None], tgt[None], options=options, lines=[(origins, dirs)]).value[
            0
        ]

    shift = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    value(shift).backward()
    eps = 1e-7
    numeric = torch.stack([(value(eps * e) - value(-eps * e)) / (2 * eps) for e in torch.eye(3, dtype=torch.float64)])
    torch.testing.assert_close(shift.grad, numeric, rtol=1e-4, atol=1e-6)


def test_batched_equals_per_sample():
    srcs = [blob(200, 10), blob(200, 11)]
    tgts = [transform_points(rigid([2, 3, 4], [0.0, 0.05, 0.0]), blob(250, 12)), blob(250, 13)]
    lines = [lines_for(s, t, 800, seed=i) for i, (s, t) in enumerate(zip(srcs, tgts, strict=True))]
    batched = line_intersection_metric(torch.stack(srcs), torch.stack(tgts), lines=lines)
    single = [
        line_intersection_metric(s[None], t[None], lines=[ln]).value[0]
        for s, t, ln in zip(srcs, tgts, lines, strict=True)
    ]
    torch.testing.assert_close(batched.value, torch.stack(single))


def test_padded_batch_uses_lengths():
    src, tgt = blob(200, 14), blob(230, 15)
    lines = [lines_for(src, tgt, 800, seed=0)]
    padded_src = torch.cat([src, torch.full((40, 3), 9.0, dtype=src.dtype)])
    reference = line_intersection_metric(src[None], tgt[None], lines=lines).value
    padded = line_intersection_metric(
        padded_src[None], tgt[None], torch.tensor([200]), torch.tensor([230]), lines=lines
    ).value
    torch.testing.assert_close(padded, reference)


def test_deterministic_with_a_seed():
    src, tgt = blob(300, 16).float(), blob(300, 17).float()
    batch = PairBatch(src_xyz=src[None], tgt_xyz=tgt[None])
    output = RegistrationOutput(transforms=[torch.eye(4)[None]])
    first = LineIntersectionLoss(seed=5, num_lines=2000)(output, batch).total
    second = LineIntersectionLoss(seed=5, num_lines=2000)(output, batch).total
    other = LineIntersectionLoss(seed=6, num_lines=2000)(output, batch).total
    assert first.item() == second.item()
    assert first.item() != other.item()


@pytest.mark.parametrize("sampling", SAMPLERS)
def test_every_sampler_gives_unit_lines_near_the_clouds(sampling):
    src, tgt = blob(200, 18), blob(200, 19) + 0.3
    origins, dirs = lines_for(src, tgt, 1000, seed=2, sampling=sampling)
    assert origins.shape == dirs.shape and origins.shape[1] == 3 and 0 < len(origins) <= 1000
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-12)
    # Distance from the clouds' centre to each line is bounded by the covering sphere.
    center = torch.cat([src, tgt]).mean(0).numpy()
    rel = center - origins
    dist = np.linalg.norm(rel - (rel * dirs).sum(1, keepdims=True) * dirs, axis=1)
    assert np.median(dist) < 3.0


@pytest.mark.parametrize(
    "overrides",
    [{"sampling": s} for s in SAMPLERS]
    + [{"intersection": i} for i in ("convex", "candidates", "triplet", "pierce")]
    + [{"variant": "authors"}, {"variant": "linereg"}],
)
def test_every_configuration_runs_and_is_differentiable(overrides):
    src = blob(300, 20).float().requires_grad_(True)
    tgt = transform_points(rigid([5, 5, 5], [0.05, 0.05, 0.0]), blob(300, 21)).float()
    variant = overrides.pop("variant", "paper")
    options = LineMetricOptions.for_variant(variant, num_lines=3000, **overrides)
    result = line_intersection_metric(src[None], tgt[None], options=options, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(result.value).all() and result.value.item() > 0
    result.value.sum().backward()
    assert torch.isfinite(src.grad).all() and src.grad.abs().sum() > 0


def test_lines_that_miss_give_zero_with_zero_gradient():
    src = blob(100, 22).requires_grad_(True)
    far = [(np.array([[100.0, 100.0, 100.0]] * 5), np.array([[1.0, 0.0, 0.0]] * 5))]
    result = line_intersection_metric(src[None], blob(100, 23)[None], lines=far)
    assert result.value.item() == 0.0
    assert result.stats["lines_hit_both"] == 0
    result.value.sum().backward()
    assert torch.all(src.grad == 0)


def test_all_identical_points_give_a_defined_zero():
    same = torch.ones(50, 3, dtype=torch.float64, requires_grad=True)
    result = line_intersection_metric(same[None], blob(100, 24)[None], generator=torch.Generator().manual_seed(0))
    assert result.value.item() == 0.0 and result.stats["intersections_src"] == 0
    result.value.sum().backward()
    assert torch.isfinite(same.grad).all()


@pytest.mark.parametrize(
    ("src", "message"),
    [
        (torch.full((1, 10, 3), float("nan")), "NaN"),
        (torch.zeros(1, 10, 2), r"\(B, N, 3\)"),
        (torch.zeros(10, 3), r"\(B, N, 3\)"),
        (torch.zeros(1, 2, 3), "at least 3"),
        (torch.zeros(1, 0, 3), "at least 3"),
    ],
)
def test_bad_input_raises_a_clear_error(src, message):
    with pytest.raises(ValueError, match=message):
        line_intersection_metric(src, torch.rand(1, 20, 3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sampling": "grid"}, "sampling"),
        ({"intersection": "x"}, "intersection"),
        ({"nu0": 0}, "nu0"),
        ({"num_lines": 0}, "num_lines"),
    ],
)
def test_bad_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LineMetricOptions(**kwargs)


def test_registry_builds_and_rejects_unknown_options():
    loss = build_loss({"name": "line_intersection", "num_lines": 500, "variant": "authors", "seed": 1})
    assert isinstance(loss, LineIntersectionLoss) and not loss.needs_gt
    assert loss.options.intersection == "triplet" and loss.options.num_lines == 500
    with pytest.raises(TypeError, match="num_line"):
        build_loss({"name": "line_intersection", "num_line": 500})


def test_unsupervised_loss_never_reads_ground_truth():
    src, tgt = blob(300, 25).float(), blob(300, 26).float()
    output = RegistrationOutput(transforms=[torch.eye(4)[None]])
    with_gt = PairBatch(src_xyz=src[None], tgt_xyz=tgt[None], gt_transform=torch.eye(4)[None])
    without_gt = PairBatch(src_xyz=src[None], tgt_xyz=tgt[None])
    seen = []

    class Spy(LineIntersectionLoss):
        def compute(self, output, batch):
            seen.append(batch.gt_transform)
            return super().compute(output, batch)

    a = Spy(seed=0, num_lines=1000)(output, with_gt).total
    b = Spy(seed=0, num_lines=1000)(output, without_gt).total
    assert seen == [None, None]
    assert a.item() == b.item()


def test_iteration_discount_weights_each_estimate():
    src, tgt = blob(300, 27).float(), blob(300, 28).float()
    batch = PairBatch(src_xyz=src[None], tgt_xyz=tgt[None])
    T1 = rigid([10, 0, 0], [0, 0, 0]).float()[None]
    T2 = torch.eye(4)[None]
    two = LineIntersectionLoss(seed=0, num_lines=1000, nu=0.05)(RegistrationOutput(transforms=[T1, T2]), batch).total
    first = LineIntersectionLoss(seed=0, num_lines=1000, nu=0.05)(RegistrationOutput(transforms=[T1]), batch).total
    loss = LineIntersectionLoss(seed=0, num_lines=1000, nu=0.05)
    loss.metric(transform_points(T1, src[None]), tgt[None])
    second = loss(RegistrationOutput(transforms=[T2]), batch).total
    torch.testing.assert_close(two, 0.5 * first + second)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    src, tgt = blob(300, 29).float(), blob(300, 30).float()
    lines = [lines_for(src, tgt, 2000, seed=0)]
    cpu = line_intersection_metric(src[None], tgt[None], lines=lines).value
    gpu = line_intersection_metric(src[None].cuda(), tgt[None].cuda(), lines=lines).value
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("lengths", "error", "message"),
    [
        (torch.tensor([64, -5]), ValueError, r"src_lengths\[1\] = -5 is outside \[3, 64\]"),
        (torch.tensor([64, 65]), ValueError, r"src_lengths\[1\] = 65 is outside \[3, 64\]"),
        (torch.tensor([64, 0]), ValueError, r"src_lengths\[1\] = 0"),
        (torch.tensor([64.0, 59.5]), TypeError, "src_lengths must have an integer dtype"),
        (torch.tensor([64]), ValueError, r"src_lengths must have shape \(2,\)"),
        ([64, 59], TypeError, "src_lengths must be a torch.Tensor or numpy array"),
    ],
)
def test_bad_lengths_raise_a_clear_error(lengths, error, message):
    src, tgt = torch.rand(2, 64, 3), torch.rand(2, 40, 3)
    with pytest.raises(error, match=message):
        line_intersection_metric(src, tgt, lengths, None, options=LineMetricOptions(num_lines=100))


@pytest.mark.parametrize(
    "options", [LineMetricOptions.for_variant("authors"), LineMetricOptions(sampling="box_point_direction")]
)
def test_a_too_short_sample_is_named_for_every_sampler(options):
    src, tgt = torch.rand(2, 64, 3), torch.rand(2, 40, 3)
    with pytest.raises(ValueError, match=r"tgt_lengths\[0\] = 0 is outside \[3, 40\]"):
        line_intersection_metric(src, tgt, None, torch.tensor([0, 40]), options=options)


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        ([(np.zeros((5, 3)), np.tile([1.0, 0.0, 0.0], (5, 1)))], r"list of 2 \(origins, dirs\) pairs.*got 1 entries"),
        ("lines", r"list of 2 \(origins, dirs\) pairs"),
        ([(np.zeros((5, 3)), np.zeros((5, 3)))] * 2, r"lines\[0\] has a zero direction \(row 0\)"),
        ([(np.zeros((5, 3)), np.ones((4, 3)))] * 2, r"lines\[0\] must hold origins and dirs of one shape"),
        ([(np.full((5, 3), np.nan), np.ones((5, 3)))] * 2, r"lines\[0\] contains NaN or Inf"),
        ([(np.zeros((5, 3)),)] * 2, r"lines\[0\] must be a pair"),
    ],
)
def test_bad_lines_raise_a_clear_error(lines, message):
    with pytest.raises(ValueError, match=message):
        line_intersection_metric(
            blob(50, 31)[None].expand(2, -1, -1), blob(50, 32)[None].expand(2, -1, -1), lines=lines
        )


def test_explicit_directions_need_not_be_unit():
    src, tgt = blob(200, 33), blob(220, 34)
    origins, dirs = lines_for(src, tgt, 600, seed=4)
    unit = line_intersection_metric(src[None], tgt[None], lines=[(origins, dirs)]).value
    scaled = line_intersection_metric(src[None], tgt[None], lines=[(origins, 3.0 * dirs)]).value
    torch.testing.assert_close(scaled, unit)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"nu0": float("nan")}, "nu0 must be a finite number > 0"),
        ({"nu0": float("inf")}, "nu0 must be a finite number > 0"),
        ({"nu0": -1.0}, "nu0 must be a finite number > 0"),
        ({"nu": float("nan")}, "nu must be a finite number > 0"),
        ({"k": 1.5}, "k must be an integer >= 1"),
        ({"distance_eps": float("nan")}, "distance_eps must be a finite number >= 0"),
    ],
)
def test_non_finite_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LineMetricOptions(**kwargs)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("detach_weights", [True, False])
def test_every_float_dtype_gives_a_finite_value_and_gradient(dtype, detach_weights):
    src = transform_points(rigid([6, 0, -4], [0.05, 0.0, 0.0]), blob(300, 35)).to(dtype).requires_grad_(True)
    tgt = blob(300, 36).to(dtype)
    options = LineMetricOptions(num_lines=2000, detach_weights=detach_weights)
    result = line_intersection_metric(src[None], tgt[None], options=options, generator=torch.Generator().manual_seed(0))
    assert result.value.dtype == dtype and torch.isfinite(result.value).all() and result.value.item() > 0
    result.value.sum().backward()
    assert torch.isfinite(src.grad).all() and src.grad.abs().sum() > 0


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 1e3, 1e6])
@pytest.mark.parametrize("intersection", ["convex", "pierce", "triplet"])
def test_the_value_does_not_depend_on_the_unit_of_length(scale, intersection):
    src = transform_points(rigid([5, -3, 2], [0.04, 0.0, 0.02]), blob(300, 37))
    tgt = blob(300, 38)
    options = LineMetricOptions(num_lines=2000, intersection=intersection)
    reference = line_intersection_metric(
        src[None], tgt[None], options=options, generator=torch.Generator().manual_seed(0)
    ).value
    leaf = (src * scale).requires_grad_(True)
    scaled = line_intersection_metric(
        leaf[None], (tgt * scale)[None], options=options, generator=torch.Generator().manual_seed(0)
    ).value
    torch.testing.assert_close(scaled, reference, rtol=1e-6, atol=1e-9)
    scaled.sum().backward()
    assert torch.isfinite(leaf.grad).all() and leaf.grad.abs().sum() > 0
