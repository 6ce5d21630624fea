"""Training, evaluation and registration entry points (``python -m train``, ``train.evaluate``, ...).

``train(cfg)`` (:mod:`linereg.train.loop`) is imported on first use, so that light entry points of this
package (``train.summary``) start without loading torch and the models.
"""

from __future__ import annotations

from typing import Any

__all__ = ["train"]


def __getattr__(name: str) -> Any:
    if name == "train":
        from linereg.train.loop import train

        return train
    raise AttributeError(f"module 'train' has no attribute {name!r}")
