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
import hashlib
import json
import logging
import os
import struct
import threading
import time
import zipfile
import zlib
from glob import escape as glob_escape
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from annotator.labels import (
    LABELS_SCHEMA_VERSION,
    Delta,
    HistoryEntry,
    InstanceInfo,
    LabelSet,
    table_from_json,
    table_to_json,
)
from efem_viz.data.io import atomic_write, atomic_write_bytes

log = logging.getLogger(__name__)

MAGIC = b"EFJ1"
_HEAD = struct.Struct("<4sII")
RECORD_KINDS = ("base", "snapshot", "do", "undo", "redo")
"""``base``: the first record, full labels + table + scan identity; ``snapshot``: a full state written after a
recovery or an accepted scan change (replay restarts from the newest full state); ``do``/``undo``/``redo``: edits."""


class JournalError(ValueError):
    """A journal or label file that cannot be used (wrong scan, corrupt, locked by another process)."""


# ---------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Record:
    """One journal record. Its arrays stay on disk until asked for (`arrays` reads them back each time), so an
    open journal costs memory for its headers only, whatever edits it holds."""

    seq: int
    """1-based sequence number (the base record is 0)."""
    kind: str
    """One of `RECORD_KINDS`."""
    header: dict[str, Any]
    """The JSON header (label, time, client, table changes, scan identity...)."""
    loaded: dict[str, np.ndarray] | None = field(default=None, repr=False)
    """The arrays when they are held in memory (a record being written), else None."""
    offset: int = -1
    """Byte offset of the record in its journal file."""
    journal: "Journal | None" = field(default=None, repr=False, compare=False)
    """The journal to read the arrays from."""

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        """Named arrays: for "do": idx, before, after; for "base"/"snapshot": labels.

        Raises:
            JournalError: the record can no longer be read back (the file changed under the annotator).
        """
        if self.loaded is not None:
            return self.loaded
        if self.journal is None:
            return {}
        return self.journal.read_arrays(self)


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
        seq=r.seq,
    )


