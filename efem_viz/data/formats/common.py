"""Pieces several scene formats share: the categories table of PLY comments and NPZ, polygon fan
triangulation (PLY, OFF) and the arrays of a trimesh geometry (OBJ, GLB)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.scene import SceneError

log = logging.getLogger(__name__)

CATEGORIES_COMMENT = "efem_categories"
"""PLY header comment holding a scene's categories `{id: name}` as JSON (also written by the annotator)."""
PROVENANCE_COMMENT = "efem_provenance"
"""PLY header comment holding a scene's provenance as JSON."""


def parse_categories(text: str) -> dict[int, str]:
    """A scene's categories `{id: name}` from their JSON object (a PLY comment, an NPZ's `categories_json`).

    Raises:
        SceneError: not a JSON object, or an id that is not an integer.
    """
    raw = json.loads(text)
    if not isinstance(raw, dict):
        raise SceneError(f"categories must be a JSON object {{id: name}}, got {type(raw).__name__}")
    try:
        return {int(k): str(v) for k, v in raw.items()}
    except ValueError as exc:
        raise SceneError(f"category ids must be integers: {exc}") from exc

def triangulate(polys: list[np.ndarray], p: Path) -> np.ndarray | None:
    """Fan-triangulate polygon faces into (M, 3) int64 (None for no faces); see `triangulate_flat`."""
    if not polys:
        return None
    lens = np.fromiter((len(f) for f in polys), dtype=np.int64, count=len(polys))
    return triangulate_flat(lens, np.concatenate(polys), p)


def triangulate_flat(lens: np.ndarray, flat: np.ndarray, p: Path) -> np.ndarray | None:
    """Fan-triangulate flattened polygons: polygon i is `flat[o_i : o_i + lens[i]]` with o_i = sum(lens[:i]).

    Polygon (v0, v1, ..., vn-1) becomes the triangles (v0, v1, v2), (v0, v2, v3), ..., in polygon order.

    Args:
        lens: (F,) int, vertices per polygon.
        flat: (sum(lens),) int (or the PLY list's value type), vertex indices of all polygons in order.
        p: the file, for the error message.

    Returns:
        (M, 3) int64 triangles, or None when there are no polygons.

    Raises:
        SceneError: a polygon has fewer than 3 vertices.
    """
    if len(lens) == 0:
        return None
    if (lens == 3).all():
        return flat.reshape(-1, 3).astype(np.int64)
    if (lens < 3).any():
        raise SceneError(f"{p}: {(lens < 3).sum()} faces have fewer than 3 vertices")
    n_tri = lens - 2
    first = np.repeat(np.cumsum(lens) - lens, n_tri)  # index in `flat` of each triangle's polygon's v0
    k = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)  # triangle's rank in polygon
    return np.stack([flat[first], flat[first + 1 + k], flat[first + 2 + k]], axis=1).astype(np.int64)


def from_trimesh(geom: Any, p: Path) -> dict[str, Any]:
    """Arrays from a trimesh Trimesh or PointCloud."""
    import trimesh

    out: dict[str, Any] = {}
    if isinstance(geom, trimesh.PointCloud):
        out["points"] = np.asarray(geom.vertices)
        cols = getattr(geom, "colors", None)
        if cols is not None and len(cols) == len(geom.vertices):
            out["colors"] = np.asarray(cols)[:, :3]
        return out
    if not isinstance(geom, trimesh.Trimesh):
        raise SceneError(f"{p}: contains no mesh or point cloud (got {type(geom).__name__})")
    out["points"] = np.asarray(geom.vertices)
    faces = np.asarray(geom.faces)
    out["faces"] = faces if faces.size else None
    if "vertex_normals" in geom._cache:  # stored in the file; otherwise the Scene derives them on first use
        nrm = np.asarray(geom.vertex_normals)
        if len(nrm) == len(geom.vertices) and np.isfinite(nrm).all():
            out["normals"] = nrm
    # duck-typed on `kind`: ColorVisuals ("vertex"/"face") or TextureVisuals ("texture")
    visual: Any = geom.visual
    if getattr(visual, "kind", None) == "vertex":
        out["colors"] = np.asarray(visual.vertex_colors)[:, :3]
    elif getattr(visual, "kind", None) == "face":
        # ColorVisuals with per-face colours: trimesh averages them onto the vertices (to_color() is for textures)
        out["colors"] = np.asarray(visual.vertex_colors)[:, :3]
    elif getattr(visual, "kind", None) == "texture":
        try:
            out["colors"] = np.asarray(visual.to_color().vertex_colors)[:, :3]
        except Exception as exc:  # texture without UVs etc.: keep default grey
            log.warning("%s: could not convert the material/texture to vertex colours (%s)", p, exc)
    return out

