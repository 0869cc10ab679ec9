"""Add a tool to the annotator: one `annotator.tools.Tool` entry (name, label, hotkey, help, controls, apply).

The annotator builds its toolbar, hotkeys, help text and setting controls from its tool table
(`annotator.tools.DEFAULT_TOOLS`, or the `tools=` given to `AnnotatorApp`) and dispatches every click through
the active entry, so a new tool is a function plus one table entry. This example adds "Lift": a click paints
the part of the scan that lies more than a few millimetres above the table (z = 0) and is connected to the
clicked point, within a radius of it: the object under the cursor, lifted off the table in one click. Its two
settings get their own sliders.

It copies a bundled sample scan without its labels into `--out`, opens the annotator on it (port 0, no
browser), clicks on each of the first ground-truth mugs with the new tool as the GUI would, prints the IoU of
each painted instance with the true mug, undoes and redoes one click, exports the labels and closes.

Run (a few seconds)::

    python examples/add_annotator_tool.py
    python examples/add_annotator_tool.py --radius-cm 8 --objects 3 --out /tmp/annotate
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from annotator.panel_views import recent_steps
from annotator.tools import DEFAULT_TOOLS, Control, Hit, Tool, ToolHost

REPO = Path(__file__).resolve().parents[1]

LIFT_RADIUS = Control("lift_radius", "Lift radius (cm)", "slider", 15.0, min=1.0, max=30.0, step=0.5,
                      scale=100.0)
LIFT_ABOVE = Control("lift_above", "Lift: above table (mm)", "slider", 5.0, min=0.0, max=50.0, step=1.0,
                     scale=1000.0, hint="vertices at most this high above z = 0 are left to the table")


def lift(host: ToolHost, hit: Hit) -> object:
    """Paint the part of the scan above the table that is connected to the hit, within `lift_radius` of it."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    radius = float(host.toolbox.settings.extra["lift_radius"])  # metres (the slider shows cm: Control.scale)
    above = float(host.toolbox.settings.extra["lift_above"])
    geom = host.scan.geom
    near = np.asarray(geom.tree.query_ball_point(hit.position, radius), np.int64)
    cand = np.sort(near[geom.points[near, 2] > above])
    if hit.vertex not in cand:
        return None  # clicked on the table: nothing to lift
    indptr, indices = geom.adjacency  # mesh edges, or a kNN graph for point clouds
    graph = sp.csr_matrix((np.ones(len(indices), np.int8), indices, indptr), shape=(geom.n, geom.n))
    _, comp = connected_components(graph[cand][:, cand], directed=False)
    idx = cand[comp == comp[np.searchsorted(cand, hit.vertex)]]
    return host.painting.paint(idx, client=hit.client)  # one journalled, undoable edit


LIFT = Tool("lift", "Lift", "U",
            "click paints the object under the point (connected, above the table, within a radius)",
            controls=(LIFT_RADIUS, LIFT_ABOVE), apply_at=lift)
TOOLS: tuple[Tool, ...] = (*DEFAULT_TOOLS, LIFT)


def click_ray(geom: Any, scene: Any, gid: int) -> tuple[np.ndarray, np.ndarray]:
    """A camera ray that meets object `gid` of `scene` first, as a user's click would: from 30 cm away at mid
    height, looking at the object's centre from the first of 16 directions around it that no object blocks."""
    from annotator.selection import pick

    pts = scene.points[scene.instance == gid]
    centre = np.r_[pts[:, :2].mean(axis=0), 0.5 * pts[:, 2].max()]
    for a in np.linspace(0.0, 2 * np.pi, 16, endpoint=False):
        u = np.array([np.cos(a), np.sin(a), 0.0])
        hit = pick(geom, centre + 0.3 * u, -u)
        if hit is not None and scene.instance[hit[0]] == gid:
            return centre + 0.3 * u, -u
    raise ValueError(f"object {gid} cannot be clicked from the side")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="syn_z_1", help="a sample_scenes/<name>.ply with ground truth")
    ap.add_argument("--objects", type=int, default=3, help="ground-truth objects to click on")
    ap.add_argument("--radius-cm", type=float, default=15.0, help="the Lift radius slider's value (cm)")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temp dir)")
    args = ap.parse_args(argv)

    from annotator.app import AnnotatorApp
    from efem_viz.data.io import load_scene, save_scene

    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)
    truth = load_scene(REPO / "sample_scenes" / f"{args.scene}.ply")
    assert truth.instance is not None, f"{args.scene} has no ground truth to compare with"
    scan = save_scene(truth.replace(name=f"{truth.name}_unlabelled", instance=None, categories={}),
                      out / f"{truth.name}_unlabelled.ply")

    app = AnnotatorApp(scan, out_dir=out, port=0, autosave_delay=0, tools=TOOLS)
    try:
        print(f"annotator at {app.url}; tools {list(app.panels.gui_tool.options)}")
        line = next(x for x in app.panels.gui_help.content.splitlines() if "Lift" in x)
        print(f"help line: {line}")
        app.set_tool("lift")  # what pressing U (or picking it in the Tool dropdown) does
        app.panels.gui_controls["lift_radius"].value = args.radius_cm  # the slider, in cm
        print(f"lift settings: radius {app.session.toolbox.settings.extra['lift_radius']:.3f} m, "
              f"above {app.session.toolbox.settings.extra['lift_above']:.3f} m; controls shown "
              f"{[k for k, c in app.panels.gui_controls.items() if c.visible]}")
        for gid in truth.instance_ids()[: args.objects]:
            iid = app.session.instances.new_instance(category=truth.categories.get(int(gid), "object"))
            origin, direction = click_ray(app.session.scan.geom, truth, int(gid))
            v = app.session.painting.click(origin, direction)
            assert v is not None, "the ray missed the scan"
            painted = app.session.scan.store.labels == iid
            true = truth.instance == gid
            iou = (painted & true).sum() / max((painted | true).sum(), 1)
            step = recent_steps(app.session.scan.store.labelset.undo_stack, 1)[0]
            print(f"  instance {iid} ({step}): {int(painted.sum())} vertices, IoU with true object {int(gid)}: "
                  f"{iou:.2f}")
        before = int((app.session.scan.store.labels > 0).sum())
        app.session.instances.undo()
        after_undo = int((app.session.scan.store.labels > 0).sum())
        app.session.instances.redo()
        after_redo = int((app.session.scan.store.labels > 0).sum())
        print(f"labelled vertices {before}; after undo {after_undo}; after redo {after_redo}")
        for p in app.session.files.export("ply"):
            print(f"exported {p.name}")
    finally:
        app.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
