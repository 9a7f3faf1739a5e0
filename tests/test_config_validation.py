"""Every setting is checked before any work: schema defaults = conf/, reported cases, a property test."""

from __future__ import annotations

import copy
import functools
import typing
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf
from pipeline_helpers import composed, run_cli_subprocess
from pydantic import BaseModel

from nerfart_plugin.config import compose as config_help
from nerfart_plugin.config import issues as config_issues
from nerfart_plugin.config import schema, validate
from nerfart_plugin.config import sections as config_components
from nerfart_plugin.config.compose import config_dir, group_options
from nerfart_plugin.config.migrate import CONFIG_FORMAT, to_format_1
from nerfart_plugin.errors import ConfigError, NerfArtError
from nerfart_plugin.run.pipeline import Pipeline, check_stage


def _plain_of(c):
    """The plain validated settings of ``c`` (the one validation, :func:`validate.parse_config`)."""
    return validate.parse_config(c)[1]


def _validated(c):
    """``c`` validated as the pipeline does: the config's own checks, then the stage's."""
    run, plain = validate.parse_config(c)
    check_stage(run)
    return plain


@functools.lru_cache(maxsize=None)
def _composed(*overrides: str) -> dict:
    return OmegaConf.to_container(composed(*overrides), resolve=True)


def cfg(*overrides: str) -> dict:
    """The composed config (a fresh copy) with ``overrides`` (Hydra syntax)."""
    return copy.deepcopy(_composed(*overrides))


def error_of(*overrides: str) -> str:
    with pytest.raises(ConfigError) as info:
        _plain_of(cfg(*overrides))
    return str(info.value)


# ---------------------------------------------------------------------- the schema is the one source of defaults
def _schema_keys(model: type[BaseModel], prefix: str = "") -> set[str]:
    keys = set()
    for name, info in model.model_fields.items():
        if typing.get_origin(info.annotation) is dict:
            continue  # a component section: its config group
        sub = config_issues._model_in(info.annotation)
        keys |= _schema_keys(sub, f"{prefix}{name}.") if sub is not None else {f"{prefix}{name}"}
    return keys


def _yaml_keys(node: Any, prefix: str = "") -> set[str]:
    if not isinstance(node, dict):
        return {prefix[:-1]}
    return set().union(*(_yaml_keys(v, f"{prefix}{k}.") for k, v in node.items())) if node else set()


def test_yaml_repeats_no_schema_default():
    """conf/config.yaml, experiment=full and preset=balanced set nothing the schema declares."""
    declared = _schema_keys(schema.RunConfig)
    raw = OmegaConf.to_container(OmegaConf.load(config_dir() / "config.yaml"))
    assert raw["defaults"][:2] == [config_help.SCHEMA_NODE, "_self_"]
    raw = {k: v for k, v in raw.items() if k not in ("defaults", "hydra")}
    assert not _yaml_keys(raw) & declared, "conf/config.yaml repeats schema defaults"
    for name in ("experiment/full.yaml", "preset/balanced.yaml"):
        assert not OmegaConf.to_container(OmegaConf.load(config_dir() / name)), f"conf/{name} sets values"


def test_composed_defaults_are_the_schema_defaults():
    composed = cfg()
    defaults = schema.RunConfig().model_dump(mode="json", exclude=set(config_components.TOP_LEVEL))
    assert {k: composed[k] for k in defaults} == defaults
    assert _plain_of(composed) == composed  # validation changes nothing in the defaults


def test_help_lists_every_setting_with_its_description():
    text = config_help.help_text()
    for key in _schema_keys(schema.RunConfig):
        assert f"  {key}=" in text, key
    assert "reconstruct.val_every=1000: steps between validations" in text


def test_cache_keys_leave_out_only_what_does_not_change_results():
    c = schema.RunConfig.model_validate(cfg())
    assert "chunk" not in validate.result_settings(c.render) and "num_samples" in validate.result_settings(c.render)
    assert {"precision", "devices", "num_nodes", "strategy"} <= set(validate.result_settings(c.trainer))
    assert "log_every_n_steps" not in validate.result_settings(c.trainer)
    rc = validate.result_settings(c.reconstruct)
    assert not {"val_every", "val_views", "checkpoint_every"} & set(rc) and "steps" in rc
    sc = validate.result_settings(c.stylize)
    assert not {"render_every", "checkpoint_every", "video_frames", "video_fps"} & set(sc) and "tau" in sc
    assert "subject" not in validate.component_result_settings("data", cfg()["data"])


