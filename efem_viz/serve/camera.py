"""The camera of both browser apps: the view that fits the scene, "Reset view", and a guard that brings a camera
back when it has left the scene.

Why the guard: viser's browser client (1.1.1, `CameraControls.tsx`) moves the camera while W/A/S/D/Q/E are held
(truck / forward / elevate at 2 scene units per second; the arrow keys orbit) and scales each step by the frame's
time step. Frames are drawn on demand, so the first frame after an idle period spans the whole pause: a quick tap
after ten idle seconds throws the camera and its look-at point about 20 m away, and a tabletop scan is left as a
thin strip (or out of sight) where clicks miss it. The server cannot switch these keys off (viser has no option
for it), so

* the apps use none of `VISER_CAMERA_KEYS` as a hotkey (`annotator.tools.check_tools` refuses them), and
* `CameraGuard` watches every client's camera: when its look-at point leaves the scene's box grown by
  `LOST_MARGIN` scene diagonals (no view a person chooses on purpose looks at a point that far from the scan),
  the camera is put back on the fitted view and that client is told why and how to get the view back (R).

Usage (what the apps do):

```python
guard = CameraGuard(server, fitted_view(lo, hi, direction=(0.5, -0.95, 0.85)), lo, hi)
server.on_client_connect(guard.attach)
guard.set_scene(fitted_view(lo2, hi2), lo2, hi2)   # another scene: every camera is fitted to it
guard.reset(client)                                 # the "Reset view" command
```

No viser import: the guard works on the server and client handles it is given.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from efem_viz.geometry.transforms import xyz_tuple

log = logging.getLogger(__name__)

VISER_CAMERA_KEYS: tuple[str, ...] = ("W", "A", "S", "D", "Q", "E")
"""Letter keys that viser's browser client binds to camera motion (by key position: `KeyW` ... `KeyE`), whatever
the page does with them; a hotkey on one of them would also fly the camera. (The arrow keys orbit.)"""
LOST_MARGIN = 2.0
"""A camera whose look-at point is farther than this many scene diagonals outside the scene's box has left it."""
NOTIFY_EVERY_S = 5.0
"""At most one "view reset" notification per client in this many seconds (a held key keeps pushing it out)."""

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class View:
    """A camera placement, world frame (+Z up)."""

    look_at: Vec3
    """The point looked at (the orbit centre)."""
    position: Vec3
    """The camera centre."""
    up: Vec3 = (0.0, 0.0, 1.0)
    """The up direction."""


VISER_FOV = float(np.deg2rad(75.0))
"""The vertical field of view of viser's browser camera (radians; three.js's default, which viser keeps)."""
FIT_ASPECT = 1.2
"""Width / height of the view a fitted camera plans for: a browser window less the apps' side panel is rarely
narrower."""
FIT_FILL = 0.85
"""A fitted scene's box spans this fraction of the view's height or width (whichever binds first)."""
PANEL_PX = 24 * 16 + 32
"""Pixels of the canvas's right side the viewer's control panel covers (viser 1.1.1 floats it over the canvas:
`control_width="large"` is 24 em of 16 px, plus its margins)."""


