"""Train a shape prior (docs/design/efem-method.md §2): ``efem-viz train-prior``.

The module top is light (the CLI imports it); torch/open3d are imported inside functions.

Outputs under ``out_dir`` (default ``runs/<category>``): ``config.json`` (resolved run config) and ``last.pt``
(full resume checkpoint: model, optimizer, iteration, RNG states, curve); progress goes to logging. The best
model by validation IoU goes to ``export`` (default ``<out_dir>/<category>.pt``; shipping it is explicit) with
``<stem>_training_report.json`` / ``.md`` next to it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

if TYPE_CHECKING:
    import torch

    from efem_viz.prior.data import ObjectData, SampleConfig
    from efem_viz.prior.model import PriorConfig, ShapePrior

log = logging.getLogger(__name__)

Preset = Literal["spec", "cpu", "cpu-chair", "cpu-small", "tiny"]

PRESETS: dict[str, dict[str, Any]] = {
    # the released mug architecture (§1.3)
    "spec": {},
    # CPU budget: widths halved, 256 input points, latent 128, small decoder (mug_training_report.md: timings)
    # δ is multiplied by σ (as in the kit4cates prior): with a calibrated σ ≈ 1e6 an unscaled δ starts ~1e-6
    # and the centre head cannot learn within a CPU budget (observed: |Θ_c| error unchanged after 250 its).
    # (PriorConfig.decoder_proj_gain/inv_gain = √L/L were tried as well: validation SDF L1 after 250
    # iterations was worse, 0.12 vs 0.079, so the shipped preset keeps them at 1.)
    "cpu": {"widths": (16, 16, 32, 32, 64, 128, 256), "latent_dim": 128, "center_hidden": 64, "n_pcl": 256,
            "decoder_hidden": 128, "decoder_blocks": 2, "center_times_sigma": True},
    # chairs on a CPU budget: the "cpu" widths with the spec's chair design (VN attention in blocks 2..6,
    # down-sampling factors 4, 4, 4) on 512 input points (spec 1024): 512, 512, 128, 128, 32, 8, 8 points per block
    "cpu-chair": {"widths": (16, 16, 32, 32, 64, 128, 256), "latent_dim": 128, "center_hidden": 64, "n_pcl": 512,
                  "down_factors": (4, 4, 4), "attention_blocks": (2, 3, 4, 5, 6), "decoder_hidden": 128,
                  "decoder_blocks": 2, "center_times_sigma": True},
    # quarter widths
    "cpu-small": {"widths": (8, 8, 16, 16, 32, 64, 128), "latent_dim": 64, "center_hidden": 32, "n_pcl": 256,
                  "k": 16, "decoder_hidden": 128, "decoder_blocks": 2, "center_times_sigma": True},
    # unit tests
    "tiny": {"widths": (8, 8, 16, 16), "down_blocks": (2,), "down_factors": (2,), "latent_dim": 16,
             "center_hidden": 8, "n_pcl": 64, "k": 8, "decoder_hidden": 32, "decoder_blocks": 1},
}


@dataclass
class TrainArgs:
    """Train a SIM(3)-equivariant shape prior on procedural meshes or a folder of aligned meshes."""

    category: str = "mug"
    """Procedural category (``efem_viz.data.procedural``); also the default output name."""
    meshes: Path | None = None
    """Aligned (+Z up) watertight training meshes instead of the procedural category: a folder of mesh files
    or a mesh pack (`efem-viz pack-meshes`, .npz; needs neither trimesh nor open3d)."""
    val_meshes: Path | None = None
    """Validation meshes, a folder or a mesh pack (default with --meshes: every 10th mesh is held out)."""
    n_train: int = 400
    """Training objects: the first seeds of the procedural train split, or the first meshes of a mesh pack."""
    n_val: int = 24
    """Validation objects: the first seeds of the procedural val split, or the first meshes of a mesh pack."""
    handled_only: bool = False
    """Procedural mugs with a handle only, for training and validation (the paper's ShapeNet mugs all have one;
    about 15 % of the procedural mugs are handle-less cups)."""
    out_dir: Path | None = None
    """Run folder (checkpoints, config, log). Default: runs/<category>."""
    export: Path | None = None
    """Where the best model goes. Default: <out_dir>/<category>.pt (a run never replaces a shipped prior, whose
    codebook and settings belong to its own weights, unless told to: ``--export efem_viz/weights/mug.pt``)."""
    resume_export: Path | None = None
    """Also write the latest resume state here (`write_resume_state`: without the optimiser's moments, at most
    20 MB), e.g. efem_viz/weights/mug_resume.pt."""
    resume_export_every_min: float = 10.0
    """Minutes between copies to --resume-export."""
    cache_dir: Path = Path("runs/cache")
    """Per-object data cache."""
    preset: Preset = "cpu"
    """Architecture preset; the fields below override it."""
    widths: tuple[int, ...] | None = None
    """Backbone block widths (override)."""
    latent_dim: int | None = None
    """Latent width (override)."""
    decoder_hidden: int | None = None
    """Decoder width (override)."""
    decoder_blocks: int | None = None
    """Decoder residual blocks (override)."""
    n_pcl: int | None = None
    """Encoder input points (override)."""
    k: int | None = None
    """kNN size (override)."""
    batch_size: int = 16
    """Examples per iteration."""
    iterations: int = 80000
    """Total iterations (the learning-rate decay points are fractions of this)."""
    lr: float = 1e-4
    """Adam learning rate."""
    decay_at: tuple[float, ...] = (0.625, 0.75, 0.875)
    """LR decay points as fractions of --iterations (spec: 50k/60k/70k of 80k)."""
    decay_factor: float = 0.3
    """LR multiplier at every decay point."""
    warmup_steps: int = 100
    """Linear learning-rate warm-up over this many iterations whenever Adam starts without moments: a new run,
    --init-from, or a resume state without the optimiser's moments (a shipped one). Adam's first steps move every
    weight by about the learning rate whatever its gradient, which knocks a trained prior off its optimum (a
    resumed 256x4 prior at lr 1e-4, batch 64: calibrated validation IoU 0.544 -> 0.448 in 9 steps). 0: off."""
    val_every: int = 250
    """Iterations between validations."""
    ckpt_every_min: float = 4.0
    """Minutes between resume checkpoints."""
    near_fraction: float = 0.5
    """Share of each example's SDF queries drawn near the surface (the rest uniform in the cube); 0.5 is the
    spec's 1024 + 1024."""
    steps: int | None = None
    """Stop after this many iterations of this run, counted from where it started or resumed (None: run to
    ``iterations`` or the time budget). Work-counted, so a test or a smoke run means the same on any machine."""
    time_budget_min: float | None = None
    """Stop (with a final checkpoint and validation) after this many minutes of this process."""
    threads: int = 2
    """torch CPU threads."""
    seed: int = 12345
    """Seed of the model init and of all sampling."""
    resume: bool = False
    """Continue from <out_dir>/last.pt (or --resume-from)."""
    resume_from: Path | None = None
    """Explicit checkpoint to resume from (implies --resume)."""
    init_from: Path | None = None
    """Start a new run (iteration 0, fresh optimiser, this run's schedule) from the weights of a saved prior,
    e.g. the shipped ``efem_viz/weights/mug.pt`` (fine-tuning). Ignored on resume."""
    init_matching: bool = False
    """With --init-from: keep this run's architecture (--preset and its overrides) and take from the saved prior
    every weight whose name and shape match; the rest start fresh (e.g. a chair prior with VN attention from the
    mug prior's encoder and decoder)."""
    grow_decoder_hidden: int | None = None
    """With --init-from: widen the decoder to this many units, function-preserving (`prior.widen`), before
    fine-tuning (the shipped 128-wide decoder is capacity-bound)."""
    grow_decoder_blocks: int | None = None
    """With --init-from: deepen the decoder to this many residual blocks (new blocks start as the identity)."""
    matmul_dtype: str = "float32"
    """Precision of the networks' matrix work in training steps: "bfloat16" runs them under autocast (AMX /
    AVX-512 bf16 CPUs, CUDA) with float32 master weights, optimiser and losses; validation stays float32."""
    freeze_decoder: bool = False
    """Train the encoder only: the decoder (the shape space, its level set and the codebook's meaning) stays
    as it was. With --init-from, for fine-tuning the encoder's response to sensor inputs."""
    p_table: float = 0.3
    """Probability of the table-plane augmentation."""
    table_side_p: float = 0.0
    """Probability that a table-plane patch touches the object from a random direction (uniform on the sphere,
    above included) instead of from below: objects that lie on their side, back or top in scenes, as tumbled
    chairs do. Validation inputs have no table patch."""
    neighbour_p: float = 0.0
    """Probability that the other-object points of an example are the part of a whole neighbouring object inside
    the example's reach (placed touching it or a small gap away, as in a pile) instead of small floating crops.
    Validation inputs have none."""
    member_weights: tuple[str, ...] = ()
    """Sampling weights of a family's members for the training batches, as ``member=weight`` (e.g. ``mug=2
    bowl=1.5``; a member not named weighs 1): the hard members of one prior (thin-walled mugs and bowls of the
    kitchen family) seen more often. A member is what `efem_viz.data.procedural.variant_of` names: a kitchen
    object's category, a chair's base (``stool=3``). Empty: every object equally often. Validation is unchanged."""
    min_views: int = 4
    """Fewest depth views in an input cloud (spec: 4 for mugs; 1 also trains single-view inputs, as real RGB-D
    frames are). Validation inputs are drawn with the same setting."""
    top_only_p: float = 0.6
    """Probability that an example's input uses only the views from above (elevation 30-60°); the rest draw
    from every view, side and below included. Lower it for objects seen in any orientation (tumbled chairs).
    Validation inputs are drawn with the same setting."""
    sensor_p: float = 0.0
    """Probability that a training example is a depth-sensor view (`prior.data.sensor_cloud`: 1-2 views
    mostly, Kinect/RealSense axial noise ×U(0.5, 2), quantisation, jitter, grazing dropout, 300-3000 visible
    points). 0 = the isotropic-noise inputs of earlier sessions. Validation then also reports ``sensor_*``
    metrics on fixed sensor inputs and selects the export by them."""
    inside_weight: float = 1.0
    """Weight of the SDF error at queries inside the shape (ground-truth SDF < 0) against those outside (1: the
    specification's loss). Above 1 for thin parts (chair legs, a stool's frame, a mug's handle), which have few
    inside queries and are otherwise learnt as a slightly positive shell whose field never turns negative: no
    surface to mesh or measure. The weight is not normalised: it also raises the SDF term against the centre and
    scale terms, as a somewhat larger learning rate for it would."""
    fixed_point_p: float = 0.0
    """Probability that an example is re-encoded from the model's own SDF-band inliers of its input (as one EM
    M-step would), so that one step cannot shrink a good fit."""
    fixed_point_tau: float = 0.05
    """SDF band (canonical units) of the fixed-point inliers."""
    snapshot_every: int = 0
    """Also save the model (not the optimiser) to <out_dir>/snap_<iteration>.pt every this many iterations,
    for selection by the stability bench (0: off)."""
    reset_best: bool = False
    """On resume, forget the best validation IoU so far (use when the validation inputs change, e.g. a new
    --min-views): the next validation exports."""
    progress: bool = True
    """Show a progress bar."""
    report_notes: Path | None = None
    """Markdown inserted at the top of the training report (default: <out_dir>/report_notes.md if present)."""
    device: str = "cpu"
    """Torch device."""
    log_every: int = 10
    """Iterations between entries of the training-loss curve."""
    calibrate_iso: bool = True
    """Select and export by the iso-offset-calibrated validation IoU (the offset is folded into the exported
    ``fc_out.bias`` and stored as metadata ``iso_offset``); False = the spec's raw IoU."""
    ema_decay: float = 0.0
    """Average the weights over the run as it goes (an exponential moving average with this decay per step,
    about ``1 / (1 - decay)`` steps wide, e.g. 0.999; `WeightAverage`): validation scores the averaged weights
    and the trained ones (reported as ``trained_*``) and exports whichever scores higher (metadata ``weights``);
    checkpoints carry the average (shippable resume states do not: a run resumed from one starts it again from the
    weights). For a run whose validation has stopped rising and wanders around a level, the average of the
    wandering is often better than any point of it. 0: off."""

    def run(self) -> int:
        """CLI entry: train with a tqdm progress bar. Returns 0 on success."""
        from tqdm import tqdm

        bar: Any = None

        def on_progress(it: int, total: int, info: dict[str, Any]) -> None:
            nonlocal bar
            if bar is None:
                bar = tqdm(total=total, initial=it, unit="it", dynamic_ncols=True,
                           mininterval=1.0 if os.isatty(2) else 60.0)
            post = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in info.items()}
            bar.set_postfix(post, refresh=False)
            bar.update(it - bar.n)  # tqdm redraws at most every `mininterval` seconds

        try:
            result = train(self, on_progress=on_progress if self.progress else None)
        finally:
            if bar is not None:
                bar.close()
        log.info("finished at iteration %d; best val IoU %.4f (iteration %d); exported %s",
                 result["iteration"], result["best_iou"], result["best_iteration"], result["export"])
        return 0

    # ----------------------------------------------------------------------------------------------- resolved
    def prior_config(self) -> PriorConfig:
        """The architecture: preset + overrides."""
        from efem_viz.prior.config import PriorConfig

        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; known: {sorted(PRESETS)}")
        kw = dict(PRESETS[self.preset])
        for name in ("widths", "latent_dim", "decoder_hidden", "decoder_blocks", "n_pcl", "k"):
            v = getattr(self, name)
            if v is not None:
                kw[name] = v
        return PriorConfig(**kw)

    def sample_config(self, n_pcl: int) -> SampleConfig:
        """Per-example sampling for this run."""
        from efem_viz.prior.data import SampleConfig

        if self.min_views < 1:
            raise ValueError(f"min_views must be >= 1 (got {self.min_views})")
        if not 0.0 < self.near_fraction < 1.0:
            raise ValueError(f"near_fraction must be in (0, 1) (got {self.near_fraction})")
        total = SampleConfig.n_query_uniform + SampleConfig.n_query_near
        near = int(round(total * self.near_fraction))
        if not 0.0 <= self.top_only_p <= 1.0:
            raise ValueError(f"top_only_p must be in [0, 1] (got {self.top_only_p})")
        if not 0.0 <= self.table_side_p <= 1.0:
            raise ValueError(f"table_side_p must be in [0, 1] (got {self.table_side_p})")
        if not 0.0 <= self.neighbour_p <= 1.0:
            raise ValueError(f"neighbour_p must be in [0, 1] (got {self.neighbour_p})")
        return SampleConfig(n_pcl=n_pcl, p_table=self.p_table, min_views=self.min_views, sensor_p=self.sensor_p,
                            p_top_only=self.top_only_p, p_table_any_side=self.table_side_p,
                            p_neighbour=self.neighbour_p, n_query_near=near, n_query_uniform=total - near)

    def resolved_out_dir(self) -> Path:
        """``out_dir`` or ``runs/<category>``."""
        return self.out_dir if self.out_dir is not None else Path("runs") / self.category

    def resolved_export(self) -> Path:
        """``export`` or ``<out_dir>/<category>.pt``."""
        return self.export if self.export is not None else self.resolved_out_dir() / f"{self.category}.pt"


