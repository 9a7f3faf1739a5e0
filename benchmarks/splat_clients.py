"""Real splat clients from npm, driven from Python: PlayCanvas' ``splat-transform`` (Node) and Spark (a three.js
splat renderer) in headless Chromium. The splat tests and the splat benchmark check the exported ``.ply`` with them.

:func:`install_clients` installs the pinned packages once into a cache folder (``NERFART_NPM_CACHE``, default
``~/.cache/nerfart_plugin/npm``); :func:`splat_transform` runs the converter; :func:`spark_screenshot` draws a
``.ply`` from one camera with Spark and returns the picture.
"""

from __future__ import annotations

import functools
import http.server
import json
import os
import shutil
import subprocess
import threading
import urllib.parse
from pathlib import Path
from typing import Optional

import numpy as np

#: the clients, pinned
NPM_PACKAGES = ("@playcanvas/splat-transform@3.10.2", "@sparkjsdev/spark@2.2.0", "three@0.180.0")
PAGE = Path(__file__).resolve().parent / "spark_page.html"


def missing_node() -> Optional[str]:
    """Why the npm clients cannot run here (None: they can)."""
    if shutil.which("npm") is None or shutil.which("node") is None:
        return "no npm / node here: the splat clients need them"
    return None


def install_clients(root: Optional[Path] = None) -> Path:
    """The folder holding ``node_modules`` with :data:`NPM_PACKAGES`, installed there the first time."""
    root = Path(root or os.environ.get("NERFART_NPM_CACHE", Path.home() / ".cache" / "nerfart_plugin" / "npm"))
    marker = root / ("installed-" + "-".join(p.replace("/", "_") for p in NPM_PACKAGES))
    if not marker.exists():
        root.mkdir(parents=True, exist_ok=True)
        (root / "package.json").write_text('{"name": "nerfart-splat-clients", "private": true}\n')
        subprocess.run([str(shutil.which("npm")), "install", "--no-audit", "--no-fund", "--ignore-scripts",
                        *NPM_PACKAGES], cwd=root, check=True, capture_output=True, timeout=600)
        marker.touch()
    return root


def splat_transform(clients: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``splat-transform ARGS`` (its exit status and output; not checked)."""
    tool = clients / "node_modules" / ".bin" / "splat-transform"
    return subprocess.run([str(tool), *args], capture_output=True, text=True, timeout=timeout)


def gl_matrix(c2w: np.ndarray) -> np.ndarray:
    """A camera-to-world [3,4] of OpenCV axes as the 4x4 of three.js (OpenGL axes: y up, looking along -z)."""
    m = np.eye(4)
    m[:3, :4] = c2w
    m[:3, 1:3] *= -1
    return m


def gl_projection(K: np.ndarray, W: int, H: int, near: float = 0.01, far: float = 1000.0) -> np.ndarray:
    """The OpenGL projection of pinhole intrinsics K [3,3] at W x H (principal point off centre included)."""
    return np.array([[2 * K[0, 0] / W, 0, 1 - 2 * K[0, 2] / W, 0], [0, 2 * K[1, 1] / H, 2 * K[1, 2] / H - 1, 0],
                     [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)], [0, 0, -1, 0]])


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # noqa: D102
        pass


def spark_screenshot(clients: Path, ply: Path, c2w: np.ndarray, K: np.ndarray, W: int, H: int) -> np.ndarray:
    """[H,W,3] in [0, 1]: Spark's picture of ``ply`` from the camera ``c2w`` [3,4] (OpenCV axes, the file's
    frame) with intrinsics ``K`` [3,3] at W x H, on white, in headless Chromium (software WebGL)."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    from nerfart_plugin.viewer.browser import CHROMIUM_ARGS, find_chromium

    page_dir = clients / f"page-{os.getpid()}"
    page_dir.mkdir(exist_ok=True)
    shutil.copy(PAGE, page_dir / "index.html")
    shutil.copy(ply, page_dir / "splats.ply")
    cam = {"matrix": gl_matrix(c2w).T.reshape(-1).tolist(), "projection": gl_projection(K, W, H).T.reshape(-1).tolist()}
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(clients)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    shot = page_dir / "spark.png"
    try:
        url = (f"http://127.0.0.1:{server.server_address[1]}/{page_dir.name}/index.html?w={W}&h={H}"
               f"&url=/{page_dir.name}/splats.ply&cam=" + urllib.parse.quote(json.dumps(cam)))
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=find_chromium(), args=list(CHROMIUM_ARGS))
            page = browser.new_page(viewport={"width": W, "height": H})
            page.goto(url)
            page.wait_for_function("window.__status && window.__status !== 'loading'", timeout=180_000)
            status = page.evaluate("window.__status")
            if status != "done":
                raise RuntimeError(f"Spark could not draw {ply}: {status}")
            page.locator("canvas").screenshot(path=str(shot))
            browser.close()
        return np.asarray(Image.open(shot).convert("RGB"), dtype=np.float64) / 255
    finally:
        server.shutdown()
        shutil.rmtree(page_dir, ignore_errors=True)
