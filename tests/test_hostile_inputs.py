"""Hostile and corrupt scene files: one clear `SceneError`, in bounded time and memory.

Files whose header claims huge counts are loaded in a child process under an address-space limit
(`load_bounded`), so that a regression fails fast with MemoryError instead of eating the machine's memory
(a 227-byte PLY claiming 10^9 faces once took 78 s and 7.7 GB before failing).
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import pickle
import struct
import subprocess
import sys
import textwrap
import zipfile
import zlib
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest

import efem_viz.geometry.normals as normals_mod
from efem_viz.data.io import load_scene, save_scene
from efem_viz.data.scene import Scene, SceneError
from efem_viz.geometry.normals import estimate_normals

ROOT = Path(__file__).resolve().parent.parent
XYZ = "property float x\nproperty float y\nproperty float z\n"
TRI = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)


# ---------------------------------------------------------------------------------------------- helpers
def load_bounded(path: Path, *, max_points: int | None = None, mem_mb: int = 1536, timeout_s: float = 60.0
                 ) -> dict[str, Any]:
    """`load_scene(path)` in a fresh interpreter limited to `mem_mb` of address space.

    Returns:
        {"error": exception type name or None, "message": str, "seconds": load time, "rss_mb": peak RSS}.
    """
    kw = "" if max_points is None else f", max_points={max_points}"
    code = textwrap.dedent(f"""
        import json, resource, sys, time
        sys.path.insert(0, {str(ROOT)!r})
        if sys.platform.startswith("linux"):
            lim = {mem_mb} << 20
            resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
        import numpy, plyfile, trimesh
        from efem_viz.data.io import load_scene
        t = time.perf_counter()
        out = {{"error": None, "message": ""}}
        try:
            load_scene({str(path)!r}{kw})
        except BaseException as exc:
            out = {{"error": type(exc).__name__, "message": str(exc)}}
        out["seconds"] = time.perf_counter() - t
        out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(json.dumps(out))
    """)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_clear_error(path: Path, pattern: str, **kw: Any) -> None:
    res = load_bounded(path, **kw)
    assert res["error"] == "SceneError", res
    assert str(path) in res["message"], res
    import re

    assert re.search(pattern, res["message"]), res
    assert "\n" not in res["message"], res
    assert res["seconds"] < 10.0, res


def ply_head(fmt: str, elements: str) -> bytes:
    return f"ply\nformat {fmt} 1.0\n{elements}end_header\n".encode()


# ---------------------------------------------------------------------------------------------- item 9
BILLION_FACES = ply_head(
    "binary_little_endian",
    "element vertex 3\n" + XYZ + "element face 1000000000\nproperty list uchar int vertex_indices\n",
) + TRI + struct.pack("<B3i", 3, 0, 1, 2)


def test_the_227_byte_billion_face_ply_fails_at_once(tmp_path: Path) -> None:
    p = tmp_path / "billion.ply"
    p.write_bytes(BILLION_FACES)
    assert p.stat().st_size == 227  # the file from the issue
    assert_clear_error(p, r"1,000,000,000 faces, more than the limit")
    # with the face limit out of the way, the size check names the element and the numbers
    assert_clear_error(p, r"binary PLY .*element 'face' has 1,000,000,000 rows.*13 bytes each.*holds 49 bytes",
                       max_points=10**9)


@pytest.mark.parametrize(
    "case",
    ["ascii faces", "ascii faces, plyfile body", "binary other element", "ascii other element",
     "binary big-endian vertices", "negative count"],
)
def test_every_ply_element_count_is_checked_against_the_file(tmp_path: Path, case: str) -> None:
    rows = "0 0 0\n1 0 0\n0 1 0\n"
    face = "element face 1000000000\nproperty list uchar int vertex_indices\n"
    if case == "ascii faces":
        data = ply_head("ascii", "element vertex 3\n" + XYZ + face) + (rows + "3 0 1 2\n").encode()
        pattern = r"truncated: element 'face' has 1,000,000,000 rows.*after 1 of them"
    elif case == "ascii faces, plyfile body":  # a non-ASCII byte sends the body to plyfile's own reader
        data = ply_head("ascii", "element vertex 3\n" + XYZ + face) + (rows + "3 0 1 2 \xe9\n").encode("latin-1")
        pattern = r"truncated: element 'face' has 1,000,000,000 rows"
    elif case == "binary other element":
        data = ply_head("binary_little_endian", "element vertex 3\n" + XYZ + "element material 2000000000\n"
                        "property uchar red\nproperty list uchar float k\n") + TRI + b"\x05\x00"
        pattern = r"element 'material' has 2,000,000,000 rows in the header \(2 bytes each"
    elif case == "ascii other element":
        data = ply_head("ascii", "element vertex 3\n" + XYZ + "element edge 3000000000\nproperty int vertex1\n"
                        ) + (rows + "0\n").encode()
        pattern = r"element 'edge' has 3,000,000,000 rows"
    elif case == "binary big-endian vertices":
        data = ply_head("binary_big_endian", "element vertex 4000000\n" + XYZ) + TRI
        pattern = r"element 'vertex' has 4,000,000 rows in the header \(12 bytes each.*36 bytes after the header"
    else:
        data = ply_head("ascii", "element vertex 3\n" + XYZ + "element face -5\n"
                        "property list uchar int vertex_indices\n") + rows.encode()
        pattern = r"element 'face' a negative count"
    p = tmp_path / "hostile.ply"
    p.write_bytes(data)
    assert_clear_error(p, pattern, max_points=10**10)


def test_a_header_without_end_is_refused_after_a_bounded_read(tmp_path: Path) -> None:
    p = tmp_path / "endless.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\n" + b"comment " + b"x" * (5 << 20) + b"\n")
    with pytest.raises(SceneError, match=r"no 'end_header' line in its first 4 MiB"):
        load_scene(p)


def npz_bytes(arrays: dict[str, np.ndarray], *, fake_shapes: dict[str, tuple[int, ...]] | None = None) -> bytes:
    """An .npz (stored, uncompressed); `fake_shapes` gives an array's .npy header another shape than its data."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key, arr in arrays.items():
            member = io.BytesIO()
            header = np.lib.format.header_data_from_array_1_0(arr)
            if fake_shapes and key in fake_shapes:
                header["shape"] = fake_shapes[key]
            np.lib.format.write_array_header_1_0(member, header)
            member.write(np.ascontiguousarray(arr).tobytes())
            zf.writestr(f"{key}.npy", member.getvalue())
    return buf.getvalue()


