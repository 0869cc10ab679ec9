"""Helpers shared by the real-browser tests (imported by the test modules next to this file)."""

from __future__ import annotations

import io
import time
from typing import Any, Callable, Sequence

import numpy as np

HANG_GUARD_S = 300.0
"""Every wait in the browser tests is a hang guard, not a speed check: 10x what the slowest of them took beside a
2-thread busy load (about 30 s for a page of the annotator to render a mesh in software)."""
HANG_GUARD_MS = int(HANG_GUARD_S * 1000)
"""`HANG_GUARD_S` for Playwright's timeouts (milliseconds)."""
SETTLE_S = 120.0
"""How long `settle` waits for two identical frames (it returns as soon as they agree)."""


def wait_until(cond: Callable[[], bool], timeout: float = HANG_GUARD_S, what: str = "condition") -> None:
    """Poll `cond` every 50 ms; fail the test with `what` in the message after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def on_view(client: Any, view: Any, atol: float = 1e-4) -> bool:
    """Whether a viser client's camera, as the server last heard it, sits on `view` (a `View`; None: False)."""
    return bool(view is not None and np.allclose(client.camera.look_at, view.look_at, atol=atol)
                and np.allclose(client.camera.position, view.position, atol=atol))


def png_to_array(png: bytes) -> np.ndarray:
    """(H, W, 3) int16 RGB of a PNG screenshot (signed, so differences do not wrap)."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def settle(grab: Callable[[], np.ndarray], page: Any, *, timeout: float = SETTLE_S) -> np.ndarray:
    """Screenshot until two consecutive shots agree (software rendering takes a few frames)."""
    prev = grab()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        page.wait_for_timeout(700)
        cur = grab()
        if cur.shape == prev.shape and np.abs(cur - prev).mean() < 0.05:
            return cur
        prev = cur
    return prev


def canvas_png(page: Any) -> np.ndarray:
    """(H, W, 3) int16 screenshot of the page's first canvas (the viser 3-D view)."""
    return png_to_array(page.locator("canvas").first.screenshot())


def settle_canvas(page: Any, *, timeout: float = SETTLE_S) -> np.ndarray:
    """Canvas screenshot once rendering has settled."""
    return settle(lambda: canvas_png(page), page, timeout=timeout)


def changed_mask(a: np.ndarray, b: np.ndarray, *, threshold: int = 60) -> np.ndarray:
    """(H, W) bool: pixels whose colour changed clearly (sum of |ΔRGB| > `threshold`)."""
    return np.abs(a - b).sum(axis=-1) > threshold


def open_viser_pages(pages: Sequence[Any], url: str, *, ready_text: str = "Tools", hide_notice: bool = True) -> None:
    """Open a viser app in several pages at once (they load in parallel) and wait, in each, for its GUI (a folder
    titled `ready_text`) and a sized canvas. With `hide_notice`, the "software WebGL rendering" notice of headless
    chromium is hidden (steady screenshots)."""
    for page in pages:
        page.goto(url, wait_until="commit")
    for page in pages:
        page.get_by_text(ready_text, exact=True).first.wait_for(timeout=HANG_GUARD_MS)
        page.wait_for_function(
            "Array.from(document.querySelectorAll('canvas')).some(c => c.width > 0 && c.height > 0)",
            timeout=HANG_GUARD_MS
        )
        if hide_notice:
            page.add_style_tag(content="#webgl-software-rendering { display: none !important; }")


def ctrl_drag(page: Any, start: tuple[float, float], end: tuple[float, float], *, moves: int = 12,
              steps: int = 2, pause_ms: int = 60) -> None:
    """A Ctrl+left-drag in page coordinates from `start` to `end` in `moves` moves (of `steps` mouse events each),
    pausing `pause_ms` between them so that viser's 20 Hz drag updates see intermediate points. Each mouse event
    waits for the page: with software rendering, fewer events make a much faster drag."""
    (x0, y0), (x1, y1) = start, end
    page.keyboard.down("Control")
    try:
        page.mouse.move(x0, y0)
        page.mouse.down()
        for k in range(1, moves + 1):
            t = k / moves
            page.mouse.move(x0 + t * (x1 - x0), y0 + t * (y1 - y0), steps=steps)
            page.wait_for_timeout(pause_ms)
        page.mouse.up()
    finally:
        page.keyboard.up("Control")
