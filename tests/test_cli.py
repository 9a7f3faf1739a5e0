"""The command line ``python -m nerfart_plugin``: overrides, help, clear errors, packaged configs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pipeline_helpers import composed, run_cli, run_cli_subprocess

from nerfart_plugin.__main__ import normalize_overrides
from nerfart_plugin.config.compose import config_dir, group_options

REPO = Path(__file__).resolve().parents[1]
GROUPS = ("backbone", "data", "encoding", "experiment", "guidance", "preset")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return run_cli(list(args))


def _job_cfg(*args: str) -> dict:
    proc = _cli("--cfg", "job", *args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return yaml.safe_load(proc.stdout)


# ---------------------------------------------------------------------- normalize_overrides
def test_plus_is_folded_only_where_hydra_would_refuse_it():
    argv = [
        "+backbone=neus",  # a group already in the defaults list
        "+prompt=Joker",  # a key with a default (null)
        "+render.num_samples=8",  # a nested key with a default
        "++stage=all",  # force-add: Hydra's own
        "+newkey=1",  # no default: Hydra adds it (the schema then refuses it clearly)
        "+render.ndc_bound=2.0",  # a schema key (default 1.5): folded
        "+render.new_key=1",  # no default: Hydra adds it (the schema then refuses it clearly)
        "+data@extra=h3ds",  # a second package of a group: Hydra adds it
        "-m",
        "stage=all",
        "+prompt",
        "hydra/sweeper=lambdas_optuna",
    ]
    assert normalize_overrides(argv) == [
        "backbone=neus",
        "prompt=Joker",
        "render.num_samples=8",
        "++stage=all",
        "+newkey=1",
        "render.ndc_bound=2.0",
        "+render.new_key=1",
        "+data@extra=h3ds",
        "-m",
        "stage=all",
        "+prompt",
        "hydra/sweeper=lambdas_optuna",
    ]


def test_plus_folding_follows_the_selected_group_options():
    # data.factor has a default in data=llff only; data.fps in data=selfie only
    assert normalize_overrides(["data=llff", "+data.factor=4", "+data.fps=3"]) == [
        "data=llff", "data.factor=4", "+data.fps=3"]
    assert normalize_overrides(["-m", "data=llff,selfie", "+data.fps=3"]) == ["-m", "data=llff,selfie", "data.fps=3"]
    assert normalize_overrides(["+data.factor=4"]) == ["+data.factor=4"]
    assert normalize_overrides([]) == []


def test_plus_data_at_package_parses_as_in_hydra():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    (arg,) = normalize_overrides(["+data@extra=h3ds"])
    override = OverridesParser.create().parse_override(arg)
    assert override.is_add() and override.key_or_group == "data" and override.package == "extra"
    assert override.value() == "h3ds"


def test_plus_data_at_package_composes_a_second_data_config():
    """``+data@foo=h3ds`` is Hydra's own: the composed config gains a second data package ``foo`` (the
    first ``data`` untouched), which the schema then names as an unknown top-level key."""
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.validate import parse_config
    from nerfart_plugin.errors import ConfigError

    cfg = load_config(normalize_overrides(["data=llff", "data.path=x", "+data@foo=h3ds"]))
    assert cfg.foo.name == "h3ds" and cfg.data.name == "llff"
    with pytest.raises(ConfigError, match="foo"):
        parse_config(cfg)


PROMPTS = [
    "Van Gogh's Starry Night",
    "jack-o'-lantern",
    "a portrait (oil on canvas), 1889: blue = calm",
    'the "Joker"',
    "Café Gaudí, 日本の浮世絵, Ökonomie",
    "a=b c",
    "50% ${x} \\ back\\slash",
    "true",
    "1984",
    "  padded  ",
]


@pytest.mark.slow
def test_prompts_are_quoted_for_hydra_and_arrive_intact():
    for text in PROMPTS:
        for key in ("prompt", "source_prompt"):
            for plus in ("", "+"):
                (arg,) = normalize_overrides([f"{plus}{key}={text}"])
                assert _composed_value(arg, key) == text, (text, arg)


def _composed_value(arg: str, key: str):
    from omegaconf import OmegaConf

    return OmegaConf.to_container(composed(arg), resolve=True)[key]


@settings(max_examples=300, deadline=None)
@given(text=st.text(max_size=40))
def test_any_text_survives_hydra_quoting(text):
    """Any text (quotes, backslashes, ${, commas, any unicode) -> hydra_quote -> Hydra's parser -> OmegaConf."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    from nerfart_plugin.config.overrides import hydra_quote

    value = OverridesParser.create().parse_override("prompt=" + hydra_quote(text)).value()
    assert OmegaConf.to_container(OmegaConf.create({"prompt": value}), resolve=True)["prompt"] == text


def test_hydra_syntax_in_prompt_values_keeps_its_meaning():
    assert normalize_overrides(["prompt='a,b'"]) == ["prompt='a,b'"]  # quoted by the user: one prompt
    assert normalize_overrides(["-m", "prompt=choice(Joker,Pixar)"]) == ["-m", "prompt=choice(Joker,Pixar)"]
    assert normalize_overrides(["-m", "+prompt=Joker,Pixar"]) == ["-m", "prompt=Joker,Pixar"]  # Hydra's sweep
    assert normalize_overrides(["+prompt=Joker,Pixar"]) == ["prompt='Joker,Pixar'"]  # no -m: one prompt
    assert normalize_overrides(["prompt=null"]) == ["prompt=null"]
    assert normalize_overrides(["prompt=Tolkien Elf"]) == ["prompt=Tolkien Elf"]


def test_repeated_prompts_are_one_sweep_each_taken_literally():
    argv = ["-m", "+prompt=Joker", "+prompt=Van Gogh's Starry Night", "backbone=neus,volsdf", "+prompt=a, b"]
    out = normalize_overrides(argv)
    assert out == ["-m", "prompt='Joker','Van Gogh\\'s Starry Night','a, b'", "backbone=neus,volsdf"]
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweep = OverridesParser.create().parse_override(out[1])
    assert [q.text for q in sweep.value().list] == ["Joker", "Van Gogh's Starry Night", "a, b"]
    from nerfart_plugin.errors import ConfigError

    with pytest.raises(ConfigError, match="add -m"):
        normalize_overrides(["+prompt=Joker", "+prompt=Pixar"])


def test_sweep_of_free_text_prompts_runs_one_job_per_prompt(tmp_path):
    """A real 2-job sweep: each job gets its prompt intact (they then stop at validation: no reconstruction).
    Both jobs fail, so the sweep exits 1 after writing its summary, naming the failed jobs."""
    out = tmp_path / "sweep"
    proc = _cli("-m", "stage=stylize", "guidance=toy", f"output_root={out}", f"source_checkpoint={tmp_path}/none.ckpt",
                "+prompt=Joker", "+prompt=Van Gogh's Starry Night, 1889 (Café)")
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "2 sweep job(s) failed: 0, 1" in proc.stdout + proc.stderr
    jobs = sorted(p for p in out.glob("multirun/*/*") if p.is_dir() and p.name.isdigit())
    prompts = [yaml.safe_load((j / ".hydra" / "config.yaml").read_text())["prompt"] for j in jobs]
    assert prompts == ["Joker", "Van Gogh's Starry Night, 1889 (Café)"]
    assert "source_checkpoint" in (jobs[1] / "result.json").read_text()  # the job ran and failed clearly
    assert (jobs[0].parent / "summary.md").is_file()


def test_runs_started_in_the_same_second_keep_their_own_hydra_folders(tmp_path):
    """Each run's ``.hydra/overrides.yaml`` survives: the run folder's name goes down to microseconds."""
    for name in ("abc", "xyz"):  # both stop in the stage (no such run), after Hydra wrote the folder
        assert _cli(f"output_root={tmp_path}", "stage=render", f"render.run={tmp_path}/{name}").returncode == 2
    folders = sorted((tmp_path / "hydra").iterdir())
    assert len(folders) == 2
    assert ["/abc" in (f / ".hydra" / "overrides.yaml").read_text() for f in folders] == [True, False]


def test_a_bad_setting_is_refused_before_hydra_writes_anything(tmp_path):
    """A typo or a bad value stops the command before the training stack loads: exit 2, no run folder."""
    proc = _cli(f"output_root={tmp_path}", "stage=reconstruct", "reconstruct.batch_rays=abc")
    assert proc.returncode == 2 and "reconstruct.batch_rays" in proc.stdout + proc.stderr
    assert not (tmp_path / "hydra").exists()


def test_cli_non_ascii_and_quote_prompts():
    cfg = _job_cfg("+prompt=Van Gogh's Starry Night", "source_prompt=a photo (of a face), smiling: 日本")
    assert cfg["prompt"] == "Van Gogh's Starry Night"
    assert cfg["source_prompt"] == "a photo (of a face), smiling: 日本"


def test_group_options_match_the_conf_folder():
    assert group_options("backbone") == ["nerf", "neus", "volsdf"]
    assert (config_dir() / "hydra" / "sweeper" / "lambdas_optuna.yaml").is_file()


# ---------------------------------------------------------------------- --cfg job
def test_cfg_job_plus_backbone_and_prompt():
    cfg = _job_cfg("+backbone=neus", "+prompt=Joker")
    assert cfg["backbone"]["name"] == "neus" and cfg["prompt"] == "Joker"


def test_cfg_job_quoted_prompt_and_plain_backbone():
    cfg = _job_cfg(
        "+backbone=volsdf", "+prompt=Tolkien Elf"
    )  # as the shell passes +prompt="Tolkien Elf"
    assert cfg["backbone"]["name"] == "volsdf" and cfg["prompt"] == "Tolkien Elf"
    cfg = _job_cfg("backbone=volsdf")
    assert cfg["backbone"]["name"] == "volsdf" and cfg["prompt"] is None


def test_cfg_job_default_backbone_is_volsdf():
    cfg = _job_cfg()
    assert cfg["backbone"]["name"] == "volsdf" and cfg["stage"] == "all"
    assert (
        cfg["data"]["name"] == "h3ds" and cfg["experiment"]["lambda_perceptual"] == 2.0
    )


def test_help_lists_groups():
    proc = _cli("--help")
    assert proc.returncode == 0
    for group in GROUPS:
        assert f"{group}:" in proc.stdout, (
            group
        )  # Hydra's "== Configuration groups ==" section
    assert "backbone: nerf, neus, volsdf" in proc.stdout
    assert "stage=reconstruct" in proc.stdout
    # every setting of the schema with its default and meaning
    assert "reconstruct.batch_rays=512: random training rays per step" in proc.stdout
    assert "experiment.lambda_eikonal=0.1:" in proc.stdout


# ---------------------------------------------------------------------- errors
def test_unknown_backbone_group_option_lists_options():
    proc = _cli("backbone=foo")
    assert proc.returncode != 0
    assert "Could not find 'backbone/foo'" in proc.stderr
    assert "Available options in 'backbone'" in proc.stderr
    for name in ("nerf", "neus", "volsdf"):
        assert name in proc.stderr


def _assert_clear_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-2000:]
    assert "Traceback" not in out, out[-2000:]
    assert "ConfigError" in out
    for n in needles:
        assert n in out, (n, out[-2000:])


