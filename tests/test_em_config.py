"""The solver's configuration (`efem_viz.em.config`): its groups, the names a user types, saved configs old and new."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from efem_viz.em.config import (
    FLAT_NAMES,
    GROUPS,
    PRESETS,
    EMConfig,
    preset,
    setting_names,
)

SAMPLES = Path(__file__).resolve().parents[1] / "sample_scenes"


def test_the_config_is_a_few_typed_groups() -> None:
    top = [f.name for f in dataclasses.fields(EMConfig)]
    assert len(top) <= 12 and top[:2] == ["name", "domain"] and set(top[2:]) == set(GROUPS)
    cfg = preset("real")
    for group, cls in GROUPS.items():
        assert isinstance(getattr(cfg, group), cls)
    # every setting has one dotted name, and every flat name of before points at one of them
    names = setting_names()
    assert len(names) == len(set(names))
    assert set(FLAT_NAMES.values()) <= set(names) and len(FLAT_NAMES) == 61  # the 61 flat fields, frozen


@pytest.mark.parametrize("name", PRESETS)
def test_presets_round_trip_through_json(name: str) -> None:
    cfg = preset(name)
    text = cfg.to_json()
    assert isinstance(json.loads(text)["elimination"], dict)
    assert EMConfig.from_json(text) == cfg


def test_chair_and_kitchen_solves_lower_confidences_by_what_better_fits_hold() -> None:
    """The explained-share decay comes with the prior's category: chair and kitchen fits in synthetic scenes rank
    under the fits of what they straddle; mugs keep the method's confidences (the decay demotes mugs packed close
    together in boxes), and so does every category on real captures, where it was never measured. An explicit
    value wins; a prior saved with category settings from before the field takes its known category's."""
    from types import SimpleNamespace

    from efem_viz.em.config import resolve_for_prior
    from efem_viz.prior.config import CategorySettings, category_settings

    assert all(preset(name).confidence.explained_decay is None for name in PRESETS)

    def decay(preset_name: str, category: str, metadata: dict | None = None, **change: float) -> float | None:
        cfg = preset(preset_name)
        if change:
            cfg = cfg.replace(confidence=change)
        prior = SimpleNamespace(name=category, metadata=metadata or {})
        return resolve_for_prior(cfg, prior).confidence.explained_decay

    assert [decay(p, c) for p in ("chairs", "synthetic") for c in ("chair", "kitchen", "mug")] == [2, 2, 0] * 2
    assert [decay("real", c) for c in ("chair", "kitchen", "mug")] == [0, 0, 0]
    assert decay("synthetic", "mug", explained_decay=1.5) == 1.5 and decay("chairs", "chair", explained_decay=0) == 0
    saved = category_settings("kitchen").to_dict()
    assert CategorySettings.from_dict(saved) == category_settings("kitchen")
    del saved["explained_decay"]
    assert decay("synthetic", "kitchen", {"category": saved}) == 2.0
    with pytest.raises(ValueError, match="explained_decay"):
        CategorySettings(name="x", explained_decay={"synthetic": -1.0})
    with pytest.raises(ValueError, match="capture domain"):
        CategorySettings(name="x", explained_decay={"moon": 1.0})


def test_changes_by_group_by_dotted_name_and_by_old_flat_name_agree() -> None:
    base = preset("synthetic")
    by_group = base.replace(elimination={"min_size": 150, "inclusion": "swap"}, free_space={"margin": 0.02})
    by_name = base.with_values({"elimination.min_size": 150, "elimination.inclusion": "swap",
                                "free_space.margin": 0.02})
    by_flat = base.with_values({"min_size": 150, "inclusion": "swap", "seen_through_margin": 0.02})
    assert by_group == by_name == by_flat
    assert by_group.elimination.min_size == 150 and by_group.free_space.enabled
    assert base.elimination.min_size == 300  # frozen: the preset itself is untouched
    # lists (JSON, literal_eval of a command line) become tuples
    assert base.with_values({"steps.tau_d": [0.2, 0.1]}).steps.tau_d == (0.2, 0.1)


def test_unknown_or_bad_settings_are_one_clear_line() -> None:
    base = preset("fast")
    with pytest.raises(ValueError, match=r"unknown solver setting 'elimination.min_sise'; did you mean "
                                         r"elimination.min_size"):
        base.with_values({"elimination.min_sise": 10})
    with pytest.raises(ValueError, match="unknown solver setting 'bogus'"):
        base.with_values({"bogus": 1})
    with pytest.raises(ValueError, match=r"unknown EliminationSettings field\(s\) \['min_sise'\]"):
        base.replace(elimination={"min_sise": 10})
    with pytest.raises(ValueError, match="unknown EMConfig field"):
        base.replace(min_size=10)
    with pytest.raises(ValueError, match="mesh_resolution must be in"):
        base.with_values({"review.mesh_resolution": 600})
    with pytest.raises(ValueError, match="r_init = inf: must be float"):
        base.with_values({"proposals.r_init": float("inf")})
    with pytest.raises(ValueError, match="unknown EMConfig fields in saved config"):
        EMConfig.from_dict({**preset("fast").to_dict(), "colour": 1})
    for bad in (base.to_dict(), {"name": "x"}):
        err = None
        try:
            EMConfig.from_dict({**bad, "steps": {"t1": "many"}})
        except ValueError as e:
            err = str(e)
        assert err is not None and "\n" not in err and "t1" in err


def test_a_trace_saved_with_the_flat_config_loads_grouped(tmp_path: Path) -> None:
    """Results written before the grouping carry a flat config of 63 fields (here: the one a real-frame bench
    record of that time saved, the `real` preset of then with 400 proposals): a trace with it loads, grouped, every
    flat value in its group."""
    from efem_viz.em.results import EMResult

    record = SAMPLES.parent / "bench" / "results" / "real" / "real_fs_final_2026-12-06.json"
    flat = json.loads(record.read_text())["config"]
    assert len(flat) == 63 and "seen_through_margin" in flat and "free_space" not in flat
    with np.load(SAMPLES / "real_tabletop_6.efem.npz", allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for key in ("config_json", "trace/config_json"):
        arrays[key] = np.array(json.dumps(flat))
    old = tmp_path / "old.efem.npz"
    np.savez_compressed(old, **arrays)
    res = EMResult.load(old)
    assert res.config == EMConfig.from_dict(flat) and res.trace.config == res.config
    assert res.config.free_space.margin == flat["seen_through_margin"]
    assert res.config.free_space.final is flat["seen_through_final"] is True
    assert res.config.confidence.look_alike == flat["mug_model"]
    assert res.config.proposals.n_init == tuple(flat["n_init"]) == (400,)
    assert res.config.proposals.anchor_min_height is None  # a setting that did not exist then: its default
    for name, dotted in FLAT_NAMES.items():
        group, field = dotted.split(".")
        got = getattr(getattr(res.config, group), field)
        assert (list(got) if isinstance(got, tuple) else got) == flat[name], name
