"""What both stages share: building the renderer from config + scene setup, optimizer groups."""

from __future__ import annotations

import logging
from typing import Any, Optional

import lightning as L
import torch

from nerfart_plugin.fields import OccupancyGrid, build_background, build_field
from nerfart_plugin.rendering import VolumeRenderer
from nerfart_plugin.systems.scene_setup import SceneSetup

log = logging.getLogger(__name__)


def build_renderer(backbone_cfg: dict, encoding_cfg: dict, render_cfg: dict, setup: SceneSetup) -> VolumeRenderer:
    """Field (backbone x encoding) + optional background model + occupancy grid, wrapped in the renderer."""
    field = build_field(dict(backbone_cfg), dict(encoding_cfg), bound=setup.bound)
    background = build_background({"name": "envmap"}) if setup.background_model else None
    occupancy: Optional[OccupancyGrid] = None
    if setup.occupancy_resolution > 0:
        occ = dict(render_cfg.get("occupancy") or {})
        occupancy = OccupancyGrid(
            resolution=setup.occupancy_resolution,
            bound=setup.bound,
            threshold=float(occ.get("threshold", 0.01)),
            update_every=int(occ.get("update_every", 16)),
            warmup_steps=int(occ.get("warmup_steps", 64)),
        )
    return VolumeRenderer(field, num_samples=setup.num_samples, background=background, occupancy=occupancy,
                          background_color=setup.background_color)


def param_groups(renderer: VolumeRenderer, lr_grid: float, lr_mlp: float, geometry: bool = True) -> list[dict]:
    """Adam groups: encoding parameters (grids) at ``lr_grid``, the rest (MLPs, β, inv_s, background) at
    ``lr_mlp`` times the encoding's ``mlp_lr_scale``.

    With ``geometry=False`` the field's geometry parameters are left out (frozen).
    """
    field = renderer.field
    lr_mlp = lr_mlp * float(getattr(field.encoding, "mlp_lr_scale", 1.0))
    frozen = set() if geometry else {id(p) for p in field.geometry_parameters()}
    enc = {id(p) for p in field.encoding.parameters()}
    grid_params, mlp_params = [], []
    for p in renderer.parameters():
        if not p.requires_grad or id(p) in frozen:
            continue
        (grid_params if id(p) in enc else mlp_params).append(p)
    groups = []
    if grid_params:
        groups.append({"params": grid_params, "lr": lr_grid, "name": "grid"})
    if mlp_params:
        groups.append({"params": mlp_params, "lr": lr_mlp, "name": "mlp"})
    return groups


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    return {k: (v.to(device, non_blocking=True) if torch.is_tensor(v) else v) for k, v in batch.items()}


def step_seed(seed: int, step: int) -> int:
    """A per-step seed: the randomness of step ``step`` depends only on (seed, step), so a resumed run
    draws exactly what an uninterrupted one would."""
    return (int(seed) * 1_000_003 + int(step) * 7_919 + 17) % (2**62)


class StepsDataset(torch.utils.data.IterableDataset):
    """An endless stream of placeholders; the systems draw their own rays from (seed, global_step)."""

    def __iter__(self):
        while True:
            yield torch.zeros(())


def steps_loader() -> torch.utils.data.DataLoader:
    return torch.utils.data.DataLoader(StepsDataset(), batch_size=None, num_workers=0)


class RenderSystem(L.LightningModule):
    """Base LightningModule holding a renderer built from config.

    Its checkpoints record the model they belong to (``checkpoint["nerfart"]``, see
    :func:`nerfart_plugin.checkpoints.checkpoint_meta`), so that a checkpoint that does not
    fit a run is named with what differs.
    """

    renderer: VolumeRenderer
    #: stage name recorded in checkpoints
    stage: str = "render"
    model_meta: dict[str, Any] = {}

    def remember_model(self, backbone_cfg: dict, encoding_cfg: dict, setup: SceneSetup) -> None:
        """Record the model settings for :meth:`on_save_checkpoint` (plain data)."""
        from nerfart_plugin.checkpoints import checkpoint_meta

        self.model_meta = checkpoint_meta(self.stage, backbone_cfg, encoding_cfg, setup)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        from nerfart_plugin.checkpoints import META_KEY

        checkpoint[META_KEY] = dict(self.model_meta)

    @property
    def field(self):
        return self.renderer.field
