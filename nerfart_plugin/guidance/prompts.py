"""Prompts: augmentation, source prompts, validation, negative prompts (Eq. 5).

Negative prompt files: ``#category`` header lines, then one prompt per line,
usually numbered ``N.text``. The parser tolerates blank lines, missing or
skipped numbers (``N.``, ``N)``), CRLF line endings, a UTF-8 BOM and
duplicates (dropped case-insensitively, first occurrence kept).
The package list ``negative_prompts.txt`` holds the 131 prompts of the
official NeRF-Art release (criteria/neg_text.txt) plus curated painting
styles, artists, characters and materials (~210 in total).
"""

from __future__ import annotations

import logging
import re
from importlib import resources
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.guidance.base import Guidance

log = logging.getLogger(__name__)

# ------------------------------------------------------------------ (a) augmentation
#: Lower-cased short style names -> the detailed prompt used by the paper's
#: text evaluation ("Vincent van Gogh" -> "painting, oil on canvas, Vincent van
#: Gogh self-portrait style"); the others follow the same pattern.
PROMPT_AUGMENTATIONS: dict[str, str] = {
    "vincent van gogh": "painting, oil on canvas, Vincent van Gogh self-portrait style",
    "van gogh": "painting, oil on canvas, Vincent van Gogh self-portrait style",
    "fauvism": "painting, oil on canvas, Fauvism style",
    "edvard munch": "painting, oil on canvas, Edvard Munch The Scream style",
    "munch": "painting, oil on canvas, Edvard Munch The Scream style",
    "fernando botero": "painting, oil on canvas, Fernando Botero style",
    "botero": "painting, oil on canvas, Fernando Botero style",
}


def _norm_key(prompt: str) -> str:
    return " ".join(prompt.strip().strip(".").lower().split())


def augment_prompt(prompt: str) -> str:
    """Expand a known painter/style name (whole prompt, case-insensitive) to its
    detailed form; unknown prompts are returned unchanged."""
    return PROMPT_AUGMENTATIONS.get(_norm_key(prompt), prompt)


# ------------------------------------------------------------------ (b) source prompt
def default_source_prompt(capture: str, has_person: bool) -> str:
    """Neutral source prompt t_src for Eq. 4: "a photo of a person" for faces /
    people, "a photo" otherwise (``capture`` is the Scene's capture kind; it is
    accepted for future per-capture choices and validated here)."""
    if capture not in ("object", "forward_facing", "unbounded"):
        raise ConfigError(f"Unknown capture kind {capture!r}; expected object, forward_facing or unbounded")
    return "a photo of a person" if has_person else "a photo"


# ------------------------------------------------------------------ (c) validation
def validate_prompt(prompt: object, setting: str = "prompt") -> str:
    """Return the stripped prompt; ConfigError for non-strings and empty/whitespace prompts."""
    if not isinstance(prompt, str):
        raise ConfigError(f"{setting} must be a text string, got {type(prompt).__name__}: {prompt!r}")
    text = prompt.strip()
    if not text:
        raise ConfigError(
            f"{setting} is empty: give the target style as text, e.g. {setting}='Vincent van Gogh' "
            "(on the command line: prompt=\"Vincent van Gogh\")."
        )
    return text


# ------------------------------------------------------------------ (d) negatives
_NUMBERED = re.compile(r"^\s*\d+\s*[.)]\s*(.*)$")


def parse_negative_prompts(text: str, dedupe: bool = True) -> list[tuple[str, str]]:
    """Parse a negative-prompt file's text into ``(category, prompt)`` pairs.

    Lines starting with ``#`` set the category; ``N.text`` / ``N)text`` lose
    their number; unnumbered lines are taken whole; blank lines are skipped.
    """
    out: list[tuple[str, str]] = []
    seen: set[str] = set()
    category = ""
    for raw in text.lstrip("\ufeff").splitlines():
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            category = line.lstrip("#").strip()
            continue
        m = _NUMBERED.match(line)
        prompt = " ".join((m.group(1) if m else line).split())
        if not prompt:
            continue
        key = prompt.lower()
        if dedupe and key in seen:
            continue
        seen.add(key)
        out.append((category, prompt))
    return out