def fitted_view(lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray, *,
                direction: Sequence[float] | np.ndarray = (0.5, -0.95, 0.85), fov: float = VISER_FOV,
                aspect: float = FIT_ASPECT, fill: float = FIT_FILL, points: np.ndarray | None = None) -> View:
    """The view that shows a whole scene, framed the way a person would: looking at its box centre from
    `direction`, just far enough away that all eight corners of the box (or, given `points`, the scan itself)
    fall inside `fill` of the view.

    Args:
        lo: (3,) min corner of the scene's box, world frame.
        hi: (3,) max corner, world frame.
        direction: (3,) direction from the centre to the camera (default: down at the table from the front, as the
            viewer opens scenes); only its direction matters.
        fov: vertical field of view of the camera (radians).
        aspect: width / height of the view planned for.
        fill: fraction of the view's height (or width) the box may span.
        points: (N, 3) world points of the scene (a sample is enough) to frame instead of the box's corners: a
            flat table seen from above spans much less of the view than its box.

    Raises:
        ValueError: a corner is not 3 finite numbers, or `direction` is zero.
    """
    lo_a, hi_a = np.asarray(lo, np.float64).reshape(-1), np.asarray(hi, np.float64).reshape(-1)
    if lo_a.shape != (3,) or hi_a.shape != (3,) or not (np.isfinite(lo_a).all() and np.isfinite(hi_a).all()):
        raise ValueError(f"scene box corners must be 3 finite numbers each, got {lo_a} and {hi_a}")
    u = np.asarray(direction, np.float64).reshape(3)
    norm = float(np.linalg.norm(u))
    if not norm > 0:
        raise ValueError(f"the view direction must not be zero, got {u}")
    u /= norm
    centre = (lo_a + hi_a) / 2.0
    diagonal = float(np.linalg.norm(hi_a - lo_a)) or 1.0
    forward = -u
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(forward, up)
    if float(np.linalg.norm(right)) < 1e-9:  # looking straight down or up
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    if points is not None and len(points):
        corners = np.asarray(points, np.float64).reshape(-1, 3) - centre
    else:
        corners = np.array([[x, y, z] for x in (lo_a[0], hi_a[0]) for y in (lo_a[1], hi_a[1])
                            for z in (lo_a[2], hi_a[2])]) - centre
    tan_v = np.tan(0.5 * float(fov)) * float(fill)
    tan_h = tan_v * float(aspect)
    # a corner at offset p is inside when |p·right| <= tan_h (d - p·u) and |p·cam_up| <= tan_v (d - p·u)
    along = corners @ u
    need = along + np.maximum(np.abs(corners @ right) / tan_h, np.abs(corners @ cam_up) / tan_v)
    dist = max(float(need.max()), 0.05 * diagonal)
    return View(xyz_tuple(centre), xyz_tuple(centre + dist * u))


def framing(points: np.ndarray, *, keep: float = 0.99, sample: int = 20_000,
            seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a camera frames of a scan: (lo (3,), hi (3,), sample (M, 3)): the box of the central `keep` of the
    points along each axis (a few stray points of a real scan, a far wall pixel, do not shrink the scene to a
    speck) and at most `sample` of the points inside it, for `fitted_view(lo, hi, points=sample)`.

    Args:
        points: (N, 3) world frame.
        keep: fraction of the points kept along each axis (the rest split equally on both sides).
        sample: at most this many points are looked at (drawn with `seed`).
        seed: the draw's seed.

    Raises:
        ValueError: no points, or not (N, 3).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"need (N, 3) points, got {pts.shape}")
    if len(pts) > sample:
        pts = pts[np.random.default_rng(seed).choice(len(pts), size=sample, replace=False)]
    pts = pts.astype(np.float64)
    q = 100.0 * (1.0 - float(keep)) / 2.0
    lo, hi = np.percentile(pts, [q, 100.0 - q], axis=0)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    return lo, hi, pts[inside]


FLY_TO_DISTANCE = 1.8
"""Fly-to puts the camera this many diagonals of the object's box away from the box centre."""
FLY_TO_MIN_SIZE = 0.05
"""Fly-to treats an object smaller than this fraction of the scene diagonal as this big (a tiny object, a single
vertex: the camera does not come closer than this)."""


def fly_to_view(lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray, *, home: View,
                scene_diagonal: float) -> View:
    """The view that flies to one object (an instance's points or box): looking at its box centre from the
    direction of `home` (the fitted view), `FLY_TO_DISTANCE` box diagonals away, so that it fills about half the
    view. Both apps' fly-to buttons use it.

    Args:
        lo: (3,) min corner of the object's box, world frame.
        hi: (3,) max corner, world frame.
        home: the fitted view of the scene (its viewing direction is kept).
        scene_diagonal: the scene's box diagonal (objects smaller than `FLY_TO_MIN_SIZE` of it count as that big).

    Raises:
        ValueError: a corner is not 3 finite numbers.
    """
    lo_a, hi_a = np.asarray(lo, np.float64).reshape(-1), np.asarray(hi, np.float64).reshape(-1)
    if lo_a.shape != (3,) or hi_a.shape != (3,) or not (np.isfinite(lo_a).all() and np.isfinite(hi_a).all()):
        raise ValueError(f"object box corners must be 3 finite numbers each, got {lo_a} and {hi_a}")
    direction = np.subtract(home.position, home.look_at).astype(np.float64)
    direction /= float(np.linalg.norm(direction)) or 1.0
    size = max(float(np.linalg.norm(hi_a - lo_a)), FLY_TO_MIN_SIZE * (float(scene_diagonal) or 1.0))
    centre = (lo_a + hi_a) / 2.0
    return View(xyz_tuple(centre), xyz_tuple(centre + FLY_TO_DISTANCE * size * direction), home.up)


