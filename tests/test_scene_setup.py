"""Model only what a scene requires: ``decide_setup`` picks extent, background and empty-space
skipping from the capture type, logs why, and every choice yields to config."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import pytest
import torch

from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.systems.scene_setup import decide_setup

RENDER = {"num_samples": 32, "background_model": "auto", "background_color": [1.0, 1.0, 1.0],
          "occupancy": {"enabled": "auto", "resolution": 64}}


def _scene(capture: str, masks: bool, size: int = 128) -> Scene:
    n = 2
    K = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]]).expand(n, 3, 3).clone()
    c2w = torch.eye(4)[:3].expand(n, 3, 4).clone()
    c2w[:, 2, 3] = -3.0
    return Scene(images=torch.zeros(n, size, size, 3), masks=torch.ones(n, size, size) if masks else None,
                 c2w=c2w, K=K, near=torch.full((n,), 1.0), far=torch.full((n,), 5.0), image_names=["a", "b"],
                 train_ids=[0], val_ids=[1], normalization=torch.eye(4), capture=capture, source=Path("."))


def _render(**over) -> dict:
    r = {**RENDER, "occupancy": dict(RENDER["occupancy"])}
    for k, v in over.items():
        if k.startswith("occ_"):
            r["occupancy"][k[4:]] = v
        else:
            r[k] = v
    return r


@pytest.mark.parametrize("capture,masks,ndc,bg,occ,bound", [
    ("object", True, False, False, 64, 1.0),  # head with mattes: sphere, white background, grid on
    ("unbounded", False, False, True, 64, 1.0),  # selfie video without mattes: environment map behind
    ("unbounded", True, False, False, 64, 1.0),  # with mattes the background is known
    ("forward_facing", False, True, False, 0, 1.5),  # LLFF in NDC: nothing to skip, no background model
])
def test_capture_decides_the_setup(capture: str, masks: bool, ndc: bool, bg: bool, occ: int, bound: float) -> None:
    s = decide_setup(_scene(capture, masks), _render(), ndc=ndc)
    assert (s.background_model, s.occupancy_resolution, s.bound, s.ndc) == (bg, occ, bound, ndc)
    assert s.background_color is None if (ndc or bg) else s.background_color == [1.0, 1.0, 1.0]
    assert len(s.reasons) >= 3 and all(isinstance(r, str) and r for r in s.reasons)
    if ndc:
        assert any("NDC frustum" in r for r in s.reasons)


def test_every_choice_yields_to_config() -> None:
    fern = _scene("forward_facing", False)
    assert decide_setup(fern, _render(occ_enabled=True), ndc=True).occupancy_resolution == 64
    head = _scene("object", True)
    s = decide_setup(head, _render(occ_enabled=False, background_model=True), ndc=False)
    assert s.occupancy_resolution == 0 and s.background_model and s.background_color is None
    assert any("enabled=false" in r for r in s.reasons) and any("render.background_model" in r for r in s.reasons)
    assert decide_setup(head, _render(num_samples=7), ndc=False).num_samples == 7


def test_weighted_sampling_asks_for_the_grid_and_a_density_backbone() -> None:
    """render.occupancy.sampling=weighted turns the grid on in NDC (auto) for a density backbone and is a
    config error for an SDF backbone; auto samples the occupied cells."""
    fern = _scene("forward_facing", False)
    s = decide_setup(fern, _render(occ_sampling="weighted"), ndc=True, opacity_scores=True)
    assert s.occupancy_resolution == 64 and s.occupancy_sampling == "weighted"
    assert any("sampling=weighted" in r for r in s.reasons)
    assert decide_setup(fern, _render(), ndc=True, opacity_scores=True).occupancy_resolution == 0
    head = decide_setup(_scene("object", True), _render(), ndc=False, opacity_scores=True)
    assert head.occupancy_sampling == "occupied"
    with pytest.raises(ConfigError, match="needs a density backbone"):
        decide_setup(fern, _render(occ_sampling="weighted"), ndc=True, opacity_scores=False)


def test_grid_no_finer_than_the_pixels_resolve() -> None:
    s = decide_setup(_scene("object", True, size=32), _render(occ_resolution=128), ndc=False)
    assert s.occupancy_resolution == 16 and any("cannot resolve" in r for r in s.reasons)


@pytest.mark.parametrize("key,value", [("background_model", "sometimes"), ("occ_enabled", "maybe")])
def test_bad_choice_is_a_config_error(key: str, value: Optional[str]) -> None:
    with pytest.raises(ConfigError, match="one of auto, true, false"):
        decide_setup(_scene("object", True), _render(**{key: value}), ndc=False)
