"""The ``register`` default in numpy and scipy: multi-start CD-W, Welsch IRLS, fixed-scale selection.

No torch on this path (nor Open3D, numba or matplotlib): ``linereg.register`` and the
``linereg-register`` command start in about the time numpy and scipy take to import.

1. Both clouds centred (as :func:`~linereg.registration.methods.run_centered` centres them) and
   scaled together into the unit ball; FPS subsets of ``num_points`` for the polish and the selection.
2. Round 1, coarse: IRLS on CD-W (:func:`~linereg.registration.coarse.cdw_irls`, ``nu = nu0 *
   median`` of the nearest distances, recomputed every step) from every start on small FPS
   subsets, once with both directions and once with the source-to-target term alone (a partial
   view inside a whole target). All candidates of a round form one batch; merged ones are dropped.
3. Polish: Welsch IRLS of the source-to-target distances with falling fixed scales
   (:func:`~linereg.registration.welsch.welsch_irls`).
4. Select the candidate with the lowest fixed-scale cost
   (:func:`~linereg.registration.welsch.fixed_scale_cost`). When the choice is doubtful
   (:func:`doubt`: a distinct rival nearly as good, a high cost, a low fitness), round 2 runs
   Adam on CD-W (:func:`~linereg.registration.coarse.cdw_adam`) from the same starts; still
   doubtful, round 3 searches every pose of a grid (:func:`~linereg.registration.search.pose_search`)
   and runs the one-sided IRLS from the best distinct poses. Each round ends with the polish, and
   the doubt test runs over every candidate so far. After a doubtful first round the final choice
   among all candidates is the lowest value of the polish's own objective (Welsch at its last
   scale; ``doubtful_select``): every candidate is a local minimum of that objective, while the
   coarser selection scale rewards a wrong pose that brings more of a partly overlapping view
   near the target.
5. After a doubtful first round on a target with more points than the subset (a scan), the dense
   check replaces rounds 2 and 3 as the next step (:mod:`~linereg.registration.global_stage`):
   the first round's candidates are polished against a dense target and judged by their dense
   costs, and the best is doubtful when it fails the confidence test of :func:`linereg.register`
   against that target or a distinct rival scores nearly as well. The subset test fires on every
   partly overlapping scan; this one only on wrong answers, which then bring FPFH + RANSAC and FGR
   candidates (features computed once), one at a time, each polished and judged the same way,
   until the choice is not doubtful. Rounds 2 and 3 follow only while it still is, their
   candidates judged the same way, and the choice ends with plane-to-plane steps against the
   dense target instead of step 6. One flow runs every pair: from this step on, its doubt tests
   and its final choice read the dense costs.
6. Fine polish of the chosen pose when the source lies on the target (fitness at least
   ``fine_fitness``): the IRLS goes on to ``fine_end`` times the point spacing
   (:func:`~linereg.registration.welsch.fine_scales`); partly overlapping scans keep the polish's
   pose. Then, when the two clouds are independent samplings of the surface (almost no source
   point coincides with a target point), a few plane-to-plane steps
   (:func:`~linereg.registration.planes.plane_to_plane_irls`, Generalized-ICP) remove the
   point-to-point fit's sampling offset.

The settings are :class:`~linereg.registration.robust_options.RobustOptions`, one group per stage;
:meth:`RobustRegistration.solve` returns a :class:`~linereg.registration.robust_result.RobustResult`
(the chosen pose, every candidate with its costs and origin, the steps that ran).
"""

from __future__ import annotations

import sys
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from linereg.checks import check_points
from linereg.fps import farthest_point_subset as fps
from linereg.knn import NearestNeighbors
from linereg.registration.coarse import cdw_adam, cdw_irls
from linereg.registration.evaluation import point_spacing
from linereg.registration.global_stage import DenseTarget, dense_costs, dense_doubt, dense_polish, dense_target
from linereg.registration.methods import METHODS, MethodResult, translation
from linereg.registration.planes import plane_to_plane_irls, surface_covariances
from linereg.registration.poses import (
    Poses,
    apply,
    as_matrices,
    axis_rotations,
    distinct_best,
    merged_into_earlier,
    rotation_gap_deg,
    spread_rotations,
)
from linereg.registration.robust_options import RobustOptions, SelectOptions, robust_options
from linereg.registration.robust_result import CHECK, GLOBAL, STAGES, Candidate, RobustResult, Step
from linereg.registration.search import pose_search
from linereg.registration.welsch import fine_scales, fixed_scale_cost, polish_scales, welsch_irls

