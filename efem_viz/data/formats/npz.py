"""The native scene `.npz` (the arrays of `Scene.to_npz_dict`, with `schema_version`); an `.npz` holding an RGB-D
frame (`depth_mm` or `depth`, `K`, optional `rgb`) instead of a scene is imported with
`efem_viz.data.rgbd.import_rgbd_file` and its default settings. Array headers are checked before anything is read
(`efem_viz.data.npz_guard.check_npz_headers`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, cast

import numpy as np

from efem_viz.data.formats.common import parse_categories
from efem_viz.data.npz_guard import check_npz_headers
from efem_viz.data.scene import DEFAULT_MAX_POINTS, SCENE_SCHEMA_VERSION, Scene, SceneError

def scene_from_npz(data: Any, *, name: str | None = None, max_points: int = DEFAULT_MAX_POINTS) -> Scene:
    """Build a Scene from the arrays of a native scene `.npz` (as written by `Scene.to_npz_dict`).

    Args:
        data: a mapping of arrays (an open `np.load` result or a dict).
        name: override the stored name.
        max_points: refuse scenes with more points than this.

    Raises:
        SceneError: wrong or missing schema version, missing arrays.
    """
    kwargs = _npz_kwargs(data)
    stored = kwargs.pop("name", None)
    return Scene.create(name or stored or "scene", max_points=max_points, **kwargs)


def _npz_kwargs(data: Any) -> dict[str, Any]:
    keys = set(data.keys())
    if "schema_version" not in keys:
        raise SceneError("not a native scene .npz: no 'schema_version' array (expected keys points, normals, ...)")
    version = int(np.asarray(data["schema_version"]))
    if version != SCENE_SCHEMA_VERSION:
        raise SceneError(
            f"scene schema_version {version} is not supported (this efem-viz reads version {SCENE_SCHEMA_VERSION})"
        )
    if "points" not in keys:
        raise SceneError("scene .npz has no 'points' array")
    out: dict[str, Any] = {"points": data["points"]}
    for key in ("normals", "colors", "faces", "instance"):
        if key in keys:
            out[key] = data[key]
    if "name" in keys:
        out["name"] = str(np.asarray(data["name"]))
    if "categories_json" in keys:
        out["categories"] = parse_categories(str(np.asarray(data["categories_json"])))
    if "provenance_json" in keys:
        out["provenance"] = json.loads(str(np.asarray(data["provenance_json"])))
    return out


def load(p: Path, max_points: int) -> dict[str, Any]:
    check_npz_headers(p, max_points)
    with np.load(p, allow_pickle=False) as data:
        keys = set(data.files)
        rgbd_frame = "schema_version" not in keys and "K" in keys and bool({"depth_mm", "depth"} & keys)
        if not rgbd_frame:
            kwargs = _npz_kwargs(data)
            # materialise the arrays before the file closes
            return {k: (np.array(v) if isinstance(v, np.ndarray) else v) for k, v in kwargs.items()}
    # an RGB-D frame (rgb, depth_mm or depth, K): import it with the default settings
    from efem_viz.data.rgbd import import_rgbd_file

    scene = import_rgbd_file(p)
    return {"points": scene.points, "normals": scene.normals, "colors": scene.colors,
            "provenance": dict(scene.provenance)}


def save(scene: Scene, tmp: Path, *, ascii: bool = False) -> None:
    """Write the scene's arrays compressed (`ascii` is ignored)."""
    # cast: numpy's stub would take a **dict[str, ndarray] to possibly fill `allow_pickle: bool`
    np.savez_compressed(tmp, **cast("dict[str, Any]", scene.to_npz_dict()))
