"""Score networks beyond their own test split: each protocol's generalization splits, one table each.

    python scripts/score_generalization.py --out outputs/generalization --register
    python scripts/score_generalization.py --out <dir> --runs outputs/generalization_runs --register

The shipped networks ``rpm_{gt,cd,ours}_<protocol>`` of :mod:`linereg.pretrained` are scored by
``linereg-evaluate`` on their protocol's test pairs (``in-protocol``) and on every generalization
split of :data:`SPLITS` (a dataset config of ``configs/dataset/``). With ``--runs`` (the folder of
``scripts/reproduce_generalization.sh``), also:

* ``unseen_body/<body>/<cell>_s<seed>``: each leave-one-body-out run on its own test split, the
  body its training never saw;
* ``mixed_pairs/<cell>_s<seed>``: each run trained on both Airplane pair types, on the Airplane
  splits, and on the validation pairs of both pair types (fresh poses of training shapes, the
  pairs the recipe's choice is made on) beside the shipped view-vs-view networks;
* ``human_choice/<settings>_s<seed>``: RPM-Ours on Human at other line-loss settings, on the
  validation pairs (fresh poses of every training pair; the choice) and the test pairs;
* ``recipe/<protocol>/<cell>_s<seed>``: the protocol's own cells at other seeds, on its splits
  (the shipped network is seed 0);
* ``real_choice/<cell>_test_gap_s<seed>``: the Real cells without easier pairs first, beside the
  recipe's (the shipped network and ``recipe/real`` runs), on Real's validation pairs (the choice)
  and test pairs;
* ``human_stretch/<cell>_stretch0.2_s<seed>``: the Human cells trained on stretched pairs, beside
  the recipe's, on Human's validation pairs (the choice), test pairs and other splits;
* ``objects/<cell>_s<seed>``: networks trained on every object (``dataset=objects``), with the
  shipped general model ``rpm_ours_objects`` (seed 0) and every shipped protocol network, on every
  split of every protocol (:data:`OBJECT_SPLITS`).

Every table gives the identity's error on the same pairs and, with ``--register``, that of
``linereg.register`` (the default solver, no network). Each score is cached in
``<out>/<row>/<split>.json``, so a cut run resumes; ``<out>/table.md`` holds mean Err_R (degrees).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from linereg.train import CONFIG_DIR
from linereg.train.evaluate import evaluate

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
    "real": [(IN_PROTOCOL, None), ("Kinect frames (SLAM poses)", "kinect_frames")],
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
]
GENERAL = "rpm_ours_objects"
RUN_NAME = re.compile(r".+_s\d+$")  # <cell or settings>_s<seed>
# The Human runs on the validation pairs of their choice: fresh poses of every training pair.
HUMAN_VALIDATION_PAIRS = 120


@dataclass(frozen=True)
class Job:
    """One score: ``checkpoint`` on ``split`` of ``dataset`` (None: the checkpoint's own), cached at
    ``<out>/<key>.json``; ``register_key`` names the cache of ``linereg.register`` on those pairs."""

    key: str
    checkpoint: str
    dataset: str | None
    split: str = "test"
    register_key: str | None = None
    subset: int | None = None


def score(job: Job, *, register: Path | None) -> dict[str, float]:
    """Mean Err_R of the job's network and of the identity on its pairs; with ``register`` (a cache
    file shared by the networks scored on the same pairs), also that of ``linereg.register``."""
    overrides = [f"checkpoint={job.checkpoint}", f"split={job.split}", "progress=false", "num_figures=0"]
    overrides += ["with_loss=false", *([f"dataset={job.dataset}"] if job.dataset else [])]
    if job.subset is not None:
        overrides.append(f"dataset.splits.{job.split}.subset={job.subset}")
    with tempfile.TemporaryDirectory() as scratch, initialize_config_dir(CONFIG_DIR, version_base="1.3"):
        cfg = compose("evaluate", overrides=[*overrides, f"output_dir={scratch}", f"paths.root_dir={Path.cwd()}"])
        metrics = evaluate(cfg)
    result = {
        "pairs": metrics["num_pairs"],
        "model": metrics["model"]["err_r_deg_mean"],
        "identity": metrics["identity"]["err_r_deg_mean"],
        "confident": metrics["model"].get("confident_share"),
    }
    if register is not None:
        if not register.is_file():
            register.parent.mkdir(parents=True, exist_ok=True)
            register.write_text(json.dumps({"err_r_deg_mean": register_error(cfg)}))
        result["register"] = json.loads(register.read_text())["err_r_deg_mean"]
    return result


def register_error(cfg) -> float:
    """Mean Err_R (degrees) of ``linereg.register`` (the default solver) on the pairs ``cfg`` evaluated
    (:func:`score` ran :func:`evaluate` on it, which fills in ``trainer.num_points``)."""
    import torch

    import linereg
    from linereg.checkpoint import load_checkpoint
    from linereg.datasets.splits import build_split
    from linereg.metrics import registration_errors
    from linereg.registry import plain

    dataset_config = plain(cfg.dataset) if cfg.get("dataset") else load_checkpoint(cfg.checkpoint)["config"]["dataset"]
    dataset = build_split(dataset_config, cfg.split, progress=False)
    errors = []
    for index in range(len(dataset)):
        pair = dataset[index]
        src, tgt = (np.asarray(cloud, dtype=np.float64) for cloud in (pair.src_xyz, pair.tgt_xyz))
        estimate = torch.from_numpy(linereg.register(src, tgt).transformation)[None]
        truth = torch.as_tensor(np.asarray(pair.gt_transform, dtype=np.float64))[None]
        errors.append(float(registration_errors(estimate, truth, torch.from_numpy(src)[None])["err_r_deg"][0]))
    return float(np.mean(errors))


def shipped_jobs() -> list[Job]:
    """The shipped networks on their protocol's splits."""
    return [
        Job(f"rpm_{loss}_{protocol}/{pairs}", f"rpm_{loss}_{protocol}", dataset, "test", f"{protocol}_{pairs}")
        for protocol, splits in SPLITS.items()
        for loss in LOSSES
        for _, dataset in splits
        for pairs in [dataset or "test"]
    ]


