"""Name -> class registries for components built from config.

Usage::

    from nerfart_plugin import registry

    @registry.register("backbone", "neus")
    class NeuSField(...): ...

    field = registry.get("backbone", "neus")(**cfg)

Kinds used by the project: ``backbone``, ``encoding``, ``data``, ``guidance``, ``perceptual`` (the
feature networks of Eq. 9). Other
distributions add components through entry points (:mod:`nerfart_plugin.config.plugins`).
"""

from __future__ import annotations

import importlib
from typing import Any, Callable, TypeVar

from nerfart_plugin.config.plugins import load_components
from nerfart_plugin.errors import ConfigError

T = TypeVar("T")

_REGISTRY: dict[str, dict[str, Any]] = {}

# Modules imported lazily the first time a kind is looked up, so that
# registration happens without importing everything at package import time.
_PROVIDERS: dict[str, tuple[str, ...]] = {
    "backbone": ("nerfart_plugin.fields",),
    "encoding": ("nerfart_plugin.fields",),
    "data": ("nerfart_plugin.data",),
    "guidance": ("nerfart_plugin.guidance", "nerfart_plugin.guidance.imagenet"),
    "perceptual": ("nerfart_plugin.guidance", "nerfart_plugin.guidance.imagenet"),
}


def register(kind: str, name: str) -> Callable[[T], T]:
    """Class decorator registering ``cls`` under ``kind``/``name``."""

    def deco(cls: T) -> T:
        table = _REGISTRY.setdefault(kind, {})
        if name in table and table[name] is not cls:
            raise ConfigError(f"{kind} {name!r} registered twice ({table[name]} and {cls})")
        table[name] = cls
        return cls

    return deco


def _load(kind: str) -> dict[str, Any]:
    for mod in _PROVIDERS.get(kind, ()):
        importlib.import_module(mod)
    load_components()  # third-party components (entry points, see nerfart_plugin.config.plugins)
    return _REGISTRY.get(kind, {})


def names(kind: str) -> list[str]:
    """Sorted registered names of ``kind``."""
    return sorted(_load(kind))


def get(kind: str, name: str) -> Any:
    """The class registered as ``kind``/``name``; a ConfigError listing valid names otherwise."""
    table = _load(kind)
    if name not in table:
        valid = ", ".join(sorted(table)) or "(none registered)"
        raise ConfigError(f"Unknown {kind} {name!r}. Valid {kind} names: {valid}.")
    return table[name]
