"""notebooks/quickstart.ipynb runs end to end (tiny settings injected into its parameters cell)."""

from __future__ import annotations

import base64
from pathlib import Path

import pytest
from pipeline_helpers import TINY_TOY

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "notebooks" / "quickstart.ipynb"


def _kernel_name() -> str:
    """The notebook's kernel if installed, else any Python kernel; skip only when none exists."""
    from jupyter_client.kernelspec import KernelSpecManager

    specs = (
        KernelSpecManager().find_kernel_specs()
    )  # includes ipykernel's own python3 when importable
    if not specs:
        pytest.skip(
            "no Jupyter kernel found: pip install ipykernel && python -m ipykernel install --user"
        )
    return "python3" if "python3" in specs else min(specs)


def _parameters_cell(nb) -> int:
    idx = [
        i
        for i, c in enumerate(nb.cells)
        if "parameters" in c.get("metadata", {}).get("tags", [])
    ]
    assert idx == [0], "the first cell must be the only one tagged 'parameters'"
    return idx[0]


def test_notebook_structure():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    src = nb.cells[_parameters_cell(nb)].source
    for name in ("OUTPUT_ROOT", "DATA_PATH", "PROMPT", "GUIDANCE", "OVERRIDES"):
        assert f"{name} =" in src
    assert 'GUIDANCE = "toy"' in src  # runs anywhere by default
    text = "\n".join(c.source for c in nb.cells)
    assert (
        "from nerfart_plugin.config.compose import load_config" in text
        and "from nerfart_plugin.run.pipeline import Pipeline" in text
        and "from nerfart_plugin.api import open_run" in text
        and "._" not in text  # the public API only
    )
    assert (
        "render_meshes" in text and 'GUIDANCE = "clip"' in text
    )  # the markdown says how to switch
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), (
        "commit the notebook without outputs"
    )


def _images(nb) -> int:
    n = 0
    for c in nb.cells:
        for out in c.get("outputs", []):
            data = out.get("data", {})
            if "image/png" in data:
                assert base64.b64decode(data["image/png"])[:8] == b"\x89PNG\r\n\x1a\n"
                n += 1
    return n


@pytest.mark.slow
def test_notebook_executes(tmp_path):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    out = tmp_path / "out"
    nb.cells[_parameters_cell(nb)].source = "\n".join(
        [
            f"OUTPUT_ROOT = {str(out)!r}",
            "DATA_PATH = None",
            'PROMPT = "red, Fauvism"',  # a comma: must not be split by Hydra's override parser
            'GUIDANCE = "toy"',
            'BACKBONE = "volsdf"',
            'DEVICE = "cpu"',
            f"OVERRIDES = {[o for o in TINY_TOY if not o.startswith(('guidance=', 'backbone='))]!r}",
            "SCREENSHOT_SIZE = (240, 120)",
        ]
    )
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name=_kernel_name(),
        resources={"metadata": {"path": str(tmp_path)}},
    )
    client.execute()
    errors = [
        o
        for c in nb.cells
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors, errors
    recon = list((out / "reconstructions").iterdir())
    styl = list((out / "stylizations").iterdir())
    assert len(recon) == 1 and len(styl) == 1
    assert styl[0].name.startswith("red_Fauvism-volsdf-") and styl[0].name.endswith(
        "_UNSTYLED-toy"
    )
    assert (recon[0] / "final.ckpt").is_file() and (
        recon[0] / "mesh" / "source.ply"
    ).is_file()
    assert (styl[0] / "mesh" / "source.ply").is_file()
    assert len(list((styl[0] / "mesh").glob("stylized*.ply"))) == 1
    assert list((styl[0] / "renders").glob("*.png")) and list(
        styl[0].glob("video*.mp4")
    )
    assert (styl[0] / "video_frames.png").is_file()
    shot = out / "notebook_meshes.png"
    assert shot.is_file()
    import imageio.v3 as iio

    img = iio.imread(shot)
    assert img.shape[:2] == (120, 240) and img[..., :3].std() > 5  # not blank
    assert (out / "notebook_api_views.png").is_file() and (out / "api_render" / "rgb_UNSTYLED-toy.mp4").is_file()
    # validation render, stylization render, video strip, mesh screenshot, the API's new view
    assert _images(nb) == 5


def test_the_notebook_page_shows_code_text_and_pictures(tmp_path):
    """``docs/make_notebook_page.py`` turns an executed notebook into the docs page: markdown as is, each code
    cell, its text (the scratch output folder shown as outputs/notebook, long text elided) and its pictures."""
    import runpy

    make = runpy.run_path(str(REPO / "docs" / "make_notebook_page.py"))
    png = base64.b64encode(b"\x89PNG\r\n\x1a\nfake").decode()
    nb = nbformat.v4.new_notebook(cells=[
        nbformat.v4.new_markdown_cell("## A heading"),
        nbformat.v4.new_code_cell("print(run_dir)", outputs=[
            nbformat.v4.new_output("stream", name="stdout", text="/tmp/x/outputs/notebook/stylizations/a\n"),
            nbformat.v4.new_output("display_data", data={"image/png": png, "text/plain": "<Image>"}),
            nbformat.v4.new_output("stream", name="stdout", text="\n".join(map(str, range(40)))),
            nbformat.v4.new_output("stream", name="stderr", text="INFO a log line\nEpoch 0: 10%|#"),
            nbformat.v4.new_output("stream", name="stdout", text="\nEpoch 0:   3%|  | 10/300 [00:00<00:17, 16.6it/s]"),
            nbformat.v4.new_output("stream", name="stdout", text="\x1b[A\n")]),
    ])
    page = make["notebook_page"](nb, tmp_path / "notebook", "/tmp/x/outputs/notebook")
    assert "## A heading" in page and "```python\nprint(run_dir)\n```" in page
    assert "outputs/notebook/stylizations/a" in page and "/tmp/x" not in page
    assert "![output of the cell above](../images/notebook/cell01_1.png)" in page
    assert (tmp_path / "notebook" / "cell01_1.png").read_bytes().startswith(b"\x89PNG") and "<Image>" not in page
    assert "... (15 more lines)" in page and "INFO a log line" not in page and "it/s" not in page and "[A" not in page


def test_the_committed_notebook_page_is_complete():
    """``docs/guides/notebook.md`` shows every code cell of the committed notebook and its pictures exist."""
    import re

    page = REPO / "docs" / "guides" / "notebook.md"
    text = page.read_text()
    for cell in nbformat.read(NOTEBOOK, as_version=4).cells:
        if cell.cell_type == "code":
            assert cell.source in text, "run: python docs/make_notebook_page.py"
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(images) >= 4 and all((page.parent / i).is_file() for i in images)

