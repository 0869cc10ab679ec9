"""Rigid (SE(3)) and similarity (SIM(3)) transforms, random rotations and quaternion conversion.

Conventions (as in docs/design/efem-method.md): points are column vectors; a similarity `g = (s, R, t)` acts as
`x ↦ s R x + t` with `s > 0` and `R ∈ SO(3)`. Arrays of points are stored as rows, so applying `g` to an
(N, 3) array is `s * points @ R.T + t`. Quaternions are scalar-first `wxyz` (viser's convention).
Pure NumPy; no torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from efem_viz.geometry.procrustes import rotation_from_cross_covariance

__all__ = [
    "Sim3",
    "apply_transform",
    "compose_transforms",
    "invert_transform",
    "make_transform",
    "project_to_so3",
    "quat_wxyz_to_rotation",
    "random_rotation",
    "random_rotations",
    "random_sim3",
    "rotation_about_axis",
    "rotation_angle_deg",
    "rotation_to_quat_wxyz",
    "xyz_tuple",
]


def _as_generator(seed: int | np.random.Generator | None) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)


def _check_rotation_shape(R: np.ndarray, name: str = "R") -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {R.shape}")
    return R


def random_rotations(n: int, *, seed: int | np.random.Generator | None = 0) -> np.ndarray:
    """Uniformly distributed (Haar) random proper rotations.

    Args:
        n: number of rotations (>= 0).
        seed: integer seed or Generator.

    Returns:
        (n, 3, 3) float64 rotation matrices with det = +1.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = _as_generator(seed)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return quat_wxyz_to_rotation(q)


def random_rotation(seed: int | np.random.Generator | None = 0) -> np.ndarray:
    """One uniformly distributed random rotation, (3, 3) float64, det = +1."""
    return random_rotations(1, seed=seed)[0]


