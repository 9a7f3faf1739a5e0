"""Model only what a scene requires: ``decide_setup`` picks extent, background and empty-space
skipping from the capture type, logs why, and every choice yields to config."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import pytest
import torch

from nerfart_plugin.data.scene import Scene
from nerfart_plugin.data.setup import decide_setup
from nerfart_plugin.errors import ConfigError

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
    config error for an SDF backbone; auto is weighted for a density backbone in NDC (grid on), occupied
    elsewhere, and leaves an SDF backbone in NDC without a grid."""
    fern = _scene("forward_facing", False)
    s = decide_setup(fern, _render(occ_sampling="weighted"), ndc=True, opacity_scores=True)
    assert s.occupancy_resolution == 64 and s.occupancy_sampling == "weighted"
    assert any("weighted sampling" in r for r in s.reasons)
    auto = decide_setup(fern, _render(), ndc=True, opacity_scores=True)
    assert (auto.occupancy_resolution, auto.occupancy_sampling, auto.num_samples) == (64, "weighted", 16)
    assert any("render.occupancy.weighted_samples" in r for r in auto.reasons)
    assert decide_setup(fern, _render(occ_weighted_samples=None), ndc=True, opacity_scores=True).num_samples == 32
    occupied = decide_setup(_scene("object", True), _render(), ndc=False, opacity_scores=True)
    assert occupied.num_samples == 32  # weighted_samples applies to weighted sampling only
    assert decide_setup(fern, _render(), ndc=True, opacity_scores=False).occupancy_resolution == 0
    assert decide_setup(fern, _render(occ_enabled=False), ndc=True, opacity_scores=True).occupancy_resolution == 0
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


@pytest.mark.parametrize("capture,ndc,size,cell_pixels,side", [
    ("object", False, 128, 2.0, 128),  # 128 px focal at 3 units: ~43 px per unit -> below the floor of 128
    ("object", False, 900, 2.0, 320),  # 300 px per unit x 2 units / 2 px -> 300 cells -> 320
    ("forward_facing", True, 504, 2.0, 384),  # fern images_8: 252 px per NDC unit over the 3-unit box -> 378 -> 384
    ("forward_facing", True, 504, 3.0, 256),
    ("forward_facing", True, 4032, 2.0, 512),  # a full-size phone photo: capped at 512
])
def test_auto_grid_resolution_follows_the_pixels(capture: str, ndc: bool, size: int, cell_pixels: float,
                                                 side: int) -> None:
    """encoding.resolution=auto: the grid side gives a cell about cell_pixels image pixels where the scene is,
    a multiple of 32 in [128, 512], with its reason; any other resolution is the encoding's own (None)."""
    s = decide_setup(_scene(capture, not ndc, size=size), _render(), ndc=ndc,
                     encoding_cfg={"name": "grid", "resolution": "auto", "cell_pixels": cell_pixels})
    assert s.grid_resolution == side
    assert any(f"grid encoding {side} cells per side" in r for r in s.reasons)
    assert decide_setup(_scene(capture, not ndc, size=size), _render(), ndc=ndc,
                        encoding_cfg={"name": "grid", "resolution": 96}).grid_resolution is None


def test_auto_grid_resolution_reaches_the_field() -> None:
    """build_renderer builds the grid the setup decided; an encoding built with 'auto' outside a scene setup
    takes the rule's floor, 128."""
    from nerfart_plugin.fields import build_field
    from nerfart_plugin.systems.base import build_renderer

    enc = {"name": "grid", "resolution": "auto", "n_components": 2, "out_features": 8}
    s = decide_setup(_scene("forward_facing", False, size=504), _render(), ndc=True, encoding_cfg=enc)
    r = build_renderer({"backbone": {"name": "nerf", "hidden_dim": 16, "color_hidden_dim": 16}, "encoding": enc,
                        "render": _render()}, s)
    assert r.field.encoding.resolutions == [256] and tuple(r.field.encoding.planes[0].shape) == (3, 2, 256, 256)
    assert build_field({"name": "nerf"}, enc).encoding.resolutions == [128]


@pytest.mark.parametrize("opacity_scores,resolution,levels,expected", [
    (False, "auto", "auto", 3),  # an SDF field: three levels
    (True, "auto", "auto", 1),  # a density field: one
    (False, 64, "auto", 3),  # an int side is the finest level too
    (False, [16, 64], "auto", None),  # a list gives its levels itself
    (False, "auto", 2, None),  # an explicit count is the encoding's own
])
def test_auto_grid_levels_follow_the_backbone(opacity_scores: bool, resolution, levels, expected) -> None:
    """encoding.levels=auto: SDF fields get AUTO_SDF_LEVELS levels, density fields one, with the reason."""
    s = decide_setup(_scene("object", True), _render(), ndc=False, opacity_scores=opacity_scores,
                     encoding_cfg={"name": "grid", "resolution": resolution, "levels": levels})
    assert s.grid_levels == expected
    assert any("encoding.levels=auto" in r for r in s.reasons) == (expected is not None)


def test_auto_grid_levels_reach_the_field_and_old_checkpoints_keep_one() -> None:
    """build_renderer builds the levels the setup decided; a setup saved before encoding.levels existed
    (no grid_levels) rebuilds the one-level grid it was trained with."""
    from nerfart_plugin.data.setup import SceneSetup
    from nerfart_plugin.systems.base import build_renderer

    enc = {"name": "grid", "resolution": "auto", "levels": "auto", "n_components": 2, "out_features": 8}
    s = decide_setup(_scene("object", True), _render(), ndc=False, encoding_cfg=enc)
    r = build_renderer({"backbone": {"name": "volsdf", "hidden_dim": 16, "color_hidden_dim": 16}, "encoding": enc,
                        "render": _render()}, s)
    assert r.field.encoding.resolutions == [32, 64, 128]
    old = {k: v for k, v in s.to_dict().items() if k != "grid_levels"}
    r_old = build_renderer({"backbone": {"name": "volsdf", "hidden_dim": 16, "color_hidden_dim": 16},
                            "encoding": enc, "render": _render()}, SceneSetup(**old))
    assert r_old.field.encoding.resolutions == [128]


@pytest.mark.parametrize("covered,share", [(0.25, 0.8), (0.4, 0.8), (0.56, 0.0), (1.0, 0.0)])
def test_auto_mask_ray_share_follows_the_mattes_share_of_the_frame(covered: float, share: float) -> None:
    """reconstruct.mask_ray_share=auto: 0.8 of each batch inside the mattes where they cover less than
    half of the training pixels (the head: 39%), uniform rays where the subject fills most of the frame
    (the fangzhou_nature selfie: 56%); the decision and its reason are in the setup."""
    scene = _scene("object", True)
    rows = int(round(covered * scene.height))
    scene.masks.zero_()
    scene.masks[:, :rows] = 1.0
    scene.masks[1] = 0.0  # the held-out view's matte does not count
    s = decide_setup(scene, _render(), ndc=False)
    assert s.matte_fraction == pytest.approx(rows / scene.height)
    assert s.mask_ray_share == share
    assert any("reconstruct.mask_ray_share=auto" in r and f"{s.matte_fraction:.0%}" in r for r in s.reasons)
    number = decide_setup(scene, _render(), ndc=False, reconstruct_cfg={"mask_ray_share": 0.3})
    assert number.mask_ray_share is None and not any("mask_ray_share" in r for r in number.reasons)
    no_mattes = decide_setup(_scene("object", False), _render(), ndc=False)
    assert no_mattes.matte_fraction is None and no_mattes.mask_ray_share is None
