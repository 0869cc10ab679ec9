"""Fuzz every loader: each input gives a valid object or one clear error, in bounded time and
memory, and nothing is written.

Loaders: `load_scene` on PLY (binary and ASCII), OBJ, OFF, NPZ (scene and RGB-D frame), GLB, PCD and LAS/LAZ; RGB-D
frame import (`import_rgbd_file`); the annotator's `load_labels` on every label format (PLY `instance`, checkpoint and
plain NPZ, ScanNet segs/aggregation JSON, EFEM `.efem.npz`); `EMResult.load`; the prior `load_prior` (weights
and codebook). Each starts from small valid seed files made in a temporary folder (tiny scenes through
`save_scene`, a bundled `sample_scenes/*.efem.npz`, a small ray-cast frame, the shipped `weights/mug.pt`) and
mutates them: byte flips, truncation, zeroed regions, header numbers set to huge/negative/NaN values, duplicated
or removed lines (text formats), edits inside one member of a zip (the `.npy`/`.pt` member bytes, with valid
CRCs so the loader sees them), edits of the arrays of an `.npz`, of a JSON value (ScanNet, GLB, JSON texts in
`.npz`) or of a checkpoint entry (config, tensors), random junk, an empty file, a directory, a named pipe and a
missing path.

Every input is loaded in a forked child (`os.fork`, so nothing is imported again) under an address-space limit,
with tracemalloc and the peak resident set measured, and killed after `TIME_LIMIT_S`. An outcome is

* ``ok``: the loader returned a valid object (checked: finite arrays, shapes, label ranges, finite weights);
* ``clean_error``: it raised a `ValueError` (the project's `SceneError`, `LabelIOError`, `ResultFileError`,
  `PickleRequired`, ...) or an `OSError`, with a one-line message that names the file;
* ``bad``: anything else: another exception type, a message over several lines or not naming the file, an
  invalid object, over the time or memory limit, a crash, or a file created or changed in the input folder.

`run_fuzz` is also the fuzz part of ``bench/reliability.py`` (``run_fuzz(budget_s=..., seed=0)``).
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import resource
import select
import shutil
import signal
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # bench/reliability.py imports this module with only tests/ on the path
    sys.path.insert(0, str(ROOT))

TIME_LIMIT_S = 10.0
"""A single load slower than this is a hang (the child is killed)."""
MEMORY_LIMIT_MB = 1024
"""A single load whose tracemalloc peak or resident-set growth is over this is bad."""
ADDRESS_SPACE_HEADROOM_MB = 3072
"""The child's RLIMIT_AS is its size at fork plus this: a runaway allocation fails fast instead of swapping."""
MAX_MESSAGE_CHARS = 800
"""An error message longer than this is not "one clear line"."""
RESULT_SAMPLE = ROOT / "sample_scenes" / "syn_z_1.efem.npz"
PRIOR_WEIGHTS = ROOT / "efem_viz" / "weights" / "mug.pt"
PRIOR_CODEBOOK = ROOT / "efem_viz" / "weights" / "mug_codebook.npz"

HOSTILE_NUMBERS: tuple[bytes, ...] = (
    b"0", b"-1", b"1", b"-2147483648", b"2147483647", b"2147483648", b"4294967296", b"1000000000000",
    b"9223372036854775807", b"18446744073709551616", b"99999999999999999999999999999", b"1e308", b"1e999",
    b"-1e999", b"nan", b"NaN", b"inf", b"-inf", b"3.5", b"-0", b"0x10", b"", b"1_000",
)
"""What a header number is replaced by."""
JSON_VALUES: tuple[Any, ...] = (
    None, True, 0, -1, 2**31, 2**63, -(2**63), 1e308, float("nan"), float("inf"), 3.5, "", "x" * 300,
    "../../../../etc/passwd", [], {}, [[1, 2]], {"a": 1}, [None],
)
"""What a JSON value is replaced by."""


# ---------------------------------------------------------------------------------------------- seed files
def _tiny_mesh_scene(seed: int) -> Any:
    import trimesh

    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    n = len(m.vertices)
    return Scene.create(
        "ball", m.vertices + [0.2, -0.1, 0.3], normals=m.vertex_normals,
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8), faces=m.faces, instance=rng.integers(0, 3, n),
        categories={1: "mug", 2: "bowl"}, provenance={"source": "fuzz", "seed": seed, "nested": {"a": [1, 2]}},
    )


def _tiny_cloud_scene(seed: int) -> Any:
    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(60, 3)) * [0.2, 0.2, 0.02]  # a noisy slab: PCA normals are well defined
    return Scene.create("cloud", pts, instance=(pts[:, 0] > 0).astype(np.int32), categories={1: "mug"})


def _frame_arrays(seed: int) -> dict[str, np.ndarray]:
    """A small RGB-D frame (96 x 128): a table plane seen from above at an angle, with a box standing on it."""
    rng = np.random.default_rng(seed)
    H, W, f = 96, 128, 110.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones((H, W))], axis=-1)
    n = np.array([0.0, -1.0, -0.5]) / np.linalg.norm([0.0, -1.0, -0.5])
    d = -n @ np.array([0.0, 0.25, 0.7])
    z = -d / (rays @ n)
    box = (abs(u - W / 2) < 12) & (abs(v - H / 2) < 10)
    z = np.where(box, z - 0.05, z) + rng.normal(0, 0.0005, z.shape)
    depth_mm = np.where((z > 0) & (z < 2.0), np.round(z * 1000), 0).astype(np.uint16)
    rgb = np.stack([u * 2 % 256, v * 2 % 256, np.full_like(u, 128)], axis=-1).astype(np.uint8)
    return {"rgb": rgb, "depth_mm": depth_mm, "K": K}


@dataclass
class _Seed:
    """One valid input: the files of its folder (name -> bytes) and which of them the loader opens."""

    files: dict[str, bytes]
    target: str
    text: bool = False
    """The target is a text format (lines may be duplicated or dropped)."""
    header_end: bytes | None = None
    """Header numbers are edited only before this marker (binary PLY); None: anywhere in a text file."""


@dataclass
class _Loader:
    name: str
    seeds: list[_Seed]
    call: Callable[[Path], Any]
    check: Callable[[Any], None]
    kinds: tuple[str, ...]
    magic: bytes = b""
    mutable: tuple[str, ...] = ()
    """Names of the files a mutation may pick (default: the target only)."""
    stats: dict[str, Any] = field(default_factory=dict)


def _check_scene(sc: Any) -> None:
    from efem_viz.data.scene import Scene

    assert isinstance(sc, Scene), type(sc)
    n = sc.num_points
    assert n > 0 and sc.points.shape == (n, 3) and sc.points.dtype == np.float32
    assert np.isfinite(sc.points).all(), "non-finite points"
    nrm = sc.normals  # estimated now when the file had none
    assert nrm.shape == (n, 3) and np.isfinite(nrm).all(), f"normals {nrm.shape} finite={np.isfinite(nrm).all()}"
    assert sc.colors.shape == (n, 3) and sc.colors.dtype == np.uint8
    if sc.faces is not None:
        assert sc.faces.ndim == 2 and sc.faces.shape[1] == 3 and sc.faces.dtype == np.int32
        assert sc.faces.min() >= 0 and sc.faces.max() < n, "face index out of range"
    if sc.instance is not None:
        assert sc.instance.shape == (n,) and sc.instance.dtype == np.int32
        assert sc.instance.min() >= 0, f"negative instance label {sc.instance.min()}"
    json.dumps(dict(sc.provenance), allow_nan=True)
    for k, v in sc.categories.items():
        assert isinstance(k, int) and isinstance(v, str)


