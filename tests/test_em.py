"""EFEM solver end to end: analytic sphere prior (known answer), a small random ShapePrior (smoke, cancel,
progress), result views and exports, the CLI, and a regression on a seeded mug scene with the trained prior."""

from __future__ import annotations

import dataclasses
import logging
import threading
from pathlib import Path

import numpy as np
import pytest

from efem_viz.em import EMCancelled, EMResult, Instances, StepInfo, preset, run_em
from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene
from helpers import sample_scene

WEIGHTS = Path(__file__).resolve().parents[1] / "efem_viz" / "weights" / "mug.pt"


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


def ious(inst: Instances, gt: np.ndarray) -> np.ndarray:
    """(K, G) IoU of every predicted mask against every ground-truth instance 1..G."""
    ids = [g for g in np.unique(gt) if g > 0]
    out = np.zeros((len(inst), len(ids)))
    for k, m in enumerate(inst.bool_masks(len(gt))):
        for j, g in enumerate(ids):
            t = gt == g
            out[k, j] = (m & t).sum() / max((m | t).sum(), 1)
    return out


@pytest.fixture(scope="module")
def sphere_run() -> tuple[object, object, EMResult, list[StepInfo]]:
    scene = make_sphere_scene(seed=11)
    prior = make_sphere_prior()
    steps: list[StepInfo] = []
    res = run_em(scene, prior, preset("fast").replace(proposals={"n_init": (64,)}), seed=5, on_step=steps.append)
    return scene, prior, res, steps


# ---------------------------------------------------------------------------------------------- sphere prior
def test_a_categorys_planar_check_runs_on_meshes_only_an_explicit_limit_everywhere(sphere_run: tuple) -> None:
    """A category's planar limit (`CategorySettings.max_planar`) needs a mesh's normals: on a point cloud (the
    sphere scene) the share is recorded but nothing dies as "planar", and the run is the plain one; a limit the
    caller sets in the config holds on a point cloud too."""
    import copy

    from efem_viz.prior.config import prior_category

    scene, prior, base, _ = sphere_run
    assert getattr(scene, "faces", None) is None
    strict = copy.copy(prior)
    strict.metadata = {**prior.metadata, "category": {**prior_category(prior).to_dict(),
                                                      "max_planar": {"synthetic": 0.01, "real": 0.01}}}
    cfg = preset("fast").replace(proposals={"n_init": (64,)})
    res = run_em(scene, strict, cfg, seed=5)
    assert res.config.review.max_planar is None
    assert len(res.instances) == len(base.instances) and len(res.instances) > 0
    assert res.trace.rev_planar is not None and np.isfinite(res.trace.rev_planar).any()
    told = run_em(scene, prior, cfg.replace(review={"max_planar": 0.01}), seed=5)
    reasons = [told.trace.death(k)[1] for k in range(told.trace.num_proposals) if told.trace.death(k)]
    assert len(told.instances) == 0 and "planar" in reasons


def test_free_space_check_scales_confidence_and_is_recorded(sphere_run: tuple, tmp_path: Path) -> None:
    """With a capture camera in the provenance, `seen_through_margin` measures each review's seen-through
    fraction (near 0 for spheres fitted where they are), records it in the trace (saved and loaded), and
    multiplies the confidence by (1 − fraction); the run is otherwise the same draw for draw. Without a camera
    nothing is measured."""
    from efem_viz.em.results import EMResult
    from efem_viz.em.solver import confidence
    from efem_viz.geometry.camera import look_at

    scene, prior, base, _ = sphere_run
    T = look_at(np.array([0.0, -0.6, 0.45]), np.array([0.0, 0.0, 0.03]))
    K = [[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]]
    cam_scene = dataclasses.replace(scene, provenance={**scene.provenance, "K": K, "T_world_camera": T.tolist(),
                                                       "image_size": [320, 240]})
    cfg = preset("fast").replace(proposals={"n_init": (64,)}, free_space={"margin": 0.01})
    res = run_em(cam_scene, prior, cfg, seed=5)
    tr = res.trace
    assert tr.rev_seen_through is not None and len(tr.rev_seen_through) == len(tr.rev_id)
    assert np.isfinite(tr.rev_seen_through).all() and (tr.rev_seen_through >= 0).all()
    assert len(res.instances) == len(base.instances)
    assert np.array_equal(res.instances.ids, base.instances.ids)
    for k, pid in enumerate(res.instances.ids):
        rev = tr.reviews(int(pid))[-1]
        assert rev.seen_through < 0.05
        want = confidence(float(res.instances.stationary[k]), float(res.instances.coverage[k]),
                          seen_through=rev.seen_through)
        assert res.instances.confidence[k] == pytest.approx(want, rel=1e-5)
        assert res.instances.confidence[k] <= base.instances.confidence[k] + 1e-6
    path = res.save(tmp_path / "cam.efem.npz")
    back = EMResult.load(path)
    assert back.trace.rev_seen_through is not None
    assert np.array_equal(back.trace.rev_seen_through, tr.rev_seen_through)
    # no camera: not measured, same confidences as the method
    plain = run_em(scene, prior, cfg, seed=5)
    assert plain.trace.rev_seen_through is not None and np.isnan(plain.trace.rev_seen_through).all()
    assert np.allclose(plain.instances.confidence, base.instances.confidence)


