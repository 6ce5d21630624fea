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

The splits, variants and subsets themselves are built by :mod:`linereg.datasets.splits`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

from linereg.registry import plain


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

    @property
    def without_variant(self) -> str:
        """The override that trains this stage on the pairs as they are (no dataset variant)."""
        return f"curriculum.stages.{self.name}.variant=null"

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

    def check_variants(self, dataset: Mapping[str, Any]) -> None:
        """Raise ``ValueError`` naming the override that fixes each stage whose ``variant`` the
        ``dataset`` config's ``variants`` lack."""
        variants = dataset.get("variants") or {}
        missing = [stage for stage in self.stages if stage.variant is not None and stage.variant not in variants]
        if missing:
            asked = ", ".join(sorted({repr(stage.variant) for stage in missing}))
            overrides = " ".join(stage.without_variant for stage in missing)
            raise ValueError(
                f"dataset {dataset.get('name')!r} has no variant {asked} (its variants: "
                f"{', '.join(sorted(variants)) or 'none'}); pass {overrides} to train on the pairs as they are"
            )

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