# --------------------------------------------------------------------------------------------------- helpers
def _json_default(o: Any) -> Any:
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


REPORT_CURVES = ("val_curve", "train_curve")
"""The per-validation and per-log-step curves of a training report (one JSON object per entry)."""


def report_json(rep: dict[str, Any]) -> str:
    """A training report as JSON text: its settings indented, each curve entry on one line with its numbers to five
    significant digits (the curves are most of a report: a shipped report stays small and diffs line by line)."""
    def rounded(o: Any) -> Any:
        if isinstance(o, float):
            return float(f"{o:.5g}")
        if isinstance(o, dict):
            return {k: rounded(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [rounded(v) for v in o]
        return o

    head = {k: v for k, v in rep.items() if k not in REPORT_CURVES}
    text = json.dumps(head, indent=1, default=_json_default)[:-2]  # without the closing "\n}"
    for name in REPORT_CURVES:
        if name in rep:
            rows = ",\n  ".join(json.dumps(rounded(e), default=_json_default) for e in rep[name])
            text += f',\n "{name}": [' + (f"\n  {rows}\n ]" if rows else "]")
    return text + "\n}\n"


def _write_text_atomic(path: Path, text: str) -> None:
    from efem_viz.data.io import atomic_write_text

    atomic_write_text(path, text)


def _install_stop_handlers() -> tuple[threading.Event, Callable[[], None]]:
    """SIGINT/SIGTERM ask the loop to stop after the current iteration; it then validates and checkpoints.

    Only in the main thread (signal handlers cannot be set elsewhere); elsewhere the event is never set.
    Returns the event and a function that restores the previous handlers.
    """
    import signal

    stop = threading.Event()
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        def _handler(signum: int, frame: object) -> None:  # noqa: ARG001
            if stop.is_set():  # a second signal: stop at once
                raise KeyboardInterrupt
            log.warning("signal %d: stopping after this iteration (final validation + checkpoint)", signum)
            stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, _handler)

    def restore() -> None:
        for sig, old in previous.items():
            signal.signal(sig, old)

    return stop, restore


def lr_at(iteration: int, *, base: float, total: int, decay_at: tuple[float, ...], factor: float) -> float:
    """Step-decayed learning rate at ``iteration`` (floor 1e-8)."""
    n = sum(1 for f in decay_at if iteration >= int(round(f * total)))
    return max(base * factor**n, 1e-8)


def mesh_sources(path: Path) -> list[tuple[str, Callable[[], Any]]]:
    """(name, mesh factory) of a mesh folder or a mesh pack file."""
    from efem_viz.prior.data import folder_sources, pack_sources

    return pack_sources(path) if Path(path).is_file() else folder_sources(path)


def load_objects(args: TrainArgs, split: Literal["train", "val"], *,
                 on_item: Callable[[int, int], None] | None = None) -> list[ObjectData]:
    """Load (or prepare and cache) the objects of a split."""
    from efem_viz.prior.data import PrepConfig, load_or_prepare, procedural_sources

    if args.meshes is not None:
        srcs = mesh_sources(args.meshes)
        if split == "val":
            srcs = mesh_sources(args.val_meshes) if args.val_meshes is not None else srcs[::10]
        elif args.val_meshes is None:
            srcs = [s for i, s in enumerate(srcs) if i % 10 != 0] or srcs
        given = Path(args.meshes if split == "train" or args.val_meshes is None else args.val_meshes)
        if given.is_file():  # a pack: the first n_train / n_val of its meshes
            srcs = srcs[:args.n_train if split == "train" else args.n_val]
        cache = args.cache_dir / f"{'pack' if given.is_file() else 'folder'}_{given.stem}"
    else:
        srcs = procedural_sources(args.category, split, args.n_train if split == "train" else args.n_val,
                                  handled_only=args.handled_only)
        cache = args.cache_dir / f"procedural_{args.category}"
    out = []
    for i, s in enumerate(srcs):
        seed = args.seed + i + (0 if split == "train" else 10**6)
        out.append(load_or_prepare(s, cache_dir=cache, cfg=PrepConfig(), seed=seed, device=args.device))
        if on_item is not None:
            on_item(i + 1, len(srcs))
    return out


def compute_losses(prior: ShapePrior, pcl: torch.Tensor, queries: torch.Tensor, *, n_uniform: int,
                   centroid_noise: torch.Tensor | None = None, inside_weight: float = 1.0) -> dict[str, torch.Tensor]:
    """Training losses of §2.5 for a batch.

    Args:
        prior: The model.
        pcl: (B, N, 3) input clouds (canonical frame).
        queries: (B, Q, 4) xyz + GT SDF, the first ``n_uniform`` uniform, the rest near-surface.
        n_uniform: Number of uniform queries per example.
        centroid_noise: Optional (B, 3) centroid noise.
        inside_weight: Weight of the SDF error at inside queries (GT SDF < 0; `TrainArgs.inside_weight`).

    Returns:
        Dict with ``loss`` (clamped to [-4, 4]), ``sdf``, ``center``, ``scale`` (scalars).
    """
    import torch

    lat = prior.encode(pcl, centroid_noise=centroid_noise)
    pred = prior.sdf(queries[..., :3], lat).to(queries.dtype)  # losses in the model dtype under autocast too
    err = (pred - queries[..., 3]).abs()
    w = torch.where(err.detach() < 0.1, 1.0, 0.5).to(err)
    if inside_weight != 1.0:
        w = w * torch.where(queries[..., 3] < 0, float(inside_weight), 1.0).to(err)
    we = w * err
    parts = [we[:, :n_uniform], we[:, n_uniform:]]
    parts = [p for p in parts if p.shape[1] > 0]
    l_sdf = cast("torch.Tensor", sum(p.mean() for p in parts)) / len(parts)  # sum() of tensors is a tensor
    l_center = lat.center.to(queries.dtype).abs().sum(-1).mean()
    l_scale = (lat.scale.to(queries.dtype) - 1.0).abs().mean()
    loss = l_sdf + 0.2 * l_center + 0.001 * l_scale
    return {"loss": loss.clamp(-4.0, 4.0), "sdf": l_sdf, "center": l_center, "scale": l_scale}


def validate(prior: ShapePrior, objs: list[ObjectData], cfg: SampleConfig, *, seed: int,
             n_queries: int = 10000, batch: int = 8, sensor: bool = False) -> dict[str, float]:
    """Mean volumetric IoU on the first ``n_queries`` uniform queries of each object (§2.7).

    Inputs are random depth views + noise with a fixed seed (the same inputs every validation), no
    augmentation, no centroid noise; ``sensor=True`` draws them with the depth-sensor model instead.

    Also calibrates an iso offset ``c ∈ [−0.03, 0.06]`` (`best_iso_offset`): the constant that maximises the mean
    IoU of ``sdf − c < 0`` (a thin-walled shape is first learnt as a slightly positive shell, and shifting the level
    set by ``c > 0`` recovers it; a loss that weighs the inside more, `TrainArgs.inside_weight`, learns a slightly
    fat one, ``c < 0``). ``c = 0`` is in the grid and wins ties with the others, the smallest ``|c|`` first, so
    ``iou_cal >= iou``.

    Returns:
        ``iou`` (mean), ``iou_min``, ``iou_cal`` (mean IoU at the best offset), ``iso_offset`` (that offset),
        ``center_err`` (mean L2 of Θ_c), ``scale`` (mean Θ_s), ``sdf_l1`` (mean |err|).
    """
    import torch

    from efem_viz.prior.data import input_cloud, sensor_cloud

    rng = np.random.default_rng(seed)
    clouds = np.stack([sensor_cloud(o, cfg, rng) if sensor else input_cloud(o, cfg, rng) for o in objs])
    ious, cerr, scales, l1, preds, gts = [], [], [], [], [], []
    with torch.no_grad():
        for s in range(0, len(objs), batch):
            part = objs[s:s + batch]
            pcl = torch.as_tensor(clouds[s:s + batch], dtype=prior.dtype, device=prior.device)
            q = torch.as_tensor(np.stack([o.uni[:n_queries] for o in part]), dtype=prior.dtype,
                                device=prior.device)
            lat = prior.encode(pcl)
            pred = prior.sdf(q[..., :3], lat)
            gt_in = q[..., 3] <= 0
            pr_in = pred < 0
            inter = (gt_in & pr_in).sum(1).to(torch.float64)
            union = (gt_in | pr_in).sum(1).to(torch.float64).clamp_min(1)
            ious.extend((inter / union).tolist())
            cerr.extend(lat.center.norm(dim=-1).tolist())
            scales.extend(lat.scale.tolist())
            l1.extend((pred - q[..., 3]).abs().mean(1).tolist())
            preds.append(pred.cpu().numpy())
            gts.append(gt_in.cpu().numpy())
    pred_all, gt_all = np.concatenate(preds), np.concatenate(gts)
    best_c, best_iou = best_iso_offset(pred_all, gt_all)
    out = {"iou": float(np.mean(ious)), "iou_min": float(np.min(ious)), "iou_cal": best_iou,
           "iso_offset": best_c, "center_err": float(np.mean(cerr)), "scale": float(np.mean(scales)),
           "sdf_l1": float(np.mean(l1))}
    cats = np.array([o.name.rsplit("_", 1)[0] for o in objs])
    if len(set(cats)) > 1:  # a family's prior: its calibrated IoU per category too
        pr = pred_all < best_c
        per = (pr & gt_all).sum(1) / np.maximum((pr | gt_all).sum(1), 1)
        out.update({f"iou_cal_{c}": float(np.mean(per[cats == c])) for c in sorted(set(cats))})
    return out


def fixed_point_inputs(prior: ShapePrior, pcl: np.ndarray, rng: np.random.Generator, *, p: float,
                       tau: float) -> np.ndarray:
    """Replace a fraction ``p`` of the input clouds by the model's own SDF-band inliers (fixed-point examples).

    For each chosen cloud: encode it, keep the points with |sdf| ≤ ``tau`` and draw ``N`` points from them with
    replacement, as one EM M-step re-samples what a fit explains. The target SDF stays the whole object, so
    the model learns that re-encoding what it explains must give the same shape and scale. Clouds with fewer
    than a quarter of their points in the band stay as they were.

    Args:
        prior: The model (evaluated under no_grad, in eval mode; its mode is restored).
        pcl: (B, N, 3) input clouds.
        rng: Random generator.
        p: Probability per cloud.
        tau: SDF band, canonical units.

    Returns:
        (B, N, 3) float32 clouds (a new array).
    """
    import torch

    out = np.array(pcl, np.float32, copy=True)
    pick = np.flatnonzero(rng.random(len(out)) < p)
    if len(pick) == 0:
        return out
    was_training = prior.training
    prior.eval()
    with torch.no_grad():
        x = torch.as_tensor(out[pick], dtype=prior.dtype, device=prior.device)
        d = prior.sdf(x, prior.encode(x)).abs().float().cpu().numpy()
    prior.train(was_training)
    n = out.shape[1]
    for row, b in enumerate(pick):
        ins = np.flatnonzero(d[row] <= tau)
        if len(ins) >= n // 4:
            out[b] = out[b][ins[rng.integers(0, len(ins), n)]]
    return out


ISO_OFFSETS = tuple(sorted((round(0.0025 * i, 4) for i in range(-12, 25)), key=lambda c: (abs(c), c < 0)))
"""The iso offsets `validate` calibrates over, −0.03 to 0.06 in steps of 0.0025: the smallest shift first, of two
equal shifts the positive one (a thin wall's shell, the common case)."""


def best_iso_offset(pred: np.ndarray, gt_in: np.ndarray) -> tuple[float, float]:
    """The offset of `ISO_OFFSETS` whose level set ``pred < c`` has the highest mean IoU with `gt_in`, and that
    IoU; ties go to the smallest shift (0 first, then the positive one of ±c).

    Args:
        pred: (B, Q) predicted SDF of B shapes' queries.
        gt_in: (B, Q) bool, the queries inside each shape.
    """
    best_c, best_iou = 0.0, -1.0
    for c in ISO_OFFSETS:
        pr = pred < c
        iou_c = float(np.mean((pr & gt_in).sum(1) / np.maximum((pr | gt_in).sum(1), 1)))
        if iou_c > best_iou + 1e-9:
            best_c, best_iou = c, iou_c
    return best_c, best_iou


def with_iso_offset(prior: ShapePrior, offset: float) -> ShapePrior:
    """A copy of ``prior`` whose SDF is ``sdf − offset`` (``fc_out.bias`` shifted); ``prior`` is untouched."""
    import copy

    import torch

    out = copy.deepcopy(prior)
    with torch.no_grad():
        out.decoder.fc_out.bias.sub_(offset)
    return out


def calibrate_scale_factor(prior: ShapePrior, pcl: torch.Tensor) -> float:
    """Set σ so that the mean Θ_s of ``pcl`` (unit objects) is 1 at initialisation; returns the new σ."""
    import torch

    with torch.no_grad():
        s = float(prior.encode(pcl).scale.mean())
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"cannot calibrate σ: mean Θ_s at init is {s}")
    prior.config.scale_factor = prior.config.scale_factor / s
    return prior.config.scale_factor


