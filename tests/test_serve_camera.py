"""The apps' camera (`efem_viz.serve.camera`): the fitted view, "lost" cameras, and the guard that brings a camera
back, driven through a real viser server by a scripted client that sends the camera messages a browser sends."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
from viser_client import ViserClient, wait_for

from efem_viz.serve.camera import (
    FIT_ASPECT,
    FIT_FILL,
    LOST_MARGIN,
    PANEL_PX,
    VISER_CAMERA_KEYS,
    VISER_FOV,
    CameraGuard,
    View,
    fitted_view,
    fly_to_view,
    framing,
    free_aspect,
    view_lost,
)

LO, HI = np.array([-0.15, -0.15, 0.0]), np.array([0.15, 0.15, 0.3])


def _camera_message(look_at: tuple[float, float, float], position: tuple[float, float, float]) -> dict[str, Any]:
    """A ViewerCameraMessage as the browser sends it after moving the camera (orientation is not read here)."""
    return {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": position, "fov": 1.0,
            "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640, "look_at": look_at,
            "up_direction": (0.0, 0.0, 1.0)}


def test_fitted_view_and_lost_cameras() -> None:
    """The fitted view looks at the box centre along the direction; a look-at point is lost only beyond
    `LOST_MARGIN` diagonals outside the box (or when not finite)."""
    v = fitted_view(LO, HI, direction=(0.0, -1.0, 0.0))
    diag = float(np.linalg.norm(HI - LO))
    off = np.subtract(v.position, (LO + HI) / 2)
    assert np.allclose(v.look_at, (LO + HI) / 2) and off[1] < 0 and np.allclose(off[[0, 2]], 0.0)
    assert v.up == (0.0, 0.0, 1.0)
    assert not view_lost(v.look_at, LO, HI)
    assert not view_lost(HI + [0, 0, 0.99 * LOST_MARGIN * diag], LO, HI)  # far above the scan, still near
    assert view_lost(HI + [0, 0, 1.01 * LOST_MARGIN * diag], LO, HI)
    assert view_lost((20.0, 0.0, 0.0), LO, HI)  # what a W tap after a 10 s pause does (2 m/s)
    assert view_lost((np.nan, 0.0, 0.0), LO, HI)
    with pytest.raises(ValueError, match="finite"):
        fitted_view((0, 0, np.inf), HI)
    assert set(VISER_CAMERA_KEYS) == {"W", "A", "S", "D", "Q", "E"}


def _screen_extent(view, corners: np.ndarray) -> tuple[float, float]:
    """Largest |x| / (tan(fov/2) aspect) and |y| / tan(fov/2) of the corners as the fitted camera sees them."""
    fwd = np.subtract(view.look_at, view.position)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, view.up)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd], axis=1)  # OpenCV camera axes: x right, y down, z forward
    pc = (corners - np.asarray(view.position)) @ R
    t = np.tan(VISER_FOV / 2)
    return float(np.max(np.abs(pc[:, 0] / pc[:, 2])) / (t * FIT_ASPECT)), float(np.max(np.abs(pc[:, 1] / pc[:, 2])) / t)


@pytest.mark.parametrize("seed", range(6))
def test_fitted_view_frames_the_box_tightly(seed: int) -> None:
    """(scenes opened small, a quarter of the width): every corner of the box is inside the planned
    view, and the box fills `FIT_FILL` of it along the binding axis (not a speck in the middle)."""
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-2, 2, 3)
    hi = lo + rng.uniform(0.05, 3, 3)
    direction = rng.normal(size=3)
    direction[2] = abs(direction[2]) + 0.2  # looking down, as the apps do
    v = fitted_view(lo, hi, direction=direction)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    ex, ey = _screen_extent(v, corners)
    assert max(ex, ey) == pytest.approx(FIT_FILL, rel=1e-6), (ex, ey)


def test_framing_ignore_stray_points() -> None:
    """A real scan's few far points (a wall pixel 5 m away) do not make the framed box five metres wide."""
    rng = np.random.default_rng(0)
    table = rng.uniform([-0.4, -0.3, 0.0], [0.4, 0.3, 0.2], size=(20_000, 3))
    stray = rng.uniform(4.0, 5.0, size=(50, 3))
    lo, hi, sample = framing(np.concatenate([table, stray]))
    assert np.all(hi < 0.45) and np.all(lo > -0.45) and len(sample) > 15_000 and np.all(sample < 0.45)
    # a flat table seen from above is framed by its points, closer than by its box
    v_pts = fitted_view(lo, hi, points=sample)
    v_box = fitted_view(lo, hi)
    assert np.linalg.norm(np.subtract(v_pts.position, v_pts.look_at)) < np.linalg.norm(
        np.subtract(v_box.position, v_box.look_at))
    ex, ey = _screen_extent(v_pts, sample)
    assert max(ex, ey) == pytest.approx(FIT_FILL, rel=1e-6)
    with pytest.raises(ValueError):
        framing(np.zeros((0, 3)))


