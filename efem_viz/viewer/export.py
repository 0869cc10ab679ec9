"""Exports from the viewer: results (ScanNet layout + coloured PLY) and a static, self-contained demo page.

The static demo is recorded with viser's scene serializer on a private, short-lived server bound to 127.0.0.1
(port 0, behind the access guard; its token is shown to no one): the scan, then one frame per EM step (sampled points of
the live proposals, coloured by id, the decoded
shapes of the best few when the prior is given, and a caption with the phase and the number of active proposals), then
the final result (instance colours, meshes, boxes, pose axes and category labels, drawn by the same
`efem_viz.viewer.nodes` functions as the live viewer).
`as_html()` inlines the viser client and the zstd-compressed recording, so `index.html` opens from file:// with a
playback bar (pause, scrub, speed, loop) and needs nothing else.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.colors import dim, instance_point_colors
from efem_viz.em.replay import prior_latent
from efem_viz.viewer.scene_list import trace_path_for
from efem_viz.viewer.trace_queries import decode_shape, proposal_samples, top_n
from efem_viz.terminal import count
from efem_viz.viewer.legend import category_summary
from efem_viz.viewer.nodes import (
    add_result_nodes,
    add_sample_cloud,
    add_shape_mesh,
    VIEW_DIRECTION,
    default_point_size,
    scene_diagonal,
)

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult
    from efem_viz.prior.config import ShapePriorLike

logger = logging.getLogger(__name__)

STEP_SHAPE_FACES = 1500
"""Faces of each decoded shape a static demo shows at the EM steps (the run's meshes have 5,000): the steps' 80
shapes, seen for 0.6 s each, made up half of a demo page (the mug tree scene's page: 5.6 MB with 5,000 faces, 3.1 MB
with 1,500); the final instances keep their full meshes."""


def _atomic_write_text(path: Path, text: str) -> Path:
    from efem_viz.data.io import atomic_write_text

    return Path(atomic_write_text(path, text))


def results_files(result: EMResult, scene: Scene, out_dir: Path, *, threshold: float = 0.0) -> list[Path]:
    """The folders and files `export_results` writes, in order: the folder, `pred_mask/`, one mask file per
    instance (the ScanNet layout of `Instances.to_scannet`), `<scene>.txt`, `<scene>_instances.ply` and
    `objects/` (each instance's completed mesh and `objects.json`, `Instances.export_objects`).

    Args:
        result: `efem_viz.em.EMResult`.
        scene: the `Scene` it was computed on.
        out_dir: the export folder.
        threshold: confidence threshold.
    """
    out = Path(out_dir).expanduser()
    shown = result.instances.above(float(threshold))
    masks = [out / "pred_mask" / f"{scene.name}_{k:03d}.txt" for k in range(len(shown))]
    objects = [out / "objects" / name for name in shown.object_files("glb")]
    return [out, out / "pred_mask", *masks, out / f"{scene.name}.txt", out / f"{scene.name}_instances.ply",
            out / "objects", *objects, out / "objects" / "objects.json"]


def export_results(result: EMResult, scene: Scene, out_dir: Path, *, threshold: float = 0.0,
                   root: Path | None = None) -> Path:
    """Write the instances with confidence ≥ threshold in the ScanNet benchmark layout, as a coloured PLY and as
    objects (each one's completed mesh, pose and box: `objects/objects.json`).

    Args:
        result: `efem_viz.em.EMResult`.
        scene: the `Scene` it was computed on.
        out_dir: folder (created); gets `<scene>.txt`, `pred_mask/…` and `<scene>_instances.ply`.
        threshold: confidence threshold.
        root: when given (the viewer's output root), every folder and file written must lie inside it after
            following symbolic links (`efem_viz.serve.inputs.confine_writes`), checked before anything is
            written.

    Returns:
        The output folder.

    Raises:
        ValueError: the result does not match the scene (mask indices out of range).
        ClientValueError: a path the export would write leaves `root` (nothing was written).
    """
    out = Path(out_dir).expanduser()
    if root is not None:
        from efem_viz.serve.inputs import confine_writes

        confine_writes(results_files(result, scene, out, threshold=threshold), root, what="export")
    inst = result.instances.above(float(threshold))
    n = scene.num_points
    for k, m in enumerate(inst.masks):
        m = np.asarray(m)
        if m.size and (m.min() < 0 or m.max() >= n):
            raise ValueError(f"instance {k} has point indices outside [0, {n}): "
                             f"the result does not match {scene.name!r}")
    out.mkdir(parents=True, exist_ok=True)
    inst.to_scannet(out, scene.name, n)
    inst.to_colored_ply(scene, out / f"{scene.name}_instances.ply")
    inst.export_objects(out / "objects", fmt="glb",
                        extra={"scene": scene.name, "threshold": float(threshold), "units": "metres, +Z up"})
    logger.info("exported %d instances of %s to %s", len(inst.ids), scene.name, out)
    return out


class ExportCancelled(Exception):
    """A static-demo export was cancelled (nothing was written)."""


DemoProgress = Callable[[str, float], None]
"""Called with what a static-demo export does now and the fraction done (0-1)."""


def export_static_demo(
    scene: Scene,
    result: EMResult,
    out_dir: Path,
    *,
    threshold: float = 0.0,
    max_points: int = 60_000,
    max_proposals: int = 64,
    step_seconds: float = 0.6,
    final_seconds: float = 3.0,
    seed: int = 0,
    prior: ShapePriorLike | Sequence[ShapePriorLike] | None = None,
    shapes_per_step: int = 4,
    root: Path | None = None,
    on_progress: DemoProgress | None = None,
    cancel: threading.Event | None = None,
) -> Path:
    """Record a static demo page: the scan, a playback of the EM steps, and the final result.

    Args:
        scene: the `Scene`.
        result: its `EMResult`.
        out_dir: folder for `index.html` (+ `meta.json`), created.
        threshold: confidence threshold of the final instances shown.
        max_points: the scan is subsampled (seeded) to at most this many points to keep the page small.
        max_proposals: per step, draw the sampled points of at most this many live proposals (top by score).
        step_seconds: playback time per EM step.
        final_seconds: time the final result stays before the loop restarts.
        seed: subsampling seed.
        prior: the shape prior of the run (its priors in order for a multi-prior run); when given, the decoded
            shapes of the `shapes_per_step` best live
            proposals are part of every step (decoded here, about 0.3 s each with the mug prior on a CPU).
        shapes_per_step: see `prior`.
        root: when given (the viewer's output root), the folder and both files must lie inside it after following
            symbolic links, checked before anything is recorded or written (see `export_results`).
        on_progress: called with what it records now and the fraction done (each EM step, then the page).
        cancel: when set, the recording stops at the next step and `ExportCancelled` is raised; nothing is written.

    Returns:
        Path of the written `index.html`.

    Raises:
        ClientValueError: a path the export would write leaves `root` (nothing was written).
        ExportCancelled: `cancel` was set (nothing was written).
    """
    out = Path(out_dir).expanduser()
    if root is not None:
        from efem_viz.serve.inputs import confine_writes

        confine_writes([out, out / "index.html", out / "meta.json"], root, what="static demo export")
    pts = np.asarray(scene.points, np.float32)
    n = pts.shape[0]
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(n, size=max_points, replace=False)) if n > max_points else np.arange(n)
    kept = result.instances.kept(float(threshold))
    rec = _DemoRecording(scene, result, keep, step_seconds=step_seconds, on_progress=on_progress, cancel=cancel)
    html, n_shapes = rec.record(prior=prior, shapes_per_step=shapes_per_step, max_proposals=max_proposals,
                                kept=kept, threshold=float(threshold), final_seconds=final_seconds)
    rec.check_cancel("before writing")  # the last moment a Cancel keeps the folder untouched
    out.mkdir(parents=True, exist_ok=True)
    index = out / "index.html"
    _atomic_write_text(index, html)
    meta = {
        "scene": scene.name,
        "points_shown": int(keep.size),
        "points_total": int(n),
        "steps": int(result.trace.num_steps),
        "instances": int(kept.sum()),
        "decoded_shapes": n_shapes,
        "threshold": float(threshold),
        "step_seconds": step_seconds,
        "bytes": len(html.encode("utf-8")),
    }
    _atomic_write_text(out / "meta.json", json.dumps(meta, indent=2))
    logger.info("static demo of %s: %s (%.1f MB)", scene.name, index, meta["bytes"] / 1e6)
    return index


def caption_position(lo: np.ndarray, hi: np.ndarray) -> tuple[float, float, float]:
    """Where the static demo's caption sits: in front of the scene's box (the side the framed camera looks from,
    `VIEW_DIRECTION`'s -y), at its lowest height, so that it reads below the objects and never covers the labels
    that sit above their boxes (it sat over the middle of the scene)."""
    diag = scene_diagonal(lo, hi)
    return float((lo[0] + hi[0]) / 2), float(lo[1] - 0.06 * diag), float(lo[2])


class _DemoRecording:
    """One static demo being recorded on a private, guarded server: the scan, each EM step, the final result."""

    def __init__(self, scene: Scene, result: EMResult, keep: np.ndarray, *, step_seconds: float,
                 on_progress: DemoProgress | None, cancel: threading.Event | None) -> None:
        self.scene, self.result, self.keep = scene, result, keep
        self.pts = np.asarray(scene.points, np.float32)
        lo, hi = self.pts.min(axis=0), self.pts.max(axis=0)
        diag = scene_diagonal(lo, hi)
        self.psize = default_point_size(diag)
        self.caption_pos = caption_position(lo, hi)
        self.step_seconds = step_seconds
        self.on_progress, self.cancel = on_progress, cancel

    def check_cancel(self, what: str) -> None:
        """Raise `ExportCancelled` when the export was cancelled."""
        if self.cancel is not None and self.cancel.is_set():
            raise ExportCancelled(f"static demo of {self.scene.name!r} cancelled ({what})")

    def _report(self, what: str, fraction: float) -> None:
        self.check_cancel(what)
        if self.on_progress is not None:
            self.on_progress(what, fraction)

    def record(self, *, prior: ShapePriorLike | Sequence[ShapePriorLike] | None, shapes_per_step: int,
               max_proposals: int, kept: np.ndarray, threshold: float, final_seconds: float) -> tuple[str, int]:
        """The page's HTML and the number of decoded shapes in it."""
        from efem_viz.serve.guard import start_server

        T = int(self.result.trace.num_steps)
        server, _ = start_server(host="127.0.0.1", port=0)  # guarded too: its token is never shown to anyone
        try:
            ser = server.get_scene_serializer()
            api = server.scene
            cloud = self._scan(server, api, T)
            ser.insert_sleep(self.step_seconds)
            n_shapes = 0
            for t in range(T):
                self._report(f"EM step {t + 1} of {T}", t / (T + 1))
                n_shapes += self._step(api, t, prior=prior, shapes_per_step=shapes_per_step,
                                       max_proposals=max_proposals)
                ser.insert_sleep(self.step_seconds)
            self._report("the final result and the page", T / (T + 1))
            self._final(api, cloud, kept, threshold)
            ser.insert_sleep(final_seconds)
            return ser.as_html(), n_shapes
        finally:
            server.stop()

    def _scan(self, server: Any, api: Any, T: int) -> Any:
        """The camera, the (subsampled, dimmed) scan and the opening caption; returns the scan's cloud."""
        from efem_viz.serve.camera import fitted_view, framing

        api.set_up_direction("+z")
        cam = server.initial_camera  # recorded: the page opens looking at the scene
        flo, fhi, sample = framing(self.pts)
        view = fitted_view(flo, fhi, direction=VIEW_DIRECTION, points=sample)  # the live viewer's framing
        cam.look_at, cam.position = view.look_at, view.position
        cam.up = (0.0, 0.0, 1.0)
        cloud = api.add_point_cloud("/scene/points", points=self.pts[self.keep],
                                    colors=dim(self.scene.colors[self.keep]), point_size=self.psize,
                                    point_shape="rounded")
        first = int(np.asarray(self.result.trace.active_count)[0]) if T else 0
        api.add_label("/caption", text=f"{self.scene.name}: {count(first, 'proposal')}", position=self.caption_pos)
        return cloud

    def _step(self, api: Any, t: int, *, prior: ShapePriorLike | Sequence[ShapePriorLike] | None,
              shapes_per_step: int, max_proposals: int) -> int:
        """EM step t: the samples of the best live proposals, their decoded shapes, the caption; returns the
        number of shapes decoded."""
        trace = self.result.trace
        ids, scores = trace.alive_scores(t)
        drawn = top_n(ids, scores, max_proposals)
        s_pts, s_cols = proposal_samples(trace, t, drawn, self.pts)
        if len(s_pts):
            add_sample_cloud(api, s_pts, s_cols, point_size=self.psize)
        api.remove_by_name("/em/shapes")
        n_shapes = 0
        if prior is not None and shapes_per_step > 0:
            for pid in drawn[:shapes_per_step]:
                pri, lat = prior_latent(trace, int(pid), t, prior)
                shape = decode_shape(pri, lat, resolution=trace.config.review.mesh_resolution,
                                     max_faces=STEP_SHAPE_FACES)
                if shape is None:
                    continue
                n_shapes += 1
                add_shape_mesh(api, f"/em/shapes/p{int(pid)}", *shape, pid=int(pid), dead=trace.is_dead_at(int(pid), t))
        phase = int(np.asarray(trace.phase)[t])
        api.add_label("/caption", text=f"step {t}/{trace.num_steps - 1} · phase {phase} · {len(ids)} active",
                      position=self.caption_pos)
        return n_shapes

    def _final(self, api: Any, cloud: Any, kept: np.ndarray, threshold: float) -> None:
        """The final instances (as the live viewer draws them) over the scan in their colours."""
        inst = self.result.instances.select(kept)
        api.remove_by_name("/em")
        cloud.colors = instance_point_colors(self.scene.colors, self.result.instances, kept)[self.keep]
        add_result_nodes(api, inst, visible=True)  # as the live viewer draws them (meshes, boxes, axes, labels)
        counts = category_summary(inst.category)
        api.add_label(
            "/caption", text=f"result: {count(len(inst), 'object')}" + (f" ({counts})" if counts else "")
            + f", confidence ≥ {threshold:.2f}", position=self.caption_pos,
        )


def main(argv: list[str] | None = None) -> int:
    """`python -m efem_viz.viewer.export SCENE [--prior mug] [--threshold T] [--out DIR]`: write a static demo of
    a scene and its saved `<scene>.efem.npz` (default output: `./static/<scene>/` in the current directory, never
    inside the installed package)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m efem_viz.viewer.export", description=main.__doc__)
    ap.add_argument("scene", type=Path, help="scene file; its result <scene>.efem.npz must lie next to it")
    ap.add_argument("--prior", default="mug", help="prior for the decoded shapes ('' = none)")
    ap.add_argument("--threshold", type=float, default=0.0, help="confidence threshold of the final instances")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: ./static/<scene>/)")
    args = ap.parse_args(argv)
    from efem_viz.data.io import load_scene
    from efem_viz.em import EMResult

    scene = load_scene(args.scene)
    result = EMResult.load(trace_path_for(args.scene))
    result.bind(scene)
    prior: ShapePriorLike | list[ShapePriorLike] | None = None
    if args.prior:
        from efem_viz.prior.registry import PriorSet

        prior = PriorSet(args.prior).for_run(result.trace)  # a multi-prior run names its priors
    out = args.out or Path.cwd() / "static" / "".join(c if c.isalnum() or c in "-_." else "_" for c in scene.name)
    index = export_static_demo(scene, result, out, threshold=args.threshold, prior=prior)
    print(index)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
