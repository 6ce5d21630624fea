"""Where linereg finds the optional shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_data_dir() -> Path | None:
    """The shared real-data folder, or ``None`` when it is absent.

    ``$LINEREG_SHARED_DATA`` wins; otherwise ``<repo>/../shared/data`` is used if it exists.
    """
    env = os.environ.get("LINEREG_SHARED_DATA")
    candidate = Path(env) if env else REPO_ROOT.parent / "shared" / "data"
    return candidate if candidate.is_dir() else None
