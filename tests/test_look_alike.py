"""The learned mug-vs-look-alike score (`efem_viz.em.look_alike`): fitting, shipped models, hostile files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from efem_viz.em import look_alike
from efem_viz.em.config import ConfidenceSettings, EMConfig, preset
from efem_viz.em.look_alike import FEATURES, LookAlikeModel, fit_logistic, load_model, review_features


def _features(**kw: float) -> dict[str, float]:
    base = dict(stationary=0.3, coverage=0.1, pose=0.5, radius=0.045, half_height=0.05, up_angle=10.0,
                seen_through=0.05, mask_size=900)
    base.update(kw)
    return review_features(**base)  # type: ignore[arg-type]


def test_review_features_neutral_values_for_missing_measurements() -> None:
    f = _features(pose=float("nan"), up_angle=float("nan"), seen_through=float("nan"))
    assert list(f) == list(FEATURES)
    assert f["pose score"] == 0.4 and f["cos up angle"] == 0.0 and f["seen-through"] == 0.0
    assert f["radius (cm)"] == pytest.approx(4.5) and f["log mask size"] == pytest.approx(math.log(900))


def test_fit_separates_and_probabilities_follow_the_weights() -> None:
    rng = np.random.default_rng(0)
    small = rng.normal(4.5, 0.4, 200)  # mugs: radius ~4.5 cm
    big = rng.normal(6.5, 0.4, 200)  # look-alikes: ~6.5 cm
    x = np.r_[small, big][:, None]
    y = np.r_[np.ones(200), np.zeros(200)]
    m = fit_logistic(x, y, ["radius (cm)"], l2=0.1)
    assert m.weights[0] < 0  # wider is less mug-like
    p = m.probs(x)
    assert (p[:200] > 0.5).mean() > 0.95 and (p[200:] < 0.5).mean() > 0.95
    one = m.prob(_features(radius=0.045))
    assert one == pytest.approx(float(m.probs(np.array([[4.5]]))[0]))
    assert m.prob(_features(radius=0.045)) > m.prob(_features(radius=0.065))
    # confidence: times the solver's, or alone
    assert m.confidence(0.5, _features()) == pytest.approx(0.5 * m.prob(_features()))
    alone = LookAlikeModel(m.names, m.mean, m.scale, m.weights, m.bias, times_confidence=False)
    assert alone.confidence(0.5, _features()) == pytest.approx(m.prob(_features()))


def test_save_load_round_trip(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(look_alike, "MODELS", tmp_path)
    load_model.cache_clear()
    m = LookAlikeModel(("pose score", "radius (cm)"), (0.4, 5.0), (0.1, 1.0), (1.0, -2.0), -0.5, "test", False)
    m.save(tmp_path / "t1.json")
    assert load_model("t1") == m
    load_model.cache_clear()


@pytest.mark.parametrize("body", [
    b"not json",
    json.dumps({"names": ["rm -rf"], "mean": [0], "scale": [1], "weights": [1], "bias": 0}).encode(),
    json.dumps({"names": ["pose score"], "mean": [0], "scale": [0], "weights": [1], "bias": 0}).encode(),
    json.dumps({"names": ["pose score"], "mean": [0], "scale": [1], "weights": [1e300], "bias": 0}).encode(),
    json.dumps({"names": ["pose score"], "mean": [0, 1], "scale": [1], "weights": [1], "bias": 0}).encode(),
    json.dumps({"names": ["pose score"], "mean": ["0"], "scale": [1], "weights": [1], "bias": 0}).encode(),
    json.dumps({"names": ["pose score"], "mean": [0], "scale": [1], "weights": [1], "bias": 0,
                "times_confidence": "yes"}).encode(),
    b"[" * 100_000,
    b" " * 70_000,
    b'{"names": ["pose score"], "mean": [0], "scale": [1], "weights": [1], "bias": 1' + b"0" * 400 + b"}",
    json.dumps({"names": ["pose score"], "mean": [0], "scale": [1e-310], "weights": [1], "bias": 0}).encode(),
])
def test_hostile_model_files_get_one_clear_error(tmp_path, monkeypatch, body: bytes) -> None:
    monkeypatch.setattr(look_alike, "MODELS", tmp_path)
    load_model.cache_clear()
    (tmp_path / "bad.json").write_bytes(body)
    with pytest.raises(ValueError, match="look-alike model"):
        load_model("bad")
    load_model.cache_clear()


@pytest.mark.parametrize("kind", ["dev_zero_link", "directory", "huge_sparse"])
def test_model_files_that_are_not_small_plain_files_are_refused_without_reading_them(
        tmp_path, monkeypatch, kind: str) -> None:
    """A link to /dev/zero used to exhaust memory, a 300 MB file cost 331 MB, a directory named `*.json` escaped as
    an uncaught error: at most the 64 KB cap is read, and each is one ValueError naming the model."""
    import os
    import resource

    monkeypatch.setattr(look_alike, "MODELS", tmp_path)
    load_model.cache_clear()
    target = tmp_path / "bad.json"
    if kind == "dev_zero_link":
        os.symlink("/dev/zero", target)
    elif kind == "directory":
        target.mkdir()
    else:
        with open(target, "wb") as fh:
            fh.truncate(300 << 20)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ValueError, match="look-alike model"):
        load_model("bad")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 50 * 1024  # KB: nothing was inflated
    load_model.cache_clear()


@pytest.mark.parametrize("name", ["../etc/passwd", "", "a" * 65, "no_such_model", "x.json"])
def test_only_shipped_names(name: str) -> None:
    with pytest.raises(ValueError, match="look-alike model"):
        load_model(name)
    if name == "no_such_model":  # a plain name: a config (a saved result) holding it still loads
        EMConfig(confidence=ConfidenceSettings(look_alike=name)).validate()
    else:
        with pytest.raises(ValueError, match="look-alike model"):
            EMConfig(confidence=ConfidenceSettings(look_alike=name)).validate()


def test_values_that_are_not_numbers_and_missing_measurements() -> None:
    with pytest.raises(ValueError, match="finite"):
        LookAlikeModel(("pose score",), (True,), (1.0,), (1.0,), 0.0)  # a bool is not a number
    with pytest.raises(ValueError, match="category"):
        LookAlikeModel(("pose score",), (0.0,), (1.0,), (1.0,), 0.0, category="../x")
    with pytest.raises(ValueError, match="features"):
        LookAlikeModel(([1],), (0.0,), (1.0,), (1.0,), 0.0)  # type: ignore[arg-type]
    f = _features(stationary=float("nan"), coverage=float("nan"), radius=float("nan"), half_height=float("inf"))
    assert all(math.isfinite(v) for v in f.values())


def test_shipped_models_load_and_configure() -> None:
    names = look_alike.available_models()
    assert names, "at least one shipped model"
    for name in names:
        m = load_model(name)
        assert 0.0 < m.prob(_features()) < 1.0
        cfg = preset("real").replace(confidence={"look_alike": name})
        assert EMConfig.from_json(cfg.to_json()).confidence.look_alike == name


def test_solver_confidence_is_the_models_and_instances_do_not_change(tmp_path, monkeypatch) -> None:
    """`EMConfig.confidence.look_alike`: each accepted fit's confidence is the model's (from its last review and
    stationary score, as `bench/learned_confidence.py` scores saved runs), and the instances are those of the same run
    without it (one episode: the confidence decides no elimination)."""
    import torch

    from efem_viz import em
    from efem_viz.prior import analytic

    torch.set_num_threads(1)
    monkeypatch.setattr(look_alike, "MODELS", tmp_path)
    load_model.cache_clear()
    model = LookAlikeModel(("radius (cm)", "log coverage"), (5.0, -3.0), (1.0, 1.0), (-1.5, 0.7), 0.2,
                           times_confidence=True, category="sphere")
    model.save(tmp_path / "toy.json")
    LookAlikeModel(*[getattr(model, k) for k in ("names", "mean", "scale", "weights", "bias")],
                   category="mug").save(tmp_path / "other.json")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.008, name="spheres")
    prior = analytic.make_sphere_prior()
    cfg = em.preset("fast").with_proposals(16).replace(elimination={"min_size": 30})
    plain = em.run_em(scene, prior, cfg, seed=0)
    learned = em.run_em(scene, prior, cfg.replace(confidence={"look_alike": "toy"}), seed=0)
    other = em.run_em(scene, prior, cfg.replace(confidence={"look_alike": "other"}),
                      seed=0)  # scores mugs: spheres keep theirs
    load_model.cache_clear()
    assert np.array_equal(other.instances.confidence, plain.instances.confidence)
    assert len(plain.instances) == len(learned.instances) > 0
    before = {int(i): (sorted(m), float(c)) for i, m, c in zip(plain.instances.ids, plain.instances.masks,
                                                                 plain.instances.confidence)}
    assert {int(i): sorted(m) for i, m in zip(learned.instances.ids, learned.instances.masks)} == {
        i: v[0] for i, v in before.items()}
    for k in range(len(learned.instances)):
        rev = learned.trace.reviews(int(learned.instances.ids[k]))[-1]
        f = review_features(stationary=float(learned.instances.stationary[k]), coverage=float(rev.coverage),
                            pose=float(rev.db_sim), radius=float(rev.radii[0]), half_height=float(rev.radii[1]),
                            up_angle=float(rev.up_angle), seen_through=float(rev.seen_through),
                            mask_size=len(rev.mask))
        expected = model.confidence(before[int(learned.instances.ids[k])][1], f)
        assert float(learned.instances.confidence[k]) == pytest.approx(expected, rel=1e-5)
