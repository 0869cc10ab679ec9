"""Append-only edit journal, the atomic label file, and `LabelStore` (the one lock around the labels).

Durability contract: `LabelStore.do/undo/redo` first append the edit to the journal and fsync it, then apply it
in memory, then return (the acknowledgement). A kill -9 at any moment therefore loses at most the edit in flight.
The label file (`<stem>.labels.npz`) is a checkpoint rewritten atomically (temp file in the same directory, fsync,
rename, fsync of the directory), debounced in a background thread; it records the journal sequence number it
contains. Reopening loads the checkpoint and replays the journal records after it; the undo/redo stacks are
rebuilt from the whole journal, so undo/redo survive a restart.

Journal file format (`<stem>.journal`): a sequence of records
``b"EFJ1" | u32 payload length | u32 crc32(payload) | payload``, payload = ``u32 header length | JSON header |
raw little-endian arrays`` (the header lists each array's name, dtype and length). Record kinds: ``base`` (first
record: full initial labels + table + scan identity), ``do`` (a `Delta`), ``undo``, ``redo``. A torn last record
(crash during append) fails its length/CRC check; it is moved aside to ``<journal>.torn-<time>`` and dropped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from annotator.labels import (
    LABELS_SCHEMA_VERSION,
    Delta,
    InstanceInfo,
    LabelSet,
    table_from_json,
    table_to_json,
)

log = logging.getLogger(__name__)

MAGIC = b"EFJ1"
_HEAD = struct.Struct("<4sII")


class JournalError(ValueError):
    """A journal or label file that cannot be used (wrong scan, corrupt, locked by another process)."""


# ---------------------------------------------------------------------------------------------- atomic files
def atomic_write_bytes(path: str | os.PathLike[str], writer: Callable[[Any], None]) -> None:
    """Write a file atomically with `efem_viz.data.io.atomic_write` (temp file in the same directory, fsync,
    rename, directory fsync), handing `writer` an open binary file object.

    Args:
        path: destination; an existing symlink at `path` is refused (never replaced or written through).
        writer: called with a binary file object open for writing.

    Raises:
        JournalError: `path` is a symlink.
    """
    from efem_viz.data.io import atomic_write

    p = Path(path)
    if p.is_symlink():
        raise JournalError(f"refusing to overwrite {p}: it is a symbolic link")

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            writer(f)

    atomic_write(p, write)


# ---------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Record:
    """One journal record."""

    seq: int
    """1-based sequence number (the base record is 0)."""
    kind: str
    """"base", "do", "undo" or "redo"."""
    header: dict[str, Any]
    """The JSON header (label, time, client, table changes, scan identity...)."""
    arrays: dict[str, np.ndarray]
    """Named arrays: for "do": idx, before, after; for "base": labels."""


def _encode(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    specs = []
    blobs = []
    for name, a in arrays.items():
        arr = np.ascontiguousarray(a)
        if arr.size > 0 and np.all(arr == arr.flat[0]):
            specs.append({"name": name, "dtype": arr.dtype.str, "n": int(arr.size), "const": arr.flat[0].item()})
            continue
        specs.append({"name": name, "dtype": arr.dtype.str, "n": int(arr.size)})
        blobs.append(arr.astype(arr.dtype.newbyteorder("<"), copy=False).tobytes())
    h = dict(header)
    h["arrays"] = specs
    hb = json.dumps(h, separators=(",", ":")).encode()
    return struct.pack("<I", len(hb)) + hb + b"".join(blobs)


def _decode(payload: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    (hlen,) = struct.unpack_from("<I", payload, 0)
    header = json.loads(payload[4 : 4 + hlen].decode())
    off = 4 + hlen
    arrays: dict[str, np.ndarray] = {}
    for spec in header.pop("arrays", []):
        dt = np.dtype(spec["dtype"]).newbyteorder("<")
        n = int(spec["n"])
        if "const" in spec:
            arrays[spec["name"]] = np.full(n, spec["const"], dtype=dt)
            continue
        nbytes = n * dt.itemsize
        if off + nbytes > len(payload):
            raise JournalError("array extends past the record")
        arrays[spec["name"]] = np.frombuffer(payload, dtype=dt, count=n, offset=off).copy()
        off += nbytes
    return header, arrays


def delta_to_record(d: Delta) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    header = {
        "label": d.label,
        "table_before": table_to_json(d.table_before),
        "table_after": table_to_json(d.table_after),
        "group": d.group,
    }
    return header, {"idx": d.idx.astype(np.int32), "before": d.before.astype(np.int32), "after": d.after.astype(np.int32)}


def record_to_delta(r: Record) -> Delta:
    return Delta(
        label=str(r.header.get("label", "")),
        idx=r.arrays["idx"].astype(np.int32),
        before=r.arrays["before"].astype(np.int32),
        after=r.arrays["after"].astype(np.int32),
        table_before=table_from_json(r.header.get("table_before", {})),
        table_after=table_from_json(r.header.get("table_after", {})),
        group=str(r.header.get("group", "")),
    )


class Journal:
    """An append-only, fsynced record file, held with an exclusive lock (one writer process per journal).

    Args:
        path: the journal file (created when missing).

    Raises:
        JournalError: another process holds the journal.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if self.path.is_symlink():
            raise JournalError(f"refusing to use journal {self.path}: it is a symbolic link")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock_file = open(str(self.path) + ".lock", "a+b")
        try:
            import fcntl

            fcntl.flock(self._lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock_file.close()
            raise JournalError(
                f"{self.path} is in use by another annotator process; close it or choose another --out"
            ) from None
        except ImportError:  # pragma: no cover - non-POSIX
            pass
        self.records: list[Record] = list(self._read_and_repair())
        self._f = open(self.path, "ab")
        self.next_seq = (self.records[-1].seq + 1) if self.records else 0
        self.bytes_written = 0

    def _read_and_repair(self) -> Iterator[Record]:
        if not self.path.exists():
            return
        data = self.path.read_bytes()
        off = 0
        good_end = 0
        out: list[Record] = []
        while off + _HEAD.size <= len(data):
            magic, length, crc = _HEAD.unpack_from(data, off)
            start = off + _HEAD.size
            if magic != MAGIC or start + length > len(data):
                break
            payload = data[start : start + length]
            if zlib.crc32(payload) != crc:
                break
            try:
                header, arrays = _decode(payload)
            except (ValueError, KeyError, json.JSONDecodeError, struct.error) as exc:
                log.warning("journal %s: undecodable record at byte %d: %s", self.path, off, exc)
                break
            out.append(Record(int(header.pop("seq")), str(header.pop("kind")), header, arrays))
            off = start + length
            good_end = off
        if good_end < len(data):
            torn = self.path.with_name(f"{self.path.name}.torn-{int(time.time() * 1000)}")
            torn.write_bytes(data[good_end:])
            with open(self.path, "r+b") as f:
                f.truncate(good_end)
                f.flush()
                os.fsync(f.fileno())
            log.warning(
                "journal %s: dropped an incomplete last record (%d bytes, kept in %s) — the edit in flight "
                "when the annotator stopped",
                self.path,
                len(data) - good_end,
                torn.name,
            )
        yield from out

    def append(self, kind: str, header: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> int:
        """Append one record and fsync it; returns its sequence number."""
        seq = self.next_seq
        h = {"seq": seq, "kind": kind, "time": time.time(), **header}
        payload = _encode(h, arrays or {})
        rec = _HEAD.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload
        self._f.write(rec)
        self._f.flush()
        os.fsync(self._f.fileno())
        self.bytes_written += len(rec)
        self.next_seq += 1
        self.records.append(Record(seq, kind, {k: v for k, v in h.items() if k not in ("seq", "kind")}, arrays or {}))
        return seq

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._f.close()
        with contextlib.suppress(Exception):
            self._lock_file.close()


# ---------------------------------------------------------------------------------------------- label file
def write_label_file(
    path: str | os.PathLike[str],
    labels: np.ndarray,
    table: dict[int, InstanceInfo],
    *,
    seq: int,
    scan_id: dict[str, Any],
) -> None:
    """Atomically write the checkpoint label file (NPZ, uncompressed: fast for 1M+ vertices).

    Args:
        path: destination `.npz`.
        labels: (N,) int32.
        table: instance table.
        seq: the last journal sequence number included.
        scan_id: scan identity (vertex count, file name) checked on load.
    """

    def writer(f: Any) -> None:
        np.savez(
            f,
            schema_version=np.array(LABELS_SCHEMA_VERSION, np.int32),
            instance=np.ascontiguousarray(labels, np.int32),
            instances_json=np.array(json.dumps(table_to_json(table))),
            journal_seq=np.array(seq, np.int64),
            scan_json=np.array(json.dumps(scan_id)),
        )

    atomic_write_bytes(path, writer)


def read_label_file(path: str | os.PathLike[str], n: int) -> tuple[np.ndarray, dict[int, InstanceInfo], int]:
    """Read a checkpoint label file; returns (labels (N,) int32, table, journal seq).

    Raises:
        JournalError: unreadable, or written for a scan with another vertex count.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            labels = np.asarray(z["instance"])
            table_raw = json.loads(str(z["instances_json"])) if "instances_json" in z else {}
            seq = int(z["journal_seq"]) if "journal_seq" in z else -1
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
        raise JournalError(f"cannot read label file {path}: {exc}") from exc
    if labels.shape != (n,):
        raise JournalError(f"label file {path} has {labels.shape} labels, but the scan has {n} vertices")
    table = {k: v for k, v in table_from_json(table_raw).items() if v is not None}
    return labels.astype(np.int32), table, seq


# ---------------------------------------------------------------------------------------------- the store
Listener = Callable[[Delta, str], None]


class LabelStore:
    """The label set behind one lock, journalled and autosaved. All edits from all clients go through here.

    Args:
        num_vertices: N.
        journal_path: `<out>/<stem>.journal`.
        label_path: `<out>/<stem>.labels.npz` (checkpoint).
        scan_id: scan identity stored in the journal's base record and checked on reopen
            (must contain "num_vertices").
        initial_labels: (N,) labels for a *new* session (ignored when a journal exists).
        initial_instances: table for a new session.
        autosave_delay: seconds to wait after an edit before rewriting the label file (0 = write synchronously).

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
    ) -> None:
        self.n = int(num_vertices)
        self.lock = threading.RLock()
        self.label_path = Path(label_path)
        self.scan_id = {"num_vertices": self.n, **(scan_id or {})}
        self.autosave_delay = float(autosave_delay)
        self.listeners: list[Listener] = []
        self.last_save_s = 0.0
        self.resumed = False
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
        self.save_now()

    # ------------------------------------------------------------------ recovery
    def _recover(self, initial_labels: np.ndarray | None, initial_instances: list[InstanceInfo] | None) -> LabelSet:
        recs = self.journal.records
        if not recs:
            ls = LabelSet(self.n, initial_labels, initial_instances)
            # An existing checkpoint without a journal (journal deleted by hand): start from the checkpoint.
            if self.label_path.exists():
                try:
                    lab, table, _ = read_label_file(self.label_path, self.n)
                    ls = LabelSet(self.n, lab, table.values())
                    log.warning("no journal next to %s: resuming from the label file alone", self.label_path)
                    self.resumed = True
                except JournalError as exc:
                    raise JournalError(
                        f"{exc}; refusing to overwrite it — move it away or choose another --out"
                    ) from exc
            lab, table = ls.snapshot()
            self.journal.append(
                "base",
                {"scan": self.scan_id, "table": table_to_json(table)},
                {"labels": lab},
            )
            return ls
        base = recs[0]
        if base.kind != "base":
            raise JournalError(f"journal {self.journal.path} does not start with a base record")
        jn = int(base.header.get("scan", {}).get("num_vertices", -1))
        if jn != self.n:
            raise JournalError(
                f"journal {self.journal.path} belongs to a scan with {jn} vertices, this scan has {self.n}; "
                "choose another --out directory"
            )
        self.resumed = True
        # Start state: the checkpoint when it is valid, else the base record.
        start_seq = 0
        base_table = {k: v for k, v in table_from_json(base.header.get("table", {})).items() if v is not None}
        ls = LabelSet(self.n, base.arrays["labels"], base_table.values())
        if self.label_path.exists():
            try:
                lab, table, seq = read_label_file(self.label_path, self.n)
                if 0 <= seq <= recs[-1].seq:
                    ls = LabelSet(self.n, lab, table.values())
                    start_seq = seq
                else:
                    log.warning("label file %s is newer than the journal; replaying the journal", self.label_path)
            except JournalError as exc:
                log.warning("%s; replaying the whole journal instead", exc)
        # Rebuild history over all records with the same stack logic as LabelSet; apply to the labels only the
        # records after the checkpoint.
        undo: list[Delta] = []
        redo: list[Delta] = []
        for r in recs[1:]:
            apply_now = r.seq > start_seq
            if r.kind == "do":
                d = record_to_delta(r)
                if apply_now:
                    ls._apply_raw(d)
                undo.append(d)
                redo.clear()
            elif r.kind in ("undo", "redo"):
                src, dst = (undo, redo) if r.kind == "undo" else (redo, undo)
                if not src:
                    raise JournalError(f"journal {self.journal.path}: {r.kind} record {r.seq} with empty history")
                group = src[-1].group
                while src:
                    d = src.pop()
                    if apply_now:
                        ls._apply_raw(d.inverse() if r.kind == "undo" else d)
                    dst.append(d)
                    if not group or not src or src[-1].group != group:
                        break
            else:
                raise JournalError(f"journal {self.journal.path}: unknown record kind {r.kind!r}")
        ls.undo_stack = undo
        ls.redo_stack = redo
        log.info(
            "resumed %s: %d journal records, checkpoint at %d, %d undoable edits",
            self.journal.path.name,
            len(recs),
            start_seq,
            len(undo),
        )
        return ls

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
        """
        with self.lock:
            d = build(self.labelset)
            if d.is_empty:
                return None
            if group:
                d = dataclasses.replace(d, group=group)
            header, arrays = delta_to_record(d)
            self.journal.append("do", {**header, "client": client}, arrays)
            self.labelset.apply(d)
            self._changed(d, "do")
            return d

    def undo(self, *, client: str = "") -> list[Delta]:
        """Undo the last edit or stroke (of any client); returns the applied inverses (empty: nothing to undo)."""
        with self.lock:
            if not self.labelset.undo_stack:
                return []
            self.journal.append("undo", {"client": client})
            applied = self.labelset.undo()
            for d in applied:
                self._changed(d, "undo")
            return applied

    def redo(self, *, client: str = "") -> list[Delta]:
        """Redo the last undone edit or stroke; returns the applied deltas (empty: nothing to redo)."""
        with self.lock:
            if not self.labelset.redo_stack:
                return []
            self.journal.append("redo", {"client": client})
            applied = self.labelset.redo()
            for d in applied:
                self._changed(d, "redo")
            return applied

    def _changed(self, d: Delta, how: str) -> None:
        if self.autosave_delay <= 0:
            self.save_now()
        else:
            self._dirty.set()
        for fn in list(self.listeners):
            try:
                fn(d, how)
            except Exception:  # a broken view must not lose the edit
                log.exception("label listener %r failed", fn)

    # ------------------------------------------------------------------ saving
    def save_now(self) -> float:
        """Rewrite the label file now (atomic); returns seconds taken. No-op when already up to date."""
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
        return dt

    def _autosave_loop(self) -> None:
        while not self._closed.is_set():
            if not self._dirty.wait(timeout=0.5):
                continue
            time.sleep(self.autosave_delay)
            self._dirty.clear()
            try:
                self.save_now()
            except Exception:
                log.exception("autosave of %s failed (the journal still has every edit)", self.label_path)

    def close(self) -> None:
        """Final save, stop the autosave thread, release the journal."""
        self._closed.set()
        try:
            self.save_now()
        finally:
            self.journal.close()

    # ------------------------------------------------------------------ read helpers
    @property
    def labels(self) -> np.ndarray:
        return self.labelset.labels

    def snapshot(self) -> tuple[np.ndarray, dict[int, InstanceInfo]]:
        with self.lock:
            return self.labelset.snapshot()
