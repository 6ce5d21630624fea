"""RPM-Net (Yew & Lee, CVPR 2020): iterative soft matching with learned annealing.

Per iteration (the original: yewzijian/RPMNet, ``src/models/rpmnet.py``): the source, moved
by the previous estimate (detached), and the target are described by point-pair features (PPF)
of their local neighbourhoods; a parameter network predicts the annealing parameters ``beta``
and ``alpha`` from both clouds; Sinkhorn normalisation with a slack row and column turns the
feature distances into a partial assignment; weighted Procrustes maps the *original* source
onto the assignment-weighted target points. Estimates are absolute (not composed); training
runs 2 iterations, evaluation 5. The target never moves, so its features are computed once per
forward (the original recomputed them every iteration; values and gradients are the same).

Memory and speed. The PPF network's per-neighbour activations ``(B, N, K, 2 * feature_dim)``
dominate RPM-Net's cost (:class:`PPFFeatures`). They are kept channels-last, so the 1x1
convolutions are plain matrix products and GroupNorm runs PyTorch's fused NHWC kernel. In
training (``self.training``) the shared MLP runs on all points at once, as the original. In
evaluation mode, when the widest activations would exceed ``chunk_bytes``, it runs over chunks
of centre points and never holds a per-neighbour tensor wider than the 10 raw channels
(computed once) beyond about ``chunk_bytes``:

* GroupNorm needs statistics over all points, so each layer's statistics are gathered in one
  pass over the chunks (float64 sums) before the next layer runs;
* the max over neighbours is taken *before* the last GroupNorm + ReLU, which is exact because
  both are monotone per channel (increasing where the GroupNorm scale is positive, decreasing
  where it is negative): the maximum of the normalised activations is the normalised maximum,
  or minimum, of the raw ones. The last layer therefore needs a single pass.

Both paths agree up to rounding. In training, ``checkpoint=True`` recomputes the shared MLP
during the backward pass instead of storing its activations (less memory, more compute).

The neighbourhood is a ball query built on :func:`linereg.knn.knn_points`: the ``K`` nearest
points (the centre itself first), with every neighbour farther than ``radius`` replaced by the
centre's own index. Unlike the original (the first ``K`` points in index order inside the
ball), an over-full ball keeps its ``K`` *nearest* points.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute_in_backward

from linereg.knn import knn_points
from linereg.models.base import MODELS
from linereg.se3 import transform_normals, transform_points
from linereg.structures import PairBatch, RegistrationOutput

from .blocks import (
    NormKind,
    check_pair_batch,
    make_norm,
    refine_translation,
    resolve_groups,
    shared_mlp,
    soft_correspondence_transform,
)

# Widths and GroupNorm counts of the original (yewzijian/RPMNet, src/models/rpmnet.py and feature_nets.py).
PREPOOL_HIDDEN = (96, 96)
FEATURE_GROUPS = 8
PARAM_POINTWISE_WIDTHS = (64, 64, 64, 128, 1024)
PARAM_POINTWISE_GROUPS = (8, 8, 8, 8, 16)
PARAM_HEAD_WIDTHS = (512, 256)
PARAM_HEAD_GROUPS = (16, 16)
RAW_FEATURE_CHANNELS = 10


def ball_query(xyz: torch.Tensor, radius: float, num_neighbors: int) -> torch.Tensor:
    """Neighbour indices of every point within ``radius``, padded with the point's own index.

    Args:
        xyz: tensor of shape ``(B, N, 3)`` giving the points (every point is a centre).
        radius: ball radius (Euclidean).
        num_neighbors: neighbours per point ``K``; clipped to ``N``.

    Returns:
        Long tensor of shape ``(B, N, min(K, N))``: the nearest points in ascending distance
        (the centre itself included), slots of points outside the ball hold the centre's index.
    """
    with torch.no_grad():
        found = knn_points(xyz, xyz, min(num_neighbors, xyz.shape[1]), return_nn=True)
        distances = (xyz[:, :, None] - found.knn).norm(dim=-1)
        centres = torch.arange(xyz.shape[1], device=xyz.device)[None, :, None]
        return torch.where(distances <= radius, found.idx, centres)


def _plane_norm(vectors: torch.Tensor) -> torch.Tensor:
    """Euclidean norm of vectors stored as planes ``(3, ...)``; zero gradient at zero."""
    squared = vectors.square().sum(0)
    positive = squared > 0
    return torch.where(positive, torch.where(positive, squared, 1.0).sqrt(), 0.0)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between vectors stored as planes ``(3, ...)``: ``atan2(|a x b|, a.b)``, 0 if zero."""
    return torch.atan2(_plane_norm(torch.linalg.cross(a, b, dim=0)), (a * b).sum(0))


