"""The generalization splits (``configs/dataset/<split>.yaml``): each builds from the shared data,
holds no pair of its protocol's training split, changes what it says it changes, and
``linereg-evaluate`` scores a network on it."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from linereg.datasets.splits import build_split
from linereg.registry import plain
from linereg.train.evaluate import evaluate
from tests.conftest import compose_config
from tests.pair_identities import pair_identities

ROOT = Path(__file__).resolve().parent.parent
SPLITS = {  # split -> its protocol
    "airplane_view_vs_whole": "airplane",
    "airplane_other_categories": "airplane",
    "airplane_other_categories_held_out": "airplane",
    "human_view_vs_view": "human",
    "human_armadillo": "human",
    "kinect_frames": "real",
    "redkitchen_fragments": "real",
}
BODIES = ("human_man", "human_neutral", "human_woman")
pytestmark = pytest.mark.shared_data


def _compose(name: str, overrides: list[str]):
    return compose_config(name, [f"paths.root_dir={ROOT}", *overrides])


def _split(split: str):
    """The test split of a generalization split's dataset config, without a cache."""
    cfg = _compose("evaluate", ["checkpoint=x", f"dataset={split}", "trainer.num_points=256", "dataset.cache_dir=null"])
    return build_split(plain(cfg.dataset), "test", progress=False)


def _protocol(protocol: str, split: str):
    """``split`` of a protocol's own dataset config, without a cache."""
    cfg = _compose("train", [f"protocol={protocol}", "experiment=rpm_ours", "dataset.cache_dir=null"])
    return build_split(plain(cfg.dataset), split, progress=False)


@pytest.mark.parametrize("split", sorted(SPLITS))
def test_a_split_holds_no_training_pair_of_its_protocol(split, shared_data):
    pairs = pair_identities(_split(split))
    training = pair_identities(_protocol(SPLITS[split], "train"))
    assert pairs and not pairs & training
    if split not in ("airplane_view_vs_whole", "human_view_vs_view"):  # other shapes or frames altogether
        assert not {name for name, _ in pairs} & {name for name, _ in training}


def test_the_pair_type_splits_keep_the_protocols_test_views_and_change_the_target(shared_data):
    for split, protocol in (("airplane_view_vs_whole", "airplane"), ("human_view_vs_view", "human")):
        changed, own = _split(split), _protocol(protocol, "test")
        assert pair_identities(changed) == pair_identities(own)
        assert changed.protocol.target != own.protocol.target, split


def test_the_other_categories_are_every_shared_shape_but_the_airplanes(shared_data):
    names = {Path(name).parent.name for name, _ in pair_identities(_split("airplane_other_categories"))}
    assert names == {"bottle", "car", "chair", "guitar", "person", "table", "toilet"}


def test_linereg_evaluate_scores_a_generalization_split(shared_data, tmp_path):
    overrides = ["checkpoint=rpm_ours_real", "dataset=kinect_frames", f"output_dir={tmp_path}", "progress=false"]
    metrics = evaluate(_compose("evaluate", [*overrides, "num_figures=0", "dataset.cache_dir=null"]))
    assert metrics["num_pairs"] == 4 and metrics["labelled"]
    assert math.isfinite(metrics["model"]["err_r_deg_mean"]) and metrics["identity"]["err_r_deg_mean"] > 10


@pytest.mark.parametrize("body", BODIES)
def test_leave_one_body_out_tests_every_view_of_a_body_its_training_never_saw(body, shared_data):
    cfg = _compose(
        "train",
        [
            "protocol=human",
            "experiment=rpm_ours",
            "dataset=human_unseen_body",
            f"dataset.held_out={body}",
            "dataset.cache_dir=null",
        ],
    )
    train, val, test = (build_split(plain(cfg.dataset), split, progress=False) for split in ("train", "val", "test"))

    def bodies(split) -> set[str]:
        return {Path(name).stem for name, _ in pair_identities(split)}

    assert bodies(test) == {body} and len(test) == 50
    assert bodies(train) == set(BODIES) - {body} and len(train) == 100
    assert bodies(val) <= bodies(train) and len(val) == 10


