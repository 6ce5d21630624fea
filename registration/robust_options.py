"""Settings of the ``register`` default, one frozen group per stage (as Open3D's option objects).

:class:`RobustOptions` composes :class:`CoarseOptions`, :class:`PolishOptions`,
:class:`PlaneOptions`, :class:`SelectOptions`, :class:`SearchOptions` and :class:`GlobalOptions`.
Lengths are in the unit ball of the centred pair unless a field says "target point spacings".
Users pass the settings as one flat mapping, ``register(a, b, options={"starts": 7,
"polish_steps": 30})`` or ``linereg-register source=a.ply target=b.ply +robust.starts=7`` (the
command's ``robust`` mapping starts empty, hence the ``+``), or by group, ``{"polish": {"steps": 30}}``.

Each field has one flat name, derived from the dataclasses (:func:`flat_name`; all of them in
:data:`FLAT_KEYS`):

* a compound field name is its own flat name: ``explore_steps``, ``merge_distance``, ``fine_end``,
  ``coincident_share``, ``min_fitness``, ``feature_points``, ``dense_keep``;
* a one-word field name takes its group's ``prefix``: ``coarse_points``, ``polish_steps``,
  ``plane_nu``, ``select_nu``, ``search_radius``, ``global_candidates``;
* a field whose metadata gives a flat name (:data:`FLAT`) takes that one: ``starts`` and ``rounds``
  (the settings most often changed, kept short) and ``doubtful_select`` (``SelectOptions.doubtful``).

Two fields, or a field and a group, with one flat name fail the import.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, get_type_hints

from linereg.registration.poses import axis_rotations

FLAT = "flat"
"""The field metadata key that names a field's flat name (:func:`flat_name`)."""


def _flat(default: Any, name: str) -> Any:
    """A field with ``default`` whose flat name is ``name`` (:func:`flat_name`)."""
    return field(default=default, metadata={FLAT: name})


def flat_name(group: type, name: str) -> str:
    """The flat name of field ``name`` of the option group ``group`` (the rule of the module docstring)."""
    metadata = next(spec.metadata for spec in fields(group) if spec.name == name)
    if FLAT in metadata:
        return metadata[FLAT]
    return name if "_" in name else f"{group.prefix}_{name}"


class _Checked:
    """Range checks whose messages name the flat name a user passes."""

    prefix: ClassVar[str]

    def _name(self, name: str) -> str:
        return flat_name(type(self), name)

    def _require(self, positive: tuple[str, ...] = (), non_negative: tuple[str, ...] = (), unit=()) -> None:
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{self._name(name)} must be > 0, got {getattr(self, name)}")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"{self._name(name)} must be >= 0, got {getattr(self, name)}")
        for name in unit:
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{self._name(name)} must be in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class CoarseOptions(_Checked):
    """The coarse stage: CD-W from every start, IRLS in round 1, Adam in round 2.

    Attributes:
        starts: initial rotations of rounds 1 and 2 (:func:`~linereg.registration.poses.axis_rotations`).
        points: FPS size of the source (the target gets twice as many).
        sides: every start runs once per entry: ``"both"`` (CD-W, both directions) and/or
            ``"source"`` (the source-to-target term alone: a partial view inside a whole target).
        nu0: CD-W's ``nu0`` (a wide window: robust to partial overlap).
        steps: most IRLS steps of round 1 (:func:`~linereg.registration.coarse.cdw_irls`).
        explore_steps: Adam steps of round 2 (:func:`~linereg.registration.coarse.cdw_adam`).
        explore_lr: peak learning rate (cosine decay) of those Adam steps.
        merge_distance: candidates this close (rotation entries and translation) to an earlier
            one with the same coarse loss stop and are not polished.
    """

    prefix: ClassVar[str] = "coarse"
    starts: int = _flat(4, "starts")
    points: int = 256
    sides: tuple[str, ...] = ("both", "source")
    nu0: float = 2.0
    steps: int = 80
    explore_steps: int = 100
    explore_lr: float = 0.03
    merge_distance: float = 0.01

    def __post_init__(self) -> None:
        self._require(("points", "nu0", "explore_lr"), ("steps", "explore_steps", "merge_distance"))
        sides = tuple(self.sides)
        if not sides or set(sides) - {"both", "source"} or len(set(sides)) < len(sides):
            message = "must be distinct entries of 'both' and 'source'"
            raise ValueError(f"{self._name('sides')} {message}, got {self.sides!r}")
        object.__setattr__(self, "sides", sides)
        axis_rotations(self.starts)


