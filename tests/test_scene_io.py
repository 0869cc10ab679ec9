"""Scene IO: round trips for every format, PLY details, validation errors, atomic writes, scene discovery."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest
import trimesh

from efem_viz.data.io import (
    ScenePathNotFoundError,
    atomic_write,
    atomic_write_bytes,
    atomic_write_text,
    find_scenes,
    load_scene,
    save_scene,
    scene_from_npz,
)
from efem_viz.data.scene import Scene, SceneError
from helpers import mesh_scene

from efem_viz.data.formats import FORMATS as FORMAT_TABLE

FORMATS = sorted(FORMAT_TABLE)
"""Every format of the table: a new format is round-tripped here without a line of test code."""
LABELS_KEPT = {s for s, f in FORMAT_TABLE.items() if f.keeps_labels}


def cloud_scene(seed: int = 1, n: int = 500) -> Scene:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    return Scene.create(
        "cloud",
        pts * 0.1,
        normals=nrm,
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        instance=rng.integers(0, 3, n),
        categories={1: "mug"},
        provenance={"licence": "CC0"},
    )


@pytest.mark.parametrize("suffix", FORMATS)
@pytest.mark.parametrize("make", [mesh_scene, cloud_scene], ids=["mesh", "cloud"])
def test_round_trip(tmp_path: Path, suffix: str, make) -> None:
    scene = make()
    path = save_scene(scene, tmp_path / f"s{suffix}")
    back = load_scene(path)
    assert back.name == "s"
    np.testing.assert_allclose(back.points, scene.points, atol=1e-6)
    np.testing.assert_allclose(back.normals, scene.normals, atol=1e-5)
    np.testing.assert_array_equal(back.colors, scene.colors)
    if scene.faces is None or not FORMAT_TABLE[suffix].keeps_faces:
        assert back.faces is None
    else:
        np.testing.assert_array_equal(back.faces, scene.faces)
    if suffix in LABELS_KEPT:
        np.testing.assert_array_equal(back.instance, scene.instance)
        assert back.categories == scene.categories
        assert back.provenance == scene.provenance
    else:
        assert back.instance is None  # OBJ/OFF cannot hold labels


def test_ply_ascii_and_binary_headers(tmp_path: Path) -> None:
    scene = mesh_scene()
    save_scene(scene, tmp_path / "a.ply", ascii=True)
    save_scene(scene, tmp_path / "b.ply")
    head_a = (tmp_path / "a.ply").read_bytes()[:600]
    head_b = (tmp_path / "b.ply").read_bytes()[:600]
    assert b"format ascii 1.0" in head_a and b"format binary_little_endian 1.0" in head_b
    for head in (head_a, head_b):
        assert b"property int instance" in head and b"property uchar red" in head
        assert b"comment efem_categories" in head
        assert b"property list uchar int vertex_indices" in head
    for p in ("a.ply", "b.ply"):
        back = load_scene(tmp_path / p)
        np.testing.assert_array_equal(back.instance, scene.instance)
        assert back.categories == {1: "mug", 2: "bowl", 3: "mug"}
    # other tools (trimesh here, MeshLab alike) read the same file
    tm = trimesh.load(tmp_path / "b.ply", process=False)
    np.testing.assert_allclose(tm.vertices, scene.points, atol=1e-6)


def test_glb_is_y_up_on_disk(tmp_path: Path) -> None:
    scene = mesh_scene()
    save_scene(scene, tmp_path / "m.glb")
    raw = trimesh.load(tmp_path / "m.glb", process=False)
    (geom,) = raw.geometry.values()
    # glTF +Y up: our (x, y, z) is stored as (x, z, -y)
    np.testing.assert_allclose(geom.vertices, scene.points[:, [0, 2, 1]] * [1, 1, -1], atol=1e-6)


def test_foreign_files_without_normals_colours_or_labels(tmp_path: Path) -> None:
    # a sphere mesh written by trimesh (no colours, no labels): face normals, grey colours
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    for suffix in (".ply", ".obj", ".off", ".glb"):
        p = tmp_path / f"sphere{suffix}"
        m.export(p)
        s = load_scene(p)
        assert s.is_mesh and s.instance is None
        if suffix == ".ply":
            assert (s.colors == 180).all()  # no colours in the file: grey
        outward = np.einsum("ij,ij->i", s.normals, s.points - s.points.mean(0))
        assert (outward > 0).mean() > 0.99, suffix
    # a bare point cloud PLY: normals estimated with open3d and oriented outward
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(800, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    trimesh.PointCloud(pts).export(tmp_path / "pc.ply")
    s = load_scene(tmp_path / "pc.ply")
    assert s.faces is None
    assert (np.einsum("ij,ij->i", s.normals, s.points) > 0).mean() > 0.95
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-5)


def test_quads_are_triangulated(tmp_path: Path) -> None:
    off = "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    (tmp_path / "q.off").write_text(off)
    s = load_scene(tmp_path / "q.off")
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [0, 2, 3]])
    ply = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    (tmp_path / "q.ply").write_text(ply)
    np.testing.assert_array_equal(load_scene(tmp_path / "q.ply").faces, [[0, 1, 2], [0, 2, 3]])


def _ascii_ply(tmp_path: Path, rows: list[str], *, inst_type: str = "int", n: int | None = None) -> Path:
    n = len(rows) if n is None else n
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        f"property {inst_type} instance\nend_header\n"
    )
    p = tmp_path / "t.ply"
    p.write_text(head + "".join(r + "\n" for r in rows))
    return p


def test_validation_errors(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="no such file"):
        load_scene(tmp_path / "missing.ply")
    with pytest.raises(SceneError, match="directory"):
        load_scene(tmp_path)
    (tmp_path / "x.xyz").write_text("0 0 0\n")
    with pytest.raises(SceneError, match="unknown scene format"):
        load_scene(tmp_path / "x.xyz")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(SceneError, match="empty"):
        load_scene(tmp_path / "empty.ply")
    (tmp_path / "garbage.ply").write_bytes(b"ply\nthis is not a header\n\x00\x01")
    with pytest.raises(SceneError, match="garbage.ply"):
        load_scene(tmp_path / "garbage.ply")
    (tmp_path / "r.efem.npz").write_bytes(b"x")
    with pytest.raises(SceneError, match="result"):
        load_scene(tmp_path / "r.efem.npz")
    # truncated binary PLY: cut the body in half
    save_scene(cloud_scene(), tmp_path / "full.ply")
    data = (tmp_path / "full.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneError, match="cut.ply"):
        load_scene(tmp_path / "cut.ply")
    # zero points
    with pytest.raises(SceneError, match="empty"):
        load_scene(_ascii_ply(tmp_path, []))
    # NaN coordinates
    with pytest.raises(SceneError, match="NaN"):
        load_scene(_ascii_ply(tmp_path, ["0 0 0 1", "nan 0 0 1", "1 1 1 0"]))
    # non-integer labels (a float property with fractional values)
    with pytest.raises(SceneError, match="integers"):
        load_scene(_ascii_ply(tmp_path, ["0 0 0 1.5", "1 0 0 1", "0 1 0 0"], inst_type="float"))
    # integral float labels are accepted
    s = load_scene(_ascii_ply(tmp_path, ["0 0 0 1.0", "1 0 0 2.0", "0 1 0 0.0"], inst_type="float"))
    np.testing.assert_array_equal(s.instance, [1, 2, 0])
    # more points than max_points (checked from the header, before reading)
    with pytest.raises(SceneError, match="limit"):
        load_scene(tmp_path / "full.ply", max_points=100)
    save_scene(cloud_scene(), tmp_path / "c.npz")
    with pytest.raises(SceneError, match="limit"):
        load_scene(tmp_path / "c.npz", max_points=100)
    # mismatched lengths in an npz
    d = dict(np.load(tmp_path / "c.npz"))
    d["normals"] = d["normals"][:-1]
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(SceneError, match="normals"):
        load_scene(tmp_path / "bad.npz")
    d = dict(np.load(tmp_path / "c.npz"))
    d["schema_version"] = np.array(99)
    np.savez(tmp_path / "v99.npz", **d)
    with pytest.raises(SceneError, match="schema_version 99"):
        load_scene(tmp_path / "v99.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(SceneError, match="schema_version"):
        load_scene(tmp_path / "other.npz")
    d = dict(np.load(tmp_path / "c.npz"))
    d["colors"] = d["colors"].astype(np.int64) * 10  # not 0..255: would wrap if cast
    np.savez(tmp_path / "col.npz", **d)
    with pytest.raises(SceneError, match="0..255"):
        load_scene(tmp_path / "col.npz")
    # truncated OFF
    (tmp_path / "t.off").write_text("OFF\n10 0 0\n0 0 0\n")
    with pytest.raises(SceneError, match="truncated"):
        load_scene(tmp_path / "t.off")
    # unknown suffix on save
    with pytest.raises(SceneError, match="unknown scene format"):
        save_scene(cloud_scene(), tmp_path / "x.stl")


def test_scene_from_npz_dict() -> None:
    scene = mesh_scene()
    back = scene_from_npz(scene.to_npz_dict())
    assert back.name == "ball"
    np.testing.assert_array_equal(back.faces, scene.faces)
    np.testing.assert_array_equal(back.instance, scene.instance)


def test_atomic_write(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "f.txt"
    atomic_write_text(target, "one")
    assert target.read_text() == "one"
    mode = stat.S_IMODE(target.stat().st_mode)
    assert mode & 0o044, f"new files must be readable by others like a normal file, got {oct(mode)}"

    def failing(tmp: Path) -> None:
        tmp.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, failing)
    assert target.read_text() == "one"  # untouched
    assert sorted(os.listdir(target.parent)) == ["f.txt"]  # no temporary left behind
    # np.savez keeps the name (no doubled .npz)
    atomic_write(tmp_path / "a.npz", lambda t: np.savez(t, x=np.arange(3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "sub"]
    # an existing file keeps its permissions; bytes payloads take the same path
    os.chmod(target, 0o640)
    assert atomic_write_bytes(target, b"two") == target
    assert target.read_bytes() == b"two" and stat.S_IMODE(target.stat().st_mode) == 0o640


def test_atomic_write_refuses_symlinks(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    link = tmp_path / "link.txt"
    os.symlink(victim, link)
    for write in (lambda: atomic_write_text(link, "x"), lambda: atomic_write_bytes(link, b"x"),
                  lambda: save_scene(cloud_scene(n=20), tmp_path / "link.ply")):
        if not (tmp_path / "link.ply").is_symlink():
            os.symlink(victim, tmp_path / "link.ply")
        with pytest.raises(ValueError, match="symbolic link"):
            write()
    assert victim.read_text() == "keep me" and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.ply", "link.txt", "victim.txt"]  # no temporaries


def test_find_scenes(tmp_path: Path) -> None:
    d = tmp_path / "scenes"
    d.mkdir()
    scene = cloud_scene(n=50)
    for name in ("b.ply", "a.npz", "c.glb"):
        save_scene(scene, d / name)
    (d / "a.efem.npz").write_bytes(b"result")
    (d / ".hidden.ply").write_bytes(b"x")
    (d / "notes.txt").write_text("x")
    (d / "nested").mkdir()
    save_scene(scene, d / "nested" / "z.ply")
    found = find_scenes(d)
    assert [p.name for p in found] == ["a.npz", "b.ply", "c.glb"]
    extra = tmp_path / "x.off"
    save_scene(scene, extra)
    assert [p.name for p in find_scenes([extra, d, d / "b.ply"])] == ["x.off", "a.npz", "b.ply", "c.glb"]
    with pytest.raises(SceneError, match="no such"):
        find_scenes([tmp_path / "nope"])
    with pytest.raises(FileNotFoundError, match="no such"):  # the same error, for the viewer's discover_scenes
        find_scenes([tmp_path / "nope"])
    assert issubclass(ScenePathNotFoundError, SceneError) and issubclass(ScenePathNotFoundError, FileNotFoundError)
    with pytest.raises(SceneError, match="result"):
        find_scenes([d / "a.efem.npz"])
    with pytest.raises(SceneError, match="unknown scene format"):
        find_scenes([d / "notes.txt"])
    # recursive walks sub-folders (sorted by path); a hidden file named explicitly is kept
    assert [p.relative_to(d).as_posix() for p in find_scenes(d, recursive=True)] == [
        "a.npz", "b.ply", "c.glb", "nested/z.ply"]
    assert find_scenes(d / ".hidden.ply") == [d / ".hidden.ply"]
    # a symlink to a file already listed is a duplicate
    os.symlink(d / "b.ply", d / "0link.ply")
    assert [p.name for p in find_scenes(d)] == ["0link.ply", "a.npz", "c.glb"]


def test_info_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from efem_viz.cli import main

    save_scene(mesh_scene(), tmp_path / "m.ply")
    save_scene(cloud_scene(), tmp_path / "c.npz")
    assert main(["info", str(tmp_path), "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [r["name"] for r in rows] == ["c", "m"]
    m = rows[1]
    assert m["kind"] == "mesh" and m["points"] == 162 and m["faces"] == 320
    assert m["categories"] == {"mug": 2, "bowl": 1}
    assert main(["info", str(tmp_path / "m.ply")]) == 0
    out = capsys.readouterr().out
    assert "162" in out and "mug" in out
    (tmp_path / "bad.ply").write_bytes(b"ply\ngarbage")
    assert main(["info", str(tmp_path / "bad.ply")]) == 1


@pytest.mark.parametrize("suffix", [".glb", ".obj"])
def test_mesh_with_face_colours_keeps_them(tmp_path: Path, suffix: str) -> None:
    import trimesh

    m = trimesh.creation.box()
    m.visual.face_colors = np.tile([200, 30, 40, 255], (len(m.faces), 1))
    p = tmp_path / f"box{suffix}"
    m.export(p)
    s = load_scene(p)
    assert s.faces is not None and len(s.faces) == 12
    assert np.array_equal(s.colors, np.tile([200, 30, 40], (s.num_points, 1)))  # not the default grey


def test_glb_mesh_keeps_its_stored_normals(tmp_path: Path) -> None:
    """The file's NORMAL attribute survives loading (trimesh's copy() used to drop it: face normals came back)."""
    m = mesh_scene(subdivisions=1)
    rng = np.random.default_rng(0)
    custom = m.replace(normals=m.normals + 0.5 * rng.normal(size=m.normals.shape))
    save_scene(custom, tmp_path / "n.glb")
    back = load_scene(tmp_path / "n.glb")
    assert not back.normals_pending
    np.testing.assert_allclose(back.normals, custom.normals, atol=1e-5)


def test_a_scannet_scene_folder_opens_with_its_instance_ground_truth(tmp_path: Path) -> None:
    """`scene0000_00_vh_clean_2.ply` beside its `.aggregation.json` and `_vh_clean_2.0.010000.segs.json` (ScanNet's
    layout, its `segmentsFile` prefixed "scannet."): the instances become the scene's ground truth, objectId + 1
    with the object's label as category; the annotator reads the same pair as labels."""
    import json

    from annotator.io import load_labels
    from efem_viz.data.io import load_scene, save_scene

    mesh = mesh_scene(0)
    n = mesh.num_points
    seg = np.arange(n) // 10  # segments of 10 vertices
    folder = tmp_path / "scene0007_00"
    folder.mkdir()
    save_scene(mesh.with_labels(None, {}), folder / "scene0007_00_vh_clean_2.ply")
    (folder / "scene0007_00_vh_clean_2.0.010000.segs.json").write_text(json.dumps({"segIndices": seg.tolist()}))
    groups = [{"objectId": 0, "label": "chair", "segments": [0, 1, 2]},
              {"objectId": 4, "label": "cup", "segments": [int(seg[-1])]}]
    (folder / "scene0007_00.aggregation.json").write_text(json.dumps(
        {"sceneId": "scannet.scene0007_00", "segmentsFile": "scannet.scene0007_00_vh_clean_2.0.010000.segs.json",
         "segGroups": groups}))
    scene = load_scene(folder / "scene0007_00_vh_clean_2.ply")
    assert scene.has_gt and set(np.unique(scene.instance)) == {0, 1, 5}
    assert (scene.instance[:30] == 1).all() and scene.instance[-1] == 5
    assert scene.categories == {1: "chair", 5: "cup"}
    labels = load_labels(folder / "scene0007_00.aggregation.json", n)
    assert np.array_equal(labels.labels, scene.instance)
    (folder / "scene0007_00_vh_clean_2.0.010000.segs.json").write_text(json.dumps({"segIndices": [0, 1]}))
    with pytest.raises(SceneError, match="segIndices, the scan has"):
        load_scene(folder / "scene0007_00_vh_clean_2.ply")


def test_help_texts_name_every_scene_format() -> None:
    """Every help text or docstring that lists the scene suffixes lists all of `FORMATS` (a format added to the
    table and not to the texts users read fails here)."""
    import re

    root = Path(__file__).resolve().parents[1]
    stale = []
    for f in [*root.glob("efem_viz/**/*.py"), *root.glob("annotator/**/*.py")]:
        for n, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"\.ply\W", line) and ".npz" in line and ".pcd" in line:  # a list of scene suffixes
                missing = [s for s in FORMATS if s not in line]
                if missing:
                    stale.append(f"{f.relative_to(root)}:{n} lacks {missing}")
    assert not stale, stale
