"""Several datasets as one, optionally split into train/test (the paper's mixed Real dataset).

``{name: concat, datasets: [{name: threedmatch, ...}, {name: rgbd_sequence, ...}],
split: train, train_fraction: 0.8}`` concatenates the parts and keeps a seeded random
``train_fraction`` share of the pairs (``split: test`` keeps the rest, ``all`` everything).

``common`` holds keys merged (deeply) into every part, so that a dataset config's splits and
variants reach parts that split themselves::

    {name: concat, datasets: [...], splits: {train: {common: {split: train}}},
     variants: {easy: {common: {protocol: {max_angle_deg: 15}}}}}

Each part then takes its own train split (its shapes, its views) and the concat keeps all of them.
A part of another kind may carry its own ``splits`` and ``variants`` instead (depth frames split in
time): :func:`linereg.datasets.splits.dataset_config` gives it its own entry, not ``common``.
``datasets`` may also be a mapping of named parts (kept in order), so that a config can add a part
to another's (``defaults: [objects, _self_]`` and ``datasets: {rooms: {...}}``).
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping, Sequence
from itertools import accumulate
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from linereg.datasets.base import DATASETS, PairDataset
from linereg.structures import PairSample

SPLITS = ("train", "test", "all")


class ConcatPairs(PairDataset):
    """The pairs of ``parts`` one after the other, restricted to a seeded random split.

    Args:
        parts: the datasets.
        split: ``"train"``, ``"test"`` or ``"all"``.
        train_fraction: share of the concatenated pairs that is train.
        split_seed: seed of the permutation that assigns pairs to splits.
    """

    registry_name = "concat"

    def __init__(
        self,
        parts: Sequence[PairDataset],
        *,
        split: str = "all",
        train_fraction: float = 0.8,
        split_seed: int = 0,
    ) -> None:
        if not parts:
            raise ValueError("concat needs at least one dataset")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if not 0 < train_fraction < 1:
            raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
        self.parts = list(parts)
        self.ends = list(accumulate(len(part) for part in self.parts))
        total = self.ends[-1]
        order = np.random.default_rng(split_seed).permutation(total)
        num_train = round(train_fraction * total)
        chosen = {"train": order[:num_train], "test": order[num_train:], "all": np.arange(total)}
        self.indices = np.sort(chosen[split])
        if len(self.indices) == 0:
            raise ValueError(f"split {split!r} of {total} pairs is empty")
        self.split = split
        self.train_fraction = train_fraction
        self.split_seed = split_seed

    def __len__(self) -> int:
        return len(self.indices)

    def make_pair(self, index: int) -> PairSample:
        flat = int(self.indices[index])
        part = bisect.bisect_right(self.ends, flat)
        start = self.ends[part - 1] if part else 0
        pair = self.parts[part][flat - start]
        pair.meta = {**pair.meta, "concat_index": index, "part": part}
        return pair

    def settings(self) -> dict[str, Any]:
        return {
            "dataset": self.registry_name,
            "parts": [part.settings() for part in self.parts],
            "split": self.split,
            "train_fraction": self.train_fraction,
            "split_seed": self.split_seed,
        }


def concat_parts(datasets: Sequence[Any] | Mapping[str, Any]) -> list[Any]:
    """A concat's part configs as a list: a mapping's named parts in order, those set to ``null``
    (by a split or a variant) left out."""
    if isinstance(datasets, Mapping):
        return [part for part in datasets.values() if part is not None]
    return list(datasets)


@DATASETS.register("concat")
def build_concat(
    *,
    datasets: Sequence[Mapping[str, Any]] | Mapping[str, Mapping[str, Any]],
    split: str = "all",
    train_fraction: float = 0.8,
    split_seed: int = 0,
    common: Mapping[str, Any] | None = None,
) -> ConcatPairs:
    """Concatenate dataset configs (each ``{name: ..., **kwargs}``, with ``common`` merged into
    each; a mapping: named parts, in order, see :func:`concat_parts`) and take a split."""
    from linereg.datasets import build_dataset

    datasets = concat_parts(datasets)
    if common is not None and not isinstance(common, Mapping):
        raise TypeError(f"concat's common must be a mapping of keys for every part, got {type(common).__name__}")
    merged = [OmegaConf.to_container(OmegaConf.merge(config, common or {})) for config in datasets]
    parts = [build_dataset(config) for config in merged]
    uncached = [p for p in parts if not isinstance(p, PairDataset)]
    if uncached:
        raise ValueError("concat parts must be generators, not caches; cache the concat instead")
    return ConcatPairs(parts, split=split, train_fraction=train_fraction, split_seed=split_seed)
