"""`EMTrace`: everything an EFEM run did, step by step, stored compactly (docs/design/efem-method.md §3.11).

Stored per step (global step index over all episodes): phase, episode, step within the episode, the schedule
(α_D, τ_D, α_N, τ_N), and for every proposal that took part (a "row"): its id, latent (float32, exact replay),
stationary score, inlier count and the M sampled point indices (int32). Stored per proposal: birth (episode,
anchor, r_init, r_err, first step) and death (step, reason, partner, ratio). Stored per review (end of each
phase) and proposal: pose, OBB, coverage, codebook similarity, scale radii, up angle, pass flags, the
tentative mask and the mesh (vertices float16 relative to Θ_c, faces int32).

Not stored: the weights over the scene and the decoded shapes. `em.replay.TraceReplay.view` re-derives them
from the stored latents with the same code the solver uses (`em.estep.energy_weights`), and caches the result (LRU).
The weights that produced step t's samples are `W_out` of step t−1; at the first step of an episode they are
the crop mask.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np

from efem_viz.em.config import EMConfig
from efem_viz.em.rules import LEGACY_REASONS, REASON_SURVIVE, REVIEW_COLUMNS, ReviewRecord, reason_names

if TYPE_CHECKING:
    import trimesh


logger = logging.getLogger(__name__)

TRACE_SCHEMA_VERSION = 1


class DeathEvent(NamedTuple):
    """A proposal's termination (`reason` one of the trace's `reason_names`; `survive` = accepted).

    `ratio` depends on the reason: the inlier count ("proposal too small"), the IoU or inclusion ratio with
    `partner` ("duplicated", "included"; "includes a better fit": the included fit's overlap), the largest scale
    radius in metres ("scale-fail"), the up-axis angle in degrees ("pose-fail"), or the confidence ("survive").
    `partner` is −1 unless a duplicate/inclusion.
    """

    step: int
    proposal_id: int
    reason: str
    partner: int
    ratio: float


class ProposalView(NamedTuple):
    """What the viewer shows for one proposal at one step (Fig. S9), re-derived on demand.

    Attributes:
        proposal_id: the proposal.
        step: the global step of the record shown (the requested step, or the death step if it died before).
        weights: (N,) float32 W_in over the scene: the weights that produced this step's samples (in the
            joint phase the samples come from the part of W_in this proposal won in the competition).
        sample_idx: (M,) int32 sampled scene indices (with repeats).
        sampled_points: (M, 3) float32 world points of the samples.
        mesh: the decoded shape of this step's latent (world frame), or None (no prior / not asked).
        scores: {"stationary", "inliers", and for a review step "coverage", "db_sim", ...}.
        schedule: {"alpha_d", "tau_d", "alpha_n", "tau_n"} at this step.
        alive: False when the proposal is dead at (the end of) the requested step.
        death: (step, reason, partner, ratio) or None while it lives (accepted ones: reason "survive").
        latent: dict of this step's latent arrays (R (C,3), inv (C,), center (3,), scale ()).
    """

    proposal_id: int
    step: int
    weights: np.ndarray
    sample_idx: np.ndarray
    sampled_points: np.ndarray
    mesh: "trimesh.Trimesh | None"
    scores: dict[str, float]
    schedule: dict[str, float]
    alive: bool
    death: tuple[int, str, int, float] | None
    latent: dict[str, np.ndarray]
    category: str = ""
    """Category of the proposal's prior ("" for traces that predate category tables)."""


def _ragged_to_npz(prefix: str, values: np.ndarray, offsets: np.ndarray, out: dict[str, np.ndarray]) -> None:
    out[prefix] = values
    out[prefix + "_offsets"] = np.asarray(offsets, np.int64)


def _scalar(x: Any) -> Any:
    """A stored scalar as the Python type of its record field (bool, int or float)."""
    kind = np.asarray(x).dtype.kind
    return bool(x) if kind == "b" else int(x) if kind in "iu" else float(x)


def _ragged_get(values: np.ndarray, offsets: np.ndarray, i: int) -> np.ndarray:
    return values[int(offsets[i]) : int(offsets[i + 1])]


def _offsets(lengths: list[int] | np.ndarray) -> np.ndarray:
    out = np.zeros(len(lengths) + 1, np.int64)
    if len(lengths):
        np.cumsum(np.asarray(lengths, np.int64), out=out[1:])
    return out


