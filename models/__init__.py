"""Registration models and their registry (timm style).

Every model maps a :class:`linereg.structures.PairBatch` to a
:class:`linereg.structures.RegistrationOutput`. Importing this package registers the builders
``dcp_v1``, ``dcp_v2``, ``rpmnet`` and ``fmr``; :func:`build_model` creates one from a config
mapping ``{name: ..., **kwargs}``.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from torch import nn

from linereg.registry import Registry

MODELS: Registry[nn.Module] = Registry("model")

# Imported after MODELS exists: each module registers its builders on import.
from . import dcp, fmr, rpmnet  # noqa: E402

__all__ = ["MODELS", "build_model", "dcp", "fmr", "list_models", "rpmnet"]


def build_model(config: Mapping[str, Any]) -> nn.Module:
    """Build a registered model from ``{name: <registered name>, **kwargs}``.

    Raises:
        KeyError: no ``name``, or an unknown one (the message lists the registered models).
        TypeError: a keyword argument the model's builder does not accept (the message names
            the model and lists the accepted arguments).
    """
    options = dict(config)
    if "name" not in options:
        raise KeyError(f"a model config needs a 'name', one of {', '.join(MODELS.names())}")
    name = options.pop("name")
    builder = MODELS.get(name)
    accepted = inspect.signature(builder).parameters
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise TypeError(f"model {name!r} got unknown argument(s) {unknown}; it accepts {sorted(accepted)}")
    return builder(**options)


def list_models(pattern: str = "*") -> list[str]:
    """Sorted names of the registered models matching a shell-style wildcard ``pattern``."""
    return MODELS.names(pattern)
