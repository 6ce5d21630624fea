"""Farthest-point sampling of one ``(N, 3)`` numpy cloud (``fpsample``), without torch.

The one home of the FPS core: :func:`linereg.pointcloud.farthest_point_sampling` (arrays and
tensors, batched) and the torch-free ``register`` default (:mod:`linereg.registration.robust`)
both call :func:`farthest_point_indices`.
"""

from __future__ import annotations

import fpsample
import numpy as np


def farthest_point_indices(cloud: np.ndarray, n_samples: int, start_index: int | None = None) -> np.ndarray:
    """Indices ``(n_samples,)`` (int64, distinct, in sampling order) of FPS on ``cloud (N, 3)``.

    With ``start_index=None`` the bucket/KD-line variant of ``fpsample`` runs from a start point
    it picks itself (deterministic for a given cloud); an explicit ``start_index`` runs vanilla
    FPS from that point (fpsample's bucket variants ignore it). Once every remaining point
    coincides with a sample (duplicated points), the remaining slots take unused indices in
    ascending order. ``1 <= n_samples <= N`` is the caller's to check.
    """
    num_points = len(cloud)
    cloud = np.ascontiguousarray(cloud, dtype=np.float32)
    if start_index is not None or num_points < 64:
        idx = fpsample.fps_sampling(cloud, n_samples, start_index or 0)
    else:
        height = int(np.clip(round(np.log2(num_points) / 2 - 1.5), 1, 10))
        idx = fpsample.bucket_fps_kdline_sampling(cloud, n_samples, height, 0)
    return _unique_fill(idx.astype(np.int64), num_points)


def _unique_fill(idx: np.ndarray, num_points: int) -> np.ndarray:
    """Replace repeated indices (clouds with fewer distinct points than samples) by unused ones."""
    _, first = np.unique(idx, return_index=True)
    if len(first) == len(idx):
        return idx
    kept = idx[np.sort(first)]
    unused = np.setdiff1d(np.arange(num_points), kept)[: len(idx) - len(kept)]
    return np.concatenate([kept, unused])


def farthest_point_subset(points: np.ndarray, count: int | None) -> np.ndarray:
    """The FPS subset ``(count, 3)`` of ``points (N, 3)`` as a set: its points keep their order
    in ``points`` (all points if ``count`` is ``None`` or ``N <= count``).

    Keeping the input order makes an FPS of the subset (the register default's coarse subsets
    are FPS of its FPS subsets) start from the same point whether or not the cloud was subsampled.
    """
    if count is None or len(points) <= count:
        return points
    return points[np.sort(farthest_point_indices(points, count))]
