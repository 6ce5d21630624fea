"""Scoring a training run: validation during training, the best checkpoint, the final evaluation.

* :class:`Monitor`: the monitored validation metric and its best value so far (``best.pt``);
* :class:`RunEvaluator`: the run's model on a split, its errors measured on the iterate chosen
  by the run's ``iterate`` rule (:mod:`linereg.registration.iterates`; the loss sees every
  iterate), and the final evaluation of a checkpoint written to ``<run>/evaluation/``;
* :func:`write_run_metrics`: ``<run>/metrics.json``.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import Dataset

from linereg.datasets.splits import build_split
from linereg.registration.iterates import IterateRule
from linereg.train import distributed
from linereg.train.evaluate import Evaluation, evaluate_model, is_labelled, report, write_evaluation
from linereg.train.randomness import seed_evaluation
from linereg.train.settings import TrainerSettings

CHECK_SCORE = "val/check_score"
"""The label-free validation score: register's check of the network's poses on the validation pairs,
confident share + mean fitness (:meth:`linereg.train.evaluate.Evaluation.assessment_means`)."""

TIE_BREAK = "val/loss"
"""What decides between two epochs of equal :data:`CHECK_SCORE` (lower wins)."""


@dataclass
class Monitor:
    """The validation metric that chooses ``best.pt``, and its best value so far.

    Attributes:
        metric: the monitored key (``trainer.monitor``); on validation data without ground truth
            :data:`CHECK_SCORE` (higher is better; ties go to the lower :data:`TIE_BREAK`), else
            ``val/loss`` without a check.
        mode: ``"min"`` or ``"max"``.
        value: the best value so far (``None``: none yet).
        epoch: the epoch that reached it (0: the initial weights).
        tie: its :data:`TIE_BREAK` value (:data:`CHECK_SCORE` only).
    """

    metric: str
    mode: str = "min"
    value: float | None = None
    epoch: int | None = None
    tie: float | None = None

    def __post_init__(self) -> None:
        if self.metric == CHECK_SCORE:
            self.mode = "max"

    def state(self) -> dict[str, Any]:
        """``{"metric", "mode", "value", "epoch", "tie"}``: the ``best`` entry of a checkpoint."""
        return {"metric": self.metric, "mode": self.mode, "value": self.value, "epoch": self.epoch, "tie": self.tie}

    def load(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state`."""
        self.metric = state.get("metric") or self.metric
        self.mode = state.get("mode") or self.mode
        self.value, self.epoch, self.tie = state["value"], state["epoch"], state.get("tie")

    def read(self, metrics: Mapping[str, float]) -> float | None:
        """The monitored value in ``metrics`` (``None`` when empty); on unlabelled validation data
        falls back to :data:`CHECK_SCORE` (else ``val/loss``), with a warning.

        Raises:
            KeyError: the metric is not among the validation metrics (they are listed).
        """
        if not metrics:
            return None
        if self.metric not in metrics:
            if "val/loss" in metrics and "val/err_r_deg_mean" not in metrics:
                fallback = CHECK_SCORE if CHECK_SCORE in metrics else "val/loss"
                how = (
                    f"register's check of the validation pairs ({CHECK_SCORE}: confident share + mean fitness, "
                    f"ties by {TIE_BREAK})"
                    if fallback == CHECK_SCORE
                    else "val/loss"
                )
                warnings.warn(
                    f"trainer.monitor={self.metric!r} is unavailable (the validation data has no ground truth); "
                    f"selecting the best checkpoint by {how}",
                    stacklevel=3,
                )
                self.metric, self.mode = fallback, "max" if fallback == CHECK_SCORE else self.mode
            else:
                raise KeyError(
                    f"trainer.monitor={self.metric!r} is not a validation metric; available: {sorted(metrics)}"
                )
        return float(metrics[self.metric])

    def observe(self, metrics: Mapping[str, float], epoch: int) -> tuple[float | None, bool]:
        """Read ``metrics`` of ``epoch`` and record them when they beat the best so far.

        Returns:
            The monitored value (``None`` without metrics) and whether it is the new best.
        """
        value = self.read(metrics)
        tie = metrics.get(TIE_BREAK) if self.metric == CHECK_SCORE else None
        return value, self.update(value, epoch, tie)

    def update(self, value: float | None, epoch: int, tie: float | None = None) -> bool:
        """Record ``value`` of ``epoch`` when it beats the best so far (an equal value with a lower
        ``tie`` does too); whether it did."""
        if value is None or not math.isfinite(value):
            return False
        if self.value is not None:
            better = value < self.value if self.mode == "min" else value > self.value
            breaks_tie = value == self.value and tie is not None and self.tie is not None and tie < self.tie
            if not (better or breaks_tie):
                return False
        self.value, self.epoch, self.tie = value, epoch, tie
        return True


