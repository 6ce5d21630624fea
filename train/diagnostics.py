"""Diagnostics of training steps: which samples of a batch make the loss non-finite (the message of a
skipped step), and the gradient norm of each loss term."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import fields, replace
from typing import Any

import torch
from torch import nn

from linereg.structures import LossOutput, PairBatch, RegistrationOutput

log = logging.getLogger(__name__)


def select_sample(value: Any, index: int, batch_size: int) -> Any:
    """Sample ``index`` of batched values (tensors with a leading batch axis, lists, dicts)."""
    if isinstance(value, torch.Tensor):
        return value[index : index + 1] if value.ndim and value.shape[0] == batch_size else value
    if isinstance(value, list | tuple):
        if len(value) == batch_size and not any(isinstance(v, torch.Tensor) for v in value):
            return type(value)([value[index]])
        return type(value)(select_sample(v, index, batch_size) for v in value)
    if isinstance(value, dict):
        return {key: select_sample(v, index, batch_size) for key, v in value.items()}
    return value


def describe_non_finite_loss(
    loss: nn.Module, batch: PairBatch, output: RegistrationOutput, loss_output: LossOutput, where: str
) -> str:
    """Name the samples of ``batch`` whose transform or loss is non-finite, one at a time.

    Args:
        loss: the training loss.
        batch: the batch whose loss was non-finite.
        output: the model's output on it.
        loss_output: the loss of the whole batch.
        where: the step, for the message (e.g. ``"epoch 3 step 120"``).

    Returns:
        A one-paragraph message: the batch loss and its terms, then each culprit's metadata.
    """
    culprits = []
    size = batch.batch_size
    with torch.no_grad():
        for b in range(size):
            sample_batch = PairBatch(
                **{f.name: select_sample(getattr(batch, f.name), b, size) for f in fields(PairBatch)}
            )
            sample_output = replace(
                output,
                transforms=[T[b : b + 1] for T in output.transforms],
                extras=select_sample(output.extras, b, size),
            )
            finite_transform = all(bool(torch.isfinite(T).all()) for T in sample_output.transforms)
            try:
                value = float(loss(sample_output, sample_batch).total)
            except (RuntimeError, ValueError) as error:
                value = float("nan")
                log.debug("loss of sample %d failed: %s", b, error)
            if not (finite_transform and math.isfinite(value)):
                meta = batch.meta[b] if batch.meta else {}
                culprits.append(
                    f"sample {b} (meta {meta}): transform {'finite' if finite_transform else 'NON-FINITE'}, "
                    f"loss {value}"
                )
    terms = ", ".join(f"{name}={float(value.detach()):.4g}" for name, value in loss_output.terms.items())
    found = "; ".join(culprits) if culprits else "no single sample reproduces it"
    return f"non-finite loss {float(loss_output.total.detach())} ({terms}) at {where}: {found}"


def term_gradient_norms(loss_output: LossOutput, parameters: Iterable[nn.Parameter], scale: float) -> dict[str, float]:
    """``{"grad_norm/<term>": L2 norm of d term / d parameters}`` for each (weighted) loss term.

    One extra backward pass per term through the retained graph (``torch.autograd.grad``, leaving
    ``.grad`` alone), on this process's batch; a term that does not depend on the parameters has
    norm 0. Under float16 AMP (``scale``: the gradient scaler's factor, else 1) the term is scaled
    like the loss and the norm unscaled.
    """
    if "total" in loss_output.terms:
        raise ValueError(
            "a loss term is named 'total', which clashes with train/grad_norm/total; rename the term in the "
            "loss config (or set trainer.log_term_grad_norms=false)"
        )
    parameters = [p for p in parameters if p.requires_grad]
    norms = {}
    for name, term in loss_output.terms.items():
        grads = []
        if term.requires_grad:
            grads = torch.autograd.grad(term * scale, parameters, retain_graph=True, allow_unused=True)
        squares = [grad.float().square().sum() for grad in grads if grad is not None]
        norms[f"grad_norm/{name}"] = float(torch.stack(squares).sum().sqrt()) / scale if squares else 0.0
    return norms
