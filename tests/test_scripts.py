"""``scripts/`` and ``scripts/studies/``: every script starts and prints its usage."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MODULES = sorted(
    ".".join(path.relative_to(ROOT).with_suffix("").parts)
    for folder in (ROOT / "scripts", ROOT / "scripts" / "studies")
    for path in folder.glob("[!_]*.py")
)


def test_the_studies_are_found():
    assert "scripts.bench_register" in MODULES and "scripts.studies.check_iterations" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_every_script_prints_its_help(name, capsys):
    module = importlib.import_module(name)
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--help"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith("usage: ")
