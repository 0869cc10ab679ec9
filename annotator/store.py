"""`LabelStore`: the one lock around the labels, journal first, the autosaved checkpoint, recovery, undo/redo.

Durability contract: `LabelStore.do/undo/redo` first append the edit to the journal and fsync it, then apply it
in memory, then return (the acknowledgement). A kill -9 at any moment therefore loses at most the edit in flight.
The label file is rewritten by a debounced background thread. Reopening loads the checkpoint and replays the
journal records after it (`RecoveryReport` says what was recovered and what was not); the undo/redo stacks are
rebuilt from the whole journal, so undo/redo survive a restart. Edits beyond `history_bytes` (`HISTORY_BYTES`)
stay on disk as `JournalEdit`s and are read back from the journal on undo/redo.

The file formats (journal records, the label file, the scan fingerprint) are `annotator/journal.py`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from annotator.journal import (
    Journal,
    JournalError,
    Record,
    delta_to_record,
    read_label_file_with_scan,
    record_to_delta,
    write_label_file,
)
from annotator.labels import Delta, HistoryEntry, InstanceInfo, LabelSet, table_from_json, table_to_json

log = logging.getLogger(__name__)

Listener = Callable[[Delta, str], None]
ProblemListener = Callable[[str | None], None]


@dataclass(frozen=True)
class RecoveryReport:
    """What reopening a damaged session recovered and what it could not (shown to the user in the GUI)."""

    start: str
    """The state replay started from, e.g. "checkpoint (record 8)" or "journal base record"."""
    replayed: int
    """Edit records applied on top of the start state."""
    damage: tuple[str, ...]
    """Problems found in the journal and the label file, one line each."""
    lost: tuple[int, ...]
    """Sequence numbers of records whose effect is not in the recovered labels (unverifiable, after the start)."""
    skipped: tuple[str, ...]
    """Verified records that could not be replayed, and why."""
    aside: tuple[str, ...]
    """Files where damaged bytes were kept."""
    verified: str = ""
    """What was checked and found intact, e.g. "12 journal records (0-11, checksums match); checkpoint: missing"."""
    unverified: tuple[str, ...] = ()
    """What cannot be verified from the files left, one line each (e.g. whether edits followed a journal that ends
    in an incomplete record, when no checkpoint holds them)."""

    @property
    def complete(self) -> bool:
        """True when no edit is known to be missing: no damaged record after the start state, none skipped. (Edits
        that left no trace cannot be known: see `unverified`.)"""
        return not self.lost and not self.skipped

    @property
    def verified_complete(self) -> bool:
        """True when no edit is known to be missing and nothing was left unverifiable."""
        return self.complete and not self.unverified

    def summary(self) -> str:
        """A few lines for the user: what was recovered, what was verified, the damage, what was lost, and what
        cannot be verified. It claims no more than the files show: never that nothing was lost."""
        if not self.complete:
            verdict = "some edits could not be recovered."
        elif self.unverified:
            verdict = "every verified edit was restored, but not everything can be verified (below)."
        else:
            verdict = "no edit recorded in the journal or the checkpoint is missing."
        lines = [f"Recovered from {self.start} + {self.replayed} edit records replayed from the journal: {verdict}"]
        if self.verified:
            lines.append(f"verified: {self.verified}")
        lines.extend(self.damage)
        if self.lost:
            lines.append(f"not recovered: journal records {_ranges(self.lost)} (damaged)")
        lines.extend(f"not recovered: {s}" for s in self.skipped)
        lines.extend(f"cannot be verified: {s}" for s in self.unverified)
        if self.aside:
            lines.append("damaged bytes kept in " + ", ".join(self.aside))
        return "\n".join(lines)


def _ranges(seqs: tuple[int, ...]) -> str:
    out: list[str] = []
    start = prev = seqs[0]
    for s in seqs[1:]:
        if s == prev + 1:
            prev = s
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        start = prev = s
    out.append(f"{start}" if start == prev else f"{start}-{prev}")
    return ", ".join(out)


HISTORY_BYTES = 256 << 20
"""Default bytes of edit arrays the undo/redo history keeps in memory (`LabelStore.history_bytes`)."""


@dataclass(frozen=True)
class JournalEdit:
    """An edit on the undo/redo history that lives in the journal only (`labels.StoredEdit`)."""

    record: Record
    """The journal's "do" record of the edit."""
    label: str
    group: str
    seq: int

    @classmethod
    def of(cls, r: Record) -> JournalEdit:
        """The stored edit of a "do" record (its header is checked now, its arrays when it is read).

        Raises:
            ValueError, KeyError, TypeError: the header does not describe an edit.
        """
        table_from_json(r.header.get("table_before", {}))
        table_from_json(r.header.get("table_after", {}))
        return cls(r, str(r.header.get("label", "")), str(r.header.get("group", "")), r.seq)

    def load(self) -> Delta:
        """The edit, read back from the journal.

        Raises:
            JournalError: the record cannot be read or is not an edit any more.
        """
        arrays = self.record.arrays
        try:
            return record_to_delta(dataclasses.replace(self.record, loaded=arrays))
        except (KeyError, ValueError, TypeError) as exc:
            raise JournalError(f"the edit of journal record {self.seq} cannot be read back ({exc})") from exc


