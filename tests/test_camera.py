"""Pinhole camera model (geometry/camera.py): projection round trip, provenance parsing, depth view, seen-through."""

from __future__ import annotations

import numpy as np
import pytest

from efem_viz.data.rgbd import backproject
from efem_viz.geometry.camera import MAX_FREE_SPACE_VIEWS, MAX_RECORDED_CAMERAS, Camera, DepthView, FreeSpace, look_at

K = np.array([[500.0, 0.0, 159.5], [0.0, 500.0, 119.5], [0.0, 0.0, 1.0]])


def _camera() -> Camera:
    return Camera(K=K, T_world_camera=look_at(np.array([0.0, -1.0, 0.6]), np.array([0.0, 0.0, 0.0])),
                  width=320, height=240)


def test_project_inverts_backproject() -> None:
    cam = _camera()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, (240, 320))
    pts_cam, idx = backproject(depth, K)
    T = cam.T_world_camera
    world = pts_cam @ T[:3, :3].T + T[:3, 3]
    u, v, z, ok = cam.project(world)
    assert ok.all()
    assert np.array_equal(v * 320 + u, idx)
    assert np.allclose(z, depth.reshape(-1)[idx])
    # behind the camera or outside the image: not ok
    behind = T[:3, 3] - 0.5 * T[:3, 2]
    far_side = world[:1] + 10.0 * T[:3, 0]
    assert not cam.project(np.stack([behind, far_side[0]]))[3].any()


def test_from_provenance_accepts_an_import_and_refuses_malformed_records() -> None:
    cam = _camera()
    prov = {"K": K.tolist(), "T_world_camera": cam.T_world_camera.tolist(), "image_size": [320, 240]}
    got = Camera.from_provenance(prov)
    assert got is not None and got.width == 320 and got.height == 240 and np.allclose(got.K, K)
    assert Camera.from_provenance(None) is None and Camera.from_provenance({}) is None
    bad = [{**prov, "K": [[1, 2], [3, 4]]}, {**prov, "K": np.full((3, 3), np.nan).tolist()},
           {**prov, "image_size": [0, 240]}, {**prov, "image_size": "big"},
           {**prov, "T_world_camera": (2 * np.eye(4)).tolist()}, {**prov, "T_world_camera": None}]
    for p in bad:
        assert Camera.from_provenance(p) is None, p
        cam_p, problem = Camera.parse(p)
        assert cam_p is None and problem, p  # a recorded camera that cannot be used says why
    assert Camera.parse({"source": "fused"}) == (None, None)  # no camera recorded: nothing to say
    assert "missing" in str(Camera.parse({"K": K.tolist()})[1])
    assert "not positive" in str(Camera.parse({**prov, "K": np.diag([0.0, 500.0, 1.0]).tolist()})[1])
    assert "rotation" in str(Camera.parse({**prov, "T_world_camera": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()})[1])


def test_seen_through_is_space_in_front_of_the_observed_surface() -> None:
    """A wall 1 m in front of a camera: shape samples in front of it are seen through, samples on it or behind it
    are not, samples outside the image or on unobserved pixels are unknown."""
    cam = Camera(K=K, T_world_camera=np.eye(4), width=320, height=240)
    g = np.linspace(-0.25, 0.25, 120)
    xx, yy = np.meshgrid(g, g)
    wall = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], 1)  # covers |x|,|y| <= 0.25 at z = 1
    view = DepthView.of_points(cam, wall)
    assert view.depth_at(160, 120) == pytest.approx(1.0)
    assert np.isinf(view.depth_at(5, 5))  # beyond the wall's footprint: unobserved
    assert view.depth.dtype == np.float32 and view.depth.size < 320 * 240  # the window of the points only
    inside = np.array([[0.0, 0.0, 0.5], [0.05, 0.0, 0.6], [0.0, 0.05, 0.7], [0.0, 0.0, 0.995],
                       [0.0, 0.0, 1.0], [0.02, 0.0, 1.3]])
    frac, known = view.seen_through(inside, 0.01)
    assert known == 1.0 and frac == pytest.approx(3 / 6)
    # a looser margin forgives the near-surface sample only
    assert view.seen_through(inside, 0.35)[0] == pytest.approx(2 / 6)
    unknown = np.array([[0.0, 0.0, -0.5], [5.0, 0.0, 1.0], [0.6, 0.45, 1.0]])
    frac, known = view.seen_through(np.vstack([inside[:1], unknown]), 0.01)
    assert frac == 1.0 and known == pytest.approx(1 / 4)
    assert view.seen_through(unknown, 0.01) == (0.0, 0.0)
    assert view.seen_through(np.zeros((0, 3)), 0.01) == (0.0, 0.0)


