"""Selection tools against naive reference computations on small meshes and point clouds."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from annotator import selection as sel
from annotator.render import build_chunks, color_lut, compose_colors, splat_proxy
from annotator.labels import InstanceInfo


@pytest.fixture(scope="module")
def box_on_plane() -> sel.ScanGeometry:
    """A 20 cm box standing on a 1 m plane (separate components glued only by geometry), as one mesh."""
    plane = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    plane.apply_translation((0, 0, -0.01))
    plane = plane.subdivide().subdivide().subdivide()
    cube = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide().subdivide().subdivide()
    cube.apply_translation((0, 0, 0.1))
    m = trimesh.util.concatenate([plane, cube])
    return sel.ScanGeometry(np.asarray(m.vertices, np.float32), np.asarray(m.vertex_normals, np.float32),
                            faces=np.asarray(m.faces))


@pytest.fixture(scope="module")
def sphere_points() -> sel.ScanGeometry:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(4000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return sel.ScanGeometry((0.1 * p).astype(np.float32), p.astype(np.float32))


def test_brush_matches_naive_ball_and_normal_limit(sphere_points: sel.ScanGeometry) -> None:
    g = sphere_points
    c = g.points[17]
    got = sel.brush(g, c, 0.03)
    naive = np.flatnonzero(np.linalg.norm(g.points - c, axis=1) <= 0.03)
    assert np.array_equal(got, naive)
    lim = sel.brush(g, c, 0.03, normal=g.normals[17], max_normal_angle_deg=5.0)
    cos = g.normals[naive] @ g.normals[17]
    assert np.array_equal(lim, naive[cos >= np.cos(np.deg2rad(5.0))])
    assert 0 < len(lim) < len(naive)
    with pytest.raises(ValueError):
        sel.brush(g, c, 0.0)


def test_brush_segment_is_the_capsule(sphere_points: sel.ScanGeometry) -> None:
    g = sphere_points
    a, b = g.points[3], g.points[3] + np.array([0.0, 0.0, 0.03], np.float32)
    got = sel.brush_segment(g, a, b, 0.01)
    seg = b - a
    t = np.clip((g.points - a) @ seg / (seg @ seg), 0, 1)
    d = np.linalg.norm(g.points - (a + t[:, None] * seg), axis=1)
    assert np.array_equal(got, np.flatnonzero(d <= 0.01))
    # union of the end dabs is a subset of the capsule
    ends = np.union1d(sel.brush(g, a, 0.01), sel.brush(g, b, 0.01))
    assert np.isin(ends, got).all()


def test_pick_mesh_and_points(box_on_plane: sel.ScanGeometry, sphere_points: sel.ScanGeometry) -> None:
    v, hit = sel.pick(box_on_plane, np.array([0.01, 0.02, 1.0]), np.array([0, 0, -1.0]))
    assert hit[2] == pytest.approx(0.2, abs=1e-5)  # the top of the box, not the plane below
    assert np.linalg.norm(box_on_plane.points[v] - hit) < 0.05
    assert sel.pick(box_on_plane, np.array([5.0, 5, 1]), np.array([0, 0, 1.0])) is None
    res = sel.pick(sphere_points, np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert res is not None
    v, _ = res
    assert sphere_points.points[v][2] > 0.09  # front side of the sphere
    assert sel.pick(sphere_points, np.array([0, 0, 1.0]), np.array([0, 0, 0.0])) is None


def test_region_grow_stops_at_crease_and_distance(box_on_plane: sel.ScanGeometry) -> None:
    g = box_on_plane
    top = np.flatnonzero(np.isclose(g.points[:, 2], 0.2) & (np.abs(g.points[:, :2]).max(axis=1) < 0.099))
    seed = int(top[len(top) // 2])
    grown = sel.region_grow(g, seed, max_angle_deg=20.0)
    # Exactly the top face (vertex normals at the face border bend by ~45 degrees and stop the fill).
    assert np.all(np.isclose(g.points[grown, 2], 0.2, atol=1e-6))
    assert np.isin(top, grown).all()
    everything = sel.region_grow(g, seed, max_angle_deg=90.0)
    assert len(everything) > len(grown)
    assert np.all(g.points[everything, 2] > 0.0 - 1e-6)  # still never jumps to the plane (not connected)
    near = sel.region_grow(g, seed, max_angle_deg=90.0, max_distance=0.05)
    assert np.linalg.norm(g.points[near] - g.points[seed], axis=1).max() <= 0.05
    capped = sel.region_grow(g, seed, max_angle_deg=90.0, max_vertices=10)
    assert len(capped) == 10 and seed in capped
    allowed = np.ones(g.n, bool)
    allowed[top[::2]] = False
    partial = sel.region_grow(g, seed if allowed[seed] else int(top[1]), max_angle_deg=20.0, allowed=allowed)
    assert not np.isin(top[::2], partial).any()


def test_knn_graph_and_fill(sphere_points: sel.ScanGeometry) -> None:
    g = sphere_points
    indptr, indices = g.adjacency
    assert len(indptr) == g.n + 1 and indices.max() < g.n
    # symmetric
    a = np.repeat(np.arange(g.n), np.diff(indptr))
    pairs = set(zip(a.tolist(), indices.tolist()))
    assert all((j, i) in pairs for i, j in list(pairs)[:500])
    labels = np.zeros(g.n, np.int32)
    labels[g.points[:, 2] > 0.05] = 3
    filled = sel.fill_same_label(g, int(np.argmax(g.points[:, 2])), labels)
    assert np.all(labels[filled] == 3) and len(filled) == int((labels == 3).sum())


def test_box_select_matches_projection() -> None:
    pts = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, -5.0]], np.float32)
    nrm = np.tile(np.array([[0, 0, 1.0]], np.float32), (4, 1))
    nrm[3] = (0, 0, -1.0)  # behind the others and facing away: a back face
    g = sel.ScanGeometry(pts, nrm)
    # camera 2 m above, looking down -Z. OpenCV camera: +Z forward = world -Z; choose R with x→x, y→-y, z→-z.
    wxyz = np.array([0.0, 1.0, 0.0, 0.0])  # 180° about x
    uv, z = sel.project(pts, position=np.array([0, 0, 2.0]), wxyz=wxyz, fov=np.deg2rad(60), aspect=1.0)
    assert uv[0] == pytest.approx([0.5, 0.5]) and z[0] == pytest.approx(2.0)
    assert uv[1, 0] > 0.5 and uv[2, 1] < 0.5  # +x → right, +y → up on screen
    got = sel.box_select(g, position=np.array([0, 0, 2.0]), wxyz=wxyz, fov=np.deg2rad(60), aspect=1.0,
                         screen_min=(0.4, 0.4), screen_max=(0.9, 0.6))
    assert got.tolist() == [0, 1]
    back = sel.box_select(g, position=np.array([0, 0, -10.0]), wxyz=np.array([1.0, 0, 0, 0]), fov=1.0, aspect=1.0,
                          screen_min=(0, 0), screen_max=(1, 1))
    assert back.tolist() == [3]  # only the point facing this camera
    allp = sel.box_select(g, position=np.array([0, 0, -10.0]), wxyz=np.array([1.0, 0, 0, 0]), fov=1.0, aspect=1.0,
                          screen_min=(0, 0), screen_max=(1, 1), facing="all")
    assert len(allp) == 4


def test_chunks_partition_and_colours() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(size=(10_000, 3)).astype(np.float32)
    ch = build_chunks(pts, max_chunk=1000)
    assert np.array_equal(np.sort(ch.order), np.arange(10_000))
    sizes = np.diff(ch.offsets)
    assert sizes.max() <= 1000 and ch.count >= 10
    for c in range(ch.count):
        assert np.all(ch.chunk_of[ch.members(c)] == c)
    # spatial compactness: chunk boxes are much smaller than the whole cube
    vol = [np.prod(np.ptp(pts[ch.members(c)], axis=0)) for c in range(ch.count)]
    assert max(vol) < 0.5
    assert ch.touched(np.array([ch.members(3)[0], ch.members(3)[1], ch.members(5)[0]])).tolist() == [3, 5]
    base = np.full((4, 3), 100, np.uint8)
    lut, show = color_lut({1: InstanceInfo(1, "a", color=(255, 0, 0)), 2: InstanceInfo(2, "b", visible=False)}, 2)
    out = compose_colors(base, np.array([0, 1, 2, 9]), lut, show, alpha=1.0)
    assert out.tolist() == [[100] * 3, [255, 0, 0], [100] * 3, [100] * 3]
    # a running EFEM's overlay: drawn over unlabelled vertices only, the search tint at its own weight
    out = compose_colors(base, np.array([0, 1, 0, 0]), lut, show, alpha=1.0,
                         overlay=(np.array([1, 1, 2, 0], np.uint16), np.array([[0, 200, 200]], np.uint8)))
    assert out[1].tolist() == [255, 0, 0] and out[3].tolist() == [100] * 3  # labelled: its label; code 0: the scan
    assert out[0].tolist() == [177, 135, 50]  # half search colour (255, 170, 0), half scan colour
    assert out[2].tolist() == [140, 230, 230]  # an accepted instance as a pale pre-label, at the label weight (1.0)
    v, f = splat_proxy(pts[:50], np.tile([[0, 0, 1.0]], (50, 1)), size=0.01)
    assert v.shape == (150, 3) and f.shape == (50, 3) and f.max() == 149


def test_region_grow_on_fresh_point_cloud_does_not_deadlock() -> None:
    """Adjacency is built under the geometry lock and needs the KD-tree, built under the same lock."""
    import threading

    from annotator.selection import ScanGeometry, region_grow

    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 0.1, (400, 2)), np.zeros(400)].astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (400, 1))
    geom = ScanGeometry(pts, nrm)  # nothing built yet
    out: list[np.ndarray] = []
    t = threading.Thread(target=lambda: out.append(region_grow(geom, 0)), daemon=True)
    t.start()
    t.join(timeout=30)
    assert not t.is_alive(), "region_grow deadlocked on a fresh point-cloud geometry"
    assert len(out[0]) > 1


def test_points_in_polygon_matches_a_naive_loop() -> None:
    from annotator.selection import points_in_polygon

    rng = np.random.default_rng(3)
    poly = np.array([[0.1, 0.1], [0.9, 0.2], [0.5, 0.5], [0.8, 0.9], [0.2, 0.7]])  # concave
    uv = rng.uniform(0, 1, size=(400, 2))

    def naive(p: np.ndarray) -> bool:
        inside = False
        for i in range(len(poly)):
            (x0, y0), (x1, y1) = poly[i], poly[(i + 1) % len(poly)]
            if (y0 > p[1]) != (y1 > p[1]) and p[0] < x0 + (p[1] - y0) * (x1 - x0) / (y1 - y0):
                inside = not inside
        return inside

    assert points_in_polygon(uv, poly).tolist() == [naive(p) for p in uv]
    assert points_in_polygon(np.array([[0.3, 0.4], [0.75, 0.5]]), poly).tolist() == [True, False]  # the notch is out
    with pytest.raises(ValueError):
        points_in_polygon(uv, poly[:2])


def test_lasso_select_equals_box_select_for_a_rectangle_and_respects_facing() -> None:
    from annotator.selection import ScanGeometry, box_select, lasso_select

    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.5, 0.5, size=(3000, 3)).astype(np.float32)
    nrm = np.tile(np.array([[0, 0, 1]], np.float32), (3000, 1))
    nrm[::2] *= -1
    g = ScanGeometry(pts, nrm)
    cam = dict(position=np.array([0.0, 0.0, 2.0]), wxyz=np.array([0.0, 1.0, 0.0, 0.0]), fov=np.deg2rad(60),
               aspect=1.0)
    rect = np.array([[0.3, 0.35], [0.7, 0.35], [0.7, 0.6], [0.3, 0.6]])
    for facing in ("visible", "front", "all"):
        a = lasso_select(g, polygon=rect, facing=facing, **cam)
        b = box_select(g, screen_min=(0.3, 0.35), screen_max=(0.7, 0.6), facing=facing, **cam)
        assert np.array_equal(a, b) and len(a) > 0
    tri = lasso_select(g, polygon=rect[:3], facing="all", **cam)
    assert 0 < len(tri) < len(lasso_select(g, polygon=rect, facing="all", **cam))


def test_warm_up_stops_between_structures_once_cancelled(box_on_plane: sel.ScanGeometry) -> None:
    """Ctrl+C on a big scan waited for the whole warm-up (60 s). A cancelled warm-up builds
    nothing more; an uncancelled one builds everything and clears its ray-casting flag."""
    import threading

    geom = sel.ScanGeometry(box_on_plane.points, box_on_plane.normals, faces=box_on_plane.faces)
    cancel = threading.Event()
    cancel.set()
    geom.warm_up(cancel)
    assert geom._tree is None and geom._adj is None and geom._raycaster is None
    built: list[str] = []

    class Spy(sel.ScanGeometry):
        @property
        def spacing(self) -> float:  # cancel arrives while the second structure is built
            built.append("spacing")
            cancel.set()
            return 0.01

    spy = Spy(box_on_plane.points, box_on_plane.normals, faces=box_on_plane.faces)
    cancel.clear()
    spy.warm_up(cancel)
    assert built == ["spacing"] and spy._tree is not None and spy._adj is None and spy._raycaster is None
    geom.warm_up(threading.Event())
    assert geom._raycaster is not None and not geom.building_raycaster.is_set()


def test_warm_up_reports_its_stages_and_picks_wait_for_no_ray_caster(box_on_plane: sel.ScanGeometry) -> None:
    """on a big scan the tools were ready 8 s after the scan showed, and a click meanwhile waited
    without a word. The warm-up names each structure as it starts (the panel shows it), and while the ray caster
    is being built a pick uses the vertices at once: the same vertex as the exact cast, no ray caster built."""
    import threading

    geom = sel.ScanGeometry(box_on_plane.points, box_on_plane.normals, faces=box_on_plane.faces)
    stages: list[tuple[str, int, int]] = []
    geom.warm_up(threading.Event(), on_stage=lambda *a: stages.append(a))
    assert stages == [("search tree", 0, 4), ("point spacing", 1, 4), ("neighbour graph", 2, 4),
                      ("ray caster", 3, 4), ("", 4, 4)]
    origin = np.array([0.01, 0.013, 1.0])
    direction = np.array([0.0, 0.0, -1.0])
    exact = sel.pick(geom, origin, direction)
    for flag in ("warming", "building_raycaster"):  # any warm-up stage, the ray caster's included
        building = sel.ScanGeometry(box_on_plane.points, box_on_plane.normals, faces=box_on_plane.faces)
        getattr(building, flag).set()  # as while the warm-up thread runs
        meanwhile = sel.pick(building, origin, direction)
        assert building._raycaster is None, "the pick built (waited for) the ray caster"
        assert exact is not None and meanwhile is not None
        assert np.linalg.norm(box_on_plane.points[meanwhile[0]] - exact[1]) <= 2.5 * geom.spacing
    assert not geom.warming.is_set() and geom.raycaster_ready  # the warm-up ended: exact picks again
    cloud = sel.ScanGeometry(box_on_plane.points, box_on_plane.normals)
    assert [s[0] for s in cloud.warm_up_stages()] == ["s", "p", "n"]  # no ray caster for point clouds


def _plate_over_table(spacing: float, *, jitter: float = 0.0) -> tuple[sel.ScanGeometry, np.ndarray]:
    """A point-cloud table (z = 0) with a 12 cm plate floating 10 cm above its centre; True marks the plate."""
    rng = np.random.default_rng(1)
    g1 = np.arange(-0.3, 0.3, spacing)
    tx, ty = np.meshgrid(g1, g1)
    table = np.stack([tx.ravel(), ty.ravel(), np.zeros(tx.size)], axis=1)
    g2 = np.arange(-0.06, 0.06, spacing)
    px, py = np.meshgrid(g2, g2)
    plate = np.stack([px.ravel(), py.ravel(), np.full(px.size, 0.10)], axis=1)
    pts = np.concatenate([table, plate]) + rng.normal(scale=jitter, size=(len(table) + len(plate), 3))
    nrm = np.tile(np.array([[0, 0, 1.0]]), (len(pts), 1))
    is_plate = np.r_[np.zeros(len(table), bool), np.ones(len(plate), bool)]
    return sel.ScanGeometry(pts.astype(np.float32), nrm.astype(np.float32)), is_plate


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0, 60.0])
def test_lasso_and_box_take_only_what_the_camera_sees(tilt_deg: float) -> None:
    """a lasso around an object took the table hidden behind it ("front" keeps whatever faces
    the camera). "visible" (the default) takes the plate and the table around it, never the table in its shadow;
    the reference is exact: a table point is hidden when the ray from the camera to it crosses the plate."""
    from efem_viz.geometry.transforms import rotation_to_quat_wxyz

    g, is_plate = _plate_over_table(0.003, jitter=0.0005)
    t = np.deg2rad(tilt_deg)
    position = np.array([0.0, -0.8 * np.sin(t), 0.8 * np.cos(t)])  # 80 cm from the table centre, tilted about x
    fwd = -position / np.linalg.norm(position)
    right = np.array([1.0, 0.0, 0.0])
    down = np.cross(fwd, right)
    wxyz = rotation_to_quat_wxyz(np.stack([right, down, fwd], axis=1))
    cam = dict(position=position, wxyz=wxyz, fov=np.deg2rad(60), aspect=1.0)
    uv, _ = sel.project(g.points[is_plate], **cam)
    lo, hi = uv.min(axis=0) - 0.03, uv.max(axis=0) + 0.03
    rect = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    # exact shadow: where the ray camera -> table point crosses z = 0.10, inside the plate's square
    pts = g.points.astype(np.float64)
    s = (position[2] - 0.10) / (position[2] - pts[:, 2])
    cross = position + s[:, None] * (pts - position)
    shadow = ~is_plate & (np.abs(cross[:, 0]) < 0.06) & (np.abs(cross[:, 1]) < 0.06)
    front = sel.lasso_select(g, polygon=rect, facing="front", **cam)
    vis = sel.lasso_select(g, polygon=rect, facing="visible", **cam)
    box = sel.box_select(g, screen_min=tuple(lo), screen_max=tuple(hi), **cam)  # default: visible
    assert np.array_equal(vis, box)
    assert shadow[front].sum() > 1000, "the old rule takes the hidden table"
    # near the plate's edge a point may sit within one grid cell of the shadow: allow that rim only
    deep = shadow & (np.abs(cross[:, 0]) < 0.06 - 0.01) & (np.abs(cross[:, 1]) < 0.06 - 0.01)
    assert deep[vis].sum() == 0
    assert shadow[vis].sum() <= 0.05 * shadow.sum()
    assert is_plate[vis].sum() == is_plate.sum(), "every plate point is seen"
    # the table around the plate, in view: all of it beyond one grid cell of the plate's outline is taken
    ring = np.setdiff1d(front, np.flatnonzero(shadow | is_plate))
    clear = ring[np.maximum(np.abs(cross[ring, 0]), np.abs(cross[ring, 1])) > 0.06 + 0.01]
    assert len(clear) > 300 and np.isin(clear, vis).all()
    assert np.isin(ring, vis).mean() >= 0.85


def test_pick_by_points_in_pieces_is_the_pick_in_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """A pick by the points goes through big scans in pieces (bounded memory): the same vertex as one pass over all
    points, ties included (the lower index)."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.2, 0.2, (5000, 3)).astype(np.float32)
    pts[4000] = pts[1000]  # a tie: the first one wins
    geom = sel.ScanGeometry(pts, np.tile(np.float32([0, 0, 1]), (5000, 1)))
    rays = [(pts[i] + np.float32([0, 0, 1.0]), np.array([0.0, 0.0, -1.0])) for i in (1000, 7, 2500, 4999)]
    whole = [sel.pick(geom, o, d) for o, d in rays]
    monkeypatch.setattr(sel, "PICK_CHUNK", 333)
    pieces = [sel.pick(geom, o, d) for o, d in rays]
    assert [w[0] for w in whole] == [p[0] for p in pieces]  # type: ignore[index]
    assert whole[0][0] != 4000  # type: ignore[index]