class LabelStore:
    """The label set behind one lock, journalled and autosaved. All edits from all clients go through here.

    Args:
        num_vertices: N.
        journal_path: `<out>/<stem>.journal`.
        label_path: `<out>/<stem>.labels.npz` (checkpoint).
        scan_id: scan identity stored in the journal's base record and checked on reopen
            (vertex count, and a `content_hash` from `scan_fingerprint` when given).
        initial_labels: (N,) labels for a *new* session (ignored when a journal exists).
        initial_instances: table for a new session.
        autosave_delay: seconds to wait after an edit before rewriting the label file (0 = write synchronously).
        accept_scan_mismatch: resume a journal whose recorded content hash differs from this scan's (the user
            says it is the same scan, e.g. re-exported); the new identity is recorded.
        history_bytes: bytes of vertex arrays the undo/redo history may hold in memory; older edits stay in the
            journal only and are read back from it when they are undone or redone (every edit is undoable).

    Raises:
        JournalError: journal belongs to another scan, or is in use by another process.
    """

    def __init__(
        self,
        num_vertices: int,
        *,
        journal_path: str | os.PathLike[str],
        label_path: str | os.PathLike[str],
        scan_id: dict[str, Any] | None = None,
        initial_labels: np.ndarray | None = None,
        initial_instances: list[InstanceInfo] | None = None,
        autosave_delay: float = 0.5,
        accept_scan_mismatch: bool = False,
        history_bytes: int = HISTORY_BYTES,
    ) -> None:
        self.n = int(num_vertices)
        self.history_bytes = int(history_bytes)
        self.lock = threading.RLock()
        self.label_path = Path(label_path)
        self.scan_id = {**(scan_id or {}), "num_vertices": self.n}
        self.autosave_delay = float(autosave_delay)
        self.accept_scan_mismatch = bool(accept_scan_mismatch)
        self.listeners: list[Listener] = []
        self.problem_listeners: list[ProblemListener] = []
        """Called with a one-line message when an autosave fails, and with None when saving works again."""
        self.problem: str | None = None
        """The current autosave problem, None when the checkpoint is up to date or saving works."""
        self.last_save_s = 0.0
        self.resumed = False
        self.recovery: RecoveryReport | None = None
        """Set when reopening found damage or a newer checkpoint than the journal; None for a clean resume."""
        self.journal = Journal(journal_path)
        try:
            self.labelset = self._recover(initial_labels, initial_instances)
        except BaseException:
            self.journal.close()
            raise
        self._saved_seq = -2
        self._dirty = threading.Event()
        self._closed = threading.Event()
        self._saver = threading.Thread(target=self._autosave_loop, name="annotator-autosave", daemon=True)
        if self.autosave_delay > 0:
            self._saver.start()
        try:
            self.save_now()
        except OSError as exc:
            self._set_problem(f"the checkpoint {self.label_path.name} could not be written ({exc}); every edit is "
                              "still in the journal")

    # ------------------------------------------------------------------ recovery
    def _check_scan(self, recorded: dict[str, Any], where: str) -> None:
        jn = int(recorded.get("num_vertices", -1))
        if jn != self.n:
            raise JournalError(
                f"{where} belongs to a scan with {jn} vertices, this scan has {self.n}; choose another --out directory"
            )
        have, want = recorded.get("content_hash"), self.scan_id.get("content_hash")
        if have and want and have != want:
            if self.accept_scan_mismatch:
                log.warning("%s was written for different scan content (%s, now %s); resuming as asked",
                            where, have, want)
                return
            raise JournalError(
                f"{where} was labelled on a different scan: same vertex count ({self.n}) but other geometry "
                f"(content hash {have[:20]}…, this scan {want[:20]}…); its labels would land on the wrong points. "
                "Choose another --out, or pass --accept-scan-mismatch if this really is the same scan"
            )

    def _recover(self, initial_labels: np.ndarray | None, initial_instances: list[InstanceInfo] | None) -> LabelSet:
        """Open the labels: a new session's start labels, or the newest verifiable full state (a journal base or
        snapshot record, or the checkpoint) with the journal's later edits replayed and the undo/redo history
        rebuilt over the whole journal. Sets `resumed`, and `recovery` when there was damage to report.

        Raises:
            JournalError: another scan's journal or label file, or a journal damaged beyond recovery.
        """
        j = self.journal
        recs = j.records
        ck, ck_problem = self._read_checkpoint(has_records=bool(recs))
        if not recs and not j.damage:
            return self._start_new(initial_labels, initial_instances, ck)
        # The scan identity: the newest full-state record's, else the checkpoint's check above.
        states = [r for r in recs if r.kind in ("base", "snapshot")]
        for r in reversed(states):
            if "scan" in r.header:
                self._check_scan(r.header["scan"], f"journal {j.path}")
                break
        self.resumed = True
        ls, start_seq, start_name = self._start_state(states, ck)
        newest = max([r.seq for r in recs], default=-1)
        j.next_seq = max(j.next_seq, start_seq + 1, newest + 1)
        replay = _replay_history(recs, ls, start_seq)
        ck_seq = ck[2] if ck is not None else -1
        ck_newer = ck_seq > newest
        if ck_newer:  # the edits between the journal's end and the checkpoint are unknown: history restarts here,
            # as across any missing record (undoing the journal's last edit on top of them would corrupt labels)
            replay.undo.clear()
            replay.redo.clear()
        ls.undo_stack = replay.undo
        ls.redo_stack = replay.redo
        report = _recovery_report(j, start_seq=start_seq, start_name=start_name, replay=replay,
                                  ck_seq=ck_seq if ck is not None else None, ck_problem=ck_problem,
                                  newest=newest, label_name=self.label_path.name)
        if report is not None:
            self.recovery = report
            log.warning("journal %s recovery:\n%s", j.path.name, self.recovery.summary())
        # Make the journal alone reproduce the recovered state, whatever happens to the checkpoint later: a full
        # snapshot when replaying it would not (records missing since its newest full state, skipped records, a
        # newer checkpoint), or when the scan identity changed on purpose.
        last_state = states[-1].seq if states else -1
        scan_changed = self.accept_scan_mismatch and bool(states) and (
            states[-1].header.get("scan", {}).get("content_hash") != self.scan_id.get("content_hash")
        )
        if replay.skipped or ck_newer or scan_changed or any(g > last_state for g in j.gaps):
            lab, table = ls.snapshot()
            j.append("snapshot", {"scan": self.scan_id, "table": table_to_json(table)}, {"labels": lab})
        log.info(
            "resumed %s: %d journal records, start %s, %d undoable edits",
            j.path.name, len(recs), start_name, len(replay.undo),
        )
        return ls

    def _read_checkpoint(self, *, has_records: bool) -> tuple[_Checkpoint | None, str]:
        """The label file (the checkpoint), checked against this scan.

        Returns:
            Its (labels, table, newest record) or None when there is none or it is unusable, and a line saying
            why it is unusable ("" when it is fine or missing).

        Raises:
            JournalError: it is unusable and there is no journal to replay instead (it is never overwritten).
        """
        if not self.label_path.exists():
            return None, ""
        try:
            lab, table, seq, scan = read_label_file_with_scan(self.label_path, self.n)
            self._check_scan({**scan, "num_vertices": self.n}, f"label file {self.label_path}")
            return (lab, table, seq), ""
        except JournalError as exc:
            if not has_records:
                raise JournalError(f"{exc}; refusing to overwrite it — move it away or choose another --out") from exc
            log.warning("%s; replaying the journal instead", exc)
            return None, f"the checkpoint could not be used ({exc})"

    def _start_new(self, initial_labels: np.ndarray | None, initial_instances: list[InstanceInfo] | None,
                   ck: _Checkpoint | None) -> LabelSet:
        """A session without journal records: the start labels (or a checkpoint whose journal was deleted by
        hand), written as the journal's base record."""
        ls = LabelSet(self.n, initial_labels, initial_instances)
        if ck is not None:  # an existing checkpoint without a journal (journal deleted by hand)
            ls = LabelSet(self.n, ck[0], ck[1].values())
            log.warning("no journal next to %s: resuming from the label file alone", self.label_path)
            self.resumed = True
        lab, table = ls.snapshot()
        self.journal.append("base", {"scan": self.scan_id, "table": table_to_json(table)}, {"labels": lab})
        return ls

    def _start_state(self, states: list[Record], ck: _Checkpoint | None) -> tuple[LabelSet, int, str]:
        """The newest valid full state to replay from: the newest base/snapshot record or the checkpoint, whichever
        holds more records (never an older one).

        Returns:
            The labels, the sequence number they hold records up to, and a name for the report.

        Raises:
            JournalError: neither a full-state record nor a usable checkpoint.
        """
        start_seq, start_name = -1, ""
        ls: LabelSet | None = None
        if states and not (ck is not None and ck[2] > states[-1].seq):  # (a newer checkpoint: never read it)
            r = states[-1]
            table = {k: v for k, v in table_from_json(r.header.get("table", {})).items() if v is not None}
            ls = LabelSet(self.n, r.arrays["labels"], table.values())
            start_seq, start_name = r.seq, ("journal base record" if r.kind == "base" else f"snapshot record {r.seq}")
        if ck is not None and ck[2] >= 0 and ck[2] > start_seq:
            ls = LabelSet(self.n, ck[0], ck[1].values())
            start_seq, start_name = ck[2], f"checkpoint (record {ck[2]})"
        if ls is None:
            raise JournalError(
                f"journal {self.journal.path} is damaged beyond recovery (no verifiable full state, no usable "
                f"checkpoint); the damaged file is kept in {self.journal.aside}"
            )
        return ls, start_seq, start_name

    # ------------------------------------------------------------------ editing
    def do(self, build: Callable[[LabelSet], Delta], *, client: str = "", group: str = "") -> Delta | None:
        """Build an edit from the current state and apply it, all under the lock.

        Args:
            build: called with the label set (under the lock) and returns the delta to apply; it may raise
                ValueError/KeyError to refuse the edit.
            client: who made the edit (stored in the journal).
            group: stroke id; adjacent edits of one group undo together.

        Returns:
            The applied delta, or None when it changed nothing (nothing is journalled then).

        Raises:
            JournalError: the journal could not be written (the edit is not applied).
        """
        with self.lock:
            d = build(self.labelset)
            if d.is_empty:
                return None
            if group:
                d = dataclasses.replace(d, group=group)
            header, arrays = delta_to_record(d)
            seq = self.journal.append("do", {**header, "client": client}, arrays)
            d = dataclasses.replace(d, seq=seq)
            self.labelset.apply(d)
            self._trim_history()
            self._changed(d, "do")
            return d

    def undo(self, *, client: str = "") -> list[Delta]:
        """Undo the last edit or stroke (of any client); returns the applied inverses (empty: nothing to undo)."""
        with self.lock:
            if not self.labelset.undo_stack:
                return []
            loaded = LabelSet.top_group(self.labelset.undo_stack)  # may fail: then nothing has changed
            self.journal.append("undo", {"client": client})
            applied = self.labelset.undo(loaded)
            self._trim_history()
            for d in applied:
                self._changed(d, "undo")
            return applied

    def redo(self, *, client: str = "") -> list[Delta]:
        """Redo the last undone edit or stroke; returns the applied deltas (empty: nothing to redo)."""
        with self.lock:
            if not self.labelset.redo_stack:
                return []
            loaded = LabelSet.top_group(self.labelset.redo_stack)
            self.journal.append("redo", {"client": client})
            applied = self.labelset.redo(loaded)
            self._trim_history()
            for d in applied:
                self._changed(d, "redo")
            return applied

    def history_in_memory(self) -> int:
        """Bytes of vertex arrays the undo/redo history holds in memory now."""
        ls = self.labelset
        return sum(e.nbytes for e in (*ls.undo_stack, *ls.redo_stack) if isinstance(e, Delta))

    def _trim_history(self) -> None:
        """Keep the newest edits in memory up to `history_bytes`; older ones are left to the journal."""
        ls = self.labelset
        budget = self.history_bytes
        for stack in (ls.undo_stack, ls.redo_stack):
            for i in range(len(stack) - 1, -1, -1):
                e = stack[i]
                if not isinstance(e, Delta):
                    continue
                if e.seq >= 0 and e.nbytes > budget:
                    rec = self.journal.record(e.seq)
                    if rec is not None:
                        stack[i] = JournalEdit.of(rec)
                        continue
                budget -= e.nbytes

    def _changed(self, d: Delta, how: str) -> None:
        if self.autosave_delay <= 0:
            try:
                self.save_now()
            except OSError as exc:
                self._set_problem(f"autosave of {self.label_path.name} failed ({exc}); every edit is still in "
                                  "the journal")
        else:
            self._dirty.set()
        for fn in list(self.listeners):
            try:
                fn(d, how)
            except Exception:  # a broken view must not lose the edit
                log.exception("label listener %r failed", fn)

    # ------------------------------------------------------------------ saving
    def _set_problem(self, msg: str | None) -> None:
        if msg == self.problem:
            return
        self.problem = msg
        if msg:
            log.error("%s", msg)
        for fn in list(self.problem_listeners):
            try:
                fn(msg)
            except Exception:
                log.exception("problem listener %r failed", fn)

    def save_now(self) -> float:
        """Rewrite the label file now (atomic); returns seconds taken. No-op when already up to date.

        Raises:
            OSError: the file could not be written (the journal still holds every edit).
        """
        with self.lock:
            seq = self.journal.next_seq - 1
            if seq == self._saved_seq:
                return 0.0
            labels, table = self.labelset.snapshot()
        t0 = time.perf_counter()
        write_label_file(self.label_path, labels, table, seq=seq, scan_id=self.scan_id)
        dt = time.perf_counter() - t0
        with self.lock:
            self._saved_seq = max(self._saved_seq, seq)
            self.last_save_s = dt
        if self.problem:
            self._set_problem(None)
        return dt

    def _autosave_loop(self) -> None:
        while not self._closed.is_set():
            if not self._dirty.wait(timeout=0.5):
                continue
            time.sleep(self.autosave_delay)
            self._dirty.clear()
            try:
                self.save_now()
            except Exception as exc:
                self._set_problem(f"autosave of {self.label_path.name} failed ({exc}); every edit is still in "
                                  "the journal, retrying")
                self._dirty.set()  # retry after the next delay
                time.sleep(max(1.0, self.autosave_delay))

    def close(self) -> None:
        """Final save, stop the autosave thread, release the journal."""
        self._closed.set()
        try:
            self.save_now()
        except OSError as exc:
            log.error("final save of %s failed (%s); the journal holds every edit and is replayed next time",
                      self.label_path, exc)
        finally:
            self.journal.close()

    # ------------------------------------------------------------------ read helpers
    @property
    def labels(self) -> np.ndarray:
        return self.labelset.labels

    def snapshot(self) -> tuple[np.ndarray, dict[int, InstanceInfo]]:
        with self.lock:
            return self.labelset.snapshot()


