"""The four commands: ``--help`` pages, one-line errors with exit code 2 for bad arguments and files,
and no run folder left by a failed command."""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigAttributeError

from linereg.io import write_point_cloud
from linereg.registration.iterates import IterateRule
from linereg.train.__main__ import main as train_main
from linereg.train.cli import EXTRAS, one_line, remove_unused_run_folder
from linereg.train.evaluate import iterate_rule

ROOT = Path(__file__).resolve().parent.parent
MODULES = {
    "linereg-train": "linereg.train",
    "linereg-evaluate": "linereg.train.evaluate",
    "linereg-register": "linereg.train.register",
    "linereg-benchmark": "linereg.train.benchmark",
}


def _run(arguments: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {key: value for key, value in os.environ.items() if key != "HYDRA_FULL_ERROR"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, *arguments], cwd=cwd, capture_output=True, text=True, env=env, timeout=300, check=False
    )


def _assert_usage_error(done: subprocess.CompletedProcess, command: str, *named: str) -> str:
    """Exit code 2 and one stderr line ``<command>: error: ...`` naming ``named``; no traceback."""
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"{command}: error: ") and "Traceback" not in done.stderr
    for text in named:
        assert text in lines[0], lines[0]
    return lines[0]


def _main(command: str):
    """The ``main`` of a command's module."""
    return importlib.import_module(MODULES[command]).main if command != "linereg-train" else train_main


