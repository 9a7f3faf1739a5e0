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

from nerfart_plugin.__main__ import normalize_overrides
from nerfart_plugin.config_paths import config_dir, group_options, primary_keys

from pipeline_helpers import run_cli

REPO = Path(__file__).resolve().parents[1]
GROUPS = ("backbone", "data", "encoding", "experiment", "guidance", "preset")


def _cli(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return run_cli(list(args), timeout=timeout)


def _job_cfg(*args: str) -> dict:
    proc = _cli("--cfg", "job", *args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return yaml.safe_load(proc.stdout)


# ---------------------------------------------------------------------- normalize_overrides
def test_normalize_overrides_folds_plus_for_known_keys():
    known = primary_keys()
    assert {"backbone", "prompt", "data", "stage", "render"} <= known
    argv = [
        "+backbone=neus",
        "+prompt=Joker",
        "+render.num_samples=8",
        "++prompt=x",
        "+newkey=1",
        "+data@foo=h3ds",
        "-m",
        "stage=all",
        "+prompt",
        "hydra/sweeper=lambdas_optuna",
    ]
    assert normalize_overrides(argv, known) == [
        "backbone=neus",
        "prompt=Joker",
        "render.num_samples=8",
        "++prompt=x",
        "+newkey=1",
        "data@foo=h3ds",
        "-m",
        "stage=all",
        "+prompt",
        "hydra/sweeper=lambdas_optuna",
    ]


def test_normalize_overrides_keeps_values_with_equals_and_spaces():
    assert normalize_overrides(["+prompt=a=b c"], {"prompt"}) == ["prompt=a=b c"]
    assert normalize_overrides(["+prompt=Joker,Pixar"], {"prompt"}) == [
        "prompt=Joker,Pixar"
    ]
    assert normalize_overrides([], {"prompt"}) == []


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
        cfg["data"]["kind"] == "h3ds" and cfg["experiment"]["lambda_perceptual"] == 2.0
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


def test_blank_prompt_and_bad_stage_are_clear_errors():
    _assert_clear_error(
        _cli("prompt=  ", "stage=stylize", "guidance=toy"), "prompt", "empty"
    )
    _assert_clear_error(
        _cli("stage=bogus"), "stage='bogus'", "reconstruct, stylize, all, export"
    )


# ---------------------------------------------------------------------- the wheel
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
    proc = subprocess.run(
        check=False,
        args=[
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(src),
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(tmp_path / "dist"),
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
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
    missing = sorted(expected - names)
    assert not missing, missing
    assert any(n.startswith("nerfart_plugin/assets/head/images/") for n in names)

    # install the wheel into a folder and run the CLI from there, outside the checkout
    target = tmp_path / "site"
    proc = subprocess.run(
        check=False,
        args=[
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--target",
            str(target),
            str(wheel),
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    env = {**os.environ, "PYTHONPATH": str(target)}
    code = (
        "import nerfart_plugin, nerfart_plugin.config_paths as c; "
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
    proc = run_cli(["--cfg", "job", "+backbone=neus", "+prompt=Joker"], timeout=300, cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = yaml.safe_load(proc.stdout)
    assert cfg["backbone"]["name"] == "neus" and cfg["prompt"] == "Joker"
