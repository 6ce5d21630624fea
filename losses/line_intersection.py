"""The line-intersection metric of Deng et al., "A Robust Loss for Point Cloud Registration"
(ICCV 2021), §3.2 — sparse, batched, differentiable w.r.t. the source points.

For ``L`` random lines ``l`` (see :mod:`linereg.losses.lines`):

1. **Intersections.** Points within ``delta = delta_factor * d_nei`` of the line are candidates
   (``d_nei``: mean distance to the ``k`` nearest neighbours, per cloud). A candidate ``p0``
   whose ``k`` nearest neighbours are candidates too yields the intersection
   ``p0' = sum_p d_p p / sum_p d_p`` over ``p0`` and its neighbours, ``d_p`` the distance of
   ``p`` to the line (Eq. 7; weights detached).
2. **Matching.** On each line that meets both clouds, every source intersection is matched to
   its closest target intersection and vice versa (Eq. 3's ``sigma_l``, ``rho_l``).
3. **Value.** ``F_l = w_l * sum_pairs psi_nu(||x - y||)`` with Welsch's
   ``psi_nu(d) = 1 - exp(-d^2 / (2 nu^2))``, ``nu = nu0 * median pair distance`` (detached,
   recomputed every call) and ``w_l = exp(-| |S_l| - |T_l| | / 2)``. The metric is the mean of
   ``F_l`` over the lines that meet both clouds.

Steps 1 and 2 (:mod:`linereg.losses.line_pairs`) only choose indices and detached weights, so
memory is linear in ``N + L``. Two backends choose them (``backend`` option): ``numba``
(:mod:`linereg.losses.line_kernels`, a compiled grid walk that only examines point-line pairs
that can interact, on the CPU, threads across samples and lines) and ``torch``
(:mod:`linereg.losses.line_torch`, an all-pairs test in chunks on the tensors' device, batched,
no per-sample host round trip). ``auto`` (default) takes ``torch`` for tensors on an
accelerator and ``numba`` on the CPU. With ``numba`` and the settings of :func:`fused_path`
(the paper's and ``linereg``'s among them), the kernels also match the intersections and
compute the value with its gradient (:class:`linereg.losses.line_value.FusedLineValue`), and
the backward pass only scales that gradient; otherwise torch gathers the points and autograd
differentiates steps 2-3 (a sparse scatter, :mod:`linereg.losses.line_value`). For the same
lines both give the same value and gradient up to float rounding. Half-precision inputs are
evaluated in float32. The options live in :mod:`linereg.losses.line_options`.

Options reproduce every ablation of the paper (Table 2) and the authors' released code:

================  ==========================================  ================================
option            paper (default)                             alternatives
================  ==========================================  ================================
``sampling``      ``sphere``                                  ``box_point_direction`` (Sample1),
                                                              ``cloud_points`` (Sample2),
                                                              ``authors``
``intersection``  ``convex`` (Eq. 7)                          ``candidates`` (Insec1),
                                                              ``triplet`` (authors),
                                                              ``pierce`` (linereg)
``nu0``           0.5                                         any > 0
``k``             2                                           any >= 1
``delta_factor``  sqrt(3)/2                                   any > 0
``line_weight``   True                                        False
``nu``            None (``nu0`` x median, detached)           a fixed absolute scale
``detach_weights`` True (Eq. 7 weights are constants)         False: differentiate them too
``backend``       ``auto``                                    ``numba``, ``torch``
================  ==========================================  ================================

``variant="linereg"`` is the paper's metric with one change, ``intersection="pierce"``: the
intersection of a line with a candidate ``p0`` and its 2 neighbours is the point where the line
pierces their triangle, written with its barycentric weights (detached) as a combination of the
three points. Eq. (7)'s weights ``d_p / sum d`` give a point whose offset from the true crossing
is of the order of ``delta`` whatever the alignment, which limits how precisely the metric can
register two different samplings of one surface (see the README's registration benchmark).

``variant="authors"`` switches every default to what ``code/loss.py`` of the paper repository
does, each still overridable:

* lines from a sphere of radius = target bounding-box diagonal around the target centroid,
  kept only if they cross both bounding boxes (``sampling="authors"``);
* the hit test is stricter: a point and its 2 neighbours must *all* lie within
  ``sqrt(3)/2 * s`` of the line, ``s`` the mean pairwise spacing of that triplet (locally
  adaptive ``delta``), with ``2e-4`` added under every distance's square root
  (``intersection="triplet"``, ``distance_eps=2e-4``);
* Welsch on *squared* distances, ``psi = 1 - exp(-d^2 / (2 c))`` with ``c = median(d^2)``
  (``welsch_input="squared"``, ``nu0=1``);
* only lines with 1 to 4 intersections on each cloud count (``max_hits=4``);
* the value is averaged per (|S_l|, |T_l|) group: ``sum_g w_g (mean_rows + mean_cols) / #groups``
  (``reduction="groups"``);
* the authors' intersection point is ``mean_i(w_i p_i)``, i.e. a third of the convex
  combination. Both clouds are scaled alike and the Welsch scale is the median, so the value
  is unchanged by that factor; we keep the true convex combination.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from linereg.checks import check_lengths, check_points, check_same_batch

from .base import LOSSES, AlignmentLoss
from .chamfer import check_nu0
from .line_options import STAT_KEYS, LineMetricOptions
from .line_pairs import line_pairs
from .line_value import fused_path, fused_values, line_values, welsch_terms

__all__ = [
    "Correspondences",
    "LineIntersectionLoss",
    "LineMetricOptions",
    "LineMetricResult",
    "line_correspondences",
    "line_intersection_metric",
]


@dataclass
class LineMetricResult:
    """Per-sample values ``(B,)`` and hit statistics (floats averaged over the batch)."""

    value: torch.Tensor
    stats: dict[str, float] = field(default_factory=dict)


def _checked_inputs(src, tgt, src_lengths, tgt_lengths, options):
    """Validate the batch; return both clouds in float32 or wider and the lengths (CPU int64)."""
    check_points(src, "src", batched=True, min_points=options.k + 1)
    check_points(tgt, "tgt", batched=True, min_points=options.k + 1)
    check_same_batch(src, tgt, "src", "tgt")
    if src.device != tgt.device:
        raise ValueError(f"src and tgt must be on the same device, got {src.device} and {tgt.device}")
    batch = src.shape[0]
    need = options.k + 1
    src_lengths = check_lengths(src_lengths, "src_lengths", batch, src.shape[1], min_length=need)
    tgt_lengths = check_lengths(tgt_lengths, "tgt_lengths", batch, tgt.shape[1], min_length=need)
    if src_lengths is None:
        src_lengths = torch.full((batch,), src.shape[1], dtype=torch.int64)
    if tgt_lengths is None:
        tgt_lengths = torch.full((batch,), tgt.shape[1], dtype=torch.int64)
    work = torch.promote_types(torch.promote_types(src.dtype, tgt.dtype), torch.float32)
    return src.to(work), tgt.to(work), src_lengths, tgt_lengths


def _fresh_generator() -> torch.Generator:
    return torch.Generator().manual_seed(int(torch.randint(0, 2**62, ()).item()))


def line_intersection_metric(
    src: torch.Tensor,
    tgt: torch.Tensor,
    src_lengths: torch.Tensor | None = None,
    tgt_lengths: torch.Tensor | None = None,
    *,
    options: LineMetricOptions | None = None,
    generator: torch.Generator | None = None,
    lines: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> LineMetricResult:
    """The line-intersection metric between batched clouds.

    Args:
        src: tensor of shape ``(B, N, 3)`` giving the (transformed) source points; gradients
            flow to it.
        tgt: tensor of shape ``(B, M, 3)`` giving the target points.
        src_lengths: optional ``(B,)`` integer number of valid source points (padded batches),
            each in ``[k + 1, N]``.
        tgt_lengths: optional ``(B,)`` integer number of valid target points, in ``[k + 1, M]``.
        options: metric options; the paper's defaults when ``None``.
        generator: CPU ``torch.Generator`` for the lines (fresh randomness when ``None``).
        lines: optional explicit lines per sample ``[(origins (L_b, 3), dirs (L_b, 3)), ...]``
            (arrays or tensors; non-zero directions, normalised here), overriding the sampler.

    Returns:
        :class:`LineMetricResult` with ``value`` of shape ``(B,)`` in the dtype of ``src``
        (zero, with zero gradient, for a sample where no line meets both clouds) and
        batch-averaged hit statistics.

    Raises:
        TypeError: non-float clouds or non-integer lengths.
        ValueError: wrong shapes, NaN/Inf coordinates, a cloud with ``k`` points or fewer, a
            length outside its range, or malformed ``lines``.
    """
    options = options or LineMetricOptions()
    work_src, work_tgt, src_lengths, tgt_lengths = _checked_inputs(src, tgt, src_lengths, tgt_lengths, options)
    generator = generator or _fresh_generator()
    if fused_path(options, work_src.device):
        value, stats = fused_values(work_src, work_tgt, src_lengths, tgt_lengths, options, generator, lines)
    else:
        pairs = line_pairs(work_src, work_tgt, src_lengths, tgt_lengths, options, generator, lines)
        value, stats = line_values(pairs, options, work_src)
    mean_stats = dict(zip(STAT_KEYS, stats.mean(dim=0).tolist(), strict=True))
    return LineMetricResult(value=value.to(src.dtype), stats=mean_stats)


@dataclass
class Correspondences:
    """Weighted point pairs from the line intersections, for IRLS/Procrustes solvers.

    Attributes:
        src: ``(P, 3)`` source-side intersection points (detached).
        tgt: ``(P, 3)`` matched target-side intersection points.
        weights: ``(P,)`` ``w_l * exp(-d^2 / (2 nu^2))``, Welsch's IRLS weights.
        stats: hit statistics of the evaluation.
    """

    src: torch.Tensor
    tgt: torch.Tensor
    weights: torch.Tensor
    stats: dict[str, float]


def line_correspondences(
    src: torch.Tensor,
    tgt: torch.Tensor,
    *,
    options: LineMetricOptions | None = None,
    generator: torch.Generator | None = None,
) -> Correspondences:
    """Correspondences implied by the metric for one pair ``src (N, 3)``, ``tgt (M, 3)``.

    Replacing Welsch's function by its quadratic surrogate at the current pose gives the
    weighted least-squares problem of the supplementary's SVD solver: minimise
    ``sum w (R x + t - y)^2`` over these pairs.
    """
    options = options or LineMetricOptions()
    check_points(src, "src", batched=False, min_points=options.k + 1)
    check_points(tgt, "tgt", batched=False, min_points=options.k + 1)
    work_src, work_tgt, src_lengths, tgt_lengths = _checked_inputs(
        src.detach()[None], tgt.detach()[None], None, None, options
    )
    pairs = line_pairs(work_src, work_tgt, src_lengths, tgt_lengths, options, generator or _fresh_generator(), None)
    _, stats = line_values(pairs, options, work_src)
    line_w, dist_sq, two_c, _ = welsch_terms(pairs, options)
    x = pairs.src_points[pairs.src_index]
    y = pairs.tgt_points[pairs.tgt_index]
    weights = line_w * torch.exp(-dist_sq / two_c)
    return Correspondences(
        x.to(src.dtype), y.to(src.dtype), weights.to(src.dtype), dict(zip(STAT_KEYS, stats[0].tolist(), strict=True))
    )


@LOSSES.register("line_intersection", needs_gt=False)
class LineIntersectionLoss(AlignmentLoss):
    """The line-intersection metric as a loss on each iteration's transformed source.

    Args:
        variant: ``paper`` (default), ``authors`` or ``linereg`` (see the module docstring).
        seed: seeds the line generator (reproducible runs); fresh randomness when ``None``.
        discount, last_k, normalize_iterations: iteration weighting (:class:`AlignmentLoss`).
        nu0_final: anneal the Welsch scale factor during training, geometrically from ``nu0``
            at the first epoch to ``nu0_final`` at the last (:meth:`set_progress`; the training
            loop calls it before each epoch); ``None`` keeps ``nu0`` throughout.
        **options: any :class:`LineMetricOptions` field, overriding the variant's default.
    """

    def __init__(
        self,
        variant: str = "paper",
        seed: int | None = None,
        discount: float = 0.5,
        last_k: int | None = None,
        normalize_iterations: bool = False,
        nu0_final: float | None = None,
        **options: Any,
    ) -> None:
        super().__init__(discount=discount, last_k=last_k, normalize_iterations=normalize_iterations)
        known = set(LineMetricOptions.__dataclass_fields__)
        unknown = set(options) - known
        if unknown:
            raise TypeError(f"unknown line_intersection option(s) {sorted(unknown)}; known: {sorted(known)}")
        self.options = LineMetricOptions.for_variant(variant, **options)
        if nu0_final is not None:
            if self.options.nu is not None:
                raise ValueError("nu0_final anneals nu0, which a fixed absolute scale nu overrides: set one of them")
            check_nu0(nu0_final, "nu0_final")
            nu0_final = float(nu0_final)
        self.nu0_start = self.options.nu0
        self.nu0_final = nu0_final
        self.generator = torch.Generator()
        self.generator.manual_seed(seed if seed is not None else int(torch.randint(0, 2**62, ()).item()))

    def set_progress(self, fraction: float) -> dict[str, float]:
        """Set ``nu0 = nu0_start * (nu0_final / nu0_start) ** fraction``; ``{"nu0": value}``, or ``{}`` unscheduled."""
        if self.nu0_final is None:
            return {}
        self.options = replace(self.options, nu0=self.nu0_start * (self.nu0_final / self.nu0_start) ** fraction)
        return {"nu0": self.options.nu0}

    def metric(self, src, tgt, src_lengths=None, tgt_lengths=None):
        result = line_intersection_metric(
            src, tgt, src_lengths, tgt_lengths, options=self.options, generator=self.generator
        )
        return result.value, result.stats