GROUP_VARIANTS = [(), ("data=llff", "data.path=x"), ("data=selfie", "data.path=x")] + [
    (f"{group}={option}",) for group in ("backbone", "encoding", "guidance", "experiment", "preset")
    for option in group_options(group)]


@pytest.mark.parametrize("overrides", GROUP_VARIANTS, ids=lambda o: " ".join(o) or "default")
def test_every_group_option_validates(overrides):
    c = cfg(*overrides)
    assert _plain_of(c) == c


# ---------------------------------------------------------------------- the reported cases (preset=draft)
REPORTED = [
    ("reconstruct.steps=-5", "reconstruct.steps=-5: an integer in [1, "),
    ("reconstruct.batch_rays=0", "reconstruct.batch_rays=0: an integer in [1, "),
    ("render.num_samples=0", "render.num_samples=0: an integer in [1, 1024]"),
    ("reconstruct.batch_rays=abc", "reconstruct.batch_rays='abc': an integer in [1, "),
    ("seed=abc", "seed='abc': an integer in [0, 4294967295]"),
    ("render.chunk=0", "render.chunk=0: an integer in [1, 1048576] (there is no 'no chunking'"),
]


@pytest.mark.parametrize("override,message", REPORTED, ids=[r[0] for r in REPORTED])
def test_reported_impossible_settings_are_one_config_error(override, message):
    text = error_of("preset=draft", override)
    assert text.startswith(message), text
    assert "\n" not in text  # one violation, one line


def test_val_every_zero_means_no_validation():
    c = _plain_of(cfg("preset=draft", "reconstruct.val_every=0"))
    assert c["reconstruct"]["val_every"] == 0


def test_zero_like_values_say_how_to_turn_the_feature_off():
    assert "render.occupancy.enabled=false turns the grid off" in error_of("render.occupancy.resolution=0")
    assert "export.enabled=false turns mesh export off" in error_of("export.resolution=0")
    assert "export.enabled=false" in error_of("export.formats=[]")
    assert "experiment.lambda_global=0 experiment.lambda_local=0" in error_of("stylize.tau=0")
    assert "stylize.video_frames=0 turns the video off" in error_of("stylize.video_fps=0")
    assert "last.ckpt" in error_of("reconstruct.checkpoint_every=0")
    assert "stage=" in error_of("stylize.steps=0")
    # not zero: no hint, just the range
    assert "turns" not in error_of("render.occupancy.resolution=1000")


