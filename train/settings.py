"""The ``trainer`` section of a training config, validated."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from linereg.registry import plain


@dataclass(frozen=True)
class TrainerSettings:
    """The ``trainer`` section of the config (see ``configs/train.yaml`` for each key)."""

    device: str = "auto"
    threads: int | None = None
    amp: str | bool = False
    batch_size: int = 8
    eval_batch_size: int = 16
    num_points: int | None = 512
    num_workers: int = 0
    grad_clip_norm: float | None = 10.0
    val_every: int = 1
    val_before_training: bool = True
    monitor: str = "val/err_r_deg_mean"
    monitor_mode: str = "min"
    max_steps_per_epoch: int | None = None
    max_eval_batches: int | None = None
    log_every: int = 10
    progress: bool = True
    max_bad_steps: int = 20
    detect_anomaly: bool = False
    ddp_find_unused_parameters: bool = False
    alphas: tuple[float, ...] = (0.01, 0.02, 0.05, 0.1)
    untrained: bool = False
    evaluate_checkpoint: str = "best"
    log_term_grad_norms: bool = True
    checkpoint_every_steps: int | None = None

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> TrainerSettings:
        """Validated settings; unknown keys raise ``ValueError`` listing the accepted ones."""
        config = dict(plain(config))
        accepted = {f.name for f in fields(cls)}
        unknown = sorted(set(config) - accepted)
        if unknown:
            raise ValueError(f"unknown trainer key(s) {unknown}; accepted: {sorted(accepted)}")
        if "alphas" in config:
            config["alphas"] = tuple(float(a) for a in config["alphas"])
        settings = cls(**config)
        if settings.monitor_mode not in ("min", "max"):
            raise ValueError(f"trainer.monitor_mode must be 'min' or 'max', got {settings.monitor_mode!r}")
        if settings.evaluate_checkpoint not in ("best", "last"):
            raise ValueError(
                f"trainer.evaluate_checkpoint must be 'best' or 'last', got {settings.evaluate_checkpoint!r}"
            )
        for name in ("untrained", "log_term_grad_norms"):
            if not isinstance(getattr(settings, name), bool):
                raise ValueError(f"trainer.{name} must be true or false, got {getattr(settings, name)!r}")
        for name in ("batch_size", "eval_batch_size", "val_every", "log_every", "max_bad_steps"):
            if getattr(settings, name) < 1:
                raise ValueError(f"trainer.{name} must be >= 1, got {getattr(settings, name)}")
        every = settings.checkpoint_every_steps
        if every is not None and (isinstance(every, bool) or not isinstance(every, int) or every < 1):
            raise ValueError(f"trainer.checkpoint_every_steps must be an int >= 1 or null, got {every!r}")
        return settings
