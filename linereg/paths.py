"""Where linereg finds its data folders, whatever the current folder.

Two folders hold data: the shared real data (``$LINEREG_SHARED_DATA``, default ``../shared/data``)
and downloaded datasets (``$LINEREG_DATA``, default ``data``). An absolute path is used as it is;
a relative one (the defaults included) is looked for first under the project root (the checkout
that holds this package) and then under the current folder, so that a command run from another
folder reads the same data. An installed package has no project root: there a relative path is
read from the current folder alone.

The configs read both through the ``${linereg.data_folder:VARIABLE,default}`` resolver
(``configs/paths/default.yaml``), registered when this module is imported.
"""

from __future__ import annotations

import os
from pathlib import Path

from omegaconf import OmegaConf

REPO_ROOT = Path(__file__).resolve().parent.parent
"""The folder above this package: the checkout's root, or ``site-packages`` when installed."""

SHARED_DATA = ("LINEREG_SHARED_DATA", "../shared/data")
"""The shared real-data folder: its environment variable and its default."""

DATA = ("LINEREG_DATA", "data")
"""The folder of downloaded datasets (``scripts/download_*.py``): its environment variable and its default."""


def project_root() -> Path | None:
    """The checkout linereg runs from (its ``pyproject.toml`` beside this package), or ``None`` when installed."""
    return REPO_ROOT if (REPO_ROOT / "pyproject.toml").is_file() else None


def data_folder_places(variable: str, default: str) -> list[Path]:
    """Where the data folder named by ``$variable`` (else ``default``) may be, in the order looked at.

    Args:
        variable: the environment variable that names the folder (unset or empty: ``default``).
        default: the folder when the variable is unset.

    Returns:
        Normalised absolute paths: the folder itself when it is absolute; for a relative one, the
        folder under the project root (in a checkout), then under the current folder, without
        duplicates.
    """
    folder = Path(os.environ.get(variable) or default).expanduser()
    bases = [] if folder.is_absolute() else [base for base in (project_root(), Path.cwd()) if base is not None]
    places = [Path(os.path.normpath(base / folder)) for base in bases] or [Path(os.path.normpath(folder))]
    return list(dict.fromkeys(places))


def data_folder(variable: str, default: str) -> Path | None:
    """The first existing folder of :func:`data_folder_places`, or ``None`` when none exists."""
    return next((place for place in data_folder_places(variable, default) if place.is_dir()), None)


def shared_data_dir() -> Path | None:
    """The shared real-data folder (``$LINEREG_SHARED_DATA``, default ``../shared/data``), or ``None`` when absent."""
    return data_folder(*SHARED_DATA)


def _config_data_folder(variable: str, default: str) -> str:
    """The ``${linereg.data_folder:VARIABLE,default}`` resolver: the folder found, else where it belongs.

    A config resolves it even where no dataset reads it (a run on procedural shapes saves its whole
    config), so a missing folder is not an error here: the value is the first place looked at, and the
    dataset that reads it names it in its own error.
    """
    found = data_folder(variable, default)
    return str(found if found is not None else data_folder_places(variable, default)[0])


OmegaConf.register_new_resolver("linereg.data_folder", _config_data_folder, replace=True)
