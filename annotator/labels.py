"""The label store: per-vertex instance ids, an instance table, and invertible edits with undo/redo (pure).

Every change to the labels is a `Delta`: the vertices it touches with their labels before and after, and the
instance-table entries before and after. A delta is its own undo record (`Delta.inverse()` swaps before and
after), so the whole history is a list of deltas that can be written to a journal and replayed
(`annotator.journal`). `LabelSet` builds deltas for the operations the GUI offers (paint, erase, create, rename,
recolour, hide, lock, delete, merge, import) without applying them, and `LabelSet.apply` / `undo` / `redo`
apply them. `LabelSet` is not thread-safe: the app holds one lock around it (`annotator.store.LabelStore`).

Label ids: 0 = unlabelled; instance ids are positive int32. Vertices of a *locked* or *hidden* instance are
protected: paint, erase and fill leave them alone (one cannot change what one cannot see or has frozen).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Protocol, Union

import numpy as np

from efem_viz.colors import instance_color

LABELS_SCHEMA_VERSION = 1


@dataclass(frozen=True)
class InstanceInfo:
    """One row of the instance table."""

    id: int
    """Positive instance id (the value stored per vertex)."""
    name: str
    """Display name, e.g. "mug 1"."""
    category: str = "object"
    """Semantic category, e.g. "mug" (written to ScanNet `label` and PLY categories)."""
    color: tuple[int, int, int] = (255, 0, 0)
    """Display colour, RGB uint8."""
    visible: bool = True
    """Shown in the viewport; hidden instances are drawn in scan colour and protected from edits."""
    locked: bool = False
    """Locked instances neither lose nor gain vertices."""
    note: str = ""
    """Free text."""

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["color"] = [int(c) for c in self.color]
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "InstanceInfo":
        """Parse a table row; raises ValueError on malformed input."""
        try:
            iid = int(d["id"])
            color = tuple(int(c) for c in d.get("color", instance_color(iid)))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:  # OverflowError: int(inf)
            raise ValueError(f"malformed instance record {dict(d)!r}: {exc}") from exc
        if iid <= 0:
            raise ValueError(f"instance ids must be positive, got {iid}")
        if len(color) != 3 or not all(0 <= c <= 255 for c in color):
            raise ValueError(f"instance {iid}: colour must be 3 values in [0, 255], got {color}")
        return cls(
            id=iid,
            name=str(d.get("name", f"instance {iid}")),
            category=str(d.get("category", "object")),
            color=(color[0], color[1], color[2]),
            visible=bool(d.get("visible", True)),
            locked=bool(d.get("locked", False)),
            note=str(d.get("note", "")),
        )

    @property
    def protected(self) -> bool:
        """True when edits must leave this instance's vertices alone (locked or hidden)."""
        return self.locked or not self.visible

    @property
    def unreviewed(self) -> bool:
        """An EFEM pre-label nobody has reviewed yet (its note starts with "unreviewed", `prelabel_note`)."""
        return self.note.startswith("unreviewed")

    @property
    def confidence(self) -> float:
        """A pre-label's EFEM confidence, read from its note (`prelabel_note`); 0 when the note has none."""
        m = re.search(r"confidence (-?[0-9]+(?:\.[0-9]+)?)", self.note)
        return float(m.group(1)) if m else 0.0


def prelabel_note(source: str, confidence: float | None) -> str:
    """The note of a new pre-label: "unreviewed; from <source>[; confidence 0.873]" (Accept turns "unreviewed"
    into "accepted")."""
    return f"unreviewed; from {source}" + (f"; confidence {confidence:.3f}" if confidence is not None else "")


def unreviewed_prelabels(table: Mapping[int, InstanceInfo]) -> list[int]:
    """Ids of the unreviewed pre-labels of an instance table, most confident first (ties: lower id first)."""
    return sorted((k for k, v in table.items() if v.unreviewed), key=lambda k: (-table[k].confidence, k))


