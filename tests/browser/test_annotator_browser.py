"""Real-browser test of the annotator (headless Debian chromium, software WebGL): run with `-m browser`.

A Ctrl+left-drag across the scan (a mesh, and a point cloud) in the page must paint vertices: the label store changes,
and the canvas
changes colour where the stroke went. Two tabs on one scan see each other's strokes, and the store keeps both.
Tools and keys are driven only by playwright mouse and keyboard events, their effect checked on the server: the
lasso (O, Ctrl+clicks, Enter), a failing tool's error shown in the page, [ / ] brush size, Tab / Shift+Tab active
instance, ? cheat sheet.
With EFEM_SAVE_SCREENSHOTS=1 screenshots go to docs/img/ for the guide.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest
from browser_utils import (HANG_GUARD_MS, HANG_GUARD_S, changed_mask, ctrl_drag, on_view, open_viser_pages,
                           settle_canvas, wait_until)

pytestmark = [pytest.mark.browser, pytest.mark.timeout(600)]

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"
SAVE = os.environ.get("EFEM_SAVE_SCREENSHOTS") == "1"


def _last_step(app: Any) -> str:
    """The newest line of the edit history panel (what the next undo takes back)."""
    from annotator.panel_views import recent_steps

    with app.session.scan.store.lock:
        steps = recent_steps(app.session.scan.store.labelset.undo_stack, 1)
    return steps[0] if steps else ""


@pytest.fixture(params=["mesh", "points", "reduced"])
def annotator(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Any]:
    """The annotator on a small sphere (software rendering is slow): a 2.5k-vertex mesh, or 6k points (whose
    drags land on the invisible splat proxy surface), or the mesh over a display budget of 900 points (level of
    detail: a subset drawn, every vertex labelled)."""
    import trimesh

    from annotator.app import AnnotatorApp

    scan = tmp_path / "ball.ply"
    if request.param in ("mesh", "reduced"):
        trimesh.creation.icosphere(subdivisions=4, radius=0.15).export(scan)
    else:
        from efem_viz.data.io import save_scene
        from efem_viz.data.scene import Scene

        p = np.random.default_rng(0).normal(size=(6000, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        save_scene(Scene.create("ball", (0.15 * p).astype(np.float32), normals=p.astype(np.float32)), scan)
    app = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0,
                       display_points=900 if request.param == "reduced" else 1_000_000)
    assert app.view.reduced == (request.param == "reduced")
    app.session.instances.new_instance(category="mug")
    app.session.toolbox.settings.radius = 0.03
    app.kind = request.param
    yield app
    app.close()



def test_ctrl_drag_on_mesh_paints_vertices(annotator: Any, page: Any) -> None:
    """A ctrl-drag paints: the label store changes (one undoable stroke) and so does the canvas."""
    app = annotator
    iid = app.session.toolbox.settings.active_id
    page.goto(app.url)
    page.get_by_text("Tools", exact=True).first.wait_for(timeout=HANG_GUARD_MS)
    wait_until(lambda: len(app.server.get_clients()) > 0, HANG_GUARD_S, "client connection")
    before = settle_canvas(page)
    box = page.locator("canvas").first.bounding_box()
    assert box is not None
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    painted = 0
    for attempt in range(3):  # the first gesture can land while the scene is still streaming in
        ctrl_drag(page, (cx - 40, cy), (cx + 44, cy + 24))
        try:
            wait_until(lambda: int((app.session.scan.store.labels == iid).sum()) > 0, HANG_GUARD_S, "painted vertices")
        except AssertionError:
            continue
        app.wait_idle()
        painted = int((app.session.scan.store.labels == iid).sum())
        break
    assert painted > 10, "a ctrl-drag on the mesh did not paint any vertex"
    if app.view.reduced:  # the stroke labels the vertices that are not drawn too
        assert np.isin(np.flatnonzero(app.session.scan.store.labels == iid), app.view.display, invert=True).sum() > 5
    # the whole stroke is one undoable journal group
    groups = {r.header.get("group") for r in app.session.scan.store.journal.records
              if r.kind == "do" and r.arrays["idx"].size}
    assert len(groups) == 1  # one stroke landed (earlier attempts, if any, painted nothing)
    after = settle_canvas(page)
    changed = int(changed_mask(after, before).sum())
    assert changed > 50, f"the canvas barely changed after painting ({changed} pixels)"
    if SAVE:
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(DOCS_IMG / f"annotator_brush_{app.kind}.png"))
    app.session.instances.undo()
    assert int((app.session.scan.store.labels == iid).sum()) == 0



def _strokes(app: Any) -> list[tuple[str, str, np.ndarray]]:
    """(client, group, vertices) of each stroke in the journal, in order (adjacent edits of one group merged)."""
    out: list[tuple[str, str, np.ndarray]] = []
    for r in app.session.scan.store.journal.records:
        if r.kind != "do" or not r.arrays["idx"].size:
            continue
        client, group = str(r.header.get("client")), str(r.header.get("group"))
        if out and out[-1][:2] == (client, group):
            out[-1] = (client, group, np.union1d(out[-1][2], r.arrays["idx"]))
        else:
            out.append((client, group, np.unique(r.arrays["idx"])))
    return out


def _stroke(page: Any, app: Any, stroke: tuple[tuple[float, float], tuple[float, float]],
            painted: Callable[[], bool]) -> None:
    """Ctrl-drag along `stroke` (offsets from the canvas centre) until `painted()` holds, at most 3 tries (a
    gesture can land while the scene is still streaming in); then wait for the edit thread."""
    box = page.locator("canvas").first.bounding_box()
    assert box is not None
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    (x0, y0), (x1, y1) = stroke
    for _ in range(3):
        ctrl_drag(page, (cx + x0, cy + y0), (cx + x1, cy + y1), moves=6, steps=1)
        try:
            wait_until(painted, HANG_GUARD_S, "painted vertices")
        except AssertionError:
            continue
        app.wait_idle()
        return
    raise AssertionError("a ctrl-drag on the mesh did not paint any vertex")


def _seen(before: np.ndarray, after: np.ndarray, stroke: tuple[tuple[float, float], tuple[float, float]],
          margin: int = 70) -> tuple[int, int]:
    """(changed pixels near `stroke` (offsets from the canvas centre, box grown by `margin`), all changed pixels)."""
    changed = changed_mask(after, before)
    h, w = changed.shape
    (x0, y0), (x1, y1) = stroke
    xa, xb = int(w / 2 + min(x0, x1)) - margin, int(w / 2 + max(x0, x1)) + margin
    ya, yb = int(h / 2 + min(y0, y1)) - margin, int(h / 2 + max(y0, y1)) + margin
    return int(changed[max(ya, 0): yb, max(xa, 0): xb].sum()), int(changed.sum())


# Two tabs render in software on 2 cores: small pages (fewer pixels, faster input) and short strokes, above and
# below the sphere's centre (the control panel covers the right of the view).
SMALL = {"width": 960, "height": 600}
STROKE_A = ((-70.0, -50.0), (10.0, -40.0))
STROKE_B = ((-70.0, 50.0), (10.0, 60.0))


@pytest.mark.parametrize("annotator", ["mesh"], indirect=True)
def test_two_tabs_see_each_others_edits(annotator: Any, new_page: Callable[..., Any]) -> None:
    """Two browser tabs (separate contexts, like two users) on one scan (a 2.5k-vertex sphere) see each other's
    edits, and none is lost.

    Tab A paints a stroke through its page: the label store changes and tab B's canvas changes where A painted.
    Then tab B paints a second stroke below it: tab A's canvas changes there, the store keeps A's vertices and adds
    B's, and the journal holds the two strokes in order under the two tabs' client ids.
    """
    app = annotator
    iid = app.session.toolbox.settings.active_id
    tab_a, tab_b = new_page(SMALL), new_page(SMALL)
    open_viser_pages([tab_a, tab_b], app.url)
    wait_until(lambda: len(app.server.get_clients()) >= 2, HANG_GUARD_S, "two connected tabs")
    b0 = settle_canvas(tab_b)

    # ---- tab A paints; tab B shows it
    _stroke(tab_a, app, STROKE_A, painted=lambda: bool((app.session.scan.store.labels == iid).any()))
    by_a = app.session.scan.store.labels == iid
    strokes = _strokes(app)
    assert len(strokes) == 1, strokes
    client_a = strokes[0][0]
    assert np.array_equal(strokes[0][2], np.flatnonzero(by_a))
    near, total = _seen(b0, settle_canvas(tab_b), STROKE_A)
    assert near > 50, f"tab B did not show tab A's stroke ({near} pixels changed there, {total} in all)"
    assert near >= 0.5 * total, f"tab B changed mostly away from tab A's stroke ({near} of {total} pixels)"

    # ---- tab B paints elsewhere; tab A shows it; nothing of A's edit is lost
    a1 = settle_canvas(tab_a)
    _stroke(tab_b, app, STROKE_B, painted=lambda: bool(((app.session.scan.store.labels == iid) & ~by_a).any()))
    labels = app.session.scan.store.labels
    assert (labels[by_a] == iid).all(), "tab B's stroke lost vertices painted by tab A"
    by_b = (labels == iid) & ~by_a
    assert by_b.sum() > 0
    strokes = _strokes(app)
    assert [c for c, _, _ in strokes][:1] == [client_a] and len(strokes) == 2, strokes
    assert strokes[1][0] != client_a, "both strokes were journalled under one client id"
    assert set(np.flatnonzero(by_b)) <= set(strokes[1][2].tolist())
    near, total = _seen(a1, settle_canvas(tab_a), STROKE_B)
    assert near > 50, f"tab A did not show tab B's stroke ({near} pixels changed there, {total} in all)"
    assert near >= 0.5 * total, f"tab A changed mostly away from tab B's stroke ({near} of {total} pixels)"


# ============================================================================ tools and keys, by real input events
def _centre(page: Any) -> tuple[float, float, dict[str, float]]:
    box = page.locator("canvas").first.bounding_box()
    assert box is not None
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2, box


def _ctrl_click(page: Any, x: float, y: float) -> None:
    page.keyboard.down("Control")
    try:
        page.mouse.click(x, y)
    finally:
        page.keyboard.up("Control")


def _open(app: Any, page: Any) -> None:
    open_viser_pages([page], app.url)
    wait_until(lambda: len(app.server.get_clients()) > 0, HANG_GUARD_S, "client connection")


@pytest.mark.parametrize("annotator", ["mesh"], indirect=True)
def test_lasso_by_ctrl_clicks_then_enter_paints_inside(annotator: Any, new_page: Callable[..., Any]) -> None:
    """O picks the lasso; four Ctrl+clicks on the canvas make a 4-point outline at the clicked screen positions;
    Enter paints exactly the vertices inside it (as seen by the first click's camera); one undo step.

    (Before the fix every click failed on the server with "'float' object is not iterable", and Enter said "the
    lasso has 0 points".)"""
    from annotator import selection as sel

    app = annotator
    iid = app.session.toolbox.settings.active_id
    page = new_page(SMALL)
    _open(app, page)
    page.keyboard.press("o")
    wait_until(lambda: app.session.toolbox.settings.tool == "lasso", HANG_GUARD_S, "the lasso tool (O)")
    cx, cy, box = _centre(page)
    corners = [(cx - 40, cy - 35), (cx + 40, cy - 35), (cx + 40, cy + 35), (cx - 40, cy + 35)]
    for k, (x, y) in enumerate(corners):
        _ctrl_click(page, x, y)
        wait_until(lambda k=k: len(app.session.box_lasso.lasso_outline) == k + 1, HANG_GUARD_S,
                   f"lasso point {k + 1} on the server")
    expect = [((x - box["x"]) / box["width"], (y - box["y"]) / box["height"]) for x, y in corners]
    assert np.allclose(app.session.box_lasso.lasso_outline.points, expect, atol=0.01), (
        app.session.box_lasso.lasso_outline.points, expect)
    camera, polygon = app.session.box_lasso.lasso_outline.polygon()
    assert int((app.session.scan.store.labels == iid).sum()) == 0, "clicks only draw the outline"
    page.keyboard.press("Enter")
    # the edit is done (labels, redraw, history) when its history line is there
    wait_until(lambda: "(lasso" in _last_step(app), HANG_GUARD_S, "the lasso's paint (Enter)")
    inside = sel.lasso_select(app.session.scan.geom, position=camera.position, wxyz=camera.wxyz, fov=camera.fov,
                              aspect=camera.aspect, polygon=polygon)
    painted = np.flatnonzero(app.session.scan.store.labels == iid)
    assert len(painted) > 10 and np.array_equal(painted, np.sort(inside))
    assert len(app.session.box_lasso.lasso_outline) == 0
    assert page.get_by_text("that did not work").count() == 0
    app.session.instances.undo()
    assert int((app.session.scan.store.labels == iid).sum()) == 0


def test_lasso_around_a_box_takes_no_hidden_table(tmp_path: Path, new_page: Callable[..., Any]) -> None:
    """in the page: a box standing on a table, a lasso drawn with Ctrl+clicks around the box as the
    page shows it, Enter. No vertex the page's camera cannot see is labelled (exact ray casting against the mesh
    from the camera the lasso used), while the old rule ("front": whatever faces the camera) would have taken
    hidden table."""
    import open3d as o3d
    import trimesh

    from annotator import selection as sel
    from annotator.app import AnnotatorApp

    table = trimesh.creation.box(extents=(0.5, 0.5, 0.02))
    table.apply_translation((0, 0, -0.01))
    block = trimesh.creation.box(extents=(0.08, 0.08, 0.16))
    block.apply_translation((0, 0, 0.08))
    mesh = trimesh.util.concatenate([table.subdivide_to_size(0.01), block.subdivide_to_size(0.01)])
    scan = tmp_path / "box_on_table.ply"
    mesh.export(scan)
    app = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0)
    try:
        iid = app.session.instances.new_instance(category="box")
        page = new_page(SMALL)
        _open(app, page)
        page.keyboard.press("o")
        wait_until(lambda: app.session.toolbox.settings.tool == "lasso", HANG_GUARD_S, "the lasso tool (O)")
        client = next(iter(app.server.get_clients().values()))
        _, _, box = _centre(page)
        pts = app.session.scan.geom.points
        on_block = (np.abs(pts[:, 0]) <= 0.0401) & (np.abs(pts[:, 1]) <= 0.0401) & (pts[:, 2] > 0.001)
        uv, _ = sel.project(pts[on_block], position=np.asarray(client.camera.position),
                            wxyz=np.asarray(client.camera.wxyz), fov=float(client.camera.fov),
                            aspect=box["width"] / box["height"])
        lo, hi = uv.min(axis=0) - 0.03, uv.max(axis=0) + 0.03
        assert (lo > 0).all() and (hi < 1).all(), "the box is in view"
        corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
        for k, (u, v) in enumerate(corners):
            _ctrl_click(page, box["x"] + u * box["width"], box["y"] + v * box["height"])
            wait_until(lambda k=k: len(app.session.box_lasso.lasso_outline) == k + 1, HANG_GUARD_S,
                       f"lasso point {k + 1} on the server")
        camera, polygon = app.session.box_lasso.lasso_outline.polygon()
        page.keyboard.press("Enter")
        wait_until(lambda: "(lasso" in _last_step(app), HANG_GUARD_S, "the lasso's paint (Enter)")
        painted = np.flatnonzero(app.session.scan.store.labels == iid)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(pts), o3d.core.Tensor(app.session.scan.geom.faces.astype(np.uint32)))

        def hidden(idx: np.ndarray) -> np.ndarray:
            d = pts[idx].astype(np.float64) - camera.position
            dist = np.linalg.norm(d, axis=1)
            rays = np.concatenate([np.tile(camera.position, (len(idx), 1)), d / dist[:, None]], 1).astype(np.float32)
            t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            return t < dist - 0.003  # something is in front of the vertex on its ray

        front = sel.lasso_select(app.session.scan.geom, position=camera.position, wxyz=camera.wxyz, fov=camera.fov,
                                 aspect=camera.aspect, polygon=polygon, facing="front")
        assert hidden(front).sum() > 20, "the old rule takes hidden table here (else the test shows nothing)"
        assert len(painted) > 50 and on_block[painted].sum() > 20
        assert hidden(painted).sum() == 0, f"{hidden(painted).sum()} hidden vertices labelled"
        assert "hidden left out" in _last_step(app)
    finally:
        app.close()


