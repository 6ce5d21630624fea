"""Writing checkpoints during training: atomic saves, resume with fallback.

A checkpoint is a ``torch.save`` dict holding only tensors and plain Python values, so it loads
with ``torch.load(weights_only=True)``::

    format, version     "linereg-checkpoint", 1
    config              the resolved run config (model, loss, dataset, curriculum, ...)
    half_extent         the cube [-h, h]^3 the training pairs were scaled into (None: their own units)
    model               model state dict
    optimizer, scheduler, scaler
    progress            {epoch: the epoch to run (or to finish), batch: its batches already run
                        (0 at the end of an epoch), global_step, stage, stage_name, bad_steps}
    epoch_sums          sums of the training values of the unfinished epoch (None at an epoch's end)
    best                {metric, value, epoch}
    initial_metrics     validation of the initial weights (``val_initial/...``)
    metrics             validation metrics of the epoch (empty in a step checkpoint)

No generator state is stored: a run's randomness is derived from its seed and position
(:mod:`linereg.train.randomness`). Runs keep ``<run>/checkpoints/last.pt`` (every epoch, and every
``trainer.checkpoint_every_steps`` steps) and ``best.pt`` (best monitored metric).
A file that cannot be read (truncated, empty, garbage) raises :class:`CorruptCheckpointError`
naming it (:func:`linereg.checkpoint.load_checkpoint` reads one);
:func:`load_resume_checkpoint` falls back to the newest readable checkpoint of the same folder with a warning.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from linereg.checkpoint import (
    BEST,
    FORMAT,
    LAST,
    VERSION,
    CorruptCheckpointError,
    find_checkpoint,
    load_checkpoint,
)
from linereg.train.faults import kill_point

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
        kill_point("checkpoint")
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
