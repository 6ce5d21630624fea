"""Registration errors of the paper (Eq. "eval_metric", §4 "Evaluation Criteria") and summaries.

With ground truth ``(R_gt, t_gt)``, an estimate ``(R, t)`` and the source cloud ``X``:

* ``Err_R = angle(R_gt^-1 @ R)`` in degrees, ``angle(A) = arccos((tr A - 1) / 2)``;
* ``Err_t = || t_gt - t ||_*``;
* ``Err_pw = 1/|X| sum_{x in X} || R_gt x + t_gt - R x - t ||_*``;

where ``||.||_*`` is the l1 or the l2 norm. ``Err_t`` and ``Err_pw`` are in the length units of
the input; the paper's tables print them multiplied by 10 (a ``x10^-1`` column header) and
report mean values over a benchmark. The paper's alpha-recall is the fraction of pairs whose
l2 pointwise error is below ``alpha``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch

from linereg.checks import check_points, check_same_batch, check_shape, check_transform
from linereg.se3 import matrix_to_rt, rotation_angle, transform_points

NORMS = ("l1", "l2")
ERROR_KEYS = ("err_r_deg", "err_t_l1", "err_t_l2", "err_pw_l1", "err_pw_l2")
SUCCESS_THRESHOLDS_DEG = (1.0, 5.0)


def _vector_norm(vectors: torch.Tensor, norm: str) -> torch.Tensor:
    """l1 or l2 norm over the last axis."""
    if norm not in NORMS:
        raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
    return torch.linalg.vector_norm(vectors, ord=1 if norm == "l1" else 2, dim=-1)


def rotation_error_deg(R_pred: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """Isotropic rotation error ``Err_R = angle(R_gt^T @ R_pred)``, in degrees.

    Args:
        R_pred: tensor of shape ``(..., 3, 3)`` giving estimated rotations.
        R_gt: tensor of shape ``(..., 3, 3)`` giving ground-truth rotations.

    Returns:
        Tensor of shape ``(...)`` in ``[0, 180]`` degrees (see :func:`linereg.se3.rotation_angle`).
    """
    check_shape(R_pred, "R_pred", (3, 3))
    check_shape(R_gt, "R_gt", (3, 3))
    return torch.rad2deg(rotation_angle(R_gt.transpose(-1, -2) @ R_pred))


def translation_error(t_pred: torch.Tensor, t_gt: torch.Tensor, norm: str = "l2") -> torch.Tensor:
    """Translation error ``Err_t = || t_gt - t_pred ||``.

    Args:
        t_pred: tensor of shape ``(..., 3)`` giving estimated translations.
        t_gt: tensor of shape ``(..., 3)`` giving ground-truth translations.
        norm: ``"l1"`` (``|dx| + |dy| + |dz|``) or ``"l2"`` (Euclidean).

    Returns:
        Tensor of shape ``(...)`` in the length units of the input.
    """
    check_shape(t_pred, "t_pred", (3,))
    check_shape(t_gt, "t_gt", (3,))
    return _vector_norm(t_gt - t_pred, norm)


def _valid_point_mask(points: torch.Tensor, lengths: torch.Tensor | None) -> torch.Tensor:
    """``(B, N)`` bool mask of the first ``lengths[b]`` points (all points when ``None``)."""
    batch_size, num_points = points.shape[:2]
    if lengths is None:
        return torch.ones(batch_size, num_points, dtype=torch.bool, device=points.device)
    if lengths.shape != (batch_size,):
        raise ValueError(f"lengths must have shape ({batch_size},), got {tuple(lengths.shape)}")
    if bool(((lengths < 1) | (lengths > num_points)).any()):
        raise ValueError(f"lengths must lie in [1, {num_points}], got {lengths.tolist()}")
    return torch.arange(num_points, device=points.device) < lengths.to(points.device)[:, None]


def pointwise_error(
    T_pred: torch.Tensor,
    T_gt: torch.Tensor,
    points: torch.Tensor,
    norm: str = "l2",
    lengths: torch.Tensor | None = None,
) -> torch.Tensor:
    """Pointwise error ``Err_pw``: mean over the source points of ``|| T_gt x - T_pred x ||``.

    Args:
        T_pred: tensor of shape ``(B, 4, 4)`` giving estimated source-to-target transforms.
        T_gt: tensor of shape ``(B, 4, 4)`` giving ground-truth transforms.
        points: tensor of shape ``(B, N, 3)`` giving source points (padded with ``lengths``).
        norm: ``"l1"`` or ``"l2"``, applied to each point's displacement.
        lengths: long tensor of shape ``(B,)`` giving the number of valid points per cloud, or
            ``None`` (all valid).

    Returns:
        Tensor of shape ``(B,)`` in the length units of ``points``.
    """
    check_shape(T_pred, "T_pred", (4, 4))
    check_shape(T_gt, "T_gt", (4, 4))
    check_shape(points, "points", (3,))
    if points.ndim != 3:
        raise ValueError(f"points must have shape (B, N, 3), got {tuple(points.shape)}")
    displacement = transform_points(T_gt, points) - transform_points(T_pred, points)
    per_point = _vector_norm(displacement, norm)
    mask = _valid_point_mask(points, lengths)
    return torch.where(mask, per_point, torch.zeros_like(per_point)).sum(1) / mask.sum(1)


def registration_errors(
    T_pred: torch.Tensor,
    T_gt: torch.Tensor,
    src: torch.Tensor,
    src_lengths: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """All errors of the paper's Eq. for a batch of pairs, computed in float64.

    Args:
        T_pred: tensor of shape ``(B, 4, 4)`` giving estimated source-to-target transforms.
        T_gt: tensor of shape ``(B, 4, 4)`` giving ground-truth transforms.
        src: tensor of shape ``(B, N, 3)`` giving the source clouds (padded with ``src_lengths``).
        src_lengths: long tensor of shape ``(B,)`` or ``None`` (all points valid).

    Returns:
        Dict of float64 tensors of shape ``(B,)`` with keys ``err_r_deg`` (degrees),
        ``err_t_l1``, ``err_t_l2``, ``err_pw_l1``, ``err_pw_l2`` (length units of ``src``).
    """
    check_transform(T_pred, "T_pred")
    check_transform(T_gt, "T_gt")
    check_points(src, "src", batched=True)
    if T_pred.ndim != 3 or T_gt.shape != T_pred.shape:
        raise ValueError(
            f"T_pred and T_gt must both have shape (B, 4, 4), got {tuple(T_pred.shape)} and {tuple(T_gt.shape)}"
        )
    check_same_batch(T_pred, src, "T_pred", "src")
    T_pred, T_gt, src = T_pred.double(), T_gt.double(), src.double()
    R_pred, t_pred = matrix_to_rt(T_pred)
    R_gt, t_gt = matrix_to_rt(T_gt)
    return {
        "err_r_deg": rotation_error_deg(R_pred, R_gt),
        "err_t_l1": translation_error(t_pred, t_gt, "l1"),
        "err_t_l2": translation_error(t_pred, t_gt, "l2"),
        "err_pw_l1": pointwise_error(T_pred, T_gt, src, "l1", src_lengths),
        "err_pw_l2": pointwise_error(T_pred, T_gt, src, "l2", src_lengths),
    }


def alpha_recall(err_pw_l2: torch.Tensor, alphas: torch.Tensor) -> torch.Tensor:
    """Alpha-recall ``|S_alpha| / |S|``: the fraction of pairs with ``err_pw_l2 < alpha``.

    Args:
        err_pw_l2: tensor or array of shape ``(P,)`` giving each pair's l2 pointwise error.
        alphas: tensor or array of shape ``(A,)`` giving the thresholds.

    Returns:
        Float64 tensor of shape ``(A,)`` with values in ``[0, 1]``.
    """
    errors = torch.as_tensor(err_pw_l2, dtype=torch.float64)
    thresholds = torch.as_tensor(alphas, dtype=torch.float64, device=errors.device)
    if errors.ndim != 1 or errors.numel() == 0:
        raise ValueError(f"err_pw_l2 must have shape (P,) with P >= 1, got {tuple(errors.shape)}")
    if thresholds.ndim != 1:
        raise ValueError(f"alphas must have shape (A,), got {tuple(thresholds.shape)}")
    return (errors[None, :] < thresholds[:, None]).double().mean(1)


def summarize(errors: Mapping[str, torch.Tensor | np.ndarray]) -> dict[str, float]:
    """Mean and median of every per-pair error.

    Args:
        errors: mapping from a name (e.g. ``"err_r_deg"``) to a tensor or array of shape ``(P,)``.

    Returns:
        Dict with ``f"{name}_mean"`` and ``f"{name}_median"`` for every name, as floats.
    """
    summary = {}
    for name, values in errors.items():
        array = (
            values.detach().cpu().double().numpy()
            if isinstance(values, torch.Tensor)
            else np.asarray(values, dtype=np.float64)
        )
        if array.ndim != 1 or array.size == 0:
            raise ValueError(f"errors[{name!r}] must have shape (P,) with P >= 1, got {array.shape}")
        summary[f"{name}_mean"] = float(array.mean())
        summary[f"{name}_median"] = float(np.median(array))
    return summary


def aggregate_errors(
    errors: Mapping[str, torch.Tensor | np.ndarray],
    *,
    alphas: Sequence[float] = (),
    success_deg: Sequence[float] = (),
) -> dict[str, float]:
    """Everything a results table reports about per-pair errors ``{name: (P,)}``.

    Args:
        errors: per-pair errors (``err_pw_l2`` needed for ``alphas``, ``err_r_deg`` for
            ``success_deg``); other columns (e.g. ``seconds``) are summarised too.
        alphas: alpha-recall thresholds: ``recall@<alpha>`` (fraction with ``err_pw_l2 < alpha``).
        success_deg: rotation thresholds: ``success_<t>deg`` (fraction with ``err_r_deg < t``).

    Returns:
        :func:`summarize`'s means and medians, ``pairs`` when ``success_deg`` is given, the recalls
        and the success rates, as floats.
    """
    values = summarize(errors)
    if alphas:
        recall = alpha_recall(errors["err_pw_l2"], list(alphas))
        values.update({f"recall@{alpha:g}": float(r) for alpha, r in zip(alphas, recall, strict=True)})
    if success_deg:
        rotation = torch.as_tensor(errors["err_r_deg"]).detach().cpu().double().numpy()
        values["pairs"] = len(rotation)
        values.update({f"success_{t:g}deg": float(np.mean(rotation < t)) for t in success_deg})
    return values


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    """Markdown lines of a table: ``| header |``, the separator ``|---|...`` and one line per row of
    formatted cells."""
    return [
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
        *("| " + " | ".join(row) + " |" for row in rows),
    ]


def paper_table(rows: Mapping[str, Mapping[str, float]], stat: str = "mean") -> str:
    """A markdown table in the layout of the paper's tables, from :func:`summarize` outputs.

    Columns: Method | Err_R (deg) | Err_t (x10^-1) (l1, l2) | Err_pw (x10^-1) (l1, l2), using
    the ``*_{stat}`` values; translation and pointwise errors are multiplied by 10 as the paper
    prints them. Numbers have three decimals.

    Args:
        rows: mapping from a method name to its summary (needs ``err_*_{stat}`` for every key
            in ``ERROR_KEYS``).
        stat: ``mean`` (the paper's tables) or ``median``.

    Returns:
        The table as a string (header, separator, one line per method).
    """
    if stat not in ("mean", "median"):
        raise ValueError(f"stat must be 'mean' or 'median', got {stat!r}")
    cells = []
    for method, summary in rows.items():
        missing = [f"{key}_{stat}" for key in ERROR_KEYS if f"{key}_{stat}" not in summary]
        if missing:
            raise KeyError(f"summary of {method!r} lacks {', '.join(missing)}")
        cells.append(
            [
                method,
                f"{summary[f'err_r_deg_{stat}']:.3f}",
                f"{10 * summary[f'err_t_l1_{stat}']:.3f}, {10 * summary[f'err_t_l2_{stat}']:.3f}",
                f"{10 * summary[f'err_pw_l1_{stat}']:.3f}, {10 * summary[f'err_pw_l2_{stat}']:.3f}",
            ]
        )
    header = ["Method", "Err_R (deg)", "Err_t (x10^-1) (l1, l2)", "Err_pw (x10^-1) (l1, l2)"]
    return "\n".join(markdown_table(header, cells))


def alpha_recall_table(rows: Mapping[str, Mapping[str, float]], alphas: Sequence[float]) -> list[str]:
    """Markdown lines: each method's alpha-recall (``recall@<alpha>`` of :func:`aggregate_errors`) at
    every alpha, three decimals."""
    header = ["Method", *(f"alpha={alpha:g}" for alpha in alphas)]
    cells = ([method, *(f"{summary[f'recall@{alpha:g}']:.3f}" for alpha in alphas)] for method, summary in rows.items())
    return markdown_table(header, cells)
