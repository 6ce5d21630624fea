"""Benchmark harness (train/benchmark.py, registration/benchmark_results.py): records, written results,
pair sources, CLI."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from linereg.datasets.benchmark_pairs import (
    airplane_pairs,
    dragon_pairs,
    human_pairs,
    select_indices,
    threedmatch_pairs,
)
from linereg.datasets.procedural import procedural_shape
from linereg.io import write_point_cloud, write_transform
from linereg.metrics import ERROR_KEYS
from linereg.paths import REPO_ROOT
from linereg.random_poses import random_transform_paper
from linereg.registration.benchmark_results import plot_alpha_recall, recall_lines, recall_shortfalls
from linereg.registration.methods import MethodResult
from linereg.structures import PairSample
from linereg.train.benchmark import (
    benchmark,
    build_methods,
    expand_folder_argument,
    object_diameter,
    run_benchmark,
    write_results,
)
from tests.conftest import compose_config

RECORD_KEYS = {
    "pair",
    "method",
    "seconds",
    "diameter",
    "transform",
    "gt_transform",
    "meta",
    "info",
    "confident",
    "fitness",
    "bbox_diagonal",
    *ERROR_KEYS,
}


def _tiny_pair(seed: int, num_points: int = 300) -> PairSample:
    """A procedural shape, its points moved by the paper's composite transform."""
    mesh = procedural_shape(np.random.default_rng(seed))
    src, _ = trimesh.sample.sample_surface_even(mesh, num_points, seed=seed)
    transform = random_transform_paper(1, seed, max_angle_deg=10.0, dtype=torch.float64)[0].numpy()
    tgt = src @ transform[:3, :3].T + transform[:3, 3]
    return PairSample(
        src_xyz=src.astype(np.float32),
        tgt_xyz=tgt.astype(np.float32),
        gt_transform=transform.astype(np.float32),
        meta={"shape": f"procedural_{seed}"},
    )


@pytest.fixture(scope="module")
def tiny_records():
    pairs = [_tiny_pair(1), _tiny_pair(2)]
    methods = build_methods(["icp_point", "plane"], {"plane": {"name": "icp_plane", "max_iterations": 50}})
    return run_benchmark(pairs, methods, progress=False)


def test_run_benchmark_records_every_pair_and_method(tiny_records):
    assert [(r["pair"], r["method"]) for r in tiny_records] == [
        (0, "icp_point"),
        (0, "plane"),
        (1, "icp_point"),
        (1, "plane"),
    ]
    for record in tiny_records:
        assert set(record) == RECORD_KEYS
        assert record["err_r_deg"] < 1.0
        assert np.asarray(record["transform"]).shape == (4, 4)
        assert record["diameter"] > 0
    json.dumps(tiny_records)


