"""Statistics and reports of benchmark records: recall, overlap bins, the confidence flag, tables.

A *record* is one method's result on one labelled pair, as ``linereg-benchmark`` measures it:
``pair``, ``method``, ``seconds``, the paper's errors (:data:`linereg.metrics.ERROR_KEYS`: ``Err_R``
in degrees, ``Err_t`` and ``Err_pw`` in l1 and l2), ``diameter``, ``bbox_diagonal``,
``confident``, ``fitness``, ``gt_transform`` and the pair's ``meta``. From records this module
builds ``results.json`` (:func:`results_content`), ``table.md`` (:func:`results_table`) and
``alpha_recall.png`` (:func:`plot_alpha_recall`, with matplotlib: ``pip install linereg[plot]``): the
paper's Table 1 (means, then medians, time and success rates) and

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

Alpha-recall (paper §4.2, after FGR): the fraction of pairs whose l2 pointwise error is below
``alpha``. By default ``alpha`` is absolute, in the units of the pairs (the synthetic pairs are
scaled into ``[-1, 1]^3`` as in the paper); with ``relative_alpha`` each pair's error is
divided by its object diameter (twice the largest distance of a target point from the target
centroid, a rotation-invariant size recorded as ``diameter``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from linereg.datasets.fragments import DEFAULT_BINS, bin_index, bin_label
from linereg.metrics import (
    ERROR_KEYS,
    SUCCESS_THRESHOLDS_DEG,
    aggregate_errors,
    alpha_recall,
    markdown_table,
    paper_table,
    rotation_error_deg,
)

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


def jsonable(value: Any) -> Any:
    """``value`` with numpy/torch numbers and arrays turned into Python lists and floats."""
    if isinstance(value, Mapping):
        return {str(key): jsonable(item) for key, item in value.items()}
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [jsonable(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    return repr(value)


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
    header = [
        "Method",
        "pairs",
        *(f"recall (RRE <= {deg:g} deg, RTE <= {t:g} {units})" for deg, t in RECALL_THRESHOLDS),
        "RRE mean (deg)",
        "RRE median (deg)",
        f"RTE mean ({units})",
        f"RTE median ({units})",
        "RRE mean, registered (deg)",
        f"RTE mean, registered ({units})",
        "time mean (s)",
    ]
    rows = [
        [
            method,
            f"{stats['pairs']}",
            *(f"{stats[recall_key(*thresholds)]:.3f}" for thresholds in RECALL_THRESHOLDS),
            f"{stats['err_r_deg_mean']:.2f}",
            f"{stats['err_r_deg_median']:.2f}",
            f"{stats['err_t_l2_mean']:.3f}",
            f"{stats['err_t_l2_median']:.3f}",
            f"{stats['err_r_deg_registered_mean']:.2f}",
            f"{stats['err_t_l2_registered_mean']:.3f}",
            f"{stats['seconds_mean']:.2f}",
        ]
        for method, stats in summary.items()
    ]
    return markdown_table(header, rows)


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
    header = ["Rows", "records", "TP", "FP", "FN", "TN", "precision", "recall"]

    def table(groups: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[str]:
        rows = []
        for name, members in groups.items():
            c = confusion(members)
            counts = [f"{c[key]}" for key in ("tp", "fp", "fn", "tn")]
            rows.append([name, f"{len(members)}", *counts, f"{c['precision']:.3f}", f"{c['recall']:.3f}"])
        return markdown_table(header, rows)

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
        *markdown_table(
            ["Method", "pairs", "time mean (s)", "time median (s)", "Err_R < 1 deg", "Err_R < 5 deg"],
            (
                [
                    method,
                    f"{stats['pairs']}",
                    f"{stats['seconds_mean']:.3f}",
                    f"{stats['seconds_median']:.3f}",
                    f"{stats['success_1deg']:.2f}",
                    f"{stats['success_5deg']:.2f}",
                ]
                for method, stats in summary.items()
            ),
        ),
    ]
    return "\n".join(lines) + "\n"


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


def alpha_grid(alphas: Sequence[float] | None, relative_alpha: bool = False) -> np.ndarray:
    """``alphas`` as float64, or by default :data:`ALPHA_STEPS` values spaced geometrically over
    :data:`ABSOLUTE_ALPHA_RANGE` (:data:`RELATIVE_ALPHA_RANGE` with ``relative_alpha``)."""
    if alphas is None:
        return np.geomspace(*(RELATIVE_ALPHA_RANGE if relative_alpha else ABSOLUTE_ALPHA_RANGE), ALPHA_STEPS)
    return np.asarray(alphas, dtype=np.float64)


def results_content(
    records: Sequence[Mapping[str, Any]],
    alphas: np.ndarray,
    *,
    relative_alpha: bool = False,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The contents of ``results.json``: ``settings``, ``summary`` (:func:`summarize_records`),
    ``alpha_recall`` (``alphas``, ``relative``, ``recall`` per method, ``below_first``:
    :func:`recall_shortfalls`) and ``records``."""
    errors = recall_errors(records, relative_alpha=relative_alpha)
    return {
        "settings": jsonable(dict(settings or {})),
        "summary": summarize_records(records),
        "alpha_recall": {
            "alphas": alphas.tolist(),
            "relative": relative_alpha,
            "recall": recall_curves(records, alphas, relative_alpha=relative_alpha),
            "below_first": recall_shortfalls(errors),
        },
        "records": [jsonable(record) for record in records],
    }


