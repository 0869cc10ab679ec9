"""The Export tab's actions: its output folder field, its two buttons, and what each export shows in the tab.

The writing itself is the session's (`efem_viz.viewer.parts.exporting`); this module confines the GUI's folder to the
output root chosen at start, runs the exports in the worker thread (`efem_viz.viewer.jobs`) and reports where they
went. No viser import at run time.
"""

from __future__ import annotations

from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from efem_viz.serve.inputs import read_text, resolve_inside_root

if TYPE_CHECKING:
    from efem_viz.viewer.jobs import Jobs
    from efem_viz.viewer.panels import Panels
    from efem_viz.viewer.session import ViewerSession


class ExportTab:
    """Exports started from the GUI (or from a Python caller, with a folder of its choice).

    Args:
        session: the viewer session (writes the exports; its `out_root` confines the GUI's folder).
        panels: the viewer's panels (`gui_out_dir`, `gui_export_info`).
        jobs: the viewer's worker threads (exports run in `jobs.worker`).
    """

    def __init__(self, session: ViewerSession, panels: Panels, jobs: Jobs) -> None:
        self.session = session
        self.panels = panels
        self.jobs = jobs

    def gui_out_folder(self) -> Path:
        """The folder in the GUI's "Output folder" field, resolved inside the output root chosen at start.

        Raises:
            ClientValueError: the field names a place outside the output root (`..`, another absolute path, a
                symlink pointing out), or is not a usable path.
        """
        return resolve_inside_root(read_text(self.panels.gui_out_dir), self.session.out_root, what="output folder")

    def export_from_gui(self, kind: Literal["results", "static"]) -> Future[Path | None] | None:
        """The Export buttons: results into the GUI's output folder, the static demo into
        `<output folder>/static/<scene>/`; both confined to the output root. Returns the job's Future.

        Raises:
            ClientValueError: the output folder field is outside the output root.
        """
        folder = self.gui_out_folder()
        root = self.session.out_root
        if kind == "results":
            return self.jobs.submit(self.jobs.worker, self.export_results, folder, root=root)
        target = self.session.export.static_target(folder)
        return self.jobs.submit(self.jobs.worker, self.export_static, target, root=root)

    def export_results(self, out_dir: str | Path, *, root: Path | None = None) -> Path | None:
        """Write the thresholded result: ScanNet layout + coloured PLY under `out_dir` (see
        `ViewerSession.export_results`); the tab says where."""
        out = self.session.export.export_results(out_dir, root=root)
        if out is not None:
            self.panels.gui_export_info.content = f"Results written to `{out}`"
        return out

    def export_static(self, out_dir: str | Path | None = None, *, root: Path | None = None) -> Path | None:
        """Write the static demo page `<out_dir>/index.html` (final result + playback of the steps); None =
        `<output root>/static/<scene>/` (see `ViewerSession.export_static`); the tab says where."""
        self.panels.gui_export_info.content = ""  # a cancelled or failed export must not show the last one's path
        out = self.session.export.export_static(out_dir, root=root, on_progress=self._show_progress)
        if out is not None:
            self.panels.gui_export_info.content = f"Static demo written to `{out}`"
        return out

    def _show_progress(self, fraction: float | None) -> None:
        """The recording's progress bar and Cancel button (None: the export ended)."""
        p = self.panels
        running = fraction is not None
        if fraction is not None:
            p.gui_export_progress.value = round(100.0 * fraction, 1)
        p.gui_export_progress.visible = running
        p.gui_export_cancel.disabled = not running
        p.gui_export_static.disabled = running

    def cancel(self) -> None:
        """The Cancel export button: the static demo stops at its next step, nothing is written."""
        self.session.export.cancel_export()
