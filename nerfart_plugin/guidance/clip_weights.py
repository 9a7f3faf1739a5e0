"""Where CLIP's weights are looked for offline: open_clip's Hugging Face hub cache and its URL cache, and the
error text that says where the search went and how to supply the file (used by
:class:`~nerfart_plugin.guidance.clip.CLIPGuidance`; the policy itself is :mod:`nerfart_plugin.guidance.weights`).
"""

from __future__ import annotations

import logging
import os
import zipfile
from pathlib import Path

log = logging.getLogger(__name__)

#: open_clip's default weight file names in a Hugging Face repository
_HF_WEIGHT_FILES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")


def _hf_cache_dir(cache_dir: str | None) -> str:
    if cache_dir:
        return str(Path(cache_dir).expanduser())
    from huggingface_hub import constants

    return str(constants.HF_HUB_CACHE)


def _url_cache_dir(cache_dir: str | None) -> str:
    return str(Path(cache_dir).expanduser()) if cache_dir else os.path.expanduser("~/.cache/clip")


def find_cached(tag_cfg: dict, cache_dir: str | None) -> tuple[str | None, list[str]]:
    """Look for a tag's checkpoint in local caches. Returns (file or None, places searched)."""
    searched: list[str] = []
    hf = tag_cfg.get("hf_hub", "")
    if hf:
        from huggingface_hub import try_to_load_from_cache

        # open_clip convention: "org/repo/filename" or "org/repo/" (default file names)
        repo_id, filename = os.path.split(hf)
        candidates = [filename] if filename else list(_HF_WEIGHT_FILES)
        if filename.endswith((".bin", ".pth")):
            candidates.insert(0, filename[:-4] + ".safetensors")
        hub_dir = _hf_cache_dir(cache_dir)
        for fn in candidates:
            searched.append(f"{hub_dir} (HF repo {repo_id}, file {fn})")
            try:
                hit = try_to_load_from_cache(repo_id=repo_id, filename=fn, cache_dir=hub_dir)
            except Exception as exc:  # malformed cache etc.
                log.debug("try_to_load_from_cache(%s, %s) failed: %s", repo_id, fn, exc)
                hit = None
            if isinstance(hit, str) and os.path.isfile(hit):
                return hit, searched
    url = tag_cfg.get("url", "")
    if url:
        target = os.path.join(_url_cache_dir(cache_dir), os.path.basename(url))
        searched.append(target)
        if os.path.isfile(target):
            return target, searched
    return None, searched


def missing_message(model: str, tag: str, searched: list[str], cache_dir: str | None, hint: str) -> str:
    """The WeightsMissingError text: what was looked for, where, and the three ways to supply the weights."""
    where = "\n  - ".join(searched) if searched else "(no local cache location known for this tag)"
    cache_arg = f", cache_dir={cache_dir!r}" if cache_dir else ""
    return (
        f"CLIP weights not found: model {model!r} with pretrained={tag!r}.\n"
        f"Looked for them in:\n  - {where}\n"
        f"{hint}\n"
        "How to supply them:\n"
        f"  (a) on a machine with internet run\n"
        f"      python -c \"import open_clip; open_clip.create_model_and_transforms('{model}', "
        f"pretrained='{tag}'{cache_arg})\"\n"
        f"      and copy the resulting cache folder ({_hf_cache_dir(cache_dir)}) to the same place here "
        "(or point guidance.cache_dir / HF_HUB_CACHE at it);\n"
        "  (b) or pass a local checkpoint file: guidance.pretrained=/path/to/file.pt "
        "(e.g. the OpenAI ViT-B-32.pt or an open_clip .bin/.safetensors);\n"
        "  (c) tests only: guidance.allow_random_weights=true (random weights, results are meaningless)."
    )


def is_torchscript_archive(path: str) -> bool:
    """A TorchScript zip (OpenAI's own ViT-B-32.pt): its weights need QuickGELU."""

    try:
        with zipfile.ZipFile(path) as zf:
            return any(n.endswith("constants.pkl") for n in zf.namelist())
    except (zipfile.BadZipFile, OSError):
        return False