__all__ = ["RobustOptions", "RobustRegistration", "RobustResult", "degeneracy", "doubt"]

PROGRESS_AFTER = 1.0
"""Seconds into a registration after which ``progress=True`` prints each stage as it starts."""


def degeneracy(points: np.ndarray, name: str) -> str | None:
    """``None`` for a cloud spread in 2 or 3 directions; a warning for a collinear one.

    Raises:
        ValueError: all points coincide (no direction at all), naming the cloud.
    """
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    scale = max(float(np.abs(points).max()), 1e-300)
    if singular[0] <= 1e-9 * scale * np.sqrt(len(points)):
        raise ValueError(f"{name}: all {len(points)} points coincide; no rotation can be determined")
    if singular[1] <= 1e-6 * singular[0]:
        return f"{name}: the {len(points)} points are collinear; the rotation about their line is arbitrary"
    return None


def doubt(
    select: SelectOptions,
    poses: Poses,
    costs: np.ndarray,
    src: np.ndarray,
    tgt_index: NearestNeighbors,
    inlier_distance: float,
    best: int | None = None,
    ranking: np.ndarray | None = None,
) -> tuple[bool, float, float]:
    """Whether candidate ``best`` of ``poses`` is doubtful (the test of
    :class:`~linereg.registration.robust_options.SelectOptions`).

    Args:
        select: the thresholds of the test.
        poses: ``K`` candidates; costs: their selection costs ``(K,)``, by which the test judges.
        src: ``(N, 3)`` source points; tgt_index: the target's index.
        inlier_distance: inlier distance of the fitness.
        best: the candidate judged (default: the lowest cost).
        ranking: ``(K,)`` values of the cost that chose it (default: ``costs``).

    Returns:
        ``(doubtful, confidence, fitness)``: ``confidence`` is ``1 - ranking[best] / ranking`` of
        the best distinct rival (1 without a rival); ``fitness`` the share of source points within
        ``inlier_distance`` of the target.
    """
    best = int(costs.argmin()) if best is None else best
    ranking = costs if ranking is None else ranking
    distances, _ = tgt_index.query(apply((poses[0][best : best + 1], poses[1][best : best + 1]), src)[0])
    fitness = float((distances <= inlier_distance).mean())
    poor = float(costs[best]) > select.max_cost or fitness < select.min_fitness
    rivals = rotation_gap_deg(poses[0], poses[0][best]) > select.distinct_deg
    if not rivals.any():
        return poor, 1.0, fitness
    doubtful = poor or float(costs[rivals].min()) < select.doubt_ratio * float(costs[best])
    return doubtful, 1.0 - float(ranking[best]) / max(float(ranking[rivals].min()), 1e-12), fitness


@dataclass(frozen=True)
class _Pair:
    """One pair as the stages see it: FPS subsets scaled into the unit ball, the target indexed once."""

    src: np.ndarray
    tgt: np.ndarray
    src_whole: np.ndarray
    tgt_whole: np.ndarray
    src_coarse: np.ndarray
    tgt_coarse: np.ndarray
    tgt_index: NearestNeighbors
    spacing: float
    nus: np.ndarray
    inlier_distance: float


