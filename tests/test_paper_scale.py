"""The documented commands for the paper's full scale and for a Slurm sweep compose to what they say.

The commands are read from the docs themselves (docs/results.md, "The recipe and the paper's
settings"; README.md, "Train"), so the docs cannot drift from the configs.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from linereg.train.curriculum import Curriculum
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parent.parent
PATHS = [f"paths.root_dir={ROOT}", "paths.output_dir=/tmp/linereg-paper-scale-test"]
# The paper's §4.3 (and the backbones' own papers for their sizes): the unsupervised losses' rate,
# the supervised one's (the backbone's own), lines per pair, backbone sizes.
PAPER = {
    "rpm": {"lr": 2e-6, "gt_lr": 1e-4, "lines": 10000, "model": {"num_neighbors": 64, "feature_dim": 96}},
    "dcp": {"lr": 1e-5, "gt_lr": 1e-3, "lines": 15000, "model": {"emb_dims": 512, "ff_dims": 1024}},
    "fmr": {"lr": 1e-5, "gt_lr": 1e-3, "lines": 15000, "model": {}},
}
# The paper's initialisation of the unsupervised losses (§4.3); the supervised ones train on every pair.
UNSUPERVISED_STAGES = [("overfit", 500, 100, "easy"), ("subset", 50, 0.1, None), ("full", 50, None, None)]
SUPERVISED_STAGES = [("full", 50, None, None)]


def _commands(page: Path, marker: str) -> list[list[str]]:
    """The command lines (continuations joined, comments dropped) of the first ``bash`` block after ``marker``."""
    text = page.read_text()
    block = re.search(r"```bash\n(.*?)```", text[text.index(marker) :], re.S).group(1)
    lines = block.replace("\\\n", " ").splitlines()
    return [shlex.split(line.split("  #")[0]) for line in lines if line.strip()]


def _compose(overrides: list[str], *, hydra: bool = False):
    return compose_config("train", [*PATHS, *overrides], hydra=hydra)


def _overrides(command: list[str]) -> list[str]:
    """The ``key=value`` arguments of a command, each sweep (``a,b``) at its first value."""
    return [arg.split(",")[0] if not arg.startswith("hydra.") else arg for arg in command if "=" in arg]


def _assert_paper_scale(cfg, experiment: str, points: int) -> None:
    backbone, loss_name = experiment.split("_")
    paper = PAPER[backbone]
    assert cfg.trainer.num_points == points
    assert cfg.optimizer.lr == pytest.approx(paper["gt_lr" if loss_name == "gt" else "lr"])
    assert cfg.scheduler.name == "constant" and cfg.trainer.evaluate_checkpoint == "best"
    stages = [(s.name, s.epochs, s.subset, s.variant) for s in Curriculum.from_config(cfg.curriculum).stages]
    assert stages == (SUPERVISED_STAGES if loss_name == "gt" else UNSUPERVISED_STAGES)
    loss = OmegaConf.to_container(cfg.loss, resolve=True)
    if "alignment" in loss["terms"] and loss["terms"]["alignment"]["name"] == "line_intersection":
        assert loss["num_lines"] == paper["lines"]
    assert {key: cfg.model[key] for key in paper["model"]} == paper["model"]
    assert cfg.iterate.rule == "last"


RESULTS_COMMANDS = _commands(ROOT / "docs" / "results.md", "The paper's scale on each protocol's data")


def _dataset(command: list[str]) -> str:
    return next(arg.split("=")[1] for arg in command if arg.startswith("dataset="))


@pytest.mark.parametrize("command", RESULTS_COMMANDS, ids=_dataset)
@pytest.mark.parametrize("experiment", ["rpm_ours", "dcp_ours", "fmr_cd", "rpm_gt"])
def test_the_paper_scale_commands_compose_to_the_papers_values(command, experiment):
    overrides = [arg if not arg.startswith("experiment=") else f"experiment={experiment}" for arg in command[1:]]
    assert "recipe=paper" in overrides and not any(arg.startswith("protocol=") for arg in overrides)
    cfg = _compose(overrides)
    _assert_paper_scale(cfg, experiment, 2048 if "trainer.num_points=2048" in overrides else 1024)
    folder = cfg.paths.data_dir if _dataset(command) == "modelnet40_airplane" else cfg.paths.shared_data_dir
    assert cfg.dataset.root.startswith(folder)


def test_the_readme_gives_the_paper_scale_and_the_cpu_scale():
    train = _commands(ROOT / "README.md", "## Train")
    paper = [command for command in train if "recipe=paper" in command]
    assert len(paper) == 2
    cpu_scale = _compose(_overrides(next(c for c in paper if "protocol=airplane" in c)))
    assert cpu_scale.trainer.num_points == 256 and cpu_scale.optimizer.lr == pytest.approx(1e-4)
    full_scale = next(c for c in paper if "protocol=airplane" not in c)
    _assert_paper_scale(_compose(_overrides(full_scale)), "rpm_ours", 1024)


@pytest.mark.skipif(
    importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None, reason="no submitit launcher"
)
def test_the_readme_slurm_example_trains_a_protocol_on_the_named_data():
    (slurm,) = [command for command in _commands(ROOT / "README.md", "On several GPUs") if "launcher=slurm" in command]
    cfg = _compose(_overrides(slurm), hydra=True)
    launcher = cfg.hydra.launcher
    assert "submitit" in launcher._target_ and launcher.tasks_per_node == launcher.gpus_per_node == 4
    shared = next(arg.split("=")[1] for arg in slurm if arg.startswith("paths.shared_data_dir="))
    assert cfg.dataset.name == "modelnet40" and cfg.dataset.root == f"{shared}/modelnet40_normal_resampled"
    assert cfg.trainer.batch_size == 8  # per process: 4 processes train on 32 pairs per step (README)
