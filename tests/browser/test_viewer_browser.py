"""Real-browser tests of the viewer (headless Debian chromium, software WebGL): run with `-m browser`.

The page must render something non-blank, and moving the step slider and the confidence threshold in the GUI
must change what is drawn. With EFEM_SAVE_SCREENSHOTS=1 the screenshots are also written to docs/img/ for the user
guide (off by default, so CI leaves the tree clean).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
from browser_utils import HANG_GUARD_MS, HANG_GUARD_S, SETTLE_S, on_view, png_to_array, settle, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.timeout(600)]

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"
SAVE = os.environ.get("EFEM_SAVE_SCREENSHOTS") == "1"


@pytest.fixture(scope="module")
def viewer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A viewer on a small sphere scene (≈5k points) with a saved EM result from the real solver.

    With EFEM_GUIDE_SCENES=<folder> (screenshots for the user guide) the viewer opens that folder instead, with the
    default prior, on the scene EFEM_GUIDE_SCENE (default: the first one with a saved result).
    """
    from efem_viz.viewer.app import ViewerApp

    guide = os.environ.get("EFEM_GUIDE_SCENES")
    if guide:
        app = ViewerApp([guide], port=0, open_first=False)
        wanted = os.environ.get("EFEM_GUIDE_SCENE")
        names = [e.name for e in app.state.entries if wanted in (None, e.name) and e.trace_path.is_file()]
        if not names or not app.open_scene(names[0]):
            app.stop()
            pytest.skip(f"no scene with a saved result in {guide}")
        assert app.wait_idle(300)
        yield app
        app.stop()
        return
    import torch

    from efem_viz import em
    from efem_viz.data.io import save_scene
    from efem_viz.prior import analytic

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("browser_scenes")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    save_scene(scene, d / "spheres.ply")
    prior = analytic.make_sphere_prior()
    result = em.run_em(scene, prior, em.preset("fast").with_proposals(16).replace(elimination={"min_size": 30}), seed=0)
    result.save(d / "spheres.efem.npz")
    app = ViewerApp([d], port=0, prior=prior)
    assert app.wait_idle(60)
    yield app
    app.stop()




def _canvas_png(page: Any) -> np.ndarray:
    png = page.screenshot()  # the 3-D view fills the page; the control panel sits at the right
    img = png_to_array(png)
    return img[:, : int(img.shape[1] * 0.7)]


def _settle(page: Any, *, timeout: float = SETTLE_S) -> np.ndarray:
    """Canvas screenshot once rendering has settled."""
    return settle(lambda: _canvas_png(page), page, timeout=timeout)


def _changed_pixels(a: np.ndarray, b: np.ndarray) -> int:
    """Number of pixels whose colour changed clearly (sum of |ΔRGB| > 60)."""
    return int((np.abs(a - b).sum(axis=-1) > 60).sum())


def _open(page: Any, app: Any, *, close_notice: bool = True, canvas: bool = True) -> None:
    page.goto(app.url)
    if canvas:
        page.wait_for_function(
            "Array.from(document.querySelectorAll('canvas')).some(c => c.width > 0 && c.height > 0)",
            timeout=HANG_GUARD_MS
        )
    wait_until(lambda: len(app.server.get_clients()) >= 1, HANG_GUARD_S, "the client to connect")
    page.get_by_role("tab", name="Scene").wait_for(timeout=HANG_GUARD_MS)
    if close_notice:  # hide the "software WebGL rendering" notice of headless chromium: clean screenshots
        page.add_style_tag(content="#webgl-software-rendering { display: none !important; }")


def _save(page: Any, name: str) -> None:
    if SAVE:
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(DOCS_IMG / name))