class RunEvaluator:
    """A training run's model scored on its splits.

    Args:
        model: the model (unwrapped from DDP).
        loss: the run's loss, reported beside the errors.
        settings: the run's trainer settings (evaluation batch size, points, workers,
            alpha-recall thresholds, progress bars).
        device: where to compute.
        amp: autocast dtype of the forward (``None``: float32).
        iterate: the rule choosing the iterate whose errors are measured.
        seed: the run's seed; every evaluation draws the same randomness from it (the loss's
            lines), so it is a function of the weights alone.
    """

    def __init__(
        self,
        model: nn.Module,
        loss: nn.Module,
        settings: TrainerSettings,
        device: torch.device,
        amp: torch.dtype | None,
        iterate: IterateRule,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.loss = loss
        self.settings = settings
        self.device = device
        self.amp = amp
        self.iterate = iterate
        self.seed = seed

    def evaluate(
        self,
        dataset: Dataset,
        *,
        keep: int = 0,
        description: str = "validate",
        max_batches: int | None = None,
        assess: bool = False,
    ) -> Evaluation:
        """The model on ``dataset`` (this process only; ``max_batches``: a prefix; ``keep``: pairs for
        figures; ``assess``: register's check of every pose, :func:`~linereg.train.evaluate.assess_pairs`)."""
        seed_evaluation(self.loss, self.seed)
        loader = distributed.make_loader(
            dataset,
            batch_size=self.settings.eval_batch_size,
            num_points=self.settings.num_points,
            shuffle=False,
            num_workers=self.settings.num_workers,
        )
        return evaluate_model(
            self.model,
            loader,
            device=self.device,
            loss=self.loss,
            amp=self.amp,
            max_batches=max_batches,
            keep=keep,
            progress=self.settings.progress,
            description=description,
            iterate=self.iterate,
            assess=assess,
        )

    def final(
        self, dataset: Dataset, split: str, out_dir: Path, *, name: str, info: Mapping[str, Any], keep: int
    ) -> dict[str, float]:
        """Evaluate on the ``split`` pairs, write ``out_dir`` and print the tables.

        Returns:
            ``{"<split>/<metric>": value}``, and ``"<split>/identity/<metric>"`` on labelled data.
        """
        evaluation = self.evaluate(dataset, keep=keep, description=split, assess=not is_labelled(dataset))
        alphas = self.settings.alphas
        write_evaluation(evaluation, out_dir, name=name, alphas=alphas, info={**info, "iterate": self.iterate_info()})
        metrics = {f"{split}/{k}": v for k, v in evaluation.metrics(alphas).items()}
        if evaluation.labelled:
            metrics.update({f"{split}/identity/{k}": v for k, v in evaluation.metrics(alphas, identity=True).items()})
        print(f"\nEvaluation of {info['checkpoint']} on the {split!r} split of {info['dataset']!r}:\n")
        print(report(name, evaluation, alphas))
        return metrics

    def checkpoint_on_split(
        self, config: Mapping[str, Any], file: Path, state: Mapping[str, Any], run_dir: Path
    ) -> dict[str, float]:
        """The weights of checkpoint ``state`` (read from ``file``) loaded into the model and scored by
        :meth:`final` on the run ``config``'s ``evaluate_split`` into ``<run_dir>/evaluation`` (``{}``
        when there is none)."""
        split = config.get("evaluate_split")
        dataset = build_split(config["dataset"], split, progress=self.settings.progress) if split else None
        if dataset is None:
            return {}
        self.model.load_state_dict(state["model"])
        epoch = int(state["progress"]["epoch"])
        return self.final(
            dataset,
            split,
            run_dir / "evaluation",
            name=f"{config['model']['name']} ({file.name}, epoch {epoch})",
            info={"checkpoint": str(file), "dataset": config["dataset"].get("name"), "split": split},
            keep=int(config["logger"].get("num_figures", 0)),
        )

    def iterate_info(self) -> dict[str, Any]:
        """The iterate rule as the ``iterate`` entry of ``metrics.json``."""
        return self.iterate.as_config()


def write_run_metrics(run_dir: Path, content: Mapping[str, Any]) -> Path:
    """Write ``content`` as ``<run_dir>/metrics.json`` (non-finite floats as strings)."""
    path = run_dir / "metrics.json"
    path.write_text(json.dumps(_finite(content), indent=2))
    return path


def _finite(item: Any) -> Any:
    """``item`` with non-finite floats turned into strings, for strict JSON."""
    if isinstance(item, float) and not math.isfinite(item):
        return str(item)
    if isinstance(item, Mapping):
        return {k: _finite(v) for k, v in item.items()}
    if isinstance(item, list | tuple):
        return [_finite(v) for v in item]
    return item
