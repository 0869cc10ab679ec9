"""The annotator's files: the append-only edit journal and the atomic label file (checkpoint).

This module is the format only: journal records (`Record`, `Journal`: append with fsync, streamed CRC check,
repair of a torn tail, arrays read back on demand), the label file (`write_label_file`, `read_label_file`,
`read_label_file_with_scan`), the scan fingerprint (`scan_fingerprint`) and the clean-up of stale temporary files
(`remove_stale_temp_files`). The store that uses them (`LabelStore`: journal first, autosaved checkpoint,
recovery, the undo/redo history) is `annotator/store.py`.

The label file (`<stem>.labels.npz`) is a checkpoint rewritten atomically (temp file in the same directory,
fsync, rename, fsync of the directory); it records the journal sequence number it contains.

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
import time
import zipfile
import zlib
from glob import escape as glob_escape
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.labels import (
    LABELS_SCHEMA_VERSION,
    Delta,
    InstanceInfo,
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
    return header, {"idx": d.idx.astype(np.int32), "before": d.before.astype(np.int32),
                    "after": d.after.astype(np.int32)}


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
