"""Reading and writing scenes: `load_scene` and `save_scene` over the format table (efem_viz/data/formats/: PLY
(binary/ASCII), OBJ, OFF, GLB and the native NPZ), and the public names of the data files, re-exported here so
that `from efem_viz.data.io import ...` keeps working: `atomic_write`, `find_scenes` and the suffixes live in
efem_viz/data/files.py, the PLY header reader in efem_viz/data/formats/ply.py.

Which format keeps what (a round trip through `save_scene` then `load_scene`):

| format | points | normals | colours | faces | instance labels | categories, provenance |
|--------|--------|---------|---------|-------|-----------------|------------------------|
| .ply   | yes    | yes     | yes     | yes   | yes (`instance` int vertex property) | yes (comment lines) |
| .npz   | yes    | yes     | yes     | yes   | yes             | yes                    |
| .glb   | yes    | meshes¹ | yes     | yes   | yes¹            | yes (scene extras)     |
| .obj   | yes    | yes     | yes (`v x y z r g b`) | yes | no  | no                     |
| .off   | yes    | yes (NOFF) | yes (COFF) | yes | no         | no                     |

¹ GLB meshes carry normals and an `_instance` vertex attribute; GLB point clouds carry both in the scene's JSON
extras.

(An `.npz` holding an RGB-D frame — `depth_mm` or `depth`, `K`, optional `rgb` — instead of a scene is imported
with `efem_viz.data.rgbd.import_rgbd_file` and its default settings.)

OBJ and OFF have no place for per-vertex integer labels, so ground truth is dropped on save (with a warning) and
never present on load; use PLY or NPZ for labelled scenes. glTF is +Y up by specification: GLB files are converted
from our +Z-up world frame on save, `(x, y, z) -> (x, z, -y)`, and back on load. GLB point clouds have no normals
slot; their normals and labels travel in the scene's JSON extras.

PLY conventions (the same file the annotator writes, readable by MeshLab/CloudCompare): vertex properties
`x y z` (float), `nx ny nz` (float, optional), `red green blue` (uchar, optional), `instance` (int, optional,
0 = unlabelled); element `face` with list property `vertex_indices`. Categories and provenance are stored as
header comments `efem_categories {json}` and `efem_provenance {json}`.

Every write goes through `atomic_write`: a temporary file in the destination directory, fsync, then `os.replace`,
so a crash never leaves a half-written scene behind.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from efem_viz.data.files import (
    RESULT_SUFFIX,
    SEG_SUFFIX,
    ScenePathNotFoundError,
    atomic_write,
    atomic_write_bytes,
    atomic_write_text,
    find_scenes,
    holds_predictions,
    is_scene_file,
)
from efem_viz.data.formats import FORMATS, SceneFormat
from efem_viz.data.formats.scannet import read_scannet_instances, scannet_pair_of
from efem_viz.data.formats.npz import scene_from_npz
from efem_viz.data.formats.ply import PlyElementHeader, PlyHeader, check_ply_counts, read_ply_header
from efem_viz.data.scene import DEFAULT_MAX_POINTS, Scene, SceneError

__all__ = [
    "FORMATS",
    "RESULT_SUFFIX",
    "SEG_SUFFIX",
    "PlyElementHeader",
    "PlyHeader",
    "SceneFormat",
    "ScenePathNotFoundError",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_ply_counts",
    "find_scenes",
    "holds_predictions",
    "is_scene_file",
    "load_scene",
    "read_ply_header",
    "save_scene",
    "scene_from_npz",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- load
def load_scene(
    path: str | os.PathLike[str],
    *,
    max_points: int = DEFAULT_MAX_POINTS,
    name: str | None = None,
) -> Scene:
    """Load a scene (mesh or point cloud) from .ply, .pcd, .las, .laz, .obj, .off, .glb or .npz.

    Missing normals are estimated on first use of `Scene.normals` (area-weighted face normals for meshes, PCA
    normals oriented consistently for point clouds; `Scene.normals_pending` tells), so a caller that never
    reads them (`efem-viz info`) never pays for them; missing colours become grey.

    Hostile or corrupt files fail with one `SceneError` in time and memory bounded by the file's real size:
    every count a header declares (PLY elements, OFF counts, GLB accessors, NPZ array headers) is checked
    against the bytes the file holds, `max_points` and `MAX_FACES_PER_POINT` before anything is allocated for
    it, and an ASCII PLY or OFF with data rows beyond its header's counts is refused.

    Args:
        path: the scene file.
        max_points: refuse files with more points than this.
        name: scene name; default: the file name without its suffix.

    Returns:
        The validated `Scene` (world frame, metres, +Z up).

    Raises:
        SceneError: missing file, a directory, unknown suffix, corrupt or truncated file, a header count the
            file cannot hold, rows beyond the header's counts, empty scene, NaN/Inf, mismatched array lengths,
            non-integer labels, more than `max_points` points or `MAX_FACES_PER_POINT * max_points` faces. The
            message names the path.
    """
    p = Path(path)
    if not p.exists():
        raise SceneError(f"{p}: no such file")
    if p.is_dir():
        raise SceneError(f"{p} is a directory, not a scene file (use find_scenes to list a folder)")
    if p.name.lower().endswith(RESULT_SUFFIX):
        raise SceneError(f"{p} is an EFEM result file (load it with EMResult.load), not a scene")
    suffix = p.suffix.lower()
    if suffix not in FORMATS:
        raise SceneError(f"{p}: unknown scene format {suffix!r}; expected one of {', '.join(FORMATS)}")
    if p.stat().st_size == 0:
        raise SceneError(f"{p}: file is empty (0 bytes)")
    scene_name = name if name is not None else p.name[: -len(p.suffix)]
    try:
        kwargs = FORMATS[suffix].load(p, max_points)
    except SceneError as exc:
        msg = str(exc)
        raise SceneError(msg if str(p) in msg else f"{p}: {msg}") from exc
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # parser errors of plyfile / trimesh / numpy: corrupt or truncated file
        raise SceneError(f"{p}: could not read {suffix[1:].upper()} file ({type(exc).__name__}: {exc})") from exc
    kwargs.pop("name", None)  # the file name wins over a name stored inside the file
    pair = scannet_pair_of(p) if kwargs.get("instance") is None else None
    if pair is not None:  # a ScanNet scene mesh: its instance annotation is the ground truth
        gt = read_scannet_instances(pair[0], len(kwargs["points"]))
        kwargs["instance"], kwargs["categories"] = gt.labels, gt.categories
    try:
        return Scene.create(scene_name, max_points=max_points, **kwargs)
    except SceneError as exc:
        raise SceneError(f"{p}: {exc}") from exc


# ---------------------------------------------------------------------------------------------- save
def save_scene(scene: Scene, path: str | os.PathLike[str], *, ascii: bool = False) -> Path:
    """Save a scene; the format comes from the suffix (.ply, .pcd, .las, .laz, .obj, .off, .glb, .npz). Atomic.

    Args:
        scene: the scene.
        path: destination file.
        ascii: for .ply, write ASCII instead of binary little-endian.

    Returns:
        The destination path.

    Raises:
        SceneError: unknown suffix.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if p.name.lower().endswith(RESULT_SUFFIX):
        raise SceneError(f"{p}: the suffix {RESULT_SUFFIX} is reserved for EFEM results; choose another name")
    fmt = FORMATS.get(suffix)
    if fmt is None:
        raise SceneError(f"{p}: unknown scene format {suffix!r}; expected one of {', '.join(FORMATS)}")
    if not fmt.keeps_labels and scene.has_gt:
        log.warning("%s: %s cannot hold instance labels; they are not saved (use .ply or .npz)", p, suffix)
    if not fmt.keeps_faces and scene.is_mesh:
        log.warning("%s: %s holds points only; the mesh's vertices are saved without its faces", p, suffix)
    return atomic_write(p, lambda tmp: fmt.save(scene, tmp, ascii=ascii))
