"""scripts/reproduce_schedule.sh: every cell composes into the one schedule it promises, and its table."""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from omegaconf import OmegaConf

from linereg.train.curriculum import Curriculum
from scripts import reproduce_report
from tests.test_configs import ROOT, build_components, compose_config

SCRIPT = ROOT / "scripts" / "reproduce_schedule.sh"
BACKBONES = {"rpm": "rpmnet", "dcp": "dcp_v2", "fmr": "fmr"}
LOSSES = ("untrained", "reg", "gt", "cd", "ours", "ours_nu2")
CELLS = [f"{b}_{loss}" for b in BACKBONES for loss in LOSSES] + ["rpm_ours_quick"]
DATASETS = {"procedural": "procedural", "airplane": "modelnet40", "human": "mesh_folder", "real": "rgbd_sequence"}


def dry_run(protocol: str, cells: list[str], seeds: str = "0", **env: str) -> subprocess.CompletedProcess:
    """The script's DRY=1 output for ``cells``; ``env`` adds its other variables (EXTRA, NUM_LINES, ...)."""
    env = os.environ | env | {"DRY": "1", "PROTOCOL": protocol, "CELLS": " ".join(cells), "SEEDS": seeds}
    return subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, check=False)


def cell_overrides(protocol: str) -> dict[str, list[str]]:
    result = dry_run(protocol, CELLS)
    assert result.returncode == 0, result.stderr
    runs = [line.split() for line in result.stdout.splitlines()]
    assert [run[0] for run in runs] == CELLS and all(run[1] == "seed=0" for run in runs)
    return {run[0]: run[2:] for run in runs}


@pytest.mark.parametrize("protocol", list(DATASETS))
def test_every_cell_composes_with_one_schedule(protocol):
    for cell, overrides in cell_overrides(protocol).items():
        cfg = compose_config(overrides=overrides)
        backbone, loss = cell.split("_", 1)
        assert cfg.model.name == BACKBONES[backbone] and cfg.dataset.name == DATASETS[protocol]
        assert cfg.optimizer.name == "adam" and cfg.optimizer.lr == 1e-3 and cfg.scheduler.name == "cosine"
        assert cfg.trainer.num_points == 256 and cfg.trainer.evaluate_checkpoint == "last"
        assert cfg.trainer.untrained == (loss == "untrained")
        stages = {name: stage for name, stage in cfg.curriculum.stages.items() if stage.epochs > 0}
        if loss in ("ours_quick", "untrained"):  # the untrained control runs no stage
            assert list(stages) == ["easy", "subset", "full"]
        else:  # one stage: every training pair in its easy variant, 4 epochs
            assert list(stages) == ["easy"] and stages["easy"].epochs == 4
            assert stages["easy"].variant == "easy" and stages["easy"].subset is None
        alignment = cfg.loss.terms.get("alignment")
        if loss == "gt":
            assert alignment is None and "registration" in cfg.loss.terms
        elif loss == "cd":
            assert alignment is None if backbone == "fmr" else alignment.name == "chamfer"
        else:
            assert alignment.name == "line_intersection" and alignment.weight == (0 if loss == "reg" else 1)
            assert cfg.loss.num_lines == 5000
            assert cfg.loss.nu0 == (2.0 if loss == "ours_nu2" else None)  # None: the paper's 0.5
        if backbone == "rpm" and loss != "gt":  # pinned: not the recipe's 0.3 (configs/cell/cpu_*_rpm_*.yaml)
            assert cfg.loss.terms.outlier.weight == 1
        if backbone == "dcp":
            assert cfg.model.emb_dims == 256 and cfg.model.ff_dims == 512
        build_components(cfg)


def test_unknown_cell_or_protocol_fails_before_running():
    result = dry_run("procedural", ["rpm_ours", "rpm_typo"])
    assert result.returncode == 2 and "unknown cell rpm_typo" in result.stderr and result.stdout == ""
    result = dry_run("kitti", ["rpm_ours"])
    assert result.returncode == 2 and "unknown PROTOCOL kitti" in result.stderr