@dataclass
class _State:
    iteration: int = 0
    wall_s: float = 0.0
    best_iou: float = -1.0
    best_iteration: int = -1
    warmup_from: int = 0
    """Where Adam last started without moments (the learning-rate warm-up counts from here)."""
    ema_updates: int = 0
    """Steps the weight average (``--ema-decay``) has taken in so far."""
    curve: list[dict[str, Any]] = field(default_factory=list)
    val_curve: list[dict[str, Any]] = field(default_factory=list)


def _rng_state(rng: np.random.Generator) -> dict[str, Any]:
    return dict(rng.bit_generator.state)


def average_matches(average: Any, weights: dict[str, torch.Tensor]) -> bool:
    """Whether a saved weight average (``--ema-decay``) fits these weights: a dict of tensors with their names and
    shapes, its floating-point entries finite."""
    import torch

    return isinstance(average, dict) and set(average) == set(weights) and all(
        isinstance(v, torch.Tensor) and v.shape == weights[k].shape
        and not (v.is_floating_point() and not bool(v.isfinite().all())) for k, v in average.items())


class WeightAverage:
    """An exponential moving average of a model's weights (Polyak averaging; ``train-prior --ema-decay``).

    After each optimiser step every floating-point entry of the state dict moves to ``a ← β a + (1 − β) w`` with
    ``β = min(decay, (1 + n) / (10 + n))`` for the n-th update (the short early window lets the average leave the
    starting weights quickly); other entries are copied.

    Args:
        model: the trained module.
        decay: β's limit, in [0, 1).
        average: a saved average (`state`) to continue; None starts from the model's weights.
        updates: how many updates ``average`` already holds.
    """

    def __init__(self, model: torch.nn.Module, decay: float, *, average: dict[str, torch.Tensor] | None = None,
                 updates: int = 0) -> None:
        own = model.state_dict()
        if average is not None and not average_matches(average, own):
            raise ValueError("the saved weight average does not match the model's weights (names, shapes or "
                             "finite values)")
        src = average if average is not None else own
        self.decay, self.updates = float(decay), int(updates)
        self.average = {k: src[k].detach().to(device=v.device, dtype=v.dtype).clone() for k, v in own.items()}

    def update(self, model: torch.nn.Module) -> None:
        """Take the model's current weights into the average."""
        import torch

        beta = min(self.decay, (1.0 + self.updates) / (10.0 + self.updates))
        with torch.no_grad():
            for k, v in model.state_dict().items():
                a = self.average[k]
                if a.is_floating_point():
                    a.mul_(beta).add_(v.detach(), alpha=1.0 - beta)
                else:
                    a.copy_(v)
        self.updates += 1

    def swap(self, model: torch.nn.Module) -> None:
        """Exchange the model's weights with the average (in place; twice restores both)."""
        import torch

        with torch.no_grad():
            for k, v in model.state_dict().items():
                tmp = v.clone()
                v.copy_(self.average[k])
                self.average[k].copy_(tmp)

    def state(self) -> dict[str, torch.Tensor]:
        """The averaged weights (copies, on the CPU)."""
        return {k: v.detach().cpu().clone() for k, v in self.average.items()}


