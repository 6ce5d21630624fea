"""Every Hydra config composes and every component it names builds (lightning-hydra-template style)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf, open_dict

from linereg.datasets.splits import dataset_config
from linereg.losses import build_loss
from linereg.models import MODELS
from linereg.train.curriculum import Curriculum
from linereg.train.loop import TrainerSettings
from linereg.train.optim import OPTIMIZERS, SCHEDULERS
from tests.conftest import compose_config as shared_compose

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
PATHS = [f"paths.root_dir={ROOT}", "paths.output_dir=/tmp/linereg-config-test"]


def compose_config(name: str = "train", overrides: list[str] | None = None):
    """Compose ``configs/<name>.yaml`` with :data:`PATHS` and overrides (outside any Hydra run)."""
    return shared_compose(name, [*PATHS, *(overrides or [])])


def build_components(cfg) -> None:
    """Build what a run builds before touching data: model, loss, optimizer, scheduler, ..."""
    model = MODELS.build(OmegaConf.to_container(cfg.model, resolve=True))
    build_loss(cfg.loss)
    optimizer = OPTIMIZERS.build(cfg.optimizer, model.parameters())
    curriculum = Curriculum.from_config(cfg.curriculum)
    SCHEDULERS.build(cfg.scheduler, optimizer, epochs=curriculum.stages[0].epochs)
    TrainerSettings.from_config(cfg.trainer)
    for split in ("train", "val", "test"):
        dataset_config(cfg.dataset, split)
    for stage in curriculum.stages:
        if stage.variant is not None:
            dataset_config(cfg.dataset, "train", stage.variant)


def test_experiment_list_is_complete():
    expected = {f"{m}_{l}" for m in ("rpm", "dcp", "fmr") for l in ("ours", "cd", "cdw", "gt")}
    assert set(EXPERIMENTS) == expected


def test_default_config_builds():
    cfg = compose_config()
    assert cfg.model.name == "rpmnet" and "alignment" in cfg.loss.terms
    assert cfg.loss.terms.alignment.name == "line_intersection"
    assert cfg.dataset.name == "procedural"
    build_components(cfg)


def test_default_is_the_label_free_easy_pose_recipe():
    """``python -m train`` (README, docs/results.md): easy poses only, lr 1e-3 decayed, last checkpoint."""
    cfg = compose_config()
    curriculum = Curriculum.from_config(cfg.curriculum)
    assert [(s.name, s.variant, s.subset) for s in curriculum.stages] == [("easy", "easy", None)]
    assert curriculum.stages[0].learning_rate(cfg.optimizer.lr) == pytest.approx(1e-3)
    assert cfg.scheduler.name == "cosine" and cfg.trainer.num_points == 256
    assert cfg.trainer.evaluate_checkpoint == "last"  # no label chooses the checkpoint
    terms = OmegaConf.to_container(cfg.loss, resolve=True)["terms"]
    assert terms["outlier"]["weight"] == 0.3 and terms["alignment"]["name"] == "line_intersection"


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_recipe_cpu_sets_the_schedule_of_every_experiment_and_protocol(experiment):
    """The default recipe=cpu sets the schedule of every experiment; a protocol adapts its stages
    (configs/curriculum/cpu_<protocol>.yaml), a backbone or loss its own values (configs/cell/cpu_*.yaml)."""
    stages = {
        "": [("easy", 6, "easy")],
        "airplane": [("easy", 4, "easy")],
        "human": [("easy", 4, "easy"), ("full", 4, None)],  # then the full pose range
        "real": [("easy", 4, "easy"), ("full", 4, None)],  # then the test pairs' frame gap
    }
    for protocol, expected in stages.items():
        extra = [f"protocol={protocol}"] if protocol else []
        cfg = compose_config(overrides=[f"experiment={experiment}", *extra])
        curriculum = Curriculum.from_config(cfg.curriculum)
        if experiment.startswith("dcp") and protocol == "airplane":
            expected = [("easy", 4, "easy"), ("full", 4, None)]  # configs/cell/cpu_airplane_dcp_*.yaml
        assert [(s.name, s.epochs, s.variant) for s in curriculum.stages] == expected, protocol
        rates = [s.learning_rate(cfg.optimizer.lr) for s in curriculum.stages]
        assert all(s.subset is None for s in curriculum.stages) and rates == pytest.approx([1e-3] * len(rates))
        if experiment.endswith("_ours"):
            assert cfg.loss.terms.alignment.nu0 == (2.0 if protocol == "human" else None)
        assert cfg.scheduler.name == "cosine" and cfg.trainer.evaluate_checkpoint == "last"
        assert cfg.trainer.num_points == 256
        terms = OmegaConf.to_container(cfg.loss, resolve=True)["terms"]
        if "outlier" in terms:
            assert terms["outlier"]["weight"] == 0.3
        if terms.get("alignment", {}).get("name") == "line_intersection":
            many = protocol == "human" or (protocol, experiment) == ("airplane", "dcp_ours")
            assert terms["alignment"]["num_lines"] == (20000 if many else 5000)
        if experiment.startswith("rpm"):  # RPM-Net scores its best-fitting iterate on every protocol
            assert cfg.iterate.rule == ("best_fit" if protocol else "last")
            # Real's fit keeps 90 % of the distances (chosen on its training pairs), the others all
            assert cfg.iterate.keep_fraction == (0.9 if protocol == "real" else 1.0)
        elif experiment.startswith("fmr"):  # FMR on Human and Real
            assert cfg.iterate.rule == ("best_fit" if protocol in ("human", "real") else "last")
            assert cfg.iterate.keep_fraction == 1.0
        else:
            assert cfg.iterate.rule == "last"
        assert "keep_best_iterate" not in cfg.model and "fit_keep_fraction" not in cfg.model
        build_components(cfg)


@pytest.mark.parametrize("protocol", ["", "human", "real"])
def test_optimizer_lr_sets_every_stage_of_the_recipe(protocol):
    """``optimizer.lr=1e-4`` (fine-tuning a trained model, docs/results.md) reaches both stages."""
    extra = [f"protocol={protocol}"] if protocol else []
    cfg = compose_config(overrides=["experiment=rpm_ours", *extra, "optimizer.lr=1e-4"])
    rates = [s.learning_rate(cfg.optimizer.lr) for s in Curriculum.from_config(cfg.curriculum).stages]
    assert rates == pytest.approx([1e-4] * (1 if not protocol else 2))


@pytest.mark.parametrize("protocol", ["", "human"])
def test_one_key_per_knob_reaches_the_loss_and_the_saved_config(protocol):
    """``loss.num_lines``, ``loss.terms.outlier.weight`` and ``loss.nu0`` are the only keys of their
    knobs: set on the command line they win over the recipe's files and show in the resolved config."""
    extra = [f"protocol={protocol}"] if protocol else []
    for experiment in ("rpm_ours", "rpm_cd", "rpm_cdw"):
        cfg = compose_config(overrides=[f"experiment={experiment}", *extra, "loss.terms.outlier.weight=1"])
        assert build_loss(cfg.loss).weights["outlier"] == 1.0
    cfg = compose_config(overrides=["experiment=fmr_ours", *extra, "loss.num_lines=2000", "loss.nu0=1.5"])
    options = build_loss(cfg.loss).parts["alignment"].options
    assert (options.num_lines, options.nu0) == (2000, 1.5)
    resolved = OmegaConf.to_container(cfg.loss, resolve=True)
    assert resolved["num_lines"] == resolved["terms"]["alignment"]["num_lines"] == 2000
    assert "num_lines" not in compose_config(overrides=["experiment=fmr_cd", *extra]).loss  # no such knob


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_recipe_paper_keeps_the_experiments_schedule_and_checkpoint(experiment):
    """``recipe=paper`` is one switch back to the paper's settings, alone or at a grid's scale."""
    for extra in ([], ["protocol=airplane"]):
        cfg = compose_config(overrides=[f"experiment={experiment}", "recipe=paper", *extra])
        assert cfg.scheduler.name == "constant" and cfg.trainer.evaluate_checkpoint == "best"
        terms = OmegaConf.to_container(cfg.loss, resolve=True)["terms"]
        if "outlier" in terms:
            assert terms["outlier"]["weight"] == 10.0
    human = compose_config(overrides=[f"experiment={experiment}", "recipe=paper", "protocol=human"])
    paper = compose_config(overrides=[f"experiment={experiment}", "recipe=paper"])
    assert human.loss.nu0 == paper.loss.nu0  # the CPU recipe's Human values stay out
    if not experiment.startswith("dcp"):
        real = compose_config(overrides=[f"experiment={experiment}", "recipe=paper", "protocol=real"])
        assert human.iterate.rule == paper.iterate.rule == real.iterate.rule == "last"
        assert real.iterate.keep_fraction == 1.0  # Real's trimmed fit stays out too
    airplane = compose_config(overrides=[f"experiment={experiment}", "recipe=paper", "protocol=airplane"])
    grid = compose_config(overrides=["experiment=rpm_gt", "recipe=paper", "protocol=airplane"])  # no file of its own
    assert Curriculum.from_config(airplane.curriculum).stages == Curriculum.from_config(grid.curriculum).stages
    if experiment.endswith("_ours"):
        assert human.loss.num_lines == airplane.loss.num_lines == paper.loss.num_lines != 20000


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes_and_builds(experiment):
    cfg = compose_config(overrides=[f"experiment={experiment}"])
    assert cfg.task_name == experiment
    build_components(cfg)


