"""Name -> builder registries (timm style), shared by ``losses/`` and ``models/``.

A builder is registered by a decorator when its module is imported; ``build(name, **kwargs)``
checks the name first and lists the valid names when it is unknown.
"""

from __future__ import annotations

import fnmatch
import warnings
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """A named collection of builders returning ``T``.

    Example:
        >>> LOSSES = Registry("loss")
        >>> @LOSSES.register("zero")
        ... def _zero(**kwargs):
        ...     return 0
        >>> LOSSES.build("zero")
        0
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._builders: dict[str, Callable[..., T]] = {}
        self._metadata: dict[str, dict[str, Any]] = {}

    def register(self, name: str, **metadata: Any) -> Callable[[Callable[..., T]], Callable[..., T]]:
        """Decorator recording ``builder`` under ``name`` (with optional metadata)."""

        def decorator(builder: Callable[..., T]) -> Callable[..., T]:
            if name in self._builders:
                warnings.warn(f"{self.kind} {name!r} registered twice; the later one wins", stacklevel=2)
            self._builders[name] = builder
            self._metadata[name] = dict(metadata)
            return builder

        return decorator

    def build(self, name: str, **kwargs: Any) -> T:
        """Build the object registered as ``name`` with keyword arguments ``kwargs``."""
        return self.get(name)(**kwargs)

    def get(self, name: str) -> Callable[..., T]:
        """The builder registered as ``name``; ``KeyError`` listing the valid names otherwise."""
        if name not in self._builders:
            raise KeyError(f"unknown {self.kind} {name!r}; registered: {', '.join(self.names()) or '(none)'}")
        return self._builders[name]

    def metadata(self, name: str) -> dict[str, Any]:
        """Metadata given at registration (e.g. ``needs_gt``)."""
        self.get(name)
        return dict(self._metadata[name])

    def names(self, pattern: str = "*") -> list[str]:
        """Sorted registered names matching a shell-style wildcard ``pattern``."""
        return sorted(n for n in self._builders if fnmatch.fnmatch(n, pattern))

    def __contains__(self, name: str) -> bool:
        return name in self._builders
