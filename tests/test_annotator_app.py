"""App-level tests: build the viser app (port 0, no browser) and drive its callbacks and event handlers."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from viser import SceneClickEvent

from annotator import selection as sel
from annotator.app import TOOLS, AnnotatorApp
from annotator.tools import DEFAULT_TOOLS, Control, Hit, Tool, check_tools
from annotator.io import LabelIOError, load_labels
from efem_viz.data.io import RESULT_SUFFIX, load_scene, save_scene
from efem_viz.serve.inputs import ClientValueError
from efem_viz.data.scene import Scene


@pytest.fixture()
def mesh_path(tmp_path: Path) -> Path:
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.1)  # 2562 vertices
    p = tmp_path / "scans" / "ball.ply"
    p.parent.mkdir()
    m.export(p)
    return p


@pytest.fixture()
def app(mesh_path: Path, tmp_path: Path):
    a = AnnotatorApp(mesh_path, out_dir=tmp_path / "out", port=0, autosave_delay=0, chunk_size=300)
    yield a
    a.close()


def _client(pos=(0.0, 0.0, 1.0), wxyz=(0.0, 1.0, 0.0, 0.0)) -> SimpleNamespace:
    cam = SimpleNamespace(position=np.array(pos), wxyz=np.array(wxyz), fov=np.deg2rad(50), aspect=1.0)
    return SimpleNamespace(camera=cam)


def _drag(phase: str, start, end, client_id: int = 7) -> SimpleNamespace:
    return SimpleNamespace(phase=phase, client_id=client_id, client=_client(), start_position=tuple(start),
                           end_position=tuple(end), modifier="cmd/ctrl")


def test_open_builds_chunks_and_panel(app: AnnotatorApp) -> None:
    assert app.session.scan.n == 2562 and app.view.chunks.count >= 9
    assert app.url.startswith("http://127.0.0.1:")
    assert len(app.view.chunk_handles) == app.view.chunks.count
    assert "0.0%" in app.panels.gui_table.content


def test_drag_stroke_paints_only_touched_chunks_and_undoes_as_one(app: AnnotatorApp) -> None:
    iid = app.session.instances.new_instance(category="mug")
    app.session.toolbox.settings.radius = 0.015
    sent0 = app.view.stats.bytes_sent
    app.handle_event("drag", _drag("start", (0, 0, 0.1), (0, 0, 0.1)))
    for x in (0.01, 0.02, 0.03):
        app.handle_event("drag", _drag("update", (0, 0, 0.1), (x, 0.0, 0.5)))
    app.handle_event("drag", _drag("end", (0, 0, 0.1), (0.04, 0.0, 0.5)))
    lab = app.session.scan.store.labels
    painted = np.flatnonzero(lab == iid)
    assert len(painted) > 20
    pts = app.session.scan.scene.points[painted]
    assert pts[:, 2].min() > 0.045 and pts[:, 0].max() > 0.05  # along the stroke over the top of the ball
    sent = app.view.stats.bytes_sent - sent0
    assert 0 < sent < 3 * app.session.scan.n  # partial update: fewer bytes than resending every colour
    # the history panel counts what Ctrl+Z undoes: the new instance and the stroke, not 1 + 5 dabs
    assert app.panels.gui_history.content.startswith("2 undoable, 0 redoable")
    assert len(app.session.instances.undo()) == 5  # start + 3 updates + end undo together
    assert app.panels.gui_history.content.startswith("1 undoable, 1 redoable")
    assert (app.session.scan.store.labels == iid).sum() == 0


def test_a_scan_over_the_display_budget_is_drawn_from_a_subset_and_labelled_in_full(mesh_path: Path,
                                                                                   tmp_path: Path) -> None:
    """Level of detail: 2562 vertices over a budget of 700 draw 700 points (no mesh sent), a stroke labels hidden
    vertices too, and an edit resends the colours of drawn points only."""
    a = AnnotatorApp(mesh_path, out_dir=tmp_path / "out", port=0, autosave_delay=0, chunk_size=100,
                     display_points=700)
    try:
        v = a.view
        assert v.reduced and len(v.display) == 700 and len(np.unique(v.display)) == 700
        drawn = np.concatenate([v.chunks.members(c) for c in range(v.chunks.count)])
        assert np.array_equal(np.sort(drawn), v.display)
        assert sum(len(h.points) for h in v.chunk_handles) == 700
        assert v.surface.opacity == 0.0 and len(v.surface.vertices) == 3 * 700  # an invisible splat proxy
        hidden = np.setdiff1d(np.arange(a.session.scan.n), v.display)
        assert (v.chunks.chunk_of[hidden] == -1).all() and len(v.chunks.touched(hidden)) == 0
        iid = a.session.instances.new_instance(category="mug")
        a.session.toolbox.settings.radius = 0.02
        sent0 = v.stats.bytes_sent
        a.handle_event("drag", _drag("start", (0, 0, 0.1), (0, 0, 0.1)))
        a.handle_event("drag", _drag("end", (0, 0, 0.1), (0.02, 0.0, 0.5)))
        painted = np.flatnonzero(a.session.scan.store.labels == iid)
        assert np.isin(painted, hidden).sum() > 10  # every vertex under the brush, drawn or not
        touched = v.chunks.touched(painted)
        # two edits (start, end), each resending the colours of the drawn points of the chunks it touched
        assert 0 < v.stats.bytes_sent - sent0 <= 2 * 3 * sum(len(v.chunks.members(c)) for c in touched) < 2 * 3 * 700
        col = v.chunk_handles[int(touched[0])].colors
        shown = np.isin(v.chunks.members(int(touched[0])), painted)
        assert shown.any() and not np.array_equal(
            col[shown][0], a.session.scan.scene.colors[v.chunks.members(int(touched[0]))][shown][0]
        )  # the drawn painted points show the instance colour
    finally:
        a.close()
    with pytest.raises(ValueError, match="at least 1"):
        AnnotatorApp(mesh_path, out_dir=tmp_path / "out2", port=0, display_points=0)
    assert not (tmp_path / "out2").exists()  # refused before anything was written


def test_queued_events_are_processed_in_order(app: AnnotatorApp) -> None:
    iid = app.session.instances.new_instance()
    app._edits.put(("drag", _drag("start", (0, 0, 0.1), (0, 0, 0.1))))
    for x in np.linspace(0.0, 0.05, 8):
        app._edits.put(("drag", _drag("update", (0, 0, 0.1), (x, 0.0, 0.5))))
    app._edits.put(("drag", _drag("end", (0, 0, 0.1), (0.05, 0.0, 0.5))))
    app.wait_idle()
    assert (app.session.scan.store.labels == iid).sum() > 20
    assert not app.session.painting.strokes


def test_click_tools_grow_fill_pick_erase(app: AnnotatorApp) -> None:
    a = app.session.instances.new_instance()
    app.set_tool("grow")
    app.session.toolbox.settings.grow_angle_deg = 60
    app.session.toolbox.settings.grow_distance = 0.05
    v = app.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert v is not None
    grown = np.flatnonzero(app.session.scan.store.labels == a)
    assert len(grown) > 50
    assert (np.linalg.norm(app.session.scan.scene.points[grown] - app.session.scan.scene.points[v], axis=1).max()
            <= 0.05 + 1e-6)
    b = app.session.instances.new_instance()
    app.set_tool("fill")
    # fill the connected region of `a` with `b`
    app.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert ((app.session.scan.store.labels == a).sum() == 0
            and (app.session.scan.store.labels == b).sum() == len(grown))
    app.set_tool("pick")
    app.session.instances.set_active(a)
    app.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert app.session.toolbox.settings.active_id == b
    app.set_tool("erase")
    app.session.toolbox.settings.radius = 0.5
    app.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert (app.session.scan.store.labels > 0).sum() == 0
    assert app.session.painting.click(np.array([5.0, 5, 5]), np.array([1.0, 0, 0])) is None  # a miss changes nothing


def test_the_home_view_fills_the_view_with_the_scan(app: AnnotatorApp) -> None:
    """Where every client starts and where R returns: the scan fills most of the view planned for (it filled a
    third of it), and none of it is cut off."""
    from annotator.selection import project
    from efem_viz.geometry.transforms import rotation_to_quat_wxyz
    from efem_viz.serve.camera import FIT_ASPECT, VISER_FOV

    home = app.view.home_view
    forward = np.subtract(home.look_at, home.position)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, home.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    wxyz = rotation_to_quat_wxyz(np.stack([right, down, forward], axis=1))
    uv, z = project(app.session.scan.scene.points, position=np.asarray(home.position), wxyz=wxyz, fov=VISER_FOV,
                    aspect=FIT_ASPECT)
    assert (z > 0).all() and (uv >= 0.0).all() and (uv <= 1.0).all()  # all of it in front, in the view
    span = uv.max(axis=0) - uv.min(axis=0)
    assert span.max() > 0.7, f"the scan spans {span} of the view"


def test_rect_select_uses_client_camera(app: AnnotatorApp) -> None:
    iid = app.session.instances.new_instance()
    ev = SimpleNamespace(client_id=3, client=_client(), screen_min=(0.45, 0.45), screen_max=(0.55, 0.55))
    app.handle_event("rect", ev)
    sel = np.flatnonzero(app.session.scan.store.labels == iid)
    assert len(sel) > 0
    assert app.session.scan.scene.points[sel, 2].min() > 0.0  # front-facing only: the top half seen from above
    assert np.abs(app.session.scan.scene.points[sel, :2]).max() < 0.06


def test_instance_panel_through_gui_handles(app: AnnotatorApp) -> None:
    a = app.session.instances.new_instance(category="mug")
    app.session.painting.paint(np.arange(0, 100))
    app.panels.gui_name.value = "left mug"  # programmatic update runs the same callback as a client edit
    app.panels.gui_category.value = "cup"
    app.panels.gui_color.value = (1, 2, 3)
    info = app.session.scan.store.labelset.info(a)
    assert (info.name, info.category, info.color) == ("left mug", "cup", (1, 2, 3))
    c0 = app.view.chunks.chunk_of[0]
    m = app.view.chunks.members(c0)
    first = int(np.flatnonzero(m == 0)[0])
    app.panels.gui_visible.value = False  # hidden: drawn in scan colour
    assert tuple(app.view.chunk_handles[c0].colors[first]) == tuple(app.session.scan.scene.colors[0])
    app.panels.gui_visible.value = True
    app.panels.gui_locked.value = True
    with pytest.raises(ValueError, match="locked"):
        app.session.painting.paint(np.arange(0, 10))
    app.panels.gui_locked.value = False
    b = app.session.instances.new_instance()
    app.session.painting.paint(np.arange(200, 250))
    app.session.instances.merge([b], a)
    assert app.session.scan.store.labelset.counts() == {a: 150}
    app.session.instances.delete_instance(a)
    assert (app.session.scan.store.labels > 0).sum() == 0
    app.session.instances.undo()
    assert app.session.scan.store.labelset.counts() == {a: 150}
    assert "150" in app.panels.gui_table.content and "left mug" in app.panels.gui_table.content


def test_two_clients_concurrent_edits_are_all_kept(app: AnnotatorApp) -> None:
    a = app.session.instances.new_instance()
    b = app.session.instances.new_instance()
    errors: list[BaseException] = []

    def worker(iid: int, start: int) -> None:
        try:
            for k in range(40):
                idx = np.arange(start + 10 * k, start + 10 * k + 10)
                app.session.scan.store.do(lambda ls, idx=idx, iid=iid: ls.paint(idx, iid), client=f"c{iid}")
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    ts = [threading.Thread(target=worker, args=(a, 0)), threading.Thread(target=worker, args=(b, 1000))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errors
    assert app.session.scan.store.labelset.counts() == {a: 400, b: 400}
    kinds = [r.kind for r in app.session.scan.store.journal.records]
    assert kinds.count("do") == 2 + 80


def test_restart_resumes_labels_and_undo(mesh_path: Path, tmp_path: Path) -> None:
    a1 = AnnotatorApp(mesh_path, out_dir=tmp_path / "o", port=0, autosave_delay=0)
    iid = a1.session.instances.new_instance(category="mug")
    a1.session.painting.paint(np.arange(0, 300))
    a1.session.painting.paint(np.arange(300, 400))
    a1.close()
    a2 = AnnotatorApp(mesh_path, out_dir=tmp_path / "o", port=0, autosave_delay=0)
    try:
        assert (a2.session.scan.store.labels == iid).sum() == 400 and a2.session.toolbox.settings.active_id == iid
        a2.session.instances.undo()
        assert (a2.session.scan.store.labels == iid).sum() == 300
    finally:
        a2.close()


def test_exports_round_trip_and_never_touch_the_scan(app: AnnotatorApp, mesh_path: Path) -> None:
    before = mesh_path.read_bytes()
    app.session.instances.new_instance(category="mug")
    app.session.painting.paint(np.arange(50, 500))
    ply, = app.session.files.export("ply")
    npz, = app.session.files.export("npz")
    segs, agg = app.session.files.export("scannet")
    for p in (ply, npz, agg):
        assert np.array_equal(load_labels(p, app.session.scan.n).labels, app.session.scan.store.labels)
    assert load_scene(ply).instance is not None
    assert mesh_path.read_bytes() == before
    with pytest.raises(LabelIOError):
        app.session.files.export("ply", directory="../../..")


def test_gui_import_refuses_traversal_and_bad_files_server_stays_up(app: AnnotatorApp, tmp_path: Path) -> None:
    app.session.instances.new_instance()
    app.session.painting.paint(np.arange(10))
    state = app.session.scan.store.labels.copy()
    app.panels.gui_import_path.value = "../../../../etc/passwd"
    app.panels.gui_import.value = True  # a button "click" from Python: runs the callback; refusal is a notification
    assert np.array_equal(app.session.scan.store.labels, state)
    bad = tmp_path / "out" / "short.npz"
    np.savez(bad, instance=np.zeros(7, np.int32))
    with pytest.raises(LabelIOError, match="7"):
        app.session.files.import_labels(str(bad))
    assert app.run_reporting(lambda: app.session.files.import_labels(str(bad))) is None
    assert np.array_equal(app.session.scan.store.labels, state)
    good = tmp_path / "out" / "good.npz"
    lab = np.zeros(app.session.scan.n, np.int32)
    lab[100:120] = 5
    np.savez(good, instance=lab)
    app.session.files.import_labels(str(good))
    assert (app.session.scan.store.labels == 5).sum() == 20
    app.session.instances.undo()
    assert np.array_equal(app.session.scan.store.labels, state)
    assert app.server.get_port() > 0


def test_point_cloud_scan_and_prelabels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # the default output folder is the working directory
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    scan = tmp_path / "pc.ply"
    save_scene(Scene.create("pc", (0.1 * p).astype(np.float32), normals=p.astype(np.float32)), scan)
    a = AnnotatorApp(scan, port=0, autosave_delay=0)
    try:
        assert not a.session.scan.scene.is_mesh
        iid = a.session.instances.new_instance()
        a.session.toolbox.settings.radius = 0.02
        a.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
        assert (a.session.scan.store.labels == iid).sum() > 5
        from annotator.io import LabelData
        from annotator.labels import InstanceInfo

        pre = np.zeros(a.session.scan.n, np.int32)
        pre[a.session.scan.scene.points[:, 0] > 0.05] = 1
        pre[a.session.scan.scene.points[:, 0] < -0.05] = 2
        ids = a.session.assist.add_prelabels(LabelData(pre, [InstanceInfo(1, "x", "mug"), InstanceInfo(2, "y", "mug")],
                                        {1: 0.9, 2: 0.4}), source="test.efem.npz")
        assert len(ids) == 2
        assert all("unreviewed" in a.session.scan.store.labelset.info(i).note for i in ids)
        a.session.assist.review_prelabel(ids[0], "accept")
        assert "accepted" in a.session.scan.store.labelset.info(ids[0]).note
        a.session.assist.review_prelabel(ids[1], "reject")
        assert ids[1] not in a.session.scan.store.labelset.instances
        a.session.instances.undo()
        a.session.instances.set_active(iid)
        a.session.assist.review_prelabel(ids[1], "merge")
        assert (ids[1] not in a.session.scan.store.labelset.instances
                and (a.session.scan.store.labels == iid).sum() > 100)
    finally:
        a.close()
    assert (tmp_path / "pc.annotate" / "pc.journal").exists()


def test_bad_startup_inputs(tmp_path: Path, mesh_path: Path) -> None:
    from annotator.__main__ import main

    (tmp_path / "empty.ply").write_bytes(b"")
    assert main([str(tmp_path / "empty.ply"), "--port", "0"]) == 1
    short = tmp_path / "short.npz"
    np.savez(short, instance=np.zeros(3, np.int32))
    assert main([str(mesh_path), "--labels", str(short), "--port", "0", "--out", str(tmp_path / "o2")]) == 1
    assert not (tmp_path / "o2" / "ball.annotate" / "ball.journal").exists()


@pytest.fixture(scope="module")
def spheres(tmp_path_factory: pytest.TempPathFactory):
    """A sphere tabletop scene with a saved EFEM result from the real solver and the analytic sphere prior."""
    import torch

    from efem_viz import em
    from efem_viz.prior import analytic

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("spheres")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    save_scene(scene, d / "spheres.ply")
    prior = analytic.make_sphere_prior()
    result = em.run_em(scene, prior, em.preset("fast").with_proposals(16).replace(elimination={"min_size": 30}), seed=0)
    result.save(d / "spheres.efem.npz")
    return d, scene, prior


def _last_step(app: AnnotatorApp) -> str:
    """The newest line of the edit history panel (what the next undo takes back)."""
    from annotator.panel_views import recent_steps

    with app.session.scan.store.lock:
        steps = recent_steps(app.session.scan.store.labelset.undo_stack, 1)
    return steps[0] if steps else ""


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(1, int((a | b).sum()))


def test_the_prelabel_cut_opens_where_accept_all_accepts_the_best(spheres) -> None:
    """(annotator): with every pre-label under the cut, "Accept all ≥ cut" accepted nothing. After
    an import (a button click), the cut is at most the best unreviewed pre-label's confidence."""
    d, _, _ = spheres
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_cut", port=0, autosave_delay=0)
    try:
        a.session.scan.store.do(lambda ls: ls.replace_all(np.zeros(a.session.scan.n, np.int32), []))
        a.panels.gui_prelabel_cut.value = 0.99
        a.panels.gui_efem_path.value = "spheres.efem.npz"
        a.panels.gui_efem_import.value = True  # the click
        table = a.session.scan.store.labelset.instances
        best = max(float(table[k].confidence) for k in table)
        assert a.panels.gui_prelabel_cut.value <= best
        a.panels.gui_accept_above.value = True
        assert any("accepted" in a.session.scan.store.labelset.info(k).note
                   for k in a.session.scan.store.labelset.instances)
        assert a.session.assist.prelabel_cut() == 0.5  # nothing left to review: the usual default
    finally:
        a.close()


