"""Mesh extraction from an SDF: coarse-to-fine grid evaluation + marching cubes (docs/design/efem-method.md §3.9.1).

`mesh_from_sdf_fn` works on any callable SDF (used by tests with analytic shapes); `extract_mesh` wraps it
for a `ShapePrior` latent: the decoder is evaluated with `Θ_R`, `Θ_inv`, centre 0 and the reference scale
`s̄` (the codebook's mean scale; 1.0 when the prior has no codebook — training pulls `Θ_s` toward 1) on a
world-axis-aligned cube, and the vertices are mapped by `v ↦ (Θ_s/s̄)·v + Θ_c`.

Coarse-to-fine scheme (OccNet-style, vectorised): evaluate a `coarse`³-voxel grid; at each refinement level
halve the spacing, evaluate the new samples only inside *active* cells, and fill the rest by trilinear
interpolation of the previous level. A cell is active when its corner logits straddle 0 (the release's rule)
**or** its smallest corner |sdf| is below `lipschitz · half the cell diagonal` (every point of a cell is
within half a diagonal of some corner, so for an exact, 1-Lipschitz SDF a surface can only enter a same-sign
cell if a corner value is that small — this catches thin parts, e.g. mug walls and handles, that a pure sign
test would miss). Cells far from the surface keep interpolated values whose sign is that of their corners,
so marching cubes only produces triangles in refined cells.

Deviation from the release (documented): the default cube half-size is 0.8 instead of 0.55 (the release's cube
is world-axis-aligned and clips a unit-size mug once it is rotated off-axis, e.g. the `so3` scenes).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)

__all__ = ["MeshStats", "extract_mesh", "mesh_from_sdf_fn", "sdf_grid", "simplify_mesh"]

SdfFn = Callable[[np.ndarray], np.ndarray]


@dataclass
class MeshStats:
    """Counters and timings of one meshing call, filled in place by the call it is passed to (`stats=`).

    One object per call, so concurrent meshing (viewer workers, batch runs) never mixes counters. `sdf_grid`
    fills the counters, `mesh_from_sdf_fn` and `extract_mesh` the timings and `faces` too.
    """

    queries: int = 0
    """SDF evaluations made."""
    dense_queries: int = 0
    """Evaluations a dense grid would make, `(resolution + 1)³`."""
    levels: int = 0
    """Refinement levels after the coarse grid."""
    active_cells: list[int] = field(default_factory=list)
    """Cells refined at each level."""
    t_eval: float = 0.0
    """Seconds spent evaluating the grid."""
    t_mc: float = 0.0
    """Seconds of marching cubes."""
    t_simplify: float = 0.0
    """Seconds of decimation."""
    faces: int = 0
    """Faces of the returned mesh."""


def _upsample2(v: np.ndarray) -> np.ndarray:
    """Trilinear 2× upsampling of a lattice: (n+1)³ samples → (2n+1)³ samples (separable midpoints)."""
    out = v
    for axis in range(3):
        n = out.shape[axis]
        shape = list(out.shape)
        shape[axis] = 2 * n - 1
        up = np.empty(shape, dtype=out.dtype)
        sl_even = [slice(None)] * 3
        sl_even[axis] = slice(0, None, 2)
        up[tuple(sl_even)] = out
        sl_odd = [slice(None)] * 3
        sl_odd[axis] = slice(1, None, 2)
        a = [slice(None)] * 3
        a[axis] = slice(0, -1)
        b = [slice(None)] * 3
        b[axis] = slice(1, None)
        up[tuple(sl_odd)] = 0.5 * (out[tuple(a)] + out[tuple(b)])
        out = up
    return out


def _cell_minmax(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max over the 8 corners of every cell of an (n+1)³ lattice → two (n, n, n) arrays."""
    lo = v[:-1, :-1, :-1].copy()
    hi = lo.copy()
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                c = v[dx : v.shape[0] - 1 + dx, dy : v.shape[1] - 1 + dy, dz : v.shape[2] - 1 + dz]
                np.minimum(lo, c, out=lo)
                np.maximum(hi, c, out=hi)
    return lo, hi


def _grid_points(lo: float, h: float, idx: np.ndarray) -> np.ndarray:
    """(K, 3) integer lattice indices → (K, 3) float32 coordinates `lo + h · idx`."""
    return (lo + h * idx.astype(np.float64)).astype(np.float32)


def _evaluate(fn: SdfFn, pts: np.ndarray, batch: int) -> np.ndarray:
    """(Q,) float32 values of `fn` at (Q, 3) points, in calls of at most `batch` points (each checked for size)."""
    out = np.empty(len(pts), dtype=np.float32)
    for s in range(0, len(pts), batch):
        vals = np.asarray(fn(pts[s : s + batch]), dtype=np.float32).reshape(-1)
        n_in = min(batch, len(pts) - s)
        if vals.shape[0] != n_in:
            raise ValueError(f"sdf fn returned {vals.shape[0]} values for {n_in} points")
        out[s : s + batch] = vals
    return out


