"""A split's own ``subset`` (datasets/splits.py): validation on fresh poses of a few training pairs."""

from __future__ import annotations

import numpy as np

from linereg.datasets.splits import build_split

DATASET = {
    "name": "procedural",
    "seed": 0,
    "protocol": {"name": "human", "num_views": 2, "num_points": 32, "image_size": 40},
    "splits": {
        "train": {"split": "train", "num_shapes": 3},
        "val": {"split": "train", "num_shapes": 3, "seed": 1, "subset": 2},
        "test": {"split": "test", "num_shapes": 1},
    },
}


def test_split_subset_keeps_that_many_pairs_of_its_split():
    validation = build_split(DATASET, "val", progress=False)
    train = build_split(DATASET, "train", progress=False)
    assert len(train) == 6 and len(validation) == 2
    assert validation.indices == sorted(validation.indices)


def test_validation_pairs_are_fresh_poses_of_training_pairs():
    """``seed: 1``: the same shapes and views as the training pairs, at other poses."""
    validation = build_split(DATASET, "val", progress=False)
    train = build_split(DATASET, "train", progress=False)
    index = validation.indices[0]
    fresh, trained = validation[0], train[index]
    assert fresh.meta["shape"] == trained.meta["shape"] and fresh.meta["index"] == index
    assert not np.allclose(fresh.gt_transform, trained.gt_transform)


def test_an_explicit_subset_wins_over_the_splits_own():
    assert len(build_split(DATASET, "val", subset=3, progress=False)) == 3
    assert len(build_split(DATASET, "train", subset=1, progress=False)) == 1
