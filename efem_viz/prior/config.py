"""What a shape prior is to the rest of efem-viz: its architecture config, its category settings and the
`ShapePriorLike` protocol that the solver, the viewer and the annotator type against.

Torch-free at import time. A prior is anything with `encode`, `sdf`, `sdf_and_normals`, `codebook`, `n_pcl`,
`name` and `category` (see `ShapePriorLike`): the trained `ShapePrior` (prior/model.py) and the analytic
`SpherePrior` (prior/analytic.py) both are.

Category settings (the object sizes the scale check accepts, the up-axis range, the output-mask band τ_out)
travel with the prior: read from its metadata key "category" when present, else from `KNOWN_CATEGORIES` by
the prior's name; τ_out comes from the metadata key "tau_out" written by `efem-viz calibrate-masks`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol, Union, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from efem_viz.prior.codebook import Codebook

logger = logging.getLogger(__name__)

Range = tuple[float, float]

DEFAULT_TAU_OUT = 0.04
"""Output-mask SDF threshold of docs/design/efem-method.md §3.9.12 (canonical units) for a prior that was not
calibrated."""
MAX_TAU_OUT = 0.5
"""Largest accepted τ_out: half an object size (a larger band would take in the neighbours)."""
TAU_OUT_KEY = "tau_out"
"""Metadata key of a prior's calibrated τ_out."""
CATEGORY_KEY = "category"
"""Metadata key of a prior's category settings (a dict, see `CategorySettings.to_dict`)."""
DEFAULT_PRIOR = "mug"
"""The prior efem-viz ships weights for (efem_viz/weights/mug.pt): the default of every `--prior`."""
DOMAINS: tuple[str, ...] = ("synthetic", "real")
"""Capture domains a category may give its own sizes for (the solver's presets choose one)."""
MatmulDtype = Literal["float32", "bfloat16"]
"""Precision of the networks' matrix work (the solver's `EMConfig.compute.matmul_dtype`, training's
`--matmul-dtype`)."""
MATMUL_DTYPES: tuple[str, ...] = ("float32", "bfloat16")


def matmul_precision(dtype: str, device_type: str = "cpu") -> AbstractContextManager[Any]:
    """The context in which a prior's networks run for a `MatmulDtype`: `torch.autocast` to bfloat16 on
    ``device_type`` ("cpu" or "cuda") for "bfloat16" (AMX / AVX-512 bf16 CPUs run its matrix products 4-9x
    faster), a no-op for "float32". Parameters stay float32 (autocast casts per op); k-NN graphs stay float32
    (`geometry.knn`).

    Raises:
        ValueError: On an unknown dtype name.
    """
    if dtype == "float32":
        return nullcontext()
    if dtype != "bfloat16":
        raise ValueError(f"matmul_dtype must be one of {MATMUL_DTYPES}, got {dtype!r}")
    import torch

    if device_type == "cpu" and not fast_cpu_bf16():
        _warn_slow_bf16()
    return torch.autocast(device_type, dtype=torch.bfloat16)


def cpu_has_amx() -> bool:
    """Whether this CPU has AMX tiles (False with a torch that cannot tell)."""
    import torch

    try:
        return bool(torch.cpu._is_amx_tile_supported())
    except AttributeError:  # a torch without the probe
        return False


def fast_cpu_bf16() -> bool:
    """Whether this CPU has bf16 matrix hardware (AMX tiles or AVX-512 BF16). Without it, bf16 matrix products
    fall back to conversions around scalar code: 10-17x *slower* than float32 (measured on an AVX2-only AMD
    EPYC, docs/BENCHMARKS.md)."""
    import torch

    try:
        return cpu_has_amx() or bool(torch.cpu._is_avx512_bf16_supported())
    except AttributeError:  # a torch without the probes: assume not
        return False


_slow_bf16_warned: list[bool] = []


def _warn_slow_bf16() -> None:
    if not _slow_bf16_warned:
        _slow_bf16_warned.append(True)
        logger.warning("bfloat16 asked for, but this CPU has no AMX or AVX-512 BF16: its bf16 matrix products run "
                       "about 10x slower than float32 here (use --matmul-dtype float32)")


