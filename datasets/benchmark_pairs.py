"""Labelled pairs for benchmarks: the paper's test protocols, the user's folders, a training run's split.

Pair sources (:data:`PAIR_SOURCES`, built by ``PAIR_SOURCES.build({name: ..., **kwargs})``), each a
function returning a list of labelled :class:`~linereg.structures.PairSample`, deterministic given
``seed``; default paths are in the shared data folder, :func:`linereg.paths.shared_data_dir`:

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
    Real scans with ground truth, in metres (30k random points per cloud): any folder in the 3DMatch layout
    (one scene of ``cloud_bin_<i>.ply`` + ``gt.log``, or a folder of scenes; pairs whose
    fragments are absent are skipped); by default the shared redkitchen fragments 0 and 4
    (``gt.log``: source = fragment 4, target = fragment 0) and the GeoTransformer demo pair
    (``p_ref = gt @ p_src``). ``meta["overlap"]`` comes from ``gt_overlap.log`` or is measured
    (share of source points within 3.75 cm of the target after the ground truth).
``fragments``
    Real partial-overlap pairs built the way 3DMatch builds its fragments: runs of consecutive
    depth frames of a posed RGB-D sequence (default: the shared 7-Scenes sequence) fused into
    fragments, source and target without a common frame, drawn evenly from overlap bins
    ``[0.2, 0.3)``, ``[0.3, 0.5)``, ``[0.5, 0.8]`` (48 pairs, metres, 30k random points per cloud;
    :mod:`linereg.datasets.fragments`).
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

"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from linereg.checkpoint import find_checkpoint, load_checkpoint
from linereg.checks import nearest_rotation
from linereg.datasets import build_dataset
from linereg.datasets.fragments import DEFAULT_BINS, FragmentSettings, fragment_pairs, overlap_ratio
from linereg.datasets.protocol import Shape, ShapeViews, build_protocol
from linereg.datasets.scan_pairs import ScanSettings, finish_scan_pair
from linereg.datasets.splits import build_split
from linereg.datasets.threedmatch import NoPairsError, ThreeDMatchPairs, find_gt_log
from linereg.io import read_mesh
from linereg.paths import shared_data_dir
from linereg.random_poses import random_transform_paper
from linereg.registry import Registry, plain
from linereg.se3 import transform_normals, transform_points
from linereg.structures import PairSample

PAIR_SOURCES: Registry[list[PairSample]] = Registry("benchmark pair source")


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


def labelled_pairs(pairs: Sequence[PairSample], where: str) -> list[PairSample]:
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
    return labelled_pairs(chosen, f"dataset {dict(dataset).get('name')!r}")


@PAIR_SOURCES.register("run")
def run_pairs(
    *, run: str, split: str = "test", pairs: int | None = None, seed: int = 0, dataset_seed: int | None = None
) -> list[PairSample]:
    """The ``split`` pairs of a training run's dataset (its checkpoint's resolved config).

    Args:
        run: run folder or checkpoint file (``python -m train`` output).
        split: dataset split (``train``, ``val`` or ``test``).
        pairs: number of pairs (``None``: all).
        seed: seed of the draw.
        dataset_seed: the dataset's ``seed`` (e.g. the point samples of each frame) instead of the
            run's (``None``).
    """
    dataset = dict(load_checkpoint(find_checkpoint(run))["config"]["dataset"])
    if dataset_seed is not None:
        dataset["seed"] = dataset_seed
    built = build_split(dataset, split, progress=False)
    if built is None:
        raise ValueError(f"run {run}: its dataset has no {split!r} split")
    chosen = [built[i] for i in select_indices(len(built), pairs, seed)]
    return labelled_pairs(chosen, f"run {run} ({split!r} split)")


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


def _is_scene(folder: Path) -> bool:
    """Whether ``folder`` holds 3DMatch fragments ``cloud_bin_<i>.ply``."""
    return any(folder.glob("cloud_bin_*.ply"))


def _scenes(root: Path, gt_log: str | None, scan: dict[str, Any], seed: int) -> list[ThreeDMatchPairs]:
    """The scenes of a 3DMatch folder: ``root`` itself, else its sub-folders with fragments and a gt.log."""
    settings = {"skip_missing": True, "compute_overlap": True, **scan, "seed": seed}
    if _is_scene(root):
        return [ThreeDMatchPairs(root, gt_log=gt_log, **settings)]
    scenes = []
    for folder in sorted(path for path in root.iterdir() if path.is_dir() and _is_scene(path)):
        if find_gt_log(folder) is not None:
            with contextlib.suppress(NoPairsError):
                scenes.append(ThreeDMatchPairs(folder, **settings))
    if not scenes:
        raise FileNotFoundError(
            f"{root} is not a 3DMatch scene (cloud_bin_<i>.ply + gt.log) nor a folder of scenes with "
            "fragments and a gt.log (in the scene or in <scene>-evaluation/)"
        )
    return scenes


@PAIR_SOURCES.register("3dmatch")
def threedmatch_pairs(
    *,
    pairs: int | None = None,
    seed: int = 0,
    root: str | None = None,
    gt_log: str | None = None,
    demo: str | bool | None = None,
    num_points: int | None = None,
    dense_points: int | None = 30000,
    half_extent: float | None = None,
) -> list[PairSample]:
    """Real 3DMatch pairs with ground truth, in metres (module docstring).

    Args:
        pairs: number of pairs (``None``: all).
        seed: seed of the subsampling and of the draw.
        root: a scene folder (``cloud_bin_<i>.ply`` + ``gt.log`` in it or in a sibling
            ``<scene>-evaluation/``) or a folder of such scenes; ``None``: the shared redkitchen
            fragments 0 and 4. Pairs of a ``gt.log`` whose fragments are absent are skipped.
        gt_log: the ``gt.log`` of a single scene (``None``: found next to the fragments; with
            ``root=None`` the redkitchen log of the GeoTransformer benchmark files).
        demo: folder with ``src.npy``, ``ref.npy``, ``gt.npy`` (``p_ref = gt @ p_src``) added as
            one more pair; ``None``: the shared GeoTransformer demo pair when ``root`` is ``None``,
            none otherwise; ``False``: none.
        num_points: FPS size of each cloud after the cap (``None``: keep them all).
        dense_points: random cap of each cloud before normal estimation (``None``: every point;
            the classical baselines do not subsample, and FGR takes minutes per pair at 60k).
        half_extent: scale each pair into ``[-half_extent, half_extent]^3`` (``None``: metres).

    Returns:
        Pairs with ``meta``: ``source`` (``"3dmatch"``), ``overlap`` (``gt_overlap.log`` when it
        lists the pair, else measured: share of source points within 3.75 cm of the target),
        ``scene``, ``src_fragment`` / ``tgt_fragment`` (fragment names) for fragment pairs.
    """
    scan = {"num_points": num_points, "dense_points": dense_points, "half_extent": half_extent}
    if root is None:
        default_log = "3dmatch/geotransformer_demo/benchmarks/3DMatch/7-scenes-redkitchen/gt.log"
        scenes = _scenes(_data_path(None, "3dmatch/redkitchen_0_4"), str(_data_path(gt_log, default_log)), scan, seed)
    else:
        scenes = _scenes(_data_path(root, root), gt_log, scan, seed)
    found = []
    for scene in scenes:
        for index in range(len(scene)):
            pair = scene[index]
            meta = dict(pair.meta)
            meta.update(src_fragment=meta.pop("source"), tgt_fragment=meta.pop("target"), source="3dmatch")
            pair.meta = meta
            found.append(pair)
    if demo is None and root is None:
        demo = "3dmatch/geotransformer_demo/demo"
    if demo:
        folder = _data_path(demo, "3dmatch/geotransformer_demo/demo")
        source, target = np.load(folder / "src.npy"), np.load(folder / "ref.npy")
        gt = np.array(np.load(folder / "gt.npy"), dtype=np.float64)
        gt[:3, :3] = nearest_rotation(gt[:3, :3])
        found.append(
            finish_scan_pair(
                source,
                target,
                gt,
                ScanSettings(**scan),
                np.random.default_rng([seed, len(found)]),
                src_viewpoint=np.zeros(3),
                tgt_viewpoint=np.zeros(3),
                meta={
                    "dataset": "geotransformer_demo",
                    "source": "3dmatch",
                    "index": len(found),
                    "file": str(folder / "src.npy"),
                    "overlap": overlap_ratio(source, target, gt),
                },
            )
        )
    return labelled_pairs([found[i] for i in select_indices(len(found), pairs, seed)], "3dmatch")


@PAIR_SOURCES.register("fragments")
def fragments_source(
    *,
    pairs: int | None = 48,
    seed: int = 0,
    root: str | None = None,
    bins: Sequence[Sequence[float]] = DEFAULT_BINS,
    dense_points: int | None = 30000,
    num_points: int | None = None,
    cache_dir: str | None = None,
    ground_truth: str = "refined",
    **settings: Any,
) -> list[PairSample]:
    """Independently fused fragments of a real room drawn from overlap bins (:mod:`linereg.datasets.fragments`).

    Args:
        pairs: number of pairs (``None``: 48), split evenly across ``bins``.
        seed: seed of the draw.
        root: posed RGB-D sequence folder (default ``<shared>/rgbd/7scenes_first_half/data``).
        bins: overlap bins ``[[low, high], ...]`` (half-open, the last one closed).
        dense_points: random cap of each cloud (``None``: the whole fragment).
        num_points: FPS size of each cloud after the cap (``None``: keep them all).
        cache_dir: fragment cache folder (``None``: ``$XDG_CACHE_HOME/linereg`` or ``~/.cache/linereg``).
        ground_truth: ``"refined"`` or ``"tracking"`` (:func:`~linereg.datasets.fragments.fragment_pairs`).
        **settings: fields of :class:`~linereg.datasets.fragments.FragmentSettings`.
    """
    return fragment_pairs(
        _data_path(root, "rgbd/7scenes_first_half/data"),
        pairs=48 if pairs is None else pairs,
        seed=seed,
        bins=[tuple(b) for b in bins],
        dense_points=dense_points,
        num_points=num_points,
        cache_dir=cache_dir,
        settings=FragmentSettings(**settings),
        ground_truth=ground_truth,
    )


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


def select_pairs(source: Mapping[str, Any], *, pairs: int | None = None, seed: int = 0) -> list[PairSample]:
    """The pairs of a benchmark's ``{name: <pair source>, **kwargs}``; ``pairs`` (unless ``None``) sets the count."""
    config = dict(plain(source))
    if pairs is not None:
        config["pairs"] = pairs
    return PAIR_SOURCES.build(config, seed=seed)
