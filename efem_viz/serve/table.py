"""The instance tables of both apps, as viser can show them: viser 1.1 has no table widget, so a table is a
markdown table (one row per instance, an instance's colour as a swatch) beside a dropdown whose options name the
rows ("12: mug · 0.87") and buttons that act on the chosen row (visibility, fly-to, next / previous).

The annotator's instance list and pre-label review (`annotator.app`) and the viewer's instance table
(`efem_viz.viewer.app`) are built from these pieces. Pure string functions, no viser import.
"""

from __future__ import annotations

import html
from typing import Sequence

NO_ROW: str = "(none)"
"""The option a row dropdown shows while its table is empty."""


def swatch(color: Sequence[int]) -> str:
    """A square in an instance's colour, for a markdown cell (viser renders inline HTML in markdown).

    Args:
        color: (3,) RGB, 0-255.
    """
    r, g, b = (int(c) for c in color)
    return f'<span style="color:#{r:02x}{g:02x}{b:02x}">■</span>'


def cell(text: object) -> str:
    """Text from a file or a client, safe in a markdown table cell: HTML escaped (viser renders raw HTML in
    markdown), table pipes and markdown emphasis neutralised."""
    out = html.escape(str(text), quote=False)
    for ch in "\\|*_`[]":
        out = out.replace(ch, "\\" + ch)
    return out


def row_option(row_id: int, text: str) -> str:
    """A row dropdown's option: "<id>: <text>" (`option_id` reads the id back)."""
    return f"{int(row_id)}: {text}"


def option_id(option: str) -> int:
    """The row id of a dropdown option "12: mug 12".

    Raises:
        ValueError: the option names no row (e.g. `NO_ROW`).
    """
    head = str(option).split(":", 1)[0]
    if not head.strip().isdigit():
        raise ValueError("no instance selected")
    return int(head)


def option_for(options: Sequence[str], row_id: int) -> str:
    """The option of row `row_id` among `options` (the first option when none names it)."""
    for o in options:
        if o.split(":", 1)[0] == str(row_id):
            return o
    return options[0]


def step_row(ids: Sequence[int], current: int | None, step: int) -> int:
    """The row a Next (`step` = 1) / Previous (-1) button goes to: the one after / before `current` in `ids`,
    wrapping around; from no current row (or one no longer listed), the first / last row.

    Raises:
        ValueError: `ids` is empty.
    """
    ids = [int(i) for i in ids]
    if not ids:
        raise ValueError("the table is empty")
    if current is None or int(current) not in ids:
        return ids[0] if step > 0 else ids[-1]
    return ids[(ids.index(int(current)) + step) % len(ids)]