def test_unknown_backbone_name_is_a_config_error():
    _assert_clear_error(
        _cli("backbone.name=foo", "stage=reconstruct"), "'foo'", "nerf, neus, volsdf"
    )


def test_plus_new_key_reaches_the_schema_and_is_refused_clearly(tmp_path):
    proc = _cli("+render.new_key=1", "+render.num_sampels=8", "stage=reconstruct", f"output_root={tmp_path}")
    _assert_clear_error(proc, "render.new_key=1: unknown setting", "did you mean render.num_samples?",
                        "2 invalid settings")
    cfg = _job_cfg("+render.ndc_bound=2.0", "+backbone=neus")  # keys with a default: the + is folded
    assert cfg["render"]["ndc_bound"] == 2.0 and cfg["backbone"]["name"] == "neus"


def test_a_mistyped_key_without_plus_gets_the_closest_valid_keys(tmp_path):
    """Hydra alone answers ``render.num_sampels=3`` with "To append to your config use +render.num_sampels=3"
    (exit 1), advice that keeps the typo; the CLI gives it the schema's ConfigError instead."""
    assert normalize_overrides(["render.num_sampels=3", "render.num_samples=3", "hydra.run.dir=x"]) == [
        "+render.num_sampels=3", "render.num_samples=3", "hydra.run.dir=x"]
    assert normalize_overrides(["data=llff", "data.factor=4"]) == ["data=llff", "data.factor=4"]  # llff has it
    for typo, suggestion in (("render.num_sampels=3", "render.num_samples"), ("data.resoluton=128", "data.resolution"),
                             ("backbone.hiden_dim=64", "backbone.hidden_dim")):
        _assert_clear_error(_cli(typo, "stage=reconstruct", f"output_root={tmp_path}"), f"did you mean {suggestion}?")


