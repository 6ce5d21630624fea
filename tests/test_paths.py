"""Data folders resolve the same from any current folder (linereg/paths.py, configs/paths/default.yaml)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from linereg import paths
from linereg.paths import DATA, SHARED_DATA, data_folder_places, shared_data_dir

CONFIGS = paths.REPO_ROOT / "configs"


@pytest.fixture
def checkout(tmp_path, monkeypatch):
    """A project root ``tmp/project`` beside ``tmp/shared/data``; the test runs in ``tmp/outside/run``."""
    project = tmp_path / "project"
    project.mkdir()
    (project / "pyproject.toml").write_text("")
    (tmp_path / "shared" / "data").mkdir(parents=True)
    (tmp_path / "outside" / "run").mkdir(parents=True)
    monkeypatch.setattr(paths, "REPO_ROOT", project)
    monkeypatch.chdir(tmp_path / "outside" / "run")
    for variable in (SHARED_DATA[0], DATA[0]):
        monkeypatch.delenv(variable, raising=False)
    return project


def test_the_default_is_read_from_the_project_root_not_the_current_folder(checkout, tmp_path):
    assert data_folder_places(*SHARED_DATA) == [tmp_path / "shared" / "data", tmp_path / "outside" / "shared" / "data"]
    assert shared_data_dir() == tmp_path / "shared" / "data"


def test_a_relative_folder_is_looked_for_under_the_project_root_then_the_current_folder(
    checkout, tmp_path, monkeypatch
):
    (checkout / "scans").mkdir()
    (tmp_path / "outside" / "run" / "local").mkdir()
    monkeypatch.setenv("LINEREG_SHARED_DATA", "scans")
    assert data_folder_places(*SHARED_DATA) == [checkout / "scans", tmp_path / "outside" / "run" / "scans"]
    assert shared_data_dir() == checkout / "scans"
    monkeypatch.setenv("LINEREG_SHARED_DATA", "local")
    assert shared_data_dir() == tmp_path / "outside" / "run" / "local"
    monkeypatch.setenv("LINEREG_SHARED_DATA", "nowhere")
    assert shared_data_dir() is None


def test_an_absolute_folder_is_used_as_it_is(checkout, tmp_path, monkeypatch):
    monkeypatch.setenv("LINEREG_SHARED_DATA", str(tmp_path / "shared" / ".." / "shared" / "data"))
    assert data_folder_places(*SHARED_DATA) == [tmp_path / "shared" / "data"]
    assert shared_data_dir() == tmp_path / "shared" / "data"


def test_an_installed_package_reads_relative_folders_from_the_current_folder(checkout, tmp_path):
    (checkout / "pyproject.toml").unlink()  # no checkout: site-packages
    assert paths.project_root() is None
    assert data_folder_places(*DATA) == [tmp_path / "outside" / "run" / "data"]


def test_the_configs_resolve_the_data_folders_from_another_folder(checkout, tmp_path, hydra_compose):
    cfg = hydra_compose("train", [f"paths.root_dir={Path.cwd()}", "protocol=human"], config_dir=CONFIGS)
    assert cfg.paths.shared_data_dir == str(tmp_path / "shared" / "data")
    assert cfg.dataset.root == str(tmp_path / "shared" / "data" / "meshes" / "odedstein" / "human")
    assert cfg.paths.data_dir == str(checkout / "data")  # absent: where it belongs, named by the dataset's error
    assert cfg.paths.cache_dir == str(tmp_path / "outside" / "run" / "data_cache")  # what a run writes stays here


def test_the_command_reads_the_same_data_from_any_folder(tmp_path):
    env = {key: value for key, value in os.environ.items() if key not in (SHARED_DATA[0], DATA[0])}
    command = [sys.executable, "-m", "linereg.train", "--cfg", "job", "--resolve", "protocol=airplane"]
    printed = {}
    for folder in (paths.REPO_ROOT, tmp_path):
        result = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True, timeout=120, check=True)
        printed[folder] = [line.strip() for line in result.stdout.splitlines() if "shared_data_dir:" in line]
    assert printed[tmp_path] == printed[paths.REPO_ROOT] != []
