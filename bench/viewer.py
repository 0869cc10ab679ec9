"""Viewer benchmark (server side, no browser): step change, threshold change, opening a saved trace, bytes sent.

Default scene: the analytic sphere tabletop at ~100k points with a real `run_em` trace (analytic sphere prior, so no
trained weights are needed and the run takes well under a minute). `--scene` / `--trace` measure a given scene and
its saved `<scene>.efem.npz` instead (e.g. a sample scene with its precomputed result and the mug prior).

Bytes are measured by wrapping the server's `queue_message` and serialising every queued message exactly as the
websocket path does (msgpack metadata + raw binary buffers), so the numbers are what each client receives.

    python -m bench.viewer                       # writes bench/results/viewer/latest.json
    python -m bench.viewer --scene sample_scenes/real_tabletop_0.ply --prior mug
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import result_path, write_result  # first: the OpenMP wait policy, before torch
import numpy as np



class ByteCounter:
    """Counts the serialised size of every message the server queues (all clients receive the same bytes)."""

    def __init__(self, server: Any) -> None:
        import msgspec

        self._encode = msgspec.msgpack.encode
        self.bytes = 0
        self.messages = 0
        ws = server._websock_server
        orig = ws.queue_message

        def counting(message: Any) -> None:
            buffers: list[memoryview] = []
            meta = self._encode(message.as_serializable_dict(buffers))
            self.bytes += len(meta) + sum(b.nbytes for b in buffers)
            self.messages += 1
            orig(message)

        ws.queue_message = counting

    def take(self) -> tuple[int, int]:
        out = (self.bytes, self.messages)
        self.bytes = 0
        self.messages = 0
        return out


def make_default(tmp: Path, *, spacing: float, proposals: int, seed: int) -> tuple[Path, Any]:
    """A ~100k-point sphere scene and its saved EM result (real solver, analytic prior)."""
    from efem_viz.data.io import RESULT_SUFFIX, save_scene
    from efem_viz.em import preset, run_em
    from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

    scene = make_sphere_scene(seed=seed, spacing=spacing, radii=(0.05, 0.045, 0.055), name="bench_spheres")
    prior = make_sphere_prior()
    path = tmp / "bench_spheres.ply"
    save_scene(scene, path)
    t0 = time.perf_counter()
    cfg = preset("fast").with_proposals(proposals)
    result = run_em(scene, prior, cfg, seed=seed)
    logging.info("run_em: %.1f s, %d steps, %d instances", time.perf_counter() - t0, result.trace.num_steps,
                 len(result.instances))
    result.save(tmp / f"bench_spheres{RESULT_SUFFIX}")
    return path, prior


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="scene file with <scene>.efem.npz next to it")
    ap.add_argument("--prior", default=None, help="prior name for --scene (default: analytic sphere prior)")
    ap.add_argument("--spacing", type=float, default=0.00185, help="point spacing of the default scene (m)")
    ap.add_argument("--proposals", type=int, default=80)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=result_path("viewer"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    import torch

    torch.set_num_threads(1)
    from efem_viz.viewer import trace_queries as tq
    from efem_viz.viewer.app import ViewerApp

    tmpdir = tempfile.TemporaryDirectory()
    if args.scene is None:
        scene_path, prior = make_default(Path(tmpdir.name), spacing=args.spacing, proposals=args.proposals,
                                         seed=args.seed)
    else:
        scene_path = args.scene.resolve()
        prior = None
        if args.prior is None:
            from efem_viz.prior.analytic import make_sphere_prior

            prior = make_sphere_prior()
    app = ViewerApp([scene_path], port=0, prior=prior, prior_name=args.prior or "mug", open_first=False)
    counter = ByteCounter(app.server)
    rng = np.random.default_rng(args.seed)
    out: dict[str, Any] = {"scene": scene_path.name}
    try:
        name = app.state.entries[0].name
        t0 = time.perf_counter()
        assert app.open_scene(name), app.state.status
        out["open_scene_s"] = time.perf_counter() - t0  # includes loading the saved trace
        app.wait_idle(300)
        if app.state.result is None:
            raise RuntimeError(f"no result for {name}: {app.state.status}")
        scene = app.state.scene
        trace = app.state.result.trace
        T = trace.num_steps
        out["points"] = scene.num_points
        out["steps"] = T
        out["proposals"] = int(trace.active_count[0])
        out["instances"] = len(app.state.result.instances)
        out["trace_file_bytes"] = app.state.entries[0].trace_path.stat().st_size

        # Opening the saved trace (EMResult.load + drawing the timeline, results and last step).
        loads = []
        for _ in range(3):
            app.wait_idle(300)
            t0 = time.perf_counter()
            assert app.load_trace()
            loads.append(time.perf_counter() - t0)
        app.wait_idle(300)
        out["open_trace_s_median"] = statistics.median(loads)

        # Step changes: synchronous server-side part (samples, visibility, panels, plot), then the background
        # decoding of shapes not seen before (first visit) — measured separately.
        counter.take()
        first_visit, first_bytes, decode_s = [], [], []
        for t in range(T):
            t0 = time.perf_counter()
            app.set_step(t)
            first_visit.append((time.perf_counter() - t0) * 1e3)
            b_sync, _ = counter.take()
            t1 = time.perf_counter()
            app.wait_idle(300)
            decode_s.append(time.perf_counter() - t1)
            b_async, _ = counter.take()
            first_bytes.append((b_sync, b_async))
        revisit, revisit_bytes = [], []
        for _ in range(args.repeats):
            t = int(rng.integers(0, T))
            if t == app.state.step:
                t = (t + 1) % T
            t0 = time.perf_counter()
            app.set_step(t)
            revisit.append((time.perf_counter() - t0) * 1e3)
            app.wait_idle(300)
            revisit_bytes.append(counter.take()[0])
        out["step_change_ms_median"] = statistics.median(revisit)
        out["step_change_ms_p90"] = float(np.percentile(revisit, 90))
        out["step_change_first_visit_ms_median"] = statistics.median(first_visit)
        out["step_change_bytes_median"] = statistics.median(revisit_bytes)
        out["step_change_first_visit_sync_bytes_median"] = statistics.median(b for b, _ in first_bytes)
        out["shape_decode_first_visit_s_median"] = statistics.median(decode_s)
        out["shape_decode_bytes_median"] = statistics.median(b for _, b in first_bytes)

        # Threshold changes (instance colours on the scene + visibility of meshes/boxes/axes + panels).
        app.set_color_mode("instances")
        conf = np.asarray(app.state.result.instances.confidence, float)
        hi = float(conf.max()) + 0.02 if conf.size else 1.0
        thr_ms, thr_bytes = [], []
        counter.take()
        for i in range(args.repeats):
            # Worst case: alternate between showing every instance and none, so every change recolours all
            # points and flips every mesh/box/axes visibility.
            v = 0.0 if i % 2 == 0 else hi
            t0 = time.perf_counter()
            app.set_threshold(v)
            thr_ms.append((time.perf_counter() - t0) * 1e3)
            thr_bytes.append(counter.take()[0])
        out["threshold_change_ms_median"] = statistics.median(thr_ms)
        out["threshold_change_ms_p90"] = float(np.percentile(thr_ms, 90))
        out["threshold_change_bytes_median"] = statistics.median(thr_bytes)
        out["point_colors_bytes"] = int(scene.num_points * 3)

        # Inspecting a proposal (weights re-derived from the stored latent, heat map, crop, samples, shape).
        t_mid = T // 2
        ids, scores = trace.alive_scores(t_mid)
        pid = int(tq.top_n(ids, scores, 1)[0])
        app.set_step(t_mid)
        app.wait_idle(300)
        counter.take()
        t0 = time.perf_counter()
        fut = app.select_proposal(pid)
        if fut is not None:
            fut.result(timeout=300)
        app.wait_idle(300)
        out["inspect_proposal_s"] = time.perf_counter() - t0
        out["inspect_proposal_bytes"] = counter.take()[0]
    finally:
        app.stop()
        tmpdir.cleanup()
    out["targets"] = {"step_change_ms_median": 100, "threshold_change_ms_median": 50, "open_trace_s_median": 2.0}
    out["meets_targets"] = {
        k: bool(out[k] <= v) for k, v in out["targets"].items()
    }
    write_result(args.out, out, indent=2)
    for k, v in out.items():
        if not isinstance(v, dict):
            print(f"{k:45s} {v:.4g}" if isinstance(v, float) else f"{k:45s} {v}")
    print("meets targets:", out["meets_targets"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
