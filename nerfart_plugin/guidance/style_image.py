"""Style from a picture: the reference image a stylization follows (``+style_image=<file>``), after ARF
(Zhang et al., *ARF: Artistic Radiance Fields*, ECCV 2022).

* :func:`read_style_image` reads a PNG or JPEG of any size into [3,H,W] in [0, 1]: 8- and 16-bit, grayscale
  (repeated to RGB), with transparency (composited on white), palette images; anything else, a missing file or a
  picture smaller than :data:`MIN_SIDE` is a ConfigError naming the file, raised before any work.
* :class:`StyleImage`: the picture at ``style_image.size`` (long side) and its content hash (the run's key).
* :func:`style_features`: the network whose features are matched, the perceptual network's family
  (``guidance.perceptual``) at the style layers (``style_image.layers``; ARF's VGG16 relu3_1-3_3 by default,
  EfficientNet-Lite0's blocks 1-2 where VGG16's weights are not at hand).
* :func:`match_palette`: the source views recoloured to the picture's palette, per channel histogram matching
  (scikit-image's ``match_histograms``) of the subject's pixels, ARF's colour transfer as a target.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.guidance import build_perceptual, perceptual_section

#: the smallest side (pixels) a style picture may have: its features need a few cells at stride 8
MIN_SIDE = 32
#: the file signatures read: PNG and JPEG
SIGNATURES = {b"\x89PNG\r\n\x1a\n": "PNG", b"\xff\xd8\xff": "JPEG"}
#: the feature layers matched when ``style_image.layers`` is auto, per perceptual network
DEFAULT_LAYERS = {"vgg": ("relu3_1", "relu3_2", "relu3_3"), "imagenet": ("block1", "block2"), "edges": ()}


def read_style_image(path: str | Path, setting: str = "style_image") -> Tensor:
    """The picture at ``path`` as [3,H,W] float32 in [0, 1] (see the module docstring for what is read)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"{setting}={path}: no such file. Give a PNG or JPEG picture of the style to follow.")
    head = p.open("rb").read(8)
    kind = next((name for sig, name in SIGNATURES.items() if head.startswith(sig)), None)
    if kind is None:
        raise ConfigError(f"{setting}={path}: not a PNG or JPEG file (its first bytes are {head[:4]!r}); save the "
                          "picture as .png or .jpg and give that file.")
    raw = _decode(p, kind)
    if raw is None:
        raise ConfigError(f"{setting}={path}: the {kind} file cannot be decoded (damaged or cut short); save it "
                          "again from an image editor.")
    img = _to_rgb(_to_unit(raw, p, setting))
    h, w = img.shape[1:]
    if min(h, w) < MIN_SIDE:
        raise ConfigError(f"{setting}={path}: the picture is {w}x{h} px; a style picture needs at least "
                          f"{MIN_SIDE} px on each side.")
    return img


def _decode(path: Path, kind: str) -> Optional[np.ndarray]:
    """The pixels of a PNG (all its bits and channels: OpenCV keeps 16 bits where Pillow drops them) or a JPEG
    (its EXIF orientation applied), RGB(A) order; None when the file cannot be decoded."""
    flag = cv2.IMREAD_UNCHANGED if kind == "PNG" else cv2.IMREAD_COLOR
    raw = cv2.imdecode(np.fromfile(path, dtype=np.uint8), flag)
    if raw is None:
        return None
    if raw.ndim == 3 and raw.shape[-1] >= 3:  # OpenCV's BGR(A) -> RGB(A)
        raw = np.concatenate([raw[..., 2::-1], raw[..., 3:]], axis=-1)
    return raw


def _to_unit(raw: np.ndarray, path: Path, setting: str) -> np.ndarray:
    """Pixel values in [0, 1] from 8- or 16-bit integers (or floats already in [0, 1])."""
    if raw.dtype == np.uint8:
        return raw.astype(np.float32) / 255.0
    if raw.dtype in (np.uint16, np.int32, np.uint32) and raw.max(initial=0) <= 65535:
        return raw.astype(np.float32) / 65535.0
    if raw.dtype.kind == "f":
        return np.clip(raw.astype(np.float32), 0.0, 1.0)
    raise ConfigError(f"{setting}={path}: pixels of type {raw.dtype} are not read; save the picture with 8 or 16 "
                      "bits per channel.")