def test_a_failing_tool_shows_its_error_in_the_page(tmp_path: Path, new_page: Callable[..., Any]) -> None:
    """An exception inside a tool's click reaches the person who clicked: a notification in the page names it."""
    import trimesh

    from annotator.app import AnnotatorApp
    from annotator.tools import DEFAULT_TOOLS, Tool

    def broken(host: Any, event: Any) -> None:
        raise TypeError("'float' object is not iterable")

    scan = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=3, radius=0.15).export(scan)
    app = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0,
                       tools=(*DEFAULT_TOOLS, Tool("broken", "Broken", "K", "raises on click", on_click=broken)))
    try:
        page = new_page(SMALL)
        _open(app, page)
        page.keyboard.press("k")
        wait_until(lambda: app.session.toolbox.settings.tool == "broken", HANG_GUARD_S, "the broken tool (K)")
        cx, cy, _ = _centre(page)
        _ctrl_click(page, cx, cy)
        page.get_by_text("TypeError: 'float' object is not iterable", exact=False).first.wait_for(timeout=HANG_GUARD_MS)
    finally:
        app.close()


@pytest.fixture(scope="module")
def keyed(browser: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Any]]:
    """One annotator (a 642-vertex sphere) and one page on it, shared by the hotkey tests (each leaves the page as it
    found it: no overlay open, focus on the page)."""
    import trimesh

    from annotator.app import AnnotatorApp

    d = tmp_path_factory.mktemp("keys")
    trimesh.creation.icosphere(subdivisions=3, radius=0.15).export(d / "ball.ply")
    app = AnnotatorApp(d / "ball.ply", out_dir=d / "out", port=0, autosave_delay=0)
    context = browser.new_context(viewport=SMALL)
    page = context.new_page()
    page.set_default_timeout(HANG_GUARD_MS)
    try:
        _open(app, page)
        yield app, page
    finally:
        context.close()
        app.close()


