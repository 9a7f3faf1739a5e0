"""The one validation of a run's config (:func:`parse_config`) and the view of it that cache keys hash.

* :func:`parse_config` checks a composed config before any data, weights or training is touched, and raises ONE
  :class:`~nerfart_plugin.errors.ConfigError` listing every violation as ``key=value: what is allowed (how to
  turn it off)``: the sections with fixed keys by their models (:mod:`nerfart_plugin.config.schema`), the
  component sections by the ``Config`` of the component each names (:mod:`nerfart_plugin.config.sections`), then
  the checks that involve several keys (memory per step, blends, an objective that optimizes nothing).
* Fields declared with ``changes_results=False`` (how often a run logs, validates or saves, chunk sizes that only
  trade memory, where outputs go) are left out of the cache keys of the run folders (:func:`result_settings`);
  every other setting is in.
"""

from __future__ import annotations

import collections.abc
import typing
from pathlib import Path
from typing import Any, Optional

from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, ValidationError

from nerfart_plugin.config.issues import Issue, issues_from, raise_issues
from nerfart_plugin.config.schema import MAX_GRAD_SAMPLES, MAX_NOGRAD_SAMPLES, SECTIONS, RunConfig
from nerfart_plugin.config.sections import TOP_LEVEL, check_section, section_model
from nerfart_plugin.config.types import changes_results
from nerfart_plugin.errors import ConfigError


# ---------------------------------------------------------------------- checks across sections
def _per_step(issues: list[Issue], key: str, value: int, factor_key: str, factor: int, limit: int,
              what: str) -> None:
    if value * factor > limit:
        issues.append(Issue(key, value, f"{key}={value} x {factor_key}={factor} = {value * factor:,} samples {what}: "
                            f"at most {limit:,} fit in memory; lower one of them"))


def cross_checks(c: dict) -> list[Issue]:
    """Checks that involve several keys (run on a config whose sections are each valid)."""
    issues: list[Issue] = []
    r, rc, sc = c["render"], c["reconstruct"], c["stylize"]
    n = int(r["num_samples"])
    ns = int(sc.get("num_samples") or n)
    _per_step(issues, "reconstruct.batch_rays", rc["batch_rays"], "render.num_samples", n, MAX_GRAD_SAMPLES,
              "per training step")
    nw = int(r["occupancy"].get("weighted_samples") or 0)
    if nw > n:  # weighted sampling (NDC density fields by default) trains on these instead
        _per_step(issues, "reconstruct.batch_rays", rc["batch_rays"], "render.occupancy.weighted_samples", nw,
                  MAX_GRAD_SAMPLES, "per training step")
    _per_step(issues, "render.chunk", r["chunk"], "render.num_samples", n, MAX_NOGRAD_SAMPLES, "per chunk")
    _per_step(issues, "stylize.patch_size", sc["patch_size"] ** 2, "stylize.num_samples", ns, MAX_GRAD_SAMPLES,
              "per patch (patch_size^2 rays)")
    _per_step(issues, "stylize.chunk", sc["chunk"], "stylize.num_samples", ns, MAX_NOGRAD_SAMPLES, "per chunk")
    issues += _blend_checks(c)
    region = c.get("region") or {}
    if any(region.get(k) is not None for k in ("file", "box", "ellipsoid")) and c["stage"] == "reconstruct":
        issues.append(Issue("region", {k: v for k, v in region.items() if v is not None}, "a region applies to a "
                            "stylization (stage=stylize | all | preview) or to a finished one (stage=render | export), "
                            "not to stage=reconstruct: drop region"))
    exp = c["experiment"]
    lambdas = [k for k in exp if k.startswith("lambda_")]
    if c["stage"] in ("stylize", "all") and lambdas and all(float(exp[k]) == 0 for k in lambdas):
        issues.append(Issue("experiment", {k: exp[k] for k in lambdas}, "every lambda is 0, so stylization would "
                            "optimize nothing: set at least one, e.g. experiment.lambda_dir=1.0"))
    return issues


def _blend_checks(c: dict) -> list[Issue]:
    """``strength`` and ``mix``: one weight per run, one way to blend, only where a run is rendered or exported."""
    issues: list[Issue] = []
    runs, weights = c["mix"]["runs"], c["mix"]["weights"]
    if len(runs) != len(weights):
        issues.append(Issue("mix.weights", weights, f"one weight per run of mix.runs ({len(runs)} run(s)), e.g. "
                            "mix.runs=[A,B] mix.weights=[0.5,0.5]"))
    if runs and float(c["strength"]) != 1.0:
        issues.append(Issue("strength", c["strength"], "with mix.runs a mix's weights are its strengths: drop "
                            "strength= and scale mix.weights instead"))
    if runs and c["stage"] not in ("render", "export"):
        issues.append(Issue("mix.runs", runs, f"a mix is rendered or exported, not trained (stage={c['stage']}): "
                            "add stage=render or stage=export"))
    return issues