@dataclass
class PriorConfig:
    """Architecture of a shape prior (defaults = the released mug model, docs/design/efem-method.md §1.3)."""

    widths: tuple[int, ...] = (32, 32, 64, 64, 128, 256, 512)
    """Output width of every backbone block (the number of entries is the depth)."""
    k: int = 16
    """Neighbours of the dynamic feature-space kNN graph."""
    n_pcl: int = 512
    """Encoder input size used in training / by the solver."""
    down_blocks: tuple[int, ...] = (2, 4, 5)
    """Blocks preceded by farthest-point down-sampling."""
    down_factors: tuple[int, ...] = (2, 4, 4)
    """Down-sampling factor for each entry of ``down_blocks``."""
    global_from: int = 2
    """First block with global-context fusion."""
    attention_blocks: tuple[int, ...] = ()
    """Blocks that aggregate with VN attention instead of the mean (chairs: 2..6)."""
    att_head_dim: int = 16
    """Channels per attention head."""
    latent_dim: int = 256
    """Latent width L (rows of Θ_R, length of Θ_inv)."""
    center_hidden: int = 128
    """Hidden width of the centre-head residual block."""
    scale_factor: float = 64000.0
    """σ: fixed multiplier of the Θ_s head (set once at init so Θ_s ≈ 1 for unit objects)."""
    center_times_sigma: bool = False
    """Multiply δ by σ (the kit4cates prior does)."""
    negative_slope: float = 0.2
    """VN-LeakyReLU negative slope."""
    decoder_hidden: int = 256
    """Decoder MLP width."""
    decoder_blocks: int = 5
    """Decoder residual blocks."""
    use_qnorm: bool = True
    """Feed ‖q‖ to the decoder."""
    decoder_proj_gain: float = 1.0
    """Multiplier of the projections ``Θ_R q`` in φ (released models: 1). ChNorm makes each row of Θ_R about
    ``1/√L`` long, so the raw projections are small; ``√L`` gives them unit scale. A pure reparameterisation
    of ``fc_in`` (invariance is unaffected); it did not speed up early training in our CPU runs."""
    decoder_inv_gain: float = 1.0
    """Multiplier of Θ_inv in φ (released models: 1; each entry is ~``1/L``, so ``L`` gives unit scale)."""

    def __post_init__(self) -> None:
        self.widths = tuple(int(w) for w in self.widths)
        self.down_blocks = tuple(int(b) for b in self.down_blocks)
        self.down_factors = tuple(int(f) for f in self.down_factors)
        self.attention_blocks = tuple(int(b) for b in self.attention_blocks)
        if not self.widths or min(self.widths) < 1:
            raise ValueError(f"widths must be a non-empty tuple of positive ints, got {self.widths}")
        if len(self.down_blocks) != len(self.down_factors):
            raise ValueError(f"down_blocks {self.down_blocks} and down_factors {self.down_factors} "
                             "differ in length")
        if self.k < 1 or self.latent_dim < 1 or self.decoder_hidden < 1 or self.decoder_blocks < 0:
            raise ValueError(f"bad PriorConfig sizes: {self}")
        floats = {"scale_factor": self.scale_factor, "negative_slope": self.negative_slope,
                  "decoder_proj_gain": self.decoder_proj_gain, "decoder_inv_gain": self.decoder_inv_gain}
        bad = {k: v for k, v in floats.items() if not (isinstance(v, (int, float)) and np.isfinite(v))}
        if bad:
            raise ValueError(f"PriorConfig values must be finite numbers, got {bad}")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PriorConfig:
        """Inverse of ``to_dict``; unknown keys raise ``ValueError``."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown PriorConfig keys: {sorted(unknown)}")
        return cls(**d)

    def points_per_block(self) -> list[int]:
        """Number of points after each block for an input of ``n_pcl`` points."""
        n, out = self.n_pcl, []
        down = dict(zip(self.down_blocks, self.down_factors))
        for b in range(len(self.widths)):
            if b in down:
                n = max(1, n // down[b])
            out.append(n)
        return out


@dataclass(frozen=True)
class CategorySettings:
    """Per-category settings of the solver's reviews, carried by the prior (not by the solver presets).

    Sizes are measured on the completed shape in its canonical frame (+Z up): the horizontal radius
    max ‖Q̃_xy‖ and the half-height max |Q̃_z|, in metres.
    """

    name: str
    """Category name given to the instances this prior finds (e.g. "mug")."""
    scale_horizontal: Range = (0.0, math.inf)
    """Allowed horizontal radius of a completed shape (m)."""
    scale_height: Range = (0.0, math.inf)
    """Allowed half-height of a completed shape (m)."""
    up_range: Range = (0.0, 180.0)
    """Allowed angle between the canonical up axis and world +Z (degrees)."""
    domain_sizes: Mapping[str, tuple[Range, Range]] = field(default_factory=dict)
    """Per capture domain ("synthetic", "real"): (scale_horizontal, scale_height) replacing the defaults."""
    tau_out: float | None = None
    """Output-mask SDF band (canonical units); None = `DEFAULT_TAU_OUT`."""
    r_init: float = 0.07
    """Initial crop radius of a proposal around its anchor (m): about one object across (spec: mugs and kitchen
    0.07, synthetic chairs 0.5)."""
    r_err: float = 0.11
    """E-step neighbourhood radius around a proposal's centre (m): the object's reach from its centre with a margin
    (spec: mugs 0.11, synthetic chairs 0.8)."""
    look_alike: Mapping[str, str] = field(default_factory=dict)
    """Per capture domain, the shipped look-alike model (`efem_viz/em/models/<name>.json`) that scores this
    category's fits when a solver config asks for the category's (`ConfidenceSettings.look_alike = "category"`, as
    the `real` preset does); a domain without one keeps the plain confidence."""
    max_planar: Mapping[str, float] = field(default_factory=dict)
    """Per capture domain, the largest share of a fit's mask normals that three directions may hold
    (`EMConfig.review.max_planar`; the review kills fits above it as "planar": the edges and corners of boxes,
    which a family of round objects fits as thin bottles and cans); a domain without one is not checked. Only for
    fused scans seen from around (one view of a cylinder holds its normals in a narrow fan too), and only on
    meshes: a point cloud's estimated normals gather in a few directions (`run_em` leaves it unchecked there)."""
    min_size_patience: int = 1
    """Steps in a row this category's proposals must be under the solver's size limit before they die
    (`EMConfig.elimination.min_size_patience`); 1 = at once, the method."""
    explained_decay: Mapping[str, float] = field(default_factory=dict)
    """Per capture domain, the exponent of the explained-share decay of this category's accepted fits
    (`EMConfig.confidence.explained_decay`, `em.rules.explained_decay`): a fit over objects that better fits
    already hold ranks below them. A domain without one: off (the method)."""

    def __post_init__(self) -> None:
        if not str(self.name):
            raise ValueError("a category needs a non-empty name")
        for nm in ("scale_horizontal", "scale_height", "up_range"):
            _check_range(nm, getattr(self, nm))
        for dom, sizes in self.domain_sizes.items():
            if dom not in DOMAINS:
                raise ValueError(f"unknown capture domain {dom!r} in category {self.name!r}; use one of {DOMAINS}")
            if len(sizes) != 2:
                raise ValueError(f"domain_sizes[{dom!r}] must be (scale_horizontal, scale_height), got {sizes}")
            _check_range(f"domain_sizes[{dom!r}][0]", sizes[0])
            _check_range(f"domain_sizes[{dom!r}][1]", sizes[1])
        for nm in ("r_init", "r_err"):
            if not 0.0 < float(getattr(self, nm)) <= 10.0:
                raise ValueError(f"{nm} must be in (0, 10] m, got {getattr(self, nm)}")
        if self.tau_out is not None and not 0.0 < float(self.tau_out) <= MAX_TAU_OUT:
            raise ValueError(f"tau_out must be in (0, {MAX_TAU_OUT}] or None, got {self.tau_out}")
        for dom, model in self.look_alike.items():
            if dom not in DOMAINS:
                raise ValueError(f"unknown capture domain {dom!r} in category {self.name!r}'s look_alike; use one of "
                                 f"{DOMAINS}")
            if not isinstance(model, str) or not LOOK_ALIKE_NAME.fullmatch(model):
                raise ValueError(f"look-alike model name must be a plain name ([A-Za-z0-9_-], <= 64), got {model!r}")
        if isinstance(self.min_size_patience, bool) or not isinstance(self.min_size_patience, int) \
                or not 1 <= self.min_size_patience <= 100:
            raise ValueError(f"min_size_patience must be a whole number of steps in [1, 100], got "
                             f"{self.min_size_patience!r}")
        for dom, limit in self.max_planar.items():
            if dom not in DOMAINS:
                raise ValueError(f"unknown capture domain {dom!r} in category {self.name!r}'s max_planar; use one of "
                                 f"{DOMAINS}")
            if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not 0.0 < float(limit) <= 1.0:
                raise ValueError(f"max_planar[{dom!r}] must be a share in (0, 1], got {limit!r}")
        for dom, power in self.explained_decay.items():
            if dom not in DOMAINS:
                raise ValueError(f"unknown capture domain {dom!r} in category {self.name!r}'s explained_decay; use "
                                 f"one of {DOMAINS}")
            if isinstance(power, bool) or not isinstance(power, (int, float)) or not 0.0 <= float(power) <= 16.0:
                raise ValueError(f"explained_decay[{dom!r}] must be an exponent in [0, 16], got {power!r}")

    @property
    def out_tau(self) -> float:
        """τ_out in effect."""
        return DEFAULT_TAU_OUT if self.tau_out is None else float(self.tau_out)

    def sizes(self, domain: str) -> tuple[Range, Range]:
        """(scale_horizontal, scale_height) for a capture domain (its own sizes, else the defaults)."""
        if domain in self.domain_sizes:
            h, v = self.domain_sizes[domain]
            return (float(h[0]), float(h[1])), (float(v[0]), float(v[1]))
        return self.scale_horizontal, self.scale_height

    def replace(self, **changes: Any) -> CategorySettings:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (infinite bounds as None)."""
        def enc(r: Range) -> list[float | None]:
            return [None if not math.isfinite(float(x)) else float(x) for x in r]

        return {
            "name": self.name,
            "scale_horizontal": enc(self.scale_horizontal),
            "scale_height": enc(self.scale_height),
            "up_range": enc(self.up_range),
            "domain_sizes": {d: [enc(h), enc(v)] for d, (h, v) in self.domain_sizes.items()},
            "tau_out": self.tau_out,
            "r_init": self.r_init,
            "r_err": self.r_err,
            "look_alike": dict(self.look_alike),
            "max_planar": dict(self.max_planar),
            "min_size_patience": self.min_size_patience,
            "explained_decay": dict(self.explained_decay),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CategorySettings:
        """Inverse of `to_dict`; unknown keys or bad values raise ValueError."""
        if not isinstance(d, Mapping):
            raise ValueError(f"category settings must be a dict, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown category settings keys: {sorted(unknown)}")

        def dec(r: Any, nm: str) -> Range:
            try:
                lo, hi = r
                return (float(lo) if lo is not None else 0.0, float(hi) if hi is not None else math.inf)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"category {nm} must be a pair of numbers, got {r!r}") from exc

        kw: dict[str, Any] = {"name": str(d.get("name", ""))}
        for nm in ("scale_horizontal", "scale_height", "up_range"):
            if nm in d:
                kw[nm] = dec(d[nm], nm)
        sizes = d.get("domain_sizes") or {}
        if not isinstance(sizes, Mapping):
            raise ValueError(f"category domain_sizes must be a dict, got {type(sizes).__name__}")
        domain: dict[str, tuple[Range, Range]] = {}
        for k, v in sizes.items():
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ValueError(f"category domain_sizes[{k!r}] must be [horizontal, height] ranges, got {v!r}")
            domain[str(k)] = (dec(v[0], f"{k} horizontal"), dec(v[1], f"{k} height"))
        kw["domain_sizes"] = domain
        if d.get("tau_out") is not None:
            kw["tau_out"] = float(d["tau_out"])
        for nm in ("r_init", "r_err"):  # absent in priors saved before categories carried their crop radii
            if d.get(nm) is not None:
                try:
                    kw[nm] = float(d[nm])
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"category {nm} must be a number, got {d[nm]!r}") from exc
        models = d.get("look_alike") or {}
        if not isinstance(models, Mapping):
            raise ValueError(f"category look_alike must be a dict {{domain: model}}, got {type(models).__name__}")
        kw["look_alike"] = {str(k): v for k, v in models.items()}
        planar = d.get("max_planar") or {}
        if not isinstance(planar, Mapping):
            raise ValueError(f"category max_planar must be a dict {{domain: share}}, got {type(planar).__name__}")
        kw["max_planar"] = {str(k): v for k, v in planar.items()}
        if d.get("min_size_patience") is not None:
            kw["min_size_patience"] = d["min_size_patience"]
        decay = d.get("explained_decay") or {}
        if not isinstance(decay, Mapping):
            raise ValueError(f"category explained_decay must be a dict {{domain: exponent}}, got "
                             f"{type(decay).__name__}")
        kw["explained_decay"] = {str(k): v for k, v in decay.items()}
        return cls(**kw)


LOOK_ALIKE_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""A look-alike model's name: a plain file name (`efem_viz.em.look_alike` reads `models/<name>.json`)."""


