"""Model only what a scene requires: choose field extent, background and sampling from the scene.

Every choice is logged with its reason and can be overridden from config
(``render.background_model``, ``render.occupancy.*``, ``render.num_samples``,
``reconstruct.mask_ray_share``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Any, Optional

from nerfart_plugin.config.schema import ReconstructConfig, RenderConfig
from nerfart_plugin.config.validate import section
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

#: ``resolution: auto`` picks a side in [AUTO_GRID_MIN, AUTO_GRID_MAX], a multiple of AUTO_GRID_STEP
AUTO_GRID_MIN, AUTO_GRID_MAX, AUTO_GRID_STEP = 128, 512, 32
#: ``cell_pixels`` default: image pixels per cell that ``resolution: auto`` aims at
AUTO_CELL_PIXELS = 3.0
#: ``levels: auto`` for SDF fields (the finest side and two coarser ones, e.g. [32, 64, 128]): on the head
#: (10 min, VolSDF) held-out masked PSNR read 26.8-26.9 dB against 26.3 dB with one level (README, "grid
#: encoding"); density fields keep one level (not measured with more)
AUTO_SDF_LEVELS = 3


def auto_grid_resolution(pixels_per_unit: float, bound: float, cell_pixels: float) -> int:
    """Grid side for ``encoding.resolution=auto``: the cells across the field box ``[-bound, bound]``
    such that one cell spans about ``cell_pixels`` image pixels where the scene is
    (``pixels_per_unit``: image pixels per unit of field coordinates there), rounded up to a multiple
    of 32 and kept in [128, 512]: 128 is the side every small-image default was measured at, 512 keeps
    the planes under 7 M parameters."""
    cells = 2.0 * float(bound) * float(pixels_per_unit) / float(cell_pixels)
    side = AUTO_GRID_STEP * math.ceil(cells / AUTO_GRID_STEP - 1e-9)
    return int(min(AUTO_GRID_MAX, max(AUTO_GRID_MIN, side)))


#: ``reconstruct.mask_ray_share=auto``: the share of each batch drawn inside the mattes where the subject
#: fills less than :data:`AUTO_MATTE_MINORITY` of the training pixels (else 0: uniform rays). The runs
#: behind both numbers (the head, 39% mattes, gains at 0.8; two selfies, 52-56%, lose with any share)
#: are in README "Method".
AUTO_MASK_RAY_SHARE = 0.8
#: the matte fraction of the training pixels below which ``auto`` draws :data:`AUTO_MASK_RAY_SHARE`
AUTO_MATTE_MINORITY = 0.5


@dataclass
class SceneSetup:
    """What the renderer needs to know about a scene, decided once before training.

    Attributes:
        capture: the Scene's capture type.
        bound: half side of the field box [-bound, bound]^3 (normalized units).
        background_model: a learned environment map behind the field.
        background_color: constant colour behind the field (None: no compositing).
        ndc: rays are NDC-warped (forward-facing captures).
        occupancy_resolution: cells per side of the occupancy grid (0 = off).
        occupancy_sampling: where the grid puts samples: ``occupied`` (uniformly over occupied cells) or
            ``weighted`` (density backbones: by the cells' transmittance-weighted opacities).
        num_samples: samples per ray.
        has_masks: foreground masks are available (mask loss on).
        reasons: why each choice was made (logged, written to metrics.json).
        grid_resolution: cells per side of the grid encoding where ``encoding.resolution=auto``
            (None: the encoding's own resolution).
        grid_levels: levels of the grid encoding where ``encoding.levels=auto`` (None: the encoding's own;
            a checkpoint from before this setting rebuilds with one level).
        matte_fraction: share of the training pixels inside the mattes (mask > 0.5; None without mattes).
        mask_ray_share: share of each reconstruction batch drawn inside the mattes where
            ``reconstruct.mask_ray_share=auto`` (None: the config's number applies, or no mattes).
    """

    capture: str
    bound: float
    background_model: bool
    background_color: Optional[list[float]]
    ndc: bool
    occupancy_resolution: int
    num_samples: int
    has_masks: bool
    reasons: list[str] = field(default_factory=list)
    occupancy_sampling: str = "occupied"
    grid_resolution: Optional[int] = None
    grid_levels: Optional[int] = None
    matte_fraction: Optional[float] = None
    mask_ray_share: Optional[float] = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def auto_choices(self) -> dict[str, Any]:
        """What the scene's ``auto`` settings became (setting -> value; :mod:`nerfart_plugin.config.auto`)."""
        return {"render.background_model": self.background_model,
                "render.occupancy.enabled": self.occupancy_resolution > 0,
                "render.occupancy.sampling": self.occupancy_sampling,
                "encoding.resolution": self.grid_resolution, "encoding.levels": self.grid_levels,
                "reconstruct.mask_ray_share": self.mask_ray_share or 0.0}


def pixels_per_unit(scene: Scene, ndc: bool) -> float:
    """Image pixels per unit of field coordinates where the scene is: in NDC, the long image side over the
    2 units it spans; otherwise the median over the training cameras of focal length (px) over the
    camera's distance to the origin, the centre of the normalized scene."""
    if ndc:
        return max(scene.height, scene.width) / 2.0
    ids = scene.train_ids or list(range(scene.num_images))
    dist = scene.c2w[ids, :, 3].norm(dim=-1).clamp_min(1e-6)
    focal = scene.K[ids, 0, 0].abs()
    return float((focal / dist).median())


def decide_setup(scene: Scene, render_cfg: RenderConfig | dict[str, Any], ndc: bool,
                 opacity_scores: bool = False, encoding_cfg: Any = None,
                 reconstruct_cfg: ReconstructConfig | dict[str, Any] | None = None) -> SceneSetup:
    """Pick extent/background/sampling for ``scene`` from its capture type and resolution
    (``render_cfg``: the ``render`` section, typed or as a dict of its keys; ``opacity_scores``: the
    field's occupancy grid scores cells by opacity (density fields, ``backbone=nerf``;
    :func:`~nerfart_plugin.fields.occupancy_scores_opacity`); ``encoding_cfg``: the ``encoding``
    section, whose ``resolution: auto`` is decided here; ``reconstruct_cfg``: the ``reconstruct``
    section, whose ``mask_ray_share: auto`` is decided here (default: its defaults))."""
    rc = section(RenderConfig, render_cfg)
    reasons: list[str] = []
    has_masks = scene.masks is not None
    bg_opt = rc.background_model
    if bg_opt == "auto":
        background_model = scene.capture == "unbounded" and not has_masks
        if background_model:
            reasons.append("unbounded capture without masks: learned environment map behind the unit sphere")
        elif scene.capture == "forward_facing":
            reasons.append("forward-facing capture: NDC space reaches infinity, no background model")
        else:
            reasons.append(f"{scene.capture} capture with masks: constant background colour, no background model")
    else:  # true | false (the schema allows nothing else)
        background_model = bg_opt
        reasons.append(f"background model {'on' if bg_opt else 'off'} by render.background_model")

    background_color = rc.background_color
    if ndc or background_model:
        background_color = None
    if ndc:
        # NDC x, y of cameras away from the mean pose reach about +-1.45 (fern: 1.44) at t = 0 or 1;
        # a [-1,1] box would clip the image borders and cap the PSNR.
        bound = rc.ndc_bound
        reasons.append(f"field box [-{bound:g},{bound:g}]^3 in NDC (off-centre cameras leave the unit NDC cube)")
    else:
        bound = 1.0
        reasons.append("field box [-1,1]^3: unit sphere of the normalized scene")

    occ = rc.occupancy
    sampling = occ.sampling
    if sampling == "auto":
        # In NDC the occupied cells are nearly all of them: only a density field's opacities (a proposal)
        # tell a ray where to put its samples. Elsewhere the occupied cells are a tight shell already.
        sampling = "weighted" if ndc and opacity_scores else "occupied"
    if sampling == "weighted" and not opacity_scores:
        raise ConfigError("render.occupancy.sampling=weighted needs a density backbone (backbone=nerf): an SDF "
                          "backbone's grid marks a shell around its surface, not opacities. Use "
                          "render.occupancy.sampling=occupied (or auto).")
    enabled = occ.enabled
    if enabled == "auto":
        # An NDC frustum is scene from the near plane to infinity: a forward-facing capture leaves
        # almost no empty cells to skip (fern: ~53% occupied), and the grid's refreshes then cost
        # more than they save (BENCHMARKS.md, scene_setup). Bounded/object captures are mostly empty.
        # Weighted sampling asks for the grid (it proposes where rays end), NDC or not.
        enabled = not ndc or sampling == "weighted"
        if ndc and enabled:
            reasons.append("occupancy grid on in NDC for weighted sampling (a density backbone's default there): "
                           "the cells' transmittance-weighted opacities place the samples where rays end")
        elif ndc:
            reasons.append("occupancy grid off: an NDC frustum is nearly all occupied, nothing to skip "
                           "(render.occupancy.enabled=true forces it)")
    occ_res = occ.resolution if enabled else 0
    if occ_res:
        # No point resolving the grid finer than what a pixel footprint can resolve.
        pixel_limited = max(16, min(occ_res, 2 ** (max(scene.height, scene.width) - 1).bit_length() // 2))
        if pixel_limited < occ_res:
            reasons.append(f"occupancy grid {pixel_limited}^3 (image {scene.width}x{scene.height} cannot resolve {occ_res}^3)")
            occ_res = pixel_limited
        else:
            reasons.append(f"occupancy grid {occ_res}^3 for empty-space skipping")
    elif occ.enabled is False:
        reasons.append("occupancy grid off (render.occupancy.enabled=false): uniform stratified sampling")
    num_samples = rc.num_samples
    if occ_res and sampling == "weighted" and occ.weighted_samples:
        num_samples = occ.weighted_samples
        reasons.append(f"{num_samples} samples per ray (render.occupancy.weighted_samples): weighted sampling "
                       "crowds them where rays end")
    encoding = dict(encoding_cfg or {})  # a typed section or a mapping: its settings
    grid_levels = _grid_levels(encoding, opacity_scores, reasons)
    grid_res = _grid_resolution(scene, ndc, bound, encoding, reasons)
    matte_fraction = _matte_fraction(scene)
    mask_share = _mask_ray_share(matte_fraction, section(ReconstructConfig, reconstruct_cfg), reasons)
    setup = SceneSetup(scene.capture, bound, background_model, background_color, ndc, occ_res, num_samples,
                       has_masks, reasons, sampling if occ_res else "occupied", grid_res, grid_levels,
                       matte_fraction, mask_share)
    for r in reasons:
        log.info("scene setup: %s", r)
    return setup


def _grid_levels(encoding_cfg: dict[str, Any], opacity_scores: bool, reasons: list[str]) -> Optional[int]:
    """The grid encoding's levels for ``encoding.levels=auto`` (None for any other setting, or a list of sides)."""
    resolution = encoding_cfg.get("resolution")
    if encoding_cfg.get("levels") != "auto" or not (resolution == "auto" or isinstance(resolution, int)):
        return None
    if opacity_scores:
        reasons.append("grid encoding with one level: a density field (encoding.levels=auto)")
        return 1
    reasons.append(f"grid encoding with {AUTO_SDF_LEVELS} levels, each coarser one half the side of the next: "
                   "an SDF field (encoding.levels=auto)")
    return AUTO_SDF_LEVELS


def _grid_resolution(scene: Scene, ndc: bool, bound: float, encoding_cfg: dict[str, Any],
                     reasons: list[str]) -> Optional[int]:
    """The grid encoding's side for ``encoding.resolution=auto`` (None for any other setting)."""
    if encoding_cfg.get("resolution") != "auto":
        return None
    ppu = pixels_per_unit(scene, ndc)
    cell_pixels = float(encoding_cfg.get("cell_pixels", AUTO_CELL_PIXELS))
    side = auto_grid_resolution(ppu, bound, cell_pixels)
    reasons.append(f"grid encoding {side} cells per side: about {cell_pixels:g} image px per cell at "
                   f"{ppu:.0f} px per unit over the {2 * bound:g}-unit box (encoding.resolution=auto; 128..512)")
    return side


def _matte_fraction(scene: Scene) -> Optional[float]:
    """Share of the training views' pixels inside the mattes (mask > 0.5); None without mattes."""
    if scene.masks is None:
        return None
    ids = scene.train_ids or list(range(scene.num_images))
    return float((scene.masks[ids] > 0.5).float().mean())


def _mask_ray_share(matte_fraction: Optional[float], cfg: ReconstructConfig, reasons: list[str]) -> Optional[float]:
    """The share of each reconstruction batch drawn inside the mattes for ``reconstruct.mask_ray_share=auto``
    (None for a number, which applies as it is, or without mattes)."""
    if cfg.mask_ray_share != "auto" or matte_fraction is None:
        return None
    if matte_fraction < AUTO_MATTE_MINORITY:
        reasons.append(f"reconstruction rays: {AUTO_MASK_RAY_SHARE:.0%} of each batch from inside the mattes after "
                       f"{cfg.mask_ray_share_after} steps: they cover {matte_fraction:.0%} of the training pixels "
                       "(reconstruct.mask_ray_share=auto: the subject is a minority of the frame)")
        return AUTO_MASK_RAY_SHARE
    reasons.append(f"reconstruction rays uniform over the pixels: the mattes cover {matte_fraction:.0%} of them, "
                   "so the subject gets most of each batch already and the background keeps its rays "
                   "(reconstruct.mask_ray_share=auto)")
    return 0.0
