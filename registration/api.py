"""``linereg.register``: align two point clouds, with results modelled on Open3D's ``registration_*``.

::

    import linereg

    result = linereg.register("scan_a.ply", "scan_b.ply")          # files, (N, 3) arrays or tensors
    result.transformation                                          # (4, 4) source -> target
    result.confident, result.fitness, result.inlier_rmse

    linereg.register(src, tgt, init=T0)                            # an initial guess (4, 4)
    linereg.register(src, tgt, method="icp_point")                 # any registered method
    linereg.register(src, tgt, method="outputs/rpm_ours/runs/<run>/", refine=True)  # a trained network (+ solver)
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from linereg import pretrained
from linereg.checks import as_rigid_transform, check_points, is_tensor
from linereg.io import PointCloud, read_point_cloud
from linereg.knn import NearestNeighbors
from linereg.registration.evaluation import Assessment, assess_registration
from linereg.registration.learned import LearnedRegistration
from linereg.registration.methods import METHODS, MethodResult
from linereg.registration.noise import noisy_sides, smoothed, surface_noise
from linereg.registration.robust_result import RobustResult
from linereg.registration.similarity import scale_guesses, scale_of, similarity_polish, with_scale
from linereg.registration.trust import SCALE_MOVE, free_scale, surface_points
from linereg.registry import UnknownNameError

DEFAULT_METHOD = "robust"
MIN_POINTS = 3
"""Fewest points a cloud may have (the command's and the library's input check)."""


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
        info: what no field holds: ``method``, ``fitness_threshold``, ``sampling_distance``,
            ``tight_fitness``, ``chance_fitness``, ``warnings``, ``surface_noise``, ``smoothed``,
            ``clutter``, ``init`` and the method's own extras (``path`` of a finished network, ...).
        solution: the method's typed record, when it has one: the default solver's
            :class:`~linereg.registration.robust_result.RobustResult` (its rounds, candidates,
            steps and doubt tests).
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    confident: bool
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)
    scale: float = 1.0
    solution: RobustResult | None = None


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
        cloud = read_cloud_file(value, name)
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
    check_points(points, name, batched=False, min_points=MIN_POINTS)
    return np.asarray(points, dtype=np.float64), None if normals is None else np.asarray(normals, dtype=np.float64)


def read_cloud_file(path: str | os.PathLike, name: str) -> PointCloud:
    """The cloud in the file ``path``, given as the argument ``name``.

    Raises:
        FileNotFoundError: no such file (the message names the argument).
        ValueError: a folder, or a file :func:`linereg.io.read_point_cloud` cannot read as a cloud of at
            least :data:`MIN_POINTS` finite points (naming the argument).
    """
    file = Path(path).expanduser()
    if file.is_dir():
        raise ValueError(f"{name}={path}: is a folder, expected a point-cloud file")
    if not file.exists():
        raise FileNotFoundError(f"{name}={path}: no such file")
    try:
        return read_point_cloud(file, min_points=MIN_POINTS)
    except ValueError as error:
        raise ValueError(f"{name}={path}: {error}") from error


def _checked_init(init: Any) -> np.ndarray | None:
    """``init`` as an exactly rigid ``(4, 4)`` (a near-rigid one orthonormalised with a warning)."""
    if init is None:
        return None
    transform = init.detach().cpu().numpy() if is_tensor(init) else np.asarray(init, dtype=np.float64)
    return as_rigid_transform(transform, "init")


def quality(
    src: np.ndarray,
    tgt: np.ndarray,
    transform: np.ndarray,
    fitness_threshold: float | None = None,
    on_surface: np.ndarray | bool | None = True,
    target_index: NearestNeighbors | None = None,
) -> dict[str, Any]:
    """``fitness``, ``inlier_rmse``, ``fitness_threshold``, ``sampling_distance`` and ``confident`` of
    ``transform (4, 4)`` mapping ``src (N, 3)`` onto ``tgt (M, 3)``: the same test for every method
    (:func:`~linereg.registration.evaluation.assess_registration`).

    Args:
        fitness_threshold: inlier distance of ``fitness`` and ``inlier_rmse`` in input units
            (``None``: 3 sampling distances of the target).
        on_surface: the target's clutter-free points (``True``: found here; ``None``: all).
        target_index: the KD-tree of ``tgt``, when already built.
    """
    found = assess_registration(src, tgt, transform, fitness_threshold, on_surface, target_index)._asdict()
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
    return register_clouds(
        solver,
        description,
        (src, src_normals),
        (tgt, tgt_normals),
        initial,
        fitness_threshold=fitness_threshold,
        scale=scale,
    )


def register_clouds(
    solver,
    description: Any,
    source: tuple[np.ndarray, np.ndarray | None],
    target: tuple[np.ndarray, np.ndarray | None],
    initial: np.ndarray | None = None,
    *,
    fitness_threshold: float | None = None,
    scale: bool = False,
    on_surface: np.ndarray | bool | None = True,
) -> RegistrationResult:
    """:func:`register` on checked clouds: ``solver`` (a built method, described by ``description``)
    on ``source`` and ``target`` (``(points (N, 3), normals or None)`` each), the source moved by
    ``initial`` first; ``on_surface``: the target's clutter-free points (``True``: found here)."""
    (src, src_normals), (tgt, tgt_normals) = source, target
    start = time.perf_counter()
    if initial is not None:
        src = src @ initial[:3, :3].T + initial[:3, 3]
        src_normals = None if src_normals is None else src_normals @ initial[:3, :3].T
    indices = _Indices(NearestNeighbors(src), NearestNeighbors(tgt))
    if on_surface is True:
        on_surface = surface_points(tgt, src, target_index=indices.tgt, source_index=indices.src)
    seen, noise = _seen(src, src_normals, tgt, tgt_normals, on_surface, indices)
    solve = _solve_with_scale if scale else _solve_rigid
    result, factor, judged = solve(solver, seen, src, tgt, _Judge(fitness_threshold, on_surface, indices.tgt))
    seconds = time.perf_counter() - start
    transform = np.asarray(result.transform, dtype=np.float64)
    measured = {key: getattr(judged, key) for key in _MEASURED}
    warnings = [*result.info.get("warnings", ()), *judged.warnings]
    info = {"method": description, **result.info, **measured, "warnings": warnings, **noise}
    if on_surface is not None:
        info["clutter"] = float(1.0 - on_surface.mean())
    if initial is not None:
        info["init"] = initial.tolist()
        transform = transform @ initial
    return RegistrationResult(
        transformation=transform,
        fitness=judged.fitness,
        inlier_rmse=judged.inlier_rmse,
        confident=judged.confident,
        seconds=seconds,
        info=info,
        scale=factor,
        solution=result.solution,
    )


