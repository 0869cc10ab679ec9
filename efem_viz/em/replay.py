"""Replay of a recorded EM run: what the trace does not store, re-derived from its latents on demand.

An `EMTrace` is frozen arrays (em/trace.py). A `TraceReplay` binds one to the scene it ran on and the prior(s)
it ran with, and re-derives the weights over the scene at any step (`weights_in`, `weights_out`) and the
inspector's view of a proposal (`view`, the four views of Fig. S9) with the code the solver uses
(`em.estep.energy_weights`, `decode_rows`, `mesh_of_latent`), keeping the last views in an LRU cache. A run with several
priors decodes each proposal with its own prior (`EMTrace.prop_prior`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.em.proposals import AvailableTree
from efem_viz.em.estep import energy_weights, normals_threshold
from efem_viz.em.rules import REVIEW_COLUMNS
from efem_viz.em.trace import EMTrace, ProposalView

if TYPE_CHECKING:
    from efem_viz.data.scene import Scene
    from efem_viz.prior.config import PriorArg, ShapePriorLike

NEED_PRIOR = "re-deriving weights and shapes needs the shape prior: pass prior= or result.bind(prior=...)"
NEED_SCENE = "this replay has no scene bound: call result.bind(scene) with the scene the run was on"


def run_priors(trace: EMTrace, priors: "PriorArg") -> tuple[Any, ...]:
    """The priors given for a run, checked against it: as many as it used and, for a multi-prior run, each with the
    category name the trace recorded at its position (so a swapped list cannot decode one category with another's
    prior).

    Raises:
        ValueError: wrong number of priors, or a category name out of place.
    """
    seq: tuple[Any, ...] = tuple(priors) if isinstance(priors, (list, tuple)) else (priors,)
    names = trace.prior_names
    if len(seq) != max(1, len(names)):
        raise ValueError(f"the run used {max(1, len(names))} prior(s) {list(names)}, got {len(seq)}")
    if len(names) > 1:
        from efem_viz.prior.config import prior_category

        got = [prior_category(p).name for p in seq]
        if got != list(names):
            raise ValueError(f"the run's priors are {list(names)} in this order, got {got}")
    return seq


def prior_latent(trace: EMTrace, proposal_id: int, step: int, priors: "PriorArg") -> tuple[Any, dict[str, np.ndarray]]:
    """(the prior that owns a proposal, its latent at `step` trimmed to that prior's code width): what decoding a
    stored latent needs, for one-prior and multi-prior runs alike.

    Args:
        trace: the run.
        proposal_id: the proposal.
        step: a step it took part in.
        priors: the run's prior, or its priors in the run's order.

    Raises:
        ValueError: the proposal did not take part in `step`, or `priors` does not match the run.
    """
    from efem_viz.em.decoding import latent_width, trim_latent

    prior = run_priors(trace, priors)[trace.prior_index(proposal_id)]
    lat = trace.latent(proposal_id, step)
    return prior, (trim_latent(lat, latent_width(prior)) if trace.prop_prior is not None else lat)


class TraceReplay:
    """A trace bound to its scene and prior(s).

    Args:
        trace: the recorded run.
        scene: the scene it ran on (its point count must match), or None (bind it later).
        prior: the prior, or the list of priors of a multi-prior run (in the run's order), or None.
        cache_size: views kept in the LRU cache.

    Raises:
        ValueError: the scene has another number of points, or the number of priors does not match the run.
    """

    def __init__(self, trace: EMTrace, scene: "Scene | None" = None,
                 prior: "ShapePriorLike | Sequence[ShapePriorLike] | None" = None, *, cache_size: int = 32) -> None:
        self.trace = trace
        self.cache_size = int(cache_size)
        self._points: np.ndarray | None = None
        self._normals: np.ndarray | None = None
        self._priors: tuple[Any, ...] | None = None
        self._cache: OrderedDict[tuple[Any, ...], ProposalView] = OrderedDict()
        self.bind(scene, prior)

    # ------------------------------------------------------------------ binding
    def bind(self, scene: "Scene | None" = None,
             prior: "ShapePriorLike | Sequence[ShapePriorLike] | None" = None) -> TraceReplay:
        """Attach the scene and/or the prior(s) (None leaves that part as it is). Returns self."""
        if scene is not None:
            if scene.num_points != self.trace.num_points:
                raise ValueError(f"scene {scene.name!r} has {scene.num_points} points but the trace was recorded "
                                 f"on {self.trace.num_points}")
            self._points = np.asarray(scene.points, np.float32)
            self._normals = np.asarray(scene.normals, np.float32)
            self._cache.clear()
        if prior is not None:
            self._priors = run_priors(self.trace, prior)
            self._cache.clear()
        return self

    @property
    def has_scene(self) -> bool:
        return self._points is not None

    @property
    def priors(self) -> tuple[Any, ...] | None:
        """The bound priors, in the run's order, or None."""
        return self._priors

    def prior_of(self, proposal_id: int, prior: "PriorArg | None" = None) -> Any:
        """The prior that owns a proposal: `prior` when given (one-prior runs), else the bound one; or None."""
        k = self.trace.prior_index(proposal_id)
        if prior is not None and not isinstance(prior, (list, tuple)):
            if len(self.trace.prior_names) <= 1:
                return prior
            from efem_viz.prior.config import prior_category

            # one prior given for a multi-prior run: it serves the proposals of its own category
            return prior if prior_category(prior).name == self.trace.prior_names[k] else None
        priors = run_priors(self.trace, prior) if prior is not None else self._priors
        return None if priors is None else priors[k]

    def points(self) -> np.ndarray:
        """(N, 3) float32 scene points."""
        if self._points is None:
            raise ValueError(NEED_SCENE)
        return self._points

    def normals(self) -> np.ndarray:
        """(N, 3) float32 scene normals."""
        if self._normals is None:
            raise ValueError(NEED_SCENE)
        return self._normals

    # ------------------------------------------------------------------ re-derived views
    def weights_in(self, proposal_id: int, step: int, prior: "PriorArg | None" = None, *, full_resolution: bool = True
                   ) -> np.ndarray:
        """(N,) float32 weights that produced the samples of (proposal, step) (= W_out of step − 1).

        With `full_resolution=False` only the EM working set carries weights (exactly what the solver sampled
        from); with True every available point of the ball gets the same formula (identical on the working
        set), which is what a viewer should paint.
        """
        tr = self.trace
        r = tr.row_of(proposal_id, step)
        if r is None:
            raise ValueError(f"proposal {proposal_id} did not take part in step {step}")
        if int(tr.step_local[step]) != 0:
            return self.weights_out(proposal_id, step - 1, prior, full_resolution=full_resolution)
        pts = self.points()
        tree = AvailableTree(pts, tr.replay_mask(int(tr.step_episode[step]), full_resolution=full_resolution),
                             crop=tr.config.proposals.crop)
        rag = tree.query(pts[int(tr.prop_anchor[proposal_id])][None], float(tr.prop_r_init[proposal_id]))
        w = np.zeros(tr.num_points, np.float32)
        w[rag.idx] = 1.0
        return w

    def weights_out(self, proposal_id: int, step: int, prior: "PriorArg | None" = None, *, full_resolution: bool = True
                    ) -> np.ndarray:
        """(N,) float32 weights produced by the E-step of (proposal, step), re-derived from its latent."""
        from efem_viz.em.decoding import decode_rows, latent_width, matmul_precision, trim_latent

        tr = self.trace
        pri = self.prior_of(proposal_id, prior)
        if pri is None:
            raise ValueError(NEED_PRIOR)
        r = tr.row_of(proposal_id, step)
        if r is None:
            raise ValueError(f"proposal {proposal_id} did not take part in step {step}")
        pts, nrm = self.points(), self.normals()
        tree = AvailableTree(pts, tr.replay_mask(int(tr.step_episode[step]), full_resolution=full_resolution),
                             crop=tr.config.proposals.crop)
        rag = tree.query(tr.row_center[r][None], float(tr.prop_r_err[proposal_id]))
        lat = {k: np.asarray(v)[None] for k, v in tr.latent(proposal_id, step).items()}
        lat["scale"] = np.asarray(lat["scale"]).reshape(1)
        if tr.prop_prior is not None:
            lat = trim_latent(lat, latent_width(pri))
        sched = tuple(float(v) for v in tr.schedule[step])
        with matmul_precision(tr.config.compute.matmul_dtype, pri):  # the precision the run decoded with
            d, gamma = decode_rows(pri, lat, rag, pts, nrm, chunk=tr.config.compute.decode_chunk,
                                   normals_within=normals_threshold(tr.config, sched[1]))
        wk, _ = energy_weights(d, gamma, (sched[0], sched[1], sched[2], sched[3]), out_value=tr.config.steps.out_value)
        w = np.zeros(tr.num_points, np.float32)
        w[rag.idx] = wk
        return w

    def view(self, proposal_id: int, step: int, prior: "PriorArg | None" = None, *, mesh: bool = True,
             full_resolution: bool = True) -> ProposalView:
        """Everything the inspector shows for (proposal, step), re-derived from the stored latent and cached.

        If the proposal died before `step`, the record of its death step is shown (alive=False).

        Args:
            proposal_id: the proposal.
            step: global step.
            prior: a prior overriding the bound one(s) (in a multi-prior run it serves only the proposals of
                its own category); needed for weights after an episode's first step and for meshes.
            mesh: extract the decoded shape (a few hundred ms).
            full_resolution: weights on every point of the ball (True) or only on the EM working set.

        Raises:
            ValueError: unknown id/step, the proposal was not born yet, or scene/prior missing.
        """
        tr = self.trace
        tr.check_id(proposal_id)
        tr.check_step(step)
        pri = self.prior_of(proposal_id, prior)
        key = (int(proposal_id), int(step), id(pri), bool(mesh), bool(full_resolution))
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        birth = int(tr.prop_birth_step[proposal_id])
        if step < birth:
            raise ValueError(f"proposal {proposal_id} is born at step {birth}, not yet alive at step {step}")
        shown = min(int(step), tr.last_step(proposal_id))
        r = tr.row_of(proposal_id, shown)
        assert r is not None
        if pri is None and int(tr.step_local[shown]) != 0:
            raise ValueError(NEED_PRIOR)
        weights = self.weights_in(proposal_id, shown, prior, full_resolution=full_resolution)
        samples = tr.row_samples[r]
        dead = tr.death(proposal_id)
        alive = not (dead is not None and dead[1] != "survive" and dead[0] <= step)
        scores: dict[str, float] = {"stationary": float(tr.row_stationary[r]), "inliers": float(tr.row_inliers[r])}
        for v in np.flatnonzero((tr.rev_id == proposal_id) & (tr.rev_step == shown)):
            for col in REVIEW_COLUMNS:  # the review's measures, by the names the table gives them
                arr = getattr(tr, col.trace) if col.scores else None
                if arr is None:
                    continue
                values = np.asarray(arr[v], np.float64).reshape(-1)
                for name, value in zip(col.scores, values):
                    if not col.optional or np.isfinite(value):  # an optional measure shows only where measured
                        scores[name] = float(value)
        sch = tr.schedule[shown]
        lat = tr.latent(proposal_id, shown)
        mesh_obj = None
        if mesh and pri is not None:
            from efem_viz.em.decoding import latent_width, mesh_of_latent, trim_latent

            lat_k = trim_latent(lat, latent_width(pri)) if tr.prop_prior is not None else lat
            mesh_obj = mesh_of_latent(pri, lat_k, resolution=tr.config.review.mesh_resolution)  # float32, as reviews
        view = ProposalView(
            proposal_id=int(proposal_id),
            step=shown,
            weights=weights,
            sample_idx=samples,
            sampled_points=self.points()[samples],
            mesh=mesh_obj,
            scores=scores,
            schedule={"alpha_d": float(sch[0]), "tau_d": float(sch[1]), "alpha_n": float(sch[2]),
                      "tau_n": float(sch[3])},
            alive=alive,
            death=dead,
            latent=lat,
            category=tr.category_of(proposal_id),
        )
        self._cache[key] = view
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return view
