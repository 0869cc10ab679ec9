"""Output masks at another τ_out (re-derived from a saved run), the per-prior τ_out and its calibration."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from efem_viz.em import EMConfig, EMResult, preset, run_em
from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene
from efem_viz.em.config import DEFAULT_TAU_OUT, resolve_for_prior
from efem_viz.em.masks import instance_distances
from efem_viz.eval.calibrate import calibrate_tau_out, choose_tau_out
from efem_viz.prior.config import prior_category
from efem_viz.eval import evaluate_scene

OFFSET = 0.05
"""SDF offset of the 'blurred' sphere prior: the scan's surface decodes at d ≈ +0.05, outside τ_out = 0.04."""
SPHERE = ("sphere",)


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


def _offset_sphere_prior() -> Any:
    """The analytic sphere prior with every SDF shifted by +OFFSET (a prior whose surfaces sit too far out)."""
    base = type(make_sphere_prior())

    class OffsetSphere(base):  # type: ignore[misc, valid-type]
        def sdf(self, *args: Any, **kwargs: Any) -> Any:
            return super().sdf(*args, **kwargs) + OFFSET

        def sdf_and_normals(self, *args: Any, **kwargs: Any) -> Any:
            d, n = super().sdf_and_normals(*args, **kwargs)
            return d + OFFSET, n

    return OffsetSphere()


def _cfg(**changes: Any) -> EMConfig:
    """The fast preset with 48 proposals and ``changes`` per group (`EMConfig.replace`)."""
    return preset("fast").with_proposals(48).replace(**changes)


def _offset_cfg(**changes: Any) -> EMConfig:
    """Every SDF band but τ_out widened to 0.1, as a run with an offset prior would need (so it finds the spheres)."""
    return _cfg(confidence={"stat_tau": 0.1, "cov_tau": 0.1}, elimination={"dup_sdf": 0.1}, **changes)


@pytest.fixture(scope="module")
def sphere_runs() -> dict[str, Any]:
    scene = make_sphere_scene(seed=11)
    prior = make_sphere_prior()
    offset = _offset_sphere_prior()
    return {
        "scene": scene,
        "prior": prior,
        "offset_prior": offset,
        "exact": run_em(scene, prior, _cfg(), seed=5),
        "thinned": run_em(scene, prior, _cfg(compute={"work_voxel": 0.012}), seed=5),
        "gated": run_em(scene, prior, _cfg(output={"gamma_out": 60.0}), seed=5),
        "offset": run_em(scene, offset, _offset_cfg(), seed=5),
    }


# ---------------------------------------------------------------------------------------------- config
def test_tau_out_resolves_from_the_prior_or_the_spec() -> None:
    prior = make_sphere_prior()
    assert resolve_for_prior(_cfg(), prior).output.tau_out == DEFAULT_TAU_OUT  # no metadata: the spec's 0.04
    prior.metadata = {"tau_out": 0.07}
    assert prior_category(prior).out_tau == 0.07
    assert resolve_for_prior(_cfg(), prior).output.tau_out == 0.07
    assert resolve_for_prior(_cfg(output={"tau_out": 0.05}), prior).output.tau_out == 0.05  # an explicit value wins
    for bad in (float("nan"), -1.0, 0.0, 3.0, "wide", None):
        prior.metadata = {"tau_out": bad}
        assert prior_category(prior).out_tau == DEFAULT_TAU_OUT


def test_tau_out_validation_and_json_round_trip() -> None:
    for bad in (0.0, -0.01, 0.51):
        with pytest.raises(ValueError, match="tau_out"):
            _cfg(output={"tau_out": bad})
    for value in (None, 0.08):
        cfg = _cfg(output={"tau_out": value})
        back = EMConfig.from_json(cfg.to_json())
        assert back == cfg and back.output.out_tau == (DEFAULT_TAU_OUT if value is None else value)


def test_run_records_the_prior_tau_out_and_masks_follow_it(sphere_runs: dict[str, Any]) -> None:
    scene, offset = sphere_runs["scene"], sphere_runs["offset_prior"]
    res = sphere_runs["offset"]
    assert res.config.output.tau_out == DEFAULT_TAU_OUT  # recorded, not None
    # the offset prior puts the scan's surface at d ≈ 0.05: with the spec's 0.04 the masks miss most points
    assert len(res.instances) == 3
    assert max(len(m) for m in res.instances.masks) < 0.3 * min((scene.instance == g).sum() for g in (1, 2, 3))
    offset.metadata = {"tau_out": 0.09}
    try:
        wide = run_em(scene, offset, _offset_cfg(), seed=5)
    finally:
        offset.metadata = {}
    assert wide.config.output.tau_out == 0.09
    explicit = run_em(scene, offset, _offset_cfg(output={"tau_out": 0.09}), seed=5)
    for a, b in zip(wide.instances.masks, explicit.instances.masks, strict=True):
        assert np.array_equal(a, b)
    ev = evaluate_scene([np.asarray(m) for m in wide.instances.masks], wide.instances.confidence, scene.instance)
    assert ev.ap50 == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------- re-derivation
