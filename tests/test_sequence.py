"""Posed RGB-D sequences fused into one scan (`import-rgbd --sequence`): the layouts, the fusion, the scene frame,
every camera recorded, and one clear line for every wrong input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from efem_viz.data.io import load_scene
from efem_viz.data.scene import SceneError
from efem_viz.data.sequence import find_sequence, import_sequence
from efem_viz.geometry.camera import look_at

ROOT = Path(__file__).resolve().parents[1]
W, H = 320, 240
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
"""Scene (+Z up) -> a Y-up world: the sequence's poses live there, as many capture apps' do."""


def tabletop_mesh():  # noqa: ANN201 - trimesh
    """A 60 x 50 cm table top at z = 0 with two cylinders standing on it (metres, +Z up)."""
    import trimesh

    table = trimesh.creation.box(extents=(0.6, 0.5, 0.02))
    table.apply_translation((0, 0, -0.01))
    a = trimesh.creation.cylinder(radius=0.04, height=0.1)
    a.apply_translation((-0.1, 0.05, 0.05))
    b = trimesh.creation.cylinder(radius=0.05, height=0.08)
    b.apply_translation((0.12, -0.06, 0.04))
    return trimesh.util.concatenate([table, a, b])


def write_sequence(folder: Path, n: int = 16, *, layout: str = "7-scenes", world: np.ndarray = Y_UP) -> list[np.ndarray]:
    """Render `n` depth (+ colour) frames of `tabletop_mesh` from cameras around it into `folder`; returns the
    camera-to-world poses (in `world`)."""
    import open3d as o3d
    from PIL import Image

    mesh = tabletop_mesh()
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    folder.mkdir(parents=True, exist_ok=True)
    poses = []
    for k in range(n):
        ang = 2 * np.pi * k / n
        eye = np.array([0.7 * np.cos(ang), 0.7 * np.sin(ang), 0.45 + 0.1 * np.sin(3 * ang)])
        T = look_at(eye, np.array([0.0, 0.0, 0.03]))
        rays = rc.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(T)), W, H)
        t = rc.cast_rays(rays)["t_hit"].numpy()
        dirs = rays.numpy()[..., 3:]
        z = t * (dirs @ T[:3, 2])
        depth = np.where(np.isfinite(z), np.round(z * 1000), 0).astype(np.uint16)
        color = np.zeros((H, W, 3), np.uint8)
        color[..., 0] = np.where(depth > 0, 200, 0)
        Tw = world @ T
        poses.append(Tw)
        if layout == "7-scenes":
            Image.fromarray(depth).save(folder / f"frame-{k:06d}.depth.png")
            Image.fromarray(color).save(folder / f"frame-{k:06d}.color.png")
            np.savetxt(folder / f"frame-{k:06d}.pose.txt", Tw)
        else:
            (folder / "depth").mkdir(exist_ok=True)
            (folder / "color").mkdir(exist_ok=True)
            Image.fromarray(depth).save(folder / "depth" / f"{k}.png")
            Image.fromarray(np.repeat(np.repeat(color, 2, 0), 2, 1)).save(folder / "color" / f"{k}.jpg")  # larger
            if layout == "scannet":
                (folder / "pose").mkdir(exist_ok=True)
                np.savetxt(folder / "pose" / f"{k}.txt", Tw)
    if layout == "7-scenes":
        np.savetxt(folder / "camera-intrinsics.txt", K)
    elif layout == "scannet":
        (folder / "intrinsic").mkdir(exist_ok=True)
        K4 = np.eye(4)
        K4[:3, :3] = K
        np.savetxt(folder / "intrinsic" / "intrinsic_depth.txt", K4)
    else:
        np.savetxt(folder / "poses.txt", np.stack(poses).reshape(n, 16))
    return poses


def test_a_16_view_sequence_fuses_into_one_scan_in_the_scene_frame(tmp_path: Path) -> None:
    """7-Scenes layout, poses in a Y-up world: the full CLI fuses it, puts the table at z = 0 with +Z up, and records
    every camera in the scene frame (each camera still sees the table's centre in front of it)."""
    poses = write_sequence(tmp_path / "seq")
    out = tmp_path / "fused.ply"
    run = subprocess.run([sys.executable, "-m", "efem_viz.cli", "import-rgbd", "--sequence", str(tmp_path / "seq"),
                          "--out", str(out)], capture_output=True, text=True, timeout=600,
                         env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    assert "16 frames (7-scenes) fused into" in run.stdout
    scene = load_scene(out)
    pts = scene.points
    table = np.abs(pts[:, 0]) < 0.28
    assert abs(float(np.median(pts[table & (pts[:, 2] < 0.01), 2]))) < 0.004  # the table top at z = 0
    # the cylinders' walls, in the scene frame (up to a rotation about z, which the import leaves as it was)
    r = np.hypot(pts[:, 0] + 0.1, pts[:, 1] - 0.05)
    wall = (np.abs(r - 0.04) < 0.006) & (pts[:, 2] > 0.02) & (pts[:, 2] < 0.09)
    assert wall.sum() > 300, "the first cylinder's wall is in the fused scan"
    cams = scene.provenance["cameras"]
    assert len(cams) == 16 and scene.provenance["frames"] == 16 and cams[0]["image_size"] == [W, H]
    for cam in cams:
        T = np.array(cam["T_world_camera"])
        to_centre = np.array([0.0, 0.0, 0.03]) - T[:3, 3]
        assert to_centre @ T[:3, 2] > 0.5 * np.linalg.norm(to_centre)  # looking at the table
    assert np.allclose(np.array(scene.provenance["scan_frame"]["T_scene_file"]) @ poses[0],
                       np.array(cams[0]["T_world_camera"]), atol=1e-9)


@pytest.mark.parametrize("layout", ["scannet", "poses-file"])
def test_scannet_exports_and_a_poses_file_fuse_alike(tmp_path: Path, layout: str) -> None:
    write_sequence(tmp_path / "seq", 8, layout=layout, world=np.eye(4))
    poses = tmp_path / "seq" / "poses.txt" if layout == "poses-file" else None
    scene = import_sequence(tmp_path / "seq", name="s", poses=poses, K=K if layout == "poses-file" else None)
    assert scene.provenance["layout"] == layout and len(scene.provenance["cameras"]) == 8
    assert scene.num_points > 5000 and (scene.colors[:, 0] > 150).mean() > 0.8  # colour resampled to the depth


def test_every_wrong_sequence_is_one_line(tmp_path: Path) -> None:
    write_sequence(tmp_path / "seq", 4, layout="poses-file", world=np.eye(4))
    seq = tmp_path / "seq"
    np.savetxt(tmp_path / "short.txt", np.eye(4).reshape(1, 16).repeat(3, 0))
    with pytest.raises(SceneError, match="3 poses for 4 depth frames"):
        find_sequence(seq, poses=tmp_path / "short.txt", K=K)
    bad = np.eye(4).reshape(1, 16).repeat(4, 0)
    bad[2, 5] = np.nan
    np.savetxt(tmp_path / "nan.txt", bad)
    with pytest.raises(SceneError, match="pose 2"):
        find_sequence(seq, poses=tmp_path / "nan.txt", K=K)
    skew = np.eye(4).reshape(1, 16).repeat(4, 0)
    skew[1, 0] = 2.0
    np.savetxt(tmp_path / "skew.txt", skew)
    with pytest.raises(SceneError, match="not a rigid transform"):
        find_sequence(seq, poses=tmp_path / "skew.txt", K=K)
    with pytest.raises(SceneError, match="no intrinsics file"):
        find_sequence(seq, poses=seq / "poses.txt")
    with pytest.raises(SceneError, match="no sequence layout recognised"):
        find_sequence(tmp_path)
    from PIL import Image

    Image.fromarray(np.zeros((100, 100), np.uint16)).save(seq / "depth" / "9.png")  # another size
    np.savetxt(tmp_path / "five.txt", np.stack([p.reshape(16) for p in [np.eye(4)] * 5]))
    with pytest.raises(SceneError, match="colour images for 5 depth images"):
        find_sequence(seq, poses=tmp_path / "five.txt", K=K)
    (seq / "color" / "9.jpg").write_bytes((seq / "color" / "0.jpg").read_bytes())
    with pytest.raises(SceneError, match="depth image 100x100, the sequence's first is 320x240"):
        import_sequence(seq, name="s", poses=tmp_path / "five.txt", K=K)
    assert not list(tmp_path.glob("*.ply"))
