"""Shape-prior training: smoke run, exact resume, checkpoint round trip, data pipeline, shipped weights."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest
import torch

from efem_viz.prior.data import (
    ObjectData,
    PrepConfig,
    SampleConfig,
    augment_v1,
    input_cloud,
    load_or_prepare,
    make_example,
    normalize_mesh,
    procedural_sources,
)
from efem_viz.prior.model import WEIGHTS_DIR, PriorConfig, ShapePrior, load_prior, save_prior
from efem_viz.prior.train import (
    TrainArgs,
    best_iso_offset,
    compute_losses,
    lr_at,
    member_weight_map,
    sampling_probabilities,
    train,
    with_iso_offset,
)

SMALL_PREP = PrepConfig(n_uniform=4000, n_near=4000, n_surface=2000, resolution=64, max_view_points=800)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("prior_cache")


def _args(tmp: Path, cache: Path, **kw: object) -> TrainArgs:
    base = dict(preset="tiny", n_train=3, n_val=2, out_dir=tmp / "run", export=tmp / "w" / "mug.pt",
                cache_dir=cache, batch_size=4, iterations=40, val_every=20, threads=1, progress=False,
                log_every=1, lr=1e-3)
    base.update(kw)
    return TrainArgs(**base)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------------ data
def test_prepared_object_is_consistent(cache_dir: Path) -> None:
    src = procedural_sources("mug", "train", 1)[0]
    obj = load_or_prepare(src, cache_dir=cache_dir / "data", cfg=SMALL_PREP, seed=0)
    # normalised: longest bbox side 1, centred
    lo, hi = obj.surface.min(0), obj.surface.max(0)
    assert abs(float((hi - lo).max()) - 1.0) < 0.02 and np.abs((hi + lo) / 2).max() < 0.02
    # SDF signs: far corners outside, near-surface queries close to the surface
    assert (obj.uni[np.abs(obj.uni[:, :3]).max(1) > 0.52, 3] > 0).all()
    assert 0.0 < (obj.uni[:, 3] < 0).mean() < 0.5
    assert np.abs(obj.nss[:, 3]).mean() < 0.04
    # depth-view points lie on the surface (distance to the nearest surface sample is small)
    import open3d as o3d

    mesh = normalize_mesh(src[1]())
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    for pts in (obj.view(0), obj.view(11), obj.surface):
        assert np.abs(scene.compute_distance(o3d.core.Tensor(pts)).numpy()).max() < 1e-4
    sdf = scene.compute_signed_distance(o3d.core.Tensor(obj.uni[:, :3].copy())).numpy()
    assert np.allclose(sdf, obj.uni[:, 3], atol=1e-5)
    assert (obj.view_elev_deg[:8] >= 30).all() and (obj.view_elev_deg[10:] < -10).all()
    again = load_or_prepare(src, cache_dir=cache_dir / "data", cfg=SMALL_PREP, seed=0)  # from the cache
    assert np.array_equal(again.uni, obj.uni) and np.array_equal(again.views, obj.views)


def test_examples_and_augmentation(cache_dir: Path) -> None:
    srcs = procedural_sources("mug", "train", 2)
    objs = [load_or_prepare(s, cache_dir=cache_dir / "data", cfg=SMALL_PREP, seed=i)
            for i, s in enumerate(srcs)]
    cfg = SampleConfig(n_pcl=256)
    pcl, q = make_example(objs[0], cfg, np.random.default_rng(0), others=objs)
    assert pcl.shape == (256, 3) and q.shape == (2048, 4) and pcl.dtype == np.float32
    # same seed, same example; other seed, other example
    pcl2, _ = make_example(objs[0], cfg, np.random.default_rng(0), others=objs)
    assert np.array_equal(pcl, pcl2)
    # forced augmentation: the table patch is a flat layer at the bottom of the mug
    forced = dataclasses.replace(cfg, aug_ratio=0.7, p_obj=0.0, p_ball=0.0, p_table=1.0)
    rng = np.random.default_rng(3)
    base = input_cloud(objs[0], cfg, rng)
    for _ in range(10):
        out = augment_v1(base, objs[0], q[:1024], objs, forced, rng)
        assert out.shape == base.shape
        z_bot = objs[0].z_bottom
        n_new = int((np.abs(out[:, 2] - z_bot) < 0.04).sum() - (np.abs(base[:, 2] - z_bot) < 0.04).sum())
        if n_new > 20:
            break
    else:
        pytest.fail("the table augmentation never added a bottom plane")
    # ball removal only (+ uniform noise points): same size, different cloud
    only_ball = dataclasses.replace(cfg, p_obj=0.0, p_table=0.0, p_ball=1.0)
    noisy = augment_v1(base, objs[0], q[:1024], objs, only_ball, np.random.default_rng(5))
    assert noisy.shape == base.shape and not np.array_equal(noisy, base)


def test_table_patch_from_a_random_side_touches_the_object(tmp_path: Path, cache_dir: Path) -> None:
    """With ``table_side_p`` = 1 the support patch is a plane of any orientation tangent to the object (the whole
    surface on one side, touching it); with 0 it is the plane under the canonical bottom."""
    obj = load_or_prepare(procedural_sources("mug", "train", 1)[0], cache_dir=cache_dir / "data", cfg=SMALL_PREP,
                          seed=0)

    def patch_normals(side_p: float) -> list[np.ndarray]:
        cfg = dataclasses.replace(_args(tmp_path, cache_dir, table_side_p=side_p).sample_config(256),
                                  noise_std=0.0, aug_ratio=1.0, p_obj=0.0, p_ball=0.0, p_table=1.0)
        assert cfg.p_table_any_side == side_p
        rng = np.random.default_rng(7)
        base = input_cloud(obj, cfg, rng)
        seen = {tuple(p) for p in base.tolist()}
        normals = []
        for _ in range(12):
            out = augment_v1(base, obj, obj.uni[:1024], [obj], cfg, rng)
            new = np.array([p for p in out.tolist() if tuple(p) not in seen])
            if len(new) < 20:
                continue
            centre = new.mean(axis=0)
            normal = np.linalg.svd(new - centre)[2][-1]
            assert np.abs((new - centre) @ normal).max() < 1e-4  # one plane
            heights = (obj.surface - centre) @ normal
            if np.median(heights) < 0:
                normal, heights = -normal, -heights
            assert heights.min() == pytest.approx(0.0, abs=1e-4)  # touching, the object on one side
            normals.append(normal)
        assert len(normals) >= 5
        return normals

    assert all(n[2] == pytest.approx(1.0, abs=1e-6) for n in patch_normals(0.0))
    sides = patch_normals(1.0)
    assert sum(abs(n[2]) < 0.9 for n in sides) >= 3  # not only under the object
    with pytest.raises(ValueError, match="table_side_p"):
        _args(tmp_path, cache_dir, table_side_p=-0.1).sample_config(256)


def test_neighbour_part_lies_beside_the_object_inside_its_reach(tmp_path: Path, cache_dir: Path) -> None:
    """With ``neighbour_p`` = 1 the other-object points are one piece of a whole other object placed beside this
    one: inside the input's reach, outside the object (a gap, not through it), most of them from one rigid copy."""
    from scipy.spatial import cKDTree

    objs = [load_or_prepare(s, cache_dir=cache_dir / "data", cfg=SMALL_PREP, seed=i)
            for i, s in enumerate(procedural_sources("mug", "train", 2))]
    cfg = dataclasses.replace(_args(tmp_path, cache_dir, neighbour_p=1.0).sample_config(256),
                              noise_std=0.0, aug_ratio=1.0, p_obj=1.0, p_ball=0.0, p_table=0.0)
    assert cfg.p_neighbour == 1.0
    rng = np.random.default_rng(11)
    base = input_cloud(objs[0], cfg, rng)
    seen = {tuple(p) for p in base.tolist()}
    centre = base.mean(axis=0)
    reach = float(np.sqrt(((base - centre) ** 2).sum(-1)).max()) * 1.25  # the kept cloud's reach with a margin
    surface = cKDTree(objs[0].surface)
    # the object's inside, by its own SDF samples: a neighbour never reaches into it
    inside = cKDTree(objs[0].uni[objs[0].uni[:, 3] < -0.02, :3])
    n_checked = 0
    for _ in range(20):
        out = augment_v1(base, objs[0], objs[0].uni[:1024], objs[1:], cfg, rng)
        new = np.array([p for p in out.tolist() if tuple(p) not in seen])
        if len(new) < 20:
            continue
        assert np.sqrt(((new - centre) ** 2).sum(-1)).max() <= reach + 1e-5
        assert np.median(surface.query(new)[0]) > 0.01
        assert (inside.query(new)[0] < 0.005).mean() < 0.02
        n_checked += 1
    assert n_checked >= 8
    with pytest.raises(ValueError, match="neighbour_p"):
        _args(tmp_path, cache_dir, neighbour_p=1.5).sample_config(256)


