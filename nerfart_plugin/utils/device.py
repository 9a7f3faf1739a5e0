"""Pick the compute device; never hard-code one."""

from __future__ import annotations

from typing import Any

import torch


def pick_device(preference: str = "auto") -> torch.device:
    """``auto`` -> CUDA if available, else MPS if available, else CPU; otherwise ``torch.device(preference)``."""
    if preference != "auto":
        return torch.device(preference)
    if torch.cuda.is_available():
        return torch.device("cuda")
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    """``batch`` (a ray batch: name -> tensor or plain value) with its tensors on ``device``."""
    return {k: (v.to(device, non_blocking=True) if torch.is_tensor(v) else v) for k, v in batch.items()}
