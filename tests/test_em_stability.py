"""The real-scan stability work: depth-sensor model, one-proposal probe, M-step without
replacement, size rule on the SDF band / density-relative, plain-text batch progress."""

from __future__ import annotations

import io

import numpy as np
import pytest

from efem_viz.em.config import preset
from efem_viz.em.proposals import Ragged, sample_independent
from efem_viz.em.rules import REASON_TOO_SMALL, StepContext, apply_step_rules, size_counts
from efem_viz.geometry.knn import point_spacing
from efem_viz.prior.data import SampleConfig, SensorModel, sensor_cloud


# ---------------------------------------------------------------------------------------------- sensor model
def _plane_hits(n: int, z: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.05, 0.05, n), rng.uniform(-0.05, 0.05, n), np.full(n, z)])
    return pts, np.zeros(3)


@pytest.mark.parametrize("kind", ["kinect", "realsense"])
def test_sensor_noise_is_axial_and_grows_with_depth(kind: str) -> None:
    """Frontal plane: displacement lies along the rays; its spread follows the model's σ_z at each depth."""
    stds = []
    for z in (0.5, 1.0):
        pts, eye = _plane_hits(20000, z)
        model = SensorModel(kind=kind, quant_px=0.0, jitter_px=0.0)
        out, keep = model.apply(pts, eye, np.ones(len(pts)), np.random.default_rng(1))
        assert keep.all()
        disp = out - pts
        u = pts / np.linalg.norm(pts, axis=1, keepdims=True)
        along = (disp * u).sum(1)
        perp = disp - along[:, None] * u
        assert np.abs(perp).max() < 1e-9
        expected = float(model.axial_sigma(np.array([z]), np.array([0.0]))[0])
        assert np.std(disp[:, 2]) == pytest.approx(expected, rel=0.05)
        stds.append(np.std(disp[:, 2]))
    assert stds[1] > stds[0]
    # Kinect v1 at 1 m: 1.2 + 1.9·0.36 = 1.884 mm; D435 at 1 m: 3.7 mm
    sigma_1m = float(SensorModel(kind=kind).axial_sigma(np.array([1.0]), np.array([0.0]))[0])
    assert sigma_1m == pytest.approx(1.884e-3 if kind == "kinect" else 3.7e-3, rel=1e-6)


def test_sensor_quantises_depth_and_drops_grazing_hits() -> None:
    pts, eye = _plane_hits(5000, 1.0)
    model = SensorModel(kind="realsense", k=0.0, fx=600.0, jitter_px=0.0)
    out, _ = model.apply(pts, eye, np.ones(len(pts)), np.random.default_rng(2))
    step = 1.0 * model.quant_px / (600.0 * 0.05)  # z² q / (f B) at 1 m ≈ 4.2 mm
    z = out[:, 2]
    levels = np.unique(np.round(z / step * 1e3) / 1e3)
    assert len(levels) <= 6  # a frontal plane at one depth lands on a few quantisation levels
    cos = np.full(len(pts), np.cos(np.deg2rad(88.0)))
    _, keep = SensorModel(kind="kinect").apply(pts, eye, cos, np.random.default_rng(3))
    assert keep.mean() < 0.3
    _, keep = SensorModel(kind="kinect").apply(pts, eye, np.ones(len(pts)), np.random.default_rng(3))
    assert keep.all()


def test_isotropic_sensor_is_gaussian_of_k_mm() -> None:
    pts, eye = _plane_hits(20000, 0.8)
    out, _ = SensorModel(kind="isotropic", k=3.0).apply(pts, eye, None, np.random.default_rng(0))
    assert np.std(out - pts, axis=0) == pytest.approx([3e-3] * 3, rel=0.05)


