"""The training curriculum (paper §4.3) and the data each stage trains on.

The paper initialises its unsupervised models in three steps: overfit an easy set of 100 pairs
with small pose differences, train on 10% of the training set, then train on the whole set with
a reduced learning rate. A :class:`Curriculum` is that list of :class:`Stage` s, read from the
``curriculum`` config::

    stages:                      # run in this order; a stage with epochs: 0 is skipped
      easy: {epochs: 500, subset: 100, variant: easy, lr: 1.0e-4}
      subset: {epochs: 50, subset: 0.1, lr: 1.0e-4}
      full: {epochs: 50}         # lr: null -> optimizer.lr (x lr_scale)

``subset`` is a number of pairs (int) or a fraction of the split (float in (0, 1]), drawn at
random (seeded) once per run; ``variant`` names an entry of the dataset config's ``variants``
(overrides applied to the training split, e.g. smaller poses for ``easy``).

Dataset configs (``configs/dataset/``) hold the builder's keys plus two sections read here::

    name: procedural             # datasets.DATASETS entry; other keys are its arguments
    protocol: {...}
    splits: {train: {split: train}, val: {split: val}, test: {split: test}}  # null: no split
    variants: {easy: {protocol: {max_angle_deg: 15}}}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from linereg.datasets import build_dataset, materialize
from linereg.datasets.base import PairDataset
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset, Subset

from linereg.structures import PairSample

SPLITS = ("train", "val", "test")
_CACHE_KEYS = ("cache_dir", "cache_workers")


def plain(config: Any) -> Any:
    """A plain, resolved Python container from an OmegaConf config (other values unchanged)."""
    if isinstance(config, DictConfig) or OmegaConf.is_list(config):
        return OmegaConf.to_container(config, resolve=True)
    return config


@dataclass(frozen=True)
class Stage:
    """One curriculum stage.

    Attributes:
        name: shown in logs and stored in checkpoints.
        epochs: epochs of this stage (0 skips it).
        subset: pairs of the training split used: an int (count), a float in ``(0, 1]``
            (fraction) or ``None`` (all).
        variant: a key of the dataset config's ``variants`` applied to the training split.
        lr: learning rate of the stage; ``None`` takes ``optimizer.lr``.
        lr_scale: multiplies the learning rate.
    """

    name: str
    epochs: int
    subset: int | float | None = None
    variant: str | None = None
    lr: float | None = None
    lr_scale: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.epochs, int) or self.epochs < 0:
            raise ValueError(f"curriculum stage {self.name!r}: epochs must be an int >= 0, got {self.epochs!r}")
        if isinstance(self.subset, bool) or not (
            self.subset is None
            or (isinstance(self.subset, int) and self.subset >= 1)
            or (isinstance(self.subset, float) and 0.0 < self.subset <= 1.0)
        ):
            raise ValueError(
                f"curriculum stage {self.name!r}: subset must be a count >= 1, a fraction in (0, 1] "
                f"or null, got {self.subset!r}"
            )
        if self.lr is not None and not self.lr > 0:
            raise ValueError(f"curriculum stage {self.name!r}: lr must be > 0 or null, got {self.lr}")
        if not self.lr_scale > 0:
            raise ValueError(f"curriculum stage {self.name!r}: lr_scale must be > 0, got {self.lr_scale}")

    def learning_rate(self, base_lr: float) -> float:
        """The stage's learning rate given ``optimizer.lr``."""
        return (base_lr if self.lr is None else self.lr) * self.lr_scale

    def describe(self, base_lr: float) -> str:
        """One line: epochs, data and learning rate."""
        data = "all pairs" if self.subset is None else f"subset {self.subset}"
        variant = f", variant {self.variant!r}" if self.variant else ""
        return f"{self.name!r}: {self.epochs} epochs, {data}{variant}, lr {self.learning_rate(base_lr):.3g}"


class Curriculum:
    """Stages run in order; epochs are counted globally across stages.

    Args:
        stages: the stages (those with 0 epochs are dropped).
        allow_empty: accept a curriculum without any epoch (an untrained control run,
            ``trainer.untrained=true``); otherwise that is an error.
    """

    def __init__(self, stages: Sequence[Stage], *, allow_empty: bool = False) -> None:
        self.stages = [stage for stage in stages if stage.epochs > 0]
        if not self.stages and not allow_empty:
            raise ValueError(
                "the curriculum has no stage with epochs > 0; to evaluate the initial (untrained) model on purpose, "
                "set trainer.untrained=true"
            )
        names = [stage.name for stage in self.stages]
        if len(set(names)) != len(names):
            raise ValueError(f"curriculum stage names must be unique, got {names}")

    @classmethod
    def from_config(cls, config: Mapping[str, Any], *, allow_empty: bool = False) -> Curriculum:
        """Build from ``{stages: {name: {epochs, subset, variant, lr, lr_scale}}}`` (``allow_empty``: see the class)."""
        config = plain(config)
        if set(config) != {"stages"}:
            raise ValueError(f"the curriculum config takes only 'stages', got keys {sorted(config)}")
        accepted = {f.name for f in fields(Stage)} - {"name"}
        stages = []
        for name, stage in config["stages"].items():
            stage = dict(stage or {})
            unknown = sorted(set(stage) - accepted)
            if unknown:
                raise ValueError(f"curriculum stage {name!r}: unknown key(s) {unknown}; accepted: {sorted(accepted)}")
            if "epochs" not in stage:
                raise ValueError(f"curriculum stage {name!r} needs 'epochs'")
            stages.append(Stage(name=str(name), **stage))
        return cls(stages, allow_empty=allow_empty)

    @property
    def total_epochs(self) -> int:
        return sum(stage.epochs for stage in self.stages)

    def locate(self, epoch: int) -> tuple[int, int]:
        """``(stage index, epoch within the stage)`` of global epoch ``epoch``."""
        if not 0 <= epoch < self.total_epochs:
            raise ValueError(f"epoch {epoch} outside the curriculum's {self.total_epochs} epochs")
        for index, stage in enumerate(self.stages):
            if epoch < stage.epochs:
                return index, epoch
            epoch -= stage.epochs
        raise AssertionError("unreachable")

    def first_epoch(self, index: int) -> int:
        """Global epoch at which stage ``index`` starts."""
        return sum(stage.epochs for stage in self.stages[:index])


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
    return OmegaConf.to_container(OmegaConf.merge(*layers), resolve=True)


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
    once into the on-disk cache of :mod:`linereg.datasets.cache`.

    Args:
        config: a dataset config (see the module docstring).
        split: ``"train"``, ``"val"`` or ``"test"``.
        variant: dataset variant (curriculum stages).
        subset: pairs kept (see :class:`Stage`).
        seed: subset selection seed.
        progress: show the cache generation bar.

    Returns:
        The dataset, or ``None`` when the dataset has no such split.
    """
    builder_config = dataset_config(config, split, variant)
    if builder_config is None:
        return None
    cache = {key: builder_config.pop(key) for key in _CACHE_KEYS if key in builder_config}
    dataset = build_dataset(builder_config)
    indices = subset_indices(len(dataset), subset, seed)
    if indices is not None:
        dataset = SubsetPairs(dataset, indices) if isinstance(dataset, PairDataset) else Subset(dataset, indices)
    if cache.get("cache_dir") and isinstance(dataset, PairDataset):
        dataset = materialize(dataset, cache["cache_dir"], workers=cache.get("cache_workers"), progress=progress)
    return dataset
