"""The annotator's headless session: every action driven without a browser and without viser."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from annotator.io import LABEL_WRITERS, LabelData, LabelIOError, load_labels
from annotator.labels import InstanceInfo
from annotator.lasso import LassoCamera
from annotator.session import AnnotatorSession
from annotator.tools import Hit
from tests.helpers import ball_scan

TOP_CAMERA = LassoCamera(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0, 0.0]), float(np.deg2rad(50)), 1.0)
"""Looking down -Z at the ball from 1 m above (OpenCV camera: wxyz (0, 1, 0, 0) flips y and z)."""


@pytest.fixture()
def session(tmp_path: Path):
    s = AnnotatorSession(ball_scan(tmp_path), out_dir=tmp_path / "out", autosave_delay=0)
    yield s
    s.close()


def _top_vertex(s: AnnotatorSession) -> int:
    return int(np.argmax(s.scan.scene.points[:, 2]))


def test_session_imports_without_viser() -> None:
    code = ("import sys; import annotator.session, annotator.tools, annotator.lasso; "
            "assert 'viser' not in sys.modules, sorted(m for m in sys.modules if 'viser' in m)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])


def test_tools_do_not_import_the_app() -> None:
    root = Path(__file__).resolve().parents[1] / "annotator"
    for name in ("tools.py", "lasso.py", "session.py"):
        text = (root / name).read_text()
        assert "annotator.app" not in text.replace("`annotator.app", ""), name


def test_paint_erase_undo_redo_and_the_journal(session: AnnotatorSession) -> None:
    with pytest.raises(ValueError, match="no active instance"):
        session.painting.paint(np.arange(10))
    changes: list[int] = []
    session.on_change = lambda: changes.append(1)
    iid = session.instances.new_instance(category="mug")
    assert session.toolbox.settings.active_id == iid and changes
    d = session.painting.paint(np.arange(10))
    assert d is not None and d.num_vertices == 10 and (session.scan.store.labels[:10] == iid).all()
    session.painting.paint(np.arange(5), erase=True)
    assert (session.scan.store.labels[:5] == 0).all() and (session.scan.store.labels[5:10] == iid).all()
    session.instances.undo()
    assert (session.scan.store.labels[:10] == iid).all()
    session.instances.redo()
    assert (session.scan.store.labels[:5] == 0).all()
    journal = session.scan.work_dir / f"{session.scan.stem}.journal"
    assert journal.exists() and journal.stat().st_size > 0


def test_edits_inside_a_tool_name_the_tool(session: AnnotatorSession) -> None:
    session.instances.new_instance()
    session.instances.set_tool("grow")
    v = _top_vertex(session)
    session.painting.apply_tool(Hit(v, session.scan.scene.points[v]))
    assert "(Region grow)" in session.scan.store.labelset.undo_stack[-1].label


def test_dab_stroke_and_cursor(session: AnnotatorSession) -> None:
    session.instances.new_instance()
    session.toolbox.settings.radius = 0.02
    drawn: list[int] = []
    session.on_cursor = lambda: drawn.append(1)
    v = _top_vertex(session)
    d = session.painting.dab(v, session.scan.scene.points[v], erase=False)
    assert d is not None and d.num_vertices > 0 and drawn
    assert (session.brush.cursor is not None and session.brush.cursor.visible
            and session.brush.cursor.radius == pytest.approx(0.02))
    session.instances.set_tool("grow")
    cur = session.brush.refresh_cursor()
    assert cur is not None and not cur.visible
    session.instances.set_tool("erase")
    pts = session.scan.scene.points[session.scan.scene.points[:, 2] > 0.09][:3]
    assert session.painting.paint_stroke(pts, erase=True) > 0


def test_drag_stroke_is_one_undo_step(session: AnnotatorSession) -> None:
    iid = session.instances.new_instance()
    session.toolbox.settings.radius = 0.015
    session.painting.stroke_start(7, np.array([0.0, 0.0, 0.1]))
    for x in (0.01, 0.02, 0.03):
        session.painting.stroke_to(7, np.array([0.0, 0.0, 1.0]), np.array([x, 0.0, 0.5]))
    session.painting.stroke_to(7, np.array([0.0, 0.0, 1.0]), np.array([0.04, 0.0, 0.5]), end=True)
    assert not session.painting.strokes
    painted = int((session.scan.store.labels == iid).sum())
    assert painted > 0
    session.instances.undo()
    assert not (session.scan.store.labels == iid).any()


def test_grow_fill_pick_and_min_height(session: AnnotatorSession) -> None:
    a = session.instances.new_instance()
    session.toolbox.settings.grow_distance = 0.05
    v = _top_vertex(session)
    d = session.painting.grow(v)
    assert d is not None and 0 < d.num_vertices < session.scan.n
    b = session.instances.new_instance()
    session.toolbox.settings.grow_min_height = 0.05
    d2 = session.painting.fill(v)
    assert d2 is not None and (session.scan.scene.points[d2.idx, 2] >= 0.05).all()
    assert session.painting.pick_instance(v) == b and session.toolbox.settings.active_id == b
    session.instances.cycle_active(1)
    assert session.toolbox.settings.active_id == a


def test_click_applies_the_active_tool_or_misses(session: AnnotatorSession) -> None:
    iid = session.instances.new_instance()
    session.instances.set_tool("brush")
    v = session.painting.click(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))
    assert v is not None and (session.scan.store.labels == iid).any()
    assert session.painting.click(np.array([5.0, 5.0, 1.0]), np.array([0.0, 0.0, 1.0])) is None


def test_box_and_lasso_select_from_a_camera(session: AnnotatorSession) -> None:
    iid = session.instances.new_instance()
    d = session.box_lasso.box(position=TOP_CAMERA.position, wxyz=TOP_CAMERA.wxyz, fov=TOP_CAMERA.fov,
                    aspect=TOP_CAMERA.aspect, screen_min=(0.4, 0.4), screen_max=(0.6, 0.6))
    assert d is not None and d.num_vertices > 0
    assert (session.scan.scene.points[d.idx, 2] > 0).all()  # front: the top of the ball only
    session.instances.undo()
    lasso_changes: list[int] = []
    session.on_lasso = lambda: lasso_changes.append(len(session.box_lasso.lasso_outline))
    for uv in ((0.4, 0.4), (0.6, 0.4), (0.6, 0.6), (0.4, 0.6)):
        session.box_lasso.add_lasso_point(uv, ray_origin=TOP_CAMERA.position, ray_direction=(0.0, 0.0, -1.0),
                                camera=TOP_CAMERA)
    assert lasso_changes == [1, 2, 3, 4]
    d = session.box_lasso.apply_lasso()
    assert d is not None and d.num_vertices > 0 and len(session.box_lasso.lasso_outline) == 0
    assert "(lasso)" in d.label and (session.scan.store.labels[d.idx] == iid).all()
    with pytest.raises(ValueError, match="at least 3"):
        session.box_lasso.apply_lasso()
    with pytest.raises(ValueError):
        session.box_lasso.add_lasso_point((float("nan"), 0.5), ray_origin=(0, 0, 1), ray_direction=(0, 0, -1),
                                camera=TOP_CAMERA)


def test_a_box_that_takes_other_instances_vertices_says_so_at_once(session: AnnotatorSession) -> None:
    """A box select over an instance's vertices relabels them (the default) and the user is told how many and how to
    undo or avoid it; with *Only unlabelled vertices* nothing is taken and nothing is said; an erasing box says
    nothing either."""
    notes: list[str] = []
    session.notify = lambda title, body: notes.append(f"{title}: {body}")
    box = dict(position=TOP_CAMERA.position, wxyz=TOP_CAMERA.wxyz, fov=TOP_CAMERA.fov, aspect=TOP_CAMERA.aspect,
               screen_min=(0.4, 0.4), screen_max=(0.6, 0.6))
    first = session.instances.new_instance()
    d = session.box_lasso.box(**box)
    assert d is not None and not notes  # unlabelled vertices only: nothing to say
    session.instances.new_instance()
    d = session.box_lasso.box(**box)
    assert d is not None and len(notes) == 1
    assert f"took {int((d.before == first).sum()):,} labelled vertices" in notes[0] and "Ctrl+Z" in notes[0]
    session.instances.undo()
    session.toolbox.settings.only_unlabelled = True
    assert session.box_lasso.box(**box) is None and len(notes) == 1
    session.toolbox.settings.only_unlabelled = False
    session.instances.set_tool("erase")
    assert session.box_lasso.box(**box) is not None and len(notes) == 1


def test_instances_update_merge_delete(session: AnnotatorSession) -> None:
    a = session.instances.new_instance(category="mug")
    session.painting.paint(np.arange(10))
    b = session.instances.new_instance(category="bowl")
    session.painting.paint(np.arange(10, 20))
    session.instances.choose_category("cup")
    assert session.scan.store.labelset.info(b).category == "cup" and session.toolbox.settings.category == "cup"
    session.instances.toggle_active("visible")
    assert not session.scan.store.labelset.info(b).visible
    session.instances.update_instance(a, name="first")
    assert session.scan.store.labelset.info(a).name == "first"
    session.instances.merge([b], a)
    assert session.toolbox.settings.active_id == a and (session.scan.store.labels[:20] == a).all()
    session.instances.delete_instance(a)
    assert not session.scan.store.labels.any()


@pytest.mark.parametrize("fmt", sorted(LABEL_WRITERS))
def test_every_export_format_reads_back_and_stays_in_the_output_folder(fmt: str, session: AnnotatorSession,
                                                                         tmp_path: Path) -> None:
    """Each row of the export table: every file it writes is named as the row says and `load_labels` reads it back
    to the same labels and categories; a file of the row that is a symbolic link out of the output folder is
    refused before anything is written (a format added to the table is tested here without a new test)."""
    mug = session.instances.new_instance(category="mug")
    session.painting.paint(np.arange(30))
    bowl = session.instances.new_instance(category="bowl")
    session.painting.paint(np.arange(100, 140))
    labels = session.scan.store.labels.copy()
    writer = LABEL_WRITERS[fmt]
    out = session.files.export(fmt)
    assert sorted(p.name for p in out) == sorted(f"{session.scan.stem}{s}" for s in writer.suffixes)
    for p in out:
        assert p.parent == session.scan.out_dir
        back = load_labels(p, session.scan.n)
        assert np.array_equal(back.labels, labels)
        assert {r.id: r.category for r in back.instances} == {mug: "mug", bowl: "bowl"}
    outside = tmp_path / "outside"
    outside.mkdir()
    for p in out:
        p.unlink()
    (session.scan.out_dir / f"{session.scan.stem}{writer.suffixes[-1]}").symlink_to(outside / "victim")
    with pytest.raises(LabelIOError):
        session.files.export(fmt)
    assert not any(outside.iterdir()) and not any(p.exists() for p in out if not p.is_symlink())


def test_export_import_and_confinement(session: AnnotatorSession, tmp_path: Path) -> None:
    notes: list[str] = []
    bodies: list[str] = []
    session.notify = lambda title, body: (notes.append(title), bodies.append(body))
    iid = session.instances.new_instance(category="mug")
    session.painting.paint(np.arange(30))
    ply, = session.files.export("ply")
    npz, = session.files.export("npz")
    assert session.files.export("scannet") and notes.count("Exported") == 3
    assert bodies[0] == f"{ply.name} in {session.scan.out_dir}"  # the confirmation names the folder too
    from annotator.labels import prelabel_note

    pre = session.instances.new_instance(category="mug")
    session.painting.paint(np.arange(30, 40))
    session.instances.update_instance(pre, note=prelabel_note("efem", 0.4))
    session.files.export("npz")
    assert "1 unreviewed EFEM pre-label exported as objects" in bodies[-1]
    assert ply.parent == session.scan.out_dir and load_labels(npz, session.scan.n).labels[:30].tolist() == [iid] * 30
    with pytest.raises(LabelIOError):
        session.files.export("ply", directory="../elsewhere")
    session.painting.paint(np.arange(30), erase=True)
    session.files.import_labels(str(npz))
    assert (session.scan.store.labels[:30] == iid).all()


def test_prelabels_import_and_review(session: AnnotatorSession) -> None:
    labels = np.zeros(session.scan.n, np.int32)
    labels[:20], labels[20:50], labels[50:60] = 1, 2, 3
    rows = [InstanceInfo(k, f"p{k}", category="mug") for k in (1, 2, 3)]
    data = LabelData(labels, rows, confidence={1: 0.9, 2: 0.3, 3: 0.6})
    ids = session.assist.add_prelabels(data, source="scan.efem.npz")
    assert len(ids) == 3 and all(session.scan.store.labelset.info(i).unreviewed for i in ids)
    first = ids[0]  # most confident first
    assert session.scan.store.labelset.info(first).confidence == pytest.approx(0.9)
    session.assist.review_prelabel(first, "accept")
    assert not session.scan.store.labelset.info(first).unreviewed
    rejected = session.assist.review_prelabels(0.5, "reject")
    assert len(rejected) == 1 and rejected[0] not in session.scan.store.labelset.instances
    session.instances.undo()  # the bulk review is one undo step
    assert rejected[0] in session.scan.store.labelset.instances
    session.instances.set_active(first)
    session.assist.review_prelabel(ids[1], "merge")
    assert ids[1] not in session.scan.store.labelset.instances
    with pytest.raises(LabelIOError):
        session.assist.import_efem("../../etc/passwd")


def test_a_second_import_adds_no_fragments_of_labelled_objects(session: AnnotatorSession) -> None:
    """Importing pre-labels over a labelled scan leaves out the proposals whose vertices are mostly labelled
    already (a fragment of a labelled object) or all labelled (an empty row), and says how many."""
    hand = session.instances.new_instance(category="mug")
    session.painting.paint(np.arange(0, 100))
    labels = np.zeros(session.scan.n, np.int32)
    labels[30:130] = 1    # 30 of 100 free: a fragment of the labelled mug -> left out
    labels[10:50] = 2     # all labelled -> left out
    labels[200:260] = 3   # all free -> a pre-label
    rows = [InstanceInfo(k, f"p{k}", category="mug") for k in (1, 2, 3)]
    ids = session.assist.add_prelabels(LabelData(labels, rows, confidence={1: 0.9, 2: 0.8, 3: 0.5}),
                                       source="x.efem.npz")
    assert len(ids) == 1 and session.assist.skipped_prelabels == 2
    assert (session.scan.store.labels[200:260] == ids[0]).all() and (session.scan.store.labels[:100] == hand).all()
    assert set(session.scan.store.labelset.instances) == {hand, ids[0]}  # no empty rows


def test_click_to_segment_preview_accept_discard(session: AnnotatorSession,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import annotator.efem_runs as efem_runs

    solves: list[object] = []

    def fake(scene: object, vertex: int, *, prior_name: str, on_step: object, cancel: threading.Event,
             settings: object) -> np.ndarray:
        assert prior_name == "bowl"
        solves.append(settings)
        return np.arange(40, dtype=np.int32)

    monkeypatch.setattr(efem_runs, "segment_at_point", fake)
    progress: list[float | None] = []
    redrawn: list[int] = []
    session.on_segment = progress.append
    session.on_preview = lambda idx: redrawn.append(len(idx))
    session.toolbox.settings.prior = "bowl"
    session.assist.solve = dataclasses.replace(session.assist.solve, work_voxel=0.005, tau_out=0.06)
    mask = session.assist.segment_at(5, wait=True)
    assert solves == [session.assist.solve]  # the room's solver knobs reach the solve
    assert (mask is not None and len(mask) == 40 and session.assist.preview is not None
            and session.assist.preview[:40].all())
    assert progress[0] == 0.0 and None in progress and redrawn == [40] and not session.assist.segmenting
    d = session.assist.accept_segment()
    assert d is not None and d.num_vertices == 40 and session.assist.pending_segment is None
    assert session.scan.store.labelset.info(session.toolbox.settings.active_id).category == "bowl"
    session.assist.segment_at(5, wait=True)
    session.assist.discard_segment()
    assert session.assist.preview is None
    with pytest.raises(ValueError, match="no segment preview"):
        session.assist.accept_segment()


def test_resume_keeps_the_labels(tmp_path: Path) -> None:
    scan = ball_scan(tmp_path)
    s = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    iid = s.instances.new_instance(category="mug")
    s.painting.paint(np.arange(25))
    s.close()
    s2 = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        assert (s2.scan.store.labels[:25] == iid).all() and s2.toolbox.settings.active_id == iid
        assert s2.toolbox.settings.category == "mug"
    finally:
        s2.close()


def test_brush_resize_and_bad_tool(session: AnnotatorSession) -> None:
    r0 = session.toolbox.settings.radius
    assert session.instances.resize_brush(1.25) > r0
    assert session.instances.resize_brush(0.8) < session.toolbox.settings.radius * 1.25 + 1e-9
    with pytest.raises(ValueError, match="unknown tool"):
        session.instances.set_tool("nope")


def test_tool_settings_by_name() -> None:
    from annotator.tools import GROW_DISTANCE, Control, ToolSettings

    s = ToolSettings()
    assert s.shown_initial(GROW_DISTANCE) == pytest.approx(15.0)  # 0.15 m shown in cm
    lift = Control("lift_radius", "Lift radius (cm)", "slider", 15.0, min=1.0, max=30.0, step=0.5, scale=100.0)
    assert s.shown_initial(lift) == 15.0 and s.value("lift_radius") == pytest.approx(0.15)
    s.assign("lift_radius", 0.2)
    s.assign("grow_distance", 0.3)
    assert s.extra["lift_radius"] == 0.2 and s.grow_distance == 0.3 and s.value("grow_distance") == 0.3


def test_lasso_takes_only_the_visible_surface_and_says_what_it_left_out(tmp_path: Path) -> None:
    """through the session: a lasso around a box standing on a table, seen from the side and above,
    takes the box's visible faces and the table around it, not the table hidden behind the box; the history says
    how many hidden vertices were left out. "front" (the old rule) still takes them when asked for."""
    import trimesh

    from efem_viz.geometry.transforms import rotation_to_quat_wxyz

    table = trimesh.creation.box(extents=(0.6, 0.6, 0.02))
    table.apply_translation((0, 0, -0.01))
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.15))
    box.apply_translation((0, 0, 0.075))
    mesh = trimesh.util.concatenate([table.subdivide_to_size(0.004), box.subdivide_to_size(0.004)])
    path = tmp_path / "scans" / "box_on_table.ply"
    path.parent.mkdir(parents=True)
    mesh.export(path)
    s = AnnotatorSession(path, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        position = np.array([0.0, -0.45, 0.35])
        fwd = (np.array([0.0, 0.0, 0.07]) - position) / np.linalg.norm(np.array([0.0, 0.0, 0.07]) - position)
        right = np.array([1.0, 0.0, 0.0])
        cam = dict(position=position, wxyz=rotation_to_quat_wxyz(np.stack([right, np.cross(fwd, right), fwd], 1)),
                   fov=float(np.deg2rad(50)), aspect=1.0)
        pts = s.scan.scene.points
        in_box = (np.abs(pts[:, 0]) <= 0.0501) & (np.abs(pts[:, 1]) <= 0.0501) & (pts[:, 2] >= -1e-6)
        uv, _ = sel_project(pts[in_box], cam)
        lo, hi = uv.min(axis=0) - 0.02, uv.max(axis=0) + 0.02
        polygon = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        # the table top behind the box: rays from the camera to it pass through the box
        top = (pts[:, 2] > -1e-6) & (pts[:, 2] < 1e-6) & ~in_box
        hidden = top & _ray_hits_box(position, pts)
        assert hidden.sum() > 100
        s.instances.new_instance(category="box")
        d = s.box_lasso.lasso(polygon=polygon, **cam)
        assert d is not None
        taken = np.flatnonzero(s.scan.store.labels == s.toolbox.settings.active_id)
        assert hidden[taken].sum() <= 0.05 * hidden.sum()
        seen_faces = in_box & ((np.abs(pts[:, 1] + 0.05) < 1e-6) | (np.abs(pts[:, 2] - 0.15) < 1e-6))
        assert np.isin(np.flatnonzero(seen_faces), taken).mean() > 0.95  # the front and top faces
        label = s.scan.store.labelset.undo_stack[-1].label
        assert "hidden left out" in label and "(lasso" in label
        s.instances.undo()
        s.toolbox.settings.box_facing = "front"
        s.box_lasso.lasso(polygon=polygon, **cam)
        taken = np.flatnonzero(s.scan.store.labels == s.toolbox.settings.active_id)
        assert hidden[taken].sum() > 0.5 * hidden.sum(), "the old rule, on request, takes the hidden table"
    finally:
        s.close()


def sel_project(points: np.ndarray, cam: dict) -> tuple[np.ndarray, np.ndarray]:
    from annotator.selection import project

    return project(points, position=cam["position"], wxyz=cam["wxyz"], fov=cam["fov"], aspect=cam["aspect"])


def _ray_hits_box(origin: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Whether the segment origin -> point passes through the box [-5, 5] x [-5, 5] x [0.5, 15] cm (slab test,
    stopping short of the point so that a point on the box itself is not hidden by its own face)."""
    lo = np.array([-0.05, -0.05, 0.005])
    hi = np.array([0.05, 0.05, 0.15])
    d = pts.astype(np.float64) - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / d
        t1 = (hi - origin) / d
    tmin = np.nanmax(np.minimum(t0, t1), axis=1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=1)
    return (tmax >= tmin) & (tmin < 0.99) & (tmax > 0)


