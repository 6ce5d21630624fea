"""Fine-tuning on unlabelled scans: the start network's settings are kept, the checkpoint is chosen by
register's check on the held-out pairs without reading a pose, and the start network is a candidate;
a checkpoint carries the cube its network was trained in."""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf

from linereg.checkpoint import load_checkpoint
from linereg.registration.learned import LearnedRegistration, upgrade_checkpoint
from linereg.train import loop
from linereg.train.fine_tune import given_keys, keep_start_settings
from linereg.train.validation import CHECK_SCORE, Monitor
from tests.test_scan_folder import write_conf, write_scans
from tests.test_train_loop import SMALL_RUN, tiny_config

NAMES = [f"scan_{i}" for i in range(1, 9)]
SCAN_FOLDER = ["experiment=rpm_ours", "dataset=scan_folder", "loss.num_lines=300", "dataset.dense_points=null"]


def _start_network(tmp_path):
    """A run trained one step on a scan folder at 48 points, cube 2, iterate best_fit 0.8: (folder, run)."""
    folder = write_scans(tmp_path / "scans", NAMES)
    write_conf(folder / "poses.conf", NAMES)
    start = [*SCAN_FOLDER, f"dataset.root={folder}", "dataset.frame_gap=2", "dataset.half_extent=2.0"]
    start += ["trainer.num_points=48", "iterate.rule=best_fit", "iterate.keep_fraction=0.8", "evaluate_split=null"]
    start += ["curriculum.stages.full.epochs=1", "trainer.max_steps_per_epoch=1"]
    with pytest.warns(UserWarning, match="register's check"):
        loop.train(tiny_config(tmp_path / "start", *SMALL_RUN, *start, debug=None))
    return folder, tmp_path / "start"


@pytest.fixture(scope="module")
def start_network(tmp_path_factory):
    return _start_network(tmp_path_factory.mktemp("fine_tune"))


def test_the_start_networks_settings_are_kept_unless_given(start_network, tmp_path):
    folder, start = start_network
    cfg = tiny_config(tmp_path, *SMALL_RUN, *SCAN_FOLDER, f"dataset.root={folder}", f"init_from={start}", debug=None)
    assert cfg.trainer.num_points == 64 and cfg.iterate.rule == "last" and cfg.dataset.half_extent == 1.0
    notes = keep_start_settings(cfg, overrides=None)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved["trainer"]["num_points"] == 48 and resolved["dataset"]["num_points"] == 48  # interpolation
    assert resolved["iterate"] == {"rule": "best_fit", "keep_fraction": 0.8}
    assert resolved["dataset"]["half_extent"] == 2.0 and resolved["trainer"]["evaluate_checkpoint"] == "best"
    assert any(note.startswith("trainer.num_points=48 (as ") and "the config said 64" in note for note in notes)
    given = tiny_config(tmp_path, *SMALL_RUN, *SCAN_FOLDER, f"dataset.root={folder}", f"init_from={start}", debug=None)
    chosen = ["dataset=scan_folder", "trainer.num_points=64", "+iterate.rule=last", "seed=1"]
    notes = keep_start_settings(given, overrides=chosen)
    assert given.trainer.num_points == 64 and given.iterate.rule == "last" and given.iterate.keep_fraction == 0.8
    assert given.dataset.half_extent == 2.0  # choosing the dataset's file sets none of its keys
    assert any(note.startswith("trainer.num_points=64 from the command line") for note in notes)
    assert given_keys(["a.b=1", "++c=2", "~d", "e=f=g", "iterate={rule: last}"]) == {"a.b", "c", "e", "iterate.*"}
    mapped = tiny_config(tmp_path, *SMALL_RUN, *SCAN_FOLDER, f"dataset.root={folder}", f"init_from={start}", debug=None)
    keep_start_settings(mapped, overrides=["iterate={rule: last, keep_fraction: 1.0}"])
    assert mapped.iterate.keep_fraction == 1.0 and mapped.trainer.num_points == 48