def _check_labels(n: int) -> Callable[[Any], None]:
    def check(ld: Any) -> None:
        from annotator.io import LabelData

        assert isinstance(ld, LabelData), type(ld)
        lab = ld.labels
        assert lab.shape == (n,) and lab.dtype == np.int32, f"labels {lab.shape} {lab.dtype}"
        assert lab.min() >= 0, f"negative label {lab.min()}"
        ids = {r.id for r in ld.instances}
        missing = set(int(i) for i in np.unique(lab) if i > 0) - ids
        assert not missing, f"labels {sorted(missing)[:5]} have no instance row"
        if ld.confidence is not None:
            assert all(np.isfinite(c) for c in ld.confidence.values()), "non-finite confidence"

    return check


def _check_result(res: Any) -> None:
    from efem_viz.em.results import EMResult

    assert isinstance(res, EMResult), type(res)
    inst = res.instances
    k = len(inst)
    assert len(inst.masks) == k and len(inst.mesh_vertices) == k and len(inst.mesh_faces) == k
    assert np.isfinite(inst.confidence).all()
    lab = inst.label_array(res.num_points)
    assert lab.shape == (res.num_points,)
    for j in range(k):
        assert inst.mesh_faces[j].size == 0 or inst.mesh_faces[j].max() < len(inst.mesh_vertices[j])
    json.dumps(res.timings, allow_nan=True)


def _check_prior(prior: Any) -> None:
    import torch

    from efem_viz.prior.model import ShapePrior

    assert isinstance(prior, ShapePrior), type(prior)
    for name, t in prior.state_dict().items():
        assert t.dtype.is_floating_point is False or bool(torch.isfinite(t).all()), f"non-finite weights in {name}"
    cb = getattr(prior, "codebook", None)
    if cb is not None:
        assert cb.matches(prior)


def _make_loaders(tmp: Path) -> list[_Loader]:
    """Every loader with its seed files (built once; kept in memory as bytes)."""
    from annotator.io import InstanceInfo, load_labels, save_labels_npz, save_labels_ply, save_scannet
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.data.rgbd import import_rgbd_file
    from efem_viz.em.results import EMResult
    from efem_viz.prior.model import load_prior

    seeds_dir = tmp / "seeds"
    seeds_dir.mkdir()
    mesh, cloud = _tiny_mesh_scene(0), _tiny_cloud_scene(1)

    def saved(scene: Any, name: str, **kw: Any) -> bytes:
        p = seeds_dir / name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            logging.disable(logging.WARNING)
            try:
                save_scene(scene, p, **kw)
            finally:
                logging.disable(logging.NOTSET)
        return p.read_bytes()

    def one(name: str, data: bytes, **kw: Any) -> _Seed:
        return _Seed({name: data}, name, **kw)

    def npz_bytes(arrays: dict[str, np.ndarray], *, compressed: bool = False) -> bytes:
        buf = io.BytesIO()
        (np.savez_compressed if compressed else np.savez)(buf, **arrays)
        return buf.getvalue()

    def scene_npz_arrays(scene: Any) -> dict[str, np.ndarray]:
        with np.load(io.BytesIO(saved(scene, "s.npz")), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def pcl_compressed(scene: Any) -> bytes:
        """A binary_compressed (LZF) PCD as PCL-based tools write it (by open3d)."""
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.points.astype(np.float64)))
        pc.colors = o3d.utility.Vector3dVector(scene.colors / 255.0)
        p = seeds_dir / "c.pcd"
        o3d.io.write_point_cloud(str(p), pc, compressed=True)
        return p.read_bytes()

    frame = _frame_arrays(2)
    scene_kinds = ("byte-flip", "truncate", "zero-region", "junk")
    text_kinds = ("header-number", "line-dup", "line-drop")
    zip_kinds = ("member-bytes", "member-array", "json-value")
    loaders = [
        _Loader("scene-ply-binary", [one("a.ply", saved(mesh, "a.ply"), header_end=b"end_header\n"),
                                     one("b.ply", saved(cloud, "b.ply"), header_end=b"end_header\n")],
                lambda p: load_scene(p), _check_scene, scene_kinds + ("header-number",), b"ply\n"),
        _Loader("scene-ply-ascii", [one("a.ply", saved(mesh, "a.ply", ascii=True), text=True),
                                    one("b.ply", saved(cloud, "b.ply", ascii=True), text=True)],
                lambda p: load_scene(p), _check_scene, scene_kinds + text_kinds, b"ply\nformat ascii 1.0\n"),
        _Loader("scene-obj", [one("a.obj", saved(mesh, "a.obj"), text=True),
                              one("b.obj", saved(cloud, "b.obj"), text=True)],
                lambda p: load_scene(p), _check_scene, scene_kinds + text_kinds, b"v "),
        _Loader("scene-off", [one("a.off", saved(mesh, "a.off"), text=True),
                              one("b.off", saved(cloud, "b.off"), text=True)],
                lambda p: load_scene(p), _check_scene, scene_kinds + text_kinds, b"OFF\n"),
        _Loader("scene-npz", [one("a.npz", saved(mesh, "a.npz")),
                              one("b.npz", npz_bytes(scene_npz_arrays(cloud))),
                              one("c.npz", npz_bytes(frame))],
                lambda p: load_scene(p), _check_scene, scene_kinds + zip_kinds, b"PK\x03\x04"),
        _Loader("scene-glb", [one("a.glb", saved(mesh, "a.glb")), one("b.glb", saved(cloud, "b.glb"))],
                lambda p: load_scene(p), _check_scene, scene_kinds + ("glb-json", "glb-bin"), b"glTF\x02\x00\x00\x00"),
        _Loader("scene-pcd-binary", [one("a.pcd", saved(cloud, "a.pcd"), header_end=b"DATA binary\n"),
                                     one("b.pcd", pcl_compressed(cloud), header_end=b"DATA binary_compressed\n")],
                lambda p: load_scene(p), _check_scene, scene_kinds + ("header-number",), b"VERSION 0.7\n"),
        _Loader("scene-pcd-ascii", [one("a.pcd", saved(cloud, "a.pcd", ascii=True), text=True)],
                lambda p: load_scene(p), _check_scene, scene_kinds + text_kinds, b"VERSION 0.7\n"),
        _Loader("scene-las", [one("a.las", saved(cloud, "a.las")), one("b.laz", saved(cloud, "b.laz"))],
                lambda p: load_scene(p), _check_scene, scene_kinds, b"LASF"),
        _Loader("rgbd-frame", [one("frame.npz", npz_bytes(frame)), one("frame.npz", npz_bytes(frame, compressed=True))],
                lambda p: import_rgbd_file(p), _check_scene, scene_kinds + zip_kinds, b"PK\x03\x04"),
    ]
    # labels for the mesh scene's vertices
    n = mesh.num_points
    labels = np.asarray(mesh.instance, np.int32)
    table = {i: InstanceInfo(i, f"obj {i}", category=("mug" if i == 1 else "bowl")) for i in (1, 2)}
    p = save_labels_ply(mesh, labels, table, seeds_dir / "scan.labels.ply")
    ply_labels = p.read_bytes()
    p = save_labels_npz(labels, table, seeds_dir / "scan.labels.npz", scan_name="scan")
    ckpt_labels = p.read_bytes()
    plain_labels = npz_bytes({"instance": labels, "categories_json": np.array(json.dumps({"1": "mug"}))})
    sp, ap = save_scannet(labels, table, seeds_dir, "scan")
    scannet = {sp.name: sp.read_bytes(), ap.name: ap.read_bytes()}
    result = RESULT_SAMPLE.read_bytes()
    with np.load(RESULT_SAMPLE, allow_pickle=False) as z:
        n_result = int(z["num_points"])
    loaders += [
        _Loader("labels-ply", [one("scan.labels.ply", ply_labels, header_end=b"end_header\n")],
                lambda p: load_labels(p, n), _check_labels(n), scene_kinds + ("header-number",), b"ply\n"),
        _Loader("labels-npz", [one("scan.labels.npz", ckpt_labels), one("scan.labels.npz", plain_labels)],
                lambda p: load_labels(p, n), _check_labels(n), scene_kinds + zip_kinds, b"PK\x03\x04"),
        _Loader("labels-scannet", [_Seed(dict(scannet), ap.name, text=True), _Seed(dict(scannet), sp.name, text=True)],
                lambda p: load_labels(p, n), _check_labels(n), scene_kinds + text_kinds + ("json-value",), b"{",
                mutable=(ap.name, sp.name)),
        _Loader("labels-efem", [one("scan.efem.npz", result)],
                lambda p: load_labels(p, n_result), _check_labels(n_result), scene_kinds + zip_kinds, b"PK\x03\x04"),
        _Loader("result", [one("scene.efem.npz", result)],
                lambda p: EMResult.load(p), _check_result, scene_kinds + zip_kinds, b"PK\x03\x04"),
        _Loader("prior", [_Seed({"prior.pt": PRIOR_WEIGHTS.read_bytes(),
                                 "prior_codebook.npz": PRIOR_CODEBOOK.read_bytes()}, "prior.pt")],
                lambda p: load_prior(p), _check_prior, scene_kinds + ("member-bytes", "checkpoint-value",
                                                                      "codebook-array"), b"PK\x03\x04"),
    ]
    return loaders