OTHER_CASES = [
    ("reconstruct.lr=nan", "reconstruct.lr=nan: a number in (0, 10]"),
    ("stylize.lr=inf", "stylize.lr=inf: a number in (0, 10]"),
    ("reconstruct.lr_mlp=-0.001", "reconstruct.lr_mlp=-0.001: a number in (0, 10]"),
    ("reconstruct.lambda_mask=-1", "reconstruct.lambda_mask=-1: a number in [0, "),
    ("experiment.lambda_global=-0.2", "experiment.lambda_global=-0.2: a number in [0, "),
    ("stylize.tau=-1", "stylize.tau=-1: a number in (0, 100]"),
    ("stylize.local_patch_frac=1.5", "stylize.local_patch_frac=1.5: a number in (0, 1]"),
    ("render.neus_alpha_mode=both", "render.neus_alpha_mode='both': one of gradient, sections"),
    ("render.occupancy.enabled=maybe", "render.occupancy.enabled='maybe': one of auto, true, false"),
    ("stage=bogus", "stage='bogus': one of reconstruct, stylize, all, export"),
    ("export.formats=[stl]", "export.formats=['stl']: a list of at least one value, each one of ply, obj, glb"),
    ("render.background_color=[1,1]", "render.background_color=[1, 1]: a list of 3 values, each a number in [0, 1]"),
    ("render.background_color=[1,1,2]", "render.background_color=[1, 1, 2]: a list of 3 values"),
    ("reconstruct.batch_rays=true", "reconstruct.batch_rays=true: an integer"),
    ("reconstruct.steps=12.5", "reconstruct.steps=12.5: an integer"),
    ("prompt_augment=maybe", "prompt_augment='maybe': true or false"),
    ("device=gpu", "device='gpu': one of auto, cpu, cuda"),
    ("trainer.devices=0", "trainer.devices=0: one of auto, -1, or an integer in [1, 4096]"),
    ("trainer.precision=8", "trainer.precision=8: one of 32-true"),
    ("reconstruct.batch_rays=300000", "reconstruct.batch_rays=300000: an integer in [1, 262144]"),
    ("render.occupancy.resolution=4096", "render.occupancy.resolution=4096: an integer in [1, 256]"),
    ("backbone.hidden_dim=100000", "backbone.hidden_dim=100000: an integer in [1, 2048]"),
    ("backbone.hidden_dim=0", "backbone.hidden_dim=0: an integer in [1, 2048]"),
    ("backbone.grad_type=numeric", "backbone.grad_type='numeric': one of auto, analytic, finite_difference"),
    ("encoding.resolution=1", "encoding.resolution=1: one of auto, or an integer in [2, 2048], or a list"),
    ("encoding.n_components=abc", "encoding.n_components='abc': an integer in [1, 256]"),
    ("backbone.dir_encoding.degree=9", "backbone.dir_encoding.degree=9: an integer in [1, 4]"),
    ("data.resolution=-1", "data.resolution=-1: one of auto, or an integer in [8, 8192], or null"),
    ("data.holdout_every=-2", "data.holdout_every=-2: an integer in [0, "),
    ("data.name=foo", "data.name='foo': one of h3ds, llff, nerfstudio, selfie"),
    ("+data.kind=llff", "data.kind='llff': the loader is chosen by data.name now: data.name=llff"),
    ("backbone.name=foo", "backbone.name='foo': one of nerf, neus, volsdf"),
    ("guidance.precision=fp8", "guidance.precision='fp8': one of auto, fp32, bf16, fp16"),
    ("guidance.perceptual.layers=[relu9_9]", "guidance.perceptual.layers=['relu9_9']: a list of at least one value, each one of"),
    ("guidance.allow_download=sometimes", "guidance.allow_download='sometimes': true or false, or null"),
]


@pytest.mark.parametrize("override,message", OTHER_CASES, ids=[c[0] for c in OTHER_CASES])
def test_other_impossible_settings(override, message):
    text = error_of(override)
    assert text.startswith(message), text


#: cache keys of the component sections as runs made before the typed component configs computed them (commit
#: b040aa3, constructor reflection): moving a setting's home must not move existing run folders. Since the settings
#: format 2 (one idiom: data.name, guidance.<key>) they are the keys of the format-1 view (config.migrate), which
#: run.keys computes beside the current key so that runs made before are found again
COMPONENT_KEYS = {(): "8f4083ed19ee", ("backbone=neus",): "c30e583f41be",
                  ("backbone=nerf", "encoding=frequency"): "e5dc05d8ad24", ("data=llff", "data.path=/x"): "3cc1344a7b9f",
                  ("data=selfie", "data.path=/x"): "a722a84580aa", ("data=nerfstudio", "data.path=/x"): "2a97a4dd1ee4",
                  ("encoding.resolution=[64,128]",): "5034919e46b8",
                  ("backbone.hidden_dim=32", "data.resolution=64", "backbone.dir_encoding.degree=3"): "b453a102a338"}
#: the same for the guidance section (its keys were read from the guides' and perceptual networks' constructors)
GUIDANCE_KEYS = {(): "f3b25190bc95", ("guidance=toy",): "03c3829bbda7", ("guidance=imagenet",): "6900ee4525fb",
                 ("guidance=imagenet", "guidance.perceptual.stages=[1,2]", "+guidance.perceptual.input_size=160"):
                     "0fcc7e7f7609",
                 ("guidance=toy", "guidance.perceptual.num_scales=2"): "852a702239cf",
                 ("guidance.precision=fp32", "guidance.perceptual.layers=[relu1_2]"): "b7d49545f872",
                 ("guidance=toy", "guidance.num_structure=4"): "04b1d6bd44b7",
                 ("guidance=imagenet", "guidance.source_top_k=3"): "5139ce4198df"}