def test_the_checkpoint_is_chosen_by_the_check_without_reading_a_pose(start_network, tmp_path, monkeypatch):
    folder, start = start_network

    def no_pose(path):
        raise AssertionError(f"a pose was read: {path}")

    monkeypatch.setattr("linereg.datasets.scan_folder.read_conf", no_pose)
    tuning = [*SCAN_FOLDER, f"dataset.root={folder}", "dataset.frame_gap=2", "dataset.poses=poses.conf"]
    tuning += [f"init_from={start}", "evaluate_split=val", "curriculum.stages.full.epochs=2"]
    with pytest.warns(UserWarning, match="register's check"):
        result = loop.train(tiny_config(tmp_path / "run", *SMALL_RUN, *tuning, debug=None))
    content = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert content["best"]["metric"] == CHECK_SCORE and content["best"]["mode"] == "max"
    assert content["evaluated_checkpoint"]["file"] == "best.pt"
    assert content["evaluated_checkpoint"]["epoch"] == content["best"]["epoch"]
    assert "val/err_r_deg_mean" not in result["metrics"] and 0 <= result["metrics"]["val/fitness_mean"] <= 1


def test_a_run_that_does_not_improve_keeps_the_start_network(start_network, tmp_path):
    folder, start = start_network
    tuning = [*SCAN_FOLDER, f"dataset.root={folder}", "dataset.frame_gap=2", f"init_from={start}"]
    tuning += ["evaluate_split=null", "optimizer.lr=0.0", "curriculum.stages.full.epochs=1"]
    with pytest.warns(UserWarning, match="register's check"):
        loop.train(tiny_config(tmp_path / "run", *SMALL_RUN, *tuning, debug=None))
    content = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert content["best"]["epoch"] == 0 and content["evaluated_checkpoint"]["epoch"] == 0
    best, started = load_checkpoint(tmp_path / "run" / "checkpoints" / "best.pt"), load_checkpoint(start)
    assert all((best["model"][key] == started["model"][key]).all() for key in started["model"])


def test_the_check_score_breaks_ties_by_the_loss():
    monitor = Monitor(CHECK_SCORE, mode="min")
    assert monitor.mode == "max"
    assert monitor.observe({CHECK_SCORE: 1.2, "val/loss": 0.5}, 0) == (1.2, True)
    assert monitor.observe({CHECK_SCORE: 1.1, "val/loss": 0.1}, 1) == (1.1, False)
    assert monitor.observe({CHECK_SCORE: 1.2, "val/loss": 0.5}, 2) == (1.2, False)
    assert monitor.observe({CHECK_SCORE: 1.2, "val/loss": 0.4}, 3) == (1.2, True)
    value, improved = monitor.observe({CHECK_SCORE: math.nan, "val/loss": 0.0}, 4)
    assert math.isnan(value) and not improved
    restored = Monitor("val/err_r_deg_mean")
    restored.load(monitor.state())
    assert (
        restored.state()
        == monitor.state()
        == {
            "metric": CHECK_SCORE,
            "mode": "max",
            "value": 1.2,
            "epoch": 3,
            "tie": 0.4,
        }
    )


def test_a_checkpoint_carries_the_cube_it_was_trained_in(start_network, tmp_path):
    _, start = start_network
    state = load_checkpoint(start)
    assert state["half_extent"] == 2.0
    assert LearnedRegistration(start).half_extent == 2.0
    older = {key: value for key, value in torch.load(state["path"], weights_only=True).items() if key != "half_extent"}
    torch.save(older, tmp_path / "older.pt")
    assert "half_extent" not in load_checkpoint(tmp_path / "older.pt")
    assert upgrade_checkpoint(load_checkpoint(tmp_path / "older.pt"))["half_extent"] == 2.0  # its dataset config's


@pytest.mark.parametrize(
    ("name", "cube"), [("rpm_ours_airplane", 1.0), ("rpm_ours_real", 5.0), ("rpm_ours_objects", 1.0)]
)
def test_a_shipped_network_without_the_field_keeps_the_cube_of_its_dataset(name, cube):
    assert "half_extent" not in load_checkpoint(name)
    assert LearnedRegistration(name).half_extent == cube
    assert upgrade_checkpoint(load_checkpoint(name))["half_extent"] == cube
