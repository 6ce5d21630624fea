"""Batching: a list of :class:`PairSample` (numpy) -> one :class:`PairBatch` (torch).

Two ways to make clouds of different sizes batchable:

* ``num_points`` given: every cloud is brought to exactly that many points (FPS when it has
  more, all points plus random repeats when it has fewer). Source and target then have equal
  counts, which FMR needs. Use ``functools.partial(collate_pairs, num_points=1024)`` as a
  DataLoader ``collate_fn``.
* ``num_points=None``: clouds are zero-padded to the largest size in the batch and
  ``src_lengths`` / ``tgt_lengths`` give the valid counts (pytorch3d ``Pointclouds`` style);
  lengths stay ``None`` when no padding was needed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from linereg.datasets.base import item_rng
from linereg.datasets.protocol import subsample
from linereg.structures import PairBatch, PairSample

_COLLATE_STREAM = 13


def _stack_optional(values: list[np.ndarray | None], name: str) -> torch.Tensor | None:
    """Stack arrays that are present for every sample; ``None`` when absent for all."""
    present = [v is not None for v in values]
    if not any(present):
        return None
    if not all(present):
        missing = [i for i, p in enumerate(present) if not p]
        raise ValueError(
            f"{name} is present for some samples of the batch but missing for samples {missing}; "
            "a dataset must provide it for every pair or for none"
        )
    return torch.from_numpy(np.stack(values).astype(np.float32, copy=False))


def _pad(clouds: list[np.ndarray | None], sizes: list[int]) -> torch.Tensor:
    """``(B, max size, 3)`` float32 tensor, zero beyond each cloud's size."""
    padded = np.zeros((len(clouds), max(sizes), 3), dtype=np.float32)
    for row, (cloud, size) in enumerate(zip(clouds, sizes, strict=True)):
        padded[row, :size] = cloud
    return torch.from_numpy(padded)


def _check_sample(sample: PairSample, position: int) -> None:
    """TypeError/ValueError unless the sample's clouds are ``(N, 3)`` arrays with matching normals."""
    if not isinstance(sample, PairSample):
        raise TypeError(f"samples[{position}] must be a PairSample, got {type(sample).__name__}")
    for side in ("src", "tgt"):
        xyz, normals = getattr(sample, f"{side}_xyz"), getattr(sample, f"{side}_normals")
        if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
            raise ValueError(f"samples[{position}].{side}_xyz must have shape (N, 3) with N >= 1, got {xyz.shape}")
        if normals is not None and normals.shape != xyz.shape:
            raise ValueError(
                f"samples[{position}].{side}_normals must match {side}_xyz {xyz.shape}, got {normals.shape}"
            )


def _resized(sample: PairSample, position: int, num_points: int) -> PairSample:
    """The sample with both clouds brought to ``num_points`` points (FPS or repeats)."""
    rng = item_rng(sample.meta.get("index", position), _COLLATE_STREAM)
    fields = {}
    for side in ("src", "tgt"):
        xyz, normals = getattr(sample, f"{side}_xyz"), getattr(sample, f"{side}_normals")
        idx = np.arange(num_points) if len(xyz) == num_points else subsample(xyz, num_points, rng)
        fields[f"{side}_xyz"] = xyz[idx]
        fields[f"{side}_normals"] = None if normals is None else normals[idx]
    return PairSample(gt_transform=sample.gt_transform, meta=sample.meta, **fields)


def collate_pairs(samples: Sequence[PairSample], *, num_points: int | None = None) -> PairBatch:
    """Batch pairs into tensors.

    Args:
        samples: the pairs (numpy clouds ``(N_i, 3)``, ``(M_i, 3)``).
        num_points: bring every cloud to this many points; ``None`` pads instead.

    Returns:
        A :class:`PairBatch` of float32 tensors: ``src_xyz (B, N, 3)``, ``tgt_xyz (B, M, 3)``,
        normals when every sample has them, ``gt_transform (B, 4, 4)`` when every sample is
        labelled, lengths ``(B,)`` when padded, and the metadata list.

    Raises:
        ValueError: empty batch, malformed clouds, ``num_points < 1``, or normals / ground
            truth present for only part of the batch.
    """
    if len(samples) == 0:
        raise ValueError("cannot collate an empty list of samples")
    if num_points is not None and num_points < 1:
        raise ValueError(f"num_points must be >= 1 or None, got {num_points}")
    for position, sample in enumerate(samples):
        _check_sample(sample, position)
    if num_points is not None:
        samples = [_resized(s, i, num_points) for i, s in enumerate(samples)]
    tensors: dict[str, torch.Tensor | None] = {}
    for side in ("src", "tgt"):
        clouds = [getattr(s, f"{side}_xyz") for s in samples]
        normals = [getattr(s, f"{side}_normals") for s in samples]
        sizes = [len(c) for c in clouds]
        if len(set(sizes)) == 1:
            tensors[f"{side}_xyz"] = torch.from_numpy(np.stack(clouds).astype(np.float32))
            tensors[f"{side}_normals"] = _stack_optional(normals, f"{side}_normals")
            tensors[f"{side}_lengths"] = None
        else:
            tensors[f"{side}_xyz"] = _pad(clouds, sizes)
            _stack_optional([n if n is None else n[:1] for n in normals], f"{side}_normals")
            tensors[f"{side}_normals"] = None if normals[0] is None else _pad(normals, sizes)
            tensors[f"{side}_lengths"] = torch.tensor(sizes, dtype=torch.long)
    return PairBatch(
        gt_transform=_stack_optional([s.gt_transform for s in samples], "gt_transform"),
        meta=[dict(s.meta) for s in samples],
        **tensors,
    )
