"""The Hydra glue: where ``conf/`` lives (a checkout's or the installed ``nerfart_plugin.conf``), the schema's
defaults node Hydra composes first (:data:`SCHEMA_NODE`), :func:`load_config` (compose as the CLI does), the
``--help`` text and the rows of the settings reference."""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel

from nerfart_plugin.config.issues import _model_in, show
from nerfart_plugin.config.schema import RunConfig
from nerfart_plugin.config.sections import TOP_LEVEL
from nerfart_plugin.config.types import changes_results
from nerfart_plugin.errors import ConfigError

#: name of the schema's defaults in Hydra's ConfigStore (first entry of conf/config.yaml's defaults list)
SCHEMA_NODE = "nerfart_schema"


def defaults_node() -> dict[str, Any]:
    """Every default of the sections with fixed keys, as the plain dict Hydra composes first, plus
    ``hydra.help.template`` listing every setting with its description (``--help``)."""
    defaults = {name: info.get_default(call_default_factory=True) for name, info in RunConfig.model_fields.items()
                if name not in TOP_LEVEL}  # the component sections come from their groups (conf/data/...)
    node = RunConfig.model_construct(**defaults).model_dump(mode="json", exclude=set(TOP_LEVEL))
    node["hydra"] = {"help": {"template": help_template()}}
    return node


def register_schema() -> None:
    """Store :func:`defaults_node` in Hydra's ConfigStore as :data:`SCHEMA_NODE` (idempotent); done by
    :func:`nerfart_plugin.config.compose.config_dir`, i.e. before anything composes ``conf/``."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=SCHEMA_NODE, node=defaults_node())


def settings_rows(model: type[BaseModel] = None, prefix: str = "") -> list[tuple[str, str, str, bool]]:
    """Every setting of the sections with fixed keys as ``(dotted key, default as typed, description, in the
    cache key)``: what ``--help`` and the documentation's settings reference list."""
    rows: list[tuple[str, str, str, bool]] = []
    for name, info in (model or RunConfig).model_fields.items():
        sub = _model_in(info.annotation)
        if sub is not None:
            rows += settings_rows(sub, f"{prefix}{name}.")
            continue
        if typing.get_origin(info.annotation) is dict:
            continue  # component sections: their config groups
        default = info.get_default(call_default_factory=True)
        rows.append((f"{prefix}{name}", default if isinstance(default, str) else show(default),
                     info.description or "", changes_results(info)))
    return rows


def _settings_lines(model: type[BaseModel], prefix: str = "") -> list[str]:
    return [f"  {key}={default}: {text}{'' if cached else ' [not in the cache key]'}"
            for key, default, text, cached in settings_rows(model, prefix)]


def help_text() -> str:
    """Every setting of the sections with fixed keys, ``key=default: description``, one per line."""
    return "\n".join(_settings_lines(RunConfig))


def help_template() -> str:
    """Hydra's ``--help`` template: header, config groups, then :func:`help_text` instead of the raw config."""
    text = help_text().replace("${", "$\\{")
    return ("${hydra.help.header}\n== Configuration groups ==\nCompose your configuration from those groups "
            "(group=option)\n\n$APP_CONFIG_GROUPS\n\n== Settings (key=default: meaning) ==\n"
            "Override any of them with key=value; the component groups (data, backbone, encoding, guidance) take\n"
            "the settings of the component they name (see --cfg job).\n\n" + text + "\n\n${hydra.help.footer}\n")



def config_dir() -> Path:
    """Absolute path of the folder holding ``config.yaml``.

    A checkout (``<repo>/conf``) wins over an installed copy so that edits to a
    checkout take effect; a wheel installs the same folder as the package
    ``nerfart_plugin.conf``. Also registers the schema's defaults in Hydra's ConfigStore
    (:func:`nerfart_plugin.config.compose.register_schema`), which ``config.yaml`` composes first.
    """
    register_schema()
    checkout = Path(__file__).resolve().parents[2] / "conf"
    if (checkout / "config.yaml").is_file():
        return checkout
    # a wheel installs conf/ as nerfart_plugin/conf (a namespace package without
    # __init__.py, for which importlib.resources.files() returns a MultiplexedPath)
    installed = Path(__file__).resolve().parents[1] / "conf"
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
    top = set(OmegaConf.load(root / "config.yaml").keys()) | set(RunConfig.model_fields)
    return groups | top


def group_options(group: str) -> list[str]:
    """Option names of a config group (file stems), e.g. ``backbone`` -> [nerf, neus, volsdf]."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def load_config(overrides: Sequence[str] = ()) -> DictConfig:
    """``conf/config.yaml`` (on the schema's defaults) composed with Hydra ``overrides``, as the CLI does."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))
