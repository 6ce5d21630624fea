"""Pretrained weights by name (:mod:`linereg.pretrained`): what ships, and every place a name goes."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import linereg
from linereg import pretrained
from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.models import load_model
from linereg.train import loop
from linereg.train.evaluate import evaluate
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = {f"rpm_{loss}_{protocol}" for loss in ("gt", "cd", "ours") for protocol in ("airplane", "human", "real")}


def _compose(name: str, overrides: list[str]):
    return compose_config(name, [f"paths.root_dir={ROOT}", *overrides])


def test_every_recipe_cell_of_rpm_net_ships_with_its_record():
    assert SHIPPED <= set(pretrained.names())
    for name in pretrained.names():
        record = pretrained.entry(name)
        experiment, protocol = name.rsplit("_", 1)
        assert pretrained.path(name).is_file() and pretrained.path(name).stat().st_size < 4_000_000
        data = f"protocol={protocol}"
        if protocol == "objects":
            data = "protocol=airplane dataset=objects_and_rooms task_name=rpm_ours_objects"
        assert record.command == f"linereg-train experiment={experiment} {data} seed=0"
        assert record.description and "\n" not in record.description
        assert math.isfinite(record.test_err_r_deg) and 0 < record.test_err_r_deg < 10


def test_an_unknown_name_lists_the_shipped_ones():
    with pytest.raises(KeyError, match="rpm_ours_airplane"):
        pretrained.path("rpm_ours_plane")
    with pytest.raises(FileNotFoundError, match=r"pretrained name: .*rpm_ours_airplane"):
        find_checkpoint("rpm_ours_plane")


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_a_name_loads_its_model_with_portable_data_paths(name):
    model, state = load_model(name)
    assert state["path"] == str(pretrained.path(name))
    assert type(model).__name__ == "RPMNet" and state["config"]["model"]["num_neighbors"] == 16
    stored = torch.load(pretrained.path(name), weights_only=True)
    assert set(stored) == {"format", "version", "config", "model", "progress", "pretrained"}
    text = json.dumps(stored["config"])
    assert "${shared_data}/" in stored["config"]["dataset"]["root"]
    assert "/work/" not in text and "/home/" not in text and "/root/" not in text


def test_the_general_model_loads_by_name_with_every_part_portable():
    model, state = load_model("rpm_ours_objects")
    assert type(model).__name__ == "RPMNet" and state["config"]["task_name"] == "rpm_ours_objects"
    stored = torch.load(pretrained.path("rpm_ours_objects"), weights_only=True)
    parts = stored["config"]["dataset"]["datasets"]
    assert list(parts) == ["airplanes", "other_classes", "meshes", "rooms"]
    assert all(part["root"].startswith("${shared_data}/") for part in parts.values())
    assert stored["config"]["dataset"]["common"]["protocol"]["target"] == "mixed"
    assert "/work/" not in json.dumps(stored["config"])


def test_portable_paths_round_trip(tmp_path, monkeypatch):
    shared, cache = tmp_path / "shared", tmp_path / "run" / "data_cache"
    shared.mkdir()
    config = {"dataset": {"root": str(shared / "meshes"), "cache_dir": str(cache), "name": "x"}, "k": [str(tmp_path)]}
    portable = pretrained.portable_config(config, shared, cache)
    assert portable == {
        "dataset": {"root": "${shared_data}/meshes", "cache_dir": "${cache_dir}", "name": "x"},
        "k": [str(tmp_path)],
    }
    monkeypatch.setenv("LINEREG_SHARED_DATA", str(shared))
    monkeypatch.chdir(tmp_path)
    assert pretrained.local_config(portable) == {
        "dataset": {"root": str(shared / "meshes"), "cache_dir": str(tmp_path / "data_cache"), "name": "x"},
        "k": [str(tmp_path)],
    }


def test_init_from_a_name_starts_from_its_weights(tmp_path):
    cfg = _compose(
        "train",
        ["debug=tiny", f"paths.output_dir={tmp_path}", "init_from=rpm_gt_airplane", "trainer.untrained=true"],
    )
    loop.train(cfg)
    trained = load_checkpoint(tmp_path)["model"]
    shipped = load_checkpoint("rpm_gt_airplane")["model"]
    assert trained.keys() == shipped.keys()
    assert all(torch.equal(trained[key], shipped[key]) for key in shipped)


def _pair(seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bumpy ellipsoid and a copy turned by 20 degrees about z: (src, tgt, T)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(1500, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    src = x * (1 + 0.25 * np.sin(3 * x[:, :1]) * np.cos(2 * x[:, 1:2])) * np.array([1.4, 1.0, 0.7])
    angle = math.radians(20)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    T[:3, 3] = [0.1, -0.05, 0.05]
    return src, src @ T[:3, :3].T + T[:3, 3], T


def test_register_takes_a_name():
    src, tgt, T = _pair()
    result = linereg.register(src, tgt, method="rpm_ours_airplane", refine=True)
    assert result.info["checkpoint"] == str(pretrained.path("rpm_ours_airplane")) and result.confident
    rotation = result.transformation[:3, :3].T @ T[:3, :3]
    assert math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))) < 1.0


def test_the_commands_take_a_name(tmp_path):
    src, tgt, _ = _pair()
    np.save(tmp_path / "a.npy", src)
    np.save(tmp_path / "b.npy", tgt)
    command = [sys.executable, "-m", "linereg.train.register", f"source={tmp_path / 'a.npy'}"]
    command += [f"target={tmp_path / 'b.npy'}", "method=rpm_ours_human", f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "run" / "result.json").read_text())["method"]["checkpoint"] == "rpm_ours_human"


@pytest.mark.shared_data
@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_a_name_reproduces_its_documented_test_error(name, shared_data, tmp_path):
    """``linereg-evaluate checkpoint=<name>``: its protocol's test pairs, within 0.05 degrees."""
    cfg = _compose("evaluate", [f"checkpoint={name}", f"output_dir={tmp_path}", "progress=false", "num_figures=0"])
    metrics = evaluate(cfg)
    assert abs(metrics["model"]["err_r_deg_mean"] - pretrained.entry(name).test_err_r_deg) <= 0.05