@dataclass(frozen=True)
class EMTrace:
    """The recorded EM run: frozen arrays (+ the config and name tables). `em.replay.TraceReplay` binds it to
    the scene and prior(s) to re-derive weights and views.

    Step arrays have length T (global steps), row arrays one entry per (step, live proposal), proposal arrays
    one entry per proposal id (ids are 0..P−1 in creation order), review arrays one entry per (review,
    proposal).
    """

    config: EMConfig
    num_points: int
    # ---- steps (T,)
    step_phase: np.ndarray
    """(T,) int8: 1 = independent, 2 = joint."""
    step_episode: np.ndarray
    """(T,) int16 episode of each step."""
    step_local: np.ndarray
    """(T,) int16 step index within its episode (drives the schedule)."""
    schedule: np.ndarray
    """(T, 4) float32 (α_D, τ_D, α_N, τ_N)."""
    active_count: np.ndarray
    """(T+1,) int32: live proposals before step 0, then after each step's eliminations (and review)."""
    step_elapsed: np.ndarray
    """(T,) float32 seconds since the run started, at the end of each step (review included)."""
    row_offsets: np.ndarray
    """(T+1,) int64: rows of step t are row_offsets[t]:row_offsets[t+1]."""
    # ---- rows (R,)
    row_id: np.ndarray
    """(R,) int32 proposal id (increasing within a step)."""
    row_R: np.ndarray
    """(R, C, 3) float32 Θ_R."""
    row_inv: np.ndarray
    """(R, C) float32 Θ_inv."""
    row_center: np.ndarray
    """(R, 3) float32 Θ_c, world."""
    row_scale: np.ndarray
    """(R,) float32 Θ_s."""
    row_stationary: np.ndarray
    """(R,) float32 stationary score."""
    row_inliers: np.ndarray
    """(R,) int32 inlier count."""
    row_samples: np.ndarray
    """(R, M) int32 sampled scene indices."""
    # ---- proposals (P,)
    prop_episode: np.ndarray
    prop_anchor: np.ndarray
    """(P,) int64 anchor scene index."""
    prop_r_init: np.ndarray
    prop_r_err: np.ndarray
    prop_birth_step: np.ndarray
    """(P,) int32 first global step of the proposal."""
    death_step: np.ndarray
    """(P,) int32 global step of death (acceptance counts as the episode's last step); −1 = never decided."""
    death_reason: np.ndarray
    """(P,) int8 index into `reason_names`; −1 = none."""
    death_partner: np.ndarray
    """(P,) int32 partner proposal id (duplicates/inclusions), else −1."""
    death_ratio: np.ndarray
    """(P,) float32 IoU / inclusion ratio / inlier count, NaN if none."""
    death_order: np.ndarray
    """(P,) int32 order in which deaths happened (−1 none)."""
    # ---- episodes (E,)
    episode_unavailable: np.ndarray
    """Flat int32 scene indices assigned before each episode (ragged by `episode_unavailable_offsets`)."""
    episode_unavailable_offsets: np.ndarray
    # ---- reviews (V,)
    rev_step: np.ndarray
    """(V,) int32 global step after which the review ran (last step of its phase)."""
    rev_phase: np.ndarray
    rev_id: np.ndarray
    rev_R: np.ndarray
    """(V, 3, 3) float32 pose (columns = canonical axes in world)."""
    rev_R_raw: np.ndarray
    rev_scale_sel: np.ndarray
    rev_db_sim: np.ndarray
    rev_coverage: np.ndarray
    rev_radii: np.ndarray
    """(V, 2) float32 horizontal radius and half-height (m)."""
    rev_scale_pass: np.ndarray
    rev_up_angle: np.ndarray
    rev_pose_pass: np.ndarray
    rev_obb_center: np.ndarray
    rev_obb_axes: np.ndarray
    rev_obb_half: np.ndarray
    rev_mask: np.ndarray
    """Flat int32 tentative masks (ragged by rev_mask_offsets)."""
    rev_mask_offsets: np.ndarray
    rev_mesh_vertices: np.ndarray
    """Flat (·, 3) float16 mesh vertices relative to Θ_c (ragged by rev_mesh_vertex_offsets)."""
    rev_mesh_vertex_offsets: np.ndarray
    rev_mesh_faces: np.ndarray
    """Flat (·, 3) int32 faces (ragged by rev_mesh_face_offsets)."""
    rev_mesh_face_offsets: np.ndarray
    rev_neighbours: np.ndarray
    """Flat int32 codebook neighbour ids (ragged by rev_neighbour_offsets)."""
    rev_neighbour_offsets: np.ndarray
    work_idx: np.ndarray | None = None
    """(N_w,) int32 scene indices of the EM working set (None = every point; see EMConfig.compute.work_voxel)."""
    work_min_size: int = 0
    """min_size applied on the working set."""
    timings: dict[str, float] = field(default_factory=dict)
    reason_names: tuple[str, ...] = LEGACY_REASONS
    """Names of the death codes (saved with the trace; traces older than the table use `LEGACY_REASONS`)."""
    prop_prior: np.ndarray | None = None
    """(P,) int8 index into `prior_names` of each proposal's prior (None = a single-prior run)."""
    prior_names: tuple[str, ...] = ()
    """Category names of the priors of the solve, in order (one name for a one-prior run; empty in traces saved
    before runs recorded them, which `EMResult.load` fills from the result's one category)."""
    rev_seen_through: np.ndarray | None = None
    """(V,) float32 seen-through fraction of each review's shape (NaN: not checked); None in traces of runs
    without the free-space check (`EMConfig.free_space.margin`) and in older traces."""
    rev_planar: np.ndarray | None = None
    """(V,) float32 share of each review's mask normals that three directions hold (`ReviewRecord.planar`); None
    in older traces."""

    # ------------------------------------------------------------------ basic queries
    @property
    def num_steps(self) -> int:
        return int(len(self.step_phase))

    @property
    def num_proposals(self) -> int:
        return int(len(self.prop_anchor))

    @property
    def phase(self) -> np.ndarray:
        """(T,) int8 phase per step (1 or 2)."""
        return self.step_phase

    def rows(self, step: int) -> slice:
        """Row slice of a global step."""
        self.check_step(step)
        return slice(int(self.row_offsets[step]), int(self.row_offsets[step + 1]))

    def alive(self, step: int) -> np.ndarray:
        """(P_t,) int32 ids of the proposals that took part in `step` (live at its start)."""
        return self.row_id[self.rows(step)]

    def events(self) -> list[DeathEvent]:
        """Every termination in the order it happened (acceptances last in their episode)."""
        ids = np.flatnonzero(self.death_order >= 0)
        ids = ids[np.argsort(self.death_order[ids], kind="stable")]
        return [
            DeathEvent(
                int(self.death_step[i]),
                int(i),
                self.reason_names[int(self.death_reason[i])],
                int(self.death_partner[i]),
                float(self.death_ratio[i]),
            )
            for i in ids
        ]

    def death(self, proposal_id: int) -> tuple[int, str, int, float] | None:
        """(step, reason, partner, ratio) of a proposal, or None."""
        self.check_id(proposal_id)
        r = int(self.death_reason[proposal_id])
        if r < 0:
            return None
        return (
            int(self.death_step[proposal_id]),
            self.reason_names[r],
            int(self.death_partner[proposal_id]),
            float(self.death_ratio[proposal_id]),
        )

    def row_of(self, proposal_id: int, step: int) -> int | None:
        """Global row index of (proposal, step), or None if it did not take part in that step."""
        sl = self.rows(step)
        ids = self.row_id[sl]
        k = int(np.searchsorted(ids, proposal_id))
        if k < len(ids) and ids[k] == proposal_id:
            return sl.start + k
        return None

    def last_step(self, proposal_id: int) -> int:
        """The last global step the proposal took part in (−1 if none)."""
        self.check_id(proposal_id)
        steps = np.flatnonzero(self.row_id == proposal_id)
        if len(steps) == 0:
            return -1
        return int(np.searchsorted(self.row_offsets, steps[-1], side="right") - 1)

    def alive_scores(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """The proposals taking part in a step (live at its start) and their stationary scores.

        Args:
            step: global EM step.

        Returns:
            ((K,) int64 ids, (K,) float64 stationary scores).
        """
        rows = self.rows(int(step))
        return np.asarray(self.row_id[rows], dtype=np.int64), np.asarray(self.row_stationary[rows], dtype=np.float64)

    def sample_indices(self, proposal_id: int, step: int) -> np.ndarray | None:
        """(M,) int64 scene-point indices sampled by a proposal at a step (None when it did not take part)."""
        r = self.row_of(int(proposal_id), int(step))
        return None if r is None else np.asarray(self.row_samples[r], dtype=np.int64).reshape(-1)

    def live_samples(self, step: int) -> np.ndarray:
        """(M,) int64 sorted scene-point indices sampled at `step` by the proposals still alive after it (not
        terminated at or before it): where the run is looking at that step (a running solve's progress view)."""
        rows = self.rows(int(step))
        dead = self.dead_at(np.asarray(self.row_id[rows], np.int64), step)
        return np.unique(np.asarray(self.row_samples[rows][~dead], np.int64))

    def dead_at(self, proposal_ids: np.ndarray, step: int) -> np.ndarray:
        """(K,) bool: which of the proposals were terminated (not accepted) at or before `step`."""
        ids = np.asarray(proposal_ids, np.int64)
        survive = self.reason_names.index(REASON_SURVIVE)
        reason = self.death_reason[ids]
        return (reason >= 0) & (reason != survive) & (self.death_step[ids] <= int(step))

    def is_dead_at(self, proposal_id: int, step: int) -> bool:
        """True when the proposal was terminated (not accepted) at or before `step`."""
        self.check_id(proposal_id)
        return bool(self.dead_at(np.array([proposal_id]), step)[0])

    def center_at(self, proposal_id: int, step: int) -> np.ndarray:
        """(3,) float32 world centre Θ_c of a proposal at a step (its last recorded step if it died before).

        Raises:
            ValueError: the proposal has no record at that step.
        """
        s = min(int(step), int(self.last_step(int(proposal_id))))
        r = self.row_of(int(proposal_id), s)
        if r is None:
            raise ValueError(f"proposal {proposal_id} has no record at step {s}")
        return np.asarray(self.row_center[r], np.float32).reshape(3)

    def latent(self, proposal_id: int, step: int) -> dict[str, np.ndarray]:
        """The stored latent arrays of (proposal, step): R (C,3), inv (C,), center (3,), scale ()."""
        r = self.row_of(proposal_id, step)
        if r is None:
            raise ValueError(f"proposal {proposal_id} did not take part in step {step}")
        return {"R": self.row_R[r], "inv": self.row_inv[r], "center": self.row_center[r],
                "scale": self.row_scale[r]}

    def reviews(self, proposal_id: int) -> list[ReviewRecord]:
        """All review records of a proposal (0, 1 or 2); mesh vertices in world coordinates."""
        out = []
        for v in np.flatnonzero(self.rev_id == proposal_id):
            out.append(self.review_record(int(v)))
        return out

    def review_record(self, v: int) -> ReviewRecord:
        """Review record `v` (mesh vertices in world coordinates; an optional measure the trace lacks is NaN)."""
        got: dict[str, Any] = {}
        for col in REVIEW_COLUMNS:
            arr = getattr(self, col.trace)
            if col.offsets is not None:
                got[col.field] = _ragged_get(arr, getattr(self, col.offsets), v)
            elif arr is None:
                got[col.field] = float("nan")
            elif col.shape:
                got[col.field] = arr[v]
            else:
                got[col.field] = _scalar(arr[v])
        pid, step = got["proposal_id"], got["step"]
        r = self.row_of(pid, step)
        center = self.row_center[r] if r is not None else np.zeros(3, np.float32)
        got["mesh_vertices"] = got["mesh_vertices"].astype(np.float32) + center[None, :]
        return ReviewRecord(**got, prior=self.prior_index(pid))

    def check_step(self, step: int) -> None:
        """Raise ValueError unless 0 <= step < num_steps."""
        if not 0 <= int(step) < self.num_steps:
            raise ValueError(f"step {step} out of range [0, {self.num_steps})")

    def check_id(self, proposal_id: int) -> None:
        """Raise ValueError unless the proposal id exists."""
        if not 0 <= int(proposal_id) < self.num_proposals:
            raise ValueError(f"proposal id {proposal_id} out of range [0, {self.num_proposals})")

    # ------------------------------------------------------------------ re-derivation
    def available_mask(self, episode: int) -> np.ndarray:
        """(N,) bool points available during an episode."""
        avail = np.ones(self.num_points, bool)
        avail[_ragged_get(self.episode_unavailable, self.episode_unavailable_offsets, int(episode))] = False
        return avail

    def _work_mask(self) -> np.ndarray | None:
        if self.work_idx is None or len(self.work_idx) == self.num_points:
            return None
        m = np.zeros(self.num_points, bool)
        m[self.work_idx] = True
        return m

    def replay_mask(self, episode: int, *, full_resolution: bool = True) -> np.ndarray:
        """(N,) bool points a replay of `episode` decodes over: the available ones (on the working set only
        when `full_resolution` is False)."""
        avail = self.available_mask(episode)
        if not full_resolution and (wm := self._work_mask()) is not None:
            avail &= wm
        return avail

    def prior_index(self, proposal_id: int) -> int:
        """Index of the proposal's prior in the run (0 for one-prior runs)."""
        self.check_id(proposal_id)
        return 0 if self.prop_prior is None else int(self.prop_prior[proposal_id])

    def category_of(self, proposal_id: int) -> str:
        """Category name of the proposal's prior ("" when the trace predates category tables)."""
        names = self.prior_names
        return names[self.prior_index(proposal_id)] if names else ""

    # ------------------------------------------------------------------ persistence
    _ARRAY_FIELDS: ClassVar[tuple[str, ...]] = (
        "step_phase", "step_episode", "step_local", "schedule", "active_count", "step_elapsed", "row_offsets",
        "row_id", "row_R", "row_inv", "row_center", "row_scale", "row_stationary", "row_inliers", "row_samples",
        "prop_episode", "prop_anchor", "prop_r_init", "prop_r_err", "prop_birth_step",
        "death_step", "death_reason", "death_partner", "death_ratio", "death_order",
        "episode_unavailable", "episode_unavailable_offsets",
        *(name for col in REVIEW_COLUMNS if not col.optional for name in (col.trace, col.offsets) if name),
    )

    def to_npz_dict(self, prefix: str = "trace/", *, compact: bool = False) -> dict[str, np.ndarray]:
        """Arrays for `np.savez_compressed` (keys prefixed).

        ``compact`` stores the per-step latents (``row_R``, ``row_inv``) in float16 and the sampled point indices
        in uint16 where the scene has at most 65,536 points: about 40 % smaller, for traces that are shipped or
        shared. Loading upcasts them; replays then differ from the full trace's by float16 rounding of the
        latents (~5e-4 relative), which no view shows. The instances (masks, meshes, poses) are unaffected.
        """
        out = {prefix + k: np.asarray(getattr(self, k)) for k in self._ARRAY_FIELDS}
        if compact:
            for k in ("row_R", "row_inv"):
                out[prefix + k] = np.asarray(getattr(self, k), np.float32).astype(np.float16)
            if self.num_points <= 65536:
                out[prefix + "row_samples"] = np.asarray(self.row_samples).astype(np.uint16)
        out[prefix + "schema_version"] = np.array(TRACE_SCHEMA_VERSION, np.int32)
        out[prefix + "config_json"] = np.array(self.config.to_json())
        out[prefix + "num_points"] = np.array(self.num_points, np.int64)
        out[prefix + "timings_json"] = np.array(json.dumps(self.timings))
        out[prefix + "work_idx"] = (np.asarray(self.work_idx, np.int32) if self.work_idx is not None
                                    else np.zeros(0, np.int32))
        out[prefix + "has_work_idx"] = np.array(self.work_idx is not None)
        out[prefix + "work_min_size"] = np.array(self.work_min_size, np.int64)
        out[prefix + "reason_names_json"] = np.array(json.dumps(list(self.reason_names)))
        out[prefix + "prior_names_json"] = np.array(json.dumps(list(self.prior_names)))
        if self.prop_prior is not None:
            out[prefix + "prop_prior"] = np.asarray(self.prop_prior, np.int8)
        for col in REVIEW_COLUMNS:
            if col.optional and getattr(self, col.trace) is not None:
                out[prefix + col.trace] = np.asarray(getattr(self, col.trace), col.dtype)
        return out

    @classmethod
    def from_npz_dict(cls, data: Any, prefix: str = "trace/") -> "EMTrace":
        """Inverse of `to_npz_dict` (accepts an `np.load` result or a dict)."""
        keys = set(data.keys()) if hasattr(data, "keys") else set(data)
        ver_key = prefix + "schema_version"
        if ver_key not in keys:
            raise ValueError(f"not an EFEM trace: key {ver_key!r} missing")
        ver = int(np.asarray(data[ver_key]))
        if ver != TRACE_SCHEMA_VERSION:
            raise ValueError(
                f"unsupported trace schema_version {ver} (this build reads {TRACE_SCHEMA_VERSION})")
        missing = [k for k in cls._ARRAY_FIELDS if prefix + k not in keys]
        if missing:
            raise ValueError(f"trace is missing arrays: {missing}")
        # Any, not ndarray: typed as arrays, **arrays could (for pyright) fill the non-array fields too
        arrays: dict[str, Any] = {k: np.asarray(data[prefix + k]) for k in cls._ARRAY_FIELDS}
        for k in ("row_R", "row_inv"):  # a compact trace (`to_npz_dict(compact=True)`) stores float16
            if arrays[k].dtype == np.float16:
                arrays[k] = arrays[k].astype(np.float32)
        if arrays["row_samples"].dtype == np.uint16:
            arrays["row_samples"] = arrays["row_samples"].astype(np.int32)
        reasons = LEGACY_REASONS
        if prefix + "reason_names_json" in keys:
            reasons = _name_table(data[prefix + "reason_names_json"], "reason_names")
            if REASON_SURVIVE not in reasons:
                raise ValueError(f"trace reason table {reasons} has no {REASON_SURVIVE!r}")
        codes = arrays["death_reason"]
        if len(codes) and (int(codes.max()) >= len(reasons) or int(codes.min()) < -1):
            raise ValueError(f"trace death codes span [{int(codes.min())}, {int(codes.max())}] but its reason "
                             f"table has {len(reasons)} names")
        prior_names: tuple[str, ...] = ()
        if prefix + "prior_names_json" in keys:
            prior_names = _name_table(data[prefix + "prior_names_json"], "prior_names")
        if len(set(prior_names)) != len(prior_names) or len(set(reasons)) != len(reasons) or "" in reasons:
            raise ValueError(f"trace name tables must hold distinct names, got priors {list(prior_names)}, "
                             f"reasons {list(reasons)}")
        prop_prior = np.asarray(data[prefix + "prop_prior"]) if prefix + "prop_prior" in keys else None
        if (prop_prior is not None) != (len(prior_names) > 1):
            raise ValueError(f"trace has {len(prior_names)} prior name(s) but "
                             f"{'a' if prop_prior is not None else 'no'} per-proposal prior table")
        if prop_prior is not None:
            n_prop = len(arrays["prop_anchor"])
            if (prop_prior.shape != (n_prop,) or prop_prior.dtype.kind not in "iu"
                    or (n_prop and (int(prop_prior.min()) < 0 or int(prop_prior.max()) >= len(prior_names)))):
                raise ValueError(f"trace prop_prior {prop_prior.dtype} {prop_prior.shape} does not index its "
                                 f"{len(prior_names)} priors for {n_prop} proposals")
        measured: dict[str, Any] = {}
        for col in REVIEW_COLUMNS:
            if col.optional and prefix + col.trace in keys:
                got = np.asarray(data[prefix + col.trace])
                if got.shape != (len(arrays["rev_id"]), *col.shape) or got.dtype.kind != np.dtype(col.dtype).kind:
                    raise ValueError(f"trace {col.trace} {got.dtype} {got.shape} does not match its "
                                     f"{len(arrays['rev_id'])} reviews")
                measured[col.trace] = got
        return cls(
            config=EMConfig.from_json(str(np.asarray(data[prefix + "config_json"]))),
            num_points=int(np.asarray(data[prefix + "num_points"])),
            timings=json.loads(str(np.asarray(data[prefix + "timings_json"]))),
            work_idx=np.asarray(data[prefix + "work_idx"]) if bool(np.asarray(data[prefix + "has_work_idx"]))
            else None,
            work_min_size=int(np.asarray(data[prefix + "work_min_size"])),
            reason_names=reasons,
            prop_prior=prop_prior,
            prior_names=prior_names,
            **measured,
            **arrays,
        )

    def nbytes(self) -> int:
        """Total bytes of the stored arrays (uncompressed)."""
        return int(sum(np.asarray(getattr(self, k)).nbytes for k in self._ARRAY_FIELDS))


def _name_table(raw: Any, what: str) -> tuple[str, ...]:
    """A saved JSON list of names, validated."""
    try:
        names = json.loads(str(np.asarray(raw)))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"trace {what} is not a JSON list: {exc}") from exc
    if not isinstance(names, list) or not all(isinstance(x, str) for x in names) or len(names) > 127:
        raise ValueError(f"trace {what} must be a list of at most 127 names, got {str(names)[:80]}")
    return tuple(names)


