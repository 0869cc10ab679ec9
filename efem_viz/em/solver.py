"""The EFEM solver: proposals → EM steps (independent, then joint) → reviews → accepted instances.

Reference: efem-method.md §3 (efem-viz is +Z up). Batched over proposals: one decoder pass per step over the
error balls of all live proposals at once (rows of similar size padded into batches, see `decode_rows`),
encoder calls in chunks of `cfg.encode_batch` proposals, eliminations on sparse P×N sets. A dead proposal
costs nothing after its death. Randomness: one NumPy Generator seeded from `seed` draws anchors, Bernoulli masks and all categorical
draws (on the CPU), so a run is reproducible on any device; the network itself is deterministic.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from efem_viz.em.config import EMConfig, schedule
from efem_viz.em.proposals import (
    REASON_POSE,
    REASON_SCALE,
    REASON_SURVIVE,
    AvailableTree,
    Kill,
    Ragged,
    find_duplicates,
    find_inclusions,
    find_too_small,
    init_crops,
    lookup,
    sample_independent,
    sample_joint,
    set_matrix,
)
from efem_viz.em.trace import TraceRecorder, energy_weights

if TYPE_CHECKING:
    import trimesh

    from efem_viz.data.scene import Scene
    from efem_viz.em.results import EMResult

logger = logging.getLogger(__name__)

STAGES: tuple[str, ...] = (
    "m_step", "encode", "neighbourhood", "decode", "score", "eliminate", "review_mesh", "review_pose",
    "review_coverage", "accept",
)


class EMCancelled(RuntimeError):
    """Raised by `run_em` when its `cancel` event is set."""


@dataclass(frozen=True)
class StepInfo:
    """Progress report passed to `on_step` after every EM step."""

    step: int
    """Global step index (0-based, over all episodes)."""
    num_steps: int
    """Planned number of steps (episodes × (t1 + t2)); a run may end earlier when every proposal died."""
    phase: int
    """1 = independent, 2 = joint."""
    active: int
    """Live proposals after this step's eliminations (and review)."""
    elapsed_s: float
    """Seconds since `run_em` started."""
    episode: int = 0
    """Episode of this step."""


def confidence(stationary: float, coverage: float, *, cap: float = 0.4) -> float:
    """Final confidence of an accepted proposal: s_stat · min(coverage, cap) / cap (efem-method.md §3.10)."""
    if not cap > 0:
        raise ValueError(f"coverage cap must be > 0, got {cap}")
    return float(stationary) * min(float(coverage), cap) / cap


# ---------------------------------------------------------------------------------------------- network glue
def _latent_from_numpy(prior: Any, lat: dict[str, np.ndarray]) -> Any:
    import torch

    from efem_viz.prior.model import Latent

    dev = _prior_device(prior)
    dt = _prior_dtype(prior)
    return Latent(
        R=torch.as_tensor(np.asarray(lat["R"]), device=dev, dtype=dt),
        inv=torch.as_tensor(np.asarray(lat["inv"]), device=dev, dtype=dt),
        center=torch.as_tensor(np.asarray(lat["center"]), device=dev, dtype=dt),
        scale=torch.as_tensor(np.asarray(lat["scale"]).reshape(-1), device=dev, dtype=dt),
    )


def _prior_device(prior: Any) -> Any:
    try:
        return next(prior.parameters()).device
    except (StopIteration, AttributeError):
        return "cpu"


def _prior_dtype(prior: Any) -> Any:
    import torch

    try:
        return next(prior.parameters()).dtype
    except (StopIteration, AttributeError):
        return torch.float32


