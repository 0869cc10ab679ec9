"""Viewer tests without a browser: build the app on port 0, drive its callbacks, assert scene nodes and state.

The EM result comes from the real solver (`efem_viz.em.run_em`) on the analytic sphere scene with the analytic
sphere prior (exact, fast, no trained weights), saved next to the scene file like a precomputed result.
"""

from __future__ import annotations

import json

import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest

from efem_viz import em
from efem_viz.colors import instance_colors
from efem_viz.prior import analytic
from efem_viz import colors as pal
from efem_viz.viewer import scene_list as sc
from efem_viz.viewer import trace_queries as tq
from efem_viz.viewer.panels import slider_marks
from helpers import sample_scene


# ---------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with a sphere scene, its saved EM result, a broken scene file, and a result-less scene."""
    import torch

    from efem_viz.data.io import save_scene

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("scenes")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    save_scene(scene, d / "spheres.ply")
    prior = analytic.make_sphere_prior()
    cfg = em.preset("fast").with_proposals(16).replace(elimination={"min_size": 30})
    result = em.run_em(scene, prior, cfg, seed=0)
    assert len(result.instances) >= 1, "the sphere scene should give at least one instance"
    result.save(d / "spheres.efem.npz")
    other = analytic.make_sphere_scene(seed=1, spacing=0.012, radii=(0.05,), name="one_sphere")
    save_scene(other, d / "one_sphere.ply")
    (d / "broken.ply").write_text("ply\nthis is not a ply header\n")
    return d


@pytest.fixture(scope="module")
def prior() -> Any:
    return analytic.make_sphere_prior()


@pytest.fixture(scope="module")
def app(scene_dir: Path, prior: Any) -> Iterator[Any]:
    from efem_viz.viewer.app import ViewerApp

    a = ViewerApp([scene_dir], port=0, prior=prior, open_first=False)
    assert a.open_scene("spheres")
    assert a.wait_idle(60)
    yield a
    a.stop()


def _visible_shapes(app: Any) -> set[tuple[int, int]]:
    return {k for k, h in app.nodes.shapes.items() if h.visible}


# ---------------------------------------------------------------------------------------------- pure state
def test_discover_scenes_only_inside_given_paths(tmp_path: Path) -> None:
    inside = tmp_path / "in"
    outside = tmp_path / "out"
    inside.mkdir()
    outside.mkdir()
    (inside / "a.ply").write_text("x")
    (inside / "b.npz").write_text("x")
    (inside / "a.efem.npz").write_text("x")  # a result, not a scene
    (inside / "notes.txt").write_text("x")
    (outside / "secret.ply").write_text("x")
    os.symlink(outside / "secret.ply", inside / "link.ply")  # points outside: must be dropped
    entries = sc.discover_scenes([inside])
    assert [e.name for e in entries] == ["a", "b"]
    assert all(sc.is_inside(e.path, [inside.resolve()]) for e in entries)
    assert not sc.is_inside(outside / "secret.ply", [inside.resolve()])
    assert entries[0].trace_path.name == "a.efem.npz"
    with pytest.raises(FileNotFoundError):
        sc.discover_scenes([tmp_path / "missing"])


def test_palette_heatmap_and_marks() -> None:
    cols = instance_colors([3, 4, 5, 3])
    assert cols.dtype == np.uint8 and cols.shape == (4, 3)
    assert (cols[0] == cols[3]).all() and len({tuple(c) for c in cols[:3]}) == 3
    h = pal.heatmap(np.array([0.0, 1.0, np.nan]), vmin=0.0, vmax=1.0)
    assert h[0, 2] > h[0, 0] and h[1, 0] > h[1, 2]  # cold is blue, hot is red
    assert (h[2] == pal.BACKGROUND_COLOR).all()
    marks = tq.phase_marks(np.array([1, 1, 1, 2, 2]))
    assert [(m.step, m.label) for m in marks] == [(0, "P1"), (2, "R"), (3, "P2"), (4, "R")]
    ids = tq.top_n(np.array([7, 8, 9, 10]), np.array([0.5, np.nan, 0.9, 0.5]), 3)
    assert ids.tolist() == [9, 7, 10]


def test_weights_and_label_colors() -> None:
    base = np.full((5, 3), 100, np.uint8)
    w = np.array([0.0, 0.0, 0.5, 1.0, 0.0], np.float32)
    c = pal.weights_colors(base, w)
    assert (c[0] == c[1]).all() and not (c[2] == c[0]).all() and not (c[3] == c[2]).all()
    lab = pal.label_colors(base, np.array([0, 2, 2, 5, 0]))
    assert (lab[1] == lab[2]).all() and not (lab[1] == lab[3]).all() and (lab[0] == lab[4]).all()
    with pytest.raises(ValueError):
        pal.weights_colors(base, np.zeros(4))


# ---------------------------------------------------------------------------------------------- app: scenes
def test_app_binds_loopback_and_lists_scenes(app: Any, scene_dir: Path) -> None:
    assert app.url.startswith("http://127.0.0.1:")
    assert app.server.get_host() == "127.0.0.1"
    names = [e.name for e in app.state.entries]
    assert names == ["broken", "one_sphere", "spheres"]
    assert set(app.panels.gui_scene.options) == set(names)
    assert app.nodes.points is not None
    assert app.nodes.points.points.shape[0] == app.state.scene.num_points
    info = app.panels.gui_info.content
    assert "spheres" in info and f"{app.state.scene.num_points:,}" in info and "ground truth: 3 instances" in info


def test_saved_trace_loads_automatically(app: Any) -> None:
    s = app.state
    assert s.result is not None and s.result_source == "spheres.efem.npz"
    T = s.result.trace.num_steps
    assert app.panels.gui_step.max == T - 1 and s.step == T - 1
    marks = dict(slider_marks(app.panels.gui_step))  # the marks the browser shows (the slider's `_marks` prop)
    assert marks[0].startswith("P1") and any("R" in v for v in marks.values())
    assert len(app.nodes.results.meshes) == len(s.result.instances)
    assert app.panels.gui_active_plot.visible