def _to_rgb(img: np.ndarray) -> Tensor:
    """[H,W], [H,W,1-4] -> [3,H,W]: gray repeated, transparency composited on white."""
    if img.ndim == 2:
        img = img[..., None]
    channels = img.shape[-1]
    if channels in (2, 4):  # with alpha: on white
        alpha = img[..., -1:]
        img = img[..., :-1] * alpha + (1.0 - alpha)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return torch.from_numpy(np.ascontiguousarray(img[..., :3])).permute(2, 0, 1).float()


@dataclass(frozen=True)
class StyleImage:
    """A style picture, read and checked.

    Attributes:
        file: where it was read; content_hash: of the file's bytes (what a run's key holds);
        image: [3,H,W] in [0, 1], resized so that its long side is ``style_image.size`` px.
    """

    file: Path
    content_hash: str
    image: Tensor

    @classmethod
    def load(cls, file: str | Path, size: int) -> "StyleImage":
        img = read_style_image(file)
        scale = size / max(img.shape[1:])
        hw = [max(1, round(s * scale)) for s in img.shape[1:]]
        resized = F.interpolate(img[None], size=hw, mode="bilinear", antialias=scale < 1, align_corners=False)[0]
        digest = hashlib.sha256(Path(file).expanduser().read_bytes()).hexdigest()[:16]
        return cls(Path(file).expanduser().resolve(), digest, resized.clamp(0, 1))

    @property
    def name(self) -> str:
        """The file's stem, for folder names."""
        return self.file.stem


def style_layers(cfg: Any) -> tuple[str, tuple[str, ...]]:
    """The perceptual network family (``guidance.perceptual``'s name) and the layers ``style_image.layers``
    picks for it (auto: :data:`DEFAULT_LAYERS`)."""
    family = perceptual_section(cfg.guidance).name
    given = cfg.style_image.layers
    layers = DEFAULT_LAYERS.get(family, ()) if given == "auto" else tuple(given)
    return family, layers


def style_features(cfg: Any) -> nn.Module:
    """The frozen network whose features :func:`~nerfart_plugin.objectives.losses.nnfm_loss` matches: the
    perceptual network of ``cfg`` (its weights as ``guidance.perceptual`` loads them) at the style layers."""
    family, layers = style_layers(cfg)
    if family == "vgg":
        return build_perceptual(cfg.guidance, layers=list(layers))
    if family == "imagenet":
        bad = [n for n in layers if not (n.startswith("block") and n[5:].isdigit())]
        if bad:
            raise ConfigError(f"style_image.layers={list(layers)}: EfficientNet-Lite layers are named block0, "
                              f"block1, ... ({', '.join(bad)} is not one).")
        return build_perceptual(cfg.guidance, stages=[int(n[5:]) for n in layers])
    if layers:
        raise ConfigError(f"style_image.layers={list(layers)}: the {family!r} perceptual network has no named "
                          "layers; leave style_image.layers out.")
    return build_perceptual(cfg.guidance)


def match_palette(source: Tensor, style: Tensor, mask: Optional[Tensor] = None) -> Tensor:
    """``source`` [3,H,W] recoloured to ``style``'s [3,h,w] palette: each channel's histogram of the pixels in
    ``mask`` [H,W] (bool; default all) matched to the style picture's (``skimage.exposure.match_histograms``);
    the pixels outside ``mask`` (the background) unchanged."""
    from skimage.exposure import match_histograms

    src = source.detach().cpu().permute(1, 2, 0).numpy().astype(np.float64)
    ref = style.detach().cpu().permute(1, 2, 0).reshape(-1, 1, 3).numpy().astype(np.float64)
    keep = np.ones(src.shape[:2], dtype=bool) if mask is None else mask.detach().cpu().numpy().astype(bool)
    out = src.copy()
    if keep.any():
        out[keep] = match_histograms(src[keep][:, None, :], ref, channel_axis=-1)[:, 0, :]
    return torch.from_numpy(out).float().permute(2, 0, 1).to(source.device).clamp(0, 1)