def view_lost(look_at: Sequence[float] | np.ndarray, lo: Sequence[float] | np.ndarray,
              hi: Sequence[float] | np.ndarray, *, margin: float = LOST_MARGIN) -> bool:
    """Whether a camera looking at `look_at` has left the scene: the point lies more than `margin` scene diagonals
    outside the box [`lo`, `hi`] (a non-finite point has left it too).

    Args:
        look_at: (3,) the camera's look-at point, world frame.
        lo: (3,) min corner of the scene's box, world frame.
        hi: (3,) max corner, world frame.
        margin: allowed distance outside the box, in scene diagonals.
    """
    p = np.asarray(look_at, np.float64).reshape(3)
    if not np.isfinite(p).all():
        return True
    lo_a, hi_a = np.asarray(lo, np.float64).reshape(3), np.asarray(hi, np.float64).reshape(3)
    diagonal = float(np.linalg.norm(hi_a - lo_a)) or 1.0
    outside = np.maximum(np.maximum(lo_a - p, p - hi_a), 0.0)
    return bool(np.linalg.norm(outside) > margin * diagonal)


def clear_of_panel(view: View, width: float, height: float, *, panel_px: float, fov: float = VISER_FOV) -> View:
    """The view moved sideways (camera and look-at point together) so that what it centres on appears in the middle
    of the canvas part the control panel leaves free, not under the panel.

    Args:
        view: a view planned for the canvas's centre.
        width: the canvas width (pixels).
        height: the canvas height (pixels).
        panel_px: pixels the panel covers at the right of the canvas (0: nothing moves).
        fov: the camera's vertical field of view (radians).
    """
    if not (panel_px > 0 and width > 2 * panel_px and height > 0):
        return view
    look, pos = np.asarray(view.look_at, np.float64), np.asarray(view.position, np.float64)
    forward = look - pos
    dist = float(np.linalg.norm(forward))
    right = np.cross(forward, np.asarray(view.up, np.float64))
    if not (dist > 0 and float(np.linalg.norm(right)) > 1e-12):
        return view
    right /= np.linalg.norm(right)
    # the free part's centre lies panel_px / 2 left of the canvas centre: f = (height / 2) / tan(fov / 2) pixels
    shift = 0.5 * float(panel_px) * dist * np.tan(0.5 * float(fov)) / (0.5 * float(height))
    return View(xyz_tuple(look + shift * right), xyz_tuple(pos + shift * right), view.up)


def free_aspect(width: float, height: float, panel_px: float) -> float:
    """Width / height of the canvas part the control panel leaves free (the whole canvas's without a panel)."""
    return max(float(width) - max(float(panel_px), 0.0), 0.5 * float(width)) / max(float(height), 1.0)


def place_camera(camera: Any, view: View) -> None:
    """Put a client's camera (a viser `CameraHandle`) on a view.

    The position is set before the look-at point: viser's position setter moves the look-at point along with the
    camera, so the other order would leave the camera looking past the scene.
    """
    camera.up_direction = view.up
    camera.position = view.position
    camera.look_at = view.look_at


