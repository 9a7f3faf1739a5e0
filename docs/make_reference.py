"""Write ``docs/reference/settings.md`` from the typed config (``nerfart_plugin.config.schema``), the one source of
every setting, its default and its meaning, and ``docs/reference/errors.md`` from the error classes
(``nerfart_plugin.errors``): ``python docs/make_reference.py``. ``tests/test_docs.py`` fails when a committed
page is not what this script writes."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "reference" / "settings.md"
ERRORS_PAGE = ROOT / "docs" / "reference" / "errors.md"


def settings_page() -> str:
    from nerfart_plugin.config.compose import settings_rows

    lines = ["# Settings reference", "",
             "Every setting of the sections with fixed keys, generated from the typed config "
             "(`nerfart_plugin/config/schema.py`; `python docs/make_reference.py` rewrites this page). Set any of them on "
             "the command line (`render.num_samples=64`) or in a config group. The settings of each data loader, "
             "backbone, encoding, guide and perceptual network are listed at the end of this page; "
             "`python -m nerfart_plugin backbone=neus --cfg job` prints a composed config with its defaults.", "",
             "*Cache key*: whether the setting changes results, so that a run with another value is computed "
             "anew (no: it only changes where outputs go, how often a run logs or saves, or memory)."]
    section = None
    for key, default, text, cached in settings_rows():
        head = key.split(".")[0] if "." in key else "run"
        if head != section:
            section = head
            title = "Top-level keys" if head == "run" else f"`{head}`"
            lines += ["", f"## {title}", "", "| setting | default | meaning | cache key |", "|---|---|---|:-:|"]
        cell = text.replace("|", "\\|")
        lines.append(f"| `{key}` | `{default}` | {cell} | {'yes' if cached else 'no'} |")
    return "\n".join(lines + component_lines()) + "\n"


#: the component sections whose settings are declared beside each component: (kind, title, what the key picks)
COMPONENT_KINDS = (("data", "the scene loaders", "`data=<name>` picks the loader (`data.name`); besides `data.path`, "
                    "`data.ndc`, `data.background_color` and `data.subject`, each takes the settings below."),
                   ("backbone", "the fields", "`backbone=<name>` picks the field."),
                   ("encoding", "the position encodings", "`encoding=<name>` picks the encoding (the view "
                    "directions' `backbone.dir_encoding` takes the same settings)."),
                   ("guidance", "the guides", "`guidance=<name>` picks the guide; its settings are the section's, "
                    "next to the keys every guide has: `guidance.allow_random_weights`, `guidance.allow_download` "
                    "and the section `guidance.perceptual`."),
                   ("perceptual", "the feature networks of Eq. 9", "`guidance.perceptual.name=<name>` (or "
                    "`guidance.perceptual=<name>`, with that network's defaults) picks one (default: the guide's own "
                    "choice); its settings are the section's."))


def component_lines() -> list[str]:
    """One table per registered loader, backbone and encoding, from the typed ``Config`` beside each."""
    from nerfart_plugin.config import registry
    from nerfart_plugin.config.components import config_of
    from nerfart_plugin.config.compose import settings_rows

    lines: list[str] = []
    for kind, title, intro in COMPONENT_KINDS:
        lines += ["", f"## `{kind}`: {title}", "", f"{intro} Each is declared beside its component, in its `Config`."]
        for name in registry.names(kind):
            config = config_of(registry.get(kind, name))
            doc = (config.__doc__ or registry.get(kind, name).__doc__ or "").strip().split("\n\n")[0]
            head = f"guidance.perceptual.name={name}" if kind == "perceptual" else f"{kind}={name}"
            lines += ["", f"### `{head}`", "", " ".join(doc.split()).replace("``", "`"), "",
                      "| setting | default | meaning | cache key |", "|---|---|---|:-:|"]
            prefix = f"{config.section}." if kind in ("guidance", "perceptual") else f"{kind}."
            for key, default, text, cached in settings_rows(config, prefix):
                cell = text.replace("|", "\\|")
                lines.append(f"| `{key}` | `{default}` | {cell} | {'yes' if cached else 'no'} |")
    return lines


def errors_page() -> str:
    from nerfart_plugin.errors import CATALOGUE

    lines = ["# Error catalogue", "",
             "Every error the package raises on purpose, generated from `nerfart_plugin/errors.py` "
             "(`python docs/make_reference.py` rewrites this page). `python -m nerfart_plugin` prints the message "
             "(it names the file or setting and the fix) and exits with the code below, never with a traceback; "
             "from Python they are exceptions of these classes (all subclasses of `NerfArtError`)."]
    for cls in CATALOGUE:
        doc = " ".join((cls.__doc__ or "").split())
        lines += ["", f"## `{cls.__name__}`", "", f"{doc} Exit code {cls.exit_code}.", "",
                  "| typical cause | what to do |", "|---|---|"]
        lines += [f"| {cause} | {fix} |" for cause, fix in cls.causes]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    PAGE.parent.mkdir(parents=True, exist_ok=True)
    PAGE.write_text(settings_page())
    ERRORS_PAGE.write_text(errors_page())
    print(f"wrote {PAGE} and {ERRORS_PAGE}")
