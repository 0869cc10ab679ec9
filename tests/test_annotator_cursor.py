"""The brush cursor (item 13) without a browser: the ring's geometry, and where the app draws it (the last
brush position, the current radius, only for tools with a brush radius)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Iterator

import numpy as np
import pytest
import trimesh

from annotator.app import AnnotatorApp
from annotator.render import CURSOR_LIFT, ring_segments


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (1.0, 2.0, -0.5), (0.0, 0.0, 0.0)])
def test_ring_has_the_brush_radius_around_the_normal(normal: tuple[float, float, float]) -> None:
    """A closed ring of `radius` around the point, in the plane perpendicular to the normal, lifted along it."""
    c = np.array([0.3, -0.2, 0.5])
    seg = ring_segments(c, np.array(normal), 0.02, n=32)
    assert seg.shape == (32, 2, 3) and seg.dtype == np.float32
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n) if np.linalg.norm(n) > 0 else np.array([0.0, 0.0, 1.0])
    centre = c + CURSOR_LIFT * 0.02 * n
    pts = seg[:, 0].astype(np.float64)
    assert np.allclose(np.linalg.norm(pts - centre, axis=1), 0.02, atol=1e-6)
    assert np.allclose((pts - centre) @ n, 0.0, atol=1e-6)
    assert np.allclose(seg[1:, 0], seg[:-1, 1]) and np.allclose(seg[0, 0], seg[-1, 1], atol=1e-6)  # closed
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError):
            ring_segments(c, n, bad)
    with pytest.raises(ValueError):
        ring_segments(np.array([0.0, np.inf, 0.0]), n, 0.01)


@pytest.fixture()
def app(tmp_path: Path) -> Iterator[AnnotatorApp]:
    scan = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(scan)
    a = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0)
    yield a
    a.close()


def _drag(phase: str, start: tuple[float, ...], end: tuple[float, ...]) -> SimpleNamespace:
    cam = SimpleNamespace(position=np.array([0.0, 0.0, 1.0]), wxyz=np.array([0.0, 1.0, 0.0, 0.0]),
                          fov=np.deg2rad(50), aspect=1.0)
    return SimpleNamespace(phase=phase, client_id=3, client=SimpleNamespace(camera=cam), start_position=start,
                           end_position=end, modifier="cmd/ctrl")


def _ring_radius(app: AnnotatorApp) -> float:
    seg = np.asarray(app.view.cursor_handle.points, np.float64)
    centre = seg[:, 0].mean(axis=0)
    return float(np.linalg.norm(seg[:, 0] - centre, axis=1).mean())


def test_cursor_follows_the_brush_and_its_radius(app: AnnotatorApp) -> None:
    """No cursor before the brush touches the scan; a drag puts it where the stroke is now; [ / ] (and the radius
    slider) redraw it at the new radius; tools without a radius hide it, the brush shows it again."""
    app.session.instances.new_instance(category="mug")
    assert app.session.brush.cursor is None and app.view.cursor_handle is None
    app.session.toolbox.settings.radius = 0.02
    app.handle_event("drag", _drag("start", (0.0, 0.0, 0.1), (0.0, 0.0, 0.1)))
    assert app.session.brush.cursor is not None and app.session.brush.cursor.visible
    assert np.allclose(app.session.brush.cursor.position, (0.0, 0.0, 0.1), atol=0.01)
    app.handle_event("drag", _drag("update", (0.0, 0.0, 0.1), (0.03, 0.0, 0.5)))
    app.handle_event("drag", _drag("end", (0.0, 0.0, 0.1), (0.03, 0.0, 0.5)))
    assert app.session.brush.cursor.position[0] > 0.01, "the cursor should follow the stroke"
    cur = app.session.brush.cursor
    assert np.allclose(cur.normal, cur.position / np.linalg.norm(cur.position), atol=0.1)
    assert _ring_radius(app) == pytest.approx(0.02, rel=1e-3) and app.view.cursor_handle.visible

    r = app.resize_brush(2.0)  # ]
    assert app.session.brush.cursor.radius == r and _ring_radius(app) == pytest.approx(r, rel=1e-3)
    app.panels.gui_controls["radius"].value = 1.0  # the slider (cm), as a browser moves it
    assert app.session.brush.cursor.radius == pytest.approx(0.01) and _ring_radius(app) == pytest.approx(0.01, rel=1e-3)

    app.set_tool("grow")
    assert not app.session.brush.cursor.visible and not app.view.cursor_handle.visible
    app.set_tool("erase")
    assert app.session.brush.cursor.visible and app.view.cursor_handle.visible
    app.session.painting.dab(5, app.session.scan.scene.points[5], erase=True)  # a click dab moves it too
    assert np.allclose(app.session.brush.cursor.position, app.session.scan.scene.points[5])
