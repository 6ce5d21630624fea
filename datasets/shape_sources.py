"""Complete-shape sources on disk: any folder of meshes, and ModelNet40 (text or HDF5).

Both feed :class:`~linereg.datasets.shape_pairs.ShapePairDataset` with a pair protocol, exactly like
the procedural shapes.

Splits: ``split="all"`` keeps everything; ``"train"`` / ``"test"`` follow ``split_rule``:

* ``"official"``: ModelNet40's train/test split (split files when the folder has them, else the
  standard per-class numbering: the first ``n_train`` ids of a class are train, the rest test);
  for a mesh folder, ``train/`` and ``test/`` sub-folders (Princeton ``ModelNet40/<class>/train``).
* ``"random"``: the paper's split: the (optionally first ``max_shapes``) shapes are shuffled
  with ``split_seed`` and the first ``train_fraction`` of them are train (Airplane: 625 shapes,
  500 train / 125 test; Human: 110 meshes, 100 / 10).
* ``"views"``: every shape in both splits (the shape sources keep them all), its protocol views
  (camera stops) shuffled with ``split_seed`` and the first ``train_fraction`` of them train
  (held-out views of few shapes; the pair dataset selects them).
* ``"held_out"`` (mesh folders): the shapes named in ``held_out`` (file stems) are the test split,
  every other shape is train, with all of their views (e.g. leave one body out).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from linereg.datasets.base import DATASETS, existing_folder
from linereg.datasets.protocol import Shape, build_protocol
from linereg.datasets.shape_pairs import ShapePairDataset
from linereg.io import MESH_SUFFIXES, read_mesh, read_point_cloud
from linereg.registry import keywords_of

SPLITS = ("train", "test", "all")
SPLIT_RULES = ("official", "random", "views", "held_out")

# Official ModelNet40 sizes per class (train, test); ids 1..train are train, the rest test.
MODELNET40_SPLIT_SIZES: dict[str, tuple[int, int]] = {
    "airplane": (626, 100), "bathtub": (106, 50), "bed": (515, 100), "bench": (173, 20),
    "bookshelf": (572, 100), "bottle": (335, 100), "bowl": (64, 20), "car": (197, 100),
    "chair": (889, 100), "cone": (167, 20), "cup": (79, 20), "curtain": (138, 20),
    "desk": (200, 86), "door": (109, 20), "dresser": (200, 86), "flower_pot": (149, 20),
    "glass_box": (171, 100), "guitar": (155, 100), "keyboard": (145, 20), "lamp": (124, 20),
    "laptop": (149, 20), "mantel": (284, 100), "monitor": (465, 100),
    "night_stand": (200, 86), "person": (88, 20), "piano": (231, 100), "plant": (240, 100),
    "radio": (104, 20), "range_hood": (115, 100), "sink": (128, 20), "sofa": (680, 100),
    "stairs": (124, 20), "stool": (90, 20), "table": (392, 100), "tent": (163, 20),
    "toilet": (344, 100), "tv_stand": (267, 100), "vase": (475, 100), "wardrobe": (87, 20),
    "xbox": (103, 20),
}  # fmt: skip


def _as_list(value: str | Sequence[str] | None) -> list[str] | None:
    """A list from one string, a sequence of strings, or ``None``."""
    if value is None:
        return None
    return [value] if isinstance(value, str) else list(value)


def _check_split(split: str, split_rule: str, train_fraction: float) -> None:
    """ValueError for an unknown split / rule or a fraction outside (0, 1)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if split_rule not in SPLIT_RULES:
        raise ValueError(f"split_rule must be one of {SPLIT_RULES}, got {split_rule!r}")
    if not 0 < train_fraction < 1:
        raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")


def random_split(items: Sequence[Any], split: str, *, train_fraction: float, split_seed: int) -> list[Any]:
    """The ``split`` part of a seeded random train/test partition of ``items``."""
    if split == "all":
        return list(items)
    order = np.random.default_rng(split_seed).permutation(len(items))
    num_train = round(train_fraction * len(items))
    chosen = order[:num_train] if split == "train" else order[num_train:]
    return [items[i] for i in sorted(chosen)]