def save_checkpoint(path: Path, prior: ShapePrior, opt: Any, state: _State, rng: np.random.Generator,
                    args_dict: dict[str, Any], average: WeightAverage | None = None) -> None:
    """Full resume checkpoint (atomic); with the weight average (``ema``) when the run keeps one."""
    import torch

    from efem_viz.prior.model import CHECKPOINT_FORMAT, atomic_torch_save

    atomic_torch_save({
        "format": CHECKPOINT_FORMAT, "kind": "train", "name": prior.name, "config": prior.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in prior.state_dict().items()},
        "optimizer": opt.state_dict(), "state": dataclasses.asdict(state), "np_rng": _rng_state(rng),
        "torch_rng": torch.get_rng_state(), "args": args_dict, "metadata": dict(prior.metadata),
        **({"ema": average.state()} if average is not None else {}),
    }, path)


def _report(args: TrainArgs, prior: ShapePrior, state: _State, *, sec_per_iter: float | None,
            n_train: int, n_val: int, out_dir: Path, export: Path) -> None:
    """Write ``<export stem>_training_report.json`` and ``.md`` next to the exported weights."""
    from efem_viz.prior.model import count_parameters

    stem = export.with_suffix("")
    rep = {
        "name": prior.name, "config": prior.config.to_dict(), "args": _args_dict(args),
        "parameters": {"encoder": count_parameters(prior.encoder),
                       "decoder": count_parameters(prior.decoder)},
        "n_train_objects": n_train, "n_val_objects": n_val, "iteration": state.iteration,
        "wall_time_s": round(state.wall_s, 1), "sec_per_iter": sec_per_iter, "best_val_iou": state.best_iou,
        "best_iteration": state.best_iteration, "val_curve": state.val_curve,
        "train_curve": state.curve[-400:],
        "updated_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }
    _write_text_atomic(Path(f"{stem}_training_report.json"), report_json(rep))
    notes_path = args.report_notes if args.report_notes is not None else out_dir / "report_notes.md"
    notes = notes_path.read_text(encoding="utf-8") if notes_path.is_file() else ""
    lines = [f"# Training report: `{export.name}`", "", notes.strip(), "",
             "## Run (generated by `efem-viz train-prior`, rewritten at every validation)", "",
             f"- updated: {rep['updated_utc']} UTC; iterations: {state.iteration}; wall time: "
             f"{state.wall_s / 60:.1f} min" + (f"; {sec_per_iter:.2f} s/iter" if sec_per_iter else ""),
             f"- objects: {n_train} train / {n_val} val; batch {args.batch_size}; lr {args.lr:g}, "
             f"decay ×{args.decay_factor} at {[int(round(f * args.iterations)) for f in args.decay_at]} "
             f"of {args.iterations}",
             f"- parameters: encoder {rep['parameters']['encoder']:,}, "
             f"decoder {rep['parameters']['decoder']:,}",
             f"- architecture: `{json.dumps(prior.config.to_dict())}`",
             f"- **best validation IoU {state.best_iou:.4f} at iteration {state.best_iteration}** "
             f"(exported model; {'iso-offset calibrated' if args.calibrate_iso else 'raw'} IoU)", "",
             "| iteration | wall min | val IoU | min IoU | calibrated IoU (offset) | Θ_c error | mean Θ_s "
             "| SDF L1 | train loss | sensor inputs: calibrated IoU, Θ_s |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for v in state.val_curve:
        cal = f"{v['iou_cal']:.4f} ({v['iso_offset']:.4f})" if "iou_cal" in v else "–"
        lines.append(f"| {v['iteration']} | {v['wall_s'] / 60:.1f} | {v['iou']:.4f} | {v['iou_min']:.3f} | "
                     f"{cal} | "
                     f"{v['center_err']:.4f} | {v['scale']:.3f} | {v['sdf_l1']:.4f} | "
                     f"{v.get('train_loss', 0):.4f} | "
                     + (f"{v['sensor_iou_cal']:.4f}, {v['sensor_scale']:.3f} |" if "sensor_iou_cal" in v else "– |"))
    _write_text_atomic(Path(f"{stem}_training_report.md"), "\n".join(lines) + "\n")


def _args_dict(args: TrainArgs) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(args), default=_json_default))