def test_step_change_updates_samples_shapes_and_lists(app: Any) -> None:
    trace = app.state.result.trace
    app.set_step(0)
    assert app.wait_idle(60)
    ids0, _ = trace.alive_scores(0)
    drawn0 = set(tq.top_n(*trace.alive_scores(0), app.state.max_shapes).tolist())
    assert {p for p, t in _visible_shapes(app)} == drawn0 and all(t == 0 for _, t in _visible_shapes(app))
    samples0 = np.array(app.nodes.samples.points)
    assert f"**{len(ids0)} alive**" in app.panels.gui_step_info.content
    last = trace.num_steps - 1
    app.set_step(last)
    assert app.wait_idle(60)
    assert all(t == last for _, t in _visible_shapes(app))
    assert not np.array_equal(samples0, np.array(app.nodes.samples.points))
    n_dead = len([d for d in tq.deaths(trace) if d.step <= last])
    assert f"Terminated by step {last}: {n_dead}" in app.panels.gui_dead_info.content
    app.set_step(10_000)  # clamped
    assert app.state.step == last
    # Going back re-shows cached shapes without re-sending them.
    n_cached = len(app.nodes.shapes)
    app.set_step(0)
    assert app.wait_idle(60)
    assert len(app.nodes.shapes) == n_cached
    app.set_max_shapes(1)
    assert len(_visible_shapes(app)) == 1
    app.set_max_shapes(8)


def test_show_one_em_step_or_the_final_result(app: Any) -> None:
    """The Show switch: "EM step" shows only that step (decoded shapes, samples, scene colours; no final box,
    label or mesh), "Result" only the final instances (no step shape or samples). The timeline shows a step, the
    threshold the result. (At step 3 the final boxes, labels and TP/FP/FN colours sat on the step's shapes.)"""
    s = app.state
    inst_nodes = app.nodes.results
    app.set_color_mode("instances")
    app.set_threshold(0.0)
    assert s.view_mode == "result" and app.panels.gui_view_mode.value.startswith("Result")
    assert all(h.visible for h in inst_nodes.obbs) and all(h.visible for h in inst_nodes.labels)
    assert not _visible_shapes(app) and not (app.nodes.samples is not None and app.nodes.samples.visible)
    result_colours = np.array(app.nodes.points.colors)
    assert not np.array_equal(result_colours, s.scene.colors)

    app.panels.gui_step.value = 2  # moving the timeline, as a browser does: that step only
    assert app.wait_idle(60)
    assert s.view_mode == "step" and s.step == 2 and app.panels.gui_view_mode.value.startswith("EM step")
    assert not any(h.visible for group in (inst_nodes.obbs, inst_nodes.labels, inst_nodes.axes) for h in group)
    assert not any(h.visible for h in inst_nodes.meshes if h is not None)
    assert _visible_shapes(app) and all(t == 2 for _, t in _visible_shapes(app))
    assert app.nodes.samples is not None and app.nodes.samples.visible
    assert np.array_equal(np.array(app.nodes.points.colors), s.scene.colors)

    app.panels.gui_view_mode.value = "Result (final instances)"  # the Show dropdown
    assert s.view_mode == "result" and s.step == 2
    assert not _visible_shapes(app) and not app.nodes.samples.visible
    assert all(h.visible for h in inst_nodes.obbs)
    assert np.array_equal(np.array(app.nodes.points.colors), result_colours)
    app.set_view_mode("step")
    assert app.wait_idle(60)
    assert _visible_shapes(app) and not any(h.visible for h in inst_nodes.obbs)
    with pytest.raises(ValueError, match="view mode"):
        app.set_view_mode("both")
    app.set_threshold(0.0)
    assert s.view_mode == "result"


def test_colour_keys_tp_fp_boxes_and_grey_background(app: Any) -> None:
    """Each colouring has its key under the Colour control: TP / FP / FN swatches (and the boxes turn green / red
    as TP / FP), the weight heat map's colour bar, the instance colours' grey; scene colours have none. Points no
    shown prediction covers are grey, so a scan colour cannot read as a prediction's."""
    from efem_viz.viewer.legend import color_key_html

    s = app.state
    app.set_threshold(0.0)
    app.set_color_mode("gt_match")
    key = app.panels.gui_color_key.content
    assert key == color_key_html("gt_match") and all(w in key for w in ("TP", "FP", "FN", "grey"))
    m = app._gt_metrics()
    kept = np.flatnonzero(app.session.results.kept_mask())
    boxes = app.nodes.results.box_colors
    for k in m.tp:
        assert boxes[kept[k]] == tuple(int(c) for c in pal.TP_COLOR)
    for k in m.fp:
        assert boxes[kept[k]] == tuple(int(c) for c in pal.FP_COLOR)
    assert m.tp or m.fp
    colours = np.array(app.nodes.points.colors)
    covered = np.zeros(s.scene.num_points, bool)
    for mask in m.masks:
        covered[np.asarray(mask)] = True
    covered |= np.isin(s.scene.instance, m.fn)
    rest = colours[~covered]
    assert len(rest) and (rest[:, 0] == rest[:, 1]).all() and (rest[:, 1] == rest[:, 2]).all()
    app.set_color_mode("instances")
    assert "grey" in app.panels.gui_color_key.content and "TP" not in app.panels.gui_color_key.content
    own = [tuple(int(v) for v in c) for c in app.nodes.results.colors]
    assert app.nodes.results.box_colors == own  # the boxes' own colours again
    app.set_color_mode("rgb")
    assert app.panels.gui_color_key.content == ""
    assert "linear-gradient" in color_key_html("weights")
    app.set_color_mode("instances")


def test_inspect_proposal_shows_fig_s9_views(app: Any) -> None:
    trace = app.state.result.trace
    app.set_step(2)
    ids, _ = trace.alive_scores(2)
    pid = int(ids[0])
    fut = app.select_proposal(pid)
    fut.result(timeout=60)
    assert app.wait_idle(60)
    assert app.state.color_mode == "weights"
    assert "linear-gradient" in app.panels.gui_color_key.content  # the heat map's colour bar
    assert {"crop", "samples", "shape"} <= set(app.nodes.inspect)
    view = app.state.result.replay.view(pid, 2, app.prior())
    assert np.asarray(app.nodes.inspect["samples"].points).shape[0] == len(view.sampled_points)
    colors = np.asarray(app.nodes.points.colors)
    assert not np.array_equal(colors, app.state.scene.colors)
    assert f"Proposal #{pid} at step 2" in app.panels.gui_inspect_info.content
    assert "stationary" in app.panels.gui_inspect_info.content and "alpha_d" in app.panels.gui_inspect_info.content
    # A dead proposal lists its reason.
    dead = tq.deaths(trace)
    if dead:
        d = dead[0]
        app.set_step(d.step)
        app.select_proposal(d.pid).result(timeout=60)
        assert app.wait_idle(60)
        assert d.reason in app.panels.gui_inspect_info.content
    app.select_proposal(None)
    assert not app.nodes.inspect and app.state.color_mode == "instances"