def test_top_only_probability_chooses_the_views_an_input_comes_from(tmp_path: Path, cache_dir: Path) -> None:
    src = procedural_sources("mug", "train", 1)[0]
    obj = load_or_prepare(src, cache_dir=cache_dir / "data", cfg=SMALL_PREP, seed=0)
    n_top = int(np.sum(obj.view_elev_deg >= 30.0 - 1e-3))
    top = {tuple(p) for i in range(n_top) for p in obj.view(i).tolist()}

    def outside_top(p_top: float) -> int:
        cfg = dataclasses.replace(_args(tmp_path, cache_dir, top_only_p=p_top).sample_config(256), noise_std=0.0)
        assert cfg.p_top_only == p_top
        rng = np.random.default_rng(0)
        return sum(tuple(p) not in top for _ in range(20) for p in input_cloud(obj, cfg, rng).tolist())

    assert outside_top(1.0) == 0  # only the views from above
    assert outside_top(0.0) > 0  # side and bottom views too
    with pytest.raises(ValueError, match="top_only_p"):
        _args(tmp_path, cache_dir, top_only_p=1.5).sample_config(256)


def test_lr_schedule() -> None:
    kw = dict(base=1e-4, total=80000, decay_at=(0.625, 0.75, 0.875), factor=0.3)
    assert lr_at(0, **kw) == 1e-4 and lr_at(49999, **kw) == 1e-4
    assert lr_at(50000, **kw) == pytest.approx(3e-5) and lr_at(79999, **kw) == pytest.approx(2.7e-6)


# --------------------------------------------------------------------------------------------------- training
def test_training_smoke_loss_decreases(tmp_path: Path, cache_dir: Path) -> None:
    res = train(_args(tmp_path, cache_dir))
    losses = [c["sdf"] for c in res["curve"]]
    assert len(losses) == 40 and all(np.isfinite(losses))
    assert np.mean(losses[-8:]) < 0.9 * np.mean(losses[:8])
    assert (tmp_path / "w" / "mug.pt").is_file() and (tmp_path / "run" / "last.pt").is_file()
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["prior"]["widths"] == [8, 8, 16, 16] and cfg["n_train"] == 3
    rep = json.loads((tmp_path / "w" / "mug_training_report.json").read_text())
    assert rep["iteration"] == 40 and [v["iteration"] for v in rep["val_curve"]] == [0, 20, 40]
    assert (tmp_path / "w" / "mug_training_report.md").read_text().startswith("# Training report")
    prior = load_prior(tmp_path / "w" / "mug.pt")
    assert prior.metadata["val_iou"] == pytest.approx(res["best_iou"])
    best = max(rep["val_curve"], key=lambda v: v["iou_cal"])
    assert prior.metadata["iso_offset"] == best["iso_offset"] and best["iou_cal"] >= best["iou"]


def test_a_chair_prior_trains_on_the_procedural_chairs(tmp_path: Path, cache_dir: Path) -> None:
    """The pipeline is not mug-only: `train-prior --category chair` prepares chairs (views, SDF samples), trains
    a few steps and exports a prior whose category is "chair"."""
    res = train(_args(tmp_path, cache_dir, category="chair", iterations=6, val_every=100), max_iterations=6)
    assert res["iteration"] == 6 and all(np.isfinite([c["loss"] for c in res["curve"]]))
    prior = load_prior(tmp_path / "w" / "mug.pt")
    assert prior.category.name == "chair"


def test_a_kitchen_prior_trains_on_its_four_categories_and_validates_each(tmp_path: Path, cache_dir: Path) -> None:
    """`train-prior --category kitchen` trains one prior over mugs, bowls, bottles and cans (interleaved) and
    its validation reports the calibrated IoU of each category beside the mean of all."""
    res = train(_args(tmp_path, cache_dir, category="kitchen", n_train=4, n_val=4, iterations=4, val_every=4),
                max_iterations=4)
    last = res["val_curve"][-1]
    per = {c: last[f"iou_cal_{c}"] for c in ("mug", "bowl", "bottle", "can")}
    assert all(0.0 <= v <= 1.0 for v in per.values())
    assert np.mean(list(per.values())) == pytest.approx(last["iou_cal"], abs=1e-9)  # one object each
    assert load_prior(tmp_path / "w" / "mug.pt").category.name == "kitchen"


def test_a_run_exports_into_its_own_folder_unless_told_otherwise(tmp_path: Path) -> None:
    """Without --export the best model goes to the run's folder, never over a shipped prior (whose codebook and
    settings belong to its own weights)."""
    args = TrainArgs(category="chair", out_dir=tmp_path / "run")
    assert args.resolved_export() == tmp_path / "run" / "chair.pt"
    assert TrainArgs(category="kitchen").resolved_export() == Path("runs") / "kitchen" / "kitchen.pt"
    assert TrainArgs(category="mug", export=WEIGHTS_DIR / "mug.pt").resolved_export() == WEIGHTS_DIR / "mug.pt"