def test_page_renders_scene(viewer: Any, page: Any) -> None:
    _open(page, viewer)
    img = _settle(page)
    assert img.std() > 8.0, f"canvas looks blank (pixel std {img.std():.2f})"
    # The scene (grey table, coloured instances) is drawn: several distinct colours on the canvas.
    colors = {tuple(c) for c in (img[::8, ::8] // 32).reshape(-1, 3)}
    assert len(colors) > 4
    _save(page, "viewer_overview.png")


FRAME_COUNTER = """
window.__efemFrames = 0;
window.__efemLastClear = -1e9;
for (const C of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
  if (!C) continue;
  const clear = C.prototype.clear;
  C.prototype.clear = function (...args) {  // three.js clears once or more per rendered frame
    const now = performance.now();
    if (now - window.__efemLastClear > 4) window.__efemFrames++;
    window.__efemLastClear = now;
    return clear.apply(this, args);
  };
}
"""


def test_an_idle_page_draws_on_demand_not_every_frame(viewer: Any, page: Any) -> None:
    """With nothing moving and nothing changing, the page renders only when asked (viser's on-demand loop and
    its 1 Hz safety heartbeat), not at the display's frame rate: a browser left open on the viewer idles. Counted
    in rendered frames over 10 s of idle (a continuous loop renders ~600; measured 10-11, the heartbeat)."""
    page.add_init_script(FRAME_COUNTER)
    _open(page, viewer)
    _settle(page)
    assert page.evaluate("window.__efemFrames") > 0, "the frame counter saw no frame at all"
    time.sleep(3)  # the settle windows of the last changes close
    before = page.evaluate("window.__efemFrames")
    time.sleep(10)
    idle = page.evaluate("window.__efemFrames") - before
    assert idle <= 25, f"{idle} frames rendered in 10 s of idle"


def _saturated(img: np.ndarray, *, green: bool = False) -> int:
    """Clearly coloured pixels of the 3-D view left of the control panel (not white or grey; `green`: green ones
    only; the legend's swatches sit in the panel)."""
    rgb = img[:, : int(img.shape[1] * 0.66), :3].astype(int)
    if green:
        return int(((rgb[..., 1] > rgb[..., 0] + 40) & (rgb[..., 1] > rgb[..., 2] + 40)).sum())
    return int((rgb.max(axis=-1) - rgb.min(axis=-1) > 60).sum())


def test_tp_fp_view_draws_the_boxes_green_and_red_and_gives_them_back(viewer: Any, page: Any) -> None:
    """The TP / FP / FN colouring redraws every box in green (TP) or red (FP), as the legend says, and the
    instances colouring gives each box its own colour back (boxes were drawn white after the switch). The points
    are hidden so that only the boxes and labels are on the canvas."""
    _open(page, viewer)
    points = viewer.nodes.points
    try:
        points.visible = False
        own = _settle(page)
        assert _saturated(own) > 200, "the boxes are not drawn in their instance colours"
        viewer.set_color_mode("gt_match")
        wait_until(lambda: viewer.state.color_mode == "gt_match", HANG_GUARD_S, "the TP/FP/FN colours")
        points.visible = False  # a recolour may resend the cloud
        tp = _settle(page)
        assert _saturated(tp, green=True) > 200, "no green (TP) box on the canvas"
        viewer.set_color_mode("instances")
        points.visible = False
        back = _settle(page)
        assert _saturated(back, green=True) < _saturated(tp, green=True) / 4
        assert _saturated(back) > 200, "the boxes did not get their own colours back"
    finally:
        viewer.set_color_mode("rgb")
        points.visible = True


def test_step_slider_changes_view(viewer: Any, page: Any) -> None:
    _open(page, viewer)
    page.get_by_role("tab", name="Timeline").click()
    slider = page.get_by_role("slider").first
    slider.wait_for(timeout=HANG_GUARD_MS)
    page.get_by_text("P1", exact=True).first.wait_for(timeout=HANG_GUARD_MS)  # the phase marks reach the browser
    before = _settle(page)
    last = viewer.state.step
    slider.focus()
    page.keyboard.press("Home")  # step 0: many more proposals alive, other samples and shapes
    wait_until(lambda: viewer.state.step == 0, HANG_GUARD_S, "the step callback")
    assert viewer.wait_idle(60)
    after = _settle(page)
    assert last != 0
    changed = _changed_pixels(after, before)
    assert changed > 1500, f"moving the step slider did not change the canvas ({changed} pixels changed)"
    _save(page, "viewer_timeline.png")
    slider.focus()
    page.keyboard.press("End")
    wait_until(lambda: viewer.state.step == last, HANG_GUARD_S, "the step callback")


def test_step_slider_keeps_its_arrow_keys(viewer: Any, page: Any) -> None:
    """arrow keys on the focused Step slider step through EM iterations and leave the camera
    where it is; the same keys on the 3-D view still move the camera (the check can see a move)."""
    _open(page, viewer)
    page.get_by_role("tab", name="Timeline").click()
    slider = page.get_by_role("slider").first
    slider.wait_for(timeout=HANG_GUARD_MS)
    client = next(iter(viewer.server.get_clients().values()))
    slider.focus()
    page.keyboard.press("End")
    wait_until(lambda: viewer.state.step > 3, HANG_GUARD_S, "the last step")
    start = viewer.state.step

    def pose() -> np.ndarray:
        return np.r_[np.asarray(client.camera.position, float), np.asarray(client.camera.wxyz, float)]

    page.wait_for_timeout(600)
    before = pose()
    for _ in range(3):  # held a little, as a person presses: viser's camera moves per frame while a key is down
        page.keyboard.down("ArrowLeft")
        page.wait_for_timeout(150)
        page.keyboard.up("ArrowLeft")
    wait_until(lambda: viewer.state.step == start - 3, HANG_GUARD_S, "three steps back")
    page.wait_for_timeout(800)  # a camera move would have reached the server by now
    assert np.allclose(pose(), before, atol=1e-6), f"the camera moved with the slider's keys: {before} -> {pose()}"
    # the control: the same key on the 3-D view moves the camera
    page.evaluate("document.activeElement && document.activeElement.blur()")
    page.keyboard.down("ArrowLeft")
    page.wait_for_timeout(400)
    page.keyboard.up("ArrowLeft")
    wait_until(lambda: not np.allclose(pose(), before, atol=1e-4), HANG_GUARD_S,
               "the camera to move with a key on the view")
    assert viewer.state.step == start - 3  # and the step stayed


def test_threshold_changes_view(viewer: Any, page: Any) -> None:
    _open(page, viewer)
    page.get_by_role("tab", name="Results").click()
    slider = page.get_by_role("slider").first
    slider.wait_for(timeout=HANG_GUARD_MS)
    viewer.set_proposal_layers(shapes=False, samples=False)  # only the final instances on screen
    viewer.set_threshold(0.0)
    # the legend names each instance's category, in the category's colour
    category = str(viewer.state.result.instances.category[0])  # "sphere" here, "mug" on the guide's scenes
    legend = page.locator("b", has_text=category)
    wait_until(lambda: legend.count() == len(viewer.state.result.instances), HANG_GUARD_S,
               "one legend row per instance")
    before = _settle(page)
    _save(page, "viewer_results.png")
    slider.focus()
    page.keyboard.press("End")  # above every confidence: all instances hidden, points back to scene colours
    wait_until(lambda: viewer.state.threshold > float(np.max(viewer.state.result.instances.confidence)), HANG_GUARD_S,
               "threshold")
    after = _settle(page)
    changed = _changed_pixels(after, before)
    assert changed > 1500, f"moving the threshold did not change the canvas ({changed} pixels changed)"
    slider.focus()
    page.keyboard.press("Home")
    wait_until(lambda: viewer.state.threshold == 0.0, HANG_GUARD_S, "threshold reset")
    viewer.set_proposal_layers(shapes=True, samples=True)


def test_two_clients_share_state(viewer: Any, browser: Any, page: Any) -> None:
    _open(page, viewer, close_notice=False, canvas=False)
    ctx2 = browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        page2 = ctx2.new_page()
        _open(page2, viewer, close_notice=False, canvas=False)
        wait_until(lambda: len(viewer.server.get_clients()) >= 2, HANG_GUARD_S, "two clients")
        page.get_by_role("tab", name="Timeline").click()
        page2.get_by_role("tab", name="Timeline").click()
        viewer.set_step(1)
        s2 = page2.get_by_role("slider").first
        wait_until(lambda: s2.get_attribute("aria-valuenow") == "1", HANG_GUARD_S, "the second client to see step 1")
        viewer.set_step(viewer.state.num_steps - 1)
    finally:
        ctx2.close()


# ---------------------------------------------------------------------------------------------- user-guide shots
guide_only = pytest.mark.skipif(not SAVE, reason="screenshots for docs/USER_GUIDE.md: set EFEM_SAVE_SCREENSHOTS=1")


@guide_only
def test_guide_run_tab(viewer: Any, page: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    import efem_viz.em as em

    real_run_em = em.run_em

    def slowed_run_em(*args: Any, on_step: Any = None, **kw: Any) -> Any:
        def step(info: Any) -> None:  # a real run, paused 0.4 s per step so that the shot catches it running
            on_step(info)
            time.sleep(0.4)

        return real_run_em(*args, on_step=step, **kw)

    monkeypatch.setattr(em, "run_em", slowed_run_em)
    _open(page, viewer)
    page.get_by_role("tab", name="Run").click()
    fut = viewer.start_run(preset="fast", proposals=100, seed=0)
    assert fut is not None
    wait_until(lambda: viewer.panels.gui_progress.value >= 25 or fut.done(), HANG_GUARD_S, "a quarter of the run")
    _save(page, "viewer_run.png")
    fut.result(timeout=2 * HANG_GUARD_S)
    assert viewer.load_trace() and viewer.wait_idle(120)


@guide_only
def test_guide_proposals_tab(viewer: Any, page: Any) -> None:
    from efem_viz.viewer import trace_queries as tq

    _open(page, viewer)
    trace = viewer.state.result.trace
    t = min(2, trace.num_steps - 1)
    viewer.set_step(t)
    ids, scores = trace.alive_scores(t)
    viewer.select_proposal(int(tq.top_n(ids, scores, 1)[0])).result(timeout=HANG_GUARD_S)
    assert viewer.wait_idle(120)
    page.get_by_role("tab", name="Proposals").click()
    _settle(page)
    _save(page, "viewer_proposals.png")
    viewer.select_proposal(None)
    viewer.set_step(trace.num_steps - 1)
    assert viewer.wait_idle(120)


@guide_only
def test_guide_ground_truth(viewer: Any, page: Any) -> None:
    if not viewer.state.scene.has_gt:
        pytest.skip("the guide scene has no ground truth")
    _open(page, viewer)
    viewer.set_proposal_layers(shapes=False, samples=False)
    viewer.set_threshold(0.0)
    viewer.set_color_mode("gt_match")
    page.get_by_role("tab", name="Results").click()
    _settle(page)
    _save(page, "viewer_ground_truth.png")
    viewer.set_color_mode("instances")
    viewer.set_proposal_layers(shapes=True, samples=True)


@guide_only
def test_guide_export(viewer: Any, page: Any, tmp_path: Path) -> None:
    _open(page, viewer)
    page.get_by_role("tab", name="Export").click()
    index = viewer.export_tab.export_static(tmp_path / "demo")
    assert index is not None and index.is_file()
    page.wait_for_timeout(800)
    _save(page, "viewer_export.png")
    page.goto(index.as_uri())  # the static page, from disk, no server
    page.add_style_tag(content="#webgl-software-rendering { display: none !important; }")
    page.wait_for_timeout(9000)
    _save(page, "viewer_static_demo.png")


@guide_only
def test_real_scene_figures(viewer: Any, page: Any) -> None:
    """docs/img/efem_<scene>.png: EFEM's result on every real tabletop capture with a saved result, coloured against
    the annotated ground truth (green TP, red FP, blue FN), at confidence ≥ 0.1 (docs/BENCHMARKS.md)."""
    names = [e.name for e in viewer.state.entries if e.name.startswith("real_") and e.trace_path.is_file()]
    if not names:
        pytest.skip("no real scene with a saved result in the guide folder")
    current = viewer.state.scene_name
    _open(page, viewer)
    page.get_by_role("tab", name="Results").click()
    for name in names:
        assert viewer.open_scene(name) and viewer.wait_idle(300)
        viewer.set_proposal_layers(shapes=False, samples=False)
        viewer.set_threshold(0.1)
        viewer.set_color_mode("gt_match")
        _settle(page)
        _save(page, f"efem_{name}.png")
    assert viewer.open_scene(current) and viewer.wait_idle(300)
    viewer.set_threshold(0.0)
    viewer.set_color_mode("instances")
    viewer.set_proposal_layers(shapes=True, samples=True)


# ---------------------------------------------------------------------------------------------- instance table
def test_instance_table_cut_visibility_and_fly_to(viewer: Any, page: Any) -> None:
    """The Results tab's instance table is in the page (one row per instance); with the mouse and keyboard only:
    the confidence cut (slider keys) changes the threshold and the rows it hides, Next ▶ chooses the next row and
    flies this browser's camera to it, *Visible* off hides that instance on the server, on shows it again, and
    Fly to flies to the chosen row."""
    from efem_viz.serve.camera import fly_to_view
    from efem_viz.viewer.texts import instance_options
    from efem_viz.viewer.state import DEFAULT_CONFIDENCE_CUT

    _open(page, viewer)
    viewer.set_threshold(DEFAULT_CONFIDENCE_CUT)
    inst = viewer.state.result.instances
    page.get_by_role("tab", name="Results").click()
    table = page.locator("table", has_text="conf.")
    table.wait_for(timeout=HANG_GUARD_MS)
    wait_until(lambda: table.locator("tbody tr").count() == len(inst), HANG_GUARD_S, "one table row per instance")
    assert table.locator("th", has_text="GT (IoU)").count() == 1  # the scene has ground truth

    # ---- the confidence cut: End hides every instance, Home (0) shows them all again
    slider = page.get_by_role("slider").first
    slider.focus()
    page.keyboard.press("End")
    wait_until(lambda: viewer.state.threshold > float(np.max(inst.confidence)), HANG_GUARD_S,
               "the cut above every instance")
    wait_until(lambda: table.locator("td", has_text="below cut").count() == len(inst), HANG_GUARD_S,
               "rows below the cut")
    wait_until(lambda: (not viewer.session.results.shown_mask().any()
                        and not any(h.visible for h in viewer.nodes.results.labels)),
               HANG_GUARD_S, "no mask and no label shown")  # the labels are redrawn after the table
    page.get_by_text(f"{len(inst)} hidden", exact=False).first.wait_for(timeout=HANG_GUARD_MS)
    slider.focus()
    page.keyboard.press("Home")
    wait_until(lambda: viewer.state.threshold == 0.0, HANG_GUARD_S, "the cut at 0")
    wait_until(lambda: viewer.session.results.shown_mask().all(), HANG_GUARD_S, "every instance shown")

    # ---- Next ▶ chooses a row and flies this browser's camera to it
    client = next(iter(viewer.server.get_clients().values()))
    ids = [int(o.split(":", 1)[0]) for o in instance_options(inst)]
    start = viewer.state.table_row
    page.get_by_role("button", name="Next ▶").click()
    nxt = ids[(ids.index(start) + 1) % len(ids)] if start in ids else ids[0]
    wait_until(lambda: viewer.state.table_row == nxt, HANG_GUARD_S, "the next row chosen (Next ▶)")
    k = int(np.flatnonzero(np.asarray(inst.ids) == nxt)[0])
    pts = viewer.state.scene.points[np.asarray(inst.masks[k])]
    lo, hi = viewer.state.scene.bounds
    flown = fly_to_view(pts.min(axis=0), pts.max(axis=0), home=viewer.camera_guard.view,
                        scene_diagonal=float(np.linalg.norm(np.subtract(hi, lo))))

    def at_instance() -> bool:
        """The camera on the view the server sent: the instance's view moved sideways clear of the panel for the
        canvas as it was then (the canvas's pixel count follows viser's frame-rate-scaled pixel ratio, so the
        view is not recomputed from the size now): the same viewing offset, its look-at point near the instance."""
        sent = viewer.camera_guard.last_placed(client)
        return bool(on_view(client, sent) and viewer.camera_guard.last_placed(client, home=True) is None
                    and np.allclose(np.subtract(sent.position, sent.look_at),
                                    np.subtract(flown.position, flown.look_at), atol=1e-6)
                    and np.linalg.norm(np.subtract(sent.look_at, flown.look_at))
                    < 0.5 * np.linalg.norm(np.subtract(flown.position, flown.look_at)))

    wait_until(at_instance, HANG_GUARD_S, "the camera at the instance")

    # ---- Visible off / on, by a mouse click on the checkbox
    visible = page.get_by_role("checkbox", name="Visible")
    assert visible.is_checked()
    visible.click()
    wait_until(lambda: nxt in viewer.state.hidden, HANG_GUARD_S, "the instance hidden on the server")
    assert not viewer.session.results.shown_mask()[k] and not viewer.nodes.results.labels[k].visible
    assert not viewer.nodes.results.obbs[k].visible
    wait_until(lambda: table.locator("td", has_text="hidden").count() == 1, HANG_GUARD_S, "its row says hidden")
    visible.click()
    wait_until(lambda: nxt not in viewer.state.hidden and viewer.session.results.shown_mask()[k], HANG_GUARD_S,
               "the instance shown again")

    # ---- Fly to: back at the fitted view first, then the button brings the camera to the chosen row again
    viewer.reset_view(client)
    wait_until(lambda: on_view(client, viewer.camera_guard.last_placed(client, home=True)), HANG_GUARD_S,
               "the fitted view")
    page.get_by_role("button", name="Fly to").click()
    wait_until(at_instance, HANG_GUARD_S, "the camera flown to it")
    if SAVE:
        _settle(page)
        _save(page, "viewer_instance_table.png")
    viewer.set_threshold(DEFAULT_CONFIDENCE_CUT)


def test_run_tab_precision_and_run_button(viewer: Any, page: Any) -> None:
    """The Run tab, with the mouse and keyboard only: choose Precision bfloat16 and Free space on in their
    dropdowns, type a proposal count, press Run EFEM; the server runs EFEM with those settings (the knobs reach the
    solver)."""
    from efem_viz.em.config import FREE_SPACE_FUSED

    _open(page, viewer, canvas=False)
    page.get_by_role("tab", name="Run").click()
    precision = page.get_by_role("combobox", name="Precision")
    precision.click()
    page.get_by_role("option", name="bfloat16").click()
    wait_until(lambda: viewer.panels.gui_precision.value == "bfloat16", HANG_GUARD_S,
               "the dropdown's value on the server")
    page.get_by_role("combobox", name="Free space").click()
    page.get_by_role("option", name="on", exact=True).click()
    wait_until(lambda: viewer.panels.gui_free_space.value == "on", HANG_GUARD_S, "the free-space mode on the server")
    proposals = page.get_by_role("textbox", name="Proposals")
    proposals.click()
    page.keyboard.press("Control+A")
    page.keyboard.type("12")
    page.keyboard.press("Enter")
    wait_until(lambda: viewer.panels.gui_proposals.value == 12, HANG_GUARD_S, "the proposal count on the server")
    before = viewer.state.result
    page.get_by_role("button", name="Run EFEM").click()
    wait_until(lambda: viewer.state.result is not before and viewer.state.result_source.startswith("run"), HANG_GUARD_S,
               "the run's result shown")
    cfg = viewer.state.result.config
    assert cfg.compute.matmul_dtype == "bfloat16" and cfg.proposals.n_init[0] == 12
    assert cfg.compute.encoder_dtype == "float32"  # on the CPU: the decoder's products in bf16, the encoder float32
    assert cfg.free_space.margin == FREE_SPACE_FUSED.margin


def test_tab_from_seed_goes_to_run_without_opening_a_dropdown(viewer: Any, page: Any) -> None:
    """Tab from the Run tab's Seed field moves the focus to Run EFEM; no dropdown opens over the button (the
    Precision dropdown sat between them and opened on focus)."""
    _open(page, viewer, canvas=False)
    page.get_by_role("tab", name="Run").click()
    page.get_by_role("textbox", name="Seed").click()
    page.keyboard.press("Tab")
    page.wait_for_timeout(500)  # a dropdown opens within a frame of its focus
    assert page.get_by_role("listbox").count() == 0 or not page.get_by_role("listbox").first.is_visible()
    assert page.evaluate("document.activeElement && document.activeElement.textContent") == "Run EFEM"
    page.keyboard.press("Escape")


def test_a_wide_scene_opens_clear_of_the_control_panel(tmp_path: Path, new_page: Any) -> None:
    """A 4 m long table with boxes at both ends opens framed in the part of the canvas the floating control panel
    leaves free: its box projects left of the panel with the browser's own camera, and no scene pixel is drawn
    right of the panel's left edge (below the panel, where the canvas shows, it ran on to the right end)."""
    from annotator.selection import project
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene
    from efem_viz.serve.camera import PANEL_PX
    from efem_viz.viewer.app import ViewerApp

    g = np.random.default_rng(0)
    table = np.column_stack([g.uniform(-2, 2, 20000), g.uniform(-0.3, 0.3, 20000), np.zeros(20000)])
    boxes = [np.column_stack([g.uniform(x - 0.1, x + 0.1, 1500), g.uniform(-0.1, 0.1, 1500), g.uniform(0, 0.2, 1500)])
             for x in (-1.8, 0.0, 1.8)]
    pts = np.concatenate([table, *boxes])
    (tmp_path / "s").mkdir()
    save_scene(Scene.create("wide", pts, colors=np.tile(np.array([[200, 40, 40]], np.uint8), (len(pts), 1))),
               tmp_path / "s" / "wide.ply")
    app = ViewerApp([tmp_path / "s"], port=0)
    try:
        assert app.wait_idle(120)
        page = new_page()
        _open(page, app)
        client = next(iter(app.server.get_clients().values()))
        wait_until(lambda: on_view(client, app.camera_guard.last_placed(client, home=True)), HANG_GUARD_S,
                   "the camera fitted to this canvas")
        cam = client.camera
        w = page.viewport_size["width"]  # CSS pixels (the camera's image_width follows viser's scaled pixel ratio)
        corners = np.array([[x, y, z] for x in (-2, 2) for y in (-0.3, 0.3) for z in (0, 0.2)])
        uv, depth = project(corners, position=np.asarray(cam.position), wxyz=np.asarray(cam.wxyz), fov=float(cam.fov),
                            aspect=float(cam.aspect))
        assert (depth > 0).all() and uv[:, 0].min() > 0.0 and uv[:, 0].max() < 1.0 - PANEL_PX / w, uv[:, 0]
        img = _settle(page)  # the left 70 % of the page
        full = png_to_array(page.screenshot())
        red = (full[..., 0] > 150) & (full[..., 1] < 110) & (full[..., 2] < 110)
        cols = np.flatnonzero(red.any(axis=0))
        assert len(cols) and cols.max() < w - PANEL_PX, f"scene pixels reach x = {cols.max()} of {w}"
        assert cols.max() - cols.min() > 0.5 * (w - PANEL_PX), "the scene fills the free part of the canvas"
        assert img.std() > 8.0
    finally:
        app.stop()


def test_a_changing_status_moves_no_button(viewer: Any, page: Any) -> None:
    """the status line sat above the tabs, so a longer or shorter status pushed every tab and
    button by 19-38 px between two clicks. It now sits below them: the Run tab's buttons stay where they were."""
    _open(page, viewer, canvas=False)
    page.get_by_role("tab", name="Run").click()
    run = page.get_by_role("button", name="Run EFEM")
    viewer.session.set_status("short")
    page.wait_for_timeout(300)
    before = run.bounding_box()
    viewer.session.set_status("a much longer status line " * 12 + "\n\nwith a second paragraph")
    page.get_by_text("with a second paragraph").wait_for(timeout=HANG_GUARD_MS)
    after = run.bounding_box()
    assert before is not None and after is not None and abs(after["y"] - before["y"]) < 1.0, (before, after)
