"""TOY guidance: a deterministic colour-statistics image/text encoder pair.

Not CLIP and not learned; it exists so that the stylization pipeline can be
run and tested end to end without pretrained weights (``is_real=False``).

Embedding layout (D = 5 + ``num_structure``):

=========  =====================================================================
dims       meaning
=========  =====================================================================
0..2       chroma: mean RGB minus its grey level (image) / colour minus grey (text)
3          brightness: mean luminance − 0.5
4          constant 0.5 (keeps every embedding non-zero, so cosines are defined)
5..        structure: fixed random projection (seed 0) of the Sobel edge
           magnitude of the 16×16 downsampled intensity (image); 0 for colour
           words (text)
=========  =====================================================================

Text: prompts containing colour words ("red", "green", "blue", "yellow",
"purple", "orange", "white", "black", "gray"/"grey", "pink", "brown", "cyan",
"magenta") map to that colour (several -> their mean); neutral source prompts
made only of words like "a photo of a person" map to grey; anything else gets a
deterministic pseudo-random embedding seeded by the SHA-256 of the
lower-cased prompt. The image encoder is differentiable, so optimizing an
image with the directional loss toward "red" from "a photo" makes it redder.
"""

from __future__ import annotations

import hashlib
import re
from typing import Annotated, Any, ClassVar, Optional

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Int, Limits, Setting
from nerfart_plugin.guidance.base import Guidance, WeightsPolicy

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.0, 0.0),
    "green": (0.0, 1.0, 0.0),
    "blue": (0.0, 0.0, 1.0),
    "yellow": (1.0, 1.0, 0.0),
    "purple": (0.5, 0.0, 0.5),
    "orange": (1.0, 0.5, 0.0),
    "white": (1.0, 1.0, 1.0),
    "black": (0.0, 0.0, 0.0),
    "gray": (0.5, 0.5, 0.5),
    "grey": (0.5, 0.5, 0.5),
    "pink": (1.0, 0.75, 0.8),
    "brown": (0.6, 0.3, 0.1),
    "cyan": (0.0, 1.0, 1.0),
    "magenta": (1.0, 0.0, 1.0),
}

#: Prompts made only of these words are "neutral" (source prompts) -> grey.
NEUTRAL_WORDS = frozenset(
    "a an the of photo photograph picture image render rendering person people human face head "
    "man woman girl boy portrait scene object selfie".split()
)

_LUMA = (0.299, 0.587, 0.114)
_GREY = (0.5, 0.5, 0.5)
_STRUCT_RES = 16


def _luma(rgb: tuple[float, float, float]) -> float:
    return sum(c * w for c, w in zip(rgb, _LUMA))


@register("guidance", "toy")
class ToyGuidance(Guidance):
    """TOY deterministic encoder pair (see module docstring). ``is_real=False``.

    Args:
        num_structure: number of structure (edge projection) dims.
        structure_scale: weight of the structure dims relative to colour.
        input_size: nominal input side reported to callers (patch / render size);
            the encoder itself accepts any size (structure features are pooled to 16×16).
    """

    name = "toy"
    is_real = False

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance"

        num_structure: Annotated[Int, Limits(ge=0, le=1024)] = Setting(
            8, description="structure (edge projection) dimensions of the embedding")
        structure_scale: Annotated[Float, Limits(ge=0.0, le=100.0)] = Setting(
            0.5, description="weight of the structure dimensions relative to colour")
        input_size: Annotated[Int, Limits(ge=8, le=1024)] = Setting(
            64, description="nominal input side reported to callers (patch and render size)")

    #: the perceptual network (``guidance.perceptual``) used with this guide unless set
    default_perceptual = "edges"

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None, **options: Any) -> None:
        super().__init__()
        self.cfg = c = self.Config.build(cfg, **options)
        num_structure, structure_scale, input_size = c.num_structure, c.structure_scale, c.input_size
        self.num_structure = int(num_structure)
        self.structure_scale = float(structure_scale)
        self.input_size = int(input_size)
        self.embed_dim = 5 + self.num_structure
        g = torch.Generator().manual_seed(0)
        proj = torch.randn(_STRUCT_RES * _STRUCT_RES, self.num_structure, generator=g) / _STRUCT_RES
        self.register_buffer("proj", proj, persistent=False)
        self.register_buffer("luma", torch.tensor(_LUMA), persistent=False)

    # ---------------------------------------------------------------------- images
    def _encode_image(self, img: Tensor) -> Tensor:
        x = img.float()
        mean_rgb = x.mean(dim=(2, 3))  # [B,3]
        chroma = mean_rgb - mean_rgb.mean(dim=1, keepdim=True)
        bright = (mean_rgb * self.luma).sum(dim=1, keepdim=True) - 0.5
        bias = torch.full_like(bright, 0.5)
        gray = (x * self.luma.view(1, 3, 1, 1)).sum(dim=1, keepdim=True)
        small = F.adaptive_avg_pool2d(gray, _STRUCT_RES)  # area downsample (anti-aliased, cheap)
        edges = kornia.filters.sobel(small).flatten(1)  # [B,256]
        struct = self.structure_scale * (edges @ self.proj)
        return torch.cat([chroma, bright, bias, struct], dim=1)

    # ------------------------------------------------------------------------ text
    def _text_vector(self, text: str) -> Tensor:
        words = re.findall(r"[a-z]+", text.lower())
        colours = [COLOURS[w] for w in words if w in COLOURS]
        if not colours and all(w in NEUTRAL_WORDS for w in words) and words:
            colours = [_GREY]
        if colours:
            rgb = tuple(sum(c[i] for c in colours) / len(colours) for i in range(3))
            grey = sum(rgb) / 3.0
            head = [rgb[0] - grey, rgb[1] - grey, rgb[2] - grey, _luma(rgb) - 0.5, 0.5]  # type: ignore[arg-type]
            return torch.tensor(head + [0.0] * self.num_structure)
        seed = int.from_bytes(hashlib.sha256(text.strip().lower().encode("utf-8")).digest()[:8], "little")
        g = torch.Generator().manual_seed(seed % (2**63))
        v = torch.randn(self.embed_dim, generator=g)
        v = v / v.norm()
        v[4] = 0.5
        return v

    def _encode_texts(self, texts: list[str]) -> Tensor:
        return torch.stack([self._text_vector(t) for t in texts]).to(self.device)
