"""`bench.explained_decay`: saved runs re-scored exactly at any power, per folder or per solver seed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from efem_viz.data.io import save_scene
from efem_viz.em import preset, run_em
from efem_viz.prior.analytic import make_sphere_prior, make_sphere_scene

from helpers import ROOT, bench_module


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A sphere scene with three saved solves: solver seeds 0 and 1 without the decay, seed 2 with it, and seed 2
    without it in a folder of its own."""
    folder = tmp_path_factory.mktemp("runs")
    plain = tmp_path_factory.mktemp("plain")
    scene = make_sphere_scene(seed=11)
    prior = make_sphere_prior()
    save_scene(scene, folder / f"{scene.name}.ply")
    save_scene(scene, plain / f"{scene.name}.ply")
    cfg = preset("fast").replace(proposals={"n_init": (32,)})
    runs = {}
    for seed, power in ((0, 0.0), (1, 0.0), (2, 2.0)):
        runs[seed] = run_em(scene, prior, cfg.replace(confidence={"explained_decay": power}), seed=seed)
        runs[seed].save(folder / f"{scene.name}_s{seed}.efem.npz")
    runs["plain"] = run_em(scene, prior, cfg, seed=2)
    runs["plain"].save(plain / f"{scene.name}_s2.efem.npz")
    return folder, {"plain_dir": plain, **runs}


def test_a_decayed_run_gives_back_its_method_confidences_and_scores_as_the_plain_one(saved: tuple) -> None:
    mod = bench_module("explained_decay")
    folder, runs = saved
    loaded = mod.load_runs(folder)
    groups = mod.by_seed(loaded)
    assert list(groups) == ["0", "1", "2"] and all(len(g) == 1 for g in groups.values())
    decayed, plain = groups["2"][0][2], mod.load_runs(runs["plain_dir"])[0][2]
    assert decayed.config.confidence.explained_decay == 2.0 and not plain.config.confidence.explained_decay
    np.testing.assert_allclose(mod.method_confidences(decayed), plain.instances.confidence, rtol=1e-6)
    on, off = mod.prepared(groups["2"], None), mod.prepared(mod.load_runs(runs["plain_dir"]), None)
    for power in (0.0, 2.0):
        a, b = mod.score(on, power, None), mod.score(off, power, None)
        assert a == pytest.approx(b, abs=1e-9), power


def test_by_seed_scores_each_seed_as_its_own_set(saved: tuple, tmp_path: Path) -> None:
    folder, _ = saved
    out = tmp_path / "scores.json"
    res = subprocess.run([sys.executable, "-m", "bench.explained_decay", str(folder), "--powers", "0", "2",
                          "--by-seed", "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    rec = json.loads(out.read_text())
    assert sorted(rec) == [f"{folder}#s{k}" for k in range(3)]
    mod = bench_module("explained_decay")
    alone = mod.prepared(mod.by_seed(mod.load_runs(folder))["1"], None)
    assert rec[f"{folder}#s1"]["0"] == pytest.approx(mod.score(alone, 0.0, None), abs=1e-9)