def test_iso_offset_calibration_thins_a_fat_field_and_fattens_a_shell() -> None:
    """Queries on a line through a 0.2-wide slab (SDF |x| − 0.1): a field 0.01 too low everywhere (fat, as the
    inside-weighted loss learns) is calibrated with c = −0.01, one 0.02 too high (a thin wall's positive shell)
    with c = +0.02, each to IoU 1; an exact field keeps c = 0 even where other offsets tie with it."""
    x = np.linspace(-0.5, 0.5, 2001)[None]
    sdf = np.abs(x) - 0.1
    inside = sdf <= 0
    for bias, want in ((-0.01, -0.01), (0.02, 0.02), (0.0, 0.0)):
        c, iou = best_iso_offset(sdf + bias, inside)
        assert c == pytest.approx(want, abs=1e-9) and iou == pytest.approx(1.0, abs=1e-3), (bias, c, iou)
    c, _ = best_iso_offset(np.where(inside, -1.0, 1.0), inside)  # a sharp field: every offset in (-1, 1) ties
    assert c == 0.0


def test_inside_weight_scales_the_sdf_error_inside_the_shape_only(tmp_path: Path, cache_dir: Path) -> None:
    """Worked by hand: a model that predicts 0 everywhere, two uniform queries (GT SDF -0.02 inside, 0.03 outside)
    and two near ones (-0.01, 0.04). The SDF loss is the mean of the two groups' means: 0.025 with the
    specification's weights, (3 x 0.02 + 0.03) / 2 and (3 x 0.01 + 0.04) / 2 averaged = 0.04 with the inside
    weight 3. The weight must be a positive number."""
    fake = SimpleNamespace(
        encode=lambda pcl, centroid_noise=None: SimpleNamespace(center=torch.zeros(1, 3, dtype=torch.float64),
                                                                scale=torch.ones(1, dtype=torch.float64)),
        sdf=lambda x, lat: torch.zeros(x.shape[:2], dtype=torch.float64))
    q = torch.zeros(1, 4, 4, dtype=torch.float64)
    q[0, :, 3] = torch.tensor([-0.02, 0.03, -0.01, 0.04], dtype=torch.float64)
    pcl = torch.zeros(1, 8, 3, dtype=torch.float64)
    spec = compute_losses(cast(Any, fake), pcl, q, n_uniform=2)
    inside = compute_losses(cast(Any, fake), pcl, q, n_uniform=2, inside_weight=3.0)
    assert float(spec["sdf"]) == pytest.approx(0.025, abs=1e-12)
    assert float(inside["sdf"]) == pytest.approx(0.04, abs=1e-12)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="inside-weight"):
            train(_args(tmp_path, cache_dir, inside_weight=bad))


def test_member_weights_draw_the_named_members_more_often(tmp_path: Path, cache_dir: Path,
                                                        monkeypatch: Any) -> None:
    """``--member-weights mug=3`` makes a mug three times as likely as any other object in every batch; a typo'd
    member, a bad weight or a repeated member is refused before any data is loaded."""
    names = ("mug_000000", "bowl_000000", "can_000000", "bottle_000000")
    objs = cast(list[ObjectData], [SimpleNamespace(name=n) for n in names])
    p = sampling_probabilities(objs, member_weight_map(["mug=3"]))
    assert p is not None and p.tolist() == pytest.approx([0.5, 1 / 6, 1 / 6, 1 / 6])
    assert sampling_probabilities(objs, {}) is None
    # a chair's member is its base: `stool=3` weighs the stools of the chair family
    from efem_viz.data.chairs import sample_chair_params

    chairs = cast(list[ObjectData], [SimpleNamespace(name=f"chair_{s:06d}") for s in range(12)])
    stool = np.array([sample_chair_params(s).base == "stool" for s in range(12)])
    assert 0 < stool.sum() < 12
    p = sampling_probabilities(chairs, {"stool": 3.0})
    assert p is not None and np.allclose(p[stool], 3 * p[~stool][0]) and np.allclose(p[~stool], p[~stool][0])
    with pytest.raises(ValueError, match="names no training object: mugg"):
        sampling_probabilities(objs, {"mugg": 2.0})
    for bad in (["mug"], ["mug=0"], ["mug=nan"], ["mug=-1"], ["=2"], ["mug=2", "mug=3"]):
        with pytest.raises(ValueError, match="member=weight"):
            member_weight_map(bad)
    with pytest.raises(ValueError, match="member=weight"):
        train(_args(tmp_path, cache_dir, member_weights=("mug=x",)))
    # a run draws its batches with these probabilities
    drawn: list[str] = []
    import efem_viz.prior.data as data_mod
    real = data_mod.make_batch

    def spy(objs_: Any, *a: Any, **k: Any) -> Any:
        drawn.extend(o.name.split("_")[0] for o in objs_)
        return real(objs_, *a, **k)

    monkeypatch.setattr(data_mod, "make_batch", spy)
    train(_args(tmp_path, cache_dir, category="kitchen", n_train=4, n_val=4, iterations=12, val_every=100,
                member_weights=("mug=20",)), max_iterations=12)
    assert len(drawn) == 12 * _args(tmp_path, cache_dir).batch_size
    assert drawn.count("mug") > 0.7 * len(drawn)  # expected 20/23 = 0.87


def test_resume_is_exact(tmp_path: Path, cache_dir: Path) -> None:
    straight = train(_args(tmp_path / "a", cache_dir, iterations=6, val_every=100))
    first = train(_args(tmp_path / "b", cache_dir, iterations=6, val_every=100), max_iterations=3)
    assert first["iteration"] == 3 and first["stop_reason"] == "max_iterations"
    ck = torch.load(tmp_path / "b" / "run" / "last.pt", weights_only=False)
    assert ck["state"]["iteration"] == 3 and "optimizer" in ck and "np_rng" in ck
    resumed = train(_args(tmp_path / "b", cache_dir, iterations=6, val_every=100, resume=True))
    assert resumed["iteration"] == 6
    assert [c["iteration"] for c in resumed["curve"]] == list(range(1, 7))
    assert np.allclose([c["loss"] for c in resumed["curve"]], [c["loss"] for c in straight["curve"]],
                       rtol=1e-6)
    sa = torch.load(tmp_path / "a" / "run" / "last.pt", weights_only=False)
    sb = torch.load(tmp_path / "b" / "run" / "last.pt", weights_only=False)
    for k, v in sa["state_dict"].items():
        assert torch.allclose(v, sb["state_dict"][k], rtol=1e-6, atol=1e-9), k
    assert sa["np_rng"] == sb["np_rng"]


