"""Benchmark registration methods on labelled pairs: the paper's Table 1 and Dragon alpha-recall.

``linereg-benchmark benchmark=<human|airplane|dragon|3dmatch|folder> methods=[...]
pairs=N out=<dir>`` (Hydra, ``configs/benchmark.yaml``; ``benchmark=<a folder path>`` is
short for ``benchmark=folder benchmark.root=<path>``). Every method runs on every pair;
the errors of the paper's Eq. (``Err_R`` in degrees, ``Err_t`` and ``Err_pw`` in l1 and l2, on
the pair's source points, :func:`linereg.metrics.registration_errors`) and the time are kept
per pair and method, then written as ``results.json``, ``table.md`` and ``alpha_recall.png``.

``table.md`` holds the paper's Table 1 (means, then medians, time and success rates) and:

* registration recall (3DMatch's definition): the share of pairs with RRE (the geodesic angle of
  ``R_est^T R_gt``, degrees) at most 15 deg and RTE (``||t_est - t_gt||``, pair units) at most 0.3,
  and the tighter 5 deg / 0.1, with the mean and median RRE and RTE over all pairs, their means
  over the registered pairs (within 15 deg / 0.3, as DGR reports RE and TE), the mean time and the
  identity baseline (the errors of not moving the source). The thresholds are in the pairs' units: metres
  for the real sources (``3dmatch``, ``fragments``), where this table comes first; for the
  normalised synthetic pairs it follows the paper's tables. The same per overlap bin
  (:data:`OVERLAP_BINS`) when the pairs carry ``meta["overlap"]``;
* the confidence flag: every record carries ``confident`` and ``fitness`` of
  :func:`linereg.registration.api.quality`, scored against *correct* = RRE at most 2 deg and RTE
  at most 2 % of the target's axis-aligned bounding-box diagonal (TP/FP/FN/TN, precision,
  recall) per method, over all records and per pair source (``meta["source"]``, else the
  benchmark's name). :func:`pooled_records` and ``scripts/bench_confidence.py`` pool several
  ``results.json`` into one such table.

The pairs come from :data:`linereg.datasets.benchmark_pairs.PAIR_SOURCES` (``benchmark.name``).

Alpha-recall (paper §4.2, after FGR): the fraction of pairs whose l2 pointwise error is below
``alpha``. By default ``alpha`` is absolute, in the units of the pairs (the synthetic pairs are
scaled into ``[-1, 1]^3`` as in the paper); with ``relative_alpha`` each pair's error is
divided by its object diameter (twice the largest distance of a target point from the target
centroid, a rotation-invariant size recorded as ``diameter``).
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
from linereg.datasets.benchmark_pairs import labelled_pairs, select_pairs
from linereg.datasets.fragments import DEFAULT_BINS, bin_index, bin_label
from linereg.metrics import (
    ERROR_KEYS,
    SUCCESS_THRESHOLDS_DEG,
    aggregate_errors,
    alpha_recall,
    paper_table,
    registration_errors,
    rotation_error_deg,
)
from linereg.registration.api import quality
from linereg.registration.baselines import diameter
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
ABSOLUTE_ALPHA_RANGE = (1e-4, 1.0)
RELATIVE_ALPHA_RANGE = (3e-5, 0.3)
ALPHA_STEPS = 201
RECALL_THRESHOLDS = ((15.0, 0.3), (5.0, 0.1))
"""Registration recall thresholds ``(RRE degrees, RTE pair units)``: 3DMatch's, then a tighter one."""
OVERLAP_BINS = (
    f"< {DEFAULT_BINS[0][0]:g}",
    *(bin_label(low, high, index == len(DEFAULT_BINS) - 1) for index, (low, high) in enumerate(DEFAULT_BINS)),
    f"> {DEFAULT_BINS[-1][1]:g}",
)
"""Labels of the per-bin recall tables: the ``fragments`` source's overlap bins
(:data:`linereg.datasets.fragments.DEFAULT_BINS`) and the overlaps below and above them."""
CORRECT_ROTATION_DEG = 2.0
CORRECT_TRANSLATION_FRACTION = 0.02
"""A registration is *correct* (scoring the confidence flag) with RRE <= 2 deg and RTE <= 2 % of
the target's axis-aligned bounding-box diagonal."""
METRIC_SOURCES = ("3dmatch", "fragments")
IDENTITY = "identity (no motion)"


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
        "meta": _jsonable(pair.meta),
    }


