"""``SceneDataModule``: the loaded scene of a ``data`` config, as ray batches.

* ``train_rays`` (after ``setup("fit")``): every training pixel as one flat ray batch,
  precomputed once; the reconstruction draws its random rays from it.
* ``val_dataloader()``: one full held-out view per batch (ray batch dict with ints ``H``, ``W``).

For masked object scenes the RGB target is composited onto the background
colour, ``rgb * mask + bg * (1 - mask)`` (what the field renders with that
background); ``mask`` stays in the batch. Forward-facing scenes use NDC rays
(``near = 0``, ``far = 1``) when ``ndc`` is true (default: auto).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

from torch.utils.data import DataLoader, Dataset

from nerfart_plugin.config.validate import to_plain
from nerfart_plugin.data import load_scene
from nerfart_plugin.data.loader import LoaderContext
from nerfart_plugin.data.rays import rays_for_views
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

#: The shipped default scene (31 views of a head at 256x256, see assets/head/SOURCE.md).
DEFAULT_SCENE = Path(__file__).resolve().parents[1] / "assets" / "head"

#: keys of the data config the datamodule reads itself; every other key goes to the loader
_DM_KEYS = {"name", "path", "ndc", "background_color", "subject", "cache_root", "_target_"}
_NAMED_COLORS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def default_scene_path() -> Path:
    """Folder of the shipped default scene (loadable with ``name="h3ds"``)."""
    return DEFAULT_SCENE


class _ViewDataset(Dataset):
    def __init__(self, dm: "SceneDataModule", ids: list[int]) -> None:
        self.dm, self.ids = dm, list(ids)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        return self.dm.view_batch(self.ids[i])


class SceneDataModule:
    """The scene of a ``data`` config.

    Config keys: ``name`` (the loader, "h3ds"), ``path`` (None: the shipped default head scene, h3ds only),
    ``ndc`` (None = auto: true for forward-facing scenes), ``background_color`` ([r, g, b] in [0, 1],
    white | black, or None = no compositing; default white), ``subject`` (for the stylization),
    ``cache_root`` (the loaders' cache folder; the pipeline: ``<output_root>/cache``); every other key
    (``resolution``, ``holdout_every``, ``use_masks``, ``factor``, ...) is a setting of the loader's ``Config``
    (checked: an unknown one is a ConfigError).
    """

    def __init__(self, cfg: Optional[dict] = None, **overrides: Any) -> None:
        cfg = {**to_plain(cfg), **overrides}
        self.cfg = cfg
        self.kind = cfg.get("name") or "h3ds"
        self.path = cfg.get("path")
        if self.path is None:
            if self.kind != "h3ds":
                raise ConfigError(f"data.path is required for data={self.kind} (only h3ds has a default scene).")
            self.path = DEFAULT_SCENE
        self.ndc_opt = cfg.get("ndc")
        bg = cfg.get("background_color", (1.0, 1.0, 1.0))
        if isinstance(bg, str):
            if bg not in _NAMED_COLORS:
                raise ConfigError("data.background_color must be white, black, null or [r,g,b] in [0,1].")
            bg = _NAMED_COLORS[bg]
        self.background = None if bg is None else tuple(float(x) for x in bg)
        self.loader_opts = {k: v for k, v in cfg.items() if k not in _DM_KEYS}
        self.cache_root = Path(cfg["cache_root"]) if cfg.get("cache_root") else None
        self.scene: Optional[Scene] = None
        self.train_rays: Optional[dict] = None

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

            context = LoaderContext(background=self.background, cache_root=self.cache_root)
            self.scene = load_scene(self.kind, self.path, context=context, **self.loader_opts)
        return self.scene

    def setup(self, stage: Optional[str] = None) -> None:
        """Load the scene; for ``stage="fit"`` (or None) also precompute ``train_rays``."""
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

    def val_dataloader(self) -> DataLoader:
        """The held-out views (the first training view when there are none), one full view per batch."""
        scene = self.load()
        ids = scene.val_ids or scene.train_ids[:1]
        return DataLoader(_ViewDataset(self, ids), batch_size=None, num_workers=0)


def datamodule_of(cfg: Any, cache_root: Optional[Path] = None) -> "SceneDataModule":
    """The datamodule of a run's ``data`` section (``cfg``: a RunConfig), behind ``render.background_color`` unless
    ``data.background_color`` says otherwise; ``cache_root``: the loaders' cache folder (selfie frames, SfM)."""
    return SceneDataModule({"background_color": cfg.render.background_color, **cfg.plain["data"],
                            **({"cache_root": str(cache_root)} if cache_root is not None else {})})