@pytest.fixture()
def guarded() -> Iterator[tuple[Any, CameraGuard, ViserClient]]:
    """A bare viser server with a guard for the box LO-HI and one scripted client (with a button, which
    `ViserClient` waits for)."""
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        guard = CameraGuard(server, fitted_view(LO, HI), LO, HI, hint="R resets it.")
        server.on_client_connect(guard.attach)
        server.gui.add_button("ok")
        client = ViserClient(f"ws://127.0.0.1:{server.get_port()}")
        try:
            assert wait_for(lambda: len(server.get_clients()) == 1, 30), "the client did not connect"
            yield server, guard, client
        finally:
            client.close()
    finally:
        server.stop()


def test_a_camera_that_left_the_scene_is_put_back_with_a_word(guarded: tuple[Any, CameraGuard, ViserClient]) -> None:
    """A camera message looking 20 m away (a W tap after a pause in viser's client) puts that client's camera back
    on the fitted view, exactly (position and look-at), and tells it why; a camera moved near the scene is left
    alone."""
    server, guard, client = guarded
    handle = next(iter(server.get_clients().values()))
    view = guard.view
    # near the scene: nothing happens
    client.send(_camera_message((0.1, 0.0, 0.1), (0.1, -0.8, 0.6)))
    assert wait_for(lambda: np.allclose(handle.camera.look_at, (0.1, 0.0, 0.1)), 10)
    assert guard.resets == {}
    # thrown away: put back
    client.send(_camera_message((0.0, 20.0, 0.1), (0.0, 19.2, 0.6)))
    assert wait_for(lambda: guard.resets.get(handle.client_id) == 1, 10), guard.resets
    assert np.allclose(handle.camera.look_at, view.look_at), (handle.camera.look_at, view.look_at)
    assert np.allclose(handle.camera.position, view.position), (handle.camera.position, view.position)
    assert wait_for(lambda: any(t.startswith("View reset:") and "R resets it." in t
                                for t in client.notification_texts()), 10), client.notification_texts()


def test_reset_and_another_scene_place_every_camera_exactly(guarded: tuple[Any, CameraGuard, ViserClient]) -> None:
    """`reset` and `set_scene` put the camera on the view exactly: viser's position setter drags the look-at point
    along, so setting the look-at first (what the viewer did on a scene change) left the camera looking past the
    scene."""
    server, guard, client = guarded
    handle = next(iter(server.get_clients().values()))
    client.send(_camera_message((0.05, 0.05, 0.05), (0.3, -0.5, 0.4)))
    assert wait_for(lambda: np.allclose(handle.camera.look_at, (0.05, 0.05, 0.05)), 10)
    guard.reset(handle)
    assert np.allclose(handle.camera.look_at, guard.view.look_at)
    assert np.allclose(handle.camera.position, guard.view.position)
    lo2, hi2 = LO + 5.0, HI + 5.0
    other = fitted_view(lo2, hi2)
    guard.set_scene(other, lo2, hi2)
    assert np.allclose(handle.camera.look_at, other.look_at) and np.allclose(handle.camera.position, other.position)
    assert np.allclose(server.initial_camera.look_at, other.look_at)
    assert not view_lost(handle.camera.look_at, lo2, hi2)


