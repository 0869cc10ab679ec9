"""Real-browser test of the annotator (headless Debian chromium, software WebGL): run with `-m browser`.

A Ctrl+left-drag across the scan (a mesh, and a point cloud) in the page must paint vertices: the label store changes, and the canvas
changes colour where the stroke went. With EFEM_SAVE_SCREENSHOTS=1 screenshots go to docs/img/ for the guide.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
from browser_utils import png_to_array, settle, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.timeout(150)]

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"
SAVE = os.environ.get("EFEM_SAVE_SCREENSHOTS") == "1"


@pytest.fixture(params=["mesh", "points"])
def annotator(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Any]:
    """The annotator on a small sphere (software rendering is slow): a 2.5k-vertex mesh, or 6k points (whose
    drags land on the invisible splat proxy surface)."""
    import trimesh

    from annotator.app import AnnotatorApp

    scan = tmp_path / "ball.ply"
    if request.param == "mesh":
        trimesh.creation.icosphere(subdivisions=4, radius=0.15).export(scan)
    else:
        from efem_viz.data.io import save_scene
        from efem_viz.data.scene import Scene

        p = np.random.default_rng(0).normal(size=(6000, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        save_scene(Scene.create("ball", (0.15 * p).astype(np.float32), normals=p.astype(np.float32)), scan)
    app = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0)
    app.new_instance(category="mug")
    app.settings.radius = 0.03
    app.kind = request.param
    yield app
    app.close()




def _canvas_png(page: Any) -> np.ndarray:
    png = page.locator("canvas").first.screenshot()
    return png_to_array(png)


def _settle(page: Any, *, timeout: float = 15.0) -> np.ndarray:
    """Canvas screenshot once rendering has settled."""
    return settle(lambda: _canvas_png(page), page, timeout=timeout)


def test_ctrl_drag_on_mesh_paints_vertices(annotator: Any, page: Any) -> None:
    """A ctrl-drag paints: the label store changes (one undoable stroke) and so does the canvas."""
    app = annotator
    iid = app.settings.active_id
    page.goto(app.url)
    page.get_by_text("Tools", exact=True).first.wait_for(timeout=30_000)
    wait_until(lambda: len(app.server.get_clients()) > 0, 30, "client connection")
    before = _settle(page)
    box = page.locator("canvas").first.bounding_box()
    assert box is not None
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    painted = 0
    for attempt in range(3):  # the first gesture can land while the scene is still streaming in
        page.keyboard.down("Control")
        page.mouse.move(cx - 40, cy)
        page.mouse.down()
        for k in range(1, 13):
            page.mouse.move(cx - 40 + 7 * k, cy + 2 * k, steps=2)
            page.wait_for_timeout(60)
        page.mouse.up()
        page.keyboard.up("Control")
        try:
            wait_until(lambda: int((app.store.labels == iid).sum()) > 0, 10, "painted vertices")
        except AssertionError:
            continue
        app.wait_idle()
        painted = int((app.store.labels == iid).sum())
        break
    assert painted > 10, "a ctrl-drag on the mesh did not paint any vertex"
    # the whole stroke is one undoable journal group
    groups = {r.header.get("group") for r in app.store.journal.records if r.kind == "do" and r.arrays["idx"].size}
    assert len(groups) == 1  # one stroke landed (earlier attempts, if any, painted nothing)
    after = _settle(page)
    changed = int((np.abs(after - before).sum(axis=-1) > 60).sum())
    assert changed > 50, f"the canvas barely changed after painting ({changed} pixels)"
    if SAVE:
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(DOCS_IMG / f"annotator_brush_{app.kind}.png"))
    app.undo()
    assert int((app.store.labels == iid).sum()) == 0
