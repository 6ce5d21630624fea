"""A network trained by ``python -m train`` as a registration method: its pose, and the solver's finish.

::

    learned = LearnedRegistration("rpm_ours_airplane", refine=True)
    learned(src, tgt)                          # MethodResult: the finished pose, info["path"]
    learned.predict_many([(src, tgt), ...])    # the network's poses, forward in batches

The network starts and the solver finishes (:class:`Finish`): the network's pose
is polished locally on the clouds in their own units and judged by register's check; only when the
check does not trust it does the whole solver run, and its answer replaces the polished network
pose when the check trusts it, or when neither is trusted and it lies closer to the target
(:func:`fits_better`). A flip of the solver never replaces a trusted network pose, and a wrong
network costs time where the solver's answer fits better.
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.registration.evaluation import Assessment, assess_registration
from linereg.registration.methods import METHODS, MethodResult, run_with_init, translation
from linereg.registration.trust import soft_fitness, spacing_of, surface_points

DEFAULT_SOLVER = "robust"

POLISH_ONLY = {
    "starts": 1,
    "coarse_steps": 0,
    "rounds": 1,
    "global_candidates": "never",
    "polish_nu": 0.2,
    "polish_steps": 40,
}
"""The solver's options of the polish that finishes a network's pose: from that pose alone, no
coarse stage, no later round, no global candidates (the Welsch IRLS polish and the fine steps), both
clouds keeping the network's relative pose (:meth:`Finish.polish`). The polish starts at a Welsch
scale of 0.2 (the solver's polish: 0.05), falling over 40 steps, so that a network pose a few degrees
off reaches the basin; coarse steps first would leave poses trusted that are wrong on 256-point views.
Both chosen on the Airplane protocol's validation views (``scripts/studies/finish_polish.py``)."""


FINISH_ITERATIONS = 2
"""RPM-Net's iterations when the solver finishes its pose (its own: 5). After 2 the polish trusts the
same poses at the same errors on the Airplane and Real protocols' validation views, at 0.5-0.6x the
forward (``scripts/studies/finish_costs.py --iterations``)."""


class _Prepared(NamedTuple):
    """One pair as the network reads it: FPS subsets in its cube, their normals, and the maps back
    (the clouds' centroids, then ``x' = (x - center) * scale``)."""

    src: np.ndarray
    tgt: np.ndarray
    src_normals: np.ndarray
    tgt_normals: np.ndarray
    src_centroid: np.ndarray
    tgt_centroid: np.ndarray
    center: np.ndarray
    scale: float


class LearnedRegistration:
    """A network trained by ``python -m train`` as a registration method, optionally finished by the solver.

    The clouds are centred, farthest-point sampled to the run's ``trainer.num_points``, scaled
    together into the cube its training pairs were scaled into (the checkpoint's ``half_extent``),
    given normals (estimated on the subsets); of the model's iterates, the one the run's ``iterate``
    rule chooses (:mod:`linereg.registration.iterates`, from the checkpoint's config) is mapped back
    to the original frames.

    Args:
        checkpoint: a checkpoint file, a run folder (the checkpoint the run evaluated, else
            ``best.pt``) or a pretrained name (:mod:`linereg.pretrained`).
        device: torch device of the model (loaded once per process and device).
        num_points: points per cloud fed to the model (``None``: the run's ``trainer.num_points``).
        refine: finish the network's pose with the solver (:class:`Finish`); a mapping gives
            :class:`~linereg.registration.robust.RobustOptions` fields of both the polish and the
            solver (numpy, on the CPU whatever ``device``). RPM-Net then runs
            :data:`FINISH_ITERATIONS` iterations.
        iterations: the model's iterations in evaluation mode (RPM-Net's and FMR's ``test_iters``;
            ``None``: the model's own, or :data:`FINISH_ITERATIONS` for RPM-Net with ``refine``).
    """

    def __init__(
        self,
        checkpoint: str | Path,
        *,
        device: str | Any = "cpu",
        num_points: int | None = None,
        refine: bool | Mapping[str, Any] = False,
        iterations: int | None = None,
    ) -> None:
        import torch

        from linereg.models.rpmnet import RPMNet
        from linereg.registration.iterates import IterateRule

        self.model, state = _loaded(str(checkpoint), str(device))
        if iterations is None and refine and isinstance(self.model, RPMNet):
            iterations = FINISH_ITERATIONS
        if iterations is not None and (iterations < 1 or not hasattr(self.model, "test_iters")):
            raise ValueError(f"iterations={iterations}: needs a model with iterations (RPM-Net, FMR) and >= 1")
        self.iterations = iterations
        self.device = torch.device(device)
        self.checkpoint = state["path"]
        self.iterate = IterateRule.from_config(state["config"].get("iterate"))
        self.num_points = num_points or state["config"].get("trainer", {}).get("num_points") or 1024
        self.half_extent = state["half_extent"]
        self.finish = None
        if refine:
            self.finish = Finish(refine if isinstance(refine, Mapping) else None)

    def _prepare(self, src: np.ndarray, tgt: np.ndarray) -> _Prepared:
        """``src (N, 3)`` and ``tgt (M, 3)`` as the network reads them."""
        from linereg.pointcloud import estimate_normals, fit_into_cube

        src_centroid, tgt_centroid = src.mean(axis=0), tgt.mean(axis=0)
        clouds = (fps(src - src_centroid, self.num_points), fps(tgt - tgt_centroid, self.num_points))
        center, scale = np.zeros(3), 1.0  # half_extent None: the clouds' own units
        if self.half_extent is not None:
            clouds, center, scale = fit_into_cube(*clouds, half_extent=self.half_extent)
        normals = [estimate_normals(cloud) for cloud in clouds]
        return _Prepared(*clouds, *normals, src_centroid, tgt_centroid, center, scale)

    def predict_many(self, pairs: Sequence[tuple[np.ndarray, np.ndarray]], batch_size: int = 32) -> list[np.ndarray]:
        """The network's ``(4, 4)`` pose of every pair ``(src (N, 3), tgt (M, 3))``, in order: pairs
        whose subsets have the same sizes go through the model together, ``batch_size`` at a time."""
        from linereg.pointcloud import scale_transform

        prepared = [self._prepare(np.asarray(src, np.float64), np.asarray(tgt, np.float64)) for src, tgt in pairs]
        poses: list[np.ndarray | None] = [None] * len(prepared)
        groups: dict[tuple[int, int], list[int]] = {}
        for index, item in enumerate(prepared):
            groups.setdefault((len(item.src), len(item.tgt)), []).append(index)
        for members in groups.values():
            for first in range(0, len(members), batch_size):
                chunk = members[first : first + batch_size]
                for index, pose in zip(chunk, self._forward([prepared[i] for i in chunk]), strict=True):
                    item = prepared[index]
                    # back to the original frames: the inverse of x' = (x - c) s is x = (x' + c s) / s
                    centred = scale_transform(pose, -item.center * item.scale, 1.0 / item.scale)
                    poses[index] = translation(item.tgt_centroid) @ centred @ translation(-item.src_centroid)
        return poses

    def _forward(self, items: list[_Prepared]) -> np.ndarray:
        """``(B, 4, 4)`` poses of the chosen iterate for prepared pairs of equal sizes, in the cube."""
        import torch

        from linereg.structures import PairBatch

        def stacked(field: str):
            return torch.from_numpy(np.stack([getattr(item, field) for item in items])).float()

        batch = PairBatch(
            src_xyz=stacked("src"),
            tgt_xyz=stacked("tgt"),
            src_normals=stacked("src_normals"),
            tgt_normals=stacked("tgt_normals"),
        ).to(self.device)
        with torch.no_grad(), _test_iterations(self.model, self.iterations):
            output = self.model(batch)
            chosen, _ = self.iterate.select(output.transforms, batch.src_xyz, batch.tgt_xyz)
        return chosen.double().cpu().numpy()

    def __call__(
        self, src, tgt, src_normals=None, tgt_normals=None, *, start: np.ndarray | None = None
    ) -> MethodResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)`` (numpy; normals are re-estimated on the subsets);
        ``start``: the network's pose when already predicted (:meth:`predict_many`)."""
        began = time.perf_counter()
        network = self.predict_many([(src, tgt)])[0] if start is None else np.asarray(start, dtype=np.float64)
        seconds = time.perf_counter() - began
        info: dict[str, Any] = {
            "checkpoint": self.checkpoint,
            "iterate": self.iterate.as_config(),
            "network_transform": network.tolist(),
        }
        if self.iterations is not None:
            info["iterations"] = self.iterations
        if self.finish is None:
            return MethodResult(transform=network, seconds=seconds, info={**info, "path": "network"})
        finished = self.finish(np.asarray(src, np.float64), np.asarray(tgt, np.float64), network)
        return MethodResult(
            transform=finished.transform,
            seconds=seconds + finished.seconds,
            info={**info, **finished.info},
            solution=finished.solution,
        )


