"""``linereg.register_many``: many pairs at once, in order, a network's forward in batches.

::

    import linereg

    pairs = [("a_src.ply", "a_tgt.ply"), ("b_src.ply", "b_tgt.ply")]
    for result in linereg.register_many(pairs, method="rpm_ours_objects", refine=True):
        print(result.transformation, result.confident, result.info["path"])

Each pair gets what :func:`linereg.register` gives it (the same check, warnings and clutter
handling). With a network the model is loaded once and the pairs of a chunk go through it together
(:meth:`~linereg.registration.learned.LearnedRegistration.predict_many`); each result's ``seconds``
holds its share of the chunk's forward.
"""

from __future__ import annotations

import functools
import itertools
import os
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from linereg.registration.api import DEFAULT_METHOD, RegistrationResult, _build, as_cloud, register_clouds
from linereg.registration.learned import LearnedRegistration
from linereg.registration.trust import surface_points


def register_many(
    pairs: Iterable[tuple[Any, Any]],
    method: str | os.PathLike | Mapping[str, Any] = DEFAULT_METHOD,
    device: str | None = None,
    *,
    batch_size: int = 32,
    progress: bool = True,
    fitness_threshold: float | None = None,
    **options: Any,
) -> Iterator[RegistrationResult]:
    """Register every ``(source, target)`` of ``pairs`` (what :func:`linereg.register` takes), in order.

    Args:
        pairs: an iterable of ``(source, target)``: arrays, tensors, Open3D clouds or files.
        method, device, fitness_threshold, **options: as :func:`linereg.register` (``refine=True``
            finishes a network's poses with the solver).
        batch_size: pairs read, and forwarded through a network, at a time.
        progress: a progress bar on stderr.

    Yields:
        One :class:`~linereg.registration.api.RegistrationResult` per pair, in the order given.

    Raises:
        What :func:`linereg.register` raises, for the first pair that has the problem (the message
        names the argument as ``pairs[i]``).
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    solver, description = _build(method, device, options)
    total = len(pairs) if hasattr(pairs, "__len__") else None
    from tqdm.auto import tqdm  # here: the single-pair command does not pay for it

    bar = tqdm(total=total, desc="register", unit="pair", disable=not progress)
    iterator, done = iter(pairs), 0
    try:
        while chunk := list(itertools.islice(iterator, batch_size)):
            clouds = [_checked_pair(pair, done + offset) for offset, pair in enumerate(chunk)]
            surfaces = [surface_points(tgt[0], src[0]) for src, tgt in clouds]
            solvers, shared = [solver] * len(clouds), 0.0
            if isinstance(solver, LearnedRegistration):
                began = time.perf_counter()
                seen = [
                    (src[0], tgt[0] if mask is None else tgt[0][mask])
                    for (src, tgt), mask in zip(clouds, surfaces, strict=True)
                ]
                starts = solver.predict_many(seen, batch_size)
                shared = (time.perf_counter() - began) / len(clouds)
                solvers = [functools.partial(solver, start=start) for start in starts]
            for (src, tgt), mask, method_of_pair in zip(clouds, surfaces, solvers, strict=True):
                result = register_clouds(
                    method_of_pair, description, src, tgt, fitness_threshold=fitness_threshold, on_surface=mask
                )
                result.seconds += shared
                done += 1
                bar.update()
                yield result
    finally:
        bar.close()


def _checked_pair(pair: Any, index: int):
    """``pairs[index]`` as two checked clouds (:func:`~linereg.registration.api.as_cloud`)."""
    try:
        source, target = pair
    except (TypeError, ValueError) as error:
        raise TypeError(f"pairs[{index}]: expected a (source, target) pair, got {type(pair).__name__}") from error
    return as_cloud(source, f"pairs[{index}] source"), as_cloud(target, f"pairs[{index}] target")
