"""Arithmetic of the frozen guidance networks (CLIP's image tower, VGG16): one policy for both.

``auto`` runs them as their authors' models run on each device: fp16 on CUDA (OpenAI's CLIP),
bf16 on CPUs with native bf16 matrix units (oneDNN: AVX512-BF16 or AMX), float32 elsewhere.
Weights stay float32; callers return float32 embeddings / features.
"""

from __future__ import annotations

import functools
from typing import Literal

import torch

from nerfart_plugin.errors import ConfigError

__all__ = ["PRECISIONS", "Precision", "check_precision", "cpu_has_bf16", "compute_dtype"]

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
#: ``guidance.clip.precision`` / ``guidance.vgg.precision``
Precision = Literal["auto", "fp32", "bf16", "fp16"]


def check_precision(precision: str, setting: str) -> str:
    """``precision`` if it is one of :data:`PRECISIONS`, else a ConfigError naming ``setting``."""
    if precision not in PRECISIONS:
        raise ConfigError(f"{setting}={precision!r}; use one of {', '.join(PRECISIONS)}.")
    return precision


@functools.lru_cache(maxsize=1)
def cpu_has_bf16() -> bool:
    """Native bf16 matmuls on this CPU (oneDNN: AVX512-BF16 or AMX)."""
    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def compute_dtype(precision: str, device: torch.device, setting: str) -> torch.dtype:
    """The dtype a guidance network runs in on ``device`` for ``precision`` (one of :data:`PRECISIONS`);
    ``setting`` names the config key in errors (fp16 needs CUDA)."""
    check_precision(precision, setting)
    if precision == "auto":
        if device.type == "cuda":
            return torch.float16
        return torch.bfloat16 if device.type == "cpu" and cpu_has_bf16() else torch.float32
    if precision == "fp16" and device.type != "cuda":
        raise ConfigError(f"{setting}=fp16 needs a CUDA device (CPU autocast: use bf16 or auto).")
    return {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}[precision]
