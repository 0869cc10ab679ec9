"""GLB (binary glTF) scenes, read and written through trimesh.

glTF is +Y up by specification: GLB files are converted from our +Z-up world frame on save, `(x, y, z) -> (x, z,
-y)`, and back on load. Meshes keep instance labels in an `_instance` vertex attribute (float32, so ids below
2^24); point clouds have no normals slot: their normals and labels travel, packed, in the scene's JSON extras
(key `efem`), with the categories and the provenance. Chunk lengths and accessor counts are checked against the
file and `max_points` before trimesh reads it.
"""

from __future__ import annotations

import base64
import json
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.data.formats.common import from_trimesh
from efem_viz.data.scene import SCENE_SCHEMA_VERSION, TOO_MANY_POINTS_HINT, Scene, SceneError

_GLB_EXTRAS_KEY = "efem"
_MAX_GLB_LABEL = 2**24  # float32 represents every integer up to 2^24 exactly

_GLTF_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLTF_ITEMSIZE = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}


def _check_glb(p: Path, max_points: int) -> None:
    """Check a GLB's chunk lengths and accessor counts against the file and `max_points` before trimesh reads it.

    trimesh allocates a zero array of an accessor's full `count` when the accessor has no buffer view, and
    builds meshes of the positions' counts; a corrupt header could ask for any size. What trimesh reports well
    itself (a wrong magic number, JSON it cannot parse) is left to it.

    Raises:
        SceneError: a chunk or buffer view that runs past the file, an accessor that runs past its buffer view
            (or, without one, is larger than any scene), more vertex positions than `max_points`.
    """
    got = _read_glb_json(p)
    if got is None:
        return
    gltf, bin_len = got
    views = gltf.get("bufferViews", []) or []
    try:
        _check_buffer_views(p, views, gltf.get("buffers", []) or [], bin_len)
        n_positions = _check_accessors(p, gltf, views, max_points)
    except SceneError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError):
        return  # a malformed glTF structure: trimesh reports it
    if n_positions > max_points:
        raise SceneError(
            f"{p} has {n_positions:,} vertex positions, more than the limit of {max_points:,}; "
            f"{TOO_MANY_POINTS_HINT}"
        )


def _read_glb_json(p: Path) -> tuple[dict[str, Any], int] | None:
    """A GLB's JSON chunk and the length its binary chunk declares, both checked against the file's size.

    Returns:
        (gltf, bin_len); None when trimesh should report the file itself (not GLB, no JSON chunk, JSON it
        cannot parse, not a JSON object).

    Raises:
        SceneError: the header, the JSON chunk or the binary chunk runs past the end of the file.
    """
    import struct

    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return None
        _, length, json_len, json_type = struct.unpack("<IIII", head[4:])
        if length > size:
            raise SceneError(f"{p}: GLB header says the file has {length:,} bytes, but it has {size:,} (truncated)")
        if json_type != 0x4E4F534A:  # "JSON"
            return None
        if 20 + json_len > size:
            raise SceneError(f"{p}: GLB JSON chunk of {json_len:,} bytes runs past the end of the file ({size:,})")
        try:
            gltf = json.loads(fh.read(json_len))
        except (ValueError, UnicodeDecodeError):
            return None
        bin_head = fh.read(8)  # the JSON chunk's length includes its padding
    if not isinstance(gltf, dict):
        return None
    bin_len = struct.unpack("<I", bin_head[:4])[0] if len(bin_head) == 8 else 0
    if bin_len > max(size - 28 - json_len, 0):
        raise SceneError(f"{p}: GLB binary chunk of {bin_len:,} bytes runs past the end of the file ({size:,})")
    return gltf, bin_len