def _filter_categories(
    items: list[tuple[str, Any]], categories: list[str] | None, where: Path
) -> list[tuple[str, Any]]:
    """Items ``(category, x)`` of the wanted categories; ValueError naming unknown ones."""
    if categories is None:
        return items
    available = sorted({category for category, _ in items})
    unknown = sorted(set(categories) - set(available))
    if unknown:
        raise ValueError(f"unknown categor(ies) {unknown} in {where}; available: {available}")
    return [item for item in items if item[0] in categories]


def _held_out_split(
    items: list[tuple[str, Path]], split: str, held_out: list[str] | None, where: Path
) -> list[tuple[str, Path]]:
    """The ``split`` part of the ``"held_out"`` rule: test = the files whose stem is in ``held_out``,
    train = the others; ValueError naming a stem that is no file of the folder."""
    if not held_out:
        raise ValueError("split_rule='held_out' needs held_out: the file stems of the test shapes")
    stems = sorted(path.stem for _, path in items)
    unknown = sorted(set(held_out) - set(stems))
    if unknown:
        raise ValueError(f"held_out names {unknown} are no mesh in {where}; its meshes: {stems}")
    if split == "all":
        return items
    return [item for item in items if (item[1].stem in held_out) == (split == "test")]


def _list_digest(names: Sequence[str]) -> str:
    """Short hash of a list of names (for cache keys)."""
    return hashlib.sha256("\n".join(names).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class ShapeSelection:
    """The shapes of a folder that a dataset reads (module docstring): both sources take it.

    Attributes:
        categories: keep these categories only (a mesh folder's first path component under its
            root, a ModelNet40 class such as ``"airplane"``).
        split: ``"train"``, ``"test"`` or ``"all"``.
        split_rule: ``"official"``, ``"random"``, ``"views"`` or ``"held_out"`` (mesh folders).
        train_fraction: train share of the random and views rules.
        split_seed: seed of the random and views rules.
        max_shapes: use only the first ``max_shapes`` shapes (sorted files, ModelNet40's official
            order) before splitting.
    """

    categories: str | Sequence[str] | None = None
    split: str = "all"
    split_rule: str = "official"
    train_fraction: float = 0.8
    split_seed: int = 0
    max_shapes: int | None = None

    def __post_init__(self) -> None:
        _check_split(self.split, self.split_rule, self.train_fraction)

    def first(self, items: list[tuple[str, Any]], where: Path) -> list[tuple[str, Any]]:
        """``items`` ``(category, x)`` of the wanted categories (ValueError naming unknown ones, found
        in ``where``), the first ``max_shapes`` of them."""
        items = _filter_categories(items, _as_list(self.categories), where)
        return items if self.max_shapes is None else items[: self.max_shapes]

    def randomly(self, items: list[Any]) -> list[Any]:
        """The split's part of ``items`` by the seeded random rule."""
        return random_split(items, self.split, train_fraction=self.train_fraction, split_seed=self.split_seed)


class MeshFolderShapes:
    """Every mesh (OFF/OBJ/PLY/STL) under a folder; the first sub-folder is the category.

    Args:
        root: the folder (searched recursively).
        selection: the shapes read; its ``"official"`` rule reads ``train/`` and ``test/``
            sub-folders, its ``"held_out"`` rule holds out the shapes named in ``held_out``
            (test: those, train: the others).
        held_out: file stems of the test shapes of the ``"held_out"`` rule.
    """

    def __init__(
        self,
        root: str | Path,
        selection: ShapeSelection = ShapeSelection(),
        held_out: str | Sequence[str] | None = None,
    ) -> None:
        self.root = existing_folder(root, "mesh folder")
        self.selection, self.split = selection, selection.split  # split: a ShapeCollection's
        split, split_rule = selection.split, selection.split_rule
        files = sorted(p for p in self.root.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)
        if not files:
            raise FileNotFoundError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) under {self.root}")
        items = selection.first([(self._category(p), p) for p in files], self.root)
        if split != "all" and split_rule == "official":
            items = [item for item in items if split in item[1].relative_to(self.root).parts[:-1]]
        elif split != "all" and split_rule == "random":
            items = selection.randomly(items)
        elif split_rule == "held_out":
            items = _held_out_split(items, split, _as_list(held_out), self.root)
        elif held_out is not None:
            raise ValueError(f"held_out={held_out!r} needs split_rule='held_out', got {split_rule!r}")
        if not items:
            raise ValueError(
                f"no meshes left under {self.root} for categories={selection.categories}, split={split!r} "
                f"(split_rule={split_rule!r}: 'official' needs train/ and test/ sub-folders)"
            )
        self.items = items
        self._settings = {
            "source": "mesh_folder",
            "root": str(self.root),
            "files": _list_digest([str(p.relative_to(self.root)) for _, p in items]),
            "count": len(items),
        }

    def _category(self, path: Path) -> str:
        """First path component under the root (``""`` for files directly in it)."""
        parts = path.relative_to(self.root).parts
        return parts[0] if len(parts) > 1 else ""

    def __len__(self) -> int:
        return len(self.items)

    def load(self, index: int) -> Shape:
        """Mesh ``index``."""
        category, path = self.items[index]
        meta = {"file": str(path), "category": category}
        return Shape(name=path.stem, mesh=read_mesh(path), meta=meta)

    def describe(self) -> dict[str, Any]:
        """Settings that determine the shapes (for cache keys)."""
        return dict(self._settings, split=self.split)


