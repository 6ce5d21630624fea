"""Tables and figures of docs/results.md: per-seed cells, run folders, the schedule's table.

    python scripts/reproduce_report.py --cells docs/results/cells.csv --figures docs/results
    python scripts/reproduce_report.py outputs/schedule --figures docs/results --write-cells docs/results/cells.csv
    python scripts/reproduce_report.py outputs/reproduce            # tables of scripts/reproduce.sh's runs
    python scripts/reproduce_report.py outputs/schedule --schedule procedural

**Figures** (no run folder, or ``--figures``): one figure per protocol, ``<--figures>/<protocol>.png``
(airplane, human, real): the test Err_R (degrees, log scale) of GT / CD / Ours and the controls
(CD-W, the untrained network, the identity) of each backbone (RPM-Net, DCP, FMR), one dot per seed,
a bar at their mean, the paper's number as a cross, for the cells of ``--recipe`` (default cpu).
The cells come from the run folders when given (``<protocol>/<backbone>_<loss>_s<seed>/metrics.json``,
as ``scripts/reproduce_schedule.sh`` names them; ``--write-cells`` merges them into a table),
else from ``--cells`` (default ``docs/results/cells.csv``), one row per seed with the columns
``protocol,backbone,loss,recipe,seed,err_r_deg,err_t,median_err_r_deg`` (Err_t: the mean l1
translation error, in the pairs' units; an empty value is unknown; an identity row with an empty
backbone is drawn for every backbone).

**Tables** (a run folder without ``--figures``): reads every ``<protocol>/<cell>_s<seed>/metrics.json``
(training runs), ``<protocol>/baselines/results.json`` (classical methods on the same test pairs)
and ``real/rpm_gt_procedural_s*/metrics.json`` (a model evaluated without fine-tuning), and writes
into ``--docs``:

* ``tables.md``: per protocol, the paper-format table (means over the test pairs, averaged over
  seeds, ± the spread between seeds when there are several) beside the paper's numbers, the
  median Err_R and the wall-clock time of each cell;
* ``curves_<protocol>.png``: validation Err_R during training (the scalars TensorBoard shows,
  read from each run's ``scalars.jsonl``), one panel per backbone;
* ``figure_<protocol>_<cell>.png``: before/after views of the first test pair of the
  ``--pair-figures`` cells;

and, with ``--page``, replaces the text between ``<!-- tables:begin -->`` and
``<!-- tables:end -->`` in that page with the tables. ``--schedule <protocol>`` instead prints
the table of scripts/reproduce_schedule.sh (every seed's Err_R, the CPU seconds of each cell) and
writes nothing.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import statistics
from collections import defaultdict
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

# The paper's Tables 3-5: Err_R (deg), Err_t l1, l2 and Err_pw l1, l2 (x 10^-1).
PAPER = {
    "airplane": {
        "icp_point": (7.223, 0.131, 0.087, 0.136, 0.105),
        "fricp": (6.91, 0.076, 0.051, 0.123, 0.094),
        "fgr": (13.72, 0.099, 0.065, 0.156, 0.114),
        "dcp_gt": (2.281, 0.067, 0.044, 0.073, 0.05),
        "dcp_cd": (6.612, 0.165, 0.11, 0.198, 0.139),
        "dcp_ours": (3.808, 0.082, 0.056, 0.093, 0.063),
        "fmr_gt": (1.977, 0.086, 0.055, 0.099, 0.065),
        "fmr_cd": (5.819, 0.215, 0.153, 0.247, 0.19),
        "fmr_ours": (2.51, 0.117, 0.076, 0.134, 0.091),
        "rpm_gt": (2.19, 0.041, 0.034, 0.043, 0.03),
        "rpm_cd": (2.791, 0.103, 0.089, 0.102, 0.083),
        "rpm_ours": (1.673, 0.042, 0.034, 0.045, 0.031),
    },
    "human": {
        "dcp_gt": (3.841, 0.061, 0.039, 0.068, 0.046),
        "dcp_cd": (7.021, 0.185, 0.114, 0.193, 0.130),
        "dcp_ours": (4.841, 0.07, 0.046, 0.079, 0.054),
        "fmr_gt": (2.122, 0.058, 0.039, 0.064, 0.043),
        "fmr_cd": (6.207, 0.187, 0.123, 0.228, 0.134),
        "fmr_ours": (1.521, 0.089, 0.051, 0.091, 0.063),
        "rpm_gt": (1.921, 0.030, 0.021, 0.033, 0.023),
        "rpm_cd": (8.373, 0.197, 0.16, 0.193, 0.133),
        "rpm_ours": (1.33, 0.032, 0.024, 0.034, 0.023),
    },
    "real": {
        "icp_point": (17.98, 0.337, 0.23, 0.238, 0.194),
        "fricp": (11.08, 0.199, 0.139, 0.151, 0.112),
        "fgr": (12.79, 0.211, 0.142, 0.260, 0.21),
        "fmr_cd": (7.559, 0.469, 0.34, 0.531, 0.384),
        "fmr_ours": (3.263, 0.089, 0.065, 0.101, 0.075),
        "rpm_cd": (11.28, 0.342, 0.246, 0.376, 0.272),
        "rpm_ours": (2.972, 0.057, 0.04, 0.068, 0.05),
    },
}
KEYS = ("err_r_deg_mean", "err_t_l1_mean", "err_t_l2_mean", "err_pw_l1_mean", "err_pw_l2_mean")
SCALE = (1.0, 10.0, 10.0, 10.0, 10.0)  # the paper prints Err_t and Err_pw x 10^-1
IDENTITY = "identity"
# Control cells: the untrained network and its unsupervised regulariser alone (alignment weight 0).
CONTROLS = ("untrained", "reg")
# A supervised model evaluated as it is on Real, fine-tuned there without labels, and with them.
FINE_TUNED = ("cd_finetuned", "ours_finetuned", "ours_nu2_finetuned", "oracle_finetuned")
ROW_ORDER = (
    [IDENTITY, "icp_point", "icp_plane", "fricp", "fgr"]
    + [f"{b}_{loss}" for b in ("dcp", "fmr", "rpm") for loss in (*CONTROLS, "gt", "cd", "ours", "ours_nu2")]
    + ["rpm_ours_quick", "rpm_ours_fixed_nu", "rpm_gt_procedural", "rpm_gt_finetuned"]
    + [f"{b}_{cell}" for b in ("dcp", "fmr", "rpm") for cell in ("pretrained", *FINE_TUNED)]
)
CELL = re.compile(r"(?P<cell>.+)_s(?P<seed>\d+)$")

# The per-seed table of the figures (docs/results/cells.csv).
CELL_COLUMNS = ("protocol", "backbone", "loss", "recipe", "seed", "err_r_deg", "err_t", "median_err_r_deg")
FIGURE_PROTOCOLS = ("airplane", "human", "real")
# Backbone of a run name's prefix (``rpm_ours_s0``), in the figures' order.
BACKBONES = {"rpm": "rpmnet", "dcp": "dcp", "fmr": "fmr"}
BACKBONE_NAMES = {"rpmnet": "RPM-Net", "dcp": "DCP", "fmr": "FMR"}
# Losses in the figures' order: the three of the paper's tables, then the controls.
LOSS_NAMES = {"gt": "GT", "cd": "CD", "ours": "Ours", "cdw": "CD-W", "untrained": "untrained", IDENTITY: "identity"}
LOSS_COLOURS = {
    "gt": "tab:green",
    "cd": "tab:orange",
    "ours": "tab:blue",
    "cdw": "tab:purple",
    "untrained": "tab:gray",
    IDENTITY: "black",
}


def _runs(protocol_dir: Path) -> dict[str, list[Path]]:
    """``cell -> [run folders of each seed]`` for finished runs (or evaluations)."""
    found: dict[str, list[Path]] = defaultdict(list)
    for path in sorted(protocol_dir.iterdir()):
        match = CELL.match(path.name)
        if path.is_dir() and match and (path / "metrics.json").is_file():
            found[match["cell"]].append(path)
    return found


def _test_metrics(run: Path) -> dict[str, float]:
    """Test-split means of a training run, or of a ``train.evaluate`` output folder."""
    content = json.loads((run / "metrics.json").read_text())
    if "model" in content:  # python -m train.evaluate
        return {key: content["model"][key] for key in (*KEYS, "err_r_deg_median")}
    metrics = content["metrics"]
    return {key: metrics[f"test/{key}"] for key in (*KEYS, "err_r_deg_median")}


def _identity_metrics(run: Path) -> dict[str, float] | None:
    """Test-split means of the identity (no motion) on a training run's test pairs, if recorded."""
    metrics = json.loads((run / "metrics.json").read_text()).get("metrics", {})
    if f"test/identity/{KEYS[0]}" not in metrics:
        return None
    return {key: metrics[f"test/identity/{key}"] for key in (*KEYS, "err_r_deg_median")}


