"""Label file formats (PLY `instance`, NPZ, ScanNet segs/aggregation JSON, EFEM results) and path safety.

Formats (all writes atomic):

* **PLY** (`<scan>.labels.ply`): the whole scan (points, normals, colours, faces) with the per-vertex int
  property `instance` (0 = unlabelled) — the ground-truth format the rest of efem-viz reads
  (`efem_viz.data.io.load_scene`). Categories are in the `efem_categories` header comment; the annotator's full
  instance table (names, colours, flags) rides in `efem_provenance` under the key ``"annotator_instances"``.
* **NPZ** (`<scan>.labels.npz`): ``instance`` (N,) int32, ``instances_json`` (the instance table),
  ``journal_seq``, ``scan_json``, ``schema_version``. This is also the autosave checkpoint.
* **ScanNet** (`<scan>.segs.json` + `<scan>.aggregation.json`): ``segIndices`` (N,) per-vertex segment ids (here
  one segment per instance: segment id = instance id, 0 = unlabelled) and ``segGroups`` entries
  ``{id, objectId, label, segments}`` with ``objectId = instance id - 1`` (ScanNet object ids are 0-based).
  Import maps every vertex of a group's segments to ``objectId + 1``.
* **EFEM results** (`<scene>.efem.npz`): imported as pre-labels through `efem_viz.em.EMResult.load`.

Path safety: `resolve_inside` resolves symlinks and refuses paths that leave the allowed roots.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, cast

import numpy as np

from annotator.journal import read_label_file, write_label_file
from annotator.labels import InstanceInfo, table_from_json, table_to_json
from efem_viz.colors import instance_color, result_colors, rgb_tuple
from efem_viz.data.io import RESULT_SUFFIX
from efem_viz.terminal import one_line

log = logging.getLogger(__name__)

MAX_SCAN_POINTS = 10_000_000
"""Default vertex limit of a scan the annotator opens (a 5M-vertex scan peaks at about 2.2 GB of memory)."""

LABEL_SUFFIXES = (".labels.ply", ".labels.npz", ".ply", ".npz", ".aggregation.json", ".segs.json", RESULT_SUFFIX)


class LabelIOError(ValueError):
    """A label file that cannot be read or written, or a path that is not allowed; the message is for the user."""


@dataclass(frozen=True)
class LabelData:
    """Imported labels."""

    labels: np.ndarray
    """(N,) int32, 0 = unlabelled."""
    instances: list[InstanceInfo]
    """Instance table rows (at least one per id present in `labels`)."""
    confidence: dict[int, float] | None = None
    """Per-instance confidence (EFEM pre-labels), or None."""


# ---------------------------------------------------------------------------------------------- path safety
def resolve_inside(path: str | os.PathLike[str], roots: Iterable[str | os.PathLike[str]], *,
                   what: str = "path") -> Path:
    """Resolve `path` (following symlinks) and check it lies inside one of `roots`.

    Relative paths are taken relative to the first root.

    Args:
        path: user-supplied path.
        roots: allowed directories.
        what: noun for the error message ("label file", "export directory").

    Returns:
        The resolved absolute path.

    Raises:
        LabelIOError: empty path, NUL bytes, or the resolved path escapes every root (`..`, absolute paths
            elsewhere, symlinks pointing out).
    """
    from efem_viz.serve.inputs import resolve_inside as _resolve

    return _resolve(path, roots, what=what, error=LabelIOError)


# ---------------------------------------------------------------------------------------------- helpers
def _table_rows(table: Mapping[int, InstanceInfo] | Iterable[InstanceInfo]) -> list[InstanceInfo]:
    if isinstance(table, Mapping):
        # cast: to pyright this may also be a Mapping keyed by InstanceInfo; a Mapping here is the id table
        by_id = cast("Mapping[int, InstanceInfo]", table)
        return [by_id[k] for k in sorted(by_id)]
    return sorted(table, key=lambda i: i.id)


def _check_labels(labels: np.ndarray, n: int, path: Path | str) -> np.ndarray:
    lab = np.asarray(labels)
    if lab.ndim != 1 or lab.shape[0] != n:
        raise LabelIOError(f"{path}: has {lab.shape[0] if lab.ndim == 1 else lab.shape} labels, "
                           f"the scan has {n} vertices")
    if not np.issubdtype(lab.dtype, np.integer):
        if np.issubdtype(lab.dtype, np.floating) and np.isfinite(lab).all() and (np.round(lab) == lab).all():
            lab = lab.astype(np.int64)
        else:
            raise LabelIOError(f"{path}: labels must be integers, got dtype {lab.dtype}")
    if lab.size and lab.min() < 0:
        raise LabelIOError(f"{path}: labels must be >= 0 (0 = unlabelled), found {lab.min()}")
    if lab.size and lab.max() > np.iinfo(np.int32).max:
        raise LabelIOError(f"{path}: label {lab.max()} does not fit int32")
    return lab.astype(np.int32)


def _complete(labels: np.ndarray, rows: list[InstanceInfo],
              categories: Mapping[int, str] | None = None) -> list[InstanceInfo]:
    have = {r.id for r in rows}
    out = list(rows)
    for iid in np.unique(labels):
        i = int(iid)
        if i > 0 and i not in have:
            cat = (categories or {}).get(i, "object")
            out.append(InstanceInfo(i, f"{cat} {i}", category=cat, color=instance_color(i)))
    return sorted(out, key=lambda r: r.id)


# ---------------------------------------------------------------------------------------------- writers
def save_labels_ply(scene: Any, labels: np.ndarray, table: Mapping[int, InstanceInfo],
                    path: str | os.PathLike[str]) -> Path:
    """Write the scan with an `instance` vertex property (efem-viz ground-truth PLY). Atomic.

    Args:
        scene: the `efem_viz.data.scene.Scene` being labelled.
        labels: (N,) int32.
        table: instance table (categories and the annotator table go into the header comments).
        path: destination `.ply`.
    """
    from efem_viz.data.io import save_scene

    p = Path(path)
    if p.is_symlink():
        raise LabelIOError(f"refusing to overwrite {p}: it is a symbolic link")
    lab = np.asarray(labels, np.int32)
    present = set(int(i) for i in np.unique(lab) if i > 0)
    cats = {k: v.category for k, v in table.items() if k in present}
    prov = dict(scene.provenance)
    prov["annotator_instances"] = table_to_json({k: v for k, v in table.items()})
    prov["labelled_by"] = "efem-annotate"
    labelled = scene.replace(instance=lab, categories=cats, provenance=prov)
    return save_scene(labelled, p)


def save_labels_npz(
    labels: np.ndarray, table: Mapping[int, InstanceInfo], path: str | os.PathLike[str], *, scan_name: str = ""
) -> Path:
    """Write labels + instance table as NPZ (the checkpoint format). Atomic."""
    lab = np.asarray(labels, np.int32)
    write_label_file(path, lab, dict(table), seq=-1, scan_id={"num_vertices": int(len(lab)), "name": scan_name})
    return Path(path)


def save_scannet(
    labels: np.ndarray, table: Mapping[int, InstanceInfo], directory: str | os.PathLike[str], scan_name: str
) -> tuple[Path, Path]:
    """Write `<scan>.segs.json` and `<scan>.aggregation.json` (ScanNet layout). Atomic.

    Returns:
        (segs path, aggregation path).
    """
    from efem_viz.data.io import atomic_write_text

    lab = np.asarray(labels, np.int32)
    d = Path(directory)
    segs = {"sceneId": scan_name, "segIndices": lab.tolist()}
    groups = []
    for iid in sorted(int(i) for i in np.unique(lab) if i > 0):
        info = table.get(iid)
        groups.append(
            {
                "id": iid - 1,
                "objectId": iid - 1,
                "label": info.category if info else "object",
                "segments": [iid],
                "name": info.name if info else f"instance {iid}",
            }
        )
    agg = {"sceneId": scan_name, "appId": "efem-annotate", "segGroups": groups,
           "segmentsFile": f"{scan_name}.segs.json"}
    sp = atomic_write_text(d / f"{scan_name}.segs.json", json.dumps(segs, separators=(",", ":")))
    ap = atomic_write_text(d / f"{scan_name}.aggregation.json", json.dumps(agg, indent=1))
    return sp, ap


@dataclass(frozen=True)
class LabelWriter:
    """One label export format of the annotator (`FilePart.export(name)`): the files it writes are
    `<folder>/<stem><suffix>` for each of its suffixes, every one of which `load_labels` reads back."""

    name: str
    """What `export` is asked for ("ply", "npz", "scannet")."""
    suffixes: tuple[str, ...]
    """The file-name endings it writes, after the scan's stem."""
    write: Callable[[Any, np.ndarray, Mapping[int, InstanceInfo], Path, str], list[Path]]
    """(scene, labels, instance table, folder, stem) -> the written paths (atomic writes)."""


