"""One resolution policy across loaders: ``data.resolution=auto`` = long side min(native, 480)
(LLFF: the native size of its ``factor`` folder); null = native; an integer overrides."""

from __future__ import annotations

import logging

import pytest
from pipeline_helpers import composed

from nerfart_plugin.data import load_scene
from nerfart_plugin.data.datamodule import SceneDataModule, default_scene_path
from nerfart_plugin.data.images import choose_resolution
from nerfart_plugin.errors import ConfigError


@pytest.mark.parametrize("kind", ["h3ds", "selfie", "llff", "nerfstudio"])
def test_config_default_is_auto(kind: str) -> None:
    assert composed(f"data={kind}").data.resolution == "auto"


def test_head_default_is_native_256_and_logged(caplog) -> None:
    cfg = composed().data
    with caplog.at_level(logging.INFO, logger="nerfart_plugin"):
        scene = SceneDataModule(cfg).load()
    assert scene.images.shape[1:3] == (256, 256)
    assert any("data.resolution=auto: native 256x256" in n for n in scene.notes)
    assert any("data.resolution=auto: native 256x256" in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_selfie_frames_load_at_270x480_with_either_loader(shared_data) -> None:
    """540x960 frames: h3ds (cameras.npz) and selfie (existing COLMAP model) agree on 270x480."""
    a = load_scene("h3ds", shared_data / "yanan_nature", use_masks=False)
    b = load_scene("selfie", shared_data / "yanan_nature", use_masks=False)
    assert a.images.shape[1:3] == b.images.shape[1:3] == (480, 270)
    assert any("long side 480 px, 540x960 -> 270x480" in n for n in a.notes + b.notes)
    assert abs(float(a.K[0, 0, 0]) - float(b.K[0, 0, 0])) / float(b.K[0, 0, 0]) < 0.1  # same camera, same scale


def test_llff_auto_keeps_the_factor_size(shared_data) -> None:
    s = load_scene("llff", shared_data / "llff_fern", factor=8)
    assert s.images.shape[1:3] == (378, 504) and any("native 504x378" in n for n in s.notes)


def test_overrides_keep_working(shared_data) -> None:
    head = default_scene_path()
    assert load_scene("h3ds", head, resolution=24).images.shape[1:3] == (24, 24)
    assert load_scene("h3ds", head, resolution=None).images.shape[1:3] == (256, 256)
    s = load_scene("h3ds", shared_data / "girl", resolution=None, use_masks=False)
    assert s.images.shape[1:3] == (512, 512) and any("data.resolution=null: native 512x512" in n for n in s.notes)
    assert load_scene("h3ds", shared_data / "girl").images.shape[1:3] == (480, 480)  # auto caps at 480


@pytest.mark.parametrize("bad", [0, -5, "abc", True, 2.5, [64]])
def test_invalid_resolution_is_one_config_error(bad) -> None:
    with pytest.raises(ConfigError, match=r"data.resolution=.*: one of auto, or an integer in \[8, 8192\], or null"):
        load_scene("h3ds", default_scene_path(), resolution=bad)


def test_choose_resolution_rules() -> None:
    notes: list[str] = []
    assert choose_resolution("auto", (540, 960), notes) == 480
    assert choose_resolution("auto", (256, 256), notes) is None
    assert choose_resolution("auto", (4032, 3024), notes, cap=None) is None
    assert choose_resolution(None, (540, 960), notes) is None
    assert choose_resolution(960, (540, 960), notes) is None  # explicit = native: no resize
    assert choose_resolution(128, (540, 960), notes) == 128
    assert len(notes) == 6 and all(n.startswith("resolution: data.resolution=") for n in notes)
