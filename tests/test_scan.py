"""A user's own scan: PCD files, units and up-axis detection, `import-scan`, and results written back in the file's
own frame (`segment --frame original`)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from efem_viz.data.io import load_scene, save_scene
from efem_viz.data.scan import (
    _UP_ROTATIONS,
    ScanFrame,
    detect_scan_frame,
    import_scan,
    scene_in_scene_frame,
)
from efem_viz.data.scene import Scene, SceneError
from efem_viz.geometry.transforms import Sim3, random_rotation

ROOT = Path(__file__).resolve().parents[1]


def tabletop(seed: int = 0, n_table: int = 6000) -> Scene:
    """A 60 x 50 cm table at z = 0 (1 mm noise) with three upright cylinders on it, in metres, +Z up."""
    rng = np.random.default_rng(seed)
    table = np.column_stack([rng.uniform(-0.3, 0.3, n_table), rng.uniform(-0.25, 0.25, n_table),
                             rng.normal(0, 0.001, n_table)])
    objs = []
    for cx, cy, r, h in ((-0.15, 0.05, 0.04, 0.10), (0.1, -0.08, 0.035, 0.12), (0.12, 0.12, 0.05, 0.08)):
        a, z = rng.uniform(0, 2 * np.pi, 800), rng.uniform(0, h, 800)
        objs.append(np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a), z]))
    pts = np.concatenate([table, *objs])
    inst = np.concatenate([np.zeros(n_table, int), *[np.full(800, k + 1) for k in range(3)]])
    return Scene.create("table", pts, instance=inst)


def as_file_frame(scene: Scene, up: str, scale: float, offset: np.ndarray) -> Scene:
    """The scene as another tool would save it: `up` axis up, in units of 1/scale metres, shifted."""
    R = _UP_ROTATIONS[up].T  # scene +Z -> the file's `up` axis
    return scene.replace(points=scene.points.astype(np.float64) @ R.T * scale + offset, provenance={})


# ------------------------------------------------------------------------------------------------ PCD
@pytest.mark.parametrize("ascii", [False, True])
def test_pcd_round_trips_points_colours_labels_and_provenance(tmp_path: Path, ascii: bool) -> None:
    sc = tabletop().replace(colors=np.random.default_rng(1).integers(0, 256, (8400, 3)).astype(np.uint8),
                            categories={1: "mug"}, provenance={"source": "test"})
    back = load_scene(save_scene(sc, tmp_path / "s.pcd", ascii=ascii))
    assert np.abs(back.points - sc.points).max() < 1e-6
    assert (back.colors == sc.colors).all() and (back.instance == sc.instance).all()
    assert back.categories == {1: "mug"} and back.provenance == {"source": "test"}


def test_pcl_written_pcd_files_load_compressed_and_organised(tmp_path: Path) -> None:
    import open3d as o3d

    sc = tabletop()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sc.points.astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(np.full((sc.num_points, 3), 0.5))
    o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), pc, compressed=True)
    back = load_scene(tmp_path / "c.pcd")
    assert np.abs(back.points - sc.points).max() < 1e-6 and (np.abs(back.colors.astype(int) - 128) <= 1).all()
    # an organised cloud (WIDTH x HEIGHT) with invalid (NaN) pixels keeps its valid points
    grid = np.array([[0, 0, 1], [np.nan, np.nan, np.nan], [1, 0, 1], [0, 1, 1]], np.float32)
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n"
    (tmp_path / "o.pcd").write_bytes(head.encode() + grid.tobytes())
    assert load_scene(tmp_path / "o.pcd").num_points == 3


@pytest.mark.parametrize("header, body, message", [
    ("POINTS 900000000\nDATA binary\n", b"\0" * 120, "more than the limit"),
    ("POINTS 100\nDATA binary\n", b"\0" * 120, "truncated file"),
    ("POINTS 10\nDATA binary_compressed\n", np.array([50, 120], "<u4").tobytes() + b"\x1f" * 50, "damaged"),
    ("POINTS 10\nDATA binary_compressed\n", np.array([10**9, 120], "<u4").tobytes(), "truncated file"),
    ("POINTS 10\nDATA lzma\n", b"", "not ascii, binary or binary_compressed"),
])
def test_a_hostile_pcd_header_is_one_line_before_any_allocation(tmp_path: Path, header: str, body: bytes,
                                                                message: str) -> None:
    p = tmp_path / "h.pcd"
    p.write_bytes(("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\n"
                   + header).encode() + body)
    with pytest.raises(SceneError, match=message) as exc:
        load_scene(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


# ------------------------------------------------------------------------------------------------ detection
@pytest.mark.parametrize("up", ["+z", "-z", "+y", "-y", "+x", "-x"])
@pytest.mark.parametrize("unit, scale", [("m", 1.0), ("cm", 100.0), ("mm", 1000.0)])
def test_units_and_up_axis_are_detected_and_the_round_trip_lands_on_the_scene(up: str, unit: str, scale: float) -> None:
    sc = tabletop()
    raw = as_file_frame(sc, up, scale, np.array([0.4, -1.3, 0.742]) * scale)
    imported, frame = import_scan(raw)
    assert (frame.units, frame.up, frame.decided) == (unit, up, "detected")
    # the support plane at z = 0 (to the millimetre), x/y as the file had them rotated into place
    assert abs(float(np.median(imported.points[:6000, 2]))) < 1e-3
    assert np.abs(imported.points[:, 2] - sc.points[:, 2]).max() < 1.5e-3
    # back to the file's frame: the file's own coordinates
    back = frame.to_scene.inverse().apply(imported.points)
    assert np.abs(back - raw.points).max() < 2e-6 * scale
    assert ScanFrame.from_provenance(imported.provenance).to_scene.matrix() == pytest.approx(frame.to_scene.matrix())


def test_a_scene_already_in_metres_with_z_up_is_left_exactly_as_it_is() -> None:
    sc = tabletop().replace(points=tabletop().points + np.array([0.2, 0.0, 0.004]))  # the table 4 mm up: kept
    imported, frame = import_scan(sc)
    assert frame.is_identity and np.array_equal(imported.points, sc.points)
    assert scene_in_scene_frame(sc)[1] is None


def test_a_tilted_scan_takes_the_support_planes_normal_as_up() -> None:
    sc = tabletop()
    R = random_rotation(3)
    raw = sc.replace(points=sc.points.astype(np.float64) @ R.T)
    frame = detect_scan_frame(raw.points)
    assert frame.up == "plane"
    up_in_file = R @ np.array([0.0, 0.0, 1.0])
    assert frame.to_scene.R @ up_in_file == pytest.approx([0, 0, 1], abs=0.01)


def test_what_cannot_be_decided_is_one_line_naming_the_flag() -> None:
    blob = np.random.default_rng(0).normal(size=(5000, 3)) * 0.2  # no support plane
    with pytest.raises(SceneError, match="pass --up"):
        detect_scan_frame(blob)
    huge = tabletop().points * 1e7  # 6000 km across: no unit fits
    with pytest.raises(SceneError, match="pass --units"):
        detect_scan_frame(huge)
    frame = detect_scan_frame(blob, up="+y", units="mm")  # given: no detection needed
    assert frame.decided == "given" and frame.to_scene.scale == 0.001
    with pytest.raises(SceneError, match="unknown up axis"):
        detect_scan_frame(blob, up="y")  # type: ignore[arg-type]


def test_instances_move_with_the_frame_and_back() -> None:
    from efem_viz.em.results import Instances

    rng = np.random.default_rng(0)
    rows = [{"proposal_id": k, "mask": np.arange(5), "confidence": 0.5, "mesh_vertices": rng.normal(size=(6, 3)),
             "mesh_faces": np.zeros((1, 3), int), "R": random_rotation(k), "center": rng.normal(size=3),
             "scale": 0.1, "obb_center": rng.normal(size=3), "obb_axes": random_rotation(k + 5),
             "obb_half_extents": np.array([0.05, 0.04, 0.06]), "coverage": 0.5, "stationary": 0.1,
             "db_sim": 0.9} for k in range(2)]
    inst = Instances.from_rows(rows, category="mug")
    sim = Sim3(1000.0, _UP_ROTATIONS["+y"].T, np.array([10.0, 742.0, -30.0]))
    moved = inst.transformed(sim)
    corners = np.stack([inst.obb(k).corners for k in range(2)])
    assert np.stack([moved.obb(k).corners for k in range(2)]) == pytest.approx(
        np.stack([sim.apply(c) for c in corners]), rel=1e-5, abs=1e-3)
    assert moved.mesh_vertices[1] == pytest.approx(sim.apply(inst.mesh_vertices[1]), rel=1e-5, abs=1e-3)
    assert moved.scale == pytest.approx(inst.scale * 1000)
    back = moved.transformed(sim.inverse())
    assert back.R == pytest.approx(inst.R, abs=1e-5) and back.center == pytest.approx(inst.center, abs=1e-4)
    assert [m.tolist() for m in back.masks] == [m.tolist() for m in inst.masks]
    geo = Sim3(1.0, np.eye(3), np.array([512345.25, 4123456.5, 312.0]))  # a georeferenced file's frame
    far = inst.transformed(geo)
    assert np.abs(far.center - (inst.center.astype(np.float64) + geo.t)).max() < 1e-6  # no float32 rounding (3 cm)
    assert np.abs(far.obb_center - (inst.obb_center.astype(np.float64) + geo.t)).max() < 1e-6


# ------------------------------------------------------------------------------------------------ full CLI
def test_import_scan_then_segment_writes_results_back_on_the_files_own_vertices(tmp_path: Path) -> None:
    """A millimetre, Y-up PCD: `import-scan` records its frame; `segment --frame original` of the imported scene
    and of the PCD opened directly both write the coloured PLY on the file's own coordinates and the objects in
    its units."""
    raw = as_file_frame(tabletop(), "+y", 1000.0, np.array([10.0, 742.0, -30.0]))
    save_scene(raw, tmp_path / "phone.pcd")
    env = {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    run = subprocess.run([sys.executable, "-m", "efem_viz.cli", "import-scan", str(tmp_path / "phone.pcd")],
                         capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "millimetres, +Y up (detected)" in run.stdout
    imported = load_scene(tmp_path / "phone.scene.ply")
    assert imported.provenance["scan_frame"]["units"] == "mm"
    bad = subprocess.run([sys.executable, "-m", "efem_viz.cli", "import-scan", str(tmp_path / "phone.scene.ply"),
                          "--out", str(tmp_path / "again.ply")], capture_output=True, text=True, env=env, timeout=600)
    assert bad.returncode != 0 and "imported already" in bad.stderr and not (tmp_path / "again.ply").exists()

    (tmp_path / "in").mkdir()
    for name, copy in (("phone.pcd", "phone.pcd"), ("phone.scene.ply", "phone_scene.ply")):
        (tmp_path / "in" / copy).write_bytes((tmp_path / name).read_bytes())
    seg = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(tmp_path / "in"), "--out",
                          str(tmp_path / "out"), "--prior", "sphere", "--proposals", "8", "--frame", "original",
                          "--threads", "1", "--export-objects", str(tmp_path / "objects"), "--object-format", "ply"],
                         capture_output=True, text=True, env=env, timeout=1200)
    assert seg.returncode == 0, seg.stdout + seg.stderr
    assert "read as millimetres, +Y up (detected)" in seg.stdout + seg.stderr  # the PCD opened directly
    for name in ("phone", "phone_scene"):
        ply = load_scene(tmp_path / "out" / f"{name}.seg.ply")
        assert np.abs(ply.points - raw.points).max() < 1e-2  # within 10 µm of the file's own millimetres
        objects = json.loads((tmp_path / "out" / f"{name}.objects.json").read_text())
        assert objects["frame"] == "original (mm)" and objects["scan_frame"]["up"] == "+y"
        for obj in objects["instances"]:  # boxes in millimetres, around the file's points
            assert 1.0 < max(obj["obb"]["half_extents"]) < 1000.0
        exported = json.loads((tmp_path / "objects" / name / "objects.json").read_text())
        assert exported["instances"] == [{**o, "mesh": e["mesh"]} for o, e in zip(objects["instances"],
                                                                                  exported["instances"])]
        assert len(exported["instances"]) > 0, "the spheres' stand-ins were found"
        for obj in exported["instances"]:  # each completed mesh, in millimetres, inside its own box
            mesh = load_scene(tmp_path / "objects" / name / obj["mesh"])
            local = (mesh.points - np.array(obj["obb"]["center"])) @ np.array(obj["obb"]["axes"])
            assert (np.abs(local) <= np.array(obj["obb"]["half_extents"]) * 1.05 + 0.5).mean() > 0.95


def test_segment_picks_each_scenes_preset_and_refuses_a_scan_far_from_metric(tmp_path: Path) -> None:
    """`segment` (default --preset auto): a single-view capture runs with `real`, a fused scan with `synthetic`,
    each scene's line says which; a 5 km "mug" is refused with the reason and the others still run."""
    from efem_viz.prior.analytic import make_sphere_scene

    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "capture.ply").write_bytes((ROOT / "sample_scenes" / "real_tabletop_0.ply").read_bytes())
    spheres = make_sphere_scene(seed=0, spacing=0.012, radii=(0.05,))
    save_scene(spheres, tmp_path / "in" / "fused.ply")
    save_scene(spheres.replace(points=spheres.points * 5e4, provenance={}), tmp_path / "in" / "huge.ply")
    env = {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    seg = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(tmp_path / "in"), "--out",
                          str(tmp_path / "out"), "--prior", "sphere", "--proposals", "4", "--threads", "1",
                          "--no-scannet"], capture_output=True, text=True, env=env, timeout=1200)
    out = seg.stdout
    assert seg.returncode == 1, out + seg.stderr  # one scene failed
    assert out.splitlines()[0].endswith(
        "preset auto (real for single-view captures, chairs for the chair prior, else synthetic)")
    assert re.search(r"capture: \d+ instances in .* \(local, preset real, free space from 1 camera\)", out), out
    assert re.search(r"fused: \d+ instances in .* \(local, preset synthetic\)", out), out
    assert re.search(r"huge: failed: SceneError: the scene spans [\d.e+]+ m: not a scan in metres", out), out


