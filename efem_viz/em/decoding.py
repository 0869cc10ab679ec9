"""The network glue of the solver and of trace replay: encode point sets, decode SDF and normal angles over
ragged neighbourhoods, mesh a latent; for one prior or a table of priors (a multi-category solve).

Latents cross module boundaries as dicts of float32 numpy arrays: R (P, C, 3), inv (P, C), center (P, 3),
scale (P,). In a solve over several priors every row belongs to one prior (`owner`); the latents of priors
with a narrower code are zero-padded to the widest C (`PriorTable.width`) and trimmed again before decoding,
so one trace holds them all. With a single prior nothing is padded and every call is the one-prior code path.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from efem_viz.em.proposals import Ragged

if TYPE_CHECKING:
    import trimesh

    from efem_viz.prior.config import ShapePriorLike

LatentArrays = dict[str, np.ndarray]
"""A latent (or a batch of them) as numpy arrays: "R", "inv", "center", "scale"."""


def latent_from_numpy(prior: "ShapePriorLike", lat: dict[str, np.ndarray]) -> Any:
    """A torch `Latent` on the prior's device and dtype from numpy arrays R (P,C,3), inv (P,C), center (P,3),
    scale (P,)."""
    import torch

    from efem_viz.prior.model import Latent

    dev = prior_device(prior)
    dt = prior_dtype(prior)
    return Latent(
        R=torch.as_tensor(np.asarray(lat["R"]), device=dev, dtype=dt),
        inv=torch.as_tensor(np.asarray(lat["inv"]), device=dev, dtype=dt),
        center=torch.as_tensor(np.asarray(lat["center"]), device=dev, dtype=dt),
        scale=torch.as_tensor(np.asarray(lat["scale"]).reshape(-1), device=dev, dtype=dt),
    )


def prior_device(prior: "ShapePriorLike") -> Any:
    """The device of the prior's first parameter (CPU for a prior without parameters)."""
    try:
        return next(prior.parameters()).device
    except (StopIteration, AttributeError):
        return "cpu"


def prior_dtype(prior: "ShapePriorLike") -> Any:
    """The dtype of the prior's first parameter (float32 for a prior without parameters)."""
    import torch

    try:
        return next(prior.parameters()).dtype
    except (StopIteration, AttributeError):
        return torch.float32


def matmul_precision(dtype: str, prior: "ShapePriorLike | None" = None) -> AbstractContextManager[Any]:
    """The context in which the solver runs the networks for `EMConfig.compute.matmul_dtype`
    (`prior.config.matmul_precision` on the prior's device type). Outputs leave the networks as float32
    (`decode_rows`, `encode_samples` convert)."""
    from efem_viz.prior.config import matmul_precision as _precision

    return _precision(dtype, _device_type(prior))


def _device_type(prior: "ShapePriorLike | None") -> str:
    """"cpu" or "cuda": the autocast device type of the prior's parameters."""
    import torch

    return torch.device(prior_device(prior)).type if prior is not None else "cpu"


def one_pass_enabled() -> bool:
    """Whether `decode_rows` decodes SDF and band normals in one pass (`ShapePrior.sdf_and_band_normals`: one
    forward for every entry, the input gradient by hand on the band rows; the default) instead of an SDF pass and
    then autograd on the band (``EFEM_VIZ_ONE_PASS=0``).

    Each call equals the two-pass result to float rounding (the SDF bit for bit, a few normals at ReLU kinks a few
    degrees apart); whole runs, sensitive to rounding, then differ on some scenes, in both directions. Over the
    quick fixed set with three solver seeds each (36 runs, docs/BENCHMARKS.md) the per-run AP50 moved by
    -1.6 ± 1.9 points (paired, not significant; 23 runs identical) for 10 % less CPU time."""
    import os

    return os.environ.get("EFEM_VIZ_ONE_PASS", "1") != "0"


