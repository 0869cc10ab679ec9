"""RGB-D import: a ray-cast synthetic frame with known geometry, the real tabletop frames, the CLI, sample scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from efem_viz.data.io import load_scene
from efem_viz.data.rgbd import REAL_TABLETOP_LICENSE, import_rgbd, load_rgbd_npz
from efem_viz.data.scene import Scene, SceneError

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_tabletop"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real_tabletop")
SAMPLES = Path(__file__).resolve().parents[1] / "sample_scenes"

MUG_H = 0.10
MUG_R = 0.04


def render_synthetic(seed: int = 0, noise: float = 0.001) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a depth image: a 0.8 x 0.8 m table at z = 0, a floor at z = -0.7, a closed cylinder (r 4 cm,
    h 10 cm) standing on the table; camera at (0, -0.6, 0.5) looking at the table centre (OpenCV camera).

    Returns:
        (depth_m (240, 320) float32, K (3, 3), cam_world (3,)).
    """
    H, W, f = 240, 320, 300.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    cam = np.array([0.0, -0.6, 0.5])
    fwd = np.array([0.0, 0.05, 0.0]) - cam
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R_wc = np.stack([right, down, fwd], axis=1)
    v, u = np.mgrid[0:H, 0:W]
    d_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u, float)], axis=-1).reshape(-1, 3)
    d = d_cam @ R_wc.T  # world ray directions; the ray parameter t equals the camera depth
    t_best = np.full(len(d), np.inf)

    def plane_hit(z0: float, half: float) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z0 - cam[2]) / d[:, 2]
        p = cam + t[:, None] * d
        ok = (t > 0) & (np.abs(p[:, 0]) <= half) & (np.abs(p[:, 1]) <= half)
        return np.where(ok, t, np.inf)

    t_best = np.minimum(t_best, plane_hit(0.0, 0.4))
    t_best = np.minimum(t_best, plane_hit(-0.7, 3.0))
    c = np.array([0.05, 0.0])
    oc = cam[:2] - c
    a = (d[:, :2] ** 2).sum(1)
    b = 2 * (d[:, :2] @ oc)
    cc = oc @ oc - MUG_R**2
    disc = b**2 - 4 * a * cc
    with np.errstate(invalid="ignore"):
        t_side = (-b - np.sqrt(disc)) / (2 * a)
    z_side = cam[2] + t_side * d[:, 2]
    ok = (disc > 0) & (t_side > 0) & (z_side >= 0) & (z_side <= MUG_H)
    t_best = np.minimum(t_best, np.where(ok, t_side, np.inf))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_top = (MUG_H - cam[2]) / d[:, 2]
    p_top = cam + t_top[:, None] * d
    ok = (t_top > 0) & (((p_top[:, :2] - c) ** 2).sum(1) <= MUG_R**2)
    t_best = np.minimum(t_best, np.where(ok, t_top, np.inf))
    depth = np.where(np.isfinite(t_best), t_best, 0.0).reshape(H, W)
    rng = np.random.default_rng(seed)
    depth = np.where(depth > 0, depth + rng.normal(0, noise, depth.shape), 0.0)
    return depth.astype(np.float32), K, cam


def table_plane_stats(scene: Scene) -> tuple[float, float]:
    """(normal · Z, mean |z|) of a plane fitted to the points with |z| < 1 cm."""
    q = scene.points[np.abs(scene.points[:, 2]) < 0.01].astype(np.float64)
    c = q.mean(axis=0)
    n = np.linalg.svd(q - c, full_matrices=False)[2][2]
    return float(abs(n[2])), float(np.abs(q[:, 2]).mean())


def camera_position(scene: Scene) -> np.ndarray:
    return np.asarray(scene.provenance["T_world_camera"])[:3, 3]


