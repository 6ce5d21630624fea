"""The training loop: ``train(cfg) -> dict`` (what ``python -m train`` runs, and tests call).

One run::

    seed -> model, loss, optimizer (registries, ``name:`` keys) -> for each curriculum stage:
        training split (subset / variant of the stage), learning rate, scheduler
        for each epoch: steps (AMP, gradient clipping, non-finite guard), validation every
        ``trainer.val_every`` epochs, ``last.pt`` (+ ``best.pt`` when the monitored metric
        improves), TensorBoard (every ``trainer.log_every`` steps: losses, their terms, the
        gradient norm of each term and the total, line statistics)
    -> evaluation of ``best.pt`` (``trainer.evaluate_checkpoint=last``: ``last.pt``) on
       ``evaluate_split`` (printed table, ``evaluation/``)
    -> ``metrics.json`` in the run folder (``evaluated_checkpoint``: which file, which epoch)

Unlabelled validation pairs are scored by register's check (``val/check_score``), which then
chooses ``best.pt``. A fine-tuning run (``init_from``) keeps its start network's points, cube and
iterate rule (:mod:`linereg.train.fine_tune`), and the start network is epoch 0's candidate.

The loss trains on every iterate the model returns; validation and evaluation measure the
errors of the iterate the config's ``iterate`` block chooses (:mod:`linereg.train.validation`).

``trainer.untrained=true`` runs no epoch (whatever the curriculum; an all-zero curriculum is an
error otherwise): the initial weights are validated, written as ``last.pt`` and evaluated
exactly like a trained run's, the control cell "untrained network" of a results table.

Checkpoints are written atomically at the end of every epoch (and every
``trainer.checkpoint_every_steps`` steps), so a run killed at any moment (Ctrl-C, ``kill -9``, a
pre-empted job) loses at most the steps since the last one; ``resume=true`` continues it, in a
new process, on exactly the uninterrupted run's trajectory: the checkpoint holds the weights,
optimizer, scheduler, curriculum stage and the sums of an unfinished epoch, and everything
random is derived from the seed and the position (:mod:`linereg.train.randomness`).
"""

from __future__ import annotations

import gc
import logging
import math
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from torch import nn
from tqdm.auto import tqdm

from linereg.checkpoint import BEST, CHECKPOINT_DIR, LAST, load_checkpoint
from linereg.datasets import configured_half_extent
from linereg.datasets.splits import build_split
from linereg.losses import build_loss, set_training_progress
from linereg.models import MODELS, upgrade_run_config
from linereg.registration.iterates import IterateRule
from linereg.structures import LossOutput, PairBatch, RegistrationOutput
from linereg.train import distributed, randomness
from linereg.train.checkpoint import load_resume_checkpoint, save_checkpoint
from linereg.train.curriculum import Curriculum, Stage
from linereg.train.diagnostics import describe_non_finite_loss, term_gradient_norms
from linereg.train.epoch import EpochSums
from linereg.train.evaluate import is_labelled
from linereg.train.faults import kill_point
from linereg.train.figures import registration_figure
from linereg.train.fine_tune import keep_start_settings
from linereg.train.logging import RunLogger
from linereg.train.optim import OPTIMIZERS, SCHEDULERS
from linereg.train.resume import config_for_resume, resume_checkpoint
from linereg.train.settings import TrainerSettings
from linereg.train.validation import Monitor, RunEvaluator, write_run_metrics

log = logging.getLogger(__name__)