def box_before_wall() -> tuple[Camera, np.ndarray]:
    """A camera at the origin looking down +Z, a 10 cm square box face at 0.8 m in front of a 60 cm wall at 1.5 m."""
    cam = Camera(K=K, T_world_camera=np.eye(4), width=320, height=240)
    g = np.linspace(-0.3, 0.3, 300)
    xx, yy = np.meshgrid(g, g)
    wall = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 1.5)], 1)
    b = np.linspace(-0.05, 0.05, 60)
    bx, by = np.meshgrid(b, b)
    box = np.stack([bx.ravel(), by.ravel(), np.full(bx.size, 0.8)], 1)
    return cam, np.vstack([wall, box])


def test_sideways_tolerance_forgives_a_silhouette_overhang_but_not_free_space() -> None:
    """A box 0.8 m from the camera in front of a far wall: a shape that overhangs the box's edge by 5 mm is seen
    through there at pixel precision, not with a 1 cm sideways tolerance; a shape floating 5 cm beside the box,
    over the wall, is seen through either way."""
    cam, pts = box_before_wall()
    strict = DepthView.of_points(cam, pts)
    loose = DepthView.of_points(cam, pts, lateral=0.01)
    overhang = np.stack([np.full(20, 0.055), np.linspace(-0.04, 0.04, 20), np.full(20, 0.8)], 1)
    assert strict.seen_through(overhang, 0.01)[0] == pytest.approx(1.0)
    assert loose.seen_through(overhang, 0.01)[0] == pytest.approx(0.0)
    floating = overhang + np.array([0.05, 0.0, 0.0])
    assert strict.seen_through(floating, 0.01)[0] == pytest.approx(1.0)
    assert loose.seen_through(floating, 0.01)[0] == pytest.approx(1.0)
    assert DepthView.of_points(cam, pts, lateral=0.0).depth.tobytes() == strict.depth.tobytes()


def test_depth_view_memory_is_bounded_by_the_scene_not_the_declared_image() -> None:
    """A header may declare a 16384 x 16384 image: the view keeps only the window the points fall in."""
    cam = Camera(K=np.array([[2000.0, 0, 8191.5], [0, 2000.0, 8191.5], [0, 0, 1]]), T_world_camera=np.eye(4),
                 width=16384, height=16384)
    g = np.linspace(-0.05, 0.05, 50)
    xx, yy = np.meshgrid(g, g)
    pts = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], 1)
    view = DepthView.of_points(cam, pts)
    assert view.depth.nbytes < 4 * 300 * 300  # about 210 x 210 pixels of float32, not 16384² float64 (2 GB)
    centre = pts[np.abs(pts[:, :2]).max(1) < 0.03]
    assert view.seen_through(centre - np.array([0.0, 0.0, 0.1]), 0.01) == (1.0, 1.0)
    assert view.seen_through(centre + np.array([0.0, 0.0, 0.1]), 0.01) == (0.0, 1.0)