@pytest.mark.parametrize(
    ("experiment", "lr", "lines", "radius"),
    [("rpm_ours", 2e-6, 10000, 1.0), ("dcp_ours", 1e-5, 15000, 0.5), ("fmr_ours", 1e-5, 15000, 0.5)],
)
def test_experiment_values_win_over_train_yaml(experiment, lr, lines, radius):
    """recipe=paper: each backbone's learning rate and the loss files' line settings are the ones used."""
    cfg = compose_config(overrides=[f"experiment={experiment}", "recipe=paper"])
    assert cfg.optimizer.lr == pytest.approx(lr)
    alignment = OmegaConf.to_container(cfg.loss, resolve=True)["terms"]["alignment"]
    assert (alignment["num_lines"], alignment["radius_factor"]) == (lines, radius)
    assert cfg.trainer.num_points == 1024
    assert cfg.dataset.protocol.num_points == 1024  # the dataset follows trainer.num_points


def test_paper_loss_weights():
    terms = {
        name: OmegaConf.to_container(
            compose_config(overrides=[f"experiment={name}", "recipe=paper"]).loss.terms, resolve=True
        )
        for name in ("rpm_ours", "dcp_ours", "fmr_ours")
    }
    assert terms["rpm_ours"]["outlier"]["weight"] == 10.0 and terms["rpm_ours"]["alignment"]["weight"] == 1.0
    assert terms["dcp_ours"]["cycle"]["weight"] == 0.01
    assert terms["fmr_ours"]["reconstruction"]["weight"] == 0.001
    assert terms["fmr_ours"]["alignment"]["last_k"] == 3


