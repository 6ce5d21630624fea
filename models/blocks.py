"""Building blocks shared by the registration models (one home for each).

* :func:`make_norm` / :func:`shared_mlp`: normalisation layers and 1x1-convolution (or fully
  connected) stacks. ``norm="group"`` is the paper's choice (BatchNorm replaced by GroupNorm so
  that batches of 1-4 pairs train stably); ``"batch"`` reproduces the original DCP/FMR;
  ``"none"`` drops normalisation.
* :func:`check_pair_batch`: the input contract every model checks first.
* :func:`soft_correspondence_transform`: the rigid head of DCP and RPM-Net (a soft assignment
  turned into virtual target points, then :func:`linereg.procrustes.weighted_procrustes`),
  reporting failing samples by batch index.
* :func:`refine_translation`: nearest-neighbour translation steps after a model's estimate.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Literal

import torch
from torch import nn

from linereg.checks import check_points, check_same_batch
from linereg.knn import knn_points
from linereg.procrustes import weighted_procrustes
from linereg.se3 import transform_points
from linereg.structures import PairBatch

NormKind = Literal["group", "batch", "none"]
LayerKind = Literal["linear", "conv1d", "conv2d"]
NORM_KINDS: tuple[str, ...] = ("group", "batch", "none")

# Added to the assignment mass of a row before dividing by it (RPM-Net's epsilon).
ASSIGNMENT_EPS = 1e-5


def check_norm_kind(norm: str) -> None:
    """Raise ``ValueError`` unless ``norm`` is one of :data:`NORM_KINDS`."""
    if norm not in NORM_KINDS:
        raise ValueError(f"norm must be one of {NORM_KINDS}, got {norm!r}")


def make_norm(norm: NormKind, channels: int, groups: int, *, layer: LayerKind) -> nn.Module:
    """A normalisation layer for ``channels`` features.

    Args:
        norm: ``"group"`` (``nn.GroupNorm(groups, channels)``), ``"batch"`` (BatchNorm of the
            dimensionality ``layer`` needs) or ``"none"`` (identity).
        channels: number of feature channels.
        groups: GroupNorm group count (ignored otherwise); must divide ``channels``.
        layer: the layer the norm follows, ``"linear"`` and ``"conv1d"`` take ``(B, C[, N])``
            inputs, ``"conv2d"`` takes ``(B, C, H, W)``.

    Returns:
        The module.
    """
    check_norm_kind(norm)
    if norm == "none":
        return nn.Identity()
    if norm == "group":
        if channels % groups:
            raise ValueError(f"GroupNorm groups ({groups}) must divide the channels ({channels})")
        return nn.GroupNorm(groups, channels)
    return nn.BatchNorm2d(channels) if layer == "conv2d" else nn.BatchNorm1d(channels)


def resolve_groups(defaults: Sequence[int], override: int | None) -> tuple[int, ...]:
    """The per-layer GroupNorm group counts: the paper's ``defaults``, or ``override`` for all."""
    if override is None:
        return tuple(defaults)
    if override < 1:
        raise ValueError(f"groups must be a positive integer or None, got {override}")
    return (override,) * len(defaults)


def shared_mlp(
    in_channels: int,
    widths: Sequence[int],
    *,
    norm: NormKind,
    groups: Sequence[int],
    layer: LayerKind = "conv1d",
    bias: bool = True,
) -> nn.Sequential:
    """A stack of (linear or 1x1 convolution, norm, ReLU) blocks.

    Args:
        in_channels: input channels.
        widths: output channels of each block.
        norm: normalisation kind (see :func:`make_norm`).
        groups: GroupNorm group count of each block (same length as ``widths``).
        layer: ``"linear"`` for ``(B, C)`` inputs, ``"conv1d"`` for ``(B, C, N)``, ``"conv2d"``
            for ``(B, C, H, W)``.
        bias: whether the linear/convolution layers have a bias.

    Returns:
        ``nn.Sequential`` mapping ``in_channels`` to ``widths[-1]`` channels.
    """
    if len(groups) != len(widths):
        raise ValueError(f"groups needs one entry per layer ({len(widths)}), got {len(groups)}")
    blocks: list[nn.Module] = []
    for width, group in zip(widths, groups, strict=True):
        if layer == "linear":
            blocks.append(nn.Linear(in_channels, width, bias=bias))
        elif layer == "conv1d":
            blocks.append(nn.Conv1d(in_channels, width, 1, bias=bias))
        else:
            blocks.append(nn.Conv2d(in_channels, width, 1, bias=bias))
        blocks += [make_norm(norm, width, group, layer=layer), nn.ReLU()]
        in_channels = width
    return nn.Sequential(*blocks)