def test_a_huge_focal_length_gives_a_coarser_view_of_the_same_rays_in_bounded_memory() -> None:
    """A focal length of 30000 with a 16384² image spreads a 30 cm scene over the whole image (2.3 GB, 85 s
    before): the view is taken at a coarser resolution (at most `MAX_VIEW_PIXELS`), with the same answers."""
    import time

    from efem_viz.geometry.camera import MAX_VIEW_PIXELS

    cam = Camera(K=np.array([[30000.0, 0, 8191.5], [0, 30000.0, 8191.5], [0, 0, 1]]), T_world_camera=np.eye(4),
                 width=16384, height=16384)
    g = np.linspace(-0.15, 0.15, 200)
    xx, yy = np.meshgrid(g, g)
    pts = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], 1)
    c0 = time.process_time()
    view = DepthView.of_points(cam, pts, lateral=0.005)
    assert view.depth.size <= MAX_VIEW_PIXELS and view.camera.width < cam.width
    assert time.process_time() - c0 < 60  # a hang guard (about 1 s of work), not a speed test
    centre = pts[np.abs(pts[:, :2]).max(1) < 0.1]
    assert view.seen_through(centre - np.array([0.0, 0.0, 0.1]), 0.01) == (1.0, 1.0)
    assert view.seen_through(centre + np.array([0.0, 0.0, 0.1]), 0.01) == (0.0, 1.0)


def test_depth_edges_are_no_evidence_and_the_margin_grows_with_range() -> None:
    """A box 0.8 m from the camera in front of a wall at 1.5 m: with `edge`, the pixels along the box's silhouette
    (where a mixed pixel or a slightly mis-scaled fit sits) say nothing; the middle of the wall and of the box
    still do. The range term widens the margin as depth² (a sample 2 cm in front of the wall at 1.5 m: seen
    through with a 1 cm margin, not with 1 cm + 0.01 x 1.5²)."""
    cam, pts = box_before_wall()
    plain, edged = DepthView.of_points(cam, pts), DepthView.of_points(cam, pts, edge=0.05)
    beside = np.array([[0.0828, 0.0, 1.2]])  # in front of the wall, 3 pixels beside the box's silhouette
    assert plain.seen_through(beside, 0.01) == (1.0, 1.0)
    assert edged.seen_through(beside, 0.01) == (0.0, 0.0)  # unobserved: an edge pixel
    far = np.array([[0.2, 0.1, 1.2]])  # in front of the wall, far from any edge
    assert edged.seen_through(far, 0.01) == (1.0, 1.0)
    near_wall = np.array([[0.2, 0.1, 1.48]])
    assert plain.seen_through(near_wall, 0.01) == (1.0, 1.0)
    assert plain.seen_through(near_wall, 0.01, per_depth2=0.01) == (0.0, 1.0)


def _record(cam: Camera, size_key: str = "image_size") -> dict:
    return {"K": cam.K.tolist(), "T_world_camera": cam.T_world_camera.tolist(), size_key: [cam.width, cam.height]}


def test_every_recorded_camera_is_read_and_each_unusable_one_says_why() -> None:
    """A fused scan's provenance lists its cameras (`import-rgbd --sequence` writes ``image_size``, the generator
    ``size``); a frame records one. Each unusable entry is named with its position; a hostile list is read only
    up to `MAX_RECORDED_CAMERAS`."""
    a = _camera()
    b = Camera(K=K, T_world_camera=look_at(np.array([1.0, 0.0, 0.6]), np.zeros(3)), width=320, height=240)
    cams, problems = Camera.parse_all({"cameras": [_record(a), _record(b, "size")]})
    assert problems == [] and len(cams) == 2
    assert np.allclose(cams[1].T_world_camera, b.T_world_camera) and (cams[1].width, cams[1].height) == (320, 240)
    one, problems = Camera.parse_all(_record(a))
    assert len(one) == 1 and problems == [] and np.allclose(one[0].K, K)
    assert Camera.parse_all({}) == ([], []) and Camera.parse_all(None) == ([], [])
    bad = {**_record(b), "K": [[1, 2], [3, 4]]}
    cams, problems = Camera.parse_all({"cameras": [_record(a), bad, "junk", {"note": 1}]})
    assert len(cams) == 1
    assert len(problems) == 3 and problems[0].startswith("camera 2 of 4: K has shape")
    assert problems[1].startswith("camera 3 of 4") and problems[2].startswith("camera 4 of 4")
    assert Camera.parse_all({"cameras": "many"})[1] == ["the recorded cameras are a str, not a list"]
    flood = [_record(a)] * (MAX_RECORDED_CAMERAS + 10)
    cams, problems = Camera.parse_all({"cameras": flood})
    assert len(cams) == MAX_RECORDED_CAMERAS and "only the first" in problems[0]