def test_region_grow_keeps_to_objects_on_an_imported_tabletop(tmp_path: Path) -> None:
    """region grow with min height 0 flooded a 15 cm disc of table. On a tabletop imported from an
    RGB-D frame (the table at z = 0) the min height now starts above the table's fit residual; a grow from a mug's
    side then stays on the mug. Other scans keep 0 (off)."""
    from annotator.session import TABLE_CLEARANCE_MIN, table_clearance

    assert table_clearance({"source": "rgbd", "plane_residual_rms_m": 0.00302}) == pytest.approx(0.008)
    assert table_clearance({"source": "rgbd"}) == TABLE_CLEARANCE_MIN
    for prov in (None, {}, {"source": "synthetic"}, {"source": "rgbd", "plane_residual_rms_m": "nan"}):
        assert table_clearance(prov) in (0.0, TABLE_CLEARANCE_MIN)
    assert table_clearance({"source": "synthetic", "plane_residual_rms_m": 0.003}) == 0.0
    repo = Path(__file__).resolve().parents[1]
    s = AnnotatorSession(repo / "sample_scenes" / "real_tabletop_0.ply", out_dir=tmp_path / "out", autosave_delay=0)
    try:
        assert s.toolbox.settings.grow_min_height == pytest.approx(0.008)
        s.instances.new_instance(category="mug")
        mug = s.scan.scene.instance == int(np.bincount(s.scan.scene.instance[s.scan.scene.instance > 0]).argmax())
        pts = s.scan.scene.points
        seed = int(np.flatnonzero(mug & (pts[:, 2] > 0.03))[0])
        s.painting.grow(seed)
        grown = np.flatnonzero(s.scan.store.labels == s.toolbox.settings.active_id)
        assert len(grown) > 50 and pts[grown, 2].min() >= 0.008
        assert (~mug[grown]).mean() < 0.2, "the grow stays (mostly) on the mug, not the table"
    finally:
        s.close()
    ball = AnnotatorSession(ball_scan(tmp_path), out_dir=tmp_path / "out2", autosave_delay=0)
    try:
        assert ball.toolbox.settings.grow_min_height == 0.0
    finally:
        ball.close()


