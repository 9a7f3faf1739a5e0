"""Presets compose to what they promise (ordered by cost), and every backbone builds under each of them."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf
from pipeline_helpers import composed

from nerfart_plugin.fields import build_field


def _cfg(*overrides: str) -> dict:
    return OmegaConf.to_container(composed(*overrides), resolve=True)


def test_paper_preset_is_the_papers_settings() -> None:
    c = _cfg("preset=paper", "backbone=neus")
    assert c["encoding"]["name"] == "frequency"
    assert c["backbone"]["hidden_dim"] == 256 and c["backbone"]["n_layers"] == 8
    assert c["render"]["num_samples"] == 192 and c["data"]["resolution"] == "auto"  # the capture's resolution
    assert c["backbone"]["color_normal"] is True and c["backbone"]["grad_samples"] == 1.0
    assert c["backbone"]["alpha_mode"] == "gradient"
    assert c["stylize"]["resolution"] == "auto" and c["stylize"]["epochs"] == 4


def test_presets_order_by_cost() -> None:
    samples = [_cfg(f"preset={p}")["render"]["num_samples"] for p in ("draft", "balanced", "paper")]
    assert samples == sorted(samples) and len(set(samples)) == 3


def test_draft_is_cheaper_than_balanced() -> None:
    d, b = _cfg("preset=draft"), _cfg("preset=balanced")
    assert d["render"]["num_samples"] < b["render"]["num_samples"]
    assert d["reconstruct"]["steps"] < b["reconstruct"]["steps"]
    assert d["render"]["occupancy"]["resolution"] < b["render"]["occupancy"]["resolution"]


@pytest.mark.parametrize("preset", ["draft", "balanced"])
@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_every_backbone_builds_under_preset(preset: str, backbone: str) -> None:
    c = _cfg(f"preset={preset}", f"backbone={backbone}")
    field = build_field(c["backbone"], c["encoding"])
    assert field.is_sdf == (backbone != "nerf")