# ---------------------------------------------------------------------------------------------- mutations
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _flip(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    if not b:
        return b"\xff", "1 byte"
    a = bytearray(b)
    at = sorted(int(i) for i in rng.integers(0, len(a), int(rng.integers(1, 9))))
    for i in at:
        a[i] ^= int(rng.integers(1, 256))
    return bytes(a), f"bytes {at[:4]}{'...' if len(at) > 4 else ''} of {len(b)}"


def _truncate(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    cut = int(rng.integers(0, max(len(b), 1)))
    return b[:cut], f"at {cut} of {len(b)}"


def _zero(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    if not b:
        return b"\0", "1 byte"
    start = int(rng.integers(0, len(b)))
    length = int(rng.integers(1, max(2, len(b) // 4)))
    a = bytearray(b)
    end = min(len(a), start + length)
    a[start:end] = bytes(end - start)
    return bytes(a), f"[{start}, {end}) of {len(b)}"


def _number_edit(rng: np.random.Generator, b: bytes, end: bytes | None = None) -> tuple[bytes, str]:
    limit = b.find(end) if end is not None and end in b else len(b)
    hits = [m for m in _NUMBER.finditer(b, 0, limit)]
    if not hits:
        return _flip(rng, b)
    # header numbers (the first ones) are picked more often: they are the counts
    m = hits[int(rng.integers(0, min(len(hits), 24)))] if rng.random() < 0.6 else hits[int(rng.integers(0, len(hits)))]
    new = HOSTILE_NUMBERS[int(rng.integers(0, len(HOSTILE_NUMBERS)))]
    return b[: m.start()] + new + b[m.end():], f"{m.group().decode()!r} at {m.start()} -> {new.decode()!r}"


def _lines(rng: np.random.Generator, b: bytes, *, dup: bool) -> tuple[bytes, str]:
    lines = b.split(b"\n")
    i = int(rng.integers(0, len(lines)))
    if rng.random() < 0.4:
        i = int(rng.integers(0, min(len(lines), 16)))  # the header lines more often
    if dup:
        lines.insert(i, lines[i])
    else:
        del lines[i]
    return b"\n".join(lines), f"line {i} {'duplicated' if dup else 'removed'}"


def _junk(rng: np.random.Generator, magic: bytes) -> tuple[bytes, str]:
    n = int(rng.integers(1, 4096))
    data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    if rng.random() < 0.5:
        return magic + data, f"{len(magic) + n} random bytes after the magic {magic[:8]!r}"
    return data, f"{n} random bytes"


def _byte_mutation(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    r = int(rng.integers(0, 4))
    if r == 0:
        return _flip(rng, b)
    if r == 1:
        return _truncate(rng, b)
    if r == 2:
        return _zero(rng, b)
    return _number_edit(rng, b[:160]) if len(b) else _flip(rng, b)  # .npy / pickle headers live up front


def _number_edit_head(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    head, desc = _number_edit(rng, b[:160])
    return head + b[160:], desc


def _zip_members(b: bytes) -> list[tuple[zipfile.ZipInfo, bytes]]:
    with zipfile.ZipFile(io.BytesIO(b)) as zf:
        return [(i, zf.read(i)) for i in zf.infolist()]


def _zip_write(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members:
            zf.writestr(name, data)
    return buf.getvalue()


def _member_bytes(rng: np.random.Generator, b: bytes) -> tuple[bytes, str]:
    """Mutate the bytes of one zip member and rewrite the archive with valid CRCs (the loader sees the damage)."""
    members = _zip_members(b)
    k = int(rng.integers(0, len(members)))
    info, data = members[k]
    r = int(rng.integers(0, 4))
    new, desc = (_flip, _truncate, _zero, _number_edit_head)[r](rng, data)
    out = [(i.filename, d) for i, d in members]
    out[k] = (info.filename, new)
    return _zip_write(out), f"member {info.filename}: {('flip', 'truncate', 'zero', 'number')[r]} {desc}"


def _json_mutate(rng: np.random.Generator, obj: Any) -> tuple[Any, str]:
    """Replace, drop or duplicate one value somewhere in a parsed JSON document."""
    spots: list[tuple[Any, Any, str]] = []  # (container, key, path)

    def walk(o: Any, path: str, depth: int) -> None:
        if depth > 6 or len(spots) > 4000:
            return
        if isinstance(o, dict):
            for k, v in o.items():
                spots.append((o, k, f"{path}.{k}"))
                walk(v, f"{path}.{k}", depth + 1)
        elif isinstance(o, list):
            idx = (range(len(o)) if len(o) <= 8
                   else sorted({0, len(o) - 1, *(int(i) for i in rng.integers(0, len(o), 6))}))
            for i in idx:
                spots.append((o, i, f"{path}[{i}]"))
                walk(o[i], f"{path}[{i}]", depth + 1)

    walk(obj, "$", 0)
    if not spots or rng.random() < 0.05:
        v = JSON_VALUES[int(rng.integers(0, len(JSON_VALUES)))]
        return v, f"document -> {json.dumps(v)[:40]}"
    parent, key, path = spots[int(rng.integers(0, len(spots)))]
    r = rng.random()
    if r < 0.15:
        del parent[key]
        return obj, f"{path} removed"
    if r < 0.25 and isinstance(parent[key], list) and parent[key]:
        parent[key] = parent[key] + parent[key][: int(rng.integers(1, len(parent[key]) + 1))]
        return obj, f"{path} list lengthened"
    if r < 0.32 and isinstance(parent[key], list):
        parent[key] = parent[key][: int(rng.integers(0, len(parent[key]) + 1))]
        return obj, f"{path} list shortened"
    v = JSON_VALUES[int(rng.integers(0, len(JSON_VALUES)))]
    parent[key] = v
    return obj, f"{path} -> {json.dumps(v)[:40]}"


def _json_text_mutate(rng: np.random.Generator, text: str) -> tuple[str, str]:
    try:
        obj = json.loads(text)
    except ValueError:
        return text[: len(text) // 2], "truncated JSON"
    if rng.random() < 0.1:
        return text[: int(rng.integers(0, len(text) + 1))], "JSON text cut"
    obj, desc = _json_mutate(rng, obj)
    return json.dumps(obj), desc


def _array_edit(rng: np.random.Generator, a: np.ndarray) -> tuple[np.ndarray | None, str]:
    """A hostile version of one array (None: drop it)."""
    ops = ["drop", "nan", "huge", "negative", "empty", "reshape", "dtype", "scalar", "longer", "shorter", "string",
           "object"]
    op = ops[int(rng.integers(0, len(ops)))]
    if op == "drop":
        return None, "dropped"
    if op in ("nan", "huge", "negative") and a.size and a.dtype.kind in "biufc":
        out = a.astype(np.float64) if (op == "nan" and a.dtype.kind != "f") else a.copy()
        flat = out.reshape(-1)
        at = rng.integers(0, flat.size, int(rng.integers(1, 4)))
        if op == "nan":
            flat[at] = [np.nan, np.inf, -np.inf][int(rng.integers(0, 3))]
        elif op == "huge":
            flat[at] = np.finfo(out.dtype).max if out.dtype.kind == "f" else (
                np.iinfo(out.dtype).max if out.dtype.kind in "iu" else 1)
        else:
            flat[at] = -1 if out.dtype.kind in "if" else (np.iinfo(out.dtype).max if out.dtype.kind == "u" else 0)
        return out, f"{op} at {at.tolist()}"
    if op == "empty":
        return np.zeros((0, *a.shape[1:]), a.dtype), "empty"
    if op == "reshape":
        shapes = [(-1,), (1, -1), (*a.shape, 1)] if a.size else [(0, 0)]
        if a.ndim == 2 and a.shape[1] > 1:
            return a[:, :-1], f"last column dropped {a.shape}"
        s = shapes[int(rng.integers(0, len(shapes)))]
        return a.reshape(s), f"reshaped {a.shape} -> {s}"
    if op == "dtype":
        dt = [np.float16, np.float64, np.int8, np.uint8, np.int64, np.bool_, np.complex64, "U3", "S2"][
            int(rng.integers(0, 9))]
        try:
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return a.astype(dt), f"{a.dtype} -> {np.dtype(dt)}"
        except (ValueError, TypeError):
            return np.zeros(a.shape, dt), f"zeros as {np.dtype(dt)}"
    if op == "scalar":
        v = [0, -1, 2**40, np.nan, 1e30][int(rng.integers(0, 5))]
        return np.array(v), f"scalar {v}"
    if op == "longer" and a.ndim:
        k = int(rng.integers(1, 4))
        return np.concatenate([a, a[:k]] if len(a) else [a]), f"{k} rows more"
    if op == "shorter" and a.ndim and len(a):
        k = int(rng.integers(1, len(a) + 1))
        return a[:-k], f"{k} rows fewer"
    if op == "string":
        return np.array(["x", "not json {"][int(rng.integers(0, 2))]), "string"
    if op == "object":
        return np.array([1, "a", None], dtype=object), "object array (pickled)"
    return a.copy(), "unchanged"


def _npz_edit(rng: np.random.Generator, b: bytes, *, json_only: bool = False) -> tuple[bytes, str]:
    with np.load(io.BytesIO(b), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    keys = sorted(arrays)
    if json_only:
        text_keys = [k for k in keys if arrays[k].dtype.kind == "U" and arrays[k].size == 1
                     and str(arrays[k]).lstrip()[:1] in "{["]
        if not text_keys:
            return _npz_edit(rng, b)
        key = text_keys[int(rng.integers(0, len(text_keys)))]
        text, desc = _json_text_mutate(rng, str(arrays[key]))
        arrays[key] = np.array(text)
        desc = f"{key}: {desc}"
    elif rng.random() < 0.05:
        arrays[f"extra_{int(rng.integers(0, 99))}"] = np.arange(3)
        desc = "unknown array added"
    else:
        key = keys[int(rng.integers(0, len(keys)))]
        new, d = _array_edit(rng, arrays[key])
        if new is None:
            del arrays[key]
        else:
            arrays[key] = new
        desc = f"{key}: {d}"
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # allow_pickle is on for save: an object array lands pickled in the file
    return buf.getvalue(), desc


def _glb_parts(b: bytes) -> tuple[dict[str, Any], bytes]:
    import struct

    jlen, = struct.unpack_from("<I", b, 12)
    doc = json.loads(b[20 : 20 + jlen])
    rest = b[20 + jlen :]
    blen, = struct.unpack_from("<I", rest, 0)
    return doc, rest[8 : 8 + blen]


def _glb_pack(doc: dict[str, Any], binary: bytes) -> bytes:
    import struct

    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<I4s", len(j), b"JSON") + j + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _glb_edit(rng: np.random.Generator, b: bytes, *, part: str) -> tuple[bytes, str]:
    doc, binary = _glb_parts(b)
    if part == "json":
        doc, desc = _json_mutate(rng, doc)
        return _glb_pack(doc, binary), f"JSON {desc}"
    new, desc = _byte_mutation(rng, binary)
    return _glb_pack(doc, new), f"BIN {desc}"


def _ckpt_edit(rng: np.random.Generator, ckpt: dict[str, Any]) -> tuple[bytes, str]:
    """A hostile version of one entry of a prior checkpoint (config value, tensor, name, metadata), re-saved."""
    import torch

    out = dict(ckpt)
    r = rng.random()
    if r < 0.35:
        cfg = dict(out["config"])
        key = sorted(cfg)[int(rng.integers(0, len(cfg)))]
        choices: list[Any] = [None, -1, 0, 10**9, 2**63, float("nan"), float("inf"), "x", [], [0], [10**6],
                              [-1, 2], {"a": 1}, True]
        v = choices[int(rng.integers(0, len(choices)))]
        if rng.random() < 0.1:
            del cfg[key]
            desc = f"config.{key} removed"
        else:
            cfg[key] = v
            desc = f"config.{key} -> {v!r}"
        out["config"] = cfg
    elif r < 0.75:
        sd = dict(out["state_dict"])
        key = sorted(sd)[int(rng.integers(0, len(sd)))]
        a = sd[key].numpy()
        new, d = _array_edit(rng, a)
        if new is None:
            del sd[key]
        elif new.dtype.kind in "biufc" and new.dtype != np.float16:
            sd[key] = torch.from_numpy(np.ascontiguousarray(new))
        else:
            sd[key] = [1, "x"] if new.dtype.kind == "O" else str(new)
        desc = f"state_dict[{key}]: {d}"
        out["state_dict"] = sd
    elif r < 0.85:
        key = ["format", "name", "metadata", "config", "state_dict"][int(rng.integers(0, 5))]
        v = [None, 7, "x", [], {}, torch.zeros(2)][int(rng.integers(0, 6))]
        out[key] = v
        desc = f"{key} -> {type(v).__name__}"
    elif r < 0.92:
        key = ["config", "state_dict"][int(rng.integers(0, 2))]
        del out[key]
        desc = f"{key} removed"
    else:
        v = [[1, 2], torch.zeros(3), "prior", 42][int(rng.integers(0, 4))]
        buf = io.BytesIO()
        torch.save(v, buf)
        return buf.getvalue(), f"checkpoint is a {type(v).__name__}"
    buf = io.BytesIO()
    torch.save(out, buf)
    return buf.getvalue(), desc


@dataclass
class _Case:
    kind: str
    detail: str
    files: dict[str, bytes]
    target: str
    special: str | None = None
    """"directory", "missing" or "fifo": the target is not a regular file."""


FIXED_KINDS = ("valid", "empty", "directory", "missing", "fifo")


def _make_case(loader: _Loader, i: int, rng: np.random.Generator, ckpt: dict[str, Any] | None) -> _Case:
    """The i-th input of a loader: first every seed unchanged and the special paths, then the mutations in turn."""
    n_seeds = len(loader.seeds)
    if i < n_seeds:
        s = loader.seeds[i]
        return _Case("valid", f"seed {i}", dict(s.files), s.target)
    j = i - n_seeds
    s = loader.seeds[int(rng.integers(0, n_seeds))]
    files = dict(s.files)
    if j < len(FIXED_KINDS) - 1:
        kind = FIXED_KINDS[1 + j]
        if kind == "empty":
            files[s.target] = b""
            return _Case(kind, "0 bytes", files, s.target)
        del files[s.target]
        return _Case(kind, kind, files, s.target, special=kind)
    kind = loader.kinds[(j - len(FIXED_KINDS) + 1) % len(loader.kinds)]
    name = s.target
    if loader.mutable and kind not in ("junk",):
        name = loader.mutable[int(rng.integers(0, len(loader.mutable)))]
    b = files[name]
    if kind == "byte-flip":
        new, d = _flip(rng, b)
    elif kind == "truncate":
        new, d = _truncate(rng, b)
    elif kind == "zero-region":
        new, d = _zero(rng, b)
    elif kind == "junk":
        new, d = _junk(rng, loader.magic)
    elif kind == "header-number":
        new, d = _number_edit(rng, b, s.header_end)
    elif kind in ("line-dup", "line-drop"):
        new, d = _lines(rng, b, dup=kind == "line-dup")
    elif kind == "member-bytes":
        new, d = _member_bytes(rng, b)
    elif kind == "member-array":
        new, d = _npz_edit(rng, b)
    elif kind == "json-value":
        if name.endswith(".json"):
            text, d = _json_text_mutate(rng, b.decode())
            new = text.encode()
        else:
            new, d = _npz_edit(rng, b, json_only=True)
    elif kind == "glb-json":
        new, d = _glb_edit(rng, b, part="json")
    elif kind == "glb-bin":
        new, d = _glb_edit(rng, b, part="bin")
    elif kind == "checkpoint-value":
        assert ckpt is not None
        new, d = _ckpt_edit(rng, ckpt)
    elif kind == "codebook-array":
        name = next(k for k in files if k.endswith("_codebook.npz"))
        new, d = _npz_edit(rng, files[name])
    else:  # pragma: no cover - a kind without a mutation is a bug of this file
        raise AssertionError(kind)
    files[name] = new
    return _Case(kind, f"{name}: {d}" if name != s.target else d, files, s.target)


# ---------------------------------------------------------------------------------------------- one bounded call
def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    out: dict[str, tuple[int, int]] = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for n in dirnames + filenames:
            q = Path(dirpath) / n
            st = q.lstat()
            out[str(q.relative_to(folder))] = (st.st_size, st.st_mtime_ns)
    return out


def _proc_status_kb(key: str) -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _child(call: Callable[[Path], Any], check: Callable[[Any], None], path: Path, folder: Path, w: int) -> None:
    """Runs in the forked child: load, check, report one JSON line on the pipe. Never returns."""
    import tracemalloc

    out: dict[str, Any] = {}
    try:
        os.chdir(folder)  # a loader that writes to a relative path writes where we look
        logging.disable(logging.CRITICAL)
        warnings.simplefilter("ignore")
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        size_kb = _proc_status_kb("VmSize")
        if size_kb and sys.platform.startswith("linux"):
            lim = (size_kb << 10) + (ADDRESS_SPACE_HEADROOM_MB << 20)
            resource.setrlimit(resource.RLIMIT_AS, (lim, resource.getrlimit(resource.RLIMIT_AS)[1]))
        try:  # reset the peak-RSS mark (Linux >= 4.0), so VmHWM - VmRSS is this call's growth
            Path("/proc/self/clear_refs").write_text("5")
            rss0 = _proc_status_kb("VmRSS")
        except OSError:
            rss0 = -1
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            obj = call(path)
            out["seconds"] = time.perf_counter() - t0
            try:
                check(obj)
                out["outcome"] = "ok"
            except Exception as exc:  # noqa: BLE001 - the object failed its check
                out["outcome"] = "invalid"
                out["message"] = f"{type(exc).__name__}: {exc}"[:300]
        except BaseException as exc:  # noqa: BLE001 - classified by the parent
            out["seconds"] = time.perf_counter() - t0
            out["outcome"] = "raised"
            out["type"] = f"{type(exc).__module__}.{type(exc).__qualname__}"
            out["value_error"] = isinstance(exc, ValueError)
            out["os_error"] = isinstance(exc, OSError)
            out["memory_error"] = isinstance(exc, MemoryError)
            try:
                out["message"] = str(exc)
            except Exception:  # noqa: BLE001
                out["message"] = "<str() failed>"
            tb = traceback.extract_tb(exc.__traceback__)
            if tb:
                f = tb[-1]
                out["where"] = f"{Path(f.filename).name}:{f.lineno} {f.name}"
        out["traced_peak_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        out["rss_growth_mb"] = max(0, _proc_status_kb("VmHWM") - rss0) / 1024 if rss0 >= 0 else 0.0
        data = json.dumps(out, default=str).encode()
    except BaseException as exc:  # noqa: BLE001
        data = json.dumps({"outcome": "harness", "message": repr(exc)[:300]}).encode()
    try:
        while data:
            data = data[os.write(w, data):]
    finally:
        os._exit(0)


def _run_bounded(call: Callable[[Path], Any], check: Callable[[Any], None], path: Path, folder: Path,
                 *, time_limit_s: float) -> dict[str, Any]:
    r, w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    t0 = time.monotonic()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child's coverage is not collected
        os.close(r)
        _child(call, check, path, folder, w)
    os.close(w)
    chunks: list[bytes] = []
    timed_out = False
    try:
        while True:
            left = time_limit_s - (time.monotonic() - t0)
            if left <= 0:
                timed_out = True
                break
            ready, _, _ = select.select([r], [], [], left)
            if not ready:
                continue
            chunk = os.read(r, 1 << 16)
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(r)
        if timed_out:
            os.kill(pid, signal.SIGKILL)
        _, status = os.waitpid(pid, 0)
    wall = time.monotonic() - t0
    if timed_out:
        return {"outcome": "timeout", "seconds": wall}
    try:
        res = json.loads(b"".join(chunks))
    except ValueError:
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
        return {"outcome": "crash", "seconds": wall,
                "message": f"child died ({'signal ' + str(sig) if sig else 'exit ' + str(os.WEXITSTATUS(status))})"}
    res.setdefault("seconds", wall)
    return res


def _classify(res: dict[str, Any], names: list[str], changed: list[str], *, memory_limit_mb: float,
              time_limit_s: float) -> tuple[str, str]:
    """(outcome "ok" / "clean_error" / "bad", reason for a bad one)."""
    peak = max(float(res.get("traced_peak_mb", 0.0)), float(res.get("rss_growth_mb", 0.0)))
    if changed:
        return "bad", "wrote files in the input folder"
    o = res["outcome"]
    if o == "timeout":
        return "bad", f"over the time limit ({time_limit_s:g} s)"
    if o in ("crash", "harness"):
        return "bad", o
    if peak > memory_limit_mb:
        return "bad", f"over the memory limit ({memory_limit_mb:g} MB)"
    if float(res.get("seconds", 0.0)) > time_limit_s:
        return "bad", f"over the time limit ({time_limit_s:g} s)"
    if o == "ok":
        return "ok", ""
    if o == "invalid":
        return "bad", "returned an invalid object"
    if res.get("memory_error"):
        return "bad", "MemoryError"
    if not (res.get("value_error") or res.get("os_error")):
        return "bad", f"raised {res.get('type')}"
    msg = str(res.get("message", ""))
    if "\n" in msg.strip() or "Traceback" in msg:
        return "bad", "multi-line message"
    if len(msg) > MAX_MESSAGE_CHARS:
        return "bad", f"message over {MAX_MESSAGE_CHARS} characters"
    if not any(n in msg for n in names):
        return "bad", "message does not name the file"
    return "clean_error", ""


# ---------------------------------------------------------------------------------------------- the fuzzer
def run_fuzz(*, budget_s: float, seed: int, per_loader: int | None = None,
             time_limit_s: float = TIME_LIMIT_S, memory_limit_mb: float = MEMORY_LIMIT_MB,
             keep_bad: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Fuzz every loader for about `budget_s` seconds (setup included; the last call may overrun it by at most
    `time_limit_s`).

    Loaders take turns, the one with the least time spent so far going next, so each gets about the same share
    of the budget. Input i of a loader depends only on (`seed`, the loader, i), so with `per_loader` set and a
    budget that is not exhausted the run is deterministic.

    Args:
        budget_s: wall-clock budget, seconds.
        seed: seed of the mutations.
        per_loader: stop each loader after this many inputs (None: until the budget is spent).
        time_limit_s: a call slower than this is bad (the child is killed at this time).
        memory_limit_mb: a call whose tracemalloc peak or resident-set growth exceeds this is bad.
        keep_bad: copy the folder of every bad input here (for a reproduction), or None.

    Returns:
        A JSON-serialisable dict: ``loaders`` (per loader: inputs, ok / clean_error / bad counts, counts per
        mutation kind, error types, up to 3 sample error messages, worst seconds and peak MB), ``totals``, ``worst_s``
        and ``worst_peak_mb``
        (with the loader and kind), ``bad`` (the count and up to 5 examples of each bad reason per loader),
        ``budget_exhausted``, ``elapsed_s`` and the limits used.
    """
    t_start = time.monotonic()
    if not hasattr(os, "fork"):
        return {"skipped": "os.fork is not available on this platform"}
    # every loader's modules are imported here, once, so that each forked child starts warm
    import open3d  # noqa: F401
    import plyfile  # noqa: F401
    import scipy.spatial  # noqa: F401
    import torch
    import trimesh  # noqa: F401

    import annotator.io  # noqa: F401
    import efem_viz.data.rgbd  # noqa: F401
    import efem_viz.geometry.normals  # noqa: F401
    import efem_viz.prior.codebook  # noqa: F401

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # no OpenMP pool in the parent: forked children would inherit a broken one
    tmp = Path(tempfile.mkdtemp(prefix="efem-fuzz-"))
    try:
        loaders = _make_loaders(tmp)
        ckpt = torch.load(PRIOR_WEIGHTS, map_location="cpu", weights_only=True)
        counts = {ld.name: 0 for ld in loaders}
        spent = {ld.name: 0.0 for ld in loaders}
        stats: dict[str, dict[str, Any]] = {
            ld.name: {"inputs": 0, "ok": 0, "clean_error": 0, "bad": 0, "by_kind": {}, "errors": {},
                      "sample_messages": [], "worst_s": 0.0, "worst_peak_mb": 0.0} for ld in loaders}
        worst_s = {"value": 0.0, "loader": None, "kind": None}
        worst_mb = {"value": 0.0, "loader": None, "kind": None}
        examples: dict[str, list[dict[str, Any]]] = {}
        n_bad = 0
        exhausted = False
        work = tmp / "inputs"
        work.mkdir()
        while True:
            if time.monotonic() - t_start >= budget_s:
                exhausted = True
                break
            todo = [ld for ld in loaders if per_loader is None or counts[ld.name] < per_loader]
            if not todo:
                break
            ld = min(todo, key=lambda x: spent[x.name])
            i = counts[ld.name]
            t_case = time.monotonic()
            rng = np.random.default_rng([seed, loaders.index(ld), i])
            case = _make_case(ld, i, rng, ckpt)
            folder = work / f"{ld.name}-{i}"
            folder.mkdir()
            for name, data in case.files.items():
                (folder / name).write_bytes(data)
            target = folder / case.target
            if case.special == "directory":
                target.mkdir()
            elif case.special == "fifo":
                os.mkfifo(target)
            before = _snapshot(folder)
            res = _run_bounded(ld.call, ld.check, target, folder, time_limit_s=time_limit_s)
            after = _snapshot(folder)
            changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
            names = [str(target), target.name, *case.files]
            outcome, reason = _classify(res, names, changed, memory_limit_mb=memory_limit_mb,
                                        time_limit_s=time_limit_s)
            st = stats[ld.name]
            st["inputs"] += 1
            st[outcome] += 1
            kind = st["by_kind"].setdefault(case.kind, {"ok": 0, "clean_error": 0, "bad": 0})
            kind[outcome] += 1
            if res.get("outcome") == "raised":
                t = str(res.get("type", "?")).rsplit(".", 1)[-1]
                st["errors"][t] = st["errors"].get(t, 0) + 1
                if outcome == "clean_error" and case.kind not in FIXED_KINDS and len(st["sample_messages"]) < 3:
                    msg = str(res.get("message", "")).replace(str(folder), "<dir>")
                    if msg not in st["sample_messages"]:
                        st["sample_messages"].append(msg[:300])
            secs = float(res.get("seconds", 0.0))
            peak = max(float(res.get("traced_peak_mb", 0.0)), float(res.get("rss_growth_mb", 0.0)))
            st["worst_s"] = round(max(st["worst_s"], secs), 4)
            st["worst_peak_mb"] = round(max(st["worst_peak_mb"], peak), 2)
            if secs > worst_s["value"]:
                worst_s.update(value=round(secs, 4), loader=ld.name, kind=case.kind)
            if peak > worst_mb["value"]:
                worst_mb.update(value=round(peak, 2), loader=ld.name, kind=case.kind)
            if outcome == "bad":
                n_bad += 1
                key = f"{ld.name}: {reason}"
                ex = examples.setdefault(key, [])
                if len(ex) < 5:
                    ex.append({"input": i, "kind": case.kind, "detail": case.detail,
                               "error": res.get("type"), "where": res.get("where"),
                               "message": str(res.get("message", ""))[:400], "changed": changed[:5],
                               "seconds": round(secs, 3), "peak_mb": round(peak, 1)})
                if keep_bad is not None:
                    dest = Path(keep_bad) / folder.name
                    if case.special == "fifo":
                        target.unlink()
                    shutil.copytree(folder, dest, dirs_exist_ok=True)
            shutil.rmtree(folder, ignore_errors=True)
            counts[ld.name] += 1
            spent[ld.name] += time.monotonic() - t_case
    finally:
        torch.set_num_threads(threads)
        shutil.rmtree(tmp, ignore_errors=True)
    totals = {k: sum(s[k] for s in stats.values()) for k in ("inputs", "ok", "clean_error", "bad")}
    return {
        "seed": seed,
        "budget_s": budget_s,
        "elapsed_s": round(time.monotonic() - t_start, 2),
        "budget_exhausted": exhausted,
        "limits": {"time_s": time_limit_s, "memory_mb": memory_limit_mb, "message_chars": MAX_MESSAGE_CHARS},
        "totals": totals,
        "loaders": stats,
        "worst_s": worst_s,
        "worst_peak_mb": worst_mb,
        "bad": {"count": n_bad, "examples": examples},
    }


def format_bad(res: dict[str, Any]) -> str:
    """The bad outcomes of a `run_fuzz` result, one block per reason, for a failure message."""
    lines = [f"{res['bad']['count']} bad outcome(s) of {res['totals']['inputs']} inputs:"]
    for key, exs in res["bad"]["examples"].items():
        lines.append(f"* {key}")
        for e in exs:
            lines.append(f"    input {e['input']} [{e['kind']}] {e['detail']}")
            if e.get("error") or e.get("message"):
                lines.append(f"      {e.get('error')} at {e.get('where')}: {e['message'][:240]!r}")
            if e.get("changed"):
                lines.append(f"      changed: {e['changed']}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- tests
@pytest.mark.slow  # 28 inputs per loader, each in a forked child: about a minute on two cores
@pytest.mark.skipif(not hasattr(os, "fork"), reason="the fuzzer forks one child per input")
def test_every_loader_gives_a_valid_object_or_one_clear_error() -> None:
    # The work is counted: 28 inputs per loader (about 30 s on a quiet core). The wall-clock budget is only a hang
    # guard (20× that), so a loaded machine runs the same inputs, slower.
    res = run_fuzz(budget_s=600.0, seed=0, per_loader=28)
    json.dumps(res)  # bench/reliability.py writes it as JSON
    assert res["bad"]["count"] == 0, format_bad(res)
    for name, st in res["loaders"].items():
        valid = st["by_kind"]["valid"]
        assert valid["ok"] > 0 and valid["clean_error"] == valid["bad"] == 0, (name, "a seed file does not load")
        assert st["inputs"] == 28, (name, st["inputs"], "the hang guard stopped the fuzzer")
    assert res["worst_peak_mb"]["value"] < MEMORY_LIMIT_MB


def _found_cases(tmp: Path) -> dict[str, tuple[Callable[[Path], Any], Path, Callable[[Any], None] | None]]:
    """The inputs the fuzzer found bad (before their fixes), rebuilt deterministically.

    Returns:
        name -> (loader, input, None for "one clear error expected" or the check of the object it must return).
    """
    import struct

    import torch

    from annotator.io import InstanceInfo, load_labels, save_labels_ply
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.data.rgbd import import_rgbd_file
    from efem_viz.em.results import EMResult
    from efem_viz.prior.model import load_prior

    mesh = _tiny_mesh_scene(0)
    n = mesh.num_points
    cases: dict[str, tuple[Callable[[Path], Any], Path, Callable[[Any], None] | None]] = {}

    def put(name: str, data: bytes, call: Callable[[Path], Any], fname: str,
            check: Callable[[Any], None] | None = None) -> None:
        d = tmp / name
        d.mkdir()
        (d / fname).write_bytes(data)
        cases[name] = (call, d / fname, check)

    def labels(p: Path) -> Any:
        return load_labels(p, n)

    # PLY labels whose header claims 2^31 - 1 faces: plyfile allocated 16 GiB before reading
    table = {1: InstanceInfo(1, "a"), 2: InstanceInfo(2, "b")}
    ply = save_labels_ply(mesh, np.asarray(mesh.instance), table, tmp / "l.labels.ply").read_bytes()
    put("ply-labels-face-count", ply.replace(b"element face 80", b"element face 2147483647"), labels, "s.labels.ply")
    # PLY labels whose instance table holds a colour of 1e999 (int(inf): OverflowError); the comment is ignored
    prov = json.dumps({"annotator_instances": {"1": {"id": 1, "name": "a", "color": [1e999, 0, 0]}}})
    put("ply-labels-inf-colour", re.sub(rb"comment efem_provenance [^\n]*", b"comment efem_provenance " +
                                        prov.encode().replace(b"Infinity", b"1e999"), ply), labels, "s.labels.ply",
        _check_labels(n))
    # NPZ labels: a zip central directory entry needing "zip file version 11.4" (NotImplementedError)
    buf = io.BytesIO()
    np.savez(buf, instance=np.asarray(mesh.instance, np.int32))
    npz = bytearray(buf.getvalue())
    cd = npz.find(b"PK\x01\x02")
    npz[cd + 6 : cd + 8] = struct.pack("<H", 114)
    put("npz-labels-zip-version", bytes(npz), labels, "s.labels.npz")
    # NPZ labels: a .npy header with a zeroed middle (numpy's header parser raised tokenize.TokenError)
    member = io.BytesIO()
    np.save(member, np.asarray(mesh.instance, np.int32))
    head = bytearray(member.getvalue())
    head[20:60] = bytes(40)
    put("npz-labels-zeroed-header", _zip_write([("instance.npy", bytes(head))]), labels, "s.labels.npz")
    # ScanNet aggregation whose segGroups holds `true` (AttributeError)
    d = tmp / "scannet"
    d.mkdir()
    (d / "s.segs.json").write_text(json.dumps({"segIndices": [0] * n}))
    (d / "s.aggregation.json").write_text(json.dumps({"segGroups": [True]}))
    cases["scannet-group-not-object"] = (labels, d / "s.aggregation.json", None)
    # EFEM result: a zeroed stretch of compressed data (zlib.error); a result on another point count as labels
    res = RESULT_SAMPLE.read_bytes()
    put("result-zlib", res[:167438] + bytes(32469) + res[199907:], lambda p: EMResult.load(p), "s.efem.npz")
    with np.load(RESULT_SAMPLE, allow_pickle=False) as z:
        n_result = int(z["num_points"])
    put("efem-labels-other-scan", res, lambda p: load_labels(p, n_result + 5), "s.efem.npz")  # was imported
    # RGB-D frame without valid depth: the import's error named the scene, not the file
    frame = _frame_arrays(0)
    frame["depth_mm"] = np.zeros_like(frame["depth_mm"])
    buf = io.BytesIO()
    np.savez(buf, **frame)
    put("rgbd-no-depth", buf.getvalue(), lambda p: import_rgbd_file(p), "f.npz")
    # RGB-D frame whose principal point is 1e300 px off: Open3D's voxel grid raised a multi-line RuntimeError
    frame = _frame_arrays(0)
    frame["K"][0, 2] = 1e300
    buf = io.BytesIO()
    np.savez(buf, **frame)
    put("rgbd-absurd-intrinsics", buf.getvalue(), lambda p: import_rgbd_file(p), "f.npz")
    # OBJ with a face index of 10^12: trimesh allocated 7 TiB for it
    obj = tmp / "mesh.obj"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.disable(logging.WARNING)
        try:
            save_scene(mesh, obj)
        finally:
            logging.disable(logging.NOTSET)
    text = obj.read_bytes()
    at = text.index(b"\nf ") + 3
    put("obj-face-index", text[:at] + b"1000000000000" + text[text.index(b"/", at):], lambda p: load_scene(p),
        "s.obj")
    # scene NPZ whose provenance_json holds a number (TypeError in Scene.create), or a label of 2^40 (wrapped)
    scene_npz = io.BytesIO()
    np.savez(scene_npz, **{k: v for k, v in mesh.to_npz_dict().items()} | {"provenance_json": np.array("Infinity")})
    put("scene-provenance-number", scene_npz.getvalue(), lambda p: load_scene(p), "s.npz")
    scene_npz = io.BytesIO()
    np.savez(scene_npz, **mesh.to_npz_dict() | {"instance": np.full(n, 2**40, np.int64)})
    put("scene-label-over-int32", scene_npz.getvalue(), lambda p: load_scene(p), "s.npz")
    # priors: junk the weights-only unpickler pops from an empty stack on (IndexError); NaN weights; a config
    # with a million channels per block (built before any check); a codebook with two rows too many
    put("prior-pickle-pop", b"s.", lambda p: load_prior(p), "p.pt")  # SETITEM on an empty stack
    ckpt = torch.load(PRIOR_WEIGHTS, map_location="cpu", weights_only=True)
    for name, edit in {"prior-nan-weights": lambda c: c["state_dict"][sorted(c["state_dict"])[0]].fill_(np.nan),
                       "prior-huge-config": lambda c: c["config"].__setitem__("widths", [10**6] * 7)}.items():
        c = {**ckpt, "config": dict(ckpt["config"]),
             "state_dict": {k: v.clone() for k, v in ckpt["state_dict"].items()}}
        edit(c)
        buf = io.BytesIO()
        torch.save(c, buf)
        put(name, buf.getvalue(), lambda p: load_prior(p), "p.pt")
    with np.load(PRIOR_CODEBOOK, allow_pickle=False) as z:
        cb = {k: z[k] for k in z.files}
    cb["eigvals"] = np.concatenate([cb["eigvals"], cb["eigvals"][:2]])
    buf = io.BytesIO()
    np.savez(buf, **cb)
    put("prior-codebook-rows", PRIOR_WEIGHTS.read_bytes(), lambda p: load_prior(p), "p.pt")
    (tmp / "prior-codebook-rows" / "p_codebook.npz").write_bytes(buf.getvalue())
    return cases


@pytest.mark.skipif(not hasattr(os, "fork"), reason="loads run in a forked child")
def test_the_inputs_the_fuzzer_found_give_one_clear_error(tmp_path: Path) -> None:
    def no_check(obj: Any) -> None:
        raise AssertionError(f"loaded {type(obj).__name__}; an error was expected")

    for name, (call, path, check) in _found_cases(tmp_path).items():
        before = _snapshot(path.parent)
        res = _run_bounded(call, check or no_check, path, path.parent, time_limit_s=TIME_LIMIT_S)
        changed = sorted(set(_snapshot(path.parent).items()) ^ set(before.items()))
        outcome = _classify(res, [str(path), path.name, *os.listdir(path.parent)], [str(c) for c in changed],
                            memory_limit_mb=256, time_limit_s=TIME_LIMIT_S)
        assert outcome == ("clean_error" if check is None else "ok", ""), (name, outcome, res)


def test_the_classifier_flags_what_is_not_a_clean_error() -> None:
    names = ["/x/a.ply", "a.ply"]
    ok = {"outcome": "raised", "value_error": True, "message": "/x/a.ply: truncated", "seconds": 0.1}
    assert _classify(ok, names, [], memory_limit_mb=1024, time_limit_s=10)[0] == "clean_error"
    cases = [
        ({**ok, "value_error": False, "type": "builtins.KeyError"}, [], "raised builtins.KeyError"),
        ({**ok, "message": "truncated"}, [], "message does not name the file"),
        ({**ok, "message": "/x/a.ply: bad\n  File \"x.py\""}, [], "multi-line message"),
        ({**ok, "traced_peak_mb": 2048.0}, [], "over the memory limit (1024 MB)"),
        ({"outcome": "timeout", "seconds": 10.0}, [], "over the time limit (10 s)"),
        ({"outcome": "ok", "seconds": 0.1}, ["a.ply.tmp"], "wrote files in the input folder"),
        ({"outcome": "invalid", "message": "AssertionError: nan"}, [], "returned an invalid object"),
    ]
    for res, changed, reason in cases:
        assert _classify(res, names, changed, memory_limit_mb=1024, time_limit_s=10) == ("bad", reason)


def test_the_bounded_call_kills_a_hang_and_catches_a_write(tmp_path: Path) -> None:
    res = _run_bounded(lambda p: time.sleep(30), lambda o: None, tmp_path / "x", tmp_path, time_limit_s=0.5)
    assert res["outcome"] == "timeout" and res["seconds"] < 5
    before = _snapshot(tmp_path)
    res = _run_bounded(lambda p: Path("junk.tmp").write_text("x"), lambda o: None, tmp_path / "x", tmp_path,
                       time_limit_s=5)
    assert res["outcome"] == "ok" and set(_snapshot(tmp_path)) - set(before) == {"junk.tmp"}
    res = _run_bounded(lambda p: np.empty(2**28), lambda o: None, tmp_path / "x", tmp_path, time_limit_s=5)
    assert res["traced_peak_mb"] >= 2000
