"""What the four commands share: a bad argument, an unreadable file or a missing extra ends the
command with one line on stderr naming it, and exit code 2 (no traceback); a failed command
leaves no run folder that holds nothing but Hydra's bookkeeping.

Hydra reports its own errors (an unknown key, an unknown config option, a malformed override)
over several lines and exits with 1; :func:`run_app` asks Hydra to raise them instead
(``HYDRA_FULL_ERROR``) and writes them as one line, and :func:`reported` does the same for the
errors of a command's body. An error that is no usage error (a bug, a diverged training) keeps
its traceback. A user who sets ``HYDRA_FULL_ERROR=1`` gets every traceback, as Hydra documents.

When a command fails (any error, a usage error or not), :func:`reported` removes the run folder
Hydra created for it (:func:`remove_unused_run_folder`) unless the command wrote anything into it
besides Hydra's ``.hydra/`` files and the log file: a checkpoint, a result or a TensorBoard file
keeps the folder. The job folders of a multirun stay, as rows of the sweep's summary.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, NoReturn

from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from linereg.registry import UnknownNameError

EXIT_USAGE = 2
"""The exit code of a bad argument or file (as argparse's)."""

USAGE_ERRORS: tuple[type[BaseException], ...] = (
    HydraException,
    OmegaConfBaseException,
    ValueError,
    UnknownNameError,
    FileNotFoundError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
)
"""Errors that mean a bad argument or an unreadable file; their messages name it."""

EXTRAS: Mapping[str, str] = {
    "matplotlib": "train",
    "tensorboard": "train",
    "h5py": "train",
    "fricp_cpp": "baselines",
    "submitit": "cluster",
}
"""The modules that an extra of ``pyproject.toml`` (``[project.optional-dependencies]``) installs."""

HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")
"""What Hydra writes into ``<run folder>/<hydra.output_subdir>/`` (``.hydra/``)."""

_USER_TRACEBACKS = os.environ.get("HYDRA_FULL_ERROR") == "1"
"""The user asked for every traceback (read before :func:`run_app` sets the variable itself)."""


def fail(command: str, message: str) -> NoReturn:
    """Write ``<command>: error: <message>`` (one line) to stderr and exit with :data:`EXIT_USAGE`."""
    print(f"{command}: error: {message}", file=sys.stderr)
    sys.exit(EXIT_USAGE)


def one_line(error: BaseException) -> str:
    """The message of ``error`` on one line: Hydra's option lists joined by commas, its cause appended."""
    text = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
    text = text.split("\nConfig search path:")[0]
    parts = []
    for block in text.split("\n\n"):
        lines = [line.strip() for line in block.splitlines() if line.strip()]
        if len(lines) > 1 and lines[0].endswith(":"):
            parts.append(f"{lines[0]} {', '.join(lines[1:])}")
        elif lines:
            parts.append(" ".join(lines))
    message = "; ".join(parts) or type(error).__name__
    cause = error.__cause__
    if isinstance(error, HydraException) and isinstance(cause, OmegaConfBaseException) and str(cause):
        message += f" ({str(cause).splitlines()[0]})"
    return message


def missing_extra(error: ModuleNotFoundError) -> str | None:
    """``pip install 'linereg[<extra>]'`` advice when ``error`` is a module of an extra, else ``None``."""
    top = (error.name or "").split(".")[0]
    extra = EXTRAS.get(top)
    if extra is None:
        return None
    return f"{top} is not installed; it comes with the [{extra}] extra: pip install 'linereg[{extra}]'"


def require(cfg: DictConfig, command: str, hints: Mapping[str, str]) -> None:
    """End the command when mandatory values (``???``) are not given, naming each with ``hints[key]``."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        named = ", ".join(f"{key}=... ({hints[key]})" if key in hints else f"{key}=..." for key in missing)
        fail(command, f"missing {named}; see {command} --help")


@contextmanager
def reported(command: str) -> Iterator[None]:
    """End the command with :func:`fail` when the block raises a usage error or misses an extra,
    and remove the run folder of a failed command when nothing was written into it.

    Used around the body of each command (Hydra adds lines of its own to errors that leave the
    task function) and by :func:`run_app` around Hydra's composition (no run folder yet).
    """
    run = _single_run()
    try:
        with _usage_errors(command):
            yield
    except BaseException:
        if run is not None:
            with suppress(OSError):  # the command's own error is the one to report
                remove_unused_run_folder(*run)
        raise


def _single_run() -> tuple[Path, str | None] | None:
    """``(run folder, hydra.output_subdir)`` inside the job of a single Hydra run, else ``None``."""
    if not HydraConfig.initialized():
        return None
    hydra = HydraConfig.get()
    if hydra.mode != RunMode.RUN:
        return None
    return Path(hydra.runtime.output_dir), hydra.output_subdir


def remove_unused_run_folder(folder: Path, output_subdir: str | None = ".hydra") -> bool:
    """Remove the run ``folder`` of a failed command, and its parents that it leaves empty below the
    working folder, when it holds nothing but Hydra's :data:`HYDRA_FILES` in ``output_subdir``, the
    files of open logging file handlers (the command's log, closed first) and empty folders.

    Returns:
        Whether the folder was removed.
    """
    folder, cwd = folder.resolve(), Path.cwd().resolve()
    if not folder.is_dir() or folder == cwd or folder in cwd.parents:
        return False
    handlers = [
        (logger, handler)
        for logger in [logging.getLogger(), *logging.Logger.manager.loggerDict.values()]
        if isinstance(logger, logging.Logger)
        for handler in logger.handlers
        if isinstance(handler, logging.FileHandler) and folder in Path(handler.baseFilename).resolve().parents
    ]
    bookkeeping = {Path(handler.baseFilename).resolve() for _, handler in handlers}
    if output_subdir is not None:
        bookkeeping |= {folder / output_subdir / name for name in HYDRA_FILES}
    for path in folder.rglob("*"):
        if path.is_symlink() or (not path.is_dir() and path not in bookkeeping):
            return False
    for logger, handler in handlers:
        logger.removeHandler(handler)
        handler.close()
    shutil.rmtree(folder)
    for parent in folder.parents:
        if cwd not in parent.parents or any(parent.iterdir()):
            break
        parent.rmdir()
    return True


@contextmanager
def _usage_errors(command: str) -> Iterator[None]:
    """End the command with :func:`fail` when the block raises a usage error or misses an extra."""
    if _USER_TRACEBACKS:
        yield
        return
    try:
        yield
    except ModuleNotFoundError as error:
        advice = missing_extra(error)
        if advice is None:
            raise
        fail(command, f"{command} needs an extra: {advice}")
    except USAGE_ERRORS as error:
        fail(command, one_line(error))


def run_app(command: str, app: Callable[[], Any]) -> Any:
    """Run a ``@hydra.main`` app, its composition errors (unknown keys or options, bad overrides)
    ending the command with :func:`fail`.

    Args:
        command: the command's name, the prefix of the message.
        app: the decorated Hydra app (it parses ``sys.argv``).

    Returns:
        What ``app`` returns.
    """
    if _USER_TRACEBACKS:
        return app()
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises its errors instead of printing them
    try:
        with reported(command):
            return app()
    finally:
        os.environ.pop("HYDRA_FULL_ERROR", None)
