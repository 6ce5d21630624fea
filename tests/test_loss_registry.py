"""Registry-wide rules of losses/: composition, metadata, and the ground-truth guard."""

from __future__ import annotations

import pytest
import torch

from linereg.losses import LOSSES, WeightedSum, build_loss, set_training_progress
from linereg.structures import PairBatch, RegistrationOutput


def _batch(with_gt: bool) -> PairBatch:
    g = torch.Generator().manual_seed(0)
    src = torch.nn.functional.normalize(torch.randn(1, 300, 3, generator=g), dim=-1)
    gt = torch.eye(4)[None] if with_gt else None
    return PairBatch(src_xyz=src, tgt_xyz=src * torch.tensor([1.0, 1.0, 0.9]), gt_transform=gt)


def _rpm_output() -> RegistrationOutput:
    perm = torch.full((1, 300, 300), 0.5 / 300)
    return RegistrationOutput(transforms=[torch.eye(4)[None]] * 2, extras={"perm_matrices": [perm, perm]})


def test_composite_rpmnet_outlier_plus_line_loss():
    config = {
        "terms": {
            "outlier": {"name": "rpmnet_outlier", "weight": 10.0},
            "line": {"name": "line_intersection", "weight": 1.0, "num_lines": 1000, "seed": 0},
        }
    }
    loss = build_loss(config)
    assert isinstance(loss, WeightedSum) and not loss.needs_gt
    out = loss(_rpm_output(), _batch(with_gt=False))
    outlier = build_loss({"name": "rpmnet_outlier"})(_rpm_output(), _batch(with_gt=False)).total
    line = build_loss({"name": "line_intersection", "num_lines": 1000, "seed": 0})(_rpm_output(), _batch(False)).total
    torch.testing.assert_close(out.terms["outlier"], 10.0 * outlier)
    torch.testing.assert_close(out.terms["line"], line)
    torch.testing.assert_close(out.total, 10.0 * outlier + line)
    assert "line/lines_hit_both" in out.stats


def test_nu0_final_anneals_the_welsch_scale_geometrically():
    line = {"name": "line_intersection", "num_lines": 1000, "seed": 0}
    annealed = {**line, "nu0": 2.0, "nu0_final": 0.5}
    loss = build_loss({"terms": {"outlier": {"name": "rpmnet_outlier"}, "line": annealed}})
    assert loss.parts["line"].options.nu0 == 2.0  # before the first epoch: nu0
    assert set_training_progress(loss, 0.5) == {"parts.line.nu0": pytest.approx(1.0)}
    assert set_training_progress(loss, 1.0) == {"parts.line.nu0": pytest.approx(0.5)}
    # At the end of the schedule the loss is the fixed-scale loss at nu0_final (the same lines).
    fixed = build_loss({**line, "nu0": 0.5})
    torch.testing.assert_close(
        loss.parts["line"](_rpm_output(), _batch(False)).total, fixed(_rpm_output(), _batch(False)).total
    )
    assert set_training_progress(fixed, 0.3) == {} and fixed.options.nu0 == 0.5  # unscheduled: untouched


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"nu0_final": 0.0}, "nu0_final must be a finite number > 0"),
        ({"nu0_final": float("nan")}, "nu0_final must be a finite number > 0"),
        ({"nu0_final": True}, "nu0_final must be a finite number > 0"),
        ({"nu0_final": 0.5, "nu": 0.1}, "set one of them"),
    ],
)
def test_bad_nu0_schedules_are_named(options, message):
    with pytest.raises(ValueError, match=message):
        build_loss({"name": "line_intersection", **options})


@pytest.mark.parametrize("fraction", [-0.1, 1.5, float("nan")])
def test_training_progress_outside_zero_one_is_refused(fraction):
    with pytest.raises(ValueError, match=r"training progress must lie in \[0, 1\]"):
        set_training_progress(build_loss({"name": "line_intersection", "nu0_final": 0.5}), fraction)


def test_a_composite_with_a_supervised_part_needs_gt():
    loss = build_loss({"terms": {"gt": {"name": "gt_rpmnet"}, "line": {"name": "line_intersection"}}})
    assert loss.needs_gt
    with pytest.raises(ValueError, match="gt_transform"):
        loss(_rpm_output(), _batch(with_gt=False))


@pytest.mark.parametrize("name", LOSSES.names())
def test_every_loss_declares_whether_it_needs_ground_truth(name):
    declared = LOSSES.metadata(name)["needs_gt"]
    assert declared == name.startswith("gt_")


@pytest.mark.parametrize("name", [n for n in LOSSES.names() if not n.startswith("gt_")])
def test_unsupervised_losses_never_see_ground_truth(name):
    loss = build_loss({"name": name})
    seen = []
    original = loss.compute

    def spy(output, batch):
        seen.append(batch.gt_transform)
        return original(output, batch)

    loss.compute = spy
    output = _rpm_output()
    if name == "dcp_cycle":
        output.extras["transform_reverse"] = torch.eye(4)[None]
    if name == "fmr_reconstruction":
        cloud = _batch(False).src_xyz
        output.extras["reconstructions"] = [(cloud, cloud * 1.01)]
    try:
        loss(output, _batch(with_gt=True))
    except ValueError as err:  # a regulariser may need extras of another model
        pytest.skip(f"{name} needs other extras: {err}")
    assert seen == [None]


def test_unknown_loss_and_keys():
    with pytest.raises(KeyError, match="line_intersection"):
        build_loss({"name": "nope"})
    with pytest.raises(KeyError, match="name"):
        build_loss({"nu0": 1})
    with pytest.raises(TypeError, match="chamfer"):
        build_loss({"name": "chamfer", "bogus": 1})
