"""Third-party components without a fork: entry points.

A distribution registers components (backbones, encodings, data loaders,
guidance) with the ``@nerfart_plugin.config.registry.register`` decorator in a module
and names that module in the entry-point group ``nerfart_plugin.config.components``;
its Hydra config groups (``backbone/mine.yaml``, ...) go in a package named in
``nerfart_plugin.configs``, which the CLI appends to Hydra's config search path
(:func:`searchpath_overrides`)::

    [project.entry-points."nerfart_plugin.components"]
    my_backbone = "my_backbone_plugin.fields"
    [project.entry-points."nerfart_plugin.configs"]
    my_backbone = "my_backbone_plugin.conf"

The component modules are imported the first time the registry is asked for
a name (:func:`load_components`); a module that fails to import is a
ConfigError naming the distribution and the entry point.
"""

from __future__ import annotations

import functools
import logging
import sys
from importlib.metadata import EntryPoint, entry_points

from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

COMPONENTS_GROUP = "nerfart_plugin.components"
CONFIGS_GROUP = "nerfart_plugin.configs"
_loaded: set[str] = set()


def _entry_points(group: str) -> list[EntryPoint]:
    """The entry points of ``group``, by name: scanned once per ``sys.path`` (a scan reads the metadata of
    every installed distribution, and the registry asks on every lookup)."""
    return _scan(group, tuple(sys.path))


@functools.lru_cache(maxsize=16)
def _scan(group: str, path: tuple[str, ...]) -> list[EntryPoint]:
    return sorted(entry_points(group=group), key=lambda ep: ep.name)


def _origin(ep: EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return f"{dist.name} {dist.version}" if dist is not None else "an unknown distribution"


def load_components() -> list[str]:
    """Import every ``nerfart_plugin.config.components`` entry point once (their ``@register`` decorators run);
    returns the names of the entry points imported by this call."""
    done = []
    for ep in _entry_points(COMPONENTS_GROUP):
        if ep.name in _loaded:
            continue
        _loaded.add(ep.name)
        try:
            ep.load()
        except Exception as exc:  # noqa: BLE001 - any failure of a third-party module gets the same message
            raise ConfigError(f"The plugin entry point {ep.name!r} = {ep.value!r} of {_origin(ep)} failed to "
                              f"import ({type(exc).__name__}: {exc}); fix or uninstall that distribution.") from exc
        log.info("plugin components loaded: %s = %s (%s)", ep.name, ep.value, _origin(ep))
        done.append(ep.name)
    return done


def config_packages() -> list[tuple[str, str]]:
    """``(name, package)`` of every ``nerfart_plugin.configs`` entry point: packages holding config groups."""
    return [(ep.name, ep.value) for ep in _entry_points(CONFIGS_GROUP)]


def searchpath_overrides(argv: list[str]) -> list[str]:
    """``hydra.searchpath=[pkg://...]`` for the config packages of installed plugins, to append to the
    command line (nothing when there are none, or when the user sets ``hydra.searchpath`` already)."""
    packages = config_packages()
    if not packages:
        return []
    if any(a.lstrip("+").startswith("hydra.searchpath=") for a in argv):
        log.info("hydra.searchpath is set on the command line: the plugins' config folders (%s) are not added",
                 ", ".join(p for _, p in packages))
        return []
    return ["hydra.searchpath=[" + ",".join(f"pkg://{p}" for _, p in packages) + "]"]