def test_fine_tuning_cells_start_from_init_from():
    result = dry_run("real", ["rpm_pretrained"])
    assert result.returncode == 2 and "rpm_pretrained needs INIT_FROM" in result.stderr
    env = os.environ | {"DRY": "1", "PROTOCOL": "real", "INIT_FROM": "/runs/rpm_gt_s0"}
    env["CELLS"] = "rpm_pretrained rpm_cd_finetuned rpm_ours_nu2_finetuned"
    result = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, check=True)
    runs = {line.split()[0]: line.split()[2:] for line in result.stdout.splitlines()}
    assert runs["rpm_pretrained"] == [*cell_overrides("real")["rpm_untrained"], "init_from=/runs/rpm_gt_s0"]
    for cell in ("rpm_cd", "rpm_ours_nu2"):
        assert runs[f"{cell}_finetuned"] == [*cell_overrides("real")[cell], "init_from=/runs/rpm_gt_s0"]
    cfg = compose_config(overrides=runs["rpm_ours_nu2_finetuned"])
    assert cfg.init_from == "/runs/rpm_gt_s0" and cfg.dataset.name == "rgbd_sequence" and cfg.loss.nu0 == 2.0


def test_fine_tuning_cells_exist_for_every_backbone():
    cells = ["fmr_pretrained", "fmr_cd_finetuned", "fmr_ours_finetuned", "dcp_ours_nu2_finetuned"]
    cells.append("rpm_oracle_finetuned")
    result = dry_run("real", cells, INIT_FROM="/runs/fmr_gt_s0")
    assert result.returncode == 0, result.stderr
    runs = {line.split()[0]: line.split()[2:] for line in result.stdout.splitlines()}
    real = cell_overrides("real")
    assert runs["fmr_pretrained"] == [*real["fmr_untrained"], "init_from=/runs/fmr_gt_s0"]
    for cell in ("fmr_cd", "fmr_ours", "dcp_ours_nu2"):
        assert runs[f"{cell}_finetuned"] == [*real[cell], "init_from=/runs/fmr_gt_s0"]
    assert runs["rpm_oracle_finetuned"] == [*real["rpm_gt"], "init_from=/runs/fmr_gt_s0"]
    assert "registration" in compose_config(overrides=runs["rpm_oracle_finetuned"]).loss.terms  # supervised
    result = dry_run("real", ["icp_cd_finetuned"], INIT_FROM="/runs/fmr_gt_s0")
    assert result.returncode == 2 and "unknown cell icp_cd " in result.stderr


def test_num_lines_reaches_every_line_loss_cell_only():
    result = dry_run("procedural", ["dcp_reg", "dcp_cd", "dcp_ours", "fmr_ours_nu2"], NUM_LINES="20000")
    assert result.returncode == 0, result.stderr
    runs = {line.split()[0]: compose_config(overrides=line.split()[2:]) for line in result.stdout.splitlines()}
    lines = [runs[cell].loss.terms.alignment.num_lines for cell in ("dcp_reg", "dcp_ours", "fmr_ours_nu2")]
    assert lines == [20000] * 3
    assert runs["dcp_cd"].loss.terms.alignment.name == "chamfer"


def test_seeds_repeat_every_cell():
    result = dry_run("procedural", ["dcp_gt", "fmr_cd"], seeds="1 2")
    assert [line.split()[:2] for line in result.stdout.splitlines()] == [
        ["dcp_gt", "seed=1"],
        ["fmr_cd", "seed=1"],
        ["dcp_gt", "seed=2"],
        ["fmr_cd", "seed=2"],
    ]


def _run(folder, err_r: float, cpu: str | None) -> None:
    folder.mkdir(parents=True)
    keys = ("err_r_deg", "err_t_l1", "err_t_l2", "err_pw_l1", "err_pw_l2")
    metrics = {f"test/{key}_mean": err_r / 100 for key in keys} | {"test/err_r_deg_mean": err_r}
    metrics |= {"test/err_r_deg_median": err_r / 2, "test/identity/err_r_deg_median": 44.0}
    metrics |= {f"test/identity/{key}_mean": 0.3 for key in keys} | {"test/identity/err_r_deg_mean": 45.0}
    (folder / "metrics.json").write_text(json.dumps({"metrics": metrics}))
    if cpu is not None:
        (folder.parent / f"{folder.name}.cpu").write_text(cpu)


