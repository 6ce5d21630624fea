"""The base class every dataset derives from, and per-item random generators.

A dataset is a map-style ``torch.utils.data.Dataset`` of :class:`~linereg.structures.PairSample`
that is a pure function of its settings and ``(seed, index)``: each item draws from its own
generator :func:`item_rng`, so DataLoader workers, reruns and the on-disk cache agree.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import Dataset

from linereg.registry import Registry
from linereg.structures import PairSample

DATASETS: Registry[Dataset] = Registry("dataset")


def existing_folder(root: str | Path, what: str) -> Path:
    """``root`` resolved (``~`` expanded); FileNotFoundError naming ``what`` when it is no folder."""
    path = Path(root).expanduser()
    if not path.is_dir():
        raise FileNotFoundError(f"{what} not found: {path}")
    return path.resolve()


def item_rng(seed: int, *stream: int) -> np.random.Generator:
    """A generator seeded from ``seed`` and item coordinates (e.g. ``(split, index)``)."""
    return np.random.default_rng([int(seed), *(int(s) for s in stream)])


class PairDataset(Dataset):
    """A deterministic, indexable collection of registration pairs.

    Subclasses implement ``__len__``, :meth:`make_pair` and :meth:`settings`.
    """

    registry_name = "pairs"

    def __len__(self) -> int:
        raise NotImplementedError

    def make_pair(self, index: int) -> PairSample:
        """Build pair ``index`` (``0 <= index < len(self)``) from scratch."""
        raise NotImplementedError

    def settings(self) -> dict[str, Any]:
        """JSON-serialisable description of everything that determines the pairs.

        The cache keys its folders by a hash of this dictionary.
        """
        raise NotImplementedError

    def __getitem__(self, index: int) -> PairSample:
        length = len(self)
        if not -length <= index < length:
            raise IndexError(f"index {index} out of range for {type(self).__name__} of {length}")
        return self.make_pair(index % length)
