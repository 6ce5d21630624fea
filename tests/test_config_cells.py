"""Every measured training cell composes to its reference values; the config files stay plain.

A cell is a command line of ``python -m train``: every recipe x protocol x experiment, the runs
of ``scripts/reproduce.sh`` and of ``scripts/reproduce_schedule.sh`` (its ``DRY=1`` lines), and a
few knobs of the README. :func:`resolve_cells` composes them (``configs/train.yaml``) and returns
each one's resolved values as a flat ``{dotted.key: value}`` mapping, without the run-dependent
keys (``hydra``, ``paths``). ``tests/data/config_cells.json`` holds the reference: each cell's
values as the results of docs/results.md were measured, in the keys those runs' saved configs
hold (``model.keep_best_iterate``, ``model.fit_keep_fraction``, other validation splits), which
:func:`renamed` maps to today's; see :func:`pack` for its layout.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from tests.pair_identities import pair_identities

ROOT = Path(__file__).resolve().parent.parent
RECIPES = ("cpu", "paper")
PROTOCOLS = ("none", "airplane", "human", "real", "procedural")
EXPERIMENTS = ("none", *(f"{b}_{loss}" for b in ("rpm", "dcp", "fmr") for loss in ("gt", "cd", "cdw", "ours")))
# Fixed paths, so that resolved values do not depend on the checkout or the environment.
PATHS = [
    "paths.root_dir=/ROOT",
    "paths.output_dir=/ROOT/outputs/run",
    "paths.data_dir=/ROOT/data",
    "paths.shared_data_dir=/ROOT/../shared/data",
]
ENVIRONMENT = ("LINEREG_DATA", "LINEREG_SHARED_DATA")
DROPPED = ("hydra", "paths")


def grid_cells() -> Iterator[tuple[str, list[str]]]:
    """``<recipe>/<protocol>/<experiment>``: every recipe x protocol x experiment (``none``: the default)."""
    for recipe in RECIPES:
        for protocol in PROTOCOLS:
            for experiment in EXPERIMENTS:
                overrides = [f"recipe={recipe}"]
                overrides += [] if protocol == "none" else [f"protocol={protocol}"]
                overrides += [] if experiment == "none" else [f"experiment={experiment}"]
                yield f"{recipe}/{protocol}/{experiment}", overrides


def _reproduce_cell(protocol: str, experiment: str, *extra: str) -> list[str]:
    """The overrides ``scripts/reproduce.sh`` passes for one run (seed 1)."""
    sizes = {"rpm": ["model.num_neighbors=16"], "dcp": ["model.emb_dims=256", "model.ff_dims=512"], "fmr": []}
    overrides = [f"experiment={experiment}", f"protocol={protocol}", "recipe=paper", "seed=1"]
    overrides += sizes[experiment.split("_")[0]]
    overrides += ["loss.num_lines=5000"] if experiment.endswith("_ours") else []
    return [*overrides, *extra]


def reproduce_cells() -> Iterator[tuple[str, list[str]]]:
    """``reproduce/<protocol>/<run>``: the runs of ``scripts/reproduce.sh``."""
    for protocol in ("airplane", "human"):
        for backbone in ("rpm", "dcp", "fmr"):
            for loss in ("ours", "cd", "gt"):
                yield f"reproduce/{protocol}/{backbone}_{loss}", _reproduce_cell(protocol, f"{backbone}_{loss}")
            ours = f"{backbone}_ours"
            yield (
                f"reproduce/{protocol}/{backbone}_untrained",
                _reproduce_cell(protocol, ours, "trainer.untrained=true"),
            )
            yield (
                f"reproduce/{protocol}/{backbone}_reg",
                _reproduce_cell(protocol, ours, "loss.terms.alignment.weight=0"),
            )
    for experiment in ("rpm_ours", "rpm_cd", "fmr_ours", "fmr_cd"):
        yield f"reproduce/real/{experiment}", _reproduce_cell("real", experiment)
    yield "reproduce/real/rpm_ours_fixed_nu", _reproduce_cell("real", "rpm_ours", "+loss.terms.alignment.nu=0.25")
    yield "reproduce/procedural/rpm_gt", _reproduce_cell("procedural", "rpm_gt")
    yield (
        "reproduce/real/rpm_gt_finetuned",
        _reproduce_cell(
            "real", "rpm_ours", "init_from=/runs/rpm_gt_s1", "curriculum=none", "curriculum.stages.full.epochs=4"
        ),
    )


def knob_cells() -> Iterator[tuple[str, list[str]]]:
    """``knob/<name>``: the README's knobs and the debug presets."""
    yield "knob/lines", ["experiment=rpm_ours", "protocol=human", "loss.num_lines=8000"]
    yield "knob/epochs", ["experiment=dcp_ours", "protocol=airplane", "curriculum.stages.easy.epochs=2"]
    yield "knob/finetune_lr", ["experiment=rpm_ours", "protocol=real", "optimizer.lr=1e-4", "init_from=/runs/x"]
    yield "knob/nu0", ["experiment=fmr_ours", "protocol=human", "loss.nu0=1.0"]
    yield "knob/outlier", ["experiment=rpm_cd", "loss.terms.outlier.weight=1"]
    yield "debug/tiny", ["debug=tiny"]
    yield "debug/tiny_fmr", ["debug=tiny", "experiment=fmr_ours"]
    yield "debug/default", ["debug=default"]