def _run_in_process(command: str, arguments: list[str], monkeypatch, tmp_path) -> int:
    """Run a command's ``main`` here (no interpreter start-up); its exit code."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", [command, *arguments])
    try:
        _main(command)()
    except SystemExit as exit:
        return int(exit.code or 0)
    return 0


@pytest.mark.parametrize("command", list(MODULES))
def test_help_has_a_usage_line_the_main_keys_and_examples(command, tmp_path, monkeypatch, capsys):
    assert _run_in_process(command, ["--help"], monkeypatch, tmp_path) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{command}: ")
    assert f"usage: {command} " in out and "Examples:" in out
    assert out.split("Examples:")[1].count(f"\n  {command} ") >= 3
    assert not list(tmp_path.iterdir())  # help writes no run folder


@pytest.mark.parametrize(
    ("arguments", "named"),
    [(["nonsense=1"], ["'nonsense'"]), (["experiment=no_such"], ["experiment/no_such", "rpm_ours"])],
    ids=["unknown-key", "unknown-option"],
)
def test_a_bad_override_ends_in_one_line_and_exit_code_2(arguments, named, tmp_path, monkeypatch, capsys):
    assert _run_in_process("linereg-train", arguments, monkeypatch, tmp_path) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("linereg-train: error: ") and all(text in line for text in named)
    assert not list(tmp_path.iterdir())


def test_register_names_every_method_with_method_alone(tmp_path, monkeypatch, capsys):
    """``solver=`` is no key of linereg-register: ``method=robust|adam_loss|svd_irls|...`` is."""
    arguments = ["source=a.ply", "target=b.ply", "solver=adam"]
    assert _run_in_process("linereg-register", arguments, monkeypatch, tmp_path) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("linereg-register: error: ") and "'solver'" in line
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("command", "arguments", "named"),
    [
        ("linereg-register", [], ["missing source=", "target="]),
        ("linereg-evaluate", [], ["missing checkpoint="]),
        ("linereg-benchmark", ["benchmark=run"], ["missing benchmark.run="]),
    ],
    ids=["register", "evaluate", "benchmark"],
)
def test_a_missing_mandatory_value_ends_in_one_line_and_exit_code_2(command, arguments, named, tmp_path):
    done = _run(["-m", MODULES[command], *arguments], tmp_path)
    _assert_usage_error(done, command, *named)
    assert not (tmp_path / "outputs" / "register").exists()


@pytest.mark.parametrize(
    ("command", "arguments", "named"),
    [
        ("linereg-evaluate", ["checkpoint=/nonexistent"], "checkpoint not found: /nonexistent"),
        ("linereg-register", ["source=/nonexistent", "target=/nonexistent"], "source=/nonexistent: no such file"),
        ("linereg-benchmark", ["benchmark=run", "benchmark.run=/nonexistent"], "/nonexistent"),
    ],
    ids=["evaluate", "register", "benchmark"],
)
def test_a_failed_command_leaves_no_run_folder(command, arguments, named, tmp_path, monkeypatch, capsys):
    assert _run_in_process(command, arguments, monkeypatch, tmp_path) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"{command}: error: ") and named in line
    assert not list(tmp_path.iterdir())  # neither the run folder nor the outputs/ folders above it


def test_training_on_pairs_without_an_easy_variant_names_the_override(tmp_path, monkeypatch, capsys):
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    cloud = np.random.default_rng(0).standard_normal((100, 3))
    write_point_cloud(pairs / "a_src.ply", cloud)
    write_point_cloud(pairs / "a_tgt.ply", cloud + 0.1)
    arguments = ["dataset=pairs_folder", f"dataset.root={pairs}", "trainer.num_points=64", "trainer.device=cpu"]
    arguments.append("curriculum.stages.easy.epochs=1")
    (tmp_path / "work").mkdir()
    assert _run_in_process("linereg-train", arguments, monkeypatch, tmp_path / "work") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == (
        "linereg-train: error: dataset 'pairs_folder' has no variant 'easy' (its variants: none); "
        "pass curriculum.stages.easy.variant=null to train on the pairs as they are"
    )
    assert not list((tmp_path / "work").iterdir())  # the failed run leaves no folder


def test_only_a_run_folder_without_results_is_removed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    runs = tmp_path / "outputs" / "train" / "runs"
    for name in ("bare", "checkpoint"):
        (runs / name / ".hydra").mkdir(parents=True)
        for file in ("config.yaml", "hydra.yaml", "overrides.yaml"):
            (runs / name / ".hydra" / file).write_text("{}")
        (runs / name / "tensorboard").mkdir()  # an empty folder is nothing written
    (runs / "checkpoint" / "checkpoints").mkdir()
    (runs / "checkpoint" / "checkpoints" / "last.pt").write_bytes(b"weights")
    assert not remove_unused_run_folder(runs / "checkpoint")
    assert (runs / "checkpoint" / "checkpoints" / "last.pt").is_file()
    assert remove_unused_run_folder(runs / "bare")
    assert not (runs / "bare").exists() and runs.is_dir()  # its parents stay while they hold another run
    assert not remove_unused_run_folder(tmp_path)  # never the working folder


def test_a_corrupt_checkpoint_is_named_without_a_traceback(tmp_path):
    corrupt = tmp_path / "best.pt"
    corrupt.write_bytes(b"not a checkpoint")
    done = _run(["-m", MODULES["linereg-evaluate"], f"checkpoint={corrupt}", f"hydra.run.dir={tmp_path}/run"], tmp_path)
    _assert_usage_error(done, "linereg-evaluate", f"{corrupt}: cannot read the checkpoint")


def test_training_without_the_train_extra_names_the_extra(tmp_path):
    script = (
        "import sys\n"
        "sys.modules['matplotlib'] = None  # as in an install without the [train] extra\n"
        f"sys.argv = ['linereg-train', 'debug=tiny', 'hydra.run.dir={tmp_path}/run']\n"
        "from linereg.train.__main__ import main\n"
        "main()\n"
    )
    done = _run(["-c", script], tmp_path)
    _assert_usage_error(done, "linereg-train", "matplotlib is not installed", "pip install 'linereg[train]'")


def test_one_line_joins_hydras_option_lists_and_causes():
    cause = ConfigAttributeError("Key 'nonsense' is not in struct\n    full_key: nonsense\n    object_type=dict")
    error = ConfigCompositionException("Could not override 'nonsense'.\nTo append to your config use +nonsense=1")
    error.__cause__ = cause
    assert one_line(error) == (
        "Could not override 'nonsense'. To append to your config use +nonsense=1 (Key 'nonsense' is not in struct)"
    )
    listing = ValueError("Could not find 'x/y'\n\nAvailable options in 'x':\n\ta\n\tb\nConfig search path:\n\tz")
    assert one_line(listing) == "Could not find 'x/y'; Available options in 'x': a, b"
    assert one_line(KeyError("a key")) == "a key"


def test_the_extras_map_matches_pyproject():
    tomllib = pytest.importorskip("tomllib")
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for module, extra in EXTRAS.items():
        names = [re.split(r"[<>=;\[ ]", line)[0].replace("-", "_") for line in extras[extra]]
        assert module in names, (module, extra, names)


def test_evaluate_takes_the_runs_iterate_rule_unless_overridden():
    stored = {"iterate": {"rule": "best_fit", "keep_fraction": 0.9}}
    assert iterate_rule(stored, {"rule": None, "keep_fraction": None}) == IterateRule("best_fit", 0.9)
    assert iterate_rule(stored, {"rule": "last", "keep_fraction": None}) == IterateRule("last", 0.9)
    assert iterate_rule({}, None) == IterateRule()
    with pytest.raises(ValueError, match=r"iterate\.rule must be one of"):
        iterate_rule(stored, {"rule": "best"})


@pytest.mark.shared_data
def test_register_orthonormalises_geotransformers_ground_truth_with_a_warning(shared_data, tmp_path):
    demo = shared_data / "3dmatch" / "geotransformer_demo" / "demo"
    if not (demo / "gt.npy").is_file():
        pytest.skip(f"{demo} not found")
    arguments = [f"source={demo / 'src.npy'}", f"target={demo / 'ref.npy'}", f"gt={demo / 'gt.npy'}"]
    quick = ["+robust.rounds=1", "num_points=512", "progress=false", f"hydra.run.dir={tmp_path}/run"]
    done = _run(["-m", MODULES["linereg-register"], *arguments, *quick], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    (line,) = [line for line in done.stderr.splitlines() if "warning" in line]
    assert line.startswith("linereg-register: warning: gt: not exactly rigid, orthonormalised (max |R^T R - I| = ")
    assert "Err_R" in done.stdout
    assert json.loads((tmp_path / "run" / "result.json").read_text())["warnings"][0] == line.split("warning: ", 1)[1]


@pytest.mark.parametrize("argument", ["gt", "init"])
def test_register_rejects_a_far_from_rigid_transform_in_one_line(argument, tmp_path, monkeypatch, capsys):
    cloud = np.random.default_rng(0).standard_normal((50, 3)).astype(np.float32)
    np.save(tmp_path / "a.npy", cloud)
    np.save(tmp_path / "far.npy", np.diag([1.0, 1.0, 1.01, 1.0]))
    arguments = ["source=a.npy", "target=a.npy", f"{argument}={tmp_path / 'far.npy'}"]
    assert _run_in_process("linereg-register", arguments, monkeypatch, tmp_path) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"linereg-register: error: {argument}=") and "is not a rigid transform" in line
    assert not (tmp_path / "outputs").exists()