def _read_lines(path: Path) -> list[str]:
    """Non-empty stripped lines of a text file."""
    return [line.strip() for line in path.read_text().splitlines() if line.strip()]


class ModelNet40Shapes:
    """ModelNet40 point clouds: ``modelnet40_normal_resampled`` text or ``ply_hdf5_2048``.

    Args:
        root: dataset folder: ``<class>/<class>_XXXX.txt`` files (``x,y,z,nx,ny,nz`` lines) or
            ``ply_data_{train,test}*.h5`` files (``data``, ``normal``, ``label``).
        selection: the shapes read, by the ``"official"``, ``"random"`` (the paper's 500/125
            Airplane split) or ``"views"`` rule.
        file_format: ``"auto"``, ``"text"`` or ``"hdf5"``.
    """

    def __init__(
        self, root: str | Path, selection: ShapeSelection = ShapeSelection(split="train"), file_format: str = "auto"
    ) -> None:
        split, split_rule = selection.split, selection.split_rule
        if split_rule == "held_out":
            raise ValueError(
                "split_rule='held_out' is a mesh folder's rule; ModelNet40 takes 'official', 'random' or 'views'"
            )
        self.root = existing_folder(root, "ModelNet40 folder")
        self.selection, self.split = selection, selection.split  # split: a ShapeCollection's
        if file_format == "auto":
            file_format = "hdf5" if any(self.root.glob("*.h5")) else "text"
        if file_format not in ("text", "hdf5"):
            raise ValueError(f"file_format must be 'auto', 'text' or 'hdf5', got {file_format!r}")
        self.file_format = file_format
        official = split if split_rule == "official" else "all"
        if file_format == "text":
            items = self._text_items(official)
        else:
            items = self._hdf5_items(official)
        items = selection.first(items, self.root)
        if split_rule == "random":
            items = selection.randomly(items)
        if not items:
            raise ValueError(
                f"no ModelNet40 shapes in {self.root} for categories={selection.categories}, "
                f"split={split!r}, split_rule={split_rule!r}"
            )
        self.items = items
        self._settings = {
            "source": "modelnet40",
            "root": str(self.root),
            "format": file_format,
            "shapes": _list_digest([str(item) for _, item in items]),
            "count": len(items),
        }

    def _text_items(self, split: str) -> list[tuple[str, Any]]:
        """``(category, path)`` of the text files of an official split (or all)."""
        files = sorted(self.root.glob("*/*.txt"))
        if not files:
            raise FileNotFoundError(f"no ModelNet40 text files (<class>/<class>_XXXX.txt) under {self.root}")
        items = [(p.parent.name, p) for p in files]
        if split == "all":
            return items
        split_file = self.root / f"modelnet40_{split}.txt"
        if split_file.is_file():
            wanted = set(_read_lines(split_file))
            return [item for item in items if item[1].stem in wanted]
        return [item for item in items if self._official_split(item[1].stem) == split]

    def _official_split(self, stem: str) -> str:
        """``"train"`` / ``"test"`` of a ``<class>_XXXX`` id by the standard numbering."""
        category, _, number = stem.rpartition("_")
        if category not in MODELNET40_SPLIT_SIZES or not number.isdigit():
            raise ValueError(
                f"{self.root}: cannot tell the official split of {stem!r} (no "
                "modelnet40_train.txt / modelnet40_test.txt and not a ModelNet40 '<class>_XXXX' id)"
            )
        return "train" if int(number) <= MODELNET40_SPLIT_SIZES[category][0] else "test"

    def _hdf5_items(self, split: str) -> list[tuple[str, Any]]:
        """``(category, (file name, row))`` of the HDF5 shapes of an official split (or all)."""
        import h5py

        names_file = self.root / "shape_names.txt"
        if not names_file.is_file():
            raise FileNotFoundError(f"{names_file} not found (ModelNet40 HDF5 class names)")
        class_names = _read_lines(names_file)
        patterns = ["ply_data_train*.h5", "ply_data_test*.h5"]
        if split != "all":
            patterns = [f"ply_data_{split}*.h5"]
        files = sorted(p for pattern in patterns for p in self.root.glob(pattern))
        if not files:
            raise FileNotFoundError(f"no ply_data_*.h5 files for split {split!r} in {self.root}")
        items = []
        for path in files:
            with h5py.File(path, "r") as archive:
                missing = {"data", "label"} - set(archive.keys())
                if missing:
                    raise ValueError(f"{path}: missing HDF5 dataset(s) {sorted(missing)}")
                labels = np.asarray(archive["label"]).reshape(-1)
            items += [(class_names[int(c)], (path.name, row)) for row, c in enumerate(labels)]
        return items

    def __len__(self) -> int:
        return len(self.items)

    def load(self, index: int) -> Shape:
        """Shape ``index`` as a dense point cloud with normals."""
        category, item = self.items[index]
        if self.file_format == "text":
            cloud = read_point_cloud(item)
            meta = {"file": str(item), "category": category}
            return Shape(name=item.stem, points=cloud.xyz, normals=cloud.normals, meta=meta)
        import h5py

        file_name, row = item
        with h5py.File(self.root / file_name, "r") as archive:
            points = np.asarray(archive["data"][row], dtype=np.float32)
            normals = np.asarray(archive["normal"][row], dtype=np.float32) if "normal" in archive else None
        meta = {"file": str(self.root / file_name), "row": row, "category": category}
        return Shape(name=f"{Path(file_name).stem}_{row:04d}", points=points, normals=normals, meta=meta)

    def describe(self) -> dict[str, Any]:
        """Settings that determine the shapes (for cache keys)."""
        return dict(self._settings, split=self.split)