def test_a_fused_scans_cameras_all_check_free_space_and_a_bad_one_is_said(sphere_run: tuple) -> None:
    """A scene whose provenance lists several cameras (a fused scan) is checked against every usable one: the
    same instances as the plain run (spheres fitted where they are), each review's seen-through fraction
    measured; an unusable entry among them is named in the result's warnings and the others still check."""
    from efem_viz.geometry.camera import look_at

    scene, prior, base, _ = sphere_run
    K = [[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]]
    cams = [{"K": K, "T_world_camera": look_at(np.array(eye), np.array([0.0, 0.0, 0.03])).tolist(),
             "image_size": [320, 240]} for eye in ([0.0, -0.6, 0.45], [0.6, 0.0, 0.45], [-0.4, 0.4, 0.5])]
    cfg = preset("fast").replace(proposals={"n_init": (64,)}, free_space={"margin": 0.01})
    fused = dataclasses.replace(scene, provenance={**scene.provenance, "cameras": cams})
    res = run_em(fused, prior, cfg, seed=5)
    assert res.warnings == ()
    tr = res.trace
    assert tr.rev_seen_through is not None and np.isfinite(tr.rev_seen_through).all()
    assert np.array_equal(res.instances.ids, base.instances.ids)
    bad = {**cams[1], "T_world_camera": np.full((4, 4), np.nan).tolist()}
    partly = dataclasses.replace(scene, provenance={**scene.provenance, "cameras": [cams[0], bad, cams[2]]})
    res2 = run_em(partly, prior, cfg, seed=5)
    assert len(res2.warnings) == 1 and "camera 2 of 3" in res2.warnings[0] and "uses the other 2" in res2.warnings[0]
    assert res2.trace.rev_seen_through is not None and np.isfinite(res2.trace.rev_seen_through).all()


def test_sphere_scene_each_object_found_once(sphere_run: tuple) -> None:
    scene, _, res, _ = sphere_run
    m = ious(res.instances, scene.instance)
    assert m.shape == (3, 3), f"expected 3 instances, got {len(res.instances)}"
    assert (m.max(axis=0) >= 0.9).all()  # every sphere matched
    assert ((m >= 0.5).sum(axis=0) == 1).all()  # exactly once
    assert (res.instances.confidence > 0.5).all()
    # the fitted Θ_s of a sphere is its diameter
    assert np.allclose(np.sort(res.instances.scale), np.sort(2 * np.array(scene.provenance["radii"])), atol=0.01)


def test_explained_decay_sets_the_confidences_of_the_instances_and_the_trace(sphere_run: tuple,
                                                                              monkeypatch: pytest.MonkeyPatch
                                                                              ) -> None:
    """`confidence.explained_decay` passes the episode's survivors (their method confidences and final masks) to
    `rules.explained_decay` once, and what it returns is each instance's confidence and its survival record in
    the trace; the fits themselves are the same draw for draw as with the decay off (the method; the sphere's
    category has none)."""
    from efem_viz.em import solver as solver_module
    from efem_viz.em.rules import explained_decay

    scene, prior, off, _ = sphere_run
    assert off.config.confidence.explained_decay == 0.0
    calls: list[tuple] = []

    def halve(conf: np.ndarray, masks: list, n: int, power: float) -> np.ndarray:
        calls.append((np.array(conf), [np.array(m) for m in masks], n, power))
        return np.asarray(conf) * 0.5

    cfg = preset("fast").replace(proposals={"n_init": (64,)}, confidence={"explained_decay": 3.0})
    monkeypatch.setattr(solver_module, "explained_decay", halve)
    res = run_em(scene, prior, cfg, seed=5)
    assert len(calls) == 1
    conf, masks, n, power = calls[0]
    assert (n, power) == (len(scene.points), 3.0)
    assert np.array_equal(res.instances.ids, off.instances.ids)
    np.testing.assert_allclose(conf, off.instances.confidence, rtol=1e-6)
    assert all(np.array_equal(a, np.asarray(b)) for a, b in zip(masks, off.instances.masks))
    np.testing.assert_allclose(res.instances.confidence, 0.5 * off.instances.confidence, rtol=1e-6)
    for k, pid in enumerate(res.instances.ids):
        death = res.trace.death(int(pid))
        assert death is not None and death[1] == "survive"
        assert death[3] == pytest.approx(float(res.instances.confidence[k]), rel=1e-6)
    monkeypatch.undo()
    real = run_em(scene, prior, cfg, seed=5)
    want = explained_decay(off.instances.confidence, list(off.instances.masks), len(scene.points), 3.0)
    np.testing.assert_allclose(real.instances.confidence, want, rtol=1e-6)


def test_a_joint_solve_ranks_with_the_weakest_decay_of_its_priors(sphere_run: tuple) -> None:
    """A solve takes the explained-share decay of its prior's category; a joint solve one ranking with the smallest
    of its priors' (a category without the decay keeps the method's confidences beside one that has it)."""
    from efem_viz.prior.analytic import make_sphere_prior
    from efem_viz.prior.config import category_settings

    scene = sphere_run[0]
    decaying, plain = make_sphere_prior(), make_sphere_prior()
    decaying.metadata = {"category": category_settings("sphere").replace(explained_decay={"synthetic": 2.0}).to_dict()}
    plain.name = "ball"
    cfg = preset("fast").replace(proposals={"n_init": (8,)}, steps={"t1": 2, "t2": 1, "end_step": 1})
    assert run_em(scene, decaying, cfg, seed=0).config.confidence.explained_decay == 2.0
    assert run_em(scene, priors=[decaying, plain], cfg=cfg, seed=0).config.confidence.explained_decay == 0.0


