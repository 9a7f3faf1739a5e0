"""``auto`` settings: each is decided in one named place, and a run records what it became."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from pipeline_helpers import composed

from nerfart_plugin.config.auto import AUTO_SETTINGS, component_choices, recorded, setting_of
from nerfart_plugin.config.compose import config_dir


def _auto_keys(node: dict, prefix: str = "") -> set[str]:
    keys = set()
    for k, v in node.items():
        if isinstance(v, dict):
            keys |= _auto_keys(v, f"{prefix}{k}.")
        elif v == "auto":
            keys.add(f"{prefix}{k}")
    return keys


def test_every_auto_setting_names_where_it_is_decided():
    """Over every option of every component group, the settings whose default is ``auto`` are exactly the
    table's: a new ``auto`` setting fails here until it names its resolver (and a stale entry fails too)."""
    found: set[str] = set()
    for group in ("data", "backbone", "encoding", "guidance"):
        for option in sorted((config_dir() / group).glob("*.yaml")):
            cfg = OmegaConf.to_container(composed(f"{group}={option.stem}", "+prompt=Joker"), resolve=False)
            found |= _auto_keys(cfg)
    assert found == set(AUTO_SETTINGS), (sorted(found - set(AUTO_SETTINGS)), sorted(set(AUTO_SETTINGS) - found))


def test_the_record_keeps_what_was_auto_and_refuses_an_unnamed_setting():
    cfg = {"encoding": {"resolution": "auto", "levels": 4}, "device": "auto", "data": {"name": "h3ds"}}
    block = recorded(cfg, {"encoding.resolution": 256, "encoding.levels": 4, "device": torch.device("cpu"),
                           "data.resolution": 256})
    assert block == {"encoding.resolution": 256, "device": "cpu"}  # levels was set by the user; no data.resolution
    assert setting_of(cfg, "encoding.resolution") == "auto" and setting_of(cfg, "render.resolution") is None
    with pytest.raises(KeyError, match="AUTO_SETTINGS"):
        recorded(cfg, {"encoding.new_knob": 3})


def test_components_report_what_their_auto_became():
    from nerfart_plugin.fields import build_field
    from nerfart_plugin.guidance.toy import ToyGuidance

    grid = build_field({"name": "volsdf"}, encoding_cfg={"name": "grid", "resolution": 32, "levels": 1})
    freq = build_field({"name": "volsdf"}, encoding_cfg={"name": "frequency"})
    cpu = torch.device("cpu")
    # the grid's double backward through grid_sample is slow: auto picks finite differences for it
    assert component_choices(cpu, [grid, None]) == {"backbone.grad_type": "finite_difference"}
    assert component_choices(cpu, [freq])["backbone.grad_type"] == "analytic"
    assert component_choices(cpu, [ToyGuidance()]) == {}  # a component without auto settings reports nothing


def test_every_deciding_function_named_in_the_table_exists():
    """AUTO_SETTINGS names a module and a function (or class attribute) of the package for each setting; a move
    that forgets the table fails here."""
    import importlib

    for setting, where in AUTO_SETTINGS.items():
        dotted = where.split(" ")[0] if not where.startswith("Lightning") else where.split("(")[1].rstrip(")")
        parts = dotted.split(".")
        for cut in range(len(parts) - 1, 0, -1):
            try:
                obj = importlib.import_module("nerfart_plugin." + ".".join(parts[:cut]))
            except ModuleNotFoundError:
                continue
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
            break
        else:
            raise AssertionError(f"{setting}: {where} names no module of the package")
