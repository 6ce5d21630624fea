"""The coarse stage of the ``register`` default: CD-W from many starting poses at once (numpy).

CD-W is the Chamfer distance with Welsch's function, ``mean psi(d_xy) + mean psi(d_yx)`` with
``psi(d) = 1 - exp(-d^2 / 2 nu^2)`` and ``nu = nu0 * median`` of the nearest distances (the
paper's Welsch scale). :func:`cdw_irls` minimises it by IRLS (majorise-minimise: the nearest
basin, fast); :func:`cdw_adam` by Adam in the tangent space of each pose, whose fixed-length
steps slide across shallow barriers that stop IRLS. Where a pose's ``two_sided`` flag is false
only the source-to-target term counts: the model of a partial source inside a whole target.
"""

from __future__ import annotations

import numpy as np

from linereg.knn import NearestNeighbors
from linereg.procrustes import weighted_procrustes_numpy
from linereg.registration.poses import Poses, apply, merged_into_earlier, rodrigues
from linereg.registration.welsch import lower_median, welsch_cost, welsch_weights


def cdw(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    src_index: NearestNeighbors,
    tgt_index: NearestNeighbors,
    two_sided: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest neighbours of CD-W at each pose, both directions, from indices built once.

    The target-to-source matches query the target moved back by the inverse pose in the index of
    the unmoved source, so no index is built per pose.

    Returns:
        ``d_xy (K, N)``, ``j (K, N)`` (nearest target of each moved source point), ``d_yx (K, M)``,
        ``i (K, M)`` (nearest source point of each target point), ``median (K,)`` (of both
        directions where ``two_sided``, of ``d_xy`` alone elsewhere).
    """
    rotations, translations = poses
    d_xy, j = tgt_index.query(apply(poses, src))
    back = (tgt[None] - translations[:, None, :]) @ rotations
    d_yx, i = src_index.query(back)
    median = np.where(two_sided, lower_median(np.concatenate([d_xy, d_yx], axis=1)), lower_median(d_xy))
    return d_xy, j, d_yx, i, median


def cdw_value(poses: Poses, src: np.ndarray, tgt: np.ndarray, nu: np.ndarray, two_sided: np.ndarray) -> np.ndarray:
    """CD-W at each pose with a given scale ``nu (K,)``: ``mean psi(d_xy) + [two_sided] mean psi(d_yx)``."""
    d_xy, _, d_yx, _, _ = cdw(poses, src, tgt, NearestNeighbors(src), NearestNeighbors(tgt), two_sided)
    return welsch_cost(d_xy, nu[:, None]) + two_sided * welsch_cost(d_yx, nu[:, None])


def cdw_irls(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    two_sided: np.ndarray,
    nu0: float,
    steps: int,
    *,
    fixed_nu: np.ndarray | None = None,
    tolerance: float = 1e-6,
    merge_distance: float = 0.0,
) -> tuple[Poses, np.ndarray]:
    """IRLS (MM) on CD-W from every pose at once: the first round's coarse stage.

    Each step matches both ways (:func:`cdw`), weights each match by Welsch's
    ``exp(-d^2 / 2 nu^2)`` divided by its direction's point count (the objective is a mean per
    direction) and solves one weighted Procrustes problem over the union of the matches.

    Args:
        poses: ``K`` starting poses.
        src: ``(N, 3)`` source points; tgt: ``(M, 3)`` target points.
        two_sided: ``(K,)`` booleans.
        nu0: ``nu = nu0 * median`` nearest distance of the current pose (CD-W's scale).
        steps: most IRLS steps; a pose that moves less than ``tolerance`` stops early.
        fixed_nu: ``(K,)`` scales held constant instead (then every step decreases CD-W at that scale).
        merge_distance: a pose whose rotation (as a chord: ``|R_a - R_b|`` max entry) and
            translation both lie within this of an earlier pose with the same ``two_sided``
            has merged into its basin: it stops and is flagged (0: never).

    Returns:
        ``(poses, merged (K,))``: the ``K`` final poses, and which of them merged into an earlier one.
    """
    src_index, tgt_index = NearestNeighbors(src), NearestNeighbors(tgt)
    rotations, translations = (array.copy() for array in poses)
    active = np.ones(len(rotations), dtype=bool)
    merged = np.zeros(len(rotations), dtype=bool)
    scale = np.concatenate([np.full(len(src), 1.0 / len(src)), np.full(len(tgt), 1.0 / len(tgt))])
    for _ in range(steps):
        if not active.any():
            break
        current = (rotations[active], translations[active])
        sides = two_sided[active]
        d_xy, j, d_yx, i, median = cdw(current, src, tgt, src_index, tgt_index, sides)
        nu = np.maximum(nu0 * median if fixed_nu is None else fixed_nu[active], 1e-12)[:, None]
        weights = np.concatenate([welsch_weights(d_xy, nu), welsch_weights(d_yx, nu) * sides[:, None]], axis=1)
        p = np.concatenate([np.broadcast_to(src, (len(j), *src.shape)), src[i]], axis=1)
        q = np.concatenate([tgt[j], np.broadcast_to(tgt, (len(i), *tgt.shape))], axis=1)
        new_r, new_t, valid = weighted_procrustes_numpy(p, q, weights * scale)
        new_r[~valid], new_t[~valid] = current[0][~valid], current[1][~valid]
        moved = np.abs(new_r - current[0]).max(axis=(1, 2)) + np.abs(new_t - current[1]).max(axis=1)
        rotations[active], translations[active] = new_r, new_t
        active[np.flatnonzero(active)[moved < tolerance]] = False
        if merge_distance > 0:
            duplicate = merged_into_earlier((rotations, translations), two_sided, merged, merge_distance)
            merged |= duplicate
            active &= ~duplicate
    return (rotations, translations), merged


def cdw_gradient(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    src_index: NearestNeighbors,
    tgt_index: NearestNeighbors,
    two_sided: np.ndarray,
    nu0: float,
) -> np.ndarray:
    """Gradient ``(K, 6)`` (rotation, then translation) of CD-W under a left perturbation
    ``T <- exp(xi) T`` at ``xi = 0``, with ``nu = nu0 * median`` held constant (as the loss detaches it)."""
    d_xy, j, d_yx, i, median = cdw(poses, src, tgt, src_index, tgt_index, two_sided)
    nu_sq = np.square(np.maximum(nu0 * median, 1e-12))[:, None, None]
    moved = apply(poses, src)
    force_xy = (moved - tgt[j]) * welsch_weights(d_xy, np.sqrt(nu_sq[:, :, 0]))[..., None] / (nu_sq * len(src))
    matched = np.take_along_axis(moved, i[..., None], axis=1)
    weights_yx = welsch_weights(d_yx, np.sqrt(nu_sq[:, :, 0])) * two_sided[:, None]
    force_yx = (matched - tgt) * weights_yx[..., None] / (nu_sq * len(tgt))
    rotation = np.cross(moved, force_xy).sum(axis=1) + np.cross(matched, force_yx).sum(axis=1)
    return np.concatenate([rotation, force_xy.sum(axis=1) + force_yx.sum(axis=1)], axis=1)


def cdw_adam(
    poses: Poses,
    src: np.ndarray,
    tgt: np.ndarray,
    two_sided: np.ndarray,
    nu0: float,
    steps: int,
    lr: float,
    *,
    merge_distance: float = 0.0,
) -> tuple[Poses, np.ndarray]:
    """Adam on CD-W from every pose at once, in the tangent space of the current pose
    (``T <- exp(-step) T``, moments kept per pose), with a cosine-decaying learning rate.

    Its fixed-length steps slide across shallow barriers that stop IRLS (an MM method descends
    into the nearest basin): the later rounds' coarse stage that finds the basin.
    Arguments and ``merge_distance`` as :func:`cdw_irls`.

    Returns:
        ``(poses, merged (K,))``.
    """
    src_index, tgt_index = NearestNeighbors(src), NearestNeighbors(tgt)
    rotations, translations = (array.copy() for array in poses)
    count = len(rotations)
    first, second = np.zeros((count, 6)), np.zeros((count, 6))
    active = np.ones(count, dtype=bool)
    merged = np.zeros(count, dtype=bool)
    for step in range(steps):
        if not active.any():
            break
        rate = lr * 0.5 * (1.0 + np.cos(np.pi * step / steps))
        current = (rotations[active], translations[active])
        grad = cdw_gradient(current, src, tgt, src_index, tgt_index, two_sided[active], nu0)
        first[active] = 0.9 * first[active] + 0.1 * grad
        second[active] = 0.999 * second[active] + 0.001 * np.square(grad)
        update = (
            -rate
            * (first[active] / (1 - 0.9 ** (step + 1)))
            / (np.sqrt(second[active] / (1 - 0.999 ** (step + 1))) + 1e-8)
        )
        turn = rodrigues(update[:, :3])
        rotations[active] = turn @ current[0]
        translations[active] = (turn @ current[1][:, :, None])[:, :, 0] + update[:, 3:]
        if merge_distance > 0:
            duplicate = merged_into_earlier((rotations, translations), two_sided, merged, merge_distance)
            merged |= duplicate
            active &= ~duplicate
    return (rotations, translations), merged