def _seconds(run: Path) -> float | None:
    file = run.parent / f"{run.name}.seconds"
    if not file.is_file():
        return None
    return sum(float(line) for line in file.read_text().split())


def _cpu_seconds(run: Path) -> float | None:
    """User + system CPU seconds of a run, summed over its attempts (``<run>.cpu``, ``time -f "%U %S"``)."""
    file = run.parent / f"{run.name}.cpu"
    if not file.is_file():
        return None
    attempts = [line.split() for line in file.read_text().splitlines()]
    # A failed attempt adds a "Command exited with non-zero status" line before its times.
    return sum(float(user) + float(system) for user, system in (a for a in attempts if len(a) == 2))


def _fmt(values: list[float], scale: float) -> str:
    mean = statistics.fmean(values) * scale
    if len(values) == 1:
        return f"{mean:.3f}"
    return f"{mean:.3f} ± {statistics.stdev(values) * scale:.3f}"


def _row(cols: list[str], median_r: float, seeds: str, time: str) -> dict[str, str]:
    """A table row from the five formatted error columns (Err_R, Err_t l1/l2, Err_pw l1/l2)."""
    return {
        "err_r": cols[0],
        "err_t": f"{cols[1]}, {cols[2]}",
        "err_pw": f"{cols[3]}, {cols[4]}",
        "median_r": f"{median_r:.3f}",
        "seeds": seeds,
        "time": time,
    }


