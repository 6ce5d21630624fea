"""Tests for linereg.knn against a naive twin: every search path, padding, gradients, numpy index."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import linereg.knn as knn_module
from linereg.knn import KNN, NearestNeighbors, knn_distances, knn_gather, knn_points

PATHS = {
    "dense": {"linereg.knn.DENSE_MAX_PAIRS": 2**62},
    "kdtree": {"linereg.knn.DENSE_MAX_PAIRS": 0},
    "dense_chunked": {"linereg.knn.DENSE_MAX_PAIRS": 2**62, "linereg.knn._CPU_CHUNK_ELEMENTS": 7 * 90},
}


def _knn_naive(
    query: torch.Tensor,
    reference: torch.Tensor,
    k: int,
    query_lengths: torch.Tensor | None = None,
    reference_lengths: torch.Tensor | None = None,
) -> KNN:
    """Brute force, one query point at a time: squared distances sorted, padding as documented."""
    if query.ndim == 2:
        found = _knn_naive(query[None], reference[None], k)
        return KNN(found.dists[0], found.idx[0])
    batch, num_query = query.shape[:2]
    dists = torch.full((batch, num_query, k), torch.inf, dtype=query.dtype)
    idx = torch.full((batch, num_query, k), -1, dtype=torch.long)
    for b in range(batch):
        rows = num_query if query_lengths is None else int(query_lengths[b])
        size = reference.shape[1] if reference_lengths is None else int(reference_lengths[b])
        for i in range(rows):
            squared = ((reference[b, :size] - query[b, i]) ** 2).sum(-1)
            values, order = squared.sort()
            dists[b, i, : min(k, size)] = values[:k]
            idx[b, i, : min(k, size)] = order[:k]
    return KNN(dists, idx)


def _use_path(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    for name, value in PATHS[path].items():
        monkeypatch.setattr(name, value)


def _clouds(seed: int, query_shape: tuple[int, ...], reference_shape: tuple[int, ...]):
    generator = torch.Generator().manual_seed(seed)
    query = torch.rand(query_shape, generator=generator, dtype=torch.float64)
    return query, torch.rand(reference_shape, generator=generator, dtype=torch.float64)


@pytest.mark.parametrize("path", sorted(PATHS))
@pytest.mark.parametrize("batched", [True, False])
def test_knn_points_matches_naive(monkeypatch: pytest.MonkeyPatch, path: str, batched: bool) -> None:
    _use_path(monkeypatch, path)
    query, reference = _clouds(0, (3, 70, 3), (3, 90, 3)) if batched else _clouds(0, (70, 3), (90, 3))
    result = knn_points(query, reference, 6)
    expected = _knn_naive(query, reference, 6)
    assert result.idx.shape == (*query.shape[:-1], 6)
    assert result.idx.dtype == torch.long
    assert result.knn is None
    torch.testing.assert_close(result.idx, expected.idx, rtol=0, atol=0)
    torch.testing.assert_close(result.dists, expected.dists)


def test_knn_points_dense_and_kdtree_paths_agree_on_float32(monkeypatch: pytest.MonkeyPatch) -> None:
    generator = torch.Generator().manual_seed(9)
    # Coordinates on a coarse grid plus float32 noise: many neighbours nearly tie.
    query, reference = (
        (torch.randint(0, 8, (2, n, 3), generator=generator) / 8 + 1e-6 * torch.rand(2, n, 3, generator=generator))
        for n in (300, 400)
    )
    found = {}
    for path in ("dense", "kdtree"):
        _use_path(monkeypatch, path)
        found[path] = knn_points(query, reference, 8)
    torch.testing.assert_close(found["dense"].idx, found["kdtree"].idx, rtol=0, atol=0)
    torch.testing.assert_close(found["dense"].dists, found["kdtree"].dists, rtol=0, atol=0)


def test_knn_points_chooses_path_by_size(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    for name in ("_dense_indices", "_kdtree_indices"):
        search = getattr(knn_module, name)
        monkeypatch.setattr(
            knn_module, name, lambda *args, _search=search, _name=name: calls.append(_name) or _search(*args)
        )
    knn_points(*_clouds(1, (2, 16, 3), (2, 16, 3)))
    knn_points(*_clouds(1, (1, 300, 3), (1, 300, 3)))
    assert calls == ["_dense_indices", "_kdtree_indices"]


@pytest.mark.parametrize("path", sorted(PATHS))
def test_knn_points_padded_batch(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    _use_path(monkeypatch, path)
    query, reference = _clouds(2, (3, 40, 3), (3, 50, 3))
    query_lengths, reference_lengths = torch.tensor([40, 17, 0]), torch.tensor([50, 3, 9])
    result = knn_points(query, reference, 5, query_lengths, reference_lengths, return_nn=True)
    expected = _knn_naive(query, reference, 5, query_lengths, reference_lengths)
    torch.testing.assert_close(result.idx, expected.idx, rtol=0, atol=0)
    torch.testing.assert_close(result.dists, expected.dists)
    assert (result.idx[1, :17, 3:] == -1).all() and (result.idx[1, 17:] == -1).all()
    assert (result.knn[result.idx < 0] == 0).all()
    torch.testing.assert_close(result.knn[0], reference[0][result.idx[0]])


@pytest.mark.parametrize("path", ["dense", "kdtree"])
def test_knn_points_unsorted_holds_the_same_neighbours(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    _use_path(monkeypatch, path)
    query, reference = _clouds(3, (2, 30, 3), (2, 40, 3))
    result = knn_points(query, reference, 4, return_sorted=False)
    expected = _knn_naive(query, reference, 4)
    torch.testing.assert_close(result.idx.sort(dim=-1).values, expected.idx.sort(dim=-1).values, rtol=0, atol=0)


@pytest.mark.parametrize("path", ["dense", "kdtree"])
def test_knn_points_exclude_self(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    _use_path(monkeypatch, path)
    points = torch.rand(2, 60, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    result = knn_points(points, points, 4, exclude_self=True)
    expected = _knn_naive(points, points, 5)
    own = torch.arange(60)[None, :, None]
    assert not (result.idx == own).any()
    torch.testing.assert_close(result.idx, expected.idx[..., 1:], rtol=0, atol=0)
    torch.testing.assert_close(result.dists, expected.dists[..., 1:])


@pytest.mark.parametrize("path", ["dense", "kdtree"])
def test_knn_points_exclude_self_keeps_duplicates(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    _use_path(monkeypatch, path)
    base = torch.rand(10, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    points = torch.cat([base] * 5)
    result = knn_points(points, points, 2, exclude_self=True)
    own = torch.arange(50)[:, None]
    assert not (result.idx == own).any()
    torch.testing.assert_close(result.dists, torch.zeros(50, 2, dtype=torch.float64))
    assert ((result.idx % 10) == (own % 10)).all()


@pytest.mark.parametrize("path", ["dense", "kdtree"])
def test_knn_points_gradients_reach_both_clouds(monkeypatch: pytest.MonkeyPatch, path: str) -> None:
    _use_path(monkeypatch, path)
    query, reference = _clouds(5, (2, 20, 3), (2, 30, 3))
    query.requires_grad_(True)
    reference.requires_grad_(True)
    torch.autograd.gradcheck(lambda q, r: knn_points(q, r, 3).dists, (query, reference))
    torch.autograd.gradcheck(lambda q, r: knn_distances(q, r, 3), (query, reference))
    knn_points(query, reference, 3).dists.sum().backward()
    assert query.grad.abs().sum() > 0 and reference.grad.abs().sum() > 0


def test_knn_distances_are_euclidean_with_zero_gradient_at_coincident_points() -> None:
    query, reference = _clouds(6, (2, 25, 3), (2, 35, 3))
    torch.testing.assert_close(knn_distances(query, reference, 3), knn_points(query, reference, 3).dists.sqrt())
    points = torch.rand(12, 3, dtype=torch.float64, requires_grad=True)
    distances = knn_distances(points, points.detach().clone())
    assert (distances == 0).all()
    distances.sum().backward()
    assert torch.equal(points.grad, torch.zeros_like(points))


def test_knn_gather() -> None:
    features = torch.arange(24.0).reshape(2, 4, 3)
    idx = torch.tensor([[[3, -1]], [[0, 2]]])
    expected = torch.tensor([[[[9.0, 10, 11], [0, 0, 0]]], [[[12.0, 13, 14], [0, 0, 0]]]])
    torch.testing.assert_close(knn_gather(features, idx, lengths=torch.tensor([4, 2])), expected)
    with pytest.raises(ValueError, match="knn_gather needs"):
        knn_gather(features[0], idx)


def test_knn_points_errors() -> None:
    points = torch.rand(2, 5, 3)
    with pytest.raises(ValueError, match="k must be between 1 and 5"):
        knn_points(points, points, 6)
    with pytest.raises(ValueError, match="k must be between 1 and 4"):
        knn_points(points, points, 5, exclude_self=True)
    with pytest.raises(ValueError, match="k must be between"):
        knn_points(points, points, 0)
    with pytest.raises(ValueError, match="exclude_self=True requires query"):
        knn_points(points, points + 1, 2, exclude_self=True)
    with pytest.raises(ValueError, match="exclude_self=True requires query"):
        knn_points(points, points, 2, torch.tensor([5, 4]), torch.tensor([5, 5]), exclude_self=True)
    with pytest.raises(ValueError, match="both be batched or both unbatched"):
        knn_points(points, points[0], 2)
    with pytest.raises(ValueError, match="batch size"):
        knn_points(points, torch.rand(3, 5, 3), 2)
    with pytest.raises(ValueError, match=r"query must have shape"):
        knn_points(torch.rand(5, 2), torch.rand(5, 2), 1)
    with pytest.raises(ValueError, match="need batched clouds"):
        knn_points(points[0], points[0], 1, reference_lengths=torch.tensor([3]))
    with pytest.raises(ValueError, match="outside"):
        knn_points(points, points, 1, reference_lengths=torch.tensor([6, 2]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_knn_points_cuda_matches_cpu() -> None:
    query, reference = _clouds(7, (3, 500, 3), (3, 700, 3))
    lengths = torch.tensor([500, 321, 1])
    on_cpu = knn_points(query, reference, 5, lengths, lengths + 100)
    on_cuda = knn_points(query.cuda(), reference.cuda(), 5, lengths.cuda(), lengths.cuda() + 100)
    torch.testing.assert_close(on_cuda.idx.cpu(), on_cpu.idx, rtol=0, atol=0)
    torch.testing.assert_close(on_cuda.dists.cpu(), on_cpu.dists)


def test_nearest_neighbors_matches_naive() -> None:
    rng = np.random.default_rng(8)
    reference, query = rng.random((200, 3)), rng.random((4, 30, 3))
    index = NearestNeighbors(reference)
    assert len(index) == 200
    np.testing.assert_array_equal(index.points, reference)
    squared = ((query[..., None, :] - reference) ** 2).sum(-1)
    distances, indices = index.query(query)
    assert distances.shape == indices.shape == (4, 30)
    np.testing.assert_array_equal(indices, squared.argmin(-1))
    np.testing.assert_allclose(distances, np.sqrt(squared.min(-1)))
    distances, indices = index.query(query[0], k=3, workers=-1)
    np.testing.assert_array_equal(indices, np.argsort(squared[0], axis=-1)[:, :3])


def test_nearest_neighbors_answer_the_same_on_every_core() -> None:
    """A large query runs on all cores by default; the answer equals one thread's, bit for bit."""
    rng = np.random.default_rng(9)
    index, query = NearestNeighbors(rng.random((2048, 3))), rng.random((7, 2048, 3))
    for k, bound in ((1, 0.05), (4, np.inf)):
        default, single = (
            index.query(query, k=k, distance_upper_bound=bound),
            index.query(query, k=k, workers=1, distance_upper_bound=bound),
        )
        for ours, theirs in zip(default, single, strict=True):
            np.testing.assert_array_equal(ours, theirs)


def test_nearest_neighbors_upper_bound_marks_missing() -> None:
    index = NearestNeighbors(np.zeros((3, 3)))
    distances, indices = index.query(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 5.0]]), distance_upper_bound=1.0)
    np.testing.assert_array_equal(distances, [0.5, np.inf])
    np.testing.assert_array_equal(indices, [0, 3])
    with pytest.raises(ValueError, match="points must have shape"):
        NearestNeighbors(np.zeros((2, 3, 3)))