class _Indices(NamedTuple):
    """The KD-trees of the source and the whole target, built once for every test of ``register``."""

    src: NearestNeighbors
    tgt: NearestNeighbors


class _Judge(NamedTuple):
    """How ``register`` judges an answer (:func:`quality`): the reported inlier distance, the
    target's clutter-free points and the KD-tree of the whole target."""

    fitness_threshold: float | None
    on_surface: np.ndarray | None
    target_index: NearestNeighbors

    def __call__(self, src: np.ndarray, tgt: np.ndarray, transform: np.ndarray) -> Assessment:
        """The :class:`~linereg.registration.evaluation.Assessment` of ``transform (4, 4)`` mapping
        ``src (N, 3)`` onto the whole target ``tgt (M, 3)``."""
        return assess_registration(src, tgt, transform, self.fitness_threshold, self.on_surface, self.target_index)


_MEASURED = ("fitness_threshold", "sampling_distance", "tight_fitness", "chance_fitness")
"""The fields of the check's :class:`~linereg.registration.evaluation.Assessment` that
:class:`RegistrationResult` keeps in ``info`` (the others are its own fields)."""


class _Seen(NamedTuple):
    """The clouds the solver sees: the source and the target's clutter-free points, each smoothed
    when it is far noisier than the other (:mod:`~linereg.registration.noise`)."""

    src: np.ndarray
    tgt: np.ndarray
    src_normals: np.ndarray | None
    tgt_normals: np.ndarray | None


