"""Fragment pairs fused from an RGB-D sequence (datasets/fragments.py) and their ``fragments`` pair source."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from linereg.datasets import fragments as fragments_module
from linereg.datasets.benchmark_pairs import PAIR_SOURCES
from linereg.datasets.fragments import (
    FragmentSettings,
    bin_index,
    draw_pairs,
    fragment_pairs,
    overlap_ratio,
    refine_pose,
)
from linereg.pointcloud import estimate_normals

SEQUENCE = "rgbd/7scenes_first_half/data"
# 10 fragments of 3 depth frames (frames 100..218), coarse enough to build in a few seconds.
SMALL = {
    "frames_per_fragment": 3,
    "fragment_stride": 6,
    "frame_range": [100, 220],
    "pixel_stride": 4,
    "voxel_size": 0.02,
    "overlap_points": 4000,
}
SMALL_BINS = [[0.1, 0.3], [0.3, 0.5], [0.5, 1.0]]
SMALL_LABELS = ["[0.1, 0.3)", "[0.3, 0.5)", "[0.5, 1]"]


def test_overlap_ratio_counts_source_points_near_the_target():
    rng = np.random.default_rng(0)
    target = rng.uniform(0, 1, (4000, 3))
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, [0.1, 0.2, 0.3]
    source = (target - transform[:3, 3]) @ rotation  # p_target = transform @ p_source
    assert overlap_ratio(source, target, transform) == 1.0
    far = transform.copy()
    far[0, 3] += 5.0
    assert overlap_ratio(source, target, far) == 0.0
    half = np.concatenate([source[:2000], source[:2000] + np.array([0.0, 0.0, 10.0])])
    assert overlap_ratio(half, target, transform) == pytest.approx(0.5)
    assert overlap_ratio(half, target, transform, max_points=1000) == pytest.approx(0.5, abs=0.08)


def test_bins_are_half_open_except_the_last():
    bins = [[0.2, 0.3], [0.3, 0.5], [0.5, 0.8]]
    assert [bin_index(v, bins) for v in (0.1, 0.2, 0.2999, 0.3, 0.5, 0.8, 0.81)] == [None, 0, 0, 1, 2, 2, None]


def test_draw_pairs_is_balanced_seeded_and_warns_when_a_bin_runs_short():
    overlaps = np.array([0.25] * 3 + [0.4] * 10 + [0.6] * 10 + [0.05, 0.9])
    bins = [[0.2, 0.3], [0.3, 0.5], [0.5, 0.8]]
    with pytest.warns(UserWarning, match=r"\[0.2, 0.3\) holds 3 candidate pairs, fewer than the 4"):
        drawn = draw_pairs(overlaps, bins, 12, seed=1)
    assert [b for _, b in drawn] == [0] * 3 + [1] * 4 + [2] * 4
    assert all(bin_index(overlaps[c], bins) == b for c, b in drawn)
    assert len({c for c, _ in drawn}) == len(drawn)
    assert draw_pairs(overlaps, bins[1:], 6, seed=1) == draw_pairs(overlaps, bins[1:], 6, seed=1)
    assert draw_pairs(overlaps, bins[1:], 6, seed=1) != draw_pairs(overlaps, bins[1:], 6, seed=2)
    with pytest.raises(ValueError, match=r"overlap bin \[0.5, 0.2\]"):
        draw_pairs(overlaps, [[0.5, 0.2]], 6, seed=1)


def _room(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` random points on a floor, two walls and a box of a 3 m x 2 m room."""
    u = rng.uniform(0, 1, (count, 2))
    parts = np.array_split(u, 4)
    floor = np.column_stack([3 * parts[0][:, 0], 2 * parts[0][:, 1], np.zeros(len(parts[0]))])
    back = np.column_stack([3 * parts[1][:, 0], np.full(len(parts[1]), 2.0), 2 * parts[1][:, 1]])
    side = np.column_stack([np.zeros(len(parts[2])), 2 * parts[2][:, 0], 2 * parts[2][:, 1]])
    box = np.column_stack([1 + 0.5 * parts[3][:, 0], 0.5 + 0.4 * parts[3][:, 1], np.full(len(parts[3]), 0.6)])
    return np.concatenate([floor, back, side, box])


def test_refine_pose_recovers_a_perturbed_pose_between_independent_samplings():
    rng = np.random.default_rng(0)
    target = _room(rng, 40000)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    truth[:3, 3] = [0.3, -0.1, 0.2]
    source = (_room(rng, 40000) - truth[:3, 3]) @ truth[:3, :3]  # p_target = truth @ p_source
    start = truth.copy()
    start[:3, :3] = Rotation.from_rotvec(np.radians([1.0, -1.0, 1.5])).as_matrix() @ truth[:3, :3]
    start[:3, 3] += [0.02, -0.03, 0.01]
    normals = estimate_normals(target, k=20, orient_towards=np.array([1.5, 1.0, 1.0]))

    refined = refine_pose(source, target, normals, start, voxel_size=0.01)

    rotation_gap = np.degrees(Rotation.from_matrix(refined[:3, :3].T @ truth[:3, :3]).magnitude())
    assert rotation_gap < 0.1 and np.linalg.norm(refined[:3, 3] - truth[:3, 3]) < 0.003
    assert np.degrees(Rotation.from_matrix(start[:3, :3].T @ truth[:3, :3]).magnitude()) > 1.5


