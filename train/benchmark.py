"""Benchmark registration methods on labelled pairs: the paper's Table 1 and Dragon alpha-recall.

``python -m train.benchmark benchmark=<human|airplane|dragon|3dmatch|folder> methods=[...]
pairs=N out=<dir>`` (Hydra, ``configs/benchmark.yaml``; ``benchmark=<a folder path>`` is
short for ``benchmark=folder benchmark.root=<path>``). Every method runs on every pair;
the errors of the paper's Eq. (``Err_R`` in degrees, ``Err_t`` and ``Err_pw`` in l1 and l2, on
the pair's source points, :func:`linereg.metrics.registration_errors`) and the time are kept
per pair and method, then written as ``results.json``, ``table.md`` (mean values as the
paper's Table 1, then medians, then time and success rates) and ``alpha_recall.png``.

Pair sources (:data:`PAIR_SOURCES`, each a function returning a list of labelled
:class:`~linereg.structures.PairSample`, deterministic given ``seed``; default paths are in the
shared data folder, :func:`linereg.paths.shared_data_dir`):

``human``
    The paper's Human protocol (``datasets.protocol``, preset ``human``) on the SMPL/SMPL-X
    bodies of ``meshes/odedstein/human``: source = the visible part from one of 50 cameras
    orbiting the body, target = the whole body, 1024 points each, pair scaled into
    ``[-1, 1]^3``, target moved by the composite transform (Euler angles U[0, 45] deg,
    translation U[-0.2, 0.2]^3).
``airplane``
    The paper's Airplane protocol (preset ``airplane``) on the ModelNet40 airplanes of
    ``modelnet40_normal_resampled``: source and target are views from two cameras (18 orbit
    stops; the second turned by U[-75, 75] deg), same points, scaling and transform.
``dragon``
    The Dragon experiment: ONE pair from ``meshes/stanford_lowres/dragon.ply`` built with the
    Human protocol and no pose (source = the view from orbit stop ``view``, target = the whole
    model, 1024 points each, in ``[-1, 1]^3``), then ``pairs`` (100) random poses of the target
    drawn from the paper's composite transform (``max_angle_deg``, ``max_translation``).
``3dmatch``
    Real scans with ground truth: 3DMatch redkitchen fragments 0 and 4 (``gt.log``: source =
    fragment 4, target = fragment 0) and the GeoTransformer demo pair (``p_ref = gt @ p_src``),
    2048 points each, scaled into ``[-5, 5]^3`` as the paper's Real dataset.
``folder``
    The user's pairs ``<name>_src/_tgt.<ext>`` + ``<name>_gt.txt`` (``datasets.pairs_folder``).
``dataset``
    Any labelled dataset config of :func:`linereg.datasets.build_dataset`.
``run``
    The pairs of one split (default ``test``) of a training run's dataset, read from the run's
    checkpoint: the classical methods scored on exactly the pairs a trained model was
    evaluated on (``scripts/reproduce.sh``).

When a source holds more pairs than requested, ``pairs`` of them are drawn at random without
replacement (seeded) and kept in index order.

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
from linereg.datasets import build_dataset
from linereg.datasets.protocol import ScanSettings, Shape, ShapeViews, build_protocol, finish_scan_pair
from linereg.datasets.threedmatch import ThreeDMatchPairs
from linereg.train import baselines, solvers  # noqa: F401  (importing registers the baselines and adam_loss / svd_irls)
from linereg.train.checkpoint import find_checkpoint, load_checkpoint
from linereg.train.curriculum import build_split
from linereg.train.methods import METHODS, Method, build_method
from tqdm.auto import tqdm

from linereg.io import read_mesh
from linereg.metrics import ERROR_KEYS, alpha_recall, paper_table, registration_errors, summarize
from linereg.paths import shared_data_dir
from linereg.random_poses import random_transform_paper
from linereg.registry import Registry
from linereg.se3 import transform_normals, transform_points
from linereg.structures import PairSample

PAIR_SOURCES: Registry[list[PairSample]] = Registry("benchmark pair source")

SUCCESS_THRESHOLDS_DEG = (1.0, 5.0)
ABSOLUTE_ALPHA_RANGE = (1e-4, 1.0)
RELATIVE_ALPHA_RANGE = (3e-5, 0.3)
ALPHA_STEPS = 201


def _data_path(root: str | Path | None, default: str) -> Path:
    """``root``, else ``default``; a relative path that does not exist is taken in the shared data."""
    base = shared_data_dir()
    if root is not None:
        path = Path(root).expanduser()
        return path if path.is_absolute() or path.exists() or base is None else base / path
    if base is None:
        raise FileNotFoundError(
            f"the shared data folder was not found (set $LINEREG_SHARED_DATA); pass the path of {default}"
        )
    return base / default


def select_indices(total: int, num_pairs: int | None, seed: int) -> list[int]:
    """``num_pairs`` distinct indices in ``[0, total)`` drawn with ``seed``, sorted (all if ``None``).

    Raises:
        ValueError: ``num_pairs < 1``.
    """
    if num_pairs is not None and num_pairs < 1:
        raise ValueError(f"pairs must be >= 1 (or None for all), got {num_pairs}")
    if num_pairs is None or num_pairs >= total:
        return list(range(total))
    return sorted(int(i) for i in np.random.default_rng(seed).choice(total, num_pairs, replace=False))


def _labelled(pairs: Sequence[PairSample], where: str) -> list[PairSample]:
    """``pairs`` as a list; ValueError when one has no ground truth."""
    unlabelled = [i for i, pair in enumerate(pairs) if pair.gt_transform is None]
    if unlabelled:
        raise ValueError(f"{where}: a benchmark needs ground truth, pairs {unlabelled[:5]} have none")
    return list(pairs)


@PAIR_SOURCES.register("dataset")
def dataset_pairs(dataset: Mapping[str, Any], *, pairs: int | None = None, seed: int = 0) -> list[PairSample]:
    """``pairs`` labelled pairs of any dataset config (see :func:`linereg.datasets.build_dataset`).

    Args:
        dataset: ``{name: <registered dataset>, **kwargs}``.
        pairs: number of pairs (``None``: all), drawn with ``seed`` when fewer than the dataset.
        seed: seed of the draw.

    Returns:
        List of :class:`PairSample` with ``gt_transform``.
    """
    built = build_dataset(dataset)
    chosen = [built[i] for i in select_indices(len(built), pairs, seed)]
    return _labelled(chosen, f"dataset {dict(dataset).get('name')!r}")


@PAIR_SOURCES.register("run")
def run_pairs(*, run: str, split: str = "test", pairs: int | None = None, seed: int = 0) -> list[PairSample]:
    """The ``split`` pairs of a training run's dataset (its checkpoint's resolved config).

    Args:
        run: run folder or checkpoint file (``python -m train`` output).
        split: dataset split (``train``, ``val`` or ``test``).
        pairs: number of pairs (``None``: all).
        seed: seed of the draw.
    """
    config = load_checkpoint(find_checkpoint(run))["config"]
    built = build_split(config["dataset"], split, progress=False)
    if built is None:
        raise ValueError(f"run {run}: its dataset has no {split!r} split")
    chosen = [built[i] for i in select_indices(len(built), pairs, seed)]
    return _labelled(chosen, f"run {run} ({split!r} split)")


@PAIR_SOURCES.register("human")
def human_pairs(
    *, pairs: int | None = 20, seed: int = 0, root: str | None = None, num_points: int = 1024
) -> list[PairSample]:
    """The paper's Human protocol on a folder of body meshes (module docstring).

    Args:
        pairs: number of pairs among 50 views per body (``None``: all).
        seed: seed of the pairs' transforms and of the draw.
        root: mesh folder (default ``<shared>/meshes/odedstein/human``).
        num_points: points per cloud.
    """
    dataset = {
        "name": "mesh_folder",
        "root": str(_data_path(root, "meshes/odedstein/human")),
        "protocol": {"name": "human", "num_points": num_points},
        "split": "all",
        "seed": seed,
    }
    return dataset_pairs(dataset, pairs=pairs, seed=seed)


@PAIR_SOURCES.register("airplane")
def airplane_pairs(
    *, pairs: int | None = 20, seed: int = 0, root: str | None = None, num_points: int = 1024
) -> list[PairSample]:
    """The paper's Airplane protocol on ModelNet40 airplanes (module docstring).

    Args:
        pairs: number of pairs among 18 views per airplane (``None``: all).
        seed: seed of the pairs' cameras and transforms and of the draw.
        root: ModelNet40 folder (default ``<shared>/modelnet40_normal_resampled``).
        num_points: points per cloud.
    """
    dataset = {
        "name": "modelnet40",
        "root": str(_data_path(root, "modelnet40_normal_resampled")),
        "categories": "airplane",
        "protocol": {"name": "airplane", "num_points": num_points},
        "split": "all",
        "seed": seed,
    }
    return dataset_pairs(dataset, pairs=pairs, seed=seed)


@PAIR_SOURCES.register("dragon")
def dragon_pairs(
    *,
    pairs: int | None = 100,
    seed: int = 0,
    mesh: str | None = None,
    view: int = 0,
    num_points: int = 1024,
    max_angle_deg: float = 45.0,
    max_translation: float = 0.2,
) -> list[PairSample]:
    """One source/target pair of a mesh under ``pairs`` random initial poses (module docstring).

    Args:
        pairs: number of poses (``None``: 100).
        seed: seed of the base pair and of the poses.
        mesh: mesh file (default ``<shared>/meshes/stanford_lowres/dragon.ply``).
        view: orbit stop (of 50) of the source camera.
        num_points: points per cloud.
        max_angle_deg: bound of the three Euler angles of each pose.
        max_translation: bound of each translation component of each pose.

    Returns:
        ``pairs`` pairs sharing the source; ``gt_transform`` is the pose of the target.
    """
    path = _data_path(mesh, "meshes/stanford_lowres/dragon.ply")
    protocol = build_protocol({"name": "human", "num_points": num_points, "max_angle_deg": 0.0, "max_translation": 0.0})
    shape = Shape(name=path.stem, mesh=read_mesh(path), meta={"file": str(path)})
    base = protocol.make_pair(ShapeViews(shape), view, np.random.default_rng([seed, view]))
    poses = random_transform_paper(
        100 if pairs is None else pairs,
        seed,
        max_angle_deg=max_angle_deg,
        max_translation=max_translation,
        dtype=torch.float64,
    )
    tgt_xyz = torch.from_numpy(base.tgt_xyz.astype(np.float64))
    tgt_normals = torch.from_numpy(base.tgt_normals.astype(np.float64))
    return [
        PairSample(
            src_xyz=base.src_xyz,
            tgt_xyz=transform_points(pose, tgt_xyz).numpy().astype(np.float32),
            src_normals=base.src_normals,
            tgt_normals=transform_normals(pose, tgt_normals).numpy().astype(np.float32),
            gt_transform=pose.numpy().astype(np.float32),
            meta={**base.meta, "dataset": "dragon", "shape": path.stem, "index": index, "pose": index},
        )
        for index, pose in enumerate(poses)
    ]


@PAIR_SOURCES.register("3dmatch")
def threedmatch_pairs(
    *,
    pairs: int | None = None,
    seed: int = 0,
    root: str | None = None,
    gt_log: str | None = None,
    demo: str | None = "3dmatch/geotransformer_demo/demo",
    num_points: int = 2048,
    half_extent: float | None = 5.0,
) -> list[PairSample]:
    """Real 3DMatch pairs with ground truth (module docstring).

    Args:
        pairs: number of pairs (``None``: all).
        seed: seed of the subsampling and of the draw.
        root: fragment folder (default ``<shared>/3dmatch/redkitchen_0_4``); pairs of
            ``gt_log`` whose fragments are absent are skipped.
        gt_log: the scene's ``gt.log`` (default: the redkitchen log of the GeoTransformer
            benchmark files in the shared data).
        demo: folder with ``src.npy``, ``ref.npy``, ``gt.npy`` (``p_ref = gt @ p_src``) added
            as one more pair, or ``None``.
        num_points: points per cloud.
        half_extent: pairs are scaled into ``[-half_extent, half_extent]^3`` (``None``: metres).
    """
    fragments = ThreeDMatchPairs(
        _data_path(root, "3dmatch/redkitchen_0_4"),
        gt_log=_data_path(gt_log, "3dmatch/geotransformer_demo/benchmarks/3DMatch/7-scenes-redkitchen/gt.log"),
        skip_missing=True,
        num_points=num_points,
        half_extent=half_extent,
        seed=seed,
    )
    found = [fragments[i] for i in range(len(fragments))]
    if demo is not None:
        folder = _data_path(demo, "3dmatch/geotransformer_demo/demo")
        settings = ScanSettings(num_points=num_points, half_extent=half_extent)
        found.append(
            finish_scan_pair(
                np.load(folder / "src.npy"),
                np.load(folder / "ref.npy"),
                np.load(folder / "gt.npy"),
                settings,
                np.random.default_rng([seed, len(found)]),
                src_viewpoint=np.zeros(3),
                tgt_viewpoint=np.zeros(3),
                meta={"dataset": "geotransformer_demo", "index": len(found), "file": str(folder / "src.npy")},
            )
        )
    return _labelled([found[i] for i in select_indices(len(found), pairs, seed)], "3dmatch")


@PAIR_SOURCES.register("folder")
def folder_pairs(
    *,
    root: str,
    pairs: int | None = None,
    seed: int = 0,
    num_points: int | None = None,
    half_extent: float | None = None,
) -> list[PairSample]:
    """The user's labelled pairs in a folder (see :mod:`linereg.datasets.pairs_folder`).

    Args:
        root: the folder of ``<name>_src``, ``<name>_tgt`` and ``<name>_gt.txt`` files.
        pairs: number of pairs (``None``: all).
        seed: seed of the draw.
        num_points: FPS size of each cloud (``None``: every point).
        half_extent: scale each pair into ``[-half_extent, half_extent]^3`` (``None``: file units).
    """
    dataset = {
        "name": "pairs_folder",
        "root": str(Path(root).expanduser()),
        "num_points": num_points,
        "half_extent": half_extent,
        "seed": seed,
    }
    return dataset_pairs(dataset, pairs=pairs, seed=seed)


@PAIR_SOURCES.register("partial_vs_whole")
def partial_vs_whole_source(
    *,
    root: str,
    pairs: int | None = 40,
    seed: int = 0,
    patterns: Sequence[str] | None = None,
    **settings: Any,
) -> list[PairSample]:
    """A partial view against the whole shape, for any folder of meshes or point files
    (:mod:`linereg.datasets.partial_vs_whole`: source = a hidden-point-removal view of 1024 points,
    target = 2048 random points of the whole shape, both in ``[-1, 1]^3``, the paper's pose).

    Args:
        root: the folder (a relative path that does not exist is taken in the shared data).
        pairs: number of pairs (``None``: 40); pair ``i`` uses shape ``i mod S``.
        seed: seed of every draw.
        patterns: glob patterns under ``root`` (e.g. ``["airplane/*.txt"]``).
        **settings: fields of :class:`~linereg.datasets.partial_vs_whole.PartialVsWholeSettings`.
    """
    from linereg.datasets.partial_vs_whole import PartialVsWholeSettings, partial_vs_whole_pairs

    return partial_vs_whole_pairs(
        _data_path(root, root),
        pairs=40 if pairs is None else pairs,
        seed=seed,
        patterns=None if patterns is None else list(patterns),
        settings=PartialVsWholeSettings(**settings),
    )


def object_diameter(points: np.ndarray) -> float:
    """Twice the largest distance of a point of ``points (N, 3)`` from their centroid."""
    points = np.asarray(points, dtype=np.float64)
    return 2.0 * float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())


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
        methods: display name -> method (see :mod:`linereg.train.methods`).
        progress: show a tqdm bar.
        journal: a JSON-lines file that receives every record as soon as it is measured;
            records already in it (same pair and method) are reused, so an interrupted run
            resumes where it stopped.

    Returns:
        One record per (pair, method), pairs outer: ``pair`` (position in ``pairs``),
        ``method``, ``seconds``, every key of :data:`linereg.metrics.ERROR_KEYS` (float),
        ``diameter`` (:func:`object_diameter` of the target), ``transform`` and
        ``gt_transform`` (4x4 lists), ``meta`` (the pair's) and ``info`` (the method's).

    Raises:
        ValueError: no pairs, no methods, or a pair without ground truth.
        RuntimeError: a method failed; the message names the method and the pair.
    """
    if not pairs or not methods:
        raise ValueError(f"need at least one pair and one method, got {len(pairs)} and {len(methods)}")
    _labelled(pairs, "run_benchmark")
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
                records.append(done[(index, name)])
                bar.update()
                continue
            bar.set_postfix(method=name, pair=index)
            try:
                result = method(pair.src_xyz, pair.tgt_xyz, pair.src_normals, pair.tgt_normals)
            except Exception as error:
                raise RuntimeError(f"method {name!r} failed on pair {index} ({pair.meta}): {error}") from error
            errors = registration_errors(
                torch.as_tensor(result.transform, dtype=torch.float64)[None],
                torch.as_tensor(pair.gt_transform, dtype=torch.float64)[None],
                torch.as_tensor(pair.src_xyz, dtype=torch.float64)[None],
            )
            records.append(
                {
                    "pair": index,
                    "method": name,
                    "seconds": float(result.seconds),
                    **{key: float(errors[key][0]) for key in ERROR_KEYS},
                    "diameter": object_diameter(pair.tgt_xyz),
                    "transform": np.asarray(result.transform, dtype=np.float64).tolist(),
                    "gt_transform": np.asarray(pair.gt_transform, dtype=np.float64).tolist(),
                    "meta": _jsonable(pair.meta),
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


def summarize_records(records: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Per method: mean and median of every error and of the time, pair count, success rates.

    Returns:
        ``{method: {"<key>_mean", "<key>_median" for the ERROR_KEYS and "seconds", "pairs",
        "success_1deg", "success_5deg"}}`` (success = fraction of pairs with ``Err_R`` below).
    """
    summary = {}
    for method, rows in _by_method(records).items():
        columns = {key: np.array([row[key] for row in rows], dtype=np.float64) for key in (*ERROR_KEYS, "seconds")}
        stats = summarize(columns)
        stats["pairs"] = len(rows)
        for threshold in SUCCESS_THRESHOLDS_DEG:
            stats[f"success_{threshold:g}deg"] = float(np.mean(columns["err_r_deg"] < threshold))
        summary[method] = stats
    return summary


def recall_curves(
    records: Sequence[Mapping[str, Any]], alphas: np.ndarray, *, relative_alpha: bool = False
) -> dict[str, list[float]]:
    """Alpha-recall of every method over ``alphas (A,)`` (l2 pointwise error below alpha)."""
    curves = {}
    for method, rows in _by_method(records).items():
        errors = np.array([row["err_pw_l2"] for row in rows], dtype=np.float64)
        if relative_alpha:
            errors = errors / np.array([row["diameter"] for row in rows], dtype=np.float64)
        curves[method] = alpha_recall(errors, alphas).tolist()
    return curves


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
        ``relative``, ``recall`` per method) and ``records``.
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
    paths = {"json": out / "results.json", "table": out / "table.md", "plot": out / "alpha_recall.png"}
    content = {
        "settings": _jsonable(dict(settings or {})),
        "summary": summary,
        "alpha_recall": {"alphas": alphas.tolist(), "relative": relative_alpha, "recall": curves},
        "records": [_jsonable(record) for record in records],
    }
    paths["json"].write_text(json.dumps(content, indent=1, allow_nan=True))
    paths["table"].write_text(markdown_tables(summary))
    _plot(paths["plot"], alphas, curves, summary, relative_alpha)
    return paths


def build_methods(selected: Sequence[str], zoo: Mapping[str, Mapping[str, Any]]) -> dict[str, Method]:
    """Methods to run, by display name: an entry of ``zoo`` or a registered method name.

    Args:
        selected: display names.
        zoo: display name -> ``{name: <registered method>, **kwargs}``.

    Raises:
        KeyError: a name neither in ``zoo`` nor registered (both lists in the message).
    """
    methods = {}
    for display in selected:
        if display in zoo:
            config = dict(zoo[display])
        elif display in METHODS:
            config = {"name": display}
        else:
            raise KeyError(
                f"unknown method {display!r}: not in the method zoo ({', '.join(zoo) or 'empty'}) "
                f"nor registered ({', '.join(METHODS.names())})"
            )
        methods[display] = build_method(config)
    return methods


def build_pairs(source: Mapping[str, Any], *, pairs: int | None, seed: int) -> list[PairSample]:
    """Pairs of a benchmark config ``{name: <pair source>, **kwargs}`` (see :data:`PAIR_SOURCES`)."""
    config = dict(source)
    if "name" not in config:
        raise KeyError(f"a benchmark config needs a 'name' (one of {', '.join(PAIR_SOURCES.names())})")
    builder = PAIR_SOURCES.get(config.pop("name"))
    if pairs is not None:
        config["pairs"] = pairs
    return builder(seed=seed, **config)


def benchmark(config: Mapping[str, Any]) -> dict[str, Path]:
    """Run a benchmark config (``configs/benchmark.yaml``) and write its results.

    Keys: ``benchmark`` (pair source config), ``methods`` (display names), ``method_zoo``,
    ``pairs``, ``seed``, ``out``, ``relative_alpha``, ``alphas``, ``progress``. Records are
    journaled to ``<out>/records.jsonl``: rerunning with the same ``out`` resumes.
    """
    pairs = build_pairs(config["benchmark"], pairs=config.get("pairs"), seed=int(config.get("seed", 0)))
    methods = build_methods(list(config["methods"]), config.get("method_zoo") or {})
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
    """``python -m train.benchmark`` (Hydra app on ``configs/benchmark.yaml``)."""
    import hydra
    from omegaconf import DictConfig, OmegaConf

    @hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark")
    def app(config: DictConfig) -> None:
        paths = benchmark(OmegaConf.to_container(config, resolve=True))
        print(paths["table"].read_text())
        print("\n".join(f"{kind}: {path}" for kind, path in paths.items()))

    sys.argv = [sys.argv[0], *expand_folder_argument(sys.argv[1:])]
    app()


if __name__ == "__main__":
    main()