def _check_buffer_views(p: Path, views: list[Any], buffers: list[Any], bin_len: int) -> None:
    """Every buffer view inside its buffer, and every embedded buffer inside the binary chunk (`bin_len` bytes).

    Raises:
        SceneError: a buffer or buffer view runs past its end; KeyError, IndexError, TypeError, ValueError or
            AttributeError for a malformed structure (`_check_glb` leaves it to trimesh).
    """
    for i, view in enumerate(views):
        buf = buffers[int(view.get("buffer", 0))]
        buf_len = int(buf.get("byteLength", 0))
        if "uri" not in buf and buf_len > bin_len:
            raise SceneError(f"{p}: GLB buffer {view.get('buffer', 0)} claims {buf_len:,} bytes, but the "
                             f"binary chunk holds {bin_len:,}")
        if int(view.get("byteOffset", 0)) + int(view["byteLength"]) > buf_len:
            raise SceneError(f"{p}: GLB bufferView {i} runs past the end of its buffer ({buf_len:,} bytes)")


def _check_accessors(p: Path, gltf: dict[str, Any], views: list[Any], max_points: int) -> int:
    """Every accessor inside its buffer view (or, without one, no larger than any scene); returns the number of
    vertex positions of the meshes' primitives.

    Raises:
        SceneError: a negative count, an accessor past its buffer view, a data-less accessor larger than any
            scene; KeyError, IndexError, TypeError, ValueError or AttributeError for a malformed structure.
    """
    n_positions = 0
    position_ids = {
        int(prim["attributes"]["POSITION"])
        for mesh in gltf.get("meshes", []) or []
        for prim in mesh.get("primitives", []) or []
        if "POSITION" in (prim.get("attributes") or {})
    }
    for i, acc in enumerate(gltf.get("accessors", []) or []):
        count = int(acc["count"])
        comps = _GLTF_COMPONENTS[acc["type"]]
        itemsize = _GLTF_ITEMSIZE[int(acc["componentType"])]
        if count < 0:
            raise SceneError(f"{p}: GLB accessor {i} has a negative count ({count})")
        if i in position_ids:
            n_positions += count
        if "bufferView" in acc:
            view = views[int(acc["bufferView"])]
            elem = comps * itemsize
            stride = int(view.get("byteStride", elem)) or elem
            need = int(acc.get("byteOffset", 0)) + ((count - 1) * stride + elem if count else 0)
            if need > int(view["byteLength"]):
                raise SceneError(
                    f"{p}: GLB accessor {i} claims {count:,} items ({need:,} bytes), more than its bufferView "
                    f"holds ({int(view['byteLength']):,} bytes): corrupt file"
                )
        elif count * comps > 16 * max(max_points, 1):
            raise SceneError(
                f"{p}: GLB accessor {i} has no data but claims {count:,} items, more than any scene this "
                f"reader accepts (max_points {max_points:,})"
            )
    return n_positions


def load(p: Path, max_points: int) -> dict[str, Any]:
    import trimesh

    _check_glb(p, max_points)
    loaded = trimesh.load(str(p), file_type="glb", process=False)
    extras: dict[str, Any] = {}
    if isinstance(loaded, trimesh.Scene):
        extras = dict(loaded.metadata.get(_GLB_EXTRAS_KEY, {}) or {})
        geoms = list(loaded.geometry.values())
        if not geoms:
            raise SceneError(f"{p}: GLB file has no geometry")
        if len(geoms) == 1 and len(loaded.graph.nodes_geometry) == 1:
            node = loaded.graph.nodes_geometry[0]
            T, gname = loaded.graph[node]
            src = loaded.geometry[gname]
            geom = src.copy()  # copy() drops trimesh's cached vertex normals: the file's NORMAL attribute
            geom.apply_transform(T)
            if isinstance(src, trimesh.Trimesh) and "vertex_normals" in src._cache:
                nrm = np.asarray(src.vertex_normals, np.float64) @ np.linalg.inv(np.asarray(T)[:3, :3])
                geom.vertex_normals = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        else:
            geom = loaded.to_geometry()
    else:
        geom = loaded
    out = from_trimesh(geom, p)
    # glTF is +Y up: (x, y, z)_gltf -> (x, -z, y)_world
    for key in ("points", "normals"):
        if key in out and out[key] is not None:
            arr = np.asarray(out[key], dtype=np.float64)
            out[key] = np.stack([arr[:, 0], -arr[:, 2], arr[:, 1]], axis=1)
    attrs = getattr(geom, "vertex_attributes", {}) or {}
    for key in ("_instance", "instance"):
        if key in attrs:
            out["instance"] = np.asarray(attrs[key]).reshape(-1)
            break
    n_pts = len(out.get("points", ()))  # packed arrays hold one row per point: inflate no more than that
    if "instance_zb64" in extras and "instance" not in out:
        out["instance"] = _unpack_array(extras["instance_zb64"], np.int32, max_items=n_pts)
    if "normals_zb64" in extras and "normals" not in out:  # world frame
        out["normals"] = _unpack_array(extras["normals_zb64"], np.float32, max_items=3 * n_pts).reshape(-1, 3)
    if "categories" in extras:
        out["categories"] = {int(k): str(v) for k, v in dict(extras["categories"]).items()}
    if "provenance" in extras:
        out["provenance"] = dict(extras["provenance"])
    return out


