"""Choosing one of a model's iterates: the rule that evaluation, training's validation and
``register(method=<run>)`` apply to :attr:`linereg.structures.RegistrationOutput.transforms`.

Iterative models (RPM-Net, FMR) return one estimate per iteration and never pick one
themselves, as pytorch3d's ``iterative_closest_point`` returns its history and leaves the
choice to the caller. The rule is configured by a run's top-level block::

    iterate:
      rule: last          # last | best_fit
      keep_fraction: 1.0  # best_fit: share of each direction's nearest-neighbour distances judged

``best_fit`` keeps, per pair, the iterate whose moved source lies closest to the target by
:func:`linereg.pointcloud.trimmed_chamfer_distance` (no label is read): iterations past the ones
a pair's motion needs can drift away from the solution, and this picks the estimate back.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import torch

from linereg.pointcloud import trimmed_chamfer_distance
from linereg.se3 import transform_points

ITERATE_RULES: tuple[str, ...] = ("last", "best_fit")


@dataclass(frozen=True)
class IterateRule:
    """Which iterate a model's output answers with.

    Attributes:
        rule: ``"last"`` (the final iterate) or ``"best_fit"`` (per pair, the iterate of the
            lowest trimmed Chamfer distance between the moved source and the target).
        keep_fraction: ``best_fit``: share of each direction's nearest-neighbour distances
            judged, in ``(0, 1]``; 1 is the Chamfer distance.
    """

    rule: str = "last"
    keep_fraction: float = 1.0

    def __post_init__(self) -> None:
        if self.rule not in ITERATE_RULES:
            raise ValueError(f"iterate.rule must be one of {', '.join(ITERATE_RULES)}, got {self.rule!r}")
        fraction = self.keep_fraction
        if isinstance(fraction, bool) or not isinstance(fraction, int | float) or not 0.0 < fraction <= 1.0:
            raise ValueError(f"iterate.keep_fraction must be a number in (0, 1], got {fraction!r}")

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None) -> IterateRule:
        """The rule of an ``iterate:`` block (``None``: the last iterate).

        Raises:
            ValueError: an unknown key (the accepted ones are listed) or a bad value.
        """
        if config is None:
            return cls()
        accepted = {f.name for f in fields(cls)}
        unknown = sorted(set(config) - accepted)
        if unknown:
            raise ValueError(f"unknown iterate key(s) {unknown}; accepted: {sorted(accepted)}")
        return cls(**{key: value for key, value in config.items() if value is not None})

    def as_config(self) -> dict[str, Any]:
        """The rule as an ``iterate:`` block (``{"rule": ..., "keep_fraction": ...}``)."""
        return {"rule": self.rule, "keep_fraction": self.keep_fraction}

    def select(
        self,
        transforms: Sequence[torch.Tensor],
        src: torch.Tensor,
        tgt: torch.Tensor,
        src_lengths: torch.Tensor | None = None,
        tgt_lengths: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`select_iterate` with this rule."""
        return select_iterate(transforms, src, tgt, self.rule, self.keep_fraction, src_lengths, tgt_lengths)


LAST_ITERATE = IterateRule()
"""The rule that answers with each pair's last iterate."""


def select_iterate(
    transforms: Sequence[torch.Tensor],
    src: torch.Tensor,
    tgt: torch.Tensor,
    rule: str = "last",
    keep_fraction: float = 1.0,
    src_lengths: torch.Tensor | None = None,
    tgt_lengths: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pair, the iterate a rule answers with; ``transforms`` is left untouched.

    Args:
        transforms: ``I`` source -> target estimates of shape ``(B, 4, 4)``, one per iteration.
        src: tensor of shape ``(B, N, 3)`` giving the source clouds (padded when
            ``src_lengths`` is given).
        tgt: tensor of shape ``(B, M, 3)`` giving the target clouds.
        rule: ``"last"`` or ``"best_fit"`` (see :class:`IterateRule`).
        keep_fraction: ``best_fit``: share of each direction's nearest-neighbour distances
            judged, in ``(0, 1]``.
        src_lengths: optional ``(B,)`` numbers of valid source points.
        tgt_lengths: optional ``(B,)`` numbers of valid target points.

    Returns:
        ``(transform, index)``: the chosen estimates ``(B, 4, 4)`` (gradients flow through
        them) and the ``(B,)`` long index of each pair's iterate; ties keep the earliest.

    Raises:
        ValueError: an unknown rule, a ``keep_fraction`` outside ``(0, 1]``, no iterate, or
            iterates whose shape is not ``(B, 4, 4)``.
    """
    IterateRule(rule, keep_fraction)
    if len(transforms) == 0:
        raise ValueError("transforms is empty: a model returns at least one iterate")
    batch = src.shape[0]
    for position, transform in enumerate(transforms):
        if transform.shape != (batch, 4, 4):
            raise ValueError(f"transforms[{position}] must have shape ({batch}, 4, 4), got {tuple(transform.shape)}")
    if rule == "last":
        last = torch.full((batch,), len(transforms) - 1, dtype=torch.long, device=transforms[-1].device)
        return transforms[-1], last
    with torch.no_grad():
        fits = torch.stack([_fit(T, src, tgt, keep_fraction, src_lengths, tgt_lengths) for T in transforms])
    kept = fits.argmin(0)
    pairs = torch.arange(batch, device=kept.device)
    return torch.stack(list(transforms))[kept, pairs], kept


def _fit(
    transform: torch.Tensor,
    src: torch.Tensor,
    tgt: torch.Tensor,
    keep_fraction: float,
    src_lengths: torch.Tensor | None,
    tgt_lengths: torch.Tensor | None,
) -> torch.Tensor:
    """``(B,)`` trimmed Chamfer distances between the moved sources and the targets (valid points only)."""
    moved = transform_points(transform, src)
    if src_lengths is None and tgt_lengths is None:
        return trimmed_chamfer_distance(moved, tgt, keep_fraction)
    src_counts = [src.shape[1]] * src.shape[0] if src_lengths is None else src_lengths.tolist()
    tgt_counts = [tgt.shape[1]] * tgt.shape[0] if tgt_lengths is None else tgt_lengths.tolist()
    return torch.stack(
        [
            trimmed_chamfer_distance(moved[b, : int(n)], tgt[b, : int(m)], keep_fraction)
            for b, (n, m) in enumerate(zip(src_counts, tgt_counts, strict=True))
        ]
    )
