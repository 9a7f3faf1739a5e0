"""The cache keys of run folders: what identifies a run, so that the same settings find the same folder and any
change another (:func:`~nerfart_plugin.utils.io.config_hash` of every setting that changes the result).

Each key is computed for the current settings layout (:data:`~nerfart_plugin.config.migrate.CONFIG_FORMAT`,
hashed with it) and for the layouts before it, newest first: a run folder made by an earlier version is found
again under its own key (:meth:`~nerfart_plugin.run.folders.RunFolder.find`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from nerfart_plugin.config.migrate import CONFIG_FORMAT, to_format_1
from nerfart_plugin.config.validate import component_result_settings, result_settings
from nerfart_plugin.regions.region import region_from_config
from nerfart_plugin.utils.io import config_hash, hash_files

#: the settings layouts a key is computed for, newest first
FORMATS = (CONFIG_FORMAT, 1)


def _plain(scene: Any, fmt: int) -> dict:
    return scene.plain if fmt == CONFIG_FORMAT else to_format_1(scene.plain)


def _hashed(body: dict, fmt: int) -> str:
    return config_hash({**body, "format": fmt} if fmt >= 2 else body)


def scene_settings(scene: Any, fmt: int = CONFIG_FORMAT) -> dict[str, Any]:
    """What identifies the photos and how they are rendered, in every key that depends on them: the scene's
    content and the ``changes_results`` settings of data and render."""
    return {"scene": scene.scene.content_hash, "data": component_result_settings("data", _plain(scene, fmt)["data"]),
            "render": result_settings(scene.cfg.render)}


def reconstruction_keys(scene: Any) -> dict[int, str]:
    """Settings format -> the reconstruction's key: the scene's content and every setting that changes the
    reconstruction (the schema's ``changes_results`` fields of render / reconstruct / trainer, the component
    sections, the seed)."""
    c = scene.cfg
    out = {}
    for fmt in FORMATS:
        plain = _plain(scene, fmt)
        out[fmt] = _hashed({**scene_settings(scene, fmt), "backbone": plain["backbone"], "encoding": plain["encoding"],
                            "reconstruct": result_settings(c.reconstruct), "trainer": result_settings(c.trainer),
                            "seed": c.seed}, fmt)
    return out


def checkpoint_keys(scene: Any, checkpoint: Path) -> dict[int, str]:
    """Settings format -> what identifies an explicit ``source_checkpoint`` in a stylization's key: its content
    (a file that does not exist: its path; reading it fails clearly later) with the scene's content and the data
    and render settings, which the stylization uses too."""
    content = hash_files([checkpoint]) if checkpoint.is_file() else str(checkpoint.resolve())
    return {fmt: config_hash({"checkpoint": content, **scene_settings(scene, fmt)}) for fmt in FORMATS}


def stylization_keys(scene: Any, style: Any, source_keys: dict[int, str], stylize: Any) -> dict[int, str]:
    """Settings format -> the stylization's key: its source (``source_keys``: the reconstruction's keys or the
    checkpoint's), the prompts, the guidance, the loss weights, the ``stylize`` settings (``stylize``: the section
    as keyed before the negatives' threshold was resolved, so existing runs keep their keys), trainer and seed,
    the region's content when the stylization is inside one, and the style picture's content and settings when
    there is one (not its path: a copy elsewhere is the same style)."""
    c = scene.cfg
    region = region_from_config(c.region)
    out = {}
    for fmt in FORMATS:
        body = {"recon": source_keys[fmt], "prompt": style.prompt, "source_prompt": style.source_prompt,
                "guidance": _plain(scene, fmt)["guidance"], "experiment": result_settings(c.experiment),
                "stylize": result_settings(stylize), "trainer": result_settings(c.trainer), "seed": c.seed}
        if region is not None:  # inside a region: its content and the grid it is sampled on
            body["region"] = {"content": region.content_hash, "resolution": c.region.resolution}
        if style.image is not None:  # a style picture: its content and how it is matched
            body["style_image"] = {**result_settings(c.style_image), "content": style.image.content_hash}
        out[fmt] = _hashed(body, fmt)
    return out
