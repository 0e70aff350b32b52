"""`Registry`: the names of one pluggable kind (MVS backbones, samplers, field kinds, scene
formats, mesh methods) and what each name builds, filled by a decorator where the piece is
written.

Each kind has one `Registry` and no wrapper functions of its own: the piece's module decorates it
with ``REGISTRY.register(name, **declared)`` (the kind's module names that bound method
``register_<kind>`` for its pieces to import), and readers call ``REGISTRY.get(name)`` and
``REGISTRY.names()``. What a piece declares beside its name (the options it reads, what it can
do) goes into its entry, built by the registry's ``entry`` function, so callers ask the entry and
never compare a name.

A registry knows the package its pieces live in and the decorator that registers them: the first
time it is read, it imports every module of that package whose source uses the decorator
(``@register_backbone(`` in ``svolsdf/mvs/*.py``, say). Adding a piece is then one file with one
decorator: no list of modules is edited, and no module is imported before a name is asked for.
A piece written elsewhere (a test, a plugin) is registered when its module is imported.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Generic, TypeVar

from svolsdf.errors import InputError

__all__ = ["DeclaresOptions", "Registry"]

T = TypeVar("T")


class DeclaresOptions:
    """A registry entry that declares the config options its piece reads, as ``options``: a
    tuple of dotted keys of the run's config (``"mesh.poisson.depth"``), or a function of the
    config returning them (options that act only with others set). What the piece's result
    depends on is then asked, not known by name: ``entry.reads(cfg)``."""

    options: tuple[str, ...] | Callable[[Any], tuple[str, ...]] = ()

    def option_keys(self, cfg: Any) -> tuple[str, ...]:
        """The dotted keys of the options the piece reads under ``cfg``."""
        return tuple(self.options(cfg) if callable(self.options) else self.options)

    def reads(self, cfg: Any) -> dict[str, Any]:
        """{dotted key: value} of the options the piece reads under ``cfg``, in declaration
        order."""
        out = {}
        for key in self.option_keys(cfg):
            value = cfg
            for part in key.split("."):
                value = getattr(value, part)
            out[key] = value
        return out


class Registry(Generic[T]):
    """Name -> entry of one kind, in registration order (or sorted by name).

    Args:
        kind: what a name names, for messages ("MVS backbone").
        package: the package whose modules hold the built-in pieces ("svolsdf.mvs").
        decorator: the registering decorator's name ("register_backbone"); a module of
            ``package`` whose source contains ``@decorator(`` is imported on the first read.
        sort: `names` in alphabetical order instead of registration order.
        entry: ``entry(name, obj, *args, **declared)`` -> the entry `register` stores for the
            decorated ``obj`` (default: ``obj`` itself; a declaration is then refused).
    """

    def __init__(self, kind: str, package: str, decorator: str, sort: bool = False,
                 entry: Callable[..., T] | None = None):
        self.kind = kind
        self.package = package
        self.marker = f"@{decorator}("
        self.sort = sort
        self._entry = entry
        self._entries: dict[str, T] = {}
        self._discovered = False

    def add(self, name: str, entry: T) -> T:
        """Register ``entry`` under ``name`` (a later entry of the same name replaces it)."""
        self._entries[name] = entry
        return entry

    def remove(self, name: str) -> None:
        """Withdraw ``name`` (a test's piece, say); unknown names are ignored."""
        self._entries.pop(name, None)

    def _discover(self) -> None:
        """Import the package's modules that register pieces (once)."""
        if self._discovered:
            return
        self._discovered = True  # before the imports: a module may read the registry
        try:
            pkg = importlib.import_module(self.package)
            for path in sorted(Path(p) for d in pkg.__path__ for p in Path(d).glob("*.py")):
                if path.stem != "__init__" and self.marker in path.read_text(encoding="utf-8"):
                    importlib.import_module(f"{self.package}.{path.stem}")
        except BaseException:
            self._discovered = False
            raise

    def names(self) -> list[str]:
        """The registered names (the built-in ones discovered first)."""
        self._discover()
        return sorted(self._entries) if self.sort else list(self._entries)

    def items(self) -> Iterator[tuple[str, T]]:
        """(name, entry) pairs in `names` order."""
        return ((n, self._entries[n]) for n in self.names())

    def get(self, name: str) -> T:
        """The entry registered as ``name``.

        Raises:
            InputError: no entry has that name (the message lists the available ones).
        """
        if name not in self._entries:
            self._discover()
        if name not in self._entries:
            raise InputError(f"unknown {self.kind} {name!r} (available: {', '.join(self.names())})")
        return self._entries[name]

    def __contains__(self, name: object) -> bool:
        self._discover()
        return name in self._entries

    def register(self, name: str, *args: Any, **declared: Any) -> Callable[[Any], Any]:
        """A decorator registering ``entry(name, obj, *args, **declared)`` under ``name`` and
        returning ``obj`` unchanged: ``@BACKBONES.register("planesweep")``,
        ``@MESH_METHODS.register("poisson", needs_points=True, options=(...))``.

        Raises:
            TypeError: a declaration given to a registry whose entries are the objects alone.
        """
        if self._entry is None and (args or declared):
            raise TypeError(f"a {self.kind} declares nothing beside its name")

        def deco(obj):
            self.add(name, obj if self._entry is None else
                     self._entry(name, obj, *args, **declared))
            return obj

        return deco

    def decorator(self, name: str, make: Callable[[Any], T] | None = None):
        """A decorator registering ``make(obj)`` (default: ``obj`` itself) under ``name`` and
        returning ``obj`` unchanged."""

        def deco(obj):
            self.add(name, make(obj) if make is not None else obj)
            return obj

        return deco