class Finish:
    """The solver's finish of a network's pose (module docstring): ``finish(src, tgt, start)``.

    Args:
        options: :class:`~linereg.registration.robust.RobustOptions` fields of both the polish
            (on top of :data:`POLISH_ONLY`) and the solver.
    """

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        options = dict(options or {})
        self.polisher = METHODS.build({"name": DEFAULT_SOLVER, "center": False, "options": {**POLISH_ONLY, **options}})
        self.solver = METHODS.build({"name": DEFAULT_SOLVER, "options": options})

    def __call__(self, src: np.ndarray, tgt: np.ndarray, start: np.ndarray) -> MethodResult:
        """The network's pose ``start (4, 4)`` finished on ``src (N, 3)`` and ``tgt (M, 3)`` in their own
        units: a local polish from it (:data:`POLISH_ONLY`); when register's check
        (:func:`~linereg.registration.evaluation.assess_registration`) does not trust it, the whole
        solver from scratch, whose answer replaces the polished one when the check trusts it, or
        when neither is trusted and it fits better (:func:`fits_better`). ``info["path"]``:
        ``"polished network"`` or ``"solver"``, with ``"solver_ran"``, and the seconds of the polish
        with its check (``"polish_seconds"``) and of the solver with its check (``"solver_seconds"``,
        0 when it did not run)."""
        began = time.perf_counter()
        polished = self.polish(src, tgt, start)
        check = pose_check(src, tgt)
        judged = check(polished.transform)
        polished_at = time.perf_counter()
        info = {"solver_ran": False, "polished_confident": judged.confident, "polish_seconds": polished_at - began}
        if judged.confident:
            info |= {"path": "polished network", "solver_seconds": 0.0}
            return MethodResult(polished.transform, polished_at - began, {**polished.info, **info}, polished.solution)
        solved = self.solver(src, tgt)
        rival = check(solved.transform)
        info |= {"solver_ran": True, "solver_seconds": time.perf_counter() - polished_at}
        solver_wins = rival.confident or fits_better(src, tgt, solved.transform, polished.transform)
        winner, path = (solved, "solver") if solver_wins else (polished, "polished network")
        seconds = time.perf_counter() - began
        return MethodResult(winner.transform, seconds, {**winner.info, **info, "path": path}, winner.solution)

    def polish(self, src: np.ndarray, tgt: np.ndarray, start: np.ndarray) -> MethodResult:
        """The local polish of ``start (4, 4)``: both clouds shifted by the target's centroid alone
        (centring each on its own centroid, as the solver does from scratch, would drop the
        network's translation)."""
        centroid = tgt.mean(axis=0)
        polished = run_with_init(self.polisher, src, tgt - centroid, init=translation(-centroid) @ start)
        transform = translation(centroid) @ polished.transform
        return MethodResult(transform, polished.seconds, polished.info, polished.solution)


