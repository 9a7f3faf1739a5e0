"""Where the Hydra configs live: a checkout's ``conf/`` or the installed ``nerfart_plugin.conf``."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from nerfart_plugin.errors import ConfigError


def config_dir() -> Path:
    """Absolute path of the folder holding ``config.yaml``.

    A checkout (``<repo>/conf``) wins over an installed copy so that edits to a
    checkout take effect; a wheel installs the same folder as the package
    ``nerfart_plugin.conf``. Also registers the schema's defaults in Hydra's ConfigStore
    (:func:`nerfart_plugin.config_help.register_schema`), which ``config.yaml`` composes first.
    """
    from nerfart_plugin.config_help import register_schema

    register_schema()
    checkout = Path(__file__).resolve().parents[1] / "conf"
    if (checkout / "config.yaml").is_file():
        return checkout
    # a wheel installs conf/ as nerfart_plugin/conf (a namespace package without
    # __init__.py, for which importlib.resources.files() returns a MultiplexedPath)
    installed = Path(__file__).resolve().parent / "conf"
    if (installed / "config.yaml").is_file():
        return installed
    try:
        from importlib.resources import files

        installed = Path(str(files("nerfart_plugin.conf")))
        if (installed / "config.yaml").is_file():
            return installed
    except ModuleNotFoundError:
        pass
    raise ConfigError(
        f"Could not find the configs: neither {checkout}/config.yaml nor the installed package "
        "nerfart_plugin.conf exists. Reinstall with `pip install -e .` from the repository."
    )


def primary_keys() -> set[str]:
    """Config groups and top-level keys of the primary config (keys that already have a default)."""
    root = config_dir()
    groups = {p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(("_", "."))}
    from nerfart_plugin.schema import RunConfig

    top = set(OmegaConf.load(root / "config.yaml").keys()) | set(RunConfig.model_fields)
    return groups | top


def group_options(group: str) -> list[str]:
    """Option names of a config group (file stems), e.g. ``backbone`` -> [nerf, neus, volsdf]."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))