def results_table(
    records: Sequence[Mapping[str, Any]], settings: Mapping[str, Any] | None = None, *, relative_alpha: bool = False
) -> str:
    """The text of ``table.md``.

    :func:`header_lines`, then for metric pairs (:func:`pair_units` of ``settings["benchmark"]``)
    :func:`recall_sections` and :func:`confidence_lines` before the paper's tables
    (:func:`markdown_tables`), otherwise after them; it ends with :func:`recall_lines` when
    there are several methods.
    """
    name = str((settings or {}).get("benchmark", {}).get("name", "pairs"))
    units = pair_units((settings or {}).get("benchmark"))
    sections = [
        "\n".join(recall_sections(records, units or "pair units")) + "\n",
        "\n".join(confidence_lines(records, name)) + "\n",
    ]
    paper = markdown_tables(summarize_records(records))
    parts = [*sections, paper] if units else [paper, *sections]
    table = "\n".join([*header_lines(records, name, units), *parts])
    errors = recall_errors(records, relative_alpha=relative_alpha)
    if len(errors) > 1:
        table += "\n" + "\n".join(recall_lines(errors)) + "\n"
    return table


def plot_alpha_recall(path: str | Path, content: Mapping[str, Any]) -> Path:
    """Draw ``alpha_recall.png``: the alpha-recall curves of :func:`results_content` beside each
    method's mean l2 pointwise error.

    Raises:
        ModuleNotFoundError: matplotlib is not installed (the ``plot`` extra).
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError("the alpha-recall plot needs matplotlib: pip install 'linereg[plot]'") from error

    curves = content["alpha_recall"]
    alphas = np.asarray(curves["alphas"], dtype=np.float64)
    figure = Figure(figsize=(11, 4))
    FigureCanvasAgg(figure)
    left, right = figure.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    for method, recall in curves["recall"].items():
        left.plot(alphas, recall, label=method)
    relative = curves["relative"]
    left.set_xlabel("alpha / object diameter" if relative else "alpha (l2 pointwise error, pair units)")
    left.set_ylabel("alpha-recall")
    if np.all(alphas > 0):
        left.set_xscale("log")
    left.set_ylim(0, 1.02)
    left.grid(alpha=0.3)
    left.legend()
    names = list(curves["recall"])
    right.bar(names, [content["summary"][name]["err_pw_l2_mean"] for name in names], color="tab:gray")
    right.set_ylabel("mean l2 pointwise error")
    right.tick_params(axis="x", labelrotation=30)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    return Path(path)
