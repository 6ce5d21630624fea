"""scripts/prepare_dataset.py and the concat dataset it uses for the Real mix."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from linereg.datasets import build_dataset
from linereg.datasets.splits import dataset_config
from scripts import prepare_dataset

SMALL = {"name": "procedural", "num_shapes": 1, "protocol": {"name": "airplane", "num_views": 5, "num_points": 64}}


def test_concat_splits_partition_the_parts():
    parts = [SMALL, {**SMALL, "seed": 1}]
    train = build_dataset({"name": "concat", "datasets": parts, "split": "train", "train_fraction": 0.7})
    test = build_dataset({"name": "concat", "datasets": parts, "split": "test", "train_fraction": 0.7})
    everything = build_dataset({"name": "concat", "datasets": parts})
    assert (len(train), len(test), len(everything)) == (7, 3, 10)
    assert set(train.indices) | set(test.indices) == set(range(10))
    assert not set(train.indices) & set(test.indices)
    second_part = build_dataset({**SMALL, "seed": 1})
    np.testing.assert_array_equal(everything[7].gt_transform, second_part[2].gt_transform)
    assert everything[7].meta["part"] == 1
    with pytest.raises(ValueError, match="split must be one of"):
        build_dataset({"name": "concat", "datasets": parts, "split": "val"})


def test_concat_common_keys_reach_every_part_and_let_each_split_itself(tmp_path):
    meshes = tmp_path / "meshes"
    for category in ("a", "b"):
        (meshes / category).mkdir(parents=True)
        for number in range(5):
            trimesh.creation.box(extents=(1.0, 0.5 + 0.1 * number, 0.3)).export(
                meshes / category / f"{category}{number}.obj"
            )
    part = {"name": "mesh_folder", "root": str(meshes), "split_rule": "random", "train_fraction": 0.6}
    parts = [{**part, "categories": "a"}, {**part, "categories": "b"}]
    common = {"protocol": {"name": "airplane", "num_views": 2, "max_angle_deg": 15.0}, "split": "train", "seed": 3}
    train = build_dataset({"name": "concat", "datasets": parts, "common": common})
    assert len(train) == 2 * 3 * 2  # each part's 3 training shapes, 2 views each; the concat keeps all
    assert [p.protocol.max_angle_deg for p in train.parts] == [15.0, 15.0]
    assert [p.seed for p in train.parts] == [3, 3]
    test = build_dataset({"name": "concat", "datasets": parts, "common": {**common, "split": "test"}})
    assert {p.shapes.items[0][0] for p in test.parts} == {"a", "b"} and len(test) == 2 * 2 * 2
    with pytest.raises(TypeError, match="common must be a mapping"):
        build_dataset({"name": "concat", "datasets": parts, "common": "train"})


def test_a_concat_part_with_its_own_splits_takes_them_instead_of_common():
    """Named parts in order; the part that splits itself (as depth frames split in time) takes its
    own entry and variant, never the concat's ``common``, and is left out where its entry is null."""
    own = {
        **SMALL,
        "splits": {"train": {"num_shapes": 2}, "val": None, "test": {"split": "test"}},
        "variants": {"easy": {"protocol": {"max_angle_deg": 5.0}}},
    }
    config = {
        "name": "concat",
        "datasets": {"shapes": SMALL, "frames": own},
        "common": {"seed": 3},
        "splits": {"train": {"common": {"split": "train"}}, "val": {"common": {"split": "val"}}},
        "variants": {"easy": {"common": {"protocol": {"max_angle_deg": 15.0}}}},
    }
    train = build_dataset(dataset_config(config, "train", "easy"))
    assert [len(part) for part in train.parts] == [5, 10]
    assert [part.seed for part in train.parts] == [3, 0]
    assert [part.protocol.max_angle_deg for part in train.parts] == [15.0, 5.0]
    assert [part["split"] for part in dataset_config(config, "val")["datasets"]] == ["val"]
    test = dataset_config(config, "test")["datasets"]
    assert test[1] == {**SMALL, "split": "test"} and "common" not in dataset_config(config, "test")
    with pytest.raises(ValueError, match="has no variant 'hard'"):
        dataset_config({**config, "variants": {"hard": {}}}, "train", "hard")


def test_a_variant_leaves_out_the_named_parts_it_sets_to_null():
    """A curriculum stage on one part of a concat: the variant nulls the others."""
    own = {**SMALL, "splits": {"train": {"num_shapes": 2}}, "variants": {"frames_only": {"seed": 4}}}
    config = {
        "name": "concat",
        "datasets": {"shapes": SMALL, "frames": own},
        "splits": {"train": {"common": {"split": "train"}}},
        "variants": {"frames_only": {"datasets": {"shapes": None}}},
    }
    train = build_dataset(dataset_config(config, "train", "frames_only"))
    assert [(len(part), part.seed) for part in train.parts] == [(10, 4)]
    assert len(build_dataset(dataset_config(config, "train")).parts) == 2


def test_prepare_procedural_writes_a_loadable_cache(tmp_path, capsys):
    argv = ["procedural", "--num-shapes", "1", "--out", str(tmp_path), "--workers", "0", "--splits", "test"]
    assert prepare_dataset.main(argv) == 0
    out = capsys.readouterr().out
    assert "procedural test: 18 pairs in" in out and "load with: {name: cached, path:" in out
    path = out.split("path: ")[1].split("}")[0]
    cached = build_dataset({"name": "cached", "path": path})
    assert len(cached) == 18 and cached[3].src_xyz.shape == (1024, 3)


def test_paper_configs_match_the_paper_protocol(tmp_path):
    (tmp_path / "airplane" / "train").mkdir(parents=True)
    configs = prepare_dataset.airplane_configs(tmp_path, seed=0)
    assert configs["train"]["name"] == "modelnet40" and configs["train"]["max_shapes"] == 625
    assert configs["train"]["train_fraction"] * 625 == pytest.approx(500)
    (tmp_path / "airplane" / "train" / "airplane_0001.off").touch()
    meshes = prepare_dataset.airplane_configs(tmp_path, seed=0)["test"]
    assert meshes["name"] == "mesh_folder" and meshes["protocol"]["view_axis"] == [0, 0, 1]
    human = prepare_dataset.human_configs(tmp_path, seed=0)["train"]
    assert human["protocol"] == "human" and human["train_fraction"] * 110 == pytest.approx(100)

    for folder in ("3dmatch/scene_a", "3dmatch/scene_b", "rgbd/chess/seq-01", "rgbd/tum/fr1"):
        (tmp_path / folder).mkdir(parents=True)
    for scene in ("scene_a", "scene_b"):
        (tmp_path / "3dmatch" / scene / "cloud_bin_0.ply").touch()
    (tmp_path / "rgbd/chess/seq-01/frame-000000.depth.png").touch()
    (tmp_path / "rgbd/tum/fr1/depth.txt").touch()
    real = prepare_dataset.real_configs(tmp_path / "3dmatch", tmp_path / "rgbd", seed=0)["train"]
    names = [(part["name"], part["root"].rsplit("/", 1)[-1]) for part in real["datasets"]]
    assert names == [
        ("threedmatch", "scene_a"),
        ("threedmatch", "scene_b"),
        ("rgbd_sequence", "seq-01"),
        ("rgbd_sequence", "fr1"),
    ]
    assert real["datasets"][0]["min_overlap"] == 0.7 and real["datasets"][2]["frame_gap"] == 20
    with pytest.raises(SystemExit, match="no 3DMatch scene"):
        prepare_dataset.real_configs(tmp_path / "empty", None, seed=0)