def test_progress_and_active_counts(sphere_run: tuple) -> None:
    _, _, res, steps = sphere_run
    tr = res.trace
    drawn, steps = steps[0], steps[1:]  # the first report: the proposals are drawn, no step done
    assert drawn.step == -1 and drawn.active == tr.active_count[0] and drawn.time_left_s is None
    assert [s.step for s in steps] == list(range(tr.num_steps))
    assert all(s.num_steps == 20 for s in steps)
    assert [s.active for s in steps] == tr.active_count[1:].tolist()
    assert [s.phase for s in steps] == tr.step_phase.tolist()
    assert np.all(np.diff([s.elapsed_s for s in steps]) >= 0)
    assert set(res.timings) >= {"encode", "decode", "m_step", "eliminate", "review_mesh", "total"}


def test_same_seed_same_run_other_seed_other_anchors(sphere_run: tuple) -> None:
    scene, prior, res, _ = sphere_run
    cfg = res.config.replace(steps={"t1": 2, "t2": 1, "end_step": 2})
    a = run_em(scene, prior, cfg, seed=5)
    b = run_em(scene, prior, cfg, seed=5)
    c = run_em(scene, prior, cfg, seed=6)
    assert np.array_equal(a.trace.row_samples, b.trace.row_samples)
    assert np.array_equal(a.trace.prop_anchor, res.trace.prop_anchor)  # anchors are the first draw
    assert not np.array_equal(a.trace.prop_anchor, c.trace.prop_anchor)


def test_anchor_candidates_seed_the_first_episode_there(sphere_run: tuple) -> None:
    scene, prior, _, _ = sphere_run
    g = int(scene.instance_ids()[1])
    members = np.flatnonzero(scene.instance == g)[:5]
    cfg = preset("fast").replace(proposals={"n_init": (12,)}, steps={"t1": 4, "t2": 2, "end_step": 3})
    res = run_em(scene, prior, cfg, seed=3, anchor_candidates=members)
    assert set(res.trace.prop_anchor.tolist()) <= set(members.tolist())
    m = ious(res.instances, scene.instance)
    k = list(scene.instance_ids()).index(g)
    assert len(res.instances) >= 1 and m[:, k].max() >= 0.9  # the seeded sphere is found
    thin = run_em(scene, prior, cfg.replace(compute={"work_voxel": 0.02}), seed=3, anchor_candidates=members)
    d = np.linalg.norm(scene.points[thin.trace.prop_anchor][:, None] - scene.points[members][None], axis=2)
    assert d.min(axis=1).max() < 0.02 * np.sqrt(3)  # thinned working set: the kept point nearest a candidate
    for bad in (np.array([], np.int64), np.array([0.5]), np.array([scene.num_points]), np.array([[1]])):
        with pytest.raises(ValueError, match="anchor_candidates"):
            run_em(scene, prior, cfg, anchor_candidates=bad)


def test_anchors_above_the_support_plane(sphere_run: tuple) -> None:
    """`proposals.anchor_min_height` anchors every episode's proposals only on points that high above z = 0 (the
    table's points still join the crops), falls back to anywhere when nothing available is that high, keeps the
    click candidates' restriction, and refuses a height that is not a finite number."""
    scene, prior, _, _ = sphere_run
    z = scene.points[:, 2]
    h = 0.01  # most of this scene is its table at z = 0
    assert (z < h).mean() > 0.5
    cfg = preset("fast").replace(proposals={"n_init": (24, 8), "anchor_min_height": h},
                                 steps={"t1": 3, "t2": 2, "end_step": 2})
    res = run_em(scene, prior, cfg, seed=3)
    tr = res.trace
    first, second = tr.prop_anchor[tr.prop_episode == 0], tr.prop_anchor[tr.prop_episode == 1]
    assert len(first) == 24 and (z[first] >= h).all()
    claimed = np.zeros(len(z), bool)  # the second episode draws among what the first one's instances left
    for k in np.flatnonzero(tr.prop_episode[res.instances.ids] == 0):
        claimed[res.instances.masks[k]] = True
    assert len(second) == 0 or (z[second] >= h).all() or not ((z >= h) & ~claimed).any()
    plain = run_em(scene, prior, cfg.replace(proposals={"anchor_min_height": None}), seed=3)
    assert (z[plain.trace.prop_anchor] < h).any()  # without it the draw lands low too
    rows = tr.rows(0)
    assert (z[np.unique(tr.row_samples[rows])] < h).any()  # the crops still take the low points
    high_all = run_em(scene, prior, cfg.replace(proposals={"anchor_min_height": float(z.max()) + 1.0}), seed=3)
    np.testing.assert_array_equal(high_all.trace.prop_anchor[:24], plain.trace.prop_anchor[:24])  # anywhere
    low = np.flatnonzero(z < h)[:5]
    clicked = run_em(scene, prior, cfg.replace(proposals={"n_init": (6,)}), seed=3, anchor_candidates=low)
    assert set(clicked.trace.prop_anchor.tolist()) <= set(low.tolist())  # no candidate high enough: the clicks win
    for bad in (float("nan"), float("inf"), "5 cm"):
        with pytest.raises(ValueError, match="anchor_min_height"):
            preset("fast").replace(proposals={"anchor_min_height": bad})


