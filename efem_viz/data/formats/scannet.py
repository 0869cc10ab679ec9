"""ScanNet's instance annotation: ``<scene>.segs.json`` (``segIndices``: a segment id per mesh vertex) and
``<scene>.aggregation.json`` (``segGroups``: each object's id, label and segments).

The one reader of the pair: `load_scene` attaches it as ground truth to a ScanNet scene mesh opened directly
(`scannet_pair_of`: ``scene0000_00_vh_clean_2.ply`` with ``scene0000_00.aggregation.json`` and
``scene0000_00_vh_clean_2.0.010000.segs.json`` beside it), and the annotator imports and exports labels in it.
Instance ids are ``objectId + 1`` (0 = unlabelled); the category is the object's ``label``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efem_viz.data.scene import SceneError
from efem_viz.terminal import one_line

MESH_SUFFIX = "_vh_clean_2.ply"
"""The suffix of ScanNet's annotated scene meshes."""


class ScanNetInstances(NamedTuple):
    """What a segs/aggregation pair says about a scan's vertices."""

    labels: np.ndarray
    """(N,) int32 instance id per vertex (objectId + 1; 0 = none)."""
    categories: dict[int, str]
    """Instance id -> label."""
    names: dict[int, str]
    """Instance id -> the object's name (its `name`, else "<label> <id>")."""
    segs_path: Path
    aggregation_path: Path


def scannet_pair_of(mesh: Path) -> tuple[Path, Path] | None:
    """(aggregation, segs) beside a ScanNet scene mesh ``<scene>_vh_clean_2.ply``, or None."""
    if not mesh.name.endswith(MESH_SUFFIX):
        return None
    scene = mesh.name[: -len(MESH_SUFFIX)]
    agg = next((p for p in (mesh.with_name(f"{scene}.aggregation.json"),
                            mesh.with_name(f"{scene}_vh_clean.aggregation.json")) if p.is_file()), None)
    segs = mesh.with_name(f"{scene}_vh_clean_2.0.010000.segs.json")
    return (agg, segs) if agg is not None and segs.is_file() else None


def read_scannet_instances(path: Path, n: int, *, error: type[ValueError] = SceneError) -> ScanNetInstances:
    """Per-vertex instance ids from a segs/aggregation pair (`path`: either file; the other is found beside it,
    or by the aggregation's ``segmentsFile`` name, never by a path inside the file).

    Raises:
        `error`: unreadable or malformed JSON, a vertex count other than `n`, non-integer segment ids, an objectId
            out of range.
    """
    p = Path(path)
    name = p.name
    stem = name[: -len(".aggregation.json")] if name.endswith(".aggregation.json") else name[: -len(".segs.json")]
    agg_p = p if name.endswith(".aggregation.json") else p.with_name(stem + ".aggregation.json")
    segs_p = p if name.endswith(".segs.json") else p.with_name(stem + ".segs.json")
    try:
        agg = json.loads(agg_p.read_text(encoding="utf-8"))
        if not isinstance(agg, dict):
            raise TypeError(f"{agg_p.name} holds a JSON {type(agg).__name__}, not an object")
        segs_name = agg.get("segmentsFile") or f"{stem}.segs.json"
        named = p.with_name(Path(str(segs_name)).name)  # never follow a path inside the file
        if not name.endswith(".segs.json") and named.exists():
            segs_p = named
        elif not name.endswith(".segs.json") and str(segs_name).startswith("scannet."):
            plain = p.with_name(Path(str(segs_name)).name[len("scannet."):])  # ScanNet's own files name it so
            segs_p = plain if plain.exists() else segs_p
        segs = json.loads(segs_p.read_text(encoding="utf-8"))
        if not isinstance(segs, dict):
            raise TypeError(f"{segs_p.name} holds a JSON {type(segs).__name__}, not an object")
        seg_idx = np.asarray(segs["segIndices"])
        groups = agg["segGroups"]
        if not isinstance(groups, list):
            raise TypeError(f"segGroups is a JSON {type(groups).__name__}, not a list")
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise error(f"{p}: could not read ScanNet segs/aggregation pair ({one_line(exc, limit=300)})") from exc
    if seg_idx.ndim != 1 or len(seg_idx) != n:
        raise error(f"{segs_p}: has {seg_idx.shape} segIndices, the scan has {n} vertices")
    if not np.issubdtype(seg_idx.dtype, np.integer):
        raise error(f"{segs_p}: segIndices must be integers, got {seg_idx.dtype}")
    labels = np.zeros(n, np.int32)
    categories: dict[int, str] = {}
    names: dict[int, str] = {}
    for k, g in enumerate(groups):
        try:
            if not isinstance(g, dict):
                raise TypeError(f"a JSON {type(g).__name__}, not an object")
            raw_id: Any = g.get("objectId", g.get("id"))  # None (neither key) fails int() as a TypeError
            iid = int(raw_id) + 1
            segments = np.asarray([int(s) for s in g["segments"]], np.int64)
            cat = str(g.get("label", "object"))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise error(f"{agg_p}: malformed segGroups[{k}] {repr(g)[:80]} ({one_line(exc, limit=300)})") from exc
        if not 0 < iid <= np.iinfo(np.int32).max:
            raise error(f"{agg_p}: segGroups[{k}] objectId must be in [0, {np.iinfo(np.int32).max - 1}], "
                        f"got {iid - 1}")
        labels[np.isin(seg_idx, segments)] = iid
        categories[iid] = cat
        names[iid] = str(g.get("name", f"{cat} {iid}"))
    return ScanNetInstances(labels, categories, names, segs_p, agg_p)