def test_the_viewer_fits_every_camera_on_a_scene_change(tmp_path: Path) -> None:
    """Opening another scene in the viewer puts each connected browser's camera on that scene's fitted view (the
    look-at point at its centre), and *Reset view* puts a moved camera back."""
    from efem_viz.data.io import save_scene
    from efem_viz.prior import analytic
    from efem_viz.viewer.app import ViewerApp

    save_scene(analytic.make_sphere_scene(seed=0, spacing=0.02, radii=(0.05,), name="a"), tmp_path / "a.ply")
    far = analytic.make_sphere_scene(seed=1, spacing=0.02, radii=(0.05,), name="b")
    save_scene(far.replace(points=far.points + np.float32(3.0)), tmp_path / "b.ply")
    app = ViewerApp([tmp_path], port=0, prior=analytic.make_sphere_prior(), open_first=False,
                    out_dir=tmp_path / "out")
    try:
        client = ViserClient(app.url)
        try:
            assert wait_for(lambda: len(app.server.get_clients()) == 1, 30)
            handle = next(iter(app.server.get_clients().values()))
            for name in ("a", "b"):
                assert app.open_scene(name)
                lo, hi, sample = framing(app.state.scene.points)
                # fitted to the part of this client's 640 x 480 canvas the control panel leaves free (too narrow
                # to move the scene sideways: the look-at point stays at the centre)
                view = fitted_view(lo, hi, direction=(0.5, -0.95, 0.85), points=sample,
                                   aspect=free_aspect(640, 480, PANEL_PX))
                assert np.allclose(app.camera_guard.view_for(handle).position, view.position, atol=1e-9)
                assert np.allclose(handle.camera.look_at, view.look_at, atol=1e-5), (name, handle.camera.look_at)
                assert np.allclose(handle.camera.position, view.position, atol=1e-5), name
            client.send(_camera_message((3.1, 3.0, 3.0), (3.5, 2.0, 4.0)))
            assert wait_for(lambda: np.allclose(handle.camera.look_at, (3.1, 3.0, 3.0)), 10)
            client.click("Reset view")
            assert wait_for(lambda: np.allclose(handle.camera.look_at, view.look_at, atol=1e-5), 10)
        finally:
            client.close()
    finally:
        app.stop()



def test_a_view_clear_of_the_panel_centres_the_scene_in_the_free_part() -> None:
    """`clear_of_panel` moves camera and look-at point together so that the point looked at projects at the middle
    of the canvas part a right-hand panel leaves free; `free_aspect` is that part's aspect."""
    from annotator.selection import project
    from efem_viz.geometry.transforms import rotation_to_quat_wxyz
    from efem_viz.serve.camera import clear_of_panel

    v = fitted_view(LO, HI)
    w, h, panel = 1280, 800, 416
    moved = clear_of_panel(v, w, h, panel_px=panel)
    assert np.allclose(np.subtract(moved.position, moved.look_at), np.subtract(v.position, v.look_at))  # same view
    forward = np.subtract(moved.look_at, moved.position)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, moved.up)
    right /= np.linalg.norm(right)
    wxyz = rotation_to_quat_wxyz(np.stack([right, np.cross(forward, right), forward], axis=1))
    uv, _ = project(np.asarray([v.look_at]), position=np.asarray(moved.position), wxyz=wxyz, fov=VISER_FOV,
                    aspect=w / h)
    assert abs(uv[0, 0] * w - (w - panel) / 2) < 0.5 and abs(uv[0, 1] - 0.5) < 1e-9
    assert clear_of_panel(v, w, h, panel_px=0) == v and clear_of_panel(v, 600, h, panel_px=panel) == v  # too narrow
    assert free_aspect(w, h, panel) == pytest.approx((w - panel) / h) and free_aspect(w, h, 0) == w / h