def test_bracket_keys_resize_the_brush(keyed: tuple[Any, Any]) -> None:
    """] makes the brush larger, [ smaller: the radius the tools use changes, and the slider shows it."""
    app, page = keyed
    r0 = app.session.toolbox.settings.radius
    def slider_shows_radius() -> bool:
        # the key handler sets the radius, then the slider: wait for both, not for the first alone
        return app.panels.gui_controls["radius"].value == pytest.approx(100 * app.session.toolbox.settings.radius)

    page.keyboard.press("]")
    wait_until(lambda: app.session.toolbox.settings.radius > r0 and slider_shows_radius(), HANG_GUARD_S,
               "a larger brush (]) on the slider")
    page.keyboard.press("[")
    page.keyboard.press("[")
    wait_until(lambda: app.session.toolbox.settings.radius < r0 and slider_shows_radius(), HANG_GUARD_S,
               "a smaller brush ([ [) on the slider")


def test_tab_makes_the_next_instance_active(keyed: tuple[Any, Any]) -> None:
    """Tab makes the next instance active (wrapping around), Shift+Tab the previous one; the Active dropdown follows."""
    app, page = keyed
    ids = [app.session.instances.new_instance(category="mug") for _ in range(3)]
    first = min(app.session.scan.store.labelset.instances)
    assert app.session.toolbox.settings.active_id == ids[-1]
    page.keyboard.press("Tab")
    wait_until(lambda: app.session.toolbox.settings.active_id == first, HANG_GUARD_S,
               "the first instance active (Tab wraps)")
    page.keyboard.press("Tab")
    second = sorted(app.session.scan.store.labelset.instances)[1]
    # the key handler sets the active id, then the dropdown: wait for both (reading between the two was a race)
    wait_until(lambda: (app.session.toolbox.settings.active_id == second
                        and str(app.panels.gui_active.value).startswith(f"{second}:")), HANG_GUARD_S,
               "the next instance active (Tab), shown in the Active dropdown")
    page.keyboard.press("Shift+Tab")
    wait_until(lambda: app.session.toolbox.settings.active_id == first, HANG_GUARD_S,
               "the previous instance active (Shift+Tab)")