def test_efem_prelabels_import_and_review(spheres) -> None:
    d, scene, _ = spheres
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_import", port=0, autosave_delay=0)
    try:
        # start unlabelled (file has GT)
        a.session.scan.store.do(lambda ls: ls.replace_all(np.zeros(a.session.scan.n, np.int32), []))
        ids = a.session.assist.import_efem("spheres.efem.npz")
        assert ids, "EFEM found no sphere"
        gt = scene.instance
        best = [max(_iou(a.session.scan.store.labels == i, gt == g) for g in scene.instance_ids()) for i in ids]
        assert max(best) > 0.5
        assert a.panels.gui_prelabel.options[0] != "(none)"
        a.session.assist.review_prelabel(ids[0], "accept")
        assert "accepted" in a.session.scan.store.labelset.info(ids[0]).note
        with pytest.raises(LabelIOError):
            a.session.assist.import_efem("spheres.ply")  # not an EFEM result
    finally:
        a.close()


def test_click_to_segment_previews_then_accepts(spheres) -> None:
    from annotator.efem_runs import segment_at_point
    from efem_viz.em.config import SolveSettings

    d, scene, prior = spheres
    g = int(scene.instance_ids()[0])
    members = np.flatnonzero(scene.instance == g)
    top = int(members[np.argmax(scene.points[members, 2])])
    idx = segment_at_point(scene, top, prior=prior, settings=SolveSettings(preset="fast"), n_proposals=8,
                           crop_radius=0.1, elimination={"min_size": 30})
    assert _iou(np.isin(np.arange(scene.num_points), idx), scene.instance == g) > 0.5
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_seg", port=0, autosave_delay=0)
    try:
        before = a.session.scan.store.labels.copy()
        a.session.assist.set_preview(idx)
        assert np.array_equal(a.session.scan.store.labels, before)  # a preview is not an edit
        assert not a.panels.gui_seg_accept.disabled
        a.session.assist.accept_segment()
        new = a.session.toolbox.settings.active_id
        assert a.session.scan.store.labelset.info(new).category == a.panels.gui_prior.value  # the prior's category
        assert set(np.flatnonzero(a.session.scan.store.labels == new)) <= set(idx.tolist())
        assert a.session.assist.pending_segment is None and a.panels.gui_seg_accept.disabled
        with pytest.raises(ValueError, match="no segment preview"):
            a.session.assist.accept_segment()
    finally:
        a.close()


