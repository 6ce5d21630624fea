"""How far an epoch went: the running sums behind its logged means (``epoch/...``).

A step checkpoint stores them (``epoch_sums``), so an epoch resumed in its middle runs the
remaining batches and logs the same means as an uninterrupted epoch.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass
class EpochSums:
    """Running sums of one epoch's training values.

    Attributes:
        batches: batches run so far (skipped steps included); the next batch's index.
        steps: optimizer steps taken so far (batches whose step was not skipped).
        totals: sum of each logged value over the steps that logged it.
        counts: number of steps that logged each value (term gradient norms come on logging
            steps only).
    """

    batches: int = 0
    steps: int = 0
    totals: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))

    def add(self, values: Mapping[str, float] | None) -> None:
        """Count one batch, and the values of its step (``None``: the step was skipped)."""
        self.batches += 1
        if values is None:
            return
        self.steps += 1
        for name, value in values.items():
            self.totals[name] += value
            self.counts[name] += 1

    def means(self) -> dict[str, float]:
        """The mean of each value over the steps that logged it."""
        return {name: value / self.counts[name] for name, value in self.totals.items()}

    def state(self) -> dict[str, Any]:
        """The ``epoch_sums`` entry of a step checkpoint."""
        return {"batches": self.batches, "steps": self.steps, "totals": dict(self.totals), "counts": dict(self.counts)}

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> EpochSums:
        """Restore :meth:`state`."""
        return cls(
            batches=int(state["batches"]),
            steps=int(state["steps"]),
            totals=defaultdict(float, state["totals"]),
            counts=defaultdict(int, state["counts"]),
        )