def test_write_results_writes_json_table_and_plot(tiny_records, tmp_path):
    paths = write_results(tiny_records, tmp_path / "out", settings={"benchmark": {"name": "tiny"}})

    assert set(paths) == {"json", "table", "plot"}
    content = json.loads(paths["json"].read_text())
    assert set(content) == {"settings", "summary", "alpha_recall", "records"}
    assert content["settings"]["benchmark"]["name"] == "tiny"
    assert set(content["summary"]) == {"icp_point", "plane"}
    summary = content["summary"]["plane"]
    for key in (*ERROR_KEYS, "seconds"):
        assert {f"{key}_mean", f"{key}_median"} <= set(summary)
    assert summary["pairs"] == 2
    assert summary["success_1deg"] == 1.0
    recall = content["alpha_recall"]
    assert len(recall["alphas"]) == len(recall["recall"]["icp_point"]) == 201
    curve = recall["recall"]["icp_point"]
    assert np.all(np.diff(curve) >= 0)
    assert curve[-1] == 1.0
    assert len(content["records"]) == 4
    table = paths["table"].read_text()
    assert "| icp_point |" in table and "| plane |" in table
    assert "Median" in table and "time mean (s)" in table
    assert paths["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    errors = {name: [r["err_pw_l2"] for r in tiny_records if r["method"] == name] for name in ("icp_point", "plane")}
    assert recall["below_first"]["plane"] == [list(span) for span in recall_shortfalls(errors)["plane"]]
    assert ("on or above `plane` at every alpha" in table) == (not recall["below_first"]["plane"])


def test_the_plot_draws_from_results_json_alone_and_names_its_extra(tiny_records, tmp_path, monkeypatch):
    """The library draws alpha_recall.png from results.json's content; without matplotlib it says
    which extra to install."""
    paths = write_results(tiny_records, tmp_path / "out")
    content = json.loads(paths["json"].read_text())
    drawn = plot_alpha_recall(tmp_path / "again.png", content)
    assert drawn.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    monkeypatch.setitem(sys.modules, "matplotlib.backends.backend_agg", None)
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'linereg\[plot\]'"):
        plot_alpha_recall(tmp_path / "none.png", content)


def test_recall_shortfalls_cover_every_alpha_not_a_grid():
    errors = {"ours": [0.5, 0.5, 2.0, 3.0], "icp": [0.4, 0.6, 1.0, 9.0], "fgr": [5.0, 6.0]}
    # icp recalls 1/4 on (0.4, 0.5] (ours 0) and 3/4 on (1.0, 2.0] (ours 2/4)
    assert recall_shortfalls(errors) == {"icp": [(0.4, 0.5), (1.0, 2.0)], "fgr": []}
    lines = recall_lines(errors)
    assert lines[2] == "- `ours` is below `icp` for alpha in (0.4, 0.5], (1, 2]"
    assert lines[3] == "- `ours` is on or above `fgr` at every alpha"
    assert recall_shortfalls({"ours": [0.1], "same": [0.1]}) == {"same": []}


def test_relative_alpha_divides_by_the_diameter(tiny_records, tmp_path):
    alphas = [0.0, 1e-12, 1.0]
    paths = write_results(tiny_records, tmp_path, alphas=alphas, relative_alpha=True)

    recall = json.loads(paths["json"].read_text())["alpha_recall"]
    assert recall["relative"] is True
    assert recall["recall"]["plane"] == [0.0, 0.0, 1.0]


def test_run_benchmark_rejects_unlabelled_pairs():
    pair = _tiny_pair(3)
    pair.gt_transform = None
    with pytest.raises(ValueError, match="needs ground truth"):
        run_benchmark([pair], build_methods(["icp_point"], {}), progress=False)


def test_run_benchmark_names_the_failing_method():
    def broken(src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        raise ArithmeticError("diverged")

    with pytest.raises(RuntimeError, match=r"method 'broken' failed on pair 0.*diverged"):
        run_benchmark([_tiny_pair(4)], {"broken": broken}, progress=False)


def test_build_methods_rejects_unknown_names():
    with pytest.raises(KeyError, match="unknown method 'nope'"):
        build_methods(["nope"], {"fast": {"name": "icp_point"}})


def test_select_indices_is_seeded_sorted_and_distinct():
    chosen = select_indices(150, 20, seed=3)
    assert chosen == select_indices(150, 20, seed=3)
    assert chosen == sorted(set(chosen)) and len(chosen) == 20
    assert chosen != select_indices(150, 20, seed=4)
    assert select_indices(5, None, seed=0) == select_indices(5, 9, seed=0) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="pairs must be >= 1"):
        select_indices(5, 0, seed=0)


def test_expand_folder_argument(tmp_path):
    argv = ["benchmark=human", f"benchmark={tmp_path}", "pairs=3"]
    assert expand_folder_argument(argv) == [
        "benchmark=human",
        "benchmark=folder",
        f"benchmark.root={tmp_path.resolve()}",
        "pairs=3",
    ]


def test_object_diameter_is_rotation_invariant():
    points = np.random.default_rng(0).normal(size=(200, 3))
    rotation = random_transform_paper(1, 0, dtype=torch.float64)[0, :3, :3].numpy()
    assert object_diameter(points @ rotation.T) == pytest.approx(object_diameter(points))


def _write_pair_folder(folder: Path) -> None:
    for seed in (5, 6):
        pair = _tiny_pair(seed)
        write_point_cloud(folder / f"p{seed}_src.ply", pair.src_xyz)
        write_point_cloud(folder / f"p{seed}_tgt.ply", pair.tgt_xyz)
        write_transform(folder / f"p{seed}_gt.txt", pair.gt_transform)


def _check_folder_results(out: Path, folder: Path) -> None:
    content = json.loads((out / "results.json").read_text())
    assert content["settings"]["benchmark"] == {
        "name": "folder",
        "root": str(folder.resolve()),
        "num_points": None,
        "half_extent": None,
    }
    assert content["summary"]["icp_point"]["pairs"] == 2
    assert content["summary"]["icp_point"]["err_r_deg_mean"] < 1.0
    assert (out / "table.md").is_file() and (out / "alpha_recall.png").is_file()


def test_config_runs_a_folder_of_pairs(tmp_path):
    from omegaconf import OmegaConf

    folder, out = tmp_path / "pairs", tmp_path / "out"
    _write_pair_folder(folder)
    overrides = ["benchmark=folder", f"benchmark.root={folder.resolve()}", "methods=[icp_point]"]
    config = compose_config("benchmark", [*overrides, f"out={out}", "progress=false"])

    assert set(config.method_presets) >= {"icp_point", "icp_plane", "fgr", "fricp"}
    benchmark(OmegaConf.to_container(config, resolve=True))

    _check_folder_results(out, folder)


def test_every_method_preset_builds():
    config = compose_config("benchmark", ["benchmark=dragon"])

    presets = config.method_presets
    assert set(build_methods(list(presets), presets)) == set(presets)
    assert config.benchmark.name == "dragon" and config.pairs is None


@pytest.mark.slow
def test_command_line_runs_a_folder_of_pairs(tmp_path):
    folder, out = tmp_path / "pairs", tmp_path / "out"
    _write_pair_folder(folder)
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    command = [sys.executable, "-m", "train.benchmark", f"benchmark={folder}", "methods=[icp_point]"]
    command += [f"out={out}", "progress=false"]

    subprocess.run(command, cwd=REPO_ROOT, env=env, check=True, capture_output=True, timeout=300)

    _check_folder_results(out, folder)


def _median_nn(points: np.ndarray, transform: np.ndarray, target: np.ndarray) -> float:
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    return float(np.median(cKDTree(target).query(moved)[0]))


def _assert_ground_truth_aligns(pairs: list[PairSample], absolute: float | None) -> None:
    for pair in pairs:
        truth = pair.gt_transform.astype(np.float64)
        aligned = _median_nn(pair.src_xyz, truth, pair.tgt_xyz)
        unaligned = min(
            _median_nn(pair.src_xyz, np.eye(4), pair.tgt_xyz),
            _median_nn(pair.src_xyz, np.linalg.inv(truth), pair.tgt_xyz),
        )
        assert aligned < 0.75 * unaligned, pair.meta
        if absolute is not None:
            assert aligned < absolute, pair.meta


@pytest.mark.shared_data
@pytest.mark.parametrize("source", [human_pairs, airplane_pairs])
def test_protocol_pairs_are_aligned_by_their_ground_truth(source, shared_data):
    pairs = source(pairs=2, seed=0)

    assert len(pairs) == 2
    np.testing.assert_array_equal(pairs[1].gt_transform, source(pairs=2, seed=0)[1].gt_transform)
    for pair in pairs:
        assert pair.src_xyz.shape == pair.tgt_xyz.shape == (1024, 3)
        assert np.abs(pair.tgt_xyz).max() <= 1.0 + 0.2 * np.sqrt(3) + 1e-5
    _assert_ground_truth_aligns(pairs, absolute=0.05)


@pytest.mark.shared_data
def test_dragon_pairs_share_the_source_under_different_poses(shared_data):
    pairs = dragon_pairs(pairs=3, seed=0)

    assert len(pairs) == 3
    np.testing.assert_array_equal(pairs[0].src_xyz, pairs[2].src_xyz)
    assert not np.allclose(pairs[0].gt_transform, pairs[1].gt_transform)
    _assert_ground_truth_aligns(pairs, absolute=0.05)


@pytest.mark.shared_data
def test_threedmatch_pairs_are_aligned_by_their_ground_truth(shared_data):
    pairs = threedmatch_pairs(seed=0)

    assert [pair.meta["dataset"] for pair in pairs] == ["threedmatch", "geotransformer_demo"]
    assert pairs[0].meta["src_fragment"] == "cloud_bin_4" and pairs[0].meta["tgt_fragment"] == "cloud_bin_0"
    _assert_ground_truth_aligns(pairs, absolute=None)


def test_run_benchmark_resumes_from_its_journal(tmp_path):
    pairs = [_tiny_pair(1), _tiny_pair(2)]
    journal = tmp_path / "records.jsonl"
    first = run_benchmark(pairs[:1], build_methods(["icp_point"], {}), progress=False, journal=journal)
    assert len(journal.read_text().splitlines()) == 1

    seen = []

    def identity(src, tgt, src_normals=None, tgt_normals=None):
        seen.append(len(src))
        return MethodResult(transform=np.eye(4), seconds=0.0)

    resumed = run_benchmark(pairs, {"icp_point": identity}, progress=False, journal=journal)
    assert seen == [len(pairs[1].src_xyz)]  # pair 0 came from the journal
    assert resumed[0] == json.loads(json.dumps(first[0]))
    assert len(resumed) == 2 and len(journal.read_text().splitlines()) == 2


def test_a_resumed_record_is_scored_against_the_pairs_ground_truth(tmp_path):
    pair = _tiny_pair(1)
    journal = tmp_path / "records.jsonl"
    (first,) = run_benchmark([pair], build_methods(["icp_point"], {}), progress=False, journal=journal)
    shifted = pair.gt_transform.copy()
    shifted[0, 3] += 0.3
    moved = dataclasses.replace(pair, gt_transform=shifted)

    def not_run(src, tgt, src_normals=None, tgt_normals=None):
        raise AssertionError("the record should come from the journal")

    (resumed,) = run_benchmark([moved], {"icp_point": not_run}, progress=False, journal=journal)
    assert resumed["transform"] == first["transform"] and resumed["seconds"] == first["seconds"]
    assert resumed["gt_transform"] == np.asarray(moved.gt_transform, dtype=np.float64).tolist()
    expected = np.linalg.norm(np.array(first["transform"])[:3, 3] - shifted[:3, 3])
    assert resumed["err_t_l2"] == pytest.approx(expected, rel=1e-5)
    assert abs(resumed["err_t_l2"] - first["err_t_l2"]) > 0.1


def test_partial_vs_whole_pairs_from_meshes_and_point_files(tmp_path):
    from linereg.datasets.partial_vs_whole import PartialVsWholeSettings, partial_vs_whole_pairs

    procedural_shape(np.random.default_rng(3)).export(tmp_path / "shape.off")
    points, _ = trimesh.sample.sample_surface(procedural_shape(np.random.default_rng(4)), 5000, seed=4)
    np.savetxt(tmp_path / "cloud.xyz", points)
    (tmp_path / "notes.md").write_text("not a shape")
    settings = PartialVsWholeSettings(source_points=256, target_points=512, dense_points=4000)
    pairs = partial_vs_whole_pairs(tmp_path, pairs=4, seed=1, settings=settings)
    again = partial_vs_whole_pairs(tmp_path, pairs=4, seed=1, settings=settings)

    assert [Path(pair.meta["file"]).name for pair in pairs] == ["cloud.xyz", "shape.off"] * 2
    for pair, twin in zip(pairs, again, strict=True):
        assert pair.src_xyz.shape == (256, 3) and pair.tgt_xyz.shape == (512, 3)
        np.testing.assert_array_equal(pair.tgt_xyz, twin.tgt_xyz)
        truth = pair.gt_transform.astype(np.float64)
        moved = pair.src_xyz @ truth[:3, :3].T + truth[:3, 3]
        aligned = np.median(cKDTree(pair.tgt_xyz).query(moved)[0])
        unaligned = np.median(cKDTree(pair.tgt_xyz).query(pair.src_xyz)[0])
        assert aligned < 0.75 * unaligned and aligned < 0.15
    with pytest.raises(FileNotFoundError, match="not a folder of shapes"):
        partial_vs_whole_pairs(tmp_path / "shape.off")
    with pytest.raises(FileNotFoundError, match="no mesh or point file"):
        partial_vs_whole_pairs(tmp_path, patterns=["*.stl"])


@pytest.mark.shared_data
def test_partial_vs_whole_source_on_the_shared_airplanes(shared_data):
    config = {"name": "partial_vs_whole", "root": "modelnet40_normal_resampled", "patterns": ["airplane/*.txt"]}
    from linereg.datasets.benchmark_pairs import select_pairs

    pairs = select_pairs(config, pairs=2, seed=0)
    assert [pair.src_xyz.shape for pair in pairs] == [(1024, 3)] * 2
    assert [pair.tgt_xyz.shape for pair in pairs] == [(2048, 3)] * 2
    assert all(np.abs(pair.tgt_xyz).max() <= 1.0 + 0.2 * np.sqrt(3) + 1e-5 for pair in pairs)


@pytest.fixture(scope="module")
def network_run(tmp_path_factory):
    """A run folder of ``python -m train``'s format holding a small untrained RPM-Net."""
    from linereg.models import MODELS
    from linereg.train.checkpoint import save_checkpoint

    model_config = {"name": "rpmnet", "feature_dim": 16, "num_neighbors": 8, "test_iters": 2}
    torch.manual_seed(0)
    run = tmp_path_factory.mktemp("run")
    model = MODELS.build(model_config)
    state = {"config": {"model": model_config, "trainer": {"num_points": 256}}, "model": model.state_dict()}
    save_checkpoint(state, run / "checkpoints" / "best.pt")
    return run


def test_networks_run_bare_and_finished_by_the_solver(network_run):
    pair = _tiny_pair(1, num_points=600)
    presets = {"finished": {"network": str(network_run), "refine": True}}

    records = run_benchmark([pair], build_methods([str(network_run), "finished"], presets), progress=False)

    bare, finished = records
    assert bare["info"]["path"] == "network"
    assert finished["info"]["path"] in ("polished network", "solver")
    assert finished["err_r_deg"] < 0.5 and finished["confident"]
    assert finished["err_r_deg"] < bare["err_r_deg"]


def test_refine_finishes_every_network_but_no_other_method(network_run):
    methods = build_methods([str(network_run), "icp_point"], {}, refine=True)

    assert methods[str(network_run)].finish is not None
    assert not hasattr(methods["icp_point"], "finish")