LABEL_WRITERS: dict[str, LabelWriter] = {w.name: w for w in (
    LabelWriter("ply", (".labels.ply",),
                lambda scene, lab, table, d, stem: [save_labels_ply(scene, lab, table, d / f"{stem}.labels.ply")]),
    LabelWriter("npz", (".labels.npz",),
                lambda scene, lab, table, d, stem: [save_labels_npz(lab, table, d / f"{stem}.labels.npz",
                                                                    scan_name=stem)]),
    LabelWriter("scannet", (".segs.json", ".aggregation.json"),
                lambda scene, lab, table, d, stem: list(save_scannet(lab, table, d, stem))),
)}
"""The label formats the annotator exports, by name (one row per format; `load_labels` reads each back)."""

EXPORT_FRAMES: tuple[str, ...] = ("scene", "original")
"""Frames an export is written in: the scan as opened, or an imported scan's original file frame
(`annotator.parts.files.FilePart.export`)."""


# ---------------------------------------------------------------------------------------------- readers
def _read_ply_labels(p: Path, n: int) -> LabelData:
    import plyfile

    from efem_viz.data.formats.common import CATEGORIES_COMMENT, PROVENANCE_COMMENT
    from efem_viz.data.formats.ply import check_ply_counts, read_ply_header
    from efem_viz.data.scene import DEFAULT_MAX_POINTS, SceneError

    try:
        # the scene reader's bounds checks: a header count the file cannot hold fails before plyfile allocates
        head = read_ply_header(p)
        if head is not None:
            check_ply_counts(p, head, max(n, DEFAULT_MAX_POINTS))
    except SceneError as exc:
        raise LabelIOError(str(exc)) from exc
    try:
        ply = plyfile.PlyData.read(str(p))
        v = ply["vertex"].data
    except MemoryError:
        raise
    except Exception as exc:  # plyfile raises many types on corrupt input
        raise LabelIOError(f"{p}: could not read PLY ({one_line(exc, limit=300)})") from exc
    props = v.dtype.names or ()
    key = next((k for k in ("instance", "instance_id", "objectId", "label") if k in props), None)
    if key is None:
        raise LabelIOError(f"{p}: PLY has no 'instance' vertex property (has {list(props)})")
    labels = _check_labels(np.asarray(v[key]), n, p)
    cats: dict[int, str] = {}
    rows: list[InstanceInfo] = []
    for c in list(ply.comments) + list(getattr(ply, "obj_info", [])):
        c = c.strip()
        try:
            if c.startswith(CATEGORIES_COMMENT + " "):
                cats = {int(k): str(val) for k, val in json.loads(c[len(CATEGORIES_COMMENT) + 1 :]).items()}
            elif c.startswith(PROVENANCE_COMMENT + " "):
                prov = json.loads(c[len(PROVENANCE_COMMENT) + 1 :])
                if isinstance(prov, dict) and isinstance(prov.get("annotator_instances"), dict):
                    rows = [r for r in table_from_json(prov["annotator_instances"]).values() if r is not None]
        except (ValueError, TypeError, AttributeError) as exc:
            log.warning("%s: ignoring an unreadable header comment (%s)", p, exc)
    return LabelData(labels, _complete(labels, rows, cats))


