"""Journal recovery and write failures (items 1-4), at the `LabelStore` level.

A damaged record in the middle of the journal, a checkpoint newer than the journal, a failed append (ENOSPC on
write, EIO on fsync), a different scan with the same vertex count, autosave failures and stale temp files.
The same guarantees are checked on the full `efem-annotate` CLI in tests/test_annotator_cli_reliability.py.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

import annotator.journal as journal_mod
import annotator.store as store_mod
from annotator.journal import (
    MAGIC,
    JournalError,
    read_label_file,
    remove_stale_temp_files,
    scan_fingerprint,
)
from annotator.store import LabelStore

N = 500


def _store(tmp: Path, n: int = N, **kw) -> LabelStore:
    kw.setdefault("autosave_delay", 0)
    return LabelStore(n, journal_path=tmp / "s.journal", label_path=tmp / "s.labels.npz", **kw)


def _nine_edits(s: LabelStore) -> None:
    """Records 1-9: two instances, then seven paints over disjoint ranges."""
    s.do(lambda ls: ls.create_instance(category="mug"))  # 1
    s.do(lambda ls: ls.create_instance(category="bowl"))  # 2
    for k in range(7):  # 3..9
        s.do(lambda ls, k=k: ls.paint(np.arange(50 * k, 50 * k + 40), 1 + k % 2))


def _record_offsets(path: Path) -> list[int]:
    data = path.read_bytes()
    offs, off = [], 0
    while True:
        off = data.find(MAGIC, off)
        if off < 0:
            return offs
        offs.append(off)
        off += 1


def _flip_byte_in_record(path: Path, k: int) -> None:
    offs = _record_offsets(path)
    data = bytearray(path.read_bytes())
    data[offs[k] + 40] ^= 0xFF  # inside the payload: the CRC fails
    path.write_bytes(bytes(data))


def test_bad_middle_record_with_newer_checkpoint_loses_nothing(tmp_path: Path) -> None:
    s = _store(tmp_path, autosave_delay=60)
    _nine_edits(s)
    s.save_now()  # checkpoint at record 9... then one more edit only in the journal
    s.do(lambda ls: ls.paint(np.arange(450, 470), 2))  # 10
    final = s.labels.copy()
    ck_before = read_label_file(tmp_path / "s.labels.npz", N)[2]
    s.journal.close()
    assert ck_before == 9
    _flip_byte_in_record(tmp_path / "s.journal", 4)
    damaged = (tmp_path / "s.journal").read_bytes()
    s2 = _store(tmp_path)
    assert np.array_equal(s2.labels, final), "every acknowledged edit must survive"
    rep = s2.recovery
    assert rep is not None and rep.complete and rep.start == "checkpoint (record 9)"
    assert "no edit recorded in the journal or the checkpoint is missing" in rep.summary()
    assert "damaged" in rep.summary() and "nothing was lost" not in rep.summary()
    assert rep.verified_complete and "checkpoint: holds records up to 9" in rep.summary()
    # the damaged bytes are kept aside; the checkpoint was never replaced by an older state
    aside = list(tmp_path.glob("s.journal.damaged-*"))
    assert len(aside) == 1 and aside[0].read_bytes() == damaged
    assert read_label_file(tmp_path / "s.labels.npz", N)[2] >= 10
    # later edits land and survive; the journal alone (checkpoint deleted) gives the same state
    s2.do(lambda ls: ls.paint(np.arange(480, 490), 1))
    final2 = s2.labels.copy()
    s2.close()
    os.unlink(tmp_path / "s.labels.npz")
    s3 = _store(tmp_path)
    assert np.array_equal(s3.labels, final2)
    assert s3.recovery is None, "a repaired journal reopens cleanly"
    s3.close()


def test_bad_middle_record_without_checkpoint_keeps_every_verified_record(tmp_path: Path) -> None:
    s = _store(tmp_path)
    _nine_edits(s)
    final = s.labels.copy()
    s.journal.close()
    os.unlink(tmp_path / "s.labels.npz")
    _flip_byte_in_record(tmp_path / "s.journal", 4)  # record 4 = the paint of vertices 50..89
    s2 = _store(tmp_path)
    rep = s2.recovery
    assert rep is not None and rep.lost == (4,) and not rep.complete
    assert "journal records 4" in rep.summary()
    expect = final.copy()
    expect[50:90] = 0
    assert np.array_equal(s2.labels, expect), "records 5-9 must be replayed, only record 4 is lost"
    # undo works inside the history after the damage, never across it
    assert len(s2.labelset.undo_stack) == 5
    s2.close()


def test_checkpoint_newer_than_a_truncated_journal_wins(tmp_path: Path) -> None:
    s = _store(tmp_path)
    _nine_edits(s)
    final = s.labels.copy()
    s.close()
    jp = tmp_path / "s.journal"
    offs = _record_offsets(jp)
    with open(jp, "r+b") as f:
        f.truncate(offs[4])  # records 4-9 gone
    s2 = _store(tmp_path)
    assert np.array_equal(s2.labels, final)
    assert s2.recovery is not None and s2.recovery.complete
    assert s2.journal.next_seq > 9, "sequence numbers must never be reused"
    s2.do(lambda ls: ls.paint(np.arange(490, 495), 1))
    final2 = s2.labels.copy()
    s2.close()
    os.unlink(tmp_path / "s.labels.npz")
    s3 = _store(tmp_path)
    assert np.array_equal(s3.labels, final2)
    s3.close()


def test_a_journal_one_record_behind_its_checkpoint_starts_a_new_undo_history(tmp_path: Path) -> None:
    """A folder copied while writing (the checkpoint holds record 10, the journal ends at 9): the labels are the
    checkpoint's, and Undo must not undo record 9 on top of the unknown record 10 (it used to delete an instance
    whose vertices kept its id, fail every later Undo as stale, and lose the instance's name after a restart)."""
    s = _store(tmp_path)
    _nine_edits(s)
    s.do(lambda ls: ls.create_instance(category="cup", name="the blue cup"))  # 10
    s.do(lambda ls: ls.paint(np.arange(450, 500), 3))  # 11
    s.close()
    final = s.labels.copy()
    jp = tmp_path / "s.journal"
    offs = _record_offsets(jp)
    with open(jp, "r+b") as f:
        f.truncate(offs[11])  # the journal ends at record 10; the checkpoint holds 11
    s2 = _store(tmp_path)
    assert np.array_equal(s2.labels, final) and s2.recovery is not None
    assert s2.labelset.undo_stack == [] and s2.undo() == []  # nothing to undo across the missing record
    assert np.array_equal(s2.labels, final)
    s2.do(lambda ls: ls.paint(np.arange(400, 410), 3))
    assert len(s2.undo()) == 1 and np.array_equal(s2.labels, final)  # the new edit undoes cleanly
    s2.close()
    s3 = _store(tmp_path)
    assert np.array_equal(s3.labels, final)
    info = s3.snapshot()[1][3]
    assert (info.name, info.category) == ("the blue cup", "cup")
    s3.close()


