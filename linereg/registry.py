"""Name -> builder registries, one idiom for every layer (losses, models, datasets, methods, ...).

A builder (a class or a function) is registered under a name when its module is imported, and
built from a config ``{name: <registered name>, **kwargs}`` (a mapping or an OmegaConf config)::

    >>> LOSSES = Registry("loss")
    >>> @LOSSES.register("zero")
    ... class Zero:
    ...     def __init__(self, scale: float = 1.0):
    ...         self.scale = scale
    >>> LOSSES.build({"name": "zero", "scale": 2.0}).scale
    2.0

An unknown name raises :class:`UnknownNameError` (a ``KeyError``) listing the registered names;
an argument the builder does not take, or a required one that is missing, raises
:class:`ArgumentError` (a ``TypeError`` and a ``ValueError``) naming it and the accepted ones.
"""

from __future__ import annotations

import fnmatch
import inspect
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class UnknownNameError(KeyError):
    """A name that is not registered; the message lists the registered names."""

    def __str__(self) -> str:
        return str(self.args[0])


class ArgumentError(TypeError, ValueError):
    """A config key the builder does not accept, or a required one missing; the message names them."""


def plain(config: Any) -> Any:
    """A plain, resolved Python container from an OmegaConf config (other values unchanged).

    OmegaConf is imported only when ``config`` is one of its containers.
    """
    if type(config).__module__.startswith("omegaconf"):
        from omegaconf import OmegaConf

        return OmegaConf.to_container(config, resolve=True)
    return config


def keywords_of(target: Callable, *, without: Sequence[str] = ()) -> Callable[[Callable], Callable]:
    """Decorator: a builder that passes ``**options`` on to ``target`` names ``target``'s keyword
    parameters (less ``without``) beside its own in its signature, so that :meth:`Registry.build`
    checks a config's keys against them (and lists them) without the builder restating them."""

    def decorate(builder: Callable) -> Callable:
        keyword = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        own = [p for p in inspect.signature(builder).parameters.values() if p.kind in keyword]
        taken = {p.name for p in own} | set(without)
        passed = [p for p in inspect.signature(target).parameters.values() if p.kind in keyword and p.name not in taken]
        parameters = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in (*passed, *own)]
        builder.__signature__ = inspect.signature(builder).replace(parameters=parameters)
        return builder

    return decorate


def _keyword_parameters(function: Callable, positional: int) -> list[str] | None:
    """Names ``function`` takes by keyword after its first ``positional`` ones; ``None`` with ``**kwargs``."""
    parameters = list(inspect.signature(function).parameters.values())
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return None
    keyword = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return [p.name for p in parameters[positional:] if p.kind in keyword]


class Registry(Generic[T]):
    """A named collection of builders returning ``T``.

    Args:
        kind: what is registered, for messages (``"loss"``, ``"model"``, ...).
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._builders: dict[str, Callable[..., T]] = {}
        self._metadata: dict[str, dict[str, Any]] = {}

    def register(self, name: str, **metadata: Any) -> Callable[[Callable[..., T]], Callable[..., T]]:
        """Decorator recording a class or function under ``name`` (with optional metadata)."""

        def decorator(builder: Callable[..., T]) -> Callable[..., T]:
            if name in self._builders:
                warnings.warn(f"{self.kind} {name!r} registered twice; the later one wins", stacklevel=2)
            self._builders[name] = builder
            self._metadata[name] = dict(metadata)
            return builder

        return decorator

    def build(self, config: Mapping[str, Any] | str, *args: Any, **kwargs: Any) -> T:
        """Build from ``{name: ..., **options}`` (or a bare name); ``kwargs`` join the options.

        Args:
            config: a mapping or OmegaConf config with ``name``; the other keys are the builder's
                keyword arguments. A string is a name without options.
            *args: positional arguments put before the options (e.g. an optimiser's parameters).
            **kwargs: further options (e.g. set by the caller rather than the user's config).

        Raises:
            UnknownNameError: no ``name``, or one that is not registered (lists the valid ones).
            ArgumentError: unknown or missing arguments (names them and the accepted ones).
        """
        options = {"name": config} if isinstance(config, str) else plain(config)
        if not isinstance(options, Mapping):
            raise TypeError(f"a {self.kind} config must be a mapping {{name: ..., **options}}, got {options!r}")
        options = dict(options)
        if "name" not in options:
            raise UnknownNameError(f"a {self.kind} config needs a 'name', one of: {self._listing()}")
        name = options.pop("name")
        clash = sorted(set(options) & set(kwargs))
        if clash:
            raise ArgumentError(f"{self.kind} {name!r}: {clash} given both in the config and by the caller")
        options.update(kwargs)
        builder = self.get(name)
        self._check_arguments(name, builder, len(args), options)
        if self.accepted(name, len(args)) is not None:
            return builder(*args, **options)
        try:  # a builder taking **kwargs checks them itself: name it in its complaint
            return builder(*args, **options)
        except TypeError as error:
            raise ArgumentError(f"{self.kind} {name!r}: {error}") from error

    def accepted(self, name: str, positional: int = 0) -> list[str] | None:
        """Keyword arguments the builder of ``name`` takes (``None``: any, it has ``**kwargs``)."""
        return _keyword_parameters(self.get(name), positional)

    def _check_arguments(self, name: str, builder: Callable[..., T], positional: int, options: Mapping) -> None:
        accepted = self.accepted(name, positional)
        if accepted is None:
            return
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise ArgumentError(f"{self.kind} {name!r} got unknown argument(s) {unknown}; it accepts {accepted}")
        parameters = list(inspect.signature(builder).parameters.values())[positional:]
        missing = [p.name for p in parameters if p.default is p.empty and p.name in accepted and p.name not in options]
        if missing:
            raise ArgumentError(f"{self.kind} {name!r} needs argument(s) {missing}; it accepts {accepted}")

    def get(self, name: str) -> Callable[..., T]:
        """The builder registered as ``name``; :class:`UnknownNameError` listing the valid names otherwise."""
        if name not in self._builders:
            raise UnknownNameError(f"unknown {self.kind} {name!r}; registered: {self._listing()}")
        return self._builders[name]

    def metadata(self, name: str) -> dict[str, Any]:
        """Metadata given at registration (e.g. ``needs_gt``), as a copy."""
        self.get(name)
        return dict(self._metadata[name])

    def names(self, pattern: str = "*") -> list[str]:
        """Sorted registered names matching a shell-style wildcard ``pattern``."""
        return sorted(n for n in self._builders if fnmatch.fnmatch(n, pattern))

    def _listing(self) -> str:
        return ", ".join(self.names()) or "(none)"

    def __contains__(self, name: str) -> bool:
        return name in self._builders
