"""Nearest neighbours: the one k-nearest-neighbour search shared by losses, models and solvers.

* :func:`knn_points` (torch) follows pytorch3d's ``knn_points``: padded batches ``(B, N, 3)``
  with optional per-cloud lengths, squared Euclidean distances differentiable with respect to
  both clouds, and the neighbours themselves on request. Small clouds are searched with one
  dense distance matrix; large clouds on the CPU with a KD-tree per cloud
  (``scipy.spatial.cKDTree``), elsewhere with chunked brute force.
* :func:`knn_distances` gives Euclidean (not squared) distances, with a zero gradient at
  coincident points where the square root of ``knn_points``'s distances would give NaN.
* :func:`knn_gather` gathers features of the neighbours found (pytorch3d's ``knn_gather``).
* :class:`NearestNeighbors` (numpy) is an index built once and queried many times, for
  solvers that match the same cloud again and again.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from linereg.checks import check_lengths, check_points, check_same_batch

if TYPE_CHECKING:
    import torch

__all__ = ["KNN", "NearestNeighbors", "knn_distances", "knn_gather", "knn_points"]

# A cloud pair with at most this many query x reference distances is searched densely on the
# CPU (faster than building a KD-tree up to about 128 x 128 points); larger pairs use a KD-tree.
DENSE_MAX_PAIRS = 2**14
# Distances in one block of the brute-force search: on the CPU 2**20 (float64 differences,
# 24 MB), elsewhere 2**24 (64 MB of float32).
_CPU_CHUNK_ELEMENTS = 2**20
_CHUNK_ELEMENTS = 2**24
# KD-tree queries of at least this many query x k entries run on all cores: a tree built per
# query (knn_points), and a tree built once and queried many times (NearestNeighbors).
_PARALLEL_QUERY_MIN = 50_000
_PARALLEL_INDEX_QUERY_MIN = 8192


class KNN(NamedTuple):
    """Result of :func:`knn_points`.

    Attributes:
        dists: tensor of shape ``(..., N, K)`` giving the squared Euclidean distance from
            each query point to its neighbours (ascending when sorted), differentiable with
            respect to both clouds; ``inf`` where there is no neighbour (see ``idx``).
        idx: long tensor of shape ``(..., N, K)`` giving the index of each neighbour in the
            reference cloud; ``-1`` for rows of padded query points and for slots beyond a
            reference cloud's length.
        knn: tensor of shape ``(..., N, K, 3)`` giving the neighbours (zeros where ``idx`` is
            ``-1``) when ``return_nn=True``, else ``None``.
    """

    dists: torch.Tensor
    idx: torch.Tensor
    knn: torch.Tensor | None = None


def knn_points(
    query: torch.Tensor,
    reference: torch.Tensor,
    k: int = 1,
    query_lengths: torch.Tensor | None = None,
    reference_lengths: torch.Tensor | None = None,
    return_sorted: bool = True,
    *,
    return_nn: bool = False,
    exclude_self: bool = False,
) -> KNN:
    """The ``k`` nearest reference points of every query point.

    Indices are searched without gradient: densely (all ``query x reference`` distances and
    ``topk``, in blocks of at most ``2**20`` distances on the CPU and ``2**24`` elsewhere)
    when a cloud pair has at most :data:`DENSE_MAX_PAIRS` distances or the clouds are not on
    the CPU, else with one ``scipy.spatial.cKDTree`` per cloud. On the CPU both paths compare
    squared distances in float64. Distances are then recomputed from the gathered points, so
    that gradients reach both clouds. Ties between equally distant neighbours may be broken
    either way.

    Args:
        query: tensor of shape ``(B, N, 3)`` or ``(N, 3)`` giving the query points.
        reference: tensor of shape ``(B, M, 3)`` or ``(M, 3)`` (batched like ``query``)
            giving the points searched.
        k: neighbours per query point: ``1 <= k <= M`` (``k <= M - 1`` with
            ``exclude_self``); slots beyond a cloud's ``reference_lengths`` hold ``-1``.
        query_lengths: optional ``(B,)`` integer number of valid query points per cloud
            (batched input only); rows past it hold ``idx = -1`` and ``dists = inf``.
        reference_lengths: optional ``(B,)`` integer number of valid reference points per
            cloud (batched input only); padded points are never neighbours.
        return_sorted: neighbours in ascending distance; ``False`` allows any order (the
            KD-tree and ``exclude_self`` still sort).
        return_nn: also return the neighbours' coordinates in ``KNN.knn``.
        exclude_self: ``query`` must be ``reference`` (same lengths); each point is left out
            of its own neighbour list (exactly one entry is dropped per row, so duplicated
            points still find their duplicates).

    Returns:
        :class:`KNN` with ``dists`` and ``idx`` of shape ``(B, N, k)`` or ``(N, k)``.

    Raises:
        TypeError: non-float inputs.
        ValueError: bad shapes, mismatched batching or devices, lengths on unbatched input or
            outside ``[0, N]`` / ``[0, M]``, ``k`` out of range, or ``exclude_self`` with two
            different clouds.
    """
    import torch

    query, reference, unbatched = _check_clouds(query, reference)
    if unbatched and (query_lengths is not None or reference_lengths is not None):
        raise ValueError("query_lengths and reference_lengths need batched clouds (B, N, 3)")
    query_lengths = check_lengths(query_lengths, "query_lengths", query.shape[0], query.shape[1], min_length=0)
    reference_lengths = check_lengths(
        reference_lengths, "reference_lengths", reference.shape[0], reference.shape[1], min_length=0
    )
    if exclude_self and not _same_cloud(query, reference, query_lengths, reference_lengths):
        raise ValueError("exclude_self=True requires query to be the reference cloud itself")
    num_ref = reference.shape[1]
    searched = k + 1 if exclude_self else k
    if k < 1 or searched > num_ref:
        limit = f"{num_ref - 1} (exclude_self drops each point itself)" if exclude_self else num_ref
        raise ValueError(f"k must be between 1 and {limit} for {num_ref} reference points, got {k}")

    with torch.no_grad():
        if query.device.type == "cpu" and query.shape[1] * num_ref > DENSE_MAX_PAIRS:
            idx = _kdtree_indices(query, reference, searched, query_lengths, reference_lengths)
        else:
            ordered = return_sorted or exclude_self
            idx = _dense_indices(query, reference, searched, query_lengths, reference_lengths, ordered)
        if exclude_self:
            idx = _drop_self(idx)
    found = knn_gather(reference, idx)
    dists = (query[:, :, None, :] - found).square().sum(-1).masked_fill(idx < 0, torch.inf)
    result = KNN(dists, idx, found if return_nn else None)
    if unbatched:
        return KNN(*(None if value is None else value[0] for value in result))
    return result


def knn_distances(
    query: torch.Tensor,
    reference: torch.Tensor,
    k: int = 1,
    *,
    exclude_self: bool = False,
) -> torch.Tensor:
    """Euclidean distances from every query point to its ``k`` nearest reference points.

    The norm of the difference to each neighbour found by :func:`knn_points`: differentiable
    with respect to both clouds, with a zero (not NaN) gradient where the points coincide.

    Args:
        query: tensor of shape ``(B, N, 3)`` or ``(N, 3)``.
        reference: tensor of shape ``(B, M, 3)`` or ``(M, 3)``, batched like ``query``.
        k: neighbours per query point, as in :func:`knn_points`.
        exclude_self: as in :func:`knn_points`.

    Returns:
        Tensor of shape ``(B, N, k)`` or ``(N, k)``, ascending along the last dimension.
    """
    found = knn_points(query, reference, k, return_nn=True, exclude_self=exclude_self)
    return (query.unsqueeze(-2) - found.knn).norm(dim=-1)


def knn_gather(x: torch.Tensor, idx: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
    """Gather the rows of ``x`` that :func:`knn_points` found (pytorch3d's ``knn_gather``).

    Args:
        x: tensor of shape ``(B, M, D)`` (reference points or their features).
        idx: long tensor of shape ``(B, N, K)`` with values in ``[0, M)`` or ``-1``.
        lengths: optional ``(B,)`` number of valid rows of each ``x``; indices at or past it
            count as ``-1``.

    Returns:
        Tensor of shape ``(B, N, K, D)``; zeros where the index is ``-1``.
    """
    import torch

    if x.ndim != 3 or idx.ndim != 3 or x.shape[0] != idx.shape[0]:
        raise ValueError(f"knn_gather needs x (B, M, D) and idx (B, N, K), got {tuple(x.shape)} and {tuple(idx.shape)}")
    missing = idx < 0
    if lengths is not None:
        missing = missing | (idx >= lengths.to(idx.device)[:, None, None])
    batch = torch.arange(x.shape[0], device=x.device)[:, None, None]
    gathered = x[batch, idx.masked_fill(missing, 0)]
    if not bool(missing.any()):
        return gathered
    return gathered.masked_fill(missing[..., None], 0)


class NearestNeighbors:
    """A KD-tree over one numpy cloud, built once and queried many times.

    A thin wrapper of ``scipy.spatial.cKDTree`` that keeps its conventions: distances are
    Euclidean, and a neighbour not found within ``distance_upper_bound`` has distance ``inf``
    and index ``len(points)``.

    Args:
        points: array of shape ``(M, 3)``.
    """

    def __init__(self, points: np.ndarray) -> None:
        check_points(points, "points", batched=False)
        self._tree = cKDTree(points)

    @property
    def points(self) -> np.ndarray:
        """Float64 array of shape ``(M, 3)``: the indexed points."""
        return self._tree.data

    def __len__(self) -> int:
        return self._tree.n

    def query(
        self,
        points: np.ndarray,
        k: int = 1,
        *,
        distance_upper_bound: float = np.inf,
        workers: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest indexed points of every query point.

        Args:
            points: array of shape ``(..., 3)`` giving the query points.
            k: neighbours per query point.
            distance_upper_bound: neighbours farther than this are not returned.
            workers: threads (``-1``: all cores); ``None``: all cores from 8192 query points x
                ``k`` on, else one (threads cost more than they save on small queries). The answer
                does not depend on it.

        Returns:
            ``(distances, indices)``: arrays of shape ``(...)`` for ``k=1``, else
            ``(..., k)``, sorted by distance.
        """
        if workers is None:
            workers = -1 if np.size(points) // 3 * k >= _PARALLEL_INDEX_QUERY_MIN else 1
        return self._tree.query(points, k=k, distance_upper_bound=distance_upper_bound, workers=workers)


def _check_clouds(query: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Validate two clouds; return them batched and whether they came unbatched."""
    check_points(query, "query")
    check_points(reference, "reference")
    if query.ndim != reference.ndim:
        raise ValueError(
            f"query and reference must both be batched or both unbatched, got shapes "
            f"{tuple(query.shape)} and {tuple(reference.shape)}"
        )
    if query.device != reference.device:
        raise ValueError(f"query and reference must be on the same device, got {query.device} and {reference.device}")
    unbatched = query.ndim == 2
    if unbatched:
        query, reference = query.unsqueeze(0), reference.unsqueeze(0)
    check_same_batch(query, reference, "query", "reference")
    return query, reference, unbatched


def _same_cloud(
    query: torch.Tensor,
    reference: torch.Tensor,
    query_lengths: torch.Tensor | None,
    reference_lengths: torch.Tensor | None,
) -> bool:
    """Whether ``query`` and ``reference`` are one cloud (same points and lengths)."""
    import torch

    if query.shape != reference.shape or not torch.equal(query.detach(), reference.detach()):
        return False
    if query_lengths is None or reference_lengths is None:
        return query_lengths is None and reference_lengths is None
    return torch.equal(query_lengths, reference_lengths)


def _kdtree_indices(
    query: torch.Tensor,
    reference: torch.Tensor,
    k: int,
    query_lengths: torch.Tensor | None,
    reference_lengths: torch.Tensor | None,
) -> torch.Tensor:
    """``(B, N, k)`` neighbour indices from one cKDTree per cloud, ``-1`` where none."""
    import torch

    batch, num_query = query.shape[:2]
    query_np = query.detach().numpy()
    reference_np = reference.detach().numpy()
    idx = np.full((batch, num_query, k), -1, dtype=np.int64)
    for b in range(batch):
        rows = num_query if query_lengths is None else int(query_lengths[b])
        size = reference.shape[1] if reference_lengths is None else int(reference_lengths[b])
        if rows == 0 or size == 0:
            continue
        # Worker threads cost more than they save on small queries.
        workers = -1 if rows * k >= _PARALLEL_QUERY_MIN else 1
        _, found = cKDTree(reference_np[b, :size]).query(query_np[b, :rows], k=k, workers=workers)
        found = found.reshape(rows, k)
        idx[b, :rows] = np.where(found < size, found, -1)
    return torch.from_numpy(idx)


def _dense_indices(
    query: torch.Tensor,
    reference: torch.Tensor,
    k: int,
    query_lengths: torch.Tensor | None,
    reference_lengths: torch.Tensor | None,
    return_sorted: bool,
) -> torch.Tensor:
    """``(B, N, k)`` neighbour indices from brute-force distances in blocks, ``-1`` where none."""
    import torch

    batch, num_query = query.shape[:2]
    num_ref = reference.shape[1]
    columns = torch.arange(num_ref, device=query.device)
    chunk = _CPU_CHUNK_ELEMENTS if query.device.type == "cpu" else _CHUNK_ELEMENTS
    rows_at_once = max(1, chunk // num_ref)
    batch_step = max(1, rows_at_once // num_query)
    query_step = min(num_query, rows_at_once)
    idx = torch.empty((batch, num_query, k), dtype=torch.long, device=query.device)
    for b0 in range(0, batch, batch_step):
        b1 = b0 + batch_step
        for p0 in range(0, num_query, query_step):
            p1 = p0 + query_step
            dists = _block_distances(query[b0:b1, p0:p1], reference[b0:b1])
            if reference_lengths is not None:
                padded = columns >= reference_lengths[b0:b1, None, None].to(query.device)
                dists = dists.masked_fill(padded, torch.inf)
            nearest = dists.topk(k, dim=-1, largest=False, sorted=return_sorted)
            idx[b0:b1, p0:p1] = nearest.indices.masked_fill(nearest.values == torch.inf, -1)
    if query_lengths is not None:
        rows = torch.arange(num_query, device=query.device)
        idx = idx.masked_fill((rows >= query_lengths[:, None].to(query.device))[..., None], -1)
    return idx


def _block_distances(query: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """``(b, n, m)`` distances that order the neighbours: on the CPU squared and in float64, as
    the KD-tree computes them (so both paths agree), elsewhere Euclidean in the clouds' dtype."""
    import torch

    if query.device.type == "cpu":
        return (query.double()[:, :, None, :] - reference.double()[:, None, :, :]).square().sum(-1)
    return torch.cdist(query, reference, compute_mode="donot_use_mm_for_euclid_dist")


def _drop_self(idx: torch.Tensor) -> torch.Tensor:
    """Remove each point's own index from its ``k + 1`` neighbours (else the last one)."""
    import torch

    num_points = idx.shape[1]
    own = torch.arange(num_points, device=idx.device)[None, :, None]
    drop = idx == own
    drop[..., -1] |= ~drop.any(dim=-1)
    return idx[~drop].reshape(idx.shape[0], num_points, idx.shape[2] - 1)