SCHEDULE_CELLS = [f"{b}_{loss}" for b in ("rpm", "dcp", "fmr") for loss in ("untrained", "reg", "gt", "cd", "ours")]
SCHEDULE_CELLS += [f"{b}_ours_nu2" for b in ("rpm", "dcp", "fmr")] + ["rpm_ours_quick"]
MEASURED = ["rpm_gt", "rpm_cd", "rpm_ours", "dcp_cd", "dcp_ours", "fmr_gt", "fmr_cd", "fmr_ours"]
FULL_STAGE = "curriculum.stages.full.epochs=4 curriculum.stages.full.lr_scale=1.0"
# scripts/reproduce_schedule.sh's runs: every cell under its defaults, then the cells measured on each
# protocol with the environment that measured them (on Human the line loss's `_nu2` cells).
SCHEDULE_RUNS = {
    "procedural/default": ({"PROTOCOL": "procedural"}, SCHEDULE_CELLS),
    "airplane/default": ({"PROTOCOL": "airplane"}, SCHEDULE_CELLS),
    "human/default": ({"PROTOCOL": "human"}, SCHEDULE_CELLS),
    "real/default": ({"PROTOCOL": "real"}, SCHEDULE_CELLS),
    "airplane/measured": ({"PROTOCOL": "airplane", "RPM_OUTLIER_WEIGHT": "0.3"}, MEASURED),
    "airplane/measured_dcp": (
        {"PROTOCOL": "airplane", "RPM_OUTLIER_WEIGHT": "0.3", "EXTRA": FULL_STAGE, "NUM_LINES": "20000"},
        ["dcp_cd", "dcp_ours"],
    ),
    "human/measured": (
        {"PROTOCOL": "human", "RPM_OUTLIER_WEIGHT": "0.3", "EXTRA": FULL_STAGE, "NUM_LINES": "20000"},
        [cell.replace("_ours", "_ours_nu2") for cell in MEASURED],
    ),
    "real/measured": ({"PROTOCOL": "real", "RPM_OUTLIER_WEIGHT": "0.3", "EXTRA": FULL_STAGE}, MEASURED),
    "real/finetune": (
        {"PROTOCOL": "real", "INIT_FROM": "/runs/rpm_gt_s0"},
        ["rpm_pretrained", "rpm_cd_finetuned", "rpm_ours_nu2_finetuned", "fmr_oracle_finetuned"],
    ),
}


def schedule_dry_run(script: Path, env: Mapping[str, str], cells: Iterable[str]) -> dict[str, list[str]]:
    """``{cell: overrides}`` of ``DRY=1 script`` (``scripts/reproduce_schedule.sh``)."""
    env = dict(os.environ) | dict(env) | {"DRY": "1", "CELLS": " ".join(cells), "SEEDS": "0"}
    result = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, check=True)
    return {line.split()[0]: line.split()[2:] for line in result.stdout.splitlines()}