def test_question_mark_toggles_the_cheat_sheet(keyed: tuple[Any, Any]) -> None:
    """? (Shift+/ on a US keyboard) opens the keyboard cheat sheet over this page, ? again closes it; so does its
    Close button."""
    app, page = keyed
    sheet = page.get_by_text("Smaller brush", exact=True)
    page.keyboard.press("Shift+Slash")
    wait_until(lambda: len(app.cheat_sheets) == 1, HANG_GUARD_S, "the cheat sheet open on the server (?)")
    sheet.wait_for(state="visible", timeout=HANG_GUARD_MS)
    page.keyboard.press("Shift+Slash")
    wait_until(lambda: not app.cheat_sheets, HANG_GUARD_S, "the cheat sheet closed on the server (? again)")
    sheet.wait_for(state="detached", timeout=HANG_GUARD_MS)
    page.keyboard.press("?")  # a layout where ? needs no Shift
    wait_until(lambda: len(app.cheat_sheets) == 1, HANG_GUARD_S, "the cheat sheet open again")
    page.get_by_role("button", name="Close (?)").click()
    wait_until(lambda: not app.cheat_sheets, HANG_GUARD_S, "the cheat sheet closed by its button")
    sheet.wait_for(state="detached", timeout=HANG_GUARD_MS)


# ============================================================================ camera (item 4)
def _camera(app: Any) -> tuple[Any, np.ndarray, np.ndarray]:
    """(client handle, position, look-at) of the page's camera as the server last heard it."""
    handle = next(iter(app.server.get_clients().values()))
    return handle, np.array(handle.camera.position), np.array(handle.camera.look_at)