def decode_rows(
    prior: "ShapePriorLike",
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

    With `normals_within`, the normal angle is computed only for entries with |d| ≤ normals_within (the others
    get γ = 180°): in one decoder pass with a hand-made backward on those rows where the prior offers it
    (`ShapePrior.sdf_and_band_normals`, `one_pass_enabled`), else an SDF pass and then autograd on them. The solver sets
    it to the largest SDF threshold any later test applies (τ_D(t), the stationary and output thresholds), so every
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
        latent = latent_from_numpy(prior, latent)
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
    if one_pass_enabled() and callable(getattr(prior, "sdf_and_band_normals", None)):  # one pass (`ShapePrior`)
        d, g1 = _decode_padded(prior, latent, rag.idx, row, pts_t, nrm_t, chunk=chunk, with_normals=False,
                               band=float(normals_within))
        assert g1 is not None
        if stats is not None:
            stats["normal_queries"] = stats.get("normal_queries", 0.0) + int(np.count_nonzero(g1 < 180.0))
        return d, g1
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
    prior: "ShapePriorLike",
    latent: Any,
    idx: np.ndarray,
    row: np.ndarray,
    pts_t: Any,
    nrm_t: Any,
    *,
    chunk: int,
    with_normals: bool,
    band: float | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode entries (row r, scene point idx) grouped by row: rows of similar length are padded into dense
    (G, L, 3) batches of at most `chunk` queries and sent through the prior's batched form (one latent per
    batch row), which avoids gathering a per-query copy of the folded first layer. `row` must be sorted.
    With `band`, the angles come from the prior's one-pass `sdf_and_band_normals` for the entries with
    |d| <= band (180° for the others)."""
    import torch

    k = len(idx)
    dev = prior_device(prior)
    dt = prior_dtype(prior)
    n_rows = int(row[-1]) + 1 if k else 0
    counts = np.bincount(row, minlength=n_rows)
    starts = np.zeros(n_rows + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    present = np.flatnonzero(counts > 0)
    order = present[np.argsort(counts[present], kind="stable")]
    d_out = np.empty(k, np.float32)
    g_out = np.empty(k, np.float32) if with_normals else (np.full(k, 180.0, np.float32) if band is not None else None)
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
        if band is not None and not with_normals:
            sdf, nrm, in_band = prior.sdf_and_band_normals(x, lat_g, within=band)  # type: ignore[attr-defined]
            take = (in_band.cpu().reshape(-1).numpy() & vmask)
            if take.any():
                sel_t = torch.from_numpy(np.flatnonzero(take))
                n_sel = nrm.float().cpu().reshape(-1, 3)[sel_t]
                cos = (n_sel * nrm_t[pidx.reshape(-1)[sel_t]]).sum(-1).clamp(-1.0, 1.0)
                g_out[pos.reshape(-1)[take]] = torch.rad2deg(torch.arccos(cos)).numpy()  # type: ignore[index]
        elif with_normals:
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


def encode_samples(prior: "ShapePriorLike", pts: np.ndarray, *, batch: int = 30) -> dict[str, np.ndarray]:
    """Encode (P, M, 3) world point sets in chunks of `batch`; returns numpy latent arrays (float32)."""
    import torch

    dev = prior_device(prior)
    dt = prior_dtype(prior)
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


def mesh_of_latent(prior: "ShapePriorLike", lat: dict[str, np.ndarray], *, resolution: int = 32) -> "trimesh.Trimesh":
    """World-frame mesh of one latent (dict of arrays R (C,3), inv (C,), center (3,), scale ()).

    Uses `efem_viz.prior.meshing.extract_mesh` (coarse-to-fine from resolution/2).
    """
    from efem_viz.prior.meshing import extract_mesh

    one = {k: np.asarray(v)[None] if k != "scale" else np.asarray(v).reshape(1) for k, v in lat.items()}
    coarse = resolution // 2 if resolution % 2 == 0 else None
    return extract_mesh(prior, latent_from_numpy(prior, one), resolution=resolution, coarse=coarse)


# ---------------------------------------------------------------------------------------------- several priors
def latent_width(prior: "ShapePriorLike") -> int:
    """C, the number of rows of the prior's Θ_R (its config's `latent_dim`, else measured by one encode)."""
    width = getattr(getattr(prior, "config", None), "latent_dim", None)
    if isinstance(width, (int, np.integer)) and int(width) > 0:
        return int(width)
    probe = np.random.default_rng(0).normal(size=(1, 16, 3)).astype(np.float32)
    return int(encode_samples(prior, probe)["R"].shape[1])


def trim_latent(lat: LatentArrays, width: int) -> LatentArrays:
    """The first `width` code rows of (possibly zero-padded) latent arrays (leading batch axis or not)."""
    r, inv = np.asarray(lat["R"]), np.asarray(lat["inv"])
    if r.shape[-2] == width:
        return lat
    return {**lat, "R": r[..., :width, :], "inv": inv[..., :width]}


def _pad_latent(lat: LatentArrays, width: int) -> LatentArrays:
    r, inv = lat["R"], lat["inv"]
    c = r.shape[1]
    if c == width:
        return lat
    r_pad = np.zeros((len(r), width, 3), np.float32)
    inv_pad = np.zeros((len(inv), width), np.float32)
    r_pad[:, :c], inv_pad[:, :c] = r, inv
    return {**lat, "R": r_pad, "inv": inv_pad}


@dataclass(frozen=True)
class PriorTable:
    """The priors of one solve, in order (the owner code of a proposal indexes this table).

    Attributes:
        priors: the priors.
        widths: C of each prior's latent.
    """

    priors: tuple[Any, ...]
    widths: tuple[int, ...]

    @classmethod
    def of(cls, priors: "Sequence[ShapePriorLike] | ShapePriorLike") -> PriorTable:
        """A table of one prior or a sequence of priors."""
        seq: tuple[Any, ...] = tuple(priors) if isinstance(priors, (list, tuple)) else (priors,)
        if not seq:
            raise ValueError("need at least one prior")
        return cls(priors=seq, widths=tuple(latent_width(p) for p in seq))

    def __len__(self) -> int:
        return len(self.priors)

    @property
    def width(self) -> int:
        """The widest latent (the width stored in a trace)."""
        return max(self.widths)

    def latent_of(self, k: int, lat: LatentArrays) -> LatentArrays:
        """Latent arrays trimmed to prior k's width."""
        return trim_latent(lat, self.widths[k])


