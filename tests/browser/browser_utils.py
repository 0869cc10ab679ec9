"""Helpers shared by the real-browser tests (imported by the test modules next to this file)."""

from __future__ import annotations

import io
import time
from typing import Any, Callable

import numpy as np


def wait_until(cond: Callable[[], bool], timeout: float = 20.0, what: str = "condition") -> None:
    """Poll `cond` every 50 ms; fail the test with `what` in the message after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def png_to_array(png: bytes) -> np.ndarray:
    """(H, W, 3) int16 RGB of a PNG screenshot (signed, so differences do not wrap)."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def settle(grab: Callable[[], np.ndarray], page: Any, *, timeout: float = 15.0) -> np.ndarray:
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