def test_tool_hotkeys_leave_the_camera_alone(keyed: tuple[Any, Any]) -> None:
    """Each tool's hotkey, held down for a while as a person might, switches the tool and never moves the camera.

    (viser's client flies the camera while W/A/S/D/Q/E are held, and a key pressed after a pause throws it tens of
    metres: erase was E and segment S, so picking either flew the camera off the scan.)"""
    from annotator.tools import DEFAULT_TOOLS

    app, page = keyed
    handle, pos0, look0 = _camera(app)
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    handle.camera.on_update(lambda cam: seen.append((np.array(cam.position), np.array(cam.look_at))))
    diag = float(np.linalg.norm(np.ptp(app.session.scan.scene.points, axis=0)))
    order = [t for t in DEFAULT_TOOLS if t.name != app.session.toolbox.settings.tool] + [
        t for t in DEFAULT_TOOLS if t.name == app.session.toolbox.settings.tool]
    for t in order:
        page.wait_for_timeout(600)  # idle first: the first frame after a pause spans it
        page.keyboard.down(t.hotkey.lower())
        try:
            wait_until(lambda t=t: app.session.toolbox.settings.tool == t.name, HANG_GUARD_S,
                       f"the {t.name} tool ({t.hotkey})")
            page.wait_for_timeout(400)  # held: frames are drawn meanwhile
        finally:
            page.keyboard.up(t.hotkey.lower())
    page.wait_for_timeout(1500)  # camera messages (20 Hz) of any motion have arrived
    moved = [float(max(np.linalg.norm(p - pos0), np.linalg.norm(q - look0))) for p, q in seen]
    assert max(moved, default=0.0) < 1e-3 * diag, f"a tool hotkey moved the camera by up to {max(moved):.3f} m"
    assert not app.view.camera_guard.resets, app.view.camera_guard.resets


def test_camera_thrown_off_the_scan_comes_back(keyed: tuple[Any, Any]) -> None:
    """W held after a pause throws viser's camera off the scan: the server puts it back and says so in the page; R
    then puts it exactly on the fitted view."""
    from efem_viz.serve.camera import view_lost

    app, page = keyed
    handle, _, _ = _camera(app)
    lo, hi = app.session.scan.scene.points.min(axis=0), app.session.scan.scene.points.max(axis=0)
    page.wait_for_timeout(1000)
    page.keyboard.down("w")
    try:
        wait_until(lambda: app.view.camera_guard.resets.get(handle.client_id, 0) >= 1, HANG_GUARD_S,
                   "the camera put back")
    finally:
        page.keyboard.up("w")
    page.get_by_text("View reset", exact=True).first.wait_for(timeout=HANG_GUARD_MS)
    wait_until(lambda: not view_lost(handle.camera.look_at, lo, hi), HANG_GUARD_S, "the camera back at the scan")
    # the camera glides on for a moment after the key is released, and its reports (20 Hz) trail it: wait until it
    # has stopped, so that no report of the glide reaches the server after R's placement
    last = [time.monotonic()]
    handle.camera.on_update(lambda _cam: last.__setitem__(0, time.monotonic()))
    wait_until(lambda: time.monotonic() - last[0] > 1.0, HANG_GUARD_S, "the camera at rest")
    page.keyboard.press("r")
    _wait_on_fitted_view(app, handle, "the fitted view (R)")


def _wait_on_fitted_view(app: Any, handle: Any, what: str, canvas: Callable[[float], bool] = lambda _a: True,
                         *, leaving: Any = None) -> Any:
    """Wait until the page's camera sits on the fitted view the server last put it on (for its canvas, clear of the
    control panel) and the canvas's aspect (width / height) satisfies `canvas`; with `leaving`, until that view is
    another than `leaving` (a resize: the canvas reports its new shape before the server has placed the camera for
    it, and for that moment the camera still sits on the old view). Returns that view. A timeout says where the
    camera, that view and the canvas are. (The canvas's pixel count follows viser's frame-rate-scaled pixel ratio,
    so views are compared with what the server placed, not recomputed from the size now.)"""
    guard = app.view.camera_guard

    def aspect() -> float:
        return float(handle.camera.image_width) / max(float(handle.camera.image_height), 1.0)

    def placed() -> bool:
        view = guard.last_placed(handle, home=True)
        return (leaving is None or view != leaving) and on_view(handle, view)

    try:
        wait_until(lambda: canvas(aspect()) and placed(), HANG_GUARD_S, what)
    except AssertionError as exc:  # say where the camera is, so that a failure elsewhere can be read
        raise AssertionError(
            f"{exc}: camera at {np.round(handle.camera.position, 4).tolist()} looking at "
            f"{np.round(handle.camera.look_at, 4).tolist()}, fitted view {guard.last_placed(handle, home=True)}, "
            f"canvas {handle.camera.image_width}x{handle.camera.image_height}, "
            f"clients {list(app.server.get_clients())}, "
            f"resets {guard.resets}") from None
    return guard.last_placed(handle, home=True)


def test_a_resized_window_keeps_the_scan_framed(keyed: tuple[Any, Any]) -> None:
    """R, then the browser window made narrower: the camera moves to the view fitted to the new canvas (the server
    sees the new shape and the camera on that view); back to the old size, back to a view fitted to it."""
    app, page = keyed
    handle, _, _ = _camera(app)
    page.keyboard.press("r")
    wide = _wait_on_fitted_view(app, handle, "the fitted view (R)")
    shape = SMALL["width"] / SMALL["height"]
    narrow = (SMALL["width"] - 260) / SMALL["height"]
    try:
        page.set_viewport_size({"width": SMALL["width"] - 260, "height": SMALL["height"]})
        moved = _wait_on_fitted_view(app, handle, "the view fitted to the narrower window",
                                     lambda a: abs(a - narrow) < 0.05, leaving=wide)
        # the narrower canvas sees less across: the fitted view stands further back
        assert np.linalg.norm(np.subtract(moved.position, moved.look_at)) > np.linalg.norm(
            np.subtract(wide.position, wide.look_at))
    finally:
        page.set_viewport_size(SMALL)
    _wait_on_fitted_view(app, handle, "the view fitted to the window again", lambda a: abs(a - shape) < 0.05,
                         leaving=moved)


