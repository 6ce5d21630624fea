"""Where the randomness of a training run comes from.

Everything random a run consumes after its model is initialised is derived from the run's seed
and a position, never from what ran before, so a run resumed in a new process (or a DDP rank)
draws exactly what the uninterrupted run draws:

* each training step: the python, numpy and torch (CPU and CUDA) global generators (dropout and
  any other draw of the model) and the loss's generators (its random lines) are seeded from
  ``(seed, epoch, batch of the epoch, rank)``;
* the data loader of an epoch: its order from ``(seed, epoch)`` (each rank its shard), its
  workers' seeds from ``(seed, epoch, rank)`` (:func:`linereg.train.distributed.make_loader`);
* each evaluation (validation, the final evaluation) seeds the global generators and the
  loss's from the seed alone: an evaluation is a function of the weights.

The pairs themselves (poses, views, augmentations) are pure functions of ``(seed, index)``
(:func:`linereg.datasets.base.item_rng`). Bit-exact results also need the same thread counts
(:func:`linereg.train.distributed.set_threads`) and, on a GPU, ``deterministic=true``.
"""

from __future__ import annotations

import os
import random
import zlib

import numpy as np
import torch
from torch import nn

# Streams of derived seeds (distinct first coordinates).
_STEP_STREAM = 1
_LOADER_STREAM = 2
_EVALUATION_STREAM = 3


def seed_everything(seed: int, deterministic: bool = False) -> None:
    """Seed python, numpy and torch; optionally ask torch for deterministic kernels."""
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (seeds libraries that draw from the global generator)
    torch.manual_seed(seed)
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
        torch.backends.cudnn.deterministic = True


def derived_seed(seed: int, *coordinates: int) -> int:
    """A 63-bit seed that is a pure function of ``seed`` and the integer ``coordinates``."""
    state = np.random.SeedSequence([int(seed), *(int(c) for c in coordinates)]).generate_state(2, dtype=np.uint32)
    return (int(state[0]) << 31) ^ int(state[1])


def loss_generators(module: nn.Module) -> dict[str, torch.Generator]:
    """Every ``torch.Generator`` attribute of ``module`` and its submodules, by dotted name."""
    found = {}
    for prefix, submodule in module.named_modules():
        for attribute, value in vars(submodule).items():
            if isinstance(value, torch.Generator):
                found[f"{prefix}.{attribute}" if prefix else attribute] = value
    return found


def _seed_all(loss: nn.Module, seed: int, *coordinates: int) -> None:
    """Seed the python, numpy and torch global generators and those of ``loss`` from ``(seed, coordinates)``."""
    position_seed = derived_seed(seed, *coordinates)
    random.seed(position_seed)
    np.random.seed(position_seed % 2**32)  # noqa: NPY002 (the global generator, as libraries use it)
    torch.manual_seed(position_seed)
    for name, generator in loss_generators(loss).items():
        generator.manual_seed(derived_seed(seed, *coordinates, zlib.crc32(name.encode())))


def seed_training_step(loss: nn.Module, seed: int, epoch: int, batch: int, rank: int) -> None:
    """Seed the global generators and those of ``loss`` for batch ``batch`` of epoch ``epoch`` on ``rank``."""
    _seed_all(loss, seed, _STEP_STREAM, epoch, batch, rank)


def seed_evaluation(loss: nn.Module, seed: int) -> None:
    """Seed the global generators and those of ``loss`` for an evaluation (the same at every one)."""
    _seed_all(loss, seed, _EVALUATION_STREAM)


def loader_generator(seed: int, epoch: int, rank: int) -> torch.Generator:
    """The generator of epoch ``epoch``'s data loader on rank ``rank`` (its workers' seeds)."""
    return torch.Generator().manual_seed(derived_seed(seed, _LOADER_STREAM, epoch, rank))