def test_synthetic_frame_table_at_zero_and_objects_above() -> None:
    depth, K, cam = render_synthetic()
    scene = import_rgbd(depth, K, name="synthetic", voxel=0.004)
    nz, mean_abs_z = table_plane_stats(scene)
    assert nz > 0.99 and mean_abs_z < 0.005
    z = scene.points[:, 2]
    assert z.min() > -0.02, "the floor 0.7 m below the table must be cropped away"
    above = scene.points[z > 0.02]
    assert len(above) > 100
    assert abs(above[:, 2].max() - MUG_H) < 0.01  # the cylinder's top at its true height
    radial = np.linalg.norm(above[:, :2] - above[:, :2].mean(0), axis=1)
    assert radial.max() < MUG_R * 1.6  # one compact upright object, not smeared sideways
    # the camera's height above the table is preserved by the rigid transform
    assert camera_position(scene)[2] == pytest.approx(cam[2], abs=0.01)
    # normals point toward the camera
    to_cam = camera_position(scene) - scene.points
    assert (np.einsum("ij,ij->i", scene.normals, to_cam) > 0).mean() > 0.99
    # table normals are +Z
    table = np.abs(z) < 0.005
    assert np.median(scene.normals[table, 2]) > 0.98
    assert scene.provenance["plane_residual_rms_m"] < 0.003
    assert np.linalg.det(np.asarray(scene.provenance["T_world_camera"])[:3, :3]) == pytest.approx(1.0)


def test_import_is_deterministic_and_validates() -> None:
    depth, K, _ = render_synthetic()
    a = import_rgbd(depth, K, name="a", seed=3)
    b = import_rgbd(depth, K, name="a", seed=3)
    np.testing.assert_array_equal(a.points, b.points)
    with pytest.raises(SceneError, match="depth"):
        import_rgbd(depth[0], K, name="x")
    with pytest.raises(SceneError, match="K"):
        import_rgbd(depth, np.eye(2), name="x")
    with pytest.raises(SceneError, match="rgb"):
        import_rgbd(depth, K, np.zeros((10, 10, 3), np.uint8), name="x")
    with pytest.raises(SceneError, match="valid depth"):
        import_rgbd(np.zeros_like(depth), K, name="x")


def test_load_rgbd_npz_errors(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="no such file"):
        load_rgbd_npz(tmp_path / "none.npz")
    np.savez(tmp_path / "nok.npz", depth_mm=np.zeros((4, 4), np.uint16))
    with pytest.raises(SceneError, match="'K'"):
        load_rgbd_npz(tmp_path / "nok.npz")
    np.savez(tmp_path / "nodepth.npz", K=np.eye(3))
    with pytest.raises(SceneError, match="depth_mm"):
        load_rgbd_npz(tmp_path / "nodepth.npz")


def test_cli_depth_png_and_npy(tmp_path: Path) -> None:
    from PIL import Image

    from efem_viz.cli import main

    depth, K, _ = render_synthetic()
    mm = np.round(depth * 1000).astype(np.uint16)
    Image.fromarray(mm).save(tmp_path / "d.png")
    rgb = np.zeros((*depth.shape, 3), np.uint8)
    rgb[..., 0] = 200
    Image.fromarray(rgb).save(tmp_path / "c.png")
    intr = ["--fx", str(K[0, 0]), "--fy", str(K[1, 1]), "--cx", str(K[0, 2]), "--cy", str(K[1, 2])]
    out = tmp_path / "s.ply"
    assert main(["import-rgbd", "--depth", str(tmp_path / "d.png"), "--rgb", str(tmp_path / "c.png"),
                 "--out", str(out), *intr]) == 0
    s = load_scene(out)
    assert (s.colors[:, 0] == 200).all() and s.provenance["source_file"] == "d.png"
    assert table_plane_stats(s)[0] > 0.99
    np.save(tmp_path / "d.npy", depth)
    np.savez(tmp_path / "frame.npz", depth_mm=mm, K=K.astype(np.float32), rgb=rgb)
    assert main(["import-rgbd", "--depth", str(tmp_path / "d.npy"), "--out", str(tmp_path / "n.npz"), *intr]) == 0
    assert main(["import-rgbd", str(tmp_path / "frame.npz"), "--out", str(tmp_path / "f.ply")]) == 0
    assert load_scene(tmp_path / "f.ply").num_points == pytest.approx(s.num_points, rel=0.02)
    # load_scene imports an RGB-D frame .npz directly
    direct = load_scene(tmp_path / "frame.npz")
    np.testing.assert_array_equal(direct.points, load_scene(tmp_path / "f.ply").points)
    assert main(["import-rgbd", "--out", str(tmp_path / "x.ply")]) == 1  # neither a frame nor --depth
    assert main(["import-rgbd", "--depth", str(tmp_path / "d.npy"), "--out", str(tmp_path / "y.ply")]) == 1


