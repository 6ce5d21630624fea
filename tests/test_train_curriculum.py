"""Curriculum stages, split/variant configs and subsets (train/curriculum.py)."""

from __future__ import annotations

import numpy as np
import pytest

from linereg.datasets import build_dataset
from linereg.datasets.cache import CachedPairs
from linereg.datasets.splits import SubsetPairs, build_split, dataset_config, subset_indices
from linereg.train.curriculum import Curriculum, Stage

DATASET = {
    "name": "procedural",
    "seed": 0,
    "protocol": {"name": "human", "num_views": 2, "num_points": 32, "image_size": 40},
    "splits": {"train": {"split": "train", "num_shapes": 2}, "val": None, "test": {"split": "test", "num_shapes": 1}},
    "variants": {"easy": {"protocol": {"max_angle_deg": 5.0}}},
}


def test_stages_run_in_order_and_locate_epochs():
    curriculum = Curriculum.from_config(
        {"stages": {"easy": {"epochs": 2, "subset": 10}, "skipped": {"epochs": 0}, "full": {"epochs": 3}}}
    )
    assert [s.name for s in curriculum.stages] == ["easy", "full"]
    assert curriculum.total_epochs == 5
    assert [curriculum.locate(e) for e in range(5)] == [(0, 0), (0, 1), (1, 0), (1, 1), (1, 2)]
    assert curriculum.first_epoch(1) == 2
    with pytest.raises(ValueError, match="outside"):
        curriculum.locate(5)


def test_stage_learning_rate():
    assert Stage("a", 1).learning_rate(1e-3) == pytest.approx(1e-3)
    assert Stage("a", 1, lr=1e-4, lr_scale=0.5).learning_rate(1e-3) == pytest.approx(5e-5)


@pytest.mark.parametrize(
    ("stage", "message"),
    [
        ({"epochs": -1}, "epochs must be an int >= 0"),
        ({"epochs": 1, "subset": 1.5}, "subset must be"),
        ({"epochs": 1, "subset": 0}, "subset must be"),
        ({"epochs": 1, "lr": 0.0}, "lr must be > 0"),
        ({"epochs": 1, "lr_scale": -1.0}, "lr_scale must be > 0"),
        ({"subset": 3}, "needs 'epochs'"),
        ({"epochs": 1, "lrs": 3}, r"unknown key\(s\) \['lrs'\]"),
    ],
)
def test_invalid_stages(stage, message):
    with pytest.raises(ValueError, match=message):
        Curriculum.from_config({"stages": {"bad": stage}})


def test_empty_curriculum_is_refused():
    with pytest.raises(ValueError, match=r"no stage with epochs > 0; .*set trainer\.untrained=true"):
        Curriculum.from_config({"stages": {"only": {"epochs": 0}}})
    with pytest.raises(ValueError, match="only 'stages'"):
        Curriculum.from_config({"stages": {}, "epochs": 3})


def test_empty_curriculum_is_accepted_for_an_untrained_run():
    curriculum = Curriculum.from_config({"stages": {"a": {"epochs": 0}, "b": {"epochs": 0}}}, allow_empty=True)
    assert curriculum.stages == [] and curriculum.total_epochs == 0
    with pytest.raises(ValueError, match="outside the curriculum's 0 epochs"):
        curriculum.locate(0)


def test_subset_indices():
    assert subset_indices(50, None, 0) is None
    assert subset_indices(50, 80, 0) is None
    picked = subset_indices(50, 10, 3)
    assert len(picked) == 10 and len(set(picked.tolist())) == 10 and np.all(np.diff(picked) > 0)
    np.testing.assert_array_equal(picked, subset_indices(50, 10, 3))
    assert len(subset_indices(50, 0.1, 0)) == 5


def test_dataset_config_merges_split_and_variant():
    train = dataset_config(DATASET, "train", "easy")
    assert train["split"] == "train" and train["num_shapes"] == 2
    assert train["protocol"] == {
        "name": "human",
        "num_views": 2,
        "num_points": 32,
        "image_size": 40,
        "max_angle_deg": 5.0,
    }
    assert "splits" not in train and "variants" not in train
    assert dataset_config(DATASET, "val") is None
    with pytest.raises(ValueError, match="has no variant 'hard'"):
        dataset_config(DATASET, "train", "hard")
    with pytest.raises(ValueError, match="split must be one of"):
        dataset_config(DATASET, "dev")


def test_subset_split_is_cached_by_its_own_pairs(tmp_path):
    config = {**DATASET, "cache_dir": str(tmp_path), "cache_workers": 0}
    subset = build_split(config, "train", variant="easy", subset=2, seed=0, progress=False)
    assert isinstance(subset, CachedPairs) and len(subset) == 2
    full = build_dataset(dataset_config(DATASET, "train", "easy"))
    indices = subset_indices(len(full), 2, 0)
    for position, index in enumerate(indices):
        np.testing.assert_array_equal(subset[position].src_xyz, full[int(index)].src_xyz)
    assert SubsetPairs(full, indices).settings()["indices"] == indices.tolist()
    assert [p.name.split("-")[0] for p in tmp_path.iterdir()] == ["procedural"]