def test_sensor_cloud_is_seeded_and_has_n_pcl_points() -> None:
    import trimesh

    from efem_viz.prior.data import PrepConfig, normalize_mesh, prepare_object

    obj = prepare_object(normalize_mesh(trimesh.creation.cylinder(radius=0.04, height=0.1)), name="c",
                         cfg=PrepConfig(n_uniform=500, n_near=500, n_surface=500, n_views=3, n_top_views=2,
                                        resolution=48), seed=0)
    assert obj.view_eyes is not None and obj.view_eyes.shape == (3, 3)
    assert obj.view_cos is not None and len(obj.view_cos) == len(obj.views)
    cfg = SampleConfig(n_pcl=128, sensor_p=1.0)
    a = sensor_cloud(obj, cfg, np.random.default_rng(5))
    b = sensor_cloud(obj, cfg, np.random.default_rng(5))
    assert a.shape == (128, 3) and np.array_equal(a, b)
    from scipy.spatial import cKDTree

    # no noise: every point is a view hit; the noise is metric: 3 mm on a 0.1 m object is 0.03 canonical
    c = sensor_cloud(obj, cfg, np.random.default_rng(5), sensor=SensorModel(kind="isotropic", k=0.0), size=0.1)
    assert cKDTree(obj.views).query(c)[0].max() < 1e-5
    c3 = sensor_cloud(obj, cfg, np.random.default_rng(5), sensor=SensorModel(kind="isotropic", k=3.0), size=0.1,
                      n_views=1)
    assert 0.02 < float(np.median(cKDTree(obj.views).query(c3)[0])) < 0.06


# ---------------------------------------------------------------------------------------------- M-step
def test_m_step_without_replacement_draws_distinct_points_and_tops_up_small_supports() -> None:
    rag = Ragged.from_lists([np.arange(0, 500), np.arange(500, 530)])
    w = np.ones(len(rag.idx), np.float32)
    out = sample_independent(rag, w, 256, 1e-4, np.random.default_rng(0), fallback=np.arange(600),
                             replace=False)
    assert len(np.unique(out[0])) == 256 and set(out[0]) <= set(range(500))
    assert set(out[1][:30]) == set(range(500, 530)) and set(out[1]) <= set(range(500, 530))
    # weights still matter: zero-weight entries are never drawn
    w2 = w.copy()
    w2[:250] = 0.0
    out2 = sample_independent(rag, w2, 200, 1e-4, np.random.default_rng(1), fallback=np.arange(600),
                              replace=False)
    assert out2[0].min() >= 250 and len(np.unique(out2[0])) == 200


# ---------------------------------------------------------------------------------------------- size rule
def test_size_rule_on_band_ignores_normals_and_scales_with_density() -> None:
    rag = Ragged.from_lists([np.arange(0, 10), np.arange(10, 20)])
    d = np.array([0.0] * 6 + [0.5] * 4 + [0.0] * 10, np.float32)  # row 0: 6 in the band, row 1: 10
    inliers = np.array([2, 3])  # normal-filtered counts
    cfg = preset("real")
    counts, thr = size_counts(cfg, inliers, d, rag, 5, 0.1)
    assert counts.tolist() == [2, 3] and thr.tolist() == [5, 5]
    counts, thr = size_counts(cfg.replace(elimination={"min_size_on": "band"}), inliers, d, rag, 5, 0.1)
    assert counts.tolist() == [6, 10]
    # row 0's points 2× as far apart as the reference: a quarter of the points cover the same area
    spacing = np.array([0.008] * 10 + [0.004] * 10)
    _, thr = size_counts(cfg.replace(elimination={"min_size_on": "band", "min_size_spacing": 0.004}), inliers, d, rag,
                         8, 0.1,
                         spacing=spacing)
    assert thr.tolist() == [2.0, 8.0]
    ctx = StepContext(phase=1, step=0, local_step=0, cfg=cfg.replace(elimination={"min_size_on": "band"}),
                      inliers=inliers,
                      stationary=np.ones(2), d=d, rag=rag, n_points=20, min_size=7,
                      owner=np.zeros(2, np.int64), tau_d=0.1)
    kills = apply_step_rules(ctx)
    assert [(k.row, k.reason) for k in kills] == [(0, REASON_TOO_SMALL)]


