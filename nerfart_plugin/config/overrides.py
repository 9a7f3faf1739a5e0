"""Command-line overrides as a user types them -> as Hydra 1.3 parses them.

Two things Hydra's override grammar gets in the way of:

* **Prompts are free text.** ``+prompt="Van Gogh's Starry Night"`` reaches us as
  ``+prompt=Van Gogh's Starry Night`` (the shell removed the quotes) and dies in
  Hydra's lexer; so do parentheses, ``=``, non-ASCII letters, and a comma makes it a
  sweep. :func:`quote_prompts` quotes ``prompt=`` / ``source_prompt=`` values for Hydra
  so the text arrives intact (``${`` included: it is text, not an interpolation). A value
  that already means something to Hydra is kept: a string the user quoted
  (``prompt='a,b'``), ``choice(...)``, ``null`` (no prompt), and, with ``-m``, a plain
  comma sweep (``-m +prompt=Joker,Pixar``: two jobs).
  **Sweeping free-text prompts:** repeat the override, one prompt per argument::

      python -m nerfart_plugin -m +prompt=Joker +prompt="Van Gogh's Starry Night"

  Repeated ``prompt=`` arguments are each one prompt, taken literally (commas and
  quotes included), and become one Hydra sweep over them.
* **``+key`` for keys that have a default.** Hydra refuses ``+backbone=neus`` and
  ``+prompt=Joker`` ("Could not append to config" / "Multiple values for ..."), which
  users type naturally. :func:`fold_plus` drops that ``+`` exactly where Hydra would
  refuse it: a key that already exists in the composed primary config, or a config
  group already in the defaults list. Every other ``+key`` (``+render.ndc_bound=2.0``,
  ``+data@extra=h3ds``) behaves exactly as in Hydra.
"""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Optional

from omegaconf import OmegaConf

from nerfart_plugin.config.compose import config_dir, primary_keys
from nerfart_plugin.errors import ConfigError

log = logging.getLogger("nerfart_plugin")

PROMPT_KEYS = ("prompt", "source_prompt")
MULTIRUN_FLAGS = ("-m", "--multirun")
_PROMPT_ARG = re.compile(r"^(\+{0,2})(" + "|".join(PROMPT_KEYS) + r")=(.*)$", re.DOTALL)


# ---------------------------------------------------------------------- prompts
def hydra_quote(text: str) -> str:
    """``text`` as a single-quoted Hydra value that Hydra and OmegaConf turn back into exactly ``text``.

    OmegaConf: a literal ``${`` is written ``\\${`` (and backslashes right before it doubled);
    Hydra: inside quotes, ``\\'`` is a quote and backslashes right before a quote or the end are doubled.
    """
    text = re.sub(r"(\\*)\$\{", lambda m: m.group(1) * 2 + "\\${", text)
    text = re.sub(r"(\\+)(?='|$)", lambda m: m.group(1) * 2, text)
    return "'" + text.replace("'", "\\'") + "'"