def check_pair_batch(
    batch: PairBatch,
    model_name: str,
    *,
    needs_normals: bool = False,
    equal_counts: bool = False,
    dtype: torch.dtype | None = None,
) -> None:
    """Check the parts of a :class:`PairBatch` a model reads.

    Args:
        batch: the input pairs.
        model_name: named in the messages.
        needs_normals: the model reads ``batch.src_normals`` and ``batch.tgt_normals``.
        equal_counts: the model needs as many source as target points.
        dtype: the dtype of the model's parameters, which the clouds must share (``None``: any).

    Raises:
        TypeError: ``batch`` is not a ``PairBatch``, or its clouds are not of ``dtype``.
        ValueError: bad point shapes, fewer than 2 points, NaN/Inf coordinates, mismatched
            batch sizes, missing or non-finite normals (when ``needs_normals``), different
            source/target counts (when ``equal_counts``), or ``*_lengths`` other than the padded
            size (ragged batches are not supported).
    """
    if not isinstance(batch, PairBatch):
        raise TypeError(f"{model_name} expects a PairBatch, got {type(batch).__name__}")
    # One point cannot define a rotation (and normalisation layers need two values per channel).
    check_points(batch.src_xyz, "batch.src_xyz", batched=True, min_points=2)
    check_points(batch.tgt_xyz, "batch.tgt_xyz", batched=True, min_points=2)
    check_same_batch(batch.src_xyz, batch.tgt_xyz, "batch.src_xyz", "batch.tgt_xyz")
    for side in ("src", "tgt"):
        points = getattr(batch, f"{side}_xyz")
        if dtype is not None and points.dtype != dtype and not torch.is_autocast_enabled(points.device.type):
            raise TypeError(
                f"{model_name}'s parameters are {dtype} but batch.{side}_xyz is {points.dtype}: convert the "
                f"clouds (tensor.to({dtype})) or the model (model.to({points.dtype}))"
            )
    for side in ("src", "tgt"):
        points = getattr(batch, f"{side}_xyz")
        lengths = getattr(batch, f"{side}_lengths")
        if lengths is not None and (
            lengths.shape != points.shape[:1] or lengths.is_floating_point() or bool((lengths != points.shape[1]).any())
        ):
            raise ValueError(
                f"{model_name} needs full clouds: batch.{side}_lengths must be None or {points.shape[1]} (the "
                f"padded size) for each of the {points.shape[0]} clouds, got {lengths.tolist()}; resample every "
                "cloud of the batch to the same number of points"
            )
        if not needs_normals:
            continue
        normals = getattr(batch, f"{side}_normals")
        if normals is None:
            raise ValueError(
                f"{model_name} needs normals, but batch.{side}_normals is None; datasets compute "
                "them with Open3D (open3d.geometry.PointCloud.estimate_normals) when a source "
                "has none: use a dataset that provides normals, or estimate them yourself"
            )
        if normals.shape != points.shape:
            raise ValueError(
                f"batch.{side}_normals must have the shape of batch.{side}_xyz "
                f"{tuple(points.shape)}, got {tuple(normals.shape)}"
            )
        check_points(normals, f"batch.{side}_normals", batched=True)
    if equal_counts and batch.src_xyz.shape[1] != batch.tgt_xyz.shape[1]:
        raise ValueError(
            f"{model_name} needs equal source and target point counts, got "
            f"{batch.src_xyz.shape[1]} and {batch.tgt_xyz.shape[1]}: resample both clouds to "
            "the same number of points"
        )


