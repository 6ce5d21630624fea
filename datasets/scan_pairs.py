"""Real scan pairs finished like the paper's Real dataset: a random cap, normals, FPS and a joint
scaling into a cube (3DMatch, RGB-D sequences, room fragments, folders of scan pairs)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from linereg.datasets.protocol import float32_or_none, subsample
from linereg.pointcloud import estimate_normals, fit_into_cube, resample_indices, scale_transform
from linereg.structures import PairSample


@dataclass(frozen=True)
class ScanSettings:
    """How real scan pairs are finished (the paper's Real dataset: 2048 points in [-5, 5]^3).

    Attributes:
        num_points: points per cloud after FPS; ``None`` keeps every (capped) point.
        dense_points: random cap applied before normal estimation (bounds the cost on 300k-point
            fragments); ``None`` disables it.
        normal_k: neighbours for normal estimation.
        half_extent: pairs are scaled jointly into ``[-half_extent, half_extent]^3``;
            ``None`` keeps the original units.
    """

    num_points: int | None = 2048
    dense_points: int | None = 20000
    normal_k: int = 30
    half_extent: float | None = 5.0

    def __post_init__(self) -> None:
        for name in ("num_points", "dense_points", "half_extent"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"{name} must be positive or None, got {value}")


def finish_scan_pair(
    src_xyz: np.ndarray,
    tgt_xyz: np.ndarray,
    gt_transform: np.ndarray | None,
    settings: ScanSettings,
    rng: np.random.Generator,
    *,
    src_normals: np.ndarray | None = None,
    tgt_normals: np.ndarray | None = None,
    src_viewpoint: np.ndarray | None = None,
    tgt_viewpoint: np.ndarray | None = None,
    meta: dict[str, Any] | None = None,
) -> PairSample:
    """Cap, add normals, FPS and scale one real pair (labelled or not).

    Args:
        src_xyz: ``(N, 3)`` source points.
        tgt_xyz: ``(M, 3)`` target points.
        gt_transform: ``(4, 4)`` source-to-target transform in the input units, or ``None``.
        settings: sampling and scaling settings.
        rng: generator of this pair (random cap, repeats).
        src_normals: ``(N, 3)`` normals when the data has them; otherwise they are estimated.
        tgt_normals: ``(M, 3)`` likewise.
        src_viewpoint: sensor location used to orient estimated source normals (``None``:
            consistent orientation, slower).
        tgt_viewpoint: likewise for the target.
        meta: metadata; ``scale`` and ``center`` of the scaling are added.

    Returns:
        The finished :class:`PairSample` (``gt_transform`` expressed between the scaled clouds).
    """
    clouds = []
    for xyz, normals, viewpoint in (
        (src_xyz, src_normals, src_viewpoint),
        (tgt_xyz, tgt_normals, tgt_viewpoint),
    ):
        xyz = np.asarray(xyz, dtype=np.float64)
        if settings.dense_points is not None and len(xyz) > settings.dense_points:
            keep = resample_indices(len(xyz), settings.dense_points, rng)
            xyz, normals = xyz[keep], None if normals is None else normals[keep]
        if normals is None:
            normals = estimate_normals(xyz, k=min(settings.normal_k, len(xyz) - 1), orient_towards=viewpoint)
        idx = subsample(xyz, settings.num_points, rng)
        clouds.append((xyz[idx], np.asarray(normals)[idx]))
    (src_xyz, src_normals), (tgt_xyz, tgt_normals) = clouds
    meta = dict(meta or {})
    if settings.half_extent is not None:
        (src_xyz, tgt_xyz), center, scale = fit_into_cube(src_xyz, tgt_xyz, half_extent=settings.half_extent)
        if gt_transform is not None:
            gt_transform = scale_transform(gt_transform, center, scale)
        meta.update(scale=float(scale), center=[float(c) for c in center])
    return PairSample(
        src_xyz=float32_or_none(src_xyz),
        tgt_xyz=float32_or_none(tgt_xyz),
        src_normals=float32_or_none(src_normals),
        tgt_normals=float32_or_none(tgt_normals),
        gt_transform=float32_or_none(gt_transform),
        meta=meta,
    )
