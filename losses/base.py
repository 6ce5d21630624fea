"""Loss base classes and the loss registry.

Every loss maps ``(RegistrationOutput, PairBatch) -> LossOutput``. A loss declares
``needs_gt``; the base class hands an unsupervised loss a copy of the batch *without*
``gt_transform``, so it cannot read ground truth even by mistake.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from linereg.registry import ArgumentError, Registry, plain
from linereg.se3 import transform_points
from linereg.structures import LossOutput, PairBatch, RegistrationOutput

LOSSES: Registry[Loss] = Registry("loss")


class Loss(nn.Module):
    """Base class: subclasses implement :meth:`compute` and set ``needs_gt``."""

    needs_gt: bool = False

    def forward(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        if not self.needs_gt:
            batch = batch.without_ground_truth()
        elif batch.gt_transform is None:
            raise ValueError(f"{type(self).__name__} is supervised and needs batch.gt_transform, which is missing")
        return self.compute(output, batch)

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        raise NotImplementedError

    def set_progress(self, fraction: float) -> dict[str, float]:
        """Move any schedule of this loss to ``fraction`` of training (0: first epoch, 1: last).

        Returns the scheduled values by name (none here: a loss with a schedule overrides this).
        """
        return {}


def set_training_progress(loss: nn.Module, fraction: float) -> dict[str, float]:
    """Call :meth:`Loss.set_progress` on every loss inside ``loss`` (the loop does, before each epoch).

    Returns every scheduled value, named ``<module path>.<name>`` (e.g. ``parts.alignment.nu0``).
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"training progress must lie in [0, 1], got {fraction}")
    values = {}
    for path, module in loss.named_modules():
        if isinstance(module, Loss):
            values.update({".".join(filter(None, (path, key))): v for key, v in module.set_progress(fraction).items()})
    return values


def iteration_weights(num_iterations: int, discount: float = 0.5, last_k: int | None = None) -> list[float]:
    """Per-iteration weights ``discount ** (n - 1 - i)``, zero outside the last ``last_k`` iterations.

    RPM-Net weighs iteration ``i`` of ``n`` by ``0.5 ** (n - 1 - i)``; the paper's FMR training
    uses the last 3 iterates with the same discount. ``discount=0`` keeps only the last one.
    """
    first = 0 if last_k is None else max(0, num_iterations - last_k)
    return [
        0.0 if i < first else (1.0 if i == num_iterations - 1 else discount ** (num_iterations - 1 - i))
        for i in range(num_iterations)
    ]


