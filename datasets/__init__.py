"""Registration pairs: sources, the paper's pair protocol, caching and collation.

Every dataset yields :class:`linereg.structures.PairSample` (numpy): float32 source/target
clouds, normals (computed when the data has none), ``gt_transform`` mapping source to target
(``tgt ≈ R @ src + t``) or ``None`` for unlabeled data, and metadata. Pairs are deterministic
given ``(seed, index)``. :func:`linereg.datasets.collate.collate_pairs` batches them into a
:class:`~linereg.structures.PairBatch`.

Registered datasets (``DATASETS.names()``): ``procedural`` (default, no files), ``mesh_folder``,
``modelnet40``, ``threedmatch``, ``rgbd_sequence``, ``pairs_folder``, ``scan_folder``, ``concat`` (several
datasets, optionally split), ``cached`` (a cache folder written by
``scripts/prepare_dataset.py``).

Configs are mappings ``{name: <registered>, **kwargs}``; two extra keys apply to every dataset:
``cache_dir`` (generate every pair once into a compressed on-disk cache there and serve it
from memory) and ``cache_workers`` (processes used to fill it; default all cores).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from torch.utils.data import Dataset

from linereg.datasets import (  # noqa: F401  (importing registers the builders)
    cache,
    combine,
    pairs_folder,
    procedural,
    rgbd,
    scan_folder,
    shape_sources,
    threedmatch,
)
from linereg.datasets.base import DATASETS, PairDataset, item_rng
from linereg.datasets.cache import CachedPairs, materialize
from linereg.datasets.collate import collate_pairs
from linereg.registry import plain

__all__ = [
    "CACHE_KEYS",
    "DATASETS",
    "CachedPairs",
    "PairDataset",
    "build_dataset",
    "collate_pairs",
    "configured_half_extent",
    "item_rng",
    "materialize",
]

CACHE_KEYS = ("cache_dir", "cache_workers")


def build_dataset(config: Mapping[str, Any]) -> Dataset:
    """Build a dataset from ``{name: <registered>, **kwargs}`` (a dict or a Hydra config).

    Args:
        config: ``name`` selects the builder in :data:`DATASETS`; other keys are its keyword
            arguments, plus the optional ``cache_dir`` / ``cache_workers``.

    Returns:
        The dataset, or its :class:`CachedPairs` when ``cache_dir`` is given.

    Raises:
        TypeError: ``config`` is not a mapping.
        linereg.registry.UnknownNameError: no or an unknown dataset name (lists the registered ones).
        linereg.registry.ArgumentError: keys the builder does not accept, or required ones missing.
    """
    config = plain(config)
    if not isinstance(config, Mapping):
        raise TypeError(f"dataset config must be a mapping {{name: ..., **kwargs}}, got {type(config).__name__}")
    config = dict(config)
    cache_options = {key: config.pop(key) for key in CACHE_KEYS if key in config}
    dataset = DATASETS.build(config)
    if cache_options.get("cache_dir") is not None:
        if not isinstance(dataset, PairDataset):
            raise ValueError(f"dataset {config['name']!r} is already a cache; drop 'cache_dir'")
        return materialize(dataset, cache_options["cache_dir"], workers=cache_options.get("cache_workers"))
    return dataset


def configured_half_extent(config: Mapping[str, Any]) -> float | None:
    """Half the side of the cube ``[-h, h]^3`` a dataset config scales its pairs into (``None``: the
    pairs keep their own units): ``half_extent`` of the config or of its pair protocol, else its
    builder's default, else 1 (the pair protocols' cube)."""
    for section in (config, config.get("protocol") or {}):
        if isinstance(section, Mapping) and "half_extent" in section:
            return section["half_extent"]
    name = config.get("name")
    if name in DATASETS.names():
        parameter = inspect.signature(DATASETS.get(name)).parameters.get("half_extent")
        if parameter is not None and parameter.default is not inspect.Parameter.empty:
            return parameter.default
    return 1.0
