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


def write_sequence(folder: Path, n: int = 16, *, layout: str = "7-scenes",
                   world: np.ndarray = Y_UP) -> list[np.ndarray]:
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


def fuse_with_the_cli(folder: Path, out: Path, said: str):  # noqa: ANN201 - Scene
    """`efem-viz import-rgbd --sequence folder --out out` as a user runs it: it succeeds, says `said`, and the
    fused scan's table top lies at z = 0 (within 4 mm); returns the scan."""
    run = subprocess.run([sys.executable, "-m", "efem_viz.cli", "import-rgbd", "--sequence", str(folder), "--out",
                          str(out)], capture_output=True, text=True, timeout=600,
                         env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    assert said in run.stdout
    scene = load_scene(out)
    pts = scene.points
    table = np.abs(pts[:, 0]) < 0.28
    assert abs(float(np.median(pts[table & (pts[:, 2] < 0.01), 2]))) < 0.004
    return scene


def test_a_16_view_sequence_fuses_into_one_scan_in_the_scene_frame(tmp_path: Path) -> None:
    """7-Scenes layout, poses in a Y-up world: the full CLI fuses it, puts the table at z = 0 with +Z up, and records
    every camera in the scene frame (each camera still sees the table's centre in front of it)."""
    poses = write_sequence(tmp_path / "seq")
    scene = fuse_with_the_cli(tmp_path / "seq", tmp_path / "fused.ply", "16 frames (7-scenes) fused into")
    pts = scene.points
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


def _quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()  # x y z w


def write_tum(folder: Path, n: int = 12) -> list[np.ndarray]:
    """A TUM RGB-D folder of `write_sequence`'s frames: depth at 5000 per metre, timestamped lists, colour images
    5 ms after their depth, ground truth at 100 Hz (the true pose at every sample; the depth times fall between
    samples, at steady camera motion) with a comment header; returns the poses at the depth times."""
    from PIL import Image

    raw = folder.parent / f"{folder.name}_raw"
    poses = write_sequence(raw, n)
    (folder / "depth").mkdir(parents=True)
    (folder / "rgb").mkdir()
    depth_lines, rgb_lines = ["# depth maps", "# timestamp filename"], ["# color images"]
    for k in range(n):
        t = 1305031102.0 + k / 30.0 + 0.003
        mm = np.asarray(Image.open(raw / f"frame-{k:06d}.depth.png")).astype(np.uint32)
        Image.fromarray((mm * 5).astype(np.uint16)).save(folder / "depth" / f"{t:.6f}.png")
        (folder / "rgb" / f"{t + 0.005:.6f}.png").write_bytes((raw / f"frame-{k:06d}.color.png").read_bytes())
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
        rgb_lines.append(f"{t + 0.005:.6f} rgb/{t + 0.005:.6f}.png")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k in range(n):  # two samples around every depth time, both the frame's pose: interpolation keeps it exact
        t = 1305031102.0 + k / 30.0 + 0.003
        T = poses[k]
        for dt in (-0.002, 0.008):
            gt.append(f"{t + dt:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *_quat(T[:3, :3]))))
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    np.savetxt(folder / "intrinsics.txt", K)
    return poses


def test_a_tum_folder_is_associated_by_time_and_fused_at_its_depth_scale(tmp_path: Path) -> None:
    """TUM RGB-D: depth, colour and ground truth associated by timestamp, depth at 5000 per metre (the layout's,
    without --depth-scale), every camera where its ground truth puts it — through the full CLI."""
    poses = write_tum(tmp_path / "rgbd_dataset_freiburg1_desk")
    # the table at z = 0 in metres: the depth scale was 5000
    scene = fuse_with_the_cli(tmp_path / "rgbd_dataset_freiburg1_desk", tmp_path / "fused.ply",
                              "12 frames (tum) fused into")
    pts = scene.points
    r = np.hypot(pts[:, 0] + 0.1, pts[:, 1] - 0.05)
    wall = (np.abs(r - 0.04) < 0.006) & (pts[:, 2] > 0.02) & (pts[:, 2] < 0.09)
    assert wall.sum() > 200
    assert (scene.colors[:, 0] > 150).mean() > 0.8  # each depth image found its colour image 5 ms later
    cams = scene.provenance["cameras"]
    S = np.array(scene.provenance["scan_frame"]["T_scene_file"])
    for cam, T in zip(cams, poses):
        assert np.allclose(S @ T, np.array(cam["T_world_camera"]), atol=1e-6)
    assert np.allclose(cams[0]["K"], K)  # the folder's intrinsics file wins over the published ones


def test_tum_poses_interpolate_between_samples_and_skip_gaps(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation, Slerp

    from efem_viz.data.sequence import TUM_INTRINSICS, tum_pose_at

    rots = Rotation.from_euler("xyz", [[0, 0, 0], [0.2, -0.4, 1.0], [0.3, 0.1, 2.5]])
    stamps = np.array([10.0, 10.04, 10.5])  # a 0.46 s gap between the last two
    trans = np.array([[0.0, 0, 0], [0.1, 0.2, -0.3], [1.0, 1.0, 1.0]])
    gt = np.concatenate([trans, rots.as_quat()], axis=1)
    T = tum_pose_at(10.01, stamps, gt)
    assert T is not None
    want = Slerp(stamps[:2], rots[:2])([10.01]).as_matrix()[0]
    assert np.allclose(T[:3, :3], want, atol=1e-9) and np.allclose(T[:3, 3], 0.25 * trans[1], atol=1e-12)
    assert np.allclose(tum_pose_at(10.04, stamps, gt)[:3, 3], trans[1])  # type: ignore[index] - on a sample
    assert tum_pose_at(10.2, stamps, gt) is None  # inside the gap
    assert tum_pose_at(9.9, stamps, gt) is None and tum_pose_at(10.6, stamps, gt) is None  # outside the span
    # a folder without intrinsics named after a Freiburg sequence takes the published ones
    write_tum(tmp_path / "rgbd_dataset_freiburg3_office", 3)
    (tmp_path / "rgbd_dataset_freiburg3_office" / "intrinsics.txt").unlink()
    seq = find_sequence(tmp_path / "rgbd_dataset_freiburg3_office")
    fx, fy, cx, cy = TUM_INTRINSICS["freiburg3"]
    assert seq.layout == "tum" and seq.depth_scale == 5000.0 and len(seq.frames) == 3
    assert np.allclose(seq.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])


def test_every_wrong_tum_folder_is_one_line(tmp_path: Path) -> None:
    folder = tmp_path / "mine"
    write_tum(folder, 3)
    (folder / "intrinsics.txt").unlink()
    with pytest.raises(SceneError, match="no intrinsics file"):
        find_sequence(folder)  # not a Freiburg name: no guess
    np.savetxt(folder / "intrinsics.txt", K)
    depth_txt = (folder / "depth.txt").read_text()
    (folder / "depth.txt").write_text(depth_txt + "1305031109.0 ../../etc/passwd\n1305031109.1 x.png\n")
    gt = (folder / "groundtruth.txt").read_text()
    (folder / "groundtruth.txt").write_text(gt + "".join(f"{t} 0 0 0 0 0 0 1\n" for t in
                                                         (1305031108.98, 1305031109.03, 1305031109.08, 1305031109.13)))
    with pytest.raises(SceneError, match="lies outside the sequence folder"):
        find_sequence(folder)
    (folder / "depth.txt").write_text(depth_txt + "1305031109.1 depth/none.png\n")
    with pytest.raises(SceneError, match="none.png: missing"):
        find_sequence(folder)
    (folder / "depth.txt").write_text(depth_txt + "nan-ish depth/x.png\n")
    with pytest.raises(SceneError, match="timestamp is not a number"):
        find_sequence(folder)
    (folder / "depth.txt").write_text(depth_txt)
    (folder / "groundtruth.txt").write_text("# nothing\n1.0 0 0 0\n")
    with pytest.raises(SceneError, match="a TUM list line has 8"):
        find_sequence(folder)
    (folder / "groundtruth.txt").write_text("# far in the past\n5.0 0 0 0 0 0 0 1\n5.01 0 0 0 0 0 0 1\n")
    with pytest.raises(SceneError, match="no depth frames found with a ground-truth pose"):
        find_sequence(folder)
