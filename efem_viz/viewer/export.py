"""Exports from the viewer: results (ScanNet layout + coloured PLY) and a static, self-contained demo page.

The static demo is recorded with viser's scene serializer on a private, short-lived server bound to 127.0.0.1
(port 0, behind the access guard; its token is shown to no one): the scan, then one frame per EM step (sampled points of the live proposals, coloured by id, the decoded
shapes of the best few when the prior is given, and a caption with the phase and the number of active proposals), then
the final result (instance colours, meshes, boxes, pose axes and category labels, drawn by the same
`efem_viz.viewer.nodes` functions as the live viewer).
`as_html()` inlines the viser client and the zstd-compressed recording, so `index.html` opens from file:// with a
playback bar (pause, scrub, speed, loop) and needs nothing else.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from efem_viz.colors import dim, instance_point_colors
from efem_viz.em.replay import prior_latent
from efem_viz.viewer.scenes import trace_path_for
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


def _atomic_write_text(path: Path, text: str) -> Path:
    from efem_viz.data.io import atomic_write_text

    return Path(atomic_write_text(path, text))


def results_files(result: EMResult, scene: Scene, out_dir: Path, *, threshold: float = 0.0) -> list[Path]:
    """The folders and files `export_results` writes, in order: the folder, `pred_mask/`, one mask file per
    instance (the ScanNet layout of `Instances.to_scannet`), `<scene>.txt` and `<scene>_instances.ply`.

    Args:
        result: `efem_viz.em.EMResult`.
        scene: the `Scene` it was computed on.
        out_dir: the export folder.
        threshold: confidence threshold.
    """
    out = Path(out_dir).expanduser()
    n = len(result.instances.above(float(threshold)))
    masks = [out / "pred_mask" / f"{scene.name}_{k:03d}.txt" for k in range(n)]
    return [out, out / "pred_mask", *masks, out / f"{scene.name}.txt", out / f"{scene.name}_instances.ply"]


def export_results(result: EMResult, scene: Scene, out_dir: Path, *, threshold: float = 0.0,
                   root: Path | None = None) -> Path:
    """Write the instances with confidence ≥ threshold in the ScanNet benchmark layout and as a coloured PLY.

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
            raise ValueError(f"instance {k} has point indices outside [0, {n}): the result does not match {scene.name!r}")
    out.mkdir(parents=True, exist_ok=True)
    inst.to_scannet(out, scene.name, n)
    inst.to_colored_ply(scene, out / f"{scene.name}_instances.ply")
    logger.info("exported %d instances of %s to %s", len(inst.ids), scene.name, out)
    return out


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

    Returns:
        Path of the written `index.html`.

    Raises:
        ClientValueError: a path the export would write leaves `root` (nothing was written).
    """
    from efem_viz.serve.guard import start_server
    from efem_viz.serve.camera import fitted_view, framing

    out = Path(out_dir).expanduser()
    if root is not None:
        from efem_viz.serve.inputs import confine_writes

        confine_writes([out, out / "index.html", out / "meta.json"], root, what="static demo export")
    out.mkdir(parents=True, exist_ok=True)
    pts = np.asarray(scene.points, np.float32)
    n = pts.shape[0]
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(n, size=max_points, replace=False)) if n > max_points else np.arange(n)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    diag = scene_diagonal(lo, hi)
    psize = default_point_size(diag)
    trace = result.trace
    T = int(trace.num_steps)
    kept = result.instances.kept(float(threshold))
    inst = result.instances.select(kept)
    caption_pos = (float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), float(hi[2] + 0.08 * diag))

    n_shapes = 0
    server, _ = start_server(host="127.0.0.1", port=0)  # guarded too: its token is never shown to anyone
    try:
        ser = server.get_scene_serializer()
        api = server.scene
        api.set_up_direction("+z")
        cam = server.initial_camera  # recorded: the page opens looking at the scene
        flo, fhi, sample = framing(pts)
        view = fitted_view(flo, fhi, direction=VIEW_DIRECTION, points=sample)  # the live viewer's framing
        cam.look_at, cam.position = view.look_at, view.position
        cam.up = (0.0, 0.0, 1.0)
        cloud = api.add_point_cloud(
            "/scene/points", points=pts[keep], colors=dim(scene.colors[keep]), point_size=psize, point_shape="rounded"
        )
        api.add_label("/caption", text=f"{scene.name}: {count(int(np.asarray(trace.active_count)[0]) if T else 0, 'proposal')}", position=caption_pos)
        ser.insert_sleep(step_seconds)
        for t in range(T):
            ids, scores = trace.alive_scores(t)
            drawn = top_n(ids, scores, max_proposals)
            s_pts, s_cols = proposal_samples(trace, t, drawn, pts)
            if len(s_pts):
                add_sample_cloud(api, s_pts, s_cols, point_size=psize)
            api.remove_by_name("/em/shapes")
            if prior is not None and shapes_per_step > 0:
                for pid in drawn[:shapes_per_step]:
                    pri, lat = prior_latent(trace, int(pid), t, prior)
                    shape = decode_shape(pri, lat, resolution=trace.config.mesh_resolution)
                    if shape is None:
                        continue
                    n_shapes += 1
                    add_shape_mesh(api, f"/em/shapes/p{int(pid)}", *shape, pid=int(pid),
                                   dead=trace.is_dead_at(int(pid), t))
            phase = int(np.asarray(trace.phase)[t])
            api.add_label("/caption", text=f"step {t}/{T - 1} · phase {phase} · {len(ids)} active", position=caption_pos)
            ser.insert_sleep(step_seconds)
        api.remove_by_name("/em")
        cloud.colors = instance_point_colors(scene.colors, result.instances, kept)[keep]  # same colours as the meshes
        add_result_nodes(api, inst, visible=True)  # as the live viewer draws them (meshes, boxes, axes, labels)
        counts = category_summary(inst.category)
        api.add_label(
            "/caption", text=f"result: {count(len(inst), 'object')}" + (f" ({counts})" if counts else "")
            + f", confidence ≥ {threshold:.2f}", position=caption_pos,
        )
        ser.insert_sleep(final_seconds)
        html = ser.as_html()
    finally:
        server.stop()
    index = out / "index.html"
    _atomic_write_text(index, html)
    meta = {
        "scene": scene.name,
        "points_shown": int(keep.size),
        "points_total": int(n),
        "steps": T,
        "instances": int(len(inst.ids)),
        "decoded_shapes": n_shapes,
        "threshold": float(threshold),
        "step_seconds": step_seconds,
        "bytes": len(html.encode("utf-8")),
    }
    _atomic_write_text(out / "meta.json", json.dumps(meta, indent=2))
    logger.info("static demo of %s: %s (%.1f MB)", scene.name, index, meta["bytes"] / 1e6)
    return index


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