def schedule_cells(script: Path) -> Iterator[tuple[str, list[str]]]:
    """``schedule/<protocol>/<environment>/<cell>``: the runs of ``scripts/reproduce_schedule.sh``."""
    for name, (env, cells) in SCHEDULE_RUNS.items():
        for cell, overrides in schedule_dry_run(script, env, cells).items():
            yield f"schedule/{name}/{cell}", overrides


def all_cells(script: Path) -> dict[str, list[str]]:
    """Every cell's id and overrides."""
    return dict([*grid_cells(), *reproduce_cells(), *knob_cells(), *schedule_cells(script)])


def flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists stay values; an empty mapping stays ``{}``)."""
    if not isinstance(value, Mapping) or (not value and prefix):
        return {prefix: value}
    flat = {}
    for key, item in value.items():
        flat |= flatten(item, f"{prefix}.{key}" if prefix else str(key))
    return flat


def _resolved(cfg: Any, key: str) -> Any:
    """The resolved value of ``cfg[key]`` (interpolations resolve against the whole config)."""
    value = cfg[key]
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def resolve_cells(config_dir: Path, cells: Mapping[str, list[str]]) -> dict[str, dict[str, Any]]:
    """Each cell's resolved config, flat, without ``hydra`` and ``paths`` (see the module docstring)."""
    saved = {key: os.environ.pop(key) for key in ENVIRONMENT if key in os.environ}
    resolved = {}
    try:
        with initialize_config_dir(str(config_dir), version_base="1.3"):
            for name, overrides in cells.items():
                cfg = compose("train", overrides=[*PATHS, *overrides], return_hydra_config=True)
                HydraConfig.instance().set_config(cfg)  # resolves ${hydra:runtime.choices...}
                config = {key: _resolved(cfg, key) for key in cfg if key not in DROPPED}
                resolved[name] = flatten(config)
    finally:
        os.environ.update(saved)
    return resolved


def component(key: str) -> str:
    """The component a flat key belongs to: its first part, or ``run`` for top-level values."""
    return key.split(".", 1)[0] if "." in key else "run"