@pytest.mark.parametrize("overrides", list(COMPONENT_KEYS))
def test_component_sections_keep_the_cache_keys_of_existing_runs(overrides: tuple[str, ...]) -> None:
    from nerfart_plugin.utils.io import config_hash

    old = to_format_1(validate.parse_config(cfg(*overrides))[1])
    sections = {"backbone": old["backbone"], "encoding": old["encoding"],
                "data": validate.component_result_settings("data", old["data"])}
    assert config_hash(sections) == COMPONENT_KEYS[overrides]


@pytest.mark.parametrize("overrides", list(GUIDANCE_KEYS))
def test_the_guidance_section_keeps_the_cache_keys_of_existing_runs(overrides: tuple[str, ...]) -> None:
    from nerfart_plugin.utils.io import config_hash

    assert config_hash({"guidance": to_format_1(validate.parse_config(cfg(*overrides))[1])["guidance"]}) \
        == GUIDANCE_KEYS[overrides]


def test_interpolated_keys_are_reported_with_their_source():
    text = error_of("render.sdf_grad_samples=0")  # backbone.grad_samples is ${render.sdf_grad_samples}
    assert "render.sdf_grad_samples=0: a number in (0, 1] (reconstruct.lambda_eikonal=0" in text
    assert "backbone.grad_samples=0" in text


def test_memory_of_several_settings_together_is_bounded():
    text = error_of("reconstruct.batch_rays=100000", "render.num_samples=1000")
    assert "reconstruct.batch_rays=100000 x render.num_samples=1000" in text and "lower one of them" in text
    text = error_of("stylize.patch_size=1024", "stylize.num_samples=1000")
    assert "stylize.patch_size" in text


def test_grid_and_other_constructor_checks_are_config_errors():
    from nerfart_plugin.fields import build_field

    with pytest.raises(ConfigError, match="encoding.resolution or encoding.n_components"):
        build_field({"name": "nerf"}, {"name": "grid", "resolution": 2048, "n_components": 256})
    with pytest.raises(ConfigError, match="beta_init"):
        build_field({"name": "volsdf", "beta_init": 1e-5, "beta_min": 1e-4}, {"name": "grid", "resolution": 8})


@pytest.mark.slow
def test_unknown_keys_suggest_the_closest_valid_key():
    assert "did you mean render.num_samples?" in error_of("+render.num_sampels=3")
    assert "did you mean seed?" in error_of("+seeed=3")
    assert "did you mean backbone.hidden_dim?" in error_of("+backbone.hiden_dim=3")
    assert "did you mean stylize.num_negatives?" in error_of("+stylize.num_negative=3")
    text = error_of("+render.new_key=1")
    assert text.startswith("render.new_key=1: unknown setting") and "render.num_samples" in text
    assert "did you mean guidance.pretrained?" in error_of("+guidance.pretraind=x")


def test_every_key_the_code_reads_has_a_default():
    c = _plain_of(cfg("render.ndc_bound=2.0", "experiment.lambda_eikonal=0.3"))
    assert c["render"]["ndc_bound"] == 2.0 and c["experiment"]["lambda_eikonal"] == 0.3


def test_every_violation_in_one_error():
    text = error_of("reconstruct.lr=-1", "stylize.lr=inf", "render.occupancy.enabled=maybe", "seed=abc")
    first, *lines = text.split("\n")
    assert first == "4 invalid settings:"
    assert sorted(line.split("=")[0].strip() for line in lines) == [
        "reconstruct.lr", "render.occupancy.enabled", "seed", "stylize.lr"]