def decode_rows(
    prior: Any,
    latent: Any,
    rag: Ragged,
    points: np.ndarray,
    normals: np.ndarray,
    *,
    chunk: int = 30000,
    normals_within: float | None = None,
    stats: dict[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """SDF and normal angle of every (row, point) entry, decoding all rows in one ragged pass.

    With `normals_within`, a first no-grad pass computes the SDF of every entry and the (3× dearer) gradient
    pass runs only on entries with |d| ≤ normals_within; the others get γ = 180°. The solver sets it to the
    largest SDF threshold any later test applies (τ_D(t), the stationary and output thresholds), so every
    result is unchanged: an entry beyond it fails the SDF test anyway, and its weight exp(−U − E_N) is 0.

    Args:
        prior: the shape prior.
        latent: a batched `Latent` (torch) or a dict of numpy arrays with one latent per row of `rag`.
        rag: the rows' neighbourhoods (scene indices).
        points: (N, 3) float32 scene points, world frame.
        normals: (N, 3) float32 scene unit normals.
        chunk: decoder queries per chunk.
        normals_within: see above; None = normals for every entry.
        stats: if given, "normal_queries" is incremented by the number of gradient queries.

    Returns:
        d (K,) float32 canonical SDF and γ (K,) float32 signed angle (degrees) between the scene normal and
        the decoded normal; one value per entry of `rag`.
    """
    import torch

    if isinstance(latent, dict):
        latent = _latent_from_numpy(prior, latent)
    k = len(rag.idx)
    if k == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    pts_t = torch.from_numpy(np.asarray(points, np.float32))
    nrm_t = torch.from_numpy(np.asarray(normals, np.float32))
    row = rag.row
    if normals_within is None:
        d, g = _decode_padded(prior, latent, rag.idx, row, pts_t, nrm_t, chunk=chunk, with_normals=True)
        if stats is not None:
            stats["normal_queries"] = stats.get("normal_queries", 0.0) + k
        assert g is not None  # with_normals=True always fills the angles
        return d, g
    d, _ = _decode_padded(prior, latent, rag.idx, row, pts_t, nrm_t, chunk=chunk, with_normals=False)
    g = np.full(k, 180.0, np.float32)
    sel = np.flatnonzero(np.abs(d) <= float(normals_within))
    if stats is not None:
        stats["normal_queries"] = stats.get("normal_queries", 0.0) + len(sel)
    if len(sel):
        _, g_sel = _decode_padded(prior, latent, rag.idx[sel], row[sel], pts_t, nrm_t, chunk=chunk,
                                  with_normals=True)
        g[sel] = g_sel
    return d, g


def _decode_padded(
    prior: Any,
    latent: Any,
    idx: np.ndarray,
    row: np.ndarray,
    pts_t: Any,
    nrm_t: Any,
    *,
    chunk: int,
    with_normals: bool,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode entries (row r, scene point idx) grouped by row: rows of similar length are padded into dense
    (G, L, 3) batches of at most `chunk` queries and sent through the prior's batched form (one latent per
    batch row), which avoids gathering a per-query copy of the folded first layer. `row` must be sorted."""
    import torch

    k = len(idx)
    dev = _prior_device(prior)
    dt = _prior_dtype(prior)
    n_rows = int(row[-1]) + 1 if k else 0
    counts = np.bincount(row, minlength=n_rows)
    starts = np.zeros(n_rows + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    present = np.flatnonzero(counts > 0)
    order = present[np.argsort(counts[present], kind="stable")]
    d_out = np.empty(k, np.float32)
    g_out = np.empty(k, np.float32) if with_normals else None
    i = 0
    while i < len(order):
        # grow a group of rows while the padded size stays within the chunk budget
        j = i + 1
        while j < len(order) and (j + 1 - i) * counts[order[j]] <= chunk:
            j += 1
        grp = order[i:j]
        lens = counts[grp]
        lmax = int(lens.max())
        if len(grp) * lmax > chunk and len(grp) == 1:
            lmax = int(lens[0])  # a single row longer than the chunk: one big batch
        ar = np.arange(lmax)
        valid = ar[None, :] < lens[:, None]
        # pad each row with its last entry
        pos = starts[grp][:, None] + np.minimum(ar[None, :], lens[:, None] - 1)
        pidx = torch.from_numpy(idx[pos])
        x = pts_t[pidx].to(device=dev, dtype=dt)
        lat_g = latent[torch.from_numpy(grp).to(latent.R.device)]
        vmask = valid.reshape(-1)
        flat_pos = pos.reshape(-1)[vmask]
        if with_normals:
            sdf, nrm = prior.sdf_and_normals(x, lat_g)
            cos = (nrm.float().cpu() * nrm_t[pidx]).sum(-1).clamp(-1.0, 1.0)
            g = torch.rad2deg(torch.arccos(cos)).reshape(-1).numpy()
            g_out[flat_pos] = g[vmask]  # type: ignore[index]
        else:
            with torch.no_grad():
                sdf = prior.sdf(x, lat_g)
        d_out[flat_pos] = sdf.detach().float().cpu().reshape(-1).numpy()[vmask]
        i = j
    return d_out, g_out


def normals_threshold(cfg: EMConfig, tau_d: float) -> float:
    """The largest |d| at which a decoded normal can still matter at a step with SDF truncation `tau_d`."""
    out = [tau_d, cfg.stat_tau]
    if cfg.gamma_out < 180.0:
        out.append(cfg.out_tau)
    return float(max(out))


def encode_samples(prior: Any, pts: np.ndarray, *, batch: int = 30) -> dict[str, np.ndarray]:
    """Encode (P, M, 3) world point sets in chunks of `batch`; returns numpy latent arrays (float32)."""
    import torch

    dev = _prior_device(prior)
    dt = _prior_dtype(prior)
    parts: dict[str, list[np.ndarray]] = {"R": [], "inv": [], "center": [], "scale": []}
    with torch.no_grad():
        for s in range(0, len(pts), batch):
            x = torch.from_numpy(np.ascontiguousarray(pts[s : s + batch])).to(device=dev, dtype=dt)
            lat = prior.encode(x)
            parts["R"].append(lat.R.detach().float().cpu().numpy())
            parts["inv"].append(lat.inv.detach().float().cpu().numpy())
            parts["center"].append(lat.center.detach().float().cpu().numpy())
            parts["scale"].append(lat.scale.detach().float().cpu().numpy().reshape(-1))
    return {k: np.concatenate(v) for k, v in parts.items()}


def mesh_of_latent(prior: Any, lat: dict[str, np.ndarray], *, resolution: int = 32) -> "trimesh.Trimesh":
    """World-frame mesh of one latent (dict of arrays R (C,3), inv (C,), center (3,), scale ()).

    Uses `efem_viz.prior.meshing.extract_mesh` (coarse-to-fine from resolution/2).
    """
    from efem_viz.prior.meshing import extract_mesh

    one = {k: np.asarray(v)[None] if k != "scale" else np.asarray(v).reshape(1) for k, v in lat.items()}
    coarse = resolution // 2 if resolution % 2 == 0 else None
    return extract_mesh(prior, _latent_from_numpy(prior, one), resolution=resolution, coarse=coarse)


def working_set(points: np.ndarray, voxel: float | None) -> np.ndarray:
    """Indices of the points EM iterates on: one point per `voxel`-sized cell (the first in index order), or
    every point when `voxel` is None/0. Sorted increasingly.

    Args:
        points: (N, 3) float32 world points.
        voxel: cell size (m) or None.

    Returns:
        (N_w,) int64 indices into `points`.
    """
    n = len(points)
    if not voxel:
        return np.arange(n, dtype=np.int64)
    keys = np.floor(np.asarray(points, np.float64) / float(voxel)).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, first = np.unique(flat, return_index=True)
    return np.sort(first).astype(np.int64)


# ---------------------------------------------------------------------------------------------- pool state
@dataclass
class _Pool:
    """Live proposals of an episode, rows in increasing id order."""

    ids: np.ndarray  # (P,) int64
    rag: Ragged  # supports of the current weights
    w: np.ndarray  # (K,) float32 weights (W_out of the last step; crop mask at t = 0)
    d: np.ndarray | None = None  # (K,) last E-step SDF over rag
    gamma: np.ndarray | None = None  # (K,) last E-step normal angles
    latent: dict[str, np.ndarray] | None = None
    stationary: np.ndarray | None = None  # (P,)
    inliers: np.ndarray | None = None  # (P,)

    @property
    def size(self) -> int:
        return int(len(self.ids))

    def keep(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, np.int64)
        self.rag, pos = self.rag.take_rows(rows)
        self.ids = self.ids[rows]
        self.w = self.w[pos]
        if self.d is not None:
            self.d = self.d[pos]
        if self.gamma is not None:
            self.gamma = self.gamma[pos]
        if self.latent is not None:
            self.latent = {k: v[rows] for k, v in self.latent.items()}
        if self.stationary is not None:
            self.stationary = self.stationary[rows]
        if self.inliers is not None:
            self.inliers = self.inliers[rows]


class _Timer:
    def __init__(self) -> None:
        self.t: dict[str, float] = {k: 0.0 for k in STAGES}

    def add(self, key: str, t0: float) -> float:
        now = time.perf_counter()
        self.t[key] = self.t.get(key, 0.0) + now - t0
        return now


# ---------------------------------------------------------------------------------------------- main entry
def run_em(
    scene: "Scene",
    prior: Any,
    cfg: EMConfig | None = None,
    *,
    seed: int = 0,
    device: str = "cpu",
    on_step: Callable[[StepInfo], None] | None = None,
    cancel: threading.Event | None = None,
    anchor_candidates: np.ndarray | None = None,
) -> "EMResult":
    """Segment a scene with EFEM (efem-method.md §3) and record the full trace.

    Args:
        scene: the scan (points (N,3) float32 world metres, +Z up, unit normals).
        prior: a `ShapePrior` (encode / sdf_and_normals / codebook). It is moved to `device` if needed.
        cfg: solver config (default `preset("synthetic_mugs")`).
        seed: seeds the NumPy generator of every random draw.
        device: "cpu" or "cuda" (or a torch device string).
        on_step: called with a `StepInfo` after every step.
        cancel: when set, the run stops at the next check and raises `EMCancelled`.
        anchor_candidates: optional (K,) int scene point indices: the first episode draws its proposal anchors
            only among these (with replacement; on a thinned working set, among the kept points nearest to
            them), e.g. the points around a click for click-to-segment. Crops, E-steps and later episodes still
            use the whole scene. None = every point (the method as specified).

    Returns:
        EMResult with trace, instances, config and `timings`: wall seconds per stage (`STAGES`: m_step, encode,
        neighbourhood, decode, score, eliminate, review_mesh, review_pose, review_coverage, accept), `total`
        (wall), `total_cpu` (process CPU time, all threads), and the counts `decoder_queries`,
        `normal_queries` (the gradient subset) and `encoded_sets`.

    Raises:
        ValueError: bad config, a scene without points, or a prior without the needed methods.
        EMCancelled: `cancel` was set.
    """
    from efem_viz.em.config import preset
    from efem_viz.em.masks import resolve_config
    from efem_viz.em.results import EMResult, Instances

    cfg = resolve_config(cfg if cfg is not None else preset("synthetic_mugs"), prior)
    for meth in ("encode", "sdf_and_normals", "sdf"):
        if not callable(getattr(prior, meth, None)):
            raise ValueError(f"prior {type(prior).__name__} has no {meth}() method")
    points = np.ascontiguousarray(scene.points, np.float32)
    normals = np.ascontiguousarray(scene.normals, np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"scene points must be a non-empty (N, 3) array, got {points.shape}")
    if normals.shape != points.shape:
        raise ValueError(f"scene normals {normals.shape} do not match points {points.shape}")
    if anchor_candidates is not None:
        anchor_candidates = np.asarray(anchor_candidates)
        if anchor_candidates.ndim != 1 or len(anchor_candidates) == 0 or anchor_candidates.dtype.kind not in "iu":
            raise ValueError(f"anchor_candidates must be a non-empty (K,) integer array, got "
                             f"{anchor_candidates.dtype} {anchor_candidates.shape}")
        if anchor_candidates.min() < 0 or anchor_candidates.max() >= len(points):
            raise ValueError(f"anchor_candidates must index the scene's {len(points)} points, got range "
                             f"[{anchor_candidates.min()}, {anchor_candidates.max()}]")
    _move_prior(prior, device)
    was_training = getattr(prior, "training", False)
    if hasattr(prior, "eval"):
        prior.eval()
    try:
        solver = _Solver(scene.name, points, normals, prior, cfg, seed=seed, on_step=on_step, cancel=cancel,
                         anchor_candidates=anchor_candidates)
        inst_rows = solver.run()
    finally:
        if was_training and hasattr(prior, "train"):
            prior.train(True)
    timings = dict(solver.timer.t)
    timings["total"] = time.perf_counter() - solver.t_start
    timings["total_cpu"] = time.process_time() - solver.cpu_start
    timings["decoder_queries"] = float(solver.n_queries)
    timings["encoded_sets"] = float(solver.n_encoded)
    timings["normal_queries"] = float(solver.stats["normal_queries"])
    trace = solver.rec.finish(timings)
    trace.bind(scene, prior)
    instances = Instances.from_rows(inst_rows, category=str(getattr(prior, "name", "object")))
    logger.info(
        "%s: %d instances, %d steps, %.1f s (%s)",
        scene.name, len(instances), trace.num_steps, timings["total"],
        ", ".join(f"{k} {v:.1f}" for k, v in timings.items() if k in STAGES and v > 0.05),
    )
    return EMResult(trace=trace, instances=instances, config=cfg, timings=timings, scene_name=scene.name,
                    num_points=len(points), seed=int(seed))


def _move_prior(prior: Any, device: str) -> None:
    import torch

    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available")
    cur = _prior_device(prior)
    if hasattr(prior, "to") and torch.device(cur).type != dev.type:
        prior.to(dev)


class _Solver:
    def __init__(
        self,
        name: str,
        points: np.ndarray,
        normals: np.ndarray,
        prior: Any,
        cfg: EMConfig,
        *,
        seed: int,
        on_step: Callable[[StepInfo], None] | None,
        cancel: threading.Event | None,
        anchor_candidates: np.ndarray | None = None,
    ) -> None:
        self.name = name
        self.full_points = points
        self.full_normals = normals
        self.n_full = len(points)
        self.work_idx = working_set(points, cfg.work_voxel)
        self.identity = len(self.work_idx) == self.n_full
        self.points = points[self.work_idx] if not self.identity else points
        self.normals = normals[self.work_idx] if not self.identity else normals
        self.n = len(self.points)
        self.anchor_mask: np.ndarray | None = None
        if anchor_candidates is not None:
            self.anchor_mask = self._anchor_mask(points, anchor_candidates)
        # min_size is defined at the scene's resolution; on a thinned working set it scales with the density
        self.min_size = max(1, int(round(cfg.min_size * self.n / self.n_full)))
        self.prior = prior
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.seed = int(seed)
        self.on_step = on_step
        self.cancel = cancel
        self.m = int(cfg.n_pcl or getattr(getattr(prior, "config", None), "n_pcl", 512))
        self.rec = TraceRecorder(cfg, self.n_full, work_idx=self.work_idx, work_min_size=self.min_size)
        self.timer = _Timer()
        self.t_start = time.perf_counter()
        self.cpu_start = time.process_time()
        self.n_queries = 0
        self.n_encoded = 0
        self.stats: dict[str, float] = {"normal_queries": 0.0}
        self.planned_steps = cfg.num_episodes * cfg.steps_per_episode
        cb = getattr(prior, "codebook", None)
        self.ref_scale = float(cb.mean_scale) if cb is not None else 1.0
        if not self.identity and cfg.work_voxel:  # a thinned working set implies work_voxel > 0
            logger.info("%s: EM on a %.1f mm working set of %d of %d points (min_size %d -> %d)", name,
                        cfg.work_voxel * 1000, self.n, self.n_full, cfg.min_size, self.min_size)

    def _anchor_mask(self, points: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """(n,) bool over the working set: the candidates, or (thinned set) the kept point nearest to each."""
        if self.identity:
            mask = np.zeros(self.n, bool)
            mask[candidates] = True
            return mask
        from efem_viz._typeshims import cKDTree

        _, near = cKDTree(self.points).query(points[candidates])
        mask = np.zeros(self.n, bool)
        mask[np.asarray(near, np.int64)] = True
        return mask

    def _check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise EMCancelled(f"EM on {self.name!r} cancelled after {self.rec.num_steps} steps")

    # ------------------------------------------------------------------ episodes
    def run(self) -> list[dict[str, Any]]:
        cfg = self.cfg
        assigned = np.zeros(self.n_full, bool)  # full resolution
        accepted: list[dict[str, Any]] = []
        for ep, n_init in enumerate(cfg.n_init):
            self._check_cancel()
            available_full = ~assigned
            available = available_full[self.work_idx]
            n_avail = int(available.sum())
            if n_avail <= self.min_size:
                logger.info("episode %d skipped: %d available points <= min_size %d", ep, n_avail,
                            self.min_size)
                break
            tree = AvailableTree(self.points, available, crop=cfg.crop)
            full_tree = tree if self.identity else None
            anchors, crops = init_crops(self.points, available, n_init, cfg.r_init, self.rng, crop=cfg.crop,
                                        tree=tree, anchor_mask=self.anchor_mask if ep == 0 else None)
            ids = self.rec.birth(ep, self.work_idx[anchors], cfg.r_init, cfg.r_err)
            self.rec.start_episode(np.flatnonzero(assigned), len(ids))
            pool = _Pool(ids=ids, rag=crops, w=np.ones(len(crops.idx), np.float32))
            last_review: dict[int, dict[str, Any]] = {}
            for t in range(cfg.steps_per_episode):
                if pool.size == 0:
                    break
                self._check_cancel()
                phase = 1 if t < cfg.t1 else 2
                step = self._em_step(pool, tree, ep, t, phase)
                self._eliminate(pool, step, phase)
                if (phase == 1 and t == cfg.t1 - 1) or (phase == 2 and t == cfg.steps_per_episode - 1):
                    if full_tree is None:
                        full_tree = AvailableTree(self.full_points, available_full, crop=cfg.crop)
                    last_review = self._review(pool, full_tree, step, phase)
                elapsed = time.perf_counter() - self.t_start
                self.rec.end_step(pool.size, elapsed)
                if self.on_step is not None:
                    self.on_step(StepInfo(step, self.planned_steps, phase, pool.size, elapsed, ep))
            t0 = time.perf_counter()
            final_step = self.rec.num_steps - 1
            for r, pid in enumerate(pool.ids):
                # every live proposal has been through an E-step, which sets both
                assert pool.stationary is not None and pool.latent is not None
                rev = last_review[int(pid)]
                s_stat = float(pool.stationary[r])
                conf = confidence(s_stat, float(rev["coverage"]), cap=cfg.cov_cap)
                self.rec.death(int(pid), final_step, REASON_SURVIVE, -1, conf)
                accepted.append({**rev, "confidence": conf, "stationary": s_stat,
                                 "center": pool.latent["center"][r], "scale": float(pool.latent["scale"][r])})
                assigned[rev["mask"]] = True
            self.timer.add("accept", t0)
        return accepted

    # ------------------------------------------------------------------ one EM step
    def _em_step(self, pool: _Pool, tree: AvailableTree, ep: int, t: int, phase: int) -> int:
        cfg = self.cfg
        fallback = tree.avail_idx
        t0 = time.perf_counter()
        if phase == 1 or pool.stationary is None:
            samples = sample_independent(pool.rag, pool.w, self.m, cfg.omega, self.rng, fallback=fallback)
        else:
            samples, _ = sample_joint(pool.rag, pool.w, pool.stationary, self.m, cfg.omega, self.rng,
                                      fallback=fallback)
        t0 = self.timer.add("m_step", t0)
        latent = encode_samples(self.prior, self.points[samples], batch=cfg.encode_batch)
        self.n_encoded += len(samples)
        review_step = t in (cfg.t1 - 1, cfg.steps_per_episode - 1)
        if cfg.refine_steps > 0 and pool.size <= cfg.refine_max_pool and (cfg.refine_at == "every_step"
                                                                          or review_step):
            from efem_viz.em.refine import RefineSettings, refine_latents

            latent, _ = refine_latents(self.prior, latent, self.points[samples],
                                       RefineSettings(steps=cfg.refine_steps, lr=cfg.refine_lr, reg=cfg.refine_reg))
        t0 = self.timer.add("encode", t0)
        rag = tree.query(latent["center"], cfg.r_err)
        t0 = self.timer.add("neighbourhood", t0)
        sched = schedule(cfg, t)
        d, gamma = decode_rows(self.prior, latent, rag, self.points, self.normals, chunk=cfg.decode_chunk,
                               normals_within=normals_threshold(cfg, sched[1]), stats=self.stats)
        self.n_queries += len(rag.idx)
        t0 = self.timer.add("decode", t0)
        w, inlier = energy_weights(d, gamma, sched, out_value=cfg.out_value)
        inliers = np.bincount(rag.row[inlier], minlength=pool.size).astype(np.int32)
        # stationary score: samples explained by the shape they produced (outside the ball: placeholder 1000)
        pos = lookup(rag, np.repeat(np.arange(pool.size), self.m).reshape(pool.size, self.m), samples)
        found = pos >= 0
        pc = np.maximum(pos, 0)
        hit = found & (np.abs(d[pc]) < cfg.stat_tau) & (gamma[pc] < cfg.stat_gamma) if len(d) else found
        stationary = hit.mean(axis=1).astype(np.float32) if self.m else np.zeros(pool.size, np.float32)
        pool.rag, pool.w, pool.d, pool.gamma = rag, w, d, gamma
        pool.latent, pool.stationary, pool.inliers = latent, stationary, inliers
        self.timer.add("score", t0)
        return self.rec.step(phase=phase, episode=ep, local=t, sched=sched, ids=pool.ids, latent=latent,
                             stationary=stationary, inliers=inliers, samples=self.work_idx[samples])

    # ------------------------------------------------------------------ eliminations (§3.8)
    def _eliminate(self, pool: _Pool, step: int, phase: int) -> None:
        cfg = self.cfg
        t0 = time.perf_counter()
        assert pool.inliers is not None and pool.d is not None and pool.stationary is not None
        kills: list[Kill] = find_too_small(pool.inliers, self.min_size)
        active = np.ones(pool.size, bool)
        for k in kills:
            active[k.row] = False
        if active.sum() > 1:
            sets = set_matrix(pool.rag, np.abs(pool.d) < cfg.dup_sdf, self.n)
            thr = cfg.dup_iou if phase == 1 else cfg.joint_dup_iou
            dups = find_duplicates(sets, pool.stationary, thr, active=active)
            for k in dups:
                active[k.row] = False
            kills += dups
            if phase == 2 and active.sum() > 1:
                inc = find_inclusions(sets, cfg.joint_incl, active=active)
                for k in inc:
                    active[k.row] = False
                kills += inc
        for k in kills:
            partner = int(pool.ids[k.partner]) if k.partner >= 0 else -1
            self.rec.death(int(pool.ids[k.row]), step, k.reason, partner, k.ratio)
        if kills:
            pool.keep(np.flatnonzero(active))
        self.timer.add("eliminate", t0)

    # ------------------------------------------------------------------ review (§3.9)
    def _review(
        self, pool: _Pool, full_tree: AvailableTree, step: int, phase: int
    ) -> dict[int, dict[str, Any]]:
        cfg = self.cfg
        assert pool.latent is not None and pool.d is not None and pool.gamma is not None
        records: dict[int, dict[str, Any]] = {}
        keep = np.ones(pool.size, bool)
        up = np.array([0.0, 0.0, 1.0])
        t0 = time.perf_counter()
        if self.identity:
            full_rag, d_full, g_full = pool.rag, pool.d, pool.gamma
        else:  # masks and coverage at the scene's full resolution
            full_rag = full_tree.query(pool.latent["center"], cfg.r_err)
            d_full, g_full = decode_rows(
                self.prior, pool.latent, full_rag, self.full_points, self.full_normals, chunk=cfg.decode_chunk,
                normals_within=cfg.out_tau if cfg.gamma_out < 180.0 else -1.0)
            self.n_queries += len(full_rag.idx)
        self.timer.add("review_coverage", t0)
        for r in range(pool.size):
            self._check_cancel()
            pid = int(pool.ids[r])
            lat = {k: v[r] for k, v in pool.latent.items()}
            center = lat["center"].astype(np.float64)
            scale = float(lat["scale"])
            t0 = time.perf_counter()
            if np.isfinite(center).all() and np.isfinite(scale) and scale > 0:
                mesh = mesh_of_latent(self.prior, lat, resolution=cfg.mesh_resolution)
            else:  # a degenerate latent has no shape (it fails the scale check below)
                import trimesh

                mesh = trimesh.Trimesh()
                center = np.nan_to_num(center)
                scale = 1.0
            if len(mesh.faces) and np.isfinite(np.asarray(mesh.vertices)).all():
                samples, fidx = _sample_surface(mesh, cfg.n_store, seed=self.seed * 1_000_003 + pid)
                fnorm = np.asarray(mesh.face_normals, np.float64)[fidx]
                Q = samples - center
            else:
                Q = np.zeros((cfg.n_store, 3))
                fnorm = np.zeros((cfg.n_store, 3))
            t0 = self.timer.add("review_mesh", t0)
            R, R_raw, s_sel, db_sim, nbrs = self._pose(lat, Q, fnorm)
            t0 = self.timer.add("review_pose", t0)
            from efem_viz.geometry.obb import oriented_box

            obb = oriented_box(Q + center, center, R)
            # coverage: completed-shape samples explained by observed points of the ball around Θ_c
            sl = full_rag.row_slice(r)
            ball = full_rag.idx[sl]
            cov = 0.0
            if len(ball) and np.any(Q):
                from efem_viz._typeshims import cKDTree

                dist, j = cKDTree(self.full_points[ball]).query(Q + center)
                dist_c = dist * (s_sel / scale)
                cosang = np.clip((fnorm * self.full_normals[ball][j]).sum(1), -1.0, 1.0)
                ang = np.degrees(np.arccos(cosang))
                cov = float(np.mean((dist_c <= cfg.cov_tau) & (ang <= cfg.cov_gamma)))
            Qt = Q @ R
            radii = np.array([np.linalg.norm(Qt[:, :2], axis=1).max(), np.abs(Qt[:, 2]).max()])
            scale_pass = bool(
                cfg.scale_horizontal[0] <= radii[0] <= cfg.scale_horizontal[1]
                and cfg.scale_height[0] <= radii[1] <= cfg.scale_height[1]
            )
            up_angle = float(np.degrees(np.arccos(np.clip(R_raw[:, 2] @ up, -1.0, 1.0))))
            pose_pass = bool(cfg.up_range[0] <= up_angle <= cfg.up_range[1])
            dsl, gsl = d_full[sl], g_full[sl]
            m_ok = np.abs(dsl) < cfg.out_tau
            if cfg.gamma_out < 180.0:
                m_ok &= gsl < cfg.gamma_out
            mask = ball[m_ok].astype(np.int32)
            rec = {
                "step": step,
                "phase": phase,
                "proposal_id": pid,
                "R": R,
                "R_raw": R_raw,
                "scale_sel": s_sel,
                "db_sim": db_sim,
                "coverage": cov,
                "radii": radii,
                "scale_pass": scale_pass,
                "up_angle": up_angle,
                "pose_pass": pose_pass,
                "obb_center": obb.center,
                "obb_axes": obb.axes,
                "obb_half_extents": obb.half_extents,
                "mask": mask,
                "mesh_vertices": (np.asarray(mesh.vertices) - center).astype(np.float32),
                "mesh_faces": np.asarray(mesh.faces, np.int32),
                "neighbours": np.asarray(nbrs, np.int32),
            }
            self.rec.review(rec)
            records[pid] = rec
            if not scale_pass:
                keep[r] = False
                self.rec.death(pid, step, REASON_SCALE, -1, float(radii.max()))
            elif not pose_pass:
                keep[r] = False
                self.rec.death(pid, step, REASON_POSE, -1, up_angle)
            self.timer.add("review_coverage", t0)
        if not keep.all():
            pool.keep(np.flatnonzero(keep))
        return records

    def _pose(
        self, lat: dict[str, np.ndarray], Q: np.ndarray, fnorm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
        """(R, R_raw, s_sel, db_sim, neighbour ids) from the codebook, or identity without one."""
        cb = getattr(self.prior, "codebook", None)
        if cb is None or not self.cfg.pose_retrieval:
            eye = np.eye(3)
            return eye, eye.copy(), self.ref_scale, float("nan"), np.zeros(0, np.int32)
        from efem_viz.prior.pose import estimate_pose

        one = {k: np.asarray(v)[None] if k != "scale" else np.asarray(v).reshape(1) for k, v in lat.items()}
        est = estimate_pose(self.prior, _latent_from_numpy(self.prior, one), Q, fnorm)
        s_sel = float(est.scale_sel) if np.isfinite(est.scale_sel) and est.scale_sel > 0 else self.ref_scale
        R = np.asarray(est.R, np.float64)
        return R, np.asarray(est.R_raw, np.float64), s_sel, float(est.score_db_sim), np.asarray(est.neighbour_ids)


def _sample_surface(mesh: "trimesh.Trimesh", n: int, *, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n area-weighted samples on a mesh (points (n,3) float64, face index (n,) int)."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(mesh.triangles, np.float64)
    area = np.asarray(mesh.area_faces, np.float64)
    if area.sum() <= 0:
        return np.repeat(tri[:1, 0], n, axis=0), np.zeros(n, np.int64)
    fidx = rng.choice(len(tri), size=n, p=area / area.sum())
    u = rng.random((n, 2))
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    t = tri[fidx]
    pts = t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])
    return pts, fidx