def test_the_mixed_airplane_pairs_are_the_protocols_shapes_with_both_targets(shared_data):
    cfg = _compose(
        "train", ["protocol=airplane", "experiment=rpm_ours", "dataset=airplane_mixed_pairs", "dataset.cache_dir=null"]
    )
    mixed = build_split(plain(cfg.dataset), "train", progress=False)
    assert pair_identities(mixed) == pair_identities(_protocol("airplane", "train"))
    assert {mixed.protocol.target_of(view) for _, view in pair_identities(mixed)} == {"view", "whole"}


def _objects(split: str, dataset: str = "objects", variant: str | None = None):
    """``split`` (at a ``variant``) of a general model's data (every object, both pair types;
    ``objects_and_rooms``: and the Real protocol's room frames), without a cache."""
    overrides = ["protocol=airplane", "experiment=rpm_ours", f"dataset={dataset}", "dataset.cache_dir=null"]
    return build_split(plain(_compose("train", overrides).dataset), split, variant=variant, progress=False)


@pytest.mark.parametrize("dataset", ["objects", "objects_and_rooms"])
def test_the_general_model_trains_on_no_pair_it_is_scored_on(dataset, shared_data):
    """Every object of the shared data (and the room frames) trains the general model, but no test
    pair of a split it is scored on, and no shape or frame of the held-out splits; its test split
    holds the protocols' test pairs and the held-out shapes."""
    training, test = pair_identities(_objects("train", dataset)), pair_identities(_objects("test", dataset))
    protocols = {protocol: _protocol(protocol, "test") for protocol in ("airplane", "human", "real")}
    scored = {**protocols, **{split: _split(split) for split in SPLITS if split != "airplane_other_categories"}}
    for name, split in scored.items():
        assert not pair_identities(split) & training, name
    files = {file for file, _ in training}
    for name in ("airplane_other_categories_held_out", "human_armadillo", "real", "kinect_frames"):
        assert not {file for file, _ in pair_identities(scored[name])} & files, name
    assert {Path(file).parent.name for file in files} >= {"airplane", "chair", "human", "bunny", "plane"}
    own = ("airplane", "human", "airplane_other_categories_held_out") + (("real",) if dataset != "objects" else ())
    for name in own:
        assert pair_identities(scored[name]) <= test, name
    rooms = {file for file in files if file.endswith(".depth.png")}
    assert (len(rooms) == 190) == (dataset == "objects_and_rooms"), len(rooms)
    if dataset == "objects_and_rooms":  # the rooms' second stage: training frames alone
        alone = pair_identities(_objects("train", dataset, variant="rooms_only"))
        assert len(alone) == 190 and {file for file, _ in alone} <= rooms
        assert not any(pair_identities(split) & alone for split in scored.values())
    assert _objects("train", dataset).parts[0].protocol.target == "mixed"


TRAINABLE = {  # dataset config -> the protocol it trains under
    "airplane_views": "airplane",
    "airplane_view_vs_whole": "airplane",
    "airplane_mixed_pairs": "airplane",
    "objects": "airplane",
    "objects_and_rooms": "airplane",
    "human_bodies": "human",
    "human_view_vs_view": "human",
    "human_unseen_body": "human",
}


@pytest.mark.parametrize("dataset", [*sorted(TRAINABLE), "real"])
def test_every_choice_is_made_on_validation_pairs_of_the_training_side(dataset, shared_data):
    """What a run validates on (the pairs every recipe choice and checkpoint rule may look at) is
    drawn from its training split, never from a test pair."""
    overrides = ["protocol=real"] if dataset == "real" else [f"protocol={TRAINABLE[dataset]}", f"dataset={dataset}"]
    cfg = _compose("train", [*overrides, "experiment=rpm_ours", "dataset.cache_dir=null"])
    train, val, test = (build_split(plain(cfg.dataset), split, progress=False) for split in ("train", "val", "test"))
    if dataset == "real":  # frames: the validation pairs are training pairs, no test frame
        assert pair_identities(val) <= pair_identities(train)
        assert not {name for name, _ in pair_identities(val)} & {name for name, _ in pair_identities(test)}
        return
    assert pair_identities(val) <= pair_identities(train) and not pair_identities(val) & pair_identities(test)