def test_a_click_off_the_scan_says_so(keyed: tuple[Any, Any]) -> None:
    """With the segment tool (C), a Ctrl+click beside the scan tells the user that it missed the scan (it used to
    do nothing, silently)."""
    app, page = keyed
    page.keyboard.press("c")
    wait_until(lambda: app.session.toolbox.settings.tool == "segment", HANG_GUARD_S, "the segment tool (C)")
    app.reset_view()
    _, _, box = _centre(page)
    _ctrl_click(page, box["x"] + 0.12 * box["width"], box["y"] + 0.88 * box["height"])
    page.get_by_text("Missed the scan", exact=True).first.wait_for(timeout=HANG_GUARD_MS)
    assert app.session.assist.pending_segment is None


# ====================================================================== brush cursor and labels-only view (item 13)
@pytest.mark.parametrize("annotator", ["mesh"], indirect=True)
def test_brush_cursor_and_labels_only_view(annotator: Any, new_page: Callable[..., Any]) -> None:
    """A Ctrl+drag paints and leaves the brush cursor (a ring of the brush radius) where the stroke ended; ] makes
    the ring larger; the eraser keeps it, region grow hides it. A mouse click on *Labels only* dims every unlabelled
    vertex on the server (the painted ones keep their colour) and the canvas changes; a second click restores."""
    app = annotator
    iid = app.session.toolbox.settings.active_id
    page = new_page(SMALL)
    _open(app, page)
    assert app.session.brush.cursor is None
    _stroke(page, app, STROKE_A, painted=lambda: bool((app.session.scan.store.labels == iid).any()))
    wait_until(lambda: app.session.brush.cursor is not None and app.view.cursor_handle is not None, HANG_GUARD_S,
               "the brush cursor drawn")
    cur = app.session.brush.cursor
    assert (cur.visible and app.view.cursor_handle.visible
            and cur.radius == pytest.approx(app.session.toolbox.settings.radius))
    painted = np.flatnonzero(app.session.scan.store.labels == iid)
    gap = np.min(np.linalg.norm(app.session.scan.scene.points[painted] - cur.position, axis=1))
    assert gap <= app.session.toolbox.settings.radius, f"the cursor is {gap:.3f} m from the painted vertices"
    r0 = cur.radius
    page.keyboard.press("]")
    wait_until(lambda: app.session.brush.cursor.radius > r0, HANG_GUARD_S, "a larger ring (])")

    def ring() -> float:
        seg = np.asarray(app.view.cursor_handle.points, np.float64)
        return float(np.linalg.norm(seg[:, 0] - seg[:, 0].mean(axis=0), axis=1).mean())

    # the key sets the radius, then the ring is redrawn: wait for both (reading between the two was a race)
    wait_until(lambda: abs(ring() - app.session.toolbox.settings.radius) <= 1e-3 * app.session.toolbox.settings.radius,
               HANG_GUARD_S, "the ring redrawn at the new radius")
    page.keyboard.press("x")
    wait_until(lambda: app.session.toolbox.settings.tool == "erase", HANG_GUARD_S, "the erase tool (X)")
    assert app.session.brush.cursor.visible
    page.keyboard.press("g")
    wait_until(lambda: app.session.toolbox.settings.tool == "grow", HANG_GUARD_S, "the grow tool (G)")
    wait_until(lambda: not app.view.cursor_handle.visible, HANG_GUARD_S, "the ring hidden for region grow")
    page.keyboard.press("b")
    wait_until(lambda: app.session.toolbox.settings.tool == "brush" and app.view.cursor_handle.visible, HANG_GUARD_S,
               "the ring back (B)")

    def drawn() -> np.ndarray:
        out = np.zeros((app.session.scan.n, 3), np.uint8)
        for c, h in enumerate(app.view.chunk_handles):
            out[app.view.chunks.members(c)] = np.asarray(h.colors)
        return out

    before_cols, before_img = drawn(), settle_canvas(page)
    labels = app.session.scan.store.labels.copy()
    box = page.get_by_role("checkbox", name="Labels only")
    box.click()
    wait_until(lambda: app.session.toolbox.settings.labels_only, HANG_GUARD_S, "the labels-only view on (click)")
    wait_until(lambda: not np.array_equal(drawn()[labels == 0], before_cols[labels == 0]), HANG_GUARD_S,
               "dimmed vertices")
    on = drawn()
    rest = on[labels == 0]
    assert (rest[:, 0] == rest[:, 1]).all() and (rest[:, 1] == rest[:, 2]).all() and rest.min() >= 180
    assert np.array_equal(on[labels == iid], before_cols[labels == iid])
    changed = int(changed_mask(settle_canvas(page), before_img, threshold=30).sum())
    assert changed > 200, f"the canvas barely changed with the labels-only view ({changed} pixels)"
    if SAVE:
        page.mouse.move(5, 5)  # no tooltip over the panel
        page.wait_for_timeout(800)
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(DOCS_IMG / "annotator_labels_only.png"))
    box.click()
    wait_until(lambda: not app.session.toolbox.settings.labels_only, HANG_GUARD_S, "the labels-only view off (click)")
    wait_until(lambda: np.array_equal(drawn(), before_cols), HANG_GUARD_S, "the scan's colours back")
    assert np.array_equal(app.session.scan.store.labels, labels)


