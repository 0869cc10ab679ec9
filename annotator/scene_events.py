"""Scene events → session calls: the checks every viser scene event passes, and the drag backlog's coalescing.

Pure (no viser import): the events are read by attribute, as viser delivers them (`SceneClickEvent`,
`ScenePointerEvent`, drag events) or as tests build them.
"""

from __future__ import annotations

import queue
from typing import Any

import numpy as np

from efem_viz.serve.inputs import ClientValueError

MISSED_SCAN = ("Nothing of the scan is under the cursor, so the tool did nothing: Ctrl/Cmd+click on the scan. If "
               "the scan is out of sight or tiny, R (reset view) fits it to the view.")
"""What a Ctrl/Cmd+click that misses the scan tells the user."""


def coalesce_drag_updates(edits: queue.Queue[tuple[str, Any]], event: Any) -> Any:
    """The last of a backlog of drag updates of one client queued after `event` (taken off the queue): the stroke
    segment from the last point covers them.

    Args:
        edits: the app's event queue of (kind, event).
        event: a drag update just taken off it.
    """
    while True:
        try:
            k2, e2 = edits.queue[0]
        except IndexError:
            return event
        if k2 == "drag" and e2.phase == "update" and e2.client_id == event.client_id:
            edits.get_nowait()
            edits.task_done()
            event = e2
        else:
            return event


def _finite(value: Any, n: int, what: str) -> None:
    try:
        a = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ClientValueError(f"{what}: expected {n} numbers") from None
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ClientValueError(f"{what}: expected {n} finite numbers")


def check_event(kind: str, event: Any) -> None:
    """Refuse scene events whose coordinates no browser produces (NaN, inf, wrong length)."""
    if kind == "click":
        _finite(event.ray_origin, 3, "click ray origin")
        _finite(event.ray_direction, 3, "click ray direction")
        _finite(event.screen_pos, 2, "click screen position")
    elif kind == "rect":
        _finite(event.screen_min, 2, "box corner")
        _finite(event.screen_max, 2, "box corner")
        cam = event.client.camera
        _finite(cam.position, 3, "camera position")
        _finite(cam.wxyz, 4, "camera orientation")
        _finite((cam.fov, cam.aspect), 2, "camera fov/aspect")
        if not (0.0 < float(cam.fov) < np.pi and float(cam.aspect) > 0.0):
            raise ClientValueError("camera fov/aspect out of range")
    elif kind == "drag":
        _finite(event.start_position, 3, "drag start")
        if event.phase != "start":
            _finite(event.end_position, 3, "drag position")
            _finite(event.client.camera.position, 3, "camera position")