def test_threshold_filters_instances_without_rerun(app: Any) -> None:
    inst = app.state.result.instances
    app.set_result_layers(meshes=True, obbs=True, axes=True)
    app.set_threshold(0.0)
    vis_all = [h.visible for h in app.nodes.results.obbs]
    assert all(vis_all) and len(vis_all) == len(inst)
    colors_all = np.array(app.nodes.points.colors)
    app.set_threshold(float(np.max(inst.confidence)) + 0.001)
    assert not any(h.visible for h in app.nodes.results.obbs)
    assert not any(h.visible for h in app.nodes.results.axes)
    assert not any(h.visible for h in app.nodes.results.labels)
    assert "**0 of" in app.panels.gui_result_info.content
    assert f"SDF\\| < {app.state.result.config.output.out_tau:g} (τ_out" in app.panels.gui_result_info.content
    assert not np.array_equal(colors_all, np.array(app.nodes.points.colors))
    assert app.state.result.instances is inst  # a view, not a re-run
    app.set_threshold(0.0)
    app.set_result_layers(meshes=False, obbs=True, axes=False)
    assert not any(h.visible for h in app.nodes.results.meshes if h is not None)


def test_several_categories_in_labels_legend_counts_and_inspector(app: Any) -> None:
    """A result with two categories (as a joint solve over two priors gives): the scene labels, the legend, the
    per-category counts and the inspector name each instance's category; the threshold updates the counts."""
    import dataclasses

    from efem_viz.viewer.legend import category_color

    res = app.state.result
    inst = res.instances
    k_all = len(inst)
    assert k_all >= 2, "the sphere scene gives several instances"
    cats = np.array(["mug"] + ["sphere"] * (k_all - 1))
    app.set_result(dataclasses.replace(res, instances=dataclasses.replace(inst, category=cats)), source="two priors")
    try:
        app.set_result_layers(meshes=True, obbs=True, axes=False)
        app.set_threshold(0.0)
        assert f"mug: 1 of 1 · sphere: {k_all - 1} of {k_all - 1}" in app.panels.gui_result_info.content
        assert f"{k_all} instances (mug 1 · sphere {k_all - 1})" in app.panels.gui_run_info.content
        texts = [h.text for h in app.nodes.results.labels]
        assert texts[0] == f"mug #{int(inst.ids[0])} · {float(inst.confidence[0]):.2f}"
        assert all(t.startswith("sphere #") for t in texts[1:])
        assert all(h.visible for h in app.nodes.results.labels)
        legend = app.panels.gui_legend.content
        mug, sphere = pal.hex_color(category_color("mug")), pal.hex_color(category_color("sphere"))
        assert mug != sphere
        assert legend.count(f'color:{mug}">mug</b>') == 1 and legend.count(f'color:{sphere}">sphere</b>') == k_all - 1
        for pid, col in zip(inst.ids, instance_colors(inst.ids)):  # each row's swatch has its instance's colour
            assert f'<span style="color:{pal.hex_color(col)}">&#9632;</span> #{int(pid)} ' in legend
        # A threshold just above the mug's confidence: the counts, legend rows and labels follow.
        conf = np.asarray(inst.confidence, float)
        app.set_threshold(float(conf[0]) + 1e-4)
        kept = conf >= app.state.threshold
        n_sphere = int(kept[1:].sum())
        assert f"mug: 0 of 1 · sphere: {n_sphere} of {k_all - 1}" in app.panels.gui_result_info.content
        assert app.panels.gui_legend.content.count("&#9632;") == int(kept.sum())
        assert [h.visible for h in app.nodes.results.labels] == kept.tolist()
        app.set_threshold(0.0)
        app.set_step(app.state.num_steps - 1)
        app.select_proposal(int(inst.ids[0])).result(timeout=60)
        assert app.wait_idle(60)
        assert "final instance: **mug**" in app.panels.gui_inspect_info.content
        app.select_proposal(None)
    finally:
        assert app.load_trace() and app.wait_idle(60)
    assert app.state.result_source == "spheres.efem.npz"


