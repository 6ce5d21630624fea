"""The pair cache and build_dataset: generate once, reload identical pairs, resume, errors."""

from __future__ import annotations

import json
import multiprocessing
import sys

import numpy as np
import pytest
from omegaconf import OmegaConf

from linereg.datasets import DATASETS, build_dataset
from linereg.datasets.base import PairDataset
from linereg.datasets.cache import MANIFEST, CachedPairs, CorruptCacheError, cache_path, materialize
from linereg.structures import PairSample

CONFIG = {
    "name": "procedural",
    "num_shapes": 2,
    "protocol": {"name": "airplane", "num_views": 8, "num_points": 256},
    "seed": 3,
}


def _assert_same(a, b):
    for name in ("src_xyz", "tgt_xyz", "src_normals", "tgt_normals", "gt_transform"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.meta == b.meta


def test_cache_holds_exactly_the_generated_pairs(tmp_path):
    generator = build_dataset(CONFIG)
    cached = materialize(generator, tmp_path, workers=0, progress=False)
    assert isinstance(cached, CachedPairs) and len(cached) == len(generator) == 16
    for index in (0, 9, 15):
        _assert_same(cached[index], generator[index])
    manifest = json.loads((cached.path / MANIFEST).read_text())
    assert manifest["settings"]["protocol"]["num_views"] == 8
    assert manifest["settings"]["seed"] == 3
    assert manifest["num_pairs"] == 16 and len(manifest["shards"]) == 2
    assert all(s["file"].endswith(".npz") for s in manifest["shards"])


def test_existing_cache_is_reused_and_partial_cache_resumed(tmp_path):
    generator = build_dataset(CONFIG)
    first = materialize(generator, tmp_path, workers=0, progress=False)
    assert materialize(generator, tmp_path, workers=0, progress=False).manifest == first.manifest
    (first.path / MANIFEST).unlink()
    (first.path / first.manifest["shards"][1]["file"]).unlink()
    resumed = materialize(generator, tmp_path, workers=0, progress=False)
    assert resumed.manifest["generated_pairs"] == 8
    _assert_same(resumed[12], generator[12])


def test_deleted_or_corrupt_shards_are_named_and_regenerated(tmp_path):
    generator = build_dataset(CONFIG)
    first = materialize(generator, tmp_path, workers=0, progress=False)
    deleted, truncated = (first.path / shard["file"] for shard in first.manifest["shards"])
    deleted.unlink()
    truncated.write_bytes(truncated.read_bytes()[:300])
    with pytest.raises(CorruptCacheError, match=rf"{deleted.name}: missing\n.*{truncated.name}: unreadable") as error:
        CachedPairs(first.path)
    assert "generate the cache again" in str(error.value)
    with pytest.warns(RuntimeWarning, match=rf"regenerating: .*{deleted.name}.*{truncated.name}"):
        again = materialize(generator, tmp_path, workers=0, progress=False)
    assert again.manifest["generated_pairs"] == 16
    for index in (0, 15):
        _assert_same(again[index], generator[index])


def test_corrupt_manifest_is_named_and_rewritten(tmp_path):
    generator = build_dataset(CONFIG)
    first = materialize(generator, tmp_path, workers=0, progress=False)
    manifest = first.path / MANIFEST
    manifest.write_text('{"version": 1, "num_pa')
    with pytest.raises(CorruptCacheError, match=rf"{MANIFEST}: not a valid cache manifest \(JSONDecodeError"):
        CachedPairs(first.path)
    manifest.write_text("[1, 2]")
    with pytest.raises(CorruptCacheError, match=r"not a cache manifest \(expected a JSON object"):
        CachedPairs(first.path)
    with pytest.warns(RuntimeWarning, match=rf"{MANIFEST}: unreadable cache manifest; writing a new one"):
        again = materialize(generator, tmp_path, workers=0, progress=False)
    assert again.manifest["generated_pairs"] == 0
    _assert_same(again[3], generator[3])


def test_changed_settings_get_their_own_cache(tmp_path):
    base = build_dataset(CONFIG)
    other = build_dataset({**CONFIG, "seed": 4})
    assert cache_path(base, tmp_path) != cache_path(other, tmp_path)
    assert cache_path(base, tmp_path) == cache_path(build_dataset(CONFIG), tmp_path)


def test_build_dataset_with_cache_dir_uses_worker_processes(tmp_path):
    cached = build_dataset(OmegaConf.create({**CONFIG, "cache_dir": str(tmp_path), "cache_workers": 2}))
    assert isinstance(cached, CachedPairs)
    assert cached.manifest["workers"] == 2
    _assert_same(cached[5], build_dataset(CONFIG)[5])
    reloaded = build_dataset({"name": "cached", "path": str(cached.path)})
    _assert_same(reloaded[15], cached[15])


def test_unlabeled_and_variable_size_pairs_round_trip(tmp_path):
    from linereg.datasets.cache import write_shard
    from linereg.structures import PairSample

    samples = [
        PairSample(np.ones((5, 3), np.float32), np.zeros((7, 3), np.float32), meta={"i": 0}),
        PairSample(
            np.ones((3, 3), np.float32),
            np.zeros((2, 3), np.float32),
            np.ones((3, 3), np.float32),
            gt_transform=np.eye(4, dtype=np.float32),
        ),
    ]
    write_shard(samples, tmp_path / "shard.npz")
    (tmp_path / MANIFEST).write_text(
        json.dumps({"version": 1, "settings": {}, "num_pairs": 2, "shards": [{"file": "shard.npz"}]})
    )
    cached = CachedPairs(tmp_path)
    assert cached[0].gt_transform is None and cached[0].src_normals is None
    assert cached[0].tgt_xyz.shape == (7, 3) and cached[0].meta == {"i": 0}
    np.testing.assert_array_equal(cached[1].src_normals, np.ones((3, 3)))
    assert cached[1].tgt_normals is None and cached[1].gt_transform.shape == (4, 4)
    with pytest.raises(IndexError):
        cached[2]


def test_build_dataset_errors_name_the_problem(tmp_path):
    with pytest.raises(KeyError, match=r"unknown dataset 'modelnet'.*modelnet40"):
        build_dataset({"name": "modelnet"})
    with pytest.raises(ValueError, match=r"unknown argument\(s\) \['num_shape'\].*num_shapes"):
        build_dataset({"name": "procedural", "num_shape": 3})
    with pytest.raises(ValueError, match=r"needs argument\(s\) \['root'\]"):
        build_dataset({"name": "mesh_folder"})
    with pytest.raises(KeyError, match="needs a 'name'"):
        build_dataset({"root": "x"})
    with pytest.raises(TypeError, match="must be a mapping"):
        build_dataset("procedural")
    with pytest.raises(FileNotFoundError, match="no pair cache"):
        build_dataset({"name": "cached", "path": str(tmp_path)})


def test_every_source_is_registered():
    assert set(DATASETS.names()) >= {
        "procedural",
        "mesh_folder",
        "modelnet40",
        "threedmatch",
        "rgbd_sequence",
        "pairs_folder",
        "cached",
    }


class _LockstepPairs(PairDataset):
    """Large random pairs; every process waits for the others before each pair, so that
    concurrent writers of the same cache write each shard at the same moment."""

    registry_name = "lockstep"

    def __init__(self, barrier) -> None:
        self.barrier = barrier

    def __len__(self) -> int:
        return 6

    def settings(self) -> dict:
        return {"pairs": 6, "points": 50_000}

    def make_pair(self, index: int) -> PairSample:
        self.barrier.wait(timeout=60)
        rng = np.random.default_rng(index)
        xyz = rng.standard_normal((50_000, 3)).astype(np.float32)
        return PairSample(src_xyz=xyz, tgt_xyz=xyz + 1, gt_transform=np.eye(4, dtype=np.float32), meta={"i": index})


def _generate_in_lockstep(barrier, cache_root, errors) -> None:
    """Child process: generate the lockstep cache (one pair per shard), report any error."""
    try:
        cached = materialize(_LockstepPairs(barrier), cache_root, workers=0, shard_size=1, progress=False)
        np.testing.assert_array_equal(cached[5].tgt_xyz, _LockstepPairs(barrier).make_pair(5).tgt_xyz)
    except Exception as error:  # reported to the test, which fails with it
        errors.put(f"{type(error).__name__}: {error}")


@pytest.mark.skipif(sys.platform != "linux", reason="forks the test process (Linux)")
def test_processes_generating_the_same_cache_at_once_do_not_collide(tmp_path):
    context = multiprocessing.get_context("fork")  # spawn would re-import torch in each child (slow)
    barrier, errors = context.Barrier(2), context.Queue()
    processes = [context.Process(target=_generate_in_lockstep, args=(barrier, tmp_path, errors)) for _ in range(2)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(timeout=120)
    reported = []
    while not errors.empty():
        reported.append(errors.get(timeout=1))
    assert not reported, reported
    assert [process.exitcode for process in processes] == [0, 0]
    (folder,) = tmp_path.iterdir()
    assert sorted(file.name for file in folder.iterdir()) == [MANIFEST] + [
        f"shard_{i:07d}_{i + 1:07d}.npz" for i in range(6)
    ]  # no temporaries left behind
    assert len(CachedPairs(folder)) == 6