def test_the_learning_rate_warms_up_whenever_adam_starts_without_moments(tmp_path: Path, cache_dir: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A new run and a resume state without the optimiser's moments ramp the learning rate up linearly; a full
    checkpoint (moments kept) continues the ramp where it was."""
    from efem_viz.prior.train import write_resume_state

    kw = dict(val_every=100, warmup_steps=4, iterations=20)
    first = train(_args(tmp_path / "a", cache_dir, **kw), max_iterations=2)
    assert [c["lr"] for c in first["curve"]] == pytest.approx([2.5e-4, 5e-4])
    cont = train(_args(tmp_path / "a", cache_dir, resume=True, **kw), max_iterations=3)
    assert [c["lr"] for c in cont["curve"]][2:] == pytest.approx([7.5e-4, 1e-3, 1e-3])
    shipped = tmp_path / "shipped.pt"
    assert write_resume_state(tmp_path / "a" / "run" / "last.pt", shipped) is not None
    restarted = train(_args(tmp_path / "b", cache_dir, resume_from=shipped, **kw), max_iterations=2)
    assert restarted["iteration"] == 7
    assert [c["lr"] for c in restarted["curve"]][5:] == pytest.approx([2.5e-4, 5e-4])
    # a resume state keeps the last entries of the training-loss curve (the report's window), not the whole curve
    import efem_viz.prior.train as train_mod

    monkeypatch.setattr(train_mod, "RESUME_CURVE_KEEP", 3)
    assert write_resume_state(tmp_path / "b" / "run" / "last.pt", shipped) is not None
    kept = torch.load(shipped, weights_only=False)["state"]["curve"]
    assert [c["iteration"] for c in kept] == [c["iteration"] for c in restarted["curve"][-3:]]


def test_weight_average_follows_its_formula_swaps_back_and_refuses_a_foreign_average() -> None:
    """`WeightAverage`: a ← β a + (1 − β) w with β = min(decay, (1 + n) / (10 + n)) on floating-point entries,
    integer entries copied; swapping twice gives both sets back; a saved average of other shapes or with NaN is
    refused."""
    from efem_viz.prior.train import WeightAverage

    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2).double()
    model.register_buffer("count", torch.zeros((), dtype=torch.long))
    avg = WeightAverage(model, 0.5)
    expect = {k: v.clone() for k, v in model.state_dict().items()}
    for n in range(4):
        with torch.no_grad():
            model.weight.add_(torch.randn(2, 3, dtype=torch.float64))
            model.bias.mul_(-2.0)
            model.count += 3
        beta = min(0.5, (1 + n) / (10 + n))
        for k, v in model.state_dict().items():
            expect[k] = beta * expect[k] + (1 - beta) * v if v.is_floating_point() else v.clone()
        avg.update(model)
    assert avg.updates == 4
    for k, v in avg.state().items():
        assert torch.allclose(v, expect[k], rtol=0, atol=1e-15), k
    trained, averaged = {k: v.clone() for k, v in model.state_dict().items()}, avg.state()
    avg.swap(model)
    assert torch.equal(model.weight, averaged["weight"]) and torch.equal(avg.average["weight"], trained["weight"])
    avg.swap(model)
    assert all(torch.equal(model.state_dict()[k], trained[k]) for k in trained)
    with pytest.raises(ValueError, match="does not match"):
        WeightAverage(model, 0.5, average={"weight": torch.zeros(3, 3), "bias": torch.zeros(2),
                                           "count": torch.zeros((), dtype=torch.long)})
    bad = avg.state()
    bad["bias"][0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        WeightAverage(model, 0.5, average=bad)
    with pytest.raises(ValueError, match="ema-decay"):
        train(TrainArgs(ema_decay=1.0))


def test_a_weight_averaged_run_resumes_its_average_exactly_and_exports_it(tmp_path: Path, cache_dir: Path) -> None:
    """`--ema-decay`: checkpoints carry the average, a resumed run continues it to the same values as a straight
    run (a shippable resume state leaves it out: a run resumed from one starts it again), validation reports the
    trained weights beside the averaged ones, and the export is whichever of the two scored higher."""
    from efem_viz.prior.train import write_resume_state

    kw = dict(iterations=6, val_every=100, ema_decay=0.9, calibrate_iso=False)
    train(_args(tmp_path / "a", cache_dir, **kw))
    train(_args(tmp_path / "b", cache_dir, **kw), max_iterations=3)
    resumed = train(_args(tmp_path / "b", cache_dir, resume=True, **kw))
    sa = torch.load(tmp_path / "a" / "run" / "last.pt", weights_only=False)
    sb = torch.load(tmp_path / "b" / "run" / "last.pt", weights_only=False)
    assert sa["state"]["ema_updates"] == sb["state"]["ema_updates"] == 6
    for k, v in sa["ema"].items():
        assert torch.allclose(v, sb["ema"][k], rtol=1e-6, atol=1e-9), k
    moved = [k for k, v in sa["ema"].items() if v.is_floating_point() and not torch.equal(v, sa["state_dict"][k])]
    assert moved  # the average is not the trained weights
    last = resumed["val_curve"][-1]
    assert last["iteration"] == 6 and {"trained_iou", "trained_iou_cal", "trained_iso_offset"} <= set(last)
    # a validation of the finished run with the best forgotten exports the better of the two
    again = train(_args(tmp_path / "a", cache_dir, resume=True, reset_best=True, **kw))["val_curve"][-1]
    exported = load_prior(tmp_path / "a" / "w" / "mug.pt")
    took = "trained" if again["trained_iou"] > again["iou"] else "average"
    assert exported.metadata["weights"] == took
    assert exported.metadata["val_iou"] == pytest.approx(again["trained_iou" if took == "trained" else "iou"])
    want = sa["state_dict"] if took == "trained" else sa["ema"]
    for k, v in want.items():
        assert torch.allclose(exported.state_dict()[k].float(), v.float(), rtol=1e-6, atol=1e-7), k
    shipped = tmp_path / "shipped.pt"
    assert write_resume_state(tmp_path / "a" / "run" / "last.pt", shipped) is not None
    state = torch.load(shipped, weights_only=False)  # the average stays out of the shippable state (its size)
    assert "ema" not in state and state["optimizer"] is None and state["state"]["ema_updates"] == 6
    cont = train(_args(tmp_path / "c", cache_dir, resume_from=shipped, **{**kw, "iterations": 7}))
    ck = torch.load(tmp_path / "c" / "run" / "last.pt", weights_only=False)
    assert cont["iteration"] == 7 and ck["state"]["ema_updates"] == 1  # started again from the weights
    bad = dict(sa, ema={**sa["ema"], moved[0]: torch.full_like(sa["ema"][moved[0]], float("nan"))})
    torch.save(bad, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="weight average does not match"):
        train(_args(tmp_path / "d", cache_dir, resume_from=tmp_path / "bad.pt", **kw))
    assert not (tmp_path / "d" / "run" / "config.json").exists()  # refused before any work


def test_resume_without_checkpoint_fails(tmp_path: Path, cache_dir: Path) -> None:
    with pytest.raises(FileNotFoundError, match="resume"):
        train(_args(tmp_path, cache_dir, resume=True))


def test_save_load_round_trip(tmp_path: Path) -> None:
    torch.manual_seed(0)
    prior = ShapePrior(PriorConfig(widths=(8, 8, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                                   center_hidden=8, decoder_hidden=32, decoder_blocks=1, n_pcl=64, k=8,
                                   scale_factor=123.0), name="cup")
    path = save_prior(prior, tmp_path / "cup.pt", extra={"note": "x"})
    back = load_prior(path)
    assert back.name == "cup" and back.metadata["note"] == "x" and back.config == prior.config
    pts = torch.rand(2, 64, 3)
    x = torch.rand(2, 100, 3) - 0.5
    with torch.no_grad():
        a, b = prior.encode(pts), back.encode(pts)
        assert all(torch.equal(u, v) for u, v in zip(a, b))
        assert torch.equal(prior.sdf(x, a), back.sdf(x, b))
        shifted = with_iso_offset(prior, 0.02)
        assert torch.allclose(shifted.sdf(x, a), prior.sdf(x, a) - 0.02, atol=1e-6)
        assert torch.equal(prior.sdf(x, a), back.sdf(x, b))  # the original is untouched
    with pytest.raises(FileNotFoundError):
        load_prior(tmp_path / "missing.pt")
    with pytest.raises(FileNotFoundError):
        load_prior("no_such_prior_name")
    torch.save({"foo": 1}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not an efem-viz prior"):
        load_prior(tmp_path / "bad.pt")
    # float16 storage: half the bytes, weights rounded to float16, computed in float32; saving again keeps it
    half = save_prior(prior, tmp_path / "cup16.pt", storage="float16")
    assert half.stat().st_size < 0.7 * path.stat().st_size
    h = load_prior(half)
    assert h.metadata["storage"] == "float16" and next(h.parameters()).dtype == torch.float32
    for k, v in prior.state_dict().items():
        assert torch.equal(h.state_dict()[k], v.half().float())
    again = save_prior(h, tmp_path / "again.pt")
    assert load_prior(again).metadata["storage"] == "float16" and again.stat().st_size < 0.7 * path.stat().st_size
    with pytest.raises(ValueError, match="storage"):
        save_prior(prior, tmp_path / "x.pt", storage="int8")


# ------------------------------------------------------------------------------------------ shipped weights
SHIPPED = WEIGHTS_DIR / "mug.pt"
#: Measured 2026-12-01 on the shipped iteration-29000 export with exactly this test: mean IoU 0.653 from
#: 4-12 top views (0.78/0.63/0.63/0.57) and 0.660 from 1-12 views incl. single ones (0.75/0.63/0.67/0.59); Θ_s/s
#: 0.93-1.04; centre error 0.01-0.08 (relative to s). (Earlier exports: iteration-21000 export: 0.659 / 0.626;
#: iteration-14500 export: 0.639 / 0.580; iteration-2500 export: 0.35 from top views.) The bars leave a margin for float
#: and platform differences, not for a worse prior.
SHIPPED_IOU_BAR = {"top views": 0.6, "1-12 views": 0.57}
#: weights exported before this many iterations are snapshots of a training run still in progress
MIN_SHIPPED_ITERATIONS = 2000


@pytest.mark.skipif(not SHIPPED.is_file(), reason="efem_viz/weights/mug.pt not trained yet")
def test_shipped_mug_reconstructs_held_out_partial_scan(cache_dir: Path) -> None:
    """Held-out test mugs, seen from above only (4-12 top depth views, then 1-12 incl. single views; noise; the
    bottom never seen), placed in a random world pose at real scale: the shipped prior recovers scale, centre and
    volume (IoU)."""
    prior = load_prior("mug")
    assert SHIPPED.stat().st_size < 20 * 2**20
    if int(prior.metadata.get("iteration", 0)) < MIN_SHIPPED_ITERATIONS:
        pytest.skip(f"shipped mug.pt is an early snapshot of a running training (iteration "
                    f"{prior.metadata.get('iteration')})")
    for label, cfg in (("top views", SampleConfig(n_pcl=prior.config.n_pcl, p_top_only=1.0)),
                       ("1-12 views", SampleConfig(n_pcl=prior.config.n_pcl, p_top_only=1.0, min_views=1))):
        rng = np.random.default_rng(0)
        gen = torch.Generator().manual_seed(0)
        ious = []
        for i, src in enumerate(procedural_sources("mug", "test", 4)):
            obj = load_or_prepare(src, cache_dir=cache_dir / "test", cfg=PrepConfig(), seed=1000 + i)
            pcl = torch.as_tensor(input_cloud(obj, cfg, rng), dtype=torch.float32)
            q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen))
            R = q * torch.sign(torch.det(q))
            s, t = 0.12, torch.tensor([0.3, -0.2, 0.8])
            x = torch.as_tensor(obj.uni[:10000, :3])
            with torch.no_grad():
                lat = prior.encode((s * pcl @ R.T + t)[None])
                sdf = prior.sdf(s * x @ R.T + t, lat[0])
            gt_in = torch.as_tensor(obj.uni[:10000, 3]) <= 0
            pr_in = sdf < 0
            ious.append(float((gt_in & pr_in).sum() / (gt_in | pr_in).sum()))
            assert abs(float(lat.scale) / s - 1.0) < 0.15, (label, i)
            assert float((lat.center[0] - t).norm()) / s < 0.15, (label, i)  # canonical bbox centre ↦ t
        assert np.mean(ious) > SHIPPED_IOU_BAR[label], (label, ious)


def test_sigterm_stops_cleanly_with_a_final_checkpoint(tmp_path: Path, cache_dir: Path) -> None:
    """A background run that gets SIGTERM (or Ctrl+C) validates, checkpoints and can be resumed."""
    import os
    import signal

    def kill_at_3(it: int, total: int, info: dict) -> None:
        if it == 3:
            os.kill(os.getpid(), signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    res = train(_args(tmp_path, cache_dir, iterations=10, val_every=100), on_progress=kill_at_3)
    assert res["stop_reason"].startswith("interrupted") and res["iteration"] == 3
    assert signal.getsignal(signal.SIGTERM) is before
    ck = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    assert ck["state"]["iteration"] == 3
    resumed = train(_args(tmp_path, cache_dir, iterations=5, val_every=100, resume=True))
    assert resumed["iteration"] == 5


def test_sensor_and_fixed_point_training_runs_and_reports_sensor_metrics(tmp_path: Path, cache_dir: Path) -> None:
    """--sensor-p / --fixed-point-p / --snapshot-every: the run trains, validates on sensor inputs too (and selects
    by them), writes snapshots; fixed-point inputs are drawn from the cloud's own points."""
    import torch

    from efem_viz.prior.model import ShapePrior
    from efem_viz.prior.train import fixed_point_inputs, train

    args = _args(tmp_path, cache_dir, sensor_p=0.75, fixed_point_p=0.5, snapshot_every=10, iterations=20,
                 val_every=10)
    res = train(args)
    assert res["iteration"] == 20
    v = res["val_curve"][-1]
    assert "sensor_iou_cal" in v and 0.0 <= v["sensor_iou_cal"] <= 1.0
    assert (tmp_path / "run" / "snap_10.pt").is_file() and (tmp_path / "run" / "snap_20.pt").is_file()
    prior = ShapePrior(args.prior_config())
    pcl = np.random.default_rng(0).normal(size=(3, prior.config.n_pcl, 3)).astype(np.float32) * 0.3
    # a band that holds every point: chosen clouds are re-drawn from their own points; p = 0 changes nothing
    out = fixed_point_inputs(prior, pcl, np.random.default_rng(1), p=1.0, tau=1e9)
    assert out.shape == pcl.shape and not np.array_equal(out, pcl)
    for b in range(3):
        assert {tuple(r) for r in out[b]} <= {tuple(r) for r in pcl[b]}
    assert np.array_equal(fixed_point_inputs(prior, pcl, np.random.default_rng(1), p=0.0, tau=1e9), pcl)
    # a band that holds no point leaves the clouds as they were
    assert np.array_equal(fixed_point_inputs(prior, pcl, np.random.default_rng(1), p=1.0, tau=-1.0), pcl)
    assert torch.is_grad_enabled()


def test_init_from_a_prior_with_a_frozen_decoder_trains_only_the_encoder(tmp_path: Path, cache_dir: Path) -> None:
    """--init-from starts a new run (iteration 0, fresh optimiser) from a saved prior's weights; --freeze-decoder
    leaves the decoder bit-identical while the encoder moves."""
    first = _args(tmp_path / "a", cache_dir, iterations=4, val_every=100, calibrate_iso=False)
    train(first)
    start = load_prior(first.resolved_export(), load_codebook=False)
    args = _args(tmp_path / "b", cache_dir, iterations=5, val_every=100, init_from=first.resolved_export(),
                 freeze_decoder=True, calibrate_iso=False, sensor_p=0.5)
    res = train(args)
    assert res["iteration"] == 5 and res["val_curve"][0]["iteration"] == 0
    ck = torch.load(tmp_path / "b" / "run" / "last.pt", weights_only=False)
    after = ck["state_dict"]
    before = start.state_dict()
    dec = [k for k in before if k.startswith("decoder.")]
    enc = [k for k in before if k.startswith("encoder.")]
    assert dec and enc
    assert all(torch.equal(before[k], after[k]) for k in dec)
    assert any(not torch.equal(before[k], after[k]) for k in enc)
    # the first validation (iteration 0) is the initial prior's: same IoU as that prior on the same inputs
    from efem_viz.prior.train import load_objects, validate

    start.eval()
    ref = validate(start, load_objects(args, "val"), args.sample_config(start.config.n_pcl), seed=args.seed + 99)
    assert res["val_curve"][0]["iou"] == pytest.approx(ref["iou"])
    assert load_prior(args.resolved_export(), load_codebook=False).metadata["init_from"] == str(first.resolved_export())


def test_init_from_another_category_keeps_the_weights_not_the_settings(tmp_path: Path, cache_dir: Path) -> None:
    """A bowl prior started from a mug prior's weights must not carry the mug's τ_out, its calibration or its
    category settings (they would be read as the bowl's)."""
    first = _args(tmp_path / "a", cache_dir, iterations=2, val_every=100, calibrate_iso=False)
    train(first)
    mug = load_prior(first.resolved_export(), load_codebook=False)
    mug.metadata = {**mug.metadata, "tau_out": 0.05, "tau_out_calibration": {"scenes": ["syn_z_0"]},
                    "category": {"name": "mug", "scale_horizontal": [0.03, 0.13]}}
    src = save_prior(mug, tmp_path / "mug_tuned.pt")
    args = _args(tmp_path / "b", cache_dir, category="bowl", export=tmp_path / "w" / "bowl.pt", iterations=2,
                 val_every=100, init_from=src, calibrate_iso=False)
    train(args)
    bowl = load_prior(args.resolved_export(), load_codebook=False)
    assert bowl.name == "bowl" and bowl.metadata["init_from"] == str(src)
    assert not {"tau_out", "tau_out_calibration", "category"} & set(bowl.metadata)
    # the same category keeps what the earlier run learnt about itself
    again = _args(tmp_path / "c", cache_dir, export=tmp_path / "w2" / "mug.pt", iterations=2, val_every=100,
                  init_from=src, calibrate_iso=False)
    train(again)
    assert load_prior(again.resolved_export(), load_codebook=False).metadata["tau_out"] == 0.05
    # ... but not the record of the saved prior's own validation: a snapshot of the new run shows none of it
    mug.metadata = {**mug.metadata, "val_iou": 0.99, "val_metrics": {"iou": 0.99}, "iso_offset": 0.02,
                    "weights": "average", "iteration": 123456}
    src = save_prior(mug, tmp_path / "mug_scored.pt")
    snap = _args(tmp_path / "d", cache_dir, export=tmp_path / "w3" / "mug.pt", iterations=2, val_every=100,
                 snapshot_every=1, init_from=src, calibrate_iso=False)
    train(snap)
    meta = load_prior(Path(snap.out_dir) / "snap_1.pt", load_codebook=False).metadata
    assert meta["iteration"] == 1 and meta["tau_out"] == 0.05
    assert not {"val_iou", "val_metrics", "iso_offset", "weights"} & set(meta)


def test_init_matching_takes_the_shared_weights_into_an_attention_encoder(tmp_path: Path, monkeypatch: Any) -> None:
    """`--init-from P --init-matching`: the run keeps its own architecture (here VN attention in blocks 2-3, as the
    chair preset's) and takes every tensor of P whose name and shape match; the attention layers start fresh."""
    from efem_viz.prior import train as train_mod

    src = save_prior(_trained_tiny(), tmp_path / "mug.pt")
    att = dict(train_mod.PRESETS["tiny"], attention_blocks=(2, 3), att_head_dim=8)
    monkeypatch.setitem(train_mod.PRESETS, "tiny-att", att)
    args = _args(tmp_path, tmp_path, preset="tiny-att", init_from=src, init_matching=True)
    prior, from_init = train_mod._build_prior(args, None)
    assert from_init and prior.config.attention_blocks == (2, 3)
    own, mug = prior.state_dict(), load_prior(src, load_codebook=False).state_dict()
    shared = [k for k in own if k in mug]
    assert shared and all(torch.equal(own[k], mug[k].to(own[k].dtype)) for k in shared)
    assert any(k.startswith("encoder.Q_list") for k in own) and not any(k.startswith("encoder.Q_list") for k in mug)
    # without --init-matching the saved prior's own architecture wins, as before
    plain, _ = train_mod._build_prior(_args(tmp_path, tmp_path, preset="tiny-att", init_from=src), None)
    assert plain.config.attention_blocks == ()


# ------------------------------------------------------------------------------------------ growth and bf16
def _trained_tiny(seed: int = 0) -> ShapePrior:
    """A tiny prior whose decoder weights are all non-zero (as a trained one's are)."""
    torch.manual_seed(seed)
    prior = ShapePrior(PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                                   center_hidden=8, n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=2))
    with torch.no_grad():
        for prm in prior.decoder.parameters():
            prm.add_(0.1 * torch.randn_like(prm))
    return prior.double().eval()


