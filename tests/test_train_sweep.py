"""Hydra multirun sweeps: readable job folders and the summary table (train/summary.py)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

from linereg.train.summary import collect_runs, main, write_summary

ROOT = Path(__file__).resolve().parent.parent


def _fake_job(sweep: Path, name: str, overrides: list[str], metrics: dict | None) -> None:
    job = sweep / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {item}\n" for item in overrides))
    if metrics is not None:
        (job / "metrics.json").write_text(json.dumps({"metrics": metrics}))


def test_summary_of_fake_jobs(tmp_path, capsys):
    _fake_job(tmp_path, "10_experiment=rpm_cd", ["experiment=rpm_cd"], {"test/err_r_deg_mean": 4.0, "extra": 1.0})
    _fake_job(tmp_path, "2_experiment=rpm_ours,seed=1", ["experiment=rpm_ours", "seed=1"], {"test/err_r_deg_mean": 2.5})
    _fake_job(tmp_path, "3_experiment=rpm_ours,seed=2", ["experiment=rpm_ours", "seed=2"], None)
    runs = collect_runs(tmp_path)
    assert [r["job"].split("_")[0] for r in runs] == ["2", "3", "10"]
    assert runs[1]["status"] == "no metrics.json"
    csv_path, markdown_path = write_summary(tmp_path)
    rows = list(csv.DictReader(csv_path.open()))
    assert [r["experiment"] for r in rows] == ["rpm_ours", "rpm_ours", "rpm_cd"]
    assert rows[0]["seed"] == "1" and rows[2]["seed"] == "" and rows[2]["extra"] == "1"
    lines = markdown_path.read_text().splitlines()
    assert lines[0] == "| job | experiment | seed | test/err_r_deg_mean |"
    assert lines[2] == "| 2 | rpm_ours | 1 | 2.5 |" and lines[3] == "| 3 | rpm_ours | 2 | no metrics.json |"
    main([str(tmp_path)])
    assert "| 10 | rpm_cd |  | 4 |" in capsys.readouterr().out
    assert write_summary(tmp_path / "empty") is None


def test_short_sweep_into_tmp_path(tmp_path):
    """``python -m train -m experiment=rpm_ours,rpm_cd loss.nu0=...`` with tiny settings."""
    command = [
        sys.executable,
        "-m",
        "train",
        "-m",
        "experiment=rpm_ours,rpm_cd",
        "loss.nu0=0.5",
        "debug=tiny",
        "curriculum=none",
        "curriculum.stages.full.epochs=1",
        "model.num_neighbors=8",
        f"hydra.sweep.dir={tmp_path}",
    ]
    completed = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=900, check=False)
    assert completed.returncode == 0, completed.stderr[-3000:]
    jobs = sorted(p.name for p in tmp_path.iterdir() if p.is_dir())
    assert len(jobs) == 2
    for number, (job, experiment) in enumerate(zip(jobs, ("rpm_ours", "rpm_cd"), strict=True)):
        assert job.startswith(f"{number}_") and f"experiment={experiment}," in job and "loss.nu0=0.5" in job
    assert "loss.nu0=0.5 has no effect" in completed.stderr  # CD has no Welsch scale
    rows = list(csv.DictReader((tmp_path / "summary.csv").open()))
    assert [r["experiment"] for r in rows] == ["rpm_ours", "rpm_cd"]
    assert all(float(r["test/err_r_deg_mean"]) >= 0 for r in rows)
    assert "| 1 | rpm_cd | " in (tmp_path / "summary.md").read_text()  # constant overrides are left out