# ------------------------------------------------------------------------------------------------------ train
def _check_args(args: TrainArgs) -> None:
    """Refuse a run that cannot work, before any data is loaded.

    Raises:
        ValueError: an unknown matmul precision, a grown decoder without a prior to grow, a batch size, iteration
            count or validation interval below 1, an inside weight that is not a positive number, a weight-average
            decay outside [0, 1), or bad member weights.
    """
    from efem_viz.prior.config import matmul_precision

    matmul_precision(args.matmul_dtype)  # an unknown name fails here, before any data is loaded
    if (args.grow_decoder_hidden is not None or args.grow_decoder_blocks is not None) and args.init_from is None \
            and args.resume_from is None and not args.resume:
        raise ValueError("--grow-decoder-hidden/--grow-decoder-blocks grow a trained prior: give --init-from")
    if args.batch_size < 1 or args.iterations < 1 or args.val_every < 1:
        raise ValueError(f"batch_size/iterations/val_every must be >= 1 (got {args.batch_size}, "
                         f"{args.iterations}, {args.val_every})")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1 (got {args.steps})")
    if not (math.isfinite(args.inside_weight) and args.inside_weight > 0):
        raise ValueError(f"--inside-weight must be a positive number (got {args.inside_weight})")
    if not (math.isfinite(args.ema_decay) and 0.0 <= args.ema_decay < 1.0):
        raise ValueError(f"--ema-decay must be in [0, 1) (got {args.ema_decay})")
    member_weight_map(args.member_weights)


def member_weight_map(items: Sequence[str]) -> dict[str, float]:
    """``("mug=2", "bowl=1.5")`` as a mapping; each weight finite and > 0.

    Raises:
        ValueError: an item without ``=``, an empty or repeated member, or a weight that is not a positive number.
    """
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = str(item).partition("=")
        name = name.strip()
        try:
            w = float(value)
        except ValueError:
            w = math.nan
        if not sep or not name or name in out or not (math.isfinite(w) and w > 0):
            raise ValueError(f"--member-weights takes distinct member=weight items with a weight > 0 (got {item!r})")
        out[name] = w
    return out


def sampling_probabilities(objs: Sequence[ObjectData], weights: dict[str, float]) -> np.ndarray | None:
    """Per-object sampling probabilities from member weights (an object takes its member's weight,
    `efem_viz.data.procedural.variant_of`, others 1); None when no weight is given (uniform).

    Raises:
        ValueError: a weighted member that names no training object (a typo would silently train uniform).
    """
    if not weights:
        return None
    from efem_viz.data.procedural import variant_of  # (trimesh): only when weights are given

    members = [variant_of(o.name) for o in objs]
    unknown = sorted(set(weights) - set(members))
    if unknown:
        raise ValueError(f"--member-weights names no training object: {', '.join(unknown)} "
                         f"(members: {', '.join(sorted(set(members)))})")
    w = np.array([weights.get(m, 1.0) for m in members], dtype=np.float64)
    return w / w.sum()


def _read_resume_checkpoint(args: TrainArgs, last: Path) -> tuple[Path | None, dict[str, Any] | None]:
    """The checkpoint a resumed run starts from (``--resume-from``, or ``last`` with ``--resume``), checked.

    Returns:
        Its path and contents; (None, None) for a run that does not resume.

    Raises:
        FileNotFoundError: resuming without a checkpoint.
        ValueError: not a train-prior resume checkpoint, or one the prior loaders refuse.
    """
    resume_path = args.resume_from if args.resume_from is not None else (last if args.resume else None)
    if resume_path is None:
        return None, None
    if not Path(resume_path).is_file():
        raise FileNotFoundError(f"no checkpoint to resume from: {resume_path}")
    from efem_viz.prior.model import checked_prior_parts, read_checkpoint

    ckpt = read_checkpoint(resume_path)
    need = ("config", "state_dict", "optimizer", "state")
    if not isinstance(ckpt, dict) or any(k not in ckpt for k in need):
        raise ValueError(f"{resume_path}: not a train-prior resume checkpoint (needs {', '.join(need)})")
    # the prior loaders' checks (sizes declared, shapes, views, finite values) before anything is allocated or
    # any data is prepared (a 16 KB file declaring a 20,000-wide decoder cost 90 s and 6.5 GB)
    checked_prior_parts(ckpt, Path(resume_path))
    ema = ckpt.get("ema")
    if ema is not None and not average_matches(ema, ckpt["state_dict"]):  # checked before any data is prepared
        raise ValueError(f"{resume_path}: its weight average does not match its weights")
    return resume_path, ckpt


