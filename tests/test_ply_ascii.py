"""ASCII PLY: the numpy reader (`_read_ply_ascii`) against plyfile's row-by-row reader and the binary path.

The oracle for every file here is the reader that existed before: `load_scene` with the numpy reader switched
off (plyfile parses the body). Both must give the same Scene, bit for bit, or both must raise `SceneError`.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator
from unittest import mock

import numpy as np
import pytest
import trimesh

import efem_viz.data.formats.ply as ply_format
from efem_viz.data.formats.common import triangulate, triangulate_flat
from efem_viz.data.io import load_scene, save_scene
from efem_viz.data.scene import Scene, SceneError
from helpers import mesh_scene

HEAD_XYZ = "property float x\nproperty float y\nproperty float z\n"
QUAD = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"


# ---------------------------------------------------------------------------------------------- helpers
def cloud_scene(seed: int = 1, n: int = 500) -> Scene:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    return Scene.create(
        "cloud",
        pts * 0.1,
        normals=pts / np.linalg.norm(pts, axis=1, keepdims=True),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        instance=rng.integers(0, 3, n),
        categories={1: "mug"},
        provenance={"licence": "CC0"},
    )


@contextmanager
def plyfile_only() -> Iterator[None]:
    """The reader as it was: plyfile parses every ASCII body."""
    with mock.patch.object(ply_format, "_read_ply_ascii", return_value=(None, None)):
        yield


def load_plyfile(path: Path, **kw) -> Scene:
    with plyfile_only():
        return load_scene(path, **kw)


def uses_numpy_reader(path: Path) -> bool:
    return ply_format._read_ply_ascii(path)[0] is not None


def assert_same_scene(a: Scene, b: Scene, *, atol: float = 0.0) -> None:
    def same(x, y):
        if atol:
            np.testing.assert_allclose(x, y, rtol=0, atol=atol)
        else:
            np.testing.assert_array_equal(x, y)
            assert np.asarray(x).dtype == np.asarray(y).dtype

    same(a.points, b.points)
    same(a.normals, b.normals)
    np.testing.assert_array_equal(a.colors, b.colors)
    assert (a.faces is None) == (b.faces is None)
    if a.faces is not None:
        np.testing.assert_array_equal(a.faces, b.faces)
        assert a.faces.dtype == b.faces.dtype
    assert (a.instance is None) == (b.instance is None)
    if a.instance is not None:
        np.testing.assert_array_equal(a.instance, b.instance)
        assert a.instance.dtype == b.instance.dtype
    assert a.categories == b.categories
    assert a.provenance == b.provenance


def assert_same_tables(path: Path) -> None:
    """The numpy reader's element arrays equal plyfile's, field by field and dtype by dtype."""
    import plyfile

    ply, polys = ply_format._read_ply_ascii(path)
    assert ply is not None, f"{path.name} fell back to plyfile"
    ref = plyfile.PlyData.read(str(path))
    assert [e.name for e in ply.elements] == [e.name for e in ref.elements]
    assert ply.comments == ref.comments and ply.obj_info == ref.obj_info
    for elt, ref_elt in zip(ply.elements, ref.elements):
        assert elt.data.dtype == ref_elt.data.dtype and len(elt.data) == len(ref_elt.data)
        for q in elt.properties:
            if not isinstance(q, plyfile.PlyListProperty):
                np.testing.assert_array_equal(elt.data[q.name], ref_elt.data[q.name])
    if polys is not None:
        key = next(k for k in ("vertex_indices", "vertex_index") if k in ref["face"].data.dtype.names)
        ref_lists = ref["face"].data[key]
        np.testing.assert_array_equal(polys[0], [len(f) for f in ref_lists])
        flat = np.concatenate(list(ref_lists)) if len(ref_lists) else np.zeros(0, polys[1].dtype)
        np.testing.assert_array_equal(polys[1], flat)
        assert polys[1].dtype == flat.dtype


def assert_matches_plyfile(path: Path, *, fast: bool = True) -> Scene:
    """Load `path` both ways; same Scene, and (when `fast`) the numpy reader really read it, to the same arrays."""
    if fast:
        assert_same_tables(path)
    s = load_scene(path)
    assert_same_scene(s, load_plyfile(path))
    return s


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    p = tmp_path / name
    if isinstance(text, str):
        p.write_text(text, newline="")
    else:
        p.write_bytes(text)
    return p


def ply(
    vertex_rows: str,
    *,
    n: int | None = None,
    props: str = HEAD_XYZ,
    faces: str = "",
    n_faces: int | None = None,
    face_props: str = "property list uchar int vertex_indices\n",
    extra_head: str = "",
) -> str:
    n = vertex_rows.count("\n") if n is None else n
    head = f"ply\nformat ascii 1.0\ncomment hand-written\nelement vertex {n}\n{props}"
    if faces or n_faces is not None:
        nf = faces.count("\n") if n_faces is None else n_faces
        head += f"element face {nf}\n{face_props}"
    return head + extra_head + "end_header\n" + vertex_rows + faces


# ---------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("make", [mesh_scene, cloud_scene], ids=["mesh", "cloud"])
def test_ascii_round_trip_matches_binary_and_plyfile(tmp_path: Path, make) -> None:
    scene = make()
    a = save_scene(scene, tmp_path / "a.ply", ascii=True)
    b = save_scene(scene, tmp_path / "b.ply")
    s_ascii = assert_matches_plyfile(a)
    s_bin = load_scene(b)
    # points are written with 9 significant digits (exact for float32); normals with 7
    np.testing.assert_array_equal(s_ascii.points, s_bin.points)
    assert_same_scene(s_ascii, s_bin, atol=1e-6)
    np.testing.assert_array_equal(s_ascii.instance, scene.instance)
    assert s_ascii.categories == scene.categories and s_ascii.provenance == scene.provenance


def test_open3d_ascii_files_load_like_binary(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(3)
    pc = o3d.geometry.PointCloud()
    pts = rng.normal(size=(300, 3))
    pc.points = o3d.utility.Vector3dVector(pts)
    pc.normals = o3d.utility.Vector3dVector(pts / np.linalg.norm(pts, axis=1, keepdims=True))
    pc.colors = o3d.utility.Vector3dVector(rng.random((300, 3)))
    mesh = o3d.geometry.TriangleMesh.create_sphere(0.2, resolution=8)
    mesh.compute_vertex_normals()
    mesh.vertex_colors = o3d.utility.Vector3dVector(rng.random((len(mesh.vertices), 3)))
    for name, write_fn, geom in [
        ("pc", o3d.io.write_point_cloud, pc),
        ("mesh", o3d.io.write_triangle_mesh, mesh),
    ]:
        a, b = tmp_path / f"{name}_a.ply", tmp_path / f"{name}_b.ply"
        assert write_fn(str(a), geom, write_ascii=True) and write_fn(str(b), geom, write_ascii=False)
        assert b"format ascii" in a.read_bytes()[:200] and b"property double x" in a.read_bytes()[:400]
        s_ascii = assert_matches_plyfile(a)
        s_bin = load_scene(b)
        # open3d writes ASCII values with 6 significant digits; the binary file holds the exact doubles
        assert_same_scene(s_ascii, s_bin, atol=1e-5)
        assert (s_ascii.faces is not None) == (name == "mesh")


def test_trimesh_ascii_files_load_like_binary(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    mesh.visual.vertex_colors = rng.integers(0, 256, (len(mesh.vertices), 4)).astype(np.uint8)
    cloud = trimesh.PointCloud(
        rng.normal(size=(200, 3)), colors=rng.integers(0, 256, (200, 4)).astype(np.uint8)
    )
    for name, geom in [("mesh", mesh), ("cloud", cloud)]:
        a = write(tmp_path, f"{name}_a.ply", geom.export(file_type="ply", encoding="ascii"))
        b = write(tmp_path, f"{name}_b.ply", geom.export(file_type="ply", encoding="binary"))
        s_ascii = assert_matches_plyfile(a)
        s_bin = load_scene(b)
        assert_same_scene(s_ascii, s_bin, atol=1e-7)  # trimesh writes ASCII floats with 8 decimals


def test_meshlab_style_file_with_face_colours_alpha_and_quality(tmp_path: Path) -> None:
    props = (
        HEAD_XYZ + "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "property float quality\n"
    )
    rows = "0 0 0 255 0 0 255 0.5\n1 0 0 0 255 0 255 1.5\n1 1 0 0 0 255 255 2\n0 1 0 9 9 9 255 -1e-3\n"
    faces = "3 0 1 2 10 20 30\n3 0 2 3 40 50 60\n"
    face_props = "property list uchar int vertex_indices\n" + "".join(
        f"property uchar {c}\n" for c in ("red", "green", "blue")
    )
    s = assert_matches_plyfile(
        write(tmp_path, "ml.ply", ply(rows, props=props, faces=faces, face_props=face_props))
    )
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(s.colors[:3], [[255, 0, 0], [0, 255, 0], [0, 0, 255]])


def test_header_comments_carry_categories_and_provenance(tmp_path: Path) -> None:
    text = ply("0 0 0 1\n1 0 0 2\n0 1 0 0\n", props=HEAD_XYZ + "property int instance\n").replace(
        "comment hand-written\n",
        'comment efem_categories {"1": "mug", "2": "bowl"}\nobj_info scanner X\n'
        'comment efem_provenance {"source": "hand", "n": 3}\n',
    )
    s = assert_matches_plyfile(write(tmp_path, "c.ply", text))
    assert s.categories == {1: "mug", 2: "bowl"}
    assert s.provenance == {"source": "hand", "n": 3}
    np.testing.assert_array_equal(s.instance, [1, 2, 0])


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r"], ids=["lf", "crlf", "cr"])
def test_line_endings_tabs_and_spacing(tmp_path: Path, newline: str) -> None:
    rows = "  0\t0 0 7\n1  0 0\t1 \n0 1 0 0\n1 1 1 2"  # no newline after the last row
    text = ply(rows + "\n", props=HEAD_XYZ + "property int instance\n")[:-1].replace("\n", newline)
    s = assert_matches_plyfile(write(tmp_path, "nl.ply", text))
    np.testing.assert_array_equal(s.instance, [7, 1, 0, 2])


def test_property_types_and_16_bit_colour(tmp_path: Path) -> None:
    props = (
        "property double x\nproperty double y\nproperty double z\n"
        "property ushort red\nproperty ushort green\n"
        "property ushort blue\nproperty float instance\nproperty char c\nproperty uint u\nproperty short h\n"
    )
    rows = (
        "0.1 0.2 0.30000000000000004 65535 0 257 1.0 -128 4294967295 -32768\n"
        "1e-3 -2.5E+1 +3 1000 2000 3000 2 127 0 32767\n"
        "1 1 1 0 0 0 0 0 1 0\n"
    )
    s = assert_matches_plyfile(write(tmp_path, "types.ply", ply(rows, props=props)))
    v = ply_format._read_ply_ascii(tmp_path / "types.ply")[0]["vertex"].data  # doubles stay doubles until Scene
    assert v["z"][0] == 0.30000000000000004 and v.dtype["u"] == np.uint32 and v["u"][0] == 4294967295
    np.testing.assert_array_equal(s.instance, [1, 2, 0])
    np.testing.assert_array_equal(s.colors[0], [255, 0, 1])


# ---------------------------------------------------------------------------------------------- polygons
def test_quads_and_mixed_polygons_are_fan_triangulated(tmp_path: Path) -> None:
    s = assert_matches_plyfile(write(tmp_path, "q.ply", ply(QUAD, faces="4 0 1 2 3\n")))
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3]])
    # all quads
    rows = "".join(f"{x} {y} 0\n" for y in range(3) for x in range(3))
    quads = "4 0 1 4 3\n4 1 2 5 4\n4 3 4 7 6\n4 4 5 8 7\n"
    s = assert_matches_plyfile(write(tmp_path, "qq.ply", ply(rows, faces=quads)))
    assert s.faces.shape == (8, 3)
    # triangles, a quad, a pentagon and a hexagon, in that order; `vertex_index` and an `int` length type
    rows = "".join(f"{np.cos(a):.6f} {np.sin(a):.6f} 0\n" for a in np.linspace(0, 6, 8))
    mixed = "3 0 1 2\n4 0 2 3 4\n5 0 1 2 3 4\n3 5 6 7\n6 0 1 2 3 4 5\n"
    text = ply(rows, faces=mixed, face_props="property list int uint vertex_index\n")
    s = assert_matches_plyfile(write(tmp_path, "mixed.ply", text))
    np.testing.assert_array_equal(
        s.faces,
        [
            [0, 1, 2],
            [0, 2, 3],
            [0, 3, 4],
            [0, 1, 2],
            [0, 2, 3],
            [0, 3, 4],
            [5, 6, 7],
            [0, 1, 2],
            [0, 2, 3],
            [0, 3, 4],
            [0, 4, 5],
        ],
    )
    # mixed polygons with a per-face scalar after the list
    text = ply(
        rows,
        faces="3 0 1 2 9\n4 0 2 3 4 8\n",
        face_props="property list uchar int vertex_indices\nproperty int flags\n",
    )
    s = assert_matches_plyfile(write(tmp_path, "mixed_flags.ply", text))
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3], [0, 3, 4]])


def test_triangulate_flat_matches_per_polygon_loop() -> None:
    rng = np.random.default_rng(0)
    lens = rng.integers(3, 9, 200)
    flat = rng.integers(0, 1000, int(lens.sum()))
    polys = np.split(flat, np.cumsum(lens)[:-1])
    naive = [(f[0], f[k], f[k + 1]) for f in polys for k in range(1, len(f) - 1)]
    np.testing.assert_array_equal(triangulate_flat(lens, flat, Path("x")), naive)
    np.testing.assert_array_equal(triangulate(polys, Path("x")), naive)


def test_empty_face_element_and_faces_before_vertices(tmp_path: Path) -> None:
    s = assert_matches_plyfile(write(tmp_path, "nf.ply", ply(QUAD + "", props=HEAD_XYZ, n_faces=0)))
    assert s.faces is None
    text = (
        "ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int vertex_indices\nelement vertex 4\n"
        + HEAD_XYZ
        + "end_header\n3 0 1 2\n3 0 2 3\n"
        + QUAD
    )
    s = assert_matches_plyfile(write(tmp_path, "fv.ply", text))
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3]])


def test_extra_elements_are_read_past(tmp_path: Path) -> None:
    text = (
        "ply\nformat ascii 1.0\nelement material 2\nproperty uchar ambient_red\nproperty float shininess\n"
        "element vertex 4\n" + HEAD_XYZ + "property int instance\n"
        "element edge 3\nproperty int vertex1\nproperty int vertex2\nproperty uchar red\n"
        "element range_grid 3\nproperty list uchar int vertex_indices\n"
        "element face 2\nproperty list uchar int vertex_indices\n"
        "element camera 1\nproperty float view_px\nproperty list uchar float k\nproperty list uchar float d\n"
        "end_header\n"
        "10 0.5\n20 0.25\n"
        "0 0 0 1\n1 0 0 1\n1 1 0 2\n0 1 0 2\n"
        "0 1 255\n1 2 0\n2 3 7\n"
        "1 0\n0\n2 2 3\n"
        "3 0 1 2\n3 0 2 3\n"
        "1.5 2 0.1 0.2 3 1 2 3\n"
    )
    s = assert_matches_plyfile(write(tmp_path, "extra.ply", text))
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(s.instance, [1, 1, 2, 2])
    # a malformed row in an element we do not use still makes the file invalid, as with plyfile
    bad = text.replace("1 2 0\n", "1 two 0\n")
    with pytest.raises(SceneError, match=r"element 'edge', row 2 of 3.*'two'.*'vertex2'.*not an int"):
        load_scene(write(tmp_path, "bad_edge.ply", bad))


def test_trailing_blank_lines_are_fine_but_extra_rows_are_refused(tmp_path: Path) -> None:
    """rows beyond the header's counts used to load silently (the header lied about them)."""
    s = assert_matches_plyfile(write(tmp_path, "blank.ply", ply(QUAD, faces="3 0 1 2\n") + "\n \t\n\r\n"))
    assert s.faces.shape == (1, 3)
    cases = {
        "garbage": (ply(QUAD, faces="3 0 1 2\n") + "\n\ngarbage here\n", r"line 18 .*'garbage here'"),
        "extra face": (ply(QUAD, faces="3 0 1 2\n") + "3 0 2 3\n", r"\(vertex 4, face 1\).*line 16 .*'3 0 2 3'"),
        "extra vertex, no faces": (ply(QUAD, n=3), r"\(vertex 3\).*line 12 .*'0 1 0'"),
        "CR line ends": (ply(QUAD, faces="3 0 1 2\n").replace("\n", "\r") + "3 0 2 3", r"line 16 .*'3 0 2 3'"),
    }
    for case, (text, pattern) in cases.items():
        p = write(tmp_path, "extra.ply", text)
        for loader in (load_scene, load_plyfile):  # both body readers
            with pytest.raises(SceneError, match="more rows than its header declares.*" + pattern) as info:
                loader(p)
            assert str(p) in str(info.value), case


