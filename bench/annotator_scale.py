"""Annotator server-side benchmark on a 1M-vertex mesh: open, brush stroke, region grow, autosave, bytes sent.

Builds a procedural 1000x1000-vertex tabletop height field (1M vertices, 2M triangles) with mug-sized bumps,
opens it in `AnnotatorApp` (port 0, no browser) and drives the same handlers the GUI calls:

* open: `AnnotatorApp(...)` construction (load PLY, store + journal, chunks, draw, GUI), and until the search
  structures (kd-tree, adjacency graph, ray caster) are built in the background.
* brush: a ctrl-drag stroke of 1 start + 30 updates + end through `handle_event("drag", ...)`: ray cast,
  capsule selection, journal append + fsync, colour update of the touched chunks. Median ms per drag event,
  payload bytes per event and per stroke.
* region grow: `grow(seed)` (20° / 15 cm) including the paint edit.
* autosave: `store.save_now()` (atomic checkpoint rewrite of 1M labels).
* memory: the server's resident set after open, after the warm-up and at its peak.
* `--browser`: headless Debian chromium (software WebGL) opens the page: seconds until the canvas shows the scan and
  stops changing, then a real Ctrl+drag (playwright mouse events) and the seconds until the server has the stroke.

Scans over the display budget (1M vertices) are drawn from a subset (`annotator.scan_view`). Writes
bench/results/annotator_scale/latest.json (annotator_scale_<n>[_display<k>].json for other sizes). Usage:
`python -m bench.annotator_scale [--n-side 1000|2236] [--browser]`.
"""

from __future__ import annotations

import argparse
import logging
import platform
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bench.common import result_path, rss_mb, write_result  # first: the OpenMP wait policy, before torch


def make_surface(n_side: int, *, seed: int = 0) -> "object":
    """A (n_side x n_side)-vertex height-field mesh, 1.2 m square, with cylinder-like bumps (metres, +Z up)."""
    from efem_viz.data.scene import Scene

    rng = np.random.default_rng(seed)
    xs = np.linspace(-0.6, 0.6, n_side, dtype=np.float32)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    Z = np.zeros_like(X)
    for _ in range(8):
        cx, cy = rng.uniform(-0.45, 0.45, size=2)
        r = rng.uniform(0.035, 0.05)
        h = rng.uniform(0.08, 0.12)
        d = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
        Z = np.maximum(Z, h / (1.0 + np.exp((d - r) / 0.004)))
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1).astype(np.float32)
    i = np.arange(n_side - 1)
    a = (i[:, None] * n_side + i[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + n_side, a + 1], 1), np.stack([a + 1, a + n_side, a + n_side + 1], 1)])
    return Scene.create("bench_surface", pts, faces=faces.astype(np.int32), max_points=len(pts))



FRAMES_JS = """() => new Promise(done => {
  let n = 0; const t0 = performance.now();
  const tick = () => { n += 1; if (performance.now() - t0 < 10000) requestAnimationFrame(tick);
                       else done(n / ((performance.now() - t0) / 1000)); };
  requestAnimationFrame(tick);
})"""
"""Frames the page draws per second, counted over 10 s."""


