"""One setter per key: every value of a training run is written in one config file.

A run of ``python -m train`` composes the files of ``configs/train.yaml``'s defaults list and of the
files they name (configs/README.md). For every cell of :mod:`tests.test_config_cells` (every
recipe x protocol x experiment, the runs of the reproduction scripts, the README's knobs) and every
training run of ``scripts/reproduce_generalization.sh`` (the generalization splits' datasets),
:func:`setters` lists the files that set each key (the run's defaults list as Hydra computes it,
each file read at its package) and the test fails when two files of one run set a key, or one sets
a key inside a value another sets. Values given on the command line are no file; the debug presets
(``configs/debug/``, command-line overlays) are left out, and so is the per-term gradient-norm
logging (:data:`LOGGING`: off in ``configs/train.yaml``, on in an experiment; no weight changes with
it). The run's name is the cell's alone.

``python -m tests.test_config_setters experiment=rpm_ours protocol=human`` prints which file sets
each key of a run.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import yaml
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.types import RunMode

from tests.test_config_cells import MACHINE, PATHS, SCHEDULE_SCRIPT, all_cells, flatten, run_name

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
RECIPES = ("cpu", "paper")
LOGGING = ("trainer.log_term_grad_norms",)


def _setters(loader, overrides: Iterable[str]) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for element in loader.compute_defaults_list("train", [*PATHS, *overrides], RunMode.RUN).defaults:
        path = CONFIGS / f"{element.config_path}.yaml"
        if element.config_path is None or not path.is_file():  # Hydra's own configs
            continue
        values = {key: value for key, value in (yaml.safe_load(path.read_text()) or {}).items() if key != "defaults"}
        if not values:  # a file that only composes others sets no key
            continue
        for part in reversed(element.package.split(".") if element.package else []):
            values = {part: values}
        for key in flatten(values):
            found.setdefault(key, []).append(str(path.relative_to(CONFIGS)))
    return found


def setters(cells: Mapping[str, list[str]]) -> dict[str, dict[str, list[str]]]:
    """``{cell: {dotted key: [the files that set it]}}`` of each cell's ``python -m train`` run."""
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        return {name: _setters(loader, overrides) for name, overrides in cells.items()}


def clashes(found: Mapping[str, list[str]]) -> dict[str, list[str]]:
    """Keys set by more than one file: the same key, or a key inside a value another file sets."""
    result = {}
    for key in found:
        parts = key.split(".")
        owners = {file for i in range(1, len(parts) + 1) for file in found.get(".".join(parts[:i]), ())}
        if len(owners) > 1 and key not in LOGGING:
            result[key] = sorted(owners)
    return result


def measured_cells() -> dict[str, list[str]]:
    """The cells of tests/test_config_cells.py without a debug preset."""
    return {
        name: overrides
        for name, overrides in all_cells(SCHEDULE_SCRIPT).items()
        if not any(item.startswith("debug=") for item in overrides)
    }


def generalization_runs() -> dict[str, list[str]]:
    """The training runs of scripts/reproduce_generalization.sh, one seed each."""
    env = dict(os.environ) | {"DRY": "1", "SEEDS": "0", "PROTOCOL_SEEDS": "1"}
    script = ROOT / "scripts" / "reproduce_generalization.sh"
    lines = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, check=True).stdout
    return {folder: args.split() for folder, args in (line.split(" ", 1) for line in lines.splitlines())}


def test_every_key_of_a_cell_is_set_by_one_file():
    cells = measured_cells() | generalization_runs()
    assert len(cells) > 200
    found = setters(cells)
    failures = [
        f"{name}: {key} set by {', '.join(files)}"
        for name, keys in found.items()
        for key, files in clashes(keys).items()
    ]
    assert not failures, "\n".join(failures)


def test_a_cell_reads_its_cell_file():
    """``python -m train experiment=rpm_ours protocol=human`` reads configs/cell/cpu_human_rpm_ours.yaml,
    the run without an experiment the cell of its loss (rpm_ours); every value of a cell file is its own."""
    found = setters({"cell": ["experiment=rpm_ours", "protocol=human"], "default": ["recipe=paper"]})
    assert found["cell"]["loss.num_lines"] == ["cell/cpu_human_rpm_ours.yaml"]
    assert found["cell"]["model.num_neighbors"] == ["recipe_model/cpu_rpmnet.yaml"]
    assert found["cell"]["dataset.root"] == ["dataset/human_bodies.yaml"]
    assert found["default"]["loss.num_lines"] == ["cell/paper_none_rpm_ours.yaml"]
    assert found["default"]["model.num_neighbors"] == ["recipe_model/paper_rpmnet.yaml"]


def test_the_cell_alone_names_the_run():
    """``task_name`` is one plain value of the cell file: ``<loss>_<protocol>``, the loss alone without
    a protocol (the run without an experiment is named for the loss it trains)."""
    found = setters({"cell": ["experiment=dcp_cd", "protocol=real"], "default": [], "paper": ["recipe=paper"]})
    assert found["cell"]["task_name"] == ["cell/cpu_real_dcp_cd.yaml"]
    assert found["default"]["task_name"] == ["cell/cpu_none_rpm_ours.yaml"]
    assert found["paper"]["task_name"] == ["cell/paper_none_rpm_ours.yaml"]
    for path in (CONFIGS / "cell").glob("*.yaml"):
        _, protocol, loss = path.stem.split("_", 2)
        assert yaml.safe_load(path.read_text())["task_name"] == run_name([f"loss={loss}", f"protocol={protocol}"])


def test_every_recipe_protocol_and_loss_has_its_cell_file():
    """The defaults list names configs/cell/<recipe>_<protocol>_<loss>.yaml for every choice (a missing
    file fails the composition), and no cell file names a choice that does not exist."""
    options = {group: sorted(path.stem for path in (CONFIGS / group).glob("*.yaml")) for group in ("protocol", "loss")}
    expected = {f"{r}_{p}_{loss}" for r in RECIPES for p in options["protocol"] for loss in options["loss"]}
    assert {path.stem for path in (CONFIGS / "cell").glob("*.yaml")} == expected
    assert set(RECIPES) == {path.stem for path in (CONFIGS / "recipe").glob("*.yaml")}


def test_no_cell_file_sets_the_machine():
    for path in (CONFIGS / "cell").glob("*.yaml"):
        values = flatten({k: v for k, v in (yaml.safe_load(path.read_text()) or {}).items() if k != "defaults"})
        assert not [key for key in values for machine in MACHINE if key == machine or key.startswith(machine + ".")]


def main(argv: list[str]) -> int:
    """Print ``key  file`` for every key of the run ``python -m train <argv>``."""
    found = setters({"run": argv})["run"]
    width = max(map(len, found))
    for key, files in sorted(found.items()):
        print(f"{key:<{width}}  {', '.join(files)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
