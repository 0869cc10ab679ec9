"""Transitional: `efem-viz segment` moved to `efem_viz.batch.commands` (the CLI sits on top of the batch layer).

Kept only while `efem_viz/cli.py` still points `segment` here; delete this file once it names
`efem_viz.batch.commands:SegmentArgs`.
"""

from __future__ import annotations

from efem_viz.batch.commands import SegmentArgs

__all__ = ["SegmentArgs"]