def test_the_history_lists_undo_steps_and_survives_a_restart(tmp_path: Path) -> None:
    """The edit history shows one line per undo step (a brush stroke's dabs are one line, as one Ctrl+Z takes
    them back), newest first, and lists the same steps after a restart, whose undo history the journal restores."""
    from annotator.panel_views import panel_view

    scan = ball_scan(tmp_path)
    s = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        s.instances.new_instance(category="mug")
        for k in range(8):  # one stroke: eight dabs in one group
            s.painting.paint(np.arange(10 * k, 10 * k + 10), group="stroke-1")
        s.painting.paint(np.arange(200, 220))
        before = panel_view(s.scan.store, s.toolbox.settings.active_id).history
    finally:
        s.close()
    lines = [ln for ln in before.splitlines() if ln.startswith("- ")]
    assert len(lines) == 3, before  # the lone paint, the stroke, the new instance
    assert "(+7 more edits in this step)" in lines[1] and "200" not in lines[1]
    again = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        assert panel_view(again.scan.store, again.toolbox.settings.active_id).history == before
        again.instances.undo()
        assert ("(+7 more edits"
                in panel_view(again.scan.store, again.toolbox.settings.active_id).history.splitlines()[2])
    finally:
        again.close()


def test_slow_typing_of_a_name_is_one_undo_step(session: AnnotatorSession) -> None:
    """Each pause while typing commits the name so far, but the commits of one field with no other edit between
    form one undo step: one Ctrl+Z brings back the name from before the typing; an edit in between starts a new
    step."""
    iid = session.instances.new_instance(category="mug")
    before = session.scan.store.labelset.info(iid).name
    for text in ("b", "bl", "blu", "blue"):  # the person pauses after each letter: each is committed
        session.instances.type_text("name", text)
        session.instances.flush_typing()
    assert session.scan.store.labelset.info(iid).name == "blue"
    session.instances.undo()
    assert session.scan.store.labelset.info(iid).name == before
    session.instances.redo()
    session.painting.paint(np.arange(10))
    session.instances.type_text("name", "blue mug")
    session.instances.flush_typing()
    session.instances.undo()
    assert session.scan.store.labelset.info(iid).name == "blue"  # the paint was between: a step of its own
    assert not (session.scan.work_dir / "typing.json").exists()


