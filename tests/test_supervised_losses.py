"""Tests for losses/supervised.py: values at and away from ground truth, ground-truth guards."""

from __future__ import annotations

import pytest
import torch

from linereg.losses.base import LOSSES, build_loss
from linereg.losses.supervised import (
    DCPCycleLoss,
    DCPSupervisedLoss,
    FMRReconstructionLoss,
    FMRSupervisedLoss,
    RPMNetOutlierLoss,
    RPMNetSupervisedLoss,
    outlier_penalty,
)
from linereg.random_poses import random_transform_paper
from linereg.se3 import inverse, rt_to_matrix
from linereg.structures import PairBatch, RegistrationOutput

SUPERVISED = ["gt_rpmnet", "gt_dcp", "gt_fmr"]
UNSUPERVISED = ["rpmnet_outlier", "dcp_cycle", "fmr_reconstruction"]
NUM_POINTS = 16


def _batch(with_gt: bool = True) -> PairBatch:
    generator = torch.Generator().manual_seed(0)
    src = torch.rand(2, NUM_POINTS, 3, generator=generator) - 0.5
    T = random_transform_paper(2, 1)
    tgt = src @ T[:, :3, :3].mT + T[:, None, :3, 3]
    return PairBatch(src, tgt, gt_transform=T if with_gt else None)


def _output(batch: PairBatch, transform: torch.Tensor, *, iterations: int = 2) -> RegistrationOutput:
    """A model output carrying every extra the losses read, all consistent with ``transform``."""
    perm = torch.eye(NUM_POINTS).expand(2, NUM_POINTS, NUM_POINTS)
    reconstructions = [(cloud, cloud.clone()) for cloud in (batch.src_xyz, batch.tgt_xyz)]
    return RegistrationOutput(
        transforms=[transform] * iterations,
        extras={
            "perm_matrices": [perm] * iterations,
            "transform_reverse": inverse(transform),
            "reconstructions": reconstructions,
        },
    )


def _translated(T: torch.Tensor, offset: tuple[float, float, float]) -> torch.Tensor:
    """``T`` followed by a translation by ``offset``."""
    shift = rt_to_matrix(torch.eye(3), torch.tensor(offset))
    return shift @ T


def test_registry_metadata_matches_classes():
    for name in SUPERVISED + UNSUPERVISED:
        loss = build_loss({"name": name})
        assert LOSSES.metadata(name)["needs_gt"] is loss.needs_gt is (name in SUPERVISED)


@pytest.mark.parametrize("name", SUPERVISED + UNSUPERVISED)
def test_zero_at_ground_truth(name):
    batch = _batch()
    loss = build_loss({"name": name, **({"cycle_weight": 0.1} if name == "gt_dcp" else {})})
    result = loss(_output(batch, batch.gt_transform), batch)
    assert result.total.shape == ()
    assert abs(result.total.item()) < 1e-6
    torch.testing.assert_close(sum(result.terms.values()), result.total)


@pytest.mark.parametrize("name", SUPERVISED)
def test_positive_away_from_ground_truth(name):
    batch = _batch()
    rotated = rt_to_matrix(random_transform_paper(1, 5)[0, :3, :3], torch.zeros(3))
    for wrong in (_translated(batch.gt_transform, (0.1, 0.0, 0.0)), batch.gt_transform @ rotated):
        assert build_loss({"name": name})(_output(batch, wrong), batch).total.item() > 1e-4


@pytest.mark.parametrize("name", SUPERVISED)
def test_supervised_losses_need_ground_truth(name):
    batch = _batch(with_gt=False)
    with pytest.raises(ValueError, match=r"needs batch\.gt_transform"):
        build_loss({"name": name})(_output(batch, torch.eye(4).expand(2, 4, 4)), batch)


@pytest.mark.parametrize("name", UNSUPERVISED)
def test_unsupervised_losses_run_without_ground_truth(name):
    batch = _batch(with_gt=False)
    output = _output(batch, random_transform_paper(2, 3))
    assert torch.isfinite(build_loss({"name": name})(output, batch).total)


def test_rpmnet_values():
    batch = _batch()
    wrong = _translated(batch.gt_transform, (0.3, 0.0, -0.3))
    output = _output(batch, wrong)
    output.extras["perm_matrices"] = [0.5 * p for p in output.extras["perm_matrices"]]
    result = RPMNetSupervisedLoss()(output, batch)
    # Iteration weights 0.5 and 1; L1 = mean(|0.3|, 0, |0.3|) = 0.2; penalty = 0.5 + 0.5 = 1.
    torch.testing.assert_close(result.terms["registration"], torch.tensor(1.5 * 0.2))
    torch.testing.assert_close(result.terms["outlier"], torch.tensor(1.5 * 0.01))
    torch.testing.assert_close(RPMNetOutlierLoss()(output, batch).total, torch.tensor(1.5))
    torch.testing.assert_close(outlier_penalty(torch.zeros(1, 3, 4)), torch.tensor(2.0))


def test_rpmnet_outlier_term_needs_perm_matrices():
    batch = _batch()
    output = RegistrationOutput(transforms=[batch.gt_transform])
    with pytest.raises(ValueError, match=r"extras\['perm_matrices'\], which RPM-Net returns"):
        RPMNetSupervisedLoss()(output, batch)
    assert RPMNetSupervisedLoss(outlier_weight=0.0)(output, batch).total.item() == 0.0


