"""What :meth:`RobustRegistration.solve <linereg.registration.robust.RobustRegistration.solve>` returns.

A frozen, typed record (as Open3D's ``RegistrationResult`` or pytorch3d's ``ICPSolution``): the
chosen pose, every candidate left at the end with its costs and origin, one entry per step of the
solver with the doubt test after it, and the flags of the final steps. :attr:`RobustResult.info`
reaches :class:`~linereg.registration.methods.MethodResult` and ``register``'s result as their
``solution``; :attr:`RobustResult.summary` is its plain summary for the JSON outputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

CHECK = "dense check"
"""The :attr:`Step.stage` of the dense check of a scan's first-round answer."""
GLOBAL = "FPFH + RANSAC and FGR"
"""The :attr:`Step.stage` of the global candidates."""
STAGES = {1: "IRLS on CD-W", 2: "Adam on CD-W", 3: "pose search"}
"""The :attr:`Step.stage` of each round."""


@dataclass(frozen=True)
class Candidate:
    """One candidate left at the end, polished.

    Attributes:
        transform: ``(4, 4)`` float64 source-to-target transform of the input clouds.
        cost: the cost the doubt test judges by: the fixed-scale cost at ``select_nu`` on the
            solver's subset, or the dense cost (:func:`~linereg.registration.global_stage.dense_costs`)
            when the dense judgement chose.
        objective: the value the final choice ranked by: ``cost``, or the polish's objective
            (the fixed-scale cost at the polish's last scale) when ``selection`` is ``"polish"``.
        round: the round that produced it (1, 2, 3); the global candidates join in round 1.
        origin: ``"start"`` (a start of rounds 1 and 2), ``"search"`` (a pose of round 3's
            search) or ``"global"`` (an FPFH + RANSAC or FGR candidate).
        start: its index among that round's starts: ``side * starts + k`` for start ``k`` of
            :func:`~linereg.registration.poses.axis_rotations` and entry ``side`` of
            ``coarse_sides``; the rank of the searched pose; the index of the global candidate.
    """

    transform: np.ndarray
    cost: float
    objective: float
    round: int
    origin: str
    start: int


@dataclass(frozen=True)
class Step:
    """One step of the solver and the doubt test after it.

    Attributes:
        round: the round (1, 2, 3) it belongs to.
        stage: what ran (:data:`STAGES`, :data:`CHECK` or :data:`GLOBAL`).
        starts: coarse candidates it ran (starts x coarse sides, the searched poses; 0 for the
            dense check and the global candidates).
        added: candidates it added: those polished (not merged), the global candidates that ran
            (the stage stops at the first after which the choice is not doubtful), 0 for the
            dense check.
        judgement: ``"fixed"`` (the selection cost on the subset) or ``"dense"`` (the dense
            judgement), the test that followed.
        doubtful: that test's verdict on the best candidate so far.
        margin: its margin (``1 -`` best cost / cost of the best distinct rival by the fixed
            judgement, ``1 -`` rival score / best score by the dense one; 1 without a rival).
    """

    round: int
    stage: str
    starts: int
    added: int
    judgement: str
    doubtful: bool
    margin: float


@dataclass(frozen=True)
class RobustResult:
    """The outcome of :class:`~linereg.registration.robust.RobustRegistration`.

    Attributes:
        transform: ``(4, 4)`` float64 source-to-target transform of the input clouds: the chosen
            candidate after the fine polish and the plane-to-plane steps.
        candidates: every candidate left at the end (all the polished ones; the ``dense_keep``
            judged ones after the dense judgement), in the solver's order.
        chosen: the index in ``candidates`` of the chosen one.
        selection: what chose: ``"fixed"`` (the lowest ``cost``), ``"polish"`` (the lowest
            ``objective`` after a doubtful first round: ``doubtful_select``) or ``"dense"``.
        doubtful: the final choice fails the doubt test
            (:class:`~linereg.registration.robust_options.SelectOptions`).
        margin: that test's margin for the final choice (:attr:`Step.margin`, by the ranking
            that chose).
        history: every step that ran, in order.
        checked: the first round's answer as the dense check of a scan judged it (the candidate
            of lowest dense cost after the dense polish); ``None`` when the check did not run.
        fine: the chosen pose got the fine polish.
        coincident: the share of source points on a target point, measured before the
            plane-to-plane steps (``None`` when that test did not run).
        plane: the plane-to-plane steps ran.
        warnings: notes on the input clouds (collinear points).
        seconds: wall-clock time of the registration.
    """

    transform: np.ndarray
    candidates: tuple[Candidate, ...]
    chosen: int
    selection: str
    doubtful: bool
    margin: float
    history: tuple[Step, ...]
    checked: Candidate | None
    fine: bool
    coincident: float | None
    plane: bool
    warnings: tuple[str, ...] = ()
    seconds: float = 0.0

    @property
    def global_candidates(self) -> int:
        """The global candidates that ran (0 when that stage did not run)."""
        return sum(step.added for step in self.history if step.stage == GLOBAL)

    @property
    def rounds(self) -> int:
        """The last round that ran."""
        return self.history[-1].round

    @property
    def starts(self) -> int:
        """The coarse candidates of all rounds (starts x coarse sides, searched poses)."""
        return sum(step.starts for step in self.history)

    @property
    def cost(self) -> float:
        """The chosen candidate's :attr:`Candidate.cost`."""
        return self.candidates[self.chosen].cost

    @property
    def summary(self) -> dict[str, Any]:
        """The record in plain values (``result.json``, the benchmark's records): ``doubtful``,
        ``margin``, ``global_candidates``, ``cost``, ``rounds``, ``starts``, ``candidates`` (how many
        are left), ``selection``, ``fine``, ``coincident`` and ``plane``."""
        return {
            "doubtful": self.doubtful,
            "margin": self.margin,
            "global_candidates": self.global_candidates,
            "cost": self.cost,
            "rounds": self.rounds,
            "starts": self.starts,
            "candidates": len(self.candidates),
            "selection": self.selection,
            "fine": self.fine,
            "coincident": self.coincident,
            "plane": self.plane,
        }