def test_widened_decoder_computes_the_same_sdf_in_float64() -> None:
    from efem_viz.prior.widen import widen_decoder

    prior = _trained_tiny()
    grown = widen_decoder(prior, hidden=80, blocks=4, seed=3)
    assert (grown.config.decoder_hidden, grown.config.decoder_blocks) == (80, 4)
    assert grown.dtype == torch.float64 and grown.decoder.fc_in.weight.shape[0] == 80
    g = torch.Generator().manual_seed(1)
    pts = torch.randn(3, 64, 3, generator=g, dtype=torch.float64) * 0.3
    x = torch.randn(3, 500, 3, generator=g, dtype=torch.float64) * 0.5
    lat = prior.encode(pts)
    ref = prior.sdf(x, lat)
    out = grown.sdf(x, grown.encode(pts))
    assert torch.allclose(out, ref, rtol=0, atol=1e-12)
    # negative control: the new units are live, so a nudge of a new fc_out weight changes the function
    with torch.no_grad():
        grown.decoder.fc_out.weight[0, 32:] += 1.0
    assert (grown.sdf(x, grown.encode(pts)) - ref).abs().max() > 1e-6
    # the source prior is untouched, and shrinking is refused
    assert prior.config.decoder_hidden == 32 and torch.equal(prior.sdf(x, lat), ref)
    with pytest.raises(ValueError, match="grow"):
        widen_decoder(prior, hidden=16)