def validation_jobs(checkpoints: Mapping[str, str]) -> list[Job]:
    """Each Airplane network ``{row: checkpoint}`` on the validation pairs of both pair types."""
    return [
        Job(f"{row}/val_{dataset}", checkpoint, dataset, "val", f"airplane_val_{dataset}", VALIDATION_PAIRS)
        for row, checkpoint in checkpoints.items()
        for _, dataset in VALIDATION
    ]


def run_folders(runs: Path, step: str) -> dict[str, Path]:
    """``{relative name: folder}`` of the finished runs of a step of ``reproduce_generalization.sh``
    (folders linked in from elsewhere included)."""
    found = {}
    for folder, _, files in sorted(os.walk(runs / step, followlinks=True)):
        if "metrics.json" in files and RUN_NAME.match(Path(folder).name):
            found[str(Path(folder).relative_to(runs))] = Path(folder)
    return found


def run_jobs(runs: Path) -> list[Job]:
    """The leave-one-body-out runs on their held-out body, the mixed-pairs runs on the Airplane splits."""
    jobs = [
        Job(f"{name}/test", str(folder), None, "test", f"human_unseen_{folder.parent.name}")
        for name, folder in run_folders(runs, "unseen_body").items()
    ]
    for name, folder in run_folders(runs, "mixed_pairs").items():
        for column, dataset in MIXED_SPLITS:  # the register cache of the shipped networks' same pairs
            pairs = "test" if column == IN_PROTOCOL else dataset
            jobs.append(Job(f"{name}/{dataset}", str(folder), dataset, "test", f"airplane_{pairs}"))
    return jobs


def seed_jobs(runs: Path) -> list[Job]:
    """The ``recipe/<protocol>/<cell>_s<seed>`` runs (the protocol's cells at other seeds) on its splits."""
    jobs = []
    for protocol, splits in SPLITS.items():
        for name, folder in run_folders(runs / "recipe", protocol).items():
            for _, dataset in splits:
                pairs = dataset or "test"
                jobs.append(Job(f"recipe/{name}/{pairs}", str(folder), dataset, "test", f"{protocol}_{pairs}"))
    return jobs