def test_npz_headers_are_checked_before_numpy_allocates(tmp_path: Path) -> None:
    base = {"schema_version": np.array(1, np.int32), "points": np.zeros((4, 3), np.float32)}
    p = tmp_path / "lying.npz"
    p.write_bytes(npz_bytes(base, fake_shapes={"points": (10**11, 3)}))
    assert_clear_error(p, r"array 'points' claims shape \(100000000000, 3\).*archive holds 48 bytes",
                       max_points=10**12)
    big = {"schema_version": np.array(1, np.int32), "points": np.zeros((300, 3), np.float32)}
    p2 = tmp_path / "big.npz"
    p2.write_bytes(npz_bytes(big))
    with pytest.raises(SceneError, match=r"array 'points' has shape \(300, 3\).*limit of 100"):
        load_scene(p2, max_points=100)
    p3 = tmp_path / "faces.npz"
    p3.write_bytes(npz_bytes({**base, "faces": np.zeros((500, 3), np.int32)}))
    with pytest.raises(SceneError, match=r"array 'faces'.*more faces than the limit of 400"):
        load_scene(p3, max_points=100)


def glb_bytes(gltf: dict[str, Any], binary: bytes) -> bytes:
    js = json.dumps(gltf).encode()
    js += b" " * ((-len(js)) % 4)
    binary += b"\0" * ((-len(binary)) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _triangle_gltf(position_accessor: dict[str, Any]) -> dict[str, Any]:
    return {
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]}],
        "buffers": [{"byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}],
        "accessors": [position_accessor],
    }


@pytest.mark.parametrize("case", ["bufferless accessor", "accessor past its view", "too many positions"])
def test_glb_accessor_counts_are_checked(tmp_path: Path, case: str) -> None:
    if case == "bufferless accessor":  # trimesh would allocate np.zeros(count * 3)
        acc = {"componentType": 5126, "type": "VEC3", "count": 10**10}
        pattern, max_points = r"accessor 0 has no data but claims 10,000,000,000 items", 10**6
    elif case == "accessor past its view":
        acc = {"bufferView": 0, "componentType": 5126, "type": "VEC3", "count": 10**9}
        pattern, max_points = r"accessor 0 claims 1,000,000,000 items.*bufferView holds \(36 bytes\)", 10**10
    else:
        acc = {"bufferView": 0, "componentType": 5126, "type": "VEC3", "count": 3}
        pattern, max_points = r"3 vertex positions, more than the limit of 2", 2
    p = tmp_path / "hostile.glb"
    p.write_bytes(glb_bytes(_triangle_gltf(acc), TRI))
    assert_clear_error(p, pattern, max_points=max_points)


def test_glb_packed_extras_cannot_inflate_past_the_point_limit(tmp_path: Path) -> None:
    import trimesh

    rng = np.random.default_rng(0)
    pc = trimesh.PointCloud(rng.normal(size=(10, 3)))
    ts = trimesh.Scene(pc)
    bomb = base64.b64encode(zlib.compress(b"\0" * (64 << 20), 9)).decode()  # 64 MiB of zeros in ~65 KB
    ts.metadata["efem"] = {"schema_version": 1, "normals_zb64": bomb}
    p = tmp_path / "bomb.glb"
    p.write_bytes(ts.export(file_type="glb"))
    with pytest.raises(SceneError, match=r"inflates to more than 30 items"):
        load_scene(p)


def test_off_and_obj_counts(tmp_path: Path) -> None:
    off = tmp_path / "neg.off"
    off.write_text("OFF\n-3 0 0\n0 0 0\n")
    with pytest.raises(SceneError, match="negative counts"):
        load_scene(off)
    off.write_text("OFF\n3 900 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(SceneError, match=r"declares 900 faces, more than the limit of 400"):
        load_scene(off, max_points=100)
    off.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 2 1\n")  # for OFF too
    with pytest.raises(SceneError, match=r"more rows than its header declares \(3 vertices, 1 faces\).*'3 0 2 1'"):
        load_scene(off)
    off.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n\n# a comment\n  \n")
    assert load_scene(off).faces.shape == (1, 3)
    obj = tmp_path / "many.obj"
    obj.write_text("".join(f"v {i} 0 0\n" for i in range(50)))
    with pytest.raises(SceneError, match=r"50 vertices \('v' lines\), more than the limit of 10"):
        load_scene(obj, max_points=10)


# ---------------------------------------------------------------------------------------------- item 10
def bare_cloud(n: int = 3000, seed: int = 0) -> np.ndarray:
    """Points on a unit sphere (float32)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def write_bare_ply(path: Path, pts: np.ndarray) -> Path:
    import plyfile

    v = np.empty(len(pts), [("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))
    return path


def test_info_never_estimates_normals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz.data.commands import InfoArgs

    p = write_bare_ply(tmp_path / "bare.ply", bare_cloud())
    with mock.patch.object(normals_mod, "estimate_normals", side_effect=AssertionError("normals estimated")):
        assert InfoArgs(scenes=[p], json=True).run() == 0
        assert InfoArgs(scenes=[p]).run() == 0
    out = capsys.readouterr().out
    assert json.loads(out.splitlines()[0])["normals"] == "estimated on use"
    assert "none (estimated on use)" in out


def test_missing_normals_are_estimated_once_on_first_use() -> None:
    pts = bare_cloud()
    calls = []
    real = normals_mod.estimate_normals

    def counting(*args: Any, **kw: Any) -> np.ndarray:
        calls.append(1)
        return real(*args, **kw)

    with mock.patch.object(normals_mod, "estimate_normals", side_effect=counting):
        s = Scene.create("s", pts)
        assert s.normals_pending and not calls
        relabelled = s.with_labels(np.ones(len(pts), np.int64))
        renamed = s.replace(name="t")
        copied = pickle.loads(pickle.dumps(s))
        assert relabelled.normals_pending and renamed.normals_pending and copied.normals_pending and not calls
        n = s.normals
        assert calls == [1] and not s.normals_pending and s.normals is n
        assert n.shape == (len(pts), 3) and n.dtype == np.float32
        assert (np.einsum("ij,ij->i", n, pts) > 0.9).mean() > 0.99  # outward, the orientation rule kept
        np.testing.assert_array_equal(copied.normals, n)
        assert calls == [1, 1]
    given = Scene.create("g", pts, normals=pts)
    assert not given.normals_pending
    np.testing.assert_allclose(given.normals, pts, atol=1e-6)
    with pytest.raises(Exception, match="cannot assign"):
        s.normals = n  # type: ignore[misc]  # still a frozen dataclass


def test_loaders_leave_normals_pending_unless_the_file_has_them(tmp_path: Path) -> None:
    pts = bare_cloud(500)
    bare = load_scene(write_bare_ply(tmp_path / "bare.ply", pts))
    assert bare.normals_pending
    full = Scene.create("f", pts, normals=pts)
    for suffix in (".ply", ".npz", ".glb", ".off", ".obj"):
        save_scene(full, tmp_path / f"f{suffix}")
        back = load_scene(tmp_path / f"f{suffix}")
        assert not back.normals_pending, suffix
        np.testing.assert_allclose(back.normals, full.normals, atol=1e-5)


def naive_pca_normals(pts: np.ndarray, k: int) -> np.ndarray:
    """One point at a time: the k nearest points by brute force, covariance, smallest eigenvector."""
    out = np.empty_like(pts)
    for i, q in enumerate(pts):
        nb = pts[np.argsort(np.linalg.norm(pts - q, axis=1), kind="stable")[:k]]
        c = np.cov(nb.T, bias=True)
        out[i] = np.linalg.eigh(c)[1][:, 0]
    return out


def test_chunked_pca_matches_a_naive_loop() -> None:
    from efem_viz.geometry.normals import pca_normals

    rng = np.random.default_rng(3)
    uv = rng.uniform(-1, 1, (400, 2))
    pts = np.c_[uv, 0.2 * np.sin(3 * uv[:, 0]) + 0.01 * rng.standard_normal(400)]
    fast, nbrs = pca_normals(pts, knn=12, chunk=37, keep_neighbours=5)  # chunks that do not divide N
    ref = naive_pca_normals(pts, 12)
    cos = np.abs(np.einsum("ij,ij->i", fast, ref))
    assert cos.min() > 1 - 1e-9
    assert nbrs is not None and nbrs.shape == (400, 5) and (nbrs[:, 0] == np.arange(400)).all()


def test_orientation_rule_per_piece_and_toward_a_sensor() -> None:
    d = bare_cloud(4000).astype(np.float64)
    two = np.concatenate([d, 0.3 * d + [5.0, 0, 0]])  # two separate spheres: each outward
    n = estimate_normals(two)
    assert (np.einsum("ij,ij->i", n[:4000], d) > 0.9).mean() > 0.99
    assert (np.einsum("ij,ij->i", n[4000:], d) > 0.9).mean() > 0.99
    rng = np.random.default_rng(1)
    table = np.c_[rng.uniform(-1, 1, (3000, 2)), 0.002 * rng.standard_normal(3000)]  # flat: +Z
    assert (estimate_normals(table)[:, 2] > 0.95).mean() > 0.99
    below = estimate_normals(table, toward=np.array([0.3, 0.0, -1.0]))
    assert (below[:, 2] < -0.95).mean() > 0.99
    # a flat scene with objects that do not touch the table: the table up, every object outward (the old
    # whole-cloud flip gave all pieces one sign chosen by the table, leaving closed objects inward at random)
    balls = [0.1 * d[i::4][:1000] + c for i, c in enumerate([[-0.5, 0, 0.2], [0.5, 0.3, 0.2], [0, -0.5, 0.25]])]
    scene = np.concatenate([table, *balls])
    n = estimate_normals(scene)
    assert (n[:3000, 2] > 0.95).mean() > 0.99
    for i, (ball, c) in enumerate(zip(balls, [[-0.5, 0, 0.2], [0.5, 0.3, 0.2], [0, -0.5, 0.25]])):
        nb = n[3000 + 1000 * i : 4000 + 1000 * i]
        assert (np.einsum("ij,ij->i", nb, ball - c) > 0).mean() > 0.99, i
    with pytest.raises(ValueError, match="NaN"):
        estimate_normals(np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0]]))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        estimate_normals(np.zeros((5, 2)))


def test_progress_is_reported_per_chunk(caplog: pytest.LogCaptureFixture) -> None:
    pts = bare_cloud(2500)
    seen: list[tuple[str, int, int]] = []
    estimate_normals(pts, chunk=1000, on_progress=lambda *a: seen.append(a))
    assert [a for a in seen if a[0] == "pca"] == [("pca", 1000, 2500), ("pca", 2000, 2500), ("pca", 2500, 2500)]
    assert [a for a in seen if a[0] == "orient"] == [("orient", 1, 3), ("orient", 2, 3), ("orient", 3, 3)]
    s = Scene.create("s", pts)
    seen.clear()
    with caplog.at_level(logging.DEBUG, logger="efem_viz.geometry.normals"):
        s.compute_normals(on_progress=lambda *a: seen.append(a))
    assert seen[-1] == ("orient", 3, 3) and not s.normals_pending
    assert any("normals: PCA" in r.getMessage() for r in caplog.records)
