"""Execute ``notebooks/quickstart.ipynb`` as committed (its own parameters; results under a scratch folder) and
write what it printed and drew as the documentation page ``docs/guides/notebook.md``, its pictures under
``docs/images/notebook/``. The committed notebook stays without outputs; this page shows them.

    python docs/make_notebook_page.py          # a few minutes on a CPU
"""

from __future__ import annotations

import base64
import re
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "quickstart.ipynb"
PAGE = ROOT / "docs" / "guides" / "notebook.md"
IMAGES = ROOT / "docs" / "images" / "notebook"
#: lines of one text output kept on the page (the rest is elided)
MAX_TEXT_LINES = 25


def _text_of(output: dict[str, Any]) -> str:
    """What a user reads of one output: printed text and results; not the log lines and progress bars (stderr)."""
    if output.get("output_type") == "stream":
        return "".join(output.get("text", "")) if output.get("name") == "stdout" else ""
    data = output.get("data", {})
    return "".join(data.get("text/plain", "")) if "image/png" not in data else ""


#: a progress bar's line (tqdm / Lightning): "... | 10/300 [00:01<00:14, ...]" or "0/? [00:00<?, ?it/s]"
_PROGRESS = re.compile(r"\|.*\[\d+:\d+(<|\])")


#: terminal control sequences (colours, tqdm's cursor moves)
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _clip(text: str) -> str:
    lines = [ln for ln in _ANSI.sub("", text).strip("\n").splitlines() if not _PROGRESS.search(ln)]
    if len(lines) > MAX_TEXT_LINES:
        lines = lines[:MAX_TEXT_LINES] + [f"... ({len(lines) - MAX_TEXT_LINES} more lines)"]
    return "\n".join(lines)


def notebook_page(nb: Any, images: Path, scratch: str) -> str:
    """The Markdown page of the executed notebook ``nb``: its markdown cells, each code cell and what it printed
    (``scratch``, the run's output folder, shown as ``outputs/notebook``; paths in the checkout relative to it; the
    log lines and progress bars on stderr left out), its pictures written to ``images``."""
    images.mkdir(parents=True, exist_ok=True)
    rel = Path("..") / "images" / images.name
    lines = ["# The Python API, run: the quickstart notebook", "",
             "What `notebooks/quickstart.ipynb` prints and draws when it runs as committed (toy guidance, a few "
             "minutes on a CPU). This page is written by `python docs/make_notebook_page.py` from a real run.", ""]
    n_images = 0
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "markdown":
            lines += [cell.source, ""]
            continue
        if cell.cell_type != "code":
            continue
        lines += ["```python", cell.source, "```", ""]
        for output in cell.get("outputs", []):
            data = output.get("data", {})
            if "image/png" in data:
                n_images += 1
                name = f"cell{i:02d}_{n_images}.png"
                (images / name).write_bytes(base64.b64decode(data["image/png"]))
                lines += [f"![output of the cell above]({rel / name})", ""]
                continue
            text = _clip(_text_of(output).replace(scratch, "outputs/notebook").replace(str(ROOT) + "/", ""))
            if text.strip():
                lines += ["```text", text, "```", ""]
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    import nbclient
    import nbformat

    nb = nbformat.read(NOTEBOOK, as_version=4)
    with tempfile.TemporaryDirectory() as tmp:
        scratch = str(Path(tmp) / "outputs" / "notebook")
        nb.cells[0].source = nb.cells[0].source.replace('OUTPUT_ROOT = "outputs/notebook"', f"OUTPUT_ROOT = {scratch!r}")
        nbclient.NotebookClient(nb, timeout=1800, resources={"metadata": {"path": tmp}}).execute()
        nb.cells[0].source = nbformat.read(NOTEBOOK, as_version=4).cells[0].source  # the page shows the original
        for old in IMAGES.glob("*.png"):
            old.unlink()
        PAGE.write_text(notebook_page(nb, IMAGES, scratch))
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