def _check_npz_headers(p: Path, n: int) -> None:
    """The scene reader's `.npz` check: every array header agrees with the bytes its member holds (so numpy never
    allocates what a corrupt header claims)."""
    from efem_viz.data.npz_guard import check_npz_headers
    from efem_viz.data.scene import DEFAULT_MAX_POINTS, SceneError

    try:
        check_npz_headers(p, max(n, DEFAULT_MAX_POINTS))
    except SceneError as exc:
        raise LabelIOError(str(exc)) from exc


def _read_npz_labels(p: Path, n: int) -> LabelData:
    _check_npz_headers(p, n)
    cats_text: str | None = None
    try:
        with np.load(p, allow_pickle=False) as z:
            keys = set(z.files)
            if "instances_json" in keys:
                instance = None
            elif "instance" not in keys:
                raise LabelIOError(f"{p}: NPZ has no 'instance' array (has {sorted(keys)})")
            else:
                instance = np.asarray(z["instance"])
                cats_text = str(z["categories_json"]) if "categories_json" in keys else None
    except LabelIOError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # zipfile, zlib and numpy raise many types on a corrupt archive
        raise LabelIOError(f"{p}: could not read NPZ ({one_line(exc, limit=300)})") from exc
    if instance is None:
        try:
            labels, table, _ = read_label_file(p, n)
        except MemoryError:
            raise
        except Exception as exc:  # JournalError (a ValueError) names the file; others are corrupt members
            msg = " ".join(str(exc).split()) if isinstance(exc, ValueError) else one_line(exc, limit=300)
            raise LabelIOError(msg if str(p) in msg else f"{p}: {msg}") from exc
        return LabelData(_check_labels(labels, n, p), _complete(labels, list(table.values())))
    labels = _check_labels(instance, n, p)
    cats: dict[int, str] = {}
    if cats_text is not None:
        try:
            raw = json.loads(cats_text)
            if not isinstance(raw, dict):
                raise TypeError(f"a JSON object was expected, got {type(raw).__name__}")
            cats = {int(k): str(v) for k, v in raw.items()}
        except (ValueError, TypeError) as exc:
            log.warning("%s: ignoring unreadable categories (%s)", p, exc)
    return LabelData(labels, _complete(labels, [], cats))