def _raw_features(xyz_planes: torch.Tensor, normal_planes: torch.Tensor, neighbors: torch.Tensor) -> torch.Tensor:
    """Raw features ``(B, N, K, 10)`` of every point's neighbourhood (contiguous).

    Per (centre, neighbour): centre ``xyz`` (3), ``d = p_neighbour - p_centre`` (3),
    ``angle(n_centre, d)``, ``angle(n_neighbour, d)``, ``angle(n_centre, n_neighbour)``, ``|d|``.
    Points and normals come as coordinate planes ``(3, B, N)``, which keeps the small
    reductions over coordinates element-wise.
    """
    batch_index = torch.arange(xyz_planes.shape[1], device=xyz_planes.device)[:, None, None]
    centre_xyz = xyz_planes[..., None]
    centre_normals = normal_planes[..., None]
    offsets = xyz_planes[:, batch_index, neighbors] - centre_xyz
    neighbour_normals = normal_planes[:, batch_index, neighbors]
    centre_normals = centre_normals.expand_as(offsets)
    features = torch.cat(
        (
            centre_xyz.expand_as(offsets),
            offsets,
            torch.stack(
                (
                    _angle(centre_normals, offsets),
                    _angle(neighbour_normals, offsets),
                    _angle(centre_normals, neighbour_normals),
                    _plane_norm(offsets),
                )
            ),
        )
    )
    return features.permute(1, 2, 3, 0).contiguous()


class _ChannelSums(NamedTuple):
    """Per-sample, per-channel running sums (float64) of a GroupNorm input and their count."""

    count: int
    total: torch.Tensor
    squares: torch.Tensor


def _accumulate(sums: _ChannelSums | None, values: torch.Tensor) -> _ChannelSums:
    """Add the channels-last ``values (B, P, K, C)`` to the running sums."""
    count = values.shape[1] * values.shape[2]
    total = values.sum(dim=(1, 2)).double()
    squares = values.square().sum(dim=(1, 2)).double()
    if sums is None:
        return _ChannelSums(count, total, squares)
    return _ChannelSums(sums.count + count, sums.total + total, sums.squares + squares)


class _Affine(NamedTuple):
    """A per-sample, per-channel affine map ``y * scale + shift`` (a GroupNorm, resolved)."""

    scale: torch.Tensor
    shift: torch.Tensor


def _group_norm_affine(sums: _ChannelSums, norm: nn.GroupNorm) -> _Affine:
    """The ``(B, C)`` scale and shift equivalent to ``norm`` for inputs with these ``sums``."""
    batch = sums.total.shape[0]
    per_group = norm.num_channels // norm.num_groups
    count = sums.count * per_group
    mean = sums.total.reshape(batch, norm.num_groups, per_group).sum(-1) / count
    mean_square = sums.squares.reshape(batch, norm.num_groups, per_group).sum(-1) / count
    variance = (mean_square - mean.square()).clamp_min(0.0)
    rstd = torch.rsqrt(variance + norm.eps).to(norm.weight.dtype)
    scale = rstd.repeat_interleave(per_group, dim=1) * norm.weight
    shift = norm.bias - mean.to(scale.dtype).repeat_interleave(per_group, dim=1) * scale
    return _Affine(scale, shift)


def _apply(values: torch.Tensor, affine: _Affine | None) -> torch.Tensor:
    """``values (B, ..., C) * scale + shift`` broadcast over the middle axes (``None``: as is)."""
    if affine is None:
        return values
    shape = (values.shape[0],) + (1,) * (values.ndim - 2) + (values.shape[-1],)
    return values * affine.scale.reshape(shape) + affine.shift.reshape(shape)


def _pooled_activation(highest: torch.Tensor, lowest: torch.Tensor, affine: _Affine | None) -> torch.Tensor:
    """``max_k ReLU(norm(y))`` from ``max_k y`` and ``min_k y`` of shape ``(B, N, C)``."""
    if affine is None:
        return F.relu(highest)
    increasing = affine.scale[:, None, :] >= 0
    return F.relu(_apply(torch.where(increasing, highest, lowest), affine))


