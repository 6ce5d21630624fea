"""The generalization tables of ``scripts/score_generalization.py``: which splits each protocol is
scored on, and the markdown tables drawn from the cached scores (``{job key: {"model", "identity",
"register", ...}}``, mean Err_R in degrees)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

IN_PROTOCOL = "in-protocol"
# protocol -> (column, dataset config or None for the checkpoint's own test pairs)
SPLITS: dict[str, list[tuple[str, str | None]]] = {
    "airplane": [
        (IN_PROTOCOL, None),
        ("view vs whole shape", "airplane_view_vs_whole"),
        ("7 other ModelNet40 classes", "airplane_other_categories"),
    ],
    "human": [
        (IN_PROTOCOL, None),
        ("view vs view", "human_view_vs_view"),
        ("armadillo (no SMPL body)", "human_armadillo"),
    ],
    "real": [
        (IN_PROTOCOL, None),
        ("Kinect frames (SLAM poses)", "kinect_frames"),
        ("3DMatch redkitchen fragments (1 pair)", "redkitchen_fragments"),
    ],
}
LOSSES = ("gt", "cd", "ours")
BODIES = ("human_man", "human_neutral", "human_woman")
# The validation pairs of the mixed-pairs choice: fresh poses (the val split's seed) of 144
# training pairs, one column per pair type.
VALIDATION_PAIRS = 144
VALIDATION = [("val: view vs view", "airplane_views"), ("val: view vs whole", "airplane_view_vs_whole")]
# The mixed-pairs runs on the Airplane splits; airplane_views holds the protocol's own pairs.
MIXED_SPLITS = [(IN_PROTOCOL, "airplane_views"), *SPLITS["airplane"][1:]]
# The general model's table: every protocol's splits; other classes only as the shapes it held out.
OBJECT_SPLITS: list[tuple[str, str, str]] = [  # (protocol, column, dataset config)
    ("airplane", "Airplane in-protocol", "airplane_views"),
    ("airplane", "Airplane view vs whole", "airplane_view_vs_whole"),
    ("airplane", "6 held-out shapes of 7 other classes", "airplane_other_categories_held_out"),
    ("human", "Human in-protocol", "human_bodies"),
    ("human", "Human view vs view", "human_view_vs_view"),
    ("human", "armadillo", "human_armadillo"),
    ("real", "Real in-protocol", "sevenscenes_frames"),
    ("real", "Kinect frames", "kinect_frames"),
    ("real", "3DMatch redkitchen fragments", "redkitchen_fragments"),
]
GENERAL = "rpm_ours_objects"
# The general model's training data: the ``reproduce_generalization.sh`` step (its dataset config)
# -> what it holds; the shipped ``rpm_ours_objects`` is seed 0 of GENERAL_SHIPPED's ``rpm_ours``.
GENERAL_DATA = {
    "objects": "every object",
    "objects_and_rooms": "every object and the room frames (6 frames apart)",
    "objects_and_rooms_gap20": "every object and the room frames (20 frames apart)",
    "objects_then_rooms": "every object and the room frames, then the room frames alone",
    "objects_then_far_rooms": "every object and the room frames, then the rooms 20 frames apart beside the objects",
}
GENERAL_SHIPPED = "objects_and_rooms"
# The general models' validation pairs (the choice of their training data): (column, dataset config).
GENERAL_VALIDATION = [
    ("val: every object and the room frames", "objects_and_rooms"),
    ("val: Real frames", "sevenscenes_frames"),
]
# The Human runs on the validation pairs of their choice: fresh poses of every training pair.
HUMAN_VALIDATION_PAIRS = 120


@dataclass(frozen=True)
class ScheduleChoice:
    """A curriculum choice made on validation pairs: the recipe's runs against the step's runs
    (``<step>/<backbone>_<loss><suffix>_s<seed>``), on ``val_pairs`` validation pairs and the test pairs."""

    title: str
    protocol: str
    backbone: str
    suffix: str
    labels: tuple[str, str]  # (the recipe's schedule, the alternative); the table marks the recipe
    val_pairs: int | None = None  # a subset of the validation pairs of ``val_dataset``
    val_dataset: str | None = None  # None: the checkpoint's own dataset

    @property
    def alternative(self) -> str:
        """The alternative schedule's row folder (the run-name suffix without its underscore)."""
        return self.suffix.lstrip("_")


SCHEDULE_CHOICES = {
    "real_choice": ScheduleChoice("Real, easier pairs first", "real", "rpm", "_test_gap", ("gap 6, then 20", "gap 20")),
    "dcp_choice": ScheduleChoice(
        "Airplane, DCP's full-range stage",
        "airplane",
        "dcp",
        "_easy_only",
        ("easy, then full", "easy"),
        VALIDATION_PAIRS,
        "airplane_views",
    ),
}