def _read_scannet(p: Path, n: int) -> LabelData:
    from efem_viz.data.formats.scannet import read_scannet_instances

    got = read_scannet_instances(p, n, error=LabelIOError)
    rows = [InstanceInfo(iid, got.names[iid], category=cat, color=instance_color(iid))
            for iid, cat in got.categories.items()]
    return LabelData(got.labels, _complete(got.labels, rows))


def _read_efem(p: Path, n: int, *, threshold: float = 0.0) -> LabelData:
    try:
        from efem_viz.em import EMResult  # type: ignore[attr-defined]
    except ImportError as exc:
        raise LabelIOError(f"{p}: EFEM results need efem_viz.em.EMResult, which is not available ({exc})") from exc
    try:
        res = EMResult.load(p)
    except MemoryError:
        raise
    except Exception as exc:  # the result loader raises its own errors; all mean "cannot use this file"
        msg = " ".join(str(exc).split())
        if isinstance(exc, (ValueError, OSError)) and str(p) in msg:  # ResultFileError names the file already
            raise LabelIOError(f"could not load EFEM result: {msg}") from exc
        raise LabelIOError(f"{p}: could not load EFEM result ({one_line(exc, limit=300)})") from exc
    return labels_from_result(res, n, where=str(p), threshold=threshold)


