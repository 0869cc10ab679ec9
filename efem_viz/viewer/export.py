"""Exports from the viewer: results (ScanNet layout + coloured PLY) and a static, self-contained demo page.

The static demo is recorded with viser's scene serializer on a private, short-lived server bound to 127.0.0.1
(port 0, behind the access guard; its token is shown to no one): the scan, then one frame per EM step (sampled points of the live proposals, coloured by id, the decoded
shapes of the best few when the prior is given, and a caption with the phase and the number of active proposals), then the final result (instance colours, meshes, boxes).
`as_html()` inlines the viser client and the zstd-compressed recording, so `index.html` opens from file:// with a
playback bar (pause, scrub, speed, loop) and needs nothing else.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from efem_viz.viewer import state as st
from efem_viz.viewer.nodes import obb_segments, rotation_to_wxyz

logger = logging.getLogger(__name__)


def _atomic_write_text(path: Path, text: str) -> Path:
    from efem_viz.data.io import atomic_write_text

    return Path(atomic_write_text(path, text))


def export_results(result: Any, scene: Any, out_dir: Path, *, threshold: float = 0.0) -> Path:
    """Write the instances with confidence ≥ threshold in the ScanNet benchmark layout and as a coloured PLY.

    Args:
        result: `efem_viz.em.EMResult`.
        scene: the `Scene` it was computed on.
        out_dir: folder (created); gets `<scene>.txt`, `pred_mask/…` and `<scene>_instances.ply`.
        threshold: confidence threshold.

    Returns:
        The output folder.

    Raises:
        ValueError: the result does not match the scene (mask indices out of range).
    """
    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    inst = result.instances.above(float(threshold))
    n = scene.num_points
    for k, m in enumerate(inst.masks):
        m = np.asarray(m)
        if m.size and (m.min() < 0 or m.max() >= n):
            raise ValueError(f"instance {k} has point indices outside [0, {n}): the result does not match {scene.name!r}")
    inst.to_scannet(out, scene.name, n)
    inst.to_colored_ply(scene, out / f"{scene.name}_instances.ply")
    logger.info("exported %d instances of %s to %s", len(inst.ids), scene.name, out)
    return out


def export_static_demo(
    scene: Any,
    result: Any,
    out_dir: Path,
    *,
    threshold: float = 0.0,
    max_points: int = 60_000,
    max_proposals: int = 64,
    step_seconds: float = 0.6,
    final_seconds: float = 3.0,
    seed: int = 0,
    prior: Any = None,
    shapes_per_step: int = 4,
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
        prior: the shape prior of the run; when given, the decoded shapes of the `shapes_per_step` best live
            proposals are part of every step (decoded here, about 0.3 s each with the mug prior on a CPU).
        shapes_per_step: see `prior`.

    Returns:
        Path of the written `index.html`.
    """
    from efem_viz.viewer.guard import start_server

    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    pts = np.asarray(scene.points, np.float32)
    n = pts.shape[0]
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(n, size=max_points, replace=False)) if n > max_points else np.arange(n)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    psize = max(diag * 0.004, 1e-4)
    trace = result.trace
    T = int(trace.num_steps)
    inst = result.instances.above(float(threshold))
    caption_pos = (float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), float(hi[2] + 0.08 * diag))

    n_shapes = 0
    server, _ = start_server(host="127.0.0.1", port=0)  # guarded too: its token is never shown to anyone
    try:
        ser = server.get_scene_serializer()
        api = server.scene
        api.set_up_direction("+z")
        center = (lo + hi) / 2.0
        cam = server.initial_camera  # recorded: the page opens looking at the scene
        cam.look_at = st.xyz_tuple(center)
        cam.position = st.xyz_tuple(center + diag * np.array([0.5, -0.95, 0.85]))
        cam.up = (0.0, 0.0, 1.0)
        cloud = api.add_point_cloud(
            "/scene/points", points=pts[keep], colors=st.dim(scene.colors[keep]), point_size=psize, point_shape="rounded"
        )
        api.add_label("/caption", text=f"{scene.name}: {int(np.asarray(trace.active_count)[0]) if T else 0} proposals", position=caption_pos)
        ser.insert_sleep(step_seconds)
        for t in range(T):
            ids, scores = st.alive_table(trace, t)
            drawn = st.top_n(ids, scores, max_proposals)
            cols = st.palette(drawn)
            p_list, c_list = [], []
            for k, pid in enumerate(drawn):
                idx = st.sample_indices(trace, int(pid), t)
                if idx is None or idx.size == 0:
                    continue
                idx = np.unique(idx)
                p_list.append(pts[idx])
                c_list.append(np.repeat(cols[k : k + 1], idx.size, axis=0))
            if p_list:
                api.add_point_cloud(
                    "/em/samples",
                    points=np.concatenate(p_list),
                    colors=np.concatenate(c_list),
                    point_size=psize * 1.6,
                    point_shape="circle",
                )
            api.remove_by_name("/em/shapes")
            if prior is not None and shapes_per_step > 0:
                from efem_viz.em.solver import mesh_of_latent

                res = int(getattr(trace.config, "mesh_resolution", 32))
                for pid in drawn[:shapes_per_step]:
                    mesh = mesh_of_latent(prior, trace.latent(int(pid), t), resolution=res)
                    if mesh is None or not len(mesh.faces):
                        continue
                    n_shapes += 1
                    dead = st.is_dead_at(trace, int(pid), t)
                    col = st.DEAD_COLOR if dead else st.palette([int(pid)])[0]
                    api.add_mesh_simple(
                        f"/em/shapes/p{int(pid)}",
                        vertices=np.asarray(mesh.vertices, np.float32),
                        faces=np.asarray(mesh.faces, np.int32),
                        color=st.rgb_tuple(col),
                        opacity=0.85,
                    )
            phase = int(np.asarray(trace.phase)[t])
            api.add_label("/caption", text=f"step {t}/{T - 1} · phase {phase} · {len(ids)} active", position=caption_pos)
            ser.insert_sleep(step_seconds)
        api.remove_by_name("/em")
        kept = np.asarray(result.instances.confidence, float) >= float(threshold)
        cloud.colors = st.instance_colors(scene.colors, result.instances, kept)[keep]  # same colours as the meshes
        ids_all = np.asarray(inst.ids).reshape(-1)
        pal = st.palette(ids_all)
        for k in range(ids_all.shape[0]):
            col = st.rgb_tuple(pal[k])
            if k < len(inst.mesh_vertices) and inst.mesh_vertices[k] is not None and len(inst.mesh_faces[k]):
                api.add_mesh_simple(
                    f"/results/mesh/k{k}",
                    vertices=np.asarray(inst.mesh_vertices[k], np.float32),
                    faces=np.asarray(inst.mesh_faces[k], np.int32),
                    color=col,
                    opacity=0.75,
                )
            api.add_line_segments(
                f"/results/obb/k{k}",
                points=obb_segments(inst.obb_center[k], inst.obb_axes[k], inst.obb_half_extents[k]),
                colors=col,
                thickness=2.0,
                thickness_units="screen",
            )
            api.add_frame(
                f"/results/axes/k{k}",
                wxyz=tuple(rotation_to_wxyz(inst.R[k])),
                position=st.xyz_tuple(np.asarray(inst.center[k]).reshape(3)),
                axes_length=float(np.max(inst.obb_half_extents[k])) * 1.2,
                axes_radius=float(np.max(inst.obb_half_extents[k])) * 0.05,
            )
        api.add_label(
            "/caption", text=f"result: {ids_all.shape[0]} objects (confidence ≥ {threshold:.2f})", position=caption_pos
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
    result = EMResult.load(st.trace_path_for(args.scene))
    result.trace.bind(scene)
    prior = None
    if args.prior:
        from efem_viz.prior import load_prior

        prior = load_prior(args.prior)
    out = args.out or Path.cwd() / "static" / "".join(c if c.isalnum() or c in "-_." else "_" for c in scene.name)
    index = export_static_demo(scene, result, out, threshold=args.threshold, prior=prior)
    print(index)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