def test_widened_decoder_trains_its_new_units() -> None:
    """One gradient step moves the new units' outgoing weights (a zero-init that gets no gradient would stay
    dead) and the appended blocks' output layers."""
    from efem_viz.prior.widen import widen_decoder

    grown = widen_decoder(_trained_tiny(), hidden=48, blocks=3, seed=0).train()
    g = torch.Generator().manual_seed(2)
    pts = torch.randn(4, 64, 3, generator=g, dtype=torch.float64) * 0.3
    x = torch.randn(4, 300, 3, generator=g, dtype=torch.float64) * 0.5
    loss = (grown.sdf(x, grown.encode(pts)) - 0.1).abs().mean()
    loss.backward()
    dec = grown.decoder
    assert dec.fc_out.weight.grad[0, 32:].abs().max() > 0
    assert dec.block0.fc_1.weight.grad[:32, 32:].abs().max() > 0
    assert dec.block2.fc_1.weight.grad.abs().max() > 0


def test_grown_bf16_run_starts_from_the_source_prior(tmp_path: Path, cache_dir: Path) -> None:
    """--init-from with --grow-decoder-* and --matmul-dtype bfloat16: the iteration-0 validation equals the
    source prior's (the growth preserves the function and validation runs in float32), the run trains, and the
    export has the grown architecture."""
    first = _args(tmp_path / "a", cache_dir, iterations=4, val_every=100, calibrate_iso=False)
    train(first)
    args = _args(tmp_path / "b", cache_dir, iterations=6, val_every=100, init_from=first.resolved_export(),
                 grow_decoder_hidden=48, grow_decoder_blocks=2, matmul_dtype="bfloat16", calibrate_iso=False)
    res = train(args)
    from efem_viz.prior.train import load_objects, validate

    start = load_prior(first.resolved_export(), load_codebook=False).eval()
    ref = validate(start, load_objects(args, "val"), args.sample_config(start.config.n_pcl), seed=args.seed + 99)
    assert res["val_curve"][0]["iou"] == pytest.approx(ref["iou"], abs=1e-6)
    assert res["iteration"] == 6 and all(np.isfinite([c["loss"] for c in res["curve"]]))
    out = load_prior(args.resolved_export(), load_codebook=False)
    assert (out.config.decoder_hidden, out.config.decoder_blocks) == (48, 2)
    with pytest.raises(ValueError, match="matmul_dtype"):
        train(_args(tmp_path / "c", cache_dir, matmul_dtype="float16"))
    with pytest.raises(ValueError, match="init-from"):
        train(_args(tmp_path / "d", cache_dir, grow_decoder_hidden=64))