@dataclass(frozen=True)
class Delta:
    """One invertible edit.

    Attributes are arrays over the K vertices the edit changes (only vertices whose label really changes) and
    the instance-table rows it changes (None = row absent).
    """

    label: str
    """Human-readable description ("paint 1,234 → mug 1")."""
    idx: np.ndarray
    """(K,) int32 vertex indices, unique."""
    before: np.ndarray
    """(K,) int32 labels before the edit."""
    after: np.ndarray
    """(K,) int32 labels after the edit."""
    table_before: Mapping[int, InstanceInfo | None] = field(default_factory=dict)
    """Instance rows before (None = did not exist)."""
    table_after: Mapping[int, InstanceInfo | None] = field(default_factory=dict)
    """Instance rows after (None = removed)."""
    group: str = ""
    """Edits with the same non-empty group that are adjacent on the undo stack undo/redo together (the
    segments of one brush stroke)."""
    seq: int = -1
    """The journal record that holds exactly this edit (set by `LabelStore`), -1 when none does; an edit with a
    record can leave memory and be read back from the journal when it is undone or redone."""

    def inverse(self) -> "Delta":
        """The delta that undoes this one."""
        return Delta(
            label=f"undo {self.label}",
            idx=self.idx,
            before=self.after,
            after=self.before,
            table_before=dict(self.table_after),
            table_after=dict(self.table_before),
            group=self.group,
        )

    def load(self) -> "Delta":
        """The edit itself (a `StoredEdit` reads it back from where it was kept)."""
        return self

    @property
    def nbytes(self) -> int:
        """Bytes its vertex arrays hold in memory."""
        return int(self.idx.nbytes + self.before.nbytes + self.after.nbytes)

    @property
    def is_empty(self) -> bool:
        """True when the edit changes nothing."""
        return len(self.idx) == 0 and all(self.table_before.get(k) == v for k, v in self.table_after.items())

    @property
    def num_vertices(self) -> int:
        return int(len(self.idx))


class StoredEdit(Protocol):
    """An edit on the undo/redo history whose arrays live outside memory (`annotator.store.JournalEdit`)."""

    @property
    def label(self) -> str:
        """The edit's history label."""
        ...

    @property
    def group(self) -> str:
        """Its stroke group ("" for none)."""
        ...

    @property
    def seq(self) -> int:
        """The journal record that holds it."""
        ...

    def load(self) -> Delta:
        """The full edit (raises when it can no longer be read)."""
        ...


HistoryEntry = Union[Delta, StoredEdit]
"""One entry of `LabelSet.undo_stack` / `redo_stack`: an edit in memory or one kept elsewhere."""


def _as_index(idx: Iterable[int] | np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(idx)
    if a.size == 0:
        return np.zeros(0, np.int32)
    if a.dtype == bool:
        if a.shape != (n,):
            raise ValueError(f"boolean mask must have shape ({n},), got {a.shape}")
        return np.flatnonzero(a).astype(np.int32)
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"vertex indices must be integers, got dtype {a.dtype}")
    a = a.reshape(-1)
    if a.min() < 0 or a.max() >= n:
        raise ValueError(f"vertex indices must lie in [0, {n}), got [{a.min()}, {a.max()}]")
    return np.unique(a).astype(np.int32)


