"""Deep Closest Point (Wang & Solomon, ICCV 2019), with GroupNorm as in the paper's repository.

DCP embeds both clouds point-wise (DGCNN on a static kNN graph, or PointNet), optionally lets
each embedding attend to the other (DCP-v2's "pointer" transformer), matches every source point
to a soft average of target points (softmax of scaled feature dot products) and fits the rigid
transform with Procrustes (the original: WangYueFt/dcp, ``model.py``). One iteration, so
``transforms`` has one entry.

Differences from the original: GroupNorm instead of BatchNorm by default (the group counts of
the paper's repository, Dengzhi-USTC/A-robust-registration-loss,
``code/exps_deep_learning/dcp/model.py``), kNN on the input's device, ``nn.LayerNorm`` (biased
variance, eps inside the square root) instead of the original hand-written layer norm, and the
rigid fit through :func:`linereg.procrustes.weighted_procrustes` (float64, never NaN).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from linereg.knn import knn_points
from linereg.models.base import MODELS
from linereg.registry import keywords_of
from linereg.se3 import inverse
from linereg.structures import PairBatch, RegistrationOutput

from .blocks import (
    NormKind,
    check_norm_kind,
    check_pair_batch,
    resolve_groups,
    shared_mlp,
    soft_correspondence_transform,
)

# GroupNorm group counts of the paper's repository (code/exps_deep_learning/dcp/model.py).
DGCNN_GROUPS = (8, 8, 8, 16, 16)
POINTNET_GROUPS = (8, 8, 8, 16, 16)
DGCNN_EDGE_WIDTHS = (64, 64, 128, 256)
POINTNET_WIDTHS = (64, 64, 64, 128)


class DGCNNEmbedding(nn.Module):
    """Per-point DGCNN features on a static kNN graph of the input coordinates.

    Each point's ``k`` nearest neighbours (itself included) give edge features
    ``concat(x_neighbour, x_point)``; four 1x1-convolution blocks run on the edge tensor, the
    maximum over neighbours after each block is kept, and the concatenation is fused to
    ``emb_dims`` channels.
    """

    def __init__(self, emb_dims: int, k: int, norm: NormKind, groups: tuple[int, ...]) -> None:
        super().__init__()
        self.k = k
        in_channels = 6
        self.edge_blocks = nn.ModuleList()
        for width, group in zip(DGCNN_EDGE_WIDTHS, groups[:-1], strict=True):
            block = shared_mlp(in_channels, [width], norm=norm, groups=[group], layer="conv2d", bias=False)
            self.edge_blocks.append(block)
            in_channels = width
        self.fuse = shared_mlp(sum(DGCNN_EDGE_WIDTHS), [emb_dims], norm=norm, groups=groups[-1:], bias=False)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """Map points ``(B, N, 3)`` to features ``(B, emb_dims, N)``."""
        num_points = xyz.shape[1]
        with torch.no_grad():
            idx = knn_points(xyz, xyz, min(self.k, num_points)).idx
        batch_index = torch.arange(xyz.shape[0], device=xyz.device)[:, None, None]
        neighbours = xyz[batch_index, idx]
        centres = xyz[:, :, None, :].expand_as(neighbours)
        edges = torch.cat((neighbours, centres), dim=-1).permute(0, 3, 1, 2).contiguous()
        pooled = []
        for block in self.edge_blocks:
            edges = block(edges)
            pooled.append(edges.amax(dim=-1))
        return self.fuse(torch.cat(pooled, dim=1))


class PointNetEmbedding(nn.Module):
    """Per-point PointNet features (shared MLP, no pooling)."""

    def __init__(self, emb_dims: int, norm: NormKind, groups: tuple[int, ...]) -> None:
        super().__init__()
        widths = [*POINTNET_WIDTHS, emb_dims]
        self.mlp = shared_mlp(3, widths, norm=norm, groups=groups, bias=False)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        """Map points ``(B, N, 3)`` to features ``(B, emb_dims, N)``."""
        return self.mlp(xyz.transpose(1, 2))


class _FeedForward(nn.Sequential):
    """Position-wise feed-forward layer ``d -> ff -> d``."""

    def __init__(self, dims: int, ff_dims: int, dropout: float) -> None:
        super().__init__(nn.Linear(dims, ff_dims), nn.ReLU(), nn.Dropout(dropout), nn.Linear(ff_dims, dims))


class _EncoderBlock(nn.Module):
    """Pre-norm self-attention and feed-forward, each with a residual connection."""

    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.attention_norm = nn.LayerNorm(dims)
        self.attention = nn.MultiheadAttention(dims, heads, dropout=dropout, batch_first=True)
        self.feed_forward_norm = nn.LayerNorm(dims)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.attention_norm(x)
        x = x + self.attention(h, h, h, need_weights=False)[0]
        return x + self.feed_forward(self.feed_forward_norm(x))


class _DecoderBlock(nn.Module):
    """Pre-norm self-attention, attention to a memory, and feed-forward, with residuals."""

    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.self_attention_norm = nn.LayerNorm(dims)
        self.self_attention = nn.MultiheadAttention(dims, heads, dropout=dropout, batch_first=True)
        self.cross_attention_norm = nn.LayerNorm(dims)
        self.cross_attention = nn.MultiheadAttention(dims, heads, dropout=dropout, batch_first=True)
        self.feed_forward_norm = nn.LayerNorm(dims)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        h = self.self_attention_norm(x)
        x = x + self.self_attention(h, h, h, need_weights=False)[0]
        h = self.cross_attention_norm(x)
        x = x + self.cross_attention(h, memory, memory, need_weights=False)[0]
        return x + self.feed_forward(self.feed_forward_norm(x))


class PointerTransformer(nn.Module):
    """DCP-v2's attention module: each cloud's embedding is corrected by attending to the other.

    ``phi(x, y) = Decoder(x, memory=Encoder(y))`` with shared weights; the outputs are
    ``f_src + phi(f_src, f_tgt)`` and ``f_tgt + phi(f_tgt, f_src)``. No positional encoding.
    """

    def __init__(self, dims: int, heads: int, ff_dims: int, blocks: int, dropout: float) -> None:
        super().__init__()
        self.encoder = nn.ModuleList(_EncoderBlock(dims, heads, ff_dims, dropout) for _ in range(blocks))
        self.encoder_norm = nn.LayerNorm(dims)
        self.decoder = nn.ModuleList(_DecoderBlock(dims, heads, ff_dims, dropout) for _ in range(blocks))
        self.decoder_norm = nn.LayerNorm(dims)

    def _attend(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """Decoder(x, Encoder(context)) for features of shape ``(B, N, d)`` and ``(B, M, d)``."""
        memory = context
        for block in self.encoder:
            memory = block(memory)
        memory = self.encoder_norm(memory)
        for block in self.decoder:
            x = block(x, memory)
        return self.decoder_norm(x)

    def forward(self, src_features: torch.Tensor, tgt_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected features ``(B, N, d)`` and ``(B, M, d)``."""
        return (
            src_features + self._attend(src_features, tgt_features),
            tgt_features + self._attend(tgt_features, src_features),
        )