def test_points_below_min_point_height_join_no_proposal(sphere_run: tuple, caplog: pytest.LogCaptureFixture
                                                        ) -> None:
    """`proposals.min_point_height` keeps the support plane's points out of every crop, M-step draw and mask (the
    spheres on the table are still found, whole above that height); a scene with nothing that high ends with no
    instance and no error; a height that is not a finite number is refused."""
    scene, prior, _, _ = sphere_run
    z = scene.points[:, 2]
    h = 0.01
    cfg = preset("fast").replace(proposals={"n_init": (24,), "min_point_height": h},
                                 steps={"t1": 3, "t2": 2, "end_step": 2})
    res = run_em(scene, prior, cfg, seed=3)
    tr = res.trace
    assert (z[tr.prop_anchor] >= h).all() and (z[np.unique(tr.row_samples)] >= h).all()
    assert len(res.instances) >= 1 and all((z[m] >= h).all() for m in res.instances.masks)
    m = ious(res.instances, np.where(z >= h, scene.instance, 0))
    assert (m.max(axis=0) >= 0.8).sum() >= 1  # a sphere found, its points above the plane
    plain = run_em(scene, prior, cfg.replace(proposals={"min_point_height": None}), seed=3)
    assert (z[np.unique(plain.trace.row_samples)] < h).any()  # the method's crops hold table points
    none = run_em(scene, prior, cfg.replace(proposals={"min_point_height": float(z.max()) + 1.0}), seed=3)
    assert len(none.instances) == 0
    # a scan whose support plane is not at z = 0 (its origin a metre above the table) keeps every point, said once
    from efem_viz.data.scene import Scene

    low = Scene.create("low", scene.points - np.array([0.0, 0.0, 1.0], np.float32), normals=scene.normals,
                       instance=scene.instance)
    with caplog.at_level(logging.WARNING, logger="efem_viz.em.solver"):
        kept = run_em(low, prior, cfg, seed=3)
    assert "not its support plane" in caplog.text and "low:" in caplog.text
    uncut = run_em(low, prior, cfg.replace(proposals={"min_point_height": None}), seed=3)
    np.testing.assert_array_equal(kept.trace.row_samples, uncut.trace.row_samples)  # the same run as without a cut
    assert len(kept.instances) == len(uncut.instances)
    for bad in (float("nan"), float("-inf"), "2 cm"):
        with pytest.raises(ValueError, match="min_point_height"):
            preset("fast").replace(proposals={"min_point_height": bad})


def test_cancel_raises(sphere_run: tuple) -> None:
    scene, prior, _, _ = sphere_run
    ev = threading.Event()
    seen: list[int] = []

    def on_step(s: StepInfo) -> None:
        seen.append(s.step)
        if s.step == 1:
            ev.set()

    with pytest.raises(EMCancelled):
        run_em(scene, prior, preset("fast").replace(proposals={"n_init": (16,)}), on_step=on_step, cancel=ev)
    assert seen == [-1, 0, 1]


def test_bad_inputs_raise_clear_errors(sphere_run: tuple) -> None:
    scene, prior, _, _ = sphere_run
    with pytest.raises(ValueError, match="no encode"):
        run_em(scene, object(), preset("fast"))
    with pytest.raises(ValueError, match="n_init"):
        preset("fast").replace(proposals={"n_init": ()})
    with pytest.raises(ValueError, match="CUDA|cuda"):
        import torch

        if torch.cuda.is_available():
            pytest.skip("CUDA present")
        run_em(scene, prior, preset("fast"), device="cuda")


def test_episodes_reseed_only_unassigned_points(sphere_run: tuple) -> None:
    scene, prior, _, _ = sphere_run
    cfg = preset("fast").replace(proposals={"n_init": (40, 30)}, steps={"t1": 4, "t2": 2, "end_step": 3})
    res = run_em(scene, prior, cfg, seed=2)
    tr = res.trace
    assert tr.num_proposals == 70
    ep1 = np.flatnonzero(tr.prop_episode == 1)
    if len(ep1) == 0:
        pytest.skip("episode 1 skipped (too few unassigned points)")
    taken = np.concatenate([res.instances.masks[k] for k in range(len(res.instances))
                            if tr.prop_episode[res.instances.ids[k]] == 0])
    assert not np.isin(tr.prop_anchor[ep1], taken).any()
    assert np.array_equal(np.sort(tr.episode_unavailable[tr.episode_unavailable_offsets[1]:]), np.unique(taken))
    assert tr.step_local.tolist() == list(range(6)) * 2 or tr.num_steps < 12


def test_phase_two_rules_see_each_rows_phase_one_review_coverage() -> None:
    """`EMConfig.elimination.inclusion_by` = "confidence" needs each live row's review coverage: the solver hands
    the step rules the phase-1 review's coverage of exactly the rows alive in every phase-2 step (none in phase 1), and
    a solve with that mode runs through and finds each sphere once."""
    from efem_viz.em.rules import STEP_RULES, StepContext, StepRule

    scene = make_sphere_scene(seed=11)
    prior = make_sphere_prior()
    seen: list[tuple[int, int, np.ndarray | None, int]] = []

    def record(ctx: StepContext) -> list:
        seen.append((ctx.phase, ctx.step, None if ctx.coverage is None else ctx.coverage.copy(), len(ctx.inliers)))
        return []

    cfg = preset("fast").replace(proposals={"n_init": (64,)}, elimination={"inclusion": "score",
                                                                           "inclusion_by": "confidence"})
    res = run_em(scene, prior, cfg, seed=5, step_rules=(StepRule("record", record), *STEP_RULES))
    tr = res.trace
    assert [p for p, *_ in seen] == [1] * cfg.steps.t1 + [2] * cfg.steps.t2
    assert all(cov is None for p, _, cov, _ in seen if p == 1)
    for phase, step, cov, rows in seen:
        if phase == 2:
            assert cov is not None and len(cov) == rows
            ids, _ = tr.alive_scores(step)
            want = [next(r.coverage for r in tr.reviews(int(i)) if r.phase == 1) for i in ids]
            np.testing.assert_allclose(cov, want)
    best = ious(res.instances, scene.instance).max(axis=0)
    assert (best >= 0.5).all()