@dataclass(frozen=True)
class PolishOptions(_Checked):
    """The Welsch IRLS polish of every candidate (:func:`~linereg.registration.welsch.welsch_irls`).

    Attributes:
        steps: IRLS steps with :func:`~linereg.registration.welsch.polish_scales`.
        nu: first IRLS scale.
        end: last IRLS scale, in target point spacings.
        settle: most further steps at the last scale, each candidate until it stops moving.
        fine_end: when the chosen pose has a fitness of at least ``fine_fitness`` (the source lies
            on the target: a view inside the whole), its polish goes on with scales falling from
            ``end`` to this, in spacings (:func:`~linereg.registration.welsch.fine_scales`). A
            partial overlap (real scans: fitness 0.70-0.73 on 3DMatch) stays at ``end``.
        fine_fitness: that fitness, within ``fitness_spacings`` target point spacings.
    """

    prefix: ClassVar[str] = "polish"
    steps: int = 20
    nu: float = 0.05
    end: float = 0.3
    settle: int = 60
    fine_end: float = 0.1
    fine_fitness: float = 0.95

    def __post_init__(self) -> None:
        self._require(("nu", "end", "fine_end"), ("steps", "settle"), ("fine_fitness",))


@dataclass(frozen=True)
class PlaneOptions(_Checked):
    """Plane-to-plane steps after the fine polish (:func:`~linereg.registration.planes.plane_to_plane_irls`).

    They run when the clouds are independent samplings of the surface: fewer than
    ``coincident_share`` of the source points lie within ``coincident_distance`` target point
    spacings of a target point (clouds cut from one sampling share points, and a point-to-point
    fit is exact there).

    Attributes:
        steps: Gauss-Newton steps (0: never).
        nu: Welsch scale, in target point spacings.
        neighbours, epsilon: the points of each cloud's local planes and their thickness
            (:func:`~linereg.registration.planes.surface_covariances`).
        coincident_distance, coincident_share: that test.
    """

    prefix: ClassVar[str] = "plane"
    steps: int = 10
    nu: float = 1.0
    neighbours: int = 10
    epsilon: float = 0.01
    coincident_distance: float = 0.02
    coincident_share: float = 0.01

    def __post_init__(self) -> None:
        self._require(("nu", "epsilon", "coincident_distance"), ("steps",), ("coincident_share",))
        if self.neighbours < 3:
            raise ValueError(f"{self._name('neighbours')} must be >= 3 (a plane needs 3 points), got {self.neighbours}")


@dataclass(frozen=True)
class SelectOptions(_Checked):
    """The choice among the candidates, and the doubt that sends the solver to the next round.

    A pose is doubtful when another candidate more than ``distinct_deg`` away costs less than
    ``doubt_ratio`` times its cost, or its cost exceeds ``max_cost``, or fewer than
    ``min_fitness`` of the source points lie within ``fitness_spacings`` target point spacings of
    the target. A doubtful pose sends the solver to the next round: 2, Adam from the same starts;
    3, the pose search (``rounds`` caps them).

    Attributes:
        nu: scale of the selection cost :func:`~linereg.registration.welsch.fixed_scale_cost`.
        doubtful: the final choice after a doubtful first round: ``"polish"``, the lowest polish
            objective (the fixed-scale cost at the polish's last scale), or ``"fixed"``, the
            lowest cost at ``nu``.
        doubt_ratio, distinct_deg, max_cost: that test.
        min_fitness: fitness below which the fit is doubtful (a right pose of a view inside the
            whole target scores 0.99-1, a wrong basin 0.7-0.87).
        fitness_spacings: inlier distance of that fitness, in target point spacings.
        rounds: most rounds (1..3).
    """

    prefix: ClassVar[str] = "select"
    nu: float = 0.03
    doubtful: str = _flat("polish", "doubtful_select")
    doubt_ratio: float = 1.25
    distinct_deg: float = 10.0
    max_cost: float = 0.5
    min_fitness: float = 0.985
    fitness_spacings: float = 3.0
    rounds: int = _flat(3, "rounds")

    def __post_init__(self) -> None:
        self._require(("nu", "distinct_deg", "max_cost", "fitness_spacings"), unit=("min_fitness",))
        if self.doubt_ratio < 1:
            raise ValueError(f"{self._name('doubt_ratio')} must be >= 1, got {self.doubt_ratio}")
        if self.doubtful not in ("polish", "fixed"):
            raise ValueError(f"{self._name('doubtful')} must be 'polish' or 'fixed', got {self.doubtful!r}")
        if self.rounds not in (1, 2, 3):
            raise ValueError(f"{self._name('rounds')} must be 1, 2 or 3, got {self.rounds}")


@dataclass(frozen=True)
class SearchOptions(_Checked):
    """The third round's pose search (:func:`~linereg.registration.search.pose_search`).

    Attributes:
        rotations: rotations searched (:func:`~linereg.registration.poses.spread_rotations`).
        radius: largest translation; spacing: the translation step.
        points: FPS size of the source.
        nu: Welsch scale of the cost; cell: cell side of its cost table.
        keep: best distinct poses (``distinct_deg`` apart) from which the one-sided coarse IRLS runs.
    """

    prefix: ClassVar[str] = "search"
    rotations: int = 600
    radius: float = 0.5
    spacing: float = 0.1
    points: int = 64
    nu: float = 0.07
    cell: float = 0.05
    keep: int = 24

    def __post_init__(self) -> None:
        self._require(tuple(f.name for f in fields(self)))