def test_free_space_of_several_cameras_is_what_any_of_them_saw_empty() -> None:
    """A box 0.8 m in front of a wall, seen from the front and from the side: a shape sample beside the box is
    seen through by the front camera; a sample 10 cm behind the box's front face is hidden from the front
    camera (occluded: no evidence) but the side camera sees the wall through it — only the two cameras together
    find it. One camera's `FreeSpace` is exactly its `DepthView`."""
    front, pts = box_before_wall()
    # the box as a solid 10 cm cube (its side faces too), so that the side camera sees its side face
    b = np.linspace(-0.05, 0.05, 40)
    yy, zz = np.meshgrid(b, b + 0.85)
    side_face = np.stack([np.full(yy.size, 0.05), yy.ravel(), zz.ravel()], 1)
    g = np.linspace(-0.3, 0.3, 200)
    gy, gz = np.meshgrid(g, np.linspace(0.5, 1.5, 200))
    far_wall = np.stack([np.full(gy.size, -0.3), gy.ravel(), gz.ravel()], 1)  # what the side camera looks at
    pts = np.vstack([pts, side_face, far_wall])
    side = Camera(K=K, T_world_camera=look_at(np.array([1.0, 0.0, 0.85]), np.array([0.0, 0.0, 0.85])),
                  width=320, height=240)
    behind_box = np.array([[0.0, 0.0, 1.0], [0.01, 0.01, 1.05]])  # behind the cube, hidden from the front
    beside_box = np.array([[0.15, 0.0, 0.8]])
    only_front = FreeSpace.of_points([front], pts)
    both = FreeSpace.of_points([front, side], pts)
    assert only_front.seen_through(behind_box, 0.01)[0] == 0.0  # occluded from the front: no evidence
    assert both.seen_through(behind_box, 0.01)[0] == pytest.approx(1.0)  # the side camera saw the far wall
    assert both.seen_through(beside_box, 0.01) == only_front.seen_through(beside_box, 0.01) == (1.0, 1.0)
    mixed = np.vstack([behind_box, np.array([[0.0, 0.0, 1.6]])])  # + a point behind the wall: occluded for both
    frac, known = both.seen_through(mixed, 0.01)
    assert frac == pytest.approx(2 / 3) and known == 1.0
    rng = np.random.default_rng(3)
    samples = rng.uniform([-0.3, -0.3, 0.3], [0.3, 0.3, 1.7], (500, 3))
    view = DepthView.of_points(front, pts, edge=0.02)
    assert FreeSpace.of_points([front], pts, edge=0.02).seen_through(samples, 0.01, per_depth2=0.01) == \
        view.seen_through(samples, 0.01, per_depth2=0.01)
    assert FreeSpace(views=()).seen_through(samples, 0.01) == (0.0, 0.0)


def test_a_long_sequence_keeps_a_bounded_number_of_evenly_spaced_views() -> None:
    cams = [Camera(K=K, T_world_camera=look_at(np.array([np.cos(a), np.sin(a), 0.6]), np.zeros(3)), width=320,
                   height=240) for a in np.linspace(0, 2 * np.pi, 3 * MAX_FREE_SPACE_VIEWS, endpoint=False)]
    pts = np.random.default_rng(0).uniform(-0.2, 0.2, (2000, 3))
    fs = FreeSpace.of_points(cams, pts)
    assert len(fs.views) == MAX_FREE_SPACE_VIEWS
    assert fs.views[0].camera is cams[0] and fs.views[-1].camera is cams[-1]