def test_values_are_converted_only_where_their_meaning_changes():
    c = cfg()
    c["reconstruct"]["batch_rays"] = "512"
    c["prompt_augment"] = "false"
    c["prompt"] = 1984
    c["data"]["resolution"] = 128
    out = _plain_of(c)
    assert out["reconstruct"]["batch_rays"] == 512 and out["prompt_augment"] is False and out["prompt"] == "1984"
    assert type(out["data"]["resolution"]) is int and type(out["reconstruct"]["lr"]) is float


@pytest.mark.slow
def test_pipeline_validates_before_touching_data(tmp_path):
    missing = tmp_path / "no-such-scene"
    with pytest.raises(ConfigError, match="reconstruct.batch_rays"):
        Pipeline(cfg("stage=reconstruct", f"data.path={missing}", "reconstruct.batch_rays=0"))
    with pytest.raises(ConfigError, match="source_checkpoint=.*no such file"):
        Pipeline(cfg("stage=export", f"source_checkpoint={missing}.ckpt", f"output_root={tmp_path}"))
    with pytest.raises(ConfigError, match="device=cuda:7"):
        _validated(cfg("stage=reconstruct", "device=cuda:7"))


@pytest.mark.slow
def test_cli_bad_value_is_one_config_error_line_without_traceback(tmp_path):
    proc = run_cli_subprocess(["preset=draft", "reconstruct.batch_rays=abc", f"output_root={tmp_path}",
                    f"hydra.run.dir={tmp_path}/hydra"], timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-2000:]
    assert "Traceback" not in out and "Error executing job" not in out, out[-2000:]
    lines = [line for line in out.splitlines() if "ConfigError" in line]
    assert len(lines) == 1 and "reconstruct.batch_rays='abc': an integer in [1, " in lines[0], out[-2000:]


# ---------------------------------------------------------------------- property test: every setting
def _leaves(model: type[BaseModel], prefix: str) -> list[str]:
    out = []
    for name, info in model.model_fields.items():
        if name in config_components.TOP_LEVEL:
            continue  # a component section: enumerated from its component below
        sub = config_issues._model_in(info.annotation)
        out += _leaves(sub, f"{prefix}{name}.") if sub is not None else [f"{prefix}{name}"]
    return out


def _component_leaves(variant: tuple[str, ...]) -> list[str]:
    c = cfg(*variant)
    keys = []
    for section in config_components.TOP_LEVEL:
        keys += [k for k in config_components.section_keys(section, c[section]["name"])
                 if k != "guidance.perceptual"]
    keys += [f"backbone.dir_encoding.{k}" for k in c["backbone"]["dir_encoding"]]
    keys += config_components.section_keys("guidance.perceptual", c["guidance"]["perceptual"]["name"])
    return keys


#: every option of every component group is among the variants (test_property_test_covers_every_section)
VARIANTS = [("guidance=toy",), ("backbone=nerf", "encoding=frequency"), ("backbone=neus",),
            ("data=llff", "data.path=x"), ("data=selfie", "data.path=x", "guidance=clip"),
            ("data=nerfstudio", "data.path=x", "guidance=imagenet")]
SETTINGS = sorted({(v, key) for v in VARIANTS for key in _leaves(schema.RunConfig, "") + _component_leaves(v)})

BAD_VALUES = st.one_of(
    st.sampled_from([0, -1, 0.0, -0.5, float("nan"), float("inf"), -float("inf"), 10**12, 2**63, 1e300, True,
                     False, None, "", "abc", "0", "auto", [], [1, 2], {}, {"a": 1}, "???", "nan", "1e9"]),
    st.integers(min_value=-(2**64), max_value=2**64),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.lists(st.one_of(st.integers(-5, 5), st.floats(-2, 2), st.text(max_size=3)), max_size=4),
)


def _set(c: dict, key: str, value: Any) -> None:
    """``c[a][b][leaf] = value`` for ``key`` = "a.b.leaf" (nothing if a parent is no longer a section)."""
    *parents, leaf = key.split(".")
    node: Any = c
    for p in parents:
        node = node.get(p) if isinstance(node, dict) else None
    if isinstance(node, dict):
        node[leaf] = value


