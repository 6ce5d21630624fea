"""Shared pytest fixtures."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from linereg.paths import shared_data_dir

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def compose_config(
    name: str, overrides: Sequence[str] = (), *, config_dir: Path = CONFIGS, hydra: bool = False
) -> DictConfig:
    """``configs/<name>.yaml`` (or ``<config_dir>/<name>.yaml``) composed with ``overrides``, outside
    any Hydra run, as its command composes it; ``hydra=True`` keeps the ``hydra`` node."""
    with initialize_config_dir(str(config_dir), version_base="1.3"):
        return compose(name, overrides=[*overrides], return_hydra_config=hydra)


def compose_register(**values: Any) -> DictConfig:
    """``configs/register/register.yaml`` with ``key=value`` overrides, as ``linereg-register`` composes it."""
    overrides = [f"{key}={value}" for key, value in values.items()]
    return compose_config("register", overrides, config_dir=CONFIGS / "register")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared real-data folder; skips the test when it is absent (a user's fresh clone)."""
    path = shared_data_dir()
    if path is None:
        pytest.skip("shared data not found: set $LINEREG_SHARED_DATA or place it at ../shared/data")
    return path


@pytest.fixture(scope="module")
def one_torch_thread():
    """One intra-op torch thread for a module of tiny tensors: avoids OpenMP stalls on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def hydra_compose() -> Callable[..., DictConfig]:
    """:func:`compose_config`: ``hydra_compose("train", ["experiment=rpm_ours"])``."""
    return compose_config
