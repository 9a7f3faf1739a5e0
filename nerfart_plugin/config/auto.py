"""``auto`` settings: who decides each one, and the record of what it became in a run.

Every setting that accepts ``auto`` is decided in one place, by the concern it belongs to (the table
:data:`AUTO_SETTINGS`), and a finished run writes what each became into ``metrics.json`` under ``auto``
(setting -> chosen value, only for the settings that were ``auto`` in that run), e.g. ``{"encoding.resolution":
256, "device": "cpu", "stylize.negative_threshold": 0.2}``. A component whose own settings can be ``auto``
reports its choices through ``auto_choices(device) -> {setting: value}`` (fields, guides, perceptual networks),
which :func:`component_choices` asks generically.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping, Optional

import torch

#: every setting that accepts ``auto`` -> where it is decided
AUTO_SETTINGS: dict[str, str] = {
    # the scene: what a capture requires, decided once before training
    "render.background_model": "data.setup.decide_setup",
    "render.occupancy.enabled": "data.setup.decide_setup",
    "render.occupancy.sampling": "data.setup.decide_setup",
    "encoding.resolution": "data.setup.decide_setup",
    "encoding.levels": "data.setup.decide_setup",
    "reconstruct.mask_ray_share": "data.setup.decide_setup",
    # the data: the loader's image size policy
    "data.resolution": "data.images.choose_resolution (each loader)",
    # compute
    "device": "utils.device.pick_device",
    "trainer.strategy": "Lightning's Trainer (run.fit.build_trainer)",
    "compile": "fields.compiled.decide_compile (per stage: the training steps, the frames)",
    # components, each deciding its own
    "backbone.grad_type": "fields.sdf.SDFField",
    "guidance.precision": "guidance.precision.compute_dtype (the CLIP guide)",
    "guidance.perceptual.precision": "guidance.precision.compute_dtype (the VGG perceptual network)",
    # the style: the stylization's prompts, negatives and view size
    "source_prompt": "guidance.style.build_style",
    "stylize.resolution": "run.factories.stylize_settings",
    "stylize.negatives": "run.factories.stylize_settings",
    "stylize.negative_threshold": "run.factories.stylize_settings",
    "style_image.layers": "guidance.style_image.style_layers (the perceptual network's family)",
    "preview.resolution": "run.stages.preview.preview_scene (128 px, at most the stylization's)",
    # outputs and sweeps
    "render.resolution": "results.run.Run.camera_path (stage=render; recorded in the render folder's summary)",
    "objective": "run.sweep.objective (a sweep's result, not a run's)",
}


def setting_of(cfg: Any, dotted: str) -> Any:
    """The value of the dotted setting ``dotted`` in ``cfg`` (a typed config, a dict or a DictConfig; None
    where the run's config has no such key, e.g. ``encoding.resolution`` with ``encoding=frequency``)."""
    node = cfg
    for part in dotted.split("."):
        if node is None:
            return None
        node = node.get(part) if isinstance(node, Mapping) or hasattr(node, "keys") else getattr(node, part, None)
    return node


def recorded(cfg: Any, choices: Mapping[str, Any]) -> dict[str, Any]:
    """The ``auto`` block of ``metrics.json``: of ``choices`` (setting -> what was chosen), those that are
    ``auto`` in ``cfg``, in :data:`AUTO_SETTINGS`'s order. A setting missing from that table is a programming
    error (a new ``auto`` setting must name where it is decided)."""
    unknown = sorted(set(choices) - set(AUTO_SETTINGS))
    if unknown:
        raise KeyError(f"{unknown}: not in nerfart_plugin.config.auto.AUTO_SETTINGS; add where each is decided")
    return {k: _plain(choices[k]) for k in AUTO_SETTINGS if k in choices and setting_of(cfg, k) == "auto"}


def component_choices(device: torch.device, components: Iterable[Any]) -> dict[str, Any]:
    """What the ``auto`` settings of ``components`` (fields, guides, perceptual networks; None skipped) became
    on ``device``: the union of their ``auto_choices(device)``."""
    out: dict[str, Any] = {}
    for component in components:
        report = getattr(component, "auto_choices", None)
        if callable(report):
            out.update(report(device))
    return out


def dtype_name(dtype: torch.dtype) -> str:
    """``torch.float32`` -> ``fp32`` (the names of the precision settings)."""
    return {torch.float32: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}.get(dtype, str(dtype))


def _plain(value: Any) -> Optional[Any]:
    """A JSON-friendly copy of a chosen value (devices and dtypes as their names)."""
    if isinstance(value, torch.device):
        return str(value)
    if isinstance(value, torch.dtype):
        return dtype_name(value)
    return value