def _small(c: dict) -> bool:
    """Components cheap enough to build in the property test (sizes at most moderate)."""
    nums = [v for sec in ("backbone", "encoding") for v in c[sec].values() if isinstance(v, int)]
    res = c["encoding"].get("resolution", 1)
    res = 128 if res == "auto" else res  # without a scene setup: the auto rule's floor
    return all(v <= 256 for v in nums) and all(r <= 256 for r in (res if isinstance(res, list) else [res]))


def _build_cheap_components(c: dict, tmp: Path) -> None:
    """Everything that can be built without data, weights or training, from a config that validated."""
    from nerfart_plugin.data.datamodule import SceneDataModule
    from nerfart_plugin.export import MeshExtractor
    from nerfart_plugin.fields import OccupancyGrid, build_field
    from nerfart_plugin.guidance import build_guidance, build_perceptual
    from nerfart_plugin.run.fit import build_trainer

    if _small(c):
        build_field(c["backbone"], c["encoding"], bound=float(c["render"]["ndc_bound"]))
    occ = c["render"]["occupancy"]
    OccupancyGrid(resolution=min(int(occ["resolution"]), 32), threshold=occ["threshold"],
                  update_every=occ["update_every"], warmup_steps=occ["warmup_steps"])
    ec = c["export"]
    MeshExtractor(resolution=ec["resolution"], chunk=ec["chunk"], level=ec["level"],
                  remove_floaters=ec["remove_floaters"])
    SceneDataModule({"background_color": c["render"]["background_color"], **c["data"]})
    if c["guidance"]["name"] == "toy":
        build_guidance(c["guidance"])
        build_perceptual(c["guidance"])
    import torch

    build_trainer(int(c["reconstruct"]["steps"]), torch.device("cpu"), c["trainer"], run_dir=tmp)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(setting=st.sampled_from(SETTINGS), value=BAD_VALUES, extra=st.sampled_from(SETTINGS), value2=BAD_VALUES,
       two=st.booleans())
def test_property_any_value_of_any_setting_is_valid_or_a_project_error(tmp_path, setting, value, extra, value2, two):
    """Out-of-range, zero, negative, NaN, inf, huge and wrong-typed values of every setting of every section (one
    or two at a time): validation (then building the cheap components) succeeds or raises a NerfArtError."""
    variant, key = setting
    c = cfg(*variant, "stage=reconstruct")
    _set(c, key, value)
    if two and extra[0] == variant:
        _set(c, extra[1], value2)
    try:
        out = _validated(c)
    except NerfArtError:
        return
    try:
        _build_cheap_components(out, tmp_path)
    except NerfArtError:
        pass


EDGE_VALUES = [0, -1, 0.5, -0.5, float("nan"), float("inf"), 10**12, True, None, "", "abc", [], [0, 0], {"k": 1}]


@pytest.mark.slow
@pytest.mark.parametrize("variant", VARIANTS, ids=" ".join)
def test_every_setting_with_every_edge_value(tmp_path, variant):
    """The exhaustive counterpart of the property test: each setting of the variant x each edge value."""
    for v, key in SETTINGS:
        if v != variant:
            continue
        for value in EDGE_VALUES:
            c = cfg(*variant, "stage=reconstruct")
            _set(c, key, copy.deepcopy(value))
            try:
                out = _validated(c)
            except NerfArtError:
                continue
            try:
                _build_cheap_components(out, tmp_path)
            except NerfArtError:
                pass


def test_property_test_covers_every_section():
    """Every setting of the schema and every option of every component group is driven: a new section or
    group option is covered without editing this list."""
    sections = {key.split(".")[0] for _, key in SETTINGS}
    assert set(schema.RunConfig.model_fields) <= sections, set(schema.RunConfig.model_fields) - sections
    chosen = {o for v in VARIANTS for o in v if "=" in o and "." not in o.split("=")[0]}
    defaults = {f"{g}={cfg()[g]['name']}" for g in ("data", "backbone", "encoding", "guidance")}
    for group in ("data", "backbone", "encoding", "guidance"):
        missing = {f"{group}={o}" for o in group_options(group)} - chosen - defaults
        assert not missing, f"no property-test variant selects {sorted(missing)}: add one to VARIANTS"
    keys = {key for _, key in SETTINGS}
    assert {"data.sfm_threads", "data.factor", "guidance.precision", "guidance.input_size",
            "guidance.perceptual.layers", "guidance.perceptual.num_scales", "backbone.inv_s_max", "backbone.beta_min",
            "backbone.density_activation", "encoding.n_freqs", "encoding.n_components", "encoding.mlp_lr_scale",
            "backbone.dir_encoding.degree", "render.occupancy.threshold", "trainer.precision"} <= keys