def _browser_stage(app: "object") -> dict[str, float]:
    """Open the page in headless chromium: seconds to a settled canvas showing the scan, then one real Ctrl+drag
    across the middle of the view and the seconds until the server has painted it; frames per second in between."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "browser"))
    from browser_utils import canvas_png, ctrl_drag, wait_until
    from conftest import CHROMIUM_ARGS, CHROMIUM_PATH, VIEWPORT
    from playwright.sync_api import sync_playwright

    iid = app.session.instances.new_instance(category="mug")  # type: ignore[attr-defined]
    app.session.toolbox.settings.radius = 0.03  # type: ignore[attr-defined]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM_PATH, headless=True, args=CHROMIUM_ARGS)
        try:
            page = browser.new_context(viewport=VIEWPORT).new_page()
            page.set_default_timeout(600_000)  # software WebGL with a million points: minutes, not seconds
            t0 = time.perf_counter()
            page.goto(app.url, wait_until="commit")  # type: ignore[attr-defined]
            page.get_by_text("Tools", exact=True).first.wait_for(timeout=600_000)
            gui_s = time.perf_counter() - t0
            print(f"page: GUI after {gui_s:.1f} s", file=sys.stderr, flush=True)
            shown: list[float] = []

            def drawn() -> bool:  # the share of the canvas that is not background (the corner pixel's colour)
                img = canvas_png(page)
                shown.append(float((abs(img - img[2, 2]).sum(axis=-1) > 30).mean()))
                print(f"page: {time.perf_counter() - t0:.1f} s, {100 * shown[-1]:.1f}% of the canvas drawn",
                      file=sys.stderr, flush=True)
                return shown[-1] > 0.02

            wait_until(drawn, 900, "the scan drawn")
            first_s = time.perf_counter() - t0
            fps = page.evaluate(FRAMES_JS)
            page.screenshot(path=str(Path(tempfile.gettempdir()) / "bench_annotator_page.png"))
            box = page.locator("canvas").first.bounding_box()
            cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            t1 = time.perf_counter()
            ctrl_drag(page, (cx - 60, cy), (cx + 60, cy + 20))
            drag_s = time.perf_counter() - t1
            wait_until(lambda: bool((app.session.scan.store.labels == iid).any()), 120,  # type: ignore[attr-defined]
                       "the stroke on the server")
            stroke_s = time.perf_counter() - t1
        finally:
            browser.close()
    return {"page_gui_s": round(gui_s, 1), "page_scan_visible_s": round(first_s, 1),
            "page_frames_per_s": round(float(fps), 2), "page_canvas_drawn": round(shown[-1], 3),
            "page_drag_s": round(drag_s, 1), "page_stroke_on_server_s": round(stroke_s, 1),
            "page_painted": int((app.session.scan.store.labels == iid).sum())}  # type: ignore[attr-defined]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n-side", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--browser", action="store_true", help="also time the page in headless chromium")
    ap.add_argument("--display-points", type=int, default=None, help="display budget (default: the annotator's)")
    args = ap.parse_args()
    if args.out is None:
        tag = "" if args.n_side == 1000 else f"{args.n_side ** 2}"
        if args.display_points is not None:
            tag = f"{tag}_display{args.display_points}".lstrip("_")
        args.out = result_path("annotator_scale", tag or None)
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    from annotator.app import AnnotatorApp
    from efem_viz.data.io import save_scene

    tmp = Path(tempfile.mkdtemp(prefix="bench_annotator_"))
    t0 = time.perf_counter()
    cached = Path.home() / ".cache" / "efem-viz" / "bench" / f"surface_{args.n_side}.ply"
    if not cached.is_file():  # about a minute at 5M vertices: kept for the next run
        cached.parent.mkdir(parents=True, exist_ok=True)
        save_scene(make_surface(args.n_side), cached)
    scan = shutil.copy(cached, tmp / "surface.ply")
    gen_s = time.perf_counter() - t0
    n = args.n_side ** 2
    faces = 2 * (args.n_side - 1) ** 2

    t0 = time.perf_counter()
    budget = {} if args.display_points is None else {"display_points": args.display_points}
    app = AnnotatorApp(scan, out_dir=tmp / "out", port=0, autosave_delay=0.5, max_points=max(n, 2_000_000), **budget)
    open_s = time.perf_counter() - t0
    rss_open = rss_mb()
    app.session.scan.geom.warm_up()
    ready_s = time.perf_counter() - t0
    rss_ready = rss_mb()
    try:
        page_stats = _browser_stage(app) if args.browser else {}
        iid = app.session.instances.new_instance(category="mug")
        app.session.toolbox.settings.radius = 0.02
        cam = SimpleNamespace(position=np.array([0.0, -0.3, 1.0]), wxyz=np.array([0.0, 1.0, 0.0, 0.0]),
                              fov=0.9, aspect=1.5)
        client = SimpleNamespace(camera=cam)

        def ev(phase: str, end: np.ndarray) -> SimpleNamespace:
            return SimpleNamespace(phase=phase, client_id=1, client=client, start_position=tuple(start),
                                   end_position=tuple(end), modifier="cmd/ctrl")

        event_ms: list[float] = []
        event_bytes: list[int] = []
        stroke_bytes: list[int] = []
        for s in range(5):
            y = -0.4 + 0.2 * s
            start = np.array([-0.5, y, 0.0], np.float32)
            b0 = app.view.stats.bytes_sent
            for k in range(32):
                phase = "start" if k == 0 else ("end" if k == 31 else "update")
                x = -0.5 + 0.03 * k
                # a point on the drag plane between the camera and the surface point (x, y, 0)
                target = np.array([x, y, 0.0])
                end = cam.position + 0.5 * (target - cam.position)
                bb = app.view.stats.bytes_sent
                t1 = time.perf_counter()
                app.handle_event("drag", ev(phase, end))
                event_ms.append(1000 * (time.perf_counter() - t1))
                event_bytes.append(app.view.stats.bytes_sent - bb)
            stroke_bytes.append(app.view.stats.bytes_sent - b0)
        painted = int((app.session.scan.store.labels == iid).sum())

        # region grow on a bump top: seed = highest vertex
        app.session.toolbox.settings.grow_angle_deg = 20.0
        app.session.toolbox.settings.grow_distance = 0.15
        grow_ms = []
        grow_sel_ms = []
        tops = np.argsort(app.session.scan.scene.points[:, 2])[-1:]
        seeds = [int(tops[0])] + [int(i) for i in np.random.default_rng(1).choice(n, size=4, replace=False)]
        from annotator import selection as sel

        for sd in seeds:
            b = app.session.instances.new_instance()
            t1 = time.perf_counter()
            idx = sel.region_grow(app.session.scan.geom, sd, max_angle_deg=20.0, max_distance=0.15)
            grow_sel_ms.append(1000 * (time.perf_counter() - t1))
            t1 = time.perf_counter()
            d = app.session.painting.grow(sd)
            grow_ms.append(1000 * (time.perf_counter() - t1))
            assert d is None or d.num_vertices <= len(idx)
            assert b > 0
        grown_sizes = [int(len(sel.region_grow(app.session.scan.geom, sd, max_angle_deg=20.0, max_distance=0.15)))
                       for sd in seeds]

        save_ms = []
        for k in range(5):
            app.session.painting.paint(np.arange(k * 10, k * 10 + 10))
            t1 = time.perf_counter()
            app.session.scan.store.save_now()
            save_ms.append(1000 * (time.perf_counter() - t1))
        journal_bytes = app.session.scan.store.journal.bytes_written
    finally:
        app.close()
        shutil.rmtree(tmp, ignore_errors=True)

    res = {
        "machine": platform.platform(),
        "vertices": n,
        "faces": faces,
        "chunks": app.view.chunks.count,
        "chunk_size_max": int(np.diff(app.view.chunks.offsets).max()),
        "generate_or_copy_ply_s": round(gen_s, 2),
        "open_s": round(open_s, 2),
        "open_until_tools_ready_s": round(ready_s, 2),
        "drawn_points": int(len(app.view.display)),
        "rss_after_open_mb": rss_open,
        "rss_after_warmup_mb": rss_ready,
        "rss_peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        **page_stats,
        "brush_event_ms_median": round(statistics.median(event_ms), 2),
        "brush_event_ms_p90": round(float(np.percentile(event_ms, 90)), 2),
        "brush_bytes_per_event_median": int(statistics.median(event_bytes)),
        "brush_bytes_per_stroke_median": int(statistics.median(stroke_bytes)),
        "brush_stroke_events": 32,
        "brush_radius_m": 0.02,
        "painted_vertices": painted,
        "full_colour_resend_bytes": 3 * n,
        "region_grow_ms_median": round(statistics.median(grow_ms), 1),
        "region_grow_select_only_ms_median": round(statistics.median(grow_sel_ms), 1),
        "region_grow_sizes": grown_sizes,
        "autosave_ms_median": round(statistics.median(save_ms), 1),
        "journal_bytes": journal_bytes,
        "threads": 1,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_result(args.out, res)
    for k, v in res.items():
        print(f"{k:36s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