# ---------------------------------------------------------------------------------------------- random ShapePrior
def test_random_shape_prior_smoke() -> None:
    import torch

    from efem_viz.prior.model import PriorConfig, ShapePrior

    torch.manual_seed(0)
    prior = ShapePrior(PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                                   center_hidden=8, n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=1),
                       name="rand").eval()
    scene = make_sphere_scene(seed=1, radii=(0.05, 0.05))
    cfg = preset("fast").replace(proposals={"n_init": (24,)},
                                 steps={"t1": 3, "t2": 2, "end_step": 2, "tau_d": (5.0, 5.0)},
                                 elimination={"min_size": 1},
                                 review={"scale_horizontal": (0.0, 100.0), "scale_height": (0.0, 100.0),
                                         "mesh_resolution": 16, "n_store": 200})
    steps: list[StepInfo] = []
    res = run_em(scene, prior, cfg, seed=0, on_step=steps.append)
    tr = res.trace
    assert len(steps) == tr.num_steps + 1 and tr.num_steps >= 1  # the proposals drawn, then every step
    assert np.all(np.diff(tr.active_count) <= 0)
    for e in tr.events():
        assert e.reason in ("proposal too small", "duplicated", "included", "includes a better fit", "scale-fail",
                            "pose-fail", "survive")
    assert (tr.death_reason >= 0).all()  # every proposal ended with a recorded reason
    assert tr.row_R.shape[1:] == (16, 3) and tr.row_samples.shape[1] == 64
    assert res.timings["encoded_sets"] == tr.row_offsets[-1]


# ---------------------------------------------------------------------------------------------- results
def _toy_instances() -> Instances:
    rows = []
    for k, (mask, conf) in enumerate([([0, 1, 2, 3], 0.9), ([3, 4, 5], 0.2), ([5, 6], 0.5)]):
        rows.append({
            "proposal_id": 10 + k, "mask": np.array(mask), "confidence": conf, "R": np.eye(3),
            "center": np.zeros(3), "scale": 0.1, "obb_center": np.zeros(3), "obb_axes": np.eye(3),
            "obb_half_extents": np.ones(3), "mesh_vertices": np.zeros((3, 3)), "mesh_faces": np.array([[0, 1, 2]]),
            "coverage": 0.5, "stationary": conf, "db_sim": 0.3,
        })
    return Instances.from_rows(rows, category="mug")


def test_instances_above_and_label_array() -> None:
    inst = _toy_instances()
    hi = inst.above(0.5)
    assert hi.ids.tolist() == [10, 12] and len(inst) == 3  # a view; the original is untouched
    assert inst.above(0.95).label_array(8).tolist() == [0] * 8
    lab = inst.label_array(8)
    # point 3: instance 1 (0.9) beats instance 2 (0.2); point 5: instance 3 (0.5) beats instance 2
    assert lab.tolist() == [1, 1, 1, 1, 2, 3, 3, 0]
    with pytest.raises(ValueError, match="n_points"):
        inst.label_array(4)


def test_scannet_export_readable(tmp_path: Path) -> None:
    inst = _toy_instances()
    txt = inst.to_scannet(tmp_path, "scene0", 8)
    lines = txt.read_text().splitlines()
    assert len(lines) == 3
    for k, line in enumerate(lines):
        rel, label, conf = line.split()
        assert rel == f"pred_mask/scene0_{k:03d}.txt" and label == "1"
        assert conf == f"{inst.confidence[k]:.4f}"
        m = np.loadtxt(tmp_path / rel, dtype=int)
        assert m.shape == (8,)
        assert np.flatnonzero(m).tolist() == inst.masks[k].tolist()
    from efem_viz.eval import load_scannet_predictions

    (pred,) = load_scannet_predictions(tmp_path)
    assert pred.name == "scene0"
    assert [np.flatnonzero(m).tolist() for m in pred.masks] == [m.tolist() for m in inst.masks]
    assert np.allclose(pred.confidences, np.round(inst.confidence, 4))


def test_colored_ply_round_trip(sphere_run: tuple, tmp_path: Path) -> None:
    from efem_viz.data.io import load_scene

    scene, _, res, _ = sphere_run
    p = res.instances.to_colored_ply(scene, tmp_path / "seg.ply")
    back = load_scene(p)
    assert back.num_points == scene.num_points
    assert np.array_equal(back.instance, res.instances.label_array(scene.num_points))
    assert len(np.unique(back.colors[back.instance > 0], axis=0)) == len(res.instances)


# ---------------------------------------------------------------------------------------------- CLI
def test_segment_cli(tmp_path: Path) -> None:
    import torch

    from efem_viz import cli
    from efem_viz.data.io import save_scene
    from efem_viz.prior.model import PriorConfig, ShapePrior, save_prior

    torch.manual_seed(0)
    prior = ShapePrior(PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                                   center_hidden=8, n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=1),
                       name="rand")
    pt = save_prior(prior, tmp_path / "rand.pt")
    scene = make_sphere_scene(seed=2, radii=(0.05,))
    sp = save_scene(scene, tmp_path / "one.npz")
    out = tmp_path / "out"
    rc = cli.main(["segment", str(sp), "--prior", str(pt), "--out", str(out), "--preset", "fast",
                   "--proposals", "8", "--seed", "3"])
    assert rc == 0
    res = EMResult.load(out / "one.efem.npz")
    assert res.trace.num_proposals == 8 and res.seed == 3
    assert (out / "scannet" / "one.txt").is_file()
    assert (out / "one.seg.ply").is_file()


