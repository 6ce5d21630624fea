"""Tests for linereg.fps, the torch-free FPS core of linereg.pointcloud and the register default."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import torch

from linereg.fps import farthest_point_indices, farthest_point_subset
from linereg.paths import REPO_ROOT
from linereg.pointcloud import farthest_point_sampling


def _naive_fps(points: np.ndarray, count: int, start: int) -> np.ndarray:
    chosen = [start]
    nearest = np.linalg.norm(points - points[start], axis=1)
    for _ in range(count - 1):
        chosen.append(int(nearest.argmax()))
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def test_indices_are_farthest_point_order_and_the_same_as_pointcloud():
    points = np.random.default_rng(0).normal(size=(500, 3))
    np.testing.assert_array_equal(farthest_point_indices(points, 40, start_index=7), _naive_fps(points, 40, 7))
    bucket = farthest_point_indices(points, 64)
    assert len(np.unique(bucket)) == 64 and bucket.dtype == np.int64
    np.testing.assert_array_equal(farthest_point_sampling(points, 64), bucket)
    np.testing.assert_array_equal(farthest_point_sampling(torch.from_numpy(points), 64).numpy(), bucket)


def test_duplicated_points_fill_with_unused_indices_in_ascending_order():
    points = np.repeat(np.eye(3), 4, axis=0)  # 3 distinct points, 12 rows
    idx = farthest_point_indices(points, 5)
    assert sorted({tuple(p) for p in points[idx[:3]]}) == sorted({tuple(p) for p in np.eye(3)})
    assert len(np.unique(idx)) == 5
    np.testing.assert_array_equal(idx[3:], np.setdiff1d(np.arange(12), idx[:3])[:2])


def test_the_subset_keeps_the_input_order():
    points = np.random.default_rng(1).normal(size=(300, 3))
    subset = farthest_point_subset(points, 50)
    np.testing.assert_array_equal(subset, points[np.sort(farthest_point_indices(points, 50))])
    assert farthest_point_subset(points, None) is points and farthest_point_subset(points, 300) is points


def test_the_fps_core_does_not_import_torch():
    code = "import sys, linereg.fps; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, check=False).returncode == 0