def _check_range(name: str, r: Any) -> None:
    if len(r) != 2 or any(np.isnan(float(x)) for x in r) or float(r[0]) > float(r[1]) or float(r[0]) < 0:
        raise ValueError(f"{name} must be a pair 0 <= lo <= hi, got {r}")


KNOWN_CATEGORIES: dict[str, CategorySettings] = {
    "mug": CategorySettings(
        name="mug",
        scale_horizontal=(0.03, 0.13),
        scale_height=(0.015, 0.30),
        domain_sizes={"real": ((0.03, 0.08), (0.015, 0.10)), "synthetic": ((0.03, 0.08), (0.015, 0.30))},
        look_alike={"real": "mug_uois_tune"},
    ),
    "bowl": CategorySettings(name="bowl", scale_horizontal=(0.04, 0.15), scale_height=(0.01, 0.09)),
    "sphere": CategorySettings(name="sphere", scale_horizontal=(0.03, 0.13), scale_height=(0.03, 0.13)),
    "chair": CategorySettings(name="chair", scale_horizontal=(0.12, 0.50), scale_height=(0.12, 0.65), r_init=0.5,
                              r_err=0.8, explained_decay={"synthetic": 2.0}),
    "kitchen": CategorySettings(name="kitchen", scale_horizontal=(0.02, 0.13), scale_height=(0.01, 0.30),
                                max_planar={"synthetic": 0.5}, min_size_patience=2, explained_decay={"synthetic": 2.0}),
}
"""Settings of the categories efem-viz ships priors for, used when a prior's metadata carries none. Mug sizes:
real mugs lie within 3-8 cm radius and 20 cm height; synthetic scenes scale objects over a wider range of heights,
but no true synthetic fit is wider than 7.5 cm (bundled scenes), while fits merging two or three mugs in a box or
a pile are 6.7-9 cm: the synthetic radius range stops at 8 cm too (`bench/em.py
--mode tsdf --config base= --config "tight=scale_horizontal=(0.03, 0.08)"`, box AP50 46.1 -> 66.4 on 4 scenes,
tree 51.7 -> 55.1, so3 91.6 -> 92.5, z, pile and shelf unchanged on 3-4 scenes each). The unqualified range
(3-13 cm) is for other domains. Bowls: the
procedural bowls (12-20 cm across, shallow) with a margin. Chairs: the procedural chairs (`efem_viz.data.chairs`:
stools 32 cm across to armchairs and swivel chairs 60 cm, 40 cm to 1.1 m tall) with a margin. Kitchen (the
family of mugs, bowls, bottles and cans, `procedural.FAMILIES`): the union of its members' sizes, from 2.5 cm cans
to 13 cm bowls and mugs with handles, bottles up to 26 cm tall. Its fits on fused scans are checked for
planarity (`CategorySettings.max_planar`, 0.5): on SynKit-like tuning scenes the kitchen prior fitted the edges of
the boxes beside the objects as thin bottles and cans at confidences up to 0.9, with 37-67 % of their masks' normals
in three directions against 23-43 % for true objects (docs/BENCHMARKS.md). Its proposals must be too small for two
steps in a row before they die (`CategorySettings.min_size_patience`): a tumbled bowl lying flat flips between two
fits from step to step, under the size limit on every other one (SynKit-like so3 AP50 82.7 -> 96.7). Chair and
kitchen fits in synthetic scenes rank by what better fits leave unexplained (`CategorySettings.explained_decay`, 2):
on their fixed sets over four solver seeds AP50 rose in 11 of 12 configuration-seeds for chairs (+1.5 on average)
and for the kitchen family (+0.4; the twelfth −0.1), while mugs in boxes fell (−1.5): two true mugs in a box share
a few points of their masks (docs/BENCHMARKS.md)."""


