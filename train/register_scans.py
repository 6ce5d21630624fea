"""Register a folder of scans into one frame: ``linereg-register scans=<folder>``, and resume.

The folder's point-cloud files, in natural name order (``scan_2`` before ``scan_10``), go through
:func:`linereg.register_scans` (``mode=sequence`` or ``unordered``, any ``method=``, ``refine=`` with a
network). The run folder receives:

* ``edges.csv``: one row per registered pair, appended as each is registered: ``source``, ``target``
  (scan names; the transform maps the source into the target's frame), ``kind``, the 16 numbers of
  ``transform`` (row-major), ``fitness``, ``inlier_rmse``, ``confident``, ``seconds``, ``warnings``
  (joined by `` | ``) and, once the pose graph has run, ``kept``;
* ``poses.txt``: one line per placed scan, its name and the 16 numbers of its pose into the first
  scan's frame; a ``#`` line with the reason for each scan left out;
* ``scans.csv``: per scan ``name``, ``placed``, ``verdict`` and, with ``gt=``, ``err_r_deg`` and ``err_t``
  against the ground truth relative to the first scan;
* ``merged.ply``: the placed scans together, one point per voxel.

``gt=`` takes a Stanford ``.conf`` (scans matched by file name), a 3DMatch/Redwood ``.log``
trajectory (one block per scan, in order) or a folder of 4x4 files (one per scan, in natural name
order): each scan's pose in a common frame. Run again in the same folder (``hydra.run.dir=<it>``),
the command registers only the pairs ``edges.csv`` lacks.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from linereg.io import POINT_CLOUD_SUFFIXES

COLUMNS = ("source", "target", "kind", "transform", "fitness", "inlier_rmse", "confident", "seconds", "warnings")


def scan_files(folder: Any, exclude: tuple[Path, ...] = ()) -> list[Path]:
    """The point-cloud files of ``folder`` in natural name order, at least two.

    Raises:
        ValueError: not a folder, or fewer than two point-cloud files in it.
    """
    from linereg.datasets.scan_folder import list_scans

    root = Path(str(folder)).expanduser()
    if not root.is_dir():
        raise ValueError(f"scans={folder}: not a folder")
    files = list_scans(root, exclude)
    if len(files) < 2:
        raise ValueError(
            f"scans={folder}: {len(files)} point-cloud file(s); multiway registration needs at least 2 "
            f"({', '.join(POINT_CLOUD_SUFFIXES)})"
        )
    return files


def read_gt_poses(path: Any, files: list[Path]) -> list[np.ndarray]:
    """Each scan's ``(4, 4)`` ground-truth pose in the first scan's frame, from ``gt=`` (see the module docstring).

    Raises:
        ValueError, FileNotFoundError: a missing or malformed file, or one that does not cover every scan.
    """
    from linereg.datasets.formats import read_conf, read_log
    from linereg.datasets.scan_folder import natural_key
    from linereg.io import read_transform

    source = Path(str(path)).expanduser()
    if not source.exists():
        raise FileNotFoundError(f"gt={path}: no such file or folder")
    if source.is_dir():
        truths = [file for file in sorted(source.iterdir(), key=lambda p: natural_key(p.name)) if file.is_file()]
        poses = [read_transform(file) for file in truths]
    elif source.suffix.lower() == ".conf":
        found = read_conf(source)
        by_stem = {Path(name).stem: pose for name, pose in found.items()}
        missing = [file.name for file in files if file.stem not in by_stem]
        if missing:
            raise ValueError(f"gt={path}: no pose for {', '.join(missing)}")
        poses = [by_stem[file.stem] for file in files]
    elif source.suffix.lower() == ".log":
        poses = [entry.transform for entry in read_log(source)]
    else:
        raise ValueError(f"gt={path}: expected a .conf, a .log or a folder of 4x4 files")
    if len(poses) != len(files):
        raise ValueError(f"gt={path}: {len(poses)} poses for {len(files)} scans")
    first = np.linalg.inv(poses[0])
    return [first @ pose for pose in poses]


def pose_errors(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """``(rotation error in degrees, translation error)`` of ``pose`` against ``truth`` (both ``(4, 4)``)."""
    cosine = (np.trace(truth[:3, :3].T @ pose[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))), float(np.linalg.norm(pose[:3, 3] - truth[:3, 3]))


def done_edges(table: Path, names: list[str]) -> dict[tuple[int, int], Any]:
    """The edges ``table`` (an ``edges.csv``) already holds, by ``(source, target)`` index; empty when absent."""
    from linereg.registration.multiway import Edge

    if not table.is_file():
        return {}
    index = {name: k for k, name in enumerate(names)}
    found = {}
    with table.open(newline="") as stream:
        for row in csv.DictReader(stream):
            if row["source"] not in index or row["target"] not in index:
                continue
            source, target = index[row["source"]], index[row["target"]]
            found[source, target] = Edge(
                source,
                target,
                np.array([float(value) for value in row["transform"].split()]).reshape(4, 4),
                float(row["fitness"]),
                float(row["inlier_rmse"]),
                row["confident"] == "true",
                float(row["seconds"]),
                row["kind"],
                warnings=tuple(filter(None, row["warnings"].split(" | "))),
            )
    return found


def _row(names: list[str], edge) -> dict[str, str]:
    """An ``edges.csv`` row of one edge (``kept`` left to the caller)."""
    return {
        "source": names[edge.source],
        "target": names[edge.target],
        "kind": edge.kind,
        "transform": " ".join(f"{value:.9g}" for value in edge.transformation.ravel()),
        "fitness": f"{edge.fitness:.6f}",
        "inlier_rmse": f"{edge.inlier_rmse:.6g}",
        "confident": str(bool(edge.confident)).lower(),
        "seconds": f"{edge.seconds:.3f}",
        "warnings": " | ".join(edge.warnings),
    }


def register_folder_scans(cfg: DictConfig, out_dir: Path, method: Any) -> dict[str, Any]:
    """Register the scans of ``cfg.scans`` with ``method`` (:func:`~linereg.train.register.method_config`)
    and write the outputs of the module docstring into ``out_dir``.

    Returns:
        ``{"scans", "placed", "edges", "registered", "resumed", "seconds", "seconds_per_edge", "errors"}``
        (``errors``: the largest rotation and translation errors with ``gt=``, else ``None``).

    Raises:
        ValueError, FileNotFoundError: a bad folder, ground truth, scan or option.
    """
    from linereg.registration.multiway import MultiwayOptions, register_scans

    gt_path = Path(str(cfg.gt)).expanduser().resolve() if cfg.gt else None
    files = scan_files(cfg.scans, () if gt_path is None else (gt_path,))
    names = [file.stem for file in files]
    truths = read_gt_poses(cfg.gt, files) if cfg.gt else None
    options = MultiwayOptions(**(OmegaConf.to_container(cfg.multiway) if cfg.multiway else {}))
    refine = OmegaConf.to_container(cfg.refine) if OmegaConf.is_config(cfg.refine) else cfg.refine
    table = out_dir / "edges.csv"
    registered = done_edges(table, names)

    def append(edge) -> None:
        fresh = not table.is_file()
        out_dir.mkdir(parents=True, exist_ok=True)
        with table.open("a", newline="") as stream:
            writer = csv.DictWriter(stream, fieldnames=COLUMNS)
            if fresh:
                writer.writeheader()
            writer.writerow(_row(names, edge))

    result = register_scans(
        files,
        method=method,
        mode=cfg.mode,
        device=cfg.device,
        options=options,
        registered=registered,
        on_edge=append,
        progress=cfg.progress,
        fitness_threshold=cfg.fitness_threshold,
        **({"refine": refine} if cfg.refine else {}),
    )
    errors = _write_outputs(out_dir, result, truths)
    registered_seconds = [edge.seconds for edge in result.edges]
    return {
        "scans": len(files),
        "placed": sum(result.placed),
        "edges": len(result.edges),
        "registered": result.info["registered"],
        "resumed": result.info["resumed"],
        "seconds": result.seconds,
        "seconds_per_edge": float(np.mean(registered_seconds)) if registered_seconds else 0.0,
        "errors": errors,
    }


def _write_outputs(out_dir: Path, result, truths: list[np.ndarray] | None) -> tuple[float, float] | None:
    """``edges.csv`` (rewritten with ``kept``), ``poses.txt``, ``scans.csv`` and ``merged.ply``; the largest
    errors against ``truths`` among the placed scans (``None`` without ground truth or placed scans)."""
    from linereg.io import write_point_cloud

    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / "edges.csv").open("w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=(*COLUMNS, "kept"))
        writer.writeheader()
        for edge in result.edges:
            writer.writerow({**_row(result.names, edge), "kept": str(edge.kept).lower()})
    lines = []
    for name, pose, verdict in zip(result.names, result.poses, result.verdicts, strict=True):
        numbers = None if pose is None else " ".join(f"{value:.9g}" for value in pose.ravel())
        lines.append(f"# {name}: {verdict}" if pose is None else f"{name} {numbers}")
    (out_dir / "poses.txt").write_text("\n".join(lines) + "\n")
    rows, worst = [], None
    for k, name in enumerate(result.names):
        row = {"name": name, "placed": str(result.placed[k]).lower(), "verdict": result.verdicts[k]}
        if truths is not None:
            rotation, translation = pose_errors(result.poses[k], truths[k]) if result.placed[k] else (np.nan, np.nan)
            row.update(err_r_deg=f"{rotation:.6f}", err_t=f"{translation:.6g}")
            if result.placed[k]:
                worst = (max(rotation, worst[0]), max(translation, worst[1])) if worst else (rotation, translation)
        rows.append(row)
    with (out_dir / "scans.csv").open("w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    if len(result.merged) >= 1:
        write_point_cloud(out_dir / "merged.ply", result.merged)
    return worst
