"""Third-party components by entry point: a tiny distribution adds a backbone used by name from the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from pipeline_helpers import cli_args, run_cli_subprocess

PLUGIN_MODULE = '''
"""A third-party backbone: VolSDF with a different name (registered on import)."""
from nerfart_plugin.fields.volsdf import VolSDFField
from nerfart_plugin.config.registry import register


@register("backbone", "tiny_sdf")
class TinySDF(VolSDFField):
    """VolSDF under another name, to prove the registry found it."""
'''

PYPROJECT = '''
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "tiny-sdf-plugin"
version = "0.0.1"

[project.entry-points."nerfart_plugin.components"]
tiny_sdf = "tiny_sdf_plugin.fields"

[project.entry-points."nerfart_plugin.configs"]
tiny_sdf = "tiny_sdf_plugin.conf"

[tool.setuptools]
packages = ["tiny_sdf_plugin", "tiny_sdf_plugin.conf", "tiny_sdf_plugin.conf.backbone"]

[tool.setuptools.package-data]
"tiny_sdf_plugin.conf.backbone" = ["*.yaml"]
'''


def build_plugin(root: Path) -> Path:
    """Write the tiny distribution and pip-install it into ``root/site`` (no network: no build isolation)."""
    src = root / "src"
    pkg = src / "tiny_sdf_plugin"
    (pkg / "conf" / "backbone").mkdir(parents=True)
    (src / "pyproject.toml").write_text(PYPROJECT)
    (pkg / "__init__.py").write_text("")
    (pkg / "fields.py").write_text(PLUGIN_MODULE)
    (pkg / "conf" / "__init__.py").write_text("")
    (pkg / "conf" / "backbone" / "__init__.py").write_text("")
    volsdf = Path(__file__).resolve().parents[1] / "conf" / "backbone" / "volsdf.yaml"
    (pkg / "conf" / "backbone" / "tiny_sdf.yaml").write_text(
        volsdf.read_text().replace("name: volsdf", "name: tiny_sdf"))
    site = root / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--target", str(site), str(src)], check=True, capture_output=True, text=True, timeout=300)
    return site


@pytest.mark.slow
def test_installed_plugin_backbone_is_used_by_name(tmp_path: Path) -> None:
    site = build_plugin(tmp_path / "plugin")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "out"
    from nerfart_plugin.data.datamodule import DEFAULT_SCENE

    r = run_cli_subprocess(cli_args(out, DEFAULT_SCENE, "stage=reconstruct", "backbone=tiny_sdf", "reconstruct.steps=3",
                         "export.enabled=false"), env=env, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "plugin components loaded: tiny_sdf" in r.stdout + r.stderr
    runs = list((out / "reconstructions").iterdir())
    assert len(runs) == 1 and "-tiny_sdf-" in runs[0].name and (runs[0] / "final.ckpt").is_file()
    # without the distribution the name is unknown, and the error lists the valid ones
    r2 = run_cli_subprocess(cli_args(out, DEFAULT_SCENE, "stage=reconstruct", "backbone=tiny_sdf"), timeout=300)
    assert r2.returncode != 0 and "tiny_sdf" in r2.stdout + r2.stderr


def test_a_broken_plugin_is_a_clear_error(monkeypatch) -> None:
    from importlib.metadata import EntryPoint

    import nerfart_plugin.config.plugins as plugins
    from nerfart_plugin.errors import ConfigError

    broken = EntryPoint(name="broken", value="no_such_module_xyz", group=plugins.COMPONENTS_GROUP)
    monkeypatch.setattr(plugins, "_entry_points", lambda group: [broken] if group == plugins.COMPONENTS_GROUP else [])
    monkeypatch.setattr(plugins, "_loaded", set())
    with pytest.raises(ConfigError, match="'broken' = 'no_such_module_xyz'.*failed to import"):
        plugins.load_components()
    assert plugins.searchpath_overrides([]) == []


def test_searchpath_override(monkeypatch) -> None:
    import nerfart_plugin.config.plugins as plugins

    monkeypatch.setattr(plugins, "config_packages", lambda: [("a", "pkg_a.conf"), ("b", "pkg_b.conf")])
    assert plugins.searchpath_overrides(["x=1"]) == ["hydra.searchpath=[pkg://pkg_a.conf,pkg://pkg_b.conf]"]
    assert plugins.searchpath_overrides(["hydra.searchpath=[file:///x]"]) == []
