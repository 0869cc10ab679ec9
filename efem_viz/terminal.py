"""Text from outside (file and scene names, error messages) as the command line prints it.

A file name may hold any byte but `/` and NUL: an ESC sequence in one can clear the screen or recolour the
terminal, a newline or CR can fake a line of output, a bidirectional override can reorder what is shown. Rich
markup escaping does not cover these. `terminal_text` is the one such rule of the CLI output: the one-line error
messages (`efem_viz.cli.error_message`), the log lines of both command lines (`log_to_terminal`), the batch console,
`efem-viz info`, and the start-up lines of both servers. `console_text` adds rich-markup escaping for what goes
through a rich console.
"""

from __future__ import annotations

import logging
import unicodedata
from typing import Any

BIDI_CONTROLS = frozenset("\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")
"""Unicode bidirectional embedding, override and isolate characters (escaped like control characters)."""


def terminal_text(text: str) -> str:
    """`text` with control characters (ESC, newline, CR, backspace, DEL, C1 ...) and bidirectional overrides shown
    as Python escapes (`\\x1b`, `\\n`, `\\u202e`); everything else, non-ASCII letters included, unchanged.

    Args:
        text: any text, e.g. a scene file name.

    Returns:
        Text that prints as one inert line.
    """
    if text.isprintable():
        return text
    return "".join(c.encode("unicode_escape").decode("ascii")
                   if unicodedata.category(c) == "Cc" or c in BIDI_CONTROLS else c for c in text)


class TerminalFormatter(logging.Formatter):
    """A log formatter whose messages pass `terminal_text` (a scene name in a warning cannot reach the terminal
    raw); tracebacks (`--debug`, `logger.exception`) keep their lines."""

    def formatMessage(self, record: logging.LogRecord) -> str:  # noqa: N802 - logging's name
        return terminal_text(super().formatMessage(record))


LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"
"""The command lines' log line."""


def one_line(exc: BaseException, *, limit: int = 500) -> str:
    """An exception as one line, `Type: message` (whitespace collapsed, the message cut to `limit` characters):
    what every command, batch record and app notice says of an error."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:limit]}" if text else type(exc).__name__


def count(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and the noun in the number it needs: "1 object", "3 objects", "1,204 points" (the one plural rule
    of every count a person reads: GUI labels, captions, status lines)."""
    return f"{int(n):,} {noun if int(n) == 1 else (plural or noun + 's')}"


def console_text(text: object) -> str:
    """Text from outside (scene and file names, provenance strings, error messages) as a rich console prints
    it: `terminal_text` (control characters visible and inert), then rich markup escaped (a ``[red]`` in a
    name stays literal). Rich is imported here only when called."""
    from rich.markup import escape

    return escape(terminal_text(str(text)))


def log_to_terminal(level: int = logging.INFO) -> None:
    """Set up the root logger of a command-line program (`efem-viz`, `efem-annotate`): `LOG_FORMAT` on stderr through
    `TerminalFormatter`. Like `logging.basicConfig`, does nothing when the root logger already has handlers."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = logging.StreamHandler()
    handler.setFormatter(TerminalFormatter(LOG_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)


FILE_WIDTH = 200
"""Columns of tables written to a file or pipe (rich's default, 80, cut paths and wrapped rows)."""


def console(stream: Any = None) -> Any:
    """The rich `Console` the CLIs print tables with: the terminal's width on a terminal, `FILE_WIDTH` columns when
    the output goes to a file or a pipe (``COLUMNS`` in the environment still wins). rich is imported here, lazily.
    """
    import os
    import sys

    from rich.console import Console

    out = stream if stream is not None else sys.stdout
    wide = not (hasattr(out, "isatty") and out.isatty()) and "COLUMNS" not in os.environ
    return Console(file=stream, width=FILE_WIDTH if wide else None)