# (column, dataset config or None for the checkpoint's own, split, cache key's last part)
STRETCH_SPLITS = [
    ("validation", "human_bodies", "val", "val"),
    ("test", None, "test", "test"),
    *((column, dataset, "test", dataset) for column, dataset in SPLITS["human"][1:]),
]


def stretch_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Human's stretched training pairs against the recipe: Err_R per split, over seeds."""
    if not any(key.startswith("human_stretch/stretch/") for key in scores):
        return ""
    columns = [column for column, *_ in STRETCH_SPLITS]
    lines = ["### Human, stretched training pairs", "", "| cell | training pairs | " + " | ".join(columns) + " |"]
    lines.append("|---|---|" + "---:|" * len(columns))
    for loss in ("cd", "ours"):
        for schedule, suffix, label in (
            ("recipe", "", "as they are (the recipe)"),
            ("stretch", "_stretch0.2", "stretched by up to 20 %"),
        ):
            cells = [
                _per_seed(_seeds_of(scores, rf"human_stretch/{schedule}/rpm_{loss}{suffix}_s{{seed}}/{leaf}"))
                for *_, leaf in STRETCH_SPLITS
            ]
            lines.append(f"| rpm_{loss} | {label} | " + " | ".join(cells) + " |")
    return "\n".join([*lines, ""])