def test_with_a_panel_each_client_gets_the_view_fitted_to_its_free_canvas() -> None:
    """A guard with a panel: before a client reports its canvas it gets the shared view; after, the scene's view
    fitted to the free part of its canvas, moved clear of the panel (and so does any view placed for it)."""
    from types import SimpleNamespace

    from efem_viz.serve.camera import clear_of_panel

    server = SimpleNamespace(initial_camera=SimpleNamespace(up=None, position=None, look_at=None),
                             get_clients=lambda: {})
    fit = lambda aspect: fitted_view(LO, HI, aspect=aspect)  # noqa: E731
    guard = CameraGuard(server, fitted_view(LO, HI), LO, HI, panel_px=416)
    guard.set_scene(fitted_view(LO, HI), LO, HI, fit=fit)

    class Camera:
        @property
        def image_width(self) -> int:
            raise AssertionError("no camera state yet")  # what viser does before the first report

    early = SimpleNamespace(camera=Camera())
    assert guard.view_for(early) == guard.view
    client = SimpleNamespace(camera=SimpleNamespace(image_width=1600, image_height=900))
    want = clear_of_panel(fit(free_aspect(1600, 900, 416)), 1600, 900, panel_px=416)
    assert guard.view_for(client) == want
    other = fitted_view(LO / 2, HI / 2)
    assert guard.view_for(client, other) == clear_of_panel(other, 1600, 900, panel_px=416)


def test_a_resized_canvas_keeps_the_fitted_view_and_a_moved_camera_stays() -> None:
    """A camera the guard put on the fitted view follows its canvas when the window is resized (the view fitted to
    the new free part); once the person moved it (or it flew to an object) a resize leaves it where it is."""
    import contextlib
    from types import SimpleNamespace

    server = SimpleNamespace(initial_camera=SimpleNamespace(up=None, position=None, look_at=None),
                             get_clients=lambda: {})
    guard = CameraGuard(server, fitted_view(LO, HI), LO, HI, panel_px=416,
                        fit=lambda aspect: fitted_view(LO, HI, aspect=aspect))
    camera = SimpleNamespace(image_width=1600, image_height=900, position=None, look_at=None, up_direction=None)
    reports: list[Any] = []
    camera.on_update = reports.append
    client = SimpleNamespace(client_id=7, camera=camera, atomic=contextlib.nullcontext, flush=lambda: None)
    guard.attach(client)

    def report() -> None:  # the browser reports its camera (and canvas size)
        reports[0](camera)

    def placed() -> View:
        return View(tuple(camera.look_at), tuple(camera.position))

    guard.reset(client)
    wide = guard.view_for(client)
    assert placed() == wide == guard.last_placed(client, home=True)
    camera.image_width, camera.image_height = 1400, 787  # viser lowered its pixel ratio (a slow frame rate)
    report()
    assert placed() == wide  # the same window: the camera does not jump
    camera.image_width, camera.image_height = 1000, 900  # the window made narrower
    report()
    narrow = guard.view_for(client)
    assert narrow != wide and placed() == narrow
    report()  # the report of that placement: nothing moves again
    assert placed() == narrow
    camera.position = tuple(np.add(camera.position, (0.0, 0.0, 0.3)))  # the person orbits
    moved = placed()
    camera.image_width = 1600
    report()
    assert placed() == moved
    guard.place(fly_to_view(LO / 4, HI / 4, home=guard.view, scene_diagonal=1.0), client)  # fly to an object
    flown = placed()
    assert guard.last_placed(client, home=True) is None
    camera.image_width = 1000
    report()
    assert placed() == flown
