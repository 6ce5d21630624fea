"""Pretrained weights by name: networks trained by ``linereg-train`` that ship with the package.

``names()`` lists them, ``path(name)`` gives the checkpoint file, ``entry(name)`` its description,
the command that trained it and its test error. A name goes wherever a checkpoint does::

    linereg-evaluate checkpoint=rpm_ours_airplane             # its protocol's test pairs (shared data)
    linereg-train experiment=rpm_ours protocol=real init_from=rpm_gt_airplane
    linereg.register(a, b, method="rpm_ours_airplane", refine=True)

Names are ``<experiment>_<protocol>``; ``rpm_ours_objects`` is the general model, trained on every
object of the shared data with both pair types and on the Real protocol's room frames
(``configs/dataset/objects_and_rooms.yaml``). Each file is a
linereg checkpoint (:mod:`linereg.checkpoint`) holding the model weights and the run's resolved
config only, with its data paths portable
(:func:`portable_config`): ``${shared_data}`` stands for the shared data folder
(``$LINEREG_SHARED_DATA``, else ``../shared/data`` beside the repository) and ``${cache_dir}`` for
``./data_cache``, the training command's cache of generated pairs.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
SHARED_DATA = "${shared_data}"
CACHE_DIR = "${cache_dir}"


@dataclass(frozen=True)
class Pretrained:
    """One shipped network.

    Attributes:
        name: ``<experiment>_<protocol>`` (``_objects``: every object), the file ``linereg/weights/<name>.pt``.
        description: one line: the backbone, the loss and the data it learned from.
        command: the ``linereg-train`` command that trained it.
        test_err_r_deg: mean rotation error (degrees) on its protocol's test pairs, as
            ``linereg-evaluate checkpoint=<name>`` prints it.
    """

    name: str
    description: str
    command: str
    test_err_r_deg: float

    @property
    def file(self) -> Path:
        return WEIGHTS_DIR / f"{self.name}.pt"


def _cell(experiment: str, protocol: str, description: str, err_r: float) -> Pretrained:
    """A recipe cell at seed 0 (``scripts/reproduce_recipe.sh``, docs/results.md)."""
    command = f"linereg-train experiment={experiment} protocol={protocol} seed=0"
    return Pretrained(f"{experiment}_{protocol}", description, command, err_r)


_AIRPLANE = "ModelNet40 airplanes, two partial views (Airplane protocol)"
_HUMAN = "a partial view against the whole body of 3 SMPL/SMPL-X bodies (Human protocol)"
_REAL = "7-Scenes depth frames 20 apart, frames 0-399 (Real protocol)"
_OBJECTS = (
    "every object of the shared data: ModelNet40 airplanes and 7 other classes, 3 SMPL/SMPL-X bodies, a bunny "
    "and a plane mesh, partial views against a second view or the whole shape; and the Real protocol's "
    "7-Scenes depth frames 0-399"
)
_ENTRIES = (
    _cell("rpm_gt", "airplane", f"RPM-Net, supervised (ground-truth poses), on {_AIRPLANE}", 1.995),
    _cell("rpm_cd", "airplane", f"RPM-Net, Chamfer distance, no labels, on {_AIRPLANE}", 3.555),
    _cell("rpm_ours", "airplane", f"RPM-Net, line-intersection loss, no labels, on {_AIRPLANE}", 2.248),
    _cell("rpm_gt", "human", f"RPM-Net, supervised (ground-truth poses), on {_HUMAN}", 2.016),
    _cell("rpm_cd", "human", f"RPM-Net, Chamfer distance, no labels, on {_HUMAN}", 2.361),
    _cell("rpm_ours", "human", f"RPM-Net, line-intersection loss, no labels, on {_HUMAN}", 2.300),
    _cell("rpm_gt", "real", f"RPM-Net, supervised (camera poses), on {_REAL}", 5.644),
    _cell("rpm_cd", "real", f"RPM-Net, Chamfer distance, no labels, on {_REAL}", 5.955),
    _cell("rpm_ours", "real", f"RPM-Net, line-intersection loss, no labels, on {_REAL}", 5.141),
    Pretrained(
        "rpm_ours_objects",
        f"RPM-Net, line-intersection loss, no labels, on {_OBJECTS}",
        "linereg-train experiment=rpm_ours protocol=airplane dataset=objects_and_rooms task_name=rpm_ours_objects "
        "seed=0",
        5.872,
    ),
)
REGISTRY: dict[str, Pretrained] = {entry.name: entry for entry in _ENTRIES}


def names() -> list[str]:
    """The shipped names, sorted."""
    return sorted(REGISTRY)


def entry(name: str) -> Pretrained:
    """The :class:`Pretrained` record of ``name``.

    Raises:
        KeyError: an unknown name; the message lists the shipped ones.
    """
    if name not in REGISTRY:
        raise KeyError(f"no pretrained weights named {name!r} (shipped: {', '.join(names())})")
    return REGISTRY[name]


def path(name: str) -> Path:
    """The checkpoint file of ``name``.

    Raises:
        KeyError: an unknown name.
        FileNotFoundError: the package was installed without its weights.
    """
    file = entry(name).file
    if not file.is_file():
        raise FileNotFoundError(f"pretrained weights {name!r}: {file} is missing from this installation")
    return file


def is_name(value: Any) -> bool:
    """Whether ``value`` is a shipped name (and not a path)."""
    return isinstance(value, str) and value in REGISTRY


def _map_strings(value: Any, function: Callable[[str], str]) -> Any:
    """``value`` (nested mappings and lists) with ``function`` applied to every string."""
    if isinstance(value, Mapping):
        return {key: _map_strings(item, function) for key, item in value.items()}
    if isinstance(value, list):
        return [_map_strings(item, function) for item in value]
    return function(value) if isinstance(value, str) else value


def portable_config(config: Any, shared_data: str | Path, cache_dir: str | Path) -> Any:
    """``config`` (nested dicts and lists) with every absolute path under ``shared_data`` or
    ``cache_dir`` rewritten to start with ``${shared_data}`` or ``${cache_dir}``."""
    prefixes = ((str(Path(shared_data).resolve()), SHARED_DATA), (str(Path(cache_dir).resolve()), CACHE_DIR))

    def portable(value: str) -> str:
        if not os.path.isabs(value):
            return value
        resolved = str(Path(value).resolve())
        for prefix, marker in prefixes:
            if resolved == prefix or resolved.startswith(prefix + os.sep):
                return marker + resolved[len(prefix) :]
        return value

    return _map_strings(config, portable)


def local_config(config: Any) -> Any:
    """Inverse of :func:`portable_config` on this machine: ``${shared_data}`` becomes the shared
    data folder (``$LINEREG_SHARED_DATA``, else ``../shared/data`` beside the repository, else
    ``./shared_data`` so that the error names a path), ``${cache_dir}`` becomes ``./data_cache``."""
    from linereg.paths import shared_data_dir

    shared = shared_data_dir() or Path(os.environ.get("LINEREG_SHARED_DATA") or "shared_data").resolve()
    markers = ((SHARED_DATA, str(shared)), (CACHE_DIR, str(Path("data_cache").resolve())))

    def local(value: str) -> str:
        for marker, folder in markers:
            if value.startswith(marker):
                return folder + value[len(marker) :]
        return value

    return _map_strings(config, local)