class AlignmentLoss(Loss):
    """A correspondence-free metric between the transformed source and the target.

    Applied to each iteration's estimate ``T_i`` as ``metric(T_i @ src, tgt)`` and combined with
    :func:`iteration_weights`. Subclasses implement :meth:`metric`.

    Args:
        discount: per-iteration discount (see :func:`iteration_weights`).
        last_k: only the last ``last_k`` iterations contribute (``None``: all).
        normalize_iterations: divide by the number of iterations (the paper repo's RPM-Net).
    """

    needs_gt = False

    def __init__(self, discount: float = 0.5, last_k: int | None = None, normalize_iterations: bool = False) -> None:
        super().__init__()
        self.discount = discount
        self.last_k = last_k
        self.normalize_iterations = normalize_iterations

    def metric(
        self,
        src: torch.Tensor,
        tgt: torch.Tensor,
        src_lengths: torch.Tensor | None = None,
        tgt_lengths: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Per-sample metric ``(B,)`` between ``src (B, N, 3)`` and ``tgt (B, M, 3)``, plus stats."""
        raise NotImplementedError

    def compute(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        weights = iteration_weights(len(output.transforms), self.discount, self.last_k)
        total = batch.src_xyz.new_zeros(())
        stats: dict[str, float] = {}
        for weight, transform in zip(weights, output.transforms, strict=True):
            if weight == 0.0:
                continue
            moved = transform_points(transform.to(batch.src_xyz.dtype), batch.src_xyz)
            value, stats = self.metric(moved, batch.tgt_xyz, batch.src_lengths, batch.tgt_lengths)
            total = total + weight * value.mean()
        if self.normalize_iterations:
            total = total / len(output.transforms)
        return LossOutput(total=total, terms={"alignment": total}, stats=stats)


class WeightedSum(Loss):
    """Weighted sum of named losses, e.g. RPM-Net's outlier regulariser + the line loss.

    Args:
        terms: mapping ``name -> (weight, loss)``.
    """

    def __init__(self, terms: dict[str, tuple[float, Loss]]) -> None:
        super().__init__()
        self.weights = {name: float(w) for name, (w, _) in terms.items()}
        self.parts = nn.ModuleDict({name: loss for name, (_, loss) in terms.items()})
        self.needs_gt = any(loss.needs_gt for loss in self.parts.values())

    def forward(self, output: RegistrationOutput, batch: PairBatch) -> LossOutput:
        # Each part applies its own ground-truth guard.
        total = batch.src_xyz.new_zeros(())
        terms: dict[str, torch.Tensor] = {}
        stats: dict[str, float] = {}
        for name, loss in self.parts.items():
            part = loss(output, batch)
            weighted = self.weights[name] * part.total
            total = total + weighted
            terms[name] = weighted
            stats.update({f"{name}/{k}": v for k, v in part.stats.items()})
        return LossOutput(total=total, terms=terms, stats=stats)


def _is_handle(value: Any) -> bool:
    """Whether a loss-config value may serve as a handle: a scalar or null."""
    return value is None or isinstance(value, bool | int | float | str)


def build_loss(config: Mapping[str, Any]) -> Loss:
    """Build a loss from a config: a mapping or an OmegaConf config (``configs/loss/``).

    Either a single loss ``{name: <registered name>, **kwargs}`` or a weighted sum
    ``{terms: {label: {name, weight, **kwargs}}, **handles}``. Handles are top-level scalars
    that terms reference by interpolation (``nu0: ${loss.nu0}``), so that sweeps can write
    ``loss.nu0=...`` whatever the term is called; they are not passed to the builder. A handle
    set to a value but referenced by no term of an OmegaConf config gets a warning (it would
    change nothing). A handle set to null stands for the term's own default: a term argument
    of the same name that is null is left out (``nu0: null`` gives each line variant its nu0).

    Raises:
        linereg.registry.UnknownNameError: an unknown loss name (lists the registered losses).
        linereg.registry.ArgumentError: unknown arguments of a loss, or a non-scalar key next
            to ``terms``.
    """
    resolved = dict(plain(config))
    if "terms" not in resolved:
        resolved.pop("weight", None)
        return LOSSES.build(resolved)
    handles = {key: value for key, value in resolved.items() if key != "terms"}
    structured = sorted(key for key, value in handles.items() if not _is_handle(value))
    if structured:
        raise ArgumentError(
            f"loss config: unknown key(s) {structured} next to 'terms' (only scalar handles such as nu0 may "
            "sit there; put loss arguments inside a term)"
        )
    if type(config).__module__.startswith("omegaconf"):
        from omegaconf import OmegaConf

        referenced = repr(OmegaConf.to_container(config, resolve=False)["terms"])
        names = ", ".join(f"{label}: {term.get('name')}" for label, term in resolved["terms"].items())
        for key, value in handles.items():
            if value is not None and "${loss." + key + "}" not in referenced:
                warnings.warn(
                    f"loss.{key}={value!r} has no effect: no term of this loss ({names}) uses it", stacklevel=2
                )
    parts = {}
    defaulted = {key for key, value in handles.items() if value is None}
    for label, term in resolved["terms"].items():
        term = {key: value for key, value in term.items() if not (key in defaulted and value is None)}
        weight = float(term.pop("weight", 1.0))
        parts[label] = (weight, build_loss(term))
    return WeightedSum(parts)
