"""The EFEM viewer (viser). Import `efem_viz.viewer.app.ViewerApp` to embed it; `efem-viz view` runs it.
`efem_viz.viewer.session.ViewerSession` is the same viewer without a GUI (no viser): drive it from a script.

This package is the only place (with annotator/app.py) that imports viser; the import happens inside functions so
that `import efem_viz.viewer` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from efem_viz.viewer.app import ViewerApp as ViewerApp
    from efem_viz.viewer.commands import ViewArgs as ViewArgs

__all__ = ["ViewerApp", "ViewArgs"]


def __getattr__(name: str):  # lazy re-exports keep the CLI start-up light
    if name == "ViewerApp":
        from efem_viz.viewer.app import ViewerApp

        return ViewerApp
    if name == "ViewArgs":
        from efem_viz.viewer.commands import ViewArgs

        return ViewArgs
    raise AttributeError(name)