@runtime_checkable
class ShapePriorLike(Protocol):
    """What the solver, the trace replay, the viewer and the annotator need of a shape prior.

    `encode` maps (B, M, 3) world points to a batched `Latent` (torch); `sdf(x, latent)` gives canonical SDF
    values of (G, L, 3) world queries, one latent per batch row; `sdf_and_normals` also returns unit normals
    (world frame). The tensors live on the prior's device and dtype (those of its first parameter). Priors are
    torch modules (`parameters`, `to`, `eval`, `train`).
    """

    name: str
    """Display name (also the default category name)."""
    codebook: Codebook | None
    """Pose-retrieval codebook, or None (poses fall back to identity)."""
    metadata: dict[str, Any]
    """Free-form metadata: "tau_out", "category", training provenance."""

    @property
    def n_pcl(self) -> int:
        """Points per encoded set (the encoder's training size)."""
        ...

    @property
    def category(self) -> CategorySettings:
        """The category settings of this prior."""
        ...

    def encode(self, points: Any) -> Any:
        ...

    def parameters(self) -> Iterator[Any]:
        """Its tensors (a torch module's); the first one sets the device and dtype of every call."""
        ...

    def to(self, device: Any) -> Any:
        ...

    def eval(self) -> Any:
        ...

    def train(self, mode: bool = True) -> Any:
        ...

    def sdf(self, x: Any, latent: Any) -> Any:
        ...

    def sdf_and_normals(self, x: Any, latent: Any) -> tuple[Any, Any]:
        ...