def test_an_imported_frame_carries_only_the_licence_given(tmp_path: Path) -> None:
    """A user's frame is not stamped with the UOIS licence of the bundled frames: `import-rgbd` records the licence
    given with --licence, or none; the points do not depend on it (bench/real.py's scan hashes stay valid)."""
    import json

    from efem_viz.cli import main

    depth, K, _ = render_synthetic()
    np.savez(tmp_path / "frame.npz", depth_mm=np.round(depth * 1000).astype(np.uint16), K=K)
    assert main(["import-rgbd", str(tmp_path / "frame.npz"), "--out", str(tmp_path / "plain.ply")]) == 0
    plain = load_scene(tmp_path / "plain.ply")
    assert "licence" not in plain.provenance and "UOIS" not in json.dumps(dict(plain.provenance), default=str)
    assert plain.provenance["source_file"] == "frame.npz"
    mine = "CC0-1.0, (c) 2026 A. Person"
    assert main(["import-rgbd", str(tmp_path / "frame.npz"), "--out", str(tmp_path / "mine.ply"),
                 "--licence", mine]) == 0
    given = load_scene(tmp_path / "mine.ply")
    assert given.provenance["licence"] == mine
    np.testing.assert_array_equal(given.points, plain.points)
    assert "licence" not in load_scene(tmp_path / "frame.npz").provenance  # a frame opened directly: none either
    s = import_rgbd(depth, K, name="uois", licence=REAL_TABLETOP_LICENSE)
    assert s.provenance["licence"] == REAL_TABLETOP_LICENSE
    np.testing.assert_array_equal(s.points, import_rgbd(depth, K, name="uois").points)


@pytest.mark.skipif(not REAL.is_dir(), reason="shared real_tabletop frames not available")
def test_real_frame_table_flat_and_upright() -> None:
    rgb, depth, K = load_rgbd_npz(REAL / "image_0000.npz")
    assert rgb.shape == (480, 640, 3) and depth.dtype == np.float32 and K.shape == (3, 3)
    scene = import_rgbd(depth, K, rgb, name="real0", licence=REAL_TABLETOP_LICENSE)
    nz, mean_abs_z = table_plane_stats(scene)
    assert nz > 0.99 and mean_abs_z < 0.005
    z = scene.points[:, 2]
    assert z.min() > -0.02 and z.max() < 0.41
    assert (z > 0.05).sum() > 2000  # mugs, bowls, boxes stand on the table
    to_cam = camera_position(scene) - scene.points
    assert (np.einsum("ij,ij->i", scene.normals, to_cam) > 0).mean() > 0.99
    assert scene.provenance["licence"].startswith("MIT")


def _real_samples() -> list[Path]:
    """The imported frames `real_tabletop_<k>.ply` (not label files such as `real_tabletop_<k>.labels.ply`)."""
    return sorted(p for p in SAMPLES.glob("real_tabletop_*.ply") if p.name.count(".") == 1)


@pytest.mark.skipif(not _real_samples(), reason="no real sample scenes")
def test_real_sample_scenes() -> None:
    files = _real_samples()
    assert len(files) == 3
    assert (SAMPLES / "LICENSE-real_tabletop.txt").read_text().count("Chris Xie") >= 1
    for f in files:
        assert f.stat().st_size <= 3_000_000
        s = load_scene(f)
        assert s.provenance["licence"] == "MIT, UOIS example images, (c) 2019 Chris Xie"
        assert s.provenance["source_file"].startswith("image_")
        nz, mean_abs_z = table_plane_stats(s)
        assert nz > 0.99 and mean_abs_z < 0.005, f.name


def test_a_frame_larger_than_any_sensor_is_refused_before_it_is_inflated(tmp_path: Path) -> None:
    """a 130 KB .npz with an 8000x8000 depth image ran import-rgbd for 77 s and 10.4 GB. On the
    full CLI: one line naming the size, at once, nothing written."""
    import os
    import subprocess
    import sys

    big = tmp_path / "big.npz"
    np.savez_compressed(big, depth_mm=np.zeros((8000, 8000), np.uint16),
                        K=np.array([[600.0, 0, 4000], [0, 600.0, 4000], [0, 0, 1]]))
    assert big.stat().st_size < 1_000_000
    root = Path(__file__).resolve().parents[1]
    code = ("import resource, sys; lim = 1536 << 20; resource.setrlimit(resource.RLIMIT_AS, (lim, lim)); "
            "from efem_viz import cli; sys.exit(cli.main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "import-rgbd", str(big), "--out", str(tmp_path / "s.ply")],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(root)})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr[-2000:]
    assert "8000x8000 pixels" in lines[0] and "big.npz" in lines[0]
    assert not (tmp_path / "s.ply").exists()  # (the child ran under a 1.5 GB address-space limit)
