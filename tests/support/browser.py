"""Headless Chromium for tests: Debian's ``chromium`` driven by Playwright (no browser download).

Skips the calling test with a message when Playwright or the browser is missing
(``GS_NO_BROWSER=1 ./bootstrap.sh`` leaves chromium out). The flags are the ones that work on
these machines (no sandbox as root, no GPU, no background networking: the network is closed);
WebGL/WebGPU run on the SwiftShader software rasterizer.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator

import pytest

CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",
]  # fmt: skip


def chromium_path() -> str:
    path = (
        os.environ.get("GS_CHROMIUM")
        or shutil.which("chromium")
        or shutil.which("chromium-browser")
    )
    if path is None:
        pytest.skip("no chromium on PATH (Debian package 'chromium'; ./bootstrap.sh installs it)")
    return path


@contextlib.contextmanager
def browser_page(width: int = 1280, height: int = 800) -> Iterator:
    """A Playwright page in a fresh headless Chromium (a new, empty profile)."""
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="playwright is not installed (pip install -e '.[dev]')"
    )
    exe = chromium_path()
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_FLAGS)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.set_default_timeout(120_000)  # software rendering on a shared, loaded machine
            yield page
        finally:
            browser.close()
