"""The Results tab's instance table as the GUI drives it: choose a row, show or hide it, fly the camera to it.

The table's rows and choices are the session's (`efem_viz.viewer.parts.instances`); this module draws them into
the panels (`efem_viz.viewer.panel_views.show_instance_table`) and points a browser's camera at an instance
(`efem_viz.serve.camera.fly_to_view`). No viser import at run time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from efem_viz.serve.camera import fly_to_view
from efem_viz.viewer import panel_views as pv

if TYPE_CHECKING:
    from viser import ClientHandle

    from efem_viz.serve.camera import CameraGuard
    from efem_viz.viewer.panel_views import GuiSet
    from efem_viz.viewer.panels import Panels
    from efem_viz.viewer.session import ViewerSession


class InstanceTable:
    """The instance table's GUI actions.

    Args:
        session: the viewer session (the table's rows, the chosen row, visibility, fly targets; its lock).
        panels: the viewer's panels (the table, its dropdown, *Visible* box and buttons).
        gui_set: sets a control without re-entering its callback (`ViewerApp.gui_set`).
        camera_guard: places a browser's camera (its fitted view gives the direction to look from).
        redraw_results: redraws the result layers, colours, summary, legend and table after a visibility change
            (the app's redraw at the current threshold).
    """

    def __init__(self, session: ViewerSession, panels: Panels, *, gui_set: GuiSet, camera_guard: CameraGuard,
                 redraw_results: Callable[[], None]) -> None:
        self.session = session
        self.panels = panels
        self.gui_set = gui_set
        self.camera_guard = camera_guard
        self.redraw_results = redraw_results

    def choose_instance(self, pid: int | None) -> None:
        """Choose a row of the instance table (None: none); its *Visible* box and mark follow."""
        with self.session.lock:
            self.session.instances.choose_instance(pid)
            pv.show_instance_table(self.panels, self.session, self.gui_set)

    def set_instance_visible(self, pid: int | None, visible: bool) -> None:
        """Show or hide one final instance (its mesh, box, label and point colours); a view like the threshold.

        Raises:
            ValueError: no such instance.
        """
        with self.session.lock:
            self.session.instances.set_instance_visible(pid, visible)
            self.redraw_results()

    def fly_to_instance(self, pid: int | None, *, client: ClientHandle | None = None) -> None:
        """Point one browser's camera (every browser's when None) at an instance: the box of its points (of its
        box when it has none), seen from the fitted view's direction (`efem_viz.serve.camera.fly_to_view`).

        Raises:
            ValueError: no such instance.
        """
        with self.session.lock:
            f = self.session.instances.fly_target(pid)
            view = fly_to_view(f.lo, f.hi, home=self.camera_guard.view, scene_diagonal=f.scene_diagonal)
            pv.show_instance_table(self.panels, self.session, self.gui_set)
        self.camera_guard.place(view, client)

    def step_instance(self, step: int, *, client: ClientHandle | None = None) -> int:
        """Choose the next (`step` = 1) or previous (-1) row of the instance table (most confident first, wrapping
        around) and fly to it; returns its proposal id.

        Raises:
            ValueError: no result or no instance.
        """
        pid = self.session.instances.next_instance(step)
        self.fly_to_instance(pid, client=client)
        return pid
