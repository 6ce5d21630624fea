"""The entry layer: training (``linereg-train``, ``python -m train``), ``evaluate``, ``register``,
``benchmark`` and the training loop.

Every command of the package is a module here, so this file runs before any of them imports
torch: it asks OpenMP threads to sleep rather than spin while they wait (``OMP_WAIT_POLICY``,
unless the user set it), since spinning threads oversubscribe small machines.
``train(cfg)`` (:mod:`linereg.train.loop`) is imported on first use, so that light entry points
(``linereg.train.summary``) start without loading torch and the models.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import linereg.paths  # noqa: F401  (registers the configs' ${linereg.data_folder:...} resolver)

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")
"""The Hydra configs: ``configs/`` of a checkout, ``linereg/configs/`` of an installed package."""

__all__ = ["CONFIG_DIR", "train"]


def __getattr__(name: str) -> Any:
    if name == "train":
        from linereg.train.loop import train

        return train
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
