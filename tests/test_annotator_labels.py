"""Label store: edits, undo/redo (also across restarts), protection, merge, journal replay and repair."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from annotator.journal import JournalError, read_label_file
from annotator.store import LabelStore
from annotator.labels import InstanceInfo, LabelSet

N = 200


def _store(tmp: Path, n: int = N, **kw) -> LabelStore:
    return LabelStore(
        n, journal_path=tmp / "s.journal", label_path=tmp / "s.labels.npz", autosave_delay=0, **kw
    )


def _naive_counts(labels: np.ndarray) -> dict[int, int]:
    ids, c = np.unique(labels, return_counts=True)
    return {int(i): int(k) for i, k in zip(ids, c) if i > 0}


# ---------------------------------------------------------------------------------------------- LabelSet
def test_paint_erase_counts_and_progress() -> None:
    ls = LabelSet(N)
    ls.apply(ls.create_instance(category="mug"))
    ls.apply(ls.create_instance(category="bowl"))
    ls.apply(ls.paint(np.arange(0, 50), 1))
    ls.apply(ls.paint(np.arange(40, 80), 2))
    assert _naive_counts(ls.labels) == {1: 40, 2: 40}
    assert ls.counts() == {1: 40, 2: 40}
    assert ls.progress() == pytest.approx(80 / N)
    d = ls.erase(np.arange(70, 100))
    assert d.num_vertices == 10  # only vertices that really change are recorded
    ls.apply(d)
    assert ls.count(2) == 30 and ls.count(0) == N - 70
    # paint with overwrite=False only fills unlabelled vertices
    d = ls.paint(np.arange(0, 120), 2, overwrite=False)
    assert set(d.idx.tolist()) == set(range(80, 120)) | set(range(70, 80)) - set()
    assert np.all(ls.labels[d.idx] == 0)


def test_labels_view_is_read_only() -> None:
    ls = LabelSet(N)
    with pytest.raises(ValueError):
        ls.labels[0] = 3


def test_locked_and_hidden_instances_are_protected() -> None:
    ls = LabelSet(N)
    ls.apply(ls.create_instance())
    ls.apply(ls.create_instance())
    ls.apply(ls.paint(np.arange(0, 20), 1))
    ls.apply(ls.update_instance(1, locked=True))
    d = ls.paint(np.arange(0, 40), 2)
    assert set(d.idx.tolist()) == set(range(20, 40))
    assert ls.erase(np.arange(0, 20)).is_empty
    with pytest.raises(ValueError, match="locked"):
        ls.paint([25], 1)
    with pytest.raises(ValueError, match="locked"):
        ls.delete_instance(1)
    ls.apply(ls.update_instance(1, locked=False, visible=False))
    assert ls.erase(np.arange(0, 20)).is_empty  # hidden: protected too
    ls.apply(ls.update_instance(1, visible=True))
    assert ls.erase(np.arange(0, 20)).num_vertices == 20


def test_merge_and_delete_with_undo() -> None:
    ls = LabelSet(N)
    for _ in range(3):
        ls.apply(ls.create_instance(category="mug"))
    ls.apply(ls.paint(np.arange(0, 10), 1))
    ls.apply(ls.paint(np.arange(10, 30), 2))
    ls.apply(ls.paint(np.arange(30, 60), 3))
    before = ls.snapshot()
    ls.apply(ls.merge([1, 2], 3))
    assert ls.counts() == {3: 60}
    assert set(ls.instances) == {3}
    ls.undo()
    assert np.array_equal(ls.labels, before[0]) and ls.instances == before[1]
    ls.apply(ls.delete_instance(2))
    assert 2 not in ls.instances and ls.count(0) == N - 40
    ls.undo()
    assert ls.instances[2] == before[1][2] and ls.count(2) == 20
    with pytest.raises(ValueError):
        ls.merge([3], 3)
    with pytest.raises(KeyError):
        ls.merge([1], 99)


def test_bad_inputs_are_refused_with_shapes() -> None:
    with pytest.raises(ValueError, match=r"\(5,\)"):
        LabelSet(N, labels=np.zeros(5, np.int32))
    with pytest.raises(ValueError, match=">= 0"):
        LabelSet(3, labels=np.array([0, -1, 2]))
    ls = LabelSet(N)
    ls.apply(ls.create_instance())
    with pytest.raises(ValueError, match="indices"):
        ls.paint([N + 3], 1)
    with pytest.raises(KeyError):
        ls.paint([1], 7)
    with pytest.raises(ValueError, match="colour"):
        ls.update_instance(1, color=(300, 0, 0))
    with pytest.raises(ValueError, match="shape"):
        ls.replace_all(np.zeros(N + 1, np.int32), [])


ops = st.lists(
    st.tuples(st.sampled_from(["new", "paint", "erase", "undo", "redo", "merge", "rename"]),
              st.integers(0, N - 1), st.integers(1, 60), st.integers(0, 5)),
    min_size=1, max_size=25,
)


@settings(max_examples=40, deadline=None)
@given(ops)
def test_random_edit_sequences_undo_to_start_and_redo_to_end(seq) -> None:
    """Property: undoing everything restores the start exactly; redoing everything restores the tip."""
    ls = LabelSet(N)
    start = ls.snapshot()
    for op, a, b, k in seq:
        ids = sorted(ls.instances)
        try:
            if op == "new":
                ls.apply(ls.create_instance())
            elif op == "paint" and ids:
                ls.apply(ls.paint(np.arange(a, min(N, a + b)), ids[k % len(ids)]))
            elif op == "erase":
                ls.apply(ls.erase(np.arange(a, min(N, a + b))))
            elif op == "undo":
                ls.undo()
            elif op == "redo":
                ls.redo()
            elif op == "merge" and len(ids) >= 2:
                ls.apply(ls.merge([ids[k % len(ids)]], ids[(k + 1) % len(ids)]))
            elif op == "rename" and ids:
                ls.apply(ls.update_instance(ids[k % len(ids)], name=f"n{a}"))
        except ValueError:
            pass
        assert ls.counts() == {i: _naive_counts(ls.labels).get(i, 0) for i in ls.instances}
        assert set(_naive_counts(ls.labels)) <= set(ls.instances)
    while ls.redo():  # the tip of the history
        pass
    end = ls.snapshot()
    while ls.undo():
        pass
    assert np.array_equal(ls.labels, start[0]) and ls.instances == start[1]
    while ls.redo():
        pass
    assert np.array_equal(ls.labels, end[0]) and ls.instances == end[1]


# ---------------------------------------------------------------------------------------------- LabelStore + journal
def test_stroke_group_undoes_as_one(tmp_path: Path) -> None:
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    for a in range(0, 50, 10):
        s.do(lambda ls, a=a: ls.paint(np.arange(a, a + 10), 1), group="stroke-1")
    s.do(lambda ls: ls.paint(np.arange(100, 110), 1), group="stroke-2")
    assert s.labelset.count(1) == 60
    assert len(s.undo()) == 1 and s.labelset.count(1) == 50
    assert len(s.undo()) == 5 and s.labelset.count(1) == 0
    assert len(s.redo()) == 5 and s.labelset.count(1) == 50
    s.close()


def test_journal_replay_restores_labels_and_history(tmp_path: Path) -> None:
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance(category="mug"))
    s.do(lambda ls: ls.paint(np.arange(0, 30), 1))
    s.do(lambda ls: ls.create_instance(category="bowl"))
    s.do(lambda ls: ls.paint(np.arange(20, 60), 2))
    s.do(lambda ls: ls.update_instance(2, name="big bowl", color=(1, 2, 3)))
    s.undo()  # name change undone, on the redo stack
    labels, table = s.snapshot()
    s.journal.close()  # no final checkpoint: simulate a crash after the last fsync
    s2 = _store(tmp_path)
    assert s2.resumed
    assert np.array_equal(s2.labels, labels) and s2.labelset.instances == table
    assert len(s2.labelset.undo_stack) == 4 and len(s2.labelset.redo_stack) == 1
    s2.redo()
    assert s2.labelset.info(2).name == "big bowl"
    s2.undo()
    s2.undo()  # undo the bowl paint across the restart
    assert s2.labelset.count(2) == 0 and s2.labelset.count(1) == 30
    s2.close()


def test_replay_over_stale_checkpoint_and_without_checkpoint(tmp_path: Path) -> None:
    s = LabelStore(N, journal_path=tmp_path / "s.journal", label_path=tmp_path / "s.labels.npz", autosave_delay=60)
    s.do(lambda ls: ls.create_instance())
    s.do(lambda ls: ls.paint(np.arange(0, 10), 1))
    s.save_now()
    ckpt_labels, _, ckpt_seq = read_label_file(tmp_path / "s.labels.npz", N)
    s.do(lambda ls: ls.paint(np.arange(10, 25), 1))  # not in the checkpoint (autosave delay)
    final = s.labels.copy()
    s.journal.close()
    assert ckpt_labels.sum() == 10 and ckpt_seq == 2
    s2 = _store(tmp_path)
    assert np.array_equal(s2.labels, final)
    s2.journal.close()
    os.unlink(tmp_path / "s.labels.npz")
    s3 = _store(tmp_path)
    assert np.array_equal(s3.labels, final)
    s3.close()


def test_torn_last_record_is_dropped_and_kept_aside(tmp_path: Path) -> None:
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    s.do(lambda ls: ls.paint(np.arange(0, 10), 1))
    good = s.labels.copy()
    s.journal.close()
    jp = tmp_path / "s.journal"
    size = jp.stat().st_size
    with open(jp, "ab") as f:  # half of a record: the crash happened during append
        f.write(b"EFJ1\x00\x10\x00\x00garbage")
    os.unlink(tmp_path / "s.labels.npz")
    s2 = _store(tmp_path)
    assert np.array_equal(s2.labels, good)
    assert jp.stat().st_size == size  # truncated back to the last whole record, so new appends are valid
    assert list(tmp_path.glob("s.journal.torn-*"))
    s2.do(lambda ls: ls.paint(np.arange(50, 60), 1))
    s2.journal.close()
    s3 = _store(tmp_path)
    assert s3.labelset.count(1) == 20
    s3.close()


def test_journal_of_another_scan_is_refused_untouched(tmp_path: Path) -> None:
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    s.close()
    before = (tmp_path / "s.journal").read_bytes()
    with pytest.raises(JournalError, match="200 vertices"):
        _store(tmp_path, n=N + 1)
    assert (tmp_path / "s.journal").read_bytes() == before


def test_second_writer_is_locked_out(tmp_path: Path) -> None:
    s = _store(tmp_path)
    with pytest.raises(JournalError, match="in use"):
        _store(tmp_path)
    s.close()


def test_initial_labels_and_checkpoint_contents(tmp_path: Path) -> None:
    init = np.zeros(N, np.int32)
    init[:5] = 4
    s = _store(tmp_path, initial_labels=init, initial_instances=[InstanceInfo(4, "cup", "mug", (9, 9, 9))])
    assert s.labelset.info(4).color == (9, 9, 9)
    s.do(lambda ls: ls.paint([10], 4))
    s.close()
    lab, table, seq = read_label_file(tmp_path / "s.labels.npz", N)
    assert lab[10] == 4 and lab[:5].tolist() == [4] * 5 and table[4].name == "cup" and seq == 1
