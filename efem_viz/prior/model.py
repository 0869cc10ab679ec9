"""``ShapePrior``: SIM(3)-equivariant encoder + invariant SDF decoder, its ``Latent`` and checkpoint IO.

Frames: ``encode`` takes points in any (world) frame; ``Latent.center``/``Latent.scale`` live in that frame;
``sdf`` takes world queries and returns a *canonical-unit* SDF (negative inside); world distance ≈ Θ_s · sdf.

Precision: the network computes in the dtype of its parameters (``prior.double()`` for float64); inputs and
latents are cast to it.
"""

from __future__ import annotations

import logging
import math
import os
import pickle
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
from torch import nn

from efem_viz.prior.config import DEFAULT_PRIOR, CategorySettings, PriorConfig, category_settings
from efem_viz.prior.decoder import SDFDecoder
from efem_viz.prior.encoder import VNDGCNNEncoder

if TYPE_CHECKING:
    from efem_viz.prior.codebook import Codebook

log = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
CHECKPOINT_FORMAT = "efem-viz-prior/1"
MAX_PRIOR_PARAMETERS = 50_000_000
"""Most parameters a prior file may declare (the shipped mug prior has 0.6M, the released EFEM priors a few M).
A file declaring more is refused before anything is built: a few KB of zero-stride views can otherwise declare
billions of weights that the loader would allocate and copy."""
MAX_PRIOR_BLOCKS = 256
"""Most encoder blocks (``widths`` entries) and decoder blocks a prior file may declare (the shipped priors use
7 and 2-5): bounds the cost of building the network on the meta device to count its parameters."""


class Latent(NamedTuple):
    """Batched latent code Θ = (Θ_R, Θ_inv, Θ_c, Θ_s) (torch tensors, or numpy arrays after ``.numpy()``).

    Attributes:
        R: ``(B, L, 3)`` Θ_R, transforms as ``Θ_R Rᵀ`` (rows rotate), scale-free.
        inv: ``(B, L)`` Θ_inv, invariant.
        center: ``(B, 3)`` Θ_c, world frame (transforms as ``sRΘ_c + t``).
        scale: ``(B,)`` Θ_s, world units per canonical unit (transforms as ``sΘ_s``).

    Integer indexing ``latent[i]`` keeps a batch axis of size 1; slices, index tensors/arrays and boolean
    masks select along the batch axis.
    """

    R: Any
    inv: Any
    center: Any
    scale: Any

    def __getitem__(self, idx: Any) -> Latent:  # type: ignore[override]
        if isinstance(idx, (int, np.integer)):
            n = len(self)
            i = int(idx)
            if not -n <= i < n:
                raise IndexError(f"latent index {i} out of range for batch size {n}")
            idx = slice(i, i + 1 if i != -1 else None)
        return Latent(*(t[idx] for t in tuple.__iter__(self)))

    def __len__(self) -> int:
        return int(tuple.__getitem__(self, 3).shape[0])

    def select(self, idx: Any) -> Latent:
        """Select latents along the batch axis (int keeps a size-1 axis; index array or bool mask)."""
        return self[idx]

    @property
    def batch_size(self) -> int:
        """Number of latents B."""
        return len(self)

    def to(self, device: Any = None, dtype: Any = None) -> Latent:
        """Move/cast every tensor (torch latents only)."""
        return Latent(*(t.to(device=device, dtype=dtype) for t in tuple.__iter__(self)))

    def detach(self) -> Latent:
        """Detach every tensor from the autograd graph."""
        return Latent(*(t.detach() for t in tuple.__iter__(self)))

    def numpy(self) -> Latent:
        """A ``Latent`` of numpy arrays (detached, on CPU)."""
        return Latent(*(t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t)
                        for t in tuple.__iter__(self)))

    def torch(self, device: Any = "cpu", dtype: Any = None) -> Latent:
        """A ``Latent`` of torch tensors from numpy arrays or tensors."""
        return Latent(*(torch.as_tensor(t, device=device, dtype=dtype) for t in tuple.__iter__(self)))

    @staticmethod
    def cat(latents: list[Latent]) -> Latent:
        """Concatenate torch latents along the batch axis."""
        if not latents:
            raise ValueError("Latent.cat needs at least one latent")
        return Latent(*(torch.cat(parts, dim=0) for parts in zip(*(tuple.__iter__(x) for x in latents))))