def test_static_demo_draws_results_with_the_viewers_functions(
    app: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The static demo draws the final instances through `nodes.add_result_nodes`, as the live viewer does."""
    from efem_viz.viewer import export, nodes
    from efem_viz.viewer.legend import instance_label

    calls: list[tuple[Any, bool, nodes.ResultNodes]] = []
    real = nodes.add_result_nodes

    def spy(api: Any, instances: Any, *, visible: bool) -> nodes.ResultNodes:
        out = real(api, instances, visible=visible)
        calls.append((instances, visible, out))
        return out

    monkeypatch.setattr(export, "add_result_nodes", spy)
    inst = app.state.result.instances
    conf = np.asarray(inst.confidence, float)
    thr = float(np.sort(conf)[len(conf) // 2])
    export.export_static_demo(app.state.scene, app.state.result, tmp_path / "demo", threshold=thr)
    (shown, visible, out), = calls
    assert visible and np.array_equal(shown.ids, inst.ids[conf >= thr]) and len(shown) >= 1
    assert [h.text for h in out.labels] == [instance_label(shown, k) for k in range(len(shown))]
    live = [h for h in app.nodes.results.meshes if h is not None]
    demo = [h for h in out.meshes if h is not None]
    assert live and demo and {h.opacity for h in live} == {h.opacity for h in demo} == {nodes.RESULT_MESH_OPACITY}
    k = int(np.flatnonzero(conf >= thr)[0])  # the same instance: same box colour and pose axes in both
    assert np.array_equal(np.asarray(out.obbs[0].colors), np.asarray(app.nodes.results.obbs[k].colors))
    assert out.axes[0].axes_length == pytest.approx(app.nodes.results.axes[k].axes_length)
    assert np.allclose(out.axes[0].wxyz, app.nodes.results.axes[k].wxyz)
    # the caption never covers an instance label in the page's framing
    from efem_viz.serve.camera import fitted_view, framing
    from efem_viz.viewer.label_layout import label_rects, overlapping_pairs

    pts = np.asarray(app.state.scene.points, np.float32)
    flo, fhi, sample = framing(pts)
    view = fitted_view(flo, fhi, direction=nodes.VIEW_DIRECTION, points=sample)
    cap = np.asarray([export.caption_position(pts.min(axis=0), pts.max(axis=0))])
    rects = label_rects(np.concatenate([cap, out.label_positions]), ["result: 10 objects, confidence ≥ 0.50",
                                                                    *[h.text for h in out.labels]], view=view)
    assert not [pair for pair in overlapping_pairs(rects) if 0 in pair]


def test_legend_escapes_names_from_files() -> None:
    from types import SimpleNamespace

    from efem_viz.viewer.legend import category_counts, legend_html, result_summary_markdown

    inst = SimpleNamespace(ids=np.array([3, 4]), confidence=np.array([0.9, 0.2]),
                           obb_center=np.array([[0.0, 0, 0], [1.0, 0, 0]]), obb_half_extents=np.full((2, 3), 0.05),
                           category=np.array(["<img src=x onerror=alert(1)>", "cup_*x*"]))
    html = legend_html(inst, np.array([True, True]))
    assert "<img" not in html and "&lt;img" in html
    assert html.index("#3") < html.index("#4")  # highest confidence first
    assert legend_html(inst, np.array([False, False])) == ""
    md = result_summary_markdown(inst, np.array([True, False]), threshold=0.5, out_tau=0.04)
    assert "**1 of 2 instances**" in md and "cup\\_\\*x\\*: 0 of 1" in md and "\\<img" in md
    assert category_counts(["b", "a", "b"]) == {"b": 2, "a": 1}


def test_mask_band_rederives_masks_without_rerun(app: Any, tmp_path: Path) -> None:
    """The τ_out slider re-derives the masks from the stored latents: wider band ⊇ narrower; colours, GT metrics
    and exports follow; back at the run's band the run's masks return exactly."""
    res0 = app.state.result
    tau0 = res0.config.output.out_tau
    assert app.panels.gui_mask_band.value == pytest.approx(tau0) and not app.panels.gui_mask_band.disabled
    app.set_color_mode("instances")
    app.set_threshold(0.0)
    colors0 = np.array(app.nodes.points.colors)
    assert app.set_mask_band(0.15)
    res1 = app.state.result
    assert res1.trace is res0.trace and res1.config.output.out_tau == pytest.approx(0.15)  # no re-run
    grew = False
    for a, b in zip(res0.instances.masks, res1.instances.masks, strict=True):
        assert set(a.tolist()) <= set(b.tolist())
        grew |= len(b) > len(a)
    assert grew, "a band 4x wider must take in more points"
    assert not np.array_equal(colors0, np.array(app.nodes.points.colors))
    assert "SDF\\| < 0.15" in app.panels.gui_result_info.content
    out = app.export_tab.export_results(tmp_path / "exp")
    assert out is not None
    assert app.set_mask_band(tau0)
    for a, b in zip(res0.instances.masks, app.state.result.instances.masks, strict=True):
        assert np.array_equal(np.sort(a), np.sort(b))
    assert np.array_equal(colors0, np.array(app.nodes.points.colors))
    # clamped to the slider
    assert app.set_mask_band(5.0) and app.state.result.config.output.out_tau == pytest.approx(0.2)
    assert app.set_mask_band(tau0)


def test_bad_scene_shows_error_and_server_stays_up(app: Any) -> None:
    assert app.open_scene("broken") is False
    assert app.state.error is not None and "broken.ply" in app.state.error
    assert "broken.ply" in app.panels.gui_status.content
    assert app.state.scene_name == "spheres"  # previous scene kept
    assert app.open_scene("one_sphere") is True
    assert app.state.result is None and app.state.error is None
    assert app.panels.gui_mask_band.disabled and app.set_mask_band(0.1) is False  # no result: nothing to re-derive
    assert app.load_trace() is False and "No saved trace" in app.state.status
    assert app.open_scene("spheres") is True and app.state.result is not None
    assert app.wait_idle(60)


def test_never_reads_outside_given_paths(app: Any, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere.efem.npz"
    outside.write_bytes(b"not read")
    assert app.load_trace(outside) is False
    assert "outside the given paths" in app.state.error
    with pytest.raises(KeyError):
        app.state.entry("../elsewhere")


def test_run_in_worker_with_progress_and_cancel(app: Any) -> None:
    import threading

    gate = threading.Event()
    app._submit(app._runner, gate.wait, 30)  # keep the run thread busy so the cancel lands before the run starts
    before = app.state.result
    fut = app.start_run(preset="fast", proposals=8, seed=3)
    assert fut is not None and app.state.running
    assert app.panels.gui_run.disabled and not app.panels.gui_cancel.disabled and app.panels.gui_progress.visible
    assert app.start_run(preset="fast") is None  # one run at a time
    # The UI stays usable during a run: loading a trace (worker thread) does not wait for it.
    assert app._submit(app._worker, app.load_trace).result(timeout=30) is True
    before = app.state.result
    app.session.runs.cancel_run()
    gate.set()
    assert fut.result(timeout=120) is None
    assert app.state.status == "Run cancelled." and app.state.result is before
    assert not app.state.running and not app.panels.gui_run.disabled and not app.panels.gui_progress.visible
    fut = app.start_run(preset="fast", proposals=8, seed=3)
    res = fut.result(timeout=120)
    assert res is not None and app.state.result is res
    assert app.state.result_source.startswith("run (fast, seed 3")
    assert len(res.trace.alive(0)) == 8
    assert app.load_trace() is True  # back to the saved one
    assert app.wait_idle(60)


def test_a_first_run_says_it_builds_the_kernels(app: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the encoder's kernels are not built yet, the Run's progress line says so while they compile."""
    from efem_viz.prior import fused

    seen: list[str] = []
    monkeypatch.setattr(fused, "pending_build", lambda: True)
    monkeypatch.setattr(fused, "load", lambda: seen.append(app.panels.gui_run_info.content) or False)
    res = app.start_run(preset="fast", proposals=8, seed=3).result(timeout=120)
    assert res is not None and seen == [fused.BUILD_NOTICE]
    assert app.wait_idle(60)


def test_a_run_is_shown_as_it_goes_then_its_final_result(app: Any) -> None:
    """Progressive results: with no wait between shown states, the proposals as drawn (a dot at each anchor), then
    every step's state of a run (its proposals' samples at the newest step, the instances accepted so far) is shown
    in the step view, each with more steps, then the finished result in the result view; the progress line says
    the time left."""
    shown: list[tuple[int, int, str]] = []
    drawn: list[tuple[str, int, bool]] = []  # the view, and the sample points on screen after each shown state
    original = app.set_result

    def spy(result: Any, *, source: str, view_mode: str = "result") -> None:
        shown.append((result.trace.num_steps, len(result.instances), source))
        original(result, source=source, view_mode=view_mode)  # type: ignore[arg-type]
        sm = app.nodes.samples
        drawn.append((app.state.view_mode, 0 if sm is None else len(sm.points), bool(sm is not None and sm.visible)))

    from efem_viz.viewer import scene_views

    decode = scene_views.decode_shapes
    decoded_while_running: list[Any] = []

    def watch(nodes: Any, session: Any, keys: Any, generation: int) -> None:
        if session.state.running:
            decoded_while_running.append(keys)
        decode(nodes, session, keys, generation)

    app.set_result = spy
    scene_views.decode_shapes = watch
    try:
        app.run_panel.progressive_every_s = 0.0
        fut = app.start_run(preset="fast", proposals=8, seed=3)
        res = fut.result(timeout=600)
    finally:
        app.set_result = original
        scene_views.decode_shapes = decode
        app.run_panel.progressive_every_s = None
    assert res is not None and app.state.result is res
    first, partial, final = shown[0], shown[1:-1], shown[-1]
    assert first[0] == 0 and first[2] == "running: 8 proposals drawn, step 1 of 20 under way"  # at once
    assert drawn[0] == ("step", 8, True), "a dot at each proposal's anchor"
    assert all(mode == "step" and n > 8 and vis for mode, n, vis in drawn[1:3]), "the first steps' samples"
    assert drawn[-1][0] == "result" and not drawn[-1][2], "the finished run: its instances, no samples"
    assert not decoded_while_running, "no shape is decoded while the run needs the CPU"
    assert app.session.timeline.step_view() is not None
    steps = [n for n, _, _ in partial]
    assert steps == list(range(1, res.trace.num_steps + 1)), steps  # one state per step, in order
    assert all(src.startswith(f"running: step {n} of ") for n, _, src in partial)
    accepted = [k for _, k, _ in partial]  # instances appear as their episodes end, never disappear
    assert accepted == sorted(accepted) and accepted[-1] <= len(res.instances)

    # cancelled after its second shown state: the screen keeps what the run had, saying it stopped and is not saved
    def cancel_at_two(result: Any, *, source: str, view_mode: str = "result") -> None:
        original(result, source=source, view_mode=view_mode)  # type: ignore[arg-type]
        if source.startswith("running: step 2 "):
            app.session.runs.cancel_run()

    app.set_result = cancel_at_two
    try:
        app.run_panel.progressive_every_s = 0.0
        assert app.start_run(preset="fast", proposals=8, seed=3).result(timeout=600) is None
    finally:
        app.set_result = original
        app.run_panel.progressive_every_s = None
    assert app.state.result_source == "stopped run (not saved): as far as it went, step 2 of 20"
    assert app.state.result.trace.num_steps == 2 and not app.state.running
    assert app.load_trace() is True  # back to the saved one, for the module's later tests
    assert app.wait_idle(60)
    assert final[0] == res.trace.num_steps and final[2].startswith("run (fast, seed 3")
    assert app.wait_idle(60)


def test_export_results_and_static_demo(app: Any, tmp_path: Path) -> None:
    app.set_threshold(0.0)
    out = app.export_tab.export_results(tmp_path / "res")
    assert out is not None
    txt = (out / "spheres.txt").read_text().splitlines()
    assert len(txt) == len(app.state.result.instances)
    assert (out / "spheres_instances.ply").is_file()
    index = app.export_tab.export_static(tmp_path / "static" / "spheres")
    assert index is not None and index.name == "index.html"
    html = index.read_text()
    assert "__VISER_EMBED_DATA__" in html and len(html) < 20_000_000
    import json

    meta = json.loads((index.parent / "meta.json").read_text())
    assert meta["steps"] == app.state.result.trace.num_steps
    assert meta["decoded_shapes"] > 0  # the viewer's prior decoded the best proposals of every step


def test_static_demo_export_shows_progress_and_cancels(app: Any, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """the static demo (seconds: it records every EM step) says which step it records, with a
    progress bar; *Cancel export* stops it and nothing is written; the buttons come back."""
    from efem_viz.viewer import export

    app.set_threshold(0.0)
    seen: list[tuple[str, bool, bool]] = []
    real_step = export._DemoRecording._step

    def step(self: Any, api: Any, t: int, **kw: Any) -> int:
        p = app.panels
        seen.append((app.state.status, p.gui_export_progress.visible, p.gui_export_cancel.disabled))
        if t == 2 and len(seen) == 3:  # the first export only
            app.export_tab.cancel()
        return real_step(self, api, t, **kw)

    monkeypatch.setattr(export._DemoRecording, "_step", step)
    target = tmp_path / "static" / "cancelled"
    assert app.export_tab.export_static(target) is None
    assert not target.exists()  # not even the folder
    assert "cancelled: nothing was written" in app.state.status
    assert seen[0][0].endswith("EM step 1 of %d … (Cancel export stops it)" % app.state.result.trace.num_steps)
    assert all(visible and not disabled for _, visible, disabled in seen) and len(seen) == 3
    p = app.panels
    assert not p.gui_export_progress.visible and p.gui_export_cancel.disabled and not p.gui_export_static.disabled
    assert app.export_tab.export_static(tmp_path / "static" / "again") is not None  # the next export runs to the end
    assert len(seen) == 3 + app.state.result.trace.num_steps


def test_ground_truth_panel(app: Any) -> None:
    app.set_threshold(0.0)
    app.set_color_mode("gt_match")
    m = app._gt_metrics()
    assert len(m.tp) + len(m.fn) == len(app.state.scene.instance_ids())
    assert "AP50" in app.panels.gui_gt_info.content
    colors = np.asarray(app.nodes.points.colors)
    if m.tp:
        assert (colors[m.masks[m.tp[0]]] == pal.TP_COLOR).all()
    assert app.panels.gui_pr_plot.visible
    app.set_color_mode("instances")


def test_view_args_defaults() -> None:
    from efem_viz.viewer.commands import ViewArgs

    args = ViewArgs()
    assert args.host == "127.0.0.1" and args.port == 8080 and args.paths == ()
    with pytest.raises(FileNotFoundError):
        ViewArgs(paths=(Path("/nonexistent/dir"),)).run()


def test_exports_default_to_the_user_data_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without --out-dir the viewer's exports go to `view/` in the user's data folder, never into the working
    directory (run from the checkout, `./efem_out` landed in `git status`)."""
    import sys

    from efem_viz.serve.outputs import default_output_dir
    from efem_viz.viewer.app import ViewerApp
    from efem_viz.viewer.commands import ViewArgs

    repo = Path(__file__).resolve().parents[1]
    assert ViewArgs().out_dir is None
    assert not default_output_dir("view").resolve().is_relative_to(repo)
    if sys.platform.startswith("linux"):
        monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
        assert default_output_dir("view") == tmp_path / "data" / "efem-viz" / "view"
    monkeypatch.chdir(repo)
    a = ViewerApp([tmp_path], port=0, open_first=False)
    try:
        assert a.out_root == default_output_dir("view").resolve()
        assert not a.out_root.is_relative_to(repo)
    finally:
        a.stop()


def test_single_file_path_reads_its_saved_result_only(scene_dir: Path, prior: Any) -> None:
    from efem_viz.viewer.app import ViewerApp

    a = ViewerApp([scene_dir / "spheres.ply"], port=0, prior=prior)
    try:
        assert [e.name for e in a.state.entries] == ["spheres"]
        assert a.state.result is not None  # spheres.efem.npz next to the given file is part of it
        assert a.load_trace(scene_dir / "one_sphere.ply") is False  # a sibling that was not given
        assert "outside the given paths" in (a.state.error or "")
    finally:
        a.stop()


def test_labels_copy_shares_the_base_result(tmp_path: Path) -> None:
    (tmp_path / "scan.ply").write_text("x")
    (tmp_path / "scan.labels.ply").write_text("x")
    entries = {e.name: e for e in sc.discover_scenes([tmp_path])}
    assert entries["scan.labels"].trace_path.name == "scan.labels.efem.npz"  # no result yet anywhere
    (tmp_path / "scan.efem.npz").write_text("x")
    assert entries["scan.labels"].trace_path.name == "scan.efem.npz"
    (tmp_path / "scan.labels.efem.npz").write_text("x")
    assert entries["scan.labels"].trace_path.name == "scan.labels.efem.npz"  # its own result wins
    assert entries["scan"].trace_path.name == "scan.efem.npz"


def test_prior_mismatch_is_reported_once(scene_dir: Path) -> None:
    from efem_viz.viewer.app import ViewerApp

    class OtherPrior:  # the run's category (a run is decoded with the prior of its category), another network
        name = "other"
        metadata = {"category": {"name": "sphere"}}
        config = type("Cfg", (), {"latent_dim": 999})()

    a = ViewerApp([scene_dir], port=0, prior=OtherPrior(), open_first=False)
    try:
        assert a.open_scene("spheres")
        assert a.wait_idle(60)
        a.set_step(1)  # the result view decodes no step shape; a step does
        assert a.wait_idle(60)
        assert "latent size" in (a.state.error or "")
        a.set_step(2)
        assert a.wait_idle(60)
        assert not a.nodes.shapes  # nothing decoded with the wrong prior, and no retry per step
        assert a.nodes.samples is not None and a.nodes.samples.visible  # the rest of the timeline works
    finally:
        a.stop()


def test_playback_advances_and_stops_at_the_end(app: Any) -> None:
    import time

    app.set_step(0)
    app.state.speed = 40.0
    app.playback.play()
    assert app.state.playing and app.panels.gui_play.label == "Pause"
    deadline = time.monotonic() + 30
    while app.state.playing and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not app.state.playing and app.state.step == app.state.num_steps - 1
    assert app.panels.gui_play.label == "Play" and app.panels.gui_step.value == app.state.step
    app.state.speed = 2.0
    assert app.wait_idle(60)


def test_gui_callbacks_drive_the_app(app: Any) -> None:
    """Setting a GUI value (as a browser does) runs the callback; programmatic updates do not re-enter."""
    app.panels.gui_step.value = 1
    assert app.state.step == 1
    app.panels.gui_threshold.value = app.panels.gui_threshold.max
    assert app.state.threshold == app.panels.gui_threshold.max and app.session.results.kept_mask().sum() == 0
    app.panels.gui_threshold.value = 0.0
    assert app.session.results.kept_mask().all()
    app.panels.gui_max_shapes.value = 2
    assert app.state.max_shapes == 2
    app.panels.gui_max_shapes.value = 8
    app.panels.gui_color.value = "scene colours"
    assert app.state.color_mode == "rgb"
    assert np.array_equal(np.asarray(app.nodes.points.colors), app.state.scene.colors)
    app.set_step(app.state.num_steps - 1)
    assert app.wait_idle(60)


def test_mesh_scene_shows_mesh_and_overlays_points_for_colourings(tmp_path: Path, prior: Any) -> None:
    import trimesh

    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene
    from efem_viz.viewer.app import ViewerApp

    box = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    scene = Scene.create("box", np.asarray(box.vertices), faces=np.asarray(box.faces))
    save_scene(scene, tmp_path / "box.ply")
    a = ViewerApp([tmp_path], port=0, prior=prior)
    try:
        assert a.state.scene is not None and a.state.scene.is_mesh
        assert a.state.display == "mesh" and a.nodes.mesh is not None
        assert a.nodes.mesh.visible and not a.nodes.points.visible
        a.set_color_mode("instances")  # no result: scene colours, but the overlay is on
        assert a.nodes.points.visible and a.nodes.mesh.visible
        a.set_display("points")
        assert not a.nodes.mesh.visible and a.nodes.points.visible
        with pytest.raises(ValueError):
            a.set_display("voxels")
    finally:
        a.stop()


def test_export_command_writes_a_demo(scene_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from efem_viz.viewer.export import main

    assert main([str(scene_dir / "spheres.ply"), "--prior", "", "--out", str(tmp_path / "demo")]) == 0
    index = tmp_path / "demo" / "index.html"
    assert index.is_file() and str(index) in capsys.readouterr().out
    assert index.stat().st_size < 20_000_000


def test_results_folder_is_searched_and_refreshed(scene_dir: Path, prior: Any, tmp_path: Path) -> None:
    """`view SCENES --results DIR`: a scene's result in a segment output folder is found; one written after the
    scene was opened is found too, and the scene panel says so once it is loaded."""
    import shutil

    from efem_viz.viewer.app import ViewerApp

    scenes, results = tmp_path / "scenes", tmp_path / "results"
    scenes.mkdir()
    results.mkdir()
    shutil.copy(scene_dir / "spheres.ply", scenes / "spheres.ply")
    a = ViewerApp([scenes], port=0, prior=prior, open_first=False, results=[results])
    try:
        assert a.open_scene("spheres") and a.wait_idle(60)
        assert "saved trace: none" in a.panels.gui_info.content
        assert not a.load_trace()
        shutil.copy(scene_dir / "spheres.efem.npz", results / "spheres.efem.npz")  # e.g. segment --out results
        assert a.state.entry("spheres").trace_path == (results / "spheres.efem.npz").resolve()
        assert a.load_trace() and a.wait_idle(60)
        assert a.state.result is not None
        assert "saved trace: `spheres.efem.npz`" in a.panels.gui_info.content
    finally:
        a.stop()


def test_the_viewer_opens_on_a_scene_with_a_saved_result(scene_dir: Path, prior: Any, tmp_path: Path) -> None:
    """A folder of scans of which only some have a saved result (the bundled scenes: the real frames first in the
    list have none) opens on the first one with a result, drawn at once; the list keeps its order."""
    import shutil

    from efem_viz.viewer.app import ViewerApp

    shutil.copy(scene_dir / "spheres.ply", tmp_path / "a_plain.ply")
    shutil.copy(scene_dir / "spheres.ply", tmp_path / "b_run.ply")
    shutil.copy(scene_dir / "spheres.efem.npz", tmp_path / "b_run.efem.npz")
    a = ViewerApp([tmp_path], port=0, prior=prior)
    try:
        assert [e.name for e in a.state.entries] == ["a_plain", "b_run"]
        assert a.wait_idle(60) and a.state.scene_name == "b_run" and a.state.result is not None
    finally:
        a.stop()
    (tmp_path / "b_run.efem.npz").unlink()  # no result anywhere: the first scene
    a = ViewerApp([tmp_path], port=0, prior=prior)
    try:
        assert a.wait_idle(60) and a.state.scene_name == "a_plain" and a.state.result is None
    finally:
        a.stop()


def test_a_results_folder_alone_lists_its_segment_outputs(scene_dir: Path, prior: Any, tmp_path: Path) -> None:
    import shutil

    from efem_viz.viewer.app import ViewerApp

    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(scene_dir / "spheres.ply", out / "spheres.seg.ply")  # what segment writes beside the result
    shutil.copy(scene_dir / "spheres.efem.npz", out / "spheres.efem.npz")
    a = ViewerApp([], port=0, prior=prior, open_first=False, results=[out])
    try:
        assert [e.name for e in a.state.entries] == ["spheres.seg"]
        assert a.state.entries[0].trace_path == (out / "spheres.efem.npz").resolve()
    finally:
        a.stop()
    with pytest.raises(FileNotFoundError, match="results folder"):
        ViewerApp([scene_dir], port=0, prior=prior, results=[tmp_path / "nope"])


def test_a_two_prior_result_decodes_and_inspects_each_proposal_with_its_own_prior(tmp_path: Path) -> None:
    """A joint solve over the mug and the sphere prior: the viewer (started with the mug prior) decodes the shapes
    and inspects the proposals of both categories, loading the sphere prior by its category name."""
    import torch

    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.prior import load_priors
    from efem_viz.viewer.app import ViewerApp

    torch.set_num_threads(1)
    scene = analytic.add_spheres(load_scene(sample_scene("syn_z_0")), [0.045], seed=0)
    scene = scene.replace(name="mixed")
    mug, sphere = load_priors(["mug", "sphere"])
    cfg = em.preset("fast").replace(proposals={"n_init": (12,)}, steps={"t1": 3, "t2": 1, "end_step": 2})
    res = em.run_em(scene, priors=[mug, sphere], cfg=cfg, seed=0)
    save_scene(scene, tmp_path / "mixed.ply")
    res.save(tmp_path / "mixed.efem.npz")
    app = ViewerApp([tmp_path], port=0, prior=mug, open_first=False)
    try:
        assert app.open_scene("mixed") and app.wait_idle(60)
        tr = app.state.result.trace
        assert tr.prior_names == ("mug", "sphere")
        t = tr.num_steps - 1
        for kind in ("mug", "sphere"):
            alive = [int(p) for p in tr.alive(t) if tr.category_of(int(p)) == kind]
            assert alive, f"no {kind} proposal alive at the last step"
            fut = app.select_proposal(alive[0])
            assert fut is not None
            fut.result(timeout=120)
            assert app.wait_idle(60)
            assert "shape" in app.nodes.inspect, f"no decoded shape for the {kind} proposal"
            if kind == "sphere":  # decoded with the sphere prior: a sphere of radius Θ_s / 2 (drawn shifted aside)
                lat = tr.latent(alive[0], t)
                v = np.asarray(app.nodes.inspect["shape"].vertices, np.float64)
                r = np.linalg.norm(v - v.mean(axis=0), axis=1)
                assert np.allclose(r, float(lat["scale"]) / 2, rtol=0.05), "sphere proposal decoded by another prior"
        app.set_step(t)
        assert app.wait_idle(120)
        assert any(app.nodes.has_shape(int(p), t) for p in tr.alive(t)), "no proposal shape decoded"
        # the static demo decodes the shapes of both categories, each with its prior
        from efem_viz.viewer.export import export_static_demo

        index = export_static_demo(app.state.scene, app.state.result, tmp_path / "demo", prior=[mug, sphere],
                                   shapes_per_step=2)
        meta = json.loads((index.parent / "meta.json").read_text())
        assert meta["decoded_shapes"] > 0
    finally:
        app.stop()


def test_a_run_started_in_the_viewer_solves_over_the_extra_priors(tmp_path: Path) -> None:
    """`efem-viz view --prior sphere --prior mug`: the Run button solves jointly over both priors; the result names
    both categories and the viewer decodes the proposals of each with its own prior."""
    import torch

    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.viewer.app import ViewerApp

    torch.set_num_threads(1)
    scene = analytic.add_spheres(load_scene(sample_scene("syn_z_0")), [0.045], seed=1).replace(name="mixed_run")
    save_scene(scene, tmp_path / "mixed_run.ply")
    app = ViewerApp([tmp_path], port=0, prior=analytic.make_sphere_prior(), prior_name="sphere", run_priors=["mug"],
                    open_first=False)
    try:
        assert app.open_scene("mixed_run") and app.wait_idle(60)
        fut = app.start_run(preset="fast", proposals=12, seed=0)
        assert fut is not None
        fut.result(timeout=300)
        assert app.wait_idle(120)
        res = app.state.result
        assert res is not None and res.trace.prior_names == ("sphere", "mug")
        assert set(res.instances.category) <= {"sphere", "mug"} and len(set(res.trace.prior_names)) == 2
        t = res.trace.num_steps - 1
        mug_pid = next(int(p) for p in res.trace.alive(t) if res.trace.category_of(int(p)) == "mug")
        fut = app.select_proposal(mug_pid)
        assert fut is not None
        fut.result(timeout=120)
        assert app.wait_idle(60) and "shape" in app.nodes.inspect
    finally:
        app.stop()


def test_the_proposals_field_follows_the_preset_until_a_person_edits_it(tmp_path: Path, prior: Any) -> None:
    """The Run tab's Proposals field started at 100 and overrode every preset (120 for `real`, 80 for `fast`). It
    shows the chosen preset's number, follows the preset the scene suggests and a person's preset choice, and keeps
    a number a person typed."""
    from efem_viz.data.io import load_scene, save_scene
    from efem_viz.em.config import preset
    from efem_viz.viewer.app import ViewerApp

    repo = Path(__file__).resolve().parents[1]
    for name in ("real_tabletop_6", "syn_pile_0"):
        save_scene(load_scene(repo / "sample_scenes" / f"{name}.ply"), tmp_path / f"{name}.ply")
    a = ViewerApp([tmp_path], port=0, prior=prior, open_first=False)
    try:
        p = a.panels
        assert p.gui_proposals.value == preset("fast").proposals.n_init[0]
        assert a.open_scene("real_tabletop_6") and a.wait_idle(600)
        assert p.gui_preset.value == "real" and p.gui_proposals.value == preset("real").proposals.n_init[0] == 120
        p.gui_preset.value = "synthetic"  # a person's choice (the handle's callbacks run as for a client)
        assert p.gui_proposals.value == preset("synthetic").proposals.n_init[0]
        p.gui_proposals.value = 123  # typed by a person: kept from now on
        p.gui_preset.value = "fast"
        assert p.gui_proposals.value == 123
        assert a.open_scene("syn_pile_0") and a.wait_idle(600)
        assert p.gui_proposals.value == 123 and a.state.proposals_by_user
    finally:
        a.stop()


def test_a_mesh_scene_opened_with_its_result_shows_the_instance_colours(tmp_path: Path, prior: Any) -> None:
    """A mesh scan opened with its saved result starts in the instances colouring, as the legend says: the
    recoloured points are drawn over the mesh (the mesh alone showed the scan's own colours)."""
    import shutil

    from efem_viz.viewer.app import ViewerApp

    repo = Path(__file__).resolve().parents[1]
    for f in ("syn_pile_0.ply", "syn_pile_0.efem.npz"):
        shutil.copy(repo / "sample_scenes" / f, tmp_path / f)
    a = ViewerApp([tmp_path], port=0, prior=prior, open_first=False)
    try:
        assert a.open_scene("syn_pile_0") and a.wait_idle(600)
        assert a.state.display == "mesh" and a.state.color_mode == "instances" and a.session.scenes.recolored()
        assert a.nodes.points is not None and a.nodes.points.visible, "the instance colours are hidden under the mesh"
        a.set_color_mode("rgb")
        assert not a.nodes.points.visible and a.nodes.mesh is not None and a.nodes.mesh.visible
    finally:
        a.stop()


def test_a_scene_with_astronomic_coordinates_is_refused_and_the_others_open(tmp_path: Path, prior: Any) -> None:
    """A scene of 1e30-metre coordinates first in the list aborted the viewer's start-up (an internal
    OverflowError): it is one status line, and the viewer starts on the next scene."""
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene
    from efem_viz.viewer.app import ViewerApp

    rng = np.random.default_rng(0)
    up = np.tile(np.float32([0, 0, 1]), (400, 1))
    grey = np.full((400, 3), 100, np.uint8)
    save_scene(Scene(name="a", points=(rng.normal(size=(400, 3)) * 1e30).astype(np.float32), normals=up,
                     colors=grey), tmp_path / "a_huge.ply")
    save_scene(Scene(name="b", points=(rng.normal(size=(400, 3)) * 0.1).astype(np.float32), normals=up,
                     colors=grey), tmp_path / "b_ok.ply")
    a = ViewerApp([tmp_path], port=0, prior=prior)
    try:
        assert a.state.scene_name == "b_ok"
        assert not a.open_scene("a_huge")
        assert "not a scan in metres" in a.state.status and a.state.scene_name == "b_ok"
    finally:
        a.stop()


def test_a_result_without_steps_loads_and_a_run_on_a_two_point_scene_finishes(tmp_path: Path, prior: Any) -> None:
    """A scene of one or two points gives a trace with zero steps: the viewer could not load it ("step 0 out of
    range [0, 0)") and its Run failed with a traceback. Both now show the (empty) result."""
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene
    from efem_viz.viewer.app import ViewerApp

    two = Scene(name="two", points=np.float32([[0, 0, 0], [0.01, 0, 0]]), normals=np.float32([[0, 0, 1]] * 2),
                colors=np.full((2, 3), 100, np.uint8))
    save_scene(two, tmp_path / "two.ply")
    res = em.run_em(two, prior, em.preset("fast"), seed=0)
    assert len(res.trace.step_phase) == 0
    res.save(tmp_path / "two.efem.npz")
    a = ViewerApp([tmp_path], port=0, prior=prior, prior_name="sphere")
    try:
        assert a.state.result is not None and "Loaded result" in a.state.status, a.state.status
        a.start_run()
        assert a.wait_idle(600)
        assert a.state.result is not None and a.state.result_source.startswith("run"), a.state.status
        assert "failed" not in a.state.status
    finally:
        a.stop()