def soft_correspondence_transform(
    src: torch.Tensor,
    tgt: torch.Tensor,
    assignment: torch.Tensor,
    *,
    weighted: bool,
    model_name: str,
) -> torch.Tensor:
    """Rigid transform from a soft assignment of source points to target points.

    Every source point ``x_j`` gets a virtual target point and the transform is the Procrustes
    solution mapping ``x_j`` to it. With ``weighted`` (RPM-Net, rows of partial mass), the
    virtual point is ``sum_k A_jk y_k / (sum_k A_jk + eps)`` and ``x_j`` weighs
    ``sum_k A_jk``; otherwise (DCP, rows summing to one) it is ``sum_k A_jk y_k`` with uniform
    weights. Samples for which Procrustes is degenerate are named in a warning.

    Args:
        src: tensor of shape ``(B, J, 3)`` giving the source points.
        tgt: tensor of shape ``(B, K, 3)`` giving the target points.
        assignment: tensor of shape ``(B, J, K)`` giving non-negative matching weights.
        weighted: weigh each source point by its assignment mass.
        model_name: named in the warning.

    Returns:
        Tensor of shape ``(B, 4, 4)`` giving ``T_tgt_src``.
    """
    virtual_tgt = assignment @ tgt
    if weighted:
        mass = assignment.sum(-1)
        result = weighted_procrustes(src, virtual_tgt / (mass[..., None] + ASSIGNMENT_EPS), mass)
    else:
        result = weighted_procrustes(src, virtual_tgt)
    non_finite = ~torch.isfinite(assignment).flatten(1).all(dim=1)
    degenerate = ~result.valid & ~non_finite
    if bool(non_finite.any()):
        warnings.warn(
            f"{model_name}: the soft assignment is NaN/Inf for batch index(es) "
            f"{non_finite.nonzero().flatten().tolist()} (non-finite features or weights: extreme "
            "coordinates, or diverged parameters); their estimate falls back to the identity rotation",
            stacklevel=3,
        )
    if bool(degenerate.any()):
        warnings.warn(
            f"{model_name}: the rigid fit is degenerate for batch index(es) "
            f"{degenerate.nonzero().flatten().tolist()} (coincident or collinear points, or no "
            "assignment mass); their estimate falls back towards the identity rotation",
            stacklevel=3,
        )
    return result.transform


def refine_translation(
    src: torch.Tensor,
    tgt: torch.Tensor,
    transform: torch.Tensor,
    weights: torch.Tensor,
    iterations: int,
) -> torch.Tensor:
    """Refine the translation of ``transform`` by nearest-neighbour steps, keeping its rotation.

    Each step moves the transformed source by the ``weights``-weighted mean offset from every
    source point to its nearest target point (the translation-only step of point-to-point ICP).
    RPM-Net's soft assignment, when nearly uniform, turns weighted Procrustes into centroid
    alignment, whose translation is off by the distance between the centroids of a partial view
    and of the whole shape; these steps bring the translation back onto the surface
    (``docs/studies/translation-floor.md``). The nearest neighbours are not differentiable: the shift
    is a constant for autograd (gradients reach ``transform`` as if it were not refined).

    Args:
        src: tensor of shape ``(B, J, 3)`` giving the source points.
        tgt: tensor of shape ``(B, K, 3)`` giving the target points.
        transform: tensor of shape ``(B, 4, 4)`` giving the estimate ``T_tgt_src`` to refine.
        weights: tensor of shape ``(B, J)`` giving non-negative per-source-point weights (RPM-Net:
            the assignment's row mass); rows summing to zero count every point equally.
        iterations: number of steps (0 returns ``transform`` unchanged).

    Returns:
        Tensor of shape ``(B, 4, 4)``: ``transform`` with its translation refined.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    check_points(src, "src", batched=True)
    check_points(tgt, "tgt", batched=True)
    check_same_batch(src, tgt, "src", "tgt")
    if transform.shape != (src.shape[0], 4, 4):
        raise ValueError(f"transform must have shape ({src.shape[0]}, 4, 4), got {tuple(transform.shape)}")
    if weights.shape != src.shape[:2]:
        raise ValueError(f"weights must have shape {tuple(src.shape[:2])}, got {tuple(weights.shape)}")
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("weights must be finite and non-negative")
    with torch.no_grad():
        weights = torch.where(weights.sum(-1, keepdim=True) > 0, weights, torch.ones_like(weights))
        probabilities = weights / weights.sum(-1, keepdim=True)
        moved = transform_points(transform, src)
        shift = torch.zeros_like(moved[:, 0])
        for _ in range(iterations):
            shifted = moved + shift[:, None]
            nearest = knn_points(shifted, tgt, 1).idx[..., 0]
            matched = torch.gather(tgt, 1, nearest[..., None].expand(-1, -1, 3))
            shift = shift + (probabilities[..., None] * (matched - shifted)).sum(1)
    offset = torch.zeros_like(transform)
    offset[:, :3, 3] = shift.to(transform.dtype)
    return transform + offset
