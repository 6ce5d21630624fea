"""Splits of a dataset config, seeded subsets and on-disk caching of the pairs actually used.

Dataset configs (``configs/dataset/``) hold the builder's keys plus two sections read here::

    name: procedural             # linereg.datasets.DATASETS entry; other keys are its arguments
    protocol: {...}
    splits: {train: {split: train}, val: {split: train, seed: 1, subset: 36}, test: {split: test}}
    variants: {easy: {protocol: {max_angle_deg: 15}}}

A split's entry overrides the common keys (``null`` removes the split) and may hold ``subset``,
the pairs of that split kept (e.g. a validation set of fresh poses of a few training shapes).
``variants`` are overrides applied to a split (e.g. smaller poses for a curriculum's first stage);
a subset is a number of pairs (int) or a fraction of the split (float in ``(0, 1]``), drawn at
random (seeded).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from omegaconf import OmegaConf
from torch.utils.data import Dataset, Subset

from linereg.datasets import CACHE_KEYS, build_dataset, materialize
from linereg.datasets.base import PairDataset
from linereg.datasets.combine import concat_parts
from linereg.registry import plain
from linereg.structures import PairSample

SPLITS = ("train", "val", "test")
# Keys of a split's entry read here, not by the dataset builder.
SPLIT_KEYS = ("subset",)


class SubsetPairs(PairDataset):
    """Selected pairs of a :class:`PairDataset`, itself cacheable (its settings name the pairs).

    Args:
        base: the full dataset.
        indices: the pairs kept, in this order.
    """

    def __init__(self, base: PairDataset, indices: Sequence[int]) -> None:
        self.base = base
        self.indices = [int(i) for i in indices]
        self.registry_name = f"{base.registry_name}-subset"

    def __len__(self) -> int:
        return len(self.indices)

    def make_pair(self, index: int) -> PairSample:
        return self.base.make_pair(self.indices[index])

    def settings(self) -> dict[str, Any]:
        return {"base": self.base.settings(), "indices": self.indices}


def subset_indices(length: int, subset: int | float | None, seed: int) -> np.ndarray | None:
    """Sorted random indices of ``subset`` pairs out of ``length`` (``None``: keep all).

    Args:
        length: pairs in the split.
        subset: a count, a fraction in ``(0, 1]`` or ``None``.
        seed: selection seed.
    """
    if subset is None:
        return None
    count = subset if isinstance(subset, int) else max(1, round(subset * length))
    if count >= length:
        return None
    return np.sort(np.random.default_rng(seed).choice(length, size=count, replace=False))


def dataset_config(config: Mapping[str, Any], split: str, variant: str | None = None) -> dict[str, Any] | None:
    """The builder config of one split: common keys + ``splits[split]`` + ``variants[variant]``.

    Args:
        config: a dataset config (see the module docstring).
        split: ``"train"``, ``"val"`` or ``"test"``.
        variant: a key of ``config["variants"]``, or ``None``.

    Returns:
        The mapping for :func:`linereg.datasets.build_dataset`, or ``None`` when the dataset has no
        such split (``splits: {val: null}``).
    """
    config = plain(config)
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    splits = config.get("splits") or {}
    variants = config.get("variants") or {}
    unknown_splits = sorted(set(splits) - set(SPLITS))
    if unknown_splits:
        raise ValueError(f"dataset splits must be among {SPLITS}, got {unknown_splits}")
    if split in splits and splits[split] is None:
        return None
    if variant is not None and variant not in variants:
        raise ValueError(
            f"dataset {config.get('name')!r} has no variant {variant!r} (a curriculum stage asks for it); "
            f"variants: {sorted(variants) or 'none'}"
        )
    base = {key: value for key, value in config.items() if key not in ("splits", "variants")}
    layers = [base, splits.get(split) or {}, variants.get(variant) or {}]
    merged = OmegaConf.to_container(OmegaConf.merge(*layers), resolve=True)
    return _split_parts(merged, split, variant) if merged.get("name") == "concat" else merged


def _split_parts(config: dict[str, Any], split: str, variant: str | None) -> dict[str, Any]:
    """A concat's parts for one split: a part with its own ``splits`` (a dataset config of another
    kind, e.g. depth frames split in time) takes its own entry for ``split`` and ``variant`` and is
    left out where that entry is ``null``; the other parts get the concat's ``common`` keys. A named
    part set to ``null`` (by a split or a variant) is left out."""
    parts = concat_parts(config.get("datasets") or [])
    config = {**config, "datasets": parts}
    if not any(isinstance(part, Mapping) and "splits" in part for part in parts):
        return config
    common = config.pop("common", None) or {}
    resolved = []
    for part in parts:
        if "splits" not in part:
            resolved.append(OmegaConf.to_container(OmegaConf.merge(part, common)))
        elif (own := dataset_config(part, split, variant)) is not None:
            resolved.append({key: value for key, value in own.items() if key not in CACHE_KEYS})  # the concat caches
    return {**config, "datasets": resolved}


def build_split(
    config: Mapping[str, Any],
    split: str,
    *,
    variant: str | None = None,
    subset: int | float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> Dataset | None:
    """The dataset of one split, optionally a seeded subset, cached on disk when configured.

    A ``cache_dir`` key generates the pairs actually used (the subset, not the whole split)
    once into the on-disk cache of :mod:`linereg.datasets.cache`. The split's own ``subset``
    (its entry in ``splits``) applies when ``subset`` is ``None``.

    Args:
        config: a dataset config (see the module docstring).
        split: ``"train"``, ``"val"`` or ``"test"``.
        variant: dataset variant (curriculum stages).
        subset: pairs kept (see :class:`linereg.train.curriculum.Stage`).
        seed: subset selection seed.
        progress: show the cache generation bar.

    Returns:
        The dataset, or ``None`` when the dataset has no such split.
    """
    builder_config = dataset_config(config, split, variant)
    if builder_config is None:
        return None
    cache = {key: builder_config.pop(key) for key in CACHE_KEYS if key in builder_config}
    own = {key: builder_config.pop(key) for key in SPLIT_KEYS if key in builder_config}
    if subset is None:
        subset = own.get("subset")
    dataset = build_dataset(builder_config)
    indices = subset_indices(len(dataset), subset, seed)
    if indices is not None:
        dataset = SubsetPairs(dataset, indices) if isinstance(dataset, PairDataset) else Subset(dataset, indices)
    if cache.get("cache_dir") and isinstance(dataset, PairDataset):
        dataset = materialize(dataset, cache["cache_dir"], workers=cache.get("cache_workers"), progress=progress)
    return dataset