# ---------------------------------------------------------------------------------------------- fallbacks
@pytest.mark.parametrize(
    "rows",
    [
        "0 0 0 1_0\n1 0 0 1\n0 1 0 0\n",  # Python-style digit grouping: plyfile takes it, numpy does not
        "0 0 0 1\n1 0 0 1\n0 1 0 0\x0b\n",  # other whitespace
        "0 0 0 1\n1 0 0 1\n0 1 0 0 \xc2\xa0\n",  # non-ASCII
    ],
    ids=["underscore", "vtab", "non-ascii"],
)
def test_what_numpy_does_not_settle_falls_back_to_plyfile(tmp_path: Path, rows: str) -> None:
    body = rows.encode("latin-1")
    p = write(tmp_path, "fb.ply", ply("", n=3, props=HEAD_XYZ + "property int instance\n").encode() + body)
    assert not uses_numpy_reader(p)
    try:
        expected = load_plyfile(p)
    except SceneError:
        with pytest.raises(SceneError):
            load_scene(p)
    else:
        assert_same_scene(load_scene(p), expected)


def test_binary_files_are_not_touched(tmp_path: Path) -> None:
    save_scene(cloud_scene(), tmp_path / "b.ply")
    assert ply_format._read_ply_ascii(tmp_path / "b.ply") == (None, None)


