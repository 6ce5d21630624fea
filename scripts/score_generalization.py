"""Score networks beyond their own test split: each protocol's generalization splits, one table each.

    python scripts/score_generalization.py --out outputs/generalization --register
    python scripts/score_generalization.py --out <dir> --runs outputs/generalization_runs --register

The shipped networks ``rpm_{gt,cd,ours}_<protocol>`` of :mod:`linereg.pretrained` are scored by
``linereg-evaluate`` on their protocol's test pairs (``in-protocol``) and on every generalization
split of :data:`SPLITS` (a dataset config of ``configs/dataset/``). With ``--runs`` (the folder of
``scripts/reproduce_generalization.sh``), also:

* ``unseen_body/<body>/<cell>_s<seed>``: each leave-one-body-out run on the body it never saw;
* ``mixed_pairs/<cell>_s<seed>``: each run trained on both Airplane pair types, on the Airplane
  splits and on validation pairs of both pair types (fresh poses of training shapes: the choice);
* ``human_choice/<settings>_s<seed>``: RPM-Ours on Human at other line-loss settings, on the
  validation pairs (fresh poses of every training pair: the choice) and the test pairs;
* ``recipe/<protocol>/<cell>_s<seed>``: the protocol's own cells (any backbone) at other seeds, on
  its splits (the shipped RPM-Net is seed 0);
* ``real_choice/<cell>_test_gap_s<seed>``, ``dcp_choice/<cell>_easy_only_s<seed>``: Real without
  easier pairs first, DCP on Airplane without its full-range stage, beside the recipe's runs, on
  validation pairs (the choice) and test pairs (:data:`SCHEDULE_CHOICES`);
* ``human_stretch/<cell>_stretch0.2_s<seed>``: the Human cells trained on stretched pairs, beside
  the recipe's, on Human's validation pairs (the choice), test pairs and other splits;
* ``objects/<cell>_s<seed>``, ``objects_and_rooms/<cell>_s<seed>`` and the other steps of
  :data:`GENERAL_DATA`: networks trained on every object (``dataset=objects``), and on the room
  frames too (``dataset=objects_and_rooms``, at other gaps and schedules), with
  the shipped general model ``rpm_ours_objects`` (seed 0 of :data:`GENERAL_SHIPPED`) and every
  shipped protocol network, on every split of every protocol (:data:`OBJECT_SPLITS`), and each
  protocol's RPM-CD at its other seeds on the splits its protocol never trained on.

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

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from scripts._generalization_tables import (  # noqa: E402
    GENERAL,
    GENERAL_DATA,
    GENERAL_VALIDATION,
    HUMAN_VALIDATION_PAIRS,
    IN_PROTOCOL,
    LOSSES,
    MIXED_SPLITS,
    OBJECT_SPLITS,
    PROTOCOL_DATA,
    SCHEDULE_CHOICES,
    SPLITS,
    STRETCH_SPLITS,
    TABLES,
    VALIDATION,
    VALIDATION_PAIRS,
)

RUN_NAME = re.compile(r".+_s\d+$")  # <cell or settings>_s<seed>


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


def _recipe_rows(runs: Path, protocol: str, backbone: str = "rpm") -> dict[str, str]:
    """``{row: checkpoint}`` of the protocol's CD and Ours cells of a backbone under the recipe: the
    ``recipe/<protocol>`` runs, and for RPM-Net the shipped networks as seed 0."""
    rows = {f"recipe/rpm_{loss}_s0": f"rpm_{loss}_{protocol}" for loss in ("cd", "ours")} if backbone == "rpm" else {}
    for name, folder in run_folders(runs / "recipe", protocol).items():
        if Path(name).name.startswith((f"{backbone}_cd_s", f"{backbone}_ours_s")):
            rows[f"recipe/{Path(name).name}"] = str(folder)
    return rows


def schedule_jobs(runs: Path) -> list[Job]:
    """Each :data:`SCHEDULE_CHOICES` step: the recipe's runs and the step's runs on validation and test pairs."""
    jobs = []
    for step, choice in SCHEDULE_CHOICES.items():
        rows = _recipe_rows(runs, choice.protocol, choice.backbone)
        rows.update({f"{choice.alternative}/{Path(n).name}": str(f) for n, f in run_folders(runs, step).items()})
        for row, checkpoint in rows.items():
            for split in ("val", "test"):
                dataset, subset = (choice.val_dataset, choice.val_pairs) if split == "val" else (None, None)
                key = f"{choice.protocol}_{split}" + (f"_{dataset}" if dataset else "")
                jobs.append(Job(f"{step}/{row}/{split}", checkpoint, dataset, split, key, subset))
    return jobs


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


def _pairs_key(protocol: str, dataset: str) -> str:
    """The ``register`` cache of a dataset's test pairs (a protocol's own data: ``<protocol>_test``)."""
    return f"{protocol}_test" if dataset in PROTOCOL_DATA else f"{protocol}_{dataset}"


def object_jobs(runs: Path | None) -> list[Job]:
    """The general model, the runs of :data:`GENERAL_DATA` and every shipped protocol network on every split;
    each protocol's RPM-CD at its other seeds (``recipe/<protocol>/rpm_cd_s<seed>``) on the others."""
    from linereg import pretrained

    rows = {f"rpm_{loss}_{protocol}": f"rpm_{loss}_{protocol}" for protocol in SPLITS for loss in LOSSES}
    if pretrained.is_name(GENERAL):
        rows[GENERAL] = GENERAL
    if runs is not None:
        for step in GENERAL_DATA:
            rows.update({name: str(folder) for name, folder in run_folders(runs, step).items()})
    jobs = [
        Job(f"general/{row}/{dataset}", checkpoint, dataset, "test", _pairs_key(protocol, dataset))
        for row, checkpoint in rows.items()
        for protocol, _, dataset in OBJECT_SPLITS
    ]
    if runs is not None:  # each protocol's RPM-CD at its other seeds, on the splits it never trained on
        for protocol in SPLITS:
            for name, folder in run_folders(runs / "recipe", protocol).items():
                if Path(name).name.startswith("rpm_cd_s"):
                    jobs += [
                        Job(f"general/recipe/{name}/{dataset}", str(folder), dataset, "test", _pairs_key(own, dataset))
                        for own, _, dataset in OBJECT_SPLITS
                        if not (own == protocol and dataset in PROTOCOL_DATA)
                    ]
    return jobs


def general_validation_jobs(runs: Path) -> list[Job]:
    """The runs of :data:`GENERAL_DATA` on the validation pairs of :data:`GENERAL_VALIDATION`."""
    return [
        Job(f"general_val/{name}/{dataset}", str(folder), dataset, "val", f"general_val_{dataset}")
        for step in GENERAL_DATA
        for name, folder in run_folders(runs, step).items()
        for _, dataset in GENERAL_VALIDATION
    ]


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
        jobs += schedule_jobs(args.runs) + stretch_jobs(args.runs) + general_validation_jobs(args.runs)
    scores = run_all(jobs, args.out, args.register)
    text = "\n".join(part for part in (table(scores) for table in TABLES) if part)
    (args.out / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
