"""Real-scan results that a person can read (item 15), without a browser: the default confidence cut, labels
that do not overlap, and the instance table (visibility, fly-to, next / previous).

The layout is checked in the image of the viewer's fitted view with the same projection viser's screen-size labels
use (`efem_viz.viewer.label_layout.label_rects`); the app tests drive the real solver's result on the analytic
sphere scene, as tests/test_viewer.py does.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest

from efem_viz import em
from efem_viz.prior import analytic
from efem_viz.serve.camera import View, fitted_view, fly_to_view
from efem_viz.serve.table import option_id, step_row
from efem_viz.viewer import state as st
from efem_viz.viewer.label_layout import label_rects, leader_segments, overlapping_pairs, place_labels
from efem_viz.viewer.nodes import VIEW_DIRECTION

VIEW = fitted_view(np.array([-0.6, -0.4, 0.0]), np.array([0.6, 0.4, 0.3]), direction=VIEW_DIRECTION)


def _texts(rng: np.random.Generator, k: int) -> list[str]:
    return [f"mug #{int(rng.integers(0, 300))} · {rng.random():.2f}" for _ in range(k)]


# ---------------------------------------------------------------------------------------------- label layout
@pytest.mark.parametrize("seed", range(6))
def test_placed_labels_never_overlap(seed: int) -> None:
    """Clusters of objects (labels wanting the same spot) and scattered ones: after `place_labels` no two label
    rectangles overlap in the fitted view; only +Z changed, and never downwards; the most confident label of all
    keeps its anchor."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(2, 40))
    anchors = rng.uniform([-0.5, -0.3, 0.0], [0.5, 0.3, 0.2], (k, 3))
    anchors[: k // 2] = anchors[0] + rng.normal(0.0, 0.01, (k // 2, 3))  # half of them in one heap
    texts = _texts(rng, k)
    conf = rng.random(k)
    before = overlapping_pairs(label_rects(anchors, texts, view=VIEW))
    assert before, "the test layout should start with overlapping labels"
    pos = place_labels(anchors, texts, view=VIEW, priority=conf)
    assert overlapping_pairs(label_rects(pos, texts, view=VIEW)) == []
    assert np.array_equal(pos[:, :2], anchors[:, :2])
    assert (pos[:, 2] >= anchors[:, 2] - 1e-12).all()
    top = int(np.argmax(conf))
    assert np.array_equal(pos[top], anchors[top])
    assert np.array_equal(pos, place_labels(anchors, texts, view=VIEW, priority=conf)), "not deterministic"


def test_labels_apart_stay_and_a_heap_stacks_by_confidence() -> None:
    """Labels that do not touch are not moved (no leader lines); labels wanting one spot stack upwards, the most
    confident lowest (at its box), each hanging on a leader line to its anchor."""
    apart = np.array([[-0.5, 0.0, 0.1], [0.0, 0.0, 0.1], [0.5, 0.0, 0.1]])
    texts = ["a #1 · 0.50", "b #2 · 0.40", "c #3 · 0.30"]
    assert overlapping_pairs(label_rects(apart, texts, view=VIEW)) == []
    assert np.array_equal(place_labels(apart, texts, view=VIEW), apart)
    assert leader_segments(apart, apart).shape == (0, 2, 3)

    heap = np.tile([[0.1, 0.05, 0.12]], (4, 1))
    conf = np.array([0.2, 0.9, 0.5, 0.7])
    pos = place_labels(heap, ["mug #1 · 0.20"] * 4, view=VIEW, priority=conf)
    order = np.argsort(-conf)
    assert np.array_equal(pos[order[0]], heap[order[0]])
    assert (np.diff(pos[order, 2]) > 0).all(), "less confident labels should sit higher"
    seg = leader_segments(heap, pos)
    assert seg.shape == (3, 2, 3) and np.allclose(seg[:, 0], heap[0])


def test_place_labels_checks_its_input() -> None:
    with pytest.raises(ValueError, match="anchors"):
        place_labels(np.zeros((2, 2)), ["a", "b"], view=VIEW)
    with pytest.raises(ValueError, match="texts"):
        place_labels(np.zeros((2, 3)), ["a"], view=VIEW)
    with pytest.raises(ValueError, match="priorities"):
        place_labels(np.zeros((2, 3)), ["a", "b"], view=VIEW, priority=[1.0])
    assert place_labels(np.zeros((0, 3)), [], view=VIEW).shape == (0, 3)


# ---------------------------------------------------------------------------------------------- table pieces
def test_step_row_and_fly_to_view() -> None:
    """Next / previous wrap around and start at the first / last row; fly-to looks at the object's centre from
    the fitted view's direction, closer for a smaller object but never closer than the minimum size allows."""
    assert step_row([5, 3, 9], None, +1) == 5 and step_row([5, 3, 9], None, -1) == 9
    assert step_row([5, 3, 9], 9, +1) == 5 and step_row([5, 3, 9], 5, -1) == 9 and step_row([5, 3, 9], 3, 1) == 9
    assert step_row([5, 3, 9], 42, +1) == 5
    with pytest.raises(ValueError):
        step_row([], None, 1)
    home = View((0.0, 0.0, 0.0), (1.0, -2.0, 2.0))
    near = fly_to_view([0.0, 0.0, 0.0], [0.1, 0.1, 0.1], home=home, scene_diagonal=2.0)
    far = fly_to_view([0.0, 0.0, 0.0], [0.4, 0.4, 0.4], home=home, scene_diagonal=2.0)
    tiny = fly_to_view([0.0, 0.0, 0.0], [1e-4, 1e-4, 1e-4], home=home, scene_diagonal=2.0)
    assert np.allclose(near.look_at, 0.05) and np.allclose(far.look_at, 0.2)
    d_near = np.subtract(near.position, near.look_at)
    assert np.allclose(d_near / np.linalg.norm(d_near), np.array([1.0, -2.0, 2.0]) / 3.0)
    assert np.linalg.norm(d_near) < np.linalg.norm(np.subtract(far.position, far.look_at))
    assert np.linalg.norm(np.subtract(tiny.position, tiny.look_at)) > 0.1
    with pytest.raises(ValueError):
        fly_to_view([0.0, np.nan, 0.0], [1.0, 1.0, 1.0], home=home, scene_diagonal=1.0)


# ---------------------------------------------------------------------------------------------- the app
@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """The viewer on the analytic sphere scene (with ground truth) and a saved result of the real solver."""
    import torch

    from efem_viz.data.io import save_scene
    from efem_viz.viewer.app import ViewerApp

    torch.set_num_threads(1)
    d: Path = tmp_path_factory.mktemp("instances")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    save_scene(scene, d / "spheres.ply")
    prior = analytic.make_sphere_prior()
    result = em.run_em(scene, prior, em.preset("fast").with_proposals(16).replace(elimination={"min_size": 30}), seed=0)
    assert len(result.instances) >= 2, "the sphere scene should give several instances"
    result.save(d / "spheres.efem.npz")
    a = ViewerApp([d], port=0, prior=prior)
    assert a.wait_idle(60)
    yield a
    a.stop()


def _with_confidences(app: Any, conf: np.ndarray) -> Any:
    """Show the app's result with other confidences (what a real scan gives: many near zero)."""
    res = app.state.result
    inst = dataclasses.replace(res.instances, confidence=np.asarray(conf, np.float32))
    app.set_result(dataclasses.replace(res, instances=inst), source="near-zero confidences")
    return inst


def test_default_cut_hides_near_zero_instances_and_says_how_many(app: Any) -> None:
    """A new viewer starts at `DEFAULT_CONFIDENCE_CUT`: instances below it are hidden (meshes, boxes, labels,
    point colours), the Results tab says how many, and the table marks them "below cut"; the slider at 0 shows
    them. (On a scan without ground truth: with it, instances that match an object stay shown, tested in
    test_viewer_session.py.)"""
    assert st.ViewerState().threshold == st.DEFAULT_CONFIDENCE_CUT > 0.0
    assert app.state.threshold == st.DEFAULT_CONFIDENCE_CUT
    assert app.panels.gui_threshold.value == pytest.approx(st.DEFAULT_CONFIDENCE_CUT)
    k = len(app.state.result.instances)
    conf = np.linspace(0.9, 0.5, k)
    conf[-2:] = [0.01, 0.0]  # two near-zero instances, as EM leaves on real scans
    labelled = app.state.scene
    try:
        app.state.scene = labelled.replace(instance=None)  # a user's scan: no ground truth
        _with_confidences(app, conf)
        shown = app.session.results.shown_mask()
        assert shown.tolist() == (conf >= st.DEFAULT_CONFIDENCE_CUT).tolist() and int((~shown).sum()) == 2
        assert "**2 hidden** below the cut" in app.panels.gui_result_info.content
        r = app.nodes.results
        assert [h.visible for h in r.labels] == shown.tolist()
        assert [h.visible for h in r.obbs] == shown.tolist()
        assert app.panels.gui_instance_table.content.count("| below cut |") == 2
        app.set_threshold(0.0)
        assert all(h.visible for h in r.labels) and "hidden** below" not in app.panels.gui_result_info.content
    finally:
        app.state.scene = labelled
        assert app.load_trace() and app.wait_idle(60)
        app.set_threshold(st.DEFAULT_CONFIDENCE_CUT)


def test_shown_labels_do_not_overlap_in_the_fitted_view(app: Any) -> None:
    """Every instance in one place (a heap of objects): the labels the viewer shows are lifted apart so that none
    overlaps another in the fitted view; hiding some lays the rest out again."""
    res = app.state.result
    inst = res.instances
    k = len(inst)
    heap = dataclasses.replace(inst, obb_center=np.repeat(inst.obb_center[:1], k, axis=0))
    app.set_result(dataclasses.replace(res, instances=heap), source="a heap")
    try:
        app.set_threshold(0.0)
        r = app.nodes.results
        texts = [h.text for h in r.labels]
        positions = np.array([h.position for h in r.labels], np.float64)
        assert overlapping_pairs(label_rects(r.label_anchors, texts, view=r.label_view)), "should start overlapping"
        assert overlapping_pairs(label_rects(positions, texts, view=r.label_view)) == []
        assert r.leaders is not None and r.leaders.visible
        top = int(np.argmax(np.asarray(heap.confidence)))
        # the lowest label goes: the others move down
        app.instance_table.set_instance_visible(int(heap.ids[top]), False)
        positions2 = np.array([h.position for h in r.labels], np.float64)
        on = [i for i, h in enumerate(r.labels) if h.visible]
        assert top not in on and len(on) == k - 1
        assert overlapping_pairs(label_rects(positions2[on], [texts[i] for i in on], view=r.label_view)) == []
        assert positions2[on, 2].min() < positions[on, 2].min()
    finally:
        assert app.load_trace() and app.wait_idle(60)
        app.set_threshold(st.DEFAULT_CONFIDENCE_CUT)


def test_instance_table_rows_visibility_and_next(app: Any) -> None:
    """One table row per instance (id, category, confidence, points, TP/FP with IoU, shown), most confident first;
    the dropdown names the same rows; *Visible* off hides one instance (nodes and point colours) and says so, on
    shows it again; Next / Previous walk the rows."""
    app.set_threshold(0.0)
    inst = app.state.result.instances
    k = len(inst)
    table = app.panels.gui_instance_table.content
    lines = [ln for ln in table.splitlines() if ln.startswith("| ") and ln[2].isdigit()]
    assert len(lines) == k
    order = np.argsort(-np.asarray(inst.confidence, float), kind="stable")
    for line, i in zip(lines, order):
        assert line.startswith(f"| {int(inst.ids[i])} ")
        assert f"| {float(inst.confidence[i]):.2f} | {len(inst.masks[i]):,} |" in line
        assert " (0." in line or " (1.00)" in line  # TP/FP with its IoU: the scene has ground truth
        assert ("| TP (" in line) or ("| FP (" in line)
    assert "GT (IoU)" in table
    metrics = app._gt_metrics()
    assert len(metrics.ious) == len(metrics.masks) and all(0.0 <= v <= 1.0 for v in metrics.ious)
    for j in metrics.tp:
        assert metrics.ious[j] > 0.5
    opts = tuple(app.panels.gui_instance.options)
    assert [option_id(o) for o in opts] == [int(inst.ids[i]) for i in order]

    pid = int(inst.ids[order[1]])
    app.panels.gui_instance.value = opts[1]  # as a browser picks it
    assert app.state.table_row == pid and app.panels.gui_instance_visible.value is True
    k_idx = int(order[1])
    colors_before = np.array(app.nodes.points.colors)
    app.panels.gui_instance_visible.value = False  # as a browser unticks it
    assert pid in app.state.hidden and not app.session.results.shown_mask()[k_idx]
    r = app.nodes.results
    assert not r.labels[k_idx].visible and not r.obbs[k_idx].visible
    assert r.meshes[k_idx] is None or not r.meshes[k_idx].visible
    mask = np.asarray(inst.masks[k_idx])
    assert not np.array_equal(np.array(app.nodes.points.colors)[mask], colors_before[mask])
    assert "1 hidden in the table" in app.panels.gui_result_info.content
    assert (f"| {pid} " in app.panels.gui_instance_table.content
            and "| hidden |" in app.panels.gui_instance_table.content)
    assert app.session.results.kept_mask()[k_idx], "hiding is a view: the threshold (metrics, exports) still keeps it"
    app.instance_table.set_instance_visible(pid, True)
    assert app.session.results.shown_mask()[k_idx] and r.labels[k_idx].visible
    assert np.array_equal(np.array(app.nodes.points.colors), colors_before)

    assert app.instance_table.step_instance(+1) == int(inst.ids[order[2 % k]])
    assert app.instance_table.step_instance(-1) == pid
    with pytest.raises(ValueError, match="no instance #"):
        app.instance_table.fly_to_instance(10_000)
    app.set_threshold(st.DEFAULT_CONFIDENCE_CUT)


def test_table_without_ground_truth_and_without_result(app: Any, tmp_path: Path) -> None:
    """Without ground truth the table has no TP/FP column; without a result it is empty and its buttons are off."""
    from efem_viz.viewer.legend import instance_table_markdown

    inst = app.state.result.instances
    md = instance_table_markdown(inst, threshold=0.0, metrics=None)
    assert "GT (IoU)" not in md and "TP" not in md
    assert md.count("| yes |") == len(inst)
    app.state.result = None  # as opening a scene without a saved result leaves it
    app._draw_no_result()
    try:
        p = app.panels
        assert p.gui_fly_to.disabled and p.gui_instance_visible.disabled and p.gui_instance_next.disabled
        assert p.gui_instance_table.content == "" and p.gui_instance.options == ("(none)",)
        with pytest.raises(ValueError, match="no result"):
            app.instance_table.fly_to_instance(1)
    finally:
        assert app.load_trace() and app.wait_idle(60)
    assert not app.panels.gui_fly_to.disabled
