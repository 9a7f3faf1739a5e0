"""Stage 1: reconstruct a NeRF from posed photos (L_rec, Eq. 2; eikonal and mask terms where they apply)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Optional

import kornia
import numpy as np
import torch
import torch.nn.functional as F

from nerfart_plugin.losses import psnr, reconstruction_loss, silhouette_loss
from nerfart_plugin.systems.base import RenderSystem, build_renderer, param_groups, step_seed, to_device
from nerfart_plugin.systems.callbacks import check_finite_losses
from nerfart_plugin.systems.scene_setup import SceneSetup

log = logging.getLogger(__name__)


class ReconstructionSystem(RenderSystem):
    """Fits a field to the training rays of a scene.

    Loss (each ``loss_*`` paired with a ``lambda_*``, logged, skipped at λ=0):
      * ``rgb``: Eq. 2, mean squared error of rendered vs. photo colour;
      * ``eikonal``: SDF backbones, mean (|∇d|−1)² over samples;
      * ``mask``: scenes with masks, binary cross-entropy of ray opacity vs. mask.

    Args:
        cfg: the ``reconstruct`` config (steps, batch_rays, lr, lr_mlp, lambda_*, val_every, ...).
        backbone_cfg / encoding_cfg / render_cfg: component configs.
        setup: the :class:`SceneSetup` decided for the scene.
        train_rays: flat ray batch of all training pixels (``rays_o``, ``rays_d``,
            ``near``, ``far``, ``rgb``, optional ``mask``), kept on the CPU.
        seed: run seed; each step's randomness depends only on (seed, step).
        out_dir: where validation images go (None: not saved).
    """

    stage = "reconstruct"

    def __init__(self, cfg: dict, backbone_cfg: dict, encoding_cfg: dict, render_cfg: dict, setup: SceneSetup,
                 train_rays: Optional[dict] = None, seed: int = 0, out_dir: Optional[str] = None) -> None:
        super().__init__()
        # hyper-parameters as plain data only (checkpoints are read with weights_only=True)
        self.save_hyperparameters(ignore=["train_rays", "setup"])
        self.cfg = dict(cfg)
        self.setup_info = setup if isinstance(setup, SceneSetup) else SceneSetup(**setup)
        self.hparams["setup"] = self.setup_info.to_dict()
        self.renderer = build_renderer(backbone_cfg, encoding_cfg, render_cfg, self.setup_info)
        self.remember_model(backbone_cfg, encoding_cfg, self.setup_info)
        self.train_rays = train_rays
        self.seed = int(seed)
        self.out_dir = Path(out_dir) if out_dir else None
        self.total_steps = int(self.cfg.get("steps", 2000))
        self._t_last: Optional[float] = None
        self.val_metrics: dict[str, float] = {}

    # ------------------------------------------------------------------ training
    def sample_batch(self, step: int) -> dict[str, torch.Tensor]:
        """``batch_rays`` random training rays for ``step`` (a function of (seed, step) only)."""
        assert self.train_rays is not None, "ReconstructionSystem needs train_rays to train"
        # DDP: each rank draws its own rays (rank 0 draws what a single-device run draws)
        g = torch.Generator().manual_seed(step_seed(self.seed + 1_000_033 * self.global_rank, step))
        n = self.train_rays["rays_o"].shape[0]
        idx = torch.randint(0, n, (int(self.cfg.get("batch_rays", 1024)),), generator=g)
        return to_device({k: v[idx] for k, v in self.train_rays.items() if torch.is_tensor(v)}, self.device)

    def training_step(self, _: Any, batch_idx: int) -> torch.Tensor:
        step = self.global_step
        torch.manual_seed(step_seed(self.seed, step) + 1)  # jitter + occupancy cell points
        self.field.update_step(step, self.total_steps)
        if self.renderer.occupancy is not None and step >= 1:
            self.renderer.occupancy.update(self.field, step)
        batch = self.sample_batch(step)
        out = self.renderer(batch, perturb=True)

        terms: dict[str, torch.Tensor] = {}
        lambdas = {"rgb": float(self.cfg.get("lambda_rgb", 1.0)),
                   "eikonal": float(self.cfg.get("lambda_eikonal", 0.1)) if self.field.is_sdf else 0.0,
                   "mask": float(self.cfg.get("lambda_mask", 0.1)) if "mask" in batch else 0.0}
        if lambdas["rgb"] > 0:
            terms["rgb"] = reconstruction_loss(out["rgb"], batch["rgb"])
        if lambdas["eikonal"] > 0 and "eikonal" in out:
            terms["eikonal"] = out["eikonal"]
        if lambdas["mask"] > 0:
            terms["mask"] = silhouette_loss(out["opacity"], batch["mask"])
        check_finite_losses(terms, step, "reconstruct")
        loss = sum(lambdas[k] * v for k, v in terms.items())

        now = time.perf_counter()
        if self._t_last is not None:
            self.log("rays_s", batch["rays_o"].shape[0] / max(now - self._t_last, 1e-9), prog_bar=True)
        self._t_last = now
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v, prog_bar=(k == "rgb"))
        self.log("train/psnr", psnr(out["rgb"].detach(), batch["rgb"]), prog_bar=True)
        if hasattr(self.field, "beta"):
            self.log("train/beta", float(self.field.beta.detach()))
        return loss

    def configure_optimizers(self) -> Any:
        lr, lr_mlp = float(self.cfg.get("lr", 1e-2)), float(self.cfg.get("lr_mlp", 1e-3))
        opt = torch.optim.Adam(param_groups(self.renderer, lr, lr_mlp), betas=(0.9, 0.99), eps=1e-15)
        total = max(1, self.total_steps)
        # exponential decay to 10% of the initial rate over the run
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** min(s / total, 1.0))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # ------------------------------------------------------------------ validation
    def render_view(self, batch: dict[str, Any], chunk: int = 4096, with_normals: bool = True) -> dict[str, torch.Tensor]:
        """Render a full view batch (ints H, W) -> images [H,W,C] (``with_normals=False``: colour,
        depth and opacity only, cheaper for SDF fields)."""
        H, W = int(batch["H"]), int(batch["W"])
        out = self.renderer.render_chunked(to_device(batch, self.device), chunk=chunk, with_normals=with_normals)
        return {k: v.reshape(H, W, -1) for k, v in out.items() if torch.is_tensor(v)}

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        max_views = int(self.cfg.get("val_views", 0))
        if max_views and batch_idx >= max_views:
            return
        img = self.render_view(batch)
        metrics = view_metrics(img["rgb"], batch["rgb"].reshape(img["rgb"].shape).to(self.device),
                               batch.get("mask"))
        for k, v in metrics.items():
            self.log(f"val/{k}", v, prog_bar=(k == "psnr"), batch_size=1)
        if self.out_dir is not None and batch_idx == 0:
            save_val_grid(self.out_dir / "val" / f"step_{self.global_step:06d}.png", img,
                          batch["rgb"].reshape(img["rgb"].shape))

    def on_validation_epoch_end(self) -> None:
        self.val_metrics = {k.split("/", 1)[1]: float(v) for k, v in self.trainer.callback_metrics.items()
                            if k.startswith("val/")}


def view_metrics(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None) -> dict[str, float]:
    """PSNR (dB), SSIM (kornia, 11x11 Gaussian window) and, with a mask, PSNR inside the mask.

    ``pred``/``target`` [H,W,3] in [0,1]; ``mask`` [H*W] or [H,W] in [0,1].
    """
    pred, target = pred.clamp(0, 1).float(), target.float()
    out = {"psnr": float(psnr(pred.reshape(-1, 3), target.reshape(-1, 3)))}
    a = pred.permute(2, 0, 1)[None]
    b = target.permute(2, 0, 1)[None]
    out["ssim"] = float(kornia.metrics.ssim(a, b, window_size=11).mean())
    if mask is not None:
        m = mask.reshape(-1).to(pred.device).float() > 0.5
        if m.any():
            out["psnr_masked"] = float(psnr(pred.reshape(-1, 3)[m], target.reshape(-1, 3)[m]))
    return out


def to_image(x: torch.Tensor) -> np.ndarray:
    """[H,W,C] tensor (C=1 or 3) -> uint8 [H,W,3]."""
    x = x.detach().float().cpu()
    if x.shape[-1] == 1:
        lo, hi = float(x.min()), float(x.max())
        x = ((x - lo) / max(hi - lo, 1e-8)).expand(*x.shape[:2], 3)
    return (x.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def save_val_grid(path: Path, img: dict[str, torch.Tensor], target: torch.Tensor) -> None:
    """Photo | render | depth | normal (if any), side by side."""
    from nerfart_plugin.export.video import save_image_grid

    tiles = [to_image(target), to_image(img["rgb"]), to_image(img["depth"])]
    if "normal" in img:
        tiles.append(to_image(img["normal"] * 0.5 + 0.5))
    save_image_grid(tiles, path)