def test_dcp_values():
    batch = _batch()
    output = _output(batch, _translated(batch.gt_transform, (0.1, 0.2, 0.2)))
    result = DCPSupervisedLoss()(output, batch)
    torch.testing.assert_close(result.terms["translation"], torch.tensor(0.09 / 3))
    assert result.terms["rotation"].item() < 1e-12 and "cycle" not in result.terms
    output.extras["transform_reverse"] = torch.eye(4).expand(2, 4, 4)
    assert DCPCycleLoss()(output, batch).total.item() > 1e-3
    with_cycle = DCPSupervisedLoss(cycle_weight=0.1)(output, batch)
    torch.testing.assert_close(with_cycle.terms["cycle"], 0.1 * DCPCycleLoss()(output, batch).total)


def test_fmr_values():
    batch = _batch()
    output = _output(batch, _translated(batch.gt_transform, (0.1, 0.0, 0.0)))
    # 16 * mean over 16 entries of the squared residual = the sum of squares = 0.01.
    result = FMRSupervisedLoss()(output, batch)
    torch.testing.assert_close(result.terms["transform"], torch.tensor(0.01))
    grid = torch.stack(torch.meshgrid(*[torch.arange(n) * 0.5 for n in (2, 2, 4)], indexing="ij"))
    inputs = grid.reshape(3, -1).T.expand(2, NUM_POINTS, 3)
    output.extras["reconstructions"] = [(inputs, inputs + torch.tensor([0.0, 0.0, 0.1]))]
    # Every point's nearest decoded point is its own copy at distance 0.1 (squared 0.01), both ways.
    torch.testing.assert_close(FMRReconstructionLoss()(output, batch).total, torch.tensor(0.02))
    without = FMRSupervisedLoss(reconstruction_weight=0.0)(output, batch)
    assert set(without.terms) == {"transform"}


def test_fmr_reconstruction_needs_a_decoder():
    batch = _batch()
    output = RegistrationOutput(transforms=[batch.gt_transform], extras={"reconstructions": []})
    with pytest.raises(ValueError, match="decoder_points=None"):
        FMRReconstructionLoss()(output, batch)


def test_losses_are_differentiable_in_the_estimate():
    batch = _batch()
    estimate = _translated(batch.gt_transform, (0.05, -0.02, 0.01)).requires_grad_(True)
    for name in SUPERVISED:
        estimate.grad = None
        build_loss({"name": name})(_output(batch, estimate), batch).total.backward()
        assert estimate.grad is not None and estimate.grad.abs().sum() > 0


def _scaled(batch: PairBatch, scale: float, dtype: torch.dtype) -> PairBatch:
    """``batch`` with coordinates (and translations) multiplied by ``scale``, in ``dtype``."""
    gt = batch.gt_transform.clone()
    gt[:, :3, 3] *= scale
    return PairBatch((batch.src_xyz * scale).to(dtype), (batch.tgt_xyz * scale).to(dtype), gt_transform=gt.to(dtype))


def _large_output(batch: PairBatch) -> RegistrationOutput:
    """An estimate 40 units off the ground truth and decodings 300 units off the inputs."""
    estimate = _translated(batch.gt_transform.float(), (30.0, -20.0, 20.0)).to(batch.src_xyz.dtype)
    output = _output(batch, estimate)
    output.extras["reconstructions"] = [(cloud, cloud + 300.0) for cloud in (batch.src_xyz, batch.tgt_xyz)]
    return output


@pytest.mark.parametrize("name", [*SUPERVISED, *UNSUPERVISED])
def test_half_precision_at_large_scale_is_finite_and_matches_float64(name):
    # Coordinates of 1e3: squared distances (~1e5 and more) overflow float16 (largest value 65504).
    reference, half = _scaled(_batch(), 1e3, torch.float64), _scaled(_batch(), 1e3, torch.float16)
    loss = build_loss({"name": name})
    expected = loss(_large_output(reference), reference).total
    result = loss(_large_output(half), half).total
    assert result.dtype == torch.float32 and torch.isfinite(result)
    # float16 inputs hold 3 significant digits: the value agrees to that precision.
    torch.testing.assert_close(result.double(), expected.double(), rtol=2e-2, atol=1e-3)


@pytest.mark.parametrize("name", SUPERVISED)
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_ground_truth_is_named(name, bad):
    batch = _batch()
    output = _output(batch, batch.gt_transform)
    batch.gt_transform[1, 0, 3] = bad
    with pytest.raises(ValueError, match=r"batch\.gt_transform contains NaN or Inf"):
        build_loss({"name": name})(output, batch)


@pytest.mark.parametrize("name", ["gt_rpmnet", "gt_fmr", "fmr_reconstruction"])
@pytest.mark.parametrize("field", ["src_xyz", "tgt_xyz"])
def test_non_finite_coordinates_are_named(name, field):
    batch = _batch()
    output = _output(batch, batch.gt_transform)
    getattr(batch, field)[0, 3, 1] = float("nan")
    if name == "gt_rpmnet" and field == "tgt_xyz":  # RPM-Net's loss reads the source only
        assert torch.isfinite(build_loss({"name": name})(output, batch).total)
        return
    with pytest.raises(ValueError, match=rf"batch\.{field} contains NaN or Inf coordinates"):
        build_loss({"name": name})(output, batch)