class Trainer:
    """Trains one model through its curriculum (use :func:`linereg.train`).

    Args:
        config: the resolved run config (plain dict).
        run_dir: the run folder (checkpoints, logs, evaluation).
        ctx: distributed context of this process.
        loss: the loss (built by :func:`linereg.train` from the unresolved config, to check handles).
    """

    def __init__(self, config: dict[str, Any], run_dir: Path, ctx: distributed.DistContext, loss: nn.Module) -> None:
        self.config = config
        self.run_dir = run_dir
        self.checkpoints = run_dir / CHECKPOINT_DIR
        self.ctx = ctx
        self.settings = TrainerSettings.from_config(config["trainer"])
        self.device = ctx.device
        self.amp = distributed.amp_dtype(self.settings.amp, self.device)
        self.seed = int(config["seed"])
        self.model = MODELS.build(config["model"]).to(self.device)
        self.half_extent = configured_half_extent(config["dataset"])
        self.loss = loss.to(self.device)
        self.curriculum = Curriculum.from_config(config["curriculum"], allow_empty=self.settings.untrained)
        self.curriculum.check_variants(config["dataset"])
        self.optimizer = OPTIMIZERS.build(config["optimizer"], self.model.parameters())
        self.base_lr = float(config["optimizer"]["lr"])
        self.scheduler = None
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp == torch.float16)
        self.ddp_model = distributed.wrap(
            self.model, ctx, find_unused_parameters=self.settings.ddp_find_unused_parameters
        )
        self.epoch = 0
        self.global_step = 0
        self.stage_index: int | None = None
        self.monitor = Monitor(self.settings.monitor, self.settings.monitor_mode)
        iterate = IterateRule.from_config(config.get("iterate"))
        self.evaluator = RunEvaluator(self.model, self.loss, self.settings, self.device, self.amp, iterate, self.seed)
        self.bad_steps = 0
        self.epoch_sums: EpochSums | None = None  # the unfinished epoch of a resumed step checkpoint
        self.initial_metrics: dict[str, float] = {}
        self.train_data = None
        self.val_data = None
        self.assess_val = False
        self.logger: RunLogger | None = None

    # ----------------------------------------------------------------------------- state
    def state_dict(self, metrics: Mapping[str, float], epoch_sums: EpochSums | None = None) -> dict[str, Any]:
        """Everything needed to continue exactly (see :mod:`linereg.train.checkpoint`): at the end of
        an epoch, or (``epoch_sums``) after that many batches of epoch ``self.epoch``. Before the
        first stage (an untrained run) ``progress.stage`` and ``progress.stage_name`` are ``None``."""
        stage = None if self.stage_index is None else self.curriculum.stages[self.stage_index]
        return {
            "config": self.config,
            "half_extent": self.half_extent,
            "model": distributed.unwrap(self.model).state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": None if self.scheduler is None else self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(),
            "progress": {
                "epoch": self.epoch,
                "batch": 0 if epoch_sums is None else epoch_sums.batches,
                "global_step": self.global_step,
                "stage": self.stage_index,
                "stage_name": None if stage is None else stage.name,
                "bad_steps": self.bad_steps,
            },
            "epoch_sums": None if epoch_sums is None else epoch_sums.state(),
            "best": self.monitor.state(),
            "initial_metrics": dict(self.initial_metrics),
            "metrics": dict(metrics),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a checkpoint written by :meth:`state_dict` (the run continues after it)."""
        progress = state["progress"]
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scaler.load_state_dict(state["scaler"])
        self.epoch = int(progress["epoch"])
        self.global_step = int(progress["global_step"])
        self.bad_steps = int(progress.get("bad_steps", 0))
        self.monitor.load(state["best"])
        self.initial_metrics = dict(state.get("initial_metrics") or {})
        if state.get("epoch_sums") is not None:
            self.epoch_sums = EpochSums.from_state(state["epoch_sums"])
        if progress["stage"] is not None:  # None: saved before the first stage (an untrained run)
            self.stage_index = int(progress["stage"])
            stage = self.curriculum.stages[self.stage_index]
            if stage.name != progress["stage_name"]:
                raise ValueError(
                    f"checkpoint stage {progress['stage_name']!r} is not stage {progress['stage']} of the curriculum "
                    f"({stage.name!r})"
                )
        if self.epoch < self.curriculum.total_epochs:
            index, _ = self.curriculum.locate(self.epoch)
            self._enter_stage(index, resumed=True)
            if index == progress["stage"]:
                # The stage goes on: its learning rate and schedule as they were saved.
                for group, saved in zip(self.optimizer.param_groups, state["optimizer"]["param_groups"], strict=True):
                    group["lr"], group["initial_lr"] = saved["lr"], saved.get("initial_lr", saved["lr"])
                if self.scheduler is not None and state["scheduler"] is not None:
                    self.scheduler.load_state_dict(state["scheduler"])

    # ----------------------------------------------------------------------------- stages
    def _enter_stage(self, index: int, *, resumed: bool = False) -> None:
        """Switch to curriculum stage ``index``: its data, learning rate and scheduler."""
        stage: Stage = self.curriculum.stages[index]
        self.stage_index = index
        lr = stage.learning_rate(self.base_lr)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
            group["initial_lr"] = lr
        self.scheduler = SCHEDULERS.build(self.config["scheduler"], self.optimizer, epochs=stage.epochs)
        try:
            self.train_data = build_split(
                self.config["dataset"],
                "train",
                variant=stage.variant,
                subset=stage.subset,
                seed=self.seed,
                progress=self.settings.progress and self.ctx.is_main,
            )
        except ValueError as error:
            if stage.variant is None:
                raise
            raise ValueError(
                f"{error} (curriculum stage {stage.name!r}, variant {stage.variant!r}: "
                f"pass {stage.without_variant} to train on the pairs as they are)"
            ) from error
        if self.train_data is None or len(self.train_data) == 0:
            raise ValueError(f"curriculum stage {stage.name!r}: the training split is empty")
        verb = "resuming" if resumed else "entering"
        message = (
            f"{verb} curriculum stage {index + 1}/{len(self.curriculum.stages)} {stage.describe(self.base_lr)}: "
            f"{len(self.train_data)} training pairs"
        )
        log.info(message)
        if self.logger is not None:
            self.logger.text("curriculum", message, self.global_step)
            self.logger.scalars(
                {"curriculum/stage": index, "curriculum/train_pairs": len(self.train_data)}, self.global_step
            )

    # ----------------------------------------------------------------------------- steps
    def _forward(self, batch: PairBatch) -> tuple[RegistrationOutput, LossOutput]:
        """Model forward (autocast when AMP is on) and loss (float32)."""
        with distributed.autocast(self.device, self.amp):
            output = self.ddp_model(batch)
        output = distributed.float32_output(output)
        return output, self.loss(output, batch)

    def _train_step(self, batch: PairBatch) -> dict[str, float] | None:
        """One optimizer step; ``None`` when skipped (non-finite loss or gradients)."""
        batch = batch.to(self.device)
        output, loss_output = self._forward(batch)
        finite = bool(torch.isfinite(loss_output.total))
        if not distributed.all_ranks_true(finite, self.ctx):
            message = (
                describe_non_finite_loss(
                    self.loss, batch, output, loss_output, f"epoch {self.epoch} step {self.global_step}"
                )
                if not finite
                else "non-finite loss on another rank"
            )
            return self._skip_step(message)
        logging_step = (self.global_step + 1) % self.settings.log_every == 0
        term_norms = {}
        if logging_step and self.settings.log_term_grad_norms:
            scale = self.scaler.get_scale() if self.scaler.is_enabled() else 1.0
            term_norms = term_gradient_norms(loss_output, self.model.parameters(), scale)
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss_output.total).backward()
        self.scaler.unscale_(self.optimizer)
        max_norm = self.settings.grad_clip_norm if self.settings.grad_clip_norm is not None else math.inf
        grad_norm = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(), max_norm))
        if not math.isfinite(grad_norm) and self.amp != torch.float16:
            self.optimizer.zero_grad(set_to_none=True)
            return self._skip_step(f"non-finite gradient norm at epoch {self.epoch} step {self.global_step}")
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.bad_steps = 0
        self.global_step += 1
        values = {"loss": float(loss_output.total.detach())}
        values.update({f"loss/{name}": float(value.detach()) for name, value in loss_output.terms.items()})
        values.update({f"stats/{name}": float(value) for name, value in loss_output.stats.items()})
        values["grad_norm/total"] = grad_norm
        values.update(term_norms)
        values["lr"] = self.optimizer.param_groups[0]["lr"]
        return values

    def _skip_step(self, message: str) -> None:
        """Skip this step, warn, and give up after ``max_bad_steps`` in a row."""
        self.optimizer.zero_grad(set_to_none=True)
        self.bad_steps += 1
        warnings.warn(f"step skipped: {message}", RuntimeWarning, stacklevel=2)
        if self.logger is not None:
            self.logger.scalars({"train/skipped_steps": self.bad_steps}, self.global_step)
        if self.bad_steps >= self.settings.max_bad_steps:
            raise FloatingPointError(
                f"{self.bad_steps} consecutive steps with non-finite values; last: {message}. Lower optimizer.lr, "
                "check the data (trainer.detect_anomaly=true helps), or resume from an earlier checkpoint"
            )
        return None

    def _train_epoch(self) -> dict[str, float]:
        """One epoch over this rank's shard of the stage's training data (its remaining batches
        when a step checkpoint was resumed); the means of the logged values."""
        stage = self.curriculum.stages[self.stage_index]
        sums, self.epoch_sums = self.epoch_sums or EpochSums(), None
        loader = distributed.make_loader(
            self.train_data,
            batch_size=self.settings.batch_size,
            num_points=self.settings.num_points,
            shuffle=True,
            seed=self.seed,
            epoch=self.epoch,
            num_workers=self.settings.num_workers,
            ctx=self.ctx,
            skip_batches=sums.batches,
        )
        self.ddp_model.train()
        total_batches = sums.batches + len(loader)
        if self.settings.max_steps_per_epoch is not None:
            total_batches = min(total_batches, self.settings.max_steps_per_epoch)
        bar = tqdm(
            total=total_batches,
            initial=sums.batches,
            desc=f"epoch {self.epoch + 1}/{self.curriculum.total_epochs} [{stage.name}]",
            disable=not (self.settings.progress and self.ctx.is_main),
            leave=False,
        )
        began = time.perf_counter()
        with bar, torch.autograd.set_detect_anomaly(self.settings.detect_anomaly):
            for batch in loader:
                if sums.batches >= total_batches:
                    break
                randomness.seed_training_step(self.loss, self.seed, self.epoch, sums.batches, self.ctx.rank)
                values = self._train_step(batch)
                sums.add(values)
                bar.update(1)
                if values is not None:
                    bar.set_postfix(loss=f"{values['loss']:.4g}")
                    self._after_step(values, sums, total_batches)
        if sums.batches and not sums.steps:
            raise FloatingPointError(
                f"every training step of epoch {self.epoch + 1} ({sums.batches} of {sums.batches}) was skipped for "
                f"non-finite values (see the warnings above); the model did not train. Lower optimizer.lr (now "
                f"{self.optimizer.param_groups[0]['lr']:g}) or check the data; the checkpoints of earlier epochs "
                f"are kept in {self.checkpoints}"
            )
        means = sums.means()
        means["epoch_seconds"] = time.perf_counter() - began
        return means

    def _after_step(self, values: Mapping[str, float], sums: EpochSums, total_batches: int) -> None:
        """Log a step's values every ``log_every`` steps; write a step checkpoint every
        ``checkpoint_every_steps`` steps (unless the epoch ends here: its own checkpoint follows)."""
        if self.logger is not None and self.global_step % self.settings.log_every == 0:
            self.logger.scalars(values, self.global_step, prefix="train/")
        every = self.settings.checkpoint_every_steps
        if every and self.global_step % every == 0 and sums.batches < total_batches and self.ctx.is_main:
            save_checkpoint(self.state_dict({}, sums), self.checkpoints / LAST)
        kill_point("step", self.global_step)

    # ----------------------------------------------------------------------------- validation
    def _validate(self) -> dict[str, float]:
        """Validation metrics (``val/...``) on rank 0; ``{}`` elsewhere or without a val split."""
        if self.val_data is None or not self.ctx.is_main:
            return {}
        logger_config = self.config["logger"]
        keep = logger_config.get("num_figures", 0) if logger_config.get("tensorboard") else 0
        evaluation = self.evaluator.evaluate(
            self.val_data, keep=keep, max_batches=self.settings.max_eval_batches, assess=self.assess_val
        )
        metrics = {f"val/{k}": v for k, v in evaluation.metrics(self.settings.alphas).items()}
        if self.logger is not None:
            self.logger.scalars(metrics, self.global_step)
            for i, pair in enumerate(evaluation.kept):
                figure = registration_figure(pair.src, pair.tgt, pair.transform, title=f"epoch {self.epoch + 1}")
                self.logger.figure(f"val/registration_{i}", figure, self.global_step)
        return metrics

    # ----------------------------------------------------------------------------- run
    def fit(self) -> dict[str, Any]:
        """Run the remaining epochs of the curriculum, then the final evaluation."""
        self.logger = RunLogger(
            self.run_dir,
            tensorboard=bool(self.config["logger"].get("tensorboard", True)),
            enabled=self.ctx.is_main,
            purge_step=self.global_step if self.global_step else None,
        )
        try:
            self._run_epochs()
            return self._finish()
        except KeyboardInterrupt:
            log.warning("interrupted; continue with: python -m train resume=%s", self.run_dir)
            raise
        finally:
            self._release_ddp()
            self.logger.close()

    def _release_ddp(self) -> None:
        """Free the DistributedDataParallel wrapper now, while the process group is registered
        (:func:`~linereg.train.distributed.teardown` says why)."""
        if self.ddp_model is not self.model:
            self.ddp_model = self.model
            gc.collect()

    def _run_epochs(self) -> None:
        """Train, validate and checkpoint every remaining epoch."""
        self.val_data = build_split(self.config["dataset"], "val", progress=self.settings.progress and self.ctx.is_main)
        self.assess_val = self.val_data is not None and not is_labelled(self.val_data)
        if self.settings.untrained:
            self._save_initial_model()
            return
        if self.stage_index is None:
            if self.settings.val_before_training:
                initial = self._validate()
                self.initial_metrics = {key.replace("val/", "val_initial/", 1): v for key, v in initial.items()}
                if self.config.get("init_from"):
                    self._keep_start_as_candidate(initial)
                elif self.initial_metrics:
                    log.info("before training: %s %.4g", self.monitor.metric, self.monitor.read(initial))
            self._enter_stage(0)
        total = self.curriculum.total_epochs
        while self.epoch < total:
            index, _ = self.curriculum.locate(self.epoch)
            if index != self.stage_index:
                self._enter_stage(index)
            scheduled = set_training_progress(self.loss, self.epoch / max(total - 1, 1))
            self.logger.scalars({f"loss_schedule/{k}": v for k, v in scheduled.items()}, self.global_step)
            train_means = self._train_epoch()
            if self.scheduler is not None:
                self.scheduler.step()
            metrics: dict[str, float] = {}
            if (self.epoch + 1) % self.settings.val_every == 0 or self.epoch + 1 == total:
                metrics = self._validate()
            self.epoch += 1
            self.logger.scalars({f"epoch/{k}": v for k, v in train_means.items()}, self.global_step)
            self.logger.scalars({"epoch": self.epoch}, self.global_step)
            monitored, improved = self.monitor.observe(metrics, self.epoch)
            if self.ctx.is_main:
                state = self.state_dict(metrics)
                # best.pt first: a kill between the two writes resumes from the previous last.pt,
                # which runs this epoch again and writes the same best.pt.
                if improved or self.val_data is None:
                    save_checkpoint(state, self.checkpoints / BEST)
                save_checkpoint(state, self.checkpoints / LAST)
                log.info(
                    "epoch %d/%d: train loss %.4g%s%s (%.0f s)",
                    self.epoch,
                    total,
                    train_means.get("loss", math.nan),
                    "" if monitored is None else f", {self.monitor.metric} {monitored:.4g}",
                    " (best)" if improved else "",
                    train_means["epoch_seconds"],
                )
            self.logger.flush()
            distributed.barrier(self.ctx)

    def _keep_start_as_candidate(self, initial: Mapping[str, float]) -> None:
        """Fine-tuning: the start network's validation ``initial`` is epoch 0's, a candidate for
        ``best.pt``, so a run never ends worse than its start by its own criterion."""
        monitored, improved = self.monitor.observe(initial, 0)
        if improved and self.ctx.is_main:
            save_checkpoint(self.state_dict(initial), self.checkpoints / BEST)
            log.info("the start network is epoch 0's candidate: %s %.4g", self.monitor.metric, monitored)

    def _save_initial_model(self) -> None:
        """``trainer.untrained``: validate the initial model and write it as ``last.pt`` (no epoch runs)."""
        log.info(
            "trainer.untrained=true: evaluating the initial model; the curriculum's %d epoch(s) are not run",
            self.curriculum.total_epochs,
        )
        metrics = self._validate()
        if self.ctx.is_main:
            save_checkpoint(self.state_dict(metrics), self.checkpoints / LAST)
        self.logger.flush()
        distributed.barrier(self.ctx)

    def _evaluated_file(self) -> Path:
        """The checkpoint the final evaluation reads: ``last.pt`` for ``trainer.evaluate_checkpoint=last``
        and untrained runs, else ``best.pt`` (``last.pt`` when none was written)."""
        if self.settings.untrained or self.settings.evaluate_checkpoint == "last":
            return self.checkpoints / LAST
        return self.checkpoints / BEST if (self.checkpoints / BEST).is_file() else self.checkpoints / LAST

    def _finish(self) -> dict[str, Any]:
        """Evaluate the chosen checkpoint (:meth:`_evaluated_file`) on the evaluation split; write ``metrics.json``."""
        evaluated_file = self._evaluated_file()
        last, best = self.checkpoints / LAST, self.checkpoints / BEST
        results: dict[str, Any] = {
            "metrics": {},
            "best_checkpoint": str(best if best.is_file() else last),
            "evaluated_checkpoint": str(evaluated_file),
            "last_checkpoint": str(last),
            "output_dir": str(self.run_dir),
            "model": distributed.unwrap(self.model),
        }
        trained = not self.settings.untrained
        diverged = self.ctx.is_main and trained and self.val_data is not None and self.monitor.value is None
        if distributed.broadcast_object(diverged, self.ctx):
            raise FloatingPointError(
                f"no validation gave a finite {self.monitor.metric}: the model is not usable (no best.pt was written; "
                f"{self.checkpoints / LAST} holds the last state). Lower optimizer.lr or check the data"
            )
        if not self.ctx.is_main:
            distributed.barrier(self.ctx)
            return results
        evaluated_state = load_checkpoint(evaluated_file, map_location=self.device)
        evaluated_epoch = int(evaluated_state["progress"]["epoch"])
        metrics = {k: v for k, v in evaluated_state["metrics"].items() if k.startswith("val/")}
        evaluated = self.evaluator.checkpoint_on_split(self.config, evaluated_file, evaluated_state, self.run_dir)
        self.logger.scalars(evaluated, self.global_step)
        metrics.update(evaluated)
        metrics.update(self.initial_metrics)
        metrics["best_epoch"] = self.monitor.epoch
        content = {
            "metrics": metrics,
            "optimized_metric": self.config.get("optimized_metric"),
            "best": self.monitor.state(),
            "evaluated_checkpoint": {
                "file": evaluated_file.name,
                "path": str(evaluated_file),
                "epoch": evaluated_epoch,
            },
            "iterate": self.evaluator.iterate_info(),
            "untrained": self.settings.untrained,
            "run_dir": str(self.run_dir),
        }
        write_run_metrics(self.run_dir, content)
        log.info("run folder: %s", self.run_dir)
        distributed.barrier(self.ctx)
        results["metrics"] = metrics
        return results


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train a model as configured (``configs/train.yaml``); the body of ``python -m train``.

    Args:
        cfg: the composed config (``paths.output_dir`` is the run folder).

    Returns:
        ``{"metrics": {...}, "best_checkpoint", "evaluated_checkpoint", "last_checkpoint",
        "output_dir", "model"}``; metrics hold the evaluated checkpoint's validation metrics
        (``val/...``; ``best.pt`` unless ``trainer.evaluate_checkpoint=last`` or
        ``trainer.untrained=true``), its evaluation on ``evaluate_split`` (``test/...``,
        ``test/identity/...``) and ``best_epoch``.
    """
    ctx = distributed.setup(cfg.trainer.device)
    try:
        overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else None
        if cfg.get("init_from"):
            keep_start_settings(cfg, overrides)
        config = OmegaConf.to_container(cfg, resolve=True)
        output_dir = Path(config["paths"]["output_dir"])
        resume_file = distributed.broadcast_object(
            resume_checkpoint(config.get("resume"), output_dir, overrides) if ctx.is_main else None, ctx
        )
        state = None
        if resume_file is not None:
            state = load_resume_checkpoint(resume_file, map_location=ctx.device)
            config = config_for_resume(config, upgrade_run_config(state["config"]))
            output_dir = Path(state["path"]).parent.parent
            log.info("resuming %s at epoch %d", state["path"], state["progress"]["epoch"])
        distributed.set_threads(config["trainer"].get("threads"))
        randomness.seed_everything(int(config["seed"]), bool(config.get("deterministic", False)))
        loss = build_loss(config["loss"] if state is not None else cfg.loss)
        trainer = Trainer(config, output_dir, ctx, loss)
        if state is not None:
            trainer.load_state_dict(state)
        elif config.get("init_from"):
            init = load_checkpoint(config["init_from"], map_location=ctx.device)
            trainer.model.load_state_dict(init["model"])
            log.info("initialised the model from %s", init["path"])
        if ctx.is_main:
            log.info("run folder: %s", output_dir)
        return trainer.fit()
    finally:
        distributed.teardown(ctx)