def _jsonable(value: Any) -> Any:
    """``value`` with numpy/torch numbers and arrays turned into Python lists and floats."""
    if isinstance(value, Mapping):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [_jsonable(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    return repr(value)


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
                    "info": _jsonable(result.info),
                }
            )
            if journal is not None:
                with Path(journal).open("a") as handle:
                    handle.write(json.dumps(_jsonable(records[-1])) + "\n")
            bar.update()
    bar.close()
    return records


def _by_method(records: Sequence[Mapping[str, Any]]) -> dict[str, list[Mapping[str, Any]]]:
    """Records grouped by method, in order of first appearance."""
    grouped: dict[str, list[Mapping[str, Any]]] = {}
    for record in records:
        grouped.setdefault(record["method"], []).append(record)
    return grouped


def recall_key(max_rotation_deg: float, max_translation: float) -> str:
    """Summary key of a registration recall, e.g. ``recall_15deg_0.3``."""
    return f"recall_{max_rotation_deg:g}deg_{max_translation:g}"


def summarize_records(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Per method: mean and median of every error and of the time, pair count, success rates, recalls.

    Returns:
        ``{method: {"<key>_mean", "<key>_median" for the ERROR_KEYS and "seconds", "pairs",
        "success_1deg", "success_5deg", recall_key(...) for the RECALL_THRESHOLDS,
        "err_r_deg_registered_mean", "err_t_l2_registered_mean"}}`` (success = fraction of pairs
        with ``Err_R`` below; recall = fraction with ``Err_R`` and ``Err_t`` (l2) at most the
        thresholds; the registered means average over the pairs within the first, 3DMatch's,
        thresholds only, as DGR (Choy et al., CVPR 2020) reports RE and TE; NaN without such a pair).
    """
    summary = {}
    for method, rows in _by_method(records).items():
        columns = {key: np.array([row[key] for row in rows], dtype=np.float64) for key in (*ERROR_KEYS, "seconds")}
        summary[method] = aggregate_errors(columns, success_deg=SUCCESS_THRESHOLDS_DEG)
        hits = {
            thresholds: (columns["err_r_deg"] <= thresholds[0]) & (columns["err_t_l2"] <= thresholds[1])
            for thresholds in RECALL_THRESHOLDS
        }
        summary[method].update({recall_key(*thresholds): float(np.mean(hit)) for thresholds, hit in hits.items()})
        registered = hits[RECALL_THRESHOLDS[0]]
        for key in ("err_r_deg", "err_t_l2"):
            values = columns[key][registered]
            summary[method][f"{key}_registered_mean"] = float(values.mean()) if values.size else float("nan")
    return summary


def identity_records(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Records of not moving the source (identity transform, no time) on the pairs of ``records``.

    Returns:
        One record per distinct ``pair`` with method :data:`IDENTITY`, its errors (``Err_R`` the
        ground-truth rotation angle, ``Err_t`` the ground-truth translation length; NaN
        pointwise errors, which need the points), ``seconds`` 0 and the pair's ``meta``.
    """
    first = {}
    for record in records:
        first.setdefault(record["pair"], record)
    identities = []
    for pair, record in first.items():
        gt = np.asarray(record["gt_transform"], dtype=np.float64)
        translation = gt[:3, 3]
        rotation = float(rotation_error_deg(torch.eye(3, dtype=torch.float64), torch.from_numpy(gt[:3, :3])))
        identities.append(
            {
                "pair": pair,
                "method": IDENTITY,
                "seconds": 0.0,
                "err_r_deg": rotation,
                "err_t_l1": float(np.abs(translation).sum()),
                "err_t_l2": float(np.linalg.norm(translation)),
                "err_pw_l1": float("nan"),
                "err_pw_l2": float("nan"),
                "meta": record.get("meta", {}),
            }
        )
    return identities


def overlap_bin(overlap: float) -> str:
    """The label of :data:`OVERLAP_BINS` holding ``overlap``."""
    if np.isnan(overlap):
        raise ValueError("overlap NaN is in no bin")
    index = bin_index(overlap, DEFAULT_BINS)
    if index is None:
        return OVERLAP_BINS[0] if overlap < DEFAULT_BINS[0][0] else OVERLAP_BINS[-1]
    return OVERLAP_BINS[index + 1]


def recall_table(summary: Mapping[str, Mapping[str, float]], units: str) -> list[str]:
    """Markdown lines: registration recalls, mean and median RRE / RTE over all pairs, their means
    over the registered pairs (within 3DMatch's thresholds) and the mean time per method.

    Args:
        summary: :func:`summarize_records` output.
        units: the pairs' length unit, named in the header (e.g. ``"m"``).
    """
    recalls = " | ".join(f"recall (RRE <= {deg:g} deg, RTE <= {t:g} {units})" for deg, t in RECALL_THRESHOLDS)
    lines = [
        f"| Method | pairs | {recalls} | RRE mean (deg) | RRE median (deg) | RTE mean ({units}) "
        f"| RTE median ({units}) | RRE mean, registered (deg) | RTE mean, registered ({units}) | time mean (s) |",
        "|---|---|" + "---|" * (len(RECALL_THRESHOLDS) + 7),
    ]
    for method, stats in summary.items():
        values = " | ".join(f"{stats[recall_key(*thresholds)]:.3f}" for thresholds in RECALL_THRESHOLDS)
        lines.append(
            f"| {method} | {stats['pairs']} | {values} | {stats['err_r_deg_mean']:.2f} "
            f"| {stats['err_r_deg_median']:.2f} | {stats['err_t_l2_mean']:.3f} | {stats['err_t_l2_median']:.3f} "
            f"| {stats['err_r_deg_registered_mean']:.2f} | {stats['err_t_l2_registered_mean']:.3f} "
            f"| {stats['seconds_mean']:.2f} |"
        )
    return lines


def recall_sections(records: Sequence[Mapping[str, Any]], units: str) -> list[str]:
    """Markdown lines: :func:`recall_table` with the identity baseline, then the same per overlap bin.

    The per-bin tables cover the non-empty :data:`OVERLAP_BINS` and appear only when every
    record's ``meta`` has an ``overlap``.
    """
    deg, translation = RECALL_THRESHOLDS[0]
    baseline = summarize_records(identity_records(records))
    lines = [
        f"## Registration recall (RRE <= {deg:g} deg and RTE <= {translation:g} {units}, 3DMatch's definition)",
        "",
        *recall_table({**summarize_records(records), **baseline}, units),
    ]
    overlaps = [record.get("meta", {}).get("overlap") for record in records]
    if any(overlap is None for overlap in overlaps):
        return lines
    by_bin: dict[str, list[Mapping[str, Any]]] = {label: [] for label in OVERLAP_BINS}
    for record, overlap in zip(records, overlaps, strict=True):
        by_bin[overlap_bin(overlap)].append(record)
    for label, members in by_bin.items():
        if members:
            pairs = len({record["pair"] for record in members})
            lines += ["", f"### Overlap {label} ({pairs} pairs)", ""]
            lines += recall_table({**summarize_records(members), **summarize_records(identity_records(members))}, units)
    return lines


def is_correct(record: Mapping[str, Any]) -> bool:
    """RRE <= 2 deg and RTE <= 2 % of the target's bounding-box diagonal (scores the confidence flag)."""
    return bool(
        record["err_r_deg"] <= CORRECT_ROTATION_DEG
        and record["err_t_l2"] <= CORRECT_TRANSLATION_FRACTION * record["bbox_diagonal"]
    )


def confusion(records: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """The ``confident`` flags of ``records`` scored against :func:`is_correct`.

    Returns:
        ``tp`` (confident and correct), ``fp`` (confident, wrong), ``fn`` (not confident,
        correct), ``tn`` (neither), ``precision`` = tp / (tp + fp) and ``recall`` =
        tp / (tp + fn) (NaN when the denominator is 0).
    """
    counts = {"tp": 0, "fp": 0, "fn": 0, "tn": 0}
    for record in records:
        confident, correct = bool(record["confident"]), is_correct(record)
        counts[("t" if confident == correct else "f") + ("p" if confident else "n")] += 1
    tp, fp, fn = counts["tp"], counts["fp"], counts["fn"]
    return {
        **counts,
        "precision": tp / (tp + fp) if tp + fp else float("nan"),
        "recall": tp / (tp + fn) if tp + fn else float("nan"),
    }


def record_source(record: Mapping[str, Any], default: str) -> str:
    """The pair source of a record: its ``meta["source"]`` when that is a name, else ``default``."""
    source = record.get("meta", {}).get("source")
    return source if isinstance(source, str) else default


def confidence_lines(records: Sequence[Mapping[str, Any]], default_source: str) -> list[str]:
    """Markdown lines: :func:`confusion` per method and over all records, then per source if several.

    Args:
        records: records with ``confident``, ``bbox_diagonal`` and the errors.
        default_source: source of records whose ``meta`` names none (:func:`record_source`).

    Raises:
        ValueError: a record has no ``confident`` flag.
    """
    unflagged = [record["pair"] for record in records if "confident" not in record]
    if unflagged:
        raise ValueError(f"records of pairs {unflagged[:5]} have no 'confident' flag; run the benchmark again")
    header = ["| Rows | records | TP | FP | FN | TN | precision | recall |", "|---|---|---|---|---|---|---|---|"]

    def table(groups: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[str]:
        rows = []
        for name, members in groups.items():
            c = confusion(members)
            rows.append(
                f"| {name} | {len(members)} | {c['tp']} | {c['fp']} | {c['fn']} | {c['tn']} "
                f"| {c['precision']:.3f} | {c['recall']:.3f} |"
            )
        return header + rows

    by_source: dict[str, list[Mapping[str, Any]]] = {}
    for record in records:
        by_source.setdefault(record_source(record, default_source), []).append(record)
    lines = [
        f"## Confidence flag (`quality()['confident']`) against correct = RRE <= {CORRECT_ROTATION_DEG:g} deg "
        f"and RTE <= {100 * CORRECT_TRANSLATION_FRACTION:g} % of the target's bounding-box diagonal",
        "",
        f"Sources: {', '.join(f'{name} ({len(members)} records)' for name, members in by_source.items())}.",
        "",
        *table({**_by_method(records), "all": records}),
    ]
    if len(by_source) > 1:
        for name, members in by_source.items():
            lines += ["", f"### Source `{name}`", "", *table({**_by_method(members), "all": members})]
    return lines


def pooled_records(paths: Sequence[str | Path]) -> list[dict[str, Any]]:
    """The records of several ``results.json``, each ``meta["source"]`` set (:func:`record_source`
    with the file's benchmark name) and ``pair`` made unique across the files."""
    pooled = []
    for path in paths:
        content = json.loads(Path(path).read_text())
        default = str(content.get("settings", {}).get("benchmark", {}).get("name", Path(path).parent.name))
        for record in content["records"]:
            meta = {**record.get("meta", {}), "source": record_source(record, default)}
            pooled.append({**record, "meta": meta, "pair": f"{path}:{record['pair']}"})
    return pooled


def recall_errors(records: Sequence[Mapping[str, Any]], *, relative_alpha: bool = False) -> dict[str, np.ndarray]:
    """Per method, the errors its alpha-recall counts: l2 pointwise, divided by the diameter if ``relative_alpha``."""
    errors = {}
    for method, rows in _by_method(records).items():
        values = np.array([row["err_pw_l2"] for row in rows], dtype=np.float64)
        if relative_alpha:
            values = values / np.array([row["diameter"] for row in rows], dtype=np.float64)
        errors[method] = values
    return errors


def recall_curves(
    records: Sequence[Mapping[str, Any]], alphas: np.ndarray, *, relative_alpha: bool = False
) -> dict[str, list[float]]:
    """Alpha-recall of every method over ``alphas (A,)`` (l2 pointwise error below alpha)."""
    errors = recall_errors(records, relative_alpha=relative_alpha)
    return {method: alpha_recall(values, alphas).tolist() for method, values in errors.items()}


def recall_shortfalls(errors: Mapping[str, Sequence[float]]) -> dict[str, list[tuple[float, float]]]:
    """Where the first method's alpha-recall lies below another's, over every alpha (not a grid).

    Recall is a step function that changes only just above an error value, so comparing the
    methods just above every error value of any method covers every alpha.

    Args:
        errors: method -> its pairs' errors (the first method is the one compared).

    Returns:
        ``{method: [(low, high), ...]}`` for every other method: the alpha intervals
        ``(low, high]`` on which the first method recalls a smaller fraction of its pairs
        (empty: on or above at every alpha).
    """
    names = list(errors)
    sorted_errors = {name: np.sort(np.asarray(errors[name], dtype=np.float64)) for name in names}
    steps = np.unique(np.concatenate(list(sorted_errors.values())))
    probes = np.nextafter(steps, np.inf)
    ends = np.append(steps[1:], np.inf)

    def recall(values: np.ndarray) -> np.ndarray:
        return np.searchsorted(values, probes, side="left") / len(values)

    reference = recall(sorted_errors[names[0]])
    shortfalls = {}
    for name in names[1:]:
        below = reference < recall(sorted_errors[name]) - 1e-12
        intervals: list[tuple[float, float]] = []
        for index in np.flatnonzero(below):
            if intervals and intervals[-1][1] == steps[index]:
                intervals[-1] = (intervals[-1][0], float(ends[index]))
            else:
                intervals.append((float(steps[index]), float(ends[index])))
        shortfalls[name] = intervals
    return shortfalls


def recall_lines(errors: Mapping[str, Sequence[float]]) -> list[str]:
    """Markdown lines saying where the first method's alpha-recall is on or above each other method's."""
    names = list(errors)
    lines = ["## Alpha-recall", ""]
    for name, intervals in recall_shortfalls(errors).items():
        if intervals:
            spans = ", ".join(f"({low:.4g}, {high:.4g}]" for low, high in intervals)
            lines.append(f"- `{names[0]}` is below `{name}` for alpha in {spans}")
        else:
            lines.append(f"- `{names[0]}` is on or above `{name}` at every alpha")
    return lines


def markdown_tables(summary: Mapping[str, Mapping[str, float]]) -> str:
    """Mean table (the paper's Table 1 layout), median table, and time / success table."""
    lines = [
        "## Mean over the pairs (the paper's format)",
        "",
        paper_table(summary),
        "",
        "## Median over the pairs",
        "",
        paper_table(summary, stat="median"),
        "",
        "## Time per pair and success rates",
        "",
        "| Method | pairs | time mean (s) | time median (s) | Err_R < 1 deg | Err_R < 5 deg |",
        "|---|---|---|---|---|---|",
    ]
    for method, stats in summary.items():
        lines.append(
            f"| {method} | {stats['pairs']} | {stats['seconds_mean']:.3f} | {stats['seconds_median']:.3f} "
            f"| {stats['success_1deg']:.2f} | {stats['success_5deg']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def _plot(path: Path, alphas: np.ndarray, curves: Mapping[str, Sequence[float]], summary, relative: bool) -> None:
    """Alpha-recall curves beside the mean l2 pointwise error of every method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [3, 2]})
    for method, recall in curves.items():
        left.plot(alphas, recall, label=method)
    left.set_xlabel("alpha / object diameter" if relative else "alpha (l2 pointwise error, pair units)")
    left.set_ylabel("alpha-recall")
    if np.all(alphas > 0):
        left.set_xscale("log")
    left.set_ylim(0, 1.02)
    left.grid(alpha=0.3)
    left.legend()
    names = list(curves)
    right.bar(names, [summary[name]["err_pw_l2_mean"] for name in names], color="tab:gray")
    right.set_ylabel("mean l2 pointwise error")
    right.tick_params(axis="x", labelrotation=30)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def pair_units(source: Mapping[str, Any] | None) -> str | None:
    """``"m"`` for a real source kept in metres (:data:`METRIC_SOURCES` without ``half_extent``), else ``None``."""
    source = source or {}
    return "m" if source.get("name") in METRIC_SOURCES and source.get("half_extent") is None else None


def header_lines(records: Sequence[Mapping[str, Any]], name: str, units: str | None) -> list[str]:
    """Markdown lines naming the benchmark, its pairs per source, the units and the identity baseline."""
    sources: dict[str, set] = {}
    for record in records:
        sources.setdefault(record_source(record, name), set()).add(record["pair"])
    counted = ", ".join(f"{len(pairs)} from `{source}`" for source, pairs in sources.items())
    unit_text = (
        "errors and thresholds in metres"
        if units == "m"
        else "errors and thresholds in the pairs' own units (normalised; the metric thresholds do not apply)"
    )
    pairs, methods = len({record["pair"] for record in records}), len(_by_method(records))
    return [
        f"# Benchmark `{name}`: {pairs} pairs x {methods} methods",
        "",
        f"Pairs: {counted}; {unit_text}. `{IDENTITY}` is the error of leaving the source where it is.",
        "",
    ]


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
            1e-4 to 1, or from 3e-5 to 0.3 with ``relative_alpha``; plotted on a log axis when
            all are positive).
        relative_alpha: divide each pair's error by its ``diameter`` (module docstring).
        settings: what produced the records (benchmark config), stored in the JSON.

    Returns:
        ``{"json": ..., "table": ..., "plot": ...}`` paths. ``results.json`` holds
        ``settings``, ``summary`` (:func:`summarize_records`), ``alpha_recall`` (``alphas``,
        ``relative``, ``recall`` per method, ``below_first``: :func:`recall_shortfalls`) and
        ``records``. ``table.md``: :func:`header_lines`, then for metric pairs
        (:func:`pair_units` of ``settings["benchmark"]``) :func:`recall_sections` and
        :func:`confidence_lines` before the paper's tables (:func:`markdown_tables`), otherwise
        after them; it ends with :func:`recall_lines` when there are several methods.
    """
    if not records:
        raise ValueError("no records to write")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if alphas is None:
        alphas = np.geomspace(*(RELATIVE_ALPHA_RANGE if relative_alpha else ABSOLUTE_ALPHA_RANGE), ALPHA_STEPS)
    alphas = np.asarray(alphas, dtype=np.float64)
    summary = summarize_records(records)
    curves = recall_curves(records, alphas, relative_alpha=relative_alpha)
    errors = recall_errors(records, relative_alpha=relative_alpha)
    paths = {"json": out / "results.json", "table": out / "table.md", "plot": out / "alpha_recall.png"}
    content = {
        "settings": _jsonable(dict(settings or {})),
        "summary": summary,
        "alpha_recall": {
            "alphas": alphas.tolist(),
            "relative": relative_alpha,
            "recall": curves,
            "below_first": recall_shortfalls(errors),
        },
        "records": [_jsonable(record) for record in records],
    }
    paths["json"].write_text(json.dumps(content, indent=1, allow_nan=True))
    name = str((settings or {}).get("benchmark", {}).get("name", "pairs"))
    units = pair_units((settings or {}).get("benchmark"))
    sections = [
        "\n".join(recall_sections(records, units or "pair units")) + "\n",
        "\n".join(confidence_lines(records, name)) + "\n",
    ]
    paper = markdown_tables(summary)
    parts = [*sections, paper] if units else [paper, *sections]
    table = "\n".join([*header_lines(records, name, units), *parts])
    if len(errors) > 1:
        table += "\n" + "\n".join(recall_lines(errors)) + "\n"
    paths["table"].write_text(table)
    _plot(paths["plot"], alphas, curves, summary, relative_alpha)
    return paths


def build_methods(selected: Sequence[str], presets: Mapping[str, Mapping[str, Any]]) -> dict[str, Method]:
    """Methods to run, by display name: an entry of ``presets`` or a registered method name.

    Args:
        selected: display names.
        presets: display name -> ``{name: <registered method>, **kwargs}``.

    Raises:
        linereg.registry.UnknownNameError: a name neither in ``presets`` nor registered (both
            lists in the message).
    """
    methods = {}
    for display in selected:
        if display in presets:
            config = dict(presets[display])
        elif display in METHODS:
            config = {"name": display}
        else:
            raise UnknownNameError(
                f"unknown method {display!r}: not in method_presets ({', '.join(presets) or 'empty'}) "
                f"nor registered ({', '.join(METHODS.names())})"
            )
        methods[display] = METHODS.build(config)
    return methods


def benchmark(config: Mapping[str, Any]) -> dict[str, Path]:
    """Run a benchmark config (``configs/benchmark.yaml``) and write its results.

    Keys: ``benchmark`` (pair source config), ``methods`` (display names), ``method_presets``,
    ``pairs``, ``seed``, ``out``, ``relative_alpha``, ``alphas``, ``progress``. Records are
    journaled to ``<out>/records.jsonl``: rerunning with the same ``out`` resumes.
    """
    pairs = select_pairs(config["benchmark"], pairs=config.get("pairs"), seed=int(config.get("seed", 0)))
    methods = build_methods(list(config["methods"]), config.get("method_presets") or {})
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