INIT_VALIDATION_KEYS = ("iteration", "val_iou", "val_iou_raw", "val_metrics", "iso_offset", "weights")
"""Metadata of a saved prior that describe its own validation: a run started from it (`--init-from`) drops them, so
that its snapshots and exports never show the start's scores as their own."""
TRAINED_KEYS = ("iou", "iou_cal", "iso_offset", "sensor_iou", "sensor_iou_cal", "sensor_iso_offset")
"""Validation metrics of the trained weights a weight-averaged run reports beside the average's (``trained_*``)."""

RESUME_STATE_LIMIT_BYTES = 20 * 2**20
"""A resume state is committed with the weights: never larger than this."""


RESUME_CURVE_KEEP = 400
"""Training-loss curve entries a resume state keeps: the last ones, as many as the training report shows
(`train_curve`); the full curve of a long run was a fifth of a shipped resume state."""


def write_resume_state(checkpoint: Path, dest: Path) -> int | None:
    """Write the shippable resume state of a training checkpoint: weights (stored in float16), loop state (the
    training-loss curve cut to its last `RESUME_CURVE_KEEP` entries), RNG states and metadata, without the
    optimiser's moments (two thirds of the file; a resumed run restarts Adam, which re-estimates them within a few
    dozen steps) and without the weight average of ``--ema-decay`` (it would double the file; a run resumed from it
    starts its average from the weights, and the average forgets where it started within about ``1 / (1 - decay)``
    steps). Float16 halves what the repository carries per prior; a resumed run continues in float32 from weights
    rounded by at most 2^-11 of their size, less than one of its steps moves them. Atomic.

    Returns:
        The bytes written, or None (with a warning) when even that would exceed `RESUME_STATE_LIMIT_BYTES`.
    """
    import io

    import torch

    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    ckpt["optimizer"] = None
    ckpt.pop("ema", None)
    ckpt["state_dict"] = {k: v.half() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    state = ckpt.get("state")
    if isinstance(state, dict) and isinstance(state.get("curve"), list):
        state["curve"] = state["curve"][-RESUME_CURVE_KEEP:]
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    data = buf.getvalue()
    if len(data) > RESUME_STATE_LIMIT_BYTES:
        log.warning("resume state would be %.1f MB (> %d MB): not written to %s", len(data) / 2**20,
                    RESUME_STATE_LIMIT_BYTES // 2**20, dest)
        return None
    from efem_viz.data.io import atomic_write

    atomic_write(Path(dest), lambda tmp: Path(tmp).write_bytes(data))
    return len(data)


def _build_prior(args: TrainArgs, ckpt: dict[str, Any] | None) -> tuple[ShapePrior, bool]:
    """The prior to train: the checkpoint's architecture (its weights come with the optimiser, `_resume_state`),
    else ``--init-from``'s weights (its decoder grown when asked; its settings only for the same category), else a
    fresh one of ``args.prior_config()``. Draws the fresh weights from torch's global generator (seeded by `train`).

    Returns:
        The prior on ``args.device`` and whether its weights came from ``--init-from``.
    """
    from efem_viz.prior.model import ShapePrior

    if ckpt is not None:
        from efem_viz.prior.config import PriorConfig

        cfg = PriorConfig.from_dict(ckpt["config"])
    else:
        cfg = args.prior_config()
    init: ShapePrior | None = None
    if ckpt is None and args.init_from is not None:
        from efem_viz.prior.config import prior_category
        from efem_viz.prior.model import load_prior

        init = load_prior(args.init_from, load_codebook=False)
        if args.grow_decoder_hidden is not None or args.grow_decoder_blocks is not None:
            from efem_viz.prior.widen import widen_decoder

            h0, b0 = init.config.decoder_hidden, init.config.decoder_blocks
            init = widen_decoder(init, hidden=args.grow_decoder_hidden, blocks=args.grow_decoder_blocks,
                                 seed=args.seed)
            log.info("decoder grown %dx%d -> %dx%d (function-preserving)", h0, b0,
                     init.config.decoder_hidden, init.config.decoder_blocks)
        if not args.init_matching:
            cfg = init.config
    prior = ShapePrior(cfg, name=args.category).to(args.device)
    if init is not None and args.init_matching:
        own = prior.state_dict()
        taken = {k: v for k, v in init.state_dict().items() if k in own and own[k].shape == v.shape}
        if not taken:
            raise ValueError(f"--init-matching: no weight of {args.init_from} matches this architecture")
        prior.load_state_dict(taken, strict=False)
        fresh = sorted(k for k in own if k not in taken)
        log.info("took %d of %d weights from %s; fresh: %s", len(taken), len(own), args.init_from,
                 ", ".join(fresh) if len(fresh) <= 12 else f"{len(fresh)} tensors ({', '.join(fresh[:6])}, ...)")
    elif init is not None:
        prior.load_state_dict(init.state_dict())
        # Another category's prior gives weights only: its τ_out, calibration and category settings are not ours.
        # The same category's keep the rest; the record of the saved prior's own validation is not this run's.
        kept = dict(init.metadata or {}) if prior_category(init).name == args.category else {}
        kept = {k: v for k, v in kept.items() if k not in INIT_VALIDATION_KEYS}
        prior.metadata = {**kept, "init_from": str(args.init_from)}
        log.info("initialised from %s", args.init_from)
    return prior, init is not None


def _resume_state(args: TrainArgs, prior: ShapePrior, opt: Any, rng: np.random.Generator, ckpt: dict[str, Any],
                  resume_path: Path | None) -> _State:
    """Put a resume checkpoint back: weights, optimiser, loop state, both RNG states and the prior's metadata
    (``--reset-best`` forgets the best validation score). Returns the loop state."""
    import torch

    prior.load_state_dict(ckpt["state_dict"])
    if ckpt["optimizer"] is not None:
        opt.load_state_dict(ckpt["optimizer"])
    else:
        log.info("the resume state carries no optimiser moments (a shipped state): Adam restarts")
    state = _State(**ckpt["state"])
    rng.bit_generator.state = ckpt["np_rng"]
    torch.set_rng_state(ckpt["torch_rng"])
    prior.metadata = dict(ckpt.get("metadata") or {})
    log.info("resumed from %s at iteration %d", resume_path, state.iteration)
    if args.reset_best:
        log.info("--reset-best: forgetting best val IoU %.4f (iteration %d)", state.best_iou,
                 state.best_iteration)
        state.best_iou, state.best_iteration = -1.0, -1
    return state


def _calibrate_new_prior(args: TrainArgs, prior: ShapePrior, scfg: SampleConfig, train_objs: list[ObjectData]) -> None:
    """Calibrate a fresh prior's σ on input clouds of the first 32 training objects (their own seeded RNG)."""
    import torch

    calib_rng = np.random.default_rng(args.seed + 7)
    from efem_viz.prior.data import input_cloud

    calib = np.stack([input_cloud(o, scfg, calib_rng) for o in train_objs[:32]])
    sigma = calibrate_scale_factor(prior, torch.as_tensor(calib, dtype=prior.dtype))
    log.info("calibrated σ = %.6g", sigma)


class _TrainLoop:
    """The iterations of one `train` call: optimiser steps, validations (exporting the best model and rewriting the
    report) and resume checkpoints, with the clocks and running losses they share.

    Args:
        args: the run configuration.
        prior, opt, state, rng: the prior, its optimiser, the loop state and the data generator (a checkpoint holds
            all four).
        scfg: how training inputs and queries are sampled.
        train_objs, val_objs: the prepared objects.
        out_dir: the run folder (``last.pt``, snapshots).
        export: where the best model goes.
        args_dict: ``args`` as JSON (stored in every checkpoint).
        t_start: when `train` started (`time.monotonic`; the time budget counts from it).
        adam_fresh: Adam starts without moments here (the learning rate warms up from this iteration).
        average: the weight average (``--ema-decay``) that validation scores and exports; None: the trained
            weights.
    """

    def __init__(self, args: TrainArgs, prior: ShapePrior, opt: Any, state: _State, rng: np.random.Generator, *,
                 scfg: SampleConfig, train_objs: list[ObjectData], val_objs: list[ObjectData], out_dir: Path,
                 export: Path, args_dict: dict[str, Any], t_start: float, adam_fresh: bool = True,
                 average: WeightAverage | None = None) -> None:
        self.args, self.prior, self.opt, self.state, self.rng = args, prior, opt, state, rng
        self.average = average
        if adam_fresh:
            state.warmup_from = state.iteration
        self.scfg, self.train_objs, self.val_objs = scfg, train_objs, val_objs
        self.sample_p = sampling_probabilities(train_objs, member_weight_map(args.member_weights))
        self.out_dir, self.export, self.last, self.args_dict = out_dir, export, out_dir / "last.pt", args_dict
        self.t_start = t_start
        self.enc_params = list(prior.encoder.parameters())
        self.dec_params = list(prior.decoder.parameters())
        self.budget_s = args.time_budget_min * 60.0 if args.time_budget_min is not None else math.inf
        self.wall0 = state.wall_s
        self.t_loop = time.monotonic()
        self.last_ckpt = time.monotonic()
        self.last_resume_export = -math.inf
        self.iter_times: list[float] = []
        self.done_here = 0
        self.running: list[float] = []

    def elapsed(self) -> float:
        """Seconds since `train` started."""
        return time.monotonic() - self.t_start

    def validate(self) -> None:
        """Validate (clean inputs, and sensor-like ones when trained on them), export the model when it is the best
        so far (iso offset calibrated when asked), rewrite the training report."""
        from efem_viz.prior.model import save_prior

        args, prior, state = self.args, self.prior, self.state
        prior.eval()
        t0 = time.monotonic()
        m = self._scores()
        if self.average is not None:  # the average scored beside the trained weights (now in the model)
            trained = {f"trained_{k}": v for k, v in m.items() if k in TRAINED_KEYS}
            self.average.swap(prior)
            m = {**self._scores(), **trained}
        prior.train()
        m.update(iteration=state.iteration, wall_s=self.wall0 + (time.monotonic() - self.t_loop),
                 train_loss=float(np.mean(self.running)) if self.running else float("nan"),
                 val_time_s=round(time.monotonic() - t0, 2))
        state.val_curve.append(m)
        log.info("val @%d: IoU %.4f (min %.3f; calibrated %.4f at c=%.4f) |Θc| %.4f Θs %.3f L1 %.4f [%.1fs]%s",
                 state.iteration, m["iou"], m["iou_min"], m["iou_cal"], m["iso_offset"], m["center_err"],
                 m["scale"], m["sdf_l1"], m["val_time_s"],
                 f"; sensor inputs: calibrated IoU {m['sensor_iou_cal']:.4f} Θs {m['sensor_scale']:.3f}"
                 if "sensor_iou_cal" in m else "")
        if "trained_iou_cal" in m:
            log.info("val @%d: averaged weights above; the trained weights: calibrated IoU %.4f%s", state.iteration,
                     m["trained_iou_cal"], f", sensor inputs {m['trained_sensor_iou_cal']:.4f}"
                     if "trained_sensor_iou_cal" in m else "")
        per_cat = {k[len("sensor_iou_cal_"):]: v for k, v in m.items() if k.startswith("sensor_iou_cal_")} or \
            {k[len("iou_cal_"):]: v for k, v in m.items() if k.startswith("iou_cal_")}
        if per_cat:
            log.info("val @%d per category (calibrated IoU%s): %s", state.iteration,
                     ", sensor inputs" if args.sensor_p > 0 else "",
                     ", ".join(f"{c} {v:.4f}" for c, v in per_cat.items()))
        key = ("sensor_" if args.sensor_p > 0 else "") + ("iou_cal" if args.calibrate_iso else "iou")
        offset_key = ("sensor_" if args.sensor_p > 0 else "") + "iso_offset"
        # with an average, the export is whichever of the two scores higher (the average lags a fast-learning run)
        averaged = self.average is not None and m[key] >= m[f"trained_{key}"]
        if self.average is not None and not averaged:
            self.average.swap(prior)  # the trained weights back before the export
        weights, prefix = ("average", "") if averaged else ("trained", "trained_" if self.average is not None else "")
        score = m[prefix + key]
        if score > state.best_iou:
            state.best_iou, state.best_iteration = score, state.iteration
            trained_on = str(args.meshes) if args.meshes is not None else f"procedural:{args.category}"
            offset = m[prefix + offset_key] if args.calibrate_iso else 0.0
            save_prior(with_iso_offset(prior, offset), self.export,
                       extra={"iteration": state.iteration, "val_iou": score, "val_iou_raw": m[prefix + "iou"],
                              "iso_offset": offset, "val_metrics": m, "trained_on": trained_on,
                              "n_train": len(self.train_objs), "weights": weights})
            log.info("exported best model (%s weights) to %s", weights, self.export)
        if averaged and self.average is not None:
            self.average.swap(prior)  # the trained weights back
        spi = float(np.median(self.iter_times[-200:])) if self.iter_times else None
        _report(args, prior, state, sec_per_iter=spi, n_train=len(self.train_objs), n_val=len(self.val_objs),
                out_dir=self.out_dir, export=self.export)

    def _scores(self) -> dict[str, Any]:
        """Validation metrics of the prior's current weights: clean inputs, and sensor-like ones (``sensor_*``)
        when trained on them."""
        args = self.args
        m = validate(self.prior, self.val_objs, self.scfg, seed=args.seed + 99)
        if args.sensor_p > 0:
            ms = validate(self.prior, self.val_objs, self.scfg, seed=args.seed + 98, sensor=True)
            m.update({f"sensor_{k}": v for k, v in ms.items()})
        return m

    def checkpoint(self, final: bool = False) -> None:
        """Write the resume checkpoint ``last.pt``; copy it to ``--resume-export`` at its interval and at the end
        (when under 20 MB)."""
        args = self.args
        self.state.wall_s = self.wall0 + (time.monotonic() - self.t_loop)
        save_checkpoint(self.last, self.prior, self.opt, self.state, self.rng, self.args_dict, self.average)
        self.last_ckpt = time.monotonic()
        due = time.monotonic() - self.last_resume_export >= args.resume_export_every_min * 60
        if args.resume_export is not None and (due or final):
            size = write_resume_state(self.last, args.resume_export)
            if size is not None:
                self.last_resume_export = time.monotonic()

    def stop_reason(self, stop_requested: threading.Event, max_iterations: int | None) -> str | None:
        """Why the loop stops before the next iteration (a signal, this call's iteration cap, the time budget);
        None to go on."""
        if stop_requested.is_set():
            return "interrupted (SIGINT/SIGTERM)"
        if max_iterations is not None and self.done_here >= max_iterations:
            return "max_iterations"
        if self.elapsed() >= self.budget_s:
            return "time budget"
        return None

    def step(self) -> None:
        """One optimiser step on a random batch (fixed-point inputs when asked), with its curve and log entries.

        Raises:
            FloatingPointError: a non-finite loss.
        """
        import torch

        from efem_viz.prior.config import matmul_precision
        from efem_viz.prior.data import make_batch

        args, prior, state, rng, scfg = self.args, self.prior, self.state, self.rng, self.scfg
        t0 = time.monotonic()
        lr = lr_at(state.iteration, base=args.lr, total=args.iterations, decay_at=args.decay_at,
                   factor=args.decay_factor)
        if args.warmup_steps > 0:
            lr *= min(1.0, (state.iteration - state.warmup_from + 1) / args.warmup_steps)
        for g in self.opt.param_groups:
            g["lr"] = lr
        if self.sample_p is None:
            idx = rng.integers(0, len(self.train_objs), args.batch_size)
        else:
            idx = rng.choice(len(self.train_objs), size=args.batch_size, p=self.sample_p)
        pcl_np, q_np = make_batch([self.train_objs[i] for i in idx], scfg, rng, others=self.train_objs, augment=True)
        noise_np = rng.normal(0.0, scfg.centroid_noise, (args.batch_size, 3))
        if args.fixed_point_p > 0:
            with matmul_precision(args.matmul_dtype, prior.device.type):
                pcl_np = fixed_point_inputs(prior, pcl_np, rng, p=args.fixed_point_p,
                                            tau=args.fixed_point_tau)
        pcl = torch.as_tensor(pcl_np, dtype=prior.dtype, device=prior.device)
        q = torch.as_tensor(q_np, dtype=prior.dtype, device=prior.device)
        noise = torch.as_tensor(noise_np, dtype=prior.dtype, device=prior.device)
        with matmul_precision(args.matmul_dtype, prior.device.type):
            losses = compute_losses(prior, pcl, q, n_uniform=scfg.n_query_uniform, centroid_noise=noise,
                                    inside_weight=args.inside_weight)
        self.opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        gn_e = float(torch.nn.utils.clip_grad_norm_(self.enc_params, 4.0))
        gn_d = 0.0 if args.freeze_decoder else float(torch.nn.utils.clip_grad_norm_(self.dec_params, 4.0))
        self.opt.step()
        if self.average is not None:
            self.average.update(prior)
            state.ema_updates = self.average.updates
        state.iteration += 1
        self.done_here += 1
        dt = time.monotonic() - t0
        self.iter_times.append(dt)
        lv = float(losses["loss"].detach())
        self.running.append(lv)
        self.running[:] = self.running[-50:]
        if not math.isfinite(lv):
            raise FloatingPointError(f"non-finite loss at iteration {state.iteration}")
        if state.iteration % max(1, args.log_every) == 0:
            state.curve.append({"iteration": state.iteration, "loss": lv,
                                "sdf": float(losses["sdf"].detach()),
                                "center": float(losses["center"].detach()),
                                "scale": float(losses["scale"].detach()),
                                "grad_enc": gn_e, "grad_dec": gn_d, "lr": lr, "sec": round(dt, 3)})
        if state.iteration % 50 == 0:
            log.info("it %d loss %.4f sdf %.4f center %.4f scale %.4f |g| %.2f/%.2f lr %.2g %.2fs/it",
                     state.iteration, lv, float(losses["sdf"].detach()), float(losses["center"].detach()),
                     float(losses["scale"].detach()),
                     gn_e, gn_d, lr, float(np.median(self.iter_times[-50:])))

    def run(self, *, validate_first: bool, on_progress: Callable[[int, int, dict[str, Any]], None] | None,
            max_iterations: int | None) -> str:
        """Iterate until the last iteration, a signal, ``max_iterations`` or the time budget; validate and
        checkpoint on the way and at the end. Returns why it stopped."""
        from efem_viz.prior.model import save_prior

        args, state = self.args, self.state
        self.prior.train()
        if validate_first:
            self.validate()
        stop_reason = "iterations"
        stop_requested, restore_handlers = _install_stop_handlers()
        while state.iteration < args.iterations:
            reason = self.stop_reason(stop_requested, max_iterations)
            if reason is not None:
                stop_reason = reason
                break
            self.step()
            if on_progress is not None:
                on_progress(state.iteration, args.iterations,
                            {"loss": float(np.mean(self.running)), "best_iou": state.best_iou,
                             "left_min": (self.budget_s - self.elapsed()) / 60 if math.isfinite(self.budget_s)
                             else float("nan")})
            if state.iteration % args.val_every == 0:
                self.validate()
            if args.snapshot_every > 0 and state.iteration % args.snapshot_every == 0:
                save_prior(self.prior, self.out_dir / f"snap_{state.iteration}.pt",
                           extra={"iteration": state.iteration})
            if time.monotonic() - self.last_ckpt >= args.ckpt_every_min * 60:
                self.checkpoint()
        restore_handlers()
        if not state.val_curve or state.val_curve[-1]["iteration"] != state.iteration:
            self.validate()
        self.checkpoint(final=True)
        return stop_reason


def train(args: TrainArgs, *, on_progress: Callable[[int, int, dict[str, Any]], None] | None = None,
          max_iterations: int | None = None) -> dict[str, Any]:
    """Run (or resume) training.

    Args:
        args: Run configuration.
        on_progress: Called after every iteration with ``(iteration, total, info)``.
        max_iterations: Stop after this many iterations of *this call* (tests).

    Returns:
        Summary dict: ``iteration``, ``best_iou``, ``best_iteration``, ``export``, ``val_curve``, ``curve``.

    Raises:
        FileNotFoundError: If resuming without a checkpoint.
        ValueError: On bad arguments.
    """
    import torch

    from efem_viz.prior.model import count_parameters

    _check_args(args)
    t_start = time.monotonic()
    torch.set_num_threads(max(1, args.threads))
    out_dir = args.resolved_out_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    export = args.resolved_export()
    resume_path, ckpt = _read_resume_checkpoint(args, out_dir / "last.pt")

    log.info("loading training data ...")
    train_objs = load_objects(args, "train")
    val_objs = load_objects(args, "val")
    log.info("data: %d train / %d val objects (%.1f s)", len(train_objs), len(val_objs),
             time.monotonic() - t_start)

    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    prior, from_init = _build_prior(args, ckpt)
    scfg = args.sample_config(prior.config.n_pcl)
    if args.freeze_decoder:
        for prm in prior.decoder.parameters():
            prm.requires_grad_(False)
    opt = torch.optim.Adam([prm for prm in prior.parameters() if prm.requires_grad], lr=args.lr)
    state = _State()
    if ckpt is not None:
        state = _resume_state(args, prior, opt, rng, ckpt, resume_path)
    elif not from_init or args.init_matching:  # a new architecture's σ is measured on its own inputs
        _calibrate_new_prior(args, prior, scfg, train_objs)
    average = None
    if args.ema_decay > 0:
        saved = ckpt.get("ema") if ckpt is not None else None
        average = WeightAverage(prior, args.ema_decay, average=saved,
                                updates=state.ema_updates if saved is not None else 0)
        state.ema_updates = average.updates  # a fresh average counts from 0 in every checkpoint it reaches
    args_dict = _args_dict(args)
    _write_text_atomic(out_dir / "config.json", json.dumps(
        {"args": args_dict, "prior": prior.config.to_dict(), "sample": dataclasses.asdict(scfg),
         "n_train": len(train_objs), "n_val": len(val_objs)}, indent=1, default=_json_default) + "\n")
    log.info("model: encoder %d params, decoder %d params", count_parameters(prior.encoder),
             count_parameters(prior.decoder))
    loop = _TrainLoop(args, prior, opt, state, rng, scfg=scfg, train_objs=train_objs, val_objs=val_objs,
                      out_dir=out_dir, export=export, args_dict=args_dict, t_start=t_start,
                      adam_fresh=ckpt is None or ckpt.get("optimizer") is None, average=average)
    stop_reason = loop.run(validate_first=(state.iteration == 0 and not state.val_curve)
                           or (ckpt is not None and args.reset_best),
                           on_progress=on_progress,
                           max_iterations=max_iterations if max_iterations is not None else args.steps)
    log.info("stopped (%s) at iteration %d after %.1f min", stop_reason, state.iteration, loop.elapsed() / 60)
    return {"iteration": state.iteration, "best_iou": state.best_iou, "best_iteration": state.best_iteration,
            "export": str(export), "val_curve": state.val_curve, "curve": state.curve,
            "stop_reason": stop_reason, "checkpoint": str(loop.last)}