def test_evaluate_cli_reads_efem_results_beside_unrelated_txt(sphere_run: tuple, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A README/LICENSE .txt next to `<scene>.efem.npz` (as in sample_scenes/) must not select the ScanNet reader."""
    from efem_viz import cli
    from efem_viz.data.io import save_scene

    scene, _, res, _ = sphere_run
    save_scene(scene, tmp_path / f"{scene.name}.ply")
    res.save(tmp_path / f"{scene.name}.efem.npz")
    (tmp_path / "LICENSE.txt").write_text("Some licence text, not a ScanNet prediction list.\n")
    assert cli.main(["evaluate", str(tmp_path), "--gt", str(tmp_path / f"{scene.name}.ply"),
                     "--classes", "sphere"]) == 0
    assert "100.0" in capsys.readouterr().out  # every sphere found: AP50 = 100


# ---------------------------------------------------------------------------------------------- trained prior
def _mug_scene() -> object:
    """Three upright test-split mugs on a table (synthetic scan, seeded)."""
    from efem_viz.data.synth import generate_scene

    return generate_scene("z", seed=4242, n_objects=3, mode="tsdf", distractors=False)


def _shipped_prior_or_skip() -> object:
    """The shipped mug prior with its codebook, or skip when the weights are missing (a checkout without LFS)."""
    if not WEIGHTS.is_file():
        pytest.skip(f"trained mug prior not found at {WEIGHTS} (train it first)")
    from efem_viz.prior.model import load_prior

    prior = load_prior(WEIGHTS)
    assert prior.codebook is not None, "the shipped prior must come with the codebook built from it"
    return prior


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="the target (every mug at IoU >= 0.7) is not met by the CPU-trained prior: "
                   "measured per-mug best IoU 0.586 / 0.928 / 0.877 (iteration-29000 prior, its tau_out 0.07). "
                   "strict: once it passes, drop this marker")
def test_trained_prior_finds_mugs() -> None:
    prior = _shipped_prior_or_skip()
    scene = _mug_scene()
    res = run_em(scene, prior, preset("fast").replace(proposals={"n_init": (100,)}), seed=0)
    m = ious(res.instances, scene.instance)
    assert m.shape[1] == len(scene.instance_ids())
    best = m.max(axis=0) if len(res.instances) else np.zeros(m.shape[1])
    assert (best >= 0.7).all(), f"per-object best IoU {np.round(best, 3)}"


def test_shipped_prior_regression_each_mug_found_once() -> None:
    """EM regression with the prior as shipped now (always runs; tolerances set from its measured behaviour).

    Measured with the iteration-29000 prior (2026-12-01; calibrated IoU 0.556 on 96 validation mugs, 1-12 views; its
    calibrated output band tau_out = 0.07), fast preset, 100 proposals, seed 0: 3 instances with confidences 0.55 /
    0.52 / 0.93, one per mug; per-mug best IoU 0.586 / 0.928 / 0.877; AP50 = AP25 = 1, AP 0.70. (The earlier
    iteration-21000 prior: 0.654 / 0.726 / 0.836, AP 0.49.)
    On an Intel Xeon with AVX-512 (2026-12-04) the same run's float rounding gives 0.494 / 0.915 / 0.910: the weakest
    mug sits at the 0.5 line, one machine above it, one below. The bars hold on both: every mug covered at
    IoU >= 0.45, AP25 = 1 (each mug's best match outranks every false positive), and the instances with
    confidence >= 0.1 each claim a different mug.
    `test_trained_prior_finds_mugs` holds the issue's IoU >= 0.7 bar.
    """
    from efem_viz.eval import evaluate_scene

    prior = _shipped_prior_or_skip()
    scene = _mug_scene()
    res = run_em(scene, prior, preset("fast").replace(proposals={"n_init": (100,)}), seed=0)
    m = ious(res.instances, scene.instance)
    assert m.shape[1] == 3 and 3 <= m.shape[0] <= 5, f"expected 3-5 instances for 3 mugs, got {m.shape[0]}"
    assert res.config.output.tau_out == pytest.approx(0.07), "the shipped prior's calibrated mask band"
    assert (m.max(axis=0) >= 0.45).all(), f"per-mug best IoU {np.round(m.max(axis=0), 3)}"
    confident = res.instances.confidence >= 0.1
    claimed = m[confident].argmax(axis=1)
    assert len(set(claimed.tolist())) == len(claimed), "two confident instances claim the same mug"
    ev = evaluate_scene([np.asarray(k) for k in res.instances.masks], res.instances.confidence, scene.instance)
    assert ev.ap25 == pytest.approx(1.0), f"AP25 {ev.ap25:.3f} (AP50 {ev.ap50:.3f})"


def test_a_family_prior_names_each_instance_by_its_codebook_class() -> None:
    """A family prior (kitchen: one prior over mugs, bowls, bottles, cans) gives each accepted instance the class
    of the codebook entries its pose search retrieved, not the prior's name: here the shipped prior's codebook
    relabelled as one class "cup" of a two-class family."""
    prior = _shipped_prior_or_skip()
    cb = prior.codebook
    prior.codebook = dataclasses.replace(cb, class_id=np.ones(len(cb), np.int32),
                                         meta={**cb.meta, "classes": ["mug", "cup"]})
    try:
        res = run_em(_mug_scene(), prior, preset("fast").replace(proposals={"n_init": (40,)}), seed=0)
    finally:
        prior.codebook = cb
    assert len(res.instances) >= 1
    assert set(res.instances.category.tolist()) == {"cup"}
    plain = run_em(_mug_scene(), prior, preset("fast").replace(proposals={"n_init": (40,)}), seed=0)
    assert set(plain.instances.category.tolist()) == {"mug"}


@pytest.mark.parametrize("encoder_dtype", [None, "float32"])
def test_encoder_dtype_keeps_the_encoder_in_float32_beside_a_bf16_decoder(encoder_dtype: str | None) -> None:
    """`matmul_dtype="bfloat16"` runs the EM steps' encoder and decoder under bf16 autocast; `encoder_dtype=
    "float32"` takes the encoder out of it (its fused float32 kernels stay on) and leaves the decoder in bf16."""
    import torch

    scene, prior = make_sphere_scene(seed=11), make_sphere_prior()
    seen: dict[str, set[bool]] = {"encode": set(), "decode": set()}
    encode, sdf, sdf_and_normals = prior.encode, prior.sdf, prior.sdf_and_normals

    def spy(kind: str, fn: object) -> object:
        def call(*a: object, **kw: object) -> object:
            seen[kind].add(torch.is_autocast_enabled("cpu"))
            return fn(*a, **kw)  # type: ignore[operator]
        return call

    prior.encode, prior.sdf = spy("encode", encode), spy("decode", sdf)  # type: ignore[method-assign]
    prior.sdf_and_normals = spy("decode", sdf_and_normals)  # type: ignore[method-assign]
    cfg = preset("fast").replace(proposals={"n_init": (16,)}, compute={"matmul_dtype": "bfloat16",
                                                                       "encoder_dtype": encoder_dtype})
    res = run_em(scene, prior, cfg, seed=5)
    assert res.config.compute.encoder_dtype == encoder_dtype
    assert True in seen["decode"]  # the E-steps (the reviews decode in float32)
    assert seen["encode"] == ({False} if encoder_dtype == "float32" else {True})
    with pytest.raises(ValueError, match="encoder_dtype"):
        preset("fast").replace(compute={"encoder_dtype": "float16"})


def test_bf16_solve_finds_the_same_mugs_and_replays_in_its_precision(tmp_path: Path) -> None:
    """compute.matmul_dtype="bfloat16": the regression scene's bars hold (those of
    `test_shipped_prior_regression_each_mug_found_once`: the weakest mug sits at the 0.5 line, 0.493 here with
    the one-pass decoder on an AVX-512 Intel), the trace records the precision through a save/load round trip,
    and replay re-derives each step's inliers in that precision."""
    from efem_viz.eval import evaluate_scene

    prior = _shipped_prior_or_skip()
    scene = _mug_scene()
    res = run_em(scene, prior, preset("fast").replace(proposals={"n_init": (100,)},
                                                      compute={"matmul_dtype": "bfloat16"}), seed=0)
    m = ious(res.instances, scene.instance)
    assert (m.max(axis=0) >= 0.45).all(), f"per-mug best IoU {np.round(m.max(axis=0), 3)}"
    ev = evaluate_scene([np.asarray(k) for k in res.instances.masks], res.instances.confidence, scene.instance)
    assert ev.ap25 == pytest.approx(1.0), f"AP25 {ev.ap25:.3f} (AP50 {ev.ap50:.3f})"
    assert res.config.compute.matmul_dtype == "bfloat16"
    back = EMResult.load(res.save(tmp_path), scene=scene, prior=prior)
    assert back.config.compute.matmul_dtype == "bfloat16"
    tr = back.trace
    pid = int(back.instances.ids[0])
    for t in (0, tr.last_step(pid)):
        w = back.replay.weights_out(pid, t, full_resolution=False)
        assert int((w > 1e-30).sum()) == int(tr.row_inliers[tr.row_of(pid, t)])
    with pytest.raises(ValueError, match="matmul_dtype"):
        preset("fast").replace(compute={"matmul_dtype": "float16"})


def test_instances_npz_round_trip_including_empty() -> None:
    for inst in (_toy_instances(), Instances.empty()):
        back = Instances.from_npz_dict(inst.to_npz_dict())
        assert len(back) == len(inst)
        assert np.array_equal(back.ids, inst.ids) and np.array_equal(back.confidence, inst.confidence)
        assert all(np.array_equal(a, b) for a, b in zip(back.masks, inst.masks))
        assert all(np.array_equal(a, b) for a, b in zip(back.mesh_faces, inst.mesh_faces))
        assert back.R.shape == (len(inst), 3, 3)
        assert back.label_array(10).shape == (10,)


def test_instance_boxes_contain_their_meshes(sphere_run: tuple) -> None:
    _, _, res, _ = sphere_run
    for k in range(len(res.instances)):
        box = res.instances.obb(k)
        assert box.corners.shape == (8, 3)
        verts = res.instances.mesh_vertices[k]
        # the box is fitted to surface samples of the mesh, so the mesh lies inside up to sampling slack
        assert box.contains(verts, tol=0.005).mean() > 0.99


def test_sphere_run_scores_full_ap_with_eval(sphere_run: tuple) -> None:
    from efem_viz.eval import SceneGroundTruth, evaluate, prediction_from_instances

    scene, _, res, _ = sphere_run
    pred = prediction_from_instances(res.instances, name=scene.name, class_names=("sphere",))
    ev = evaluate([pred], [SceneGroundTruth.from_scene(scene)], class_names=("sphere",))
    assert ev.ap50 == pytest.approx(1.0) and ev.ap25 == pytest.approx(1.0)


def test_scene_below_min_size_gives_empty_result(tmp_path: Path) -> None:
    from efem_viz.data.scene import Scene

    pts = np.random.default_rng(0).uniform(-0.1, 0.1, (100, 3))
    scene = Scene.create("tiny", pts, normals=np.tile([0.0, 0.0, 1.0], (100, 1)))
    res = run_em(scene, make_sphere_prior(), preset("fast"))
    assert res.trace.num_steps == 0 and len(res.instances) == 0
    back = EMResult.load(res.save(tmp_path))
    assert back.trace.num_steps == 0 and len(back.instances) == 0
    assert back.instances.label_array(100).max() == 0


# ---------------------------------------------------------------------------------------------- several priors
@pytest.fixture(scope="module")
def mixed_run() -> tuple[object, EMResult]:
    from efem_viz.data.io import load_scene
    from efem_viz.prior import load_priors
    from efem_viz.prior.analytic import add_spheres

    scene = add_spheres(load_scene(sample_scene("syn_z_0")),
                        [0.045, 0.04], seed=0)
    return scene, run_em(scene, priors=load_priors(["mug", "sphere"]), cfg=preset("fast"), seed=0)


def test_two_priors_find_both_kinds_with_their_categories(mixed_run: tuple) -> None:
    scene, res = mixed_run
    gt, cats = scene.instance, scene.categories
    inst = res.instances
    m = ious(inst, gt)
    gt_ids = [g for g in np.unique(gt) if g > 0]
    assert set(inst.category) == {"mug", "sphere"}
    for j, g in enumerate(gt_ids):
        kind = cats[g]
        own = np.flatnonzero(inst.category == kind)
        assert m[own, j].max() >= (0.9 if kind == "sphere" else 0.5), f"{kind} {g} not found by its prior"
        other = np.flatnonzero(inst.category != kind)
        # the joint review removed the other category's fits of this object (duplicates across categories)
        assert len(other) == 0 or m[other, j].max() < 0.5, f"{kind} {g} also claimed by the other prior"
    # deaths across categories: proposals of each prior died as duplicates of the other's
    tr = res.trace
    assert tr.prior_names == ("mug", "sphere")
    cross = [e for e in tr.events() if e.reason in ("duplicated", "included")
             and tr.category_of(e.proposal_id) != tr.category_of(e.partner)]
    assert cross
    assert [c.name for c in res.categories] == ["mug", "sphere"]
    assert res.categories[0].tau_out == pytest.approx(0.07) and res.categories[1].tau_out == pytest.approx(0.04)


def test_two_prior_result_round_trips_and_replays_with_each_prior(mixed_run: tuple, tmp_path: Path) -> None:
    from efem_viz.prior import load_priors

    scene, res = mixed_run
    back = EMResult.load(res.save(tmp_path), scene=scene, prior=load_priors(["mug", "sphere"]))
    assert back.trace.prior_names == res.trace.prior_names
    assert np.array_equal(back.trace.prop_prior, res.trace.prop_prior)
    assert back.categories == res.categories and list(back.instances.category) == list(res.instances.category)
    for kind in ("mug", "sphere"):
        k = int(np.flatnonzero(res.instances.category == kind)[0])
        pid = int(res.instances.ids[k])
        v = back.replay.view(pid, res.trace.num_steps - 1)
        assert v.category == kind and v.mesh is not None and len(v.mesh.faces)
        # the replayed output weights reproduce the recorded inliers with this proposal's own prior
        t = res.trace.last_step(pid)
        w = back.replay.weights_out(pid, t, full_resolution=False)
        assert int((w > 1e-30).sum()) == int(res.trace.row_inliers[res.trace.row_of(pid, t)])
        # the live replay (trace as recorded) and the replay of the saved file decode the same bytes
        assert np.array_equal(res.replay.weights_out(pid, t, full_resolution=False), w)
    with pytest.raises(ValueError, match="prior"):
        back.bind(prior=load_priors(["mug"])[0])
    with pytest.raises(ValueError, match="in this order"):  # a swapped list must not decode mugs with the sphere
        back.bind(prior=load_priors(["sphere", "mug"]))


def test_run_em_prior_arguments_are_checked() -> None:
    scene = make_sphere_scene(seed=1, radii=(0.05,))
    sphere = make_sphere_prior()
    with pytest.raises(ValueError, match="not both"):
        run_em(scene, sphere, priors=[sphere])
    with pytest.raises(ValueError, match="not both"):
        run_em(scene)
    with pytest.raises(ValueError, match="distinct category"):
        run_em(scene, priors=[sphere, make_sphere_prior()])


def test_a_malformed_recorded_camera_is_said_on_the_cli_and_in_the_result(tmp_path: Path) -> None:
    """a scene whose recorded capture camera cannot be used runs without the free-space check,
    and says so: one warning line on the full CLI naming the problem, and the saved result's `warnings`."""
    import os
    import subprocess
    import sys

    from efem_viz.data.io import save_scene

    scene = make_sphere_scene(seed=2, radii=(0.05,))
    K = [[0.0, 0.0, 159.5], [0.0, 500.0, 119.5], [0.0, 0.0, 1.0]]  # zero focal length
    prov = {**dict(scene.provenance or {}), "K": K, "T_world_camera": np.eye(4).tolist(), "image_size": [320, 240]}
    bad = save_scene(scene.replace(provenance=prov), tmp_path / "bad.npz")
    none = save_scene(scene, tmp_path / "none.npz")
    root = Path(__file__).resolve().parents[1]
    for path, expect in ((bad, True), (none, False)):
        out = tmp_path / f"out_{path.stem}"
        proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(path), "--prior", "sphere",
                               "--preset", "real", "--proposals", "8", "--out", str(out)], capture_output=True,
                              text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(root)}, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "camera is unusable" in ln]
        res = EMResult.load(out / f"{path.stem}.efem.npz")
        if expect:
            assert len(lines) == 1 and "focal lengths" in lines[0], proc.stderr[-2000:]
            assert len(res.warnings) == 1 and "free-space check is off" in res.warnings[0]
        else:
            assert not lines and res.warnings == ()