def _channels_last_norm(values: torch.Tensor, norm: nn.Module) -> torch.Tensor:
    """Apply ``norm`` (GroupNorm or identity) to channels-last ``values (B, N, K, C)``."""
    if not isinstance(norm, nn.GroupNorm):
        return values
    # The permuted view is a channels-last NCHW tensor: PyTorch's fused NHWC kernel applies.
    normalised = F.group_norm(values.permute(0, 3, 1, 2), norm.num_groups, norm.weight, norm.bias, norm.eps)
    return normalised.permute(0, 2, 3, 1)


class PPFFeatures(nn.Module):
    """RPM-Net's "early fusion" feature network: PPF of ball neighbourhoods -> unit features.

    Per point: raw features of its ball neighbours (:func:`_raw_features`), a shared MLP
    ``10 -> 96 -> 96 -> 2 f`` (GroupNorm + ReLU each), max over neighbours, then
    ``2 f -> 2 f -> f`` (GroupNorm + ReLU) and a final linear ``f -> f``; L2-normalised.

    Args:
        feature_dim: output width ``f``.
        radius: ball-query radius (the original assumes clouds scaled to the unit sphere).
        num_neighbors: neighbours per ball.
        norm: ``"group"`` or ``"none"`` (per-sample statistics are needed for the chunked
            evaluation, so ``"batch"`` is not offered).
        groups: GroupNorm group count of every layer.
        chunk_bytes: outside training, the approximate size of the largest per-neighbour
            activation tensor held at once.
        checkpoint: in training, recompute the per-neighbour activations during the backward
            pass instead of storing them (``torch.utils.checkpoint``): less memory, one more
            forward pass of the shared MLP.
    """

    def __init__(
        self,
        feature_dim: int,
        radius: float,
        num_neighbors: int,
        norm: NormKind,
        groups: int,
        chunk_bytes: int,
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        if norm not in ("group", "none"):
            raise ValueError(
                f"RPM-Net supports norm 'group' or 'none' (its chunked feature network needs "
                f"per-sample statistics), got {norm!r}"
            )
        self.radius = radius
        self.num_neighbors = num_neighbors
        self.chunk_bytes = chunk_bytes
        self.checkpoint = checkpoint
        widths = (*PREPOOL_HIDDEN, 2 * feature_dim)
        inputs = (RAW_FEATURE_CHANNELS, *widths[:-1])
        self.prepool = nn.ModuleList(nn.Linear(i, o) for i, o in zip(inputs, widths, strict=True))
        self.prepool_norms = nn.ModuleList(make_norm(norm, width, groups, layer="linear") for width in widths)
        self.postpool = nn.Sequential(
            shared_mlp(2 * feature_dim, [2 * feature_dim, feature_dim], norm=norm, groups=[groups] * 2),
            nn.Conv1d(feature_dim, feature_dim, 1),
        )

    def _pool_whole(self, raw: torch.Tensor) -> torch.Tensor:
        """Pooled ``(B, N, 2 f)`` activations from raw features ``(B, N, K, 10)`` in one go."""
        values = raw
        for linear, norm in zip(self.prepool, self.prepool_norms, strict=True):
            values = F.relu(_channels_last_norm(linear(values), norm))
        return values.amax(dim=2)

    def _pool_chunked(self, raw: torch.Tensor, step: int) -> torch.Tensor:
        """Pooled ``(B, N, 2 f)`` activations, ``step`` centres at a time, a pass per layer."""
        affines: list[_Affine | None] = []
        last = len(self.prepool) - 1
        for depth, norm in enumerate(self.prepool_norms):
            is_group_norm = isinstance(norm, nn.GroupNorm)
            if depth < last and not is_group_norm:
                affines.append(None)
                continue
            sums: _ChannelSums | None = None
            highest, lowest = [], []
            for start in range(0, raw.shape[1], step):
                values = raw[:, start : start + step]
                for layer in range(depth):
                    values = F.relu(_apply(self.prepool[layer](values), affines[layer]))
                values = self.prepool[depth](values)
                if is_group_norm:
                    sums = _accumulate(sums, values)
                if depth == last:
                    highest.append(values.amax(dim=2))
                    lowest.append(values.amin(dim=2))
            affines.append(None if sums is None else _group_norm_affine(sums, norm))
        return _pooled_activation(torch.cat(highest, dim=1), torch.cat(lowest, dim=1), affines[-1])

    def forward(self, xyz: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """Unit features ``(B, N, f)`` of points ``(B, N, 3)`` with normals ``(B, N, 3)``."""
        neighbors = ball_query(xyz, self.radius, self.num_neighbors)
        raw = _raw_features(xyz.permute(2, 0, 1), normals.permute(2, 0, 1), neighbors)
        batch, num_points, k, _ = raw.shape
        widest = max(linear.out_features for linear in self.prepool)
        step = max(1, self.chunk_bytes // (batch * k * widest * raw.element_size()))
        if self.training and self.checkpoint and torch.is_grad_enabled():
            pooled = recompute_in_backward(self._pool_whole, raw, use_reentrant=False)
        elif self.training or step >= num_points:
            pooled = self._pool_whole(raw)
        else:
            pooled = self._pool_chunked(raw, step)
        features = self.postpool(pooled.transpose(1, 2)).transpose(1, 2)
        return F.normalize(features, dim=-1)


class ParameterNet(nn.Module):
    """Predicts the annealing parameters ``(beta, alpha)`` of a pair.

    Both clouds, tagged with a fourth coordinate (0 source, 1 target), go through a shared MLP
    ``4 -> 64 -> 64 -> 64 -> 128 -> 1024``, a global max pool and ``1024 -> 512 -> 256 -> 2``;
    ``softplus`` keeps both positive.
    """

    def __init__(self, norm: NormKind, groups: int | None) -> None:
        super().__init__()
        self.pointwise = shared_mlp(
            4,
            PARAM_POINTWISE_WIDTHS,
            norm=norm,
            groups=resolve_groups(PARAM_POINTWISE_GROUPS, groups),
        )
        self.head = nn.Sequential(
            shared_mlp(
                PARAM_POINTWISE_WIDTHS[-1],
                PARAM_HEAD_WIDTHS,
                norm=norm,
                groups=resolve_groups(PARAM_HEAD_GROUPS, groups),
                layer="linear",
            ),
            nn.Linear(PARAM_HEAD_WIDTHS[-1], 2),
        )

    def forward(self, src: torch.Tensor, tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``beta`` and ``alpha``, each ``(B,)``, for clouds ``(B, J, 3)`` and ``(B, K, 3)``."""
        tagged = torch.cat((F.pad(src, (0, 1), value=0.0), F.pad(tgt, (0, 1), value=1.0)), dim=1)
        pooled = self.pointwise(tagged.transpose(1, 2)).amax(dim=-1)
        beta, alpha = F.softplus(self.head(pooled)).unbind(dim=-1)
        return beta, alpha


def log_sinkhorn(log_affinity: torch.Tensor, iterations: int, *, slack: bool = True) -> torch.Tensor:
    """Sinkhorn normalisation in log space, optionally with a slack row and column.

    With ``slack``, a zero (log) row and column are appended; each iteration normalises the
    real rows over all columns (slack column included), then the real columns over all rows
    (slack row included), so points may stay unmatched. The slack entries are dropped at the
    end.

    Args:
        log_affinity: tensor of shape ``(B, J, K)`` giving log matching affinities.
        iterations: number of (row, column) normalisation rounds.
        slack: add the slack row and column.

    Returns:
        Tensor of shape ``(B, J, K)`` giving the log assignment.
    """
    log_alpha = F.pad(log_affinity, (0, 1, 0, 1)) if slack else log_affinity
    rows = slice(None, -1) if slack else slice(None)
    for _ in range(iterations):
        real_rows = log_alpha[:, rows]
        real_rows = real_rows - torch.logsumexp(real_rows, dim=2, keepdim=True)
        log_alpha = torch.cat((real_rows, log_alpha[:, -1:]), dim=1) if slack else real_rows
        real_cols = log_alpha[:, :, rows]
        real_cols = real_cols - torch.logsumexp(real_cols, dim=1, keepdim=True)
        log_alpha = torch.cat((real_cols, log_alpha[:, :, -1:]), dim=2) if slack else real_cols
    return log_alpha[:, rows, rows]


def _squared_feature_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances ``(B, J, K)`` between features ``(B, J, f)`` and ``(B, K, f)``."""
    squared = a.square().sum(-1)[:, :, None] + b.square().sum(-1)[:, None, :] - 2 * a @ b.mT
    return squared.clamp_min(0.0)


class RPMNet(nn.Module):
    """RPM-Net.

    Args:
        feature_dim: width of the PPF features.
        radius: ball-query radius.
        num_neighbors: neighbours per ball.
        train_iters: iterations in training mode.
        test_iters: iterations in evaluation mode.
        sinkhorn_iters: Sinkhorn rounds per iteration.
        slack: Sinkhorn slack row/column (outlier handling).
        norm: ``"group"`` (the original) or ``"none"``.
        groups: one GroupNorm group count for every layer, or ``None`` for the original's.
        chunk_bytes: memory bound of the chunked feature network (see the module docstring).
        checkpoint: recompute the feature network's per-neighbour activations in the backward
            pass (saves most of the training memory for about a third more compute).
        translation_refinement: outside training, the number of nearest-neighbour translation
            steps (:func:`linereg.models.blocks.refine_translation`, weighted by the last
            assignment's row mass; the rotation is kept) applied to the last iterate, whose
            refined copy is appended as one more estimate. 0 (the original) appends nothing. A
            nearly uniform assignment makes the translation that of centroid alignment, off by
            the offset between a partial view's centroid and the whole shape's
            (``docs/studies/translation-floor.md``).

    ``forward(batch)`` needs ``batch.src_normals`` and ``batch.tgt_normals`` and returns a
    :class:`RegistrationOutput` with one ``(B, 4, 4)`` source -> target estimate per iteration
    (then the refined one, with ``translation_refinement``; the caller picks one:
    :func:`linereg.registration.iterates.select_iterate`) and ``extras``:

    * ``"perm_matrices"``: list per iteration of ``(B, J, K)`` assignments (slack removed);
    * ``"beta"``, ``"alpha"``: lists per iteration of ``(B,)`` annealing parameters.
    """

    def __init__(
        self,
        *,
        feature_dim: int = 96,
        radius: float = 0.3,
        num_neighbors: int = 64,
        train_iters: int = 2,
        test_iters: int = 5,
        sinkhorn_iters: int = 5,
        slack: bool = True,
        norm: NormKind = "group",
        groups: int | None = None,
        chunk_bytes: int = 4 * 2**20,
        checkpoint: bool = False,
        translation_refinement: int = 0,
    ) -> None:
        super().__init__()
        if train_iters < 1 or test_iters < 1:
            raise ValueError(f"train_iters and test_iters must be >= 1, got {train_iters} and {test_iters}")
        if translation_refinement < 0:
            raise ValueError(f"translation_refinement must be >= 0, got {translation_refinement}")
        self.features = PPFFeatures(
            feature_dim,
            radius,
            num_neighbors,
            norm,
            FEATURE_GROUPS if groups is None else groups,
            chunk_bytes,
            checkpoint,
        )
        self.parameter_net = ParameterNet(norm, groups)
        self.train_iters = train_iters
        self.test_iters = test_iters
        self.sinkhorn_iters = sinkhorn_iters
        self.slack = slack
        self.translation_refinement = translation_refinement

    def forward(self, batch: PairBatch) -> RegistrationOutput:
        check_pair_batch(batch, "RPM-Net", needs_normals=True, dtype=next(self.parameters()).dtype)
        src, tgt = batch.src_xyz, batch.tgt_xyz
        src_normals, tgt_normals = batch.src_normals, batch.tgt_normals
        tgt_features = self.features(tgt, tgt_normals)
        T_tgt_src = torch.eye(4, dtype=src.dtype, device=src.device).expand(src.shape[0], 4, 4)
        transforms, perm_matrices, betas, alphas = [], [], [], []
        for _ in range(self.train_iters if self.training else self.test_iters):
            previous = T_tgt_src.detach()
            moved = transform_points(previous, src)
            moved_normals = transform_normals(previous, src_normals)
            beta, alpha = self.parameter_net(moved, tgt)
            src_features = self.features(moved, moved_normals)
            distances = _squared_feature_distances(src_features, tgt_features)
            log_affinity = -beta[:, None, None] * (distances - alpha[:, None, None])
            perm = torch.exp(log_sinkhorn(log_affinity, self.sinkhorn_iters, slack=self.slack))
            T_tgt_src = soft_correspondence_transform(src, tgt, perm, weighted=True, model_name="RPM-Net")
            transforms.append(T_tgt_src)
            perm_matrices.append(perm)
            betas.append(beta)
            alphas.append(alpha)
        if self.translation_refinement and not self.training:
            mass = perm_matrices[-1].sum(-1)
            transforms.append(refine_translation(src, tgt, transforms[-1], mass, self.translation_refinement))
        extras = {"perm_matrices": perm_matrices, "beta": betas, "alpha": alphas}
        return RegistrationOutput(transforms=transforms, extras=extras)


# The paper's defaults are the constructor's: the class itself is the builder.
MODELS.register("rpmnet")(RPMNet)