@pytest.mark.parametrize("key", ["exact", "thinned", "gated", "offset"])
def test_rederived_masks_equal_the_run_at_its_own_threshold(sphere_runs: dict[str, Any], key: str) -> None:
    res: EMResult = sphere_runs[key]
    prior = sphere_runs["offset_prior" if key == "offset" else "prior"]
    dist = instance_distances(res, sphere_runs["scene"], prior)
    assert len(dist.idx) == len(res.instances) >= 2
    for got, want in zip(dist.masks(res.config.output.out_tau, res.config.output.gamma_out), res.instances.masks,
                         strict=True):
        assert np.array_equal(np.sort(got), np.sort(want))
    # wider thresholds only add points
    for small, big in zip(dist.masks(0.03), dist.masks(0.08), strict=True):
        assert set(small.tolist()) <= set(big.tolist())


def test_rederived_masks_after_a_save_load_round_trip(sphere_runs: dict[str, Any], tmp_path: Path) -> None:
    res: EMResult = sphere_runs["exact"]
    loaded = EMResult.load(res.save(tmp_path / "r.efem.npz"), scene=sphere_runs["scene"])
    a = instance_distances(res, sphere_runs["scene"], sphere_runs["prior"]).masks(0.06)
    b = instance_distances(loaded, sphere_runs["scene"], sphere_runs["prior"]).masks(0.06)
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x, y)


def test_rederive_rejects_another_scene(sphere_runs: dict[str, Any]) -> None:
    other = make_sphere_scene(seed=3, radii=(0.05,))
    with pytest.raises(ValueError, match="points"):
        instance_distances(sphere_runs["exact"], other, sphere_runs["prior"])


# ---------------------------------------------------------------------------------------------- calibration
def test_calibration_finds_the_wider_band_an_offset_prior_needs(sphere_runs: dict[str, Any]) -> None:
    scene = sphere_runs["scene"]
    cal = calibrate_tau_out([(sphere_runs["offset"], scene)], sphere_runs["offset_prior"], class_names=SPHERE)
    row = dict(zip(cal.taus, cal.ap50, strict=True))
    assert row[0.04] < 0.5 and row[cal.best] == pytest.approx(1.0)
    assert cal.best > OFFSET  # the band must reach past the offset surface
    chosen = cal.taus.index(cal.best)
    assert cal.ap[chosen] >= max(cal.ap) - cal.tolerance and cal.tolerance == 0.005
    assert all(a < max(cal.ap) - cal.tolerance for a in cal.ap[:chosen])  # nothing tighter ties with the best
    assert "<- chosen" in cal.table() and cal.scenes == (scene.name,)


def test_calibration_row_at_the_run_threshold_is_the_run_itself(sphere_runs: dict[str, Any]) -> None:
    scene, res = sphere_runs["scene"], sphere_runs["exact"]
    cal = calibrate_tau_out([(res, scene)], sphere_runs["prior"], candidates=(0.02, 0.04, 0.1),
                            class_names=SPHERE)
    ev = evaluate_scene([np.asarray(m) for m in res.instances.masks], res.instances.confidence, scene.instance)
    k = cal.taus.index(0.04)
    assert math.isclose(cal.ap[k], ev.ap) and math.isclose(cal.ap50[k], ev.ap50)


def test_calibration_ties_choose_the_smaller_threshold(sphere_runs: dict[str, Any]) -> None:
    scene, res = sphere_runs["scene"], sphere_runs["exact"]
    cal = calibrate_tau_out([(res, scene)], sphere_runs["prior"], candidates=(0.0401, 0.04),
                            class_names=SPHERE)
    assert cal.ap[0] == cal.ap[1] and cal.best == 0.04


def test_choose_tau_out_prefers_the_tighter_band_within_the_tolerance() -> None:
    taus = (0.03, 0.04, 0.06, 0.07, 0.10)
    ap = (0.581, 0.621, 0.664, 0.671, 0.673)  # the shape of a real calibration table: a plateau from 0.07 on
    assert choose_tau_out(taus, ap) == 0.07  # 0.671 is within half a point of 0.673; 0.664 is not
    assert choose_tau_out(taus, ap, tolerance=0.0) == 0.10  # plain argmax
    assert choose_tau_out(taus, ap, tolerance=0.01) == 0.06
    assert choose_tau_out(taus, ap, tolerance=1.0) == 0.03
    assert choose_tau_out((0.04, 0.05), (0.5, 0.5), tolerance=0.0) == 0.04  # exact ties: the smaller
    for bad in [((), ()), ((0.04,), (0.5, 0.6))]:
        with pytest.raises(ValueError, match="one AP per candidate"):
            choose_tau_out(*bad)
    with pytest.raises(ValueError, match="tolerance"):
        choose_tau_out(taus, ap, tolerance=-0.1)


