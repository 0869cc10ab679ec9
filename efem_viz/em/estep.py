"""The E-step (docs/design/efem-method.md §3.6–3.7): annealed parameters, truncated energies, weights, inliers,
stationary score.

One op per function, each vectorised over the flat (K,) entries of a step's error balls (a `Ragged` of P rows):

- `schedule(cfg, t)`: (α_D, τ_D, α_N, τ_N) at local step t (§3.6.3).
- `energies(d, gamma, sched)`: the truncated energies E_D, E_N (§3.6.4).
- `inlier_mask(d, gamma, tau_d=, tau_n=)`: |d| ≤ τ_D and γ ≤ τ_N (§3.6.6).
- `energy_weights(d, gamma, sched)`: the new weights exp(−E_D − E_N) and the inlier flags (§3.6.5–6).
- `stationary_score(rag, samples, d, gamma, tau=, gamma_max=)`: the fraction of each proposal's samples that the
  shape they produced explains (§3.7).
- `normals_threshold(cfg, tau_d)`: the largest |d| at which a decoded normal still enters a test (the decoder
  skips the gradient beyond it).

The solver (`em/solver.py`), the trace replay (`em/replay.py`) and the probe (`em/probe.py`) all call these, so a
replayed step re-derives the solver's numbers with the solver's code. `tests/test_estep.py` checks each against a
per-entry loop of the formulas in float64.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from efem_viz.em.proposals import Ragged, lookup

if TYPE_CHECKING:
    from efem_viz.em.config import EMConfig

Schedule = tuple[float, float, float, float]
"""(α_D, τ_D, α_N, τ_N): the E-step's annealed parameters at one step."""


def schedule(cfg: "EMConfig", t: int) -> Schedule:
    """Annealed E-step parameters at local step t (docs/design/efem-method.md §3.6.3).

    Args:
        cfg: solver config.
        t: step index within the episode (0-based). Phase-2 steps (t >= t1) use the end values.

    Returns:
        (α_D, τ_D, α_N, τ_N).
    """
    lam = 1.0 if t >= cfg.steps.t1 else min(t, cfg.steps.end_step) / cfg.steps.end_step

    def lerp(p: tuple[float, float]) -> float:
        return float(p[0] + (p[1] - p[0]) * lam)

    return lerp(cfg.steps.alpha_d), lerp(cfg.steps.tau_d), lerp(cfg.steps.alpha_n), lerp(cfg.steps.tau_n)


def normals_threshold(cfg: "EMConfig", tau_d: float) -> float:
    """The largest |d| at which a decoded normal can still matter at a step with SDF truncation `tau_d`.

    A normal enters the inlier test and the weights only where |d| ≤ τ_D, the stationary score only where
    |d| < τ_st, and the output mask (when γ_out < 180) only where |d| < τ_out; beyond the largest of these the
    decoder may leave γ unset.

    Args:
        cfg: solver config (`stat_tau`, `gamma_out`, `out_tau`).
        tau_d: τ_D at this step.

    Returns:
        The threshold in canonical SDF units.
    """
    out = [tau_d, cfg.confidence.stat_tau]
    if cfg.output.gamma_out < 180.0:
        out.append(cfg.output.out_tau)
    return float(max(out))


def inlier_mask(d: np.ndarray, gamma: np.ndarray, *, tau_d: float, tau_n: float) -> np.ndarray:
    """The inlier test (docs/design/efem-method.md §3.6.6), in float32 as the solver computes it.

    Args:
        d: (K,) canonical SDF values.
        gamma: (K,) signed normal angles in degrees.
        tau_d: τ_D, the SDF truncation.
        tau_n: τ_N, the normal truncation in degrees.

    Returns:
        (K,) bool: |d| ≤ τ_D and γ ≤ τ_N (NaN fails).
    """
    ad = np.abs(np.asarray(d, np.float32))
    g = np.asarray(gamma, np.float32)
    return (ad <= tau_d) & (g <= tau_n)


def energies(
    d: np.ndarray, gamma: np.ndarray, sched: Schedule, *, out_value: float = 100.0
) -> tuple[np.ndarray, np.ndarray]:
    """The truncated energies (docs/design/efem-method.md §3.6.4), in float32.

    Args:
        d: (K,) canonical SDF values.
        gamma: (K,) signed normal angles in degrees.
        sched: (α_D, τ_D, α_N, τ_N).
        out_value: U, the energy of a truncated term.

    Returns:
        e_d (K,) float32 = α_D·|d| where |d| ≤ τ_D, else U; e_n (K,) float32 = α_N·γ where γ ≤ τ_N, else U.
    """
    a_d, t_d, a_n, t_n = sched
    ad = np.abs(np.asarray(d, np.float32))
    g = np.asarray(gamma, np.float32)
    e_d = np.where(ad <= t_d, np.float32(a_d) * ad, np.float32(out_value))
    e_n = np.where(g <= t_n, np.float32(a_n) * g, np.float32(out_value))
    return e_d, e_n


def energy_weights(
    d: np.ndarray,
    gamma: np.ndarray,
    sched: Schedule,
    *,
    out_value: float = 100.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Truncated energies → new weights and inlier flags (docs/design/efem-method.md §3.6.4–6).

    Args:
        d: (K,) canonical SDF values.
        gamma: (K,) signed normal angles in degrees.
        sched: (α_D, τ_D, α_N, τ_N).
        out_value: U, the energy of a truncated term.

    Returns:
        w (K,) float32 = exp(−E_D − E_N) (NaN/Inf → 0), inlier (K,) bool = |d| ≤ τ_D and γ ≤ τ_N.
    """
    e_d, e_n = energies(d, gamma, sched, out_value=out_value)
    ad = np.abs(np.asarray(d, np.float32))
    g = np.asarray(gamma, np.float32)
    w = np.exp(-(e_d + e_n)).astype(np.float32)
    w[~(np.isfinite(w) & np.isfinite(ad) & np.isfinite(g))] = 0.0
    return w, inlier_mask(ad, g, tau_d=sched[1], tau_n=sched[3])


def stationary_score(
    rag: Ragged,
    samples: np.ndarray,
    d: np.ndarray,
    gamma: np.ndarray,
    *,
    tau: float,
    gamma_max: float,
) -> np.ndarray:
    """The stationary score of every proposal (docs/design/efem-method.md §3.7).

    A sample counts when its point lies in the proposal's error ball and its decoded entry has |d| < τ_st and
    γ < γ_st; a sample outside the ball (the spec's placeholder 1000) never counts. Repeated samples count with
    their multiplicity.

    Args:
        rag: the step's error balls, P rows of sorted point indices (K entries in all).
        samples: (P, M) int point indices each proposal's latent was encoded from (row r: proposal r).
        d: (K,) canonical SDF values of the entries of `rag`.
        gamma: (K,) signed normal angles in degrees of the entries of `rag`.
        tau: τ_st (`EMConfig.confidence.stat_tau`).
        gamma_max: γ_st in degrees (`EMConfig.confidence.stat_gamma`).

    Returns:
        (P,) float32 fraction of each row's M samples explained (zeros when M = 0).
    """
    n_rows, m = samples.shape
    if not m:
        return np.zeros(n_rows, np.float32)
    pos = lookup(rag, np.repeat(np.arange(n_rows), m).reshape(n_rows, m), samples)
    found = pos >= 0
    pc = np.maximum(pos, 0)
    hit = found & (np.abs(d[pc]) < tau) & (gamma[pc] < gamma_max) if len(d) else found
    return hit.mean(axis=1).astype(np.float32)
