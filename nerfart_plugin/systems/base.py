"""What both stages share: building the renderer from config + scene setup, optimizer groups."""

from __future__ import annotations

import logging
from typing import Any, Optional

import lightning as L
import torch

from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.fields import OccupancyGrid, build_background, build_field
from nerfart_plugin.rendering import VolumeRenderer
from nerfart_plugin.systems.checkpoints import META_KEY, checkpoint_meta
from nerfart_plugin.utils.device import to_device

log = logging.getLogger(__name__)


def build_renderer(cfg: Any, setup: SceneSetup) -> VolumeRenderer:
    """Field (``cfg.backbone`` x ``cfg.encoding``) + optional background model + occupancy grid, wrapped in the
    renderer (``cfg.render``'s settings).

    ``cfg``: a RunConfig, or a mapping of its sections (what it leaves out takes the schema's defaults);
    ``setup`` decides the box, background, grid sizes (the occupancy grid's and, for ``encoding.resolution=auto``,
    the grid encoding's) and samples.
    """
    run, _ = parse_config(cfg)
    rc = run.render
    decided = {"resolution": setup.grid_resolution, "levels": setup.grid_levels}
    encoding = run.encoding.model_copy(update={k: v for k, v in decided.items()  # decided from the scene (decide_setup)
                                               if getattr(run.encoding, k, None) == "auto" and v is not None})
    field = build_field(run.backbone, encoding, bound=setup.bound)
    background = build_background({"name": "envmap"}) if setup.background_model else None
    occupancy: Optional[OccupancyGrid] = None
    if setup.occupancy_resolution > 0:
        occ = rc.occupancy
        occupancy = OccupancyGrid(resolution=setup.occupancy_resolution, bound=setup.bound, threshold=occ.threshold,
                                  update_every=occ.update_every, warmup_steps=occ.warmup_steps)
    return VolumeRenderer(field, num_samples=setup.num_samples, background=background, occupancy=occupancy,
                          background_color=setup.background_color, stop_transmittance=rc.stop_transmittance,
                          view_samples=rc.view_samples, occupancy_sampling=setup.occupancy_sampling,
                          uniform_share=rc.occupancy.uniform_share)


def param_groups(renderer: VolumeRenderer, lr_grid: float, lr_mlp: float, geometry: bool = True) -> list[dict]:
    """Adam groups: the field's grid parameters (``Field.grid_parameters``, the encoding) at ``lr_grid``,
    the rest (MLPs, beta, inv_s, background) at ``lr_mlp`` times the field's ``mlp_lr_scale``.

    With ``geometry=False`` the field's geometry parameters are left out (frozen).
    """
    field = renderer.field
    lr_mlp = lr_mlp * field.mlp_lr_scale
    frozen = set() if geometry else {id(p) for p in field.geometry_parameters()}
    grid = {id(p) for p in field.grid_parameters()}
    grid_params, mlp_params = [], []
    for p in renderer.parameters():
        if not p.requires_grad or id(p) in frozen:
            continue
        (grid_params if id(p) in grid else mlp_params).append(p)
    groups = []
    if grid_params:
        groups.append({"params": grid_params, "lr": lr_grid, "name": "grid"})
    if mlp_params:
        groups.append({"params": mlp_params, "lr": lr_mlp, "name": "mlp"})
    return groups


#: devices with a fused Adam kernel (torch >= 2.4)
_FUSED_ADAM_DEVICES = ("cpu", "cuda", "mps")


def adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam on ``groups`` (:func:`param_groups`) with the systems' betas (0.9, 0.99) and eps 1e-15, using
    torch's fused kernel (one pass over each tensor instead of a dozen) where it covers the parameters'
    device and dtype. On a CPU that is what makes a large grid affordable: the optimizer's share of a
    step grows with the grid side (``benchmarks/step_split.py``, fused versus plain)."""
    params = [p for g in groups for p in g["params"]]
    fused = bool(params) and all(p.is_floating_point() and p.device.type in _FUSED_ADAM_DEVICES for p in params)
    return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=fused or None)


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
    :func:`nerfart_plugin.systems.checkpoints.checkpoint_meta`), so that a checkpoint that does not
    fit a run is named with what differs. What a stage needs from a system after training is
    public here (:attr:`model_meta`, :attr:`occupied_fraction`, :meth:`render_view`), so
    nothing outside reaches into the renderer.
    """

    renderer: VolumeRenderer
    #: stage name recorded in checkpoints
    stage: str = "render"

    def __init__(self, cfg: Any, setup: SceneSetup) -> None:
        """``cfg``: the run's config (a RunConfig, or a mapping of its sections: the schema's defaults for what it
        leaves out); ``setup``: what the scene requires (:class:`~nerfart_plugin.data.setup.SceneSetup`)."""
        super().__init__()
        self.run_cfg, _ = parse_config(cfg)
        self.setup_info = setup if isinstance(setup, SceneSetup) else SceneSetup(**setup)
        self.render_cfg = self.run_cfg.render
        self.renderer = build_renderer(self.run_cfg, self.setup_info)
        #: the model settings recorded in checkpoints (plain data)
        self.model_meta: dict[str, Any] = checkpoint_meta(self.stage, self.run_cfg.backbone, self.run_cfg.encoding,
                                                          self.setup_info)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[META_KEY] = dict(self.model_meta)

    @property
    def field(self):
        """The field being trained (``renderer.field``)."""
        return self.renderer.field

    @property
    def view(self) -> VolumeRenderer:
        """What renders the run's views (the trained renderer; a stylization inside a region: its composite)."""
        return self.renderer

    @property
    def occupied_fraction(self) -> Optional[float]:
        """Share of occupied cells of the occupancy grid (None without one)."""
        return self.renderer.occupied_fraction

    @torch.no_grad()
    def render_view(self, batch: dict[str, Any], chunk: int, with_normals: bool = True,
                    renderer: Optional[VolumeRenderer] = None) -> dict[str, torch.Tensor]:
        """Render a full view batch (ints H, W) without grad -> images [H,W,C] (``with_normals=False``:
        colour, depth and opacity only, cheaper for SDF fields); ``renderer``: another renderer (the source)."""
        H, W = int(batch["H"]), int(batch["W"])
        r = renderer if renderer is not None else self.view
        out = r.render_chunked(to_device(batch, self.device), chunk=chunk, with_normals=with_normals)
        return {k: v.reshape(H, W, -1) for k, v in out.items() if torch.is_tensor(v)}