def encode_rows(
    table: PriorTable, owner: np.ndarray, pts: np.ndarray, *, batch: int = 30
) -> LatentArrays:
    """Encode (P, M, 3) world point sets, row p with prior `owner[p]`; latents padded to `table.width`.

    Args:
        table: the priors.
        owner: (P,) int index into `table` per row.
        pts: (P, M, 3) float32 world points.
        batch: sets per encoder call.
    """
    if len(table) == 1:
        return encode_samples(table.priors[0], pts, batch=batch)
    p, width = len(pts), table.width
    out: LatentArrays = {"R": np.zeros((p, width, 3), np.float32), "inv": np.zeros((p, width), np.float32),
                         "center": np.zeros((p, 3), np.float32), "scale": np.zeros(p, np.float32)}
    for k, prior in enumerate(table.priors):
        rows = np.flatnonzero(owner == k)
        if len(rows):
            lat = _pad_latent(encode_samples(prior, pts[rows], batch=batch), width)
            for key in out:
                out[key][rows] = lat[key]
    return out


def decode_owned_rows(
    table: PriorTable,
    owner: np.ndarray,
    latent: LatentArrays,
    rag: Ragged,
    points: np.ndarray,
    normals: np.ndarray,
    **kwargs: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """`decode_rows` where row r of `rag` is decoded by prior `owner[r]` (same arguments and results)."""
    if len(table) == 1:
        return decode_rows(table.priors[0], latent, rag, points, normals, **kwargs)
    d = np.empty(len(rag.idx), np.float32)
    g = np.empty(len(rag.idx), np.float32)
    for k, prior in enumerate(table.priors):
        rows = np.flatnonzero(owner == k)
        if not len(rows):
            continue
        sub, pos = rag.take_rows(rows)
        lat_k = table.latent_of(k, {key: np.asarray(v)[rows] for key, v in latent.items()})
        d[pos], g[pos] = decode_rows(prior, lat_k, sub, points, normals, **kwargs)
    return d, g