def protocol_rows(out: Path, protocol: str) -> list[dict[str, str]]:
    """One table row per method: our measurement, the paper's, median Err_R, seeds and time."""
    protocol_dir = out / protocol
    rows: dict[str, dict[str, str]] = {}
    identity = next(
        (m for runs in _runs(protocol_dir).values() for m in [_identity_metrics(runs[0])] if m is not None), None
    )
    if identity is not None:
        cols = [f"{identity[key] * scale:.3f}" for key, scale in zip(KEYS, SCALE, strict=True)]
        rows[IDENTITY] = _row(cols, identity["err_r_deg_median"], "-", "")
    for cell, runs in _runs(protocol_dir).items():
        metrics = [_test_metrics(run) for run in runs]
        cols = [_fmt([m[key] for m in metrics], scale) for key, scale in zip(KEYS, SCALE, strict=True)]
        times = [t for t in (_seconds(run) for run in runs) if t is not None]
        median_r = statistics.fmean(m["err_r_deg_median"] for m in metrics)
        time = f"{statistics.fmean(times) / 60:.1f} min" if times else ""
        rows[cell] = _row(cols, median_r, str(len(runs)), time)
    baseline_file = protocol_dir / "baselines" / "results.json"
    if baseline_file.is_file():
        for method, summary in json.loads(baseline_file.read_text())["summary"].items():
            cols = [f"{summary[key] * scale:.3f}" for key, scale in zip(KEYS, SCALE, strict=True)]
            time = f"{summary['seconds_mean'] * 1000:.0f} ms/pair"
            rows[method] = _row(cols, summary["err_r_deg_median"], "-", time)
    paper = PAPER.get(protocol, {})
    ordered = _ordered(rows)
    for name in ordered:
        numbers = paper.get(name)
        rows[name]["name"] = name
        rows[name]["paper_r"] = f"{numbers[0]:.3f}" if numbers else ""
        rows[name]["paper_pw"] = f"{numbers[3]:.3f}, {numbers[4]:.3f}" if numbers else ""
    return [rows[name] for name in ordered]


def markdown(rows: list[dict[str, str]]) -> str:
    header = (
        "| Method | Err_R (deg) | Err_t (x10^-1) (l1, l2) | Err_pw (x10^-1) (l1, l2) | median Err_R | "
        "paper Err_R | paper Err_pw | seeds | time |\n|---|---|---|---|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {r['name']} | {r['err_r']} | {r['err_t']} | {r['err_pw']} | {r['median_r']} | {r['paper_r']} | "
        f"{r['paper_pw']} | {r['seeds']} | {r['time']} |\n"
        for r in rows
    )
    return header + body


def _ordered(names) -> list[str]:
    return sorted(names, key=lambda name: ROW_ORDER.index(name) if name in ROW_ORDER else len(ROW_ORDER))