class ShapePrior(nn.Module):
    """Encoder + decoder with a typed config, an optional pose codebook and a name.

    Args:
        config: Architecture.
        name: Display name (e.g. ``"mug"``).
    """

    def __init__(self, config: PriorConfig | None = None, *, name: str = "prior") -> None:
        super().__init__()
        self.config = config if config is not None else PriorConfig()
        self.name = name
        self.codebook: Codebook | None = None
        self.metadata: dict[str, Any] = {}
        self.encoder = VNDGCNNEncoder(self.config)
        c = self.config
        self.decoder = SDFDecoder(c.latent_dim, c.decoder_hidden, c.decoder_blocks, use_qnorm=c.use_qnorm,
                                  proj_gain=c.decoder_proj_gain, inv_gain=c.decoder_inv_gain)

    @property
    def n_pcl(self) -> int:
        """Points per encoded set (the training size)."""
        return int(self.config.n_pcl)

    @property
    def category(self) -> CategorySettings:
        """Category settings (metadata "category"/"tau_out", else the known settings of its name)."""
        return category_settings(self.name, self.metadata)

    @property
    def dtype(self) -> torch.dtype:
        """Parameter dtype (the compute dtype)."""
        return self.decoder.fc_in.weight.dtype

    @property
    def device(self) -> torch.device:
        """Parameter device."""
        return self.decoder.fc_in.weight.device

    def encode(self, points: torch.Tensor, *, centroid_noise: torch.Tensor | None = None) -> Latent:
        """Encode point clouds (each centred by its mean internally).

        Args:
            points: ``(B, M, 3)`` (or ``(M, 3)``, treated as B=1) world-frame points.
            centroid_noise: Optional ``(B, 3)`` offset added to the centroid before centring (training, §2.4);
                Θ_c is then ``x̄ + noise + δ``.

        Returns:
            ``Latent`` with batch size B in the model dtype.

        Raises:
            ValueError: On a bad shape or an empty cloud.
        """
        if points.ndim == 2:
            points = points[None]
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 1:
            raise ValueError(f"points must be (B, M, 3) with M >= 1, got {tuple(points.shape)}")
        points = points.to(device=self.device, dtype=self.dtype)
        centroid = points.mean(dim=1)
        if centroid_noise is not None:
            if centroid_noise.shape != centroid.shape:
                raise ValueError(f"centroid_noise must be {tuple(centroid.shape)}, "
                                 f"got {tuple(centroid_noise.shape)}")
            centroid = centroid + centroid_noise.to(centroid)
        out = self.encoder(points - centroid[:, None, :])
        return Latent(R=out.R.transpose(1, 2), inv=out.inv, center=centroid + out.delta, scale=out.scale)

    def _prep_latent(self, latent: Latent) -> Latent:
        lat = latent.to(device=self.device, dtype=self.dtype)
        if lat.R.ndim == 2:  # unbatched
            lat = Latent(lat.R[None], lat.inv[None], lat.center[None], lat.scale.reshape(1))
        return lat

    def sdf(self, x: torch.Tensor, latent: Latent, index: torch.Tensor | None = None, *,
            chunk: int = 65536) -> torch.Tensor:
        """Canonical-unit SDF of world queries (negative inside).

        Args:
            x: ``(B, Q, 3)`` queries for a batch of B latents, or ``(Q, 3)`` with ``index`` (or with a single
                latent).
            latent: ``Latent`` with batch size B.
            index: Optional ``(Q,)`` int64: query q uses latent ``index[q]`` (only with ``x`` of shape
                (Q, 3)).
            chunk: Queries per chunk in the ragged form (bounds memory).

        Returns:
            ``(B, Q)`` or ``(Q,)`` SDF in the model dtype.

        Raises:
            ValueError: On inconsistent shapes.
        """
        lat = self._prep_latent(latent)
        x = x.to(device=self.device, dtype=self.dtype)
        n_lat = lat.R.shape[0]
        m, bias = self.decoder.fold(lat.R, lat.inv)
        if x.ndim == 3:
            if index is not None:
                raise ValueError("index is only supported with x of shape (Q, 3)")
            if x.shape[0] != n_lat or x.shape[-1] != 3:
                raise ValueError(f"x {tuple(x.shape)} does not match a latent batch of {n_lat}")
            q = (x - lat.center[:, None, :]) / lat.scale[:, None, None]
            return self.decoder.forward_batched(q, m, bias)
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"x must be (Q, 3) or (B, Q, 3), got {tuple(x.shape)}")
        if index is None:
            if n_lat != 1:
                raise ValueError(f"x of shape (Q, 3) needs `index` when the latent batch is {n_lat} (not 1)")
            q = (x - lat.center) / lat.scale[:, None]
            return self.decoder.forward_batched(q[None], m, bias)[0]
        index = index.to(device=self.device, dtype=torch.long)
        if index.shape != x.shape[:1]:
            raise ValueError(f"index must be ({x.shape[0]},), got {tuple(index.shape)}")
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n_lat):
            raise ValueError(f"index values must be in [0, {n_lat}), "
                             f"got [{int(index.min())}, {int(index.max())}]")
        outs = []
        for s in range(0, x.shape[0], chunk):
            xi, ii = x[s:s + chunk], index[s:s + chunk]
            q = (xi - lat.center[ii]) / lat.scale[ii, None]
            outs.append(self.decoder.forward_ragged(q, m[ii], bias[ii]))
        if not outs:
            return x.new_zeros(0)
        return torch.cat(outs)

    def sdf_and_band_normals(self, x: torch.Tensor, latent: Latent, *, within: float
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDF of every query and the outward unit normal of those with ``|sdf| <= within``, in one decoder pass
        (`SDFDecoder.sdf_and_band_grad`): what ``sdf`` and then ``sdf_and_normals`` on the band give, at the
        cost of one forward and a backward on the band rows.

        Args:
            x: ``(B, Q, 3)`` world queries, one latent per batch row.
            latent: ``Latent`` with batch size B.
            within: band half-width (canonical SDF units).

        Returns:
            ``sdf (B, Q)``, ``normals (B, Q, 3)`` (world frame; zeros outside the band), ``band (B, Q)`` bool.
        """
        with torch.no_grad():
            lat = self._prep_latent(latent)
            x = x.to(device=self.device, dtype=self.dtype)
            if x.ndim != 3 or x.shape[0] != lat.R.shape[0] or x.shape[-1] != 3:
                raise ValueError(f"x {tuple(x.shape)} does not match a latent batch of {lat.R.shape[0]}")
            m, bias = self.decoder.fold(lat.R, lat.inv)
            q = (x - lat.center[:, None, :]) / lat.scale[:, None, None]
            sdf, dq, band = self.decoder.sdf_and_band_grad(q, m, bias, within=within)
            # ∂sdf/∂x = ∂sdf/∂q / Θ_s with Θ_s > 0: the same direction
            normals = dq / dq.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return sdf, normals, band

    def sdf_and_normals(self, x: torch.Tensor, latent: Latent, index: torch.Tensor | None = None, *,
                        chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF and outward unit normals ``∂sdf/∂x / ‖·‖`` (world frame), usable inside ``torch.no_grad()``.

        The returned tensors are detached.

        Args:
            x: As in ``sdf``.
            latent: As in ``sdf``.
            index: As in ``sdf``.
            chunk: Queries per autograd chunk.

        Returns:
            ``sdf`` with the shape of ``x`` minus its last axis, and ``normals`` with the shape of ``x``.
        """
        lat = self._prep_latent(latent).detach()
        x = x.to(device=self.device, dtype=self.dtype).detach()
        sdfs, grads = [], []
        flat = x.ndim == 2
        n = x.shape[0] if flat else x.shape[1]
        with torch.enable_grad():
            for s in range(0, max(n, 1), chunk):
                xi = (x[s:s + chunk] if flat else x[:, s:s + chunk]).clone().requires_grad_(True)
                ii = index[s:s + chunk] if index is not None else None
                f = self.sdf(xi, lat, ii, chunk=chunk)
                (g,) = torch.autograd.grad(f.sum(), xi)
                sdfs.append(f.detach())
                grads.append(g)
        dim = 0 if flat else 1
        sdf = torch.cat(sdfs, dim=dim)
        grad = torch.cat(grads, dim=dim)
        normals = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return sdf, normals


def atomic_torch_save(obj: Any, path: Path) -> None:
    from efem_viz.data.io import atomic_write

    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def save_prior(prior: ShapePrior, path: str | os.PathLike[str], *,
               extra: dict[str, Any] | None = None, storage: str | None = None) -> Path:
    """Write a model-only checkpoint (config + state dict + metadata), atomically.

    Args:
        prior: The model.
        path: Target ``.pt`` file.
        extra: JSON-able metadata merged into ``prior.metadata`` (e.g. iteration, val IoU).
        storage: "float32" or "float16", the stored weights' precision (a prior loads and computes in float32
            either way); None keeps what the prior was stored in (metadata "storage", default float32). The
            chair prior ships in float16: half the bytes the repository carries, and its benchmarks are measured
            on the rounded weights.

    Returns:
        The written path.
    """
    path = Path(path)
    meta = dict(prior.metadata)
    if extra:
        meta.update(extra)
    storage = storage if storage is not None else str(meta.get("storage", "float32"))
    if storage not in ("float32", "float16"):
        raise ValueError(f"storage must be float32 or float16, got {storage!r}")
    if storage == "float16":
        meta["storage"] = storage
    else:
        meta.pop("storage", None)
    dtype = torch.float16 if storage == "float16" else torch.float32
    state = {k: v.detach().to("cpu", dtype).clone() for k, v in prior.state_dict().items()}
    atomic_torch_save({"format": CHECKPOINT_FORMAT, "name": prior.name, "config": prior.config.to_dict(),
                        "state_dict": state, "metadata": meta}, path)
    return path


def resolve_prior_path(name_or_path: str | os.PathLike[str]) -> Path:
    """Map a prior name (``"mug"``) to ``efem_viz/weights/<name>.pt``; a path is returned as is.

    Raises:
        FileNotFoundError: If the file does not exist.
    """
    s = str(name_or_path)
    p = Path(s)
    if p.suffix != ".pt" and os.sep not in s and "/" not in s:
        p = WEIGHTS_DIR / f"{s}.pt"
    if not p.is_file():
        raise FileNotFoundError(f"shape prior weights not found: {p}")
    return p


class PickleRequired(ValueError):
    """A checkpoint that loads only by a full unpickle (it holds Python objects beyond tensors), refused because
    ``allow_pickle`` was not set. Callers with their own opt-in switch can catch this to name it."""


MAX_CHECKPOINT_BYTES = 1 << 30
"""Largest total of tensor data a checkpoint may declare: a prior of `MAX_PRIOR_PARAMETERS` float32 weights with
its Adam moments is 0.6 GB (the shipped resume state: 8 MB)."""


def _check_archive_sizes(path: Path) -> None:
    """Refuse a torch zip checkpoint whose records declare more data than any prior needs, from the zip directory
    alone: nothing is inflated (a 6.4 MB file with an unused 4 GiB zero tensor cost 30 s and 4.3 GB
    before the prior checks ran). Not a zip (legacy format, or not a checkpoint): left to `torch.load`."""
    import zipfile

    try:
        if not zipfile.is_zipfile(path):
            return
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
    except (OSError, zipfile.BadZipFile, ValueError, NotImplementedError):
        return  # torch.load reports it
    declared = sum(max(int(i.file_size), 0) for i in infos)
    pickles = [i for i in infos if i.filename.endswith(".pkl")]
    if declared > MAX_CHECKPOINT_BYTES or any(i.file_size > 64 << 20 for i in pickles):
        raise ValueError(f"{path}: its records declare {declared:,} bytes of data, more than a prior checkpoint "
                         f"can hold ({MAX_CHECKPOINT_BYTES:,}); refused before loading")


def read_checkpoint(path: str | os.PathLike[str], *, allow_pickle: bool = False) -> Any:
    """``torch.load`` a checkpoint safely: tensors and plain containers only (``weights_only=True``).

    Every file efem-viz writes (priors, training checkpoints) loads this way. A file that needs a full unpickle
    (which can run arbitrary code) is refused unless ``allow_pickle`` is set.

    Raises:
        PickleRequired: the file needs a full unpickle and ``allow_pickle`` is not set.
        ValueError: the file is not a readable torch checkpoint.
    """
    path = Path(path)
    _check_archive_sizes(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        needs_globals = "global" in str(exc).lower() and "Unsupported operand" not in str(exc)
        if not needs_globals:
            raise ValueError(f"{path} is not a readable torch checkpoint (corrupt?)") from exc
        if not allow_pickle:
            names = re.findall(r"GLOBAL ([\w.]+)", str(exc))
            raise PickleRequired(
                f"{path} holds Python objects beyond tensors and plain containers"
                f"{' (' + ', '.join(names[:3]) + ')' if names else ''}; loading it means a full unpickle, which can "
                f"run code. If you trust the file, load it with allow_pickle=True") from exc
    except MemoryError:
        raise
    except Exception as exc:  # torch's zip reader and weights-only unpickler raise many types on a corrupt file
        raise ValueError(f"{path} is not a readable torch checkpoint (corrupt or truncated?): "
                         f"{str(exc).splitlines()[0][:200] if str(exc).strip() else type(exc).__name__}") from exc
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a trusted pickle that still fails to load
        raise ValueError(f"{path} could not be unpickled: {exc}") from exc


def load_prior(name_or_path: str | os.PathLike[str] = DEFAULT_PRIOR, *, device: str | torch.device = "cpu",
               load_codebook: bool = True, allow_pickle: bool = False) -> ShapePrior:
    """Load a prior saved by ``save_prior`` (and its codebook ``<stem>_codebook.npz`` if present).

    Also accepts a full training checkpoint (it carries the same ``config``/``state_dict`` keys).

    Args:
        name_or_path: A name under ``efem_viz/weights/`` or a ``.pt`` path.
        device: Target device.
        load_codebook: Try to attach the codebook.
        allow_pickle: Also load files that need a full unpickle (can run code: trusted files only).

    Returns:
        The model in eval mode, float32.

    Raises:
        FileNotFoundError: If the weights file is missing.
        ValueError: If the file is not a prior checkpoint (or is corrupt, or needs a full unpickle without
            ``allow_pickle``).
    """
    path = resolve_prior_path(name_or_path)
    ckpt = read_checkpoint(path, allow_pickle=allow_pickle)
    if not isinstance(ckpt, dict) or "config" not in ckpt or "state_dict" not in ckpt:
        keys = sorted(map(str, ckpt))[:12] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{path} is not an efem-viz prior checkpoint (keys: {keys})")
    config, state = checked_prior_parts(ckpt, path)
    name = str(ckpt.get("name") or path.stem)
    meta = ckpt.get("metadata") or {}
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: prior metadata must be a dict, got {type(meta).__name__}")
    prior = ShapePrior(config, name=name)
    try:
        prior.load_state_dict(state)
    except RuntimeError as exc:  # a dtype torch cannot copy into a float parameter
        raise ValueError(f"{path}: the weights do not load: {' '.join(str(exc).split())[:300]}") from exc
    prior.metadata = dict(meta)
    prior.eval().to(device)
    if load_codebook:
        cb_path = path.with_name(f"{path.stem}_codebook.npz")
        if cb_path.is_file():
            try:
                from efem_viz.prior.codebook import Codebook
            except ImportError:
                log.warning("codebook %s present but efem_viz.prior.codebook is unavailable", cb_path)
            else:
                codebook = Codebook.load(cb_path)
                if codebook.matches(prior):
                    prior.codebook = codebook
                else:  # retrievals and poses from another network's codes would be meaningless
                    log.warning("codebook %s was built from other weights than %s; not attached (rebuild it with "
                                "`efem-viz build-codebook --prior %s`)", cb_path, path, path)
    return prior


def checked_prior_parts(ckpt: dict[str, Any], path: Path) -> tuple[PriorConfig, dict[str, torch.Tensor]]:
    """The config and state dict of a checkpoint, checked before any layer is allocated.

    The network is first built on the meta device (no memory), so a config with absurd sizes costs nothing; its
    parameter count must be at most `MAX_PRIOR_PARAMETERS`. The stored tensors must then have exactly its
    parameter names and shapes, each own exactly its bytes (no expanded or shared views: a few stored bytes cannot
    stand for many weights), and hold finite values.

    Raises:
        ValueError: naming `path` and the first problem.
    """
    raw, state = ckpt["config"], ckpt["state_dict"]
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: prior config must be a dict, got {type(raw).__name__}")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise ValueError(f"{path}: state_dict must map parameter names to tensors")
    try:
        config = PriorConfig.from_dict(raw)
        depth = max(len(config.widths), int(config.decoder_blocks))
        if depth > MAX_PRIOR_BLOCKS:
            raise ValueError(f"{len(config.widths)} encoder and {config.decoder_blocks} decoder blocks "
                             f"(at most {MAX_PRIOR_BLOCKS} each)")
        with torch.device("meta"):
            want = {k: tuple(v.shape) for k, v in ShapePrior(config).state_dict().items()}
    except (TypeError, ValueError, OverflowError, RuntimeError, IndexError, KeyError) as exc:
        raise ValueError(f"{path}: invalid prior config: {' '.join(str(exc).split())[:300]}") from exc
    declared = sum(math.prod(s) for s in want.values())
    if declared > MAX_PRIOR_PARAMETERS:
        raise ValueError(f"{path}: the stored config declares {declared:,} parameters, more than the "
                         f"{MAX_PRIOR_PARAMETERS:,} a prior may have (refused before loading it)")
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != want:
        missing = sorted(set(want) - set(got))
        unexpected = sorted(set(got) - set(want))
        wrong = [f"{k} {got[k]} (expected {want[k]})" for k in want if k in got and got[k] != want[k]]
        raise ValueError(f"{path}: the weights do not fit the stored config: missing {missing[:3]}, unexpected "
                         f"{unexpected[:3]}, wrong shape {wrong[:2]}")
    for k, v in state.items():  # each tensor must own exactly its bytes: no zero-stride or shared views
        stored = v.untyped_storage().nbytes()
        if not v.is_contiguous() or v.storage_offset() != 0 or stored != v.numel() * v.element_size():
            raise ValueError(f"{path}: weight {k!r} {tuple(v.shape)} is stored as a view of {stored:,} bytes "
                             f"(a plain tensor of this shape holds {v.numel() * v.element_size():,})")
    for k, v in state.items():
        if v.is_complex() or (v.is_floating_point() and not bool(torch.isfinite(v).all())):
            raise ValueError(f"{path}: weight {k!r} holds {'complex' if v.is_complex() else 'NaN or Inf'} values")
    return config, state


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return int(sum(p.numel() for p in module.parameters() if p.requires_grad))


__all__ = ["PriorConfig", "Latent", "ShapePrior", "save_prior", "load_prior", "resolve_prior_path",
           "count_parameters", "WEIGHTS_DIR"]
