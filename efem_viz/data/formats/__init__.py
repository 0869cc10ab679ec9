"""Scene file formats: one module per format, all behind one table, `FORMATS` (as trimesh's `exchange/`).

`load_scene` and `save_scene` (efem_viz/data/io.py) pick the row by the file's suffix. A new format is one module
with a `load(path, max_points) -> dict` (the keyword arguments of `Scene.create`: points, normals, colors, faces,
instance, categories, provenance; bounds-checked before anything is allocated, errors as `SceneError`) and a
`save(scene, tmp_path, *, ascii)` (writes the whole file to the temporary path `atomic_write` gives it), plus one
row here. The table is read at each call, so a row added at run time (`FORMATS[".xyz"] = SceneFormat(...)`,
examples/add_scene_format.py) is a format `load_scene`, `save_scene` and `find_scenes` know from then on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, NamedTuple

from efem_viz.data.formats import glb, las, npz, obj_off, pcd, ply


class SceneFormat(NamedTuple):
    """One row of `FORMATS`: how a scene file format is read and written."""

    load: Callable[[Path, int], dict[str, Any]]
    """`load(path, max_points)`: the `Scene.create` keyword arguments read from the file."""
    save: Callable[..., None]
    """`save(scene, tmp_path, *, ascii)`: write the whole file (`ascii`: the text form, where there is a choice)."""
    keeps_labels: bool = True
    """Whether the format holds per-vertex instance labels (saving a labelled scene without it warns)."""
    keeps_faces: bool = True
    """Whether the format holds triangles (saving a mesh without it keeps the vertices only, with a warning)."""


FORMATS: dict[str, SceneFormat] = {
    ".ply": SceneFormat(ply.load, ply.save),
    ".obj": SceneFormat(obj_off.load_obj, obj_off.save_obj, keeps_labels=False),
    ".off": SceneFormat(obj_off.load_off, obj_off.save_off, keeps_labels=False),
    ".glb": SceneFormat(glb.load, glb.save),
    ".npz": SceneFormat(npz.load, npz.save),
    ".pcd": SceneFormat(pcd.load, pcd.save, keeps_faces=False),
    ".las": SceneFormat(las.load, las.save, keeps_faces=False),
    ".laz": SceneFormat(las.load, las.save_laz, keeps_faces=False),
}
"""Scene formats by lower-case file suffix (its keys are the suffixes `load_scene` understands)."""

__all__ = ["FORMATS", "SceneFormat"]