def rotation_about_axis(axis: np.ndarray | list[float], angle: float) -> np.ndarray:
    """Rotation by `angle` radians about `axis` (right-hand rule), via Rodrigues' formula.

    Args:
        axis: (3,) direction, need not be unit length (must be non-zero).
        angle: radians.

    Returns:
        (3, 3) float64 rotation matrix.
    """
    a = np.asarray(axis, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"axis must have shape (3,), got {np.asarray(axis).shape}")
    norm = np.linalg.norm(a)
    if not norm > 0:
        raise ValueError("axis must be non-zero")
    a = a / norm
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def rotation_between(a: np.ndarray | Sequence[float], b: np.ndarray | Sequence[float]) -> np.ndarray:
    """The smallest rotation taking direction `a` to direction `b` (both non-zero, need not be unit length);
    for opposite directions, a half turn about an axis perpendicular to `a`.

    Returns:
        (3, 3) float64 rotation matrix R with R â = b̂.
    """
    u = np.asarray(a, np.float64).reshape(3)
    v = np.asarray(b, np.float64).reshape(3)
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(u, v)
    s, c = float(np.linalg.norm(axis)), float(np.dot(u, v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        return rotation_about_axis(perp, np.pi)
    return rotation_about_axis(axis, float(np.arctan2(s, c)))


def quat_wxyz_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s), scalar first, to rotation matrices.

    Args:
        q: (..., 4) float, `wxyz`. Normalised internally.

    Returns:
        (..., 3, 3) float64.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have shape (..., 4), got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("zero quaternion")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (or matrices) to unit quaternion(s) `wxyz` with w >= 0 (viser's convention).

    Uses Shepperd's method (numerically stable for every angle). Input must be a proper rotation;
    it is projected to SO(3) first, so slightly non-orthogonal input is accepted.

    Args:
        R: (..., 3, 3) float.

    Returns:
        (..., 4) float64.
    """
    R = project_to_so3(_check_rotation_shape(R))
    flat = R.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for i, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            out[i] = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            out[i] = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            out[i] = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            out[i] = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[out[:, 0] < 0] *= -1.0
    return out.reshape(R.shape[:-2] + (4,))


def xyz_tuple(v: np.ndarray | Sequence[float]) -> tuple[float, float, float]:
    """A 3-vector as a plain float triple (what viser's `position`/`look_at`/`up` arguments take).

    Args:
        v: (3,) float, any frame.

    Returns:
        (x, y, z) Python floats.

    Raises:
        ValueError: `v` does not hold exactly three values.
    """
    x, y, z = (float(c) for c in v)
    return x, y, z


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest proper rotation(s) to `M` in the Frobenius norm: `U diag(1, 1, det(U Vᵀ)) Vᵀ`.

    Note that for an exact reflection (all singular values 1) the nearest rotation is not unique; this
    flips the axis of the *smallest* singular value (the last one returned by the SVD). Pose code that
    must pick a meaningful rotation should re-solve its Procrustes problem with the determinant fix
    (see `efem_viz.geometry.procrustes`) instead of projecting a reflection after the fact.

    Args:
        M: (..., 3, 3) float.

    Returns:
        (..., 3, 3) float64 with det = +1.
    """
    # the nearest rotation of M is the proper R maximising tr(Rᵀ M): one SVD rule, in procrustes.py
    return rotation_from_cross_covariance(_check_rotation_shape(M, "M"), proper=True)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray | None = None) -> np.ndarray | float:
    """Geodesic angle between rotations, in degrees: `arccos((tr(R_aᵀ R_b) − 1) / 2)`.

    Args:
        R_a: (..., 3, 3).
        R_b: (..., 3, 3) or None (then the angle of `R_a` itself).

    Returns:
        float (or array of shape (...)) in [0, 180].
    """
    R_a = _check_rotation_shape(R_a, "R_a")
    rel = R_a if R_b is None else np.swapaxes(R_a, -1, -2) @ _check_rotation_shape(R_b, "R_b")
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(ang) if np.ndim(ang) == 0 else ang


def make_transform(R: np.ndarray, t: np.ndarray | None = None, *, scale: float = 1.0) -> np.ndarray:
    """4×4 homogeneous matrix of `x ↦ scale · R x + t`.

    Args:
        R: (3, 3) rotation.
        t: (3,) translation (default 0).
        scale: positive scale (1 for SE(3)).

    Returns:
        (4, 4) float64.
    """
    R = _check_rotation_shape(R)
    if R.shape != (3, 3):
        raise ValueError(f"R must have shape (3, 3), got {R.shape}")
    T = np.eye(4)
    T[:3, :3] = scale * R
    if t is not None:
        t = np.asarray(t, dtype=np.float64)
        if t.shape != (3,):
            raise ValueError(f"t must have shape (3,), got {t.shape}")
        T[:3, 3] = t
    return T


def _check_T(T: np.ndarray, name: str = "T") -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {T.shape}")
    return T


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 (rigid or similarity) transform to row points.

    Args:
        T: (4, 4).
        points: (N, 3).

    Returns:
        (N, 3) float64.
    """
    T = _check_T(T)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    return pts @ T[:3, :3].T + T[:3, 3]


def compose_transforms(*Ts: np.ndarray) -> np.ndarray:
    """Matrix product `Ts[0] @ Ts[1] @ ...` (so the last transform is applied first)."""
    if not Ts:
        return np.eye(4)
    out = _check_T(Ts[0]).copy()
    for i, T in enumerate(Ts[1:], start=1):
        out = out @ _check_T(T, f"Ts[{i}]")
    return out


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4×4 similarity transform `[sR | t]` without a general matrix inverse.

    Args:
        T: (4, 4) with upper-left block `s R` (s > 0, R orthogonal).

    Returns:
        (4, 4) float64 with `T_inv @ T = I`.
    """
    T = _check_T(T)
    A = T[:3, :3]
    s2 = float(np.mean(np.sum(A * A, axis=0)))
    if not s2 > 0:
        raise ValueError("transform has a zero linear part")
    A_inv = A.T / s2
    out = np.eye(4)
    out[:3, :3] = A_inv
    out[:3, 3] = -A_inv @ T[:3, 3]
    return out


@dataclass(frozen=True)
class Sim3:
    """A similarity transform `x ↦ scale · R x + t` (SE(3) when scale = 1)."""

    scale: float
    """Positive scale factor."""
    R: np.ndarray
    """(3, 3) float64 rotation (columns = the source frame's axes in the target frame)."""
    t: np.ndarray
    """(3,) float64 translation."""

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"Sim3.R must have shape (3, 3), got {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"Sim3.t must have shape (3,), got {t.shape}")
        if not float(self.scale) > 0:
            raise ValueError(f"Sim3.scale must be > 0, got {self.scale}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def identity(cls) -> Sim3:
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Sim3:
        """From a 4×4 matrix `[sR | t]` (s recovered as the mean column norm)."""
        T = _check_T(T)
        A = T[:3, :3]
        s = float(np.sqrt(np.mean(np.sum(A * A, axis=0))))
        return cls(s, A / s, T[:3, 3].copy())

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous matrix."""
        return make_transform(self.R, self.t, scale=self.scale)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (N, 3) row points; returns (N, 3) float64."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        return self.scale * pts @ self.R.T + self.t

    def inverse(self) -> Sim3:
        """`x ↦ (1/s) Rᵀ (x − t)`."""
        R_inv = self.R.T
        return Sim3(1.0 / self.scale, R_inv, -(R_inv @ self.t) / self.scale)

    def compose(self, other: Sim3) -> Sim3:
        """`self ∘ other` (apply `other` first)."""
        return Sim3(
            self.scale * other.scale,
            self.R @ other.R,
            self.scale * (self.R @ other.t) + self.t,
        )

    def __matmul__(self, other: Sim3) -> Sim3:
        return self.compose(other)


def random_sim3(
    seed: int | np.random.Generator | None = 0,
    *,
    scale_range: tuple[float, float] = (0.5, 2.0),
    translation_std: float = 1.0,
) -> Sim3:
    """A random similarity: Haar rotation, log-uniform scale in `scale_range`, Gaussian translation.

    Args:
        seed: integer seed or Generator.
        scale_range: (lo, hi) with 0 < lo <= hi.
        translation_std: standard deviation of each translation component.
    """
    lo, hi = scale_range
    if not 0 < lo <= hi:
        raise ValueError(f"scale_range must satisfy 0 < lo <= hi, got {scale_range}")
    rng = _as_generator(seed)
    R = random_rotation(rng)
    s = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    t = rng.normal(0.0, translation_std, size=3)
    return Sim3(s, R, t)