def choice_jobs(runs: Path) -> list[Job]:
    """Human's line-loss settings: each ``human_choice`` run and the shipped ``rpm_ours_human`` on the
    validation pairs (the choice) and the test pairs."""
    rows = {"rpm_ours_human": "rpm_ours_human"}
    rows.update({name: str(folder) for name, folder in run_folders(runs, "human_choice").items()})
    return [
        Job(f"{row}/val", checkpoint, "human_bodies", "val", "human_val", HUMAN_VALIDATION_PAIRS)
        for row, checkpoint in rows.items()
    ] + [Job(f"{row}/test", checkpoint, None, "test", "human_test") for row, checkpoint in rows.items()]


def _recipe_rows(runs: Path, protocol: str) -> dict[str, str]:
    """``{row: checkpoint}`` of the protocol's RPM-CD and RPM-Ours under the recipe: seed 0 the
    shipped network, other seeds the ``recipe/<protocol>`` runs."""
    rows = {f"recipe/rpm_{loss}_s0": f"rpm_{loss}_{protocol}" for loss in ("cd", "ours")}
    for name, folder in run_folders(runs / "recipe", protocol).items():
        if not Path(name).name.startswith("rpm_gt"):
            rows[f"recipe/{Path(name).name}"] = str(folder)
    return rows


def real_choice_jobs(runs: Path) -> list[Job]:
    """Real's curriculum: the recipe's runs and the ``real_choice`` runs on validation and test pairs."""
    rows = _recipe_rows(runs, "real")
    rows.update(
        {f"test_gap/{Path(name).name}": str(folder) for name, folder in run_folders(runs, "real_choice").items()}
    )
    return [
        Job(f"real_choice/{row}/{split}", checkpoint, None, split, f"real_{split}")
        for row, checkpoint in rows.items()
        for split in ("val", "test")
    ]


# (column, dataset config or None for the checkpoint's own, split, cache key's last part)
STRETCH_SPLITS = [
    ("validation", "human_bodies", "val", "val"),
    ("test", None, "test", "test"),
    *((column, dataset, "test", dataset) for column, dataset in SPLITS["human"][1:]),
]