@dataclass(frozen=True)
class GlobalOptions(_Checked):
    """The stage for doubtful scans (:mod:`~linereg.registration.global_stage`): the dense check of
    the first round's answer, global candidates and the dense judgement of every candidate.

    Attributes:
        candidates: ``"doubtful"``: after a doubtful first round on a target with more points than
            the solver's subset (a scan: FPFH needs a dense sampling, and a dense judgement needs
            more than the subset), the dense check judges the first round's candidates against the
            dense target; the FPFH candidates join, one at a time until the choice is not
            doubtful, only when that check is doubtful too; ``"always"``: they join (at least the
            first) after every doubtful first round on a scan, whatever the check says;
            ``"never"``: the rounds of the local stages alone.
        feature_points: the FPFH voxel is the spacing of this many FPS target points
            (:class:`~linereg.registration.features.FeatureOptions` ``points``).
        dense_points: FPS points of the target the candidates are polished against and judged by.
        dense_keep: candidates of lowest dense cost (distinct: ``merge_distance`` apart) that get
            the dense polish, and that the judgement keeps.
        dense_start, dense_steps, dense_end, dense_settle: the dense polish: Welsch scales falling
            from ``dense_start`` to ``dense_end`` dense spacings (or the polish's last scale, if
            smaller) in ``dense_steps`` steps, then up to ``dense_settle`` more. The candidates are
            chosen by the Welsch cost at that last scale.
        dense_plane: the plane-to-plane steps of the chosen pose run with ``plane_nu`` times this
            many dense spacings.
    """

    prefix: ClassVar[str] = "global"
    candidates: str = "doubtful"
    feature_points: int = 3000
    dense_points: int = 30000
    dense_keep: int = 4
    dense_start: float = 4.0
    dense_steps: int = 10
    dense_end: float = 0.7
    dense_settle: int = 20
    dense_plane: float = 2.0

    def __post_init__(self) -> None:
        self._require(
            (
                "feature_points",
                "dense_points",
                "dense_keep",
                "dense_start",
                "dense_steps",
                "dense_end",
                "dense_plane",
            ),
            ("dense_settle",),
        )
        if self.candidates not in ("doubtful", "always", "never"):
            message = f"must be 'doubtful', 'always' or 'never', got {self.candidates!r}"
            raise ValueError(f"{self._name('candidates')} {message}")


@dataclass(frozen=True)
class RobustOptions:
    """Settings of :class:`~linereg.registration.robust.RobustRegistration`, one group per stage."""

    coarse: CoarseOptions = field(default_factory=CoarseOptions)
    polish: PolishOptions = field(default_factory=PolishOptions)
    plane: PlaneOptions = field(default_factory=PlaneOptions)
    select: SelectOptions = field(default_factory=SelectOptions)
    search: SearchOptions = field(default_factory=SearchOptions)
    global_stage: GlobalOptions = field(default_factory=GlobalOptions)

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any]) -> RobustOptions:
        """Options from flat keys (:data:`FLAT_KEYS`) and/or group mappings (``{"polish": {"steps": 30}}``).

        Raises:
            TypeError: an unknown key, naming it and listing the known ones.
            ValueError: a value out of range, naming its flat key.
        """
        unknown = sorted(key for key in options if key not in FLAT_KEYS and key not in _GROUPS)
        if unknown:
            raise TypeError(f"unknown option(s) {unknown}; known: {sorted(FLAT_KEYS)}")
        values: dict[str, dict[str, Any]] = {group: {} for group in _GROUPS}
        for key, value in options.items():
            if key in _GROUPS:
                if not isinstance(value, Mapping):
                    raise TypeError(f"{key}: expected a mapping of {_GROUPS[key].__name__} fields, got {value!r}")
                known = {f.name for f in fields(_GROUPS[key])}
                extra = sorted(set(value) - known)
                if extra:
                    raise TypeError(f"unknown {key} option(s) {extra}; known: {sorted(known)}")
                values[key].update(value)
            else:
                group, name = FLAT_KEYS[key]
                values[group][name] = value
        return cls(**{group: _GROUPS[group](**settings) for group, settings in values.items()})


def _flat_keys() -> dict[str, tuple[str, str]]:
    """``{flat name: (group, field)}`` of every field of every group (:func:`flat_name`).

    Raises:
        TypeError: two fields, or a field and a group, share a name (the new field needs ``_flat``).
    """
    keys: dict[str, tuple[str, str]] = {}
    for group, options in _GROUPS.items():
        for spec in fields(options):
            name = flat_name(options, spec.name)
            if name in keys or name in _GROUPS:
                raise TypeError(f"{group}.{spec.name}: the flat name {name!r} is taken")
            keys[name] = (group, spec.name)
    return keys


_GROUPS: dict[str, type] = get_type_hints(RobustOptions)
"""The groups of :class:`RobustOptions`: ``{attribute: options class}``."""
FLAT_KEYS = _flat_keys()
"""The flat name of every setting: ``{flat name: (group, field)}``."""


def robust_options(options: RobustOptions | Mapping[str, Any] | None) -> RobustOptions:
    """``options`` as :class:`RobustOptions` (``None``: the defaults; a mapping: :meth:`RobustOptions.from_mapping`)."""
    if options is None:
        return RobustOptions()
    if isinstance(options, RobustOptions):
        return options
    return RobustOptions.from_mapping(options)
