"""``linereg.register``: align two point clouds, with results modelled on Open3D's ``registration_*``.

::

    import linereg

    result = linereg.register("scan_a.ply", "scan_b.ply")          # files, (N, 3) arrays or tensors
    result.transformation                                          # (4, 4) source -> target
    result.confident, result.fitness, result.inlier_rmse

    linereg.register(src, tgt, init=T0)                            # an initial guess (4, 4)
    linereg.register(src, tgt, method="icp_point")                 # any registered method
    linereg.register(src, tgt, method="outputs/train/run/", refine=True)  # a trained network (+ solver)
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from linereg import pretrained
from linereg.checks import as_rigid_transform, check_points, is_tensor
from linereg.fps import farthest_point_subset as fps
from linereg.io import PointCloud, read_point_cloud
from linereg.registration.evaluation import Assessment, assess_registration
from linereg.registration.methods import METHODS, MethodResult, run_centered, run_with_init
from linereg.registration.similarity import scale_guesses, scale_of, similarity_polish, with_scale
from linereg.registration.trust import surface_points
from linereg.registry import UnknownNameError

DEFAULT_METHOD = "robust"
_MIN_POINTS = 3
POLISH_ONLY = {"starts": 1, "coarse_steps": 0, "rounds": 1, "global_candidates": "never"}
"""The solver's options of the polish that finishes a network's pose: from that pose alone, no
coarse stage, no later round, no global candidates (the Welsch IRLS polish and the fine steps)."""


@dataclass
class RegistrationResult:
    """The outcome of :func:`register` (Open3D's ``RegistrationResult``, plus time and details).

    Attributes:
        transformation: ``(4, 4)`` float64 transform mapping the source onto the target
            (``tgt ≈ R @ src + t``), the initial guess included.
        fitness: share of source points with a target point within ``info["fitness_threshold"]``
            (3 sampling distances of the target unless given: Open3D's definition).
        inlier_rmse: RMS distance of those inlier points (0 without inliers).
        confident: the pose can be trusted: the same test for every method
            (:func:`~linereg.registration.evaluation.assess_registration`).
        seconds: wall-clock time of the registration (reading files excluded).
        scale: the scale ``s`` of ``transformation = [s R | t]`` with ``scale=True`` (1 otherwise).
        info: the method's details: ``method``, ``fitness_threshold``, ``sampling_distance``, and
            for the default solver ``rounds``, ``candidates``, ``selection``, ...
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    confident: bool
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)
    scale: float = 1.0


def as_cloud(value: Any, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``(points (N, 3) float64, normals (N, 3) or None)`` from an array, a tensor, an Open3D cloud, a file
    or a :class:`linereg.io.PointCloud`.

    Raises:
        FileNotFoundError: a path that does not exist (the message names the argument).
        TypeError: an unsupported type.
        ValueError: a malformed cloud (wrong shape, NaN/Inf, fewer than 3 points), naming ``name``.
    """
    normals = None
    if isinstance(value, PointCloud):
        points, normals = value.xyz, value.normals
    elif isinstance(value, str | os.PathLike):
        path = Path(value).expanduser()
        if path.is_dir():
            raise ValueError(f"{name}={value}: is a folder, expected a point-cloud file")
        if not path.exists():
            raise FileNotFoundError(f"{name}={value}: no such file")
        try:
            cloud = read_point_cloud(path, min_points=_MIN_POINTS)
        except ValueError as error:
            raise ValueError(f"{name}={value}: {error}") from error
        points, normals = cloud.xyz, cloud.normals
    elif type(value).__module__.startswith("open3d"):
        if not hasattr(value, "points"):
            raise TypeError(f"{name}: an Open3D {type(value).__name__} is not a point cloud")
        points = np.asarray(value.points)
        normals = np.asarray(value.normals) if value.has_normals() else None
    elif is_tensor(value):
        points = value.detach().cpu().numpy()
    elif isinstance(value, np.ndarray):
        points = value
    else:
        raise TypeError(
            f"{name}: expected an (N, 3) numpy array, a torch tensor, an Open3D PointCloud or a file path, "
            f"got {type(value).__name__}"
        )
    check_points(points, name, batched=False, min_points=_MIN_POINTS)
    return np.asarray(points, dtype=np.float64), None if normals is None else np.asarray(normals, dtype=np.float64)


def _checked_init(init: Any) -> np.ndarray | None:
    """``init`` as an exactly rigid ``(4, 4)`` (a near-rigid one orthonormalised with a warning)."""
    if init is None:
        return None
    transform = init.detach().cpu().numpy() if is_tensor(init) else np.asarray(init, dtype=np.float64)
    return as_rigid_transform(transform, "init")


class LearnedRegistration:
    """A network trained by ``python -m train`` as a registration method, optionally refined.

    The clouds are centred, farthest-point sampled to the run's ``trainer.num_points``, scaled
    together into the cube its training pairs were scaled into (:func:`training_half_extent`),
    given normals (estimated on the subsets); of the model's iterates, the one the run's ``iterate`` rule chooses
    (:mod:`linereg.registration.iterates`, from the checkpoint's config) is mapped back to the
    original frames.

    Args:
        checkpoint: a checkpoint file, a run folder (the checkpoint the run evaluated, else
            ``best.pt``) or a pretrained name (:mod:`linereg.pretrained`).
        device: torch device of the model.
        num_points: points per cloud fed to the model (``None``: the run's ``trainer.num_points``).
        refine: finish the network's pose with the solver (:meth:`finish`): a local polish from it,
            register's check, and the whole solver only when the check fails; a mapping gives
            :class:`~linereg.registration.robust.RobustOptions` fields of both (numpy, on the CPU
            whatever ``device``).
    """

    def __init__(
        self,
        checkpoint: str | Path,
        *,
        device: str | Any = "cpu",
        num_points: int | None = None,
        refine: bool | Mapping[str, Any] = False,
    ) -> None:
        import torch

        from linereg.registration.iterates import IterateRule

        self.model, state = _loaded(str(checkpoint), str(device))
        self.device = torch.device(device)
        self.checkpoint = state["path"]
        self.iterate = IterateRule.from_config(state["config"].get("iterate"))
        self.num_points = num_points or state["config"].get("trainer", {}).get("num_points") or 1024
        self.half_extent = training_half_extent(state["config"].get("dataset") or {})
        self.polisher = self.solver = None
        if refine:
            options = dict(refine) if isinstance(refine, Mapping) else {}
            self.polisher = METHODS.build({"name": DEFAULT_METHOD, "options": {**POLISH_ONLY, **options}})
            self.solver = METHODS.build({"name": DEFAULT_METHOD, "options": options})

    def _predict(self, src, tgt, src_normals, tgt_normals) -> MethodResult:
        import torch

        from linereg.datasets.protocol import scale_transform
        from linereg.pointcloud import estimate_normals, fit_into_cube
        from linereg.structures import PairBatch

        src_s, tgt_s = fps(src, self.num_points), fps(tgt, self.num_points)
        center, scale = np.zeros(3), 1.0  # half_extent None: the clouds' own units
        clouds = (src_s, tgt_s)
        if self.half_extent is not None:
            clouds, center, scale = fit_into_cube(src_s, tgt_s, half_extent=self.half_extent)
        normals = [estimate_normals(cloud) for cloud in clouds]
        batch = PairBatch(
            src_xyz=torch.from_numpy(clouds[0]).float()[None],
            tgt_xyz=torch.from_numpy(clouds[1]).float()[None],
            src_normals=torch.from_numpy(normals[0]).float()[None],
            tgt_normals=torch.from_numpy(normals[1]).float()[None],
        ).to(self.device)
        with torch.no_grad():
            output = self.model(batch)
            chosen, _ = self.iterate.select(output.transforms, batch.src_xyz, batch.tgt_xyz)
        # back to the original frames: the inverse of x' = (x - c) s is x = (x' + c s) / s
        transform = scale_transform(chosen[0].double().cpu().numpy(), -center * scale, 1.0 / scale)
        return MethodResult(transform=transform)

    def __call__(self, src, tgt, src_normals=None, tgt_normals=None) -> MethodResult:
        """Register ``src (N, 3)`` onto ``tgt (M, 3)`` (numpy); normals are re-estimated on the subsets."""
        predicted = run_centered(self._predict, src, tgt)
        info: dict[str, Any] = {
            "checkpoint": self.checkpoint,
            "iterate": self.iterate.as_config(),
            "network_transform": predicted.transform.tolist(),
        }
        if self.polisher is None:
            return MethodResult(
                transform=predicted.transform, seconds=predicted.seconds, info={**info, "path": "network"}
            )
        finished = self.finish(src, tgt, predicted.transform)
        return MethodResult(
            transform=finished.transform,
            seconds=predicted.seconds + finished.seconds,
            info={**info, **finished.info},
        )

    def finish(self, src: np.ndarray, tgt: np.ndarray, start: np.ndarray) -> MethodResult:
        """The network's pose ``start (4, 4)`` finished on ``src (N, 3)`` and ``tgt (M, 3)`` in their own
        units: a local polish from it (:data:`POLISH_ONLY`); when register's check
        (:func:`~linereg.registration.evaluation.assess_registration`) does not trust it, the whole
        solver from scratch, whose answer replaces the polished one only when the check prefers it
        (:func:`preferred`). ``info["path"]``: ``"polished network"`` or ``"solver"``, with
        ``"solver_ran"``."""
        began = time.perf_counter()
        polished = run_with_init(self.polisher, src, tgt, init=start)
        judged = assess_registration(src, tgt, polished.transform)
        info = {"solver_ran": False, "polished_confident": judged.confident}
        if judged.confident:
            seconds = time.perf_counter() - began
            return MethodResult(polished.transform, seconds, {**polished.info, **info, "path": "polished network"})
        solved = self.solver(src, tgt)
        rival = assess_registration(src, tgt, solved.transform)
        info["solver_ran"] = True
        winner, path = (solved, "solver") if preferred(rival, judged) else (polished, "polished network")
        return MethodResult(winner.transform, time.perf_counter() - began, {**winner.info, **info, "path": path})


@functools.lru_cache(maxsize=4)
def _loaded(checkpoint: str, device: str):
    """:func:`linereg.models.load_model`, once per checkpoint and device in a process (the model is
    only read: evaluation mode, ``torch.no_grad``)."""
    from linereg.models import load_model

    return load_model(checkpoint, device)


def preferred(first: Assessment, second: Assessment) -> bool:
    """Whether register's check prefers the answer judged ``first`` to the one judged ``second``:
    confident before not, then the larger tight fitness (the share near the target at 1.5 point
    spacings), then the larger fitness."""

    def rank(judged: Assessment) -> tuple[bool, float, float]:
        tight = judged.tight_fitness if np.isfinite(judged.tight_fitness) else -1.0
        return judged.confident, tight, judged.fitness

    return rank(first) > rank(second)


def training_half_extent(dataset: Mapping[str, Any]) -> float | None:
    """Half the side of the cube ``[-h, h]^3`` a run's pairs were scaled into, from its dataset config
    (``half_extent`` of the dataset or of its pair protocol, else the dataset builder's default;
    ``None``: the clouds' own units)."""
    import inspect

    from linereg.datasets import DATASETS

    for section in (dataset, dataset.get("protocol") or {}):
        if "half_extent" in section:
            return section["half_extent"]
    name = dataset.get("name")
    if name in DATASETS.names():
        parameter = inspect.signature(DATASETS.get(name)).parameters.get("half_extent")
        if parameter is not None and parameter.default is not inspect.Parameter.empty:
            return parameter.default
    return 1.0


def quality(
    src: np.ndarray,
    tgt: np.ndarray,
    transform: np.ndarray,
    fitness_threshold: float | None = None,
    on_surface: np.ndarray | bool | None = True,
) -> dict[str, Any]:
    """``fitness``, ``inlier_rmse``, ``fitness_threshold``, ``sampling_distance`` and ``confident`` of
    ``transform (4, 4)`` mapping ``src (N, 3)`` onto ``tgt (M, 3)``: the same test for every method
    (:func:`~linereg.registration.evaluation.assess_registration`).

    Args:
        fitness_threshold: inlier distance of ``fitness`` and ``inlier_rmse`` in input units
            (``None``: 3 sampling distances of the target).
        on_surface: the target's clutter-free points (``True``: found here; ``None``: all).
    """
    found = assess_registration(src, tgt, transform, fitness_threshold, on_surface)._asdict()
    found["warnings"] = list(found["warnings"])
    return found


def _build(method: Any, device: str | None, options: dict[str, Any]):
    """The method object and a JSON-able description of it."""
    if isinstance(method, Mapping):
        config = {**method, **options}
    elif isinstance(method, str) and method in METHODS:
        config = {"name": method, **options}
    elif isinstance(method, str | os.PathLike) and (Path(method).expanduser().exists() or pretrained.is_name(method)):
        settings = {"device": device or "cpu", **options}
        checkpoint = method if pretrained.is_name(method) else Path(method).expanduser()
        return LearnedRegistration(checkpoint, **settings), {"checkpoint": str(method), **options}
    else:
        raise UnknownNameError(
            f"method={method!r}: not a registered method ({', '.join(METHODS.names())}), "
            f"a pretrained network ({', '.join(pretrained.names())}) nor an existing checkpoint file or run folder"
        )
    if device is not None:
        config["device"] = device
    return METHODS.build(config), {key: value for key, value in config.items() if not callable(value)}


def register(
    source: Any,
    target: Any,
    init: Any = None,
    method: str | os.PathLike | Mapping[str, Any] = DEFAULT_METHOD,
    device: str | None = None,
    *,
    fitness_threshold: float | None = None,
    scale: bool = False,
    **options: Any,
) -> RegistrationResult:
    """Find the rigid transform mapping ``source`` onto ``target``.

    Args:
        source, target: ``(N, 3)`` numpy arrays or torch tensors, Open3D ``PointCloud`` s, or
            point-cloud files (any format :func:`linereg.io.read_point_cloud` reads).
        init: optional ``(4, 4)`` initial guess (odometry, GNSS) applied to the source first;
            the result includes it.
        method: ``"robust"`` (the default: the robust solver, CPU only), any other name in
            :data:`linereg.registration.METHODS` (``adam_loss``, ``svd_irls``, ``icp_point``, ...),
            a config ``{name: ..., **options}``, a checkpoint file / run folder of
            ``python -m train`` or a pretrained name of :mod:`linereg.pretrained`
            (``rpm_ours_airplane``: the trained network; ``refine=True`` adds the solver).
        device: torch device of the method (``None``: its default, the CPU); only for methods
            that take one (the solvers and networks, not the Open3D baselines).
        fitness_threshold: inlier distance of ``fitness`` / ``inlier_rmse`` in input units
            (``None``: 3 sampling distances of the target).
        scale: solve a similarity ``tgt ≈ s R src + t`` (clouds in different units,
            :mod:`~linereg.registration.similarity`): ``transformation`` is ``[s R | t]`` and ``scale`` is ``s``.
        **options: the method's keyword arguments (e.g. ``num_points``, ``options={...}`` of
            the robust solver, ``stages`` of ``adam_loss``, ``refine`` of a network).

    Returns:
        A :class:`RegistrationResult`.

    Raises:
        FileNotFoundError: a file that does not exist.
        TypeError, ValueError: a malformed cloud or ``init`` (naming it).
        linereg.registry.UnknownNameError: an unknown method (lists the registered ones).
        linereg.registry.ArgumentError: an option the method does not take (lists the accepted ones).
    """
    src, src_normals = as_cloud(source, "source")
    tgt, tgt_normals = as_cloud(target, "target")
    initial = _checked_init(init)
    solver, description = _build(method, device, options)
    start = time.perf_counter()
    on_surface = surface_points(tgt, src)
    seen, seen_normals = tgt, tgt_normals
    if on_surface is not None:
        seen, seen_normals = tgt[on_surface], None if tgt_normals is None else tgt_normals[on_surface]
    if initial is not None:
        src = src @ initial[:3, :3].T + initial[:3, 3]
        src_normals = None if src_normals is None else src_normals @ initial[:3, :3].T
    solve = _solve_with_scale if scale else _solve_rigid
    result, factor, found = solve(solver, src, seen, src_normals, seen_normals, tgt, fitness_threshold, on_surface)
    seconds = time.perf_counter() - start
    transform = np.asarray(result.transform, dtype=np.float64)
    warnings = [*result.info.get("warnings", ()), *found.pop("warnings")]
    info = {"method": description, **result.info, **found, "warnings": warnings}
    if on_surface is not None:
        info["clutter"] = float(1.0 - on_surface.mean())
    if initial is not None:
        info["init"] = initial.tolist()
        transform = transform @ initial
    return RegistrationResult(
        transformation=transform,
        fitness=float(info.pop("fitness")),
        inlier_rmse=float(info.pop("inlier_rmse")),
        confident=bool(info.pop("confident")),
        seconds=seconds,
        info=info,
        scale=factor,
    )


def _solve_rigid(solver, src, seen, src_normals, seen_normals, tgt, fitness_threshold, on_surface):
    """``(result, 1.0, quality)``: ``solver`` on ``src`` and the target's clutter-free points ``seen``,
    judged against the whole target ``tgt``."""
    result = solver(src, seen, src_normals, seen_normals)
    return result, 1.0, quality(src, tgt, np.asarray(result.transform, dtype=np.float64), fitness_threshold, on_surface)


def _solve_with_scale(solver, src, seen, src_normals, seen_normals, tgt, fitness_threshold, on_surface):
    """``(result, scale, quality)`` of the similarity (:mod:`~linereg.registration.similarity`): the rigid
    ``solver`` on the source scaled by each guess, a similarity polish, the trusted (else best-fitting) answer."""
    best = None
    for guess in scale_guesses(src, seen):
        result = solver(guess * src, seen, src_normals, seen_normals)
        transform = similarity_polish(src, seen, with_scale(np.asarray(result.transform, dtype=np.float64), guess))
        factor = scale_of(transform)
        found = quality(factor * src, tgt, with_scale(transform, 1.0 / factor), fitness_threshold, on_surface)
        rank = (found["confident"], found["fitness"])
        if best is None or rank > best[0]:
            info = {**result.info, "scale_guess": guess}
            best = rank, MethodResult(transform=transform, seconds=result.seconds, info=info), factor, found
    return best[1:]