@pytest.mark.slow
def _small_pack(path: Path, seeds: range) -> Path:
    """A mesh pack of a few low-poly closed shapes (boxes and icospheres): cheap to prepare on any backend."""
    import trimesh

    from efem_viz.geometry.sampling import MeshArrays
    from efem_viz.prior.data import save_mesh_pack

    def source(i: int) -> tuple[str, Any]:
        m = (trimesh.creation.icosphere(subdivisions=1) if i % 2 else
             trimesh.creation.box(extents=[1.0, 0.5 + 0.05 * i, 0.8]))
        return f"shape_{i}", (lambda m=m: MeshArrays(np.asarray(m.vertices), np.asarray(m.faces)))

    return save_mesh_pack([source(i) for i in seeds], path)


def _without_open3d(folder: Path) -> Path:
    """A sitecustomize that makes open3d, trimesh, viser, pybullet, manifold3d, rich, scipy, scikit-image, plyfile
    and ray unimportable: less than the GPU machine has (it has scipy and scikit-image), so the training path is
    shown to need none of them."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(
        "import importlib.abc, sys\n"
        "class _Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.split('.')[0] in {'open3d', 'trimesh', 'viser', 'pybullet', 'manifold3d', 'rich', 'scipy',\n"
        "                                  'skimage', 'plyfile', 'ray'}:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r} (blocked)')\n"
        "sys.meta_path.insert(0, _Block())\n")
    return folder


def test_torch_preparation_gives_the_open3d_data_to_rounding() -> None:
    """The data a GPU machine prepares without open3d (torch signed distance and ray casting) equals open3d's."""
    from efem_viz.data.procedural import make_shape
    from efem_viz.geometry.sampling import MeshArrays
    from efem_viz.prior.data import prepare_object

    cfg = PrepConfig(n_uniform=300, n_near=300, n_surface=100, resolution=24, max_view_points=200)
    mesh = make_shape("mug", 11)
    a = prepare_object(mesh, name="m", cfg=cfg, seed=5, backend="open3d")
    b = prepare_object(MeshArrays(np.asarray(mesh.vertices), np.asarray(mesh.faces)), name="m", cfg=cfg, seed=5,
                       backend="torch")
    for key in ("uni", "nss", "surface", "views", "view_eyes", "view_cos"):
        assert getattr(a, key).shape == getattr(b, key).shape, key
        assert np.abs(getattr(a, key) - getattr(b, key)).max() < 1e-4, key
    assert np.array_equal(a.view_offsets, b.view_offsets) and (a.uni[:, 3] < 0).any()


def test_a_mesh_pack_round_trips_and_a_damaged_one_is_one_line(tmp_path: Path) -> None:
    from efem_viz.prior.data import normalize_mesh, pack_sources, procedural_sources, save_mesh_pack

    srcs = procedural_sources("mug", "train", 3)
    pack = save_mesh_pack(srcs, tmp_path / "p.npz")
    back = pack_sources(pack)
    assert [n for n, _ in back] == [n for n, _ in srcs]
    for (_, f0), (_, f1) in zip(srcs, back):
        m0, m1 = normalize_mesh(f0()), f1()
        assert np.abs(np.asarray(m0.vertices) - m1.vertices).max() < 1e-6 and np.array_equal(m0.faces, m1.faces)
    with np.load(pack) as z:
        data = {k: z[k] for k in z.files}
    bad = dict(data, faces=data["faces"] + 10**6)
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(ValueError, match="face indices outside"):
        pack_sources(tmp_path / "bad.npz")
    np.savez(tmp_path / "lie.npz", **dict(data, vertex_offsets=np.array([0, 10**9, 2 * 10**9, 3 * 10**9])))
    with pytest.raises(ValueError, match="inconsistent offsets"):
        pack_sources(tmp_path / "lie.npz")
    (tmp_path / "cut.npz").write_bytes(pack.read_bytes()[:1000])
    with pytest.raises(ValueError, match="unreadable mesh pack|not an efem-viz mesh pack"):
        pack_sources(tmp_path / "cut.npz")


