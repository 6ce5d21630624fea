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


def test_bench_register_scans_without_the_scans_fails_clearly(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LINEREG_SHARED_DATA", str(tmp_path))
    module = importlib.import_module("scripts.bench_register")
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--scans"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert "skipping redkitchen 4->0" in error and "no scan pair was found" in error


def test_bench_register_pairs_of_needs_the_throughput(capsys):
    module = importlib.import_module("scripts.bench_register")
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--pairs-of", "rpm_ours_human"])
    assert exit_info.value.code == 2 and "--pairs-of needs --throughput" in capsys.readouterr().err


def test_bench_register_throughput_on_pairs_the_network_never_saw(shared_data, capsys):
    """The Human network on two of the Airplane protocol's test views: every way answers both pairs."""
    module = importlib.import_module("scripts.bench_register")
    rows = module.throughput("rpm_ours_human", 2, pairs_of="rpm_ours_airplane", rounds=2)
    assert list(rows) == ["solver", "network", "finished network, every pair", "finished network"]
    assert all(row["pairs_per_s"] > 0 and 0.0 <= row["confident_share"] <= 1.0 for row in rows.values())
    assert rows["solver"]["vs_solver"] == 1.0 and all(row["vs_solver"] > 0 for row in rows.values())
    module.print_throughput("rpm_ours_human", rows, "rpm_ours_airplane")
    assert "the test pairs of rpm_ours_airplane's protocol" in capsys.readouterr().out


def test_bench_register_times_two_checkouts_in_turns(tmp_path, monkeypatch):
    """``--baseline``: the two checkouts' commands alternate run by run, which runs first alternating,
    each with its own code first on the path, and each gets its own times."""
    module = importlib.import_module("scripts.bench_register")
    order = []

    def run(command, cwd, env, **_):
        order.append(env["PYTHONPATH"].split(":")[0])
        if command[-1].startswith("hydra.run.dir="):
            out = Path(command[-1].removeprefix("hydra.run.dir="))
            out.mkdir(parents=True)
            (out / "result.json").write_text(f'{{"root": "{order[-1]}"}}')
        return type("Done", (), {"returncode": 0})()

    monkeypatch.setattr(module.subprocess, "run", run)
    other = tmp_path / "other"
    found = module._register_runs(["source=a.ply"], tmp_path / "runs", 3, (module.ROOT, other))
    first, second = str(module.ROOT), str(other)
    assert order == [first, second, second, first, first, second]
    assert [report["root"] for _, report in found] == [first, second]
    assert all(len(runs) == 3 and min(runs) >= 0.0 for runs, _ in found)
    order.clear()
    assert [len(runs) for runs in module._wall(["python"], tmp_path, 2, (module.ROOT, other))] == [2, 2]
    assert len(order) == 4


def test_paired_ratio_cancels_a_slow_spell():
    """Runs of one turn share the machine's state: a turn twice as slow leaves the ratio alone, where
    the ratio of the two medians would move with it."""
    module = importlib.import_module("scripts.bench_register")
    times, reference = [1.1, 2.2, 1.1], [1.0, 2.0, 1.0]
    assert module.paired_ratio(times, reference) == pytest.approx(1.1)
    assert module.paired_ratio([2.0, 1.0, 1.0], [1.0, 2.0, 2.0]) == pytest.approx(0.5)
