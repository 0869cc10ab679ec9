"""efem-viz: see and fix object segmentation of scanned scenes (EFEM + viser viewer + annotator)."""

from __future__ import annotations

__version__ = "0.1.0"
