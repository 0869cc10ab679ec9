"""Pose codebook ("database") of a shape prior (docs/design/efem-method.md §2.8): the stored data and its queries; it
is built by `efem_viz.prior.codebook_build.build_codebook` (`efem-viz build-codebook` is
`efem_viz.prior.commands.BuildCodebookArgs`).

For every training object we store its latent (Θ_R, Θ_inv, Θ_s, Θ_c), a noisy canonical surface cloud and a
rotation-invariant version of Θ_R, and we answer k-nearest-neighbour queries on three feature spaces
(Θ_inv; the projected Θ_R; their concatenation) for the pose search of `efem_viz.prior.pose`.

Deviation from the release (spec §8.4, documented): the projected code `Θ_R^proj = Θ_R E` (E = eigenvectors
of `S = Θ_Rᵀ Θ_R`, eigenvalues ascending) has a sign ambiguity per eigenvector. We canonicalise it: column j
of `Θ_R E` is flipped so that its third moment `Σ_c p_cj³` is positive (if that is ~0, so that its entry of
largest magnitude is positive). This makes `Θ_R^proj` invariant to rotations of Θ_R (and to the sign choices
of the eigen-solver), which the release's projection is not.

Other choices: the stored centre is the encoder's full centre `Θ_c = x̄ + δ` in the canonical frame (the
spec's "proper centre", not the release's raw offset δ); the stored cloud is `n_store` noisy surface points
in float16 (default 2000 instead of the release's 5000, to keep the shipped file small); kNN indices are
scipy cKDTrees built on the fly after loading.

This module's top is light (no torch).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


logger = logging.getLogger(__name__)

__all__ = [
    "CODEBOOK_SCHEMA_VERSION",
    "Codebook",
    "latent_to_numpy",
    "prior_fingerprint",
    "project_so3_code",
]

CODEBOOK_SCHEMA_VERSION = 1


def project_so3_code(theta_R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-invariant projection of Θ_R onto its sign-canonicalised eigenbasis.

    Args:
        theta_R: (C, 3) or (K, C, 3) float, Θ_R rows.

    Returns:
        proj (…, C, 3) float64 = Θ_R E with canonical column signs, E (…, 3, 3) the (sign-fixed) eigenvectors
        as columns (eigenvalues ascending), eigvals (…, 3).
    """
    T = np.asarray(theta_R, dtype=np.float64)
    if T.shape[-1] != 3 or T.ndim not in (2, 3):
        raise ValueError(f"theta_R must have shape (C, 3) or (K, C, 3), got {T.shape}")
    S = np.swapaxes(T, -1, -2) @ T
    evals, E = np.linalg.eigh(S)
    P = T @ E
    m3 = np.sum(P**3, axis=-2)  # (..., 3)
    scale = np.sum(np.abs(P) ** 3, axis=-2) + 1e-300
    amax = np.take_along_axis(P, np.argmax(np.abs(P), axis=-2)[..., None, :], axis=-2)[..., 0, :]
    sign = np.where(np.abs(m3) > 1e-6 * scale, np.sign(m3), np.sign(amax))
    sign = np.where(sign == 0, 1.0, sign)
    return P * sign[..., None, :], E * sign[..., None, :], evals


def prior_fingerprint(prior: Any) -> str:
    """SHA-1 of a prior's weights (float32 bytes of its state dict, in key order): ties a codebook to a prior.

    Args:
        prior: a `ShapePrior` (any torch module).

    Returns:
        40-character hex digest.
    """
    import hashlib

    h = hashlib.sha1()
    for key, tensor in prior.state_dict().items():
        h.update(key.encode())
        h.update(tensor.detach().to("cpu").float().contiguous().numpy().tobytes())
    return h.hexdigest()


