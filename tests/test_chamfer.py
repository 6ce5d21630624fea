"""Chamfer (CD) and Welsch-Chamfer (CD-W) values on hand-computed cases, and their losses."""

from __future__ import annotations

import math

import pytest
import torch

from linereg.losses import build_loss
from linereg.losses.chamfer import chamfer_distance, chamfer_welsch_distance, welsch
from linereg.se3 import rt_to_matrix
from linereg.structures import PairBatch, RegistrationOutput


def test_chamfer_on_a_hand_computed_case():
    x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    y = torch.tensor([[[0.0, 0.0, 2.0]]])
    # x->y: distances 2 and sqrt(5); y->x: 2.
    expected = (2.0 + math.sqrt(5.0)) / 2.0 + 2.0
    torch.testing.assert_close(chamfer_distance(x, y), torch.tensor([expected]))
    torch.testing.assert_close(chamfer_distance(x, y, squared=True), torch.tensor([(4.0 + 5.0) / 2.0 + 4.0]))


def test_chamfer_is_zero_at_alignment_and_symmetric():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 50, 3, generator=g)
    y = torch.rand(2, 70, 3, generator=g)
    assert torch.all(chamfer_distance(x, x) == 0)
    torch.testing.assert_close(chamfer_distance(x, y), chamfer_distance(y, x))


def test_chamfer_respects_lengths_and_is_differentiable():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 40, 3, generator=g, requires_grad=True)
    y = torch.rand(1, 30, 3, generator=g)
    padded = torch.cat([y, torch.full((1, 10, 3), 50.0)], dim=1)
    value = chamfer_distance(x, padded, None, torch.tensor([30]))
    torch.testing.assert_close(value, chamfer_distance(x, y))
    value.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_welsch_function_and_cdw_scale():
    d = torch.tensor([0.0, 1.0, 2.0])
    torch.testing.assert_close(welsch(d, 1.0), 1.0 - torch.exp(-(d**2) / 2.0))
    x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    y = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]])
    # Every closest pair is at distance 1, so nu = nu0 and each term is psi(1).
    psi = 1.0 - math.exp(-1.0 / (2.0 * 0.5**2))
    torch.testing.assert_close(chamfer_welsch_distance(x, y, nu0=0.5), torch.tensor([2.0 * psi]))


def test_cdw_is_robust_to_an_outlier():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 200, 3, generator=g)
    y = x + 0.01
    with_outlier = torch.cat([y, torch.tensor([[[100.0, 100.0, 100.0]]])], dim=1)
    assert chamfer_distance(x, with_outlier) > 10 * chamfer_distance(x, y)
    assert chamfer_welsch_distance(x, with_outlier) < 1.2 * chamfer_welsch_distance(x, y) + 0.01


@pytest.mark.parametrize("name", ["chamfer", "chamfer_welsch"])
def test_losses_from_the_registry(name):
    loss = build_loss({"name": name})
    assert not loss.needs_gt
    g = torch.Generator().manual_seed(3)
    src = torch.rand(2, 64, 3, generator=g)
    batch = PairBatch(src_xyz=src, tgt_xyz=src + 0.1)
    shift = torch.zeros(3, requires_grad=True)
    transform = rt_to_matrix(torch.eye(3).expand(2, 3, 3), shift.expand(2, 3))
    out = loss(RegistrationOutput(transforms=[transform]), batch)
    out.total.backward()
    # Moving the source towards the target (+0.1 on every axis) decreases the loss.
    assert torch.all(shift.grad < 0)


@pytest.mark.parametrize("bad", [torch.zeros(2, 3), torch.full((1, 5, 3), float("nan")), torch.zeros(1, 0, 3)])
def test_bad_input(bad):
    with pytest.raises(ValueError):
        chamfer_distance(bad, torch.rand(1, 5, 3))


@pytest.mark.parametrize("fn", [chamfer_distance, chamfer_welsch_distance])
@pytest.mark.parametrize(
    ("lengths", "error", "message"),
    [
        (torch.tensor([64, -5]), ValueError, r"x_lengths\[1\] = -5 is outside \[1, 64\]"),
        (torch.tensor([64, 65]), ValueError, r"x_lengths\[1\] = 65 is outside \[1, 64\]"),
        (torch.tensor([64, 0]), ValueError, r"x_lengths\[1\] = 0"),
        (torch.tensor([64.0, 59.0]), TypeError, "x_lengths must have an integer dtype"),
        (torch.tensor([64, 64, 64]), ValueError, r"x_lengths must have shape \(2,\)"),
    ],
)
def test_bad_lengths_raise(fn, lengths, error, message):
    with pytest.raises(error, match=message):
        fn(torch.rand(2, 64, 3), torch.rand(2, 30, 3), lengths, None)


@pytest.mark.parametrize("nu0", [0.0, -1.0, float("nan"), float("inf")])
def test_cdw_rejects_a_bad_nu0(nu0):
    with pytest.raises(ValueError, match="nu0 must be a finite number > 0"):
        chamfer_welsch_distance(torch.rand(1, 10, 3), torch.rand(1, 10, 3), nu0=nu0)
    with pytest.raises(ValueError, match="nu0 must be a finite number > 0"):
        build_loss({"name": "chamfer_welsch", "nu0": nu0})


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("fn", [chamfer_distance, chamfer_welsch_distance])
def test_every_float_dtype_gives_a_finite_value_and_gradient(fn, dtype):
    g = torch.Generator().manual_seed(3)
    x = (0.01 * torch.rand(1, 100, 3, generator=g)).to(dtype).requires_grad_(True)
    y = (0.01 * torch.rand(1, 120, 3, generator=g)).to(dtype)
    value = fn(x, y)
    assert value.dtype == dtype and torch.isfinite(value).all() and value.item() > 0
    value.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_cdw_at_exact_alignment_is_a_defined_zero():
    x = torch.rand(1, 50, 3, requires_grad=True)
    value = chamfer_welsch_distance(x, x.detach().clone())
    assert value.item() == 0.0
    value.sum().backward()
    assert torch.isfinite(x.grad).all()