def stretch_jobs(runs: Path) -> list[Job]:
    """Human's stretched training pairs: the recipe's runs and the ``human_stretch`` runs on Human's
    validation pairs (fresh poses of every training pair) and its test splits."""
    rows = _recipe_rows(runs, "human")
    rows.update({f"stretch/{Path(n).name}": str(f) for n, f in run_folders(runs, "human_stretch").items()})
    return [
        Job(
            f"human_stretch/{row}/{leaf}",
            checkpoint,
            dataset,
            split,
            f"human_{leaf}",
            HUMAN_VALIDATION_PAIRS if split == "val" else None,
        )
        for row, checkpoint in rows.items()
        for _, dataset, split, leaf in STRETCH_SPLITS
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


def real_choice_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Real's curriculum: validation (the choice) and test Err_R per schedule and loss, over seeds."""
    if not any(key.startswith("real_choice/test_gap/") for key in scores):
        return ""
    header = "| schedule | RPM-CD validation | RPM-CD test | RPM-Ours validation | RPM-Ours test |"
    lines = ["### Real, easier pairs first", "", header, "|---|---:|---:|---:|---:|"]
    for schedule, label in (("recipe", "gap 6, then gap 20 (the recipe)"), ("test_gap", "gap 20 throughout")):
        cells = []
        for loss in ("cd", "ours"):
            suffix = "_test_gap" if schedule == "test_gap" else ""
            for split in ("val", "test"):
                cells.append(
                    _per_seed(_seeds_of(scores, rf"real_choice/{schedule}/rpm_{loss}{suffix}_s{{seed}}/{split}"))
                )
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join([*lines, ""])


PROTOCOL_DATA = ("airplane_views", "human_bodies", "sevenscenes_frames")  # each protocol's own test pairs


def _pairs_key(protocol: str, dataset: str) -> str:
    """The ``register`` cache of a dataset's test pairs (a protocol's own data: ``<protocol>_test``)."""
    return f"{protocol}_test" if dataset in PROTOCOL_DATA else f"{protocol}_{dataset}"


def object_jobs(runs: Path | None) -> list[Job]:
    """The general model, the ``objects`` runs and every shipped protocol network on every split."""
    from linereg import pretrained

    rows = {f"rpm_{loss}_{protocol}": f"rpm_{loss}_{protocol}" for protocol in SPLITS for loss in LOSSES}
    if pretrained.is_name(GENERAL):
        rows[GENERAL] = GENERAL
    if runs is not None:
        rows.update({name: str(folder) for name, folder in run_folders(runs, "objects").items()})
    return [
        Job(f"general/{row}/{dataset}", checkpoint, dataset, "test", _pairs_key(protocol, dataset))
        for row, checkpoint in rows.items()
        for protocol, _, dataset in OBJECT_SPLITS
    ]


def objects_table(scores: Mapping[str, Mapping[str, float]]) -> str:
    """Every network on every protocol's splits: the general model's rows (mean over seeds, per seed)
    above the protocol networks (seed 0; ``*``: its own protocol's test pairs), then how often the
    general model's mean is at most each protocol's RPM-CD on the splits that protocol never trained
    on (every column but its own test pairs)."""
    keys = [key for key in scores if key.startswith("general/")]
    if not keys:
        return ""
    header = "| network | " + " | ".join(column for _, column, _ in OBJECT_SPLITS) + " |"
    lines = ["### Every object in one network", "", header, "|---|" + "---:|" * len(OBJECT_SPLITS)]
    general = {}
    for cell in sorted({key.split("/")[2].rsplit("_s", 1)[0] for key in keys if key.startswith("general/objects/")}):
        per_seed = []
        for _, _, dataset in OBJECT_SPLITS:
            seeds = _seeds_of(scores, rf"general/objects/{cell}_s{{seed}}/{dataset}")
            shipped = scores.get(f"general/{GENERAL}/{dataset}", {}).get("model") if cell == "rpm_ours" else None
            per_seed.append(dict(sorted((({0: shipped} if shipped is not None else {}) | seeds).items())))
        general[cell] = [float(np.mean(list(values.values()))) if values else None for values in per_seed]
        lines.append(f"| `{cell}_objects` | " + " | ".join(_per_seed(values) for values in per_seed) + " |")
    for protocol in SPLITS:
        for loss in LOSSES:
            name = f"rpm_{loss}_{protocol}"
            cells = [
                (scores.get(f"general/{name}/{dataset}", {}).get("model"), own == protocol and dataset in PROTOCOL_DATA)
                for own, _, dataset in OBJECT_SPLITS
            ]
            text = ["" if v is None else f"{v:.2f}" + ("*" if mine else "") for v, mine in cells]
            lines.append(f"| `{name}` | " + " | ".join(text) + " |")
    columns = [[k for k in keys if k.endswith("/" + dataset)] for _, _, dataset in OBJECT_SPLITS]
    lines += [*_reference_rows(scores, columns), ""]
    ours = general.get("rpm_ours", [])
    for protocol in SPLITS if ours else ():
        rival = [scores.get(f"general/rpm_cd_{protocol}/{dataset}", {}).get("model") for _, _, dataset in OBJECT_SPLITS]
        outside = [
            (mine, theirs)
            for (own, _, dataset), mine, theirs in zip(OBJECT_SPLITS, ours, rival, strict=True)
            if not (own == protocol and dataset in PROTOCOL_DATA) and mine is not None and theirs is not None
        ]
        wins = sum(mine <= theirs for mine, theirs in outside)
        lines.append(
            f"- `{GENERAL}` (mean) <= `rpm_cd_{protocol}` on {wins} of {len(outside)} splits it never trained on"
        )
    return "\n".join([*lines, ""])


def run_all(jobs: Iterable[Job], out: Path, register: bool) -> dict[str, dict[str, float]]:
    """``{job key: score}``, scoring what is not cached yet."""
    results = {}
    for job in jobs:
        cached = out / f"{job.key}.json"
        if not cached.is_file():
            start = time.perf_counter()
            shared = out / "register" / f"{job.register_key}.json" if register and job.register_key else None
            value = score(job, register=shared)
            cached.parent.mkdir(parents=True, exist_ok=True)
            cached.write_text(json.dumps(value, indent=2))
            print(f"{job.key}: {value['model']:.2f} deg ({time.perf_counter() - start:.0f} s)", flush=True)
        results[job.key] = json.loads(cached.read_text())
    return results


def _cells(values: list[float | None]) -> str:
    """`` | ``-joined cells, empty where no value."""
    return " | ".join("" if v is None else f"{v:.2f}" for v in values)


def _reference_rows(scores: Mapping[str, Mapping[str, float]], keys: list[list[str]]) -> list[str]:
    """The identity and ``register`` rows: per column, the value of the first scored key that has it."""
    lines = []
    for row, label in (("identity", "identity (no motion)"), ("register", "`linereg.register`")):
        cells = [next((scores[k][row] for k in column if k in scores and row in scores[k]), None) for column in keys]
        if any(value is not None for value in cells):
            lines.append(f"| {label} | {_cells(cells)} |")
    return lines


def _cell_seeds(scores: Mapping[str, Mapping[str, float]], protocol: str, cell: str, pairs: str) -> dict[int, float]:
    """``{seed: Err_R}`` of a protocol's cell (``rpm_ours``) on a split: the ``recipe/<protocol>``
    runs, and for RPM-Net the shipped network as seed 0."""
    seeds = _seeds_of(scores, rf"recipe/{protocol}/{cell}_s{{seed}}/{pairs}")
    shipped = scores.get(f"{cell}_{protocol}/{pairs}", {}).get("model")
    return dict(sorted((({0: shipped} if shipped is not None else {}) | seeds).items()))


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
    """How often ``<backbone>_ours`` is at most ``<backbone>_cd`` on the splits (``{seed: Err_R}`` each)."""
    paired = [(mine, theirs) for mine, theirs in zip(ours, cd, strict=True) if set(mine) & set(theirs)]
    if not paired:
        return ""
    on_mean = sum(np.mean(list(mine.values())) <= np.mean(list(theirs.values())) for mine, theirs in paired)
    on_seeds = sum(
        sum(mine[seed] <= theirs[seed] for seed in set(mine) & set(theirs)) >= min(2, len(set(mine) & set(theirs)))
        for mine, theirs in paired
    )
    return (
        f"- `{backbone}_ours` <= `{backbone}_cd` beyond the protocol's test pairs: on the mean on {on_mean} of "
        f"{len(paired)} splits, on at least 2 of 3 seeds on {on_seeds}"
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the cached scores and table.md")
    parser.add_argument("--runs", type=Path, help="the runs of scripts/reproduce_generalization.sh")
    parser.add_argument("--register", action="store_true", help="also score linereg.register on the same pairs")
    args = parser.parse_args(argv)
    jobs = shipped_jobs()
    if args.runs is not None:
        mixed = {name: str(folder) for name, folder in run_folders(args.runs, "mixed_pairs").items()}
        shipped = {f"rpm_{loss}_airplane": f"rpm_{loss}_airplane" for loss in LOSSES}
        jobs += run_jobs(args.runs) + validation_jobs({**shipped, **mixed} if mixed else {})
        jobs += seed_jobs(args.runs) + choice_jobs(args.runs)
    jobs += object_jobs(args.runs)
    if args.runs is not None:
        jobs += real_choice_jobs(args.runs) + stretch_jobs(args.runs)
    scores = run_all(jobs, args.out, args.register)
    tables = (
        shipped_table,
        unseen_body_table,
        mixed_table,
        choice_table,
        real_choice_table,
        stretch_table,
        objects_table,
    )
    text = "\n".join(part for part in (table(scores) for table in tables) if part)
    (args.out / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
