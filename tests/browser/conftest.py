"""Shared real-browser fixtures (Debian chromium driven by Python playwright; never `playwright install`).

Fixture names are stable and used by the viewer and annotator browser tests:

* `browser` — session-scoped playwright `Browser` (headless chromium, software WebGL via SwiftShader).
* `page` — a fresh `Page` (own context, 1280x800) per test, closed afterwards.
* `new_page` — a factory for more such pages (one browser context each, like separate tabs of separate users);
  all are closed after the test.

Tests using them must be marked `@pytest.mark.browser`. Everything skips cleanly (with the reason) when
playwright or /usr/bin/chromium is missing.
"""

from __future__ import annotations

import os
import shutil
from typing import Any, Callable, Iterator

import pytest
from browser_utils import HANG_GUARD_MS

CHROMIUM_PATH = os.environ.get("EFEM_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
VIEWPORT = {"width": 1280, "height": 800}


def _chromium_available() -> str | None:
    """Return a skip reason, or None when a browser can be launched."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        return f"playwright not importable: {exc}"
    if not (os.path.exists(CHROMIUM_PATH) or shutil.which(CHROMIUM_PATH)):
        return f"chromium not found at {CHROMIUM_PATH} (set EFEM_CHROMIUM)"
    return None


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    """A headless chromium `playwright.sync_api.Browser`, shared by all tests of the session."""
    reason = _chromium_available()
    if reason is not None:
        pytest.skip(reason)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM_PATH, headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture()
def page(browser: Any) -> Iterator[Any]:
    """A fresh page in its own browser context (1280x800 viewport); closed after the test."""
    context = browser.new_context(viewport=VIEWPORT)
    pg = context.new_page()
    pg.set_default_timeout(HANG_GUARD_MS)
    try:
        yield pg
    finally:
        context.close()


@pytest.fixture()
def new_page(browser: Any) -> Iterator[Callable[..., Any]]:
    """Call it for another fresh page in its own browser context (1280x800, or `viewport={"width": .., "height":
    ..}`: smaller pages render faster in software); all are closed after the test."""
    contexts: list[Any] = []

    def make(viewport: dict[str, int] | None = None) -> Any:
        context = browser.new_context(viewport=viewport or VIEWPORT)
        contexts.append(context)
        pg = context.new_page()
        pg.set_default_timeout(HANG_GUARD_MS)
        return pg

    try:
        yield make
    finally:
        for context in contexts:
            context.close()
