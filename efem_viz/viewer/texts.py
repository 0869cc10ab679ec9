"""The viewer's panel texts: pure functions from scenes, traces and views to markdown (no viser, no state).

`ViewerApp` (app.py) puts these strings into the panels' markdown handles; keeping them here leaves app.py with
the wiring and makes each text testable on its own. Names read from files (categories) pass `md_escape`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from efem_viz.data.io import holds_predictions
from efem_viz.eval.comparison import GTMetrics
from efem_viz.serve.table import row_option
from efem_viz.viewer.scene_list import SceneEntry
from efem_viz.viewer.state import NO_PROPOSAL
from efem_viz.viewer.trace_queries import Death, top_n
from efem_viz.terminal import count

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.em.results import Instances
    from efem_viz.em.trace import ProposalView

MAX_DEAD_LISTED = 40
"""The "terminated" list shows at most this many proposals (latest first)."""


def md_escape(text: str) -> str:
    """A name from a file, safe inside markdown (no emphasis, links or HTML)."""
    return "".join("\\" + ch if ch in "\\`*_[]<>#|" else ch for ch in str(text))


def step_markdown(t: int, num_steps: int, *, phase: int, alive: int, initial: int, schedule: np.ndarray) -> str:
    """The Timeline tab's text for step `t`: phase, proposals alive, schedule values.

    Args:
        t: the step.
        num_steps: steps of the trace.
        phase: EM phase at `t`.
        alive: proposals alive at `t`.
        initial: proposals in the initial pool.
        schedule: (4,) α_D, τ_D, α_N, τ_N at `t`.
    """
    if num_steps <= 0:  # a running solve before its first step
        return f"**{alive} proposals drawn** · their first step is under way (each dot: a proposal's anchor)"
    sched = np.asarray(schedule).reshape(-1)
    return (
        f"**Step {t}** / {num_steps - 1} · phase {phase} · **{alive} alive** (of {initial} initial)\n\n"
        f"α_D={sched[0]:.3g} · τ_D={sched[1]:.3g} · α_N={sched[2]:.3g} · τ_N={sched[3]:.3g}"
    )


def deaths_markdown(deaths: Sequence[Death], t: int) -> str:
    """The proposals terminated by step `t` (latest first, at most `MAX_DEAD_LISTED`), with reason and partner."""
    dead = [d for d in deaths if d.step <= t]
    lines = [f"**Terminated by step {t}: {len(dead)}**", ""]
    for d in sorted(dead, key=lambda d: (-d.step, d.pid))[:MAX_DEAD_LISTED]:
        extra = f" (partner #{d.partner}, ratio {d.ratio:.2f})" if d.partner is not None and d.partner >= 0 else ""
        lines.append(f"- #{d.pid}: {d.reason} at step {d.step}{extra}")
    if len(dead) > MAX_DEAD_LISTED:
        lines.append(f"- … {len(dead) - MAX_DEAD_LISTED} more")
    return "\n".join(lines)


def gt_markdown(n_objects: int, threshold: float, metrics: GTMetrics) -> str:
    """The ground-truth comparison: TP/FP/FN at the threshold, AP/AP50/AP25 of the whole result and, for a scene
    of several classes, AP50 per class (with its number of objects).

    Args:
        n_objects: ground-truth objects in the scene.
        threshold: the confidence threshold of the shown instances.
        metrics: `efem_viz.eval.comparison.gt_metrics` of the result at that threshold.
    """
    text = (
        f"**Ground truth** ({count(n_objects, 'object')}) at confidence ≥ {threshold:.2f}: "
        f"TP {len(metrics.tp)} · FP {len(metrics.fp)} · FN {len(metrics.fn)}\n\n"
        f"AP {metrics.ap:.3f} · AP50 {metrics.ap50:.3f} · AP25 {metrics.ap25:.3f}"
    )
    if metrics.per_class:  # several classes: AP is their mean, each shown (a named member must be the right one)
        text += "\n\nAP50 per class: " + " · ".join(
            f"{name} {ap50:.3f} ({n_gt})" for name, ap50, n_gt in metrics.per_class)
    return text


def proposal_options(ids: np.ndarray, scores: np.ndarray, *, selected: int | None) -> tuple[str, ...]:
    """Options of the "Inspect" dropdown: `NO_PROPOSAL`, then the live proposals by score, then the selected one
    when it is dead.

    Args:
        ids: (A,) int ids of the live proposals.
        scores: (A,) float their stationary scores.
        selected: the inspected proposal id, or None.
    """
    order = top_n(ids, scores, len(ids))
    score_of = dict(zip(np.asarray(ids).tolist(), np.asarray(scores).tolist()))
    options = [NO_PROPOSAL] + [f"#{int(i)}  (score {score_of[int(i)]:.3f})" for i in order]
    if selected is not None and int(selected) not in score_of:
        options.append(f"#{int(selected)}  (dead)")
    return tuple(options)


def instance_options(instances: Instances) -> tuple[str, ...]:
    """The instance table's dropdown: one option "<id>: <category> · <confidence>" per instance, most confident
    first (the table's order); `efem_viz.serve.table.option_id` reads the proposal id back."""
    conf = np.asarray(instances.confidence, float).reshape(-1)
    order = np.argsort(-conf, kind="stable")
    return tuple(row_option(int(instances.ids[k]), f"{instances.category[k]} · {conf[k]:.2f}") for k in order)


def parse_pid(option: str) -> int | None:
    """The proposal id of an "Inspect" option ("#12  (score 0.871)" → 12); None for `NO_PROPOSAL` or junk."""
    if not option or option == NO_PROPOSAL or not option.startswith("#"):
        return None
    try:
        return int(option[1:].split()[0])
    except ValueError:
        return None


def safe_name(name: str) -> str:
    """A scene name as a folder name (letters, digits, `-_.`; anything else becomes `_`)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "scene"


def scene_info_markdown(scene: Scene, entry: SceneEntry) -> str:
    """Info panel text: counts, bounds, ground truth, provenance."""
    summ = scene.summary()
    lo, hi = summ["bounds_min"], summ["bounds_max"]
    lines = [
        f"**{scene.name}** — {summ['kind']}",
        f"- points: {summ['points']:,}" + (f" · faces: {summ['faces']:,}" if summ["faces"] else ""),
        f"- bounds: [{lo[0]:.3f}, {lo[1]:.3f}, {lo[2]:.3f}] → [{hi[0]:.3f}, {hi[1]:.3f}, {hi[2]:.3f}] m",
        f"- extent: {summ['extent'][0]:.3f} × {summ['extent'][1]:.3f} × {summ['extent'][2]:.3f} m",
    ]
    if scene.has_gt:
        cats = ", ".join(f"{k}: {v}" for k, v in summ.get("categories", {}).items())
        lines.append(f"- ground truth: {count(len(scene.instance_ids()), 'instance')} ({cats}), "
                     f"{summ.get('labelled_points', 0):,} labelled points")
    else:
        lines.append("- ground truth: none")
    if holds_predictions(entry.path):
        lines.append("- the file's labels are predictions (`efem-viz segment` output), not ground truth")
    lines.append(f"- file: `{entry.path.name}`")
    prov = summ.get("provenance") or {}
    if prov:
        items = list(prov.items())[:8]
        lines.append("- provenance: " + "; ".join(f"{k}={_short(v)}" for k, v in items))
    trace = entry.trace_path
    lines.append(f"- saved trace: {'`' + trace.name + '`' if trace.is_file() else 'none'}")
    return "\n".join(lines)


def _short(v: object, n: int = 60) -> str:
    s = str(v)
    return s if len(s) <= n else s[: n - 1] + "…"


def inspect_markdown(pid: int, t: int, view: ProposalView, *, instances: Instances | None = None) -> str:
    """Inspector text: state, scores and schedule values of a proposal at a step, and the final instance it became.

    Args:
        pid: proposal id.
        t: EM step.
        view: `EMTrace.view(pid, t, ...)`.
        instances: the result's `Instances`; when the proposal is one of them, its category and confidence are
            listed.
    """
    lines = [f"**Proposal #{pid} at step {t}** — {'alive' if view.alive else 'terminated'}"]
    if instances is not None:
        hit = np.flatnonzero(np.asarray(instances.ids).reshape(-1) == int(pid))
        if hit.size:
            k = int(hit[0])
            lines.append(f"- final instance: **{md_escape(str(instances.category[k]))}**, confidence "
                         f"{float(instances.confidence[k]):.3f}")
    death = getattr(view, "death", None)
    if death is not None:
        d_step, reason, partner, ratio = (list(death) + [None] * 4)[:4]
        extra = ""
        if partner is not None and int(partner) >= 0:
            extra = f", partner #{int(partner)}" + (f", ratio {float(ratio):.2f}" if ratio is not None else "")
        lines.append(f"- death: **{reason}** at step {d_step}{extra}")
    for name, val in dict(getattr(view, "scores", {}) or {}).items():
        lines.append(f"- {name}: {_fmt(val)}")
    sched = dict(getattr(view, "schedule", {}) or {})
    if sched:
        lines.append("- schedule: " + " · ".join(f"{k}={_fmt(v)}" for k, v in sched.items()))
    lines.append(f"- sampled points: {len(np.asarray(view.sample_idx))}")
    mesh = getattr(view, "mesh", None)
    if mesh is None:
        lines.append("- decoded shape: not available (no matching prior)")
    elif not len(mesh.faces):
        lines.append("- decoded shape: **empty** (the SDF has no zero crossing on the meshing grid)")
    else:
        lines.append(f"- decoded shape: {len(mesh.vertices):,} vertices")
    return "\n".join(lines)


def _fmt(v: Any) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return f"{int(f)}" if f.is_integer() and abs(f) < 1e9 else f"{f:.4g}"
