"""A headless browser on the viewer: what the tests, the viewer benchmark and the documentation's screenshot
use to see the page as a user sees it.

Playwright (PyPI) drives a Chromium installed by the system (Debian: ``apt-get install chromium``; it
cannot download its own here), with software WebGL so that it draws without a GPU.

    python -m nerfart_plugin.viewer.browser URL --screenshot viewer.png
"""

from __future__ import annotations

import argparse
import io
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
from PIL import Image

from nerfart_plugin.errors import NerfArtError

#: Chromium flags: software WebGL (SwiftShader), no sandbox (containers, CI)
CHROMIUM_ARGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox")
#: names a system Chromium goes by
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "chrome")


def find_chromium() -> Optional[str]:
    """The Chromium executable: ``$NERFART_CHROMIUM``, else the first of :data:`CHROMIUM_NAMES` on PATH."""
    explicit = os.environ.get("NERFART_CHROMIUM")
    if explicit:
        return explicit if Path(explicit).is_file() else None
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


def missing_browser() -> Optional[str]:
    """Why no browser can be driven here (None: one can)."""
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install playwright)"
    if find_chromium() is None:
        return "no Chromium found (apt-get install chromium, or set NERFART_CHROMIUM to its executable)"
    return None


class BrowserPage:
    """One headless Chromium tab on ``url`` (a context manager).

    Args:
        url: the viewer's address; size: the window (width, height) in pixels.
    """

    def __init__(self, url: str, size: tuple[int, int] = (1200, 800), browser: Any = None) -> None:
        self.url, self.size = url, size
        self._pw: Any = None
        self._own = browser is None
        self.browser: Any = browser
        self.page: Any = None

    def __enter__(self) -> "BrowserPage":
        if self._own:
            from playwright.sync_api import sync_playwright

            why = missing_browser()
            if why:
                raise NerfArtError(f"cannot open a browser: {why}.")
            self._pw = sync_playwright().start()
            self.browser = self._pw.chromium.launch(executable_path=find_chromium(), args=list(CHROMIUM_ARGS))
        self.page = self.browser.new_page(viewport={"width": self.size[0], "height": self.size[1]})
        self.page.goto(self.url)
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self._own:
            self.page.close()
            return
        if self.browser is not None:
            self.browser.close()
        if self._pw is not None:
            self._pw.stop()

    def new_tab(self, url: Optional[str] = None, size: Optional[tuple[int, int]] = None) -> "BrowserPage":
        """Another tab of the same browser (a context manager that closes only that tab)."""
        return BrowserPage(url or self.url, size or self.size, browser=self.browser)

    # ---- what a user does
    def drag(self, dx: int, dy: int = 0, start: Optional[tuple[int, int]] = None) -> None:
        """Drag the mouse over the 3D view (orbits the camera), ``dx`` / ``dy`` pixels."""
        x, y = start or (self.size[0] // 3, self.size[1] // 2)
        self.page.mouse.move(x, y)
        self.page.mouse.down()
        self.page.mouse.move(x + dx, y + dy, steps=12)
        self.page.mouse.up()

    def click(self, name: str) -> None:
        """Click the button labelled ``name``."""
        self.page.get_by_role("button", name=name).first.click()

    def check(self, label: str) -> None:
        """Click the checkbox labelled ``label`` (ticks or clears it)."""
        self.page.get_by_role("checkbox", name=label).first.click()

    def open_folder(self, label: str) -> None:
        """Expand the collapsed panel folder ``label``."""
        self.page.get_by_text(label, exact=True).first.click()

    def slider_key(self, label_hint: str, key: str, times: int = 1) -> None:
        """Press ``key`` (Home, End, ArrowLeft, ...) on the slider whose panel row holds ``label_hint``."""
        row = self.page.locator("div", has_text=label_hint).locator("[role=slider]").first
        row.focus()
        for _ in range(times):
            self.page.keyboard.press(key)

    def fill_number(self, label: str, value: str) -> None:
        """Type ``value`` into the number field labelled ``label``."""
        box = self.page.get_by_label(label, exact=True).first
        box.fill(value)
        box.press("Enter")

    def screenshot(self, path: Optional[Path] = None) -> Any:
        """The page as an [H,W,3] uint8 array (and a PNG at ``path``)."""

        png = self.page.screenshot(path=str(path) if path else None)
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def wait_for(condition: Any, timeout: float = 30.0, every: float = 0.05) -> bool:
    """Poll ``condition()`` until it is true or ``timeout`` seconds pass; its last value."""
    t0 = time.time()
    while not condition():
        if time.time() - t0 > timeout:
            return bool(condition())
        time.sleep(every)
    return True


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m nerfart_plugin.viewer.browser",
                                description="Open a running viewer in a headless Chromium and save a screenshot.")
    p.add_argument("url")
    p.add_argument("--screenshot", type=Path, required=True)
    p.add_argument("--wait", type=float, default=5.0, help="seconds to let the frames refine first")
    p.add_argument("--size", type=int, nargs=2, default=(1200, 800), metavar=("W", "H"))
    args = p.parse_args(argv)
    try:
        with BrowserPage(args.url, tuple(args.size)) as page:
            time.sleep(args.wait)
            page.screenshot(args.screenshot)
    except NerfArtError as exc:
        p.exit(2, f"error: {exc}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