def schedule_markdown(out: Path, protocol: str) -> str:
    """The table of scripts/reproduce_schedule.sh: per cell, the test Err_R mean (± the sample
    standard deviation over seeds) with each seed's value, the median Err_R and Err_t l1 (means
    over seeds), the seeds and the mean CPU seconds of a run; the identity on the same test pairs first."""
    runs = _runs(out / protocol)
    lines = [
        "| cell | test Err_R mean (deg) | per seed | median Err_R | Err_t l1 (x10^-1) | seeds | CPU s |",
        "|---|---:|---|---:|---:|---|---:|",
    ]
    identity = next((m for cell_runs in runs.values() for m in [_identity_metrics(cell_runs[0])] if m), None)
    if identity is not None:
        lines.append(
            f"| {IDENTITY} | {identity['err_r_deg_mean']:.2f} | | {identity['err_r_deg_median']:.2f} | "
            f"{identity['err_t_l1_mean'] * 10:.2f} | - | |"
        )
    for cell in _ordered(runs):
        metrics = [_test_metrics(run) for run in runs[cell]]
        err_r = [m["err_r_deg_mean"] for m in metrics]
        mean = f"{statistics.fmean(err_r):.2f}" + (f" ± {statistics.stdev(err_r):.2f}" if len(err_r) > 1 else "")
        per_seed = ", ".join(f"{value:.2f}" for value in err_r) if len(err_r) > 1 else ""
        seeds = " ".join(CELL.match(run.name)["seed"] for run in runs[cell])
        cpu = [t for t in (_cpu_seconds(run) for run in runs[cell]) if t is not None]
        lines.append(
            f"| {cell} | {mean} | {per_seed} | {statistics.fmean(m['err_r_deg_median'] for m in metrics):.2f} | "
            f"{statistics.fmean(m['err_t_l1_mean'] for m in metrics) * 10:.2f} | {seeds} | "
            f"{f'{statistics.fmean(cpu):.0f}' if cpu else ''} |"
        )
    return "\n".join(lines) + "\n"


