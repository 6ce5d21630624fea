"""Reading checkpoints written by ``python -m train`` (the file format; writing is :mod:`linereg.train.checkpoint`).

A checkpoint is a ``torch.save`` dict holding only tensors and plain Python values, so it loads
with ``torch.load(weights_only=True)``; its ``format`` is ``"linereg-checkpoint"``, ``version`` 1,
``config`` the run's resolved config, ``model`` the model's state dict and ``half_extent`` the cube
``[-h, h]^3`` its training pairs were scaled into (``None``: their own units; older checkpoints lack
it: :func:`linereg.registration.learned.upgrade_checkpoint`). Runs keep
``<run>/checkpoints/last.pt`` (every epoch) and ``best.pt`` (best monitored metric).
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import torch

from linereg import pretrained

FORMAT = "linereg-checkpoint"
VERSION = 1
CHECKPOINT_DIR = "checkpoints"
LAST = "last.pt"
BEST = "best.pt"


class CorruptCheckpointError(ValueError):
    """A checkpoint file exists but cannot be read (truncated, empty or not a torch file)."""


def find_checkpoint(path: str | Path, prefer: tuple[str, ...] | None = None) -> Path:
    """The checkpoint file named by ``path``: the file itself, in a run folder the first of
    ``prefer`` found in ``<run>/checkpoints/`` (or directly in the folder), or the file of a
    shipped name of :mod:`linereg.pretrained` (``rpm_ours_airplane``) that is no path here.

    With ``prefer=None`` a run folder gives the checkpoint its own final evaluation used (the
    ``evaluated_checkpoint`` that ``python -m train`` records in ``<run>/metrics.json``: ``last.pt``
    when ``trainer.evaluate_checkpoint=last``), else ``best.pt``, else ``last.pt``.

    Raises:
        FileNotFoundError: nothing suitable exists.
    """
    if pretrained.is_name(path) and not Path(path).exists():
        return pretrained.path(str(path))
    path = Path(path).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        if prefer is None:
            prefer = (*_evaluated_name(path), BEST, LAST)
        for folder in (path / CHECKPOINT_DIR, path):
            for name in prefer:
                if (folder / name).is_file():
                    return folder / name
        raise FileNotFoundError(
            f"no checkpoint ({' or '.join(dict.fromkeys(prefer))}) in {path} or {path / CHECKPOINT_DIR}"
        )
    raise FileNotFoundError(
        f"checkpoint not found: {path} (not a file, a run folder or a pretrained name: {', '.join(pretrained.names())})"
    )


def _evaluated_name(run: Path) -> tuple[str, ...]:
    """``(name,)`` of the checkpoint recorded in ``<run>/metrics.json``, or ``()`` when there is none."""
    try:
        recorded = json.loads((run / "metrics.json").read_text())["evaluated_checkpoint"]["file"]
    except (OSError, ValueError, KeyError, TypeError):
        return ()
    return (recorded,) if isinstance(recorded, str) and recorded in (BEST, LAST) else ()


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` (a file, a run folder or a pretrained
    name); portable data paths of its config (:func:`linereg.pretrained.local_config`) point here.

    Raises:
        FileNotFoundError: no checkpoint there.
        CorruptCheckpointError: the file cannot be read (truncated, empty, not a torch file).
        ValueError: the file is not a linereg checkpoint of a supported version.
    """
    file = find_checkpoint(path)
    try:
        state = torch.load(file, map_location=map_location, weights_only=True)
    except (RuntimeError, EOFError, OSError, ValueError, IndexError, KeyError, pickle.UnpicklingError) as error:
        detail = str(error).split(". ", 1)[0].strip()
        raise CorruptCheckpointError(
            f"{file}: cannot read the checkpoint ({file.stat().st_size} bytes; truncated, empty or not written by "
            f"torch.save): {type(error).__name__}{': ' + detail if detail else ''}"
        ) from error
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"{file} is not a linereg checkpoint (written by train/checkpoint.py)")
    if state.get("version") != VERSION:
        raise ValueError(f"{file}: checkpoint version {state.get('version')} is not supported (expected {VERSION})")
    state["path"] = str(file)
    state["config"] = pretrained.local_config(state.get("config") or {})
    return state