class TraceRecorder:
    """Builds an `EMTrace` while the solver runs (append-only lists, concatenated at the end)."""

    def __init__(self, config: EMConfig, num_points: int, *, work_idx: np.ndarray | None = None,
                 work_min_size: int | None = None, reasons: tuple[str, ...] | None = None,
                 prior_names: tuple[str, ...] = ()) -> None:
        self.config = config
        self.reasons = tuple(reasons) if reasons is not None else reason_names()
        if REASON_SURVIVE not in self.reasons:
            raise ValueError(f"the reason table must contain {REASON_SURVIVE!r}, got {self.reasons}")
        self.prior_names = tuple(prior_names)
        self.owner: list[int] = []
        self.num_points = int(num_points)
        full = work_idx is None or len(work_idx) == num_points
        self.work_idx = None if full else np.asarray(work_idx, np.int32)
        self.work_min_size = int(work_min_size if work_min_size is not None else config.elimination.min_size)
        self.steps: list[tuple[int, int, int, tuple[float, float, float, float]]] = []
        self.active_count: list[int] = []
        self.elapsed: list[float] = []
        self.rows: list[dict[str, np.ndarray]] = []
        self.props: dict[str, list[Any]] = {k: [] for k in ("episode", "anchor", "r_init", "r_err", "birth")}
        self.deaths: dict[int, tuple[int, int, int, float, int]] = {}
        self.episode_unavail: list[np.ndarray] = []
        self.reviews: list[dict[str, Any]] = []
        self._order = 0

    @property
    def num_steps(self) -> int:
        return len(self.steps)

    def start_episode(self, unavailable: np.ndarray, initial_count: int) -> None:
        self.episode_unavail.append(np.asarray(unavailable, np.int32))
        if not self.active_count:
            self.active_count.append(int(initial_count))

    def birth(self, episode: int, anchors: np.ndarray, r_init: float, r_err: float,
              owner: np.ndarray | None = None) -> np.ndarray:
        """Register proposals (`owner`: (n,) prior index of each, default 0); returns their ids."""
        start = len(self.props["anchor"])
        n = len(anchors)
        self.owner.extend(int(o) for o in (owner if owner is not None else np.zeros(n, np.int64)))
        self.props["episode"].extend([episode] * n)
        self.props["anchor"].extend(int(a) for a in anchors)
        self.props["r_init"].extend([r_init] * n)
        self.props["r_err"].extend([r_err] * n)
        self.props["birth"].extend([self.num_steps] * n)
        return np.arange(start, start + n, dtype=np.int64)

    def step(
        self,
        *,
        phase: int,
        episode: int,
        local: int,
        sched: tuple[float, float, float, float],
        ids: np.ndarray,
        latent: dict[str, np.ndarray],
        stationary: np.ndarray,
        inliers: np.ndarray,
        samples: np.ndarray,
    ) -> int:
        """Record one step's rows; returns the global step index."""
        self.steps.append((phase, episode, local, sched))
        self.rows.append(
            {
                "id": np.asarray(ids, np.int32),
                "R": np.asarray(latent["R"], np.float32),
                "inv": np.asarray(latent["inv"], np.float32),
                "center": np.asarray(latent["center"], np.float32),
                "scale": np.asarray(latent["scale"], np.float32).reshape(-1),
                "stationary": np.asarray(stationary, np.float32),
                "inliers": np.asarray(inliers, np.int32),
                "samples": np.asarray(samples, np.int32),
            }
        )
        return self.num_steps - 1

    def end_step(self, active: int, elapsed_s: float = float("nan")) -> None:
        self.active_count.append(int(active))
        self.elapsed.append(float(elapsed_s))

    def death(
        self, proposal_id: int, step: int, reason: str, partner: int = -1, ratio: float = float("nan")
    ) -> None:
        if int(proposal_id) in self.deaths:
            raise ValueError(f"proposal {proposal_id} died twice")
        if reason not in self.reasons:
            raise ValueError(f"reason {reason!r} is not in this run's reason table {self.reasons}")
        code = self.reasons.index(reason)
        self.deaths[int(proposal_id)] = (int(step), code, int(partner), float(ratio), self._order)
        self._order += 1

    def review(self, record: ReviewRecord) -> None:
        self.reviews.append(record._asdict())

    def finish(self, timings: dict[str, float] | None = None) -> EMTrace:
        """Concatenate everything into an `EMTrace`."""
        c, m = self._row_widths()
        rows = [r for r in self.rows if len(r["id"])]

        def cat(key: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
            return _concat_rows(rows, key, shape, dtype)

        death_step, death_reason, death_partner, death_ratio, death_order = self._death_arrays()
        un_off = _offsets([len(u) for u in self.episode_unavail])
        un = np.concatenate(self.episode_unavail) if self.episode_unavail else np.zeros(0, np.int32)
        active = list(self.active_count) or [0]
        return EMTrace(
            config=self.config,
            num_points=self.num_points,
            step_phase=np.array([s[0] for s in self.steps], np.int8),
            step_episode=np.array([s[1] for s in self.steps], np.int16),
            step_local=np.array([s[2] for s in self.steps], np.int16),
            schedule=np.array([s[3] for s in self.steps], np.float32).reshape(-1, 4),
            active_count=np.array(active, np.int32),
            step_elapsed=np.array(self.elapsed, np.float32),
            row_offsets=_offsets([len(r["id"]) for r in self.rows]),
            row_id=cat("id", (), np.int32),
            row_R=cat("R", (c, 3), np.float32),
            row_inv=cat("inv", (c,), np.float32),
            row_center=cat("center", (3,), np.float32),
            row_scale=cat("scale", (), np.float32),
            row_stationary=cat("stationary", (), np.float32),
            row_inliers=cat("inliers", (), np.int32),
            row_samples=cat("samples", (m,), np.int32),
            prop_episode=np.array(self.props["episode"], np.int16),
            prop_anchor=np.array(self.props["anchor"], np.int64),
            prop_r_init=np.array(self.props["r_init"], np.float32),
            prop_r_err=np.array(self.props["r_err"], np.float32),
            prop_birth_step=np.array(self.props["birth"], np.int32),
            death_step=death_step,
            death_reason=death_reason,
            death_partner=death_partner,
            death_ratio=death_ratio,
            death_order=death_order,
            episode_unavailable=un.astype(np.int32),
            episode_unavailable_offsets=un_off,
            **self._review_fields(),
            work_idx=self.work_idx,
            work_min_size=self.work_min_size,
            timings=dict(timings or {}),
            reason_names=self.reasons,
            prop_prior=np.array(self.owner, np.int8) if len(self.prior_names) > 1 else None,
            prior_names=self.prior_names,
        )

    def _row_widths(self) -> tuple[int, int]:
        """(C, M): the latent's channels and the samples per proposal, from the first non-empty step (C 0 and M
        the config's `n_pcl` without one)."""
        for r in self.rows:
            if len(r["id"]):
                return r["R"].shape[1], r["samples"].shape[1]
        return 0, self.config.compute.n_pcl or 0

    def _death_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per proposal: death step, reason code, partner, ratio and order among the deaths (-1 / NaN: alive)."""
        n_prop = len(self.props["anchor"])
        death_step = np.full(n_prop, -1, np.int32)
        death_reason = np.full(n_prop, -1, np.int8)
        death_partner = np.full(n_prop, -1, np.int32)
        death_ratio = np.full(n_prop, np.nan, np.float32)
        death_order = np.full(n_prop, -1, np.int32)
        for pid, (st, rs, pa, ra, od) in self.deaths.items():
            death_step[pid], death_reason[pid], death_partner[pid], death_ratio[pid], death_order[pid] = (
                st, rs, pa, ra, od)
        return death_step, death_reason, death_partner, death_ratio, death_order

    def _review_fields(self) -> dict[str, Any]:
        """The review records as the `EMTrace` arrays of `REVIEW_COLUMNS`: one row per review, the ragged ones
        as values + offsets; an optional measure only when its check ran."""
        revs = self.reviews
        out: dict[str, Any] = {}
        for col in REVIEW_COLUMNS:
            if col.offsets is not None:
                parts = [np.asarray(r[col.field], col.dtype).reshape(-1, *col.shape) for r in revs]
                out[col.offsets] = _offsets([len(p) for p in parts])
                out[col.trace] = (np.concatenate(parts) if parts else np.zeros((0, *col.shape), col.dtype)
                                  ).astype(col.dtype)
            elif col.measured is not None and not col.measured(self.config):
                out[col.trace] = None
            elif not revs:
                out[col.trace] = np.zeros((0, *col.shape), col.dtype)
            else:
                out[col.trace] = np.stack([np.asarray(r[col.field], col.dtype) for r in revs]).reshape(
                    len(revs), *col.shape)
        return out


def _concat_rows(rows: list[dict[str, np.ndarray]], key: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """One per-row field of the recorded steps (`rows`, the non-empty ones) concatenated as `dtype`, C order (a
    live replay and the replay of the saved trace then decode identical bytes); (0, *shape) without rows."""
    parts = [r[key] for r in rows]
    return np.ascontiguousarray(np.concatenate(parts).astype(dtype)) if parts else np.zeros((0, *shape), dtype)
