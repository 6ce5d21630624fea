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
import statistics
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from linereg.registration.api import DEFAULT_METHOD, RegistrationResult, _build, as_cloud, register_clouds
from linereg.registration.learned import LearnedRegistration
from linereg.registration.trust import surface_points

PROBE_PAIRS = 8
"""Pairs a finished network answers before ``register_many`` first asks whether it pays (its first
chunk holds no more)."""


def register_many(
    pairs: Iterable[tuple[Any, Any]],
    method: str | os.PathLike | Mapping[str, Any] = DEFAULT_METHOD,
    device: str | None = None,
    *,
    batch_size: int = 32,
    progress: bool = True,
    fitness_threshold: float | None = None,
    keep_network: bool = False,
    **options: Any,
) -> Iterator[RegistrationResult]:
    """Register every ``(source, target)`` of ``pairs`` (what :func:`linereg.register` takes), in order.

    A network finished by the solver (``refine=True``) pays for itself only where its path (the
    forward, the polish and the solver where the check does not trust the polish) is faster than the
    solver alone. From :data:`PROBE_PAIRS` pairs on, before each chunk, when the network's path has
    taken longer per pair than the solver on the pairs that fell back to it, the remaining pairs go
    straight to the solver (``info["path"] == "solver"``, ``info["network_skipped"]``): out of a
    network's domain the pairs then cost about the solver's time, with its answers.

    Args:
        pairs: an iterable of ``(source, target)``: arrays, tensors, Open3D clouds or files.
        method, device, fitness_threshold, **options: as :func:`linereg.register` (``refine=True``
            finishes a network's poses with the solver).
        batch_size: pairs read, and forwarded through a network, at a time.
        progress: a progress bar on stderr.
        keep_network: run a finished network on every pair, even where it costs more than it saves.

    Yields:
        One :class:`~linereg.registration.api.RegistrationResult` per pair, in the order given.

    Raises:
        What :func:`linereg.register` raises, for the first pair that has the problem (the message
        names the argument as ``pairs[i]``).
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    solver, description = _build(method, device, options)
    ledger = None
    if isinstance(solver, LearnedRegistration) and solver.finish is not None and not keep_network:
        ledger = NetworkLedger()
    total = len(pairs) if hasattr(pairs, "__len__") else None
    from tqdm.auto import tqdm  # here: the single-pair command does not pay for it

    bar = tqdm(total=total, desc="register", unit="pair", disable=not progress)
    iterator, done = iter(pairs), 0
    size = min(batch_size, PROBE_PAIRS) if ledger is not None else batch_size
    try:
        while chunk := list(itertools.islice(iterator, size)):
            size = batch_size
            clouds = [_checked_pair(pair, done + offset) for offset, pair in enumerate(chunk)]
            surfaces = [surface_points(tgt[0], src[0]) for src, tgt in clouds]
            skip = ledger is not None and ledger.slower()
            methods, shared = _chunk_methods(solver, clouds, surfaces, batch_size, skip)
            for (src, tgt), mask, method_of_pair in zip(clouds, surfaces, methods, strict=True):
                result = register_clouds(
                    method_of_pair, description, src, tgt, fitness_threshold=fitness_threshold, on_surface=mask
                )
                result.seconds += shared
                if skip:
                    result.info |= {"path": "solver", "solver_ran": True, "network_skipped": True}
                elif ledger is not None:
                    ledger.record(shared, result.info)
                done += 1
                bar.update()
                yield result
    finally:
        bar.close()


def _chunk_methods(solver, clouds, surfaces, batch_size: int, skip: bool) -> tuple[list, float]:
    """The method of each pair of a chunk and each pair's share of the network's forward: a
    network's batched poses as each pair's start, or its finish's solver alone (``skip``)."""
    if not isinstance(solver, LearnedRegistration):
        return [solver] * len(clouds), 0.0
    if skip:
        return [solver.finish.solver] * len(clouds), 0.0
    began = time.perf_counter()
    seen = [
        (src[0], tgt[0] if mask is None else tgt[0][mask]) for (src, tgt), mask in zip(clouds, surfaces, strict=True)
    ]
    starts = solver.predict_many(seen, batch_size)
    shared = (time.perf_counter() - began) / len(clouds)
    return [functools.partial(solver, start=start) for start in starts], shared


class NetworkLedger:
    """What a finished network has cost per pair (its forward share, the polish and check, the
    fallback solver) against what the solver alone cost on the pairs that fell back to it."""

    def __init__(self) -> None:
        self.network: list[float] = []
        self.solver: list[float] = []

    def record(self, forward_seconds: float, info: Mapping[str, Any]) -> None:
        """One pair's costs from its forward share and its finish's ``info``."""
        self.network.append(forward_seconds + info["polish_seconds"] + info["solver_seconds"])
        if info["solver_ran"]:
            self.solver.append(info["solver_seconds"])

    def slower(self) -> bool:
        """Whether, over at least :data:`PROBE_PAIRS` pairs, the network's path took longer per pair
        than the solver (known once a pair fell back)."""
        if len(self.network) < PROBE_PAIRS or not self.solver:
            return False
        return statistics.fmean(self.network) > statistics.fmean(self.solver)


def _checked_pair(pair: Any, index: int):
    """``pairs[index]`` as two checked clouds (:func:`~linereg.registration.api.as_cloud`)."""
    try:
        source, target = pair
    except (TypeError, ValueError) as error:
        raise TypeError(f"pairs[{index}]: expected a (source, target) pair, got {type(pair).__name__}") from error
    return as_cloud(source, f"pairs[{index}] source"), as_cloud(target, f"pairs[{index}] target")
