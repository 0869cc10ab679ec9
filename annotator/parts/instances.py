"""The instances part: the active tool and the instance table (create, change, delete, merge, undo, redo)."""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

from annotator.labels import Delta
from annotator.tools import RADIUS, all_controls
from annotator.typing_buffer import TEXT_IDLE_S, TypingBuffer

LATE_KEYS_S = 1.0
"""A browser sends a text field's keystrokes and a hotkey on separate paths: the last keys of a name can reach the
server after the N that followed them. Keys of a field this soon after its value was committed by an action go to
the instance it was committed to, not to the one the action made active."""
LATE_CONTINUATION_S = 15.0
"""On a busy server (an EFEM run beside the typing) the trailing keys can come later than `LATE_KEYS_S`: a value
that only adds characters to the one just committed still goes to that instance this long after, unless it also
adds to the newly active instance's own stored value (a new instance takes the category typed last, and editing
it continues both). Typing for the newly active instance starts from the field as the panel then shows it."""

TYPING_FILE = "typing.json"
"""In the work folder: the value of a Name / Category field being typed and not committed yet, written at every
keystroke (a kill between a keystroke and its commit loses nothing: the next start commits it)."""
MAX_TYPED_CHARS = 256
"""Longest name or category the typing file may hold (a longer one is not restored)."""

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart
    from annotator.parts.cursor import CursorPart


