"""From depth frames to a scan: projective TSDF fusion into a mesh, or voxel-averaged points; mesh clean-up."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from efem_viz.data.synth.render import frame_points, RenderedFrame
from efem_viz.geometry.camera import Camera


# ====================================================================================== fusion
def voxel_average(
    points: np.ndarray, colors: np.ndarray, normals: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average points/colours/normals per voxel; output sorted by voxel key (deterministic)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    n = len(counts)

    def avg(a: np.ndarray) -> np.ndarray:
        out = np.zeros((n, a.shape[1]))
        np.add.at(out, inv, a)
        return out / counts[:, None]

    return avg(points), avg(colors.astype(np.float64)), avg(normals)


def _band_voxels(frames: Sequence[RenderedFrame], cams: Sequence[Camera], *, lo: np.ndarray, dims: np.ndarray,
                 voxel: float, trunc_voxels: float) -> np.ndarray:
    """Flat indices (into the `dims` grid with origin `lo`) of the voxels within the truncation band of some
    measurement: only they can carry |tsdf| < 1 (`fuse_tsdf`)."""
    from scipy.ndimage import binary_dilation

    occ = np.zeros(tuple(dims), bool)
    for fr, cam in zip(frames, cams):
        p, _, _ = frame_points(fr, cam)
        ijk = np.round((p - lo) / voxel).astype(np.int64)
        ijk = ijk[np.all((ijk >= 0) & (ijk < dims), axis=1)]
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    r = int(math.ceil(trunc_voxels))
    ball = np.linalg.norm(np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1], axis=0) <= r + 0.5
    return np.nonzero(binary_dilation(occ, structure=ball).ravel())[0]


def _integrate(frames: Sequence[RenderedFrame], cams: Sequence[Camera], centres: np.ndarray, *,
               trunc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective TSDF at the (n, 3) voxel `centres`: the running mean over cameras of the truncated signed
    distance (voxels in front of a measurement or less than `trunc` behind it), and of the colour (within
    `trunc` of the surface).

    Returns:
        tsdf (n,) float32 in [-1, 1], weight (n,) float32 (cameras that saw the voxel), colour (n, 3) float32.
    """
    n = len(centres)
    tsdf = np.zeros(n, np.float32)
    weight = np.zeros(n, np.float32)
    color = np.zeros((n, 3), np.float32)
    cweight = np.zeros(n, np.float32)
    for fr, cam in zip(frames, cams):
        u, v, z, ok = cam.project(centres)
        idx = np.nonzero(ok)[0]
        ui, vi = u[idx], v[idx]
        d = fr.depth[vi, ui].astype(np.float64)
        sdf = d - z[idx]
        use = (d > 0) & (sdf > -trunc)
        idx, sdf, ui, vi = idx[use], sdf[use], ui[use], vi[use]
        val = np.minimum(sdf / trunc, 1.0).astype(np.float32)
        tsdf[idx] = (tsdf[idx] * weight[idx] + val) / (weight[idx] + 1.0)
        weight[idx] += 1.0
        near = np.abs(sdf) < trunc
        cidx = idx[near]
        rgb = fr.color[vi[near], ui[near]].astype(np.float32)
        color[cidx] = (color[cidx] * cweight[cidx, None] + rgb) / (cweight[cidx, None] + 1.0)
        cweight[cidx] += 1.0
    return tsdf, weight, color


def _meshable_cubes(seen: np.ndarray) -> np.ndarray:
    """The cubes to mesh: those whose 8 corners are all usable (`seen`), marked at the cube's first corner (the
    marching-cubes mask); the last layer of each axis starts no cube."""
    cube = seen.copy()
    cube[:-1, :-1, :-1] = (
        seen[:-1, :-1, :-1] & seen[1:, :-1, :-1] & seen[:-1, 1:, :-1] & seen[:-1, :-1, 1:]
        & seen[1:, 1:, :-1] & seen[1:, :-1, 1:] & seen[:-1, 1:, 1:] & seen[1:, 1:, 1:]
    )  # fmt: skip
    cube[-1, :, :] = False
    cube[:, -1, :] = False
    cube[:, :, -1] = False
    return cube


