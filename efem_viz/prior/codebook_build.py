"""Building a prior's pose codebook (docs/design/efem-method.md §2.8) from training meshes: `build_codebook`.

Apart from `efem_viz.prior.codebook` (the stored data and its queries), so that the codebook, which the prior
carries, imports neither the prior nor its configuration.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Sequence

import numpy as np

from efem_viz.geometry.sampling import sample_surface
from efem_viz.prior.codebook import Codebook, prior_fingerprint, project_so3_code
from efem_viz.prior.config import DEFAULT_PRIOR

if TYPE_CHECKING:
    import trimesh

    from efem_viz.prior.model import ShapePrior

logger = logging.getLogger(__name__)


def _sample_objects(meshes_or_seeds: Sequence[trimesh.Trimesh | int | tuple[str, int]], rng: np.random.Generator, *,
                    n_store: int, noise: float, n_pcl: int, category: str,
                    normalise: bool) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Each object's stored cloud and encoder input (`build_codebook`), drawn from `rng` object by object.

    Returns:
        The ids (seeds, or positions of the meshes), (K, n_store, 3) float16 noisy surface samples, and
        (K, n_pcl) int32 indices of the encoder inputs among them (drawn with replacement).
    """
    from efem_viz.prior.data import normalize_mesh

    ids, clouds, input_idx = [], [], []
    for pos, item in enumerate(meshes_or_seeds):
        if isinstance(item, (int, np.integer, tuple)):
            from efem_viz.data.procedural import make_shape

            cat, seed = item if isinstance(item, tuple) else (category, item)
            mesh = make_shape(cat, int(seed))
            ids.append(int(seed))
        else:
            mesh = item
            ids.append(pos)
        if normalise:
            mesh = normalize_mesh(mesh)
        pts = sample_surface(mesh, n_store, seed=rng, empty="raise").points + rng.normal(0.0, noise, size=(n_store, 3))
        clouds.append(pts.astype(np.float16))  # encode exactly what is stored
        input_idx.append(rng.integers(0, n_store, size=n_pcl))
    return ids, np.stack(clouds), np.stack(input_idx).astype(np.int32)


def _encode_batches(prior: ShapePrior, X: np.ndarray,
                    batch: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Encode (K, n_pcl, 3) clouds `batch` at a time in float32; the latents' Θ_R, Θ_inv, Θ_c, Θ_s per batch."""
    import torch

    Rs, invs, cs, ss = [], [], [], []
    with torch.no_grad():  # the prior has no dropout/normalisation layers: no eval() toggling needed
        for s in range(0, len(X), batch):
            x = torch.as_tensor(X[s : s + batch], dtype=torch.float32)
            lat = prior.encode(x)
            Rs.append(lat.R.cpu().numpy())
            invs.append(lat.inv.cpu().numpy())
            cs.append(lat.center.cpu().numpy())
            ss.append(lat.scale.cpu().numpy())
    return Rs, invs, cs, ss


def build_codebook(
    prior: ShapePrior,
    meshes_or_seeds: Sequence[trimesh.Trimesh | int | tuple[str, int]],
    *,
    n_store: int = 2000,
    noise: float = 0.01,
    seed: int = 0,
    category: str = DEFAULT_PRIOR,
    normalise: bool = True,
    batch: int = 16,
    classes: Sequence[str] | None = None,
) -> Codebook:
    """Encode training objects into a codebook (spec §2.8).

    Per object: `n_store` area-uniform surface samples plus i.i.d. Gaussian noise (σ = `noise`, canonical
    units, as in training), rounded to the stored float16; the encoder input is `prior.config.n_pcl` of
    those drawn with replacement (their indices are kept in `input_idx`); encoded in the prior's dtype
    (float32 for a loaded prior; the encoder centres by the mean itself).

    Args:
        prior: the trained `ShapePrior`.
        meshes_or_seeds: trimesh meshes (canonical frame), integer seeds of `category`'s generator, or
            (category, seed) pairs of a training family's members (`procedural.family_seeds`): each entry's
            class id is then its category's position in `classes`.
        n_store: stored points per object.
        noise: Gaussian noise σ in canonical units.
        seed: RNG seed (the whole build is deterministic in it).
        category: procedural category for integer seeds.
        normalise: apply the training normalisation (`efem_viz.prior.data.normalize_mesh`: bbox centre to the
            origin, longest side 1) to each mesh first.
        batch: objects per encoder call.
        classes: the class names of a family's codebook (meta "classes"; `Codebook.category_of`); default:
            the categories of the (category, seed) pairs in order of appearance, none for seeds or meshes.

    Returns:
        Codebook (ids = the seeds, or the positions of the meshes in the input).
    """
    if len(meshes_or_seeds) == 0:
        raise ValueError("build_codebook needs at least one mesh or seed")
    if n_store < 1:
        raise ValueError(f"n_store must be >= 1, got {n_store}")
    pairs = [item for item in meshes_or_seeds if isinstance(item, tuple)]
    if classes is None and pairs:
        classes = list(dict.fromkeys(str(c) for c, _ in pairs))
    class_id = np.zeros(len(meshes_or_seeds), np.int32)
    if classes is not None:
        names = [str(c) for c in classes]
        for i, item in enumerate(meshes_or_seeds):
            if isinstance(item, tuple):
                if item[0] not in names:
                    raise ValueError(f"category {item[0]!r} is not among the classes {names}")
                class_id[i] = names.index(item[0])
    rng = np.random.default_rng(seed)
    n_pcl = int(prior.config.n_pcl)
    ids, pcl, idx = _sample_objects(meshes_or_seeds, rng, n_store=n_store, noise=noise, n_pcl=n_pcl,
                                    category=category, normalise=normalise)
    X = np.take_along_axis(pcl, idx[:, :, None], axis=1).astype(np.float64)
    Rs, invs, cs, ss = _encode_batches(prior, X, batch)
    z_so3 = np.concatenate(Rs).astype(np.float64)
    proj, basis, evals = project_so3_code(z_so3)
    centred = X - X.mean(axis=1, keepdims=True)
    lo, hi = centred.min(axis=1), centred.max(axis=1)
    return Codebook(
        ids=np.asarray(ids, np.int64),
        z_so3=z_so3.astype(np.float32),
        z_inv=np.concatenate(invs).astype(np.float32),
        scale=np.concatenate(ss).astype(np.float32),
        center=np.concatenate(cs).astype(np.float32),
        pcl=pcl,
        proj=proj.astype(np.float32),
        basis=basis.astype(np.float32),
        eigvals=evals.astype(np.float32),
        bbox_center=((lo + hi) / 2).astype(np.float32),
        bbox_half=((hi - lo) / 2).astype(np.float32),
        class_id=class_id,
        input_idx=idx,
        meta={
            "prior": str(getattr(prior, "name", "")),
            "prior_fingerprint": prior_fingerprint(prior),
            "category": category,
            **({"classes": [str(c) for c in classes]} if classes is not None else {}),
            "n_store": int(n_store),
            "noise": float(noise),
            "n_pcl": n_pcl,
            "seed": int(seed),
            "normalised": bool(normalise),
            "built_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    )