# ------------------------------------------------------------------------------------------------ LAS / LAZ
def test_a_georeferenced_laz_comes_in_near_the_origin_and_goes_back_to_its_own_coordinates(tmp_path: Path) -> None:
    """A LAZ scan in UTM-like coordinates (metres, +Z up, the table 312 m above sea level): the loader keeps
    millimetres by subtracting the whole-metre corner (recorded), the scan is brought to the scene frame with a
    notice that says so, and the recorded frame maps the file's own coordinates (float64) onto the scene."""
    import laspy

    base = tabletop()
    offset = np.array([512345.25, 4123456.5, 312.0])
    pts = base.points.astype(np.float64) + offset
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = np.floor(pts.min(axis=0))
    header.scales = np.array([0.0001, 0.0001, 0.0001])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.red = las.green = las.blue = np.full(len(pts), 200 * 257, np.uint16)
    las.write(str(tmp_path / "survey.laz"))
    file_xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)

    loaded = load_scene(tmp_path / "survey.laz")
    origin = np.array(loaded.provenance["file_origin"])
    assert np.array_equal(origin, np.floor(file_xyz.min(axis=0)))
    assert np.abs(loaded.points - (file_xyz - origin)).max() < 1e-4  # float32 near the origin: sub-millimetre
    assert (loaded.colors == 200).all()
    scene, notice = scene_in_scene_frame(loaded)
    assert notice is not None and "georeferenced origin" in notice
    frame = ScanFrame.from_provenance(scene.provenance)
    assert frame is not None
    table = scene.points[base.instance == 0]
    assert abs(float(np.median(table[:, 2]))) < 0.002  # the table at z = 0
    back = frame.to_scene.inverse().apply(scene.points.astype(np.float64))
    assert np.abs(back - file_xyz).max() < 1e-3  # the file's own coordinates, to the millimetre


