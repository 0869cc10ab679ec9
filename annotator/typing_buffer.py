"""Typing in a text field, committed once: a name or category is one edit, not one per keystroke.

A browser text field sends its value on every keystroke and tells the server nothing when the person presses
Enter or leaves the field. `TypingBuffer` holds the latest value of each field being typed and commits it once:
when the field has been left alone for `idle_s`, or at once when the person does anything else (the app flushes the
buffer before every other action, so "leaving the field" to click, paint or press a key commits what was typed, in
order). While a field is being typed its value is the person's, and the panels do not overwrite it
(`fields_typing`); after the commit they show the stored value.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable

log = logging.getLogger(__name__)

TEXT_IDLE_S = 2.5
"""Seconds without a keystroke after which a typed value is committed."""


class TypingBuffer:
    """The pending values of text fields, each committed once.

    Args:
        commit: called with (key, value) for each pending field, outside the buffer's lock; may raise
            ValueError/KeyError to refuse the value (reported through `on_error`, and the field is no longer
            pending).
        on_error: called with a one-line message when a commit is refused or fails.
        idle_s: seconds without a keystroke before a commit.
        on_idle: called (on the timer's thread) after an idle commit, e.g. to show the stored values.
    """

    def __init__(self, commit: Callable[[Hashable, str], None], *, on_error: Callable[[str], None] | None = None,
                 idle_s: float = TEXT_IDLE_S, on_idle: Callable[[], None] | None = None) -> None:
        if not idle_s > 0:
            raise ValueError(f"idle_s must be > 0, got {idle_s}")
        self._commit = commit
        self._on_error = on_error
        self._on_idle = on_idle
        self.idle_s = float(idle_s)
        self._lock = threading.Lock()
        self._pending: dict[Hashable, str] = {}
        self._timer: threading.Timer | None = None
        self._flushing = threading.Lock()  # commits happen in the order the values were typed

    def typed(self, key: Hashable, value: str) -> None:
        """A keystroke: `value` is the field's whole new content; the commit waits for `idle_s` of quiet."""
        with self._lock:
            self._pending.pop(key, None)
            self._pending[key] = value  # newest last
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(self.idle_s, self._idle)
            self._timer.daemon = True
            self._timer.start()

    def pending(self) -> dict[Hashable, str]:
        """A copy of the values waiting to be committed."""
        with self._lock:
            return dict(self._pending)

    def _idle(self) -> None:
        if self.flush() >= 0 and self._on_idle is not None:
            try:
                self._on_idle()
            except Exception:  # noqa: BLE001 - a timer thread
                log.exception("after-commit callback failed")

    def flush(self) -> int:
        """Commit every pending value now; returns how many values were pending (committed or refused)."""
        with self._flushing:
            with self._lock:
                items = list(self._pending.items())
                self._pending.clear()
                if self._timer is not None:
                    self._timer.cancel()
                    self._timer = None
            for key, value in items:
                try:
                    self._commit(key, value)
                except (ValueError, KeyError) as exc:
                    self._report(str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc))
                except Exception as exc:  # noqa: BLE001 - a timer thread: the person must hear of it
                    log.exception("committing a typed value failed")
                    self._report(f"that did not work: {type(exc).__name__}: {exc}")
            return len(items)

    def cancel(self) -> None:
        """Stop the timer (pending values stay pending; `flush` commits them)."""
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None

    def _report(self, msg: str) -> None:
        log.warning("typed value not used: %s", msg)
        if self._on_error is not None:
            try:
                self._on_error(msg)
            except Exception:  # noqa: BLE001 - reporting must not lose the other commits
                log.exception("error report failed")
