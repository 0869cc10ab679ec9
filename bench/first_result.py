"""How soon a run shows something: the viewer's Run and the annotator's EFEM run, from the press to the first state
drawn (its proposals, before any EM step), to the first step's state, and to the instances accepted.

Both apps run as a user runs them (server side, no browser: every colour and point array is sent to viser's
queue), on bundled scenes with the shipped mug prior: a real frame with the `real` preset and a synthetic scene
with the `synthetic` one. Wall seconds from the call that starts the run; the median over `--repeats` runs, each
after one warm-up run per app (the encoder's kernels built, the prior loaded). A run is stopped once its first
step has been drawn unless `--full` lets it finish.

    python -m bench.first_result --threads 1            # writes bench/results/first_result/latest.json
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import ROOT, machine, result_path, write_result  # first: the OpenMP wait policy, before torch

SCENES = (("real_tabletop_0", "real"), ("syn_z_1", "synthetic"))
"""(bundled scene, preset) pairs measured."""


def _viewer_run(app: Any, preset: str, full: bool) -> dict[str, float]:
    """One viewer Run: seconds to the first shown state, the first step's, and the end."""
    marks: dict[str, float] = {}
    original = app.set_result
    t0 = time.perf_counter()

    def spy(result: Any, *, source: str, view_mode: str = "result") -> None:
        original(result, source=source, view_mode=view_mode)
        now = time.perf_counter() - t0
        if source.startswith("running:"):
            marks.setdefault("first_shown_s", now)
            if result.trace.num_steps >= 1:
                marks.setdefault("first_step_s", now)
                if not full:
                    app.session.runs.cancel_run()

    app.set_result = spy
    try:
        app.run_panel.progressive_every_s = 0.0
        fut = app.start_run(preset=preset, seed=0)
        fut.result(timeout=1800)
        marks["end_s"] = time.perf_counter() - t0
    finally:
        app.set_result = original
    app.wait_idle(120)
    return marks


def _annotator_run(app: Any, preset: str, full: bool) -> dict[str, float]:
    """One annotator EFEM run on the scan: seconds to the first overlay drawn, the first step's, and the end."""
    marks: dict[str, float] = {}
    ses = app.session
    draw = ses.on_preview
    t0 = time.perf_counter()

    def spy(idx: Any) -> Any:
        out = draw(idx)
        ov = ses.assist.run_overlay
        if ov is not None:
            now = time.perf_counter() - t0
            marks.setdefault("first_shown_s", now)
            if ov.step >= 0:
                marks.setdefault("first_step_s", now)
                if not full:
                    ses.assist.cancel_efem()
        return out

    ses.on_preview = spy
    try:
        ses.assist.progressive_every_s = 0.0
        ses.assist.run_efem(preset=preset, wait=True)
        marks["end_s"] = time.perf_counter() - t0
    finally:
        ses.on_preview = draw
    return marks


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--full", action="store_true", help="let every run finish (the end time is the whole run)")
    ap.add_argument("--apps", nargs="+", default=["viewer", "annotator"], choices=["viewer", "annotator"])
    ap.add_argument("--out", type=Path, default=result_path("first_result"))
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from annotator.app import AnnotatorApp
    from efem_viz.viewer.app import ViewerApp

    samples = ROOT / "sample_scenes"
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene, preset in SCENES:
            for which in args.apps:
                if which == "viewer":
                    app: Any = ViewerApp([samples], port=0, open_first=False, out_dir=Path(tmp) / "viewer")
                    assert app.open_scene(scene) and app.wait_idle(120)
                    one = lambda: _viewer_run(app, preset, args.full)  # noqa: E731
                    close = app.stop
                else:
                    app = AnnotatorApp(samples / f"{scene}.ply", out_dir=Path(tmp) / f"ann_{scene}", port=0,
                                       autosave_delay=0)
                    one = lambda: _annotator_run(app, preset, args.full)  # noqa: E731
                    close = app.close
                try:
                    one()  # warm-up: kernels, prior, caches
                    runs = [one() for _ in range(args.repeats)]
                finally:
                    close()
                row = {"app": which, "scene": scene, "preset": preset, "runs": runs}
                for k in ("first_shown_s", "first_step_s", "end_s"):
                    vals = [r[k] for r in runs if k in r]
                    row[k] = statistics.median(vals) if vals else None
                rows.append(row)
                print(f"{which:9s} {scene:16s} {preset:9s} first shown {row['first_shown_s']:.2f} s · first step "
                      f"{row['first_step_s']:.2f} s · {'end' if args.full else 'stopped'} {row['end_s']:.2f} s")
    write_result(args.out, {"machine": machine(), "threads": args.threads, "repeats": args.repeats,
                            "full": args.full, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