@pytest.mark.parametrize("damage", ["count", "truncate", "garbage"])
def test_a_hostile_las_is_one_line_before_any_allocation(tmp_path: Path, damage: str) -> None:
    save_scene(tabletop(), tmp_path / "a.las")
    raw = bytearray((tmp_path / "a.las").read_bytes())
    if damage == "count":  # LAS 1.4: the 64-bit point count at byte 247
        raw[247:255] = (10**12).to_bytes(8, "little")
        match = "more than the limit"
    elif damage == "truncate":
        raw = raw[: len(raw) // 2]
        match = "truncated"
    else:
        raw[:4] = b"NOPE"
        match = "not a readable LAS/LAZ file"
    (tmp_path / "b.las").write_bytes(bytes(raw))
    with pytest.raises(SceneError, match=match):
        load_scene(tmp_path / "b.las")


@pytest.mark.parametrize("suffix, unit, scale, up", [(".ply", "mm", 1000.0, "+y"), (".pcd", "cm", 100.0, "-x"),
                                                     (".obj", "mm", 1000.0, "+y"), (".glb", "m", 1.0, "+y")])
def test_a_scan_in_other_units_and_axes_gives_the_same_answer_after_the_round_trip(
        tmp_path: Path, suffix: str, unit: str, scale: float, up: str) -> None:
    """The same scan saved by another tool in other units with another up axis (normals included, as scanners
    export them), read back and brought in by `import_scan`: EFEM finds the same instances with the same masks as
    on the metric, +Z-up original (the horizontal offset the file had is kept, so only rounding differs)."""
    from efem_viz.em import run_em
    from efem_viz.em.config import preset
    from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

    sc = make_sphere_scene(seed=3).replace(provenance={})
    prior = make_sphere_prior()
    cfg = preset("fast").replace(proposals={"n_init": (48,)})
    base = run_em(load_scene(save_scene(sc.replace(instance=None, categories={}), tmp_path / "orig.ply")), prior,
                  cfg, seed=1)
    R = _UP_ROTATIONS[up].T  # scene +Z -> the file's `up` axis
    raw = sc.replace(points=sc.points.astype(np.float64) @ R.T * scale + np.array([0.01, 0.742, -0.03]) * scale,
                     normals=sc.normals @ R.T, instance=None, categories={})
    imported, frame = import_scan(load_scene(save_scene(raw, tmp_path / f"file{suffix}")))
    assert (frame.units, frame.up) == (unit, up)
    got = run_em(imported, prior, cfg, seed=1)
    assert len(base.instances) == len(got.instances) == 3
    assert sorted(map(tuple, (np.sort(m) for m in base.instances.masks))) == \
        sorted(map(tuple, (np.sort(m) for m in got.instances.masks)))