def _text_field(page: Any, label: str) -> Any:
    """The text input of a viser text control, found by its visible label (viser does not tie the two)."""
    return page.get_by_text(label, exact=True).first.locator("xpath=following::input[1]")


def test_typing_a_category_is_one_edit_and_the_field_shows_what_is_stored(keyed: tuple[Any, Any]) -> None:
    """each typing pause used to be an edit, and once the store kept "b" while the field showed
    "box". Typed with real keys (with pauses, as a person types), the category is committed once, after the field
    is left alone or on the next action, and the field and the store agree."""
    app, page = keyed
    iid = app.session.instances.new_instance(category="object")
    field = _text_field(page, "Category")
    wait_until(lambda: field.input_value() == "object", HANG_GUARD_S, "the active instance's category in the field")
    before = len(app.session.scan.store.journal.records)
    typing = app.session.instances.typing
    idle_s, typing.idle_s = typing.idle_s, 25 * 0.4  # the pauses below are 1/25 of it: a busy machine may stretch them
    try:
        field.click()
        page.keyboard.press("Control+A")
        for key in "box":
            page.keyboard.type(key)
            page.wait_for_timeout(400)  # a person's pause between keys (shorter than the commit's idle time)
        wait_until(lambda: app.session.scan.store.labelset.info(iid).category == "box", HANG_GUARD_S,
                   "the typed category stored")
    finally:
        typing.idle_s = idle_s
    edits = [r for r in app.session.scan.store.journal.records[before:] if r.kind == "do"]
    assert len(edits) == 1 and "category='box'" in edits[0].header["label"], [r.header.get("label") for r in edits]
    assert field.input_value() == "box" and app.panels.gui_category.value == "box"
    # typing, then an action at once (N: a new instance) commits the typed name first, to the instance it was for.
    # Keys and hotkeys reach the server on separate paths: a key that trails the N by up to `late_keys_s` (any value)
    # or `late_continuation_s` (one that continues the committed name) still goes to the name's instance. A busy
    # machine may stretch that trail, so the short window is widened here as the idle time was above (both rules
    # are tested without a browser, in tests/test_typing_buffer.py)
    instances = app.session.instances
    late_s, instances.late_keys_s = instances.late_keys_s, 25 * instances.late_keys_s
    try:
        name = _text_field(page, "Name")
        name.click()
        page.keyboard.press("Control+A")
        page.keyboard.type("left box")
        page.mouse.click(40, 40)  # leave the field: a plain click on the view's corner (no edit)
        page.keyboard.press("n")
        wait_until(lambda: app.session.toolbox.settings.active_id != iid, HANG_GUARD_S, "a new instance (N)")
        wait_until(lambda: app.session.scan.store.labelset.info(iid).name == "left box", HANG_GUARD_S,
                   "the typed name stored")
    finally:
        instances.late_keys_s = late_s
    assert app.session.scan.store.labelset.info(app.session.toolbox.settings.active_id).category == "box"


def _pick(page: Any, label: str, option: str) -> None:
    """Choose `option` from the dropdown labelled `label` with the mouse, once the panel has stopped moving. A
    dropdown that closes before its option can be clicked (a panel redrawn meanwhile, on a busy machine) is opened
    again, at most 5 times."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeoutError

    box = page.get_by_role("combobox", name=label)
    for _ in range(5):
        _settled_boxes(page, [box])  # a folder opens with an animation, and a list opened meanwhile closes again
        box.click()
        try:
            page.get_by_role("option", name=option, exact=True).click(timeout=HANG_GUARD_MS // 10)
            return
        except PlaywrightTimeoutError:
            page.keyboard.press("Escape")
    raise AssertionError(f"could not pick {option!r} in {label!r}")


def test_choosing_the_chair_prior_in_the_page_sets_the_run_preset(keyed: tuple[Any, Any]) -> None:
    """In EFEM assist, a person picks the chair prior from *Prior for Segment tool* with the mouse: the server
    solves with it, and the page's *Run preset* now shows `chairs` (the chair prior's settings, whose floor joins
    no chair); picking the mug prior again brings back the scan's own preset, in the page too."""
    app, page = keyed
    p = app.panels
    own = p.gui_efem_preset.value
    assert "chair" in tuple(p.gui_prior.options) and own != "chairs"
    page.get_by_text("EFEM assist", exact=True).first.click()  # the folder starts collapsed
    preset = page.get_by_role("combobox", name="Run preset")
    try:
        for prior, want in (("chair", "chairs"), ("mug", own)):
            _pick(page, "Prior for Segment tool", prior)
            wait_until(lambda prior=prior: app.session.toolbox.settings.prior == prior, HANG_GUARD_S,
                       f"the {prior} prior on the server")
            wait_until(lambda want=want: p.gui_efem_preset.value == want and preset.input_value() == want,
                       HANG_GUARD_S, f"the Run preset {want!r} on the server and in the page")
    finally:
        page.keyboard.press("Escape")  # no list left open
        page.get_by_text("EFEM assist", exact=True).first.click()


def _settled_boxes(page: Any, locators: list[Any], *, timeout: float = HANG_GUARD_S) -> list[Any]:
    """The locators' bounding boxes once two reads 300 ms apart agree (panels animate when folders open)."""
    prev = [loc.bounding_box() for loc in locators]
    end = time.monotonic() + timeout  # a hang guard
    while time.monotonic() < end:
        page.wait_for_timeout(300)
        now = [loc.bounding_box() for loc in locators]
        if now == prev:
            return now
        prev = now
    raise AssertionError("the panel kept moving")


