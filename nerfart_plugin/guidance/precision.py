"""Arithmetic of the frozen guidance networks (CLIP's image tower, VGG16): one policy for both.

``auto`` runs them as their authors' models run on each device: fp16 on CUDA (OpenAI's CLIP),
bf16 on CPUs with native bf16 matrix units (oneDNN: AVX512-BF16 or AMX), float32 elsewhere.
Weights stay float32; callers return float32 embeddings / features. Under autocast a frozen weight
is cast again on every call (autocast caches only weights that require grad);
:class:`LowPrecisionWeights` casts a frozen network's matmul and convolution weights once instead.
"""

from __future__ import annotations

import functools
from typing import Literal

import torch
from torch import Tensor, nn

from nerfart_plugin.errors import ConfigError

__all__ = ["PRECISIONS", "LowPrecisionWeights", "Precision", "check_precision", "cpu_has_bf16", "compute_dtype"]

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
#: ``guidance.precision`` / ``guidance.perceptual.precision``
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


#: modules whose weights autocast's lower-precision ops (linear, conv) read; their parameters are cast
_CAST_MODULES = (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d)


def _autocast_weights(module: nn.Module) -> dict[str, Tensor]:
    """``name -> parameter`` of ``module``'s linear and convolution weights and biases, and of its
    attention blocks' packed input projections (``nn.MultiheadAttention.in_proj_*``)."""
    out: dict[str, Tensor] = {}
    for prefix, m in module.named_modules():
        for name, p in m.named_parameters(recurse=False):
            if isinstance(m, _CAST_MODULES) or (isinstance(m, nn.MultiheadAttention) and name.startswith("in_proj")):
                out[f"{prefix}.{name}" if prefix else name] = p
    return out


class LowPrecisionWeights:
    """Copies of a frozen module's linear and convolution weights in a low-precision dtype, made once.

    Autocast casts a float32 weight that does not require grad on every call; a frozen image tower
    encoding 13 images one at a time per step casts its ~88 M weights 13 times. Running the module
    with these copies (:meth:`run`, under the same autocast) computes the same ops on the same
    bf16/fp16 values: autocast rounds a weight exactly as ``Tensor.to`` does. The copies are remade
    when a weight moves (``.to``) or changes in place (``load_state_dict``); they are not part of the
    module's state, and cost half (bf16/fp16) of those weights' float32 memory.
    """

    def __init__(self, module: nn.Module) -> None:
        self.module = module
        self._key: tuple = ()
        self._weights: dict[str, Tensor] = {}

    def weights(self, dtype: torch.dtype) -> dict[str, Tensor]:
        """``name -> weight`` in ``dtype`` on the weights' device, cast now if a weight changed."""
        source = _autocast_weights(self.module)
        key = (dtype, *((p.device, p.data_ptr(), p._version) for p in source.values()))
        if key != self._key:
            self._weights = {}  # free the old copies before making the new ones
            with torch.no_grad():
                self._weights = {n: p.detach().to(dtype) for n, p in source.items()}
            self._key = key
        return self._weights

    def run(self, dtype: torch.dtype, *args: object) -> Tensor:
        """``module(*args)`` with the weights in ``dtype`` (call under an autocast to ``dtype``)."""
        return torch.func.functional_call(self.module, self.weights(dtype), args, strict=False)
