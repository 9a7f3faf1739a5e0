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
SUBJECTS = ("person", "object", "scene")


def default_source_prompt(subject: str) -> str:
    """Neutral source prompt t_src for Eq. 4 from what the capture shows (``data.subject``):
    "a photo of a person" for ``person`` (the h3ds and selfie data configs), "a photo" for
    ``object`` and ``scene``. Override it with ``source_prompt=...``."""
    if subject not in SUBJECTS:
        raise ConfigError(f"data.subject={subject!r} is not one of {', '.join(SUBJECTS)}: say what the capture "
                          "shows (person -> source prompt 'a photo of a person'), or set source_prompt=... directly.")
    return "a photo of a person" if subject == "person" else "a photo"


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


def package_negatives_path(name: str = "negative_prompts.txt") -> Path:
    """Path of a packaged list: ``negative_prompts.txt`` (curated, default) or
    ``negative_prompts_official.txt`` (the 131 prompts of the official release)."""
    return Path(str(resources.files("nerfart_plugin.guidance").joinpath(name)))


#: ``stylize.negatives`` values naming packaged lists.
PACKAGED_NEGATIVES = {"package": "negative_prompts.txt", "official": "negative_prompts_official.txt"}


def load_negative_pairs(path: str | Path | None = None, setting: str = "stylize.negatives") -> list[tuple[str, str]]:
    """``(category, prompt)`` pairs from ``path`` (default: the packaged ~210-prompt list), deduplicated."""
    p = Path(path).expanduser() if path is not None else package_negatives_path()
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(
            f"Cannot read negative prompts file {p} ({exc}); fix {setting}=/path/to/file.txt, or use "
            f"{setting}=package (curated list), {setting}=official (the paper's 131) or {setting}=auto."
        ) from exc
    pairs = parse_negative_prompts(text)
    if not pairs:
        raise DataError(f"Negative prompts file {p} contains no prompts (expected lines like '1.sketch'); "
                        f"fix it or set {setting}=package.")
    return pairs


def load_negatives(path: str | Path | None = None) -> list[str]:
    """Negative prompts from ``path`` (default: the packaged ~210-prompt list), deduplicated."""
    return [t for _, t in load_negative_pairs(path)]


#: ``stylize.negative_threshold=auto`` for a guide without its own: CLIP ViT-B/32 text-text cosines are
#: ~0.6-0.8 for unrelated short prompts and ~0.9 for near-synonyms
DEFAULT_NEGATIVE_THRESHOLD = 0.85


def negatives_origin(spec: str | None, guidance: Guidance) -> str:
    """Where the negatives of ``stylize.negatives=spec`` come from, in words (see :func:`resolve_negatives`)."""
    if spec in (None, "", "auto"):
        return "the guide's own list" if callable(getattr(guidance, "default_negatives", None)) else "package"
    return spec


def default_negative_threshold(guidance: Guidance) -> float:
    """``stylize.negative_threshold=auto``: the guide's ``negative_threshold`` (text-text cosine above which a
    negative counts as a synonym of the target), else :data:`DEFAULT_NEGATIVE_THRESHOLD`."""
    return float(getattr(guidance, "negative_threshold", DEFAULT_NEGATIVE_THRESHOLD))


def resolve_negatives(spec: str | None, guidance: Guidance, prompt: str) -> list[tuple[str, str]]:
    """The negatives ``stylize.negatives`` names, as ``(category, prompt)`` pairs.

    ``auto`` (or null): the guidance's own list when it has one (``guidance=imagenet``: the other
    ImageNet classes), else the packaged curated list; ``package`` / ``official``: a packaged list;
    anything else: a path to a file in the negative-prompt format.
    """
    if spec in (None, "", "auto"):
        own = getattr(guidance, "default_negatives", None)
        if callable(own):
            return [("", n) for n in own(prompt)]
        return load_negative_pairs()
    if spec in PACKAGED_NEGATIVES:
        return load_negative_pairs(package_negatives_path(PACKAGED_NEGATIVES[spec]))
    return load_negative_pairs(spec)


# ------------------------------------------------------------------ (e) exclusion by meaning
_STOPWORDS = frozenset("a an the of and or by in on with to for from at as is its photo picture image style".split())

#: Category rule (as the official release's ``create_fine_neg_texts``): a target mentioning one of these
#: words drops the whole ``#category`` of the negatives file, whose prompts depict the same thing.
CATEGORY_RULES: dict[str, tuple[str, ...]] = {
    "portrait": ("portrait", "painting", "botero", "mona lisa", "monalisa"),
    "zombie": ("zombie",),
    "disney": ("disney", "pixar"),
    "sketch": ("sketch", "pencil drawing"),
    "anime": ("anime", "manga"),
    "makeup": ("makeup",),
    "cartoon": ("cartoon", "simpsons"),
}


def _words(text: str) -> list[str]:
    return re.findall(r"[A-Za-z0-9]+", text)


def content_words(text: str) -> set[str]:
    """Lower-cased words of ``text`` without articles, prepositions and photo words."""
    return {w.lower() for w in _words(text) if w.lower() not in _STOPWORDS}


