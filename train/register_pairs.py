"""Register a folder of pairs: ``linereg-register pairs=<folder>`` writes one ``results.csv``, and resumes.

The folder holds ``<name>_src.<ext>`` and ``<name>_tgt.<ext>`` files, and ``<name>_gt.txt`` for
every pair or for none (:class:`~linereg.datasets.pairs_folder.FolderPairs` finds them). The pairs
run through :func:`linereg.register_many` (a network's forward in batches; ``refine=true`` finishes
its poses with the solver, and drops the network where it costs more than the solver alone unless
``keep_network=true``) in name order, and each result is appended to ``results.csv`` in the run
folder as it comes: the name, the 16 numbers of the transform (row-major), ``fitness``,
``inlier_rmse``, ``confident``, ``seconds``, the ``path`` taken (a network's: ``network``,
``polished network`` or ``solver``; ``method`` for any other method), the ``warnings`` (joined by
`` | ``), and with ground truth
``err_r_deg`` and ``err_t``. Run again in the same folder (``hydra.run.dir=<it>``), the command
skips the pairs ``results.csv`` holds.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

COLUMNS = ("name", "transform", "fitness", "inlier_rmse", "confident", "seconds", "path", "warnings")
LABELLED_COLUMNS = ("err_r_deg", "err_t")


def done_names(table: Path) -> set[str]:
    """The pairs ``table`` (a ``results.csv``) already holds; empty when it does not exist."""
    if not table.is_file():
        return set()
    with table.open(newline="") as stream:
        return {row["name"] for row in csv.DictReader(stream)}


def register_folder(cfg: DictConfig, out_dir: Path, method: Any) -> dict[str, Any]:
    """Register every pair of ``cfg.pairs`` not yet in ``out_dir/results.csv`` with ``method``
    (:func:`~linereg.train.register.method_config`) and append each result to it.

    Returns:
        ``{"pairs", "registered", "skipped", "confident", "table"}``.

    Raises:
        ValueError: the folder is missing, holds no pair, or pairs without both files.
    """
    from linereg.datasets.pairs_folder import FolderPairs
    from linereg.io import read_transform
    from linereg.registration.many import register_many

    folder = FolderPairs(Path(str(cfg.pairs)).expanduser())
    out_dir.mkdir(parents=True, exist_ok=True)
    table = out_dir / "results.csv"
    skipped = done_names(table)
    names = [name for name in folder.names if name not in skipped]
    columns = COLUMNS + (LABELLED_COLUMNS if folder.labelled else ())
    refine = OmegaConf.to_container(cfg.refine) if OmegaConf.is_config(cfg.refine) else cfg.refine
    options = {"refine": refine} if cfg.refine else {}
    results = register_many(
        [folder.files[name] for name in names],
        method=method,
        device=cfg.device,
        fitness_threshold=cfg.fitness_threshold,
        progress=cfg.progress,
        keep_network=cfg.keep_network,
        **options,
    )
    confident = 0
    with table.open("a", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=columns)
        if not skipped:
            writer.writeheader()
        for name, result in zip(names, results, strict=True):
            row = _row(name, result)
            if folder.labelled:
                row.update(_errors(result.transformation, read_transform(folder.root / f"{name}_gt.txt")))
            writer.writerow(row)
            stream.flush()
            confident += bool(result.confident)
    return {
        "pairs": len(folder.names),
        "registered": len(names),
        "skipped": len(skipped),
        "confident": confident,
        "table": table,
    }


def _row(name: str, result) -> dict[str, Any]:
    """A ``results.csv`` row of one result."""
    return {
        "name": name,
        "transform": " ".join(f"{value:.9g}" for value in result.transformation.ravel()),
        "fitness": f"{result.fitness:.6f}",
        "inlier_rmse": f"{result.inlier_rmse:.6g}",
        "confident": str(bool(result.confident)).lower(),
        "seconds": f"{result.seconds:.3f}",
        "path": result.info.get("path", "method"),
        "warnings": " | ".join(result.info.get("warnings", ())),
    }


def _errors(transform: np.ndarray, truth: np.ndarray) -> dict[str, str]:
    """``err_r_deg`` and ``err_t`` (input units) of ``transform`` against ``truth`` (both ``(4, 4)``)."""
    cosine = (np.trace(truth[:3, :3].T @ transform[:3, :3]) - 1.0) / 2.0
    rotation = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return {"err_r_deg": f"{rotation:.6f}", "err_t": f"{np.linalg.norm(transform[:3, 3] - truth[:3, 3]):.6g}"}