def _refine_mask(v: np.ndarray, h: float, lipschitz: float) -> tuple[np.ndarray, int]:
    """Which points of the next, twice finer lattice to evaluate (`sdf_grid`): those of every active cell (a sign
    change, or a corner |sdf| below `lipschitz` × half the cell diagonal `h`√3), except the known ones.

    Args:
        v: (n+1, n+1, n+1) SDF values of the current lattice.
        h: its cell size.
        lipschitz: see `sdf_grid`.

    Returns:
        ((2n+1,)*3 bool mask, number of active cells).
    """
    n = v.shape[0] - 1
    cmin, cmax = _cell_minmax(v)
    amin = np.minimum(np.abs(cmin), np.abs(cmax))
    active = (cmin <= 0) & (cmax >= 0)
    if lipschitz > 0:
        active |= amin < lipschitz * 0.5 * np.sqrt(3.0) * h
    # mark the (2n+1)³ lattice points of every active cell
    mask = np.zeros((2 * n + 1,) * 3, dtype=bool)
    for dx in range(3):
        for dy in range(3):
            for dz in range(3):
                mask[dx : dx + 2 * n : 2, dy : dy + 2 * n : 2, dz : dz + 2 * n : 2] |= active
    mask[::2, ::2, ::2] = False  # already known
    return mask, int(active.sum())