def pose_check(src: np.ndarray, tgt: np.ndarray) -> Callable[[np.ndarray], Assessment]:
    """``register``'s check (:func:`~linereg.registration.evaluation.assess_registration`) of poses
    ``(4, 4)`` mapping ``src (N, 3)`` onto ``tgt (M, 3)``, the target's KD-tree and clutter test
    (:func:`~linereg.registration.trust.surface_points`) made once for every pose it judges."""
    index = NearestNeighbors(tgt)
    surface = surface_points(tgt, src, target_index=index)
    return functools.partial(assess_registration, src, tgt, on_surface=surface, target_index=index)


@contextlib.contextmanager
def _test_iterations(model, iterations: int | None):
    """``model`` running ``iterations`` iterations in evaluation mode within the block (``None``: its
    own); the model is shared by every :class:`LearnedRegistration` of its checkpoint in the process."""
    if iterations is None:
        yield
        return
    own, model.test_iters = model.test_iters, iterations
    try:
        yield
    finally:
        model.test_iters = own


@functools.lru_cache(maxsize=4)
def _loaded(checkpoint: str, device: str):
    """:func:`linereg.models.load_model` with :func:`upgrade_checkpoint`, once per checkpoint and device
    in a process (the model is only read: evaluation mode, ``torch.no_grad``)."""
    from linereg.models import load_model

    model, state = load_model(checkpoint, device)
    return model, upgrade_checkpoint(state)


def fits_better(src: np.ndarray, tgt: np.ndarray, first: np.ndarray, second: np.ndarray) -> bool:
    """Whether the pose ``first (4, 4)`` maps ``src (N, 3)`` closer onto ``tgt (M, 3)`` than ``second``:
    the larger Gaussian score at one point spacing of the target
    (:func:`~linereg.registration.trust.soft_fitness`, the score the check's free-motion and
    symmetry tests compare). Neither answer is trusted here; the inlier share within 3 spacings
    favours loose wrong poses, and the tight share within 1.5 is not measured on poses that fail
    the inlier test (chosen on the validation pairs of ``scripts/studies/finish_fallback.py``)."""
    scores = soft_fitness(src, NearestNeighbors(tgt), np.stack([first, second]), spacing_of(tgt))
    return bool(scores[0] > scores[1])


def upgrade_checkpoint(state: dict[str, Any]) -> dict[str, Any]:
    """``state`` with ``half_extent``, the cube ``[-h, h]^3`` its network was trained in (``None``: the
    pairs' own units), in place: a checkpoint written before training recorded it gets the cube of its
    dataset config (:func:`linereg.datasets.configured_half_extent`)."""
    from linereg.datasets import configured_half_extent

    if "half_extent" not in state:
        state["half_extent"] = configured_half_extent(state["config"].get("dataset") or {})
    return state
