"""The E-step's vectorised functions (efem_viz.em.estep) against per-entry loops of docs/design/efem-method.md §3.6–3.7.

The references are written as the spec states them, one entry at a time in float64 Python arithmetic. Inputs are
float32-representable (the solver's precision), so every comparison decides the same way in both; the weights
differ only by float32 rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from efem_viz.em.config import EMConfig, preset
from efem_viz.em.estep import (
    energies,
    energy_weights,
    inlier_mask,
    normals_threshold,
    schedule,
    stationary_score,
)
from efem_viz.em.proposals import Ragged

U = 100.0


def _f32(x: float) -> float:
    return float(np.float32(x))


def _random_entries(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(K,) float64 SDF values and normal angles (float32-representable), with a few NaN/Inf entries."""
    d = rng.normal(0.0, 0.08, k).astype(np.float32).astype(np.float64)
    gamma = rng.uniform(0.0, 180.0, k).astype(np.float32).astype(np.float64)
    bad = rng.choice(k, size=k // 20, replace=False)
    d[bad[: len(bad) // 2]] = np.nan
    gamma[bad[len(bad) // 2 :]] = np.inf
    return d, gamma


def _random_sched(rng: np.random.Generator) -> tuple[float, float, float, float]:
    return (_f32(rng.uniform(1.0, 40.0)), _f32(rng.uniform(0.02, 0.2)), _f32(rng.uniform(0.001, 0.01)),
            _f32(rng.uniform(30.0, 180.0)))


def _naive_entry(d: float, g: float, sched: tuple[float, float, float, float]) -> tuple[float, float, float, bool]:
    """§3.6.4–6 for one entry: (E_D, E_N, w, inlier)."""
    a_d, t_d, a_n, t_n = sched
    e_d = a_d * abs(d) if abs(d) <= t_d else U
    e_n = a_n * g if g <= t_n else U
    w = math.exp(-e_d - e_n)
    if not (math.isfinite(w) and math.isfinite(d) and math.isfinite(g)):
        w = 0.0
    return e_d, e_n, w, (abs(d) <= t_d) and (g <= t_n)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_energies_weights_inliers_match_the_formulas(seed: int) -> None:
    rng = np.random.default_rng(seed)
    d, gamma = _random_entries(rng, 2000)
    sched = _random_sched(rng)
    e_d, e_n = energies(d, gamma, sched, out_value=U)
    w, inlier = energy_weights(d, gamma, sched, out_value=U)
    inl2 = inlier_mask(d, gamma, tau_d=sched[1], tau_n=sched[3])
    assert w.dtype == np.float32 and e_d.dtype == np.float32 and inlier.dtype == bool
    for j in range(len(d)):
        ref_ed, ref_en, ref_w, ref_in = _naive_entry(float(d[j]), float(gamma[j]), sched)
        if math.isfinite(d[j]):
            assert e_d[j] == pytest.approx(ref_ed, rel=1e-6)
        if math.isfinite(gamma[j]):
            assert e_n[j] == pytest.approx(ref_en, rel=1e-6)
        assert w[j] == pytest.approx(ref_w, rel=1e-5, abs=1e-30)
        assert bool(inlier[j]) == ref_in
        assert bool(inl2[j]) == ref_in
    assert inlier.any() and (~inlier).any()  # both branches exercised


def test_weights_at_the_truncation_edges() -> None:
    sched = (_f32(30.0), _f32(0.07), _f32(0.006), _f32(60.0))
    d = np.array([sched[1], -sched[1], np.nextafter(np.float32(sched[1]), np.float32(1.0))], np.float64)
    gamma = np.array([sched[3], 0.0, 0.0], np.float64)
    w, inlier = energy_weights(d, gamma, sched, out_value=U)
    for j in range(3):
        _, _, ref_w, ref_in = _naive_entry(float(d[j]), float(gamma[j]), sched)
        assert bool(inlier[j]) == ref_in
        assert w[j] == pytest.approx(ref_w, rel=1e-5, abs=1e-30)
    assert inlier.tolist() == [True, True, False]


def _naive_stationary(rows: list[list[int]], samples: np.ndarray, d: np.ndarray, gamma: np.ndarray,
                      tau: float, gamma_max: float) -> list[float]:
    """§3.7: per proposal, the fraction of its M samples (with multiplicity) whose D row has |d| < τ_st and
    γ < γ_st; a sample outside the error ball carries the placeholder 1000 and never counts."""
    out = []
    flat = 0
    for r, row in enumerate(rows):
        entry = {idx: flat + k for k, idx in enumerate(row)}
        flat += len(row)
        hits = 0
        for s in samples[r]:
            k = entry.get(int(s))
            dd, gg = (float(d[k]), float(gamma[k])) if k is not None else (1000.0, 1000.0)
            hits += int(abs(dd) < tau and gg < gamma_max)
        out.append(hits / samples.shape[1])
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_stationary_score_matches_the_formula(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_points, n_rows, m = 200, 6, 40
    rows = [sorted(rng.choice(n_points, size=int(rng.integers(0, 60)), replace=False).tolist()) for _ in range(n_rows)]
    rag = Ragged.from_lists(rows)
    k = len(rag.idx)
    d = rng.normal(0.0, 0.05, k).astype(np.float32)
    gamma = rng.uniform(0.0, 90.0, k).astype(np.float32)
    # half the samples from the row's own ball (with repeats), half anywhere (some outside the ball)
    samples = np.empty((n_rows, m), np.int64)
    for r, row in enumerate(rows):
        inside = rng.choice(row, size=m // 2) if row else rng.integers(0, n_points, m // 2)
        samples[r] = np.concatenate([inside, rng.integers(0, n_points, m - m // 2)])
    tau, gamma_max = _f32(0.04), _f32(45.0)
    got = stationary_score(rag, samples, d, gamma, tau=tau, gamma_max=gamma_max)
    assert got.dtype == np.float32 and got.shape == (n_rows,)
    ref = _naive_stationary(rows, samples, d.astype(np.float64), gamma.astype(np.float64), tau, gamma_max)
    np.testing.assert_allclose(got, np.array(ref), rtol=0, atol=1e-7)


def test_stationary_score_without_samples_or_entries() -> None:
    rag = Ragged.from_lists([[1, 2], [3]])
    assert stationary_score(rag, np.zeros((2, 0), np.int64), np.zeros(3, np.float32), np.zeros(3, np.float32),
                            tau=0.04, gamma_max=45.0).tolist() == [0.0, 0.0]
    empty = Ragged.from_lists([[], []])
    got = stationary_score(empty, np.array([[1, 2], [3, 3]]), np.zeros(0, np.float32), np.zeros(0, np.float32),
                           tau=0.04, gamma_max=45.0)
    assert got.tolist() == [0.0, 0.0]


def _naive_schedule(cfg: EMConfig, t: int) -> tuple[float, float, float, float]:
    """§3.6.3: λ(t) = min(t, T_e)/T_e, linear from start to end; phase-2 steps (t ≥ t1) use the end values."""
    lam = 1.0 if t >= cfg.steps.t1 else min(t, cfg.steps.end_step) / cfg.steps.end_step
    vals = []
    for start, end in (cfg.steps.alpha_d, cfg.steps.tau_d, cfg.steps.alpha_n, cfg.steps.tau_n):
        vals.append(start + (end - start) * lam)
    return vals[0], vals[1], vals[2], vals[3]


@pytest.mark.parametrize("name", ["synthetic", "real", "real_paper", "fast"])
def test_schedule_matches_the_formula(name: str) -> None:
    cfg = preset(name)
    for t in range(cfg.steps.per_episode):
        assert schedule(cfg, t) == pytest.approx(_naive_schedule(cfg, t), rel=1e-12)
    ends = tuple(p[1] for p in (cfg.steps.alpha_d, cfg.steps.tau_d, cfg.steps.alpha_n, cfg.steps.tau_n))
    assert schedule(cfg, cfg.steps.t1) == pytest.approx(ends)


def test_normals_threshold_covers_every_test_that_reads_a_normal() -> None:
    cfg = preset("synthetic")
    assert normals_threshold(cfg, 0.01) == pytest.approx(max(0.01, cfg.confidence.stat_tau, *(
        [cfg.output.out_tau] if cfg.output.gamma_out < 180.0 else [])))
    assert normals_threshold(cfg.replace(output={"gamma_out": 180.0}, confidence={"stat_tau": 0.02}),
                             0.3) == pytest.approx(0.3)
    assert normals_threshold(cfg.replace(output={"gamma_out": 90.0, "tau_out": 0.5}, confidence={"stat_tau": 0.02}),
                             0.3) == pytest.approx(0.5)