_Checkpoint = tuple[np.ndarray, dict[int, InstanceInfo], int]
"""A checkpoint as recovery reads it: (N,) int32 labels, the instance table, the newest journal record it holds."""


class _Replay(NamedTuple):
    """The journal replayed over a start state (`_replay_history`)."""

    undo: list[HistoryEntry]
    """The rebuilt undo stack (oldest first)."""
    redo: list[HistoryEntry]
    """The rebuilt redo stack."""
    skipped: list[str]
    """Verified records that could not be replayed, and why."""
    replayed: int
    """Records applied to the labels (those after the start state)."""


def _replay_history(recs: list[Record], ls: LabelSet, start_seq: int) -> _Replay:
    """Rebuild the undo/redo history over all journal records with the same stack logic as `LabelSet`, applying to
    `ls` only the records after `start_seq` (the start state holds the others). History cannot be undone across a
    missing record: the stacks restart there. Edits older than the start state are read only if they are undone.
    """
    undo: list[HistoryEntry] = []
    redo: list[HistoryEntry] = []
    skipped: list[str] = []
    replayed = 0
    prev = -1
    for r in recs:
        if r.seq != prev + 1:
            undo.clear()
            redo.clear()
        prev = r.seq
        apply_now = r.seq > start_seq
        if r.kind in ("base", "snapshot"):
            continue  # full states: the newest one (or a newer checkpoint) is the start state
        if r.kind == "do":
            try:
                entry: HistoryEntry = JournalEdit.of(r)
                if apply_now:  # read it now; older edits are read only if they are undone
                    d = record_to_delta(r)
                    forced = _force_apply(ls, d)
                    replayed += 1
                    if forced is not d:  # not what the record holds: keep this one in memory
                        entry = dataclasses.replace(forced, seq=-1)
            except (KeyError, ValueError, TypeError) as exc:
                skipped.append(f"record {r.seq}: unreadable edit ({exc})")
                undo.clear()
                redo.clear()
                continue
            undo.append(entry)
            redo.clear()
        elif r.kind in ("undo", "redo"):
            src, dst = (undo, redo) if r.kind == "undo" else (redo, undo)
            if not src:
                if apply_now:
                    skipped.append(f"record {r.seq}: {r.kind} of an edit in the damaged part")
                continue
            group = src[-1].group
            while src:
                e = src.pop()
                if apply_now:
                    d = e.load()
                    _force_apply(ls, d.inverse() if r.kind == "undo" else d)
                dst.append(e)
                if not group or not src or src[-1].group != group:
                    break
            if apply_now:
                replayed += 1
    return _Replay(undo, redo, skipped, replayed)


