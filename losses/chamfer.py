"""Chamfer distance (CD) and Welsch-Chamfer (CD-W), paper Eq. (2) and supplementary.

Nearest neighbours come from :func:`linereg.knn.knn_distances` (a KD-tree for large clouds on
the CPU, chunked brute force otherwise), so large clouds never materialise an ``N x M`` matrix;
distances are gathered afterwards and are differentiable w.r.t. both clouds.
"""

from __future__ import annotations

import math
import numbers

import torch

from linereg.checks import check_lengths, check_points, check_same_batch
from linereg.knn import knn_distances

from .base import LOSSES, AlignmentLoss


def _directed_nn_distances(
    x: torch.Tensor, y: torch.Tensor, x_lengths: torch.Tensor | None, y_lengths: torch.Tensor | None
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Validate a batch; per sample, Euclidean distances ``(N_b,)`` from x to y and ``(M_b,)``
    from y to x, in float32 or wider (half-precision inputs are promoted, their squares
    underflow)."""
    check_points(x, "x", batched=True)
    check_points(y, "y", batched=True)
    check_same_batch(x, y, "x", "y")
    x_lengths = check_lengths(x_lengths, "x_lengths", x.shape[0], x.shape[1])
    y_lengths = check_lengths(y_lengths, "y_lengths", y.shape[0], y.shape[1])
    work = torch.promote_types(torch.promote_types(x.dtype, y.dtype), torch.float32)
    x, y = x.to(work), y.to(work)
    out = []
    for b in range(x.shape[0]):
        xb = x[b, : int(x_lengths[b])] if x_lengths is not None else x[b]
        yb = y[b, : int(y_lengths[b])] if y_lengths is not None else y[b]
        out.append((knn_distances(xb, yb)[:, 0], knn_distances(yb, xb)[:, 0]))
    return out


def chamfer_distance(
    x: torch.Tensor,
    y: torch.Tensor,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
    *,
    squared: bool = False,
) -> torch.Tensor:
    """Symmetric Chamfer distance ``mean_i min_j d(x_i, y_j) + mean_j min_i d(x_i, y_j)``.

    Args:
        x: tensor of shape ``(B, N, 3)`` giving the first clouds (padded when ``x_lengths``).
        y: tensor of shape ``(B, M, 3)`` giving the second clouds.
        x_lengths: optional ``(B,)`` integer number of valid points per cloud of ``x``, in
            ``[1, N]``.
        y_lengths: optional ``(B,)`` integer number of valid points per cloud of ``y``, in
            ``[1, M]``.
        squared: ``d`` is the squared Euclidean distance when ``True`` (FMR's reconstruction
            loss), the Euclidean distance otherwise (the paper's CD).

    Returns:
        Tensor of shape ``(B,)`` in the dtype of ``x``.

    Raises:
        TypeError: non-float clouds or non-integer lengths.
        ValueError: bad shapes, NaN/Inf coordinates, or a length outside its range.
    """
    values = []
    for d_xy, d_yx in _directed_nn_distances(x, y, x_lengths, y_lengths):
        if squared:
            d_xy, d_yx = d_xy.square(), d_yx.square()
        values.append(d_xy.mean() + d_yx.mean())
    return torch.stack(values).to(x.dtype)


def welsch(distances: torch.Tensor, nu: torch.Tensor | float) -> torch.Tensor:
    """Welsch's function ``psi_nu(d) = 1 - exp(-d^2 / (2 nu^2))`` (paper Eq. 5), elementwise.

    ``2 nu^2`` is floored at the smallest normal number of the dtype, so ``nu = 0`` gives 0 for
    ``d = 0`` and 1 elsewhere, with a zero gradient instead of NaN.
    """
    two_nu_sq = torch.as_tensor(2.0 * nu * nu, dtype=distances.dtype, device=distances.device)
    return 1.0 - torch.exp(-distances.square() / two_nu_sq.clamp_min(torch.finfo(distances.dtype).tiny))


def welsch_scale(distances: torch.Tensor, nu0: float) -> torch.Tensor:
    """``nu = nu0 * median(distances)``, detached (the paper treats it as a constant)."""
    return nu0 * distances.detach().median()


def check_nu0(nu0: float, name: str = "nu0") -> None:
    """Raise ``ValueError`` unless ``nu0`` (a Welsch scale factor called ``name``) is a finite number > 0."""
    if isinstance(nu0, bool) or not isinstance(nu0, numbers.Real) or not (math.isfinite(nu0) and nu0 > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {nu0!r}")


def chamfer_welsch_distance(
    x: torch.Tensor,
    y: torch.Tensor,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
    *,
    nu0: float = 0.5,
) -> torch.Tensor:
    """Welsch-Chamfer (CD-W): ``mean psi_nu`` over the closest pairs of both directions.

    ``nu = nu0 * d_med`` with ``d_med`` the median distance of all closest pairs of the sample
    (both directions), detached and recomputed at every call (paper, supplementary).

    Returns:
        Tensor of shape ``(B,)`` in the dtype of ``x``: ``mean_i psi(d_i^{x->y}) + mean_j psi(d_j^{y->x})``.

    Raises:
        ValueError: ``nu0`` not a finite number > 0, and as :func:`chamfer_distance`.
    """
    check_nu0(nu0)
    values = []
    for d_xy, d_yx in _directed_nn_distances(x, y, x_lengths, y_lengths):
        nu = welsch_scale(torch.cat([d_xy, d_yx]), nu0)
        values.append(welsch(d_xy, nu).mean() + welsch(d_yx, nu).mean())
    return torch.stack(values).to(x.dtype)


@LOSSES.register("chamfer", needs_gt=False)
class ChamferLoss(AlignmentLoss):
    """CD between the transformed source and the target (paper Eq. 2, Euclidean ``D``)."""

    def __init__(self, squared: bool = False, **iteration_kwargs) -> None:
        super().__init__(**iteration_kwargs)
        self.squared = squared

    def metric(self, src, tgt, src_lengths=None, tgt_lengths=None):
        return chamfer_distance(src, tgt, src_lengths, tgt_lengths, squared=self.squared), {}


@LOSSES.register("chamfer_welsch", needs_gt=False)
class ChamferWelschLoss(AlignmentLoss):
    """CD-W between the transformed source and the target (supplementary, ``nu0`` default 0.5)."""

    def __init__(self, nu0: float = 0.5, **iteration_kwargs) -> None:
        super().__init__(**iteration_kwargs)
        check_nu0(nu0)
        self.nu0 = nu0

    def metric(self, src, tgt, src_lengths=None, tgt_lengths=None):
        return chamfer_welsch_distance(src, tgt, src_lengths, tgt_lengths, nu0=self.nu0), {}
