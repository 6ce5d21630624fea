"""Resuming a run: which checkpoint ``resume=...`` names, and the config the run continues with."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from linereg.checkpoint import BEST, CHECKPOINT_DIR, LAST, find_checkpoint

# Keys a resumed run takes from the current command line instead of the checkpoint.
RESUME_OVERRIDABLE = (
    "trainer.device",
    "trainer.threads",
    "trainer.num_workers",
    "trainer.progress",
    "trainer.checkpoint_every_steps",
    "resume",
)


def _flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a.b": value}`` for a nested mapping."""
    flat = {}
    for key, value in config.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _defining(overrides: list[str]) -> list[str]:
    """The overrides that define a run: without those of :data:`RESUME_OVERRIDABLE` (``resume`` included)."""
    return sorted(item for item in overrides if item.split("=", 1)[0].lstrip("+~") not in RESUME_OVERRIDABLE)


def _run_overrides(run_dir: Path) -> list[str] | None:
    """The defining command-line overrides Hydra recorded for a run folder."""
    recorded = run_dir / ".hydra" / "overrides.yaml"
    if not recorded.is_file():
        return None
    return _defining([str(item) for item in OmegaConf.load(recorded)])


def resume_checkpoint(resume: Any, output_dir: Path, overrides: list[str] | None = None) -> Path | None:
    """The checkpoint a ``resume`` setting names (``None``: start from the beginning).

    ``true``: this run folder's ``last.pt``, else that of the newest sibling run folder started
    with the same command-line ``overrides`` (when they are known; those a resume may change
    aside), else none, with a warning: a run killed before its first checkpoint starts again.
    A path: that checkpoint file or run folder.
    """
    if resume in (None, False):
        return None
    if resume is not True:
        return find_checkpoint(resume, prefer=(LAST, BEST))
    own = output_dir / CHECKPOINT_DIR / LAST
    if own.is_file():
        return own
    wanted = None if overrides is None else _defining(overrides)
    siblings = [
        path
        for path in output_dir.parent.glob(f"*/{CHECKPOINT_DIR}/{LAST}")
        if wanted is None or _run_overrides(path.parent.parent) == wanted
    ]
    if not siblings:
        warnings.warn(
            f"resume=true: no {CHECKPOINT_DIR}/{LAST} in {output_dir} or in a sibling run started with the same "
            "overrides; starting from the beginning",
            stacklevel=2,
        )
        return None
    return max(siblings, key=lambda path: path.stat().st_mtime)


def config_for_resume(current: dict[str, Any], stored: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's config, with the command line's :data:`RESUME_OVERRIDABLE` keys."""
    merged = OmegaConf.create(stored)
    current_flat, stored_flat = _flatten(current), _flatten(stored)
    for key in RESUME_OVERRIDABLE:
        if key in current_flat:
            OmegaConf.update(merged, key, current_flat[key], force_add=True)
    ignored = sorted(
        key
        for key in set(current_flat) | set(stored_flat)
        if key not in RESUME_OVERRIDABLE
        and not key.startswith("paths.")
        and current_flat.get(key) != stored_flat.get(key)
    )
    if ignored:
        warnings.warn(f"resuming with the checkpoint's config; ignored differences: {ignored}", stacklevel=3)
    return OmegaConf.to_container(merged)