def test_schedule_table(tmp_path, capsys):
    out = tmp_path / "schedule"
    _run(out / "procedural" / "fmr_ours_s0", 6.0, "100.0 10.0\n")
    _run(out / "procedural" / "fmr_ours_s1", 8.0, "Command exited with non-zero status 1\n50.0 5.0\n100.0 5.0\n")
    _run(out / "procedural" / "fmr_untrained_s0", 20.0, None)
    _run(out / "procedural" / "dcp_gt_s0", 3.0, "30.5 0.5\n")
    (out / "procedural" / "dcp_cd_s0").mkdir()  # unfinished: left out
    assert reproduce_report.main([str(out), "--schedule", "procedural"]) == 0
    rows = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines()[2:]]
    assert [row[0].strip() for row in rows] == ["identity", "dcp_gt", "fmr_untrained", "fmr_ours"]
    assert [cell.strip() for cell in rows[0]] == ["identity", "45.00", "", "44.00", "3.00", "-", ""]
    assert [cell.strip() for cell in rows[1]] == ["dcp_gt", "3.00", "", "1.50", "0.30", "0", "31"]
    assert rows[2][6].strip() == ""  # no CPU record
    assert [cell.strip() for cell in rows[3]] == ["fmr_ours", "7.00 ± 1.41", "6.00, 8.00", "3.50", "0.70", "0 1", "135"]
    with pytest.raises(SystemExit):
        reproduce_report.main([str(out), "--schedule", "airplane"])


# What each protocol's measured cells add to the schedule's environment (docs/results.md); on
# Human the measured line-loss cells are the `_nu2` ones.
MEASURED_ENV = {
    "airplane": {"EXTRA": ""},
    "human": {"EXTRA": "curriculum.stages.full.epochs=4 curriculum.stages.full.lr_scale=1.0", "NUM_LINES": "20000"},
    "real": {"EXTRA": "curriculum.stages.full.epochs=4 curriculum.stages.full.lr_scale=1.0"},
}
# A backbone's own stages under a protocol's recipe (configs/cell/cpu_airplane_dcp_*.yaml).
MEASURED_ENV_OF_BACKBONE = {
    ("airplane", "dcp"): {"EXTRA": MEASURED_ENV["human"]["EXTRA"], "NUM_LINES": "20000"},  # Human's full-range stage
}
SIZES = {"rpm": ["model=rpmnet_cpu"], "dcp": ["model.emb_dims=256", "model.ff_dims=512"], "fmr": []}


def _training(cfg) -> dict:
    """What a run trains with: stages, rates, loss terms, model, data, points, batch, checkpoint, iterate."""
    curriculum = Curriculum.from_config(cfg.curriculum)
    stages = [(s.epochs, s.subset, s.variant, s.learning_rate(cfg.optimizer.lr)) for s in curriculum.stages]
    return {
        "stages": stages,
        "optimizer": OmegaConf.to_container(cfg.optimizer, resolve=True),
        "scheduler": OmegaConf.to_container(cfg.scheduler, resolve=True),
        "loss": OmegaConf.to_container(cfg.loss.terms, resolve=True),
        "model": OmegaConf.to_container(cfg.model, resolve=True),
        "dataset": OmegaConf.to_container(cfg.dataset, resolve=True),
        "trainer": {key: cfg.trainer[key] for key in ("num_points", "batch_size", "evaluate_checkpoint")},
        "iterate": OmegaConf.to_container(cfg.iterate),
    }


@pytest.mark.parametrize("protocol", list(MEASURED_ENV))
@pytest.mark.parametrize("cell", ["rpm_gt", "rpm_cd", "rpm_ours", "dcp_cd", "dcp_ours", "fmr_gt", "fmr_cd", "fmr_ours"])
def test_experiment_under_the_recipe_trains_the_measured_cell(protocol, cell):
    """`python -m train experiment=<cell> protocol=<protocol>` (the default recipe=cpu, at the
    grid's backbone sizes) trains what the schedule's cell measured."""
    measured_cell = f"{cell}_nu2" if protocol == "human" and cell.endswith("_ours") else cell
    env = MEASURED_ENV_OF_BACKBONE.get((protocol, cell.split("_")[0]), MEASURED_ENV[protocol])
    result = dry_run(protocol, [measured_cell], RPM_OUTLIER_WEIGHT="0.3", **env)
    assert result.returncode == 0, result.stderr
    schedule = compose_config(overrides=result.stdout.split()[2:])
    experiment = compose_config(overrides=[f"experiment={cell}", f"protocol={protocol}", *SIZES[cell.split("_")[0]]])
    assert _training(experiment) == _training(schedule)