@pytest.mark.parametrize("content", [b"{not json", b'{"instance": 1, "field": "owner", "value": "x"}',
                                     b'{"instance": 1, "field": "name", "value": "' + b"a" * 5000 + b'"}'])
def test_a_hostile_typing_file_is_dropped_and_changes_nothing(tmp_path: Path, content: bytes) -> None:
    """A damaged, foreign or oversized `typing.json` in the work folder is not applied: the session opens with
    its labels as they were, and the file is gone."""
    scan = ball_scan(tmp_path)
    s = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        iid = s.instances.new_instance(category="mug")
        name = s.scan.store.labelset.info(iid).name
    finally:
        s.close()
    typing = tmp_path / "out" / "ball.annotate" / "typing.json"
    typing.write_bytes(content)
    again = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        assert again.scan.store.labelset.info(iid).name == name and again.instances.restored_typing is None
        assert not typing.exists()
    finally:
        again.close()


def test_an_imported_scan_exports_back_on_its_own_file_frame(tmp_path: Path) -> None:
    """A user's scan in millimetres with +Y up, brought in by `import-scan` (metres, +Z up, frame recorded), is
    labelled in the annotator: the PLY export in the original frame lands on the file's own coordinates and units
    with the same per-vertex labels (and no frame record: it is no longer in the scene frame); the default export
    stays in the scene frame; the label-only formats are the same either way."""
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.data.scan import import_scan
    from tests.helpers import sample_scene

    scene = load_scene(sample_scene("syn_z_1"))
    y_up = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # +Z of the scene becomes +Y
    file_pts = (scene.points.astype(np.float64) @ y_up.T * 1000.0 + np.array([120.0, 35.0, -40.0])).astype(np.float32)
    mine = scene.__class__.create("mine", file_pts, colors=scene.colors)
    imported, frame = import_scan(load_scene(save_scene(mine, tmp_path / "raw" / "mine.ply")))
    assert (frame.units, frame.up) == ("mm", "+y")
    scan = save_scene(imported, tmp_path / "scans" / "mine.ply")
    notes: list[str] = []
    s = AnnotatorSession(scan, out_dir=tmp_path / "out", autosave_delay=0)
    try:
        s.notify = lambda title, body: notes.append(body)
        s.instances.new_instance(category="mug")
        s.painting.paint(np.arange(0, len(file_pts), 7))
        labels = s.scan.store.labels.copy()
        ply, = s.files.export("ply", directory="original", frame="original")
        assert "on the scan file's own coordinates (millimetres, +Y up (detected))" in notes[-1]
        back = load_scene(ply)
        assert np.allclose(back.points, file_pts, atol=0.05)  # 0.05 mm: float32 rounding of the round trip
        assert np.array_equal(back.instance, labels) and "scan_frame" not in back.provenance
        plain, = s.files.export("ply", directory="scene")
        assert np.array_equal(load_scene(plain).points, s.scan.scene.points)
        for fmt in ("npz", "scannet"):
            a = s.files.export(fmt, directory=f"{fmt}_scene")
            b = s.files.export(fmt, directory=f"{fmt}_original", frame="original")
            assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
        with pytest.raises(ValueError, match="export frame"):
            s.files.export("ply", frame="file")
    finally:
        s.close()