def latent_to_numpy(latent_i: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One latent as float64 numpy arrays.

    Args:
        latent_i: a `Latent` (torch or numpy) with batch size 1 (Θ_R (1, C, 3)) or unbatched (Θ_R (C, 3)).

    Returns:
        Θ_R (C, 3), Θ_inv (C,), Θ_c (3,), Θ_s (float).
    """
    parts = []
    for t in (latent_i.R, latent_i.inv, latent_i.center, latent_i.scale):
        if hasattr(t, "detach"):
            t = t.detach().cpu().numpy()
        parts.append(np.asarray(t, dtype=np.float64))
    R, inv, center, scale = parts
    if R.ndim == 3:
        if R.shape[0] != 1:
            raise ValueError(f"expected a single latent, got Θ_R of shape {R.shape}")
        R, inv, center, scale = R[0], inv.reshape(inv.shape[-1]), center.reshape(3), scale.reshape(-1)
    if R.ndim != 2 or R.shape[1] != 3 or inv.shape != (R.shape[0],) or center.size != 3 or scale.size != 1:
        raise ValueError(
            f"bad latent shapes: R {R.shape}, inv {inv.shape}, center {center.shape}, scale {scale.shape}"
        )
    return R, inv, center.reshape(3), float(scale.reshape(-1)[0])


CODEBOOK_ARRAYS: tuple[str, ...] = ("ids", "z_so3", "z_inv", "scale", "center", "pcl", "proj", "basis", "eigvals",
                                    "bbox_center", "bbox_half", "class_id", "input_idx")
"""The arrays of a codebook file (with `schema_version` and `meta_json`): `Codebook.load` reads these only."""


@dataclass
class Codebook:
    """Latents and canonical clouds of the training objects, with kNN retrieval (spec §2.8)."""

    ids: np.ndarray
    """(K,) int64 object ids (procedural seeds, or indices of the meshes given)."""
    z_so3: np.ndarray
    """(K, C, 3) float32 Θ_R (canonical frame)."""
    z_inv: np.ndarray
    """(K, C) float32 Θ_inv."""
    scale: np.ndarray
    """(K,) float32 Θ_s (canonical units; ≈ 1)."""
    center: np.ndarray
    """(K, 3) float32 encoder centre Θ_c = x̄ + δ of the encoder input (canonical frame)."""
    pcl: np.ndarray
    """(K, n_store, 3) float16 noisy canonical surface points."""
    proj: np.ndarray
    """(K, C, 3) float32 sign-canonicalised projection Θ_R E (rotation invariant)."""
    basis: np.ndarray
    """(K, 3, 3) float32 eigenbasis E (columns, sign-fixed)."""
    eigvals: np.ndarray
    """(K, 3) float32 eigenvalues of Θ_Rᵀ Θ_R, ascending."""
    bbox_center: np.ndarray
    """(K, 3) float32 bounding-box centre of the centred encoder input."""
    bbox_half: np.ndarray
    """(K, 3) float32 bounding-box half-extent of the centred encoder input."""
    class_id: np.ndarray
    """(K,) int32 class id (0 for single-category priors)."""
    input_idx: np.ndarray
    """(K, n_pcl) int32 rows of `pcl` that formed each entry's encoder input (`encoder_input(k)`)."""
    meta: dict[str, Any] = field(default_factory=dict)
    """Provenance: prior name, noise, n_pcl, seed, build time."""
    _trees: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        K = len(self.ids)
        if K == 0:
            raise ValueError("a codebook needs at least one entry")
        C = self.z_so3.shape[1] if self.z_so3.ndim == 3 else -1
        expect = {
            "z_so3": (K, C, 3), "z_inv": (K, C), "scale": (K,), "center": (K, 3), "proj": (K, C, 3),
            "basis": (K, 3, 3), "eigvals": (K, 3), "bbox_center": (K, 3), "bbox_half": (K, 3),
            "class_id": (K,),
        }
        for name, shape in expect.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"Codebook.{name} must have shape {shape}, got {got}")
        if self.pcl.ndim != 3 or self.pcl.shape[0] != K or self.pcl.shape[2] != 3 or self.pcl.shape[1] < 1:
            raise ValueError(f"Codebook.pcl must have shape ({K}, n_store, 3), got {self.pcl.shape}")
        idx = np.asarray(self.input_idx)
        bad_range = idx.size > 0 and (idx.min() < 0 or idx.max() >= self.pcl.shape[1])
        if idx.ndim != 2 or idx.shape[0] != K or bad_range:
            raise ValueError(f"Codebook.input_idx must be ({K}, n_pcl) indices into pcl, got {idx.shape}")

    # ------------------------------------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return len(self.ids)

    @property
    def latent_dim(self) -> int:
        """C, the number of VN channels."""
        return int(self.z_so3.shape[1])

    @property
    def n_store(self) -> int:
        """Points per stored cloud."""
        return int(self.pcl.shape[1])

    @property
    def mean_scale(self) -> float:
        """`s̄`, the mean stored Θ_s (mesh-extraction reference scale, spec §3.9.1)."""
        return float(np.mean(self.scale.astype(np.float64)))

    def matches(self, prior: Any) -> bool:
        """True if this codebook was built from exactly these weights (see `prior_fingerprint`).

        A codebook of other weights gives meaningless retrievals and poses: rebuild it with
        `efem-viz build-codebook`. Codebooks without a stored fingerprint return True (cannot tell).
        """
        stored = self.meta.get("prior_fingerprint")
        return stored is None or stored == prior_fingerprint(prior)

    @property
    def classes(self) -> list[str]:
        """Class names of a training family's codebook (meta "classes", indexed by `class_id`); empty for a
        single category."""
        names = self.meta.get("classes")
        return [str(c) for c in names] if isinstance(names, list) else []

    def category_of(self, rows: Any, default: str, *, weights: Any = None) -> str:
        """The category of an instance whose pose search retrieved codebook `rows`: the class with the largest
        total weight among them (`weights`: how well each row aligned, its inlier ratio; default 1 each), ties
        to the class retrieved first; `default` for a codebook without classes or nothing to go by.

        A family prior (mugs, bowls, bottles and cans in one) names each instance by the training objects whose
        latents lie nearest to its own and whose surfaces fit its completed shape; rows out of range are ignored.
        """
        names = self.classes
        if not names:  # a single category's codebook: the prior's name, whatever was retrieved
            return default
        rows = np.asarray(rows, np.int64).reshape(-1)
        w = np.ones(len(rows)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
        if len(w) != len(rows):
            raise ValueError(f"{len(w)} weights for {len(rows)} rows")
        ok = (rows >= 0) & (rows < len(self)) & np.isfinite(w)
        rows, w = rows[ok], w[ok]
        if len(rows) == 0:
            return default
        ids = self.class_id[rows]
        total = np.bincount(ids, weights=w, minlength=len(names))
        best = set(np.flatnonzero(total >= total.max() - 1e-12).tolist())
        first = next(int(i) for i in ids if int(i) in best)
        return names[first] if 0 <= first < len(names) else default

    def cloud(self, k: int) -> np.ndarray:
        """(n_store, 3) float64 canonical cloud of entry `k`."""
        return self.pcl[k].astype(np.float64)

    def encoder_input(self, k: int) -> np.ndarray:
        """(n_pcl, 3) float64 the exact encoder input of entry `k` (canonical frame, not centred)."""
        return self.pcl[k][self.input_idx[k]].astype(np.float64)

    # ------------------------------------------------------------------------------------------------ kNN
    def _features(self, space: str) -> np.ndarray:
        if space == "inv":
            return self.z_inv.astype(np.float64)
        if space == "so3":
            return self.proj.reshape(len(self), -1).astype(np.float64)
        if space == "joint":
            return np.concatenate([self.proj.reshape(len(self), -1), self.z_inv], axis=1).astype(np.float64)
        raise ValueError(f"unknown feature space {space!r}")

    def tree(self, space: str) -> Any:
        """The (cached) scipy cKDTree of a feature space: "inv", "so3" or "joint"."""
        if space not in self._trees:
            from efem_viz._typeshims import cKDTree

            self._trees[space] = cKDTree(self._features(space))
        return self._trees[space]

    def query_features(self, latent_i: Any) -> dict[str, np.ndarray]:
        """The three query vectors of one latent ("inv", "so3", "joint")."""
        R, inv, _, _ = latent_to_numpy(latent_i)
        if R.shape[0] != self.latent_dim:
            raise ValueError(f"latent has {R.shape[0]} channels, codebook {self.latent_dim}")
        proj, _, _ = project_so3_code(R)
        return {"inv": inv, "so3": proj.reshape(-1), "joint": np.concatenate([proj.reshape(-1), inv])}

    def retrieve(self, latent_i: Any, *, k_inv: int = 10, k_so3: int = 3, k_joint: int = 3) -> np.ndarray:
        """Codebook rows nearest to a latent in the three feature spaces, concatenated (spec §3.9 step 3).

        Duplicates are kept (as in the release); each `k` is clipped to the codebook size.

        Args:
            latent_i: one `Latent` (world frame; the features used are rotation invariant).
            k_inv: neighbours by Θ_inv.
            k_so3: neighbours by the projected Θ_R.
            k_joint: neighbours by both.

        Returns:
            (min(k_inv,K) + min(k_so3,K) + min(k_joint,K),) int64 row indices into this codebook.
        """
        feats = self.query_features(latent_i)
        out = []
        for space, k in (("inv", k_inv), ("so3", k_so3), ("joint", k_joint)):
            k = min(int(k), len(self))
            if k <= 0:
                continue
            _, idx = self.tree(space).query(feats[space], k=k)
            out.append(np.atleast_1d(idx).astype(np.int64))
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    # ------------------------------------------------------------------------------------------------ IO
    def save(self, path: str | Path) -> Path:
        """Write an `.npz` (compressed, atomic) with a `schema_version`.

        Args:
            path: destination file (suffix `.npz`).

        Returns:
            The destination path.
        """
        import json

        from efem_viz.data.io import atomic_write

        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"codebook path must end in .npz, got {path}")
        arrays = {
            "schema_version": np.array(CODEBOOK_SCHEMA_VERSION, dtype=np.int32),
            "ids": np.asarray(self.ids, np.int64),
            "z_so3": np.asarray(self.z_so3, np.float32),
            "z_inv": np.asarray(self.z_inv, np.float32),
            "scale": np.asarray(self.scale, np.float32),
            "center": np.asarray(self.center, np.float32),
            "pcl": np.asarray(self.pcl, np.float16),
            "proj": np.asarray(self.proj, np.float32),
            "basis": np.asarray(self.basis, np.float32),
            "eigvals": np.asarray(self.eigvals, np.float32),
            "bbox_center": np.asarray(self.bbox_center, np.float32),
            "bbox_half": np.asarray(self.bbox_half, np.float32),
            "class_id": np.asarray(self.class_id, np.int32),
            "input_idx": np.asarray(self.input_idx, np.int32),
            "meta_json": np.array(json.dumps(self.meta, sort_keys=True)),
        }

        def writer(tmp: Path) -> None:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)

        return atomic_write(path, writer)

    @classmethod
    def load(cls, path: str | Path) -> Codebook:
        """Read a codebook written by `save`.

        Raises:
            FileNotFoundError: missing file.
            ValueError: naming the file: not a codebook, a corrupt archive (an array header that disagrees with
                its member's bytes is refused before numpy allocates), an unsupported schema version, arrays of
                the wrong shape or dtype, or NaN/Inf values.
        """
        import json

        from efem_viz.data.npz_guard import check_npz_headers
        from efem_viz.data.scene import SceneError

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"codebook not found: {path}")
        try:
            check_npz_headers(path, 1 << 40)
        except SceneError as exc:
            raise ValueError(str(exc)) from exc
        wanted = {"schema_version", "meta_json", *CODEBOOK_ARRAYS}  # other members are never inflated
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files if k in wanted}
        except MemoryError:
            raise
        except Exception as exc:  # zipfile, zlib and numpy raise many types on a corrupt archive
            raise ValueError(f"{path} is not a readable codebook npz: {type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:300]}") from exc
        if "schema_version" not in data:
            raise ValueError(f"{path} is not an efem-viz codebook (no schema_version; keys {sorted(data)[:12]})")
        sv = data.pop("schema_version")
        if sv.size != 1 or sv.dtype.kind not in "iu":
            raise ValueError(f"{path}: codebook schema_version must be one integer, got {sv.dtype} {sv.shape}")
        version = int(sv.reshape(()))
        if version != CODEBOOK_SCHEMA_VERSION:
            raise ValueError(f"{path}: codebook schema_version {version} is not supported "
                             f"(expected {CODEBOOK_SCHEMA_VERSION}); rebuild it with "
                             "`efem-viz build-codebook`")
        try:
            meta = json.loads(str(data.pop("meta_json"))) if "meta_json" in data else {}
        except (ValueError, RecursionError) as exc:
            raise ValueError(f"{path}: codebook meta_json is not valid JSON ({exc})") from exc
        if not isinstance(meta, dict):
            raise ValueError(f"{path}: codebook meta_json must hold a JSON object, got {type(meta).__name__}")
        required = set(CODEBOOK_ARRAYS)
        missing = required - set(data)
        if missing:
            raise ValueError(f"{path}: codebook lacks arrays {sorted(missing)}")
        for k in sorted(required):
            a = data[k]
            kinds = "iu" if k in ("ids", "class_id", "input_idx") else "f"
            if a.dtype.kind not in kinds:
                raise ValueError(f"{path}: codebook array {k!r} has dtype {a.dtype} ({kinds!r} dtype kind expected)")
            if kinds == "f" and not np.isfinite(a).all():
                raise ValueError(f"{path}: codebook array {k!r} holds NaN or Inf values")
        try:
            return cls(meta=meta, **{k: data[k] for k in required})
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc
