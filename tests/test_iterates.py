"""Choosing the iterate (:mod:`linereg.registration.iterates`) and the legacy iterate keys of stored run configs."""

from __future__ import annotations

import math

import pytest
import torch

from linereg.models import MODELS, load_model, upgrade_run_config
from linereg.pointcloud import trimmed_chamfer_distance
from linereg.random_poses import random_transform_paper
from linereg.registration.iterates import LAST_ITERATE, IterateRule, select_iterate
from linereg.se3 import se3_exp, transform_points
from linereg.train.checkpoint import save_checkpoint


def _iterates(batch: int = 4, count: int = 5, points: int = 40, seed: int = 0):
    """Clouds ``(B, N, 3)``, their targets and ``count`` estimates; pair ``b``'s estimate ``k`` is off by
    ``1 + 4 ((k + b) mod count)`` degrees, so each pair comes closest at another iterate."""
    generator = torch.Generator().manual_seed(seed)
    src = torch.rand(batch, points, 3, generator=generator, dtype=torch.float64) - 0.5
    torch.manual_seed(seed)
    truth = random_transform_paper(batch, 30).double()
    tgt = transform_points(truth, src)
    axes = torch.nn.functional.normalize(torch.randn(count, batch, 3, generator=generator, dtype=torch.float64), dim=-1)
    offsets = (torch.arange(count)[:, None] + torch.arange(batch)[None]) % count
    angles = torch.deg2rad(1.0 + 4.0 * offsets.double())
    twists = torch.cat((axes * angles[..., None], torch.zeros(count, batch, 3, dtype=torch.float64)), dim=-1)
    return src, tgt, [se3_exp(twist) @ truth for twist in twists]


def _naive(transforms, src, tgt, keep_fraction, src_counts, tgt_counts) -> torch.Tensor:
    """Per pair and iterate, the trimmed Chamfer distance of the valid points; the first minimum."""
    chosen = []
    for pair in range(src.shape[0]):
        source, target = src[pair, : src_counts[pair]], tgt[pair, : tgt_counts[pair]]
        fits = [
            float(trimmed_chamfer_distance(transform_points(T[pair], source), target, keep_fraction))
            for T in transforms
        ]
        chosen.append(fits.index(min(fits)))
    return torch.tensor(chosen)


@pytest.mark.parametrize("keep_fraction", [1.0, 0.9, 0.3])
def test_best_fit_matches_a_loop_over_pairs_and_iterates(keep_fraction):
    src, tgt, transforms = _iterates()
    before = [T.clone() for T in transforms]
    chosen, index = select_iterate(transforms, src, tgt, rule="best_fit", keep_fraction=keep_fraction)
    counts = [src.shape[1]] * src.shape[0]
    expected = _naive(transforms, src, tgt, keep_fraction, counts, counts)
    assert torch.equal(index, expected) and index.dtype == torch.long
    assert len(set(index.tolist())) > 1  # the pairs do not all pick the same iterate
    for pair, iteration in enumerate(index.tolist()):
        assert torch.equal(chosen[pair], transforms[iteration][pair])
    assert all(torch.equal(a, b) for a, b in zip(before, transforms, strict=True)) and len(transforms) == len(before)


def test_best_fit_on_padded_batches_reads_the_valid_points_only():
    src, tgt, transforms = _iterates()
    src_lengths, tgt_lengths = torch.tensor([40, 25, 31, 12]), torch.tensor([18, 40, 33, 27])
    padded_src, padded_tgt = src.clone(), tgt.clone()
    for pair in range(4):  # padding far away would win every nearest-neighbour query if it were read
        padded_src[pair, int(src_lengths[pair]) :] = 100.0
        padded_tgt[pair, int(tgt_lengths[pair]) :] = -100.0
    _, index = select_iterate(transforms, padded_src, padded_tgt, "best_fit", 0.8, src_lengths, tgt_lengths)
    assert torch.equal(index, _naive(transforms, src, tgt, 0.8, src_lengths.tolist(), tgt_lengths.tolist()))


def test_last_returns_the_final_iterate_itself():
    src, tgt, transforms = _iterates()
    chosen, index = select_iterate(transforms, src, tgt)
    assert chosen is transforms[-1] and torch.equal(index, torch.full((4,), 4))
    assert LAST_ITERATE.select(transforms, src, tgt)[0] is transforms[-1]


def test_gradients_flow_through_the_chosen_iterate():
    src, tgt, transforms = _iterates(count=3)
    leaves = [T.clone().requires_grad_(True) for T in transforms]
    chosen, index = select_iterate(leaves, src, tgt, rule="best_fit")
    chosen.sum().backward()
    for iteration, leaf in enumerate(leaves):
        expected = (index == iteration).double()[:, None, None].expand(-1, 4, 4)
        assert torch.equal(leaf.grad, expected)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rule": "best"}, r"iterate.rule must be one of last, best_fit, got 'best'"),
        ({"rule": "best_fit", "keep_fraction": 0.0}, r"iterate.keep_fraction must be a number in \(0, 1\]"),
        ({"keep_fraction": 1.5}, r"iterate.keep_fraction must be a number in \(0, 1\], got 1.5"),
        ({"keep_fraction": True}, r"iterate.keep_fraction must be a number"),
        ({"transforms": []}, "transforms is empty"),
        ({"transforms": [torch.eye(4)]}, r"transforms\[0\] must have shape \(4, 4, 4\)"),
    ],
)
def test_bad_arguments_are_named(kwargs, message):
    src, tgt, transforms = _iterates()
    arguments = {"transforms": transforms, "src": src, "tgt": tgt, **kwargs}
    with pytest.raises(ValueError, match=message):
        select_iterate(**arguments)


def test_rule_from_config():
    assert IterateRule.from_config(None) == LAST_ITERATE == IterateRule("last", 1.0)
    assert IterateRule.from_config({"rule": "best_fit", "keep_fraction": 0.9}) == IterateRule("best_fit", 0.9)
    assert IterateRule.from_config({"rule": "best_fit", "keep_fraction": None}) == IterateRule("best_fit", 1.0)
    with pytest.raises(ValueError, match=r"unknown iterate key\(s\) \['keep'\]; accepted: \['keep_fraction', 'rule'\]"):
        IterateRule.from_config({"rule": "last", "keep": 1.0})


@pytest.mark.parametrize(
    ("model", "iterate"),
    [
        ({"keep_best_iterate": True, "fit_keep_fraction": 0.9}, {"rule": "best_fit", "keep_fraction": 0.9}),
        ({"keep_best_iterate": True}, {"rule": "best_fit", "keep_fraction": 1.0}),
        ({"keep_best_iterate": False, "fit_keep_fraction": 1.0}, {"rule": "last", "keep_fraction": 1.0}),
    ],
)
def test_legacy_model_keys_become_the_iterate_block(model, iterate):
    stored = {"model": {"name": "rpmnet", "test_iters": 3, **model}, "seed": 1}
    upgraded = upgrade_run_config(stored)
    assert upgraded == {"model": {"name": "rpmnet", "test_iters": 3}, "seed": 1, "iterate": iterate}
    assert "keep_best_iterate" in stored["model"]  # the stored config itself is not changed
    assert IterateRule.from_config(upgraded["iterate"]).rule == iterate["rule"]


def test_a_config_without_legacy_keys_is_unchanged():
    stored = {"model": {"name": "fmr"}, "iterate": {"rule": "best_fit", "keep_fraction": 1.0}}
    assert upgrade_run_config(stored) == stored


def test_a_legacy_checkpoint_loads_with_its_rule(tmp_path):
    config = {"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8}
    model = MODELS.build(config)
    legacy = {"model": {**config, "keep_best_iterate": True, "fit_keep_fraction": 0.9}, "trainer": {"num_points": 64}}
    save_checkpoint({"config": legacy, "model": model.state_dict()}, tmp_path / "checkpoints" / "best.pt")
    loaded, state = load_model(tmp_path)
    assert state["config"]["iterate"] == {"rule": "best_fit", "keep_fraction": 0.9}
    assert "keep_best_iterate" not in state["config"]["model"] and not loaded.training


class _FixedIterates(torch.nn.Module):
    """A stand-in model answering every pair with the same iterates: 30 deg off, exact, 10 deg off."""

    def forward(self, batch):
        from linereg.structures import RegistrationOutput

        twists = torch.tensor([[0.0, 0.0, math.radians(30.0), 0, 0, 0], [0.0] * 6, [math.radians(10.0), 0, 0, 0, 0, 0]])
        size = batch.src_xyz.shape[0]
        transforms = [se3_exp(twist[None]).expand(size, 4, 4).to(batch.src_xyz) for twist in twists]
        return RegistrationOutput(transforms=transforms)


@pytest.mark.parametrize(("iterate", "expected_deg"), [(None, 10.0), ({"rule": "best_fit", "keep_fraction": 1.0}, 0.0)])
def test_a_trained_network_answers_with_its_runs_iterate(tmp_path, iterate, expected_deg):
    from linereg.registration.learned import LearnedRegistration
    from linereg.se3 import rotation_angle

    config = {"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8}
    run = {"model": config, "trainer": {"num_points": 128}, **({"iterate": iterate} if iterate else {})}
    save_checkpoint({"config": run, "model": MODELS.build(config).state_dict()}, tmp_path / "checkpoints" / "best.pt")
    learned = LearnedRegistration(tmp_path)
    learned.model = _FixedIterates()
    cloud = (torch.rand(300, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5).numpy()
    result = learned(cloud, cloud)
    angle = math.degrees(float(rotation_angle(torch.from_numpy(result.transform[:3, :3]))))
    assert angle == pytest.approx(expected_deg, abs=1e-4)
    assert result.info["iterate"]["rule"] == (iterate or {"rule": "last"})["rule"]


def test_a_rule_round_trips_through_its_config_block():
    rule = IterateRule("best_fit", 0.9)
    assert rule.as_config() == {"rule": "best_fit", "keep_fraction": 0.9}
    assert IterateRule.from_config(rule.as_config()) == rule
