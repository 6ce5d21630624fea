"""One table across the jobs of a sweep: ``summary.csv`` and ``summary.md`` in the sweep folder.

Written automatically when a Hydra multirun ends (``SweepSummary``, registered in
``configs/hydra/default.yaml``), or by hand::

    python -m train.summary outputs/<task_name>/multiruns/<time>

Each row is one job folder (``<n>_<overrides>``): its command-line overrides (one column per
overridden key) and the metrics of its ``metrics.json`` (written by ``train``). The CSV holds
every override and metric; the markdown table the overrides that vary between jobs and the
main metrics (:data:`MAIN_METRICS`). Jobs that failed or are
still running appear with an empty metrics part and their status.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

MAIN_METRICS = (
    "val/err_r_deg_mean",
    "test/err_r_deg_mean",
    "test/err_t_l2_mean",
    "test/err_pw_l2_mean",
    "test/recall@0.05",
    "test/identity/err_r_deg_mean",
    "best_epoch",
)
CSV_FILE = "summary.csv"
MARKDOWN_FILE = "summary.md"


def _job_order(path: Path) -> tuple[int, str]:
    """Sort key: the job number prefix of Hydra's sweep subfolders, then the name."""
    head = path.name.split("_", 1)[0]
    return (int(head) if head.isdigit() else sys.maxsize, path.name)


def collect_runs(sweep_dir: str | Path) -> list[dict[str, Any]]:
    """The jobs of a sweep folder, in job order.

    Returns:
        One dict per job: ``job`` (folder name), ``status`` (``done`` or ``no metrics.json``),
        ``overrides`` (``{key: value}`` as typed on the command line) and ``metrics``.
    """
    sweep_dir = Path(sweep_dir)
    runs = []
    for job in sorted((p.parent.parent for p in sweep_dir.glob("*/.hydra/overrides.yaml")), key=_job_order):
        overrides = {}
        for item in OmegaConf.load(job / ".hydra" / "overrides.yaml"):
            key, _, value = str(item).partition("=")
            overrides[key.lstrip("+~")] = value
        metrics_file = job / "metrics.json"
        metrics = json.loads(metrics_file.read_text())["metrics"] if metrics_file.is_file() else {}
        runs.append(
            {
                "job": job.name,
                "status": "done" if metrics_file.is_file() else "no metrics.json",
                "overrides": overrides,
                "metrics": metrics,
            }
        )
    return runs


def _format(value: Any) -> str:
    """A table cell: 4 significant digits for floats, empty for missing values."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    return str(value)


def _override_cell(value: str) -> str:
    """An override value for the markdown table: numbers shortened to 4 significant digits."""
    try:
        number = float(value)
    except ValueError:
        return value
    return value if number.is_integer() and "." not in value else f"{number:.4g}"


def _ordered_union(mappings: Sequence[dict[str, Any]]) -> list[str]:
    """Keys of all mappings, in order of first appearance."""
    keys: dict[str, None] = {}
    for mapping in mappings:
        keys.update(dict.fromkeys(mapping))
    return list(keys)


def write_summary(sweep_dir: str | Path) -> tuple[Path, Path] | None:
    """Write ``summary.csv`` (every metric) and ``summary.md`` (main metrics) into ``sweep_dir``.

    Returns:
        The two paths, or ``None`` when the folder holds no Hydra job.
    """
    sweep_dir = Path(sweep_dir)
    runs = collect_runs(sweep_dir)
    if not runs:
        return None
    override_keys = _ordered_union([run["overrides"] for run in runs])
    metric_keys = sorted(set(_ordered_union([run["metrics"] for run in runs])))
    main_keys = [key for key in MAIN_METRICS if key in metric_keys]
    csv_path, markdown_path = sweep_dir / CSV_FILE, sweep_dir / MARKDOWN_FILE
    with open(csv_path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["job", "status", *override_keys, *metric_keys])
        for run in runs:
            writer.writerow(
                [run["job"], run["status"]]
                + [run["overrides"].get(key, "") for key in override_keys]
                + [_format(run["metrics"].get(key)) for key in metric_keys]
            )
    # The markdown table shows only the overrides that vary between jobs (the CSV has them all).
    varying = [key for key in override_keys if len({run["overrides"].get(key) for run in runs}) > 1] or override_keys
    header = ["job", *varying, *main_keys]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for run in runs:
        cells = [run["job"].split("_", 1)[0]] + [_override_cell(run["overrides"].get(key, "")) for key in varying]
        cells += [_format(run["metrics"].get(key)) for key in main_keys] if run["metrics"] else [run["status"]]
        lines.append("| " + " | ".join(cells) + " |")
    markdown_path.write_text("\n".join(lines) + "\n")
    return csv_path, markdown_path


class SweepSummary(Callback):
    """Hydra callback: write the sweep summary when a multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        paths = write_summary(config.hydra.sweep.dir)
        if paths is not None:
            log.info("sweep summary: %s, %s", *paths)
            print(paths[1].read_text())


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m train.summary <sweep folder>``: write and print the summary."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        raise SystemExit("usage: python -m train.summary <sweep folder>")
    paths = write_summary(args[0])
    if paths is None:
        raise SystemExit(f"no Hydra job folders (*/.hydra/overrides.yaml) in {args[0]}")
    print(paths[1].read_text(), end="")


if __name__ == "__main__":
    main()
