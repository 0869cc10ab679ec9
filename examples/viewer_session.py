"""Embed the viewer's headless session in a script or a notebook: no viser, no browser, typed data in and out.

`efem_viz.viewer.session.ViewerSession` is everything the viewer does, without its GUI (the viser app,
`efem_viz.viewer.app.ViewerApp`, is a thin layer over it). This example

1. lists the bundled sample scenes (`sample_scenes/`) and opens one (`open_scene`);
2. loads its precomputed result (`load_result`: `<scene>.efem.npz`; `run(preset=..., on_step=...)` runs EFEM
   instead);
3. steps through the EM iterations (`set_step` returns the live proposals of a step);
4. sets a confidence threshold and prints the instances kept (and the ground-truth AP when the scene has labels);
5. exports the thresholded result (ScanNet layout + coloured PLY) under `--out`.

Run (a second or two)::

    python examples/viewer_session.py
    python examples/viewer_session.py --scene syn_pile_0 --threshold 0.5
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="syn_z_1", help="a scene of sample_scenes/ (with its precomputed result)")
    ap.add_argument("--threshold", type=float, default=0.3, help="confidence threshold")
    ap.add_argument("--out", type=Path, default=None, help="output root (default: a temp dir)")
    args = ap.parse_args(argv)

    from efem_viz.viewer.session import ViewerSession

    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)

    # ---- 1. the scenes inside the given paths; open one
    session = ViewerSession([REPO / "sample_scenes"], out_dir=out)
    session.on_status = lambda text, error: print(f"  [{'error' if error else 'status'}] {text}")
    print(f"scenes: {[e.name for e in session.state.entries]}")
    scene = session.scenes.open_scene(args.scene)
    if scene is None:
        print(f"could not open {args.scene}: {session.state.error}")
        return 1

    # ---- 2. its saved result (the trace and the final instances)
    result = session.results.load_result()
    if result is None:
        print(f"no result for {args.scene}: {session.state.error}")
        return 1
    print(f"opened {scene.name}: {scene.num_points} points; result with {result.trace.num_steps} EM steps, "
          f"{len(result.instances)} instances")

    # ---- 3. the EM iterations
    for t in (0, result.trace.num_steps // 2, result.trace.num_steps - 1):
        v = session.timeline.set_step(t)
        assert v is not None
        print(f"step {v.step}: {len(v.ids)} live proposals, top {v.drawn.tolist()}")

    # ---- 4. threshold and the instances kept
    session.results.set_threshold(args.threshold)
    kept = np.flatnonzero(session.results.kept_mask())
    inst = result.instances
    print(f"threshold {args.threshold} keeps {kept.size} of {len(inst)} instances:")
    for k in kept:
        print(f"  #{int(inst.ids[k])} {inst.category[k]} confidence {float(inst.confidence[k]):.2f}, "
              f"{len(inst.masks[k])} points")
    if scene.has_gt:
        m = session.results.gt_metrics()
        print(f"ground truth: {len(m.tp)} TP, {len(m.fp)} FP, {len(m.fn)} FN")

    # ---- 5. export (into the output root; `root=` refuses anything outside it)
    written = session.export.export_results(out / "exported", root=out)
    print(f"exported results to {written}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
