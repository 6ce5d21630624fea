"""Fine-tuning (``init_from=<network>``): the run keeps what the start network was trained with.

A network scores the pairs the way it learned them: its points per cloud
(``trainer.num_points``), the cube its pairs were scaled into (``dataset.half_extent``, where the
dataset has one; the cube :func:`linereg.register` scales into) and the rule choosing the iterate
it is judged on (``iterate.*``). A fine-tuning run takes these from the start network's config,
except the keys given on the command line, and evaluates the checkpoint its validation chose
(``best.pt``; the start network is a candidate, :class:`linereg.train.loop.Trainer`). Each value
that differs from the composed config is logged.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from linereg.checkpoint import load_checkpoint
from linereg.registration.learned import upgrade_checkpoint

log = logging.getLogger(__name__)


def start_settings(start: Mapping[str, Any], dataset: Mapping[str, Any]) -> dict[str, Any]:
    """``{dotted key: value}`` a fine-tuning run takes from its start network's checkpoint.

    Args:
        start: the start network's checkpoint (:func:`~linereg.registration.learned.upgrade_checkpoint`:
            its ``half_extent``, and its resolved run ``config``).
        dataset: the fine-tuning run's dataset config (``half_extent`` is kept only where it has one).
    """
    start_config = start["config"]
    settings: dict[str, Any] = {"trainer.num_points": start_config["trainer"]["num_points"]}
    settings.update({f"iterate.{key}": value for key, value in (start_config.get("iterate") or {}).items()})
    if "half_extent" in dataset:
        settings["dataset.half_extent"] = start["half_extent"]
    settings["trainer.evaluate_checkpoint"] = "best"
    return settings


def given_keys(overrides: Sequence[str] | None) -> set[str]:
    """The dotted keys set by command-line overrides (``+key=...``, ``key=...``; none for ``~key``).
    A key given a mapping (``key={...}``) sets its children too and ends in ``.*``; ``dataset=scan_folder``
    chooses a config file and sets none of ``dataset``'s keys itself."""
    keys = set()
    for override in overrides or ():
        key, _, value = override.partition("=")
        key = key.lstrip("+")
        if "=" in override and not key.startswith("~"):
            keys.add(f"{key}.*" if value.lstrip().startswith("{") else key)
    return keys


def keep_start_settings(cfg: DictConfig, overrides: Sequence[str] | None) -> list[str]:
    """Set ``cfg``'s :func:`start_settings` from ``cfg.init_from`` except the keys of ``overrides``.

    Args:
        cfg: the composed run config, changed in place (interpolations of the keys follow them).
        overrides: the command line's overrides (``None``: none known, every setting is kept).

    Returns:
        One line per setting that differs from the composed config (also logged).
    """
    start = upgrade_checkpoint(load_checkpoint(cfg.init_from))
    name = cfg.init_from
    given = given_keys(overrides)
    notes = []
    for key, value in start_settings(start, cfg.dataset).items():
        current = OmegaConf.select(cfg, key)
        if current == value:
            continue
        if key in given or any(key.startswith(parent[:-1]) for parent in given if parent.endswith(".*")):
            notes.append(f"{key}={current!r} from the command line; {name} was trained with {value!r}")
            continue
        with open_dict(cfg):
            OmegaConf.update(cfg, key, value, force_add=True)
        reason = (
            "fine-tuning evaluates the checkpoint validation chose"
            if key.endswith("evaluate_checkpoint")
            else (f"as {name} was trained")
        )
        notes.append(f"{key}={value!r} ({reason}; the config said {current!r})")
    for note in notes:
        log.info("init_from: %s", note)
    return notes