class Journal:
    """An append-only, fsynced record file, held with an exclusive lock (one writer process per journal).

    Opening verifies every record (length, CRC, decodable header) and repairs the file:

    - a torn last record (a crash during append) is moved aside to ``<journal>.torn-<ms>`` and truncated away;
    - damage in the middle (a flipped byte, a garbage run) does not end the read: the reader resynchronises on the
      next record magic, keeps every record that verifies, copies the whole damaged file to
      ``<journal>.damaged-<ms>`` and rewrites the journal atomically with the verified records only;
    - a record whose sequence number repeats an earlier one (a failed append that was retried by an old version)
      supersedes the earlier ones from that number on.

    What was found is in `damage` (empty for a clean file); `gaps` lists the sequence numbers that are missing.

    Appends never leave a partial record behind: a failed write or fsync truncates the file back to the end of
    the last good record and raises, so the edit is refused and later appends land on a clean file.

    Args:
        path: the journal file (created when missing).

    Raises:
        JournalError: another process holds the journal, or it is a symbolic link.
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
        self.damage: list[str] = []
        """One line per problem found and repaired when the journal was opened."""
        self.damaged_bytes = 0
        self.aside: Path | None = None
        """Where damaged bytes (or the whole damaged file) were kept, if anywhere."""
        self.torn_at: int | None = None
        """Byte offset of an incomplete last record that was dropped (None: the journal ended on a whole record).
        A crash during an append leaves one, but so does a file cut short: what followed cannot be known."""
        try:
            self.records: list[Record] = self._read_and_repair()
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        except BaseException:
            self._lock_file.close()
            raise
        self._end = os.fstat(self._fd).st_size
        self.next_seq = (self.records[-1].seq + 1) if self.records else 0
        self.bytes_written = 0
        self.broken: str | None = None
        """Set when a failed append could not be undone: no further appends are accepted."""

    def record(self, seq: int) -> Record | None:
        """The record with sequence number `seq`, None when the journal has none."""
        import bisect

        i = bisect.bisect_left(self.records, seq, key=lambda r: r.seq)
        return self.records[i] if i < len(self.records) and self.records[i].seq == seq else None

    @property
    def gaps(self) -> list[int]:
        """Sequence numbers missing between the first verified record (or 0) and the last one."""
        seqs = [r.seq for r in self.records]
        missing: list[int] = []
        prev = -1
        for s in seqs:
            missing.extend(range(prev + 1, s))
            prev = s
        return missing

    def _read_and_repair(self) -> list[Record]:
        if not self.path.exists():
            return []
        clean = self._verify_streaming()
        if clean is not None:
            return clean
        data = self.path.read_bytes()
        out: list[tuple[Record, int, int]] = []  # (record, start offset, end offset)
        bad: list[tuple[int, int]] = []  # damaged byte ranges
        off = 0
        while off < len(data):
            rec = _parse_at(data, off)
            if rec is None:
                nxt = data.find(MAGIC, off + 1)
                end = len(data) if nxt < 0 else nxt
                bad.append((off, end))
                off = end
                continue
            r, end = rec
            while out and out[-1][0].seq >= r.seq:  # a retried append: the later record wins
                dropped = out.pop()[0]
                self.damage.append(f"record {dropped.seq} ({dropped.kind}) was superseded by a later copy")
            out.append((r, off, end))
            off = end
        records = [dataclasses.replace(r, loaded=None, offset=start, journal=self) for r, start, _ in out]
        if not bad and not self.damage:
            return records
        stamp = int(time.time() * 1000)
        self.damaged_bytes = sum(e - s for s, e in bad)
        tail_only = not self.damage and len(bad) == 1 and bad[0][1] == len(data)
        if tail_only:
            good_end = bad[0][0]
            self.aside = self.path.with_name(f"{self.path.name}.torn-{stamp}")
            self.aside.write_bytes(data[good_end:])
            with open(self.path, "r+b") as f:
                f.truncate(good_end)
                f.flush()
                os.fsync(f.fileno())
            self.torn_at = good_end
            self.damage.append(
                f"the journal ended in an incomplete record at byte {good_end:,} ({len(data) - good_end:,} bytes, "
                f"dropped; kept in {self.aside.name})"
            )
            log.warning("journal %s: %s", self.path, self.damage[-1])
            return records
        self.aside = self.path.with_name(f"{self.path.name}.damaged-{stamp}")
        self.aside.write_bytes(data)
        for s, e in bad:
            self.damage.append(f"{e - s} damaged bytes at offset {s} could not be verified")
        clean = b"".join(data[s:e] for _, s, e in out)
        atomic_write_bytes(self.path, clean)
        starts = np.cumsum([0] + [e - s for _, s, e in out])[:-1]
        records = [dataclasses.replace(r, offset=int(o)) for r, o in zip(records, starts)]
        log.warning(
            "journal %s was damaged: kept %d verified records, the damaged file is kept in %s (%s)",
            self.path, len(records), self.aside.name, "; ".join(self.damage),
        )
        return records

    def append(self, kind: str, header: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> int:
        """Append one record and fsync it; returns its sequence number.

        Raises:
            JournalError: the write or the fsync failed (disk full, I/O error); the journal is left exactly as it
                was before the call, and nothing was recorded.
        """
        if self.broken:
            raise JournalError(self.broken)
        if self._fd < 0:
            raise JournalError(f"the journal {self.path.name} is closed (the annotator is shutting down)")
        seq = self.next_seq
        h = {"seq": seq, "kind": kind, "time": time.time(), **header}
        payload = _encode(h, arrays or {})
        rec = _HEAD.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload
        try:
            view = memoryview(rec)
            while view:
                n = _os_write(self._fd, view)
                view = view[n:]
            _os_fsync(self._fd)
        except OSError as exc:
            why = exc.strerror or str(exc)
            try:
                os.ftruncate(self._fd, self._end)
                _os_fsync(self._fd)
            except OSError as exc2:
                self.broken = (
                    f"the journal {self.path.name} could not be written ({why}) nor repaired "
                    f"({exc2.strerror or exc2}); restart the annotator once the disk is writable"
                )
                raise JournalError(self.broken) from exc
            raise JournalError(f"the edit was not saved: cannot write the journal ({why}); nothing changed") from exc
        offset = self._end
        self._end += len(rec)
        self.bytes_written += len(rec)
        self.next_seq += 1
        self.records.append(Record(seq, kind, {k: v for k, v in h.items() if k not in ("seq", "kind")},
                                   offset=offset, journal=self))
        return seq

    def _verify_streaming(self) -> list[Record] | None:
        """Every record of a clean file, checked (length, CRC, header) while reading it in bounded pieces, with
        its arrays left on disk; None at the first thing that does not verify (the repairing read then runs)."""
        size = self.path.stat().st_size
        out: list[Record] = []
        with open(self.path, "rb") as f:
            off = 0
            while off < size:
                head = f.read(_HEAD.size)
                if len(head) < _HEAD.size:
                    return None
                magic, length, crc = _HEAD.unpack(head)
                if magic != MAGIC or length < 4 or off + _HEAD.size + length > size:
                    return None
                first = f.read(4)
                (hlen,) = struct.unpack("<I", first)
                if 4 + hlen > length:
                    return None
                hbytes = f.read(hlen)
                run = zlib.crc32(hbytes, zlib.crc32(first))
                left = length - 4 - hlen
                while left > 0:
                    piece = f.read(min(left, _READ_PIECE))
                    if not piece:
                        return None
                    run = zlib.crc32(piece, run)
                    left -= len(piece)
                if run != crc:
                    return None
                try:
                    header = json.loads(hbytes.decode())
                    seq = int(header.pop("seq"))
                    kind = str(header.pop("kind"))
                    specs = header.pop("arrays", [])
                    need = sum(int(sp["n"]) * np.dtype(sp["dtype"]).itemsize for sp in specs if "const" not in sp)
                except (ValueError, KeyError, TypeError, UnicodeDecodeError, AttributeError):
                    return None
                if seq < 0 or kind not in RECORD_KINDS or need > length - 4 - hlen:
                    return None
                if out and out[-1].seq >= seq:
                    return None  # a retried append: the repairing read decides which copy wins
                out.append(Record(seq, kind, header, offset=off, journal=self))
                off += _HEAD.size + length
        return out

    def read_arrays(self, rec: Record) -> dict[str, np.ndarray]:
        """The arrays of one record of this journal, read back from the file and checked again.

        Raises:
            JournalError: the bytes at the record's place no longer verify.
        """
        try:
            with open(self.path, "rb") as f:
                f.seek(rec.offset)
                data = f.read(_HEAD.size)
                if len(data) == _HEAD.size:
                    _, length, _ = _HEAD.unpack(data)
                    data += f.read(length)
        except OSError as exc:
            raise JournalError(f"cannot read record {rec.seq} of {self.path.name}: {exc.strerror or exc}") from exc
        parsed = _parse_at(data, 0)
        if parsed is None or parsed[0].seq != rec.seq:
            raise JournalError(f"record {rec.seq} of {self.path.name} no longer verifies (the file changed on disk)")
        return parsed[0].loaded or {}

    def close(self) -> None:
        fd, self._fd = self._fd, -1
        if fd >= 0:
            with contextlib.suppress(Exception):
                os.close(fd)
        with contextlib.suppress(Exception):
            self._lock_file.close()


# Indirection for fault injection in tests (a full disk, an I/O error); production code uses the os functions.
_os_write = os.write
_os_fsync = os.fsync
_READ_PIECE = 16 << 20
"""Bytes read at a time while a journal is verified."""


def _parse_at(data: bytes, off: int) -> tuple[Record, int] | None:
    """The record starting at byte `off` and its end offset, or None when it does not verify."""
    if off + _HEAD.size > len(data):
        return None
    magic, length, crc = _HEAD.unpack_from(data, off)
    start = off + _HEAD.size
    if magic != MAGIC or start + length > len(data):
        return None
    payload = data[start : start + length]
    if zlib.crc32(payload) != crc:
        return None
    try:
        header, arrays = _decode(payload)
        seq = int(header.pop("seq"))
        kind = str(header.pop("kind"))
    except (ValueError, KeyError, TypeError, UnicodeDecodeError, struct.error):
        return None
    if seq < 0 or kind not in RECORD_KINDS:
        return None
    return Record(seq, kind, header, arrays), start + length


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

    Written with `efem_viz.data.io.atomic_write` (temp file in the same directory, fsync, rename, fsync of the
    directory; nothing is left behind on failure).

    Args:
        path: destination `.npz`.
        labels: (N,) int32.
        table: instance table.
        seq: the last journal sequence number included.
        scan_id: scan identity (vertex count, file name, content hash) checked on load.

    Raises:
        ValueError: `path` is a symbolic link (never replaced or written through).
        OSError: the file could not be written.
    """

    def writer(tmp: Path) -> None:
        with open(tmp, "wb") as f:  # a file object: np.savez must not append ".npz" to the temporary name
            np.savez(
                f,
                schema_version=np.array(LABELS_SCHEMA_VERSION, np.int32),
                instance=np.ascontiguousarray(labels, np.int32),
                instances_json=np.array(json.dumps(table_to_json(table))),
                journal_seq=np.array(seq, np.int64),
                scan_json=np.array(json.dumps(scan_id)),
            )

    atomic_write(path, writer)