@dataclass(frozen=True)
class _Pool:
    """``K`` candidates in the solver's frame and where each came from: ``(round, origin, start)``
    (:class:`~linereg.registration.robust_result.Candidate`)."""

    poses: Poses
    origins: tuple[tuple[int, str, int], ...]

    def joined(self, other: _Pool) -> _Pool:
        """The candidates of ``self`` then ``other``."""
        poses = np.concatenate([self.poses[0], other.poses[0]]), np.concatenate([self.poses[1], other.poses[1]])
        return _Pool(poses, self.origins + other.origins)

    def taken(self, indices: np.ndarray) -> _Pool:
        """The candidates at ``indices``, in that order."""
        return _Pool((self.poses[0][indices], self.poses[1][indices]), tuple(self.origins[k] for k in indices))


class _Verdict(NamedTuple):
    """The doubt test of the best candidate: :func:`doubt`, or
    :func:`~linereg.registration.global_stage.dense_doubt` (``fitness`` ``None``)."""

    doubtful: bool
    margin: float
    fitness: float | None


@dataclass(frozen=True)
class _Choice:
    """The candidates left when the rounds end and the one chosen.

    Attributes:
        pool: the candidates; costs: ``(K,)`` the costs the doubt test judges by; ranking:
            ``(K,)`` the values the choice ranked by.
        best: the index of the chosen one; selection: ``"fixed"``, ``"polish"`` or ``"dense"``.
        verdict: the doubt test of that choice.
        history: every step that ran.
        dense: the dense target, when the dense judgement chose.
        checked: the first round's answer the dense check judged, with its dense cost (``None``
            when the check did not run).
    """

    pool: _Pool
    costs: np.ndarray
    ranking: np.ndarray
    best: int
    selection: str
    verdict: _Verdict
    history: tuple[Step, ...]
    dense: DenseTarget | None
    checked: tuple[_Pool, float] | None = None


