"""``SceneDataModule``: a LightningDataModule around :func:`nerfart_plugin.data.load_scene`.

* train: random batches of ``batch_rays`` rays drawn from all training pixels
  (precomputed once), deterministic under ``seed``; ``steps_per_epoch`` batches
  per epoch.
* val / test: one full held-out view per batch (ray batch dict with ints ``H``, ``W``).
* predict: one full frame per batch along :func:`~nerfart_plugin.data.camera_path.orbit_path`.

For masked object scenes the RGB target is composited onto the background
colour, ``rgb * mask + bg * (1 - mask)`` (what the field renders with that
background); ``mask`` stays in the batch. Forward-facing scenes use NDC rays
(``near = 0``, ``far = 1``) when ``ndc`` is true (default: auto).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator, Optional

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset

from nerfart_plugin.data.camera_path import orbit_path
from nerfart_plugin.data.rays import ndc_rays, pixel_rays, rays_for_views
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

#: The shipped default scene (31 views of a head at 256x256, see assets/head/SOURCE.md).
DEFAULT_SCENE = Path(__file__).resolve().parents[1] / "assets" / "head"

_DM_KEYS = {"kind", "name", "path", "batch_rays", "ndc", "background_color", "background", "seed", "subject",
            "steps_per_epoch", "render_frames", "_target_"}


def default_scene_path() -> Path:
    """Folder of the shipped default scene (loadable with ``kind="h3ds"``)."""
    return DEFAULT_SCENE


class RandomRayDataset(IterableDataset):
    """Yields ``steps`` batches of ``batch_rays`` random rays; epoch ``e`` uses the generator seed ``seed * 1000003 + e``."""

    def __init__(self, rays: dict, batch_rays: int, steps: int, seed: int = 0) -> None:
        self.rays = rays
        self.batch_rays = int(batch_rays)
        self.steps = int(steps)
        self.seed = int(seed)
        self.epoch = 0
        self.n = int(rays["rays_o"].shape[0])

    def __len__(self) -> int:
        return self.steps

    def __iter__(self) -> Iterator[dict]:
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        self.epoch += 1
        for _ in range(self.steps):
            idx = torch.randint(0, self.n, (self.batch_rays,), generator=g)
            yield {k: v[idx] for k, v in self.rays.items() if isinstance(v, torch.Tensor)}


class _ViewDataset(Dataset):
    def __init__(self, dm: "SceneDataModule", ids: list[int]) -> None:
        self.dm, self.ids = dm, list(ids)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        return self.dm.view_batch(self.ids[i])


class _PathDataset(Dataset):
    def __init__(self, dm: "SceneDataModule", c2w: torch.Tensor) -> None:
        self.dm, self.c2w = dm, c2w

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def __getitem__(self, i: int) -> dict:
        return self.dm.pose_batch(self.c2w[i])


class SceneDataModule(L.LightningDataModule):
    """Data module built from the ``data`` config.

    Config keys (all optional): ``kind`` ("h3ds"), ``path`` (None: the shipped
    default head scene), ``batch_rays`` (1024), ``ndc`` (None = auto: true for
    forward-facing scenes), ``background_color`` ([1,1,1]; None = no compositing),
    ``seed`` (0), ``steps_per_epoch`` (1000), ``render_frames`` (120); every other
    key (``resolution``, ``holdout_every``, ``use_masks``, ``factor``, ...) goes to
    the loader.
    """

    def __init__(self, cfg: Optional[dict] = None, **overrides: Any) -> None:
        super().__init__()
        cfg = dict(_to_dict(cfg or {}), **overrides)
        self.cfg = cfg
        self.kind = cfg.get("kind") or cfg.get("name") or "h3ds"
        self.path = cfg.get("path")
        if self.path is None:
            if self.kind != "h3ds":
                raise ConfigError(f"data.path is required for data={self.kind} (only h3ds has a default scene).")
            self.path = DEFAULT_SCENE
        self.batch_rays = int(cfg.get("batch_rays", 1024))
        self.ndc_opt = cfg.get("ndc")
        bg = cfg.get("background_color", cfg.get("background", (1.0, 1.0, 1.0)))
        if isinstance(bg, str):
            bg = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}.get(bg)
            if bg is None:
                raise ConfigError("data.background_color must be white, black, null or [r,g,b] in [0,1].")
        self.background = None if bg is None else tuple(float(x) for x in bg)
        self.seed = int(cfg.get("seed", 0))
        self.steps_per_epoch = int(cfg.get("steps_per_epoch", 1000))
        self.render_frames = int(cfg.get("render_frames", 120))
        self.loader_opts = {k: v for k, v in cfg.items() if k not in _DM_KEYS}
        self.scene: Optional[Scene] = None
        self.train_rays: Optional[dict] = None
        self._train_ds: Optional[RandomRayDataset] = None

    # ------------------------------------------------------------------ setup
    @property
    def ndc(self) -> bool:
        """Whether rays are NDC-warped (forward-facing scenes; auto when ``ndc`` is None)."""
        assert self.scene is not None, "call setup() first"
        if self.ndc_opt is None:
            return self.scene.capture == "forward_facing"
        if self.ndc_opt and self.scene.capture != "forward_facing":
            raise ConfigError(
                f"data.ndc=true but {self.scene.source} is a {self.scene.capture} capture; NDC only suits "
                "forward-facing scenes: set data.ndc=null or false."
            )
        return bool(self.ndc_opt)

    def load(self) -> Scene:
        """Load (once) and return the scene."""
        if self.scene is None:
            import inspect

            from nerfart_plugin import registry
            from nerfart_plugin.data import load_scene

            opts = dict(self.loader_opts)
            if "background" in inspect.signature(registry.get("data", self.kind)).parameters:
                opts["background"] = self.background  # loaders that composite RGBA images (nerfstudio)
            self.scene = load_scene(self.kind, self.path, **opts)
        return self.scene

    def setup(self, stage: Optional[str] = None) -> None:
        scene = self.load()
        if stage in (None, "fit") and self.train_rays is None:
            ids = scene.train_ids or list(range(scene.num_images))
            self.train_rays = rays_for_views(scene, ids, ndc=self.ndc, background=self.background)
            self.train_rays.pop("H", None)
            self.train_rays.pop("W", None)
            log.info("precomputed %d training rays from %d views", self.train_rays["rays_o"].shape[0], len(ids))

    # ------------------------------------------------------------------ batches
    def view_batch(self, view_id: int) -> dict:
        """All rays of one view (with ``rgb``/``mask`` targets), plus ints ``H``, ``W``."""
        return rays_for_views(self.load(), [int(view_id)], ndc=self.ndc, background=self.background)

    def pose_batch(self, c2w: torch.Tensor, K: Optional[torch.Tensor] = None) -> dict:
        """Rays of a novel camera ``c2w`` [3,4] (intrinsics of view 0 by default), no targets."""
        scene = self.load()
        K = scene.K[0] if K is None else K
        H, W = scene.height, scene.width
        o, d = pixel_rays(K, c2w, H, W)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        n = o.shape[0]
        if self.ndc:
            o, d = ndc_rays(o, d, K, 1.0, H=H, W=W)
            near, far = torch.zeros(n), torch.ones(n)
        elif scene.capture == "object":
            dist = float(c2w[:3, 3].norm())
            near, far = torch.full((n,), max(dist - 1.0, 0.05)), torch.full((n,), dist + 1.0)
        else:
            near, far = torch.full((n,), float(scene.near.median())), torch.full((n,), float(scene.far.median()))
        return {"rays_o": o.float(), "rays_d": d.float(), "near": near, "far": far,
                "view_id": torch.full((n,), -1, dtype=torch.long), "H": int(H), "W": int(W)}

    # ------------------------------------------------------------------ loaders
    def train_dataloader(self) -> DataLoader:
        if self.train_rays is None:
            self.setup("fit")
        if self._train_ds is None:
            self._train_ds = RandomRayDataset(self.train_rays, self.batch_rays, self.steps_per_epoch, self.seed)
        return DataLoader(self._train_ds, batch_size=None, num_workers=0)

    def val_dataloader(self) -> DataLoader:
        scene = self.load()
        ids = scene.val_ids or scene.train_ids[:1]
        return DataLoader(_ViewDataset(self, ids), batch_size=None, num_workers=0)

    def test_dataloader(self) -> DataLoader:
        return self.val_dataloader()

    def predict_dataloader(self) -> DataLoader:
        return DataLoader(_PathDataset(self, orbit_path(self.load(), self.render_frames)), batch_size=None,
                          num_workers=0)


def _to_dict(cfg: Any) -> dict:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return dict(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)