def fuse_tsdf(
    frames: Sequence[RenderedFrame],
    cams: Sequence[Camera],
    *,
    voxel: float,
    lo: np.ndarray,
    hi: np.ndarray,
    trunc_voxels: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse depth frames into a truncated signed distance grid over the box [lo, hi] and mesh its zero level.

    Projective TSDF (Curless & Levoy / KinectFusion): every voxel centre in front of a measurement or less
    than `trunc_voxels * voxel` behind it takes the mean of the truncated signed distances of all cameras;
    marching cubes (scikit-image) runs only on cubes whose 8 corners were observed. Pure NumPy, deterministic.

    Args:
        frames: depth (H, W) float32 metres (0 = none) and colour (H, W, 3) uint8 per camera.
        cams: the cameras (intrinsics, T_world_camera).
        voxel: voxel size, metres.
        lo, hi: (3,) world-frame corners of the fused box (the grid origin moves by up to half a voxel in z).
        trunc_voxels: truncation distance in voxels.

    Returns:
        vertices (V, 3) float64 world frame, faces (F, 3) int64 (outward = towards the cameras),
        colours (V, 3) float64 in [0, 255].
    """
    from skimage.measure import marching_cubes

    # put the table top (z = 0) halfway between two voxel layers: a surface running exactly through voxel
    # centres makes marching cubes emit degenerate triangles, which leaves holes and doubles the vertex count
    lo = np.array(lo, dtype=np.float64)
    lo[2] = (math.floor(lo[2] / voxel) + 0.5) * voxel
    dims = np.maximum(np.ceil((hi - lo) / voxel).astype(int) + 1, 2)
    active = _band_voxels(frames, cams, lo=lo, dims=dims, voxel=voxel, trunc_voxels=trunc_voxels)
    ii, jj, kk = np.unravel_index(active, tuple(dims))
    centres = lo + voxel * np.stack([ii, jj, kk], axis=1).astype(np.float64)
    tsdf, weight, color = _integrate(frames, cams, centres, trunc=trunc_voxels * voxel)
    vol = np.ones(tuple(dims), np.float32)
    vol.ravel()[active] = tsdf
    # usable corners: observed, and not truncated (a jump from +1 to a negative value is a depth-discontinuity
    # or frustum-border artefact, not a surface)
    good = np.zeros(tuple(dims), bool)
    good.ravel()[active] = (weight > 0) & (np.abs(tsdf) < 0.999)
    cube = _meshable_cubes(good)
    if not cube.any() or vol[cube].min() >= 0 or vol[cube].max() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(voxel, voxel, voxel), mask=cube)
    # with the default gradient_direction="descent", scikit-image winds the faces so that their normals point
    # towards increasing values: + is free space, so the normals face the cameras (checked in tests)
    faces = faces.astype(np.int64)
    full_col = np.zeros((int(np.prod(dims)), 3), np.float32)
    full_col[active] = color
    ijk = np.clip(np.round(verts / voxel).astype(np.int64), 0, dims - 1)
    flat = np.ravel_multi_index((ijk[:, 0], ijk[:, 1], ijk[:, 2]), tuple(dims))
    vcol = full_col[flat].astype(np.float64)
    # merge coincident vertices (the masked marching cubes can emit a few) and drop collapsed faces
    uniq, first, inv = np.unique(verts, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    faces = inv[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    return uniq.astype(np.float64) + lo, faces, vcol[first]


def remove_small_components(v: np.ndarray, f: np.ndarray, min_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Drop connected components with fewer than `min_faces` faces (TSDF speckles from noise)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    if len(f) == 0:
        return np.zeros(0, bool), f
    n = len(v)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(adj, directed=False)
    face_comp = comp[f[:, 0]]
    sizes = np.bincount(face_comp, minlength=comp.max() + 1)
    keep_face = sizes[face_comp] >= min_faces
    keep_vert = np.zeros(n, bool)
    keep_vert[f[keep_face].reshape(-1)] = True
    return keep_vert, f[keep_face]


def area_weighted_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals of a mesh ((0, 0, 1) for vertices without area)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], fn)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(ln > 1e-20, acc / np.maximum(ln, 1e-20), np.array([0.0, 0.0, 1.0]))
    return out


def crop_mesh(
    v: np.ndarray, f: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the vertices in `keep` and the faces whose three vertices are kept; returns (index, faces)."""
    idx = np.nonzero(keep)[0]
    remap = -np.ones(len(v), np.int64)
    remap[idx] = np.arange(len(idx))
    fr = remap[f]
    fr = fr[(fr >= 0).all(axis=1)]
    return idx, fr