def test_retried_record_with_a_repeated_seq_supersedes_the_old_copy(tmp_path: Path) -> None:
    """An old version left a complete copy of a failed append before its retry: the retry (the edit the user
    saw applied) wins."""
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    s.do(lambda ls: ls.paint(np.arange(0, 10), 1))  # seq 2: becomes the phantom
    s.journal.close()
    jp = tmp_path / "s.journal"
    offs = _record_offsets(jp)
    phantom = jp.read_bytes()[offs[2]:]
    with open(jp, "r+b") as f:
        f.truncate(offs[2])
    os.unlink(tmp_path / "s.labels.npz")
    s = _store(tmp_path)
    s.do(lambda ls: ls.paint(np.arange(100, 120), 1))  # the real seq 2
    s.journal.close()
    data = jp.read_bytes()
    jp.write_bytes(data[:offs[2]] + phantom + data[offs[2]:])
    os.unlink(tmp_path / "s.labels.npz")
    s2 = _store(tmp_path)
    assert s2.labelset.count(1) == 20 and s2.labels[100] == 1 and s2.labels[0] == 0
    s2.close()


class _Faults:
    """Replaces the journal's os.write/os.fsync while `on`: "write" writes half a record then fails with `err`;
    "fsync" fails the fsync that follows a write (the repair's fsync works); "fsync_all" fails every fsync."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, where: str, err: int) -> None:
        self.on = False
        self.where, self.err = where, err
        real_write, real_fsync = os.write, os.fsync

        self.after_write = False

        def write(fd: int, data) -> int:
            self.after_write = True
            if self.on and self.where == "write":
                real_write(fd, bytes(data[: len(data) // 2]))  # a partial record reaches the file
                raise OSError(self.err, os.strerror(self.err))
            return real_write(fd, data)

        def fsync(fd: int) -> None:
            after_write, self.after_write = self.after_write, False
            if self.on and (self.where == "fsync_all" or (self.where == "fsync" and after_write)):
                raise OSError(self.err, os.strerror(self.err))
            real_fsync(fd)

        monkeypatch.setattr(journal_mod, "_os_write", write)
        monkeypatch.setattr(journal_mod, "_os_fsync", fsync)


@pytest.mark.parametrize(("where", "err"), [("write", errno.ENOSPC), ("fsync", errno.EIO)])
def test_failed_append_leaves_the_journal_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: str, err: int
) -> None:
    faults = _Faults(monkeypatch, where, err)
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    s.do(lambda ls: ls.paint(np.arange(0, 10), 1))
    size = (tmp_path / "s.journal").stat().st_size
    before = s.labels.copy()
    faults.on = True
    for _ in range(3):
        with pytest.raises(JournalError, match="not saved"):
            s.do(lambda ls: ls.paint(np.arange(10, 20), 1))
        assert np.array_equal(s.labels, before), "a refused edit is not applied"
        assert (tmp_path / "s.journal").stat().st_size == size, "no partial record may stay behind"
    faults.on = False
    for k in range(3):  # later edits land and survive
        s.do(lambda ls, k=k: ls.paint(np.arange(100 + 10 * k, 110 + 10 * k), 1))
    s.undo()
    final = s.labels.copy()
    s.close()
    os.unlink(tmp_path / "s.labels.npz")
    s2 = _store(tmp_path)
    assert s2.recovery is None, "the journal has no damage to report"
    assert np.array_equal(s2.labels, final)
    assert s2.labelset.count(1) == 30
    s2.close()


def test_unrepairable_append_failure_blocks_further_edits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    faults = _Faults(monkeypatch, "fsync_all", errno.EIO)
    s = _store(tmp_path)
    s.do(lambda ls: ls.create_instance())
    faults.on = True
    with pytest.raises(JournalError):
        s.do(lambda ls: ls.paint([1], 1))  # the repair's fsync fails too
    faults.on = False
    with pytest.raises(JournalError, match="restart"):
        s.do(lambda ls: ls.paint([2], 1))
    s.close()


def test_same_vertex_count_other_geometry_is_refused(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(N, 3)).astype(np.float32)
    moved = pts[rng.permutation(N)] + np.float32(5.0)
    h1, h2 = scan_fingerprint(pts), scan_fingerprint(moved)
    assert h1 != h2 and h1 == scan_fingerprint(pts.astype(np.float64))
    s = _store(tmp_path, scan_id={"content_hash": h1})
    s.do(lambda ls: ls.create_instance())
    s.do(lambda ls: ls.paint(np.arange(0, 100), 1))
    s.close()
    before = (tmp_path / "s.journal").read_bytes()
    with pytest.raises(JournalError, match="different scan.*--accept-scan-mismatch"):
        _store(tmp_path, scan_id={"content_hash": h2})
    assert (tmp_path / "s.journal").read_bytes() == before
    # the label file alone (journal deleted) is checked too
    os.rename(tmp_path / "s.journal", tmp_path / "s.journal.bak")
    with pytest.raises(JournalError, match="different scan"):
        _store(tmp_path, scan_id={"content_hash": h2})
    os.rename(tmp_path / "s.journal.bak", tmp_path / "s.journal")
    # on purpose: resumes, and records the new identity so the next open needs no flag
    s2 = _store(tmp_path, scan_id={"content_hash": h2}, accept_scan_mismatch=True)
    assert s2.labelset.count(1) == 100
    s2.close()
    s3 = _store(tmp_path, scan_id={"content_hash": h2})
    assert s3.labelset.count(1) == 100
    s3.close()


def test_autosave_failure_is_reported_and_cleared(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[str | None] = []
    s = _store(tmp_path)
    s.problem_listeners.append(seen.append)
    real = store_mod.write_label_file
    fail = {"on": True}

    def write_label_file(*a, **kw):
        if fail["on"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*a, **kw)

    monkeypatch.setattr(store_mod, "write_label_file", write_label_file)
    s.do(lambda ls: ls.create_instance())  # the edit itself is journalled and kept
    assert s.labelset.instances and s.problem and "No space left" in s.problem
    assert seen and seen[-1] == s.problem
    fail["on"] = False
    s.do(lambda ls: ls.paint([1, 2], 1))
    assert s.problem is None and seen[-1] is None
    s.close()


def test_stale_temp_files_of_this_scan_are_removed(tmp_path: Path) -> None:
    (tmp_path / ".scan.labels.ab12cd.tmp.ply").write_bytes(b"")
    (tmp_path / ".scan.labels.x.tmp.npz").write_bytes(b"")
    keep = [tmp_path / ".scan2.labels.q.tmp.ply", tmp_path / "scan.labels.ply", tmp_path / ".scan.notes"]
    for p in keep:
        p.write_bytes(b"x")
    removed = remove_stale_temp_files(tmp_path, "scan")
    assert len(removed) == 2
    assert all(p.exists() for p in keep)


def test_truncated_journal_without_checkpoint_says_what_it_cannot_verify(tmp_path: Path) -> None:
    """the journal cut to half its bytes and the checkpoint deleted. The store cannot know how
    many edits followed the cut: the notice says what was verified (the records replayed, where the journal ended,
    that the checkpoint is missing) and what cannot be verified, and never that nothing was lost."""
    s = _store(tmp_path)
    _nine_edits(s)
    s.close()
    jp = tmp_path / "s.journal"
    offs = _record_offsets(jp)
    half = jp.stat().st_size // 2
    if half in offs:  # land inside a record, as a cut anywhere almost always does
        half += 7
    torn_at = max(o for o in offs if o < half)
    kept = offs.index(torn_at)  # whole records before the cut: the base record and kept - 1 edits
    with open(jp, "r+b") as f:
        f.truncate(half)
    os.unlink(tmp_path / "s.labels.npz")
    s2 = _store(tmp_path)
    rep = s2.recovery
    assert rep is not None
    text = rep.summary()
    assert "nothing was lost" not in text and "no edit recorded" not in text
    assert rep.complete and not rep.verified_complete, "nothing known missing, but not everything verifiable"
    assert f"+ {kept - 1} edit records replayed" in text
    assert f"{kept} journal records (0-{kept - 1}, checksums match)" in text
    assert f"incomplete record at byte {torn_at:,}" in text
    assert "checkpoint: missing" in text and "no checkpoint to compare with" in text
    assert f"cannot be verified: whether edits followed record {kept - 1}" in text
    assert s2.journal.next_seq == kept
    s2.close()


def test_torn_tail_with_a_current_checkpoint_still_cannot_vouch_for_later_edits(tmp_path: Path) -> None:
    s = _store(tmp_path)
    _nine_edits(s)
    s.save_now()
    s.journal.close()
    jp = tmp_path / "s.journal"
    with open(jp, "ab") as f:  # half of a record after record 9
        f.write(b"EFJ1\x00\x10\x00\x00garbage")
    s2 = _store(tmp_path)
    text = s2.recovery.summary() if s2.recovery else ""
    assert "checkpoint: holds records up to 9" in text and "checkpoint holds nothing newer (record 9)" in text
    assert "nothing was lost" not in text
    s2.close()


# ----------------------------------------------------------------------------------------------
def _whole_scan_edits(s: LabelStore, k: int) -> list[np.ndarray]:
    """k edits that each repaint every vertex; returns the labels after each (index 0: before the first)."""
    states = [s.labels.copy()]
    ids = [s.do(lambda ls: ls.create_instance(category="mug")) for _ in range(2)]
    assert all(d is not None for d in ids)
    states = [s.labels.copy()]
    for i in range(k):
        s.do(lambda ls, i=i: ls.paint(np.arange(ls.n), 1 + i % 2))
        states.append(s.labels.copy())
    return states


def test_undo_history_in_memory_is_bounded_and_every_edit_stays_undoable(tmp_path: Path) -> None:
    n = 20_000
    per_edit = 12 * n  # idx + before + after, int32
    s = _store(tmp_path, n=n, history_bytes=2 * per_edit)
    states = _whole_scan_edits(s, 6)
    assert s.history_in_memory() <= 2 * per_edit
    stored = [e for e in s.labelset.undo_stack if not hasattr(e, "nbytes")]
    assert len(stored) >= 4, "older whole-scan edits must leave memory"
    assert all(r.loaded is None for r in s.journal.records), "the open journal holds headers only"
    for want in reversed(states[:-1]):  # undo all six, reading the old ones back from the journal
        assert s.undo()
        assert np.array_equal(s.labels, want)
        assert s.history_in_memory() <= 2 * per_edit
    for want in states[1:]:
        assert s.redo()
        assert np.array_equal(s.labels, want)
    assert s.history_in_memory() <= 2 * per_edit
    s.close()


def test_reopening_reads_only_the_checkpoint_and_later_records(tmp_path: Path, monkeypatch) -> None:
    n = 20_000
    s = _store(tmp_path, n=n)
    states = _whole_scan_edits(s, 5)
    s.close()  # final save: the checkpoint holds every record
    reads: list[int] = []
    real = journal_mod.Journal.read_arrays

    def counting(self, rec):
        reads.append(rec.seq)
        return real(self, rec)

    monkeypatch.setattr(journal_mod.Journal, "read_arrays", counting)
    s2 = _store(tmp_path, n=n)
    assert np.array_equal(s2.labels, states[-1])
    assert reads == [], "history older than the checkpoint is not read on reopen"
    assert s2.history_in_memory() == 0 and len(s2.labelset.undo_stack) == 7
    assert s2.undo() and np.array_equal(s2.labels, states[-2])
    assert len(reads) == 1, "an undo reads its one record back"
    s2.close()


def test_a_stored_edit_that_no_longer_verifies_refuses_the_undo_and_changes_nothing(tmp_path: Path) -> None:
    n = 5_000
    s = _store(tmp_path, n=n, history_bytes=0)
    states = _whole_scan_edits(s, 2)
    rec = s.journal.record(3)  # the first whole-scan paint
    assert rec is not None
    with open(tmp_path / "s.journal", "r+b") as f:  # the file changes under the annotator
        f.seek(rec.offset + 40)
        b = f.read(1)
        f.seek(rec.offset + 40)
        f.write(bytes([b[0] ^ 0xFF]))
    assert s.undo() and np.array_equal(s.labels, states[1])
    before = s.journal.next_seq
    with pytest.raises(JournalError, match="record 3"):
        s.undo()
    assert np.array_equal(s.labels, states[1]) and s.journal.next_seq == before, "nothing applied nor journalled"
    s.journal.close()