# ---------------------------------------------------------------------------------------------- errors
INST = HEAD_XYZ + "property int instance\n"
ERRORS = {
    "truncated rows": (
        ply("0 0 0 1\n1 0 0 1\n", n=5, props=INST),
        r"truncated.*'vertex' has 5 rows.*after 2",
    ),
    "truncated mid-row": (ply("0 0 0 1\n1 0", n=2, props=INST), r"row 2 of 2.*only 2 values.*'z' is missing"),
    "truncated faces": (ply(QUAD, faces="3 0 1 2\n", n_faces=3), r"truncated.*'face' has 3 rows.*after 1"),
    "too few values": (
        ply("0 0 0 1\n1 0 0\n0 1 0 0\n", props=INST),
        r"row 2 of 3.*line 11.*'instance' is missing",
    ),
    "too many values": (ply("0 0 0 1\n1 0 0 1 5\n0 1 0 0\n", props=INST), r"row 2 of 3.*5 values, 1 more"),
    "blank row": (ply("0 0 0 1\n\n0 1 0 0\n", props=INST), r"row 2 of 3.*empty row"),
    "non-numeric": (ply("0 0 0 1\n1 x 0 1\n0 1 0 0\n", props=INST), r"'x' for property 'y' is not a float"),
    "float label in int": (
        ply("0 0 0 1.5\n1 0 0 1\n0 1 0 0\n", props=INST),
        r"'1.5' for property 'instance'",
    ),
    "comma decimal": (ply("0 0 0 1\n1,5 0 0 1\n0 1 0 0\n", props=INST), r"'1,5' for property 'x'"),
    "colour out of range": (
        ply("0 0 0 300\n1 0 0 1\n0 1 0 0\n", props=HEAD_XYZ + "property uchar red\n"),
        r"'300' for property 'red' is not a uchar \(an integer 0..255\)",
    ),
    "NaN": (ply("0 0 0 1\nnan 0 0 1\n0 1 0 0\n", props=INST), r"1 of 3 points contain NaN or Inf"),
    "Inf": (ply("0 0 0 1\n1 0 0 1\n0 -inf 0 0\n", props=INST), r"NaN or Inf"),
    "float32 overflow": (ply("0 0 0 1\n1e39 0 0 1\n0 1 0 0\n", props=INST), r"NaN or Inf"),
    "empty": (ply("", props=INST), r"empty \(0 points\)"),
    "face too short": (ply(QUAD, faces="3 0 1 2\n3 0 2\n"), r"row 2 of 2.*length 3 but the row has only 2"),
    "face too long": (
        ply(QUAD, faces="3 0 1 2\n3 0 2 3 1\n"),
        r"row 2 of 2.*1 more than the properties take",
    ),
    "face bad index": (
        ply(QUAD, faces="3 0 1 2\n3 0 2 3.5\n"),
        r"'3.5' in list 'vertex_indices' is not an int \(an integer",
    ),
    "face bad length": (ply(QUAD, faces="3 0 1 2\nthree 0 2 3\n"), r"list length 'three'.*not a uchar"),
    "face index out of range": (ply(QUAD, faces="3 0 1 2\n3 0 2 9\n"), r"face indices must lie in \[0, 4\)"),
    "degenerate face": (ply(QUAD, faces="3 0 1 2\n2 0 2\n"), r"1 faces have fewer than 3 vertices"),
    "wrong length": (
        ply("0 0 0 1\n1 0 0 1\n0 1 0 0\n", props=HEAD_XYZ + "property list uchar int instance\n"),
        r"row 1 of 3.*'instance' has length 1 but the row has only 0 values",
    ),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_errors_are_clear_scene_errors(tmp_path: Path, case: str) -> None:
    text, pattern = ERRORS[case]
    p = write(tmp_path, "bad.ply", text)
    with pytest.raises(SceneError, match=pattern) as info:
        load_scene(p)
    assert str(p) in str(info.value)
    with pytest.raises(SceneError):  # the old reader rejected the file too
        load_plyfile(p)


def test_max_points_is_checked_from_the_header_before_the_body(tmp_path: Path) -> None:
    p = write(tmp_path, "huge.ply", ply("0 0 0\n", n=10**9))
    with mock.patch.object(ply_format, "_read_ply_ascii", side_effect=AssertionError("body read")):
        with pytest.raises(SceneError, match="limit"):
            load_scene(p)
    save_scene(cloud_scene(), tmp_path / "c.ply", ascii=True)
    with pytest.raises(SceneError, match="limit"):
        load_scene(tmp_path / "c.ply", max_points=100)
    assert load_scene(tmp_path / "c.ply", max_points=500).num_points == 500


def test_random_corruptions_give_scene_errors_or_the_same_scene(tmp_path: Path) -> None:
    """Seeded truncations and corruptions of a small labelled mesh with quads: never anything but SceneError,
    and always what plyfile's reader decides (same Scene, or SceneError from both)."""
    rng = np.random.default_rng(2024)
    base = mesh_scene(subdivisions=0)
    save_scene(base, tmp_path / "base.ply", ascii=True)
    text = (tmp_path / "base.ply").read_bytes()
    text = text.replace(b"\n3 0 11 5\n", b"\n4 0 11 5 1\n", 1)  # one quad among the triangles
    body_at = text.index(b"end_header\n") + len(b"end_header\n")
    inserts = [
        b"0",
        b"7",
        b"-",
        b".",
        b"e",
        b" ",
        b"\n",
        b"\t",
        b"\r",
        b"nan",
        b"inf",
        b"x",
        b"#",
        b",",
        b"1_0",
        b"\x00",
        b"\x0b",
        b"\xc3\xa9",
        b"300",
        b"-1",
        b"3 0 1",
        b"\n\n",
    ]
    outcomes = {"loaded": 0, "SceneError": 0}
    for trial in range(300):
        data = bytearray(text)
        kind = trial % 6
        at = int(rng.integers(body_at - 40 if trial % 25 == 0 else body_at, len(data)))
        if kind == 0:  # truncate
            data = data[:at]
        elif kind == 1:  # delete a few bytes
            del data[at : at + int(rng.integers(1, 4))]
        elif kind == 2:  # insert
            data[at:at] = inserts[int(rng.integers(len(inserts)))]
        elif kind == 3:  # overwrite a byte
            data[at] = int(rng.integers(0, 256))
        elif kind == 4:  # drop or duplicate a whole line
            lines = bytes(data).split(b"\n")
            i = int(rng.integers(lines.index(b"end_header") + 1, len(lines)))
            lines[i : i + 1] = [] if rng.random() < 0.5 else [lines[i], lines[i]]
            data = bytearray(b"\n".join(lines))
        else:  # replace one value by another token
            lines = bytes(data).split(b"\n")
            i = int(rng.integers(lines.index(b"end_header") + 1, len(lines) - 1))
            toks = lines[i].split(b" ")
            toks[int(rng.integers(len(toks)))] = inserts[int(rng.integers(len(inserts)))]
            lines[i] = b" ".join(toks)
            data = bytearray(b"\n".join(lines))
        p = tmp_path / f"fuzz_{trial:03d}.ply"
        p.write_bytes(bytes(data))
        fast: Scene | SceneError
        try:
            fast = load_scene(p)
        except SceneError as exc:
            fast = exc
        try:
            old: Scene | SceneError = load_plyfile(p)
        except SceneError as exc:
            old = exc
        assert isinstance(fast, SceneError) == isinstance(old, SceneError), (trial, fast, old)
        if isinstance(fast, SceneError):
            assert str(p) in str(fast)
            outcomes["SceneError"] += 1
        else:
            assert isinstance(old, Scene)
            assert_same_scene(fast, old)
            outcomes["loaded"] += 1
        p.unlink()
    assert outcomes["loaded"] > 20 and outcomes["SceneError"] > 100, outcomes
