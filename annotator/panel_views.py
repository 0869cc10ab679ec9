"""What the annotator's panels show, computed from the label store: pure text and options, no viser.

`annotator.app.AnnotatorApp._refresh_panel` writes a `PanelView` into the GUI handles; the text is built here so
that it can be tested (and read) without a server.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Sequence

from annotator.labels import HistoryEntry, InstanceInfo, unreviewed_prelabels
from efem_viz.serve.table import cell as _md
from efem_viz.serve.table import swatch as _swatch

if TYPE_CHECKING:
    from annotator.store import LabelStore

NO_OPTIONS: tuple[str, ...] = ("(none)",)
"""Dropdown options while a list is empty (typed `str` so that the handles accept real options later)."""


class PanelView(NamedTuple):
    """The Instances, History and Files panels' content at one moment."""

    active_id: int
    """The active instance (the one asked for, or the last one when it is gone; 0 = none)."""
    options: tuple[str, ...]
    """The instance dropdowns' options ("id: name")."""
    prelabel_options: tuple[str, ...]
    """Unreviewed pre-labels, most confident first ("id: name · confidence")."""
    active: InstanceInfo | None
    """The active instance's row."""
    progress: float
    """Fraction of the vertices labelled."""
    table: str
    """Markdown: progress, per-category counts and the instance table."""
    history: str
    """Markdown: undo / redo counts and the last undo steps (`recent_steps`)."""


def undo_steps(stack: Sequence[HistoryEntry]) -> int:
    """Undo steps on a stack: adjacent deltas of one stroke group count once (what one Ctrl+Z undoes)."""
    steps = 0
    prev = None
    for d in stack:
        if not d.group or d.group != prev:
            steps += 1
        prev = d.group
    return steps


def recent_steps(stack: Sequence[HistoryEntry], n: int = 8) -> list[str]:
    """The last `n` undo steps of a stack, newest first: one line per step (what one Ctrl+Z undoes: a whole brush
    stroke), its newest edit's label and how many more edits it holds. Read from the undo stack itself, so the
    list survives a restart as undo does (the stack is rebuilt from the journal)."""
    out: list[str] = []
    i = len(stack) - 1
    while i >= 0 and len(out) < n:
        e, k = stack[i], 1
        while e.group and i - k >= 0 and stack[i - k].group == e.group:
            k += 1
        out.append(e.label + (f" (+{k - 1} more edit{'s' if k > 2 else ''} in this step)" if k > 1 else ""))
        i -= k
    return out


def panel_view(store: LabelStore, active_id: int) -> PanelView:
    """The panels' content for the store's labels (read under its lock).

    Args:
        store: the label store.
        active_id: the active instance id.
    """
    with store.lock:
        ls = store.labelset
        table = dict(ls.instances)
        counts = ls.counts()
        progress = ls.progress()
        n_undo, n_redo = undo_steps(ls.undo_stack), undo_steps(ls.redo_stack)
        history = recent_steps(ls.undo_stack)
        n = len(ls.labels)
    if active_id not in table:
        active_id = max(table) if table else 0
    opts = tuple(f"{k}: {v.name}" for k, v in table.items()) or NO_OPTIONS
    pre = tuple(f"{k}: {table[k].name} · {table[k].confidence:.2f}" for k in unreviewed_prelabels(table)) or NO_OPTIONS
    rows = ["| id | name | category | vertices | flags |", "|---:|---|---|---:|---|"]
    for k, v in table.items():
        flags = ("hidden " if not v.visible else "") + ("locked " if v.locked else "")
        if v.unreviewed:
            flags += f"pre-label {v.confidence:.2f}"
        mark = " ◀" if k == active_id else ""
        rows.append(f"| {k} {_swatch(v.color)}{mark} | {_md(v.name)} | {_md(v.category)} | "
                    f"{counts.get(k, 0):,} | {flags} |")
    per_cat: dict[str, list[tuple[int, tuple[int, int, int]]]] = {}
    for k, v in table.items():
        per_cat.setdefault(v.category, []).append((counts.get(k, 0), v.color))
    cats = " · ".join(f"{''.join(_swatch(col) for _, col in m)} {_md(c)}: {len(m)} "
                      f"({sum(c_ for c_, _ in m):,} vertices)" for c, m in per_cat.items())
    text = (f"**{100 * progress:.1f}%** of {n:,} vertices labelled"
            + (f"\n\nper category: {cats}" if cats else "") + "\n\n" + "\n".join(rows))
    hist = (f"{n_undo} undoable, {n_redo} redoable" + ("; the next undo takes back, newest first:" if history else "")
            + "\n\n" + "\n".join(f"- {_md(h)}" for h in history))
    return PanelView(active_id, opts, pre, table.get(active_id), progress, text, hist)


def status_markdown(store: LabelStore, work_dir: Path, *, last_edit_bytes: int, last_edit_ms: float) -> str:
    """Autosave state for the Files panel: problems first (an autosave failure, what a recovery could not
    restore)."""
    parts: list[str] = []
    if store.problem:
        parts.append(f"**⚠ {store.problem}**")
    if store.journal.broken:
        parts.append(f"**⚠ {store.journal.broken}**")
    rec = store.recovery
    if rec is not None:
        mark = ("Recovered" if rec.verified_complete else "**⚠ Recovered with losses**" if not rec.complete
                else "**⚠ Recovered, not everything verifiable**")
        parts.append(f"{mark} at start:  \n" + "  \n".join(rec.summary().splitlines()))
    parts.append(
        f"Autosave: `{store.label_path.name}` + journal in `{work_dir}`  \n"
        f"last edit: {last_edit_bytes / 1024:.0f} KiB sent, {last_edit_ms:.0f} ms"
    )
    return "\n\n".join(parts)
