"""The viewer's browsers: the server they connect to, the status line they read, and what a new one is shown.

`start_viewer_server` starts the guarded viser server with the viewer's theme, +Z up and a `CameraGuard` fitted to a
unit box until a scene opens. `Browsers` is the session's status listener (the status line, and a notification to
every connected client for an error) and greets a client that connects (its camera, the current error). No viser
import at run time: the server comes from `efem_viz.serve.guard.start_server`.
"""

from __future__ import annotations

import contextlib
import threading
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.serve.camera import PANEL_PX, CameraGuard, fitted_view
from efem_viz.serve.guard import start_server
from efem_viz.viewer.nodes import VIEW_DIRECTION

if TYPE_CHECKING:
    import viser
    from viser import ClientHandle

    from efem_viz.serve.guard import ServerAccess
    from efem_viz.viewer.panels import Panels
    from efem_viz.viewer.state import ViewerState


def start_viewer_server(
    *, host: str, port: int, token: str | None
) -> tuple[viser.ViserServer, ServerAccess, CameraGuard]:
    """Start the viewer's server behind the access guard (`efem_viz.serve.guard.start_server`).

    Args:
        host: interface to bind.
        port: port (0 = a free random port; a busy port is replaced by the next free one).
        token: the access token (None = a fresh random one).

    Returns:
        The server (large controls, light theme, no logo, +Z up), how to reach it, and the camera guard that fits
        every browser's camera to the open scene (a unit box until one opens).

    Raises:
        GuardUnavailableError: the access guard cannot be attached to this viser (nothing is served).
    """
    server, access = start_server(host=host, port=port, token=token)
    server.gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
    server.scene.set_up_direction("+z")
    unit = (np.full(3, -0.5), np.full(3, 0.5))  # until a scene opens
    camera_guard = CameraGuard(server, fitted_view(*unit, direction=VIEW_DIRECTION), *unit,
                               hint="Reset view (Scene tab) brings it back any time.", panel_px=PANEL_PX)
    return server, access, camera_guard


class Browsers:
    """What every connected browser is told outside the scene: the status line and error notifications.

    Args:
        server: the viewer's viser server (its clients get the notifications).
        panels: the viewer's panels (`gui_status` is the status line).
        lock: the session's re-entrant lock (guards the panels).
        state: the session's state (its `error` is shown to a client that connects).
        camera_guard: fits a connecting client's camera to the open scene.
    """

    def __init__(self, server: viser.ViserServer, panels: Panels, *, lock: threading.RLock, state: ViewerState,
                 camera_guard: CameraGuard) -> None:
        self.server = server
        self.panels = panels
        self.lock = lock
        self.state = state
        self.camera_guard = camera_guard

    def show_status(self, text: str, error: bool) -> None:
        """The session's status listener: the status line, and a notification to every client for an error."""
        with self.lock:
            icon = "⚠️ " if error else ""
            self.panels.gui_status.content = f"{icon}{text}" if text else ""
        if error:
            for client in list(self.server.get_clients().values()):
                with contextlib.suppress(Exception):  # a client may disconnect meanwhile
                    client.add_notification("efem-viz", text, color="red", auto_close_seconds=8.0)

    def connect(self, client: ClientHandle) -> None:
        """A client connected: fit its camera to the open scene and show it the current error, if any."""
        self.camera_guard.attach(client)
        if self.state.error:
            client.add_notification("efem-viz", self.state.error, color="red", auto_close_seconds=8.0)
