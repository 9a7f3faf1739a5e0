"""CLIP guidance via open_clip (paper: ViT-B/32, OpenAI weights).

Weights resolution is offline-first (see :mod:`nerfart_plugin.guidance.weights`):

1. ``pretrained`` is a file path -> load it (error if it does not exist).
2. ``pretrained`` is an open_clip tag (e.g. "openai") -> look for the file in
   the Hugging Face hub cache (``cache_dir`` or ``$HF_HUB_CACHE``, via
   ``huggingface_hub.try_to_load_from_cache``) and in open_clip's URL cache
   (``cache_dir`` or ``~/.cache/clip``). Found -> load that file.
3. Not found -> download through open_clip only if downloads are allowed and
   the host answers a 2 s TCP connect; otherwise raise WeightsMissingError
   (before any training starts) naming model + tag, the places searched and
   how to supply the file.
4. ``pretrained=None`` -> random weights, only with ``allow_random_weights=True``
   (also the fallback for 3. when ``allow_random_weights=True``); logs a loud
   warning and sets ``is_real=False``.

Preprocessing is differentiable (kornia): the whole image is resized to the
model's input size ("squash": every pixel receives gradient; CLIP's own
shortest-side-resize + centre-crop would leave the borders of portrait /
landscape renders unsupervised) with antialiasing, then normalized with the
model's mean/std. ``resize_mode="shortest"`` reproduces CLIP's crop.

Prompts longer than the 77-token context are truncated by open_clip's
tokenizer (the end-of-text token is kept); we log a warning naming the prompt.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, ClassVar, Literal, Optional

import kornia
import torch
from torch import Tensor
from torch.nn.attention import SDPBackend, sdpa_kernel

from nerfart_plugin.config.auto import dtype_name
from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Setting
from nerfart_plugin.errors import ConfigError, WeightsMissingError
from nerfart_plugin.guidance import weights as wts
from nerfart_plugin.guidance.base import Guidance, WeightsPolicy
from nerfart_plugin.guidance.clip_weights import find_cached, is_torchscript_archive, missing_message
from nerfart_plugin.guidance.precision import LowPrecisionWeights, Precision, check_precision, compute_dtype

log = logging.getLogger(__name__)

#: Tiny architecture (overrides for open_clip's model config) for tests with
#: random weights: 32 px input, 1-layer 64-wide towers, D=32. ~3 M params.
TINY_TEST_OVERRIDES: dict[str, Any] = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 32, "layers": 1, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 1},
}



class PatchEmbedding(torch.nn.Conv2d):
    """A ViT's patch embedding (a convolution whose stride is its kernel, no padding) as one matmul over
    the image's non-overlapping patches: the same sums, and on CPUs a backward to the image ~15x
    faster than oneDNN's strided convolution (ViT-B/32, one 224 px image in bf16: 0.9 against 13.5 ms
    in a scratch measurement; the whole tower: ``BENCHMARKS.md``, "Paper resolution"). Same
    parameters and state-dict keys as the ``nn.Conv2d`` it replaces."""

    def forward(self, x: Tensor) -> Tensor:
        """[B,C,H,W] (H, W multiples of the patch size) -> [B,D,H/p,W/p]."""
        (ph, pw), (B, C, H, W) = self.kernel_size, x.shape
        h, w = H // ph, W // pw
        if (h * ph, w * pw) != (H, W):
            raise ValueError(f"PatchEmbedding: image {H}x{W} is not a multiple of the patch size {ph}x{pw}")
        patches = x.reshape(B, C, h, ph, w, pw).permute(0, 2, 4, 1, 3, 5).reshape(B, h * w, C * ph * pw)
        out = torch.nn.functional.linear(patches, self.weight.reshape(self.out_channels, -1), self.bias)
        return out.reshape(B, h, w, self.out_channels).permute(0, 3, 1, 2)


def attention_kernels(device: torch.device) -> contextlib.AbstractContextManager:
    """The attention kernel the image tower runs with on ``device``: torch's math kernel on CPU, where
    at a ViT's ~50 tokens the flash kernel's backward is the slower one (ViT-B/32 in bf16, 13 images
    one at a time: ~6% of the tower in a scratch measurement); torch's choice elsewhere."""
    if device.type != "cpu":
        return contextlib.nullcontext()

    return sdpa_kernel(SDPBackend.MATH)