class CameraGuard:
    """Fits every client's camera to the scene and brings it back when it leaves the scene (see the module doc).

    Args:
        server: the viser server (its `initial_camera` is the fitted view: new clients and viser's own *Reset View*).
        view: the fitted view of the scene.
        lo: (3,) min corner of the scene's box, world frame.
        hi: (3,) max corner, world frame.
        margin: `LOST_MARGIN` (scene diagonals outside the box).
        hint: the last sentence of the notification (how to get the fitted view back).
        panel_px: pixels a control panel covers at the right of every canvas (`PANEL_PX` in the viewer; 0: none).
            Each client's views are then fitted to the free part of its canvas (`set_scene`'s `fit`) and moved
            clear of the panel (`clear_of_panel`) once the client has reported its canvas size (a new page starts
            on the shared initial view and is moved on its first report).
        fit: the scene's fitted view for a canvas of a given free aspect (as `set_scene` takes it).
    """

    def __init__(self, server: Any, view: View, lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray,
                 *, margin: float = LOST_MARGIN, hint: str = "Reset view brings it back any time.",
                 panel_px: float = 0.0, fit: Callable[[float], View] | None = None) -> None:
        self.server = server
        self.margin = float(margin)
        self.hint = hint
        self.panel_px = float(panel_px)
        self.resets: dict[int, int] = {}
        """Times each client's camera was brought back because it had left the scene, by client id."""
        self._lock = threading.Lock()
        self._notified: dict[int, float] = {}
        self._placed: dict[int, tuple[View, float | None, bool]] = {}
        """By client id: the view the guard last put the client on, its canvas's aspect then (None before the client
        reported one) and whether it was the fitted view."""
        self.view = view
        """The fitted view for the planned canvas (`FIT_ASPECT`, no panel): the initial camera."""
        self.fit = fit
        """The fitted view for a canvas of a given free aspect (`set_scene`), None: `view` for every canvas."""
        self.lo = xyz_tuple(lo)
        self.hi = xyz_tuple(hi)
        self._set_initial()

    def _set_initial(self) -> None:
        cam = self.server.initial_camera
        cam.up = self.view.up
        cam.position = self.view.position
        cam.look_at = self.view.look_at

    def attach(self, client: Any) -> None:
        """Watch a client's camera (call it from `server.on_client_connect`); with a panel, the client's first
        camera report (its canvas size) puts it on the view fitted to its canvas."""
        client.camera.on_update(lambda camera, client=client: self._on_update(client, camera))

    def _on_update(self, client: Any, camera: Any) -> None:
        """A camera report: the lost-camera check, then (with a panel) a camera sitting exactly on a home view it
        no longer fits goes to the view fitted to its canvas: the shared initial view (a new page, or viser's own
        reset to it), or the fitted view this client was last put on when its canvas has changed shape since (a
        resized window keeps the scene framed; a camera the person moved stays where it is).

        Only a change of the canvas's aspect counts as a resize: viser scales its canvas's pixels with the
        browser's frame rate (0.75-1.0 of the device's pixel ratio), which changes the reported size but not the
        window, and the camera must not jump each time."""
        size = _canvas(client)
        if self.check(client, camera) or not self.panel_px or size is None:
            return
        cid = int(getattr(client, "client_id", -1))
        with self._lock:
            home, lo, hi, placed = self.view, self.lo, self.hi, self._placed.get(cid)
        tol = 1e-5 * (float(np.linalg.norm(np.subtract(hi, lo))) or 1.0)
        try:
            look, pos = np.asarray(camera.look_at, np.float64), np.asarray(camera.position, np.float64)
        except Exception:  # noqa: BLE001 - no camera state yet
            return
        if _on_view(look, pos, home, tol):
            follow = not _on_view(look, pos, self.view_for(client), tol)
        else:
            follow = (placed is not None and placed[2] and placed[1] is not None and _on_view(look, pos, placed[0], tol)
                      and not _same_shape(placed[1], size[0] / size[1]))
        if follow:
            self._place(client)

    def last_placed(self, client: Any, *, home: bool = False) -> View | None:
        """The view the guard last put this client on (as sent: fitted to its canvas then, clear of the panel), None
        if never; with `home`, None unless it was the fitted view (R, a reset, a resize) rather than a fly-to.
        Whether the camera is still there is for the client's reports to tell."""
        with self._lock:
            placed = self._placed.get(int(getattr(client, "client_id", -1)))
        return None if placed is None or (home and not placed[2]) else placed[0]

    def forget(self, client: Any) -> None:
        """Drop what the guard kept about a client that left (call it from `server.on_client_disconnect`)."""
        with self._lock:
            self._notified.pop(int(getattr(client, "client_id", -1)), None)
            self._placed.pop(int(getattr(client, "client_id", -1)), None)

    def view_for(self, client: Any, view: View | None = None) -> View:
        """A view as one client gets it: `view` (default: the scene's fitted view, fitted again to the free part of
        the client's canvas) moved clear of the panel; unchanged without a panel or before the client reported its
        canvas size."""
        with self._lock:
            home, fit = self.view, self.fit
        size = _canvas(client) if self.panel_px else None
        if view is None:
            view = fit(free_aspect(size[0], size[1], self.panel_px)) if size is not None and fit is not None else home
        if size is None:
            return view
        return clear_of_panel(view, size[0], size[1], panel_px=self.panel_px)

    def set_scene(self, view: View, lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray, *,
                  move_clients: bool = True, fit: Callable[[float], View] | None = None) -> None:
        """Another scene: its fitted view becomes the initial camera, and (with `move_clients`) every connected
        camera is put on it (`fit(aspect)`: the fitted view for a canvas of that free aspect, used per client
        with a panel)."""
        with self._lock:
            self.view, self.fit, self.lo, self.hi = view, fit, xyz_tuple(lo), xyz_tuple(hi)
        self._set_initial()
        if move_clients:
            for client in list(self.server.get_clients().values()):
                self._place(client)

    def reset(self, client: Any = None) -> None:
        """Put one client's camera (every client's when None) on the fitted view (the *Reset view* command)."""
        targets = [client] if client is not None else list(self.server.get_clients().values())
        for c in targets:
            self._place(c)

    def place(self, view: View, client: Any = None) -> None:
        """Put one client's camera (every client's when None) on another view (fly to an object); a view that
        looks at a point outside the scene is refused.

        Raises:
            ValueError: `view.look_at` has left the scene (`view_lost`).
        """
        with self._lock:
            lo, hi = self.lo, self.hi
        if view_lost(view.look_at, lo, hi, margin=self.margin):
            raise ValueError(f"refusing a view that looks at {view.look_at}, outside the scene")
        targets = [client] if client is not None else list(self.server.get_clients().values())
        for c in targets:
            self._place(c, view)

    def check(self, client: Any, camera: Any) -> bool:
        """A client's camera moved: bring it back when it has left the scene. Returns True when it was reset."""
        with self._lock:
            lo, hi = self.lo, self.hi
        try:
            look_at = np.asarray(camera.look_at, np.float64)
        except Exception:  # noqa: BLE001 - no camera state yet
            return False
        if not view_lost(look_at, lo, hi, margin=self.margin):
            return False
        cid = int(getattr(client, "client_id", -1))
        with self._lock:
            self.resets[cid] = self.resets.get(cid, 0) + 1
            now = time.monotonic()
            tell = now - self._notified.get(cid, -np.inf) >= NOTIFY_EVERY_S
            if tell:
                self._notified[cid] = now
        log.info("client %s: camera looked at %s, outside the scene: view reset", cid, np.round(look_at, 2).tolist())
        self._place(client)
        if tell:
            self._notify(client)
        return True

    def _place(self, client: Any, view: View | None = None) -> None:
        home = view is None
        view = self.view_for(client, view)
        cid = int(getattr(client, "client_id", -1))
        size = _canvas(client)
        with self._lock:
            self._placed[cid] = (view, None if size is None else size[0] / size[1], home)
        try:
            with client.atomic():
                place_camera(client.camera, view)
            client.flush()
        except Exception:  # noqa: BLE001 - a client may disconnect meanwhile
            log.debug("could not place the camera of %r", client, exc_info=True)

    def _notify(self, client: Any) -> None:
        try:
            client.add_notification(
                "View reset",
                "The camera had left the scene (W/A/S/D/Q/E move viser's camera, and a key pressed after a pause "
                f"can throw it far away), so it was put back. {self.hint}",
                auto_close_seconds=8.0, color="yellow")
        except Exception:  # noqa: BLE001 - a client may disconnect meanwhile
            log.debug("notification to %r failed", client, exc_info=True)


def _on_view(look: np.ndarray, pos: np.ndarray, view: View, tol: float) -> bool:
    """Whether a camera looking at `look` from `pos` sits on `view` (each coordinate within `tol`)."""
    return bool(np.allclose(look, view.look_at, rtol=0.0, atol=tol)
                and np.allclose(pos, view.position, rtol=0.0, atol=tol))


def _same_shape(aspect: float, other: float) -> bool:
    """Whether two canvas aspects (width / height) are one shape: within 1 %, what rounding a canvas's pixel count
    to a scaled pixel ratio can make of one window."""
    return abs(aspect - other) <= 0.01 * max(aspect, other)


def _canvas(client: Any) -> tuple[int, int] | None:
    """(width, height) in pixels of a client's canvas, None before it reported one."""
    try:
        w, h = int(client.camera.image_width), int(client.camera.image_height)
    except Exception:  # noqa: BLE001 - no camera state yet (viser asserts), or a stand-in without one
        return None
    return (w, h) if w > 0 and h > 0 else None
