"""Which pairs a split holds, as ids that do not depend on the generated points (tests of splits)."""

from __future__ import annotations

from typing import Any


def pair_identities(dataset: Any) -> set[tuple[str, Any]]:
    """``(shape file, view)``, ``(source frame file, target frame)`` or ``(source fragment file,
    target fragment)`` of every pair of a split (of every part of a concat)."""
    from linereg.datasets.splits import SubsetPairs

    indices = range(len(dataset))
    if isinstance(dataset, SubsetPairs):
        dataset, indices = dataset.base, dataset.indices
    if hasattr(dataset, "parts"):  # a concat: each part's own pairs
        flat = {int(dataset.indices[i]) for i in indices}
        found, start = set(), 0
        for part, end in zip(dataset.parts, dataset.ends, strict=True):
            kept = sorted(i - start for i in flat if start <= i < end)
            found |= pair_identities(SubsetPairs(part, kept)) if kept else set()
            start = end
        return found
    if hasattr(dataset, "entries"):  # 3DMatch fragments
        return {(str(dataset._fragment(dataset.entries[i].j)), dataset.entries[i].i) for i in indices}
    if hasattr(dataset, "pairs"):  # an RGB-D sequence
        return {(str(dataset.pairs[i][0].depth), dataset.pairs[i][1].number) for i in indices}
    return {
        (str(dataset.shapes.items[i // len(dataset.views)][1]), dataset.views[i % len(dataset.views)]) for i in indices
    }