def name_words(text: str) -> set[str]:
    """Lower-cased capitalized words of ``text`` (names and titled styles: "Van", "Gogh", "Pixar")."""
    return {w.lower() for w in _words(text) if w[0].isupper() and w.lower() not in _STOPWORDS}


def exclusion_reason(negative: str, category: str, targets: list[str]) -> str | None:
    """Why ``negative`` (from ``#category``) would contradict a target described by ``targets``
    (the prompt as typed and as augmented), or None when it is a fair negative.

    Rules, by meaning rather than by embedding score: (1) every content word of the negative is
    in the target ("Oil painting" for "painting, oil on canvas, ..."); (2) a name of the negative
    (a capitalized word) is in the target ("Self-Portrait by Van Gogh" for "Vincent van Gogh",
    "The Joker" for "joker"); (3) :data:`CATEGORY_RULES`.
    """
    neg_words, names = content_words(negative), name_words(negative)
    for target in targets:
        t_words = content_words(target)
        if neg_words and neg_words <= t_words:
            return f"all its words are in the target {target!r}"
        shared = sorted(names & t_words)
        if shared:
            return f"shares the name {shared[0]!r} with the target {target!r}"
        low = f" {' '.join(_words(target.lower()))} "
        for key in CATEGORY_RULES.get(category, ()):
            if f" {key} " in low:
                return f"category #{category} is dropped for targets mentioning {key!r}"
    return None


# ------------------------------------------------------------------ (f) sampler
class NegativeSampler:
    """Negative text embeddings for the contrastive loss (Eq. 5).

    Encodes all negatives once and EXCLUDES those that would push the result
    away from its own target, each with its reason (logged, and kept in
    :attr:`excluded` for ``metrics.json``):

    * by meaning (:func:`exclusion_reason`): shared words and names with the
      prompt as typed or as augmented, and the category rule;
    * by the guidance's own relation, if it has one (``guidance.related``; ImageNet:
      a class sharing a word with the target's synonyms, "tiger cat" for "tabby");
    * by score: text-embedding cosine to the target above ``threshold``
      (default: the guidance's ``negative_threshold``; CLIP ViT-B/32 text-text
      cosines are ~0.6-0.8 for unrelated short prompts and ~0.9 for near-synonyms,
      hence 0.85).

    :meth:`sample` draws ``num_per_step`` of the kept ones without replacement
    (all of them if None or more than available).

    Attributes: ``prompts`` (kept), ``embeddings`` [M,D] (kept, unnormalized),
    ``excluded`` list of (prompt, reason).
    """

    def __init__(
        self,
        guidance: Guidance,
        negatives: list[str] | list[tuple[str, str]],
        target_prompt: str,
        threshold: float | None = None,
        num_per_step: int | None = 64,
        raw_prompt: str | None = None,
    ) -> None:
        if not negatives:
            raise ConfigError("NegativeSampler got no negative prompts; check stylize.negatives.")
        if num_per_step is not None and num_per_step < 1:
            raise ConfigError(f"stylize.num_negatives must be >= 1 or null, got {num_per_step}")
        if threshold is None:
            threshold = default_negative_threshold(guidance)
        target_prompt = validate_prompt(target_prompt)
        pairs = [p if isinstance(p, tuple) else ("", p) for p in negatives]
        pairs = list({t: (c, t) for c, t in reversed(pairs)}.values())[::-1]  # dedupe, first kept
        texts = [t for _, t in pairs]
        targets = list(dict.fromkeys([target_prompt, *([raw_prompt] if raw_prompt else [])]))
        related = getattr(guidance, "related", None)
        emb = guidance.encode_text(texts)
        tgt = guidance.encode_text([target_prompt])
        sim = (F.normalize(emb.float(), dim=-1) @ F.normalize(tgt.float(), dim=-1).t()).squeeze(1)
        reasons: list[str | None] = []
        for (category, text), s in zip(pairs, sim.tolist()):
            why = exclusion_reason(text, category, targets)
            if why is None and callable(related):
                why = related(target_prompt, text)
            if why is None and s > threshold:
                why = f"text cosine {s:.2f} > {threshold:.2f} to the target"
            reasons.append(why)
        self.excluded: list[tuple[str, str]] = [(t, r) for t, r in zip(texts, reasons) if r is not None]
        keep = torch.tensor([r is None for r in reasons], device=sim.device)
        self.prompts: list[str] = [t for t, r in zip(texts, reasons) if r is None]
        if not self.prompts:
            raise ConfigError(
                f"All {len(texts)} negative prompts are excluded as too close to the target {target_prompt!r} "
                f"(by meaning or cosine > {threshold}); raise stylize.negative_threshold or set "
                "stylize.negatives to another list (package, official, or a file)."
            )
        self.embeddings: Tensor = emb[keep]
        self.similarities: Tensor = sim[keep]
        self.threshold = threshold
        self.num_per_step = num_per_step
        log.info("Negative prompts: kept %d of %d; excluded %d for target %r: %s", len(self.prompts), len(texts),
                 len(self.excluded), target_prompt,
                 "; ".join(f"{n!r} ({r})" for n, r in self.excluded) or "none")
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
