"""The pair cache is keyed on what generates the pairs: settings, code and library versions."""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest

from linereg.datasets import build_dataset
from linereg.datasets import cache as pair_cache
from linereg.datasets.cache import MANIFEST, cache_path, generator_code, library_versions, materialize

CONFIG = {
    "name": "procedural",
    "num_shapes": 1,
    "protocol": {"name": "airplane", "num_views": 8, "num_points": 64},
    "seed": 3,
}

GENERATOR = """
import numpy as np
import pytest

from linereg.datasets.base import PairDataset
from linereg.structures import PairSample

OFFSET = {offset}


class ProbePairs(PairDataset):
    registry_name = "probe"

    def __len__(self):
        return 8

    def settings(self):
        return {{"pairs": 8}}

    def make_pair(self, index):
        xyz = np.full((4, 3), index, np.float32)
        return PairSample(src_xyz=xyz, tgt_xyz=xyz + OFFSET, meta={{"i": index}})
"""


def _probe_module(folder, monkeypatch, offset: float):
    """Import (or re-import) ``probe_generator`` written into ``folder`` with ``OFFSET = offset``."""
    (folder / "probe_generator.py").write_text(GENERATOR.format(offset=repr(offset)))
    monkeypatch.syspath_prepend(str(folder))
    importlib.invalidate_caches()
    module = importlib.import_module("probe_generator")
    return importlib.reload(module)


def test_the_manifest_records_the_code_and_the_library_versions(tmp_path):
    generator = build_dataset(CONFIG)
    manifest = json.loads((materialize(generator, tmp_path, workers=0, progress=False).path / MANIFEST).read_text())
    assert manifest["code"] == generator_code(generator)["sha256"]
    assert manifest["libraries"]["numpy"] == np.__version__
    assert set(manifest["libraries"]) == set(pair_cache.GENERATOR_LIBRARIES)


def test_the_code_hash_covers_the_modules_that_generate_the_pairs():
    modules = generator_code(build_dataset(CONFIG))["modules"]
    assert {"linereg.datasets.procedural", "linereg.datasets.protocol", "linereg.random_poses"} <= set(modules)
    assert "linereg.losses.line_intersection" not in modules
    concat = build_dataset({"name": "concat", "datasets": [CONFIG, CONFIG]})
    assert {"linereg.datasets.combine", "linereg.datasets.procedural"} <= set(generator_code(concat)["modules"])


def test_a_changed_generator_misses_the_old_cache(tmp_path, monkeypatch):
    probe = _probe_module(tmp_path, monkeypatch, 1.0)
    first = materialize(probe.ProbePairs(), tmp_path / "caches", workers=0, progress=False)
    assert first[2].tgt_xyz[0, 0] == 3.0
    edited = _probe_module(tmp_path, monkeypatch, 10.0)  # same settings, other code
    second = materialize(edited.ProbePairs(), tmp_path / "caches", workers=0, progress=False)
    assert second.path != first.path and second.manifest["generated_pairs"] == 8
    assert second[2].tgt_xyz[0, 0] == 12.0


def test_another_library_version_misses_the_old_cache(tmp_path, monkeypatch):
    generator = build_dataset(CONFIG)
    first = materialize(generator, tmp_path, workers=0, progress=False)
    monkeypatch.setattr(pair_cache, "library_versions", lambda: {**library_versions(), "numpy": "0.0"})
    assert cache_path(generator, tmp_path) != first.path
    again = materialize(generator, tmp_path, workers=0, progress=False)
    assert again.path != first.path and again.manifest["generated_pairs"] == len(generator)


def test_a_cache_whose_manifest_names_other_code_is_generated_again(tmp_path):
    generator = build_dataset(CONFIG)
    first = materialize(generator, tmp_path, workers=0, progress=False)
    manifest = json.loads((first.path / MANIFEST).read_text())
    (first.path / MANIFEST).write_text(json.dumps({**manifest, "code": "written by other code"}))
    with pytest.warns(RuntimeWarning, match="written from other settings, code or library versions"):
        again = materialize(generator, tmp_path, workers=0, progress=False)
    assert again.path == first.path and again.manifest["generated_pairs"] == len(generator)
