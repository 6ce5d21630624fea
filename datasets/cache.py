"""On-disk cache of generated pairs: compressed shards plus a manifest of what generated them.

Layout of one cache (``<cache_root>/<dataset name>-<provenance hash>/``)::

    manifest.json            format version, generator settings, code hash, library versions,
                             pair count, shards, timing
    shard_0000000_0000256.npz  pairs [0, 256): concatenated clouds + offsets, transforms, meta

The folder name hashes the pairs' provenance (:func:`provenance`): :meth:`PairDataset.settings`,
the source of the code that generates them (:func:`generator_code`) and the versions of the
libraries it computes with (:data:`GENERATOR_LIBRARIES`). Changing a generator setting, editing the
generating code or upgrading one of those libraries writes a new cache instead of silently reusing
a stale one.

Shards are written atomically as they finish; an interrupted run resumes by generating only the
missing shards, and :func:`materialize` regenerates (with a warning) a shard that was deleted or
cannot be read and a manifest that cannot be parsed. Loading reads every shard once into memory (a
10 000-pair, 1024-point cache with normals is ~0.5 GB) and then serves pairs by slicing, shared
copy-on-write with forked DataLoader workers.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import math
import multiprocessing
import os
import secrets
import sys
import time
import warnings
import zipfile
import zlib
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from types import ModuleType
from typing import Any, BinaryIO

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from linereg.datasets.base import DATASETS, PairDataset
from linereg.structures import PairSample

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
_CLOUD_FIELDS = ("src_xyz", "tgt_xyz", "src_normals", "tgt_normals")


class CorruptCacheError(ValueError):
    """Files of a cache folder that are missing or cannot be read.

    Attributes:
        files: the missing or unreadable files (shards or the manifest).
    """

    def __init__(self, message: str, files: list[Path]) -> None:
        super().__init__(message)
        self.files = files


def _canonical(settings: dict[str, Any]) -> dict[str, Any]:
    """Settings as they read back from JSON (tuples become lists, ...)."""
    return json.loads(json.dumps(settings, sort_keys=True, default=str))


def settings_key(settings: dict[str, Any]) -> str:
    """Short stable hash of a settings dictionary."""
    text = json.dumps(_canonical(settings), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


GENERATOR_LIBRARIES: dict[str, tuple[str, ...]] = {
    "numpy": ("numpy",),
    "torch": ("torch",),
    "scipy": ("scipy",),
    "roma": ("roma",),
    "fpsample": ("fpsample",),
    "trimesh": ("trimesh",),
    "open3d": ("open3d", "open3d-cpu"),
    "pillow": ("pillow",),
    "h5py": ("h5py",),
}
"""The libraries whose results enter generated pairs (random numbers, sampling, ray casting,
normals, file readers), each with the distributions that install it."""


def library_versions() -> dict[str, str]:
    """The installed version of each of :data:`GENERATOR_LIBRARIES` (``"absent"`` when not installed)."""
    versions = {}
    for library, distributions in GENERATOR_LIBRARIES.items():
        versions[library] = "absent"
        for distribution in distributions:
            with contextlib.suppress(importlib.metadata.PackageNotFoundError):
                versions[library] = importlib.metadata.version(distribution)
                break
    return versions


def _generator_modules(dataset: PairDataset) -> set[str]:
    """Modules of the classes that ``dataset`` is made of: its own, those of the datasets it wraps (a
    concat's parts) and of every ``linereg`` object it holds (a shape source, a pair protocol)."""
    modules, pending, seen = set(), [dataset], set()
    while pending:
        item = pending.pop()
        if id(item) in seen:
            continue
        seen.add(id(item))
        if isinstance(item, (list, tuple, set, frozenset)):
            pending.extend(item)
        elif isinstance(item, dict):
            pending.extend(item.values())
        elif isinstance(item, Dataset) or type(item).__module__.startswith("linereg."):
            modules.update(
                cls.__module__
                for cls in type(item).__mro__
                if issubclass(cls, PairDataset) or cls.__module__.startswith("linereg.")
            )
            pending.extend(getattr(item, "__dict__", {}).values())
    return modules


def _linereg_modules(module: ModuleType) -> set[str]:
    """Names of the ``linereg.*`` modules that ``module``'s globals come from (imported names)."""
    names = set()
    for value in vars(module).values():
        name = value.__name__ if isinstance(value, ModuleType) else getattr(value, "__module__", None)
        if isinstance(name, str) and name.startswith("linereg.") and name in sys.modules:
            names.add(name)
    return names


def generator_code(dataset: PairDataset) -> dict[str, str]:
    """A hash of the source of every module that generates the pairs of ``dataset``.

    The modules are those defining the classes that ``dataset`` is made of (:func:`_generator_modules`)
    and, transitively, every ``linereg.*`` module whose names they import (geometry, sampling,
    readers).
    A module without a source file (defined interactively) enters by its name alone.

    Returns:
        ``{"sha256": <hash of the sources>, "modules": <their names, sorted>}``.
    """
    pending = _generator_modules(dataset)
    modules: set[str] = set()
    while pending:
        name = pending.pop()
        modules.add(name)
        pending |= _linereg_modules(sys.modules[name]) - modules
    digest = hashlib.sha256()
    for name in sorted(modules):
        file = getattr(sys.modules[name], "__file__", None)
        digest.update(name.encode() + b"\0" + (Path(file).read_bytes() if file else b"") + b"\0")
    return {"sha256": digest.hexdigest(), "modules": sorted(modules)}


def provenance(dataset: PairDataset) -> dict[str, Any]:
    """What determines the pairs of ``dataset``: its settings, its code and its libraries' versions.

    The cache folder is named by a hash of this dictionary (:func:`cache_path`), and its manifest
    records it.
    """
    return {
        "settings": _canonical(dataset.settings()),
        "code": generator_code(dataset)["sha256"],
        "libraries": library_versions(),
    }


def cache_path(dataset: PairDataset, cache_root: str | Path) -> Path:
    """The cache folder of ``dataset`` under ``cache_root``, named by a hash of its :func:`provenance`."""
    return _cache_path(provenance(dataset), dataset, cache_root)


def _cache_path(origin: dict[str, Any], dataset: PairDataset, cache_root: str | Path) -> Path:
    """The cache folder under ``cache_root`` of ``dataset`` with provenance ``origin``."""
    return Path(cache_root) / f"{dataset.registry_name}-{settings_key(origin)}"


@contextlib.contextmanager
def _atomic_temporary(path: Path) -> Iterator[BinaryIO]:
    """An open binary file that replaces ``path`` atomically once the ``with`` block succeeds.

    The temporary ``.<name>.<pid>.<random>.tmp`` beside ``path`` is unique to this writer, so
    processes generating the same cache at once never share one; the last ``os.replace`` of
    identical content wins, and a reader sees either no file or a complete one. The temporary
    is removed when the block fails.
    """
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        with open(temporary, "wb") as handle:
            yield handle
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_shard(samples: list[PairSample], path: Path) -> None:
    """Write pairs to one compressed ``.npz`` shard (atomically, via a temporary file)."""
    arrays: dict[str, np.ndarray] = {}
    for name in _CLOUD_FIELDS:
        xyz_name = name.replace("normals", "xyz")
        clouds = [getattr(s, name) for s in samples]
        present = np.array([c is not None for c in clouds])
        sizes = [len(getattr(s, xyz_name)) for s in samples]
        filled = [c if c is not None else np.zeros((n, 3), np.float32) for c, n in zip(clouds, sizes, strict=True)]
        arrays[name] = np.concatenate(filled).astype(np.float32) if filled else np.zeros((0, 3), np.float32)
        arrays[f"has_{name}"] = present
        arrays[f"{name}_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    arrays["has_gt"] = np.array([s.gt_transform is not None for s in samples])
    arrays["gt_transform"] = np.stack(
        [s.gt_transform if s.gt_transform is not None else np.eye(4) for s in samples]
    ).astype(np.float32)
    arrays["meta"] = np.array([json.dumps(s.meta, default=str) for s in samples])
    with _atomic_temporary(path) as handle:
        np.savez_compressed(handle, **arrays)


class CachedPairs(Dataset):
    """Pairs read back from a cache folder (all shards loaded into memory at construction).

    Args:
        path: the cache folder (holding ``manifest.json``).
    """

    registry_name = "cached"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        manifest_file = self.path / MANIFEST
        if not manifest_file.is_file():
            raise FileNotFoundError(
                f"no pair cache at {self.path} (missing {MANIFEST}); generate it with "
                "scripts/prepare_dataset.py or build_dataset({..., 'cache_dir': ...})"
            )
        self.manifest = read_manifest(manifest_file)
        if self.manifest.get("version") != FORMAT_VERSION:
            raise ValueError(
                f"{manifest_file}: cache format version {self.manifest.get('version')} is not "
                f"{FORMAT_VERSION}; delete the folder and regenerate it"
            )
        shards = _load_shards([self.path / s["file"] for s in self.manifest["shards"]])
        self._arrays: dict[str, np.ndarray] = {}
        for name in _CLOUD_FIELDS:
            self._arrays[name] = np.concatenate([s[name] for s in shards])
            self._arrays[f"has_{name}"] = np.concatenate([s[f"has_{name}"] for s in shards])
            starts = np.cumsum([0] + [s[f"{name}_offsets"][-1] for s in shards[:-1]])
            self._arrays[f"{name}_offsets"] = np.concatenate(
                [s[f"{name}_offsets"][:-1] + start for s, start in zip(shards, starts, strict=True)]
                + [[sum(int(s[f"{name}_offsets"][-1]) for s in shards)]]
            )
        for name in ("has_gt", "gt_transform", "meta"):
            self._arrays[name] = np.concatenate([s[name] for s in shards])
        if len(self._arrays["meta"]) != self.manifest["num_pairs"]:
            raise ValueError(
                f"{self.path}: shards hold {len(self._arrays['meta'])} pairs but the manifest "
                f"records {self.manifest['num_pairs']}; delete the folder and regenerate it"
            )

    def __len__(self) -> int:
        return int(self.manifest["num_pairs"])

    def settings(self) -> dict[str, Any]:
        """The generator settings recorded in the manifest."""
        return self.manifest["settings"]

    def _cloud(self, name: str, index: int) -> np.ndarray | None:
        """Copy of cloud ``name`` of pair ``index`` (``None`` when absent)."""
        if not self._arrays[f"has_{name}"][index]:
            return None
        offsets = self._arrays[f"{name}_offsets"]
        return self._arrays[name][offsets[index] : offsets[index + 1]].copy()

    def __getitem__(self, index: int) -> PairSample:
        length = len(self)
        if not -length <= index < length:
            raise IndexError(f"index {index} out of range for a cache of {length} pairs")
        index %= length
        gt = self._arrays["gt_transform"][index].copy() if self._arrays["has_gt"][index] else None
        return PairSample(
            src_xyz=self._cloud("src_xyz", index),
            tgt_xyz=self._cloud("tgt_xyz", index),
            src_normals=self._cloud("src_normals", index),
            tgt_normals=self._cloud("tgt_normals", index),
            gt_transform=gt,
            meta=json.loads(str(self._arrays["meta"][index])),
        )


def read_manifest(file: Path) -> dict[str, Any]:
    """The parsed ``manifest.json`` of a cache.

    Raises:
        CorruptCacheError: the file is not a JSON object with ``num_pairs`` and ``shards``.
    """
    try:
        manifest = json.loads(file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CorruptCacheError(
            f"{file}: not a valid cache manifest ({type(error).__name__}: {error}); delete it and generate the "
            "cache again with the same settings (existing shards are kept)",
            [file],
        ) from error
    if not isinstance(manifest, dict) or not {"num_pairs", "shards", "settings"} <= set(manifest):
        raise CorruptCacheError(
            f"{file}: not a cache manifest (expected a JSON object with num_pairs, shards and settings); delete it "
            "and generate the cache again",
            [file],
        )
    return manifest


def _load_shards(files: list[Path]) -> list[dict[str, np.ndarray]]:
    """Every array of every shard, read now, or one error naming each missing or unreadable shard."""
    shards, problems = [], {}
    for file in files:
        try:
            with np.load(file, allow_pickle=False) as archive:
                shards.append({name: archive[name] for name in archive.files})
        except FileNotFoundError:
            problems[file] = "missing"
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as error:
            problems[file] = f"unreadable ({type(error).__name__}: {error})"
    if problems:
        listing = "\n  ".join(f"{file}: {problem}" for file, problem in problems.items())
        raise CorruptCacheError(
            f"cache shard(s) missing or corrupt (truncated by an interrupted copy or a full disk?):\n  {listing}\n"
            "generate the cache again with the same settings (build_dataset with cache_dir, or "
            "scripts/prepare_dataset.py): only these shards are regenerated",
            list(problems),
        )
    return shards


_worker_dataset: PairDataset | None = None


def _init_worker(dataset: PairDataset) -> None:
    """Pool initializer: keep the dataset and use one torch thread per process."""
    global _worker_dataset
    _worker_dataset = dataset
    torch.set_num_threads(1)


def _generate_shard(task: tuple[int, int, str]) -> int:
    """Generate pairs ``[start, stop)`` of the worker's dataset into ``file``."""
    return _write_pairs(_worker_dataset, task)


def _write_pairs(dataset: PairDataset, task: tuple[int, int, str]) -> int:
    """Generate pairs ``[start, stop)`` of ``dataset`` into ``file``; returns their number."""
    start, stop, file = task
    write_shard([dataset.make_pair(i) for i in range(start, stop)], Path(file))
    return stop - start


def materialize(
    dataset: PairDataset,
    cache_root: str | Path,
    *,
    workers: int | None = None,
    shard_size: int = 128,
    progress: bool = True,
) -> CachedPairs:
    """Generate every pair of ``dataset`` once into a cache under ``cache_root`` and load it.

    An existing complete cache with the same provenance (settings, code, library versions) is
    loaded without generating anything;
    missing or unreadable shards and an unreadable manifest are regenerated with a warning.

    Args:
        dataset: the generator.
        cache_root: folder holding caches (created when missing).
        workers: worker processes (``None``: every CPU core; ``0``: this process).
        shard_size: most pairs per shard file; smaller datasets are cut into up to 16 shards
            (of at least 8 pairs) so that the work spreads over the workers.
        progress: show a tqdm progress bar.

    Returns:
        The loaded cache.
    """
    origin = provenance(dataset)
    path = _cache_path(origin, dataset, cache_root)
    manifest_file = path / MANIFEST
    if manifest_file.is_file():
        try:
            manifest = read_manifest(manifest_file)
        except CorruptCacheError as error:
            warnings.warn(
                f"{error.files[0]}: unreadable cache manifest; writing a new one", RuntimeWarning, stacklevel=2
            )
            manifest = {}
        if manifest and any(manifest.get(key) != value for key, value in origin.items()):
            warnings.warn(
                f"{path}: written from other settings, code or library versions; generating it again",
                RuntimeWarning,
                stacklevel=2,
            )
            for shard in path.glob("shard_*.npz"):
                shard.unlink()
        elif manifest.get("num_pairs") == len(dataset):
            try:
                return CachedPairs(path)
            except CorruptCacheError as error:
                _discard(error)
    _generate(dataset, path, origin, workers=workers, shard_size=shard_size, progress=progress)
    try:
        return CachedPairs(path)
    except CorruptCacheError as error:  # a shard left by an earlier run that wrote no manifest
        _discard(error)
    _generate(dataset, path, origin, workers=workers, shard_size=shard_size, progress=progress)
    return CachedPairs(path)


def _discard(error: CorruptCacheError) -> None:
    """Delete the unreadable files named by ``error`` (with a warning) so they are generated again."""
    names = ", ".join(str(file) for file in error.files)
    warnings.warn(f"cache file(s) missing or unreadable, regenerating: {names}", RuntimeWarning, stacklevel=3)
    for file in error.files:
        file.unlink(missing_ok=True)


def _generate(
    dataset: PairDataset, path: Path, origin: dict[str, Any], *, workers: int | None, shard_size: int, progress: bool
) -> None:
    """Generate the missing shards of the cache at ``path`` and write its manifest (with ``origin``,
    the dataset's :func:`provenance`)."""
    manifest_file = path / MANIFEST
    path.mkdir(parents=True, exist_ok=True)
    shard_size = min(shard_size, max(8, math.ceil(len(dataset) / 16)))
    shards = [
        {
            "file": f"shard_{start:07d}_{min(start + shard_size, len(dataset)):07d}.npz",
            "start": start,
            "stop": min(start + shard_size, len(dataset)),
        }
        for start in range(0, len(dataset), shard_size)
    ]
    todo = [(s["start"], s["stop"], str(path / s["file"])) for s in shards if not (path / s["file"]).is_file()]
    workers = min((os.cpu_count() or 1) if workers is None else workers, len(todo))
    began = time.perf_counter()
    with tqdm(
        total=len(dataset),
        initial=len(dataset) - sum(t[1] - t[0] for t in todo),
        unit="pair",
        desc=f"generating {path.name}",
        disable=not progress,
    ) as bar:
        if workers <= 1:
            for task in todo:
                bar.update(_write_pairs(dataset, task))
        else:
            context = multiprocessing.get_context("spawn")
            with context.Pool(workers, initializer=_init_worker, initargs=(dataset,)) as pool:
                for count in pool.imap_unordered(_generate_shard, todo):
                    bar.update(count)
    manifest = {
        "version": FORMAT_VERSION,
        "dataset": dataset.registry_name,
        **origin,
        "num_pairs": len(dataset),
        "shards": shards,
        "generated_pairs": sum(t[1] - t[0] for t in todo),
        "workers": workers,
        "elapsed_s": round(time.perf_counter() - began, 3),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    with _atomic_temporary(manifest_file) as handle:
        handle.write(json.dumps(manifest, indent=2).encode())


@DATASETS.register("cached")
def build_cached(*, path: str) -> CachedPairs:
    """Pairs from a cache folder written by :func:`materialize` / ``scripts/prepare_dataset.py``."""
    return CachedPairs(path)
