"""Typed text committed once: `annotator.typing_buffer.TypingBuffer` and the session's Name and
Category fields, driven without a browser (the browser test types with real keys)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from annotator.session import AnnotatorSession
from annotator.typing_buffer import TypingBuffer
from tests.helpers import ball_scan


def _wait(cond, what: str, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout  # a hang guard, not a speed bound
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def test_keystrokes_are_one_commit_of_the_last_value() -> None:
    done: list[tuple[object, str]] = []
    buf = TypingBuffer(lambda k, v: done.append((k, v)), idle_s=60.0)
    for v in ("b", "bo", "box"):
        buf.typed("cat", v)
    assert done == [] and buf.pending() == {"cat": "box"}
    assert buf.flush() == 1 and done == [("cat", "box")]
    assert buf.flush() == 0 and done == [("cat", "box")], "nothing twice"


def test_idle_commits_by_itself_and_a_refusal_is_reported() -> None:
    done: list[str] = []
    errors: list[str] = []

    def commit(_k: object, v: str) -> None:
        if not v:
            raise ValueError("a category cannot be empty")
        done.append(v)

    buf = TypingBuffer(commit, on_error=errors.append, idle_s=0.05)
    buf.typed("cat", "cup")
    _wait(lambda: done == ["cup"], "the idle commit")
    buf.typed("cat", "")
    _wait(lambda: bool(errors), "the refusal")
    assert errors == ["a category cannot be empty"] and done == ["cup"] and buf.pending() == {}
    with pytest.raises(ValueError):
        TypingBuffer(commit, idle_s=0)


def test_racing_flushes_commit_each_value_once() -> None:
    done: list[str] = []
    buf = TypingBuffer(lambda _k, v: done.append(v), idle_s=60.0)
    buf.typed("name", "left mug")
    threads = [threading.Thread(target=buf.flush) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert done == ["left mug"]


@pytest.fixture()
def session(tmp_path: Path):
    s = AnnotatorSession(ball_scan(tmp_path), out_dir=tmp_path / "out", autosave_delay=0)
    yield s
    s.close()


def test_the_typed_name_lands_on_the_instance_it_was_typed_for(session: AnnotatorSession) -> None:
    """Typing into mug 1's Name, then making mug 2 active (an action: it commits first) names mug 1, not mug 2;
    the history has one rename; the panels were told to refresh after the commit."""
    a = session.instances.new_instance(category="mug")
    b = session.instances.new_instance(category="mug")
    session.instances.set_active(a)
    refreshed: list[int] = []
    session.on_change = lambda: refreshed.append(1)
    for v in ("l", "le", "left", "left mug"):
        session.instances.type_text("name", v)
    assert session.instances.fields_typing() == {"name"}
    session.instances.flush_typing()  # what the app does before the next action
    session.instances.set_active(b)
    ls = session.scan.store.labelset
    assert ls.info(a).name == "left mug" and ls.info(b).name != "left mug"
    assert sum("name=" in e.label for e in ls.undo_stack) == 1
    assert refreshed and session.instances.fields_typing() == frozenset()


def test_an_empty_category_is_refused_and_the_stored_one_kept(session: AnnotatorSession) -> None:
    notes: list[tuple[str, str]] = []
    session.notify = lambda title, body: notes.append((title, body))
    a = session.instances.new_instance(category="mug")
    session.instances.type_text("category", "   ")
    assert session.instances.flush_typing() == 1  # pending, then refused
    assert session.scan.store.labelset.info(a).category == "mug" and notes and "cannot be empty" in notes[0][1]


def test_closing_commits_what_was_typed(tmp_path: Path) -> None:
    """Never lose work: a name typed just before the annotator stops is stored."""
    s = AnnotatorSession(ball_scan(tmp_path), out_dir=tmp_path / "out", autosave_delay=0)
    a = s.instances.new_instance(category="mug")
    s.painting.paint(np.arange(5))
    s.instances.type_text("name", "last mug")
    s.close()
    s2 = AnnotatorSession(ball_scan(tmp_path), out_dir=tmp_path / "out", autosave_delay=0)
    try:
        assert s2.scan.store.labelset.info(a).name == "last mug"
    finally:
        s2.close()


def test_late_keys_after_an_action_go_to_the_instance_they_were_typed_for(session: AnnotatorSession) -> None:
    """The browser sends a field's keystrokes and a hotkey on separate paths: the last keys of a name typed for mug
    A can reach the server after the N that made mug B active. Keys arriving that soon after the field was committed
    belong to A; later typing is B's."""
    a = session.instances.new_instance(category="mug")
    session.instances.type_text("name", "left b")
    session.instances.flush_typing()  # what the app does before N
    b = session.instances.new_instance(category="mug")
    session.instances.type_text("name", "left box")  # the late keys
    session.instances.flush_typing()
    ls = session.scan.store.labelset
    assert ls.info(a).name == "left box" and ls.info(b).name != "left box"
    session.instances.late_keys_s = 0.0  # long after: typing is for the active instance
    session.instances.type_text("name", "right box")
    session.instances.flush_typing()
    assert ls.info(b).name == "right box" and ls.info(a).name == "left box"


