"""The annotator's EFEM runs, with a shipped shape prior (torch; imported lazily): click-to-segment
(`segment_at_point`: one run seeded at a clicked point) and a run on the whole scan for pre-labels (`solve_scan`).

Click-to-segment runs EFEM on a *crop* of the scene (the points within `crop_radius` of the click, which bounds the
cost on big scans) with a few proposals whose anchors are forced near the click
(`run_em(anchor_candidates=...)`: the points within `anchor_radius` of it). The instance whose mask contains the clicked
point (else the one whose centre is nearest) is returned, mapped back to the scene's vertex indices.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from efem_viz.em.config import SolveSettings
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.prior.registry import PriorSet, available_priors

if TYPE_CHECKING:
    from efem_viz.em.results import EMResult, Instances
    from efem_viz.em.solver import StepInfo
    from efem_viz.prior.config import ShapePriorLike

log = logging.getLogger(__name__)

_PRIORS = PriorSet()
"""The shipped priors click-to-segment used so far, each loaded once (`efem_viz.prior.registry.PriorSet`), on the
device `use_device` chose (the CPU until then)."""


def use_device(device: str) -> None:
    """Run the assist's solves (click-to-segment, EFEM on the scan) on `device` (a `resolve_device` result):
    the priors are loaded there from now on."""
    global _PRIORS
    if device != _PRIORS.device:
        _PRIORS = PriorSet(device=device)


def solve_device() -> str:
    """The device the assist's solves run on."""
    return _PRIORS.device

SEGMENT_SETTINGS = SolveSettings(preset="real", proposals=12)
"""The solve of a click: the real-capture preset, 12 proposals, one episode (`segment_at_point`)."""


def get_prior(name: str) -> ShapePriorLike:
    """Load (once) and return a shipped or analytic shape prior by *name* (`PriorSet.get`).

    Only names of files in `efem_viz/weights/` are accepted, never paths: a prior file is a pickle, and GUI
    input must not make the server unpickle an arbitrary file.

    Raises:
        ValueError: not a shipped prior name.
    """
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name or "") or name not in available_priors():
        raise ValueError(f"unknown shape prior {name!r}; available: {available_priors()}")
    try:
        return _PRIORS.get(name)
    except FileNotFoundError as exc:
        raise ValueError(f"shape prior {name!r} is not available: {exc}") from exc