def test_growing_table_and_history_move_no_button(keyed: tuple[Any, Any]) -> None:
    """pre-label buttons moved after each Accept/Reject (the instance table above them grew) and a
    second click on *Next ▶* hit *◀ Previous*. The table and the history now sit below every button."""
    app, page = keyed
    page.get_by_text("EFEM assist", exact=True).first.click()  # the folder starts collapsed
    buttons = [page.get_by_role("button", name=n, exact=True) for n in ("Next pre-label ▶", "Accept", "Undo (Ctrl+Z)")]
    buttons[0].wait_for(timeout=HANG_GUARD_MS)
    before = _settled_boxes(page, buttons)  # the folder opens with an animation: measure once it has ended
    n0 = len(app.session.scan.store.labelset.instances)
    for _ in range(6):  # six more rows in the table, six more lines in the history
        app.session.instances.new_instance(category="mug")
    app.session.painting.paint(np.arange(20))
    wait_until(lambda: page.get_by_text(f"{n0 + 6} ", exact=False).count() > 0, HANG_GUARD_S, "the table's new rows")
    page.wait_for_timeout(300)
    after = _settled_boxes(page, buttons)
    for name, b0, b1 in zip(("Next", "Accept", "Undo"), before, after):
        assert b0 is not None and b1 is not None and abs(b1["y"] - b0["y"]) < 1.0, (name, b0, b1)
    page.get_by_text("EFEM assist", exact=True).first.click()


def test_run_efem_from_the_page_progress_cancel_then_prelabels(tmp_path: Path, new_page: Callable[..., Any],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A person opens EFEM assist, clicks *Run EFEM on this scan*, sees what it does, clicks *Cancel EFEM run*
    (nothing is added), chooses *Free space* off, then runs it to the end (the real solver; the analytic sphere prior
    stands in for a shipped one) and accepts the best pre-labels with *Accept all ≥ cut*: every step by mouse and
    keyboard in the page, checked on the server."""
    import threading

    import torch

    import annotator.efem_runs as efem_runs
    from annotator.app import AnnotatorApp
    from annotator.labels import unreviewed_prelabels
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene
    from efem_viz.em.solver import EMCancelled
    from efem_viz.em.solver import StepInfo
    from efem_viz.prior import analytic

    torch.set_num_threads(1)
    spheres = analytic.make_sphere_scene(seed=0, spacing=0.01, name="spheres")
    save_scene(Scene.create("bare", spheres.points, normals=spheres.normals, colors=spheres.colors),
               tmp_path / "bare.ply")
    prior = analytic.make_sphere_prior()
    monkeypatch.setattr(efem_runs, "get_prior", lambda name: prior)
    real_solve = efem_runs.solve_scan
    cancelled = threading.Event()
    modes: list[str] = []

    def slow_then_real(scene: Any, **kw: Any) -> Any:
        modes.append(kw["settings"].free_space)
        if not cancelled.is_set():  # the first run: steps until the person cancels it
            kw["on_step"](StepInfo(step=0, num_steps=30, phase=1, active=80, elapsed_s=1.0))
            assert kw["cancel"].wait(60), "never cancelled"
            cancelled.set()
            raise EMCancelled("cancelled")
        return real_solve(scene, **kw)

    monkeypatch.setattr(efem_runs, "solve_scan", slow_then_real)
    app = AnnotatorApp(tmp_path / "bare.ply", out_dir=tmp_path / "out", port=0, autosave_delay=0)
    try:
        page = new_page(SMALL)
        _open(app, page)
        page.get_by_text("EFEM assist", exact=True).first.click()  # the folder starts collapsed
        proposals = page.get_by_label("Proposals")
        proposals.fill("16")
        proposals.press("Enter")
        wait_until(lambda: app.panels.gui_efem_proposals.value == 16, HANG_GUARD_S, "the proposal count")
        page.get_by_role("button", name="Run EFEM on this scan").click()
        status = page.get_by_text("step 1 of 30", exact=False).first
        status.wait_for(timeout=HANG_GUARD_MS)
        assert app.session.assist.efem_running
        box, view = status.bounding_box(), page.viewport_size  # seen where Run was clicked, not below the fold
        assert box is not None and 0 <= box["y"] and box["y"] + box["height"] <= view["height"], (box, view)
        page.get_by_role("button", name="Cancel EFEM run").click()
        wait_until(lambda: cancelled.is_set() and not app.session.assist.efem_running, HANG_GUARD_S, "the run to stop")
        assert not unreviewed_prelabels(app.session.scan.store.labelset.instances)
        page.get_by_role("combobox", name="Free space").click()  # the second run without the free-space check
        page.get_by_role("option", name="off", exact=True).click()
        wait_until(lambda: app.panels.gui_efem_free_space.value == "off", HANG_GUARD_S, "the mode on the server")
        page.get_by_role("button", name="Run EFEM on this scan").click()
        wait_until(lambda: bool(unreviewed_prelabels(app.session.scan.store.labelset.instances))
                   and not app.session.assist.efem_running, 120, "the pre-labels of a finished run")
        pre = unreviewed_prelabels(app.session.scan.store.labelset.instances)
        page.get_by_role("button", name="Accept all ≥ cut").click()
        wait_until(lambda: len(unreviewed_prelabels(app.session.scan.store.labelset.instances)) < len(pre),
                   HANG_GUARD_S, "the best pre-labels accepted")
        accepted = [i for i in pre if "accepted" in app.session.scan.store.labelset.instances[i].note]
        assert accepted and all((app.session.scan.store.labels == i).any() for i in accepted)
        assert modes == ["auto", "off"]
    finally:
        app.close()