@pytest.mark.parametrize(
    "group",
    ["model", "loss", "dataset", "curriculum", "optimizer", "scheduler", "logger", "debug", "recipe", "protocol"],
)
def test_every_group_option_composes(group):
    for option in sorted(p.stem for p in (CONFIGS / group).glob("*.yaml")):
        overrides = [f"{group}={option}"]
        if group == "loss" and option.startswith(("dcp", "fmr")):
            overrides.append(f"model={'dcp_v2' if option.startswith('dcp') else 'fmr'}")
        cfg = compose_config(overrides=overrides)
        if group in ("model", "loss", "optimizer", "curriculum", "scheduler"):
            build_components(cfg)


def test_sweep_handle_on_a_loss_without_it_warns():
    cfg = compose_config(overrides=["experiment=rpm_cd", "loss.nu0=0.1"])
    with pytest.warns(UserWarning, match=r"loss.nu0=0.1 has no effect"):
        build_loss(cfg.loss)


def test_sweep_handle_reaches_the_term():
    cfg = compose_config(overrides=["experiment=rpm_ours", "loss.nu0=2"])
    loss = build_loss(cfg.loss)
    assert loss.parts["alignment"].options.nu0 == 2.0


@pytest.mark.parametrize("experiment", ["rpm_ours", "dcp_ours", "fmr_ours"])
@pytest.mark.parametrize(("variant", "nu0"), [("paper", 0.5), ("authors", 1.0), ("linereg", 0.5)])
def test_line_variant_switch_brings_its_own_nu0(experiment, variant, nu0):
    """``loss.variant=...`` is one switch: each preset keeps its Welsch scale unless loss.nu0 is set."""
    cfg = compose_config(overrides=[f"experiment={experiment}", f"loss.variant={variant}"])
    options = build_loss(cfg.loss).parts["alignment"].options
    assert options.nu0 == nu0
    assert options.sampling == ("authors" if variant == "authors" else "sphere")
    swept = compose_config(overrides=[f"experiment={experiment}", f"loss.variant={variant}", "loss.nu0=0.3"])
    assert build_loss(swept.loss).parts["alignment"].options.nu0 == 0.3


def test_null_handle_defaults_the_term_in_a_resolved_config():
    """A resumed run rebuilds its loss from the saved, resolved config: null handles still default."""
    cfg = compose_config(overrides=["experiment=rpm_ours", "loss.variant=authors"])
    resolved = OmegaConf.to_container(cfg.loss, resolve=True)
    assert resolved["nu0"] is None and resolved["terms"]["alignment"]["nu0"] is None
    assert build_loss(resolved).parts["alignment"].options.nu0 == 1.0


def test_unknown_command_line_key_is_rejected():
    with pytest.raises(ConfigCompositionException, match=r"trainer\.batch_sise"):
        compose_config(overrides=["trainer.batch_sise=4"])


