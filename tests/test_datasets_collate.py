"""collate_pairs: stacking, padding with lengths, resampling to a fixed count."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from linereg.datasets.collate import collate_pairs
from linereg.structures import PairSample


def _pair(num_src: int, num_tgt: int, *, normals: bool = True, gt: bool = True, index: int = 0):
    """A random pair with the given point counts."""
    rng = np.random.default_rng(index)
    src = rng.normal(size=(num_src, 3)).astype(np.float32)
    tgt = rng.normal(size=(num_tgt, 3)).astype(np.float32)
    unit = lambda a: (a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)  # noqa: E731
    return PairSample(
        src_xyz=src,
        tgt_xyz=tgt,
        src_normals=unit(src) if normals else None,
        tgt_normals=unit(tgt) if normals else None,
        gt_transform=np.eye(4, dtype=np.float32) if gt else None,
        meta={"index": index},
    )


def test_equal_counts_stack_without_lengths():
    batch = collate_pairs([_pair(64, 80, index=i) for i in range(3)])
    assert batch.src_xyz.shape == (3, 64, 3) and batch.tgt_xyz.shape == (3, 80, 3)
    assert batch.src_xyz.dtype == torch.float32
    assert batch.src_normals.shape == (3, 64, 3)
    assert batch.gt_transform.shape == (3, 4, 4)
    assert batch.src_lengths is None and batch.tgt_lengths is None
    assert [m["index"] for m in batch.meta] == [0, 1, 2]


def test_different_counts_are_padded_with_lengths():
    samples = [_pair(50, 70, index=0), _pair(64, 70, index=1)]
    batch = collate_pairs(samples)
    assert batch.src_xyz.shape == (2, 64, 3)
    assert batch.src_lengths.tolist() == [50, 64]
    assert batch.tgt_lengths is None
    torch.testing.assert_close(batch.src_xyz[0, :50], torch.from_numpy(samples[0].src_xyz))
    assert torch.all(batch.src_xyz[0, 50:] == 0)
    torch.testing.assert_close(batch.src_normals[1], torch.from_numpy(samples[1].src_normals))


def test_num_points_gives_equal_counts_by_fps_or_repeats():
    samples = [_pair(300, 40, index=0), _pair(128, 128, index=1)]
    batch = collate_pairs(samples, num_points=128)
    assert batch.src_xyz.shape == batch.tgt_xyz.shape == (2, 128, 3)
    assert batch.src_lengths is None and batch.tgt_lengths is None
    # Every resampled point is an original point, with its own normal.
    source = samples[0].src_xyz
    rows = [np.flatnonzero((source == p).all(axis=1))[0] for p in batch.src_xyz[0].numpy()]
    assert len(set(rows)) == 128
    np.testing.assert_array_equal(batch.src_normals[0].numpy(), samples[0].src_normals[rows])
    # Fewer points than asked: all of them, then repeats.
    assert len(np.unique(batch.tgt_xyz[0].numpy(), axis=0)) == 40
    torch.testing.assert_close(batch.src_xyz[1], torch.from_numpy(samples[1].src_xyz))
    again = collate_pairs(samples, num_points=128)
    torch.testing.assert_close(batch.tgt_xyz, again.tgt_xyz)


def test_unlabeled_batches_have_no_ground_truth():
    batch = collate_pairs([_pair(10, 10, gt=False, normals=False, index=i) for i in range(2)])
    assert batch.gt_transform is None and batch.src_normals is None


def test_mixed_labels_or_normals_are_rejected():
    with pytest.raises(ValueError, match=r"gt_transform is present for some samples.*\[1\]"):
        collate_pairs([_pair(10, 10), _pair(10, 10, gt=False)])
    with pytest.raises(ValueError, match="src_normals is present for some samples"):
        collate_pairs([_pair(10, 12), _pair(11, 12, normals=False)])


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="empty"):
        collate_pairs([])
    with pytest.raises(TypeError, match=r"samples\[0\] must be a PairSample"):
        collate_pairs([{"src_xyz": np.zeros((3, 3))}])
    bad = _pair(10, 10)
    bad.src_normals = bad.src_normals[:5]
    with pytest.raises(ValueError, match=r"samples\[0\].src_normals must match"):
        collate_pairs([bad])
    with pytest.raises(ValueError, match="num_points must be >= 1"):
        collate_pairs([_pair(10, 10)], num_points=0)


def test_works_as_a_dataloader_collate_fn():
    samples = [_pair(100 + i, 90, index=i) for i in range(6)]
    loader = DataLoader(samples, batch_size=3, collate_fn=functools.partial(collate_pairs, num_points=64))
    batches = list(loader)
    assert len(batches) == 2 and batches[0].src_xyz.shape == (3, 64, 3)