def package_negatives_path() -> Path:
    """Path of the packaged curated list ``nerfart_plugin/guidance/negative_prompts.txt``."""
    return Path(str(resources.files("nerfart_plugin.guidance").joinpath("negative_prompts.txt")))


def load_negatives(path: str | Path | None = None) -> list[str]:
    """Negative prompts from ``path`` (default: the packaged ~210-prompt list), deduplicated."""
    p = Path(path).expanduser() if path is not None else package_negatives_path()
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(
            f"Cannot read negative prompts file {p} ({exc}); fix guidance.negatives.path or leave it "
            "empty for the packaged list."
        ) from exc
    prompts = [t for _, t in parse_negative_prompts(text)]
    if not prompts:
        raise DataError(f"Negative prompts file {p} contains no prompts (expected lines like '1.sketch').")
    return prompts


# ------------------------------------------------------------------ (e) sampler
class NegativeSampler:
    """Negative text embeddings for the contrastive loss (Eq. 5).

    Encodes all negatives once; EXCLUDES those whose text-embedding cosine
    similarity to the target prompt exceeds ``threshold`` (so a "Van Gogh"
    target is not pushed away from "Self-Portrait by Van Gogh"); the
    exclusions are logged. :meth:`sample` draws ``num_per_step`` of the kept
    ones without replacement (all of them if None or more than available).

    Threshold: CLIP ViT-B/32 text-text cosines are high overall (~0.6-0.8 for
    unrelated short prompts, ~0.9 for near-synonyms), hence the default 0.85.

    Attributes: ``prompts`` (kept), ``embeddings`` [M,D] (kept, unnormalized),
    ``excluded`` list of (prompt, similarity).
    """

    def __init__(
        self,
        guidance: Guidance,
        negatives: list[str],
        target_prompt: str,
        threshold: float = 0.85,
        num_per_step: int | None = 64,
    ) -> None:
        if not negatives:
            raise ConfigError("NegativeSampler got no negative prompts; check guidance.negatives.path")
        if num_per_step is not None and num_per_step < 1:
            raise ConfigError(f"guidance.negatives.num_per_step must be >= 1 or null, got {num_per_step}")
        target_prompt = validate_prompt(target_prompt)
        negatives = list(dict.fromkeys(negatives))
        emb = guidance.encode_text(negatives)
        tgt = guidance.encode_text([target_prompt])
        sim = (F.normalize(emb.float(), dim=-1) @ F.normalize(tgt.float(), dim=-1).t()).squeeze(1)
        keep = sim <= threshold
        self.excluded: list[tuple[str, float]] = [
            (n, float(s)) for n, s, k in zip(negatives, sim.tolist(), keep.tolist()) if not k
        ]
        self.prompts: list[str] = [n for n, k in zip(negatives, keep.tolist()) if k]
        if not self.prompts:
            raise ConfigError(
                f"All {len(negatives)} negative prompts are within cosine {threshold} of the target "
                f"{target_prompt!r}; raise guidance.negatives.threshold or supply other negatives."
            )
        self.embeddings: Tensor = emb[keep]
        self.similarities: Tensor = sim[keep]
        self.threshold = threshold
        self.num_per_step = num_per_step
        log.info(
            "Negative prompts: kept %d of %d; excluded %d with cosine > %.2f to target %r: %s",
            len(self.prompts),
            len(negatives),
            len(self.excluded),
            threshold,
            target_prompt,
            ", ".join(f"{n!r} ({s:.2f})" for n, s in self.excluded) or "none",
        )
        if num_per_step is not None and num_per_step > len(self.prompts):
            log.info("num_per_step=%d > %d available negatives: using all each step", num_per_step, len(self.prompts))

    def __len__(self) -> int:
        return len(self.prompts)

    def sample(self, generator: torch.Generator | None = None) -> tuple[list[str], Tensor]:
        """``(prompts, embeddings [n,D])`` for one step, n = min(num_per_step, kept)."""
        m = len(self.prompts)
        n = m if self.num_per_step is None else min(self.num_per_step, m)
        if n == m:
            return list(self.prompts), self.embeddings
        idx = torch.randperm(m, generator=generator)[:n]
        return [self.prompts[i] for i in idx.tolist()], self.embeddings[idx.to(self.embeddings.device)]