class LabelSet:
    """Per-vertex instance labels, the instance table and the undo/redo history.

    Args:
        num_vertices: N, the number of scan vertices.
        labels: (N,) integer initial labels (0 = unlabelled), or None (all 0).
        instances: initial instance table; ids present in `labels` but missing here get default rows.

    Raises:
        ValueError: wrong label length, negative labels.
    """

    def __init__(
        self,
        num_vertices: int,
        labels: np.ndarray | None = None,
        instances: Iterable[InstanceInfo] | None = None,
    ) -> None:
        n = int(num_vertices)
        if n <= 0:
            raise ValueError(f"a label set needs at least one vertex, got {n}")
        self.n = n
        if labels is None:
            self._labels = np.zeros(n, np.int32)
        else:
            lab = np.asarray(labels)
            if lab.shape != (n,):
                raise ValueError(f"labels have shape {lab.shape}, but the scan has {n} vertices")
            if not np.issubdtype(lab.dtype, np.integer):
                raise ValueError(f"labels must be integers, got dtype {lab.dtype}")
            if lab.size and lab.min() < 0:
                raise ValueError("labels must be >= 0 (0 = unlabelled)")
            self._labels = np.ascontiguousarray(lab, dtype=np.int32).copy()
        self._table: dict[int, InstanceInfo] = {}
        for info in instances or ():
            self._table[int(info.id)] = info
        for iid in np.unique(self._labels):
            if iid > 0 and int(iid) not in self._table:
                self._table[int(iid)] = InstanceInfo(int(iid), f"instance {iid}", color=instance_color(int(iid)))
        self._counts = np.bincount(self._labels, minlength=1).astype(np.int64)
        self.undo_stack: list[HistoryEntry] = []
        self.redo_stack: list[HistoryEntry] = []
        self.version = 0
        """Increments on every applied delta (do, undo or redo)."""

    # ------------------------------------------------------------------ read access
    @property
    def labels(self) -> np.ndarray:
        """(N,) int32 labels, read-only view."""
        v = self._labels.view()
        v.flags.writeable = False
        return v

    @property
    def instances(self) -> dict[int, InstanceInfo]:
        """Copy of the instance table, id → row, sorted by id."""
        return {k: self._table[k] for k in sorted(self._table)}

    def info(self, instance_id: int) -> InstanceInfo:
        """The row of one instance; raises KeyError with the known ids."""
        try:
            return self._table[int(instance_id)]
        except KeyError:
            raise KeyError(f"no instance {instance_id}; known ids: {sorted(self._table)}") from None

    def count(self, instance_id: int) -> int:
        """Number of vertices carrying `instance_id` (0 = unlabelled)."""
        i = int(instance_id)
        return int(self._counts[i]) if 0 <= i < len(self._counts) else 0

    def counts(self) -> dict[int, int]:
        """Vertex count per instance in the table (ids with no vertices give 0)."""
        return {k: self.count(k) for k in sorted(self._table)}

    def progress(self) -> float:
        """Fraction of vertices with a label > 0, in [0, 1]."""
        return float(self.n - self.count(0)) / self.n

    def next_id(self) -> int:
        """The id a new instance gets: one above every id in the table or the labels."""
        top = max(self._table, default=0)
        return max(top, len(self._counts) - 1) + 1

    def protected_ids(self) -> np.ndarray:
        """Sorted ids of locked or hidden instances."""
        return np.array(sorted(k for k, v in self._table.items() if v.protected), np.int32)

    def editable_mask(self, idx: np.ndarray) -> np.ndarray:
        """(K,) bool: which of the vertices `idx` may be changed (not in a protected instance)."""
        prot = self.protected_ids()
        if len(prot) == 0:
            return np.ones(len(idx), bool)
        return ~np.isin(self._labels[idx], prot)

    # ------------------------------------------------------------------ delta builders (do not apply)
    def _label_delta(self, label: str, idx: np.ndarray, after: np.ndarray | int) -> Delta:
        before = self._labels[idx]
        aft = np.broadcast_to(np.asarray(after, np.int32), idx.shape)
        changed = before != aft
        return Delta(label, idx[changed], before[changed].copy(), np.array(aft[changed], np.int32))

    def paint(self, idx: Iterable[int] | np.ndarray, instance_id: int, *, overwrite: bool = True) -> Delta:
        """Delta setting `instance_id` on vertices `idx` (protected vertices are skipped).

        Args:
            idx: (K,) vertex indices or (N,) bool mask.
            instance_id: target id (> 0, in the table; 0 erases).
            overwrite: if False, only unlabelled vertices change.

        Raises:
            KeyError: unknown instance. ValueError: bad indices, or the target instance is locked/hidden.
        """
        iid = int(instance_id)
        if iid != 0:
            info = self.info(iid)
            if info.protected:
                raise ValueError(f"instance {iid} ({info.name}) is locked or hidden; unlock/show it to paint")
        ix = _as_index(idx, self.n)
        ix = ix[self.editable_mask(ix)]
        if not overwrite:
            ix = ix[self._labels[ix] == 0]
        name = self._table[iid].name if iid else "unlabelled"
        d = self._label_delta("", ix, iid)
        verb = "erase" if iid == 0 else "paint"
        return dataclasses.replace(d, label=f"{verb} {d.num_vertices:,} → {name}")

    def erase(self, idx: Iterable[int] | np.ndarray) -> Delta:
        """Delta setting vertices `idx` to 0 (protected vertices are skipped)."""
        return self.paint(idx, 0)

    def create_instance(
        self,
        *,
        name: str | None = None,
        category: str = "object",
        color: tuple[int, int, int] | None = None,
        instance_id: int | None = None,
    ) -> Delta:
        """Delta adding a new instance row (no vertices yet)."""
        iid = self.next_id() if instance_id is None else int(instance_id)
        if iid <= 0:
            raise ValueError(f"instance ids must be positive, got {iid}")
        if iid in self._table:
            raise ValueError(f"instance {iid} already exists")
        info = InstanceInfo(
            id=iid,
            name=name or f"{category} {iid}",
            category=category,
            color=tuple(int(c) for c in (color or instance_color(iid))),  # type: ignore[arg-type]
        )
        empty = np.zeros(0, np.int32)
        return Delta(f"create {info.name}", empty, empty, empty, {iid: None}, {iid: info})

    def update_instance(self, instance_id: int, **changes: Any) -> Delta:
        """Delta changing fields of one row (name, category, color, visible, locked, note)."""
        old = self.info(instance_id)
        allowed = {"name", "category", "color", "visible", "locked", "note"}
        bad = set(changes) - allowed
        if bad:
            raise ValueError(f"cannot change {sorted(bad)}; allowed fields: {sorted(allowed)}")
        if "color" in changes:
            c = tuple(int(v) for v in changes["color"])
            if len(c) != 3 or not all(0 <= v <= 255 for v in c):
                raise ValueError(f"colour must be 3 values in [0, 255], got {changes['color']}")
            changes["color"] = c
        new = dataclasses.replace(old, **changes)
        empty = np.zeros(0, np.int32)
        what = ", ".join(f"{k}={v!r}" for k, v in changes.items())
        return Delta(f"{old.name}: {what}", empty, empty, empty, {old.id: old}, {old.id: new})

    def delete_instance(self, instance_id: int) -> Delta:
        """Delta removing an instance row and unlabelling its vertices (refused when locked)."""
        old = self.info(instance_id)
        if old.locked:
            raise ValueError(f"instance {old.id} ({old.name}) is locked; unlock it to delete")
        ix = np.flatnonzero(self._labels == old.id).astype(np.int32)
        d = self._label_delta("", ix, 0)
        return Delta(f"delete {old.name}", d.idx, d.before, d.after, {old.id: old}, {old.id: None})

    def merge(self, sources: Iterable[int], into: int) -> Delta:
        """Delta relabelling the vertices of `sources` as `into` and removing the source rows."""
        dst = self.info(into)
        srcs = sorted({int(s) for s in sources} - {dst.id})
        if not srcs:
            raise ValueError("merge needs at least one instance other than the target")
        infos = [self.info(s) for s in srcs]
        locked = [i.name for i in infos + [dst] if i.locked]
        if locked:
            raise ValueError(f"cannot merge locked instances: {locked}")
        ix = np.flatnonzero(np.isin(self._labels, np.array(srcs, np.int32))).astype(np.int32)
        d = self._label_delta("", ix, dst.id)
        return Delta(
            f"merge {', '.join(i.name for i in infos)} → {dst.name}",
            d.idx,
            d.before,
            d.after,
            {i.id: i for i in infos},
            {i.id: None for i in infos},
        )

    def replace_all(
        self, labels: np.ndarray, instances: Iterable[InstanceInfo], *, label: str = "import labels"
    ) -> Delta:
        """Delta replacing every label and the whole table (imports); undoable like any other edit."""
        lab = np.asarray(labels)
        if lab.shape != (self.n,):
            raise ValueError(f"imported labels have shape {lab.shape}, but the scan has {self.n} vertices")
        if not np.issubdtype(lab.dtype, np.integer) or (lab.size and lab.min() < 0):
            raise ValueError("imported labels must be non-negative integers")
        new_table = {int(i.id): i for i in instances}
        for iid in np.unique(lab):
            if iid > 0 and int(iid) not in new_table:
                new_table[int(iid)] = InstanceInfo(int(iid), f"instance {iid}", color=instance_color(int(iid)))
        ix = np.arange(self.n, dtype=np.int32)
        d = self._label_delta("", ix, lab.astype(np.int32))
        keys = set(self._table) | set(new_table)
        return Delta(
            label,
            d.idx,
            d.before,
            d.after,
            {k: self._table.get(k) for k in keys},
            {k: new_table.get(k) for k in keys},
        )

    # ------------------------------------------------------------------ applying
    def _apply_raw(self, d: Delta) -> None:
        if len(d.idx):
            cur = self._labels[d.idx]
            if not np.array_equal(cur, d.before):
                raise ValueError(f"delta {d.label!r} does not match the current labels (stale edit)")
            top = int(max(d.after.max(initial=0), d.before.max(initial=0)))
            if top >= len(self._counts):
                self._counts = np.concatenate([self._counts, np.zeros(top + 1 - len(self._counts), np.int64)])
            m = len(self._counts)
            self._counts -= np.bincount(d.before, minlength=m)
            self._counts += np.bincount(d.after, minlength=m)
            self._labels[d.idx] = d.after
        for k, v in d.table_after.items():
            if v is None:
                self._table.pop(int(k), None)
            else:
                self._table[int(k)] = v
        self.version += 1

    def apply(self, d: Delta) -> None:
        """Apply a new edit: it goes on the undo stack and clears the redo stack."""
        self._apply_raw(d)
        self.undo_stack.append(d)
        self.redo_stack.clear()

    def undo(self, loaded: list[Delta] | None = None) -> list[Delta]:
        """Undo the last edit (a whole stroke group); returns the deltas applied (inverses), empty if none.

        Args:
            loaded: the group's edits already read (`top_group(self.undo_stack)`), so that reading them back
                cannot fail half way; None reads them here.
        """
        return self._move(self.undo_stack, self.redo_stack, invert=True, loaded=loaded)

    def redo(self, loaded: list[Delta] | None = None) -> list[Delta]:
        """Redo the last undone edit (a whole stroke group); returns the deltas applied, empty if none."""
        return self._move(self.redo_stack, self.undo_stack, invert=False, loaded=loaded)

    @staticmethod
    def top_group(stack: list[HistoryEntry]) -> list[Delta]:
        """The edits one undo (or redo) of `stack` applies, newest first, read into memory.

        Raises:
            Whatever a stored edit raises when it cannot be read (nothing has changed then).
        """
        out: list[Delta] = []
        if not stack:
            return out
        group = stack[-1].group
        for e in reversed(stack):
            if out and (not group or e.group != group):
                break
            out.append(e.load())
        return out

    def _move(self, src: list[HistoryEntry], dst: list[HistoryEntry], *, invert: bool,
              loaded: list[Delta] | None) -> list[Delta]:
        deltas = self.top_group(src) if loaded is None else loaded
        applied: list[Delta] = []
        for d in deltas:
            a = d.inverse() if invert else d
            self._apply_raw(a)
            dst.append(src.pop())  # the entry as it was kept (in memory or stored)
            applied.append(a)
        return applied

    def snapshot(self) -> tuple[np.ndarray, dict[int, InstanceInfo]]:
        """(labels copy (N,) int32, table copy)."""
        return self._labels.copy(), self.instances

    def categories(self) -> dict[int, str]:
        """Instance id → category for instances with at least one vertex."""
        return {k: v.category for k, v in self._table.items() if self.count(k) > 0}


def table_to_json(table: Mapping[int, InstanceInfo | None]) -> dict[str, Any]:
    """JSON-friendly form of a (partial) table; None rows stay None."""
    return {str(k): (v.to_json() if v is not None else None) for k, v in table.items()}


def table_from_json(d: Mapping[str, Any]) -> dict[int, InstanceInfo | None]:
    """Inverse of `table_to_json`."""
    return {int(k): (InstanceInfo.from_json(v) if v is not None else None) for k, v in d.items()}
