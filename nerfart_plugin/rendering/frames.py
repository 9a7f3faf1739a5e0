"""Frames of a camera path: the channels ``stage=render`` and the Python API write.

Channels (``render.channels``), each a list of HxWx3 uint8 frames:

* ``rgb``: the colour render;
* ``depth``: expected termination distance (normalized scene units; NDC t for forward-facing
  captures) in matplotlib's ``turbo`` colour map, ONE range for the whole path (the 1st-99th
  percentile over the covered pixels of every frame), so the video does not flicker;
* ``normal``: ``(n + 1) / 2`` of the unit normal in the normalized frame: the SDF backbones'
  rendered normals, for fields without one (NeRF) the normal of the surface the depth map
  describes (cross product of its pixel neighbours' points);
* ``opacity``: accumulated weight, grey;
* ``side``: source | stylized colour renders side by side (stylization runs).

Pixels with opacity < 0.5 show the background colour (white) in depth / normal.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.utils.device import to_device
from nerfart_plugin.utils.images import side_by_side, to_uint8

log = logging.getLogger(__name__)

CHANNELS = ("rgb", "depth", "normal", "opacity", "side")


@torch.no_grad()
def render_cameras(renderer: Any, path: Any, *, ndc: bool, near: float, far: float, chunk: int,
                   device: torch.device, channels: Sequence[str] = ("rgb",), source: Any = None,
                   labels: tuple[str, str] = ("source", "stylized"), progress: bool = True,
                   on_frame: Optional[Callable[[int, int], None]] = None,
                   outputs: Optional[dict[str, list]] = None) -> dict[str, list[np.ndarray]]:
    """Render every camera of ``path`` (:class:`~nerfart_plugin.cameras.path.RenderPath`) without grad.

    Args:
        renderer: the trained renderer (eval mode); source: the source renderer, for ``side``.
        ndc: NDC rays (forward-facing captures); near / far: ray bounds (normalized units).
        chunk: rays per no-grad chunk (memory only).
        on_frame: called with (frames done, frames in all) after each camera (a progress display).
        outputs: if given, each frame's renders as images [H,W,C] (``rgb``, ``depth``, ``opacity``, on
            ``device``) are appended to ``outputs["rendered"]`` (and the source's, for ``side``, to
            ``outputs["source"]``): what a metric over the frames reads (view consistency).

    Returns:
        channel -> list of [H,W,3] uint8 frames (``side``: [H, 2W + gap, 3]).
    """

    unknown = [c for c in channels if c not in CHANNELS]
    if unknown:
        raise ConfigError(f"render.channels: unknown {unknown}; choose from {list(CHANNELS)}.")
    if "side" in channels and source is None:
        raise ConfigError("render.channels=side shows source | stylized: render a stylization run (this one has no "
                          "source), or drop side.")
    want_normal = "normal" in channels
    raw: dict[str, list[np.ndarray]] = {c: [] for c in channels}
    depths, opacities = [], []
    for i in tqdm(range(len(path)), desc=f"rendering {path.name}", disable=not progress, leave=False):
        b = to_device(camera_batch(path.K[i], path.c2w[i], path.height, path.width, near, far, ndc), device)
        out = _images(renderer.render_chunked(b, chunk=chunk, with_normals=want_normal), path.height, path.width)
        opacity = out["opacity"][..., 0].cpu().numpy()
        if "rgb" in channels:
            raw["rgb"].append(to_uint8(out["rgb"]))
        if "side" in channels:
            src = _images(source.render_chunked(b, chunk=chunk, with_normals=False), path.height, path.width)
            raw["side"].append(side_by_side(to_uint8(src["rgb"]), to_uint8(out["rgb"]), labels=labels))
            if outputs is not None:
                outputs.setdefault("source", []).append(src)
        if outputs is not None:
            outputs.setdefault("rendered", []).append(out)
        if "opacity" in channels:
            raw["opacity"].append(to_uint8(out["opacity"]))
        if want_normal:
            n = out["normal"] if "normal" in out else depth_normals(b, out["depth"])
            raw["normal"].append(normal_image(n.cpu().numpy(), opacity))
        depths.append(out["depth"][..., 0].cpu().numpy())
        opacities.append(opacity)
        if on_frame is not None:
            on_frame(i + 1, len(path))
    if "depth" in channels:
        raw["depth"] = colorize_depth(depths, opacities)
    return raw


def _images(out: dict[str, Any], H: int, W: int) -> dict[str, torch.Tensor]:
    return {k: v.reshape(H, W, -1) for k, v in out.items() if torch.is_tensor(v)}


def depth_normals(batch: dict[str, Any], depth: torch.Tensor) -> torch.Tensor:
    """[H,W,3] unit normals of the surface a depth map [H,W,1] describes (points o + t d of the batch's
    rays; central differences), facing the camera."""
    H, W = int(batch["H"]), int(batch["W"])
    pts = (batch["rays_o"] + batch["rays_d"] * depth.reshape(-1, 1)).reshape(H, W, 3)
    du = torch.zeros_like(pts)
    dv = torch.zeros_like(pts)
    du[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dv[1:-1] = pts[2:] - pts[:-2]
    n = torch.linalg.cross(dv, du, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    facing = (n * batch["rays_d"].reshape(H, W, 3)).sum(-1, keepdim=True)
    return torch.where(facing > 0, -n, n)


def normal_image(normal: np.ndarray, opacity: np.ndarray, background: float = 1.0) -> np.ndarray:
    """[H,W,3] uint8 of ``(n + 1) / 2`` (unit-normalized) where ``opacity`` >= 0.5, else ``background``."""
    n = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    img = np.where(opacity[..., None] >= 0.5, (n + 1.0) / 2.0, background)
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def colorize_depth(depths: list[np.ndarray], opacities: list[np.ndarray],
                   limits: Optional[tuple[float, float]] = None) -> list[np.ndarray]:
    """Depth maps [H,W] -> turbo-coloured [H,W,3] uint8 frames with one range for all of them (``limits``,
    default the 1st-99th percentile of the covered pixels, opacity >= 0.5); uncovered pixels white."""
    from matplotlib import colormaps

    covered = np.concatenate([d[o >= 0.5] for d, o in zip(depths, opacities)]) if depths else np.zeros(0)
    if limits is None:
        limits = (float(np.percentile(covered, 1)), float(np.percentile(covered, 99))) if covered.size else (0.0, 1.0)
    lo, hi = limits
    cmap = colormaps["turbo"]
    frames = []
    for d, o in zip(depths, opacities):
        x = np.clip((d - lo) / max(hi - lo, 1e-8), 0, 1)
        rgb = cmap(x)[..., :3]
        rgb[o < 0.5] = 1.0
        frames.append((rgb * 255 + 0.5).astype(np.uint8))
    return frames
