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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from linereg.losses import build_loss
from linereg.losses.base import AlignmentLoss
from linereg.losses.line_intersection import LineMetricOptions, line_correspondences
from linereg.pointcloud import farthest_point_sampling
from linereg.procrustes import weighted_procrustes
from linereg.registration.methods import METHODS, MethodResult, run_centered
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


# The default schedule of adam_loss, chosen on the Human/Airplane benchmark pairs: a cheap
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

    @classmethod
    def from_register_settings(cls, settings: Mapping[str, Any]) -> dict[str, Any]:
        """This method's config from ``linereg-register``'s settings (``configs/register/register.yaml``):
        ``stages``, or one stage of ``loss`` with ``iterations`` and ``lr``; ``starts``, ``start_angle_deg``."""
        stages = settings["stages"]
        if settings.get("loss") is not None:
            loss = {"name": settings["loss"]} if isinstance(settings["loss"], str) else dict(settings["loss"])
            stages = [{"loss": loss, "iterations": settings["iterations"], "lr": settings["lr"]}]
        return {
            "name": "adam_loss",
            "stages": stages,
            "starts": settings["starts"],
            "start_angle_deg": settings["start_angle_deg"],
            **_common_settings(settings),
        }

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

    @classmethod
    def from_register_settings(cls, settings: Mapping[str, Any]) -> dict[str, Any]:
        """This method's config from ``linereg-register``'s settings (``configs/register/register.yaml``):
        its ``svd`` block (``iterations`` and :class:`~linereg.losses.line_intersection.LineMetricOptions`)."""
        svd = settings["svd"]
        return {"name": "svd_irls", "iterations": svd["iterations"], **svd["options"], **_common_settings(settings)}

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


def _common_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """The settings of ``linereg-register`` that every torch solver takes."""
    return {"num_points": settings["num_points"], "seed": settings["seed"], "progress": settings["progress"]}


# The constructors' defaults are the methods' defaults: the classes themselves are the builders.
METHODS.register("adam_loss")(AdamRegistration)
METHODS.register("svd_irls")(IRLSRegistration)