def _pack_array(a: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(np.ascontiguousarray(a).tobytes(), 6)).decode("ascii")


def _unpack_array(s: str, dtype: Any, *, max_items: int) -> np.ndarray:
    """Inverse of `_pack_array`, inflating at most `max_items` items (a zlib bomb stops there).

    Raises:
        SceneError: the data inflates to more than `max_items` items.
    """
    limit = max(int(max_items), 0) * np.dtype(dtype).itemsize
    z = zlib.decompressobj()
    raw = z.decompress(base64.b64decode(s), limit + 1)
    if len(raw) > limit or z.unconsumed_tail:
        raise SceneError(f"packed array inflates to more than {max_items:,} items of {np.dtype(dtype)}")
    return np.frombuffer(raw, dtype=dtype).copy()


def save(scene: Scene, tmp: Path, *, ascii: bool = False) -> None:
    """Write a binary glTF (`ascii` is ignored), converting the world frame (+Z up) to glTF's +Y up."""
    import trimesh

    def to_gltf(a: np.ndarray) -> np.ndarray:  # world +Z up -> glTF +Y up
        a = np.asarray(a, dtype=np.float64)
        return np.stack([a[:, 0], a[:, 2], -a[:, 1]], axis=1)

    extras: dict[str, Any] = {
        "schema_version": SCENE_SCHEMA_VERSION,
        "name": scene.name,
        "categories": {str(k): v for k, v in scene.categories.items()},
        "provenance": json.loads(json.dumps(scene.provenance, default=str)),
    }
    rgba = np.concatenate([scene.colors, np.full((scene.num_points, 1), 255, np.uint8)], axis=1)
    if scene.is_mesh:
        geom = trimesh.Trimesh(
            vertices=to_gltf(scene.points),
            faces=scene.faces,
            vertex_normals=to_gltf(scene.normals),
            vertex_colors=rgba,
            process=False,
        )
        if scene.instance is not None:
            if scene.instance.max(initial=0) >= _MAX_GLB_LABEL:
                raise SceneError(f"GLB stores labels as float32; ids must be < {_MAX_GLB_LABEL}")
            geom.vertex_attributes["instance"] = scene.instance.astype(np.float32)
    else:
        geom = trimesh.PointCloud(to_gltf(scene.points), colors=rgba)
        extras["normals_zb64"] = _pack_array(scene.normals.astype(np.float32))
        if scene.instance is not None:
            extras["instance_zb64"] = _pack_array(scene.instance.astype(np.int32))
    tscene = trimesh.Scene(geom)
    tscene.metadata[_GLB_EXTRAS_KEY] = extras
    glb = tscene.export(file_type="glb")
    if not isinstance(glb, bytes):  # trimesh types export() as str | bytes | dict; GLB is always bytes
        raise TypeError(f"trimesh returned {type(glb).__name__} for a GLB export, expected bytes")
    tmp.write_bytes(glb)
