"""EMTrace: consistency of the recorded run, save/load round trip, on-demand re-derivation of views."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from efem_viz.em import EMResult, preset, run_em
from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene
from efem_viz.em.rules import reason_names


@pytest.fixture(scope="module")
def run() -> tuple[object, object, EMResult]:
    import torch

    torch.set_num_threads(1)
    scene = make_sphere_scene(seed=3)
    prior = make_sphere_prior()
    cfg = preset("fast").replace(proposals={"n_init": (48,)}, steps={"t1": 6, "t2": 3, "end_step": 4})
    return scene, prior, run_em(scene, prior, cfg, seed=7)


def test_trace_shapes_and_bookkeeping(run: tuple) -> None:
    scene, _, res = run
    tr = res.trace
    assert tr.num_steps == 9
    assert tr.num_proposals == 48
    assert tr.active_count[0] == 48
    assert np.all(np.diff(tr.active_count) <= 0)
    for t in range(tr.num_steps):
        ids = tr.alive(t)
        assert np.all(np.diff(ids) > 0)
        assert len(ids) == tr.active_count[t]  # rows of step t = the proposals alive after step t − 1
        # every proposal that is not alive at t + 1 died at step t (or t is the last step)
        if t + 1 < tr.num_steps:
            gone = np.setdiff1d(ids, tr.alive(t + 1))
            assert all(tr.death_step[g] == t for g in gone)
    assert tr.row_samples.shape == (int(tr.row_offsets[-1]), 256)
    assert tr.row_samples.dtype == np.int32 and tr.row_samples.max() < scene.num_points
    assert list(tr.step_phase) == [1] * 6 + [2] * 3
    assert (tr.schedule[:, 0] > 0).all()
    assert np.all(np.diff(tr.step_elapsed) >= 0) and len(tr.step_elapsed) == tr.num_steps


def test_events_are_complete_and_ordered(run: tuple) -> None:
    _, _, res = run
    tr = res.trace
    ev = tr.events()
    assert len(ev) == tr.num_proposals  # every proposal dies or is accepted
    assert [e.step for e in ev] == sorted(e.step for e in ev)
    assert {e.reason for e in ev} <= set(reason_names()) and tr.reason_names == reason_names()
    accepted = [e.proposal_id for e in ev if e.reason == "survive"]
    assert sorted(accepted) == sorted(res.instances.ids.tolist())
    for e in ev:
        if e.reason == "duplicated or included":
            assert e.partner >= 0 and 0 <= e.ratio <= 1.0 + 1e-6
            # the partner was alive at that step
            assert e.partner in tr.alive(e.step)
        if e.reason == "proposal too small":
            assert e.ratio < res.config.elimination.min_size


def test_live_samples_are_the_samples_of_the_proposals_alive_after_the_step(run: tuple) -> None:
    _, _, res = run
    tr = res.trace
    for t in range(tr.num_steps):
        want = [tr.sample_indices(int(pid), t) for pid in tr.alive(t) if not tr.is_dead_at(int(pid), t)]
        expect = np.unique(np.concatenate(want)) if want else np.zeros(0, np.int64)
        got = tr.live_samples(t)
        np.testing.assert_array_equal(got, expect)
        assert got.dtype == np.int64
    t = tr.num_steps - 1  # one episode: after the last step only the accepted proposals live
    assert len(res.instances) > 0
    np.testing.assert_array_equal(tr.live_samples(t), np.unique(np.concatenate(
        [tr.sample_indices(int(p), t) for p in res.instances.ids])))


def test_the_viewers_questions_are_trace_methods(run: tuple) -> None:
    _, _, res = run
    tr = res.trace
    for t in (0, tr.num_steps - 1):
        ids, scores = tr.alive_scores(t)
        assert ids.dtype == np.int64 and scores.dtype == np.float64
        np.testing.assert_array_equal(ids, tr.alive(t))
        np.testing.assert_array_equal(scores, tr.row_stationary[tr.rows(t)])
        pid = int(ids[0])
        r = tr.row_of(pid, t)
        assert r is not None
        np.testing.assert_array_equal(tr.sample_indices(pid, t), tr.row_samples[r])
        np.testing.assert_array_equal(tr.center_at(pid, t), tr.row_center[r])
    for e in tr.events():
        dead = e.reason != "survive"
        assert tr.is_dead_at(e.proposal_id, e.step) == dead and not tr.is_dead_at(e.proposal_id, e.step - 1)
        last = tr.last_step(e.proposal_id)
        np.testing.assert_array_equal(tr.center_at(e.proposal_id, tr.num_steps - 1),
                                      tr.row_center[tr.row_of(e.proposal_id, last)])
        if e.step + 1 < tr.num_steps and dead:
            assert tr.sample_indices(e.proposal_id, e.step + 1) is None


def test_reviews_recorded_at_phase_ends(run: tuple) -> None:
    _, _, res = run
    tr = res.trace
    assert set(np.unique(tr.rev_step).tolist()) <= {5, 8}
    for pid in res.instances.ids:
        recs = tr.reviews(int(pid))
        assert [r.phase for r in recs] == [1, 2]
        final = recs[-1]
        assert final.scale_pass and final.pose_pass
        k = int(np.flatnonzero(res.instances.ids == pid)[0])
        assert np.array_equal(final.mask, res.instances.masks[k])
        assert len(final.mesh_faces) > 0
        # float16 relative vertices are accurate to well under a millimetre
        assert np.abs(final.mesh_vertices - res.instances.mesh_vertices[k]).max() < 1e-3


def test_every_review_measure_is_declared_once_and_round_trips(run: tuple, tmp_path: Path) -> None:
    """`REVIEW_COLUMNS` is the one declaration of what a review stores: its rows are exactly the `ReviewRecord`
    fields (but the prior, which the proposal table gives) and the trace's review arrays; every record read back
    from a saved trace equals the recorded one, field by field; the replay's review scores are the table's."""
    import dataclasses

    from efem_viz.em.replay import TraceReplay
    from efem_viz.em.rules import REVIEW_COLUMNS, ReviewRecord
    from efem_viz.em.trace import EMTrace

    assert [c.field for c in REVIEW_COLUMNS] == [f for f in ReviewRecord._fields if f != "prior"]
    declared = {n for c in REVIEW_COLUMNS for n in (c.trace, c.offsets) if n}
    assert declared == {f.name for f in dataclasses.fields(EMTrace) if f.name.startswith("rev_")}
    scene, prior, res = run
    back = EMResult.load(res.save(tmp_path / "r.efem.npz")).trace
    for v in range(len(res.trace.rev_id)):
        a, b = res.trace.review_record(v), back.review_record(v)
        for name in ReviewRecord._fields:
            x, y = getattr(a, name), getattr(b, name)
            assert type(x) is type(y), name
            assert np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True), name
    pid = int(res.instances.ids[0])
    step = int(res.trace.last_step(pid))
    scores = TraceReplay(back, scene, prior).view(pid, step, mesh=False).scores
    v = int(np.flatnonzero((back.rev_id == pid) & (back.rev_step == step))[0])
    assert scores["radius_horizontal"] == pytest.approx(float(back.rev_radii[v, 0]))
    assert scores["coverage"] == pytest.approx(float(back.rev_coverage[v]))
    assert "seen_through" not in scores  # not measured in this run: not shown
    named = {n for c in REVIEW_COLUMNS if not c.optional for n in c.scores}
    assert named <= set(scores) and {"stationary", "inliers"} <= set(scores)


def test_confidence_matches_recorded_scores(run: tuple) -> None:
    _, _, res = run
    tr = res.trace
    for k, pid in enumerate(res.instances.ids):
        last = tr.last_step(int(pid))
        r = tr.row_of(int(pid), last)
        cov = tr.reviews(int(pid))[-1].coverage
        expect = tr.row_stationary[r] * min(cov, 0.4) / 0.4
        assert res.instances.confidence[k] == pytest.approx(expect, rel=1e-5)


def test_weights_rederivation_matches_recorded_inliers(run: tuple) -> None:
    _, _, res = run
    tr, rp = res.trace, res.replay
    pid = int(res.instances.ids[0])
    for t in range(tr.num_steps):
        w = rp.weights_out(pid, t, full_resolution=False)
        r = tr.row_of(pid, t)
        # inliers pass both truncations (weight ≥ exp(−α_D τ_D − α_N τ_N)); outliers get ≤ exp(−100)
        assert int((w > 1e-30).sum()) == int(tr.row_inliers[r])
    # the first step's input weights are the crop mask around the anchor
    w0 = rp.weights_in(pid, 0)
    assert set(np.unique(w0).tolist()) <= {0.0, 1.0}
    anchor = tr.prop_anchor[pid]
    pts = rp.points()
    inside = np.linalg.norm(pts - pts[anchor], axis=1) < tr.prop_r_init[pid]
    assert np.array_equal(w0 > 0, inside)
    # later input weights are the previous step's output weights
    assert np.array_equal(rp.weights_in(pid, 3), rp.weights_out(pid, 2))


def test_view_contents_and_dead_proposals(run: tuple) -> None:
    scene, _, res = run
    tr, rp = res.trace, res.replay
    pid = int(res.instances.ids[0])
    v = rp.view(pid, 2)
    assert v.weights.shape == (scene.num_points,) and v.weights.dtype == np.float32
    assert np.array_equal(v.sampled_points, scene.points[v.sample_idx])
    assert v.alive and v.death is not None and v.death[1] == "survive"
    assert v.mesh is not None and len(v.mesh.faces) > 0
    assert set(v.schedule) == {"alpha_d", "tau_d", "alpha_n", "tau_n"}
    # sampled points carry positive input weight (they were drawn from it)
    assert (v.weights[v.sample_idx] > 0).all()
    assert rp.view(pid, 2) is v  # cached
    dead = [e for e in tr.events() if e.reason == "proposal too small"]
    assert dead
    e = dead[0]
    dv = rp.view(e.proposal_id, tr.num_steps - 1, mesh=False)
    assert not dv.alive and dv.step == e.step and dv.death[1] == "proposal too small"
    with pytest.raises(ValueError, match="out of range"):
        rp.view(10_000, 0)


def test_save_load_round_trip(run: tuple, tmp_path: Path) -> None:
    scene, prior, res = run
    path = res.save(tmp_path)
    assert path.name == f"{scene.name}.efem.npz"
    back = EMResult.load(path)
    for k in res.trace._ARRAY_FIELDS:
        a, b = getattr(res.trace, k), getattr(back.trace, k)
        assert a.dtype == b.dtype, k
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), k
    assert back.config == res.config
    assert back.scene_name == scene.name and back.num_points == scene.num_points
    assert np.array_equal(back.instances.confidence, res.instances.confidence)
    assert all(np.array_equal(a, b) for a, b in zip(back.instances.masks, res.instances.masks))
    with pytest.raises(ValueError, match="needs the shape prior|no scene bound"):
        back.replay.view(int(res.instances.ids[0]), 1)
    back.bind(scene, prior)
    pid = int(res.instances.ids[-1])
    for step in (0, 4, res.trace.num_steps - 1):
        v1, v2 = res.replay.view(pid, step, mesh=False), back.replay.view(pid, step, mesh=False)
        assert np.array_equal(v1.weights, v2.weights)
        assert np.array_equal(v1.sample_idx, v2.sample_idx)
        assert v1.scores.keys() == v2.scores.keys() and v1.death == v2.death
        assert np.array_equal(list(v1.scores.values()), list(v2.scores.values()), equal_nan=True)
    # the file stays small: no dense per-step weights
    assert path.stat().st_size < 2_000_000


def test_load_rejects_other_files(tmp_path: Path) -> None:
    bad = tmp_path / "x.efem.npz"
    np.savez(bad, a=np.zeros(3))
    with pytest.raises(ValueError, match="not an EFEM result"):
        EMResult.load(bad)
    with pytest.raises(FileNotFoundError):
        EMResult.load(tmp_path / "missing.efem.npz")
    # corrupt, truncated or single-array files: a ValueError naming the file, never a raw numpy/zip error
    good = tmp_path / "good.npz"
    np.savez_compressed(good, kind=np.array("efem-result"), a=np.arange(100_000))
    single = tmp_path / "single.efem.npz"
    np.save(single.with_suffix(".npy"), np.zeros(3))
    single.write_bytes(single.with_suffix(".npy").read_bytes())
    cases = {"garbage": b"not a result\n", "empty": b"", "truncated": good.read_bytes()[:400],
             "single": single.read_bytes()}
    for name, content in cases.items():
        f = tmp_path / f"{name}.efem.npz"
        f.write_bytes(content)
        with pytest.raises(ValueError, match=f"{name}.efem.npz"):
            EMResult.load(f)


def test_working_set_run_records_full_resolution_indices() -> None:
    scene = make_sphere_scene(seed=4, radii=(0.05, 0.05))
    prior = make_sphere_prior()
    cfg = preset("fast").replace(proposals={"n_init": (32,)}, steps={"t1": 4, "t2": 2, "end_step": 3},
                                 compute={"work_voxel": 0.007})
    res = run_em(scene, prior, cfg, seed=1)
    tr = res.trace
    assert tr.work_idx is not None and len(tr.work_idx) < scene.num_points
    assert tr.work_min_size < cfg.elimination.min_size
    assert np.isin(tr.row_samples, tr.work_idx).all()
    assert np.isin(tr.prop_anchor, tr.work_idx).all()
    assert len(res.instances) == 2
    # output masks are at full resolution: they contain points outside the working set
    allmask = np.concatenate(res.instances.masks)
    assert (~np.isin(allmask, tr.work_idx)).any()
    pid = int(res.instances.ids[0])
    t = tr.num_steps - 1
    w_work = res.replay.weights_out(pid, t, full_resolution=False)
    w_full = res.replay.weights_out(pid, t)
    assert int((w_work > 1e-30).sum()) == int(tr.row_inliers[tr.row_of(pid, t)])
    on = np.zeros(scene.num_points, bool)
    on[tr.work_idx] = True
    assert np.allclose(w_full[on], w_work[on], atol=1e-6)
    assert (w_work[~on] == 0).all() and (w_full[~on] > 0).any()


def test_load_binds_scene_and_checks_size(run: tuple, tmp_path: Path) -> None:
    scene, prior, res = run
    path = res.save(tmp_path / "r.efem.npz")
    back = EMResult.load(path, scene=scene, prior=prior)
    pid = int(res.instances.ids[0])
    assert np.array_equal(back.replay.view(pid, 1, mesh=False).weights, res.replay.view(pid, 1, mesh=False).weights)
    other = make_sphere_scene(seed=99, radii=(0.05,))
    with pytest.raises(ValueError, match="points"):
        EMResult.load(path, scene=other)


def test_traces_saved_before_the_name_table_still_read(tmp_path: Path) -> None:
    """A trace written before traces carried their reason and prior names (codes index the legacy table) reads
    with the legacy names: made here from a bundled trace by mapping its codes and dropping the tables."""
    from efem_viz.em.rules import LEGACY_REASONS

    root = Path(__file__).resolve().parents[1] / "sample_scenes"
    with np.load(root / "syn_z_1.efem.npz") as z:
        data = {k: z[k] for k in z.files}
    names = json.loads(str(data.pop("trace/reason_names_json")))
    data.pop("trace/prior_names_json")
    legacy = {"duplicated": "duplicated or included", "included": "duplicated or included"}
    codes = data["trace/death_reason"]
    assert set(names[c] for c in codes[codes >= 0]) <= set(LEGACY_REASONS) | set(legacy)
    data["trace/death_reason"] = np.array([LEGACY_REASONS.index(legacy.get(names[c], names[c])) if c >= 0 else c
                                           for c in codes], codes.dtype)
    old = tmp_path / "syn_z_1.efem.npz"
    np.savez_compressed(old, **data)
    res = EMResult.load(old)
    # the prior's name comes from the result's one category (the prior the run's shapes are decoded with)
    assert res.trace.reason_names == LEGACY_REASONS and res.trace.prior_names == ("mug",)
    reasons = {e.reason for e in res.trace.events()}
    assert "survive" in reasons and "duplicated or included" in reasons and reasons <= set(LEGACY_REASONS)
    assert res.trace.category_of(int(res.instances.ids[0])) == "mug"
    from efem_viz.em.trace import EMTrace

    assert EMTrace.from_npz_dict(data).prior_names == ()  # the trace alone records none


def test_a_custom_rule_is_recorded_under_its_name_and_survives_a_round_trip(tmp_path: Path) -> None:
    from efem_viz.em.rules import STEP_RULES, Kill, StepContext, StepRule

    def low_stationary(ctx: StepContext) -> list[Kill]:
        if ctx.phase != 1:
            return []
        return [Kill(int(r), "low stationary", -1, float(ctx.stationary[r]))
                for r in np.flatnonzero(ctx.active & (ctx.stationary < 0.2))]

    scene = make_sphere_scene(seed=3, radii=(0.05, 0.045))
    cfg = preset("fast").replace(proposals={"n_init": (24,)}, steps={"t1": 3, "t2": 1, "end_step": 2})
    res = run_em(scene, make_sphere_prior(), cfg, seed=2,
                 step_rules=(*STEP_RULES, StepRule("low stationary", low_stationary)))
    assert "low stationary" in res.trace.reason_names
    back = EMResult.load(res.save(tmp_path))
    assert back.trace.reason_names == res.trace.reason_names
    assert [tuple(e) for e in back.trace.events()] == [tuple(e) for e in res.trace.events()]