def _recovery_report(j: Journal, *, start_seq: int, start_name: str, replay: _Replay, ck_seq: int | None,
                     ck_problem: str, newest: int, label_name: str) -> RecoveryReport | None:
    """What a reopened session recovered and what it could not; None when there is nothing to report (no damage,
    no lost or skipped record, no checkpoint newer than the journal).

    Args:
        j: the opened journal (its damage, gaps, torn end and aside file).
        start_seq, start_name: the start state (`LabelStore._start_state`).
        replay: the journal replayed over it.
        ck_seq: the newest record the checkpoint holds; None without a usable checkpoint.
        ck_problem: why the checkpoint is unusable ("" when it is fine or missing).
        newest: the journal's newest record (-1: none).
        label_name: the checkpoint's file name.
    """
    lost = tuple(s for s in j.gaps if s > start_seq)
    damage = list(j.damage)
    if ck_problem:
        damage.append(ck_problem)
    seq = ck_seq if ck_seq is not None else -1
    if seq > newest:
        damage.append(f"the journal ends at record {newest}, the checkpoint holds records up to {seq}: "
                      "resumed from the checkpoint")
    if not (damage or lost or replay.skipped):
        return None
    seqs = [r.seq for r in j.records]
    checkpoint = (f"holds records up to {seq}" if ck_seq is not None
                  else "unreadable" if ck_problem else f"missing ({label_name})")
    unverified: list[str] = []
    if j.torn_at is not None and seq <= newest:
        unverified.append(
            f"whether edits followed record {newest}: a crash during an edit leaves an incomplete last "
            "record (that edit was never acknowledged), but so does a journal cut short, and then every "
            "later edit is gone; "
            + ("there is no checkpoint to compare with" if ck_seq is None else
               f"the checkpoint holds nothing newer (record {seq})"))
    return RecoveryReport(
        start=start_name,
        replayed=replay.replayed,
        damage=tuple(damage),
        lost=lost,
        skipped=tuple(replay.skipped),
        aside=(j.aside.name,) if j.aside is not None else (),
        verified=(f"{len(seqs)} journal records ({_ranges(tuple(seqs))}, checksums match)" if seqs
                  else "no journal record") + f"; checkpoint: {checkpoint}",
        unverified=tuple(unverified),
    )


def _force_apply(ls: LabelSet, d: Delta) -> Delta:
    """Apply a replayed delta even when an unrecoverable earlier record changed the same vertices.

    The `after` values are absolute, so they are set as recorded; `before` is taken from the current labels (so
    counts stay right). Returns the delta as applied (== `d` when nothing was missing).
    """
    if len(d.idx):
        cur = ls.labels[d.idx]
        if not np.array_equal(cur, d.before):
            d = dataclasses.replace(d, before=cur.astype(np.int32))
    ls._apply_raw(d)
    return d
