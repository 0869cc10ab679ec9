"""Add a second object category: a prior with its own category settings, and one solve over two priors.

Shows:

1. what a prior is to efem-viz: anything satisfying `efem_viz.prior.config.ShapePriorLike` (encode, sdf,
   sdf_and_normals, codebook, n_pcl, name, category, metadata). The analytic sphere prior
   (`efem_viz.prior.analytic.make_sphere_prior`) is one, with no trained weights;
2. its `CategorySettings` (object sizes per capture domain, up-axis range, output-mask band τ_out): they
   travel with the prior, taken from its metadata key "category" or else from `KNOWN_CATEGORIES` by its name;
3. a joint solve `run_em(scene, priors=[mug, sphere])` on a mug scene with spheres added
   (`efem_viz.prior.analytic.add_spheres`): every prior starts proposals, they compete in one pool, duplicates
   across categories are removed, and each instance carries the category of the prior that found it;
4. how a newly trained prior carries its category: its settings written into `metadata["category"]` are saved
   with the weights (`save_prior`) and read back by `load_prior` / `load_priors` (the same list of names and
   paths that `efem-viz segment --prior mug --prior bowl.pt` takes).

Run (about 40 s on one CPU thread with the defaults)::

    python examples/add_category_prior.py
    python examples/add_category_prior.py --scene syn_z_1 --proposals 80 --out /tmp/two_priors
"""

from __future__ import annotations

import argparse
import collections
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="syn_z_1", help="a sample_scenes/<name>.ply name, or a scene path")
    ap.add_argument("--radii", type=float, nargs="+", default=[0.045, 0.04], help="added sphere radii (m)")
    ap.add_argument("--proposals", type=int, default=30, help="proposals per prior in the first episode")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--out", type=Path, default=None, help="folder for outputs (default: a temp dir)")
    args = ap.parse_args(argv)

    import torch

    from efem_viz.data.io import load_scene
    from efem_viz.em import EMResult, preset, run_em
    from efem_viz.eval import evaluate_instances
    from efem_viz.prior import PriorConfig, ShapePrior, load_prior, load_priors, save_prior
    from efem_viz.prior.analytic import add_spheres, make_sphere_prior
    from efem_viz.prior.config import CATEGORY_KEY, KNOWN_CATEGORIES, CategorySettings, ShapePriorLike

    torch.set_num_threads(args.threads)
    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)

    # ---- 1-2. two priors and their category settings
    mug = load_prior("mug")
    sphere = make_sphere_prior()
    for p in (mug, sphere):
        cat = p.category
        print(f"prior {p.name!r}: ShapePriorLike {isinstance(p, ShapePriorLike)}, n_pcl {p.n_pcl}, "
              f"codebook {'yes' if p.codebook is not None else 'none'}; category {cat.name!r}: "
              f"radius {cat.sizes('synthetic')[0]} m, half-height {cat.sizes('synthetic')[1]} m, "
              f"real-capture sizes {cat.sizes('real')}, up range {cat.up_range} deg, tau_out {cat.out_tau:g}")
    print(f"known categories (used when a prior's metadata has none): {sorted(KNOWN_CATEGORIES)}")

    # ---- 3. one solve over both priors on a scene with both kinds of object
    path = Path(args.scene) if Path(args.scene).suffix else REPO / "sample_scenes" / f"{args.scene}.ply"
    base = load_scene(path)
    scene = add_spheres(base, args.radii, seed=args.seed)
    gt = collections.Counter(scene.categories.get(int(i), "object") for i in scene.instance_ids())
    print(f"scene {scene.name}: {scene.num_points} points, ground truth {dict(gt)}")
    cfg = preset("fast").with_proposals(args.proposals)
    result = run_em(scene, priors=[mug, sphere], cfg=cfg, seed=args.seed)
    inst, trace = result.instances, result.trace
    print(f"joint solve: {trace.num_proposals} proposals of priors {list(trace.prior_names)}, "
          f"{result.timings['total']:.1f} s")
    print("settings each prior ran with: " + "; ".join(
        f"{c.name} tau_out {c.out_tau:g}" for c in result.categories))
    print("instances by category: " + ", ".join(
        f"{c} {n}" for c, n in sorted(collections.Counter(inst.category.tolist()).items())))
    for k in np.argsort(-inst.confidence):
        print(f"  #{int(inst.ids[k])} {inst.category[k]} confidence {float(inst.confidence[k]):.2f} "
              f"mask {len(inst.masks[k])} points")
    ev = evaluate_instances(inst, scene, class_names=("mug", "sphere"))
    col50 = int(np.flatnonzero(np.isclose(ev.thresholds, 0.5))[0])
    print("AP50 per category against the ground truth: " + ", ".join(
        f"{c} {float(ev.ap_table[i, col50]):.2f} ({int(ev.n_pred[i])} predicted, {int(ev.n_gt[i])} true)"
        for i, c in enumerate(ev.class_names)))
    cross = [e for e in trace.events() if e.partner >= 0
             and trace.category_of(e.proposal_id) != trace.category_of(e.partner)]
    print(f"deaths across categories (a {trace.category_of(cross[0].proposal_id) if cross else '-'} proposal "
          f"losing to the other prior's fit of the same object): {len(cross)}")
    saved = result.save(out)
    back = EMResult.load(saved, scene=scene, prior=[mug, sphere])  # priors in the run's order
    print(f"saved {saved.name}; reloaded categories {[c.name for c in back.categories]}, "
          f"instance categories {sorted(set(back.instances.category.tolist()))}")

    # ---- 4. a new trained prior carries its category in its metadata
    bowl_settings = CategorySettings(name="bowl", scale_horizontal=(0.05, 0.15), scale_height=(0.02, 0.08),
                                     up_range=(0.0, 30.0),
                                     domain_sizes={"real": ((0.06, 0.12), (0.02, 0.06))})
    tiny = PriorConfig(widths=(8, 8), down_blocks=(), down_factors=(), latent_dim=8, center_hidden=8,
                       decoder_hidden=16, decoder_blocks=1, n_pcl=64)
    bowl = ShapePrior(tiny, name="bowl-v1")  # untrained here: `efem-viz train-prior` would fit its weights
    bowl.metadata[CATEGORY_KEY] = bowl_settings.to_dict()
    path = save_prior(bowl, out / "bowl-v1.pt")
    loaded = load_priors(["sphere", path])
    print(f"saved {path.name}; load_priors(['sphere', '{path.name}']) categories: "
          f"{[p.category.name for p in loaded]}; bowl sizes {loaded[1].category.sizes('real')}")
    assert loaded[1].category == bowl_settings
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
