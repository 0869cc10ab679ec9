"""Draw the viewer session's state into the 3-D scene (`SceneNodes`): the step's samples and shapes, the inspector,
the final instances and the point colours.

The `draw_*`/`show_*` functions read a `ViewerSession` and update `efem_viz.viewer.nodes.SceneNodes` (heavy geometry
once, then visibility and colours); `ViewerApp` calls them after each session action, holding the session's lock.
No viser import at run time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from efem_viz.viewer.nodes import SceneNodes
    from efem_viz.viewer.session import Inspection, StepView, ViewerSession


def draw_step(nodes: SceneNodes, session: ViewerSession, v: StepView) -> list[tuple[int, int]]:
    """The samples and decoded shapes of the drawn proposals at step `v.step` (only in the step view).

    Returns:
        The (proposal, step) shapes to draw that are not decoded yet.
    """
    s = session.state
    in_step = s.view_mode == "step"
    pts = np.zeros((0, 3), np.float32)
    if s.show_samples and v.drawn.size and in_step:
        pts, cols = session.timeline.samples(v.drawn, v.step)
        if len(pts):
            nodes.draw_samples(pts, cols)
    if not len(pts):
        nodes.hide_samples()
    # a running solve shows its samples only: decoding its shapes would take CPU from the run (they are decoded
    # when it has ended and a step is shown); before its first step its proposals have no shape at all
    shapes = s.show_shapes and in_step and s.num_steps > 0 and not s.running
    keys = [(int(pid), v.step) for pid in v.drawn] if shapes else []
    nodes.show_shapes(keys)
    return [k for k in keys if not nodes.has_shape(*k)]


def decode_shapes(nodes: SceneNodes, session: ViewerSession, keys: list[tuple[int, int]], generation: int) -> None:
    """Worker: decode the shapes of (proposal, step) pairs from their stored latents and send each once; stops
    (and says so once) when there is no prior to decode with."""
    for pid, t in keys:
        with session.lock:
            if generation != session.generation or session.state.step != t or nodes.has_shape(pid, t):
                continue  # the user moved on (decoded again when asked) or it is already there
        try:
            shape = session.timeline.decode_shape(pid, t)
        except RuntimeError as exc:
            session.no_shapes_generation = generation  # say it once, do not retry on every step
            session.set_status(f"Decoded shapes unavailable: {exc}", error=True)
            return
        with session.lock:
            if generation != session.generation:
                return
            add_decoded_shape(nodes, session, pid, t, shape)


def add_decoded_shape(nodes: SceneNodes, session: ViewerSession, pid: int, t: int,
                      shape: tuple[np.ndarray, np.ndarray] | None) -> None:
    """Add one decoded shape (sent once) and re-show the step's shapes when step `t` is still on screen."""
    s = session.state
    if shape is not None:
        nodes.add_shape(pid, t, *shape, dead=session.timeline.is_dead_at(pid, t))
    if s.step == t and s.show_shapes and s.view_mode == "step":
        v = session.timeline.step_view(t)
        nodes.show_shapes([(int(p_), t) for p_ in (() if v is None else v.drawn)])


def draw_inspection(nodes: SceneNodes, ins: Inspection) -> None:
    """The inspector's crop, samples and decoded shape (Fig. S9) beside the scene."""
    mesh = getattr(ins.view, "mesh", None)
    nodes.draw_inspector(
        crop_points=ins.crop_points,
        crop_colors=ins.crop_colors,
        sampled_points=ins.sampled_points,
        sample_color=ins.sample_color,
        mesh_vertices=None if mesh is None else np.asarray(mesh.vertices),
        mesh_faces=None if mesh is None else np.asarray(mesh.faces),
        center=ins.center,
        radius=ins.radius,
        label=f"#{ins.pid} t={ins.step}",
    )


def show_results(nodes: SceneNodes, session: ViewerSession) -> None:
    """Result layers per the toggles and the threshold; meshes step aside while the points carry a weight heat
    map or the TP/FP/FN colours (they would hide them); none while one EM step is on screen."""
    s = session.state
    keep = session.results.shown_mask()
    if s.view_mode != "result":  # one EM step on screen: no final instance over it
        keep = np.zeros_like(keep)
    nodes.show_results(
        keep,
        show_meshes=s.show_meshes and s.color_mode in ("rgb", "instances"),
        show_obbs=s.show_obbs,
        show_axes=s.show_axes,
    )


def draw_point_colors(nodes: SceneNodes, session: ViewerSession) -> str | None:
    """Recolour the scene points (and the boxes, in the TP/FP view) for the colour mode (sends only (N,3) uint8);
    on a mesh scene the recoloured points are shown over the mesh (`SceneNodes.set_display`).

    Returns:
        The colouring in effect (its key is shown under the Colour control), or None without a scene.
    """
    pc = session.results.point_colors(nodes.results.colors)
    if pc is None:
        return None
    nodes.set_point_colors(pc.colors, key=pc.key)
    nodes.set_box_colors(pc.boxes)
    # a mesh scene shows a recolouring on its points over the mesh: keep the two in step with the colours
    nodes.set_display(session.state.display, recolored=session.scenes.recolored())
    return pc.shown