def _seen(src, src_normals, tgt, tgt_normals, on_surface, indices: _Indices) -> tuple[_Seen, dict[str, Any]]:
    """The solver's :class:`_Seen` clouds and ``info``'s ``surface_noise`` (both clouds', in point
    spacings) and ``smoothed`` (the clouds smoothed for the solver)."""
    src_index, tgt_index = indices
    if on_surface is not None:
        tgt, tgt_normals, tgt_index = tgt[on_surface], None if tgt_normals is None else tgt_normals[on_surface], None
    tgt_index = tgt_index or NearestNeighbors(tgt)
    noise = {"source": surface_noise(src, index=src_index), "target": surface_noise(tgt, index=tgt_index)}
    smooth = noisy_sides(noise["source"], noise["target"])
    src = smoothed(src, src_index) if smooth[0] else src
    tgt = smoothed(tgt, tgt_index) if smooth[1] else tgt
    seen = _Seen(src, tgt, src_normals, tgt_normals)
    chosen = [name for name, smoothing in zip(noise, smooth, strict=True) if smoothing]
    return seen, {"surface_noise": noise, "smoothed": chosen}


def _solve_rigid(solver, seen: _Seen, src, tgt, judge: _Judge):
    """``(result, 1.0, assessment)``: ``solver`` on the :class:`_Seen` clouds, judged on the source
    ``src`` and the whole target ``tgt``."""
    result = solver(*seen)
    return result, 1.0, judge(src, tgt, np.asarray(result.transform, dtype=np.float64))


def _solve_with_scale(solver, seen: _Seen, src, tgt, judge: _Judge):
    """``(result, scale, assessment)`` of the similarity (:mod:`~linereg.registration.similarity`): the rigid
    ``solver`` on the :class:`_Seen` source scaled by each guess, a similarity polish, the trusted (else
    best-fitting) answer, judged on ``src`` and the whole target ``tgt``; when the fit leaves its scale
    free, the rigid answer at the point spacings' ratio (:func:`_scale_by_spacing`)."""
    best, by_spacing = None, None
    for guess in scale_guesses(seen.src, seen.tgt):
        result = solver(guess * seen.src, seen.tgt, seen.src_normals, seen.tgt_normals)
        by_spacing = by_spacing or (guess, result)
        rigid = np.asarray(result.transform, dtype=np.float64)
        transform = similarity_polish(seen.src, seen.tgt, with_scale(rigid, guess))
        factor = scale_of(transform)
        found = judge(factor * src, tgt, with_scale(transform, 1.0 / factor))
        loose = free_scale(seen.src, seen.tgt, transform) if found.confident else None
        if loose is not None:
            found = found._replace(confident=False, warnings=(*found.warnings, loose))
        rank = (found.confident, found.fitness)
        if best is None or rank > best[0]:
            info = {**result.info, "scale_guess": guess, "scale_from": "fit"}
            answer = MethodResult(transform=transform, seconds=result.seconds, info=info, solution=result.solution)
            best = rank, answer, factor, found, loose
    _, answer, factor, found, loose = best
    if loose is not None:
        return _scale_by_spacing((answer, factor, found), *by_spacing, src, tgt, judge)
    return answer, factor, found


def _scale_by_spacing(fitted, guess, result, src, tgt, judge: _Judge):
    """A fit ``(answer, scale, assessment)`` that leaves its scale free within
    :data:`~linereg.registration.trust.SCALE_MOVE` (a room pair whose planes slide): the rigid
    ``result`` at the point spacings' ratio ``guess`` (one sensor's points in two units) when that ratio
    lies within the free range and register's check trusts the rigid answer there, else ``fitted``."""
    _, factor, _ = fitted
    if abs(factor / guess - 1.0) > SCALE_MOVE:
        return fitted
    rigid = np.asarray(result.transform, dtype=np.float64)
    held = judge(guess * src, tgt, rigid)
    if not held.confident:
        return fitted
    info = {**result.info, "scale_guess": guess, "scale_from": "point spacings"}
    transform = with_scale(rigid, guess)
    scaled = MethodResult(transform=transform, seconds=result.seconds, info=info, solution=result.solution)
    return scaled, guess, held