def test_calibration_bad_inputs(sphere_runs: dict[str, Any]) -> None:
    scene, res, prior = sphere_runs["scene"], sphere_runs["exact"], sphere_runs["prior"]
    with pytest.raises(ValueError, match="at least one"):
        calibrate_tau_out([], prior)
    with pytest.raises(ValueError, match="candidate"):
        calibrate_tau_out([(res, scene)], prior, candidates=(0.04, 0.9), class_names=SPHERE)
    with pytest.raises(ValueError, match="tolerance"):
        calibrate_tau_out([(res, scene)], prior, class_names=SPHERE, tolerance=float("nan"))
    with pytest.raises(ValueError, match="no ground-truth instance of the classes"):
        calibrate_tau_out([(res, scene)], prior, class_names=("mug",))
    unlabelled = dataclasses.replace(scene, instance=None)
    with pytest.raises(ValueError, match="ground-truth"):
        calibrate_tau_out([(res, unlabelled)], prior, class_names=SPHERE)


def test_calibrate_masks_cli_writes_the_prior_metadata(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import torch

    from efem_viz import cli
    from efem_viz.data.io import save_scene
    from efem_viz.prior.model import PriorConfig, ShapePrior, load_prior, save_prior

    torch.manual_seed(0)
    prior = ShapePrior(PriorConfig(widths=(8, 8, 16, 16), down_blocks=(2,), down_factors=(2,), latent_dim=16,
                                   center_hidden=8, n_pcl=64, k=8, decoder_hidden=32, decoder_blocks=1),
                       name="rand")
    pt = save_prior(prior, tmp_path / "rand.pt", extra={"iteration": 7})
    scene = make_sphere_scene(seed=2, radii=(0.05,))
    sp = save_scene(scene, tmp_path / "one.npz")
    out = tmp_path / "out"
    assert cli.main(["segment", str(sp), "--prior", str(pt), "--out", str(out), "--preset", "fast",
                     "--proposals", "8"]) == 0
    # no calibration yet: the spec's
    assert EMResult.load(out / "one.efem.npz").config.output.tau_out == DEFAULT_TAU_OUT
    assert cli.main(["segment", str(sp), "--prior", str(pt), "--out", str(tmp_path / "o2"), "--preset", "fast",
                     "--proposals", "8", "--tau-out", "0.07"]) == 0
    assert EMResult.load(tmp_path / "o2" / "one.efem.npz").config.output.tau_out == 0.07  # explicit band
    assert cli.main(["segment", str(sp), "--prior", str(pt), "--out", str(tmp_path / "o3"), "--tau-out", "0.9"]) == 1
    assert cli.main(["calibrate-masks", str(out), "--gt", str(sp), "--prior", str(pt), "--classes", "sphere"]) == 0
    assert "tau_out" in capsys.readouterr().out
    assert "tau_out" not in load_prior(pt).metadata  # without --write nothing changes
    js = tmp_path / "cal.json"
    assert cli.main(["calibrate-masks", str(out), "--gt", str(sp), "--prior", str(pt), "--write", "--classes", "sphere",
                     "--candidates", "0.05", "0.07", "--json-out", str(js)]) == 0
    back = load_prior(pt)
    assert back.metadata["tau_out"] in (0.05, 0.07) and back.metadata["iteration"] == 7
    assert back.metadata["tau_out_calibration"]["taus"] == [0.05, 0.07] and js.is_file()
    assert cli.main(["calibrate-masks", str(out), "--gt", str(sp), "--prior", str(pt), "--write", "--classes", "sphere",
                     "--tolerance", "-1"]) != 0  # refused before anything is decoded or written
    assert "--tolerance must be" in capsys.readouterr().err
    assert load_prior(pt).metadata["tau_out"] == back.metadata["tau_out"]
    for k, v in prior.state_dict().items():  # the weights are untouched
        assert torch.equal(v, back.state_dict()[k])
    # errors: no --gt, no matching scene
    assert cli.main(["calibrate-masks", str(out), "--prior", str(pt)]) == 1
    other = save_scene(make_sphere_scene(seed=2, radii=(0.05,), name="other"), tmp_path / "other.npz")
    assert cli.main(["calibrate-masks", str(out), "--gt", str(other), "--prior", str(pt)]) == 1