#: constructor defaults of ``None`` that stand for a concrete setting the YAML spells out
_NONE_MEANS = {"dir_encoding": {"name": "sh", "degree": 4}}


@pytest.mark.parametrize("group", ["backbone", "encoding"])
def test_component_yaml_repeats_the_constructor_defaults(group: str) -> None:
    """conf/<group>/<name>.yaml lists a component's settings for --cfg job; every value it states is the
    default of the component's Config (or wires a render.* knob), so the Python API and the CLI build one model."""
    import yaml

    from nerfart_plugin.config import registry
    from nerfart_plugin.config.components import config_of

    for path in sorted((config_dir() / group).glob("*.yaml")):
        values = yaml.safe_load(path.read_text())
        fields = config_of(registry.get(group, values["name"])).model_fields
        for key, value in values.items():
            if key == "name" or (isinstance(value, str) and value.startswith("${")):
                continue
            default = fields[key].default
            default = _NONE_MEANS.get(key, default) if default is None else default
            assert value == default, f"{path.name}: {key}={value!r} but the Config's default is {default!r}"


def test_explicit_source_checkpoint_key_covers_its_content_and_the_render_settings(tmp_path):
    """A stylization from source_checkpoint=FILE is keyed by the file's content, the scene and the render
    settings the stylization uses: re-training into the same path or a new background is a new run."""
    from types import SimpleNamespace

    from nerfart_plugin.run.stages.stylize import stylization_source

    ckpt = tmp_path / "final.ckpt"
    ckpt.write_bytes(b"one")

    def key(*overrides: str, content: str = "scene-a") -> str:
        c, plain = validate.parse_config(cfg(f"source_checkpoint={ckpt}", *overrides))
        scene = SimpleNamespace(cfg=c, plain=plain, scene=SimpleNamespace(content_hash=content))
        return stylization_source(scene, None)[1][CONFIG_FORMAT]

    base = key()
    assert key() == base and key("render.chunk=1024") == base  # memory only
    assert key("render.background_color=[0,0,0]") != base and key(content="scene-b") != base
    ckpt.write_bytes(b"two")
    assert key() != base


def test_every_stage_has_one_plan():
    """stage= is dispatched through one table (pipeline.PLANS): every choice of the schema has its plan."""
    from typing import get_args

    from nerfart_plugin.config.schema import RunConfig
    from nerfart_plugin.run.pipeline import PLANS

    assert sorted(PLANS) == sorted(get_args(RunConfig.model_fields["stage"].annotation))
    assert [p for p, plan in PLANS.items() if plan.needs_prompt] == ["stylize", "all", "preview"]
    assert [p for p, plan in PLANS.items() if plan.multi_device] == ["reconstruct"]


def test_a_registered_perceptual_network_is_picked_by_name(monkeypatch):
    """``guidance.perceptual`` names any network of the ``perceptual`` registry (a plugin's too), and a typo gets
    the closest registered name."""
    from nerfart_plugin.config import registry
    from nerfart_plugin.guidance import build_perceptual
    from nerfart_plugin.guidance.vgg import EdgePerceptual

    class GrayEdges(EdgePerceptual):
        name = "gray_edges"

    registry.names("perceptual")  # the package's own networks first
    monkeypatch.setitem(registry._REGISTRY["perceptual"], "gray_edges", GrayEdges)
    out = _validated(cfg("guidance=toy", "guidance.perceptual=gray_edges", "stage=reconstruct"))
    assert type(build_perceptual(out["guidance"])) is GrayEdges
    assert "did you mean gray_edges?" in error_of("guidance=toy", "guidance.perceptual=gray_edge")