def test_gpu_training_script_smoke_and_run_without_open3d_counting_iterations(tmp_path: Path, cache_dir: Path) -> None:
    """scripts/train_gpu.sh as it runs on the GPU machine (no open3d, trimesh or viser; data from carried mesh
    packs), here on the CPU: the smoke mode does its 20 steps and leaves a checkpoint; a run resumes the state it
    is given and stops after exactly --steps iterations, leaving the checkpoint, export, resume state (without the
    optimiser's moments) and report. Work is counted; the time budgets are far out of reach."""
    import os
    import subprocess

    first = _args(tmp_path / "a", cache_dir, iterations=3, val_every=100, calibrate_iso=False)
    train(first)
    carry = tmp_path / "carry"
    carry.mkdir()
    _small_pack(carry / "mug_train.npz", range(5))
    _small_pack(carry / "mug_val.npz", range(5, 7))
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "EFEM_TRAIN_DEVICE": "cpu", "EFEM_TRAIN_THREADS": "1", "EFEM_CARRY": str(carry),
           "TMPDIR": str(tmp_path), "PYTHONPATH": str(_without_open3d(tmp_path / "site"))}
    script = str(root / "scripts" / "train_gpu.sh")
    resume = ["--resume-from", str(tmp_path / "a" / "run" / "last.pt"), "--batch-size", "4",
              "--time-budget-min", "600"]
    smoke = subprocess.run(["bash", script, "--smoke", str(tmp_path / "smoke"), *resume], env=env,
                           capture_output=True, text=True, timeout=1800)
    assert smoke.returncode == 0, smoke.stderr[-3000:]
    assert "resumed from" in smoke.stderr and "[train_gpu] torch" in smoke.stderr
    ck = torch.load(tmp_path / "smoke" / "last.pt", weights_only=False)
    assert ck["state"]["iteration"] == 3 + 20
    run = subprocess.run(["bash", script, str(tmp_path / "gpu"), "600", *resume, "--steps", "5"], env=env,
                         capture_output=True, text=True, timeout=1800)
    assert run.returncode == 0, run.stderr[-3000:]
    out = tmp_path / "gpu"
    for name in ("last.pt", "mug.pt", "mug_resume.pt", "mug_training_report.md", "config.json"):
        assert (out / name).is_file(), name
    ck = torch.load(out / "last.pt", weights_only=False)
    assert ck["state"]["iteration"] == 3 + 5 and ck["args"]["device"] == "cpu" and ck["optimizer"] is not None
    shipped = torch.load(out / "mug_resume.pt", weights_only=False)
    assert shipped["optimizer"] is None and shipped["state"]["iteration"] == 3 + 5
    assert not (out / "cache").exists()  # the data cache never travels back
    again = subprocess.run(["bash", script, str(tmp_path / "again"), "600", "--resume-from", str(out / "mug_resume.pt"),
                            "--batch-size", "4", "--time-budget-min", "600", "--steps", "2"], env=env,
                           capture_output=True, text=True, timeout=1800)
    assert again.returncode == 0 and "Adam restarts" in again.stderr, again.stderr[-3000:]
    assert torch.load(tmp_path / "again" / "last.pt", weights_only=False)["state"]["iteration"] == 3 + 5 + 2
    # another prior: its packs, its shipped resume state and settings, its file names
    _small_pack(carry / "kitchen_train.npz", range(4))
    _small_pack(carry / "kitchen_val.npz", range(4, 6))
    shipped = root / "efem_viz" / "weights" / "kitchen_resume.pt"
    shipped_at = torch.load(shipped, weights_only=False)["state"]["iteration"]
    kit = subprocess.run(["bash", script, str(tmp_path / "kit"), "600", "--batch-size", "4", "--n-train", "4",
                          "--n-val", "2", "--time-budget-min", "600", "--steps", "2"],
                         env={**env, "EFEM_CATEGORY": "kitchen"}, capture_output=True, text=True, timeout=1800)
    assert kit.returncode == 0, kit.stderr[-3000:]
    ck = torch.load(tmp_path / "kit" / "last.pt", weights_only=False)
    assert ck["state"]["iteration"] == shipped_at + 2 and ck["args"]["category"] == "kitchen"
    assert ck["args"]["table_side_p"] == 0.5 and (tmp_path / "kit" / "kitchen_resume.pt").is_file()
    bad = subprocess.run(["bash", script, str(tmp_path / "sofa")], env={**env, "EFEM_CATEGORY": "sofa"},
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "EFEM_CATEGORY" in bad.stderr
    assert not (tmp_path / "sofa").exists()


def test_handled_only_training_family_has_a_handle_on_every_mug() -> None:
    from efem_viz.data.procedural import sample_mug_params
    from efem_viz.prior.data import procedural_sources

    every = procedural_sources("mug", "train", 30)
    handled = procedural_sources("mug", "train", 20, handled_only=True)
    seeds = [int(name.split("_")[1]) for name, _ in handled]
    assert all(sample_mug_params(s).handle != "none" for s in seeds)
    cups = [name for name, _ in every if sample_mug_params(int(name.split("_")[1])).handle == "none"]
    assert cups and not set(cups) & {name for name, _ in handled}  # the family today does hold cups
    with pytest.raises(ValueError, match="mugs"):
        procedural_sources("bowl", "train", 3, handled_only=True)


def test_resume_from_a_hostile_checkpoint_is_refused_before_any_work(tmp_path: Path) -> None:
    """`train-prior --resume-from` used to skip the prior checks (a 16 KB file declaring a
    20,000-wide decoder cost 90 s and 6.5 GB). On the full CLI: one line, exit 1, no data prepared."""
    import os
    import subprocess
    import sys

    from efem_viz.prior.model import CHECKPOINT_FORMAT

    cfg = PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16, center_hidden=8,
                      n_pcl=64, k=8, decoder_hidden=20000, decoder_blocks=1).to_dict()
    bad = tmp_path / "bad.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "kind": "train", "name": "mug", "config": cfg,
                "state_dict": {"decoder.fc_in.weight": torch.zeros(2, 2)}, "optimizer": {}, "state": {}}, bad)
    assert bad.stat().st_size < 20_000
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "efem_viz.cli", "train-prior", "--resume-from", str(bad),
                           "--out-dir", str(tmp_path / "run"), "--cache-dir", str(tmp_path / "cache"),
                           "--no-progress"], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(root)})
    lines = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert proc.returncode == 1 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "bad.pt" in lines[0] and ("weights do not fit" in lines[0] or "declares" in lines[0])
    assert not (tmp_path / "cache").exists()
