"""Every registry of the project follows one idiom: ``Registry.build({name: ..., **kwargs})``.

For each registry: an unknown name raises ``UnknownNameError`` (a ``KeyError``) listing the
registered names; an unknown argument raises ``ArgumentError`` naming it and the accepted ones;
every registered name builds (those that need data files from a small folder written here).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import linereg.datasets
import linereg.losses
import linereg.models
import linereg.registration
from linereg.datasets.benchmark_pairs import PAIR_SOURCES
from linereg.io import write_point_cloud, write_transform
from linereg.registry import ArgumentError, Registry, UnknownNameError
from linereg.train.optim import OPTIMIZERS, SCHEDULERS

PARAMETERS = [torch.nn.Parameter(torch.zeros(2))]
TINY_PROCEDURAL = {"name": "procedural", "num_shapes": 2, "split": "val"}


def _optimizer() -> torch.optim.Optimizer:
    return torch.optim.SGD(PARAMETERS, lr=0.1)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, str]:
    """A pairs folder, a scan folder, a mesh folder and a cache folder of two procedural pairs."""
    root = tmp_path_factory.mktemp("registries")
    rng = np.random.default_rng(0)
    pairs = root / "pairs"
    pairs.mkdir()
    cloud = rng.normal(size=(200, 3)).astype(np.float32)
    write_point_cloud(pairs / "a_src.ply", cloud)
    write_point_cloud(pairs / "a_tgt.ply", cloud + 0.1)
    gt = np.eye(4)
    gt[:3, 3] = 0.1
    write_transform(pairs / "a_gt.txt", gt)
    scans = root / "scans"
    scans.mkdir()
    for index in range(4):
        write_point_cloud(scans / f"scan_{index}.ply", cloud + 0.05 * index)
    meshes = root / "meshes"
    meshes.mkdir()
    trimesh.creation.box(extents=(1.0, 0.6, 0.3)).export(meshes / "box.ply")
    dataset = linereg.datasets.build_dataset(TINY_PROCEDURAL)
    cache = linereg.datasets.materialize(dataset, root / "cache", workers=1, progress=False)
    return {"pairs": str(pairs), "scans": str(scans), "meshes": str(meshes), "cache": str(cache.path)}


# registry -> (positional arguments of build, {name: options that build it}); a name needing data
# files gets its options from the ``data`` fixture through a callable.
CASES: dict[str, tuple[Registry, tuple, dict]] = {
    "losses": (linereg.losses.LOSSES, (), {name: {} for name in linereg.losses.LOSSES.names()}),
    "models": (
        linereg.models.MODELS,
        (),
        {
            "dcp_v1": {"emb_dims": 32, "k": 8},
            "dcp_v2": {"emb_dims": 32, "k": 8, "ff_dims": 64},
            "rpmnet": {"feature_dim": 16, "num_neighbors": 8},
            "fmr": {"dim_k": 64, "decoder_points": 64},
        },
    ),
    "datasets": (
        linereg.datasets.DATASETS,
        (),
        {
            "procedural": {key: value for key, value in TINY_PROCEDURAL.items() if key != "name"},
            "concat": {"datasets": [TINY_PROCEDURAL, TINY_PROCEDURAL]},
            "cached": lambda data: {"path": data["cache"]},
            "pairs_folder": lambda data: {"root": data["pairs"]},
            "scan_folder": lambda data: {"root": data["scans"], "num_points": 64},
            "mesh_folder": lambda data: {"root": data["meshes"]},
        },
    ),
    "methods": (linereg.registration.METHODS, (), {name: {} for name in linereg.registration.METHODS.names()}),
    "pair sources": (
        PAIR_SOURCES,
        (),
        {
            "dataset": {"dataset": TINY_PROCEDURAL, "pairs": 1},
            "folder": lambda data: {"root": data["pairs"]},
            "partial_vs_whole": lambda data: {"root": data["meshes"], "pairs": 1},
        },
    ),
    "optimizers": (OPTIMIZERS, (PARAMETERS,), {"adam": {"lr": 0.1}, "adamw": {"lr": 0.1}, "sgd": {"lr": 0.1}}),
    "schedulers": (SCHEDULERS, (None,), {name: {"epochs": 3} for name in SCHEDULERS.names()}),
}
# Registered names that read a real dataset (shared data): built in their own tests.
NEEDS_REAL_DATA = {
    "datasets": {"modelnet40", "rgbd_sequence", "threedmatch"},  # tests/test_datasets_shared.py
    "pair sources": {"3dmatch", "airplane", "dragon", "fragments", "human", "run"},  # tests/test_benchmark.py
}


@pytest.mark.parametrize("kind", CASES)
def test_every_registered_name_has_a_case(kind):
    registry, _, cases = CASES[kind]
    assert set(registry.names()) == set(cases) | NEEDS_REAL_DATA.get(kind, set())


@pytest.mark.parametrize("kind", CASES)
def test_unknown_name_lists_the_registered_names(kind):
    registry, args, _ = CASES[kind]
    with pytest.raises(UnknownNameError, match=", ".join(registry.names())) as caught:
        registry.build({"name": "no_such_name"}, *args)
    assert isinstance(caught.value, KeyError)
    with pytest.raises(UnknownNameError, match="needs a 'name'"):
        registry.build({}, *args)


@pytest.mark.parametrize("kind", CASES)
def test_unknown_argument_is_named_with_the_accepted_ones(kind):
    registry, args, cases = CASES[kind]
    for name in cases:
        accepted = registry.accepted(name, len(args))
        if accepted is None:  # a builder taking **kwargs checks its own options
            continue
        with pytest.raises(ArgumentError, match=r"unknown argument\(s\) \['not_an_option'\]; it accepts") as caught:
            registry.build({"name": name, "not_an_option": 1}, *args)
        assert isinstance(caught.value, TypeError) and isinstance(caught.value, ValueError)
        for option in accepted:
            assert option in str(caught.value)


@pytest.mark.parametrize(("kind", "name"), [(kind, name) for kind, (_, _, cases) in CASES.items() for name in cases])
def test_every_registered_name_builds(kind, name, data):
    registry, args, cases = CASES[kind]
    options = cases[name](data) if callable(cases[name]) else cases[name]
    if kind == "schedulers":
        args = (_optimizer(),)
    if kind == "methods" and name == "fricp":
        pytest.importorskip("fricp_cpp")
    built = registry.build({"name": name, **options}, *args)
    if kind != "schedulers":  # the constant schedule is None
        assert built is not None


def test_missing_required_argument_is_named():
    with pytest.raises(ArgumentError, match=r"dataset 'pairs_folder' needs argument\(s\) \['root'\]"):
        linereg.datasets.DATASETS.build({"name": "pairs_folder"})


def test_options_given_twice_are_an_error():
    with pytest.raises(ArgumentError, match="given both"):
        OPTIMIZERS.build({"name": "sgd", "lr": 0.1}, PARAMETERS, lr=0.2)
