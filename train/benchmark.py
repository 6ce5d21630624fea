"""Benchmark registration methods on labelled pairs: the paper's Table 1 and Dragon alpha-recall.

``linereg-benchmark benchmark=<human|airplane|dragon|3dmatch|folder> methods=[...]
pairs=N out=<dir>`` (Hydra, ``configs/benchmark.yaml``; ``benchmark=<a folder path>`` is
short for ``benchmark=folder benchmark.root=<path>``). Every method runs on every pair;
the errors of the paper's Eq. (``Err_R`` in degrees, ``Err_t`` and ``Err_pw`` in l1 and l2, on
the pair's source points, :func:`linereg.metrics.registration_errors`) and the time are kept
per pair and method, then written as ``results.json``, ``table.md`` and ``alpha_recall.png``.
:mod:`linereg.registration.benchmark_results` computes their statistics and tables (registration
recall per overlap bin, the confidence flag, alpha-recall).

The pairs come from :data:`linereg.datasets.benchmark_pairs.PAIR_SOURCES` (``benchmark.name``).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

import linereg.registration  # noqa: F401  (importing registers the baselines and solvers)
from linereg import pretrained
from linereg.datasets.benchmark_pairs import labelled_pairs, select_pairs
from linereg.metrics import ERROR_KEYS, registration_errors
from linereg.registration.api import quality
from linereg.registration.baselines import diameter
from linereg.registration.benchmark_results import (
    alpha_grid,
    jsonable,
    plot_alpha_recall,
    results_content,
    results_table,
)
from linereg.registration.learned import LearnedRegistration
from linereg.registration.methods import METHODS, Method
from linereg.registry import UnknownNameError
from linereg.structures import PairSample
from linereg.train import CONFIG_DIR
from linereg.train.cli import reported, require, run_app

COMMAND = "linereg-benchmark"
MANDATORY_HINTS = {
    "benchmark.run": "a run folder of linereg-train",
    "benchmark.root": "a folder of labelled pairs or meshes",
}


def object_diameter(points: np.ndarray) -> float:
    """Twice the largest distance of a point of ``points (N, 3)`` from their centroid."""
    points = np.asarray(points, dtype=np.float64)
    return 2.0 * float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())


def _measure(pair: PairSample, transform: Any) -> dict[str, Any]:
    """What a record measures from its pair and transform alone.

    The paper's errors (:data:`linereg.metrics.ERROR_KEYS`), ``diameter``, ``confident`` and
    ``fitness`` (:func:`linereg.registration.api.quality`), ``bbox_diagonal``, ``gt_transform`` and
    the pair's ``meta``.
    """
    transform = np.asarray(transform, dtype=np.float64)
    errors = registration_errors(
        torch.as_tensor(transform)[None],
        torch.as_tensor(pair.gt_transform, dtype=torch.float64)[None],
        torch.as_tensor(pair.src_xyz, dtype=torch.float64)[None],
    )
    found = quality(pair.src_xyz, pair.tgt_xyz, transform)
    return {
        **{key: float(errors[key][0]) for key in ERROR_KEYS},
        "diameter": object_diameter(pair.tgt_xyz),
        "confident": bool(found["confident"]),
        "fitness": float(found["fitness"]),
        "bbox_diagonal": diameter(np.asarray(pair.tgt_xyz, dtype=np.float64)),
        "gt_transform": np.asarray(pair.gt_transform, dtype=np.float64).tolist(),
        "meta": jsonable(pair.meta),
    }


def run_benchmark(
    pairs: Sequence[PairSample],
    methods: Mapping[str, Method],
    *,
    progress: bool = True,
    journal: str | Path | None = None,
) -> list[dict[str, Any]]:
    """Run every method on every pair and measure the paper's errors.

    Args:
        pairs: labelled pairs (``gt_transform`` maps source to target).
        methods: display name -> method (see :mod:`linereg.registration.methods`).
        progress: show a tqdm bar.
        journal: a JSON-lines file that receives every record as soon as it is measured;
            records already in it (same pair and method) keep their transform, time and
            ``info``, so an interrupted run resumes where it stopped; everything else is
            measured again (:func:`_measure`: it depends on the pair and the transform only, so
            a changed ground truth or flag is scored without running the methods again).

    Returns:
        One record per (pair, method), pairs outer: ``pair`` (position in ``pairs``),
        ``method``, ``seconds``, every key of :data:`linereg.metrics.ERROR_KEYS` (float),
        ``diameter`` (:func:`object_diameter` of the target), ``bbox_diagonal`` (the target's
        bounding-box diagonal, :func:`linereg.registration.baselines.diameter`), ``confident`` and
        ``fitness`` (:func:`linereg.registration.api.quality` of the result), ``transform`` and
        ``gt_transform`` (4x4 lists), ``meta`` (the pair's) and ``info`` (the method's).

    Raises:
        ValueError: no pairs, no methods, or a pair without ground truth.
        RuntimeError: a method failed; the message names the method and the pair.
    """
    if not pairs or not methods:
        raise ValueError(f"need at least one pair and one method, got {len(pairs)} and {len(methods)}")
    labelled_pairs(pairs, "run_benchmark")
    done: dict[tuple[int, str], dict[str, Any]] = {}
    if journal is not None and Path(journal).is_file():
        for line in Path(journal).read_text().splitlines():
            if line.strip():
                record = json.loads(line)
                done[(record["pair"], record["method"])] = record
    records = []
    bar = tqdm(total=len(pairs) * len(methods), disable=not progress, desc="benchmark")
    for index, pair in enumerate(pairs):
        for name, method in methods.items():
            if (index, name) in done:
                record = done[(index, name)]
                record.update(_measure(pair, record["transform"]))
                records.append(record)
                bar.update()
                continue
            bar.set_postfix(method=name, pair=index)
            try:
                result = method(pair.src_xyz, pair.tgt_xyz, pair.src_normals, pair.tgt_normals)
            except Exception as error:
                raise RuntimeError(f"method {name!r} failed on pair {index} ({pair.meta}): {error}") from error
            records.append(
                {
                    "pair": index,
                    "method": name,
                    "seconds": float(result.seconds),
                    **_measure(pair, result.transform),
                    "transform": np.asarray(result.transform, dtype=np.float64).tolist(),
                    "info": jsonable(result.info),
                    **({} if result.solution is None else {"solver": jsonable(result.solution.summary)}),
                }
            )
            if journal is not None:
                with Path(journal).open("a") as handle:
                    handle.write(json.dumps(jsonable(records[-1])) + "\n")
            bar.update()
    bar.close()
    return records


def write_results(
    records: Sequence[Mapping[str, Any]],
    out_dir: str | Path,
    *,
    alphas: Sequence[float] | None = None,
    relative_alpha: bool = False,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Path]:
    """Write ``results.json``, ``table.md`` and ``alpha_recall.png`` into ``out_dir``.

    Args:
        records: output of :func:`run_benchmark`.
        out_dir: folder (created).
        alphas: thresholds of the recall curve (default 201 values spaced geometrically from
            1e-4 to 1, or from 3e-5 to 0.3 with ``relative_alpha``:
            :func:`~linereg.registration.benchmark_results.alpha_grid`; plotted on a log axis
            when all are positive).
        relative_alpha: divide each pair's error by its ``diameter`` (the alpha-recall of
            :mod:`linereg.registration.benchmark_results`).
        settings: what produced the records (benchmark config), stored in the JSON.

    Returns:
        ``{"json": ..., "table": ..., "plot": ...}`` paths; ``results.json`` holds
        :func:`~linereg.registration.benchmark_results.results_content`, ``table.md``
        :func:`~linereg.registration.benchmark_results.results_table`, ``alpha_recall.png``
        :func:`~linereg.registration.benchmark_results.plot_alpha_recall`.
    """
    if not records:
        raise ValueError("no records to write")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    alphas = alpha_grid(alphas, relative_alpha)
    content = results_content(records, alphas, relative_alpha=relative_alpha, settings=settings)
    paths = {"json": out / "results.json", "table": out / "table.md", "plot": out / "alpha_recall.png"}
    paths["json"].write_text(json.dumps(content, indent=1, allow_nan=True))
    paths["table"].write_text(results_table(records, settings, relative_alpha=relative_alpha))
    plot_alpha_recall(paths["plot"], content)
    return paths


def build_methods(
    selected: Sequence[str], presets: Mapping[str, Mapping[str, Any]], refine: bool = False
) -> dict[str, Method]:
    """Methods to run, by display name: an entry of ``presets``, a registered method name, or a
    network (a pretrained name of :mod:`linereg.pretrained` or a checkpoint / run folder).

    Args:
        selected: display names.
        presets: display name -> ``{name: <registered method>, **kwargs}``, or ``{network: <a
            network>, refine: ..., **kwargs}`` (:class:`~linereg.registration.learned.LearnedRegistration`).
        refine: finish every network's pose with the solver, unless its preset says otherwise.

    Raises:
        linereg.registry.UnknownNameError: a name neither in ``presets``, registered nor a network
            (the lists in the message).
    """
    methods = {}
    for display in selected:
        if display in presets:
            config = dict(presets[display])
        elif display in METHODS:
            config = {"name": display}
        elif pretrained.is_name(display) or Path(display).expanduser().exists():
            config = {"network": display}
        else:
            raise UnknownNameError(
                f"unknown method {display!r}: not in method_presets ({', '.join(presets) or 'empty'}), "
                f"registered ({', '.join(METHODS.names())}), a pretrained network ({', '.join(pretrained.names())}) "
                "nor an existing checkpoint or run folder"
            )
        if "network" in config:
            network = config.pop("network")
            methods[display] = LearnedRegistration(network, **{"refine": refine, **config})
        else:
            methods[display] = METHODS.build(config)
    return methods


def benchmark(config: Mapping[str, Any]) -> dict[str, Path]:
    """Run a benchmark config (``configs/benchmark.yaml``) and write its results.

    Keys: ``benchmark`` (pair source config), ``methods`` (display names), ``method_presets``,
    ``refine`` (finish the networks' poses with the solver), ``pairs``, ``seed``, ``out``,
    ``relative_alpha``, ``alphas``, ``progress``. Records are journaled to ``<out>/records.jsonl``:
    rerunning with the same ``out`` resumes.
    """
    pairs = select_pairs(config["benchmark"], pairs=config.get("pairs"), seed=int(config.get("seed", 0)))
    methods = build_methods(
        list(config["methods"]), config.get("method_presets") or {}, refine=bool(config.get("refine", False))
    )
    Path(config["out"]).mkdir(parents=True, exist_ok=True)
    journal = Path(config["out"]) / "records.jsonl"
    records = run_benchmark(pairs, methods, progress=bool(config.get("progress", True)), journal=journal)
    return write_results(
        records,
        config["out"],
        alphas=config.get("alphas"),
        relative_alpha=bool(config.get("relative_alpha", False)),
        settings=config,
    )


def expand_folder_argument(argv: Sequence[str]) -> list[str]:
    """Command-line overrides with ``benchmark=<existing folder>`` spelled as Hydra wants it."""
    expanded = []
    for argument in argv:
        key, _, value = argument.partition("=")
        if key == "benchmark" and value and Path(value).expanduser().is_dir():
            expanded += ["benchmark=folder", f"benchmark.root={Path(value).expanduser().resolve()}"]
        else:
            expanded.append(argument)
    return expanded


def main() -> None:
    """``linereg-benchmark`` (Hydra app on ``configs/benchmark.yaml``; ``linereg-benchmark --help``)."""
    import hydra
    from omegaconf import DictConfig, OmegaConf

    @hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="benchmark")
    def app(config: DictConfig) -> None:
        with reported(COMMAND):
            require(config, COMMAND, MANDATORY_HINTS)
            paths = benchmark(OmegaConf.to_container(config, resolve=True))
        print(paths["table"].read_text())
        print("\n".join(f"{kind}: {path}" for kind, path in paths.items()))

    sys.argv = [sys.argv[0], *expand_folder_argument(sys.argv[1:])]
    run_app(COMMAND, app)


if __name__ == "__main__":
    main()