def test_settings_are_checked():
    with pytest.raises(ValueError, match="frames_per_fragment must be >= 1"):
        FragmentSettings(frames_per_fragment=0)
    with pytest.raises(ValueError, match="frame_range"):
        FragmentSettings(frame_range=(10, 10))


def _small_pairs(shared_data, cache_dir, *, seed: int, ground_truth: str):
    """Six pairs of the small fragments, read from ``cache_dir``."""
    return fragment_pairs(
        shared_data / SEQUENCE,
        pairs=6,
        seed=seed,
        bins=SMALL_BINS,
        cache_dir=cache_dir,
        settings=FragmentSettings(**{**SMALL, "frame_range": tuple(SMALL["frame_range"])}),
        ground_truth=ground_truth,
    )


@pytest.fixture(scope="module")
def small_pairs(shared_data, tmp_path_factory):
    """Six pairs of the small fragments (built once into a temporary cache)."""
    cache = tmp_path_factory.mktemp("fragment_cache")
    config = {"name": "fragments", "root": SEQUENCE, "pairs": 6, "bins": SMALL_BINS, "cache_dir": str(cache), **SMALL}
    return PAIR_SOURCES.build(config, seed=0), config


@pytest.mark.shared_data
def test_fragment_ground_truth_maps_the_source_onto_the_target(small_pairs):
    pairs, _ = small_pairs
    assert [pair.meta["overlap_bin"] for pair in pairs] == [label for label in SMALL_LABELS for _ in range(2)]
    for pair in pairs:
        meta = pair.meta
        assert meta["source"] == "fragments" and meta["scene"] == "7scenes_first_half/data"
        assert 0.0 <= meta["overlap"] <= 1.0
        assert SMALL_LABELS[bin_index(meta["overlap"], SMALL_BINS)] == meta["overlap_bin"]
        assert meta["src_frames"][0] > meta["tgt_frames"][1]  # no common frame
        assert len(pair.src_xyz) > 5000 and pair.src_normals.shape == pair.src_xyz.shape
        assert meta["ground_truth"] == "refined"
        assert meta["gt_correction_deg"] < 5.0 and meta["gt_correction_m"] < 0.2
        gt = pair.gt_transform.astype(np.float64)
        moved = pair.src_xyz @ gt[:3, :3].T + gt[:3, 3]
        tree = cKDTree(pair.tgt_xyz)
        distances = tree.query(moved)[0]
        unmoved = tree.query(pair.src_xyz.astype(np.float64))[0]
        assert np.mean(distances < 0.0375) >= meta["overlap"] - 0.03  # overlaps are the tracking pose's
        assert np.mean(distances < 0.0375) > np.mean(unmoved < 0.0375) + 0.02
        if meta["overlap"] >= 0.5:
            assert np.median(distances) < 0.03  # most source points lie on the target


@pytest.mark.shared_data
def test_fragments_are_read_back_from_the_cache(small_pairs, shared_data, monkeypatch):
    pairs, config = small_pairs

    def no_build(*args, **kwargs):
        raise AssertionError("the fragments should come from the cache")

    monkeypatch.setattr(fragments_module, "build_fragments", no_build)
    monkeypatch.setattr(fragments_module, "refine_pose", no_build)
    again = PAIR_SOURCES.build(config, seed=0)
    assert [p.meta for p in again] == [p.meta for p in pairs]
    np.testing.assert_array_equal(again[0].src_xyz, pairs[0].src_xyz)
    other = _small_pairs(shared_data, config["cache_dir"], seed=1, ground_truth="tracking")
    assert [p.meta["overlap_bin"] for p in other] == [p.meta["overlap_bin"] for p in pairs]
    assert [p.meta["src_fragment"] for p in other] != [p.meta["src_fragment"] for p in pairs]


@pytest.mark.shared_data
def test_the_refined_ground_truth_aligns_better_than_the_tracking_pose(small_pairs, shared_data):
    pairs, config = small_pairs
    tracking = _small_pairs(shared_data, config["cache_dir"], seed=0, ground_truth="tracking")
    voxel = SMALL["voxel_size"]
    for refined, tracked in zip(pairs, tracking, strict=True):
        assert tracked.meta["ground_truth"] == "tracking" and tracked.meta["gt_correction_m"] == 0.0
        gt = tracked.gt_transform.astype(np.float64)
        moved = tracked.src_xyz @ gt[:3, :3].T + gt[:3, 3]
        overlap = np.mean(cKDTree(tracked.tgt_xyz).query(moved)[0] < 0.0375)
        assert overlap == pytest.approx(tracked.meta["overlap"], abs=0.03)
        rotation = tracked.gt_transform[:3, :3].astype(np.float64)
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
        np.testing.assert_array_equal(refined.src_xyz, tracked.src_xyz)
        tree = cKDTree(refined.tgt_xyz)
        close = [
            np.mean(tree.query(refined.src_xyz @ gt[:3, :3].T + gt[:3, 3])[0] < 1.5 * voxel)
            for gt in (refined.gt_transform.astype(np.float64), tracked.gt_transform.astype(np.float64))
        ]
        assert close[0] >= close[1] - 0.005
    with pytest.raises(ValueError, match="ground_truth must be one of"):
        fragment_pairs(shared_data / SEQUENCE, pairs=3, bins=SMALL_BINS, ground_truth="gps")