PriorArg = Union[ShapePriorLike, Sequence[ShapePriorLike]]
"""One prior, or the priors of a multi-category solve in their order."""


def category_settings(name: str, metadata: Mapping[str, Any] | None = None) -> CategorySettings:
    """The category settings of a prior from its name and metadata.

    Metadata "category" (a dict) wins over `KNOWN_CATEGORIES[name]` (a dict without "look_alike", saved before
    categories carried their look-alike models, takes the known category's of its name); an unknown category
    without metadata gets unbounded sizes (logged). Metadata "tau_out" (the calibrated band) fills `tau_out`; a
    bad value is logged and ignored.

    Args:
        name: the prior's name.
        metadata: the prior's metadata dict, or None.

    Raises:
        ValueError: malformed "category" metadata.
    """
    meta = metadata if isinstance(metadata, Mapping) else {}
    raw = meta.get(CATEGORY_KEY)
    if raw is not None:
        cat = CategorySettings.from_dict(raw)
        known = KNOWN_CATEGORIES.get(cat.name)
        if known is not None and isinstance(raw, Mapping) and "look_alike" not in raw:
            # saved before categories carried their look-alike models: the known category's
            cat = cat.replace(look_alike=known.look_alike)
        if known is not None and isinstance(raw, Mapping) and "max_planar" not in raw:
            cat = cat.replace(max_planar=known.max_planar)  # saved before categories carried a planar limit
        if known is not None and isinstance(raw, Mapping) and "min_size_patience" not in raw:
            cat = cat.replace(min_size_patience=known.min_size_patience)
        if known is not None and isinstance(raw, Mapping) and "explained_decay" not in raw:
            cat = cat.replace(explained_decay=known.explained_decay)
    elif name in KNOWN_CATEGORIES:
        cat = KNOWN_CATEGORIES[name]
    else:
        logger.info("prior %r has no category settings: object sizes are not checked", name)
        cat = CategorySettings(name=str(name) or "object")
    tau = meta.get(TAU_OUT_KEY)
    if tau is not None:
        try:
            value = float(tau)
        except (TypeError, ValueError):
            value = float("nan")
        if 0.0 < value <= MAX_TAU_OUT:  # also rejects NaN
            cat = cat.replace(tau_out=value)
        else:
            logger.warning("prior metadata %s=%r is not in (0, %s]; using %s", TAU_OUT_KEY, tau, MAX_TAU_OUT,
                           cat.out_tau)
    return cat


def prior_category(prior: Any) -> CategorySettings:
    """`prior.category` when the prior has one, else the settings from its name and metadata."""
    cat = getattr(prior, "category", None)
    if isinstance(cat, CategorySettings):
        return cat
    return category_settings(str(getattr(prior, "name", "object")), getattr(prior, "metadata", None))