@pytest.mark.parametrize("name", ["/etc/passwd", "../../weights/mug", "mug.pt", "x; rm", ""])
def test_prior_names_from_the_gui_are_never_paths(name: str) -> None:
    from annotator.efem_runs import get_prior

    with pytest.raises(ValueError, match="unknown shape prior"):
        get_prior(name)


def test_read_only_output_folder_is_refused(tmp_path: Path, mesh_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(LabelIOError, match="read-only"):
            AnnotatorApp(mesh_path, out_dir=ro, port=0)
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def _click(uv: tuple[float, float], client: SimpleNamespace, client_id: int = 7) -> SceneClickEvent:
    """A Ctrl+click as viser delivers it to `scene.on_click` callbacks: its own event type, one (u, v) pair."""
    return SceneClickEvent(client=client, client_id=client_id, ray_origin=(0.0, 0.0, 1.0),  # type: ignore[arg-type]
                           ray_direction=(0.0, 0.0, -1.0), screen_pos=uv, modifier="cmd/ctrl")


def test_lasso_tool_outline_by_clicks_then_apply(app: AnnotatorApp) -> None:
    """Lasso: Ctrl+clicks add screen points with the client camera, Apply paints the inside, one undo step."""
    app.session.instances.new_instance(category="mug")
    app.set_tool("lasso")
    client = _client()  # looking straight down at the ball from z = 1
    outline = [(0.45, 0.45), (0.55, 0.45), (0.55, 0.55), (0.45, 0.55)]
    for uv in outline:
        app.handle_event("click", _click(uv, client))
    assert app.session.box_lasso.lasso_outline.points == outline
    assert app.session.scan.store.labelset.count(app.session.toolbox.settings.active_id) == 0, (
        "clicks only draw the outline")
    assert not app.panels.gui_tool_buttons["lasso_apply"].disabled
    app.session.box_lasso.apply_lasso()
    idx = sel.lasso_select(app.session.scan.geom, position=client.camera.position, wxyz=client.camera.wxyz,
                           fov=float(client.camera.fov), aspect=1.0, polygon=np.array(outline))
    n = app.session.scan.store.labelset.count(app.session.toolbox.settings.active_id)
    assert n == len(idx) > 20
    assert app.panels.gui_tool_buttons["lasso_apply"].disabled and not app.session.box_lasso.lasso_outline.points
    with pytest.raises(ValueError, match="at least 3"):
        app.session.box_lasso.apply_lasso()
    app.session.instances.undo()
    assert app.session.scan.store.labelset.count(app.session.toolbox.settings.active_id) == 0


def test_lasso_takes_the_legacy_pointer_shape_and_refuses_bad_screen_positions(app: AnnotatorApp) -> None:
    """The legacy `ScenePointerEvent` shape ((u, v),) adds a point too; a position no click has is refused."""
    from efem_viz.serve.inputs import ClientValueError

    app.set_tool("lasso")
    legacy = SimpleNamespace(client_id=7, client=_client(), ray_origin=(0.0, 0.0, 1.0), ray_direction=(0.0, 0.0, -1.0),
                             screen_pos=((0.4, 0.6),))
    app.handle_event("click", legacy)
    assert app.session.box_lasso.lasso_outline.points == [(0.4, 0.6)]
    for bad in (0.5, ((0.1, 0.1), (0.9, 0.9)), (float("nan"), 0.5)):
        with pytest.raises(ClientValueError):
            app.handle_event("click", SimpleNamespace(**{**vars(legacy), "screen_pos": bad}))
    assert len(app.session.box_lasso.lasso_outline) == 1


def test_a_failing_tool_tells_the_user(mesh_path: Path, tmp_path: Path) -> None:
    """A bug in a tool's click (any exception) reaches the clicking client as an "Error" notification, and the
    edit thread keeps working: the next click of another tool still paints."""

    def broken(host: AnnotatorApp, event: object) -> None:
        raise TypeError("'float' object is not iterable")

    tools = (*DEFAULT_TOOLS, Tool("broken", "Broken", "K", "raises", on_click=broken))
    a = AnnotatorApp(mesh_path, out_dir=tmp_path / "o", port=0, autosave_delay=0, tools=tools)
    notes: list[tuple[str, str, object]] = []
    a.notify = lambda title, body, *, client=None, color=None: (  # type: ignore[method-assign]
        notes.append((title, body, client)))
    try:
        a.set_tool("broken")
        client = _client()
        a._on_scene_click(_click((0.5, 0.5), client))  # as viser calls it: queued for the edit thread
        a.wait_idle()
        assert [(t, c) for t, _, c in notes] == [("Error", client)]
        assert "TypeError" in notes[0][1] and "not iterable" in notes[0][1]
        iid = a.session.instances.new_instance()
        a.set_tool("brush")
        a._on_scene_click(_click((0.5, 0.5), client))
        a.wait_idle()
        assert int((a.session.scan.store.labels == iid).sum()) > 0
    finally:
        a.close()


def test_no_hotkey_flies_the_camera() -> None:
    """No key of the tools, their commands or the app is one that viser's browser client binds to camera motion
    (W/A/S/D/Q/E: pressing erase's E or segment's S also flew the camera, after a pause tens of metres), and a
    tool table that takes one is refused."""
    from annotator.tools import APP_KEYS
    from efem_viz.serve.camera import VISER_CAMERA_KEYS

    keys = [t.hotkey for t in DEFAULT_TOOLS] + [c.hotkey for t in DEFAULT_TOOLS for c in t.commands if c.hotkey]
    keys += [key for k in APP_KEYS for key, _ in k.bindings]
    assert not {k.upper() for k in keys} & set(VISER_CAMERA_KEYS), keys
    assert {t.name: t.hotkey for t in DEFAULT_TOOLS}["erase"] == "X"
    assert {t.name: t.hotkey for t in DEFAULT_TOOLS}["segment"] == "C"
    for key in ("w", "E", "s"):
        with pytest.raises(ValueError, match="viser's camera"):
            check_tools((Tool("k", "K", key, "a camera key"),))


def test_a_click_that_misses_the_scan_says_so(app: AnnotatorApp) -> None:
    """A Ctrl/Cmd+click whose ray misses the scan (a camera thrown off the scan) tells the clicking user, with how
    to get the scan back (R), instead of doing nothing silently; R (`reset_view`) puts that client's camera on the
    fitted view."""
    notes: list[tuple[str, str, object]] = []
    app.notify = lambda title, body, *, client=None, color=None: (  # type: ignore[method-assign]
        notes.append((title, body, client)))
    client = _client()
    for tool in ("segment", "brush"):
        app.set_tool(tool)
        miss = SimpleNamespace(ray_origin=(0.0, 5.0, 1.0), ray_direction=(0.0, 0.0, 1.0), screen_pos=((0.1, 0.1),),
                               client=client, client_id=3)
        app.handle_event("click", miss)
        assert notes and notes[-1][0] == "Missed the scan" and notes[-1][2] is client, notes
        assert "R (reset view)" in notes[-1][1]
    n = len(notes)
    app.session.instances.new_instance()
    hit = SimpleNamespace(ray_origin=(0.0, 0.0, 1.0), ray_direction=(0.0, 0.0, -1.0), screen_pos=((0.5, 0.5),),
                          client=client, client_id=3)
    app.handle_event("click", hit)
    assert len(notes) == n  # a hit says nothing
    placed: list[object] = []
    app.view.camera_guard.reset = lambda c=None: placed.append(c)  # type: ignore[method-assign]
    app.reset_view(client)  # type: ignore[arg-type]
    assert placed == [client]


def test_instance_table_shows_colours_and_escapes_names(app: AnnotatorApp) -> None:
    """The instance table and the per-category line show each instance's colour (which colour is which), and a
    name from a label file cannot inject HTML or break the table (viser renders raw HTML in markdown)."""
    iid = app.session.instances.new_instance(category="bowl", name="<img src=x onerror=alert(1)>|two")
    app.session.instances.update_instance(iid, color=(255, 0, 16))
    content = app.panels.gui_table.content
    assert f"| {iid} " in content and '<span style="color:#ff0010">■</span>' in content
    assert "<img" not in content and "&lt;img src=x onerror=alert(1)&gt;\\|two" in content
    assert '■</span> bowl: 1 (' in content


def test_new_instances_take_the_category_chosen_last(app: AnnotatorApp) -> None:
    """N makes an "object" until the user chooses a category (not "mug N", category mug); a category typed into
    the panel renames the active instance's category and is what the next N takes."""
    # what N and the New instance button do
    first = app.session.instances.new_instance(category=app.session.toolbox.settings.category)
    assert app.session.scan.store.labelset.info(first).category == "object"
    for typed in ("b", "bo", "bow", "bowl"):  # the user types a category for the active instance, key by key
        app.panels.gui_category.value = typed
    assert app.session.scan.store.labelset.info(first).category == "object", "typing is not an edit yet"
    assert app.session.instances.fields_typing() == {"category"}
    app.panels.gui_new.value = True  # the New instance button: doing anything else commits what was typed, once
    assert (app.session.scan.store.labelset.info(first).category == "bowl"
            and app.session.toolbox.settings.category == "bowl")
    second = app.session.toolbox.settings.active_id
    assert second != first and app.session.scan.store.labelset.info(second).category == "bowl"
    assert app.panels.gui_category.value == "bowl"
    renames = [r for r in app.session.scan.store.journal.records if r.kind == "do" and "category" in r.header["label"]]
    assert len(renames) == 1, "four keystrokes, one edit"


def test_painting_over_other_instances_says_how_many_were_taken(app: AnnotatorApp) -> None:
    """A paint that relabels another instance's vertices says so in the history (and the journal); with *Only
    unlabelled vertices* nothing is taken and nothing is said."""
    a = app.session.instances.new_instance()
    app.session.painting.paint(np.arange(100))
    app.session.instances.new_instance()
    app.session.painting.paint(np.arange(60, 160))
    assert _last_step(app).endswith(", 40 taken from other instances"), _last_step(app)
    assert int((app.session.scan.store.labels == a).sum()) == 60
    app.session.toolbox.settings.only_unlabelled = True
    app.session.painting.paint(np.arange(0, 200))
    assert "taken" not in _last_step(app) and int((app.session.scan.store.labels == a).sum()) == 60


def test_prelabel_review_by_confidence_in_bulk_and_one_by_one(app: AnnotatorApp) -> None:
    """EFEM pre-labels: the dropdown lists them most confident first with their confidence, the table flags them,
    they are drawn pale until reviewed; Next / Previous select one and fly the camera to it; Accept all ≥ cut and
    Reject all < cut review many in one undo step."""
    from annotator.io import LabelData
    from annotator.labels import InstanceInfo
    from annotator.render import color_lut

    z = app.session.scan.scene.points[:, 2]
    labels = np.select([z > 0.06, z < -0.06, np.abs(z) < 0.02], [1, 2, 3], 0).astype(np.int32)
    rows = [InstanceInfo(i, f"p{i}", category="mug", color=(200, 0, 0)) for i in (1, 2, 3)]
    ids = app.session.assist.add_prelabels(LabelData(labels, rows, confidence={1: 0.9, 2: 0.3, 3: 0.6}),
                                           source="x.efem.npz")
    table = app.session.scan.store.labelset.instances
    conf = {i: table[i].confidence for i in ids}
    assert sorted(conf.values(), reverse=True) == [0.9, 0.6, 0.3]
    opts = list(app.panels.gui_prelabel.options)
    assert [float(o.rsplit("· ", 1)[1]) for o in opts] == [0.9, 0.6, 0.3]
    assert "pre-label 0.90" in app.panels.gui_table.content
    lut, _ = color_lut(table, max(ids))
    own = {i: list(table[i].color) for i in ids}
    assert all(lut[i].tolist() != own[i] and (lut[i] >= np.array(own[i])).all() for i in ids)  # paler

    flown: list[object] = []
    app.view.camera_guard.place = lambda view, client=None: flown.append(view)  # type: ignore[method-assign]
    first = app.step_prelabel(+1)
    assert first == _id_of_option(opts[0]) and str(app.panels.gui_prelabel.value) == opts[0]
    members = app.session.scan.scene.points[app.session.scan.store.labels == first]
    assert np.allclose(flown[-1].look_at, (members.min(0) + members.max(0)) / 2,  # type: ignore[attr-defined]
                       atol=1e-5)
    assert app.step_prelabel(+1) == _id_of_option(opts[1])
    assert app.step_prelabel(-1) == first and app.step_prelabel(-1) == _id_of_option(opts[2])  # wraps around

    sent = app.view.stats.chunks_sent
    accepted = app.session.assist.review_prelabels(0.5, "accept")
    assert sorted(accepted) == sorted(i for i in ids if conf[i] >= 0.5)
    assert all(not app.session.scan.store.labelset.info(i).unreviewed for i in accepted)
    assert app.view.stats.chunks_sent > sent  # redrawn in their full colour
    lut, _ = color_lut(app.session.scan.store.labelset.instances, max(ids))
    assert all(lut[i].tolist() == own[i] for i in accepted)
    assert list(app.panels.gui_prelabel.options) == [opts[2]]
    app.session.instances.undo()  # one step undoes the bulk accept
    assert all(app.session.scan.store.labelset.info(i).unreviewed for i in accepted)
    rejected = app.session.assist.review_prelabels(0.5, "reject")
    assert (rejected == [i for i in ids if conf[i] < 0.5]
            and rejected[0] not in app.session.scan.store.labelset.instances)


def _id_of_option(option: str) -> int:
    return int(option.split(":", 1)[0])


def test_labels_only_view_dims_unlabelled_vertices(app: AnnotatorApp) -> None:
    """*Labels only* draws unlabelled vertices in a faint grey (labelled ones keep their colour), and off again
    restores the scan's colours; the labels do not change."""
    iid = app.session.instances.new_instance()
    app.session.painting.paint(np.arange(50))
    labels = app.session.scan.store.labels.copy()

    def drawn() -> np.ndarray:
        out = np.zeros((app.session.scan.n, 3), np.uint8)
        for c, h in enumerate(app.view.chunk_handles):
            out[app.view.chunks.members(c)] = np.asarray(h.colors)
        return out

    before = drawn()
    app.panels.gui_labels_only.value = True  # as a browser ticks it
    assert app.session.toolbox.settings.labels_only
    on = drawn()
    rest = on[labels == 0]
    assert (rest[:, 0] == rest[:, 1]).all() and (rest[:, 1] == rest[:, 2]).all() and rest.min() >= 180
    assert np.array_equal(on[labels == iid], before[labels == iid])
    app.set_labels_only(False)
    assert np.array_equal(drawn(), before) and np.array_equal(app.session.scan.store.labels, labels)


def test_click_to_segment_progress_cancel_and_enter_esc(app: AnnotatorApp, monkeypatch: pytest.MonkeyPatch) -> None:
    """Click-to-segment shows its progress (EM steps) next to the tools; Esc cancels a run, Enter accepts the
    preview and Esc discards it, both with the segment tool's buttons in the Tools panel (Enter still applies the
    lasso when the lasso is the active tool)."""
    import annotator.efem_runs as efem_runs
    from efem_viz.em.solver import EMCancelled

    seen: list[float] = []
    started = threading.Event()

    def fake(scene: object, vertex: int, *, prior_name: str, on_step: object, cancel: threading.Event,
             **_: object) -> np.ndarray:
        for i in range(4):
            on_step(SimpleNamespace(step=i, num_steps=4))  # type: ignore[operator]
            seen.append(float(app.panels.gui_seg_progress.value))
        started.set()
        if vertex == 0:  # "a long run": until cancelled
            assert cancel.wait(30), "never cancelled"
            raise EMCancelled("cancelled")
        return np.arange(40, dtype=np.int32)

    monkeypatch.setattr(efem_runs, "segment_at_point", fake)
    notes: list[str] = []
    app.notify = lambda title, body, *, client=None, color=None: notes.append(title)  # type: ignore[method-assign]
    app.set_tool("segment")
    buttons = app.panels.gui_tool_buttons
    assert buttons["segment_accept"].visible and not buttons["lasso_apply"].visible
    assert buttons["segment_accept"].disabled and buttons["segment_discard"].disabled

    # a run, cancelled with Esc
    app.segment_at(0)
    assert started.wait(30) and app.session.assist.segmenting and app.panels.gui_seg_progress.visible
    assert not buttons["segment_discard"].disabled
    with pytest.raises(ValueError, match="still segmenting"):
        app.segment_at(5)
    app.run_tool_hotkey("Escape")
    deadline = time.monotonic() + 30
    while app.session.assist.segmenting and time.monotonic() < deadline:
        time.sleep(0.02)
    assert (not app.session.assist.segmenting and not app.panels.gui_seg_progress.visible
            and "Segmenting cancelled" in notes)
    assert app.session.assist.pending_segment is None and buttons["segment_discard"].disabled

    # a run to the end: progress up to 100 %, Enter accepts
    seen.clear()
    assert app.segment_at(3, wait=True) is not None
    assert seen == [25.0, 50.0, 75.0, 100.0] and not app.panels.gui_seg_progress.visible
    assert not buttons["segment_accept"].disabled
    app.set_tool("lasso")
    with pytest.raises(ValueError):
        app.run_tool_hotkey("Enter")  # the lasso's Enter (no outline yet), not the segment's
    assert app.session.assist.pending_segment is not None
    app.set_tool("segment")
    app.run_tool_hotkey("enter")
    new = app.session.toolbox.settings.active_id
    assert (np.array_equal(np.flatnonzero(app.session.scan.store.labels == new), np.arange(40))
            and app.session.assist.pending_segment is None)

    # Esc discards a preview
    app.segment_at(3, wait=True)
    app.run_tool_hotkey("Escape")
    assert app.session.assist.pending_segment is None and app.session.assist.preview is None
    assert app.run_tool_hotkey("X") is None  # a key no command of the active tool has: nothing


def test_tool_command_hotkeys_act_for_the_active_tool() -> None:
    """Commands of different tools may share a hotkey (it acts for the active tool); one tool may not give two
    commands the same key, and a tool's own hotkey may not be a command's."""
    from annotator.tools import ToolCommand

    def cmd(key: str, hotkey: str) -> ToolCommand:
        return ToolCommand(key, key, lambda h: None, hotkey=hotkey)

    check_tools((Tool("a", "A", "J", "", commands=(cmd("a1", "Enter"),)),
                 Tool("b", "B", "K", "", commands=(cmd("b1", "Enter"),))))
    with pytest.raises(ValueError, match="two commands"):
        check_tools((Tool("a", "A", "J", "", commands=(cmd("a1", "Enter"), cmd("a2", "enter"))),))
    with pytest.raises(ValueError, match="taken by"):
        check_tools((Tool("a", "A", "J", "", commands=(cmd("a1", "P"),)), Tool("p", "P", "P", "")))


def test_app_keys_next_instance_and_brush_size(app: AnnotatorApp) -> None:
    """Tab / Shift+Tab cycle the active instance (wrapping); [ / ] scale the brush by at least one slider step,
    within the slider's range, and the slider shows it."""
    from annotator.tools import APP_KEYS, BRUSH_STEP, RADIUS

    with pytest.raises(ValueError, match="no instances"):
        app.session.instances.cycle_active(1)
    a, b, c = (app.session.instances.new_instance() for _ in range(3))
    assert app.session.toolbox.settings.active_id == c
    assert [app.session.instances.cycle_active(1) for _ in range(3)] == [a, b, c]
    assert [app.session.instances.cycle_active(-1) for _ in range(2)] == [b, a]
    app.session.toolbox.settings.radius = 0.01
    assert app.resize_brush(BRUSH_STEP) == pytest.approx(0.012)  # 1 cm x 1.25, on the slider's 0.1 cm steps
    assert app.panels.gui_controls["radius"].value == pytest.approx(1.2)
    assert app.resize_brush(1 / BRUSH_STEP) == pytest.approx(0.01)
    app.session.toolbox.settings.radius = RADIUS.min / RADIUS.scale
    assert app.resize_brush(BRUSH_STEP) == pytest.approx((RADIUS.min + RADIUS.step) / RADIUS.scale)  # one step
    assert app.resize_brush(1 / BRUSH_STEP) == pytest.approx(RADIUS.min / RADIUS.scale)
    assert app.resize_brush(1 / BRUSH_STEP) == pytest.approx(RADIUS.min / RADIUS.scale)  # stays in range
    app.session.toolbox.settings.radius = RADIUS.max / RADIUS.scale
    assert app.resize_brush(BRUSH_STEP) == pytest.approx(RADIUS.max / RADIUS.scale)
    assert app.panels.gui_controls["radius"].value == pytest.approx(RADIUS.max)
    assert {k.shown for k in APP_KEYS} >= {"[", "]", "Tab", "?"}
    for k in APP_KEYS:
        assert k.shown in app.panels.gui_help.content


def test_tool_table_drives_toolbar_controls_help_and_history(app: AnnotatorApp) -> None:
    """The toolbar, the controls shown, the help and the history lines all come from the tool table."""
    assert tuple(app.panels.gui_tool.options) == TOOLS == tuple(t.name for t in DEFAULT_TOOLS)
    assert app.session.toolbox.settings.tool == "brush" and "**B** Brush" in app.panels.gui_tool_help.content
    assert app.panels.gui_controls["radius"].visible and not app.panels.gui_controls["grow_angle_deg"].visible
    assert app.panels.gui_controls["box_facing"].visible  # box select works with every tool
    app.panels.gui_tool.value = "grow"  # as a browser does: the dropdown's callback switches the tool
    assert app.session.toolbox.settings.tool == "grow"
    assert app.panels.gui_controls["grow_angle_deg"].visible and not app.panels.gui_controls["radius"].visible
    assert "**G** Region grow" in app.panels.gui_tool_help.content
    assert "- ▶ **G** Region grow" in app.panels.gui_help.content and "- **O** Lasso" in app.panels.gui_help.content
    app.session.instances.new_instance(category="mug")
    app.session.toolbox.settings.grow_angle_deg, app.session.toolbox.settings.grow_distance = 60, 0.05
    app.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
    assert _last_step(app).endswith("(Region grow)")
    app.handle_event("rect", SimpleNamespace(client_id=3, client=_client(), screen_min=(0.4, 0.4),
                                             screen_max=(0.6, 0.6)))
    assert _last_step(app).endswith("(box select)")
    app.set_tool("pick")
    assert not any(app.panels.gui_controls[k].visible for k in ("radius", "grow_angle_deg", "grow_min_height"))
    with pytest.raises(ValueError, match="unknown tool"):
        app.set_tool("rm")


def test_a_new_tool_is_one_entry_plus_its_function(mesh_path: Path, tmp_path: Path) -> None:
    """An added tool (with a setting of its own) gets its dropdown option, control, help line and click."""
    ball = Control("ball_radius", "Ball radius (cm)", "slider", 3.0, min=1.0, max=10.0, step=0.5, scale=100.0)

    def paint_ball(host: AnnotatorApp, hit: Hit) -> None:
        r = float(host.toolbox.settings.extra["ball_radius"])
        host.painting.paint(np.asarray(host.scan.geom.tree.query_ball_point(hit.position, r), np.int64),
                            client=hit.client)

    tools = (*DEFAULT_TOOLS, Tool("ball", "Ball", "P", "click paints a ball", controls=(ball,), apply_at=paint_ball))
    a = AnnotatorApp(mesh_path, out_dir=tmp_path / "o", port=0, autosave_delay=0, tools=tools)
    try:
        assert a.panels.gui_tool.options[-1] == "ball" and "**P** Ball" in a.panels.gui_help.content
        assert (a.session.toolbox.settings.extra["ball_radius"] == pytest.approx(0.03)
                and not a.panels.gui_controls["ball_radius"].visible)
        a.set_tool("ball")
        assert a.panels.gui_controls["ball_radius"].visible
        a.panels.gui_controls["ball_radius"].value = 5.0  # cm in the GUI, metres in the setting
        assert a.session.toolbox.settings.extra["ball_radius"] == pytest.approx(0.05)
        iid = a.session.instances.new_instance()
        v = a.session.painting.click(np.array([0, 0, 1.0]), np.array([0, 0, -1.0]))
        assert v is not None
        painted = np.flatnonzero(a.session.scan.store.labels == iid)
        assert len(painted) > 10
        assert (np.linalg.norm(a.session.scan.scene.points[painted] - a.session.scan.scene.points[v], axis=1).max()
                <= 0.05 + 1e-6)
        assert _last_step(a).endswith("(Ball)")
    finally:
        a.close()
    with pytest.raises(ValueError, match="hotkey .b. is taken by .brush."):
        check_tools((*DEFAULT_TOOLS, Tool("bad", "Bad", "b", "clashes with the brush")))
    with pytest.raises(ValueError, match="two tools"):
        check_tools((*DEFAULT_TOOLS, DEFAULT_TOOLS[0]))
    with pytest.raises(ValueError, match="hotkey 'N'"):
        check_tools((Tool("new", "New", "N", "the app's new-instance key"),))
    for key in ("[", "]", "?", "Tab"):
        with pytest.raises(ValueError, match="is taken by 'the app'"):
            check_tools((Tool("k", "K", key, "an app key"),))


def test_efem_prelabels_carry_their_categories(spheres) -> None:
    """Pre-labels of a result with two categories (a joint solve over two priors) keep each instance's category
    in the instance table, and the panel counts instances per category."""
    import dataclasses

    from efem_viz.em import EMResult

    d, scene, _ = spheres
    res = EMResult.load(d / "spheres.efem.npz")
    k_all = len(res.instances)
    assert k_all >= 2
    cats = np.array(["mug"] + ["sphere"] * (k_all - 1))
    dataclasses.replace(res, instances=dataclasses.replace(res.instances, category=cats)).save(d / "two.efem.npz")
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_cats", port=0, autosave_delay=0)
    try:
        # start unlabelled (file has GT)
        a.session.scan.store.do(lambda ls: ls.replace_all(np.zeros(a.session.scan.n, np.int32), []))
        ids = a.session.assist.import_efem("two.efem.npz")
        got = sorted(a.session.scan.store.labelset.info(i).category for i in ids)
        assert got == sorted(cats.tolist())[: len(got)] and "mug" in got and "sphere" in got
        assert all(a.session.scan.store.labelset.info(i).name
                   == f"{a.session.scan.store.labelset.info(i).category} (EFEM)" for i in ids)
        n_sphere = got.count("sphere")
        assert "per category: " in a.panels.gui_table.content
        assert "mug: 1 (" in a.panels.gui_table.content and f"sphere: {n_sphere} (" in a.panels.gui_table.content
        assert "| mug |" in a.panels.gui_table.content
    finally:
        a.close()


def test_lasso_outline_clamps_limits_and_closes() -> None:
    from annotator.lasso import LassoCamera, LassoOutline

    cam = LassoCamera(np.zeros(3), np.array([1.0, 0, 0, 0]), 0.8, 1.5)
    other = LassoCamera(np.ones(3), np.array([0.0, 1, 0, 0]), 0.5, 1.0)
    o = LassoOutline(max_points=3)
    assert o.segments() is None
    o.add((1.5, -0.2), ray_origin=np.zeros(3), ray_direction=np.array([0.0, 0.0, -2.0]), camera=cam)
    assert o.points == [(1.0, 0.0)] and np.allclose(o.world[0], [0, 0, -0.05])  # clamped; 5 cm along the ray
    with pytest.raises(ValueError, match="at least 3"):
        o.polygon()
    o.add((0.2, 0.2), ray_origin=np.zeros(3), ray_direction=np.array([1.0, 0, 0]), camera=other)
    o.add((0.5, 0.9), ray_origin=np.zeros(3), ray_direction=np.array([0.0, 1, 0]), camera=other)
    seg = o.segments()
    assert seg is not None and seg.shape == (3, 2, 3) and np.allclose(seg[-1, 1], seg[0, 0])  # closed
    camera, poly = o.polygon()
    assert camera is cam and poly.shape == (3, 2)  # the first click's view
    with pytest.raises(ValueError, match="at most 3"):
        o.add((0.1, 0.1), ray_origin=np.zeros(3), ray_direction=np.array([1.0, 0, 0]), camera=cam)
    o.clear()
    assert len(o) == 0 and o.camera is None


def test_the_drag_surface_of_a_reduced_scan_covers_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A scan drawn from a subset, with fewer proxy splats than drawn points (the default budget on a 5M scan:
    1M drawn, 150k splats): the invisible splats must still cover the surface, or most Ctrl+drags start nowhere.
    Lower bound of the covered share: scan vertices within a splat's inradius (half its circumradius) of one."""
    import annotator.scan_view as scan_view
    from scipy.spatial import cKDTree

    g = np.linspace(0.0, 0.3, 300, dtype=np.float32)  # 90k vertices, 1 mm apart
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    pts = np.concatenate([xy, np.zeros((len(xy), 1), np.float32)], 1)
    nrm = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (len(pts), 1))
    scan = save_scene(Scene.create("plane", pts, normals=nrm), tmp_path / "plane.ply")
    monkeypatch.setattr(scan_view, "MAX_SPLATS", 5000)
    a = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0, display_points=30_000)
    try:
        verts = np.asarray(a.view.surface.vertices, np.float64).reshape(-1, 3, 3)
        assert len(verts) == 5000
        centres = verts.mean(axis=1)
        size = float(np.linalg.norm(verts[0, 0] - centres[0]))  # circumradius
        d, _ = cKDTree(centres[:, :2]).query(pts[:, :2].astype(np.float64))
        inner = pts[:, :2].min(1) > 0.01  # away from the border, where no splat lies beyond
        inner &= pts[:, :2].max(1) < 0.29
        covered = float((d[inner] <= size / 2).mean())
        assert covered > 0.75, f"the drag surface covers only about {covered:.0%} of the scan"
    finally:
        a.close()