def test_late_keys_that_continue_the_committed_name_go_to_its_instance_on_a_busy_server(
        session: AnnotatorSession) -> None:
    """A busy server (an EFEM run beside the typing) can receive the trailing keys of a name later than
    `late_keys_s` after the N: values that only add to what was committed still go to the instance they were typed
    for, every one of them (the second finds the first waiting); a new name for the new instance (the field
    restarts from that instance's own name) is the new one's, and so is a continuation arriving after
    `late_continuation_s`."""
    ins = session.instances
    ins.late_keys_s = 0.0  # every key below comes "late"
    ins.late_continuation_s = float("inf")  # ... but within the continuation window, however slow the machine
    a = ins.new_instance(category="mug")
    ins.type_text("name", "left b")
    ins.flush_typing()  # what the app does before N
    b = ins.new_instance(category="mug")
    ins.type_text("name", "left bo")  # the trailing keys, late, two of them
    ins.type_text("name", "left box")
    ins.type_text("name", "r")  # the person now names B: a fresh value, not a continuation of A's
    ins.type_text("name", "right box")
    ins.flush_typing()
    ls = session.scan.store.labelset
    assert ls.info(a).name == "left box" and ls.info(b).name == "right box"
    c = ins.new_instance(category="mug")
    ins.late_continuation_s = 0.0  # long after: even a continuation is for the active instance
    ins.type_text("name", "right box 2")
    ins.flush_typing()
    assert ls.info(c).name == "right box 2" and ls.info(b).name == "right box"


def test_editing_a_new_instances_inherited_category_stays_with_it(session: AnnotatorSession) -> None:
    """A new instance takes the category typed last ("box"); editing it to "boxes" continues both that stored value
    and the value committed for the previous instance: it is the new instance's edit. Late keys for a deleted
    instance go to the active one."""
    ins = session.instances
    ins.late_keys_s = 0.0
    ins.late_continuation_s = float("inf")
    a = ins.new_instance(category="mug")
    ins.type_text("category", "box")
    ins.flush_typing()
    b = ins.new_instance(category=session.toolbox.settings.category)  # what N does
    ls = session.scan.store.labelset
    assert ls.info(b).category == "box"
    ins.type_text("category", "boxe")
    ins.type_text("category", "boxes")
    ins.flush_typing()
    assert ls.info(b).category == "boxes" and ls.info(a).category == "box"
    ins.type_text("name", "left b")  # B's name; then N makes C, and B is deleted before its trailing keys arrive
    ins.flush_typing()
    c = ins.new_instance(category="mug")
    ins.delete_instance(b)
    ins.set_active(c)
    ins.type_text("name", "left box")
    ins.flush_typing()
    assert ls.info(c).name == "left box" and b not in ls.instances
