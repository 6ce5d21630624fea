"""Fast dev runs of ``train(cfg)`` (``debug=tiny``): every model, unlabelled data, NaN handling."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from linereg.checkpoint import load_checkpoint
from linereg.io import write_point_cloud
from linereg.losses import Loss
from linereg.models import load_model
from linereg.structures import LossOutput
from linereg.train import loop
from linereg.train.logging import read_scalars
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parent.parent


def tiny_config(output_dir: Path, *overrides: str, debug: str | None = "tiny"):
    """``configs/train.yaml`` with a debug preset and the run folder in ``output_dir``."""
    preset = [f"debug={debug}"] if debug else []
    return compose_config("train", [*preset, f"paths.root_dir={ROOT}", f"paths.output_dir={output_dir}", *overrides])


# debug=tiny without its procedural-data settings, for other datasets.
SMALL_RUN = [
    "trainer.device=cpu",
    "trainer.threads=1",
    "trainer.num_points=64",
    "trainer.batch_size=2",
    "trainer.eval_batch_size=2",
    "trainer.max_steps_per_epoch=2",
    "trainer.progress=false",
    "logger=none",
    "model.num_neighbors=8",
    "curriculum=none",
    "curriculum.stages.full.epochs=2",
]


SMALL_MODELS = {
    "rpm": ["model.num_neighbors=8"],
    "dcp": ["model.emb_dims=64", "model.ff_dims=64", "model.k=8"],
    "fmr": ["model.dim_k=64"],
}
EXPERIMENTS = sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml"))


@pytest.mark.parametrize("experiment", ["rpm_ours", "dcp_ours", "fmr_ours"])
def test_fast_dev_run_of_every_model(tmp_path, experiment):
    extra = [*SMALL_MODELS[experiment.split("_")[0]], "loss.num_lines=400"]
    cfg = tiny_config(tmp_path, f"experiment={experiment}", *extra)
    result = loop.train(cfg)
    metrics = result["metrics"]
    for key in ("val/err_r_deg_mean", "test/err_r_deg_mean", "test/identity/err_r_deg_mean", "test/recall@0.05"):
        assert np.isfinite(metrics[key]), key
    checkpoint = load_checkpoint(result["last_checkpoint"])
    # 4 training pairs: the easy stage (2 pairs) and the half stage take 1 step, the last 2.
    assert checkpoint["progress"] == {
        "epoch": 3,
        "batch": 0,
        "global_step": 4,
        "stage": 2,
        "stage_name": "full",
        "bad_steps": 0,
    }
    assert checkpoint["config"]["task_name"] == "tiny"
    assert (tmp_path / "checkpoints" / "best.pt").is_file()
    assert (tmp_path / "evaluation" / "metrics.json").is_file()
    assert json.loads((tmp_path / "metrics.json").read_text())["metrics"]["best_epoch"] in (1, 2, 3)
    records = read_scalars(tmp_path)
    steps = [r for r in records if "train/loss" in r]
    assert len(steps) == 4
    expected = {"train/loss/alignment", "train/lr", "train/grad_norm/total", "train/stats/alignment/lines_hit_both"}
    terms = [tag.removeprefix("train/loss/") for tag in steps[0] if tag.startswith("train/loss/")]
    assert expected | {f"train/grad_norm/{term}" for term in terms} <= set(steps[0])
    stage_changes = [r["curriculum/stage"] for r in records if "curriculum/stage" in r]
    assert stage_changes == [0, 1, 2]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_trains(tmp_path, experiment):
    cfg = tiny_config(tmp_path, f"experiment={experiment}", *SMALL_MODELS[experiment.split("_")[0]])
    metrics = loop.train(cfg)["metrics"]
    assert np.isfinite(metrics["test/err_r_deg_mean"]) and np.isfinite(metrics["val/loss"])


def test_curriculum_sets_data_and_learning_rate(tmp_path):
    cfg = tiny_config(
        tmp_path,
        "model.num_neighbors=8",
        "loss.num_lines=300",
        "optimizer.lr=1e-3",
        "curriculum.stages.easy.lr=5e-3",
        "curriculum.stages.full.lr_scale=0.1",
        "dataset.splits.train.num_shapes=3",
        "dataset.protocol.num_views=2",
    )
    loop.train(cfg)
    records = read_scalars(tmp_path)
    pairs = [r["curriculum/train_pairs"] for r in records if "curriculum/train_pairs" in r]
    assert pairs == [2, 3, 6]  # easy subset of 2, half of 6, all 6
    lrs = [r["train/lr"] for r in records if "train/lr" in r]
    assert lrs == pytest.approx([5e-3, 1e-3, 1e-3, 1e-4, 1e-4])


def _unlabelled_pairs(folder: Path, count: int = 4) -> None:
    """Pairs of random blobs without ``_gt.txt`` files (a dataset with no ground truth)."""
    rng = np.random.default_rng(0)
    folder.mkdir()
    for i in range(count):
        cloud = rng.normal(size=(200, 3)) * [1.0, 0.6, 0.3]
        write_point_cloud(folder / f"p{i}_src.ply", cloud)
        write_point_cloud(folder / f"p{i}_tgt.ply", cloud + 0.05)


def test_unsupervised_run_without_any_ground_truth(tmp_path):
    data = tmp_path / "pairs"
    _unlabelled_pairs(data)
    overrides = ["dataset=pairs_folder", f"dataset.root={data}", "dataset.splits.val={}", "loss.num_lines=300"]
    cfg = tiny_config(tmp_path / "run", *SMALL_RUN, *overrides, debug=None)
    with pytest.warns(UserWarning, match="selecting the best checkpoint by register's check"):
        result = loop.train(cfg)
    metrics = result["metrics"]
    assert "val/loss" in metrics and "val/check_score" in metrics and "test/err_r_deg_mean" not in metrics
    assert json.loads((tmp_path / "run" / "evaluation" / "metrics.json").read_text())["labelled"] is False


def test_fine_tuning_on_unlabelled_pairs_under_the_recipe(tmp_path):
    """The README's fine-tuning command: the recipe's stage on the pairs as they are, at ``optimizer.lr``."""
    data = tmp_path / "pairs"
    _unlabelled_pairs(data)
    recipe_stages = [o for o in SMALL_RUN if not o.startswith("curriculum")]  # keep the recipe's curriculum
    small = [*recipe_stages, "loss.num_lines=300", "dataset=pairs_folder", f"dataset.root={data}"]
    small += ["dataset.splits.val={}", "curriculum.stages.easy.epochs=1"]
    as_they_are = "curriculum.stages.easy.variant=null"
    with pytest.warns(UserWarning, match="selecting the best checkpoint"):
        loop.train(tiny_config(tmp_path / "first", "experiment=rpm_ours", *small, as_they_are, debug=None))
    tuning = ["experiment=rpm_ours", *small, as_they_are, f"init_from={tmp_path / 'first'}", "optimizer.lr=1e-4"]
    cfg = tiny_config(tmp_path / "tuned", *tuning, debug=None)
    with pytest.warns(UserWarning, match="selecting the best checkpoint"):
        loop.train(cfg)
    optimizer = load_checkpoint(tmp_path / "tuned" / "checkpoints" / "last.pt")["optimizer"]
    assert optimizer["param_groups"][0]["initial_lr"] == pytest.approx(1e-4)  # the cosine decay starts there
    with pytest.raises(ValueError, match="has no variant 'easy'"):  # the recipe's easy poses need a variant
        loop.train(tiny_config(tmp_path / "no_variant", "experiment=rpm_ours", *small, debug=None))


def test_supervised_loss_on_unlabelled_data_is_refused(tmp_path):
    data = tmp_path / "pairs"
    _unlabelled_pairs(data)
    cfg = tiny_config(
        tmp_path / "run", "experiment=rpm_gt", *SMALL_RUN, "dataset=pairs_folder", f"dataset.root={data}", debug=None
    )
    with pytest.raises(ValueError, match=r"needs batch\.gt_transform"):
        loop.train(cfg)


class _PoisonedLoss(Loss):
    """Chamfer-free stand-in: a finite loss, except NaN for pair ``bad_index`` (every pair: ``None``)."""

    def __init__(self, bad_index: int | None) -> None:
        super().__init__()
        self.bad_index = bad_index

    def compute(self, output, batch):
        value = (output.transform[:, :3, 3] ** 2).sum(dim=1)
        bad = torch.tensor([self.bad_index is None or m["index"] == self.bad_index for m in batch.meta])
        value = torch.where(bad, torch.full_like(value, float("nan")), value)
        return LossOutput(total=value.mean(), terms={"toy": value.mean()})


def test_nan_loss_skips_the_step_and_names_the_sample(tmp_path, monkeypatch):
    monkeypatch.setattr(loop, "build_loss", lambda config: _PoisonedLoss(bad_index=1))
    cfg = tiny_config(
        tmp_path,
        "model.num_neighbors=8",
        "curriculum=none",
        "curriculum.stages.full.epochs=1",
        "trainer.batch_size=1",
        "trainer.max_steps_per_epoch=null",
    )
    with pytest.warns(RuntimeWarning, match=r"step skipped: non-finite loss nan .*sample 0 \(meta \{.*'index': 1"):
        result = loop.train(cfg)
    state = load_checkpoint(result["last_checkpoint"])
    assert state["progress"]["global_step"] > 0
    assert state["best"]["value"] is not None


def test_a_run_whose_every_step_is_skipped_fails(tmp_path, monkeypatch):
    monkeypatch.setattr(loop, "build_loss", lambda config: _PoisonedLoss(bad_index=None))
    cfg = tiny_config(tmp_path, "model.num_neighbors=8", "curriculum=none", "curriculum.stages.full.epochs=1")
    with (
        pytest.raises(FloatingPointError, match=r"every training step of epoch 1 \(2 of 2\) was skipped"),
        pytest.warns(RuntimeWarning, match="step skipped"),
    ):
        loop.train(cfg)
    assert not (tmp_path / "checkpoints" / "best.pt").exists()
    assert not (tmp_path / "metrics.json").exists()


def test_a_diverging_learning_rate_does_not_exit_cleanly(tmp_path):
    cfg = tiny_config(tmp_path, "model.num_neighbors=8", "loss.num_lines=300", "optimizer.lr=1e30")
    with pytest.raises(FloatingPointError, match=r"skipped|finite"), pytest.warns(RuntimeWarning):
        loop.train(cfg)
    assert not (tmp_path / "metrics.json").exists()


def test_repeated_nan_losses_stop_the_run(tmp_path, monkeypatch):
    monkeypatch.setattr(loop, "build_loss", lambda config: _PoisonedLoss(bad_index=1))
    cfg = tiny_config(
        tmp_path,
        "model.num_neighbors=8",
        "curriculum=none",
        "curriculum.stages.full.epochs=1",
        "trainer.batch_size=4",
        "trainer.max_bad_steps=1",
    )
    with pytest.raises(FloatingPointError, match="1 consecutive steps"), pytest.warns(RuntimeWarning):
        loop.train(cfg)


def test_train_on_cuda_without_cuda_fails_before_any_data(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(loop, "build_split", lambda *args, **kwargs: pytest.fail("data was generated"))
    with pytest.raises(ValueError, match="CUDA is not available"):
        loop.train(tiny_config(tmp_path, "trainer.device=cuda"))


class _ThreeTermLoss(Loss):
    """Terms with known gradient ratios: ``double`` = 2 x ``single``, ``constant`` independent of the model."""

    def compute(self, output, batch):
        single = (output.transform[:, :3, 3] ** 2).sum(dim=1).mean()
        terms = {"single": single, "double": 2 * single, "constant": single.new_tensor(1.0)}
        return LossOutput(total=sum(terms.values()), terms=terms)


def _toy_run(folder: Path, *overrides: str) -> dict:
    cfg = tiny_config(folder, "model.num_neighbors=8", "trainer.grad_clip_norm=null", *overrides)
    return loop.train(cfg)


def test_term_gradient_norms_are_logged_on_logging_steps_without_changing_training(tmp_path, monkeypatch):
    monkeypatch.setattr(loop, "build_loss", lambda config: _ThreeTermLoss())
    logged = _toy_run(tmp_path / "logged", "trainer.log_every=2")
    records = [r for r in read_scalars(tmp_path / "logged") if "train/loss" in r]
    assert [r["step"] for r in records] == [2, 4]
    for record in records:
        single, double = record["train/grad_norm/single"], record["train/grad_norm/double"]
        assert single > 0 and double == pytest.approx(2 * single, rel=1e-5)
        assert record["train/grad_norm/constant"] == 0.0
        # The total's gradient is 3 x that of ``single`` (the constant adds none), before clipping.
        assert record["train/grad_norm/total"] == pytest.approx(3 * single, rel=1e-5)
    # The extra backward passes leave the optimisation untouched.
    plain = _toy_run(tmp_path / "plain", "trainer.log_every=2", "trainer.log_term_grad_norms=false")
    assert not any("train/grad_norm/single" in r for r in read_scalars(tmp_path / "plain"))
    for name, value in load_checkpoint(logged["last_checkpoint"])["model"].items():
        torch.testing.assert_close(value, load_checkpoint(plain["last_checkpoint"])["model"][name], rtol=0, atol=0)


def test_an_annealed_welsch_scale_moves_before_each_epoch_and_is_logged(tmp_path):
    _toy_run(tmp_path, "loss.num_lines=400", "loss.nu0=2.0", "loss.nu0_final=0.5")
    tag = "loss_schedule/parts.alignment.nu0"
    logged = [record[tag] for record in read_scalars(tmp_path) if tag in record]
    assert logged == pytest.approx([2.0, 1.0, 0.5])  # debug=tiny: three one-epoch stages


def test_a_loss_term_named_total_is_refused_for_gradient_norms(tmp_path, monkeypatch):
    class TotalTerm(Loss):
        def compute(self, output, batch):
            value = (output.transform[:, :3, 3] ** 2).sum()
            return LossOutput(total=value, terms={"total": value})

    monkeypatch.setattr(loop, "build_loss", lambda config: TotalTerm())
    with pytest.raises(ValueError, match=r"named 'total'.*log_term_grad_norms=false"):
        _toy_run(tmp_path)


def test_untrained_run_evaluates_the_initial_weights_like_a_trained_run(tmp_path):
    common = ["model.num_neighbors=8", "loss.num_lines=300"]
    trained = loop.train(tiny_config(tmp_path / "trained", *common))["metrics"]
    result = loop.train(tiny_config(tmp_path / "untrained", *common, "trainer.untrained=true"))
    run = tmp_path / "untrained"
    content = json.loads((run / "metrics.json").read_text())
    assert content["untrained"] is True
    assert content["evaluated_checkpoint"] == {
        "file": "last.pt",
        "path": str(run / "checkpoints" / "last.pt"),
        "epoch": 0,
    }
    state = load_checkpoint(run / "checkpoints" / "last.pt")
    assert state["progress"] == {
        "epoch": 0,
        "batch": 0,
        "global_step": 0,
        "stage": None,
        "stage_name": None,
        "bad_steps": 0,
    }
    assert not (run / "checkpoints" / "best.pt").exists()
    assert not any("train/loss" in record for record in read_scalars(run))
    metrics = result["metrics"]
    # Same seed, same initial weights: the trained run validated them before its first step.
    assert metrics["val/err_r_deg_mean"] == pytest.approx(trained["val_initial/err_r_deg_mean"], rel=1e-6)
    for key in ("test/err_r_deg_mean", "test/identity/err_r_deg_mean"):
        assert np.isfinite(content["metrics"][key]), key
    assert json.loads((run / "evaluation" / "metrics.json").read_text())["checkpoint"].endswith("last.pt")
    model, _ = load_model(run)  # what python -m train.evaluate reads
    for name, value in model.state_dict().items():
        torch.testing.assert_close(value, state["model"][name])


def test_an_all_zero_curriculum_needs_the_untrained_switch(tmp_path):
    zero = [f"curriculum.stages.{stage}.epochs=0" for stage in ("easy", "subset", "full")]
    with pytest.raises(ValueError, match=r"no stage with epochs > 0.*trainer\.untrained=true"):
        loop.train(tiny_config(tmp_path / "refused", "model.num_neighbors=8", *zero))
    result = loop.train(
        tiny_config(
            tmp_path / "run",
            "model.num_neighbors=8",
            "loss.num_lines=300",
            *zero,
            "trainer.untrained=true",
            "evaluate_split=null",
        )
    )
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["evaluated_checkpoint"]["epoch"] == 0
    assert "val/err_r_deg_mean" in result["metrics"]


@pytest.mark.parametrize("choice", ["best", "last"])
def test_evaluate_checkpoint_chooses_the_evaluated_file(tmp_path, choice):
    cfg = tiny_config(tmp_path, "model.num_neighbors=8", "loss.num_lines=300", f"trainer.evaluate_checkpoint={choice}")
    result = loop.train(cfg)
    content = json.loads((tmp_path / "metrics.json").read_text())
    file = tmp_path / "checkpoints" / f"{choice}.pt"
    state = load_checkpoint(file)
    assert content["evaluated_checkpoint"] == {
        "file": file.name,
        "path": str(file),
        "epoch": state["progress"]["epoch"],
    }
    assert result["evaluated_checkpoint"] == str(file)
    if choice == "last":
        assert state["progress"]["epoch"] == 3
    else:
        assert state["progress"]["epoch"] == content["best"]["epoch"] == content["metrics"]["best_epoch"]
    assert content["metrics"]["val/err_r_deg_mean"] == pytest.approx(state["metrics"]["val/err_r_deg_mean"])
    assert json.loads((tmp_path / "evaluation" / "metrics.json").read_text())["checkpoint"] == str(file)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("evaluate_checkpoint", "final", "must be 'best' or 'last'"),
        ("untrained", "yes", "untrained must be true or false"),
        ("log_term_grad_norms", 1, "log_term_grad_norms must be true or false"),
    ],
)
def test_invalid_trainer_switches_are_named(key, value, message):
    with pytest.raises(ValueError, match=rf"trainer\.{key}.*{message}|{message}"):
        loop.TrainerSettings.from_config({key: value})