def sdf_grid(
    fn: SdfFn,
    *,
    half_extent: float = 0.8,
    resolution: int = 64,
    coarse: int | None = 32,
    lipschitz: float = 1.0,
    batch: int = 65536,
    stats: MeshStats | None = None,
) -> np.ndarray:
    """SDF samples on a `(resolution+1)³` lattice over `[−half_extent, half_extent]³`, coarse-to-fine.

    Args:
        fn: maps (Q, 3) float32 points to (Q,) SDF values (negative inside); called in chunks of `batch`.
        half_extent: half side of the cube.
        resolution: final voxels per side; `resolution / coarse` must be a power of two.
        coarse: voxels per side of the first level; None or >= resolution means a dense evaluation.
        lipschitz: also refine same-sign cells whose smallest corner |sdf| < `lipschitz` × half the cell
            diagonal (1 = exact for a true SDF; 0 = the release's pure sign-change rule).
        batch: points per `fn` call.
        stats: filled in place with `queries`, `dense_queries`, `levels` and `active_cells` (optional).

    Returns:
        (R+1, R+1, R+1) float32 SDF values (exact where evaluated, interpolated elsewhere) indexed [x, y, z].
    """
    if resolution < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    if not half_extent > 0:
        raise ValueError(f"half_extent must be > 0, got {half_extent}")
    if coarse is None or coarse >= resolution:
        coarse = resolution
    ratio = resolution // coarse
    if coarse < 1 or ratio * coarse != resolution or ratio & (ratio - 1):
        raise ValueError(
            f"resolution/coarse must be a power of two; got resolution={resolution}, coarse={coarse}"
        )

    lo = -float(half_extent)
    n = coarse
    h = 2.0 * half_extent / n
    idx = np.stack(np.meshgrid(*(np.arange(n + 1),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    v = _evaluate(fn, _grid_points(lo, h, idx), batch).reshape(n + 1, n + 1, n + 1)
    queries = len(idx)
    active_counts: list[int] = []
    levels = 0
    while n < resolution:
        mask, n_active = _refine_mask(v, h, lipschitz)
        active_counts.append(n_active)
        v = _upsample2(v)
        n *= 2
        h /= 2.0
        new_idx = np.argwhere(mask)
        if len(new_idx):
            v[mask] = _evaluate(fn, _grid_points(lo, h, new_idx), batch)
        queries += len(new_idx)
        levels += 1
    if stats is not None:
        stats.queries = int(queries)
        stats.dense_queries = int((resolution + 1) ** 3)
        stats.levels = levels
        stats.active_cells = active_counts
    return v


_undecimated_warned: list[bool] = []


def simplify_mesh(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """Quadric-edge-collapse decimation to at most `max_faces` faces (unchanged if already small).

    Uses open3d (fastest here); if that breaks the watertightness of a watertight input, falls back to
    pymeshlab's topology-preserving quadric decimation. On a machine without open3d (a GPU machine running
    `bench/gpu_check.py`) the mesh is returned undecimated, with one warning per process.

    Args:
        mesh: input triangle mesh.
        max_faces: target face count (>= 4).

    Returns:
        A new trimesh.Trimesh (the input when no reduction is needed).
    """
    import trimesh

    if max_faces < 4:
        raise ValueError(f"max_faces must be >= 4, got {max_faces}")
    if len(mesh.faces) <= max_faces:
        return mesh
    try:
        import open3d as o3d
    except ImportError:
        if not _undecimated_warned:
            _undecimated_warned.append(True)
            logger.warning("open3d is not installed: completed meshes stay undecimated (more faces, the same shapes)")
        return mesh

    om = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    om = om.simplify_quadric_decimation(target_number_of_triangles=int(max_faces))
    om.remove_unreferenced_vertices()
    out = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles), process=False)
    if out.is_watertight or not mesh.is_watertight:
        return out
    # pymeshlab re-exports these with `from .pmeshlab import *` (a compiled module), which pyright cannot
    # follow; importing them from there gives the same classes and still runs pymeshlab/__init__.py first
    from pymeshlab.pmeshlab import Mesh, MeshSet

    logger.debug("open3d decimation broke watertightness; retrying with pymeshlab (preservetopology)")
    ms = MeshSet()
    ms.add_mesh(Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(max_faces), preservetopology=True,
                                                preservenormal=True)
    cm = ms.current_mesh()
    return trimesh.Trimesh(cm.vertex_matrix(), cm.face_matrix(), process=False)


def mesh_from_sdf_fn(
    fn: SdfFn,
    *,
    half_extent: float = 0.8,
    resolution: int = 64,
    coarse: int | None = 32,
    lipschitz: float = 1.0,
    max_faces: int | None = 5000,
    batch: int = 65536,
    stats: MeshStats | None = None,
) -> trimesh.Trimesh:
    """Watertight triangle mesh of the zero level set of an SDF inside a cube.

    Marching cubes (scikit-image) runs on the occupancy logit `−sdf` at level 0, on a lattice padded with a
    strongly negative (outside) value, so the surface is closed even where the shape touches the cube.
    Faces are wound counter-clockwise seen from outside (positive volume, outward normals).

    Args:
        fn: maps (Q, 3) float32 points to (Q,) float SDF values (negative inside), frame of the cube.
        half_extent: the cube is `[−half_extent, half_extent]³`.
        resolution: final voxels per side.
        coarse: first-level voxels per side (None = dense).
        lipschitz: see `sdf_grid`.
        max_faces: decimate to at most this many faces (None = keep marching-cubes output).
        batch: points per `fn` call.
        stats: filled in place with this call's counters and timings (optional; see `MeshStats`).

    Returns:
        trimesh.Trimesh in the cube's frame (empty when the level set does not cross the grid).
    """
    import trimesh
    from skimage.measure import marching_cubes

    st = MeshStats() if stats is None else stats
    t0 = time.perf_counter()
    v = sdf_grid(
        fn, half_extent=half_extent, resolution=resolution, coarse=coarse, lipschitz=lipschitz, batch=batch,
        stats=st,
    )
    t1 = time.perf_counter()
    logit = -v
    if not np.isfinite(logit).all():
        raise ValueError("sdf fn returned non-finite values")
    if not (logit.max() > 0 and logit.min() < 0):
        st.t_eval, st.t_mc, st.t_simplify, st.faces = t1 - t0, 0.0, 0.0, 0
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    h = 2.0 * half_extent / resolution
    # samples exactly on the level set make marching cubes emit duplicate vertices (holes after welding);
    # nudge them outside by a negligible amount (1e-5 of a voxel for a unit-slope SDF)
    logit[logit == 0.0] = -1e-5 * h
    pad_value = -max(1.0, 2.0 * float(np.abs(logit).max()))
    padded = np.pad(logit, 1, mode="constant", constant_values=pad_value)
    verts, faces, _, _ = marching_cubes(padded, level=0.0, spacing=(h, h, h), gradient_direction="descent")
    verts = verts - (half_extent + h)
    # scikit-image winds faces so that normals point toward decreasing values for "descent"; with the logit
    # (positive inside) that is outward, but its triangle order is clockwise: flip for CCW-outward.
    faces = faces[:, ::-1]
    mesh = trimesh.Trimesh(verts, faces, process=False)
    t2 = time.perf_counter()
    if max_faces is not None:
        mesh = simplify_mesh(mesh, max_faces)
    t3 = time.perf_counter()
    st.t_eval, st.t_mc, st.t_simplify, st.faces = t1 - t0, t2 - t1, t3 - t2, len(mesh.faces)
    logger.debug("mesh_from_sdf_fn: %s", st)
    return mesh


def _reference_scale(prior: Any) -> float:
    cb = getattr(prior, "codebook", None)
    if cb is not None:
        return float(cb.mean_scale)
    return 1.0


def _single_latent(latent_i: Any) -> Any:
    """Return the latent with a leading batch dimension of 1 (accepts (C,3) or (1,C,3) Θ_R)."""
    if latent_i.R.ndim == 2:
        return type(latent_i)(
            R=latent_i.R[None], inv=latent_i.inv[None], center=latent_i.center[None],
            scale=latent_i.scale.reshape(1),
        )
    if latent_i.R.shape[0] != 1:
        raise ValueError(f"extract_mesh needs a single latent, got Θ_R of shape {tuple(latent_i.R.shape)}")
    return latent_i


def _reference_sdf_fn(prior: Any, lat: Any, *, s_bar: float, clip_r: float | None) -> SdfFn:
    """The SDF of one latent's shape in its reference frame (centre 0, scale `s_bar`, world orientation), as a
    function of (Q, 3) float32 points (`extract_mesh`); intersected with the ball of radius `clip_r` when given."""
    import torch

    param = next(prior.parameters())
    dtype, device = param.dtype, param.device
    R = torch.as_tensor(lat.R, dtype=dtype, device=device)
    inv = torch.as_tensor(lat.inv, dtype=dtype, device=device)
    ref = type(lat)(
        R=R,
        inv=inv,
        center=torch.zeros(1, 3, dtype=dtype, device=device),
        scale=torch.full((1,), s_bar, dtype=dtype, device=device),
    )

    def fn(pts: np.ndarray) -> np.ndarray:
        # no train/eval toggling: the prior has no dropout or normalisation layers, and toggling a shared module
        # from a viewer worker thread would race with other users of it
        with torch.no_grad():
            x = torch.from_numpy(pts).to(device=device, dtype=dtype)
            out = prior.sdf(x[None], ref).reshape(-1).float().cpu().numpy()
        if clip_r is not None:
            out = np.maximum(out, (np.linalg.norm(pts, axis=1) - clip_r) / s_bar)
        return out

    return fn


def extract_mesh(
    prior: Any,
    latent_i: Any,
    *,
    resolution: int = 64,
    coarse: int | None = 32,
    world: bool = True,
    max_faces: int | None = 5000,
    half_extent: float = 0.8,
    lipschitz: float = 1.0,
    batch: int = 4096,
    reference_scale: float | None = None,
    clip_ball: bool = True,
    stats: MeshStats | None = None,
) -> trimesh.Trimesh:
    """Mesh of one latent's shape (docs/design/efem-method.md §3.9.1).

    Args:
        prior: a `ShapePrior` (its decoder is called through `prior.sdf`).
        latent_i: one `Latent` (Θ_R (1, C, 3) or (C, 3), Θ_inv, Θ_c, Θ_s), world frame.
        resolution: final grid voxels per side (64 for the viewer, 128 like the release).
        coarse: first-level voxels per side (None = dense).
        world: map vertices to the world by `v ↦ (Θ_s/s̄)·v + Θ_c`; otherwise keep the reference frame
            (centre 0, scale s̄, world orientation).
        max_faces: decimation target (None = no decimation).
        half_extent: half side of the evaluation cube (reference frame units).
        lipschitz: see `sdf_grid`.
        batch: decoder queries per call (small chunks stay in cache: ~2× faster than 64k on CPU).
        reference_scale: `s̄`; default the prior codebook's mean scale (1.0 without a codebook).
        clip_ball: intersect the shape with the ball of radius `half_extent` (a unit-size object around Θ_c
            fits in it in any orientation); this removes what the decoder extrapolates in the cube's corners,
            far outside the [−0.55, 0.55]³ training queries.
        stats: filled in place with the meshing counters and timings (optional; see `MeshStats`).

    Returns:
        trimesh.Trimesh (float64 vertices; empty if the decoded shape does not cross the cube).
    """
    import torch

    lat = _single_latent(latent_i)
    s_bar = _reference_scale(prior) if reference_scale is None else float(reference_scale)
    if not s_bar > 0:
        raise ValueError(f"reference scale must be > 0, got {s_bar}")
    fn = _reference_sdf_fn(prior, lat, s_bar=s_bar, clip_r=float(half_extent) if clip_ball else None)
    mesh = mesh_from_sdf_fn(
        fn,
        half_extent=half_extent,
        resolution=resolution,
        coarse=coarse,
        lipschitz=lipschitz,
        max_faces=max_faces,
        batch=batch,
        stats=stats,
    )
    if world and len(mesh.vertices):
        scale = float(np.asarray(torch.as_tensor(lat.scale).detach().cpu(), dtype=np.float64).reshape(-1)[0])
        center = np.asarray(torch.as_tensor(lat.center).detach().cpu(), dtype=np.float64).reshape(3)
        mesh.vertices = mesh.vertices * (scale / s_bar) + center
    return mesh
