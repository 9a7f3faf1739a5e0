"""The documentation keeps its promises: every documented command composes and validates, the settings
reference is what the schema says, the site builds strictly, the README stays short and speaks to users."""

from __future__ import annotations

import re
import runpy
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
USER_PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
_FENCE = re.compile(r"```(?:bash|sh|console)?\n(.*?)```", re.DOTALL)
_PLACEHOLDER = re.compile(r"<[^<>=]*>")


def documented_commands() -> list[tuple[str, str]]:
    """``(page, command line)`` of every ``python -m nerfart_plugin ...`` line in a fenced block of the
    README and the docs (backslash continuations joined)."""
    out = []
    for page in USER_PAGES:
        for block in _FENCE.findall(page.read_text()):
            for line in block.replace("\\\n", " ").splitlines():
                line = line.strip()
                cmd = line[line.find("python -m nerfart_plugin "):] if "python -m nerfart_plugin " in line else ""
                cmd = cmd.split("`")[0].strip()  # a command quoted inline in a comment ends at its backtick
                if cmd:
                    out.append((str(page.relative_to(REPO)), cmd))
    return out


def job_overrides(command: str) -> list[list[str]]:
    """The override lists of the jobs a documented command starts (one, or a sweep's), as the CLI sees
    them (:func:`normalize_overrides`), placeholders such as ``<run>`` filled in."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from nerfart_plugin.config.overrides import normalize_overrides

    argv = shlex.split(_PLACEHOLDER.sub("placeholder", command), comments=True)[3:]
    flags = [a for a in argv if a.startswith("-")]
    args = [a for a in argv if not a.startswith("-") and a != "job"]
    args = normalize_overrides([*args, *(["-m"] if "-m" in flags else [])])
    args = [a for a in args if a != "-m"]
    parsed = [o for o in OverridesParser.create().parse_overrides(args)
              if not o.is_sweep_override() or o.is_discrete_sweep()]  # range/interval: the sweeper's search space
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def test_the_docs_document_commands():
    pages = {page for page, _ in documented_commands()}
    assert "README.md" in pages and len(documented_commands()) >= 30


@pytest.mark.parametrize("page,command", documented_commands(), ids=lambda v: v if len(v) < 60 else v[:60])
def test_every_documented_command_composes_and_validates(page, command):
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.validate import parse_config

    if "--help" in command:
        return
    for overrides in job_overrides(command):
        parse_config(load_config(overrides))  # a ConfigError fails the test, naming the setting


def test_the_settings_reference_is_what_the_schema_says():
    make = runpy.run_path(str(REPO / "docs" / "make_reference.py"))
    page = REPO / "docs" / "reference" / "settings.md"
    assert page.read_text() == make["settings_page"](), "run: python docs/make_reference.py"
    errors = REPO / "docs" / "reference" / "errors.md"
    assert errors.read_text() == make["errors_page"](), "run: python docs/make_reference.py"
    from nerfart_plugin.config.compose import settings_rows

    assert all(f"`{key}`" in page.read_text() for key, *_ in settings_rows())


def test_the_readme_is_short_and_user_pages_do_not_leak_the_development_machine():
    assert len((REPO / "README.md").read_text().splitlines()) <= 200
    for page in USER_PAGES:
        if "developers" in page.parts or "benchmarks" in page.parts:
            continue
        text = page.read_text()
        assert "../shared" not in text and "/work/" not in text, page
    for image in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (REPO / "README.md").read_text()):
        assert (REPO / image).is_file() and (REPO / image).stat().st_size > 1000, image


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("mkdocs") is None and not any(
    (Path(p) / "mkdocs").exists() for p in sys.path), reason="mkdocs is in the dev extra")
def test_the_documentation_site_builds_strictly(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={"NO_MKDOCS_2_WARNING": "1", **__import__("os").environ})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (tmp_path / "site" / "reference" / "settings" / "index.html").is_file()