def test_unknown_keys_in_config_files_give_clear_errors():
    cfg = compose_config()
    with open_dict(cfg):
        cfg.trainer.batch_sise = 4
        cfg.curriculum.stages.easy.epoch = 3
        cfg.loss.terms.alignment.num_line = 10
        cfg.model.neighbours = 3
    with pytest.raises(ValueError, match=r"unknown trainer key\(s\) \['batch_sise'\]"):
        TrainerSettings.from_config(cfg.trainer)
    with pytest.raises(ValueError, match=r"stage 'easy': unknown key\(s\) \['epoch'\]"):
        Curriculum.from_config(cfg.curriculum)
    with pytest.raises(TypeError, match="num_line"):
        build_loss(cfg.loss)
    with pytest.raises(TypeError, match="neighbours"):
        MODELS.build(OmegaConf.to_container(cfg.model))


def test_optimizer_with_unknown_argument():
    with pytest.raises(TypeError, match=r"optimizer 'adam'.*momentum"):
        OPTIMIZERS.build({"name": "adam", "lr": 1e-3, "momentum": 0.9}, [torch.nn.Parameter(torch.zeros(1))])
    with pytest.raises(KeyError, match="registered: adam, adamw, sgd"):
        OPTIMIZERS.build({"name": "adagrad", "lr": 1e-3}, [torch.nn.Parameter(torch.zeros(1))])


def test_hydra_sweep_folder_names_are_readable(hydra_compose):
    full = hydra_compose("train", PATHS, hydra=True)
    sweep = OmegaConf.to_container(full.hydra.sweep, resolve=False)
    assert sweep["subdir"] == "${hydra.job.num}_${hydra.job.override_dirname}"
    assert full.hydra.job.config.override_dirname.kv_sep == "="
    assert full.hydra.callbacks.sweep_summary._target_ == "linereg.train.summary.SweepSummary"


@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_optuna_sweeper") is None, reason="no optuna sweeper")
def test_optuna_search_composes(hydra_compose):
    cfg = hydra_compose("train", [*PATHS, "hparams_search=optuna"], hydra=True)
    assert cfg.hydra.sweeper.params["loss.nu0"] == "interval(0.1, 2.0)"
    assert cfg.optimized_metric == "val/err_r_deg_mean"


@pytest.mark.skipif(
    importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None, reason="no submitit launcher"
)
def test_slurm_launcher_composes(hydra_compose):
    cfg = hydra_compose("train", [*PATHS, "launcher=slurm"], hydra=True)
    assert cfg.hydra.launcher.tasks_per_node == 1
    assert "submitit" in cfg.hydra.launcher._target_


def test_evaluate_config_composes_with_a_dataset():
    cfg = compose_config(
        "evaluate", overrides=["checkpoint=x.pt", "dataset=modelnet40_airplane", "trainer.num_points=256"]
    )
    assert cfg.dataset.categories == "airplane"
    assert dataset_config(cfg.dataset, "test")["protocol"]["num_points"] == 256
    assert compose_config("evaluate", overrides=["checkpoint=x.pt"]).get("dataset") is None


PROTOCOLS = sorted(p.stem for p in (CONFIGS / "protocol").glob("*.yaml") if p.stem != "none")


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("experiment", ["rpm_ours", "dcp_cd", "fmr_gt"])
def test_paper_recipe_at_a_protocol_has_one_scale_for_every_experiment(protocol, experiment):
    """``protocol=... recipe=paper`` (scripts/reproduce.sh) sets one scale for every cell of a table."""
    cfg = compose_config(overrides=[f"experiment={experiment}", f"protocol={protocol}", "recipe=paper"])
    assert cfg.task_name == f"{experiment}_{protocol}"  # the cell's, a plain value
    assert cfg.trainer.num_points == 256
    assert (cfg.trainer.device, cfg.trainer.threads, cfg.trainer.progress) == ("auto", None, True)  # the command's
    assert cfg.optimizer.lr == pytest.approx(1e-4)
    full_epochs = {"human": 8, "real": 6}.get(protocol, 2)  # the small training sets get more
    assert [(s.name, s.epochs) for s in Curriculum.from_config(cfg.curriculum).stages] == [
        ("easy", 3),
        ("subset", 1),
        ("full", full_epochs),
    ]
    assert cfg.dataset.name == {"airplane": "modelnet40", "human": "mesh_folder", "real": "rgbd_sequence"}.get(
        protocol, "procedural"
    )
    build_components(cfg)


def test_protocol_splits_on_the_shared_data(shared_data):
    """Pair counts of docs/results.md: held-out shapes, held-out views, a split in time."""
    from linereg.datasets import build_dataset

    expected = {"airplane": (864, 216), "human": (120, 30), "real": (190, 40)}
    for protocol, counts in expected.items():
        cfg = compose_config(overrides=["experiment=rpm_ours", f"protocol={protocol}"])
        dataset = OmegaConf.to_container(cfg.dataset, resolve=True)
        sizes = []
        for split in ("train", "test"):
            config = dataset_config(dataset, split)
            config.pop("cache_dir")
            sizes.append(len(build_dataset(config)))
        assert tuple(sizes) == counts, protocol
