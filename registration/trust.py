"""Whether a fit could be chance, whether its pose is determined, and whether the clouds share units.

An inlier share alone is fooled three ways: a target so dense that any placement of the source
lies near its points (clutter, or a target in smaller units: millimetres against metres), a
surface on which the source slides (a plane, a cylinder, a sphere) and a shape that maps onto
itself (a symmetric object). :func:`~linereg.registration.evaluation.assess_registration` asks
each question with a function of this module:

* :func:`chance_fitness`: the share of source points within a tight radius of the target at the
  answer, against the same share at random placements of the source on the target;
* :func:`free_motions`: the rigid motions the fit does not constrain, from the eigenvalues of the
  6x6 point-to-plane information matrix of the inliers (Gelfand, Ikemoto, Rusinkiewicz and Levoy,
  *Geometrically stable sampling for the ICP algorithm*, 3DIM 2003);
* :func:`symmetric_rival`: the answer turned by 90, 180 and 270 degrees about the inliers'
  principal axes, which fits as well when the shape is symmetric;
* :func:`scale_mismatch`: the clouds' point spacings, which differ by the unit factor;
* :func:`surface_points`: the target points as densely sampled as the source (clutter left out).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.registration.poses import apply, rodrigues, rotation_gap_deg
from linereg.registration.welsch import welsch_irls

CHANCE_PLACEMENTS = 32
"""Random placements of the source that :func:`chance_fitness` measures."""
CHANCE_QUANTILE = 0.9
"""The placements' fitness quantile that stands for chance."""
WEAK_DIRECTIONS = 3
"""Directions of least information that :func:`free_motions` moves the answer along."""
SCALE_MOVE = 0.03
"""The change of scale that :func:`free_scale` tries."""
FLAT = 1e-3
"""A variance ratio under which the overlap is a plane (its thickness under 3 % of its width)."""
FREE_MOVE = 0.2
"""The size of that move: a rotation of 0.2 rad (11 degrees) or a shift of 0.2 RMS radii of the overlap."""
RIVAL_STEPS = 8
"""Welsch IRLS steps that polish each turned answer (3 to 1 point spacings) ..."""
RIVAL_POINTS = 256
"""... on this many of the measured source points; the best-fitting one then gets
:data:`RIVAL_SETTLE` more steps on all of them."""
RIVAL_SETTLE = 2
RIVAL_GAP_DEG = 10.0
"""A polished turned answer closer than this to the answer is the answer again."""
RIVAL_FITNESS = 0.9
"""A turned answer that keeps this share of the answer's :func:`soft_fitness` fits as well."""
FREE_FITNESS = 0.93
"""A moved answer (:data:`FREE_MOVE`) that keeps this share of it leaves the motion free (right human
views keep at most 0.91 on the confidence study's pairs, seed 7; a sphere's caps 0.94 and more)."""
SCALE_MISMATCH = 3.0
"""Point-spacing ratio from which the clouds are taken to be in different units."""
NORMAL_NEIGHBOURS = 10
"""Target points of the plane fitted at each inlier (its normal)."""
SURFACE_NEIGHBOURS = 8
"""Neighbours whose distance measures a point's local density in :func:`surface_points`."""
SURFACE_DENSITY = 1.5
"""A target point is on a surface when its density distance is within this factor of the source's."""
SURFACE_SHARE = (0.02, 0.8)
"""The surface's share of the target between which the rest is clutter (else the target is kept whole)."""
SURFACE_GAP = 1.8
"""The rest of the target is clutter only when its median density distance is this many times the surface's."""
SURFACE_FLOOR = 1.2
"""The densest 5 % of the target lie within this factor of the source's density distance when
part of it is sampled as the source is (a target in other units is not)."""


def spacing_of(points: np.ndarray, sample: int = 20000, seed: int = 0) -> float:
    """The sampling distance of ``points (N, 3)`` at its full density: the median distance from a
    point to its nearest other point, on a random ``sample`` (scaled by ``sqrt(sample / N)``, the
    spacing of a surface sampled ``N / sample`` times more densely); repeated points count once."""
    order = points[np.lexsort(points.T[::-1])]  # the rows of np.unique(points, axis=0), at half its cost
    points = order[np.concatenate([[True], np.any(order[1:] != order[:-1], axis=1)])]
    rng = np.random.default_rng(seed)
    subset = points if len(points) <= sample else points[rng.choice(len(points), sample, replace=False)]
    distances, _ = NearestNeighbors(subset).query(subset, k=2)
    return float(np.median(distances[:, 1]) * np.sqrt(len(subset) / len(points)))


