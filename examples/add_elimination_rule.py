"""Add elimination rules to the EFEM solver: a per-step rule and a review rule, each with its own reason name.

The solver's rules live in one registry, `efem_viz.em.rules`: `STEP_RULES` run after every EM step on the live
proposals (too small, duplicated, included) and `REVIEW_RULES` on each proposal's `ReviewRecord` at the end of
each phase (scale, pose, seen-through). Each rule decides from the measures the solver records (`StepContext`,
`ReviewRecord`; the size and up verdicts are `rules.size_passes` / `rules.up_passes`), so changing a check means
changing its rule here. `run_em(..., step_rules=..., review_rules=...)` takes other lists. This example adds

- a `StepRule` "stationary near zero": a proposal whose stationary score is below `--min-stationary` explains
  (almost) none of its own samples; it dies now instead of lingering until it is "too small";
- a `ReviewRule` "low coverage": a completed shape that the observed points cover less than `--min-coverage`
  is rejected at review (on `syn_pile_0`, mugs tumbled onto each other, it removes fits that lie on no mug);

checks the step rule alone on a hand-made `StepContext` (how to unit-test a rule), runs EFEM with both,
prints the deaths by reason, and shows that the saved trace carries its table of reason names, so its int8
death codes read back correctly whatever rules a later build registers (traces saved before the table read
with `LEGACY_REASONS`).

Note: `StepContext` carries the phase, the global step and the step within the episode (`local_step`), so a
rule can also say "after step k".

Run (about 15 s on one CPU thread with the defaults)::

    python examples/add_elimination_rule.py
    python examples/add_elimination_rule.py --min-coverage 0.2 --out /tmp/rules
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
    ap.add_argument("--scene", default="syn_pile_0", help="a sample_scenes/<name>.ply name, or a scene path")
    ap.add_argument("--proposals", type=int, default=40, help="proposals of the first episode")
    ap.add_argument("--min-stationary", type=float, default=0.03, help="the step rule's threshold")
    ap.add_argument("--min-coverage", type=float, default=0.1, help="the review rule's threshold")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--out", type=Path, default=None, help="folder for the result (default: a temp dir)")
    args = ap.parse_args(argv)

    import torch

    from efem_viz.data.io import load_scene
    from efem_viz.em import EMResult, preset, run_em
    from efem_viz.em.proposals import Ragged
    from efem_viz.em.rules import (
        REVIEW_RULES,
        STEP_RULES,
        Kill,
        ReviewRecord,
        ReviewRule,
        StepContext,
        StepRule,
        apply_step_rules,
        reason_names,
    )
    from efem_viz.prior import load_prior

    # ---- the rules: a name, and a function of what the solver shows them
    def near_zero(ctx: StepContext) -> list[Kill]:
        rows = np.flatnonzero(ctx.active & (ctx.stationary < args.min_stationary))
        return [Kill(int(r), "stationary near zero", -1, float(ctx.stationary[r])) for r in rows]

    def covered(rec: ReviewRecord, cfg: object) -> tuple[bool, float]:
        return rec.coverage >= args.min_coverage, rec.coverage  # (passed, the ratio recorded with the death)

    step_rule = StepRule("stationary near zero", near_zero, phases=(1, 2))
    review_rule = ReviewRule("low coverage", covered)
    step_rules = (*STEP_RULES, step_rule)
    review_rules = (*REVIEW_RULES, review_rule)
    print(f"reason names of this run: {list(reason_names(step_rules, review_rules))}")

    # ---- a rule is a plain function: check it on a hand-made context before a run
    cfg = preset("fast").with_proposals(args.proposals)
    ctx = StepContext(phase=1, step=0, local_step=0, cfg=cfg, inliers=np.array([900, 900, 900]),
                      stationary=np.array([0.5, 0.01, 0.7]), d=np.zeros(0, np.float32),
                      rag=Ragged(np.zeros(0, np.int64), np.zeros(4, np.int64)), n_points=10, min_size=300,
                      owner=np.zeros(3, np.int64))
    kills = apply_step_rules(ctx, (STEP_RULES[0], step_rule))
    print(f"on a hand-made context: kills {[(k.row, k.reason) for k in kills]}, "
          f"still active {ctx.active.tolist()}")

    # ---- run with the extended registries
    torch.set_num_threads(args.threads)
    path = Path(args.scene) if Path(args.scene).suffix else REPO / "sample_scenes" / f"{args.scene}.ply"
    scene = load_scene(path)
    prior = load_prior("mug")
    result = run_em(scene, prior, cfg, seed=args.seed, step_rules=step_rules, review_rules=review_rules)
    trace = result.trace
    print(f"run on {scene.name}: {trace.num_proposals} proposals, {len(result.instances)} instances, "
          f"{result.timings['total']:.1f} s")
    counts = collections.Counter(e.reason for e in trace.events())
    print("deaths by reason: " + ", ".join(f"{r} {counts.get(r, 0)}" for r in trace.reason_names))
    for e in trace.events():
        if e.reason == review_rule.reason:
            rec = trace.reviews(e.proposal_id)[-1]
            gt = scene.instance if scene.instance is not None else np.zeros(scene.num_points, np.int32)
            on_objects = float((gt[rec.mask] > 0).mean())
            print(f"  proposal #{e.proposal_id} died at step {e.step} ({e.reason}, coverage {e.ratio:.2f}); "
                  f"{100 * on_objects:.0f}% of its mask lies on labelled mugs")

    # ---- the saved trace carries its name table
    out = args.out or Path(tempfile.mkdtemp(prefix="efem_example_"))
    out.mkdir(parents=True, exist_ok=True)
    back = EMResult.load(result.save(out))
    assert back.trace.reason_names == trace.reason_names
    assert [e.reason for e in back.trace.events()] == [e.reason for e in trace.events()]
    print(f"reloaded trace: reason names {list(back.trace.reason_names)}; "
          f"{sum(e.reason == step_rule.reason for e in back.trace.events())} deaths read back as "
          f"{step_rule.reason!r}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