def test_point_spacing_of_a_grid() -> None:
    g = np.stack(np.meshgrid(np.arange(5), np.arange(5), [0.0], indexing="ij"), -1).reshape(-1, 3) * 0.004
    assert np.allclose(point_spacing(g), 0.004)


def test_config_refuses_bad_size_rule_settings() -> None:
    with pytest.raises(ValueError, match="min_size_on"):
        preset("real").replace(elimination={"min_size_on": "normals"})
    with pytest.raises(ValueError, match="min_size_spacing"):
        preset("real").replace(elimination={"min_size_spacing": -1.0})


# ---------------------------------------------------------------------------------------------- probe
def test_probe_keeps_a_sphere_from_oracle_and_anchor_starts() -> None:
    """The analytic sphere prior on a clean sphere scene: the one-proposal loop holds the whole sphere."""
    from efem_viz.em.probe import track_proposal
    from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

    scene = make_sphere_scene(seed=0, radii=(0.05,), spacing=0.006)
    prior = make_sphere_prior()
    mask = scene.instance == 1
    cfg = preset("fast").replace(steps={"t1": 6}, elimination={"min_size": 50})
    tr = track_proposal(scene, prior, cfg, object_mask=mask, start="oracle", steps=6)
    assert len(tr.inliers) == 6 and tr.explained[-1] > 0.9 and tr.alive
    assert tr.output_iou > 0.8
    start = int(np.flatnonzero(mask)[0])
    tr2 = track_proposal(scene, prior, cfg, object_mask=mask, start=start, steps=6)
    assert tr2.explained[-1] > 0.8 and tr2.output_iou > 0.8
    # a size rule above the object's point count: the probe reports it dead
    tr3 = track_proposal(scene, prior, cfg.replace(elimination={"min_size": int(mask.sum()) * 2}), object_mask=mask,
                         start="oracle",
                         steps=3)
    assert not tr3.alive


# ---------------------------------------------------------------------------------------------- batch console
def test_batch_console_prints_progress_lines_when_not_a_terminal(tmp_path) -> None:
    from rich.console import Console

    from efem_viz.batch.console import RichBatchDisplay
    from efem_viz.batch.job import SceneTask

    buf = io.StringIO()
    display = RichBatchDisplay(Console(file=buf, width=200, force_terminal=False), plain_every_s=0.0)
    task = SceneTask(index=0, path=tmp_path / "a.ply", name="scan_a", out=tmp_path / "out")
    display.on_start(task, "local-0")
    display.on_step(task, "local-0", 3, 20, "phase 1  active 12")
    display.on_step(task, "local-0", 20, 20, "phase 2  active 2")
    text = buf.getvalue()
    assert "scan_a: started" in text and "step 3/20" in text and "step 20/20" in text
    # rate limit: with a long interval only the first and the last step are printed
    buf2 = io.StringIO()
    d2 = RichBatchDisplay(Console(file=buf2, width=200, force_terminal=False), plain_every_s=3600.0)
    d2.on_start(task, "w")
    for s in range(1, 21):
        d2.on_step(task, "w", s, 20, "x")
    assert buf2.getvalue().count("step ") == 1 and "step 20/20" in buf2.getvalue()


def test_m_step_of_a_proposal_whose_ball_is_empty_falls_back_to_available_points() -> None:
    """A proposal whose E-step ball held no point (all rows empty) draws from the fallback, not an IndexError."""
    rag = Ragged(np.zeros(0, np.int64), np.zeros(2, np.int64))
    out = sample_independent(rag, np.zeros(0, np.float32), 8, 1e-4, np.random.default_rng(0),
                             fallback=np.arange(10, 20))
    assert out.shape == (1, 8) and set(out[0]) <= set(range(10, 20))