def labels_from_result(res: Any, n: int, *, where: str, threshold: float = 0.0) -> LabelData:
    """The instances of an `EMResult` as labels (instance k -> label k + 1, its proposal's colour) with their
    confidences, for a scan of `n` vertices.

    Raises:
        LabelIOError: the result belongs to another point count or its masks are not usable (`where` names it).
    """
    p = where
    if res.num_points != n:
        raise LabelIOError(f"{p}: the EFEM result was computed on {res.num_points} points, the scan has {n} vertices")
    try:
        keep = res.instances.kept(threshold) if threshold > 0 else np.ones(len(res.instances), bool)
        inst = res.instances.select(keep)
        palette = result_colors(res.instances)[keep]  # the whole result's colours: a cut changes none
        labels = np.asarray(inst.label_array(n), np.int32)
    except (ValueError, IndexError) as exc:
        raise LabelIOError(f"{p}: could not use the EFEM result ({one_line(exc, limit=300)})") from exc
    labels = _check_labels(labels, n, p)
    rows: list[InstanceInfo] = []
    conf: dict[int, float] = {}
    # `label_array` numbers instances by position: the k-th instance is label k + 1; its colour is its
    # `result_colors` one, as in the viewer and the coloured PLY export (`efem_viz.colors`).
    for k in range(len(inst.confidence)):
        iid = k + 1
        cat = str(np.asarray(inst.category)[k]) if len(np.asarray(inst.category)) > k else "object"
        c = float(np.asarray(inst.confidence)[k])
        conf[iid] = c
        color = rgb_tuple(palette[k])
        rows.append(InstanceInfo(iid, f"efem {cat} {iid}", category=cat, color=color, note=f"EFEM confidence {c:.3f}"))
    return LabelData(labels, _complete(labels, rows), conf)


def load_labels(path: str | os.PathLike[str], num_vertices: int) -> LabelData:
    """Import labels for a scan of `num_vertices` vertices from PLY, NPZ, ScanNet JSON or an EFEM result.

    Args:
        path: the label file (for ScanNet either the `.segs.json` or the `.aggregation.json`).
        num_vertices: N of the scan; files with another length are refused.

    Raises:
        LabelIOError: missing, empty, unreadable, wrong length, non-integer or negative labels, unknown format.
    """
    p = Path(path)
    if not p.exists():
        raise LabelIOError(f"{p}: no such file")
    if p.is_dir():
        raise LabelIOError(f"{p} is a directory, not a label file")
    if p.stat().st_size == 0:
        raise LabelIOError(f"{p}: file is empty (0 bytes)")
    name = p.name.lower()
    for suffixes, read in LABEL_READERS:
        if name.endswith(suffixes):
            return read(p, num_vertices)
    raise LabelIOError(f"{p}: unknown label format; expected one of {', '.join(LABEL_SUFFIXES)}")


LABEL_READERS: tuple[tuple[tuple[str, ...], Callable[[Path, int], LabelData]], ...] = (
    ((RESULT_SUFFIX,), lambda p, n: _read_efem(p, n)),  # before ".npz": a result is an .npz too
    ((".ply",), _read_ply_labels),
    ((".npz",), _read_npz_labels),
    ((".aggregation.json", ".segs.json"), _read_scannet),
)
"""The label formats `load_labels` reads, by file-name suffix, first match wins (one row per format)."""


def load_scan(path: str | os.PathLike[str], *, max_points: int = MAX_SCAN_POINTS) -> Any:
    """Open a scan as an `efem_viz.data.scene.Scene`: PLY/OBJ/OFF/GLB/NPZ scenes or a real RGB-D frame `.npz`.

    Thin wrapper over `efem_viz.data.io.load_scene` (which also imports RGB-D frames with the table plane to +Z)
    that reports failures as `LabelIOError`. The file is only read, never written.

    Raises:
        LabelIOError: anything that prevents opening it (the message names the file and the reason).
    """
    from efem_viz.data.io import load_scene
    from efem_viz.data.scene import SceneError

    try:
        return load_scene(Path(path), max_points=max_points)
    except SceneError as exc:
        raise LabelIOError(str(exc)) from exc