def test_a_big_scan_runs_efem_on_a_working_set_no_finer_than_its_presets(session: AnnotatorSession,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Over `EFEM_FULL_RESOLUTION_POINTS` vertices EFEM iterates on a 5 mm working set, unless the preset's own is
    coarser (`chairs`, 2.5 cm: a room scan labelled with chairs keeps it); a small scan runs the preset's as it is."""
    from annotator import efem_runs
    from annotator.parts import assist as assist_mod
    from efem_viz.em.solver import EMCancelled

    seen: list[float | None] = []

    def solve(scene: Any, *, settings: Any, **kw: Any) -> Any:
        seen.append(settings.config().compute.work_voxel)
        raise EMCancelled("enough")

    said: list[str] = []
    monkeypatch.setattr(efem_runs, "solve_scan", solve)
    monkeypatch.setattr(session, "notify", lambda _title, body: said.append(body))  # "<what the run was> was stopped"
    for preset in ("fast", "chairs"):
        session.assist.run_efem(preset=preset, wait=True)
    monkeypatch.setattr(assist_mod, "EFEM_FULL_RESOLUTION_POINTS", session.scan.n - 1)  # now a "big" scan
    for preset in ("fast", "chairs"):
        session.assist.run_efem(preset=preset, wait=True)
    assert seen == [None, 0.025, assist_mod.EFEM_BIG_SCAN_VOXEL, 0.025]
    # the run's line names the working set it iterates on: the preset's own (chairs) or the big scan's
    runs = [s for s in said if s.startswith("EFEM (")]
    mm = [m.group(1) if (m := re.search(r"on a ([0-9.]+) mm working set", s)) else None for s in runs]
    assert mm == [None, "25", f"{1000 * assist_mod.EFEM_BIG_SCAN_VOXEL:g}", "25"], runs
