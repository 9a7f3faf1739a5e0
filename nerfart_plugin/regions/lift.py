"""Regions lifted from 2D masks: per-view masks voted into a grid over the field box by the rendering weights.

For every view that has a mask, rays are cast through its pixels (at most ``max_side`` pixels a side) and rendered
without grad; each sample adds its weight to the voxel it falls in, and to that voxel's inside tally when its
pixel is inside the mask. A voxel's score is the weighted share of the rays through it that fall inside masks
(``inside / total``); voxels no masked ray reaches score 0. The scores above ``threshold`` form the region
(dilated by ``dilate`` cells to close the gaps between the samples' voxels); its geometry mask is dilated further
when the region is bound to a run (:meth:`~nerfart_plugin.regions.region.Region.bind`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Union

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm.auto import tqdm

from nerfart_plugin.cameras.path import scaled_K
from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.utils.device import to_device

log = logging.getLogger(__name__)

#: image suffixes read as masks
MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def view_masks(run: Any, folder: Union[str, Path]) -> dict[int, np.ndarray]:
    """View index -> mask [H,W] in [0, 1] at the capture's image size: the files of ``folder`` named after the
    capture's images (same stem) or by view index (``7.png``, ``0007.png``); ``folder="capture"``: the capture's
    own foreground masks (its data must be on this machine)."""
    cams = run.cameras
    if str(folder) == "capture":
        scene = run.scene()
        if scene.masks is None:
            raise DataError(f"{run.folder}: the capture has no foreground masks; give a folder of masks instead.")
        return {i: scene.masks[i].numpy() for i in range(scene.masks.shape[0])}
    root = Path(folder).expanduser()
    if not root.is_dir():
        raise DataError(f"region masks: {root} is not a folder of mask images (white = region).")
    stems = {Path(n).stem: i for i, n in enumerate(cams.names)}
    out: dict[int, np.ndarray] = {}
    for path in sorted(p for p in root.iterdir() if p.suffix.lower() in MASK_SUFFIXES):
        i = stems.get(path.stem)
        if i is None and path.stem.isdigit():
            i = int(path.stem)
        if i is None or not 0 <= i < len(cams.c2w):
            raise DataError(f"region masks: {path.name} names no view of the capture (use an image's name, e.g. "
                            f"{Path(cams.names[0]).stem if cams.names else '0'}.png, or a view index 0..{len(cams.c2w) - 1}).")
        try:
            img = Image.open(path)
            img.load()
        except OSError as exc:
            raise DataError(f"region masks: {path} is not an image ({exc}).") from None
        mask = np.asarray(img.convert("L").resize((cams.width, cams.height), Image.BILINEAR), dtype=np.float32)
        out[i] = mask / 255.0
    if not out:
        raise DataError(f"region masks: {root} holds no mask images ({', '.join(MASK_SUFFIXES)}).")
    return out


@torch.no_grad()
def lift_masks(run: Any, folder: Union[str, Path], resolution: int = 64, threshold: float = 0.5, dilate: int = 1,
               max_side: int = 128, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """The region the masks of ``folder`` (:func:`view_masks`) select on ``run``'s field (``run``: a finished run,
    anything with ``renderer``, ``cameras`` and ``device``), as ``(values [D,H,W] in {0, 1},
    world_to_grid [4,4])`` for :meth:`~nerfart_plugin.regions.region.Region.grid`.

    Args:
        resolution: voxels a side over the field box; threshold: the inside share a voxel needs.
        dilate: cells the voted region grows by; max_side: long side (pixels) the views are rendered at.
    """
    cams = run.cameras
    if cams.ndc:
        raise ConfigError("region from masks: forward-facing (NDC) captures are not supported; use a box or "
                          "ellipsoid region (region.box=[...]).")
    if not 0.0 < threshold < 1.0:
        raise ConfigError(f"region from masks: threshold={threshold}: a share in (0, 1).")
    masks = view_masks(run, folder)
    renderer, device = run.renderer, run.device
    bound, n = float(renderer.field.bound), int(resolution)
    total = torch.zeros(n ** 3, dtype=torch.float64, device=device)
    inside = torch.zeros_like(total)
    scale = min(1.0, max_side / max(cams.width, cams.height))
    H, W = max(1, round(cams.height * scale)), max(1, round(cams.width * scale))
    for i, mask in tqdm(sorted(masks.items()), desc="lifting masks", leave=False):
        m = F.interpolate(torch.from_numpy(mask)[None, None], size=(H, W), mode="area").reshape(-1)
        K = scaled_K(cams, [i], H, W)[0]
        c2w = torch.as_tensor(cams.c2w[i], dtype=torch.float32)
        batch = camera_batch(K, c2w, H, W, float(cams.near[i]), float(cams.far[i]), False)
        for s in range(0, H * W, chunk):
            part = to_device({k: (v[s:s + chunk] if torch.is_tensor(v) else v) for k, v in batch.items()}, device)
            out = renderer(part)
            pts = part["rays_o"][:, None] + part["rays_d"][:, None] * out["t"][..., None]
            cell = ((pts / bound + 1.0) * 0.5 * (n - 1)).round().long()
            ok = ((cell >= 0) & (cell < n)).all(-1)
            flat = (cell[..., 2] * n + cell[..., 1]) * n + cell[..., 0]
            w = out["weights"].double() * ok
            total.index_add_(0, flat[ok], w[ok])
            inside.index_add_(0, flat[ok], (w * m[s:s + chunk].to(device).double()[:, None])[ok])
    seen = total > 1e-3
    score = torch.where(seen, inside / total.clamp_min(1e-12), torch.zeros_like(total)).float().reshape(n, n, n)
    values = (score > threshold).float()
    if dilate > 0:
        values = F.max_pool3d(values[None, None], kernel_size=2 * dilate + 1, stride=1, padding=dilate)[0, 0]
    log.info("region from %d masked view(s): %d of %d voxels (%.1f%% of those the views reach)", len(masks),
             int(values.sum()), n ** 3, 100.0 * float((score > threshold).sum()) / max(1, int(seen.sum())))
    world_to_grid = np.diag([1.0 / bound] * 3 + [1.0]) @ np.asarray(cams.normalization, dtype=np.float64)
    return values.cpu().numpy(), world_to_grid