def schedule_tables(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Each curriculum choice: validation (the choice) and test Err_R per schedule and loss, over seeds."""
    tables = []
    for step, choice in SCHEDULE_CHOICES.items():
        if not any(key.startswith(f"{step}/{choice.alternative}/") for key in scores):
            continue
        cells = [f"{choice.backbone}_{loss}" for loss in ("cd", "ours")]
        header = " | ".join(f"`{cell}` {split}" for cell in cells for split in ("validation", "test"))
        lines = [f"### {choice.title}", "", f"| schedule | {header} |", "|---|---:|---:|---:|---:|"]
        schedules = (
            ("recipe", "", f"{choice.labels[0]} (the recipe)"),
            (choice.alternative, choice.suffix, choice.labels[1]),
        )
        for schedule, suffix, label in schedules:
            row = [
                _per_seed(_seeds_of(scores, rf"{step}/{schedule}/{cell}{suffix}_s{{seed}}/{split}"))
                for cell in cells
                for split in ("val", "test")
            ]
            lines.append(f"| {label} | " + " | ".join(row) + " |")
        tables.append("\n".join([*lines, ""]))
    return "\n".join(tables)


PROTOCOL_DATA = ("airplane_views", "human_bodies", "sevenscenes_frames")  # each protocol's own test pairs


def objects_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Every network on every protocol's splits: the general models' rows (per training data of
    :data:`GENERAL_DATA`, mean over seeds, per seed) above the protocol networks (the shipped one,
    seed 0; ``*``: its own protocol's test pairs; RPM-CD's other seeds beside it off its protocol);
    then, per training data, how often the line loss's mean is at most its Chamfer twin's, and at
    most each protocol's RPM-CD (the shipped network; the mean over its seeds) on the splits that
    protocol never trained on (every column but its own test pairs)."""
    keys = [key for key in scores if key.startswith("general/")]
    if not keys:
        return ""
    header = "| network | trained on | " + " | ".join(column for _, column, _ in OBJECT_SPLITS) + " |"
    lines = ["### Every object in one network", "", header, "|---|---|" + "---:|" * len(OBJECT_SPLITS)]
    general = {}
    for step, data in GENERAL_DATA.items():
        trained = {key.split("/")[2].rsplit("_s", 1)[0] for key in keys if key.startswith(f"general/{step}/")}
        for cell in sorted(trained):
            per_seed = []
            for _, _, dataset in OBJECT_SPLITS:
                seeds = _seeds_of(scores, rf"general/{step}/{cell}_s{{seed}}/{dataset}")
                shipped = scores.get(f"general/{GENERAL}/{dataset}", {}).get("model")
                is_shipped = (step, cell) == (GENERAL_SHIPPED, "rpm_ours")
                per_seed.append(_with_shipped(shipped if is_shipped else None, seeds))
            general[step, cell] = [float(np.mean(list(values.values()))) if values else None for values in per_seed]
            row = " | ".join(_per_seed(values) for values in per_seed)
            lines.append(f"| `{cell}_objects` | {data} | {row} |")
    for protocol in SPLITS:
        for loss in LOSSES:
            text = []
            for own, _, dataset in OBJECT_SPLITS:
                seeds = _protocol_seeds(scores, protocol, loss, dataset)
                mine = own == protocol and dataset in PROTOCOL_DATA
                text.append(f"{seeds[0]:.2f}*" if mine and 0 in seeds else _per_seed({} if mine else seeds))
            lines.append(f"| `rpm_{loss}_{protocol}` | its protocol | " + " | ".join(text) + " |")
    columns = [[k for k in keys if k.endswith("/" + dataset)] for _, _, dataset in OBJECT_SPLITS]
    lines += [*_reference_rows(scores, columns, label_columns=2), ""]
    for step, data in GENERAL_DATA.items():
        lines += _general_verdicts(scores, data, general.get((step, "rpm_ours")), general.get((step, "rpm_cd")))
    return "\n".join([*lines, ""])


def general_choice_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """The general models' training data, chosen on validation pairs: a row per data and loss, a
    column per :data:`GENERAL_VALIDATION` set (mean over seeds, per seed)."""
    if not any(key.startswith("general_val/") for key in scores):
        return ""
    columns = [column for column, _ in GENERAL_VALIDATION]
    lines = [
        "### Every object in one network, the training data",
        "",
        "| trained on | cell | " + " | ".join(columns) + " |",
    ]
    lines.append("|---|---|" + "---:|" * len(columns))
    for step, data in GENERAL_DATA.items():
        for loss in ("cd", "ours"):
            row = [
                _per_seed(_seeds_of(scores, rf"general_val/{step}/rpm_{loss}_s{{seed}}/{dataset}"))
                for _, dataset in GENERAL_VALIDATION
            ]
            if any(row):
                lines.append(f"| {data} | `rpm_{loss}` | " + " | ".join(row) + " |")
    keys = [
        [k for k in scores if k.startswith("general_val/") and k.endswith("/" + dataset)]
        for _, dataset in GENERAL_VALIDATION
    ]
    lines += _reference_rows(scores, keys, label_columns=2)
    return "\n".join([*lines, ""])


def _general_verdicts(
    scores: Mapping[str, Mapping[str, float]], data: str, ours: list | None, twin: list | None
) -> list[str]:
    """A general model's verdict lines: against its Chamfer twin on every split, against each
    protocol's RPM-CD on the splits that protocol never trained on (means)."""
    if not ours:
        return []
    lines = []
    if twin:
        pairs = [(mine, theirs) for mine, theirs in zip(ours, twin, strict=True) if None not in (mine, theirs)]
        wins = sum(mine <= theirs for mine, theirs in pairs)
        lines.append(f"- on {data}: `rpm_ours` (mean) <= `rpm_cd` on the same data on {wins} of {len(pairs)} splits")
    for protocol in SPLITS:
        rivals = [_protocol_seeds(scores, protocol, "cd", dataset) for _, _, dataset in OBJECT_SPLITS]
        outside = [
            (mine, theirs)
            for (own, _, dataset), mine, theirs in zip(OBJECT_SPLITS, ours, rivals, strict=True)
            if not (own == protocol and dataset in PROTOCOL_DATA) and mine is not None and 0 in theirs
        ]
        shipped = sum(mine <= theirs[0] for mine, theirs in outside)
        text = (
            f"- on {data}: `rpm_ours` (mean) <= `rpm_cd_{protocol}` on {shipped} of {len(outside)} splits "
            f"{protocol.capitalize()} never trained on (the shipped network, seed 0)"
        )
        if all(len(theirs) > 1 for _, theirs in outside):
            seeds = "/".join(map(str, sorted({len(theirs) for _, theirs in outside})))
            mean = sum(mine <= np.mean(list(theirs.values())) for mine, theirs in outside)
            text += f"; on {mean} against its mean over {seeds} seeds"
        lines.append(text)
    return lines


def _protocol_seeds(
    scores: Mapping[str, Mapping[str, float]], protocol: str, loss: str, dataset: str
) -> dict[int, float]:
    """``{seed: Err_R}`` of a protocol's RPM-Net cell on an :data:`OBJECT_SPLITS` dataset: the shipped
    network as seed 0, its ``recipe/<protocol>`` runs (RPM-CD, off its protocol) as the others."""
    shipped = scores.get(f"general/rpm_{loss}_{protocol}/{dataset}", {}).get("model")
    return _with_shipped(shipped, _seeds_of(scores, rf"general/recipe/{protocol}/rpm_{loss}_s{{seed}}/{dataset}"))


def _cells(values: list[float | None]) -> str:
    """`` | ``-joined cells, empty where no value."""
    return " | ".join("" if v is None else f"{v:.2f}" for v in values)


def _reference_rows(
    scores: Mapping[str, Mapping[str, float]], keys: list[list[str]], label_columns: int = 1
) -> list[str]:
    """The identity and ``register`` rows: per column, the value of the first scored key that has it
    (after ``label_columns`` columns: the label, then empty ones)."""
    lines = []
    for row, label in (("identity", "identity (no motion)"), ("register", "`linereg.register`")):
        cells = [next((scores[k][row] for k in column if k in scores and row in scores[k]), None) for column in keys]
        if any(value is not None for value in cells):
            lines.append(f"| {label} | " + " | " * (label_columns - 1) + f"{_cells(cells)} |")
    return lines


def _cell_seeds(scores: Mapping[str, Mapping[str, float]], protocol: str, cell: str, pairs: str) -> dict[int, float]:
    """``{seed: Err_R}`` of a protocol's cell (``rpm_ours``) on a split: the ``recipe/<protocol>``
    runs, and for RPM-Net the shipped network as seed 0."""
    seeds = _seeds_of(scores, rf"recipe/{protocol}/{cell}_s{{seed}}/{pairs}")
    shipped = scores.get(f"{cell}_{protocol}/{pairs}", {}).get("model")
    return _with_shipped(shipped, seeds)


def _with_shipped(shipped: float | None, seeds: Mapping[int, float]) -> dict[int, float]:
    """``{seed: Err_R}`` of the runs, with a shipped network's score (when there is one) as seed 0."""
    return dict(sorted((({0: shipped} if shipped is not None else {}) | dict(seeds)).items()))


def shipped_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Per protocol, a row per cell, a column per split: RPM-Net's shipped networks (seed 0) and the
    ``recipe/<protocol>`` runs (other seeds, other backbones), as ``mean (seed 0, seed 1, ...)``;
    below, per backbone, on how many splits beyond the protocol's test pairs the line loss's mean is
    at most Chamfer's, and on how many it is so on at least 2 of 3 seeds (seeds paired by number)."""
    lines = []
    for protocol, splits in SPLITS.items():
        columns = [column for column, _ in splits]
        lines += [f"### {protocol}", "", "| network | " + " | ".join(columns) + " |", "|---|" + "---:|" * len(columns)]
        keys = [[f"rpm_{loss}_{protocol}/{dataset or 'test'}" for loss in LOSSES] for _, dataset in splits]
        trained = {key.split("/")[2].rsplit("_s", 1)[0] for key in scores if key.startswith(f"recipe/{protocol}/")}
        backbones = ["rpm", *sorted({cell.split("_")[0] for cell in trained} - {"rpm"})]
        verdicts = []
        for backbone in backbones:
            per_cell = {}
            for loss in LOSSES:
                cell = f"{backbone}_{loss}"
                per_cell[loss] = [_cell_seeds(scores, protocol, cell, dataset or "test") for _, dataset in splits]
                if backbone == "rpm" or cell in trained:
                    lines.append(f"| `{cell}_{protocol}` | " + " | ".join(_per_seed(v) for v in per_cell[loss]) + " |")
            verdicts.append(_line_loss_verdict(backbone, per_cell["ours"][1:], per_cell["cd"][1:]))
        lines += [*_reference_rows(scores, keys), "", *filter(None, verdicts), ""]
    return "\n".join(lines)


def _line_loss_verdict(backbone: str, ours: list[dict[int, float]], cd: list[dict[int, float]]) -> str:
    """How often ``<backbone>_ours`` is at most ``<backbone>_cd`` on the splits (``{seed: Err_R}``
    each): on the mean, and on a majority of the seeds both have."""
    paired = [(mine, theirs, sorted(set(mine) & set(theirs))) for mine, theirs in zip(ours, cd, strict=True)]
    paired = [item for item in paired if item[2]]
    if not paired:
        return ""
    on_mean = sum(np.mean(list(mine.values())) <= np.mean(list(theirs.values())) for mine, theirs, _ in paired)
    on_seeds = sum(2 * sum(mine[s] <= theirs[s] for s in seeds) > len(seeds) for mine, theirs, seeds in paired)
    counts = sorted({len(seeds) for *_, seeds in paired})
    return (
        f"- `{backbone}_ours` <= `{backbone}_cd` beyond the protocol's test pairs: on the mean on {on_mean} of "
        f"{len(paired)} splits, on a majority of {'/'.join(map(str, counts))} seed(s) on {on_seeds}"
    )


def _seeds_of(scores: Mapping[str, Mapping[str, float]], pattern: str) -> dict[int, float]:
    """``{seed: Err_R}`` of the keys matching ``pattern`` with ``{seed}`` in it."""
    found = {}
    for key, value in scores.items():
        match = re.fullmatch(pattern.replace("{seed}", r"(\d+)"), key)
        if match:
            found[int(match.group(1))] = value["model"]
    return dict(sorted(found.items()))


def _per_seed(values: Mapping[int, float]) -> str:
    """``mean (a, b, c)`` over seeds, or empty."""
    if not values:
        return ""
    listed = ", ".join(f"{v:.2f}" for v in values.values())
    return f"{np.mean(list(values.values())):.2f} ({listed})" if len(values) > 1 else listed


def unseen_body_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Leave one body out: a row per cell, a column per held-out body (mean over seeds, per seed)."""
    cells = sorted({key.split("/")[2].rsplit("_s", 1)[0] for key in scores if key.startswith("unseen_body/")})
    if not cells:
        return ""
    lines = ["### Human, leave one body out", "", "| cell | " + " | ".join(BODIES) + " | mean over bodies |"]
    lines.append("|---|" + "---:|" * (len(BODIES) + 1))
    for cell in cells:
        per_body = [_seeds_of(scores, rf"unseen_body/{body}/{cell}_s{{seed}}/test") for body in BODIES]
        seeds = sorted(set.intersection(*(set(values) for values in per_body)))
        means = {seed: float(np.mean([values[seed] for values in per_body])) for seed in seeds}
        lines.append(f"| {cell} | " + " | ".join(_per_seed(v) for v in per_body) + f" | {_per_seed(means)} |")
    keys = [[k for k in scores if k.startswith(f"unseen_body/{body}/")] for body in BODIES]
    lines += _reference_rows(scores, [*keys, []])
    return "\n".join([*lines, ""])


def _leaf(column: str, dataset: str, *, shipped: bool) -> str:
    """The cache key's last part of a column of :func:`mixed_table`."""
    if column.startswith("val"):
        return f"val_{dataset}"
    return "test" if shipped and column == IN_PROTOCOL else dataset


def mixed_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Airplane, view-vs-view training (the shipped networks) against both pair types (the runs):
    validation columns first (the choice), then the test splits."""
    cells = sorted({key.split("/")[1].rsplit("_s", 1)[0] for key in scores if key.startswith("mixed_pairs/")})
    if not cells:
        return ""
    columns = [*VALIDATION, *MIXED_SPLITS]
    header = "| training pairs | cell | " + " | ".join(column for column, _ in columns) + " |"
    lines = ["### Airplane, both pair types in training", "", header, "|---|---|" + "---:|" * len(columns)]
    for cell in cells:
        view = [scores.get(f"{cell}_airplane/{_leaf(c, d, shipped=True)}", {}).get("model") for c, d in columns]
        mixed = [_seeds_of(scores, rf"mixed_pairs/{cell}_s{{seed}}/{_leaf(c, d, shipped=False)}") for c, d in columns]
        lines.append(f"| view vs view (seed 0) | {cell} | {_cells(view)} |")
        lines.append(f"| both | {cell} | " + " | ".join(_per_seed(values) for values in mixed) + " |")
    keys = [[k for k in scores if k.endswith("/" + _leaf(c, d, shipped=False))] for c, d in columns]
    lines += [line.replace("| ", "| | ", 1) for line in _reference_rows(scores, keys)]
    return "\n".join([*lines, ""])


def choice_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Human's line-loss settings: validation (the choice) and test Err_R per setting."""
    rows = ["rpm_ours_human", *sorted({k.rsplit("/", 1)[0] for k in scores if k.startswith("human_choice/")})]
    if len(rows) == 1:
        return ""
    lines = ["### Human, the line loss's settings", "", "| settings | validation | test |", "|---|---:|---:|"]
    for row in rows:
        match = re.search(r"nu(?P<nu>[\d.]+)_lines(?P<lines>\d+)_s(?P<seed>\d+)", row)
        label = (
            f"ν0 = {match['nu']}, {int(match['lines'])} lines, seed {match['seed']}" if match else f"`{row}` (seed 0)"
        )
        lines.append(
            f"| {label} | {_cells([scores.get(f'{row}/{split}', {}).get('model') for split in ('val', 'test')])} |"
        )
    return "\n".join([*lines, ""])


TABLES = (
    shipped_table,
    unseen_body_table,
    mixed_table,
    choice_table,
    schedule_tables,
    stretch_table,
    objects_table,
    general_choice_table,
)
