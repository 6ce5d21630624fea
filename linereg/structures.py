"""The small typed contracts that flow between datasets, models, losses and the train loop.

Convention (everywhere in linereg): column vectors and ``tgt ≈ R @ src + t``; a 4x4
``transform`` maps source coordinates to target coordinates (``T_tgt_src``).

::

    datasets -> PairSample (numpy, one pair) -> collate -> PairBatch (torch, batched)
    models(PairBatch) -> RegistrationOutput -> losses(output, batch) -> LossOutput
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import torch


@dataclass
class PairSample:
    """One registration problem, as numpy arrays.

    Attributes:
        src_xyz: ``(N, 3)`` float32 source points.
        tgt_xyz: ``(M, 3)`` float32 target points.
        src_normals: ``(N, 3)`` float32 unit normals, or ``None``.
        tgt_normals: ``(M, 3)`` float32 unit normals, or ``None``.
        gt_transform: ``(4, 4)`` float32 source-to-target transform, or ``None`` when unlabeled.
        meta: free-form metadata (ids, source file, scale, ...).
    """

    src_xyz: np.ndarray
    tgt_xyz: np.ndarray
    src_normals: np.ndarray | None = None
    tgt_normals: np.ndarray | None = None
    gt_transform: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class PairBatch:
    """A batch of registration problems, as torch tensors.

    Attributes:
        src_xyz: ``(B, N, 3)`` source points (padded when ``src_lengths`` is given).
        tgt_xyz: ``(B, M, 3)`` target points (padded when ``tgt_lengths`` is given).
        src_normals: ``(B, N, 3)`` or ``None``.
        tgt_normals: ``(B, M, 3)`` or ``None``.
        gt_transform: ``(B, 4, 4)`` source-to-target transforms, or ``None`` (unlabeled data).
        src_lengths: ``(B,)`` long number of valid source points, or ``None`` (all valid).
        tgt_lengths: ``(B,)`` long number of valid target points, or ``None`` (all valid).
        meta: list of ``B`` metadata dicts.
    """

    src_xyz: torch.Tensor
    tgt_xyz: torch.Tensor
    src_normals: torch.Tensor | None = None
    tgt_normals: torch.Tensor | None = None
    gt_transform: torch.Tensor | None = None
    src_lengths: torch.Tensor | None = None
    tgt_lengths: torch.Tensor | None = None
    meta: list[dict[str, Any]] = field(default_factory=list)

    @property
    def batch_size(self) -> int:
        return self.src_xyz.shape[0]

    def to(self, device: torch.device | str) -> PairBatch:
        """A copy with every tensor moved to ``device``."""
        moved = {
            f.name: (
                getattr(self, f.name).to(device)
                if isinstance(getattr(self, f.name), torch.Tensor)
                else getattr(self, f.name)
            )
            for f in fields(self)
        }
        return PairBatch(**moved)

    def without_ground_truth(self) -> PairBatch:
        """A copy with ``gt_transform`` removed (what an unsupervised loss is allowed to see)."""
        return replace(self, gt_transform=None)


@dataclass
class RegistrationOutput:
    """What every registration model returns.

    Attributes:
        transforms: list with one ``(B, 4, 4)`` source-to-target estimate per iteration; the
            last entry is the final answer.
        extras: model-specific named tensors (Sinkhorn matrices, reverse transforms, decoder
            reconstructions, ...). Keys are documented by each model.
    """

    transforms: list[torch.Tensor]
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def transform(self) -> torch.Tensor:
        """The final ``(B, 4, 4)`` estimate."""
        return self.transforms[-1]


@dataclass
class LossOutput:
    """What every loss returns.

    Attributes:
        total: scalar tensor to back-propagate.
        terms: named scalar tensors that make up ``total`` (already weighted), for logging.
        stats: named floats describing the evaluation (e.g. line hit counts), for logging.
    """

    total: torch.Tensor
    terms: dict[str, torch.Tensor] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
