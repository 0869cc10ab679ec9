"""Embed the EFEM viewer in your own script: build it over a scene and a result computed in Python.

`efem_viz.viewer.app.ViewerApp` is the whole viewer (a viser server, its GUI panels and scene nodes); every
GUI control calls one of its public methods (`open_scene`, `set_result`, `set_step`, `select_proposal`,
`set_threshold`, `set_result_layers`, `export_results`, ...), so a script or a test can drive it with no
browser.
This example

1. makes the analytic sphere tabletop (`efem_viz.prior.analytic.make_sphere_scene`; no trained weights needed)
   and runs EFEM on it with the analytic sphere prior, or, with `--scene syn_z_1`, takes a bundled sample
   scene with its precomputed result and the shipped mug prior;
2. builds the viewer on port 0 (a free port, loopback only) over that scene and hands it the result;
3. calls a few callbacks as the GUI would (step slider, proposal inspector, confidence threshold, layers,
   export) and prints the scene nodes they drew;
4. stops the server, or with `--serve` keeps serving until Ctrl+C (open the printed URL: it carries the
   access token).

Run (a few seconds with the defaults)::

    python examples/embed_viewer.py
    python examples/embed_viewer.py --scene syn_z_1 --serve
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def scene_nodes(app: Any) -> list[str]:
    """Names of the scene nodes the viewer holds handles for (its `SceneNodes`)."""
    n = app.nodes
    handles = [n.points, n.mesh, n.samples, *n.shapes.values(), *n.inspect.values(), *n.results.meshes,
               *n.results.obbs, *n.results.axes, *n.results.labels]
    return [h.name for h in handles if h is not None]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="spheres",
                    help="'spheres' (analytic scene, EFEM run here) or a sample_scenes/<name> with a result")
    ap.add_argument("--proposals", type=int, default=16, help="proposals of the run on the sphere scene")
    ap.add_argument("--serve", action="store_true", help="keep serving until Ctrl+C")
    ap.add_argument("--port", type=int, default=0, help="port (0 = a free one)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--out", type=Path, default=None, help="output root of the viewer (default: a temp dir)")
    args = ap.parse_args(argv)

    import torch

    from efem_viz.data.io import save_scene
    from efem_viz.em import EMResult, preset, run_em
    from efem_viz.serve.lifecycle import stop_signals, wait_for_stop
    from efem_viz.viewer.app import ViewerApp

    torch.set_num_threads(args.threads)
    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)

    # ---- 1. a scene file and a result (the viewer lists scene *files*; results may come from anywhere)
    result: EMResult | None = None
    if args.scene == "spheres":
        from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

        scene = make_sphere_scene(seed=0, spacing=0.008, name="spheres")
        path = save_scene(scene, out / "spheres.ply")
        prior: Any = make_sphere_prior()
        # a sparse scene: small sets
        cfg = preset("fast").with_proposals(args.proposals).replace(elimination={"min_size": 30})
        result = run_em(scene, prior, cfg, seed=0)
        print(f"ran EFEM on {scene.name}: {len(result.instances)} instances in "
              f"{result.timings['total']:.1f} s")
    else:
        from efem_viz.prior import load_prior

        path = REPO / "sample_scenes" / f"{args.scene}.ply"
        prior = load_prior("mug")  # or prior=None: the viewer loads prior_name lazily when it first decodes

    # ---- 2. the viewer over that file; no scene opens until asked
    app = ViewerApp([path], port=args.port, prior=prior, open_first=False, out_dir=out)
    try:
        assert app.open_scene(path.stem), "the scene did not open (see the status line)"
        if result is not None:
            app.set_result(result, source="run_em in embed_viewer.py")
        assert app.wait_idle(60)  # a saved `<scene>.efem.npz` beside the file loads by itself
        res = app.state.result
        assert res is not None, "no result to show"
        print(f"viewer at {app.url} showing {app.state.scene_name}: {res.trace.num_steps} steps, "
              f"{len(res.instances)} instances")

        # ---- 3. the callbacks the GUI controls call
        app.set_step(1)
        assert app.wait_idle(60)
        pid = int(res.instances.ids[0]) if len(res.instances) else int(res.trace.alive(1)[0])
        fut = app.select_proposal(pid)
        if fut is not None:
            fut.result(timeout=60)
        assert app.wait_idle(60)
        print(f"inspecting proposal #{pid} at step 1: {sorted(app.nodes.inspect)}")
        app.set_result_layers(meshes=True, obbs=True, axes=False)
        app.set_threshold(0.5)
        kept = int(app.session.results.kept_mask().sum())
        print(f"threshold 0.5 keeps {kept} of {len(res.instances)} instances")
        exported = app.export_tab.export_results(out / "exported")
        print(f"exported results to {exported}")
        names = scene_nodes(app)
        print(f"scene nodes ({len(names)}):")
        for name in names:
            print(f"  {name}")
        if args.serve:
            print(f"serving {app.url} (Ctrl+C stops)")
            with stop_signals("embed_viewer"):  # Ctrl+C / SIGTERM stop it, also when started in the background
                wait_for_stop()
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