def random_rotations(count: int, rng: np.random.Generator) -> np.ndarray:
    """``(count, 3, 3)`` rotations uniform over SO(3) (normalised Gaussian quaternions)."""
    q = rng.normal(size=(count, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def chance_fitness(source: np.ndarray, target: NearestNeighbors, radius: float, seed: int = 0) -> float:
    """The share of ``source (N, 3)`` points within ``radius`` of the target that random placements
    reach: the :data:`CHANCE_QUANTILE` of :data:`CHANCE_PLACEMENTS` placements, each a uniform random
    rotation about the source's centroid and that centroid moved onto a random target point."""
    rng = np.random.default_rng(seed)
    rotations = random_rotations(CHANCE_PLACEMENTS, rng)
    anchors = target.points[rng.integers(len(target), size=CHANCE_PLACEMENTS)]
    centred = source - source.mean(axis=0)
    placed = apply((rotations, anchors), centred)
    distances, _ = target.query(placed, distance_upper_bound=radius)
    return float(np.quantile((distances <= radius).mean(axis=1), CHANCE_QUANTILE))


def target_normals(points: np.ndarray, target: NearestNeighbors) -> np.ndarray:
    """``(N, 3)`` unit normals of the target's surface near ``points (N, 3)``: the least direction
    of its :data:`NORMAL_NEIGHBOURS` nearest points."""
    _, idx = target.query(points, k=NORMAL_NEIGHBOURS)
    neighbours = target.points[idx]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(centred.transpose(0, 2, 1) @ centred)
    return vectors[:, :, 0]


class FreeMotion(NamedTuple):
    """A rigid motion the fit does not constrain: ``kind`` ``"rotation"`` (about ``axis`` through
    ``center``) or ``"translation"`` (along ``axis``), and its eigenvalue's share of the largest."""

    kind: str
    axis: np.ndarray
    center: np.ndarray
    share: float


def free_motions(moved: np.ndarray, inliers: np.ndarray, target: NearestNeighbors, sigma: float) -> list[FreeMotion]:
    """The motions of the answer that keep its fit: of the :data:`WEAK_DIRECTIONS` eigenvectors of
    least eigenvalue of the 6x6 point-to-plane information matrix ``sum J_i^T J_i`` of the ``inliers
    (n, 3)``, ``J_i = [((p_i - c) / L) x n_i, n_i]`` (``c`` their centroid, ``L`` their RMS radius,
    ``n_i`` the target's normals there), those along which a move of
    :data:`FREE_MOVE` ``L`` (either way) keeps at least :data:`FREE_FITNESS`
    of the :func:`soft_fitness` of the moved source ``moved (N, 3)`` against ``target`` at ``sigma``."""
    if len(inliers) < NORMAL_NEIGHBOURS:
        return []
    normals = target_normals(inliers, target)
    center = inliers.mean(axis=0)
    arm = inliers - center
    length = max(float(np.sqrt(np.mean(np.sum(arm**2, axis=1)))), 1e-300)
    jacobian = np.concatenate([np.cross(arm / length, normals), normals], axis=1)
    values, vectors = np.linalg.eigh(jacobian.T @ jacobian / len(inliers))
    own = float(soft_fitness(moved, target, np.eye(4)[None], sigma)[0])
    motions = []
    for value, vector in zip(values[:WEAK_DIRECTIONS], vectors.T[:WEAK_DIRECTIONS], strict=True):
        moves = np.stack([_twist(sign * FREE_MOVE * vector, center, length) for sign in (1.0, -1.0)])
        if soft_fitness(moved, target, moves, sigma).max() < FREE_FITNESS * own:
            continue
        rotation, shift = vector[:3], vector[3:]
        kind = "rotation" if np.linalg.norm(rotation) >= np.linalg.norm(shift) else "translation"
        axis = rotation if kind == "rotation" else shift
        motions.append(FreeMotion(kind, axis / np.linalg.norm(axis), center, float(value / values[-1])))
    return motions


def _twist(vector: np.ndarray, center: np.ndarray, length: float) -> np.ndarray:
    """``(4, 4)``: the motion ``vector = [a, b]`` of :func:`free_motions`' coordinates, a rotation by the
    vector ``a`` (radians) about ``center`` then a shift by ``b L``."""
    rotation = rodrigues(vector[None, :3])[0]
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = rotation, center - rotation @ center + vector[3:] * length
    return motion


def describe_free(motions: list[FreeMotion], inliers: np.ndarray) -> str:
    """A warning naming the free motions, and the plane of a flat overlap ``inliers (n, 3)`` (its
    thinnest principal direction under :data:`FLAT` of its widest)."""
    parts = [
        f"rotation about {np.round(motion.axis, 2).tolist()}"
        if motion.kind == "rotation"
        else f"translation along {np.round(motion.axis, 2).tolist()}"
        for motion in motions
    ]
    values, axes = np.linalg.eigh(np.cov((inliers - inliers.mean(axis=0)).T))
    if values[0] < FLAT * values[-1]:
        normal = np.round(axes[:, 0], 2).tolist()
        parts = [
            f"rotation about its normal {normal}" if motion.kind == "rotation" else "sliding within it"
            for motion in motions
        ]
        parts = list(dict.fromkeys(parts))
        verb = "is" if len(parts) == 1 else "are"
        return f"the pose is not unique: the overlap is planar; {' and '.join(parts)} {verb} free"
    return f"the pose is not unique: {' and '.join(parts)} {'is' if len(parts) == 1 else 'are'} free"


def turned(transform: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """``(9, 4, 4)``: ``transform`` followed by turns of 90, 180 and 270 degrees about each principal
    axis of the moved ``inliers (N, 3)`` through their centroid."""
    center = inliers.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((inliers - center).T))
    turns = []
    for axis in axes.T:
        for angle in (0.5 * np.pi, np.pi, 1.5 * np.pi):
            rotation = rodrigues(angle * axis[None])[0]
            turn = np.eye(4)
            turn[:3, :3], turn[:3, 3] = rotation, center - rotation @ center
            turns.append(turn @ transform)
    return np.stack(turns)


def tight_fitness(source: np.ndarray, target: NearestNeighbors, transforms: np.ndarray, radius: float) -> np.ndarray:
    """``(K,)`` shares of ``source (N, 3)`` points within ``radius`` of the target under each of
    ``transforms (K, 4, 4)``."""
    moved = apply((transforms[:, :3, :3], transforms[:, :3, 3]), source)
    distances, _ = target.query(moved, distance_upper_bound=radius)
    return (distances <= radius).mean(axis=1)


def free_scale(source: np.ndarray, target: np.ndarray, transform: np.ndarray) -> str | None:
    """A warning when the scale of a similarity ``transform (4, 4)`` mapping ``source (N, 3)`` onto
    ``target (M, 3)`` is not determined: scaling the answer by ``1 -/+`` :data:`SCALE_MOVE` about
    its centroid keeps :data:`FREE_FITNESS` of its :func:`soft_fitness` (else ``None``)."""
    from linereg.fps import farthest_point_subset as fps

    moved = fps(source, 2048) @ transform[:3, :3].T + transform[:3, 3]
    index, spacing = NearestNeighbors(target), spacing_of(target)
    center = moved.mean(axis=0)
    own = float(soft_fitness(moved, index, np.eye(4)[None], spacing)[0])
    scalings = np.stack([np.eye(4)] * 2)
    for scaling, factor in zip(scalings, (1.0 - SCALE_MOVE, 1.0 + SCALE_MOVE), strict=True):
        scaling[:3, :3] *= factor
        scaling[:3, 3] = center - factor * center
    if soft_fitness(moved, index, scalings, spacing).max() < FREE_FITNESS * own:
        return None
    return f"the scale is not determined: {100 * SCALE_MOVE:g} % larger or smaller fits as well (too little structure)"


def soft_fitness(source: np.ndarray, target: NearestNeighbors, transforms: np.ndarray, sigma: float) -> np.ndarray:
    """``(K,)`` mean Gaussian scores ``exp(-d^2 / 2 sigma^2)`` of the nearest-target distances of
    ``source (N, 3)`` under each of ``transforms (K, 4, 4)``: unlike a share within a radius it
    falls as soon as an exact fit moves."""
    moved = apply((transforms[:, :3, :3], transforms[:, :3, 3]), source)
    distances, _ = target.query(moved, distance_upper_bound=3.0 * sigma)
    return np.exp(-0.5 * np.square(np.minimum(distances, 3.0 * sigma) / sigma)).mean(axis=1)


def symmetric_rival(
    source: np.ndarray, target: NearestNeighbors, transform: np.ndarray, inliers: np.ndarray, sigma: float
) -> float | None:
    """The angle (degrees) from the answer of a turned one (:func:`turned`), polished by
    :data:`RIVAL_STEPS` Welsch IRLS steps down to ``sigma`` on :data:`RIVAL_POINTS` of ``source
    (n, 3)`` and, the best-fitting of them, :data:`RIVAL_SETTLE` steps on all, still more than
    :data:`RIVAL_GAP_DEG` away, whose :func:`soft_fitness` at ``sigma`` is at least
    :data:`RIVAL_FITNESS` of the answer's; ``None`` when there is none."""
    if len(inliers) < 4:
        return None
    rivals = turned(transform, inliers)
    sample = source[:: max(len(source) // RIVAL_POINTS, 1)]
    scales = np.geomspace(3.0 * sigma, sigma, RIVAL_STEPS)
    rotations, translations = welsch_irls((rivals[:, :3, :3], rivals[:, :3, 3]), sample, target, scales)
    gaps = rotation_gap_deg(rotations, transform[:3, :3])
    rivals[:, :3, :3], rivals[:, :3, 3] = rotations, translations
    fits = np.where(gaps > RIVAL_GAP_DEG, soft_fitness(sample, target, rivals, sigma), -1.0)
    best = rivals[int(fits.argmax())][None]
    rotation, translation = welsch_irls((best[:, :3, :3], best[:, :3, 3]), source, target, [sigma] * RIVAL_SETTLE)
    best[:, :3, :3], best[:, :3, 3] = rotation, translation
    gap = float(rotation_gap_deg(rotation, transform[:3, :3])[0])
    own = float(soft_fitness(source, target, transform[None], sigma)[0])
    fit = float(soft_fitness(source, target, best, sigma)[0])
    if own <= 0 or gap <= RIVAL_GAP_DEG or fit < RIVAL_FITNESS * own:
        return None
    return gap


def scale_mismatch(source_spacing: float, target_spacing: float) -> str | None:
    """A warning when the clouds' point spacings differ by :data:`SCALE_MISMATCH` or more."""
    ratio = target_spacing / max(source_spacing, 1e-300)
    hint = "different units? try scale=true"
    if ratio >= SCALE_MISMATCH:
        return f"the target's points are about {ratio:.3g}x further apart than the source's: {hint}"
    if ratio <= 1.0 / SCALE_MISMATCH:
        return f"the source's points are about {1 / ratio:.3g}x further apart than the target's: {hint}"
    return None


def surface_points(
    target: np.ndarray,
    source: np.ndarray,
    sample: int = 5000,
    seed: int = 0,
    target_index: NearestNeighbors | None = None,
    source_index: NearestNeighbors | None = None,
) -> np.ndarray | None:
    """``(M,)`` bool: the points of ``target (M, 3)`` sampled at least about as densely as ``source
    (N, 3)``, when they are between :data:`SURFACE_SHARE` of it (the rest is clutter), else ``None``.

    A point's density distance is the distance to its :data:`SURFACE_NEIGHBOURS`-th nearest other
    point; a target point is kept when its distance is at most :data:`SURFACE_DENSITY` times the
    median of the source's (uniform clutter in a volume is far sparser than a scanned surface).
    The share, whether the target's densest points match the source's density at all
    (:data:`SURFACE_FLOOR`) and whether the rest is far sparser than they are (:data:`SURFACE_GAP`:
    a target in other units or of uneven density is not cluttered) are first estimated on a random
    ``sample`` of the target. ``target_index``, ``source_index``: their KD-trees, when already built.
    """
    rng = np.random.default_rng(seed)
    k = SURFACE_NEIGHBOURS + 1
    src_sample = source if len(source) <= sample else source[rng.choice(len(source), sample, replace=False)]
    reference = float(np.median((source_index or NearestNeighbors(source)).query(src_sample, k=k)[0][:, -1]))
    index = target_index or NearestNeighbors(target)
    probe = target if len(target) <= sample else target[rng.choice(len(target), sample, replace=False)]
    density = index.query(probe, k=k)[0][:, -1]
    dense = density <= SURFACE_DENSITY * reference
    share = float(dense.mean())
    if not SURFACE_SHARE[0] <= share < SURFACE_SHARE[1] or np.quantile(density, 0.05) > SURFACE_FLOOR * reference:
        return None
    if np.median(density[~dense]) < SURFACE_GAP * np.median(density[dense]):
        return None
    return index.query(target, k=k)[0][:, -1] <= SURFACE_DENSITY * reference


TIGHT_DISTANCES = 1.5
"""Radius of the chance test, in point spacings of the target's surface (:func:`spacing_of`)."""
CHANCE_MARGIN = 0.05
"""A confident answer's tight fitness exceeds chance's by at least this share, and ..."""
CHANCE_FACTOR = 2.0
"""... is at least this multiple of chance's, or ..."""
CHANCE_MISS = 0.25
"""... leaves at most this share of the points that chance leaves (a volume-like cloud, where chance is high)."""
UNITS_HINT = 1.5
"""Point-spacing ratio from which a pose that is not trusted gets the hint to try ``scale=true``."""


def beats_chance(own: float, chance: float) -> bool:
    """Whether a tight fitness ``own`` is clearly above ``chance``'s: by :data:`CHANCE_MARGIN`, and
    :data:`CHANCE_FACTOR` times it or missing at most :data:`CHANCE_MISS` of what it misses."""
    clear = own >= CHANCE_FACTOR * chance or 1.0 - own <= CHANCE_MISS * (1.0 - chance)
    return own - chance >= CHANCE_MARGIN and clear


class Verdict(NamedTuple):
    """Result of :func:`verdict`: ``confident``, the answer's tight fitness and chance's (``nan``
    when not measured) and the warnings, one line each."""

    confident: bool
    tight_fitness: float
    chance_fitness: float
    warnings: tuple[str, ...]


def verdict(
    source: np.ndarray,
    subset: np.ndarray,
    target: np.ndarray,
    surface: np.ndarray | None,
    transform: np.ndarray,
    passed: bool,
    index: NearestNeighbors | None = None,
) -> Verdict:
    """The tests of this module on ``transform (4, 4)`` mapping ``source (N, 3)`` (``subset (n, 3)``
    of it measured) onto ``target (M, 3)``, whose clutter-free ``surface`` (:func:`surface_points`;
    ``None``: all of it) gave the inlier test its result ``passed``. Confident: ``passed``, a tight
    fitness above chance's (:func:`beats_chance`), no free motion and no symmetric rival. ``index``:
    the KD-tree of ``target``, when already built."""
    surface = target if surface is None else surface
    source_spacing, target_spacing = spacing_of(source), spacing_of(surface)
    mismatch = scale_mismatch(source_spacing, target_spacing)
    notes = [] if mismatch is None else [mismatch]
    ratio = max(target_spacing, source_spacing) / max(min(target_spacing, source_spacing), 1e-300)
    if not passed:
        if mismatch is None and ratio >= UNITS_HINT:
            notes.append(
                f"the clouds' point spacings differ {ratio:.2g}x: different units or resolutions? try scale=true"
            )
        return Verdict(False, float("nan"), float("nan"), tuple(notes))
    index = index or NearestNeighbors(target)
    radius = TIGHT_DISTANCES * target_spacing
    own = float(tight_fitness(subset, index, transform[None], radius)[0])
    chance = chance_fitness(subset, index, radius)
    failures = []
    if not beats_chance(own, chance):
        failures.append(
            f"the fit is no better than chance: {100 * own:.0f} % of the source within {TIGHT_DISTANCES:g} point "
            f"spacings of the target, {100 * chance:.0f} % at random placements (a cluttered or much denser target?)"
        )
        return Verdict(False, own, chance, tuple(notes + failures))
    moved = subset @ transform[:3, :3].T + transform[:3, 3]
    on_surface = index if surface is target else NearestNeighbors(surface)
    distances, _ = on_surface.query(moved, distance_upper_bound=radius)
    inliers = moved[distances <= radius]
    motions = free_motions(moved, inliers, on_surface, target_spacing)
    if motions:
        failures.append(describe_free(motions, inliers))
    rival = symmetric_rival(subset, on_surface, transform, inliers, target_spacing)
    if rival is not None:
        failures.append(
            f"the pose is not unique: the answer turned {rival:.0f} degrees about a principal axis of the overlap "
            "fits as well (a symmetric shape)"
        )
    return Verdict(not failures, own, chance, tuple(notes + failures))
