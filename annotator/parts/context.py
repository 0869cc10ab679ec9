"""What the annotator session's parts share: the GUI hooks and the tool table with its settings."""

from __future__ import annotations

import logging
from typing import Any, Callable, Sequence

import numpy as np

from annotator.tools import Tool, ToolSettings, check_tools

log = logging.getLogger("annotator.session")


def _nothing(*_args: object) -> None:
    """The default hook: a session without a GUI draws nothing."""


def _log_errors(fn: Callable[[], Any]) -> Any:
    """The default `report`: run `fn`, log what fails."""
    try:
        return fn()
    except Exception:  # noqa: BLE001 - a background job of a headless session: log it
        log.exception("annotator job failed")
        return None


class SessionHooks:
    """The hooks a GUI sets on the session (a headless session leaves them doing nothing); the parts call them."""

    def __init__(self) -> None:
        self.on_change: Callable[[], None] = _nothing
        """The instance table or the active instance changed (redraw the panel)."""
        self.on_cursor: Callable[[], None] = _nothing
        """The brush cursor moved or changed (redraw it)."""
        self.on_lasso: Callable[[], None] = _nothing
        """The lasso outline changed."""
        self.on_preview: Callable[[np.ndarray], object] = _nothing
        """The segment preview or a running EFEM's overlay changed: (K,) int64 vertices to draw again."""
        self.on_segment: Callable[[float | None], None] = _nothing
        """Click-to-segment progress in percent (None: the run ended, or the preview changed)."""
        self.on_efem: Callable[[str | None, float | None], None] = _nothing
        """An EFEM run on the scan: what it is doing and its progress in percent (None, None: it ended)."""
        self.notify: Callable[[str, str], None] = lambda title, body: log.info("%s: %s", title, body)
        """Tell the user something (title, body)."""
        self.report: Callable[[Callable[[], Any]], Any] = _log_errors
        """Runs background work (the segment thread) so that its errors reach the user."""


class Toolbox:
    """The tool table and the settings the tools read (the active tool is `settings.tool`).

    Args:
        tools: the tool table (`annotator.tools.Tool` entries); the first is active.

    Raises:
        ValueError: the table is not valid (`annotator.tools.check_tools`).
    """

    def __init__(self, tools: Sequence[Tool]) -> None:
        self.tools: tuple[Tool, ...] = tuple(tools)
        """The tool table the toolbar, hotkeys, help and gestures read."""
        self.tool_of = check_tools(self.tools)
        """The tools by name."""
        self.settings = ToolSettings(tool=self.tools[0].name)
        """What the tools read (active tool, radius, instance, category, grow limits, ...)."""

    @property
    def tool(self) -> Tool:
        """The active tool's table entry."""
        return self.tool_of[self.settings.tool]