def pack(resolved: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The fixture's layout: each component's distinct values once, each cell as their indices.

    ``{"components": {"model": [{flat values}, ...], ...}, "cells": {cell: {"model": index, ...}}}``.
    """
    components: dict[str, list[dict[str, Any]]] = {}
    cells = {}
    for name, values in resolved.items():
        parts: dict[str, dict[str, Any]] = {}
        for key, value in values.items():
            parts.setdefault(component(key), {})[key] = value
        cells[name] = {}
        for part, part_values in sorted(parts.items()):
            table = components.setdefault(part, [])
            if part_values not in table:
                table.append(part_values)
            cells[name][part] = table.index(part_values)
    return {"components": components, "cells": cells}


def unpack(fixture: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Inverse of :func:`pack`."""
    tables = fixture["components"]
    return {
        name: {key: value for part, index in parts.items() for key, value in tables[part][index].items()}
        for name, parts in fixture["cells"].items()
    }


# ----------------------------------------------------------------------------- the reference
FIXTURE = ROOT / "tests" / "data" / "config_cells.json"
SCHEDULE_SCRIPT = ROOT / "scripts" / "reproduce_schedule.sh"
# Validation pairs disjoint from the test pairs, per dataset (the test pairs and the training pairs stay).
VALIDATION = {
    "modelnet40": {"split": "train", "seed": 1, "subset": 36},  # fresh poses of training shapes and views
    "mesh_folder": {"split": "train", "seed": 1, "subset": 10},  # fresh poses of training views
    "rgbd_sequence": {"frame_range": [0, 400], "pair_stride": 19},  # every 19th pair of the training frames
}
# recipe=paper without an experiment: the paper's settings for RPM-Ours (the embedded default's
# model and loss), no longer the embedded default's schedule under the paper's loss weights.
PAPER_DEFAULT = (
    "curriculum.",
    "scheduler.",
    "optimizer.lr",
    "trainer.num_points",
    "trainer.evaluate_checkpoint",
    "dataset.protocol.num_points",
)
# recipe=paper without an experiment sizes RPM-Net as the paper does (64 neighbours per ball,
# recipe_model/paper_rpmnet.yaml); the reference holds the 16 of the CPU model it used to keep.
PAPER_SIZE = {"model.num_neighbors": 64}


def run_name(overrides: Sequence[str]) -> str:
    """The name of a run without an experiment or a debug preset: its cell's, after the loss it trains
    (``<loss>_<protocol>``, the loss alone without a protocol); the reference holds ``train`` and
    ``None_<protocol>`` (named after the experiment not chosen)."""
    choices = dict(item.split("=", 1) for item in overrides if item.startswith(("loss=", "protocol=")))
    loss, protocol = choices.get("loss", "rpm_ours"), choices.get("protocol", "none")
    return loss if protocol == "none" else f"{loss}_{protocol}"


def renamed(values: Mapping[str, Any]) -> dict[str, Any]:
    """A reference cell in today's names: the explicit map from the keys the configs used to have."""
    values = dict(values)
    keep_best = values.pop("model.keep_best_iterate", False)
    values["iterate.rule"] = "best_fit" if keep_best else "last"
    values["iterate.keep_fraction"] = values.pop("model.fit_keep_fraction", 1.0)
    new_validation = VALIDATION.get(values["dataset.name"])
    if new_validation is not None:
        values = {key: value for key, value in values.items() if not key.startswith("dataset.splits.val.")}
        values |= {f"dataset.splits.val.{key}": value for key, value in new_validation.items()}
    return values


# The machine a run computes on, not what it computes: the command line's alone (configs/train.yaml).
MACHINE = (
    "trainer.device",
    "trainer.threads",
    "trainer.progress",
    "trainer.num_workers",
    "trainer.checkpoint_every_steps",
)


def effective(values: Mapping[str, Any]) -> dict[str, Any]:
    """What a run does with ``values``: stages with 0 epochs are skipped (linereg.train.curriculum),
    an untrained control (``trainer.untrained``) runs no stage at all, and the machine keys
    (:data:`MACHINE`) are where it runs and how often it saves, not what it computes."""
    skipped = {
        key.rsplit(".", 1)[0]
        for key, value in values.items()
        if key.startswith("curriculum.stages.") and key.endswith(".epochs") and value == 0
    }
    untrained = values.get("trainer.untrained", False)
    return {
        key: value
        for key, value in values.items()
        if not (key.rsplit(".", 1)[0] in skipped or (untrained and key.startswith("curriculum.")) or key in MACHINE)
    }


def test_every_measured_cell_resolves_to_its_reference():
    """Every cell resolves to the reference values, through :func:`renamed` and :func:`effective`
    only; the other changes are those of the run without an experiment: under recipe=paper
    (:data:`PAPER_DEFAULT`, :data:`PAPER_SIZE`) and its name (:func:`run_name`)."""
    reference = unpack(json.loads(FIXTURE.read_text()))
    cells = all_cells(SCHEDULE_SCRIPT)
    assert set(cells) == set(reference)
    resolved = resolve_cells(ROOT / "configs", cells)
    failures = []
    for name, values in resolved.items():
        expected, actual = effective(renamed(reference[name])), effective(values)
        if name == "paper/none/none":
            expected = {k: v for k, v in expected.items() if not k.startswith(PAPER_DEFAULT)}
            actual = {k: v for k, v in actual.items() if not k.startswith(PAPER_DEFAULT)}
        if name.startswith("paper/") and name.endswith("/none"):
            expected |= PAPER_SIZE
        if not any(item.startswith(("experiment=", "debug=")) for item in cells[name]):
            expected["task_name"] = run_name(cells[name])
        differences = {
            key: (expected.get(key, "<absent>"), actual.get(key, "<absent>"))
            for key in sorted(set(expected) | set(actual))
            if expected.get(key, "<absent>") != actual.get(key, "<absent>")
        }
        if differences:
            failures.append(f"{name} {cells[name]}: {differences}")
    assert not failures, "\n".join(failures)


# ----------------------------------------------------------------------------- the files
CONFIGS = ROOT / "configs"
# Files of the training configs (configs/train.yaml and its groups).
TRAINING_GROUPS = (
    "curriculum",
    "dataset",
    "debug",
    "experiment",
    "logger",
    "loss",
    "model",
    "optimizer",
    "paths",
    "protocol",
    "recipe",
    "recipe_model",
    "cell",
    "scheduler",
)
# Interpolations a training file may hold: links to the run's own values, never to a recipe or to
# another component's choice (the defaults list names specialisation files instead).
ALLOWED_INTERPOLATIONS = re.compile(
    r"\$\{(loss\.\w+|trainer\.(num_points|monitor)|seed|paths\.\w+|linereg\.data_folder:\w+,[\w./]+"
    r"|hydra:runtime\.[\w.]+)\}"
)


def _options(group: str) -> list[str]:
    return sorted(path.stem for path in (CONFIGS / group).glob("*.yaml"))


def _training_files() -> list[Path]:
    return [CONFIGS / "train.yaml", *(path for group in TRAINING_GROUPS for path in (CONFIGS / group).glob("*.yaml"))]


def _strings(value: Any) -> Iterator[str]:
    if isinstance(value, Mapping):
        for item in value.values():
            yield from _strings(item)
    elif isinstance(value, list):
        for item in value:
            yield from _strings(item)
    elif isinstance(value, str):
        yield value


def test_no_select_and_no_value_built_from_another_choice():
    assert not [path for path in CONFIGS.rglob("*.yaml") if "oc.select" in path.read_text()]
    for path in _training_files():
        values = {k: v for k, v in (yaml.safe_load(path.read_text()) or {}).items() if k != "defaults"}
        for text in _strings(values):
            for interpolation in re.findall(r"\$\{[^}]*\}?[^}]*\}|\$\{[^}]*\}", text):
                assert ALLOWED_INTERPOLATIONS.fullmatch(interpolation), f"{path}: {interpolation}"


def test_experiment_files_hold_the_model_and_the_loss():
    for path in (CONFIGS / "experiment").glob("*.yaml"):
        config = yaml.safe_load(path.read_text())
        assert config["defaults"] == [
            {"override /model": config["defaults"][0]["override /model"]},
            {"override /loss": path.stem},
        ], path
        assert set(config) == {"defaults", "trainer"}
        assert config["trainer"] == {"log_term_grad_norms": True}  # what it logs


def test_specialisation_files_name_existing_choices():
    """A misspelt file of an optional defaults entry would never load: each names real options. Every
    curriculum file is the stages of a cell (named in its defaults list) or a preset of the command line."""
    recipes, protocols = _options("recipe"), _options("protocol")
    assert set(_options("recipe_model")) <= {f"{r}_{m}" for r in recipes for m in _options("model")}
    assert set(_options("cell")) <= {f"{r}_{p}_{loss}" for r in recipes for p in protocols for loss in _options("loss")}
    named = {
        entry["/curriculum"]
        for path in (CONFIGS / "cell").glob("*.yaml")
        for entry in yaml.safe_load(path.read_text())["defaults"]
        if "/curriculum" in entry
    }
    assert set(_options("curriculum")) - {"none", "quick", "tiny"} <= named


# Groups that describe what is trained and on which data; the machine is the command line's.
DATA_GROUPS = tuple(group for group in TRAINING_GROUPS if group not in ("debug", "logger", "paths"))


def test_no_data_file_sets_the_machine():
    """No protocol, dataset, experiment, recipe or component file sets a :data:`MACHINE` key, and
    every protocol x experiment resolves to the command's defaults: CUDA when present, torch's own
    thread count, progress bars, checkpoints at the end of each epoch only."""
    for group in DATA_GROUPS:
        for path in (CONFIGS / group).glob("*.yaml"):
            values = flatten({k: v for k, v in (yaml.safe_load(path.read_text()) or {}).items() if k != "defaults"})
            for key in MACHINE:
                assert not any(k == key or k.startswith(key + ".") for k in values), f"{path} sets {key}"
    cells = {name: overrides for name, overrides in grid_cells() if name.startswith("cpu/")}
    for name, values in resolve_cells(CONFIGS, cells).items():
        machine = {key: values[key] for key in MACHINE}
        assert machine == {
            "trainer.device": "auto",
            "trainer.threads": None,
            "trainer.progress": True,
            "trainer.num_workers": 0,
            "trainer.checkpoint_every_steps": None,
        }, name


@pytest.mark.parametrize("protocol", ["airplane", "human", "real"])
def test_validation_pairs_are_not_test_pairs(shared_data, protocol):
    """Every recipe choice can be made without the test pairs: no validation pair is a test pair."""
    from linereg.datasets.splits import build_split

    config = resolve_cells(CONFIGS, {protocol: [f"protocol={protocol}"]})[protocol]
    dataset: dict[str, Any] = {}
    for key, value in config.items():
        if key.startswith("dataset."):
            *parents, last = key.split(".")[1:]
            node = dataset
            for parent in parents:
                node = node.setdefault(parent, {})
            node[last] = value.replace("/ROOT/../shared/data", str(shared_data)) if isinstance(value, str) else value
    dataset["cache_dir"] = None
    validation = pair_identities(build_split(dataset, "val", progress=False))
    test = pair_identities(build_split(dataset, "test", progress=False))
    assert len(validation) == {"airplane": 36, "human": 10, "real": 10}[protocol] and test
    assert not validation & test


RECIPE_SCRIPT = ROOT / "scripts" / "reproduce_recipe.sh"
# Keys in which a plain experiment differs from the study script's runs without changing the run:
# the task name and the per-term gradient-norm logging (``torch.autograd.grad``, no weight update).
NOT_THE_RUN = ("task_name", "trainer.log_term_grad_norms")


def _measured_reference(protocol: str, cell: str) -> str:
    """The fixture's id of the run that measured ``cell`` of ``protocol``'s table."""
    if protocol == "human":
        return f"schedule/human/measured/{cell.replace('_ours', '_ours_nu2')}"
    if protocol == "airplane" and cell.startswith("dcp_"):
        return f"schedule/airplane/measured_dcp/{cell}"
    return f"schedule/{protocol}/measured/{cell}"


@pytest.mark.parametrize("protocol", ["airplane", "human", "real"])
def test_the_recipe_script_runs_the_measured_cells(protocol):
    """``scripts/reproduce_recipe.sh`` (a plain ``experiment=<cell> protocol=<protocol>`` per cell, no
    model override) resolves to the runs that measured the tables of docs/results.md."""
    cells = [cell for cell in MEASURED if not (protocol == "real" and cell.startswith("dcp_"))]
    env = dict(os.environ) | {"DRY": "1", "PROTOCOL": protocol, "CELLS": " ".join(cells), "SEEDS": "0"}
    lines = subprocess.run(["bash", str(RECIPE_SCRIPT)], env=env, capture_output=True, text=True, check=True)
    commands = {line.split()[0]: line.split()[2:] for line in lines.stdout.splitlines()}
    assert set(commands) == set(cells)
    assert not [arg for args in commands.values() for arg in args if arg.startswith(("model", "+model"))]
    reference = unpack(json.loads(FIXTURE.read_text()))
    resolved = resolve_cells(ROOT / "configs", commands)
    failures = []
    for cell, values in resolved.items():
        expected = effective(renamed(reference[_measured_reference(protocol, cell)]))
        actual = effective(values)
        differences = {
            key: (expected.get(key, "<absent>"), actual.get(key, "<absent>"))
            for key in sorted(set(expected) | set(actual))
            if key not in NOT_THE_RUN and expected.get(key, "<absent>") != actual.get(key, "<absent>")
        }
        if differences:
            failures.append(f"{cell}: {differences}")
    assert not failures, "\n".join(failures)