def read_label_file(path: str | os.PathLike[str], n: int) -> tuple[np.ndarray, dict[int, InstanceInfo], int]:
    """Read a checkpoint label file; returns (labels (N,) int32, table, journal seq).

    Raises:
        JournalError: unreadable, or written for a scan with another vertex count.
    """
    labels, table, seq, _ = read_label_file_with_scan(path, n)
    return labels, table, seq


def read_label_file_with_scan(
    path: str | os.PathLike[str], n: int
) -> tuple[np.ndarray, dict[int, InstanceInfo], int, dict[str, Any]]:
    """`read_label_file` plus the scan identity the file was written for ({} when it records none)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            labels = np.asarray(z["instance"])
            table_raw = json.loads(str(z["instances_json"])) if "instances_json" in z else {}
            seq = int(z["journal_seq"]) if "journal_seq" in z else -1
            scan = json.loads(str(z["scan_json"])) if "scan_json" in z else {}
    except (OSError, ValueError, KeyError, TypeError, EOFError, json.JSONDecodeError, zipfile.BadZipFile) as exc:
        raise JournalError(f"cannot read label file {path}: {exc}") from exc
    if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer) or (labels.size and labels.min() < 0):
        raise JournalError(
            f"label file {path} has {labels.shape} {labels.dtype} labels, but the scan has {n} vertices"
        )
    if not isinstance(scan, dict):
        scan = {}
    table = {k: v for k, v in table_from_json(table_raw).items() if v is not None}
    return labels.astype(np.int32), table, seq, scan


def scan_fingerprint(points: np.ndarray, faces: np.ndarray | None = None) -> str:
    """Content hash of a scan's geometry (vertex positions and faces), recorded in the journal.

    Args:
        points: (N, 3) vertex positions (hashed as little-endian float32).
        faces: (M, 3) vertex indices, or None.

    Returns:
        "blake2b:<32 hex digits>".
    """
    h = hashlib.blake2b(digest_size=16)
    pts = np.ascontiguousarray(points, dtype="<f4")
    h.update(struct.pack("<Q", pts.shape[0]))
    h.update(pts.tobytes())
    if faces is not None and len(faces):
        h.update(b"faces")
        h.update(np.ascontiguousarray(faces, dtype="<i4").tobytes())
    return "blake2b:" + h.hexdigest()


def remove_stale_temp_files(folder: str | os.PathLike[str], stem: str) -> list[Path]:
    """Delete temporary files that an interrupted atomic write of ours left for `stem` in `folder`.

    `efem_viz.data.io.atomic_write` names its temporary files ``.<destination stem>.<random>.tmp<suffix>``; a
    kill -9 during a write leaves one behind. Call this only while holding the scan's journal lock (no other
    annotator writes these names then).

    Args:
        folder: a folder the annotator writes into.
        stem: the scan's file stem.

    Returns:
        The files removed.
    """
    removed: list[Path] = []
    d = Path(folder)
    if not d.is_dir():
        return removed
    for p in d.glob(f".{glob_escape(stem)}.*"):
        if ".tmp" in p.name and p.is_file() and not p.is_symlink():
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    if removed:
        log.info("removed %d stale temporary files in %s", len(removed), d)
    return removed


# ---------------------------------------------------------------------------------------------- the store
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
        j = self.journal
        recs = j.records
        ck: tuple[np.ndarray, dict[int, InstanceInfo], int] | None = None
        ck_problem = ""
        if self.label_path.exists():
            try:
                lab, table, seq, scan = read_label_file_with_scan(self.label_path, self.n)
                self._check_scan({**scan, "num_vertices": self.n}, f"label file {self.label_path}")
                ck = (lab, table, seq)
            except JournalError as exc:
                if not recs:
                    raise JournalError(f"{exc}; refusing to overwrite it — move it away or choose another --out") from exc
                ck_problem = f"the checkpoint could not be used ({exc})"
                log.warning("%s; replaying the journal instead", exc)
        if not recs and not j.damage:
            ls = LabelSet(self.n, initial_labels, initial_instances)
            if ck is not None:  # an existing checkpoint without a journal (journal deleted by hand)
                ls = LabelSet(self.n, ck[0], ck[1].values())
                log.warning("no journal next to %s: resuming from the label file alone", self.label_path)
                self.resumed = True
            lab, table = ls.snapshot()
            j.append("base", {"scan": self.scan_id, "table": table_to_json(table)}, {"labels": lab})
            return ls
        # The scan identity: the newest full-state record's, else the checkpoint's check above.
        states = [r for r in recs if r.kind in ("base", "snapshot")]
        for r in reversed(states):
            if "scan" in r.header:
                self._check_scan(r.header["scan"], f"journal {j.path}")
                break
        self.resumed = True
        # Start from the newest valid full state: a base/snapshot record or the checkpoint (never an older one).
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
                f"journal {j.path} is damaged beyond recovery (no verifiable full state, no usable checkpoint); "
                f"the damaged file is kept in {j.aside}"
            )
        newest = max([r.seq for r in recs], default=-1)
        j.next_seq = max(j.next_seq, start_seq + 1, newest + 1)
        # Rebuild history over all records with the same stack logic as LabelSet; apply to the labels only the
        # records after the start state. History cannot be undone across a missing record: stacks restart there.
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
        ls.undo_stack = undo
        ls.redo_stack = redo
        lost = tuple(s for s in j.gaps if s > start_seq)
        damage = list(j.damage)
        if ck_problem:
            damage.append(ck_problem)
        ck_seq = ck[2] if ck is not None else -1
        ck_newer = ck_seq > newest
        if ck_newer:
            damage.append(f"the journal ends at record {newest}, the checkpoint holds records up to {ck_seq}: "
                          "resumed from the checkpoint")
        if damage or lost or skipped:
            seqs = [r.seq for r in recs]
            checkpoint = (f"holds records up to {ck_seq}" if ck is not None
                          else "unreadable" if ck_problem else f"missing ({self.label_path.name})")
            unverified: list[str] = []
            if j.torn_at is not None and ck_seq <= newest:
                unverified.append(
                    f"whether edits followed record {newest}: a crash during an edit leaves an incomplete last "
                    "record (that edit was never acknowledged), but so does a journal cut short, and then every "
                    "later edit is gone; "
                    + ("there is no checkpoint to compare with" if ck is None else
                       f"the checkpoint holds nothing newer (record {ck_seq})"))
            self.recovery = RecoveryReport(
                start=start_name,
                replayed=replayed,
                damage=tuple(damage),
                lost=lost,
                skipped=tuple(skipped),
                aside=(j.aside.name,) if j.aside is not None else (),
                verified=(f"{len(seqs)} journal records ({_ranges(tuple(seqs))}, checksums match)" if seqs
                          else "no journal record") + f"; checkpoint: {checkpoint}",
                unverified=tuple(unverified),
            )
            log.warning("journal %s recovery:\n%s", j.path.name, self.recovery.summary())
        # Make the journal alone reproduce the recovered state, whatever happens to the checkpoint later: a full
        # snapshot when replaying it would not (records missing since its newest full state, skipped records, a
        # newer checkpoint), or when the scan identity changed on purpose.
        last_state = states[-1].seq if states else -1
        scan_changed = self.accept_scan_mismatch and bool(states) and (
            states[-1].header.get("scan", {}).get("content_hash") != self.scan_id.get("content_hash")
        )
        if skipped or ck_newer or scan_changed or any(g > last_state for g in j.gaps):
            lab, table = ls.snapshot()
            j.append("snapshot", {"scan": self.scan_id, "table": table_to_json(table)}, {"labels": lab})
        log.info(
            "resumed %s: %d journal records, start %s, %d undoable edits",
            j.path.name, len(recs), start_name, len(undo),
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
