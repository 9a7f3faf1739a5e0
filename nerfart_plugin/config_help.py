"""The schema as Hydra and users see it: the defaults node Hydra composes first (:data:`SCHEMA_NODE`), the
``--help`` text, and the rows of the settings reference."""

from __future__ import annotations

import typing
from typing import Any

from pydantic import BaseModel

from nerfart_plugin.config_components import COMPONENTS
from nerfart_plugin.config_issues import _model_in, show
from nerfart_plugin.config_types import changes_results
from nerfart_plugin.schema import RunConfig


#: name of the schema's defaults in Hydra's ConfigStore (first entry of conf/config.yaml's defaults list)
SCHEMA_NODE = "nerfart_schema"


def defaults_node() -> dict[str, Any]:
    """Every default of the sections with fixed keys, as the plain dict Hydra composes first, plus
    ``hydra.help.template`` listing every setting with its description (``--help``)."""
    node = RunConfig().model_dump(mode="json", exclude=set(COMPONENTS))
    node["hydra"] = {"help": {"template": help_template()}}
    return node


def register_schema() -> None:
    """Store :func:`defaults_node` in Hydra's ConfigStore as :data:`SCHEMA_NODE` (idempotent); done by
    :func:`nerfart_plugin.config_paths.config_dir`, i.e. before anything composes ``conf/``."""
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