def test_values_hydras_lexer_refuses_get_a_sentence_or_are_quoted(tmp_path):
    root = tmp_path / "never_made"
    _assert_clear_error(_cli("stage=render", "render.run=outputs/stylizations/<run>", f"output_root={root}"),
                        "<run> is a placeholder from the docs")
    _assert_clear_error(_cli("data.path=a b(c", f"output_root={root}"), "quote it for Hydra", "'data.path=\"a b(c\"'")
    _assert_clear_error(_cli("-m", "backbone=neus,volsdf", "+prompt=Joker,Pixar", "--cfg", "job"),
                        "--cfg prints the config of ONE job")
    assert not root.exists()  # a refused command leaves no empty output folder
    # letters outside ASCII are quoted for Hydra and arrive intact
    assert normalize_overrides(["data.path=/data/scène"]) == ["data.path='/data/scène'"]
    assert _job_cfg("data.path=/data/scène")["data"]["path"] == "/data/scène"


def test_blank_prompt_and_bad_stage_are_clear_errors():
    _assert_clear_error(
        _cli("prompt=  ", "stage=stylize", "guidance=toy"), "prompt", "empty"
    )
    _assert_clear_error(
        _cli("stage=bogus"), "stage='bogus'", "reconstruct, stylize, all, export, render, preview"
    )


