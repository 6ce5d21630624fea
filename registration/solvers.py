"""Optimisation-based registration of one pair with any registered loss (paper §4.2).

``adam_loss``
    Adam on the Lie-algebra parameter ``xi`` of the source pose, ``T = exp(xi) @ T_init``
    (the paper's solver), new lines at every iteration. A schedule is a list of stages, each
    with its own loss, number of iterations and learning rate (cosine decay within a stage),
    so a coarse stage (e.g. CD-W with a wide Welsch window) can precede the line metric.
``svd_irls``
    The supplementary's SVD solver: at each step the line metric's correspondences get
    Welsch's IRLS weights ``w_l exp(-d^2 / 2 nu^2)`` and a weighted Procrustes solve updates
    the pose in closed form.

Both work on clouds centred at their centroids (``run_centered``) and scaled to a unit covering
radius, so learning rates are unit-free; the transform returned is in the original units.
Large clouds are subsampled by farthest-point sampling to ``num_points`` for the loss while the
returned transform applies to the full cloud.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from linereg.checks import check_points, check_transform
from linereg.losses import build_loss
from linereg.losses.base import AlignmentLoss
from linereg.losses.chamfer import welsch
from linereg.losses.line_intersection import LineMetricOptions, line_correspondences
from linereg.metrics import rotation_error_deg
from linereg.pointcloud import farthest_point_sampling
from linereg.procrustes import weighted_procrustes
from linereg.registration.methods import METHODS, MethodResult, run_centered
from linereg.registration.robust import (
    alignment_quality,
    cube_rotations,
    degeneracy,
    options_from,
    point_spacing,
    polish_scales,
)
from linereg.se3 import se3_exp, transform_points

Monitor = Callable[[int, np.ndarray, float], dict[str, float]]
"""Called as ``monitor(step, T (4, 4) in the solver's frame, loss)``; returns values to show."""


@dataclass(frozen=True)
class Stage:
    """One stage of an Adam schedule: a loss config, iterations, a peak learning rate and
    optionally fewer points (an FPS subset of both clouds) for a cheap coarse stage."""

    loss: Mapping[str, Any]
    iterations: int
    lr: float
    points: int | None = None


# The register default, chosen on the Human/Airplane benchmark (README, issue #4 notes): a cheap
# CD-W stage on 256 points from every start, then the line metric with the candidate points as
# intersections (the paper's "Insec1" ablation, the most precise variant here), first with a wider
# Welsch window (nu0 = 1: robust to the partial overlap), then the paper's nu0 = 0.5 to polish.
# About 2 s for a 1024-point pair on 2 CPU cores (scripts/bench_register.py).
_LINE = {"name": "line_intersection", "intersection": "candidates", "num_lines": 4000}
DEFAULT_STAGES: tuple[Stage, ...] = (
    Stage(loss={"name": "chamfer_welsch", "nu0": 2.0}, iterations=60, lr=0.03, points=256),
    Stage(loss={**_LINE, "nu0": 1.0}, iterations=80, lr=0.01),
    Stage(loss={**_LINE, "nu0": 0.5}, iterations=50, lr=0.004),
)
# Picks the best of several starts: the line metric with a fixed Welsch scale (unit-ball units).
DEFAULT_SELECT: Mapping[str, Any] = {
    "name": "line_intersection",
    "intersection": "candidates",
    "num_lines": 10000,
    "nu": 0.05,
}
PAPER_STAGES: tuple[Stage, ...] = (Stage(loss={"name": "line_intersection"}, iterations=500, lr=0.02),)


def _subsample(points: np.ndarray | torch.Tensor, num_points: int | None) -> np.ndarray | torch.Tensor:
    """The FPS subset of ``points (N, 3)`` with ``num_points`` points (all of them if ``None``)."""
    if num_points is None or len(points) <= num_points:
        return points
    single = points.astype(np.float32) if isinstance(points, np.ndarray) else points.float()
    return points[farthest_point_sampling(single, num_points)]


def _normalise(src: np.ndarray, tgt: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both (already centred) clouds scaled by one factor so that they fit in the unit ball."""
    radius = float(max(np.linalg.norm(src, axis=1).max(), np.linalg.norm(tgt, axis=1).max(), 1e-12))
    return torch.from_numpy(src / radius), torch.from_numpy(tgt / radius), radius


def _unscale(transform: np.ndarray, radius: float) -> np.ndarray:
    out = transform.copy()
    out[:3, 3] *= radius
    return out


def _as_stages(stages: Sequence[Stage | Mapping[str, Any]] | str) -> tuple[Stage, ...]:
    if isinstance(stages, str):
        presets = {"default": DEFAULT_STAGES, "paper": PAPER_STAGES}
        if stages not in presets:
            raise ValueError(f"unknown stage preset {stages!r}; choose one of {', '.join(presets)} or give a list")
        return presets[stages]
    out = []
    for stage in stages:
        if isinstance(stage, Stage):
            out.append(stage)
            continue
        stage = dict(stage)
        unknown = set(stage) - {"loss", "iterations", "lr", "points"}
        if unknown:
            raise TypeError(f"unknown stage key(s) {sorted(unknown)}; a stage has loss, iterations, lr and points")
        points = stage.get("points")
        out.append(
            Stage(
                loss=dict(stage["loss"]),
                iterations=int(stage["iterations"]),
                lr=float(stage["lr"]),
                points=None if points is None else int(points),
            )
        )
    if not out:
        raise ValueError("an Adam schedule needs at least one stage")
    return tuple(out)


class _Solver:
    """Shared plumbing: centring (``run_centered``), FPS subsampling, unit scaling."""

    num_points: int | None
    center: bool

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        return run_centered(self._solve, src, tgt, src_normals, tgt_normals, center=self.center)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        src_t, tgt_t, radius = _normalise(_subsample(src, self.num_points), _subsample(tgt, self.num_points))
        pose, info = self._optimise(src_t, tgt_t, lambda T: _unscale(T, radius))
        return MethodResult(transform=_unscale(pose.numpy(), radius), info=info)

    def _optimise(self, src: torch.Tensor, tgt: torch.Tensor, unscale) -> tuple[torch.Tensor, dict[str, Any]]:
        raise NotImplementedError


def start_poses(count: int, angle_deg: float = 90.0) -> torch.Tensor:
    """Initial poses of a multi-start: the identity, then rotations by ``angle_deg`` about +x, +y,
    +z, -x, -y, -z (the clouds are centred, so about their centroids), in that order.

    Returns:
        Float64 tensor of shape ``(count, 4, 4)``.
    """
    if not 1 <= count <= 7:
        raise ValueError(f"starts must be in 1..7 (identity and +-angle about 3 axes), got {count}")
    axes = torch.cat([torch.eye(3), -torch.eye(3)]).double()
    rotvecs = torch.cat([torch.zeros(1, 3, dtype=torch.float64), axes * np.deg2rad(angle_deg)])[:count]
    return se3_exp(torch.cat([rotvecs, torch.zeros_like(rotvecs)], dim=1))


class AdamRegistration(_Solver):
    """Adam on ``xi`` in se(3) with any registered alignment loss, optionally from several starts.

    With ``starts > 1`` the first stage runs from every pose of :func:`start_poses` at once
    (a batch), the ``select`` loss picks the best result, and the remaining stages refine it.
    The criterion needs a fixed scale: the paper's line metric sets Welsch's scale from the
    median distance of the pose being scored, which makes its value nearly pose-independent.

    Args:
        stages: list of ``{loss: {name, ...}, iterations, lr, points}`` or a preset name:
            ``default`` (a short CD-W stage, then the line metric with candidate intersections;
            chosen on the benchmark, see README) or ``paper`` (the paper's line metric alone,
            500 iterations, lr 0.02, 15000 lines; use it with ``starts=1`` for the paper's solver).
        num_points: FPS subsample size of both clouds for the loss (``None``: all points).
        seed: seeds the lines of every line-based loss.
        progress: show a progress bar with the loss (and the monitor's values).
        monitor: optional callback, e.g. the rotation error when ground truth is known.
        center: register centred clouds (:func:`~linereg.registration.methods.run_centered`).
        starts: initial poses of the first stage (1..7, see :func:`start_poses`; the default 4
            is the identity and +90 deg about x, y, z: no benchmark pair needed the others).
        start_angle_deg: rotation of the extra starts.
        select: loss config that picks the best start (lowest value), in the solver's units
            (clouds centred and scaled into the unit ball).
    """

    def __init__(
        self,
        stages: Sequence[Stage | Mapping[str, Any]] | str = "default",
        num_points: int | None = 2048,
        seed: int = 0,
        progress: bool = False,
        monitor: Monitor | None = None,
        center: bool = True,
        starts: int = 4,
        start_angle_deg: float = 90.0,
        select: Mapping[str, Any] | None = None,
    ) -> None:
        self.stages = _as_stages(stages)
        self.losses = []
        for i, stage in enumerate(self.stages):
            loss_cfg = dict(stage.loss)
            if loss_cfg.get("name") == "line_intersection":
                loss_cfg.setdefault("seed", seed + i)
            loss = build_loss(loss_cfg)
            if loss.needs_gt:
                raise ValueError(
                    f"stage {i}: loss {stage.loss.get('name')!r} needs ground truth; registration is unsupervised"
                )
            if not isinstance(loss, AlignmentLoss):
                raise ValueError(
                    f"stage {i}: loss {stage.loss.get('name')!r} is not an alignment metric between two clouds"
                )
            self.losses.append(loss)
        self.start_poses = start_poses(starts, start_angle_deg)
        select = dict(DEFAULT_SELECT if select is None else select)
        if select.get("name") == "line_intersection":
            select.setdefault("seed", seed + len(self.stages))
        self.select = build_loss(select)
        self.num_points = num_points
        self.progress = progress
        self.monitor = monitor
        self.center = center

    def _optimise(self, src_t, tgt_t, unscale):
        poses = self.start_poses.clone()
        curve: list[float] = []
        bar = tqdm(
            total=sum(s.iterations for s in self.stages), disable=not self.progress, desc="register", leave=False
        )
        chosen = 0
        for stage, loss in zip(self.stages, self.losses, strict=True):
            src, tgt = _subsample(src_t, stage.points), _subsample(tgt_t, stage.points)
            poses = self._run_stage(stage, loss, src, tgt, poses, curve, bar, unscale)
            if len(poses) > 1:
                with torch.no_grad():
                    moved = transform_points(poses, src_t.expand(len(poses), -1, -1))
                    values, _ = self.select.metric(moved, tgt_t.expand(len(poses), -1, -1).contiguous())
                chosen = int(values.argmin())
                poses = poses[chosen : chosen + 1]
        bar.close()
        return poses[0], {"loss_curve": curve, "start": chosen}

    def _run_stage(self, stage, loss, src, tgt, poses, curve, bar, unscale) -> torch.Tensor:
        """:func:`adam_stage` with the progress bar and the monitor."""
        shown: dict[str, float] = {}

        def report(transform: torch.Tensor) -> None:
            nonlocal shown
            if self.monitor is not None:
                shown = self.monitor(len(curve), unscale(transform.numpy()), curve[-1])
            bar.set_postfix(loss=f"{curve[-1]:.4g}", **{k: f"{v:.3g}" for k, v in shown.items()})
            bar.update()

        return adam_stage(stage, loss, src, tgt, poses, curve, report)


def adam_stage(
    stage: Stage,
    loss: AlignmentLoss,
    src: torch.Tensor,
    tgt: torch.Tensor,
    poses: torch.Tensor,
    curve: list[float] | None = None,
    report: Callable[[torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Adam on ``xi`` in se(3) (``T = exp(xi) @ pose``) with a cosine schedule, from every pose at once.

    Args:
        stage: iterations and peak learning rate (``stage.loss`` is not read: ``loss`` is built).
        loss: alignment loss; its ``metric`` gives one value per pose.
        src: ``(N, 3)`` source points.
        tgt: ``(M, 3)`` target points.
        poses: ``(K, 4, 4)`` starting transforms.
        curve: receives the lowest loss over the poses at each iteration.
        report: called after every iteration with the (detached) transform of the lowest loss.

    Returns:
        ``(K, 4, 4)`` final transforms.
    """
    count = len(poses)
    src_batch, tgt_batch = src.expand(count, -1, -1), tgt.expand(count, -1, -1).contiguous()
    xi = torch.zeros(count, 6, dtype=poses.dtype, device=poses.device, requires_grad=True)
    optimiser = torch.optim.Adam([xi], lr=stage.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=max(stage.iterations, 1))
    for _ in range(stage.iterations):
        transforms = se3_exp(xi) @ poses
        values, _ = loss.metric(transform_points(transforms, src_batch), tgt_batch)
        optimiser.zero_grad()
        values.sum().backward()
        optimiser.step()
        schedule.step()
        if curve is not None or report is not None:
            best = int(values.argmin())
            if curve is not None:
                curve.append(values[best].item())
            if report is not None:
                report(transforms[best].detach())
    return (se3_exp(xi) @ poses).detach()


class IRLSRegistration(_Solver):
    """The supplementary's SVD solver on the line metric's correspondences.

    Args:
        iterations: IRLS steps (each with new lines).
        num_points: FPS subsample size for the metric.
        seed: seeds the lines.
        progress, monitor, center: as for :class:`AdamRegistration`.
        **options: :class:`~linereg.losses.line_intersection.LineMetricOptions` fields.
    """

    def __init__(
        self,
        iterations: int = 60,
        num_points: int | None = 2048,
        seed: int = 0,
        progress: bool = False,
        monitor: Monitor | None = None,
        center: bool = True,
        variant: str = "paper",
        **options: Any,
    ) -> None:
        self.options = LineMetricOptions.for_variant(variant, **options)
        self.iterations = iterations
        self.num_points = num_points
        self.seed = seed
        self.progress = progress
        self.monitor = monitor
        self.center = center

    def _optimise(self, src_t, tgt_t, unscale):
        generator = torch.Generator().manual_seed(self.seed)
        pose = torch.eye(4, dtype=torch.float64)
        curve: list[float] = []
        shown: dict[str, float] = {}
        for step in tqdm(range(self.iterations), disable=not self.progress, desc="register (svd)", leave=False):
            pairs = line_correspondences(
                transform_points(pose, src_t), tgt_t, options=self.options, generator=generator
            )
            if len(pairs.weights) < 3:
                break
            update = weighted_procrustes(pairs.src[None], pairs.tgt[None], pairs.weights[None])
            if bool(update.valid[0]):
                pose = update.transform[0] @ pose
            curve.append(float((pairs.weights * (pairs.src - pairs.tgt).square().sum(1)).sum() / pairs.weights.sum()))
            if self.monitor is not None:
                shown = self.monitor(step + 1, unscale(pose.numpy()), curve[-1])
        return pose, {"loss_curve": curve, **shown}


class NearestTarget:
    """Nearest target point of many query points, the target indexed once.

    A ``scipy`` KD-tree on the CPU (all queries of a batch in one call), brute force
    ``torch.cdist`` on other devices.

    Args:
        tgt: ``(M, 3)`` target points.
    """

    def __init__(self, tgt: torch.Tensor) -> None:
        self.tgt = tgt
        self._tree = cKDTree(tgt.detach().numpy()) if tgt.device.type == "cpu" else None

    def __call__(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(distances, indices)`` of shape ``points.shape[:-1]`` (no gradient)."""
        with torch.no_grad():
            if self._tree is not None:
                flat = points.detach().reshape(-1, 3).numpy()
                _, idx = self._tree.query(flat, workers=1)
                idx = torch.from_numpy(idx.reshape(points.shape[:-1]))
            else:
                idx = torch.cdist(points.reshape(-1, 3)[None], self.tgt[None])[0].argmin(-1).reshape(points.shape[:-1])
            return (points - self.tgt[idx]).norm(dim=-1), idx


def fixed_scale_fit(poses: torch.Tensor, src: torch.Tensor, nearest: NearestTarget, nu: float) -> torch.Tensor:
    """Welsch cost of every source point's nearest target distance with a FIXED scale ``nu``.

    ``mean_i 1 - exp(-d_i^2 / 2 nu^2)`` with ``d_i`` the distance of ``T src_i`` to the target:
    0 when every source point lies on the target, 1 when none is near it. Unlike the paper's
    median-scaled metrics its value compares poses (lower is better).

    Args:
        poses: ``(K, 4, 4)`` source-to-target transforms.
        src: ``(N, 3)`` source points.
        nearest: the target's :class:`NearestTarget`.
        nu: Welsch scale, in the units of the clouds.

    Returns:
        ``(K,)`` costs in ``[0, 1]``.
    """
    distances, _ = nearest(transform_points(poses, src.expand(len(poses), -1, -1)))
    return (1.0 - torch.exp(-distances.square() / (2.0 * nu * nu))).mean(dim=1)


def chamfer_welsch_batched(
    x: torch.Tensor, y: torch.Tensor, nu0: float, two_sided: torch.Tensor | None = None
) -> torch.Tensor:
    """CD-W (:func:`linereg.losses.chamfer.chamfer_welsch_distance`) of small batched clouds.

    The same value and gradient, with the nearest neighbours of all ``B`` pairs found by one
    dense ``cdist`` (no gradient) instead of two KD-trees per pair: faster below about a
    thousand points per cloud.

    Args:
        x: ``(B, N, 3)`` moved sources.
        y: ``(B, M, 3)`` targets.
        nu0: Welsch scale factor of the median nearest distance.
        two_sided: ``(B,)`` booleans; where False, only the source-to-target term counts (and
            sets the median): the model of a partial source inside a whole target, whose every
            point has a target neighbour but not the reverse. ``None``: all two-sided.

    Returns:
        ``(B,)`` values.
    """
    with torch.no_grad():  # the search in float32: only the indices are kept
        distances = torch.cdist(x.float(), y.float())
        x_to_y, y_to_x = distances.min(dim=2).indices, distances.min(dim=1).indices
    batch = torch.arange(len(x), device=x.device)[:, None]
    d_xy = (x - y[batch, x_to_y]).norm(dim=-1)
    d_yx = (y - x[batch, y_to_x]).norm(dim=-1)
    median = torch.cat([d_xy, d_yx], dim=1).detach().median(dim=1).values
    if two_sided is not None:
        median = torch.where(two_sided, median, d_xy.detach().median(dim=1).values)
    nu = (nu0 * median).clamp_min(1e-12)[:, None]
    target_term = welsch(d_yx, nu).mean(dim=1)
    if two_sided is not None:
        target_term = target_term * two_sided
    return welsch(d_xy, nu).mean(dim=1) + target_term


class _BatchedChamferWelsch:
    """:func:`chamfer_welsch_batched` as an alignment metric for :func:`adam_stage`; ``two_sided``
    as there, one flag per pose of the batch."""

    def __init__(self, nu0: float, two_sided: torch.Tensor | None = None) -> None:
        self.nu0 = nu0
        self.two_sided = two_sided

    def metric(self, src: torch.Tensor, tgt: torch.Tensor) -> tuple[torch.Tensor, dict[str, Any]]:
        two_sided = None if self.two_sided is None else self.two_sided.to(src.device)
        return chamfer_welsch_batched(src, tgt, self.nu0, two_sided), {}


def welsch_irls(poses: torch.Tensor, src: torch.Tensor, nearest: NearestTarget, nus: Sequence[float]) -> torch.Tensor:
    """Robust point-to-point ICP: one Welsch-weighted Procrustes step per scale in ``nus``.

    Every step matches each moved source point to its nearest target point, weights the pair
    by ``exp(-d^2 / 2 nu^2)`` and solves the weighted Procrustes problem in closed form.

    Args:
        poses: ``(K, 4, 4)`` starting transforms (refined independently, as a batch).
        src: ``(N, 3)`` source points.
        nearest: the target's :class:`NearestTarget`.
        nus: Welsch scales, one per step (e.g. decreasing: coarse to fine).

    Returns:
        ``(K, 4, 4)`` refined transforms.
    """
    src_batch = src.expand(len(poses), -1, -1)
    identity = torch.eye(4, dtype=poses.dtype, device=poses.device)
    for nu in nus:
        moved = transform_points(poses, src_batch)
        distances, idx = nearest(moved)
        weights = torch.exp(-distances.square() / (2.0 * nu * nu))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a degenerate step keeps its pose (valid=False)
            update = weighted_procrustes(moved, nearest.tgt[idx], weights)
        poses = torch.where(update.valid[:, None, None], update.transform, identity) @ poses
    return poses


@contextlib.contextmanager
def torch_threads(count: int | None):
    """Run the block with ``count`` torch CPU threads (``None``: leave them), then restore."""
    if count is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@dataclass(frozen=True)
class AdamRobustOptions:
    """Settings of :class:`AdamRobustRegistration` (lengths in the unit ball of the centred pair).

    Attributes:
        starts: initial rotations of the first round (:func:`start_poses`).
        coarse_points: FPS size of the source in the coarse stage (the target gets twice).
        coarse_iterations: Adam iterations of CD-W from every start, all starts at once.
        coarse_lr: peak learning rate (cosine decay) of the coarse stage.
        coarse_nu0: CD-W's ``nu0`` (a wide window: robust to partial overlap).
        coarse_sides: every start runs once per entry, all in one batch: ``"both"`` (CD-W, both
            directions) and/or ``"source"`` (the source-to-target term alone: a partial view
            of a whole target, whose centroid is off the target's; :func:`chamfer_welsch_batched`).
        polish_steps: Welsch IRLS steps from every coarse result (:func:`welsch_irls`) with
            the scales of :func:`polish_scales`.
        polish_nu: first IRLS scale.
        polish_end: last IRLS scale, times the target's median point spacing.
        select_nu: scale of the selection cost :func:`fixed_scale_fit`.
        doubt_ratio: the pose is doubtful when another candidate more than ``distinct_deg``
            away scores within this factor of the best cost, or the best cost exceeds
            ``max_cost``, or fewer than ``min_fitness`` of the source points lie within
            ``fitness_spacings`` target point spacings of the target; a doubtful first round
            triggers a second one from the 24 cube rotations with ``escalate_factor`` times the
            coarse iterations.
        distinct_deg: rotation gap between two candidates that count as different basins.
        max_cost: selection cost above which the fit itself is doubtful.
        min_fitness: fitness (as Open3D's, on the solver's clouds) below which the fit is
            doubtful: a right pose of a view inside the whole target scores 0.99-1, a wrong basin
            0.7-0.85 (docs/registration.md); pairs with partial overlap on both sides always get
            the second round.
        fitness_spacings: inlier distance of that fitness, in target point spacings.
        escalate_factor: coarse iterations multiplier of the second round.
        refine_iterations: optional Adam iterations of the line metric (candidate
            intersections, ``refine_lines`` lines, lr ``refine_lr``) after the selection; 0 skips.
    """

    starts: int = 4
    coarse_points: int = 256
    coarse_iterations: int = 100
    coarse_lr: float = 0.03
    coarse_nu0: float = 2.0
    coarse_sides: tuple[str, ...] = ("both", "source")
    polish_steps: int = 20
    polish_nu: float = 0.05
    polish_end: float = 0.3
    select_nu: float = 0.03
    doubt_ratio: float = 1.25
    distinct_deg: float = 10.0
    max_cost: float = 0.5
    min_fitness: float = 0.95
    fitness_spacings: float = 3.0
    escalate_factor: int = 2
    refine_iterations: int = 0
    refine_lines: int = 4000
    refine_lr: float = 0.002

    def __post_init__(self) -> None:
        positive = (
            "coarse_points",
            "coarse_lr",
            "coarse_nu0",
            "polish_nu",
            "polish_end",
            "select_nu",
            "distinct_deg",
            "max_cost",
            "fitness_spacings",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("coarse_iterations", "polish_steps", "refine_iterations"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.min_fitness <= 1:
            raise ValueError(f"min_fitness must be in [0, 1], got {self.min_fitness}")
        if self.doubt_ratio < 1:
            raise ValueError(f"doubt_ratio must be >= 1, got {self.doubt_ratio}")
        if self.escalate_factor < 1:
            raise ValueError(f"escalate_factor must be >= 1, got {self.escalate_factor}")
        sides = tuple(self.coarse_sides)
        if not sides or set(sides) - {"both", "source"} or len(set(sides)) < len(sides):
            raise ValueError(f"coarse_sides must be distinct entries of 'both' and 'source', got {self.coarse_sides!r}")
        object.__setattr__(self, "coarse_sides", sides)
        start_poses(self.starts)




class AdamRobustRegistration(_Solver):
    """``robust_adam``: the torch twin of the ``register`` default (the previous default), on any
    torch device: multi-start Adam on CD-W, Welsch IRLS, fixed-scale selection.

    1. Both clouds centred (:func:`~linereg.registration.methods.run_centered`) and scaled into the unit ball.
    2. Coarse: Adam on CD-W (``nu0`` 2), two-sided and source-to-target only (``coarse_sides``),
       from every start at once, on FPS subsets.
    3. Polish: Welsch IRLS from every coarse result on the full clouds (``num_points``).
    4. Select the candidate with the lowest :func:`fixed_scale_fit`. When the choice is doubtful
       (another basin scores nearly as well, or the fit is poor), run a second round from the
       24 cube rotations with a longer coarse stage and select among all candidates.
    5. Optionally refine with the line metric (``refine_iterations``).

    The result's ``info`` holds ``fitness`` and ``inlier_rmse`` (Open3D's definitions, within
    ``fitness_threshold`` in input units; default 3 times the target's median point spacing),
    ``converged`` (the final choice is not doubtful), ``confidence`` (``1 - best cost /
    cost of the best distinct basin``; 1 without a rival), ``rounds``, ``starts`` (candidates:
    starts x coarse sides), the selection ``cost``, and ``warnings`` (collinear clouds).

    Args:
        options: :class:`AdamRobustOptions` or a mapping of its fields.
        num_points: FPS size of each cloud for the polish, selection and refinement.
        seed: seeds the refinement's lines.
        threads: torch CPU threads (``None``: 1 up to 20000 points per cloud, else torch's default;
            small problems lose time to thread hand-offs, more so on a busy machine).
        device: torch device of the computation (``"cpu"``, ``"cuda"``, ...).
        fitness_threshold: inlier distance of ``fitness`` / ``inlier_rmse`` in input units.
        progress, monitor: accepted for interface parity with :class:`AdamRegistration` (the
            solver runs well under a second; ``monitor`` is called once with the result).
        center: register centred clouds.
    """

    def __init__(
        self,
        options: AdamRobustOptions | Mapping[str, Any] | None = None,
        num_points: int | None = 2048,
        seed: int = 0,
        threads: int | None = None,
        device: str = "cpu",
        fitness_threshold: float | None = None,
        progress: bool = False,
        monitor: Monitor | None = None,
        center: bool = True,
    ) -> None:
        options = options_from(options, AdamRobustOptions)
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1 or None, got {threads}")
        if fitness_threshold is not None and not fitness_threshold > 0:
            raise ValueError(f"fitness_threshold must be > 0 or None, got {fitness_threshold}")
        self.options = options
        self.num_points = num_points
        self.seed = seed
        self.threads = threads
        self.device = torch.device(device)
        self.fitness_threshold = fitness_threshold
        self.monitor = monitor
        self.center = center
        self._refine_loss = (
            build_loss(
                {
                    "name": "line_intersection",
                    "intersection": "candidates",
                    "num_lines": options.refine_lines,
                    "seed": seed,
                }
            )
            if options.refine_iterations
            else None
        )

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None, *, init: np.ndarray | None = None) -> MethodResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)``; ``init (4, 4)`` is an initial guess applied
        to the source first (the multi-start then explores around it)."""
        check_points(src, "source", batched=False)
        check_points(tgt, "target", batched=False)
        found = [degeneracy(src, "source"), degeneracy(tgt, "target")]
        notes = [note for note in found if note is not None]
        for note in notes:
            warnings.warn(note, stacklevel=2)
        src = np.asarray(src, dtype=np.float64)
        if init is not None:
            init = np.asarray(init, dtype=np.float64)
            check_transform(torch.from_numpy(init), "init")
            src = src @ init[:3, :3].T + init[:3, 3]
        threads = self.threads
        if threads is None and self.device.type == "cpu":
            threads = 1 if max(len(src), len(tgt)) <= 20000 else None
        with torch_threads(threads):
            result = run_centered(self._solve, src, tgt, center=self.center)
        transform = result.transform if init is None else result.transform @ init
        tgt_fit = _subsample(np.asarray(tgt, dtype=np.float64), self.num_points)
        threshold = self.fitness_threshold
        if threshold is None:
            threshold = 3.0 * point_spacing(tgt_fit)
        quality = alignment_quality(_subsample(src, self.num_points), tgt_fit, result.transform, threshold)
        info = {**result.info, **quality, "fitness_threshold": threshold, "warnings": notes}
        if self.monitor is not None:
            info.update(self.monitor(1, transform, info["cost"]))
        return MethodResult(transform=transform, seconds=result.seconds, info=info)

    def _round(self, src, nearest, src_coarse, tgt_coarse, starts, iterations, nus):
        """Coarse CD-W from every start, then IRLS polish: ``(K, 4, 4)`` candidates, costs ``(K,)``."""
        options = self.options
        stage = Stage(loss={}, iterations=iterations, lr=options.coarse_lr)
        two_sided = torch.tensor([side == "both" for side in options.coarse_sides]).repeat_interleave(len(starts))
        loss = _BatchedChamferWelsch(options.coarse_nu0, two_sided)
        starts = starts.to(src).repeat(len(options.coarse_sides), 1, 1)
        poses = adam_stage(stage, loss, src_coarse, tgt_coarse, starts)
        poses = welsch_irls(poses, src, nearest, nus)
        return poses, fixed_scale_fit(poses, src, nearest, options.select_nu)

    def _doubt(self, poses: torch.Tensor, costs: torch.Tensor, src, nearest, inlier_distance) -> tuple[bool, float]:
        """``(doubtful, confidence)`` of the lowest-cost candidate (see :class:`AdamRobustOptions`)."""
        options = self.options
        best = int(costs.argmin())
        distances, _ = nearest(transform_points(poses[best], src))
        fitness = float((distances <= inlier_distance).double().mean())
        poor = float(costs[best]) > options.max_cost or fitness < options.min_fitness
        rivals = rotation_error_deg(poses[:, :3, :3], poses[best, :3, :3]) > options.distinct_deg
        if not bool(rivals.any()):
            return poor, 1.0
        rival = float(costs[rivals].min())
        return poor or rival < options.doubt_ratio * float(costs[best]), 1.0 - float(costs[best]) / max(rival, 1e-12)

    def _solve(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        options = self.options
        src_t, tgt_t, radius = _normalise(_subsample(src, self.num_points), _subsample(tgt, self.num_points))
        src_t, tgt_t = src_t.to(self.device), tgt_t.to(self.device)
        src_coarse = _subsample(src_t, options.coarse_points)
        tgt_coarse = _subsample(tgt_t, 2 * options.coarse_points)
        nearest = NearestTarget(tgt_t)
        spacing = point_spacing(tgt_t.cpu().numpy())
        nus = polish_scales(options, spacing)
        inlier_distance = options.fitness_spacings * spacing
        poses, costs = self._round(
            src_t, nearest, src_coarse, tgt_coarse, start_poses(options.starts), options.coarse_iterations, nus
        )
        doubtful, confidence = self._doubt(poses, costs, src_t, nearest, inlier_distance)
        rounds = 1
        if doubtful:
            iterations = options.escalate_factor * options.coarse_iterations
            cube = torch.eye(4, dtype=torch.float64).repeat(24, 1, 1)
            cube[:, :3, :3] = torch.from_numpy(cube_rotations())
            more, more_costs = self._round(src_t, nearest, src_coarse, tgt_coarse, cube, iterations, nus)
            poses, costs = torch.cat([poses, more]), torch.cat([costs, more_costs])
            doubtful, confidence = self._doubt(poses, costs, src_t, nearest, inlier_distance)
            rounds = 2
        best = int(costs.argmin())
        pose = poses[best]
        curve: list[float] = []
        if options.refine_iterations:
            stage = Stage(loss={}, iterations=options.refine_iterations, lr=options.refine_lr)
            pose = adam_stage(stage, self._refine_loss, src_t, tgt_t, pose[None], curve)[0]
        info = {
            "converged": not doubtful,
            "confidence": confidence,
            "cost": float(costs[best]),
            "rounds": rounds,
            "starts": len(poses),
            "loss_curve": curve,
        }
        return MethodResult(transform=_unscale(pose.double().cpu().numpy(), radius), info=info)


# The constructors' defaults are the methods' defaults: the classes themselves are the builders.
METHODS.register("robust_adam")(AdamRobustRegistration)
METHODS.register("adam_loss")(AdamRegistration)
METHODS.register("svd_irls")(IRLSRegistration)