def test_run_efem_on_the_open_scan_makes_prelabels(spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """the annotator runs EFEM on the open scan itself (the real solver, the sphere prior in place
    of a shipped one): the Run button's run shows progress with what it does, its instances become unreviewed
    pre-labels on unlabelled vertices only, the result is saved beside the journal and imports again, and the
    pre-label cut opens where "Accept all ≥ cut" takes the best."""
    import annotator.efem_runs as efem_runs
    from efem_viz.em.results import EMResult

    d, scene, prior = spheres
    monkeypatch.setattr(efem_runs, "get_prior", lambda name: prior)
    save_scene(Scene.create("bare", scene.points, normals=scene.normals, colors=scene.colors), d / "bare.ply")
    a = AnnotatorApp(d / "bare.ply", out_dir=d / "out_run", port=0, autosave_delay=0)  # no labels to start from
    try:
        assert a.panels.gui_efem_preset.value == "fast"  # a synthetic scan: no capture camera
        kept = a.session.instances.new_instance(category="table")
        a.session.painting.paint(np.arange(50))
        texts: list[str] = []
        shown = a._show_efem_run

        def spy(text: str | None, percent: float | None) -> None:
            shown(text, percent)
            if text is not None:
                texts.append(text)
                assert a.panels.gui_efem_progress.visible and a.panels.gui_efem_run.disabled
                assert not a.panels.gui_efem_cancel.disabled

        a.session.on_efem = spy
        a.panels.gui_efem_proposals.value = 16
        ids = a.run_efem(wait=True)
        assert ids, "the sphere scene's spheres become pre-labels"
        assert any("step 1 of" in t and "proposals alive" in t for t in texts)
        assert not a.panels.gui_efem_progress.visible and not a.panels.gui_efem_run.disabled
        assert a.panels.gui_efem_cancel.disabled and a.panels.gui_efem_status.content == ""
        labels = a.session.scan.store.labels
        assert (labels[:50] == kept).all()  # labelled vertices stay
        table = a.session.scan.store.labelset.instances
        assert all("unreviewed" in table[i].note for i in ids)
        best = max(table[i].confidence for i in ids)
        assert float(a.panels.gui_prelabel_cut.value) <= best
        saved = a.session.scan.work_dir / f"bare{RESULT_SUFFIX}"
        res = EMResult.load(saved)
        assert len(res.instances) == len(ids) + sum(  # every instance is a pre-label unless nothing was left free
            1 for k in range(len(res.instances)) if not np.any(np.setdiff1d(res.instances.masks[k], np.arange(50))))
        hits = [g for g in scene.instance_ids() if any(
            _iou(labels == i, scene.instance == g) > 0.5 for i in ids)]
        assert len(hits) >= 2, "the pre-labels cover the spheres"
        assert a.session.assist.import_efem(str(saved.relative_to(d))) is not None  # the saved run imports again
    finally:
        a.close()


def test_run_efem_is_drawn_as_it_goes_and_leaves_only_prelabels(spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """A running EFEM on the scan is drawn over the scan as it goes (the real solver, two episodes so that some
    instances are accepted while it still runs): as soon as its proposals are drawn the scan around their anchors
    is tinted, from its first step the points its live proposals sample, the instances of the first episode
    appear in their pre-label colours during the second, nothing is drawn over labelled vertices, the labels and
    the journal are not touched until the end, and at the end the overlay is gone and only the pre-labels
    remain."""
    import annotator.efem_runs as efem_runs
    from annotator.render import SEARCH_COLOR, compose_colors
    from efem_viz import em

    d, scene, prior = spheres
    save_scene(Scene.create("bare", scene.points, normals=scene.normals, colors=scene.colors), d / "bare2.ply")

    def two_episodes(scene_: Any, *, prior_name: str, settings: Any, seed: int, on_step: Any,
                     cancel: threading.Event) -> Any:
        cfg = em.preset("fast").replace(proposals={"n_init": (16, 8)}, elimination={"min_size": 30})
        return em.run_em(scene_, prior, cfg, seed=seed, on_step=on_step, cancel=cancel)

    monkeypatch.setattr(efem_runs, "solve_scan", two_episodes)
    a = AnnotatorApp(d / "bare2.ply", out_dir=d / "out_live", port=0, autosave_delay=0)
    try:
        ses = a.session
        ses.assist.progressive_every_s = 0.0  # every step (a count, not a clock)
        kept = ses.instances.new_instance(category="table")
        ses.painting.paint(np.arange(50))
        labels_before = ses.scan.store.labels.copy()
        records_before = len(ses.scan.store.journal.records)
        seen: list[tuple[int, int, int, int, bool]] = []  # step, tinted, accepted codes, on labelled, colour ok
        draw = a.view.draw_preview

        def spy(idx: np.ndarray) -> int:
            sent = draw(idx)
            ov = ses.assist.run_overlay
            if ov is not None:
                tinted = np.flatnonzero(ov.codes == 1)
                colour_ok = True
                if len(tinted):  # the colour sent for a tinted vertex leans toward the search colour
                    v = int(tinted[len(tinted) // 2])
                    chunk = int(a.view.chunks.chunk_of[v])
                    members = a.view.chunks.members(chunk)
                    col = np.asarray(a.view.chunk_handles[chunk].colors)[int(np.flatnonzero(members == v)[0])]
                    base = scene.colors[v].astype(float)
                    colour_ok = np.linalg.norm(col - np.asarray(SEARCH_COLOR)) < np.linalg.norm(base - SEARCH_COLOR)
                lut, show = a.view._lut()
                hand = compose_colors(scene.colors[:50], ses.scan.store.labels[:50], lut, show)
                seen.append((ov.step, len(tinted), int((ov.codes >= 2).sum()),
                             int((a.view._colors(np.arange(50), (lut, show)) != hand).any(axis=1).sum()),
                             bool(colour_ok)))
                assert np.array_equal(ses.scan.store.labels, labels_before), "a running EFEM changed labels"
            return sent

        ses.on_preview = spy
        lines: list[str] = []
        said = a._show_efem_run
        ses.on_efem = lambda text, percent: (lines.append(text or ""), said(text, percent))
        ids = a.run_efem(wait=True)
        assert any("found so far" in t for t in lines), "the progress line counts what the run accepted so far"
        assert seen and seen[0][0] == -1 and seen[0][1] > 0, "the drawn proposals show before the first step"
        assert seen[1][0] == 0 and seen[1][1] > 0, "then the first step's samples"
        assert all(ok for *_, ok in seen), "tinted vertices were sent in the search colour"
        assert all(over == 0 for *_, over, _ in seen), "nothing is drawn over the labelled vertices"
        steps = [s for s, *_ in seen]
        assert steps == sorted(steps) and len(set(steps)) >= 10
        assert any(acc > 0 for _, _, acc, _, _ in seen), "the first episode's instances show during the second"
        assert ses.assist.run_overlay is None, "the overlay goes when the run ends"
        assert ids and (ses.scan.store.labels[:50] == kept).all()
        assert len(ses.scan.store.journal.records) > records_before
        drawn = a.view._colors(np.arange(ses.scan.n), a.view._lut())
        free = ses.scan.store.labels == 0
        assert np.array_equal(drawn[free], scene.colors[free]), "nothing of the run is left on unlabelled vertices"
    finally:
        a.close()


def test_run_efem_takes_the_free_space_mode_the_panel_shows(spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """The EFEM assist folder's *Free space* dropdown reaches the solver (auto: the preset's, none for `fast`;
    on: the fused scans' check; off: none), the progress line names a mode other than auto, and a forged value
    is refused before any run starts."""
    import annotator.efem_runs as efem_runs
    import efem_viz.em as em
    from efem_viz.em.config import FREE_SPACE_FUSED

    d, scene, prior = spheres
    monkeypatch.setattr(efem_runs, "get_prior", lambda name: prior)
    margins: list[float | None] = []
    real_run = em.run_em

    def spy_run(*args: Any, **kw: Any) -> Any:
        margins.append(kw["cfg"].free_space.margin)
        return real_run(*args, **kw)

    monkeypatch.setattr(em, "run_em", spy_run)
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_free_space", port=0, autosave_delay=0)
    try:
        texts: list[str] = []
        a.session.on_efem = lambda text, percent: texts.append(text or "")
        a.panels.gui_efem_proposals.value = 8
        assert a.panels.gui_efem_free_space.value == "auto"
        for mode in ("auto", "on", "off"):
            a.panels.gui_efem_free_space.value = mode
            a.run_efem(wait=True)
        assert margins == [None, FREE_SPACE_FUSED.margin, None]
        assert any("free space on" in t for t in texts) and not any("free space auto" in t for t in texts)
        a.panels.gui_efem_free_space.value = "sideways"
        with pytest.raises(ClientValueError):
            a.run_efem(wait=True)
        assert len(margins) == 3
    finally:
        a.close()


def test_a_first_run_says_it_builds_the_kernels_before_its_first_step(spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """On a machine where the encoder's kernels are not built yet, the progress line says so while they compile
    (about half a minute without a step), then the steps follow."""
    import annotator.efem_runs as efem_runs
    from efem_viz.prior import fused

    d, scene, prior = spheres
    monkeypatch.setattr(efem_runs, "get_prior", lambda name: prior)
    monkeypatch.setattr(fused, "pending_build", lambda: True)
    texts: list[str] = []
    monkeypatch.setattr(fused, "load", lambda: texts.append("<load>") or False)  # the eager encoder serves
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_build", port=0, autosave_delay=0)
    try:
        shown = a._show_efem_run

        def spy(text: str | None, percent: float | None) -> None:
            shown(text, percent)
            if text is not None:
                texts.append(text)

        a.session.on_efem = spy
        a.panels.gui_efem_proposals.value = 8
        a.run_efem(wait=True)
        notice = next(i for i, t in enumerate(texts) if fused.BUILD_NOTICE in t)
        first_step = next(i for i, t in enumerate(texts) if "step 1 of" in t)
        assert notice < texts.index("<load>") < first_step
    finally:
        a.close()


def test_run_efem_on_a_millimetre_y_up_scan_solves_in_metres_and_labels_its_own_vertices(
        spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bare scan saved by another tool in millimetres with +Y up: EFEM runs on it brought to metres and +Z up
    (said once), the pre-labels land on the scan's own vertices, and the scan is shown and kept as it was."""
    import annotator.efem_runs as efem_runs
    from efem_viz.data.scan import _UP_ROTATIONS

    d, scene, prior = spheres
    monkeypatch.setattr(efem_runs, "get_prior", lambda name: prior)
    R = _UP_ROTATIONS["+y"].T  # scene +Z -> the file's +Y
    raw = Scene.create("raw_mm", scene.points.astype(np.float64) @ R.T * 1000.0 + np.array([400.0, 120.0, -900.0]),
                       normals=scene.normals @ R.T, colors=scene.colors)
    save_scene(raw, d / "raw_mm.ply")
    a = AnnotatorApp(d / "raw_mm.ply", out_dir=d / "out_mm", port=0, autosave_delay=0)
    try:
        notes: list[tuple[str, str]] = []
        a.session.notify = lambda title, body: notes.append((title, body))
        a.panels.gui_efem_proposals.value = 16
        ids = a.run_efem(wait=True)
        assert any("brought to metres" in body for _, body in notes), notes
        np.testing.assert_allclose(a.session.scan.scene.points, raw.points, rtol=1e-6)  # the scan as it was
        labels = a.session.scan.store.labels
        hits = [g for g in scene.instance_ids() if any(_iou(labels == i, scene.instance == g) > 0.5 for i in ids)]
        assert len(hits) >= 2, "the spheres, found in metres, are labelled on the millimetre scan's vertices"
    finally:
        a.close()


def test_run_efem_refuses_a_result_path_that_links_out_of_the_output_folder(spheres, tmp_path: Path) -> None:
    """The EFEM result `<scan>.annotate/<scan>.efem.npz` as a link to a folder elsewhere (or to a file): the run is
    refused before any work with one line, and nothing is written outside the output folder."""
    from annotator.io import LabelIOError

    d, scene, _ = spheres
    save_scene(Scene.create("linked", scene.points, normals=scene.normals, colors=scene.colors), d / "linked.ply")
    a = AnnotatorApp(d / "linked.ply", out_dir=d / "out_linked", port=0, autosave_delay=0)
    try:
        outside = tmp_path / "elsewhere"
        outside.mkdir()
        link = a.session.scan.work_dir / f"linked{RESULT_SUFFIX}"
        link.symlink_to(outside, target_is_directory=True)
        with pytest.raises(LabelIOError, match="outside|link"):
            a.session.assist.run_efem(wait=True)
        link.unlink()
        link.symlink_to(outside / "x.efem.npz")
        with pytest.raises(LabelIOError, match="outside|link"):
            a.session.assist.run_efem(wait=True)
        assert list(outside.iterdir()) == []
    finally:
        a.close()


def test_run_efem_progress_and_cancel(app: AnnotatorApp, monkeypatch: pytest.MonkeyPatch) -> None:
    """The EFEM run on the scan reports its steps and the Cancel button stops it: nothing is added, the buttons
    come back, one run at a time (click-to-segment waits for it too), and bad values are refused."""
    import annotator.efem_runs as efem_runs
    from efem_viz.em.solver import EMCancelled, StepInfo

    started = threading.Event()

    def slow(scene: object, *, prior_name: str, settings: object, seed: int, on_step: Any,
             cancel: threading.Event) -> object:
        on_step(StepInfo(step=0, num_steps=30, phase=1, active=80, elapsed_s=1.0))
        started.set()
        assert cancel.wait(30), "never cancelled"
        raise EMCancelled("cancelled")

    monkeypatch.setattr(efem_runs, "solve_scan", slow)
    notes: list[str] = []
    app.notify = lambda title, body, *, client=None, color=None: notes.append(title)  # type: ignore[method-assign]
    before = dict(app.session.scan.store.labelset.instances)
    app.run_efem()
    assert started.wait(30) and app.session.assist.efem_running
    assert "step 1 of 30" in app.panels.gui_efem_status.content and app.panels.gui_efem_progress.value > 0
    with pytest.raises(ValueError, match="still running EFEM"):
        app.run_efem()
    with pytest.raises(ValueError, match="still running EFEM"):
        app.segment_at(0)
    app.session.assist.discard_segment()  # Esc of the Segment tool: the scan run goes on
    assert app.session.assist.efem_running and not app.session.assist.segmenting
    app.session.assist.set_preview(np.arange(5))  # a segment preview from before stays: Cancel stops only the run
    assert app.session.assist.cancel_efem()  # the Cancel button's action
    deadline = time.monotonic() + 30
    while app.session.assist.efem_running and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not app.session.assist.efem_running and "EFEM run cancelled" in notes
    assert dict(app.session.scan.store.labelset.instances) == before
    assert not app.panels.gui_efem_run.disabled and app.panels.gui_efem_cancel.disabled
    assert app.session.assist.pending_segment is not None and not app.session.assist.cancel_efem()
    app.session.assist.set_preview(None)
    app.panels.gui_efem_preset.value = "turbo"  # a hostile client value
    with pytest.raises(ClientValueError):
        app.run_efem()


def test_tools_show_their_warm_up_until_ready(app: AnnotatorApp) -> None:
    """after a scan opens, the Tools folder says which structure is being built and what works
    already, and the words go when every tool is ready."""
    deadline = time.monotonic() + 60
    while app.panels.gui_tools_progress.visible and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not app.panels.gui_tools_progress.visible and app.panels.gui_tools_status.content == ""
    app._show_warm_up("ray caster", 3, 4)  # as the warm-up thread reports it on a big mesh
    assert app.panels.gui_tools_progress.visible and app.panels.gui_tools_progress.value == 75.0
    text = app.panels.gui_tools_status.content
    assert "4 of 4" in text and "ray caster" in text and "brush works" in text
    app._show_warm_up("", 4, 4)
    assert not app.panels.gui_tools_progress.visible and app.panels.gui_tools_status.content == ""


def test_closing_during_an_efem_run_stops_it_first(spheres, monkeypatch: pytest.MonkeyPatch) -> None:
    """Closing the app (Ctrl+C) during an EFEM run on the scan cancels it and waits for its thread before the journal
    closes: nothing is saved or added afterwards. Proposals 0 takes the preset's count."""
    import annotator.efem_runs as efem_runs
    from efem_viz.em.solver import EMCancelled, StepInfo

    d, scene, _ = spheres
    started = threading.Event()
    got: list[object] = []

    def slow(scene: object, *, prior_name: str, settings: Any, seed: int, on_step: Any,
             cancel: threading.Event) -> object:
        got.append(settings)
        on_step(StepInfo(step=0, num_steps=30, phase=1, active=80, elapsed_s=1.0))
        started.set()
        assert cancel.wait(30), "never cancelled"
        raise EMCancelled("cancelled")

    monkeypatch.setattr(efem_runs, "solve_scan", slow)
    a = AnnotatorApp(d / "spheres.ply", out_dir=d / "out_close", port=0, autosave_delay=0)
    assert a.panels.gui_efem_proposals.value == 0
    a.run_efem()
    assert started.wait(30)
    thread = a.session.assist._thread
    a.close()
    assert thread is not None and not thread.is_alive() and not a.session.assist.efem_running
    assert got[0].proposals is None and got[0].preset == "fast"  # type: ignore[attr-defined]
    assert not list((d / "out_close").glob("*.annotate/*.efem.npz"))


def test_a_room_sized_scan_opens_with_sliders_as_long_as_it_needs(tmp_path: Path) -> None:
    """A 9 x 6 x 3 m scan used to fail at start ("add_slider: initial_value (22.4) is outside of [0.1, 20.0]"):
    the brush starts at 2 % of the diagonal on a slider that reaches 10 % of it; a tabletop scan keeps 20 cm."""
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(0, 9, 20000), rng.uniform(0, 6, 20000), np.zeros(20000)]
    walls = np.c_[rng.uniform(0, 9, 5000), np.full(5000, 6.0), rng.uniform(0, 3, 5000)]
    pts = np.concatenate([floor, walls]).astype(np.float32)
    room = save_scene(Scene(name="room", points=pts, normals=np.tile(np.float32([0, 0, 1]), (len(pts), 1)),
                            colors=np.full((len(pts), 3), 128, np.uint8)), tmp_path / "room.ply")
    a = AnnotatorApp(room, out_dir=tmp_path / "out", port=0, autosave_delay=0)
    try:
        diagonal = float(np.linalg.norm(np.ptp(pts, axis=0)))
        slider = a.panels.gui_controls["radius"]
        assert abs(a.session.toolbox.settings.radius - 0.02 * diagonal) < 1e-6
        assert slider.max >= 0.1 * diagonal * 100 - 0.1 and slider.min <= slider.value <= slider.max
        assert abs(slider.value - 2.0 * diagonal) < 0.1  # cm
        grow = a.panels.gui_controls["grow_distance"]
        assert grow.max >= diagonal * 100 - 1
        assert a.resize_brush(100.0) <= slider.max / 100 + 1e-9  # `]` stops at the slider's end
    finally:
        a.close()


def test_the_run_preset_follows_the_prior_a_client_chooses(app: AnnotatorApp) -> None:
    """A scan labelled with chairs: choosing the chair prior (a real client's dropdown event) sets the EFEM Run
    preset to `chairs` (its floor joins no chair); back to the mug prior, the scan's own `fast` again."""
    from viser_client import RawClient, wait_for

    p = app.panels
    assert "chair" in tuple(p.gui_prior.options) and p.gui_efem_preset.value == "fast"
    assert app.session.assist.suggested_preset("chair") == "chairs"
    assert app.session.assist.suggested_preset("no-such-prior") == "fast"  # the scan alone decides
    with RawClient(app.url) as c:
        assert wait_for(lambda: len(app.server.get_clients()) == 1)
        c.set_gui(p.gui_prior, value="chair")
        assert wait_for(lambda: p.gui_efem_preset.value == "chairs")
        assert app.session.toolbox.settings.prior == "chair"
        c.set_gui(p.gui_prior, value="mug")
        assert wait_for(lambda: p.gui_efem_preset.value == "fast")