def _parse(key: str, value: str) -> Optional[Any]:
    """Hydra's parse of ``key=value`` (an Override), or None when Hydra's grammar refuses it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        return OverridesParser.create().parse_override(f"{key}={value}")
    except (HydraException, ValueError):
        return None


def keeps_hydra_meaning(key: str, value: str, multirun: bool) -> bool:
    """Whether a prompt value is Hydra syntax to keep as typed (see the module docstring)."""
    from hydra.core.override_parser.types import ValueType

    parsed = _parse(key, value)
    if parsed is None:
        return False  # Hydra's grammar refuses it: free text
    if parsed.value_type == ValueType.SIMPLE_CHOICE_SWEEP:
        return multirun  # "a, b": a sweep with -m, one prompt with a comma without
    if parsed.is_sweep_override():
        return True  # choice(...), range(...), glob(...)
    v = parsed.value()
    if v is None or value.strip()[:1] in ("'", '"'):
        return True  # null (no prompt), or a string the user quoted for Hydra
    # plain text that Hydra and OmegaConf read unchanged ("${" would be an interpolation: quoted as text)
    return isinstance(v, str) and v == value and "${" not in value


def quote_prompts(argv: list[str], multirun: bool) -> list[str]:
    """Quote every ``prompt=`` / ``source_prompt=`` value for Hydra; repeated ones become one sweep."""
    found: dict[str, list[int]] = {}
    for i, arg in enumerate(argv):
        m = _PROMPT_ARG.match(arg)
        if m:
            found.setdefault(m.group(2), []).append(i)
    out = list(argv)
    drop: set[int] = set()
    for key, idx in found.items():
        matches = [_PROMPT_ARG.match(argv[i]) for i in idx]
        plus = matches[0].group(1)  # type: ignore[union-attr]
        values = [m.group(3) for m in matches]  # type: ignore[union-attr]
        if len(values) == 1:
            v = values[0]
            out[idx[0]] = f"{plus}{key}={v if keeps_hydra_meaning(key, v, multirun) else hydra_quote(v)}"
            if "," in v and multirun and not keeps_hydra_meaning(key, v, multirun):
                log.warning("%s=%s is ONE prompt (its commas are text). To sweep several prompts, repeat the "
                            "override: -m +%s=first +%s=\"second, with a comma\"", key, v, key, key)
            continue
        if not multirun:
            raise ConfigError(f"{key}= is given {len(values)} times ({', '.join(map(repr, values))}). To run one "
                              f"job per {key}, add -m (a sweep); otherwise give it once.")
        quoted = [v if _is_quoted(key, v) else hydra_quote(v) for v in values]
        out[idx[0]] = f"{plus}{key}=" + ",".join(quoted)
        drop.update(idx[1:])
    return [a for i, a in enumerate(out) if i not in drop]


def _is_quoted(key: str, value: str) -> bool:
    """A value the user quoted for Hydra ('...' or "...", one string)."""
    parsed = _parse(key, value)
    return parsed is not None and not parsed.is_sweep_override() and value.strip()[:1] in ("'", '"')


def override_value(argv: list[str], key: str) -> Optional[Any]:
    """The value the last ``key=`` / ``+key=`` / ``++key=`` override of ``argv`` sets (None if none, or a sweep)."""
    value = None
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        k, v = arg.lstrip("+").split("=", 1)
        if k == key:
            parsed = _parse(k, v)
            value = None if parsed is None or parsed.is_sweep_override() else parsed.value()
    return value


# ---------------------------------------------------------------------- + folding
@dataclass
class PrimaryConfig:
    """What the composed primary config already has: dotted keys and the groups of its defaults list."""

    keys: set[str] = field(default_factory=set)
    groups: set[str] = field(default_factory=set)
    #: False when composition failed and ``keys`` holds only the top-level keys
    complete: bool = True


def _dotted_keys(node: Any, prefix: str = "") -> Iterable[str]:
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}{k}"
            yield key
            yield from _dotted_keys(v, key + ".")


def _group_choices(argv: list[str], groups: set[str]) -> list[list[str]]:
    """The project-group selections on the command line, as lists of single-option overrides to compose
    (a swept group contributes one list per option)."""
    base: list[str] = []
    swept: list[tuple[str, list[str]]] = []
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, value = arg.lstrip("+").split("=", 1)
        if key not in groups:
            continue
        parsed = _parse(key, value)
        if parsed is None:
            continue
        if parsed.is_sweep_override():
            swept.append((key, [str(v) for v in parsed.sweep_string_iterator()]))
        else:
            base.append(f"{key}={value}")
    runs = [base]
    for key, options in swept:
        runs += [[*base, f"{key}={o}"] for o in options]
    return runs


def primary_config(argv: list[str]) -> PrimaryConfig:
    """Compose the primary config with the group selections of ``argv`` (each option of a swept group) and
    collect its keys and defaults-list groups. Falls back to the top-level keys and groups of ``conf/`` when
    composition fails (Hydra then reports the bad selection itself)."""
    from hydra.errors import HydraException


    root = config_dir()
    groups = {p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(("_", ".", "hydra"))}
    found = PrimaryConfig()
    try:
        for overrides in _group_choices(argv, groups):
            keys, chosen_groups = _composed_keys(str(root), tuple(overrides))
            found.keys |= keys
            found.groups |= chosen_groups
    except (HydraException, ValueError, KeyError) as exc:
        log.debug("could not compose the primary config for +key folding (%s); using its top-level keys", exc)
        found = PrimaryConfig(keys=primary_keys(), groups=groups, complete=False)
    return found


@functools.lru_cache(maxsize=64)
def _composed_keys(root: str, overrides: tuple[str, ...]) -> tuple[frozenset[str], frozenset[str]]:
    """The dotted keys and the defaults-list groups of the config in ``root`` composed with ``overrides`` (group
    selections only). Remembered per process: an in-process caller (a notebook, the test suite) that normalizes
    many command lines composes each selection once."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=root, version_base="1.3"):
        cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
    plain = OmegaConf.to_container(cfg, resolve=False)
    plain.pop("hydra", None)
    return frozenset(_dotted_keys(plain)), frozenset(cfg.hydra.runtime.choices.keys())


