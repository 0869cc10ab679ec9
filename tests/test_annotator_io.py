"""Label formats (PLY / NPZ / ScanNet JSON) round trips, bad input, and path safety."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from annotator.io import (
    LabelIOError,
    load_labels,
    load_scan,
    resolve_inside,
    save_labels_npz,
    save_labels_ply,
    save_scannet,
)
from annotator.labels import InstanceInfo
from efem_viz.data.io import load_scene, save_scene
from efem_viz.data.scene import Scene


@pytest.fixture()
def scene() -> Scene:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.2, 0.2, size=(500, 3)).astype(np.float32)
    nrm = np.tile(np.array([[0, 0, 1.0]], np.float32), (500, 1))
    faces = np.stack([np.arange(0, 498), np.arange(1, 499), np.arange(2, 500)], axis=1)
    return Scene.create("toy", pts, normals=nrm, faces=faces)


@pytest.fixture()
def labelled() -> tuple[np.ndarray, dict[int, InstanceInfo]]:
    lab = np.zeros(500, np.int32)
    lab[10:60] = 1
    lab[100:180] = 4
    table = {1: InstanceInfo(1, "left mug", "mug", (10, 20, 30), locked=True),
             4: InstanceInfo(4, "bowl", "bowl", (200, 100, 0), visible=False, note="n")}
    return lab, table


def test_ply_round_trip_is_ground_truth_format(tmp_path: Path, scene: Scene, labelled) -> None:
    lab, table = labelled
    p = save_labels_ply(scene, lab, table, tmp_path / "toy.labels.ply")
    # the rest of efem-viz reads it as ground truth
    gt = load_scene(p)
    assert np.array_equal(gt.instance, lab)
    assert gt.categories == {1: "mug", 4: "bowl"}
    assert np.allclose(gt.points, scene.points) and gt.is_mesh
    back = load_labels(p, 500)
    assert np.array_equal(back.labels, lab)
    assert {r.id: r for r in back.instances} == table  # names, colours and flags survive


def test_npz_round_trip(tmp_path: Path, labelled) -> None:
    lab, table = labelled
    p = save_labels_npz(lab, table, tmp_path / "toy.labels.npz", scan_name="toy")
    back = load_labels(p, 500)
    assert np.array_equal(back.labels, lab) and {r.id: r for r in back.instances} == table


def test_scene_npz_with_instance_imports(tmp_path: Path, scene: Scene, labelled) -> None:
    lab, _ = labelled
    p = save_scene(scene.with_labels(lab, {1: "mug", 4: "bowl"}), tmp_path / "s.npz")
    back = load_labels(p, 500)
    assert np.array_equal(back.labels, lab)
    assert {r.id: r.category for r in back.instances} == {1: "mug", 4: "bowl"}


def test_scannet_round_trip(tmp_path: Path, labelled) -> None:
    lab, table = labelled
    segs, agg = save_scannet(lab, table, tmp_path, "toy")
    d = json.loads(agg.read_text())
    assert {g["objectId"] for g in d["segGroups"]} == {0, 3}
    assert {g["label"] for g in d["segGroups"]} == {"mug", "bowl"}
    assert len(json.loads(segs.read_text())["segIndices"]) == 500
    for p in (segs, agg):
        back = load_labels(p, 500)
        assert np.array_equal(back.labels, lab)
        assert {r.id: r.category for r in back.instances} == {1: "mug", 4: "bowl"}


def test_scannet_with_real_oversegmentation(tmp_path: Path) -> None:
    """Several segments per object, as ScanNet ships them."""
    seg = np.repeat(np.arange(10), 10)
    (tmp_path / "a.segs.json").write_text(json.dumps({"segIndices": seg.tolist()}))
    (tmp_path / "a.aggregation.json").write_text(json.dumps({"segGroups": [
        {"id": 0, "objectId": 0, "label": "chair", "segments": [1, 2]},
        {"id": 1, "objectId": 1, "label": "table", "segments": [7]},
    ]}))
    back = load_labels(tmp_path / "a.aggregation.json", 100)
    expect = np.zeros(100, np.int32)
    expect[10:30] = 1
    expect[70:80] = 2
    assert np.array_equal(back.labels, expect)


@pytest.mark.parametrize("case", ["missing", "empty", "garbage_ply", "wrong_length", "float_labels", "negative",
                                  "unknown_suffix", "no_instance"])
def test_bad_label_files_give_clear_errors(tmp_path: Path, scene: Scene, case: str) -> None:
    p = tmp_path / "x.ply"
    if case == "empty":
        p.write_bytes(b"")
    elif case == "garbage_ply":
        p.write_bytes(b"ply\nformat nonsense\n")
    elif case == "wrong_length":
        p = save_labels_ply(scene, np.zeros(500, np.int32), {}, tmp_path / "x.ply")
    elif case == "float_labels":
        p = tmp_path / "x.npz"
        np.savez(p, instance=np.full(500, 0.5))
    elif case == "negative":
        p = tmp_path / "x.npz"
        np.savez(p, instance=np.full(500, -2))
    elif case == "unknown_suffix":
        p = tmp_path / "x.txt"
        p.write_text("1 2 3")
    elif case == "no_instance":
        p = save_scene(scene, tmp_path / "x.ply")
    n = 499 if case == "wrong_length" else 500
    with pytest.raises(LabelIOError) as err:
        load_labels(p, n)
    assert str(p.name) in str(err.value) or "x." in str(err.value)


def test_bad_scans_give_clear_errors(tmp_path: Path) -> None:
    nan = tmp_path / "nan.ply"
    nan.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                   "end_header\n0 0 0\nnan 1 1\n")
    with pytest.raises(LabelIOError, match="NaN"):
        load_scan(nan)
    (tmp_path / "e.ply").write_bytes(b"")
    with pytest.raises(LabelIOError, match="empty"):
        load_scan(tmp_path / "e.ply")
    with pytest.raises(LabelIOError, match="no such file"):
        load_scan(tmp_path / "missing.obj")


def test_resolve_inside_refuses_traversal_and_symlinks(tmp_path: Path) -> None:
    root = tmp_path / "work"
    (root / "sub").mkdir(parents=True)
    outside = tmp_path / "secret.txt"
    outside.write_text("x")
    assert resolve_inside("sub/a.ply", [root]) == (root / "sub" / "a.ply").resolve()
    assert resolve_inside(root / "b.npz", [root]) == (root / "b.npz").resolve()
    for bad in ("../secret.txt", "sub/../../secret.txt", str(outside), "/etc/passwd", "", "a\x00b"):
        with pytest.raises(LabelIOError):
            resolve_inside(bad, [root])
    os.symlink(outside, root / "link.txt")
    with pytest.raises(LabelIOError, match="outside"):
        resolve_inside("link.txt", [root])
    os.symlink(tmp_path, root / "dirlink")
    with pytest.raises(LabelIOError):
        resolve_inside("dirlink/secret.txt", [root])
    # a second allowed root works
    assert resolve_inside(str(outside), [root, tmp_path]) == outside.resolve()


def test_writers_refuse_symlink_targets(tmp_path: Path, scene: Scene, labelled) -> None:
    lab, table = labelled
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    os.symlink(victim, tmp_path / "toy.labels.ply")
    with pytest.raises(LabelIOError, match="symbolic link"):
        save_labels_ply(scene, lab, table, tmp_path / "toy.labels.ply")
    os.symlink(victim, tmp_path / "toy.labels.npz")
    with pytest.raises(ValueError, match="symbolic link"):
        save_labels_npz(lab, table, tmp_path / "toy.labels.npz")
    assert victim.read_text() == "keep me"


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".glb", ".npz"])
def test_scans_open_in_every_format_unchanged(tmp_path: Path, scene: Scene, suffix: str) -> None:
    p = save_scene(scene, tmp_path / f"toy{suffix}")
    before = p.read_bytes()
    got = load_scan(p)
    assert got.num_points == scene.num_points and got.is_mesh
    assert np.allclose(got.points, scene.points, atol=1e-5)
    assert p.read_bytes() == before  # the source scan is only read


def test_binary_triangle_ply_fast_path_matches_general_loader(tmp_path: Path, scene: Scene) -> None:
    p = save_scene(scene.with_labels(np.arange(500) % 3, {1: "mug", 2: "bowl"}), tmp_path / "t.ply")
    fast = load_scan(p)
    ref = load_scene(p)
    for k in ("points", "normals", "colors", "faces", "instance"):
        assert np.array_equal(getattr(fast, k), getattr(ref, k)), k
    assert fast.categories == ref.categories


RGBD = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_tabletop" / "image_0000.npz"
if not RGBD.exists():
    RGBD = Path("/work/shared/data/real_tabletop/image_0000.npz")


@pytest.mark.skipif(not RGBD.exists(), reason="real RGB-D frames not present")
def test_rgbd_frame_opens_as_a_tabletop_scene() -> None:
    s = load_scan(RGBD)
    assert 10_000 < s.num_points < 2_000_000 and not s.is_mesh
    assert abs(float(np.median(s.points[:, 2]))) < 0.05  # the table plane is z = 0
