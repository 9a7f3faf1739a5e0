"""Abstract image/text guidance encoder (CLIP or a toy stand-in).

A :class:`Guidance` maps images and prompts into a shared embedding space.
The losses in :mod:`nerfart_plugin.objectives.losses` consume its outputs.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor, nn

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WeightsPolicy:
    """What a guide or perceptual network may do about its weights (the ``guidance`` section's common keys),
    handed to every one of them alike; those without downloadable weights ignore it.

    Attributes:
        allow_random_weights: permit random weights (tests only: outputs are stamped as not stylized).
        allow_download: permit network downloads; None: the environment variable NERFART_ALLOW_DOWNLOAD.
    """

    allow_random_weights: bool = False
    allow_download: Optional[bool] = None


class Guidance(nn.Module, abc.ABC):
    """Frozen joint image/text encoder.

    Attributes:
        name: registry name ("clip", "toy").
        is_real: False for random or toy weights; callers stamp their outputs
            (logs, metrics, exported files) with it so results from
            non-pretrained guidance are never mistaken for real stylizations.
        input_size: side (pixels) images are resized to before encoding.
        embed_dim: D.
    """

    name: str = "base"
    is_real: bool = False
    #: suffix of every output file of a run guided by this encoder when it is not a real CLIP
    #: (None: derived from ``is_real``: ``_UNSTYLED-<name>`` for toy / random weights)
    stamp: str | None = None
    input_size: int = 224
    embed_dim: int = 0
    #: the perceptual network (registry kind ``perceptual``) Eq. 9 uses with this guide unless
    #: ``guidance.perceptual`` says otherwise
    default_perceptual: str = "vgg"

    def __init__(self) -> None:
        super().__init__()
        self._text_cache: dict[str, Tensor] = {}

    # -- to implement -----------------------------------------------------------------
    @abc.abstractmethod
    def _encode_image(self, img: Tensor) -> Tensor:
        """``img`` [B,3,H,W] in [0,1] -> [B,D]; differentiable w.r.t. ``img``."""

    @abc.abstractmethod
    def _encode_texts(self, texts: list[str]) -> Tensor:
        """Uncached: list of M prompts -> [M,D] (called under no_grad)."""

    # -- public API -------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        for t in self.parameters():
            return t.device
        for t in self.buffers():
            return t.device
        return torch.device("cpu")

    def encode_image(self, img: Tensor) -> Tensor:
        """Image embeddings (unnormalized), differentiable.

        Args:
            img: ``[B,3,H,W]`` float in [0,1] (any H, W; resized internally).
        Returns: ``[B,D]`` float32.
        """
        if img.dim() != 4 or img.shape[1] != 3:
            raise ValueError(f"encode_image expects [B,3,H,W] in [0,1], got {tuple(img.shape)}")
        return self._encode_image(img)

    def encode_images(self, imgs: list[Tensor]) -> list[Tensor]:
        """Embeddings of several image batches (e.g. the whole view and its local patches), one
        ``[B_i,D]`` per input; encoders that can batch them into one call override this (same
        values as separate :meth:`encode_image` calls, fewer passes through the network)."""
        return [self.encode_image(x) for x in imgs]

    def encode_text(self, texts: list[str] | tuple[str, ...] | str) -> Tensor:
        """Text embeddings (unnormalized, no grad), cached per string.

        Args:
            texts: M prompts (a single string is treated as ``[texts]``).
        Returns: ``[M,D]`` on this module's device.
        """
        if isinstance(texts, str):
            texts = [texts]
        texts = list(texts)
        if not texts:
            raise ValueError("encode_text needs at least one prompt")
        missing = list(dict.fromkeys(t for t in texts if t not in self._text_cache))
        if missing:
            with torch.no_grad():
                emb = self._encode_texts(missing).detach()
            for t, e in zip(missing, emb):
                self._text_cache[t] = e
        dev = self.device
        return torch.stack([self._text_cache[t].to(dev) for t in texts])

    def source_embedding(self, prompt: str, images: Tensor) -> Tensor:
        """The source "text" embedding ``[D]`` of Eq. 4 for ``prompt``, given renders of the source
        ``images`` [B,3,H,W]; text encoders ignore the images, others may derive it from them."""
        return self.encode_text([prompt])[0]

    def output_stamp(self) -> str:
        """The suffix stamped on this run's outputs: "" for real CLIP weights."""
        if self.stamp is not None:
            return self.stamp
        return "" if self.is_real else f"_UNSTYLED-{self.name}"

    def train(self, mode: bool = True) -> "Guidance":
        """Guidance is frozen: it stays in eval mode even inside a module put in train mode."""
        return super().train(False)

    def forward(self, img: Tensor) -> Tensor:  # nn.Module entry point
        return self.encode_image(img)

    def extra_repr(self) -> str:
        return f"name={self.name!r}, is_real={self.is_real}, input_size={self.input_size}, embed_dim={self.embed_dim}"
