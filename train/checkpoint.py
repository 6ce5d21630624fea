"""Writing checkpoints during training: atomic saves, resume with fallback, RNG and generator states.

A checkpoint is a ``torch.save`` dict holding only tensors and plain Python values, so it loads
with ``torch.load(weights_only=True)``::

    format, version     "linereg-checkpoint", 1
    config              the resolved run config (model, loss, dataset, curriculum, ...)
    model               model state dict
    optimizer, scheduler, scaler
    progress            {epoch: next epoch to run, global_step, stage, stage_name}
    best                {metric, value, epoch}
    rng                 python / numpy / torch (CPU and CUDA) generator states
    generators          states of the torch.Generator attributes of the loss (line sampling)
    metrics             validation metrics of the epoch

Runs keep ``<run>/checkpoints/last.pt`` (every epoch) and ``best.pt`` (best monitored metric).
A file that cannot be read (truncated, empty, garbage) raises :class:`CorruptCheckpointError`
naming it (:func:`linereg.checkpoint.load_checkpoint` reads one);
:func:`load_resume_checkpoint` falls back to the newest readable checkpoint of the same folder with a warning.
"""

from __future__ import annotations

import os
import random
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from linereg.checkpoint import (
    BEST,
    FORMAT,
    LAST,
    VERSION,
    CorruptCheckpointError,
    find_checkpoint,
    load_checkpoint,
)

# The temporary file of an unfinished save: ``.<name>.<pid>.tmp`` beside its destination.
_TEMPORARY = re.compile(r"^\..+\.(?P<pid>\d+)\.tmp$")


def save_checkpoint(state: Mapping[str, Any], path: str | Path) -> Path:
    """Write ``state`` to ``path`` atomically (temporary file in the same folder, then rename).

    An interrupted write never leaves a truncated checkpoint behind: ``path`` holds either the
    previous checkpoint or the new one. The folder is fsynced after the rename (POSIX), so the
    rename itself survives a power cut, and temporaries left by killed writers (processes that
    no longer exist) are removed first.

    Args:
        state: the checkpoint contents (tensors and plain Python values).
        path: destination file.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_orphan_temporaries(path.parent)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as handle:
            torch.save({"format": FORMAT, "version": VERSION, **state}, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    _fsync_folder(path.parent)
    return path


def remove_orphan_temporaries(folder: str | Path) -> list[Path]:
    """Delete the ``.<name>.<pid>.tmp`` files of :func:`save_checkpoint` whose process is gone.

    A writer killed mid-save (SIGKILL, power cut) leaves its temporary behind; one whose
    process still runs may be writing it and is kept.

    Returns:
        The deleted files.
    """
    removed = []
    for candidate in Path(folder).glob(".*.tmp"):
        match = _TEMPORARY.match(candidate.name)
        if match is None or _process_exists(int(match["pid"])):
            continue
        candidate.unlink(missing_ok=True)
        removed.append(candidate)
    return removed


def _process_exists(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (this process counts)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OSError, OverflowError):  # not a valid pid on this platform
        return False
    return True


def _fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename inside it) to disk; a no-op where folders cannot be opened."""
    if os.name != "posix":
        return
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def load_resume_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load the checkpoint to resume from, falling back when it is corrupt.

    When ``path`` (or, for a run folder, its ``last.pt``) cannot be read, a warning names it and
    the newest readable checkpoint (``*.pt``, e.g. ``best.pt``) of the same folder is used.

    Raises:
        FileNotFoundError: no checkpoint there.
        CorruptCheckpointError: no checkpoint of the folder can be read (every file is named).
        ValueError: the file is not a linereg checkpoint of a supported version.
    """
    file = find_checkpoint(path, prefer=(LAST, BEST))
    try:
        return load_checkpoint(file, map_location)
    except CorruptCheckpointError as error:
        failures = [str(error)]
    others = sorted(
        (candidate for candidate in file.parent.glob("*.pt") if candidate != file),
        key=lambda candidate: candidate.stat().st_mtime,
        reverse=True,
    )
    for candidate in others:
        try:
            state = load_checkpoint(candidate, map_location)
        except ValueError as error:  # corrupt, or not a linereg checkpoint of this version
            failures.append(str(error))
            continue
        epoch = state.get("progress", {}).get("epoch")
        warnings.warn(
            f"{failures[0]}; resuming from {candidate} (epoch {epoch}) instead",
            RuntimeWarning,
            stacklevel=2,
        )
        return state
    raise CorruptCheckpointError(
        "no readable checkpoint to resume from:\n  " + "\n  ".join(failures) + "\nstart a new run or restore a backup"
    )


def rng_state() -> dict[str, Any]:
    """States of the python, numpy and torch (CPU and CUDA) global generators."""
    numpy_state = np.random.get_state(legacy=False)  # noqa: NPY002 (the global generator, as libraries use it)
    state = {
        "python": random.getstate(),
        "numpy": {
            "key": torch.from_numpy(numpy_state["state"]["key"].astype(np.int64)),
            "pos": int(numpy_state["state"]["pos"]),
            "has_gauss": int(numpy_state["has_gauss"]),
            "gauss": float(numpy_state["gauss"]),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: Mapping[str, Any]) -> None:
    """Restore the generators saved by :func:`rng_state` (CUDA only when available)."""
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    numpy_state = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        {
            "bit_generator": "MT19937",
            "state": {"key": numpy_state["key"].numpy().astype(np.uint32), "pos": numpy_state["pos"]},
            "has_gauss": numpy_state["has_gauss"],
            "gauss": numpy_state["gauss"],
        }
    )
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _generators(module: nn.Module) -> dict[str, torch.Generator]:
    """Every ``torch.Generator`` attribute of ``module`` and its submodules, by dotted name."""
    found = {}
    for prefix, submodule in module.named_modules():
        for attribute, value in vars(submodule).items():
            if isinstance(value, torch.Generator):
                found[f"{prefix}.{attribute}" if prefix else attribute] = value
    return found


def generator_states(module: nn.Module) -> dict[str, torch.Tensor]:
    """States of the generators a module owns (e.g. the line sampler of the line loss)."""
    return {name: generator.get_state() for name, generator in _generators(module).items()}


def restore_generator_states(module: nn.Module, states: Mapping[str, torch.Tensor]) -> None:
    """Restore :func:`generator_states`; the names must match the module's generators."""
    generators = _generators(module)
    if set(generators) != set(states):
        raise ValueError(
            f"the checkpoint holds generator states {sorted(states)} but the loss owns {sorted(generators)}"
        )
    for name, state in states.items():
        generators[name].set_state(state)
