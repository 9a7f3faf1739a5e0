"""SceneDataModule: training rays, compositing, NDC, full-view batches."""

from __future__ import annotations

import pytest
import torch

from nerfart_plugin.data.datamodule import SceneDataModule
from nerfart_plugin.errors import ConfigError


@pytest.fixture(scope="module")
def dm():
    m = SceneDataModule({"name": "h3ds", "path": None, "resolution": 32})
    m.setup("fit")
    return m


def test_train_rays(dm):
    rays = dm.train_rays
    n_train = len(dm.scene.train_ids) * 32 * 32
    assert rays["rays_o"].shape == (n_train, 3) and rays["rgb"].shape == (n_train, 3)
    assert rays["near"].shape == (n_train,) and rays["far"].shape == (n_train,) and rays["mask"].shape == (n_train,)
    assert rays["view_id"].dtype == torch.long and set(rays["view_id"].tolist()) == set(dm.scene.train_ids)
    assert torch.allclose(rays["rays_d"].norm(dim=-1), torch.ones(n_train), atol=1e-5)


def test_background_composite(dm):
    rays = dm.train_rays
    bgpix = rays["mask"] < 1e-3
    assert bgpix.any() and torch.allclose(rays["rgb"][bgpix], torch.ones(int(bgpix.sum()), 3), atol=1e-3)
    black = SceneDataModule({"path": None, "resolution": 16, "background_color": [0, 0, 0]})
    black.setup("fit")
    m = black.train_rays["mask"]
    assert torch.allclose(black.train_rays["rgb"][m < 1e-3], torch.zeros(int((m < 1e-3).sum()), 3), atol=1e-3)


def test_val_full_views(dm):
    batches = list(dm.val_dataloader())
    assert len(batches) == len(dm.scene.val_ids)
    b = batches[0]
    assert b["H"] == 32 and b["W"] == 32 and isinstance(b["H"], int)
    assert b["rays_o"].shape == (32 * 32, 3) and b["rgb"].shape == (32 * 32, 3)
    assert (b["view_id"] == dm.scene.val_ids[0]).all()


@pytest.mark.slow
def test_ndc_forward_facing(shared_data):
    m = SceneDataModule({"name": "llff", "path": str(shared_data / "llff_fern"), "resolution": 40})
    m.setup("fit")
    assert m.ndc
    b = {k: v[::97] for k, v in m.train_rays.items()}
    n = b["rays_o"].shape[0]
    assert torch.all(b["near"] == 0) and torch.all(b["far"] == 1)
    assert torch.allclose(b["rays_o"][:, 2], -torch.ones(n), atol=1e-5)
    end = b["rays_o"] + b["rays_d"]
    assert torch.allclose(end[:, 2], torch.ones(n), atol=1e-5)  # t = 1 is infinity
    assert end[:, :2].abs().max() < 1.6  # other views' frusta overhang the reference one a little
    off = SceneDataModule({"name": "llff", "path": str(shared_data / "llff_fern"), "resolution": 40, "ndc": False})
    off.setup("fit")
    assert not off.ndc and (off.train_rays["far"] > 1).all()


def test_config_errors(dm):
    with pytest.raises(ConfigError, match="data.path is required"):
        SceneDataModule({"name": "llff"})
    bad = SceneDataModule({"path": None, "resolution": 16, "ndc": True})
    with pytest.raises(ConfigError, match="ndc"):
        bad.setup("fit")