# ---------------------------------------------------------------------- the wheel
def _pip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pip", *args], check=False, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_wheel_ships_configs_assets_and_negatives(tmp_path):
    """`pip wheel .` packages conf/ as nerfart_plugin/conf plus the default scene and negatives, and the
    installed copy finds its configs (run from outside the checkout)."""
    src = (
        tmp_path / "src"
    )  # a copy: building in place would leave build/ and *.egg-info in the checkout
    shutil.copytree(
        REPO,
        src,
        ignore=shutil.ignore_patterns(
            ".git",
            "outputs",
            "build",
            "dist",
            "*.egg-info",
            "__pycache__",
            ".pytest_cache",
            "benchmarks",
            ".dev",
        ),
    )
    proc = _pip("wheel", str(src), "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "dist"), "-q")
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("nerfart_plugin-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {
        "nerfart_plugin/conf/config.yaml",
        "nerfart_plugin/guidance/negative_prompts.txt",
        "nerfart_plugin/conf/hydra/sweeper/lambdas_optuna.yaml",
        "nerfart_plugin/conf/hydra/launcher/slurm.yaml",
    }
    for group in GROUPS:
        expected |= {
            f"nerfart_plugin/conf/{group}/{p.name}"
            for p in (REPO / "conf" / group).glob("*.yaml")
        }
    for f in (REPO / "nerfart_plugin" / "assets").rglob("*"):
        if f.is_file():
            expected.add(f.relative_to(REPO).as_posix())
    # every module of the package, subpackages included (the web viewer was once left out)
    expected |= {f.relative_to(REPO).as_posix() for f in (REPO / "nerfart_plugin").rglob("*.py")
                 if "__pycache__" not in f.parts}
    missing = sorted(expected - names)
    assert not missing, missing
    assert any(n.startswith("nerfart_plugin/assets/head/images/") for n in names)

    # install the wheel into a folder and run the CLI from there, outside the checkout
    target = tmp_path / "site"
    proc = _pip("install", "--no-deps", "--target", str(target), str(wheel), "-q")
    assert proc.returncode == 0, proc.stderr[-3000:]
    env = {**os.environ, "PYTHONPATH": str(target)}
    code = (
        "import nerfart_plugin, nerfart_plugin.config.compose as c; "
        "print(nerfart_plugin.__file__); print(c.config_dir())"
    )
    proc = subprocess.run(
        check=False,
        args=[sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    pkg_file, conf = proc.stdout.split()
    assert (
        Path(pkg_file).is_relative_to(target)
        and Path(conf) == target / "nerfart_plugin" / "conf"
    )
    proc = run_cli_subprocess(["--cfg", "job", "+backbone=neus", "+prompt=Joker"], timeout=300, cwd=tmp_path,
                              env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = yaml.safe_load(proc.stdout)
    assert cfg["backbone"]["name"] == "neus" and cfg["prompt"] == "Joker"
