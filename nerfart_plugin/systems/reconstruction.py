"""Stage 1: reconstruct a NeRF from posed photos (L_rec, Eq. 2; mask and field regularizer terms where they apply)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.objectives.evaluation import view_metrics
from nerfart_plugin.objectives.losses import psnr, reconstruction_loss, silhouette_loss
from nerfart_plugin.systems.base import RenderSystem, adam, param_groups, step_seed
from nerfart_plugin.systems.loggers import log_images
from nerfart_plugin.systems.loss_terms import (LossTerm, compute, regularizer_terms, regularizer_weights, weighted_sum,
    weights_of)
from nerfart_plugin.utils.device import to_device
from nerfart_plugin.utils.images import image_grid, save_image, to_uint8

log = logging.getLogger(__name__)

#: The reconstruction loss, one row per term (weights ``reconstruct.lambda_<name>``), plus the field's
#: regularizers (``eikonal`` for SDF fields, weighted by ``reconstruct.lambda_eikonal``; ``grid_tv`` ...).
RECONSTRUCTION_LOSSES: tuple[LossTerm, ...] = (
    LossTerm("rgb", lambda out, batch: reconstruction_loss(out["rgb"], batch["rgb"]),
             doc="Eq. 2: mean squared error of rendered vs photo colour"),
    LossTerm("mask", lambda out, batch: silhouette_loss(out["opacity"], batch["mask"]),
             doc="binary cross-entropy of ray opacity vs the mask (scenes with masks)"),
)


class ReconstructionSystem(RenderSystem):
    """Fits a field to the training rays of a scene (loss: :data:`RECONSTRUCTION_LOSSES`).

    Args:
        cfg: the ``reconstruct`` section (a :class:`ReconstructConfig` or a dict of its keys).
        backbone_cfg / encoding_cfg: component configs; render_cfg: the ``render`` section.
        setup: the :class:`SceneSetup` decided for the scene.
        train_rays: flat ray batch of all training pixels (``rays_o``, ``rays_d``,
            ``near``, ``far``, ``rgb``, optional ``mask``), kept on the CPU.
        seed: run seed; each step's randomness depends only on (seed, step).
        out_dir: where validation images go (None: not saved).
    """

    stage = "reconstruct"

    def __init__(self, cfg: Any, setup: SceneSetup, train_rays: Optional[dict] = None,
                 out_dir: Optional[str] = None) -> None:
        """``cfg``: the run's config (its ``reconstruct``, ``backbone``, ``encoding``, ``render`` and ``seed``;
        see :class:`~nerfart_plugin.systems.base.RenderSystem`); ``train_rays``: the scene's training rays."""
        super().__init__(cfg, setup)
        c = self.run_cfg
        self.cfg = c.reconstruct
        # hyper-parameters as plain data only (checkpoints are read with weights_only=True)
        self.save_hyperparameters({"cfg": self.cfg.model_dump(mode="json"), "backbone_cfg": self.model_meta["backbone"],
                                   "encoding_cfg": self.model_meta["encoding"],
                                   "render_cfg": self.render_cfg.model_dump(mode="json"), "seed": int(c.seed),
                                   "out_dir": out_dir, "setup": self.setup_info.to_dict()})
        self.train_rays = train_rays
        self.seed = int(c.seed)
        self.out_dir = Path(out_dir) if out_dir else None
        self.total_steps = self.cfg.steps
        self.lambdas = weights_of(RECONSTRUCTION_LOSSES, self.cfg, off=() if self.setup_info.has_masks else ("mask",))
        self.reg_lambdas = regularizer_weights(self.field.regularizer_names, self.cfg)
        self._t_last: Optional[float] = None
        self.val_metrics: dict[str, float] = {}

    # ------------------------------------------------------------------ training
    def sample_batch(self, step: int) -> dict[str, torch.Tensor]:
        """``reconstruct.batch_rays`` random training rays for ``step`` (a function of (seed, step) only):
        ``reconstruct.mask_ray_share`` of them from inside the mattes (scenes with mattes, from step
        ``reconstruct.mask_ray_share_after`` on), the rest uniformly from all training pixels."""
        assert self.train_rays is not None, "ReconstructionSystem needs train_rays to train"
        # DDP: each rank draws its own rays (rank 0 draws what a single-device run draws)
        g = torch.Generator().manual_seed(step_seed(self.seed + 1_000_033 * self.global_rank, step))
        n = self.train_rays["rays_o"].shape[0]
        fg = self.foreground_rays()
        share = self.mask_ray_share if step >= self.cfg.mask_ray_share_after else 0.0
        k = int(round(share * self.cfg.batch_rays)) if fg is not None else 0
        idx = torch.randint(0, n, (self.cfg.batch_rays - k,), generator=g)
        if k:
            idx = torch.cat([fg[torch.randint(0, fg.numel(), (k,), generator=g)], idx])
        return to_device({k: v[idx] for k, v in self.train_rays.items() if torch.is_tensor(v)}, self.device)

    @property
    def mask_ray_share(self) -> float:
        """Share of each batch drawn inside the mattes (from ``reconstruct.mask_ray_share_after`` on):
        ``reconstruct.mask_ray_share``, or the scene setup's decision where it is ``auto``."""
        share = self.cfg.mask_ray_share
        return (self.setup_info.mask_ray_share or 0.0) if share == "auto" else float(share)

    def foreground_rays(self) -> Optional[torch.Tensor]:
        """Indices [F] of the training rays inside the mattes (mask > 0.5); None without mattes, when
        none is inside, or with a share of 0."""
        if not hasattr(self, "_foreground"):
            mask = self.train_rays.get("mask") if self.train_rays is not None else None
            ids = (mask.reshape(-1) > 0.5).nonzero()[:, 0] if mask is not None and self.mask_ray_share > 0 else None
            self._foreground = ids if ids is not None and ids.numel() > 0 else None
        return self._foreground

    def losses(self, out: dict[str, Any], batch: dict[str, Any]) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        """The terms of this step with a non-zero weight, and the weights (table + field regularizers)."""
        terms = compute(RECONSTRUCTION_LOSSES, self.lambdas, out, batch)
        terms.update(regularizer_terms(out, self.reg_lambdas))
        return terms, {**self.lambdas, **self.reg_lambdas}

    def training_step(self, _: Any, batch_idx: int) -> torch.Tensor:
        step = self.global_step
        torch.manual_seed(step_seed(self.seed, step) + 1)  # jitter + occupancy cell points
        self.field.update_step(step, self.total_steps)
        if step >= 1:
            self.renderer.update_occupancy(step)
        batch = self.sample_batch(step)
        out = self.renderer(batch, perturb=True)
        terms, weights = self.losses(out, batch)
        loss = weighted_sum(terms, weights, step, "reconstruct")
        self._log_step(terms, out, batch)
        return loss

    def _log_step(self, terms: dict[str, torch.Tensor], out: dict[str, Any], batch: dict[str, Any]) -> None:
        now = time.perf_counter()
        if self._t_last is not None:
            self.log("rays_s", batch["rays_o"].shape[0] / max(now - self._t_last, 1e-9), prog_bar=True)
        self._t_last = now
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v, prog_bar=(k == "rgb"))
        self.log("train/psnr", psnr(out["rgb"].detach(), batch["rgb"]), prog_bar=True)
        for k, v in self.field.scalars().items():
            self.log(f"train/{k}", v)

    def configure_optimizers(self) -> Any:
        opt = adam(param_groups(self.renderer, self.cfg.lr, self.cfg.lr_mlp))
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: self.lr_factor(s))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def lr_factor(self, step: int) -> float:
        """Multiplier of both Adam rates at ``step``: exponential decay to ``reconstruct.lr_final`` at
        :attr:`total_steps`, read at each step (a caller that re-estimates the run's length stretches it)."""
        return self.cfg.lr_final ** min(step / max(1, self.total_steps), 1.0)

    # ------------------------------------------------------------------ validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        max_views = self.cfg.val_views
        if max_views and batch_idx >= max_views:
            return
        img = self.render_view(batch, chunk=self.render_cfg.chunk)
        metrics = view_metrics(img["rgb"], batch["rgb"].reshape(img["rgb"].shape).to(self.device), batch.get("mask"))
        for k, v in metrics.items():
            self.log(f"val/{k}", v, prog_bar=(k == "psnr"), batch_size=1)
        if self.out_dir is not None and batch_idx == 0:

            grid = save_val_grid(self.out_dir / "val" / f"step_{self.global_step:06d}.png", img,
                                 batch["rgb"].reshape(img["rgb"].shape))
            log_images(self.loggers, "val/photo|render|depth|normal", [grid], self.global_step)

    def on_validation_epoch_end(self) -> None:
        self.val_metrics = {k.split("/", 1)[1]: float(v) for k, v in self.trainer.callback_metrics.items()
                            if k.startswith("val/")}


def save_val_grid(path: Path, img: dict[str, torch.Tensor], target: torch.Tensor) -> np.ndarray:
    """Photo | render | depth | normal (if any), side by side; returns the grid (uint8 [H,W,3])."""

    tiles = [to_uint8(target), to_uint8(img["rgb"]), to_uint8(img["depth"], normalize=True)]
    if "normal" in img:
        tiles.append(to_uint8(img["normal"] * 0.5 + 0.5))
    grid = image_grid(tiles)
    save_image(grid, path)
    return grid