# ---------------------------------------------------------------------- entry point
def _merge(original: Any, coerced: Any) -> Any:
    """``coerced`` where validation changed a value's meaning (``"512"`` -> 512, ``"false"`` -> False), else the
    ``original`` (so 15 stays 15 and not 15.0: cache keys hash the config)."""
    if isinstance(original, dict) and isinstance(coerced, dict):
        return {k: _merge(original[k], coerced[k]) if k in coerced else v for k, v in original.items()}
    if isinstance(original, (list, tuple)) and isinstance(coerced, (list, tuple)) and len(original) == len(coerced):
        return [_merge(a, b) for a, b in zip(original, coerced)]
    numbers = (int, float)
    same_kind = type(original) is type(coerced) or (
        isinstance(original, numbers) and isinstance(coerced, numbers)
        and not isinstance(original, bool) and not isinstance(coerced, bool))
    return original if same_kind and original == coerced else coerced


def _check(model: type[BaseModel], values: dict, prefix: str) -> tuple[dict, list[Issue]]:
    """Validate ``values`` against ``model``: (coerced values that were given, issues)."""
    try:
        return model.model_validate(values).model_dump(exclude_unset=True, exclude=set(TOP_LEVEL)), []
    except ValidationError as exc:
        return values, issues_from(exc, model, values, prefix)


def _check_settings(c: dict) -> dict:
    """Check every setting of the composed config ``c`` (a plain dict).

    Returns:
        ``c`` with the values validation converted (``"512"`` -> 512); otherwise unchanged.
    Raises:
        ConfigError: one message listing every violation, ``key=value: allowed (how to turn it off)``.
    """
    if not isinstance(c, dict):
        raise ConfigError(f"the config must be a mapping of settings, not {type(c).__name__}")
    c = {k: v for k, v in c.items() if k != "hydra"}
    fixed = {k: v for k, v in c.items() if k not in TOP_LEVEL}
    coerced, issues = _check(RunConfig, fixed, "")
    out = _merge(c, coerced)
    for key in TOP_LEVEL:
        if key in c:
            values, more = check_section(key, c[key])
            out[key] = _merge(c[key], values)
            issues += more
    if not issues:
        issues = cross_checks(RunConfig.model_validate(out).model_dump(exclude=set(TOP_LEVEL))
                              | {k: out[k] for k in TOP_LEVEL if k in out})
    raise_issues(issues)
    return out


def parse_config(c: Any) -> tuple[RunConfig, dict]:
    """The one validation of a run's config: every setting of ``c`` (a dict, DictConfig or RunConfig) checked
    before any data, weights or training is touched: types, ranges, choices, unknown keys (one ConfigError listing
    every violation, ``key=value: allowed (how to turn it off)``), each component section by its component's
    Config. Returns ``(RunConfig, the plain validated dict)``.

    The dict is what a run folder's ``config.yaml`` records (also ``RunConfig.plain``); the RunConfig is what
    code reads (``cfg.reconstruct.steps``, ``cfg.backbone.name``: each component section typed as its
    component's Config). A RunConfig is returned as it is. This is the one validation of a config; the pipeline
    adds the checks that depend on the stage (:func:`nerfart_plugin.run.pipeline.check_stage`).
    """
    if isinstance(c, RunConfig):
        return c, c.plain
    plain = _check_settings(to_plain(c))
    run = RunConfig.model_validate(plain)
    run._plain = plain
    return run, plain


# ---------------------------------------------------------------------- the one DictConfig -> dict helper
def to_plain(cfg: Any) -> dict:
    """A config as plain nested dicts: a DictConfig resolved (``${...}`` interpolations filled in), a
    mapping copied (nested mappings too), None as ``{}``; anything else is a ConfigError."""
    if cfg is None:
        return {}

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    if isinstance(cfg, collections.abc.Mapping):
        return {k: to_plain(v) if isinstance(v, (collections.abc.Mapping, DictConfig)) else v for k, v in cfg.items()}
    raise ConfigError(f"a config section must be a mapping of settings, not {type(cfg).__name__}")


# ---------------------------------------------------------------------- cache keys from the schema
def result_settings(section: BaseModel) -> dict[str, Any]:
    """The settings of ``section`` that change what a run computes: every field except those declared
    ``changes_results=False``, nested sections included (plain data, for the cache keys)."""
    out: dict[str, Any] = {}
    for name, info in type(section).model_fields.items():
        if not changes_results(info):
            continue
        value = getattr(section, name)
        out[name] = result_settings(value) if isinstance(value, BaseModel) else _dump(value)
    return out


def component_result_settings(section: str, values: dict) -> dict[str, Any]:
    """A component section (``data``, ...) without its ``changes_results=False`` settings."""
    name = values.get("name", values.get("kind"))  # kind: the settings format 1 (config.migrate)
    if section != "data" or name is None:
        return dict(values)
    fields = section_model("data", name).model_fields
    return {k: v for k, v in values.items() if k not in fields or changes_results(fields[k])}


def _dump(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [_dump(v) for v in value]
    return value


SectionT = typing.TypeVar("SectionT", bound=BaseModel)


def section(model: type[SectionT], value: Any, prefix: Optional[str] = None) -> SectionT:
    """``value`` as the typed section ``model``: an instance as it is, a mapping (or DictConfig) validated
    with the defaults for what it leaves out, None as the defaults. Raises ConfigError (each bad key, named
    under ``prefix``: by default the section's name)."""
    if isinstance(value, model):
        return value
    values = to_plain(value)
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        if prefix is None:
            prefix = next((k for k, m in SECTIONS.items() if m is model), "")
        raise_issues(issues_from(exc, model, values, prefix))
        raise  # pragma: no cover - raise_issues raised