class InstancePart:
    """Which tool and which instance are active, and every undoable change of the instance table."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks, brush: CursorPart, *,
                 text_idle_s: float = TEXT_IDLE_S) -> None:
        self.scan, self.toolbox, self.hooks, self.brush = scan, toolbox, hooks, brush
        self.late_keys_s = LATE_KEYS_S
        """Keystrokes this soon after a field was committed belong to the instance it was committed to."""
        self.late_continuation_s = LATE_CONTINUATION_S
        """Keystrokes that only add to the value a field was committed with belong to its instance this long."""
        self._committed: dict[str, tuple[int, float, str]] = {}
        """By field: the instance, time and value of its last commit."""
        self.typing = TypingBuffer(self._commit_text, on_error=lambda msg: self.hooks.notify("Not done", msg),
                                   idle_s=text_idle_s, on_idle=lambda: self.hooks.on_change())
        """The Name and Category fields being typed (each committed once: `type_text`, `flush_typing`)."""
        self._typing_file_lock = threading.Lock()
        self._text_group: tuple[tuple[int, str], str] | None = None
        """The field the last typed commit went to and its undo group: a later commit to the same field with no
        other edit between joins it, so slow typing is one undo step."""
        self.restored_typing: str | None = self._restore_typing()
        """What `_restore_typing` committed at start (a notice for the person), or None."""

    # ------------------------------------------------------------------ typed fields
    def type_text(self, field: Literal["name", "category"], value: str) -> None:
        """A keystroke in the active instance's Name or Category field: committed once, when the field is left
        alone (`TEXT_IDLE_S`) or the person does anything else (`flush_typing`), to the instance that was active
        when it was typed."""
        if field not in ("name", "category"):
            raise ValueError(f"no text field {field!r}")
        iid = self._typed_for(field, value.strip())
        with self._typing_file_lock:
            self.typing.typed((iid, field), value)
            self._write_typing_file(int(iid), field, value)

    def _typed_for(self, field: str, text: str) -> int:
        """The instance a keystroke's value `text` (stripped) belongs to: the active one, unless it is a trailing
        key of a typing for another instance that an action (N, a click) interrupted. Such keys arrive after the
        action and only add characters to what that instance's field was given: to the value committed by the
        action (within `late_keys_s` any value, within `late_continuation_s` a continuation), or to a trailing
        value already waiting for that instance. A continuation of the active instance's own stored value stays
        with it (a new instance can start with the other's category), and so does anything for an instance that
        no longer exists."""
        active = self.toolbox.settings.active_id
        instances = self.scan.store.labelset.instances

        def stored(i: int) -> str:
            info = instances.get(i)
            return str(getattr(info, field, "") or "") if info is not None else ""

        def extends(base: str) -> bool:
            return bool(base) and len(text) > len(base) and text.startswith(base)

        own = extends(stored(active))
        pending = [(cast("tuple[int, str]", k)[0], v.strip()) for k, v in self.typing.pending().items()
                   if cast("tuple[int, str]", k)[1] == field]
        if pending:  # a typing of this field is waiting: its next keys are for the same instance
            for other, waiting in pending:
                if other != active and other in instances and extends(waiting) and not own:
                    return other
            return active
        last = self._committed.get(field)
        if last is None or last[0] not in instances:
            return active
        age = time.monotonic() - last[1]
        if age < self.late_keys_s or (extends(last[2]) and not own and age < self.late_continuation_s):
            return last[0]  # the last keys of a typing that an action committed, arriving after that action
        return active

    @property
    def typing_file(self) -> Path:
        """`<work folder>/typing.json` (`TYPING_FILE`)."""
        return self.scan.work_dir / TYPING_FILE

    def _write_typing_file(self, iid: int, field: str, value: str) -> None:
        from efem_viz.data.io import atomic_write_text

        try:
            atomic_write_text(self.typing_file, json.dumps({"instance": iid, "field": field, "value": value}))
        except OSError as exc:  # the buffer still commits it; only a kill before then would lose it
            log.warning("could not keep the typed %s in %s (%s)", field, self.typing_file, exc)

    def _drop_typing_file(self) -> None:
        with self._typing_file_lock:
            if not self.typing.pending():
                self.typing_file.unlink(missing_ok=True)

    def _restore_typing(self) -> str | None:
        """Commit a value typed just before the annotator stopped (its `typing.json`), once; returns a notice."""
        path = self.typing_file
        try:
            if not path.is_file():
                return None
            if path.stat().st_size > 4 * MAX_TYPED_CHARS + 200:
                raise ValueError("file too large")
            d = json.loads(path.read_text(encoding="utf-8"))
            iid, field, value = int(d["instance"]), str(d["field"]), str(d["value"]).strip()
            if field not in ("name", "category") or not value or len(value) > MAX_TYPED_CHARS:
                raise ValueError(f"unusable field {field!r} / value")
            if iid not in self.scan.store.labelset.instances:
                raise ValueError(f"instance {iid} no longer exists")
            if getattr(self.scan.store.labelset.info(iid), field) != value:
                self.update_instance(iid, **{field: value})
                return f"the {field} {value!r} of instance {iid}, typed just before the annotator stopped, is saved"
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("typed value in %s not restored (%s)", path, exc)
            return None
        finally:
            path.unlink(missing_ok=True)

    def flush_typing(self, *, refresh: bool = True) -> int:
        """Commit what was typed now (before any other action); returns the number of fields that were pending
        (committed, or refused with a notice). With `refresh`, the panels are told to show the stored values; an
        action that flushes first refreshes after it has read its own control instead."""
        n = self.typing.flush()
        if n and refresh:
            self.hooks.on_change()
        return n

    def fields_typing(self) -> frozenset[str]:
        """The fields whose typed value is not committed yet (the panels leave them as the person typed them)."""
        return frozenset(cast("tuple[int, str]", key)[1] for key in self.typing.pending())

    def _commit_text(self, key: object, value: str) -> None:
        iid, field = cast("tuple[int, str]", key)
        text = value.strip()
        try:
            if field == "category":
                if not text:
                    raise ValueError("a category cannot be empty; the stored one is kept")
                self.toolbox.settings.category = text
            elif not text:
                raise ValueError("a name cannot be empty; the stored one is kept")
            self._committed[field] = (int(iid), time.monotonic(), text)
            if iid > 0 and iid in self.scan.store.labelset.instances:
                stack = self.scan.store.labelset.undo_stack
                key2 = (int(iid), field)
                group = (self._text_group[1] if self._text_group is not None and self._text_group[0] == key2
                         and stack and stack[-1].group == self._text_group[1] else f"type-{uuid.uuid4().hex[:12]}")
                self._text_group = (key2, group)
                self.scan.store.do(lambda ls: ls.update_instance(int(iid), **{field: text}), group=group)
        finally:
            self._drop_typing_file()

    def set_tool(self, tool: str) -> None:
        """Make a tool of the table active."""
        if tool not in self.toolbox.tool_of:
            raise ValueError(f"unknown tool {tool!r}; tools: {tuple(self.toolbox.tool_of)}")
        self.toolbox.settings.tool = tool
        self.brush.refresh_cursor()

    def set_active(self, instance_id: int) -> None:
        """Make an instance the one brushes paint."""
        self.scan.store.labelset.info(instance_id)  # KeyError when unknown
        self.toolbox.settings.active_id = int(instance_id)
        self.hooks.on_change()

    def cycle_active(self, step: int = 1) -> int:
        """Make the next (`step` = 1) or previous (-1) instance by id active, wrapping around; returns its id.

        Raises:
            ValueError: there is no instance yet.
        """
        ids = sorted(self.scan.store.labelset.instances)
        if not ids:
            raise ValueError("no instances yet: N creates one")
        current = self.toolbox.settings.active_id
        if current in ids:
            nxt = ids[(ids.index(current) + step) % len(ids)]
        else:  # none active (or it was deleted): start at the first (last going back)
            nxt = ids[0] if step > 0 else ids[-1]
        self.set_active(nxt)
        return nxt

    def resize_brush(self, factor: float) -> float:
        """Multiply the brush radius by `factor` (the `[` / `]` keys), by at least one step of its slider and within
        the slider's range. Returns the radius in metres."""
        control = next((c for c in all_controls(self.toolbox.tools) if c.setting == "radius"), RADIUS)
        shown = self.toolbox.settings.radius * control.scale
        target = shown * float(factor)
        snapped = round(round(target / control.step) * control.step, 6)
        if factor > 1.0:
            snapped = max(snapped, shown + control.step)
        elif factor < 1.0:
            snapped = min(snapped, shown - control.step)
        snapped = round(min(max(snapped, control.min), control.max), 6)
        self.toolbox.settings.radius = snapped / control.scale
        self.brush.refresh_cursor()
        return self.toolbox.settings.radius

    def choose_category(self, category: str) -> None:
        """The user typed a category: the active instance takes it, and so do new instances from now on."""
        category = category.strip()
        if not category:
            return
        self.toolbox.settings.category = category
        self.update_active(category=category)

    def new_instance(self, *, category: str = "object", name: str | None = None, client: str = "") -> int:
        """Create an instance and make it active; returns its id."""
        d = self.scan.store.do(lambda ls: ls.create_instance(category=category, name=name), client=client)
        assert d is not None
        iid = next(iter(d.table_after))
        self.toolbox.settings.active_id = int(iid)
        self.hooks.on_change()
        return int(iid)

    def update_active(self, **changes: Any) -> None:
        """Change the active instance (nothing when none is active)."""
        iid = self.toolbox.settings.active_id
        if iid <= 0:
            return
        self.scan.store.do(lambda ls: ls.update_instance(iid, **changes))

    def toggle_active(self, what: Literal["visible", "locked"]) -> None:
        """Hide / show or lock / unlock the active instance."""
        info = self.scan.store.labelset.info(self.toolbox.settings.active_id)
        self.update_active(**{what: not getattr(info, what)})

    def update_instance(self, instance_id: int, **changes: Any) -> None:
        """Rename / recategorise / recolour / hide / lock an instance (undoable)."""
        self.scan.store.do(lambda ls: ls.update_instance(instance_id, **changes))

    def delete_instance(self, instance_id: int) -> None:
        """Delete an instance (its vertices become unlabelled; undoable)."""
        self.scan.store.do(lambda ls: ls.delete_instance(instance_id))

    def merge(self, sources: list[int], into: int) -> None:
        """Merge instances into one, which becomes active (undoable)."""
        self.scan.store.do(lambda ls: ls.merge(sources, into))
        self.toolbox.settings.active_id = int(into)
        self.hooks.on_change()

    def undo(self, *, client: str = "") -> list[Delta]:
        """Undo the last edit (a whole stroke or group); returns the deltas undone."""
        return self.scan.store.undo(client=client)

    def redo(self, *, client: str = "") -> list[Delta]:
        """Redo the last undone edit; returns the deltas redone."""
        return self.scan.store.redo(client=client)

    def require_active(self) -> int:
        """The active instance id.

        Raises:
            ValueError: none is active.
        """
        iid = self.toolbox.settings.active_id
        if iid <= 0 or iid not in self.scan.store.labelset.instances:
            raise ValueError("no active instance: create one first (N)")
        return iid