def plot_curves(out: Path, protocol: str, path: Path) -> bool:
    """Validation Err_R against training steps, one panel per backbone; False when no runs."""
    runs = _runs(out / protocol)
    backbones = sorted({cell.split("_")[0] for cell in runs if (runs[cell][0] / "scalars.jsonl").is_file()})
    if not backbones:
        return False
    fig = Figure(figsize=(4.2 * len(backbones), 3.4), layout="tight")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(backbones), squeeze=False)
    for ax, backbone in zip(axes[0], backbones, strict=True):
        for cell, cell_runs in sorted(runs.items()):
            scalars = cell_runs[0] / "scalars.jsonl"
            if not cell.startswith(f"{backbone}_") or not scalars.is_file():
                continue
            records = [json.loads(line) for line in scalars.read_text().splitlines() if line.strip()]
            points = [(r["step"], r["val/err_r_deg_mean"]) for r in records if "val/err_r_deg_mean" in r]
            if points:
                ax.plot(*zip(*points, strict=True), marker=".", label=cell)
        ax.set_title(f"{protocol}: {backbone}")
        ax.set_xlabel("training step")
        ax.set_ylabel("val Err_R mean (deg)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return True


def read_cells(path: Path) -> list[dict]:
    """Rows of a per-seed table (:data:`CELL_COLUMNS`); empty values are ``None``, numbers floats."""
    with path.open(newline="") as file:
        reader = csv.DictReader(file)
        if tuple(reader.fieldnames or ()) != CELL_COLUMNS:
            raise ValueError(f"{path}: the header must be {','.join(CELL_COLUMNS)}, got {reader.fieldnames}")
        rows = list(reader)
    numbers = ("err_r_deg", "err_t", "median_err_r_deg")
    cells = []
    for line, row in enumerate(rows, start=2):
        try:
            cells.append(
                {key: (float(value) if key in numbers else value) if value else None for key, value in row.items()}
            )
        except ValueError as error:
            raise ValueError(f"{path}, line {line}: {error}") from None
    return cells


def run_cells(out: Path, recipe: str) -> list[dict]:
    """Per-seed rows of the run folders ``out/<protocol>/<backbone>_<loss>_s<seed>`` (losses of
    :data:`LOSS_NAMES`) and, per backbone, of the identity on its test pairs, labelled ``recipe``."""
    rows = []
    for protocol in FIGURE_PROTOCOLS:
        if not (out / protocol).is_dir():
            continue
        identities = {}
        for cell, runs in _runs(out / protocol).items():
            prefix, _, loss = cell.partition("_")
            if prefix not in BACKBONES or loss not in LOSS_NAMES or loss == IDENTITY:
                continue
            backbone = BACKBONES[prefix]
            for run in runs:
                seed = CELL.match(run.name)["seed"]
                rows.append(_cell_row(protocol, backbone, loss, recipe, seed, _test_metrics(run)))
                if backbone not in identities and _identity_metrics(run) is not None:
                    identities[backbone] = _cell_row(protocol, backbone, IDENTITY, recipe, None, _identity_metrics(run))
        rows += identities.values()
    return rows


def _cell_row(protocol: str, backbone: str, loss: str, recipe: str, seed: str | None, metrics: dict) -> dict:
    """A row of :data:`CELL_COLUMNS` from test-split means (:func:`_test_metrics`)."""
    return {
        "protocol": protocol,
        "backbone": backbone,
        "loss": loss,
        "recipe": recipe,
        "seed": seed,
        "err_r_deg": metrics["err_r_deg_mean"],
        "err_t": metrics["err_t_l1_mean"],
        "median_err_r_deg": metrics["err_r_deg_median"],
    }


def _cell_key(row: dict) -> tuple:
    return tuple(row[column] for column in CELL_COLUMNS[:5])


def _csv_value(value: str | float | None) -> str:
    if value is None:
        return ""
    return f"{value:.4g}" if isinstance(value, float) else value


def write_cells(path: Path, rows: list[dict]) -> None:
    """Merge ``rows`` into the table at ``path`` (created if absent): a row replaces the one of the
    same protocol, backbone, loss, recipe and seed; the others stay as they are, in their order."""
    new = {_cell_key(row): [_csv_value(row[column]) for column in CELL_COLUMNS] for row in rows}
    kept = []
    if path.is_file():
        read_cells(path)  # the header is checked
        with path.open(newline="") as file:
            kept = [line for line in list(csv.reader(file))[1:] if tuple(v or None for v in line[:5]) not in new]
    with path.open("w", newline="") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerows([CELL_COLUMNS, *kept, *new.values()])


def protocol_figure(cells: list[dict], protocol: str, recipe: str) -> Figure | None:
    """Test Err_R of every loss of each backbone of one protocol: a dot per seed, a bar at the mean
    and the paper's number as a cross, one axes per backbone; ``None`` when the table has no cell."""
    rows = [r for r in cells if r["protocol"] == protocol and r["recipe"] == recipe and r["err_r_deg"] is not None]
    backbones = [b for b in BACKBONE_NAMES if any(r["backbone"] == b for r in rows)]
    if not backbones:
        return None
    fig = Figure(figsize=(3.4 * len(backbones), 3.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(backbones), squeeze=False, sharey=True)[0]
    prefix = {backbone: name for name, backbone in BACKBONES.items()}
    for ax, backbone in zip(axes, backbones, strict=True):
        mine = [r for r in rows if r["backbone"] in (backbone, None)]
        losses = [loss for loss in LOSS_NAMES if any(r["loss"] == loss for r in mine)]
        for x, loss in enumerate(losses):
            values = [r["err_r_deg"] for r in mine if r["loss"] == loss]
            spread = [0.0] if len(values) == 1 else [0.3 * (i / (len(values) - 1) - 0.5) for i in range(len(values))]
            colour = LOSS_COLOURS[loss]
            ax.scatter([x + d for d in spread], values, s=16, color=colour, zorder=3, gid=loss)
            ax.hlines(statistics.fmean(values), x - 0.3, x + 0.3, color=colour, linewidth=2.5, alpha=0.6)
            paper = PAPER.get(protocol, {}).get(f"{prefix[backbone]}_{loss}")
            if paper is not None:
                ax.scatter([x], [paper[0]], marker="x", s=40, color="black", zorder=4, gid="paper")
        ax.set_xticks(range(len(losses)), [LOSS_NAMES[loss] for loss in losses], rotation=30, ha="right")
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 3.0, 5.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_title(BACKBONE_NAMES[backbone])
        ax.grid(axis="y", which="both", alpha=0.3)
    axes[0].set_ylabel("test Err_R (deg)")
    fig.suptitle(f"{protocol.capitalize()}, recipe={recipe}: a dot per seed, a bar at their mean, x the paper")
    return fig


def draw_figures(cells: list[dict], folder: Path, recipe: str) -> list[Path]:
    """Write ``folder/<protocol>.png`` for every protocol of :data:`FIGURE_PROTOCOLS` with cells."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for protocol in FIGURE_PROTOCOLS:
        fig = protocol_figure(cells, protocol, recipe)
        if fig is not None:
            fig.savefig(folder / f"{protocol}.png", dpi=110)
            written.append(folder / f"{protocol}.png")
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path, help="folder of run folders (default: figures from --cells)")
    parser.add_argument("--cells", default="docs/results/cells.csv", type=Path, help="per-seed table to draw")
    parser.add_argument("--figures", type=Path, help="folder of the per-protocol figures (default: docs/results)")
    parser.add_argument("--recipe", default="cpu", choices=("cpu", "paper"), help="the recipe of the cells drawn")
    parser.add_argument("--write-cells", type=Path, help="merge the run folders' cells into this table")
    parser.add_argument("--docs", default="docs/results", type=Path, help="folder of tables.md and its figures")
    parser.add_argument("--pair-figures", nargs="*", default=["rpm_ours", "rpm_cd", "rpm_gt"])
    parser.add_argument("--page", type=Path, help="a page whose marked region receives the tables")
    parser.add_argument("--schedule", metavar="PROTOCOL", help="print the table of scripts/reproduce_schedule.sh")
    args = parser.parse_args(argv)
    if args.out is not None and not args.out.is_dir():
        parser.error(f"{args.out} is not a folder (run scripts/reproduce.sh or scripts/reproduce_schedule.sh first)")
    if args.schedule is not None:
        if args.out is None or not (args.out / args.schedule).is_dir():
            parser.error(f"{args.out}/{args.schedule} is not a folder (run scripts/reproduce_schedule.sh first)")
        print(schedule_markdown(args.out, args.schedule), end="")
        return 0
    if args.out is not None and args.figures is None and args.write_cells is None:
        if args.page is not None and not args.page.is_file():
            parser.error(f"--page {args.page} is not a file")
        try:
            return write_tables(args.out, args.docs, args.page, args.pair_figures)
        except ValueError as error:  # a page without the marked region
            parser.error(str(error))
    if args.out is None and not args.cells.is_file():
        parser.error(f"{args.cells} is not a file (give a folder of runs or --cells <table>)")
    try:
        cells = read_cells(args.cells) if args.out is None else run_cells(args.out, args.recipe)
        if args.out is not None and args.write_cells is not None:
            write_cells(args.write_cells, cells)
    except ValueError as error:  # a table with another header or a value that is not a number
        parser.error(str(error))
    for path in draw_figures(cells, args.figures or Path("docs/results"), args.recipe):
        print(path)
    return 0


def write_tables(out: Path, docs: Path, page: Path | None, pair_figures: list[str]) -> int:
    """Tables mode: ``docs/tables.md``, the curves and pair views, and the marked region of ``page``."""
    docs.mkdir(parents=True, exist_ok=True)
    sections = []
    for protocol in ("airplane", "human", "real"):
        if not (out / protocol).is_dir():
            continue
        rows = protocol_rows(out, protocol)
        if not rows:
            continue
        sections.append(f"### {protocol.capitalize()}\n\n{markdown(rows)}")
        if plot_curves(out, protocol, docs / f"curves_{protocol}.png"):
            curves = f"curves_{protocol}.png"
            sections[-1] += f"\nValidation Err_R during training (first seed):\n\n![validation curves]({curves})\n"
        for cell in pair_figures:
            figure = out / protocol / f"{cell}_s1" / "evaluation" / "figures" / "pair_0000.png"
            if figure.is_file():
                name = f"figure_{protocol}_{cell}.png"
                shutil.copyfile(figure, docs / name)
                sections[-1] += f"\n{cell}, first test pair:\n\n![{cell}]({name})\n"
    text = "\n".join(sections)
    (docs / "tables.md").write_text(text)
    if page is not None:
        fill_page(page, text, docs.resolve().relative_to(page.parent.resolve()))
    print(text)
    return 0


def fill_page(page: Path, tables: str, docs: Path) -> None:
    """Replace the marked region of ``page`` with ``tables``, its figure links made relative to the page."""
    begin, end = "<!-- tables:begin -->", "<!-- tables:end -->"
    content = page.read_text()
    if begin not in content or end not in content:
        raise ValueError(f"{page} has no {begin} ... {end} region to fill")
    head, rest = content.split(begin, 1)
    tail = rest.split(end, 1)[1]
    tables = re.sub(r"\]\(([^/)]+\.png)\)", rf"]({docs.as_posix()}/\1)", tables)
    page.write_text(f"{head}{begin}\n{tables}\n{end}{tail}")


if __name__ == "__main__":
    raise SystemExit(main())
