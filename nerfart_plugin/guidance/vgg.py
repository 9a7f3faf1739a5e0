"""Perceptual features for Eq. 9: VGG16 (paper) and a weight-free edge stand-in.

:class:`Perceptual` returns VGG16 activations at named ReLU layers. Default
layers ``relu1_2, relu2_2, relu3_3, relu4_3``: the last ReLU of each of the
first four blocks, the standard choice of Johnson et al.'s perceptual loss.
They cover fine colour/edge statistics (block 1) up to object parts (block 4);
block 5 is skipped because it is nearly invariant to layout at NeRF-Art's
render sizes and costs the most. The network is truncated after the deepest
requested layer.

Weights (``weights="DEFAULT"``): torchvision's ImageNet VGG16 file
``vgg16-397923af.pth`` is looked for in ``<torch.hub.get_dir()>/checkpoints``
first; downloaded only if downloads are allowed and download.pytorch.org
answers a 2 s connect; else WeightsMissingError. A local ``.pth`` path works
too. Random weights only with ``allow_random_weights=True``.

:class:`EdgePerceptual` is the TOY perceptual extractor paired with the toy
guidance: no weights, fixed kornia Sobel edges + colour at three scales.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Optional

import kornia
import torch
from torch import Tensor, nn

from nerfart_plugin.config.auto import dtype_name
from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Int, Limits, Setting
from nerfart_plugin.errors import ConfigError, WeightsMissingError
from nerfart_plugin.guidance import weights as wts
from nerfart_plugin.guidance.base import WeightsPolicy
from nerfart_plugin.guidance.precision import Precision, check_precision, compute_dtype

log = logging.getLogger(__name__)

#: Names of VGG16 ``features`` layers -> index in ``torchvision.models.vgg16().features``.
VGG16_LAYERS: dict[str, int] = {}
_blocks = [2, 2, 3, 3, 3]
_idx = 0
for _b, _n in enumerate(_blocks, start=1):
    for _c in range(1, _n + 1):
        VGG16_LAYERS[f"conv{_b}_{_c}"] = _idx
        VGG16_LAYERS[f"relu{_b}_{_c}"] = _idx + 1
        _idx += 2
    VGG16_LAYERS[f"pool{_b}"] = _idx
    _idx += 1
del _blocks, _idx, _b, _n, _c

DEFAULT_LAYERS: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3")
#: a layer name of :data:`VGG16_LAYERS` (the type of ``guidance.perceptual.layers`` items)
VGGLayer = Literal[tuple(VGG16_LAYERS)]  # type: ignore[valid-type]
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _vgg_state_dict(weights: str, allow_download: bool | None) -> dict[str, Tensor]:
    """Load the VGG16 state dict for ``weights`` ("DEFAULT"/"IMAGENET1K_V1" or a file path)."""
    from torchvision.models import VGG16_Weights

    if weights.upper() in ("DEFAULT", "IMAGENET1K_V1"):
        url = VGG16_Weights.IMAGENET1K_V1.url
        ckpt_dir = Path(torch.hub.get_dir()) / "checkpoints"
        path = ckpt_dir / os.path.basename(url)
        if not path.is_file():
            if wts.downloads_allowed(allow_download) and wts.host_reachable(url):
                log.info("Downloading VGG16 weights to %s", path)
                return torch.hub.load_state_dict_from_url(url, model_dir=str(ckpt_dir), progress=True)
            raise WeightsMissingError(
                f"VGG16 weights (torchvision VGG16_Weights.{weights.upper()}) not found at {path}.\n"
                f"{wts.download_hint(allow_download, 'download.pytorch.org')}\n"
                "How to supply them: on a machine with internet run\n"
                "  python -c \"import torchvision; torchvision.models.vgg16(weights='DEFAULT')\"\n"
                f"and copy {path.name} to {ckpt_dir} (or set TORCH_HOME), or download {url} and pass "
                "guidance.perceptual.weights=/path/to/vgg16.pth. Tests only: guidance.allow_random_weights=true."
            )
    else:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise WeightsMissingError(
                f"VGG16 weights file not found: guidance.perceptual.weights={weights!r} (looked at {path.resolve()}). "
                "Fix the path or use guidance.perceptual.weights=DEFAULT."
            )
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise WeightsMissingError(
            f"Could not read VGG16 weights {path} ({exc}); delete the file and re-download "
            "(python -c \"import torchvision; torchvision.models.vgg16(weights='DEFAULT')\")."
        ) from exc


@register("perceptual", "vgg")
class Perceptual(nn.Module):
    """Frozen VGG16 feature extractor for Eq. 9; settings: :class:`Perceptual.Config`.

    ``weights`` None (or "none", "random") builds random weights, which need ``policy.allow_random_weights``
    (loud warning, ``is_real=False``). ``precision``: features are returned as float32, so Eq. 9 is summed in
    float32 against float32 source features; in bf16 the loss stays within 2% and its image gradient within
    cosine 0.99 of fp32, and an unchanged view scores exactly 0 (``tests/test_guidance_vgg.py``).
    """

    name = "vgg16"

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance.perceptual"

        weights: Optional[str] = Setting(
            "DEFAULT", description="DEFAULT (torchvision's ImageNet weights) or a local .pth file")
        layers: Annotated[list[VGGLayer], Limits(min_length=1)] = Setting(
            list(DEFAULT_LAYERS), description="the VGG16 layers whose features Eq. 9 compares")
        max_size: Optional[Annotated[Int, Limits(ge=16, le=8192)]] = Setting(
            None, description="views with a longer side are downscaled (antialiased) to it first; null: as they are")
        precision: Precision = Setting(
            "auto", description="the trunk's arithmetic, as guidance.precision (features returned in float32)")

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None, **options: Any) -> None:
        c = self.Config.build(cfg, **options)
        policy = policy or WeightsPolicy()
        weights, layers, max_size, precision = c.weights, c.layers, c.max_size, c.precision
        allow_random_weights, allow_download = policy.allow_random_weights, policy.allow_download
        super().__init__()
        self.cfg = c
        from torchvision.models.vgg import cfgs, make_layers

        self.precision = check_precision(precision, "guidance.perceptual.precision")

        layers = list(layers)
        bad = [n for n in layers if n not in VGG16_LAYERS]
        if bad or not layers:
            raise ConfigError(
                f"guidance.perceptual.layers has unknown names {bad or '(empty)'}; valid: {', '.join(VGG16_LAYERS)}"
            )
        self.layers = layers
        self.max_size = max_size
        if isinstance(weights, str) and weights.strip().lower() in ("", "none", "null", "random"):
            weights = None
        state = None
        if weights is None:
            if not allow_random_weights:
                raise ConfigError(
                    "guidance.perceptual.weights is empty: use DEFAULT or a .pth path; random weights need "
                    "guidance.allow_random_weights=true (tests only)."
                )
        else:
            try:
                state = _vgg_state_dict(weights, allow_download)
            except WeightsMissingError as exc:
                if not allow_random_weights:
                    raise
                log.warning("%s\nFalling back to random weights (allow_random_weights=True).", exc)
        last = max(VGG16_LAYERS[n] for n in layers)
        # Only the convolutional trunk, cut after the deepest requested layer
        # (building full vgg16() would also initialise 120 M classifier weights).
        feats = make_layers(cfgs["D"], batch_norm=False)[: last + 1]
        if state is not None:
            sub = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")} or dict(state)
            sub = {k: v for k, v in sub.items() if int(k.split(".")[0]) <= last}
            try:
                feats.load_state_dict(sub, strict=True)
            except RuntimeError as exc:
                raise WeightsMissingError(
                    f"guidance.perceptual.weights={weights!r} does not hold torchvision VGG16 weights ({exc}); "
                    "use guidance.perceptual.weights=DEFAULT or a vgg16 .pth state dict."
                ) from exc
        self.is_real = state is not None
        if not self.is_real:
            log.warning("!!! VGG16 perceptual network uses RANDOM weights: perceptual loss is meaningless. !!!")
        for m in feats:
            if isinstance(m, nn.ReLU):
                m.inplace = False
        self.features_net = feats.eval()
        for p in self.features_net.parameters():
            p.requires_grad_(False)
        self._take = {VGG16_LAYERS[n]: n for n in layers}
        self.normalize = kornia.enhance.Normalize(torch.tensor(IMAGENET_MEAN), torch.tensor(IMAGENET_STD))

    def train(self, mode: bool = True) -> "Perceptual":  # stays in eval mode (frozen)
        super().train(mode)
        self.features_net.eval()
        return self

    def compute_dtype(self, device: torch.device) -> torch.dtype:
        """The dtype the trunk runs in on ``device`` (see ``precision``)."""
        return compute_dtype(self.precision, device, "guidance.perceptual.precision")

    def auto_choices(self, device: torch.device) -> dict[str, str]:
        """What ``guidance.perceptual.precision=auto`` becomes on ``device`` (:mod:`nerfart_plugin.config.auto`)."""
        return {"guidance.perceptual.precision": dtype_name(self.compute_dtype(device))}

    def features(self, img: Tensor) -> list[Tensor]:
        """``img`` [B,3,H,W] in [0,1] -> activations of ``self.layers`` (in that order),
        each [B,C_l,H_l,W_l]; differentiable w.r.t. ``img``."""
        if img.dim() != 4 or img.shape[1] != 3:
            raise ValueError(f"Perceptual.features expects [B,3,H,W] in [0,1], got {tuple(img.shape)}")
        with torch.autocast(img.device.type, enabled=False):  # float32 resize under trainer.precision=*-mixed
            x = img.float()
            if self.max_size is not None and max(x.shape[-2:]) > self.max_size:
                x = kornia.geometry.transform.resize(x, self.max_size, side="long", antialias=True)
            x = self.normalize(x)
        dtype = self.compute_dtype(x.device)
        out: dict[str, Tensor] = {}
        with torch.autocast(x.device.type, dtype=dtype, enabled=dtype != torch.float32):
            for i, m in enumerate(self.features_net):
                x = m(x)
                if i in self._take:
                    out[self._take[i]] = x
        return [out[n].float() for n in self.layers]

    def forward(self, img: Tensor) -> list[Tensor]:
        return self.features(img)


@register("perceptual", "edges")
class EdgePerceptual(nn.Module):
    """TOY perceptual extractor (no weights): for each of ``num_scales`` scales
    (1, 1/2, 1/4, antialiased) the image itself [B,3,h,w] and its kornia Sobel
    edge magnitude [B,3,h,w]. Deterministic and cheap; pairs with the toy
    guidance. ``is_real=False``."""

    name = "edges"
    is_real = False

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance.perceptual"

        num_scales: Annotated[Int, Limits(ge=1, le=8)] = Setting(3, description="scales, each half the previous")

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None, **options: Any) -> None:
        super().__init__()
        self.cfg = c = self.Config.build(cfg, **options)
        num_scales = c.num_scales
        self.num_scales = int(num_scales)
        self.layers = [f"{kind}@1/{2**s}" for s in range(self.num_scales) for kind in ("rgb", "sobel")]

    def features(self, img: Tensor) -> list[Tensor]:
        if img.dim() != 4 or img.shape[1] != 3:
            raise ValueError(f"EdgePerceptual.features expects [B,3,H,W], got {tuple(img.shape)}")
        out: list[Tensor] = []
        x = img.float()
        for s in range(self.num_scales):
            if s > 0:
                h, w = max(1, x.shape[-2] // 2), max(1, x.shape[-1] // 2)
                x = kornia.geometry.transform.resize(x, (h, w), antialias=True)
            out += [x, kornia.filters.sobel(x)]
        return out

    def forward(self, img: Tensor) -> list[Tensor]:
        return self.features(img)