def fold_plus(arg: str, primary: PrimaryConfig) -> str:
    """``+key=value`` -> ``key=value`` where Hydra would refuse the ``+`` (see the module docstring)."""
    if not arg.startswith("+") or arg.startswith("++") or "=" not in arg:
        return arg
    key = arg[1:].split("=", 1)[0]
    return arg[1:] if key in primary.keys or key in primary.groups else arg


#: sections whose value may be a file alone: ``region=<file>`` is ``region.file=<file>``
FILE_SHORTHANDS = ("region", "style_image")


def expand_file_shorthand(arg: str) -> str:
    """``region=<file>`` / ``style_image=<file>`` -> ``<section>.file=<file>``, so that the section's other keys can
    follow on the same command line (``style_image=a.png style_image.lambda_style=2``)."""
    m = _OVERRIDE.match(arg)
    if not m or m.group(1) not in ("", "+") or m.group(2) not in FILE_SHORTHANDS or m.group(3).startswith(("{", "null")):
        return arg
    return f"{m.group(2)}.file={m.group(3)}"


def add_plus(arg: str, primary: PrimaryConfig) -> str:
    """``key=value`` -> ``+key=value`` for a key the composed config does not have (a typo such as
    ``render.num_sampels=3``): Hydra then adds it and the schema refuses it naming the closest valid keys,
    where Hydra alone would advise ``+render.num_sampels=3``, keeping the typo. Groups, Hydra's own keys
    and package or deletion syntax are left to Hydra."""
    if not primary.complete or arg.startswith(("+", "-", "~")) or "=" not in arg:
        return arg
    key = arg.split("=", 1)[0]
    if key in primary.keys or key in primary.groups or "/" in key or "@" in key or key.split(".")[0] == "hydra":
        return arg
    return "+" + arg


# ---------------------------------------------------------------------- values Hydra's lexer refuses
_OVERRIDE = re.compile(r"^(~|\+{0,2})([\w.@/-]+)=(.*)$", re.DOTALL)
_PLACEHOLDER = re.compile(r"<[^<>=]*>")
_NO_CONFIG_FLAGS = ("--cfg", "-c")


def check_value_syntax(argv: list[str]) -> list[str]:
    """Every ``key=value`` that Hydra's grammar refuses, made right or refused with a sentence: a value with
    letters outside ASCII (``data.path=/data/scène``) is quoted for Hydra; a placeholder copied from the
    docs (``<run>``) and any other unparsable value get a ConfigError saying what to type instead."""
    out = []
    for arg in argv:
        m = _OVERRIDE.match(arg)
        if not m or _parse(m.group(2), m.group(3)) is not None or _PROMPT_ARG.match(arg):
            out.append(arg)
            continue
        prefix, key, value = m.groups()
        hole = _PLACEHOLDER.search(value)
        if hole:
            raise ConfigError(f"{key}={value}: {hole.group()} is a placeholder from the docs; put the real value "
                              f"in its place (for a run: a folder under outputs/stylizations/ or "
                              "outputs/reconstructions/; ls lists them).")
        if not value.isascii() and _parse(key, hydra_quote(value)) is not None:
            out.append(f"{prefix}{key}={hydra_quote(value)}")
            continue
        raise ConfigError(f"{key}={value}: Hydra's override grammar cannot read this value; quote it for Hydra "
                          f"inside the shell's quotes: '{key}=\"{value}\"'.")
    return out


def check_flags(argv: list[str]) -> None:
    """ConfigError for flag combinations Hydra refuses with a traceback: ``-m`` with ``--cfg``."""
    if any(a in MULTIRUN_FLAGS for a in argv) and any(a in _NO_CONFIG_FLAGS or a.startswith("--cfg=") for a in argv):
        raise ConfigError("--cfg prints the config of ONE job and -m starts a sweep of several: Hydra cannot do both. "
                          "Drop -m and give one value per key (e.g. backbone=neus +prompt=Joker) to see that job's "
                          "config.")


def normalize_overrides(argv: list[str], primary: Optional[PrimaryConfig] = None) -> list[str]:
    """The command line as Hydra should see it: prompts quoted, ``+`` folded where Hydra would refuse it and
    added where Hydra would refuse a plain override of an unknown key (:func:`add_plus`).

    ``primary``: what the composed config already has (default: composed from ``argv``'s group selections).
    """
    check_flags(argv)
    multirun = any(a in MULTIRUN_FLAGS for a in argv)
    argv = check_value_syntax(quote_prompts(list(argv), multirun))
    if not any("=" in a and not a.startswith(("++", "-", "~")) for a in argv):
        return argv
    primary = primary if primary is not None else primary_config(argv)
    return [add_plus(fold_plus(expand_file_shorthand(a), primary), primary) for a in argv]