def _shape_pairs(
    shapes: MeshFolderShapes | ModelNet40Shapes, protocol: str | Mapping[str, Any], seed: int, name: str
) -> ShapePairDataset:
    """The pair dataset of a shape source; the ``"views"`` rule keeps the split's camera stops."""
    protocol = build_protocol(protocol)
    views = None
    if shapes.selection.split_rule == "views":
        views = shapes.selection.randomly(range(protocol.pairs_per_shape))
    return ShapePairDataset(shapes, protocol, seed=seed, name=name, views=views)


@DATASETS.register("mesh_folder")
@keywords_of(ShapeSelection)
def build_mesh_folder(
    *,
    root: str | Path,
    held_out: str | Sequence[str] | None = None,
    protocol: str | Mapping[str, Any] = "airplane",
    seed: int = 0,
    **selection,
) -> ShapePairDataset:
    """Pairs from any folder of meshes (:class:`MeshFolderShapes`; ``selection``: :class:`ShapeSelection`'s
    fields; see the protocol)."""
    return _shape_pairs(MeshFolderShapes(root, ShapeSelection(**selection), held_out), protocol, seed, "mesh_folder")


@DATASETS.register("modelnet40")
@keywords_of(ShapeSelection)
def build_modelnet40(
    *,
    root: str | Path,
    split: str = "train",
    file_format: str = "auto",
    protocol: str | Mapping[str, Any] = "airplane",
    seed: int = 0,
    **selection,
) -> ShapePairDataset:
    """Pairs from ModelNet40 shapes (:class:`ModelNet40Shapes`; ``split`` and ``selection``:
    :class:`ShapeSelection`'s fields; see the protocol)."""
    shapes = ModelNet40Shapes(root, ShapeSelection(split=split, **selection), file_format)
    return _shape_pairs(shapes, protocol, seed, "modelnet40")