class RobustRegistration:
    """The ``register`` default (numpy/scipy): multi-start IRLS on CD-W, Welsch IRLS polish,
    fixed-scale selection; when doubtful, on a scan the dense check and, if that doubts too, global
    candidates; then Adam on CD-W and a pose search (module docstring).

    :meth:`solve` returns a :class:`~linereg.registration.robust_result.RobustResult` (the chosen
    pose, the candidates left, every step with its doubt test, the final steps' flags); calling the
    method returns a :class:`~linereg.registration.methods.MethodResult` holding it as ``solution``,
    with the notes on the input clouds (collinear points) in ``info["warnings"]``.

    Args:
        options: :class:`~linereg.registration.robust_options.RobustOptions` or a mapping of its
            flat names (:data:`~linereg.registration.robust_options.FLAT_KEYS`) and groups.
        num_points: FPS size of each cloud for the polish and the selection.
        device: ``"cpu"`` only: the stages are numpy and scipy.
        center: register centred clouds.
        progress: print a line on stderr as each later stage starts, once the registration has run
            for :data:`PROGRESS_AFTER` seconds.
    """

    def __init__(
        self,
        options: RobustOptions | Mapping[str, Any] | None = None,
        num_points: int | None = 2048,
        device: str = "cpu",
        center: bool = True,
        progress: bool = False,
    ) -> None:
        if str(device) != "cpu":
            raise ValueError(
                f"method=robust runs on the CPU; device={device} is not supported: its stages are numpy "
                "and scipy (KD-tree searches of a few thousand points), which a GPU would not speed up"
            )
        if num_points is not None and num_points < 3:
            raise ValueError(f"num_points must be >= 3 or None, got {num_points}")
        self.options = robust_options(options)
        self.num_points = num_points
        self.center = center
        self.progress = progress
        self._started = 0.0

    @classmethod
    def from_register_settings(cls, settings: Mapping[str, Any]) -> dict[str, Any]:
        """This method's config from ``linereg-register``'s settings (``configs/register/register.yaml``):
        its ``robust`` block of :class:`~linereg.registration.robust_options.RobustOptions` names."""
        if settings.get("loss") is not None:
            raise ValueError(f"loss={settings['loss']} needs method=adam_loss (the robust solver has its own losses)")
        options = dict(settings.get("robust") or {})
        sizes = {"num_points": settings["num_points"], "progress": settings["progress"]}
        return {"name": "robust", "options": options, **sizes}

    def _stage(self, text: str) -> None:
        """A progress line for a stage that starts :data:`PROGRESS_AFTER` seconds or more into the run."""
        elapsed = time.perf_counter() - self._started
        if self.progress and elapsed >= PROGRESS_AFTER:
            print(f"register: {elapsed:4.1f} s  {text}", file=sys.stderr, flush=True)

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)`` (normals unused): :meth:`solve` as a method result."""
        result = self.solve(src, tgt)
        info = {"warnings": list(result.warnings)}
        return MethodResult(transform=result.transform, seconds=result.seconds, info=info, solution=result)

    def solve(self, src, tgt) -> RobustResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)``: both clouds centred (``center``) and scaled
        into the unit ball, the rounds, the final steps, and every pose mapped back to the input frames.

        Raises:
            ValueError: a malformed cloud, or one whose points all coincide (naming it).
        """
        check_points(src, "source", batched=False)
        check_points(tgt, "target", batched=False)
        notes = tuple(note for note in (degeneracy(src, "source"), degeneracy(tgt, "target")) if note is not None)
        for note in notes:
            warnings.warn(note, stacklevel=2)
        src, tgt = np.asarray(src, dtype=np.float64), np.asarray(tgt, dtype=np.float64)
        c_src = src.mean(axis=0) if self.center else np.zeros(3)
        c_tgt = tgt.mean(axis=0) if self.center else np.zeros(3)
        self._started = time.perf_counter()
        pair, radius = self._pair(src - c_src, tgt - c_tgt)
        choice = self._choose(pair)
        best, poses = choice.best, choice.pool.poses
        chosen, fine, coincident, plane = self._finish(
            (poses[0][best : best + 1], poses[1][best : best + 1]), choice, pair
        )
        seconds = time.perf_counter() - self._started

        def to_input(matrix: np.ndarray) -> np.ndarray:
            """A ``(4, 4)`` pose of the solver's frame as the transform between the input clouds."""
            matrix[:3, 3] *= radius
            return translation(c_tgt) @ matrix @ translation(-c_src)

        checked = None
        if choice.checked is not None:
            answer, cost = choice.checked
            checked = Candidate(to_input(as_matrices(answer.poses)[0]), cost, cost, *answer.origins[0])
        candidates = tuple(
            Candidate(to_input(matrix), float(cost), float(value), *origin)
            for matrix, cost, value, origin in zip(
                as_matrices(choice.pool.poses), choice.costs, choice.ranking, choice.pool.origins, strict=True
            )
        )
        return RobustResult(
            transform=to_input(as_matrices(chosen)[0]),
            candidates=candidates,
            chosen=choice.best,
            selection=choice.selection,
            doubtful=choice.verdict.doubtful,
            margin=choice.verdict.margin,
            history=choice.history,
            checked=checked,
            fine=fine,
            coincident=coincident,
            plane=plane,
            warnings=notes,
            seconds=seconds,
        )

    def _pair(self, src: np.ndarray, tgt: np.ndarray) -> tuple[_Pair, float]:
        """The scaled pair and the scale (the radius of the unit ball in input units)."""
        options = self.options
        src_s, tgt_s = fps(src, self.num_points), fps(tgt, self.num_points)
        radius = float(max(np.linalg.norm(src_s, axis=1).max(), np.linalg.norm(tgt_s, axis=1).max(), 1e-12))
        src_s, tgt_s = src_s / radius, tgt_s / radius
        tgt_index = NearestNeighbors(tgt_s)
        spacing = point_spacing(tgt_s, tgt_index)
        pair = _Pair(
            src=src_s,
            tgt=tgt_s,
            src_whole=src / radius,
            tgt_whole=tgt / radius,
            src_coarse=fps(src_s, options.coarse.points),
            tgt_coarse=fps(tgt_s, 2 * options.coarse.points),
            tgt_index=tgt_index,
            spacing=spacing,
            nus=polish_scales(options.polish, spacing),
            inlier_distance=options.select.fitness_spacings * spacing,
        )
        return pair, radius

    def _choose(self, pair: _Pair) -> _Choice:
        """Rounds until the choice is not doubtful (or ``rounds`` ran). After a doubtful first round
        on a target with more points than the subset (a scan), the dense check judges the first
        round's answer; only a doubtful check brings the global candidates, and the dense
        judgement replaces the selection cost for every later step (module docstring, 4-5)."""
        select, settings = self.options.select, self.options.global_stage
        pool, costs, starts = self._next_round(1, pair)
        verdict = self._verdict(pool, costs, pair, None)
        history = [Step(1, STAGES[1], starts, len(pool.origins), "fixed", verdict.doubtful, verdict.margin)]
        dense, checked = None, None
        if verdict.doubtful and settings.candidates != "never" and len(pair.tgt_whole) > len(pair.tgt):
            self._stage("first round doubtful: dense check of its answer")
            finest = float(pair.nus[-1]) if len(pair.nus) else np.inf
            dense = dense_target(pair.tgt_whole, settings, finest)
            pool, costs = self._judge(None, pool, pair, dense)
            verdict, checked = self._verdict(pool, costs, pair, dense), (pool.taken(np.arange(1)), float(costs[0]))
            history.append(Step(1, CHECK, 0, 0, "dense", verdict.doubtful, verdict.margin))
            if verdict.doubtful or settings.candidates == "always":
                pool, costs, verdict, step = self._global_round(pool, costs, verdict, pair, dense)
                history.append(step)
        rounds = 1
        while verdict.doubtful and rounds < select.rounds:
            rounds += 1
            self._stage(f"{'doubtful' if dense is None else 'still doubtful'}: round {rounds} ({STAGES[rounds]})")
            more, more_costs, starts = self._next_round(rounds, pair)
            if dense is None:
                pool, costs = pool.joined(more), np.concatenate([costs, more_costs])
            else:
                pool, costs = self._judge((pool, costs), more, pair, dense)
            verdict = self._verdict(pool, costs, pair, dense)
            judgement = "fixed" if dense is None else "dense"
            history.append(
                Step(rounds, STAGES[rounds], starts, len(more.origins), judgement, verdict.doubtful, verdict.margin)
            )
        return replace(self._select(pool, costs, verdict, tuple(history), pair, dense), checked=checked)

    def _select(
        self,
        pool: _Pool,
        costs: np.ndarray,
        verdict: _Verdict,
        history: tuple[Step, ...],
        pair: _Pair,
        dense: DenseTarget | None,
    ) -> _Choice:
        """The final choice: the lowest cost (``"fixed"``, ``"dense"``), or after doubtful local
        rounds the lowest polish objective (``"polish"``: ``doubtful_select``), judged again."""
        select = self.options.select
        best, selection, ranking = int(costs.argmin()), "fixed" if dense is None else "dense", costs
        if dense is None and history[-1].round > 1 and select.doubtful == "polish" and len(pair.nus):
            ranking = fixed_scale_cost(pool.poses, pair.src, pair.tgt_index, float(pair.nus[-1]))
            best, selection = int(ranking.argmin()), "polish"
            judged = doubt(select, pool.poses, costs, pair.src, pair.tgt_index, pair.inlier_distance, best, ranking)
            verdict = _Verdict(*judged)
        return _Choice(pool, costs, ranking, best, selection, verdict, history, dense)

    def _verdict(self, pool: _Pool, costs: np.ndarray, pair: _Pair, dense: DenseTarget | None) -> _Verdict:
        """The doubt test of the lowest cost: :func:`doubt`, or
        :func:`~linereg.registration.global_stage.dense_doubt` after the dense judgement."""
        select = self.options.select
        if dense is None:
            return _Verdict(*doubt(select, pool.poses, costs, pair.src, pair.tgt_index, pair.inlier_distance))
        return _Verdict(*dense_doubt(select, pool.poses, costs, pair.src, dense), None)

    def _next_round(self, number: int, pair: _Pair) -> tuple[_Pool, np.ndarray, int]:
        """Round ``number`` (:meth:`_round`): its candidates with their origins, their costs ``(K,)``
        and the number of coarse candidates it ran."""
        poses, costs, merged = self._round(number, pair)
        origin = "search" if number == 3 else "start"
        return _Pool(poses, tuple((number, origin, int(k)) for k in np.flatnonzero(~merged))), costs, len(merged)

    def _round(self, number: int, pair: _Pair) -> tuple[Poses, np.ndarray, np.ndarray]:
        """Round ``number`` (1, 2, 3): coarse stage from its starts, then the polish: candidates,
        their costs ``(K,)`` and which coarse candidates merged into an earlier one ``(S,)`` (dropped)."""
        coarse = self.options.coarse
        if number == 3:
            initial, sides = self._searched_poses(pair)
        else:
            starts = axis_rotations(coarse.starts)
            sides = np.repeat([side == "both" for side in coarse.sides], len(starts))
            initial = (np.tile(starts, (len(coarse.sides), 1, 1)), np.zeros((len(sides), 3)))
        shared = (pair.src_coarse, pair.tgt_coarse, sides, coarse.nu0)
        if number == 2:
            poses, merged = cdw_adam(
                initial, *shared, coarse.explore_steps, coarse.explore_lr, merge_distance=coarse.merge_distance
            )
        else:
            poses, merged = cdw_irls(initial, *shared, coarse.steps, merge_distance=coarse.merge_distance)
        kept = (poses[0][~merged], poses[1][~merged])
        poses = welsch_irls(kept, pair.src, pair.tgt_index, pair.nus, self.options.polish.settle)
        return poses, fixed_scale_cost(poses, pair.src, pair.tgt_index, self.options.select.nu), merged

    def _searched_poses(self, pair: _Pair) -> tuple[Poses, np.ndarray]:
        """The third round's starts: the best distinct poses of the pose search, each with the
        one-sided coarse loss (the search places the view; the two-sided loss would pull it to cover the target)."""
        search = self.options.search
        rotations = spread_rotations(search.rotations)
        translations, costs = pose_search(
            rotations,
            fps(pair.src_coarse, search.points),
            pair.tgt_coarse,
            radius=search.radius,
            spacing=search.spacing,
            nu=search.nu,
            cell=search.cell,
        )
        best = distinct_best(rotations, costs, search.keep, self.options.select.distinct_deg)
        return (rotations[best], translations[best]), np.zeros(len(best), dtype=bool)

    def _global_round(
        self, pool: _Pool, costs: np.ndarray, verdict: _Verdict, pair: _Pair, dense: DenseTarget
    ) -> tuple[_Pool, np.ndarray, _Verdict, Step]:
        """FPFH + RANSAC and FGR candidates (:class:`~linereg.registration.features.FeatureMatcher`:
        the features of the whole source and of the dense target, computed once), one at a time:
        each gets the polish and joins the dense judgement of ``pool`` (dense ``costs``, ``verdict``),
        and the stage stops at the first one after which the choice is not doubtful. Returns the
        judged candidates, their dense costs, the verdict and the stage's
        :class:`~linereg.registration.robust_result.Step`."""
        from linereg.registration.features import FeatureMatcher, FeatureOptions

        settings = self.options.global_stage
        self._stage("global stage: FPFH + RANSAC and FGR candidates, one at a time")
        matcher = FeatureMatcher(pair.src_whole, dense.points, FeatureOptions(points=settings.feature_points))
        tried = 0
        for tried, found in enumerate(matcher.candidates(), start=1):
            poses = welsch_irls(
                (found[None, :3, :3].copy(), found[None, :3, 3].copy()),
                pair.src,
                pair.tgt_index,
                pair.nus,
                self.options.polish.settle,
            )
            pool, costs = self._judge((pool, costs), _Pool(poses, ((1, "global", tried - 1),)), pair, dense)
            verdict = self._verdict(pool, costs, pair, dense)
            if not verdict.doubtful:
                break
        return pool, costs, verdict, Step(1, GLOBAL, 0, tried, "dense", verdict.doubtful, verdict.margin)

    def _judge(
        self, judged: tuple[_Pool, np.ndarray] | None, new: _Pool, pair: _Pair, dense: DenseTarget
    ) -> tuple[_Pool, np.ndarray]:
        """The dense judgement (:mod:`~linereg.registration.global_stage`) of ``new`` candidates
        beside ``judged`` ones (already polished against the dense target, with their dense costs):
        the ``dense_keep`` distinct new ones of lowest dense cost get the dense polish, and the
        ``dense_keep`` distinct candidates of lowest dense cost of both are kept, cheapest first."""
        new = self._cheapest(new, dense_costs(new.poses, pair.src, dense))[0]
        new = _Pool(dense_polish(new.poses, pair.src, dense, self.options.global_stage), new.origins)
        costs = dense_costs(new.poses, pair.src, dense)
        if judged is not None:
            new, costs = judged[0].joined(new), np.concatenate([judged[1], costs])
        return self._cheapest(new, costs)

    def _cheapest(self, pool: _Pool, costs: np.ndarray) -> tuple[_Pool, np.ndarray]:
        """The ``dense_keep`` distinct candidates (``merge_distance`` apart) of lowest ``costs``,
        cheapest first, and their costs."""
        order = np.argsort(costs, kind="stable")
        pool, costs = pool.taken(order), costs[order]
        none = np.zeros(len(costs), dtype=bool)
        distinct = ~merged_into_earlier(pool.poses, none, none, self.options.coarse.merge_distance)
        kept = np.flatnonzero(distinct)[: self.options.global_stage.dense_keep]
        return pool.taken(kept), costs[kept]

    def _finish(self, chosen: Poses, choice: _Choice, pair: _Pair) -> tuple[Poses, bool, float | None, bool]:
        """The fine polish and the plane-to-plane steps of the chosen pose, where they apply: the
        pose, ``fine``, ``coincident`` and ``plane``. After the dense judgement there is no fine
        polish, and the plane-to-plane steps run against the dense target, ``dense_plane`` times wider."""
        options = self.options
        if choice.dense is None:
            fine_nus = fine_scales(options.polish, pair.spacing)
            fine = choice.verdict.fitness >= options.polish.fine_fitness and len(fine_nus) > 0
            if fine:
                chosen = welsch_irls(chosen, pair.src, pair.tgt_index, fine_nus, options.polish.settle)
            target = (pair.tgt, pair.tgt_index, pair.spacing, 1.0)
        else:
            fine = False
            dense = choice.dense
            target = (dense.points, dense.index, dense.spacing, options.global_stage.dense_plane)
        if (fine or choice.dense is not None) and options.plane.steps > 0:
            chosen, coincident, plane = self._plane_steps(chosen, pair.src, *target)
            return chosen, fine, coincident, plane
        return chosen, fine, None, False

    def _plane_steps(
        self,
        chosen: Poses,
        src: np.ndarray,
        tgt: np.ndarray,
        tgt_index: NearestNeighbors,
        spacing: float,
        widen: float,
    ) -> tuple[Poses, float, bool]:
        """Plane-to-plane steps of ``chosen`` (``plane_nu * widen`` spacings) when the clouds are
        independent samplings of the surface: fewer than ``coincident_share`` of the source points
        lie within ``coincident_distance`` spacings of a target point (clouds cut from one sampling
        coincide where they overlap, and a point-to-point fit is exact there). Returns the pose,
        that share and whether the steps ran."""
        plane = self.options.plane
        distances, _ = tgt_index.query(apply(chosen, src)[0])
        coincident = float((distances <= plane.coincident_distance * spacing).mean())
        if coincident >= plane.coincident_share:
            return chosen, coincident, False
        k, epsilon = plane.neighbours, plane.epsilon
        chosen = plane_to_plane_irls(
            chosen,
            src,
            surface_covariances(src, k, epsilon),
            tgt_index,
            surface_covariances(tgt, k, epsilon),
            plane.nu * spacing * widen,
            plane.steps,
        )
        return chosen, coincident, True


METHODS.register("robust")(RobustRegistration)