TRANSFORMER_OPTIONS = ("heads", "ff_dims", "blocks", "dropout")
"""The options of DCP-v2's pointer transformer (:class:`PointerTransformer`), which DCP-v1 has not."""


class DCP(nn.Module):
    """Deep Closest Point.

    Args:
        emb_dims: embedding width ``d``.
        k: neighbours of DGCNN's static graph.
        emb_nn: ``"dgcnn"`` (the published DCP) or ``"pointnet"``.
        pointer: ``"identity"`` (DCP-v1) or ``"transformer"`` (DCP-v2).
        heads, ff_dims, blocks, dropout: transformer settings (DCP-v2 only).
        cycle: compute the reverse (target -> source) transform with a second soft matching;
            otherwise it is the inverse of the forward estimate.
        norm: ``"group"`` (paper repository), ``"batch"`` (original DCP) or ``"none"``.
        groups: one GroupNorm group count for every layer, or ``None`` for the paper
            repository's per-layer counts.

    ``forward(batch)`` returns a :class:`RegistrationOutput` with one ``(B, 4, 4)``
    source -> target transform and ``extras``:

    * ``"transform_reverse"``: ``(B, 4, 4)`` target -> source transform;
    * ``"scores"``: ``(B, N, M)`` soft-pointer attention, rows summing to one.
    """

    def __init__(
        self,
        *,
        emb_dims: int = 512,
        k: int = 20,
        emb_nn: str = "dgcnn",
        pointer: str = "identity",
        heads: int = 4,
        ff_dims: int = 1024,
        blocks: int = 1,
        dropout: float = 0.0,
        cycle: bool = False,
        norm: NormKind = "group",
        groups: int | None = None,
    ) -> None:
        super().__init__()
        check_norm_kind(norm)
        if emb_nn == "dgcnn":
            self.embedding: nn.Module = DGCNNEmbedding(emb_dims, k, norm, resolve_groups(DGCNN_GROUPS, groups))
        elif emb_nn == "pointnet":
            self.embedding = PointNetEmbedding(emb_dims, norm, resolve_groups(POINTNET_GROUPS, groups))
        else:
            raise ValueError(f"emb_nn must be 'dgcnn' or 'pointnet', got {emb_nn!r}")
        if pointer == "transformer":
            self.pointer: PointerTransformer | None = PointerTransformer(emb_dims, heads, ff_dims, blocks, dropout)
        elif pointer == "identity":
            self.pointer = None
        else:
            raise ValueError(f"pointer must be 'identity' or 'transformer', got {pointer!r}")
        self.emb_dims = emb_dims
        self.cycle = cycle

    def _scores(self, query: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
        """Soft pointer ``softmax_k(<q_j, k_k> / sqrt(d))`` of shape ``(B, N, M)``."""
        logits = query @ key.transpose(1, 2) / math.sqrt(self.emb_dims)
        return torch.softmax(logits, dim=-1)

    def forward(self, batch: PairBatch) -> RegistrationOutput:
        check_pair_batch(batch, "DCP", dtype=next(self.parameters()).dtype)
        src, tgt = batch.src_xyz, batch.tgt_xyz
        src_features = self.embedding(src).transpose(1, 2)
        tgt_features = self.embedding(tgt).transpose(1, 2)
        if self.pointer is not None:
            src_features, tgt_features = self.pointer(src_features, tgt_features)
        scores = self._scores(src_features, tgt_features)
        T_tgt_src = soft_correspondence_transform(src, tgt, scores, weighted=False, model_name="DCP")
        if self.cycle:
            reverse_scores = self._scores(tgt_features, src_features)
            T_src_tgt = soft_correspondence_transform(tgt, src, reverse_scores, weighted=False, model_name="DCP")
        else:
            T_src_tgt = inverse(T_tgt_src)
        return RegistrationOutput(transforms=[T_tgt_src], extras={"transform_reverse": T_src_tgt, "scores": scores})


@MODELS.register("dcp_v1")
@keywords_of(DCP, without=("pointer", *TRANSFORMER_OPTIONS))
def dcp_v1(**options: Any) -> DCP:
    """DCP-v1: DGCNN embeddings matched directly (no attention); ``options``: :class:`DCP`'s but the pointer's."""
    return DCP(pointer="identity", **options)


@MODELS.register("dcp_v2")
@keywords_of(DCP, without=("pointer",))
def dcp_v2(**options: Any) -> DCP:
    """DCP-v2: DGCNN embeddings corrected by the pointer transformer; ``options``: :class:`DCP`'s."""
    return DCP(pointer="transformer", **options)