def segment_at_point(
    scene: Any,
    vertex: int,
    *,
    prior_name: str = DEFAULT_PRIOR,
    prior: ShapePriorLike | None = None,
    crop_radius: float = 0.16,
    anchor_radius: float = 0.03,
    n_proposals: int | None = None,
    settings: SolveSettings = SEGMENT_SETTINGS,
    seed: int = 0,
    on_step: Callable[[StepInfo], None] | None = None,
    cancel: threading.Event | None = None,
    **overrides: Any,
) -> np.ndarray:
    """Segment the object under a vertex with EFEM restricted to a crop around it.

    Args:
        scene: `efem_viz.data.scene.Scene` (world frame, metres, +Z up).
        vertex: index of the clicked vertex.
        prior_name: prior to load when `prior` is None ("mug").
        prior: an already loaded `ShapePrior` (tests), or None.
        crop_radius: metres; EM sees only points within this distance of the click.
        anchor_radius: metres; the proposals are anchored on points within this distance of the click.
        n_proposals: proposals initialised (all anchored inside the crop); None: `settings.proposals` (else the
            preset's first-episode count).
        settings: the solver knobs (preset, proposals, work_voxel, tau_out, matmul_dtype; `SolveSettings.config()`
            builds the config). The crop runs one episode, of the first episode's proposal count.
        seed: EM seed.
        on_step: called with `efem_viz.em.StepInfo` after every EM step (progress).
        cancel: when set, EM stops at its next check and `efem_viz.em.solver.EMCancelled` is raised.
        **overrides: further `EMConfig` changes as `EMConfig.replace` takes them (per group, e.g.
            ``elimination={"min_size": 30}`` for small test objects).

    Returns:
        (K,) int32 sorted scene vertex indices of the proposed object; empty when EFEM found nothing here.

    Raises:
        ValueError: bad vertex, prior unavailable, too few points around the click.
    """
    from efem_viz._typeshims import cKDTree
    from efem_viz.data.scene import Scene
    from efem_viz.em import run_em

    n = int(scene.num_points)
    if not 0 <= int(vertex) < n:
        raise ValueError(f"vertex {vertex} outside [0, {n})")
    pts = np.asarray(scene.points, np.float32)
    centre = pts[int(vertex)]
    crop = np.sort(np.asarray(cKDTree(pts).query_ball_point(centre, crop_radius), np.int64))
    if n_proposals is not None:
        settings = dataclasses.replace(settings, proposals=int(n_proposals))
    cfg = settings.config(device=solve_device())
    cfg = cfg.replace(**overrides) if overrides else cfg
    if len(crop) <= cfg.elimination.min_size:
        raise ValueError(
            f"only {len(crop)} points within {crop_radius:.2f} m of the click (EFEM needs > {cfg.elimination.min_size})"
        )
    cfg = cfg.replace(proposals={"n_init": (int(cfg.proposals.n_init[0]),)})
    sub = Scene.create(
        f"{scene.name}_click{int(vertex)}",
        pts[crop],
        normals=np.asarray(scene.normals)[crop],
        colors=np.asarray(scene.colors)[crop],
        max_points=max(len(crop), 1),
    )
    pr = prior if prior is not None else get_prior(prior_name)
    import torch

    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
    # crop-local indices within anchor_radius of the click (never empty: the clicked vertex is at distance 0)
    near = np.flatnonzero(np.linalg.norm(pts[crop] - centre, axis=1) <= max(float(anchor_radius), 0.0))
    res = run_em(sub, cfg=cfg, priors=[pr], seed=seed, anchor_candidates=near, on_step=on_step, cancel=cancel,
                 device=solve_device())
    return _instance_at(res.instances, crop, int(vertex), centre)


def solve_scan(
    scene: Any,
    *,
    prior_name: str = DEFAULT_PRIOR,
    settings: SolveSettings,
    seed: int = 0,
    on_step: Callable[[StepInfo], None] | None = None,
    cancel: threading.Event | None = None,
) -> EMResult:
    """EFEM on the whole open scan with a shipped prior (the annotator's "Run EFEM on this scan").

    Args:
        scene: the scan as a `Scene`.
        prior_name: a shipped prior (`get_prior`).
        settings: preset, proposals, ... (`SolveSettings.config()`).
        seed: EM seed.
        on_step: called with `efem_viz.em.StepInfo` after every EM step (progress).
        cancel: when set, EM stops at its next check (`efem_viz.em.solver.EMCancelled`).

    Raises:
        ValueError: unknown prior or bad settings.
    """
    from efem_viz.em import run_em

    cfg = settings.config(device=solve_device())
    prior = get_prior(prior_name)
    return run_em(scene, cfg=cfg, priors=[prior], seed=seed, on_step=on_step, cancel=cancel, device=solve_device())


def _instance_at(inst: Instances, crop: np.ndarray, vertex: int, centre: np.ndarray) -> np.ndarray:
    """The mask of the crop's instance under the click: the most confident one containing the clicked vertex, else
    the one whose centre is nearest the click.

    Args:
        inst: the instances found in the crop.
        crop: (C,) int64 sorted scene indices of the crop's points.
        vertex: the clicked scene vertex (in `crop`).
        centre: (3,) float32 its position, world frame.

    Returns:
        (K,) int32 sorted scene vertex indices; empty when there is no instance.
    """
    if len(inst) == 0:
        return np.zeros(0, np.int32)
    local = int(np.searchsorted(crop, vertex))
    containing = [k for k in range(len(inst)) if local in set(np.asarray(inst.masks[k]).tolist())]
    if containing:
        k = max(containing, key=lambda j: float(inst.confidence[j]))
    else:
        d = np.linalg.norm(np.asarray(inst.center) - centre[None], axis=1)
        k = int(np.argmin(d))
    return np.sort(crop[np.asarray(inst.masks[k], np.int64)]).astype(np.int32)