def use_matmul_patch_embedding(visual: torch.nn.Module) -> bool:
    """Swap ``visual.conv1`` (open_clip's ViT patch embedding) for a :class:`PatchEmbedding` sharing its
    weights, where it is a plain non-overlapping convolution. Returns True if swapped."""
    conv = getattr(visual, "conv1", None)
    if (type(conv) is not torch.nn.Conv2d or conv.stride != conv.kernel_size or conv.padding != (0, 0)
            or conv.dilation != (1, 1) or conv.groups != 1 or conv.padding_mode != "zeros"):
        return False
    emb = PatchEmbedding(conv.in_channels, conv.out_channels, conv.kernel_size, stride=conv.stride,
                         bias=conv.bias is not None, device="meta")
    emb.weight, emb.bias = conv.weight, conv.bias
    visual.conv1 = emb
    return True


@register("guidance", "clip")
class CLIPGuidance(Guidance):
    """Frozen open_clip model as :class:`Guidance`; settings: :class:`CLIPGuidance.Config`.

    ``pretrained`` None (or "none", "random") builds random weights, which need
    ``policy.allow_random_weights`` (loud warning, ``is_real=False``). ``quick_gelu`` None: the tag's setting,
    for local files True iff the file is an OpenAI TorchScript archive or its name contains "openai".
    ``precision``: weights and text embeddings stay fp32 (the image tower's matmul weights get one bf16/fp16
    copy, cast once: ``guidance.precision.LowPrecisionWeights``); embeddings stay within cosine 0.99995 and
    image gradients within cosine 0.9998 of fp32 (speed: ``BENCHMARKS.md``, stylization section). On CPU bf16
    images are encoded one at a time: with batches > 1, torch 2.14's CPU bf16 ``bmm`` path is far slower.
    ``device``: where to put the model (default CPU; ``.to()`` works as usual).
    """

    name = "clip"

    class Config(ComponentConfig):
        section: ClassVar[str] = "guidance"

        model: str = Setting("ViT-B-32", description="open_clip architecture (open_clip.list_models()); paper: ViT-B-32")
        pretrained: Optional[str] = Setting(
            "openai", description="open_clip weights tag (paper: openai) or a local checkpoint file")
        cache_dir: Optional[str] = Setting(None, description="weights cache folder; null: the HF hub / ~/.cache/clip")
        quick_gelu: Optional[bool] = Setting(
            None, description="QuickGELU activation; null: the tag's setting (OpenAI weights need it)")
        resize_mode: Literal["squash", "shortest"] = Setting(
            "squash", description="squash: the whole view to the input size; shortest: CLIP's resize + centre crop")
        model_overrides: Optional[dict[str, Any]] = Setting(
            None, description="extra keyword overrides of the open_clip model config (tests)")
        precision: Precision = Setting(
            "auto", description="image-encoder arithmetic: fp32 | bf16 | fp16 (CUDA) | auto (fp16 on CUDA, bf16 on "
            "CPUs with native bf16, else fp32)")

    #: the perceptual network (``guidance.perceptual``) used with this guide unless set
    default_perceptual = "vgg"

    def __init__(self, cfg: Optional[Any] = None, *, policy: Optional[WeightsPolicy] = None,
                 device: str | torch.device | None = None, **options: Any) -> None:
        c = self.Config.build(cfg, **options)
        policy = policy or WeightsPolicy()
        model, pretrained, cache_dir, quick_gelu = (c.model, c.pretrained, c.cache_dir,
                                                    c.quick_gelu)
        resize_mode, model_overrides, precision = c.resize_mode, c.model_overrides, c.precision
        allow_random_weights, allow_download = policy.allow_random_weights, policy.allow_download
        super().__init__()
        self.cfg = c
        import open_clip

        if model not in open_clip.list_models():
            raise ConfigError(
                f"guidance.model={model!r} is not an open_clip model; "
                f"choose one of open_clip.list_models(), e.g. 'ViT-B-32' (paper)."
            )
        if resize_mode not in ("squash", "shortest"):
            raise ConfigError(f"guidance.resize_mode={resize_mode!r}; use 'squash' or 'shortest'")
        self.precision = check_precision(precision, "guidance.precision")
        if isinstance(pretrained, str) and pretrained.strip().lower() in ("", "none", "null", "random"):
            pretrained = None
        self.model_name = model
        self.pretrained = pretrained
        self.resize_mode = resize_mode
        overrides = dict(model_overrides or {})

        checkpoint, tag_cfg = self._resolve(model, pretrained, cache_dir, allow_random_weights, allow_download)
        if quick_gelu is None:
            if tag_cfg:
                quick_gelu = bool(tag_cfg.get("quick_gelu", False))
            elif checkpoint:
                quick_gelu = "openai" in os.path.basename(checkpoint).lower() or is_torchscript_archive(checkpoint)
            else:
                quick_gelu = False
        try:
            net = open_clip.create_model(
                model,
                pretrained=checkpoint,
                force_quick_gelu=bool(quick_gelu),
                cache_dir=cache_dir,
                **overrides,
            )
        except Exception as exc:  # noqa: BLE001 - a bad weights file fails in many ways (pickle, zip, safetensors)
            if checkpoint is None:
                if not isinstance(exc, (RuntimeError, OSError, KeyError, ValueError)):
                    raise
                raise ConfigError(
                    f"Could not build open_clip model {model!r} with guidance.model_overrides={overrides}: {exc}"
                ) from exc
            raise WeightsMissingError(
                f"CLIP checkpoint {checkpoint} could not be loaded into model {model!r} "
                f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else 'no detail'}). It must be CLIP "
                "weights that open_clip reads (OpenAI's ViT-B-32.pt, an open_clip .bin or .safetensors) for the "
                "architecture guidance.model names; a damaged download, another model's checkpoint or a "
                "run's final.ckpt is not. Re-download it "
                f"(python -c \"import open_clip; open_clip.create_model_and_transforms('{model}', "
                f"pretrained='{pretrained}')\") or point guidance.pretrained at the right file."
            ) from exc
        self.is_real = checkpoint is not None
        if not self.is_real:
            log.warning(
                "!!! CLIP guidance %r uses RANDOM weights (allow_random_weights=True): stylization results "
                "are meaningless; use only for tests. !!!",
                model,
            )
        net.eval()
        for p in net.parameters():
            p.requires_grad_(False)
        use_matmul_patch_embedding(net.visual)
        self.net = net
        self._visual_low = LowPrecisionWeights(net.visual)  # open_clip: encode_image(x) is visual(x)
        size = net.visual.image_size
        self.image_size: tuple[int, int] = (size, size) if isinstance(size, int) else tuple(size)  # type: ignore[assignment]
        self.input_size = int(self.image_size[0])
        mean = (tag_cfg or {}).get("mean") or getattr(net.visual, "image_mean", None) or open_clip.OPENAI_DATASET_MEAN
        std = (tag_cfg or {}).get("std") or getattr(net.visual, "image_std", None) or open_clip.OPENAI_DATASET_STD
        self.normalize = kornia.enhance.Normalize(torch.tensor(mean), torch.tensor(std))
        self.tokenizer = open_clip.get_tokenizer(model)
        self.context_length = int(getattr(self.tokenizer, "context_length", 77) or 77)
        with torch.no_grad():
            self.embed_dim = int(net.encode_text(self.tokenizer(["a"])).shape[-1])
        if device is not None:
            self.to(device)

    # -------------------------------------------------------------------------------
    @staticmethod
    def _resolve(
        model: str,
        pretrained: str | None,
        cache_dir: str | None,
        allow_random: bool,
        allow_download: bool | None,
    ) -> tuple[str | None, dict | None]:
        """Local checkpoint file (or None for random weights) and the tag's pretrained cfg."""
        import open_clip

        if pretrained is None:
            if not allow_random:
                raise ConfigError(
                    f"guidance.pretrained is empty for model {model!r}: set it to a tag such as 'openai' "
                    "or a checkpoint path; random weights need guidance.allow_random_weights=true (tests only)."
                )
            return None, None
        tag_cfg = open_clip.get_pretrained_cfg(model, pretrained) or None
        if not tag_cfg:
            path = os.path.expanduser(pretrained)
            if os.path.isfile(path):
                return path, None
            if wts.looks_like_path(pretrained):
                msg = (
                    f"CLIP checkpoint file not found: guidance.pretrained={pretrained!r} (model {model!r}); "
                    f"looked at {os.path.abspath(path)}. Fix the path, or use a tag such as 'openai' "
                    f"(tags for {model}: {open_clip.list_pretrained_tags_by_model(model)})."
                )
            else:
                raise ConfigError(
                    f"guidance.pretrained={pretrained!r} is neither a known open_clip tag for {model!r} "
                    f"({open_clip.list_pretrained_tags_by_model(model)}) nor an existing file."
                )
            if allow_random:
                log.warning("%s Falling back to random weights (allow_random_weights=True).", msg)
                return None, None
            raise WeightsMissingError(msg)

        found, searched = find_cached(tag_cfg, cache_dir)
        if found:
            log.info("CLIP %s/%s: using cached weights %s", model, pretrained, found)
            return found, tag_cfg
        host = "huggingface.co" if tag_cfg.get("hf_hub") else (tag_cfg.get("url") or "huggingface.co")
        if wts.downloads_allowed(allow_download) and wts.host_reachable(host):
            log.info("CLIP %s/%s not cached; downloading via open_clip", model, pretrained)
            try:
                from open_clip.pretrained import download_pretrained

                path = download_pretrained(tag_cfg, cache_dir=cache_dir)
                if path and os.path.isfile(path):
                    return path, tag_cfg
            except Exception as exc:  # network errors of many kinds
                log.warning("Download of CLIP %s/%s failed: %s", model, pretrained, exc)
        msg = missing_message(model, pretrained, searched, cache_dir, wts.download_hint(allow_download, host))
        if allow_random:
            log.warning("%s\nFalling back to random weights (allow_random_weights=True).", msg)
            return None, None
        raise WeightsMissingError(msg)

    # -------------------------------------------------------------------------------
    def preprocess(self, img: Tensor) -> Tensor:
        """[B,3,H,W] in [0,1] -> [B,3,S,S] normalized model input (differentiable), float32 under any autocast."""
        with torch.autocast(img.device.type, enabled=False):  # the antialiasing blur is a conv
            img = img.float()
            if self.resize_mode == "shortest":
                img = kornia.geometry.transform.resize(img, self.input_size, side="short", antialias=True)
                img = kornia.geometry.transform.center_crop(img, self.image_size)
            elif tuple(img.shape[-2:]) != self.image_size:
                img = kornia.geometry.transform.resize(img, self.image_size, interpolation="bilinear", antialias=True)
            return self.normalize(img)

    def compute_dtype(self, device: torch.device) -> torch.dtype:
        """The dtype image encoding runs in on ``device`` (see ``precision``)."""
        return compute_dtype(self.precision, device, "guidance.precision")

    def auto_choices(self, device: torch.device) -> dict[str, str]:
        """What ``guidance.precision=auto`` becomes on ``device`` (:mod:`nerfart_plugin.config.auto`)."""
        return {"guidance.precision": dtype_name(self.compute_dtype(device))}

    def _net_image(self, x: Tensor) -> Tensor:
        """The image tower on preprocessed ``x`` [B,3,S,S] in ``compute_dtype``; float32 [B,D]."""
        dtype = self.compute_dtype(x.device)
        with attention_kernels(x.device):
            if dtype == torch.float32:
                with torch.autocast(x.device.type, enabled=False):  # fp32 also under trainer.precision=*-mixed
                    return self.net.encode_image(x).float()
            with torch.autocast(x.device.type, dtype=dtype):  # weights cast once, not per call
                if x.device.type == "cpu" and x.shape[0] > 1:  # one at a time: see ``precision``
                    return torch.cat([self._visual_low.run(dtype, xi[None]) for xi in x]).float()
                return self._visual_low.run(dtype, x).float()

    def _encode_image(self, img: Tensor) -> Tensor:
        return self._net_image(self.preprocess(img))

    def encode_images(self, imgs: list[Tensor]) -> list[Tensor]:
        """One network pass for all inputs: each is preprocessed (resized) on its own, then batched."""
        for x in imgs:
            if x.dim() != 4 or x.shape[1] != 3:
                raise ValueError(f"encode_images expects [B,3,H,W] in [0,1] tensors, got {tuple(x.shape)}")
        emb = self._net_image(torch.cat([self.preprocess(x) for x in imgs]))
        return list(emb.split([x.shape[0] for x in imgs]))

    def _encode_texts(self, texts: list[str]) -> Tensor:
        encode = getattr(self.tokenizer, "encode", None)
        if callable(encode):
            for t in texts:
                try:
                    n = len(encode(t)) + 2  # + start/end tokens
                except Exception:  # tokenizers without a plain encode()
                    break
                if n > self.context_length:
                    log.warning(
                        "Prompt has %d tokens > CLIP context %d; truncated (end-of-text kept): %r",
                        n,
                        self.context_length,
                        t,
                    )
        tokens = self.tokenizer(texts).to(self.device)
        return self.net.encode_text(tokens).float()
