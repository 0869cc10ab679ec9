"""Training data for a shape prior (docs/design/efem-method.md §2.1-§2.4): per-object caches and per-example sampling.

Per object (canonical frame: +Z up, bounding-box centre at the origin, longest side 1) we cache in an npz:
``uni`` (Nu, 4) uniform queries in ``[-0.55, 0.55]³`` + SDF, ``nss`` (Nn, 4) near-surface queries + SDF,
``surface`` (Ns, 3) dense surface samples, ``views`` (V, 3) back-projected depth-view hits with
``view_offsets`` (12 + 1), ``view_elev_deg`` (12,), ``view_eyes`` (12, 3) camera centres and ``view_cos`` (V,)
the cosine of the incidence angle of every hit (for the depth-sensor model, `sensor_cloud`). SDF and depth views
come from open3d's ``RaycastingScene`` on a CPU with open3d, otherwise from the plain-torch
`efem_viz.geometry.raycast` (the same numbers to float rounding, on any device: a GPU machine without open3d
prepares its own data). Signs need watertight meshes.

Meshes travel to a machine without trimesh as a *mesh pack* (`save_mesh_pack`, `pack_sources`): one npz of
normalised vertex and face arrays.

Depth views (deviation from §2.1, documented in the training report): views 0-7 look from above (elevation
30-60°, as in the release data), views 8-9 from the side (-10..30°) and views 10-11 from below (-60..-10°),
because so3/pile scenes show mugs in any orientation. An example uses only the top views with probability
``p_top_only``.
A table-plane patch under the object (``p_table``) is an added augmentation (real scans always have a table).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

from efem_viz.geometry.sampling import MeshArrays

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)

CACHE_VERSION = 4
_CACHE_KEYS = ("uni", "nss", "surface", "views", "view_offsets", "view_elev_deg", "view_eyes", "view_cos")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".glb", ".gltf", ".stl")


@dataclass(frozen=True)
class PrepConfig:
    """How per-object training data is precomputed (all sizes in canonical units)."""

    n_uniform: int = 16000
    """Uniform SDF queries per object (cube ``[-0.55, 0.55]³``)."""
    n_near: int = 16000
    """Near-surface SDF queries per object."""
    near_sigmas: tuple[float, ...] = (0.01, 0.03)
    """Gaussian offset std of near-surface queries (split evenly)."""
    n_surface: int = 8000
    """Dense surface samples per object."""
    n_views: int = 12
    """Depth views per object."""
    n_top_views: int = 8
    """Views 0..n_top-1 from above (elevation 30-60°); the rest half from the side, half from below."""
    resolution: int = 128
    """Depth image size (square), pixels."""
    fov_deg: float = 60.0
    """Camera field of view."""
    distance: tuple[float, float] = (0.9, 1.3)
    """Camera distance range from the object centre."""
    max_view_points: int = 3000
    """Hits kept per view (random subset)."""


@dataclass
class ObjectData:
    """Cached training data of one normalised object (float32 arrays, canonical frame)."""

    name: str
    uni: np.ndarray
    """(Nu, 4) xyz + SDF, uniform queries."""
    nss: np.ndarray
    """(Nn, 4) xyz + SDF, near-surface queries."""
    surface: np.ndarray
    """(Ns, 3) surface samples."""
    views: np.ndarray
    """(V, 3) concatenated depth-view points."""
    view_offsets: np.ndarray
    """(n_views + 1,) int64 offsets into ``views``."""
    view_elev_deg: np.ndarray
    """(n_views,) camera elevation of every view."""
    view_eyes: np.ndarray | None = None
    """(n_views, 3) camera centre of every view (None in hand-built objects: the sensor model then uses the
    direction from the view's mean elevation)."""
    view_cos: np.ndarray | None = None
    """(V,) |cos| of the incidence angle of every view hit (None: taken as 1)."""

    @property
    def z_bottom(self) -> float:
        """Lowest surface z (the table height under an upright object)."""
        return float(self.surface[:, 2].min())

    def view(self, i: int) -> np.ndarray:
        """(n_i, 3) points of depth view ``i``."""
        return self.views[self.view_offsets[i]:self.view_offsets[i + 1]]


@dataclass(frozen=True)
class SampleConfig:
    """Per-example sampling and augmentation (§2.2-§2.4; mug defaults)."""

    n_pcl: int = 512
    """Encoder input points."""
    n_query_uniform: int = 1024
    """Uniform queries per example."""
    n_query_near: int = 1024
    """Near-surface queries per example."""
    min_views: int = 4
    """Minimum number of views drawn (max = all)."""
    p_top_only: float = 0.6
    """Probability that an example draws only from the top views."""
    noise_std: float = 0.01
    """Gaussian noise on input points."""
    aug_ratio: float = 0.7
    """ρ: at most ⌊ρN⌋ points are replaced."""
    p_obj: float = 0.7
    """Probability of other-object crops."""
    p_ball: float = 0.7
    """Probability of ball removal."""
    p_table: float = 0.3
    """Probability of a table-plane patch at the object bottom (deviation: replaces the unused plane aug)."""
    p_table_any_side: float = 0.0
    """Probability that a table patch touches the object from a random direction (uniform on the sphere) instead of
    from below (an object lying on its side, back or top, as tumbled chairs do, has its support plane there)."""
    p_neighbour: float = 0.0
    """Probability that the other-object points of an example are the part of a whole neighbouring object that
    falls inside the example's reach (the object placed beside it, touching or a small gap away, as a pile's
    neighbours are) instead of small crops floating around it."""
    neighbour_gap: tuple[float, float] = (0.0, 0.08)
    """Range of the gap (canonical units) between a neighbour and the object."""
    crop_radius: tuple[float, float] = (0.15, 0.09)
    """Crop radius mean / std."""
    crop_scale: tuple[float, float] = (0.5, 1.5)
    """Crop scale range."""
    placement_std: float = 0.1
    """Crop placement std L."""
    ball_max_k: int = 25
    """Points removed per ball."""
    ball_noise: float = 0.05
    """Noise on squared distances when removing balls."""
    table_scale: tuple[float, float] = (0.4, 1.0)
    """Half-size range of the table patch."""
    centroid_noise: float = 0.05
    """Std of the centroid augmentation (§2.4)."""
    sensor_p: float = 0.0
    """Probability that an example is a depth-sensor view (`sensor_cloud`) instead of `input_cloud`'s union of
    views with isotropic noise (0 = isotropic noise only, as the first priors were trained)."""
    sensor_scale: tuple[float, float] = (0.5, 2.0)
    """Range of the multiplier k of the sensor's noise model."""
    sensor_distance: tuple[float, float] = (0.4, 1.2)
    """Camera distance range, metres."""
    sensor_fx: tuple[float, float] = (430.0, 615.0)
    """Focal length range, pixels."""
    object_size: tuple[float, float] = (0.09, 0.14)
    """Metric size of the object's longest side (metres per canonical unit)."""
    p_few_views: float = 0.8
    """Probability that a sensor example unites 1-2 views (else 3-12)."""
    density: tuple[int, int] = (300, 3000)
    """Visible points a sensor example keeps before ``n_pcl`` are drawn from them with replacement."""


# ---------------------------------------------------------------------------------------------- meshes
def normalize_mesh(mesh: trimesh.Trimesh | MeshArrays) -> trimesh.Trimesh | MeshArrays:
    """Bounding-box centre to the origin, longest side to 1 (a copy of the same kind).

    Raises:
        ValueError: On an empty or degenerate mesh.
    """
    vertices = np.asarray(mesh.vertices, np.float64)
    if len(vertices) == 0 or len(mesh.faces) == 0:
        raise ValueError("cannot normalise an empty mesh")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    ext = float(np.max(hi - lo))
    if not np.isfinite(ext) or ext <= 0:
        raise ValueError(f"degenerate mesh bounds {[lo.tolist(), hi.tolist()]}")
    if isinstance(mesh, MeshArrays):
        return MeshArrays((vertices - (lo + hi) / 2.0) / ext, np.asarray(mesh.faces, np.int64))
    out = mesh.copy()
    out.apply_translation(-(lo + hi) / 2.0)
    out.apply_scale(1.0 / ext)
    return out


class _MeshQueries:
    """Signed distance and ray casting of one normalised mesh: open3d's RaycastingScene (``backend="open3d"``)
    or `efem_viz.geometry.raycast` in torch on ``device`` (``backend="torch"``)."""

    def __init__(self, mesh: trimesh.Trimesh | MeshArrays, *, backend: Literal["open3d", "torch"],
                 device: str = "cpu") -> None:
        self.backend = backend
        vertices = np.asarray(mesh.vertices, np.float32)
        faces = np.asarray(mesh.faces, np.int64)
        if backend == "open3d":
            import open3d as o3d

            from efem_viz._typeshims import o3d_tensor

            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d_tensor(vertices), o3d_tensor(faces.astype(np.uint32)))
        else:
            import torch

            self.device = torch.device(device)
            self.budget = 1 << (26 if self.device.type == "cuda" else 22)
            self.vertices = torch.as_tensor(vertices, device=self.device)
            self.faces = torch.as_tensor(faces, device=self.device)

    def signed_distance(self, pts: np.ndarray) -> np.ndarray:
        """(P,) float32 signed distance of (P, 3) points (negative inside)."""
        if self.backend == "open3d":
            from efem_viz._typeshims import o3d_tensor

            return self.scene.compute_signed_distance(o3d_tensor(pts.astype(np.float32))).numpy().astype(np.float32)
        import torch

        from efem_viz.geometry.raycast import signed_distance

        p = torch.as_tensor(np.asarray(pts, np.float32), device=self.device)
        return signed_distance(self.vertices, self.faces, p, budget=self.budget).cpu().numpy().astype(np.float32)

    def depth_view(self, eye: np.ndarray, cfg: PrepConfig) -> tuple[np.ndarray, np.ndarray]:
        """Hits of a pinhole view from ``eye`` towards the origin: (n, 3) points and (n,) |cos| of incidence."""
        import torch

        from efem_viz.geometry.raycast import cast_rays, pinhole_rays

        if self.backend == "open3d":
            from efem_viz._typeshims import o3d_tensor

            o, d = pinhole_rays(torch.as_tensor(eye, dtype=torch.float32), fov_deg=cfg.fov_deg,
                                resolution=cfg.resolution)
            r = torch.cat([o, d], dim=1).numpy()
            ans = self.scene.cast_rays(o3d_tensor(r))
            t = ans["t_hit"].numpy().reshape(-1)
            nrm = ans["primitive_normals"].numpy().reshape(-1, 3)
        else:
            o, d = pinhole_rays(torch.as_tensor(eye, dtype=torch.float32, device=self.device),
                                fov_deg=cfg.fov_deg, resolution=cfg.resolution)
            tt, nn = cast_rays(self.vertices, self.faces, o, d, budget=self.budget)
            t, nrm = tt.cpu().numpy(), nn.cpu().numpy()
            r = torch.cat([o, d], dim=1).cpu().numpy()
        hit = np.isfinite(t)
        pts = r[hit, :3] + r[hit, 3:] * t[hit, None]
        dirs = r[hit, 3:] / np.maximum(np.linalg.norm(r[hit, 3:], axis=1, keepdims=True), 1e-12)
        return pts, np.abs((dirs * nrm[hit]).sum(1))


def prep_backend(device: str = "cpu") -> Literal["open3d", "torch"]:
    """Which `_MeshQueries` backend prepares data on ``device``: open3d on a CPU that has it, else torch."""
    if device != "cpu":
        return "torch"
    try:
        import open3d  # noqa: F401
    except ImportError:
        return "torch"
    return "open3d"


def _view_elevations(cfg: PrepConfig, rng: np.random.Generator) -> np.ndarray:
    n_rest = cfg.n_views - cfg.n_top_views
    n_side = (n_rest + 1) // 2
    top = rng.uniform(30.0, 60.0, cfg.n_top_views)
    side = rng.uniform(-10.0, 30.0, n_side)
    below = rng.uniform(-60.0, -10.0, n_rest - n_side)
    return np.concatenate([top, side, below])


def render_views(mesh: trimesh.Trimesh | MeshArrays, cfg: PrepConfig, *, rng: np.random.Generator,
                 queries: _MeshQueries | None = None, details: dict[str, Any] | None = None
                 ) -> tuple[list[np.ndarray], np.ndarray]:
    """Ray-cast depth views and back-project the hits (canonical frame).

    Args:
        mesh: Normalised mesh.
        cfg: Camera settings.
        rng: Random generator (azimuths, elevations, distances, subsets).
        queries: Optional prebuilt mesh queries (default: the CPU's backend for ``mesh``).
        details: If given, filled with ``eyes`` ((n_views, 3) camera centres) and ``cos`` (list of (n_i,)
            |cos| of the incidence angle of every kept hit).

    Returns:
        (list of (n_i, 3) float32 hit points per view, (n_views,) elevations in degrees).
    """
    queries = queries if queries is not None else _MeshQueries(mesh, backend=prep_backend())
    elev = _view_elevations(cfg, rng)
    out = []
    eyes, coss = [], []
    for e in elev:
        az = rng.uniform(0.0, 2.0 * np.pi)
        d = rng.uniform(*cfg.distance)
        el = np.deg2rad(e)
        eye = d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        pts, cos = queries.depth_view(eye.astype(np.float32), cfg)
        if len(pts) > cfg.max_view_points:
            keep = rng.choice(len(pts), cfg.max_view_points, replace=False)
            pts, cos = pts[keep], cos[keep]
        out.append(pts.astype(np.float32))
        eyes.append(eye)
        coss.append(cos.astype(np.float32))
    if details is not None:
        details["eyes"] = np.asarray(eyes, np.float32).reshape(-1, 3)
        details["cos"] = coss
    return out, elev.astype(np.float32)


def prepare_object(mesh: trimesh.Trimesh | MeshArrays, *, name: str, cfg: PrepConfig, seed: int,
                   device: str = "cpu", backend: Literal["auto", "open3d", "torch"] = "auto") -> ObjectData:
    """Normalise a watertight mesh and compute its SDF queries, surface samples and depth views.

    Args:
        mesh: Watertight mesh, +Z up, any scale (a trimesh or `MeshArrays`).
        name: Object name.
        cfg: Sampling sizes.
        seed: Seed of all sampling (the same data on every backend and device, to float rounding).
        device: Where the mesh queries run ("cpu": open3d if installed, else torch; "cuda": torch on the GPU).
        backend: "auto" (`prep_backend`), or force "open3d" / "torch".

    Returns:
        ``ObjectData``.

    Raises:
        ValueError: If the mesh is empty or no depth view hits it.
    """
    from efem_viz.geometry.sampling import sample_surface

    rng = np.random.default_rng(seed)
    m = normalize_mesh(mesh)
    queries = _MeshQueries(m, backend=prep_backend(device) if backend == "auto" else backend, device=device)
    uni = rng.uniform(-0.55, 0.55, (cfg.n_uniform, 3)).astype(np.float32)
    surf = sample_surface(m, cfg.n_surface + cfg.n_near, seed=int(rng.integers(2**31)), empty="raise")
    surf_pts = np.asarray(surf.points, np.float32)
    base = surf_pts[cfg.n_surface:]
    sig = np.asarray(cfg.near_sigmas, np.float32)[np.arange(cfg.n_near) % len(cfg.near_sigmas)]
    nss = (base + rng.normal(size=base.shape).astype(np.float32) * sig[:, None]).astype(np.float32)
    det: dict[str, Any] = {}
    views, elev = render_views(m, cfg, rng=rng, queries=queries, details=det)
    if sum(len(v) for v in views) == 0:
        raise ValueError(f"object {name}: no depth view hits the mesh")
    offsets = np.concatenate([[0], np.cumsum([len(v) for v in views])]).astype(np.int64)
    return ObjectData(
        name=name,
        uni=np.concatenate([uni, queries.signed_distance(uni)[:, None]], axis=1),
        nss=np.concatenate([nss, queries.signed_distance(nss)[:, None]], axis=1),
        surface=surf_pts[:cfg.n_surface],
        views=np.concatenate(views, axis=0),
        view_offsets=offsets,
        view_elev_deg=elev,
        view_eyes=det["eyes"],
        view_cos=np.concatenate(det["cos"]) if det["cos"] else np.zeros(0, np.float32),
    )


def _save_npz_atomic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    from efem_viz.data.io import atomic_write

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to a bare name
            # cast: numpy's stub would take a **dict[str, ndarray] to possibly fill `allow_pickle: bool`
            np.savez(f, **cast("dict[str, Any]", arrays))

    atomic_write(path, write)


def load_or_prepare(source: tuple[str, Callable[[], trimesh.Trimesh | MeshArrays]], *, cache_dir: Path,
                    cfg: PrepConfig, seed: int, device: str = "cpu") -> ObjectData:
    """The cached ``ObjectData`` of ``source`` (name, mesh factory); computed (on ``device``, see
    `prepare_object`) and cached if needed."""
    name, factory = source
    key = hashlib.sha1(json.dumps([CACHE_VERSION, dataclasses.asdict(cfg), seed]).encode()).hexdigest()[:10]
    path = cache_dir / f"{name}_{key}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                return ObjectData(name=name, **{k: z[k] for k in _CACHE_KEYS})
        except (OSError, KeyError, ValueError) as exc:
            log.warning("ignoring unreadable cache %s (%s)", path, exc)
    obj = prepare_object(factory(), name=name, cfg=cfg, seed=seed, device=device)
    _save_npz_atomic(path, {k: getattr(obj, k) for k in _CACHE_KEYS})
    return obj


def procedural_sources(category: str, split: str, n: int, *, handled_only: bool = False
                       ) -> list[tuple[str, Callable[[], trimesh.Trimesh]]]:
    """(name, mesh factory) for the first ``n`` objects of a procedural split: of one category, or of a training
    family (``procedural.FAMILIES``, e.g. "kitchen": its members interleaved, ``procedural.family_seeds``), named
    ``<category>_<seed>``. ``handled_only``: of the mugs with a handle only, as every ShapeNet mug of the paper has
    one (about 15 % of the procedural mugs are handle-less cups)."""
    from efem_viz.data.procedural import family_seeds, make_shape, sample_mug_params, split_seeds

    if handled_only:
        if category != "mug":
            raise ValueError(f"handled_only applies to mugs, not {category!r}")
        kept: list[tuple[str, int]] = []
        for s in split_seeds(category, split):  # type: ignore[arg-type]  # only as far as needed: a few ms each
            if len(kept) >= n:
                break
            if sample_mug_params(s).handle != "none":
                kept.append(("mug", s))
        if n > len(kept):
            raise ValueError(f"split {split!r} of {category!r} has {len(kept)} seeds with a handle, asked for {n}")
        items = kept
    else:
        items = family_seeds(category, split, n)  # type: ignore[arg-type]
    return [(f"{c}_{s:06d}", (lambda c=c, s=s: make_shape(c, s))) for c, s in items]


MESH_PACK_FORMAT = "efem-viz mesh pack 1"
MAX_PACK_VERTICES = 50_000_000
"""Refuse packs declaring more vertices (or faces) than this: bounded memory for a hostile file."""


def save_mesh_pack(sources: Sequence[tuple[str, Callable[[], trimesh.Trimesh | MeshArrays]]], path: Path, *,
                   on_item: Callable[[int, int], None] | None = None) -> Path:
    """Write the normalised meshes of ``sources`` into one compressed npz (vertices float32, faces int32).

    The pack carries a training set to a machine without trimesh or open3d (`pack_sources` reads it there);
    vertices are stored normalised (`normalize_mesh`), so preparing from the pack normalises to the same mesh.

    Returns:
        ``path``.
    """
    names, verts, faces, v_off, f_off = [], [], [], [0], [0]
    for i, (name, factory) in enumerate(sources):
        m = normalize_mesh(factory())
        names.append(name)
        verts.append(np.asarray(m.vertices, np.float32))
        faces.append(np.asarray(m.faces, np.int32))
        v_off.append(v_off[-1] + len(verts[-1]))
        f_off.append(f_off[-1] + len(faces[-1]))
        if on_item is not None:
            on_item(i + 1, len(sources))
    arrays = {"format": np.array(MESH_PACK_FORMAT), "names": np.array(names),
              "vertices": np.concatenate(verts) if verts else np.zeros((0, 3), np.float32),
              "faces": np.concatenate(faces) if faces else np.zeros((0, 3), np.int32),
              "vertex_offsets": np.asarray(v_off, np.int64), "face_offsets": np.asarray(f_off, np.int64)}
    from efem_viz.data.io import atomic_write

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **cast("dict[str, Any]", arrays))

    atomic_write(Path(path), write)
    return Path(path)


def pack_sources(path: Path) -> list[tuple[str, Callable[[], MeshArrays]]]:
    """(name, mesh factory) for every mesh of a mesh pack written by `save_mesh_pack`.

    Raises:
        FileNotFoundError: If the file does not exist.
        ValueError: If it is not a valid mesh pack (one line saying what is wrong).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh pack not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "format" not in z.files or str(z["format"]) != MESH_PACK_FORMAT:
                raise ValueError("not an efem-viz mesh pack (no or another 'format')")
            v_off, f_off = np.asarray(z["vertex_offsets"], np.int64), np.asarray(z["face_offsets"], np.int64)
            names = [str(n) for n in np.asarray(z["names"]).reshape(-1)]
            if (len(v_off) != len(names) + 1 or len(f_off) != len(names) + 1 or v_off[0] != 0 or f_off[0] != 0
                    or np.any(np.diff(v_off) < 1) or np.any(np.diff(f_off) < 1)
                    or v_off[-1] > MAX_PACK_VERTICES or f_off[-1] > MAX_PACK_VERTICES):
                raise ValueError(f"inconsistent offsets for {len(names)} meshes")
            vertices = np.asarray(z["vertices"], np.float32)
            faces = np.asarray(z["faces"], np.int64)
    except (OSError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: unreadable mesh pack ({type(exc).__name__}: {exc})") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if vertices.shape != (v_off[-1], 3) or faces.shape != (f_off[-1], 3) or not np.isfinite(vertices).all():
        raise ValueError(f"{path}: vertex/face arrays do not match their offsets or hold non-finite values")
    out: list[tuple[str, Callable[[], MeshArrays]]] = []
    for i, name in enumerate(names):
        v = vertices[v_off[i]:v_off[i + 1]]
        f = faces[f_off[i]:f_off[i + 1]]
        if int(f.min()) < 0 or int(f.max()) >= len(v):
            raise ValueError(f"{path}: mesh {name!r} has face indices outside its {len(v)} vertices")
        out.append((name, (lambda v=v, f=f: MeshArrays(v.copy(), f.copy()))))
    return out


def folder_sources(folder: Path) -> list[tuple[str, Callable[[], trimesh.Trimesh]]]:
    """(name, mesh factory) for every mesh file in ``folder`` (sorted by name).

    Raises:
        FileNotFoundError: If the folder does not exist.
        ValueError: If it holds no mesh files.
    """
    import trimesh as tm

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"mesh folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise ValueError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) in {folder}")

    def load(p: Path) -> tm.Trimesh:
        m = tm.load(p, force="mesh")
        if not isinstance(m, tm.Trimesh) or len(m.faces) == 0:
            raise ValueError(f"{p} holds no triangle mesh")
        if not m.is_watertight:
            log.warning("%s is not watertight: its SDF signs may be wrong", p)
        return m

    return [(p.stem, (lambda p=p: load(p))) for p in files]


# ---------------------------------------------------------------------------------------------- examples
def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def input_cloud(obj: ObjectData, cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    """Partial input cloud: union of 4..12 views (with replacement), ``n_pcl`` points, Gaussian noise.

    Returns:
        (n_pcl, 3) float32, canonical frame.
    """
    n_all = len(obj.view_offsets) - 1
    n_top = int(np.sum(obj.view_elev_deg >= 30.0 - 1e-3))
    pool = n_top if (n_top > 0 and rng.random() < cfg.p_top_only) else n_all
    n_v = int(rng.integers(min(cfg.min_views, n_all), n_all + 1))
    ids = rng.integers(0, pool, n_v)
    pts = np.concatenate([obj.view(int(i)) for i in ids], axis=0)
    if len(pts) == 0:
        pts = obj.surface
    sel = rng.integers(0, len(pts), cfg.n_pcl)
    return (pts[sel] + rng.normal(0.0, cfg.noise_std, (cfg.n_pcl, 3))).astype(np.float32)


SensorKind = Literal["kinect", "realsense", "isotropic"]
SENSOR_KINDS: tuple[SensorKind, ...] = ("kinect", "realsense", "isotropic")


@dataclass(frozen=True)
class SensorModel:
    """Depth noise of an RGB-D camera, in metres (one home: training inputs and the stability bench).

    ``kinect``: axial σ_z = k·(1.2 + 1.9 (z − 0.4)²) mm plus an incidence term 0.1 mm/√z · θ²/(π/2 − θ)²
    (Nguyen, Izadi, Lovell 2012). ``realsense``: σ_z = k·3.7 z² mm (D435 RMS, Intel's D400 tuning guide) plus
    the same incidence term. Both: depth quantised to ``quant_px`` of disparity (Δz = z²·q/(f·B)), lateral
    jitter of ``jitter_px`` pixels, dropout of hits at grazing incidence beyond ``grazing_deg``.
    ``isotropic``: Gaussian noise of σ = k mm on every axis (nothing else).
    """

    kind: SensorKind = "realsense"
    k: float = 1.0
    """Multiplier of the noise model (isotropic: σ in mm)."""
    fx: float = 600.0
    """Focal length, pixels."""
    baseline: float | None = None
    """Stereo / projector baseline in metres (None: 0.075 kinect, 0.05 realsense)."""
    quant_px: float = 1.0 / 8.0
    """Disparity quantisation step, pixels (0: none)."""
    jitter_px: float = 0.5
    """Lateral jitter, pixels."""
    grazing_deg: float = 75.0
    """Incidence angle above which hits start to drop out (all gone at 90°)."""

    def axial_sigma(self, z: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Axial noise std (metres) at depth ``z`` (metres) and incidence angle ``theta`` (radians)."""
        z = np.maximum(np.asarray(z, np.float64), 0.05)
        th = np.clip(np.asarray(theta, np.float64), 0.0, np.deg2rad(80.0))  # beyond: dropped mostly
        base = 1.2 + 1.9 * (z - 0.4) ** 2 if self.kind == "kinect" else 3.7 * z * z
        inc = 0.1 / np.sqrt(z) * th * th / (np.pi / 2 - th) ** 2
        return self.k * (base + inc) * 1e-3

    def apply(self, pts: np.ndarray, eye: np.ndarray, cos: np.ndarray | None,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Noisy measurement of exact hits ``pts`` (n, 3, metres) seen from camera centre ``eye`` (3,).

        Args:
            pts: Exact surface hits, metres.
            eye: Camera centre, metres (the optical axis points from it to the hits' centroid).
            cos: (n,) |cos| of each hit's incidence angle (None: 1).
            rng: Random generator.

        Returns:
            (m, 3) noisy points (float64) and the (n,) bool mask of the hits that were kept (not dropped).
        """
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        n = len(pts)
        if n == 0:
            return pts, np.zeros(0, bool)
        if self.kind == "isotropic":
            return pts + rng.normal(0.0, self.k * 1e-3, pts.shape), np.ones(n, bool)
        c = np.ones(n) if cos is None else np.clip(np.asarray(cos, np.float64).reshape(-1), 0.0, 1.0)
        theta = np.arccos(c)
        keep = rng.random(n) >= np.clip((np.rad2deg(theta) - self.grazing_deg) / (90.0 - self.grazing_deg),
                                        0.0, 1.0)
        pts, theta = pts[keep], theta[keep]
        eye = np.asarray(eye, np.float64).reshape(3)
        ray = pts - eye
        rng_d = np.linalg.norm(ray, axis=1, keepdims=True)
        u = ray / np.maximum(rng_d, 1e-12)
        axis = pts.mean(0) - eye
        axis /= max(float(np.linalg.norm(axis)), 1e-12)
        z = ray @ axis
        cos_ax = np.maximum(u @ axis, 0.2)
        zn = z + rng.normal(0.0, 1.0, len(z)) * self.axial_sigma(z, theta)
        base = self.baseline if self.baseline is not None else (0.075 if self.kind == "kinect" else 0.05)
        if self.quant_px > 0:
            step = np.maximum(zn, 0.05) ** 2 * self.quant_px / (self.fx * base)
            phase = rng.random()  # where the quantisation levels sit
            zn = (np.round(zn / step + phase) - phase) * step
        out = pts + u * ((zn - z) / cos_ax)[:, None]
        if self.jitter_px > 0:
            lat = rng.normal(0.0, 1.0, out.shape) * (self.jitter_px * np.maximum(z, 0.05) / self.fx)[:, None]
            lat -= (lat * u).sum(1, keepdims=True) * u  # perpendicular to the ray
            out = out + lat
        return out, keep


def random_sensor(cfg: SampleConfig, rng: np.random.Generator) -> SensorModel:
    """A randomised Kinect-class or RealSense-class sensor (``cfg``'s ranges)."""
    kind: SensorKind = "kinect" if rng.random() < 0.5 else "realsense"
    return SensorModel(kind=kind, k=float(rng.uniform(*cfg.sensor_scale)), fx=float(rng.uniform(*cfg.sensor_fx)))


def sensor_cloud(obj: ObjectData, cfg: SampleConfig, rng: np.random.Generator, *,
                 sensor: SensorModel | None = None, n_views: int | None = None,
                 distance: float | None = None, size: float | None = None) -> np.ndarray:
    """Partial input cloud as a depth sensor sees the object (canonical frame, ``n_pcl`` points).

    Mostly one or two views (``p_few_views``), each measured by ``sensor`` (default: `random_sensor`) from a
    camera ``distance`` metres away (default: ``sensor_distance``) along the cached view's direction, the
    object ``size`` metres long (default: ``object_size``); then ``density`` visible points are kept and
    ``n_pcl`` drawn from them with replacement, as the solver's M-step draws.

    Deviation: the hits come from the cached ray-cast views (camera 0.9-1.3 object sizes away), so the
    visible part is that of a close camera; the noise is that of the metric camera distance.
    """
    n_all = len(obj.view_offsets) - 1
    n_top = int(np.sum(obj.view_elev_deg >= 30.0 - 1e-3))
    pool = n_top if (n_top > 0 and rng.random() < cfg.p_top_only) else n_all
    if n_views is None:
        n_views = int(rng.integers(1, 3)) if rng.random() < cfg.p_few_views else int(rng.integers(3, n_all + 1))
    sensor = sensor if sensor is not None else random_sensor(cfg, rng)
    size = float(size if size is not None else rng.uniform(*cfg.object_size))
    outs: list[np.ndarray] = []
    ids = rng.choice(pool, n_views, replace=False) if n_views <= pool else rng.integers(0, pool, n_views)
    for i in ids:
        pts = obj.view(int(i))
        if len(pts) == 0:
            continue
        lo, hi = int(obj.view_offsets[i]), int(obj.view_offsets[i + 1])
        cos = obj.view_cos[lo:hi] if obj.view_cos is not None and len(obj.view_cos) >= hi else None
        if obj.view_eyes is not None and len(obj.view_eyes) > i:
            direction = np.asarray(obj.view_eyes[i], np.float64)
        else:
            el = np.deg2rad(float(obj.view_elev_deg[i]))
            direction = np.array([np.cos(el), 0.0, np.sin(el)])
        direction /= max(float(np.linalg.norm(direction)), 1e-12)
        d = float(distance if distance is not None else rng.uniform(*cfg.sensor_distance))
        noisy, _ = sensor.apply(pts * size, direction * d, cos, rng)
        outs.append(noisy / size)
    pts_all = np.concatenate(outs, axis=0) if outs else np.zeros((0, 3))
    if len(pts_all) == 0:
        pts_all = obj.surface.astype(np.float64)
    m = int(rng.integers(cfg.density[0], cfg.density[1] + 1))
    if len(pts_all) > m:
        pts_all = pts_all[rng.choice(len(pts_all), m, replace=False)]
    return pts_all[rng.integers(0, len(pts_all), cfg.n_pcl)].astype(np.float32)


def _remove_balls(pcl: np.ndarray, n_remove: int, cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    keep = np.ones(len(pcl), bool)
    removed = 0
    while removed < n_remove:
        alive = np.flatnonzero(keep)
        anchor = pcl[alive[rng.integers(len(alive))]]
        d2 = ((pcl[alive] - anchor) ** 2).sum(-1) + rng.normal(0.0, cfg.ball_noise, len(alive))
        k = min(cfg.ball_max_k, n_remove - removed, len(alive))
        keep[alive[np.argpartition(d2, k - 1)[:k]]] = False
        removed += k
    return keep


def _object_crops(n_obj: int, pcl: np.ndarray, uni: np.ndarray, others: Sequence[ObjectData],
                  cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    crops: list[np.ndarray] = []
    total = 0
    for _ in range(64):
        if total >= n_obj:
            break
        other = others[int(rng.integers(len(others)))]
        pts = other.surface[rng.integers(0, len(other.surface), cfg.n_pcl)]
        r_crop = max(cfg.crop_radius[0] + rng.normal(0.0, cfg.crop_radius[1]), 0.01)
        anchor = pts[rng.integers(len(pts))]
        crop = pts[((pts - anchor) ** 2).sum(-1) <= r_crop * r_crop]
        crop = (crop - crop.mean(0)) * rng.uniform(*cfg.crop_scale)
        r = float(np.sqrt((crop ** 2).sum(-1).max()))
        centre = pcl[rng.integers(len(pcl))]
        for _ in range(100):
            centre = pcl[rng.integers(len(pcl))] + rng.normal(0.0, cfg.placement_std, 3)
            nearest = int(((uni[:, :3] - centre) ** 2).sum(-1).argmin())
            if uni[nearest, 3] > r:
                break
        crops.append(crop @ _random_rotation(rng).T + centre)
        total += len(crop)
    if not crops:
        return np.zeros((0, 3), np.float32)
    return np.concatenate(crops, axis=0)[:n_obj]


def _neighbour_part(n_obj: int, obj: ObjectData, pcl: np.ndarray, others: Sequence[ObjectData],
                    cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    """Up to ``n_obj`` points of a whole other object, randomly turned and scaled, slid towards this object from a
    random direction until it is within a random gap of its surface (never through it), cut to the ball that holds
    the input cloud with a margin: what a neighbour in a pile leaves in a proposal's neighbourhood."""
    from efem_viz._typeshims import cKDTree

    other = others[int(rng.integers(len(others)))]
    pts = other.surface[rng.integers(0, len(other.surface), max(4 * n_obj, 512))].astype(np.float64)
    pts = (pts - pts.mean(0)) @ _random_rotation(rng).T * rng.uniform(0.8, 1.2)
    probe = pts[:256]  # the slide tests a subset against a subset of the surface: a few ms
    tree = cKDTree(obj.surface[rng.choice(len(obj.surface), min(len(obj.surface), 2048), replace=False)])
    d = rng.normal(size=3)
    d /= max(float(np.linalg.norm(d)), 1e-12)
    centre = pcl.mean(0).astype(np.float64)
    reach = float(np.sqrt(((pcl - centre) ** 2).sum(-1)).max()) * 1.1
    gap = rng.uniform(*cfg.neighbour_gap)
    step = 0.03
    t = reach + float(np.sqrt((probe ** 2).sum(-1)).max()) + step
    placed_t = None
    while t > 0.0:  # slide in from beyond the reach; stop before the first position within the gap
        if tree.query(probe + centre + t * d, k=1)[0].min() < gap:
            break
        placed_t = t
        t -= step
    if placed_t is None:
        return np.zeros((0, 3), np.float32)
    placed = pts + centre + placed_t * d
    inside = placed[((placed - centre) ** 2).sum(-1) <= reach * reach]
    if len(inside) > n_obj:
        inside = inside[rng.choice(len(inside), n_obj, replace=False)]
    return inside.astype(np.float32)


def _support_direction(cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    """Unit normal of a table patch, pointing from the plane to the object: +Z, or with probability
    ``p_table_any_side`` uniform on the sphere."""
    if cfg.p_table_any_side > 0 and rng.random() < cfg.p_table_any_side:
        d = rng.normal(size=3)
        return d / max(float(np.linalg.norm(d)), 1e-12)
    return np.array([0.0, 0.0, 1.0])


def _frame_with_z(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is the unit vector ``up`` (columns: an orthonormal basis)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, up)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1), up], axis=1)


def augment_v1(pcl: np.ndarray, obj: ObjectData, uni: np.ndarray, others: Sequence[ObjectData],
               cfg: SampleConfig, rng: np.random.Generator) -> np.ndarray:
    """Content augmentation "v1" (§2.3) with a table patch in place of the (unused for mugs) planes.

    Args:
        pcl: (N, 3) noisy object cloud.
        obj: The object (for its bottom height).
        uni: (Nq, 4) this example's uniform queries (crop placement test).
        others: Training objects to crop distractors from.
        cfg: Augmentation parameters.
        rng: Random generator.

    Returns:
        (N, 3) float32 augmented cloud (same size).
    """
    n = len(pcl)
    n_aug = int(rng.random() * int(cfg.aug_ratio * n))
    if n_aug == 0:
        return pcl
    use_obj = rng.random() <= cfg.p_obj and len(others) > 0
    use_table = rng.random() <= cfg.p_table
    use_ball = rng.random() <= cfg.p_ball
    if not (use_obj or use_table or use_ball):
        return pcl
    n_obj = n_table = n_noise = 0
    if use_obj and use_table:
        n_obj = int(rng.random() * n_aug)
        n_table = n_aug - n_obj
    elif use_obj:
        n_obj = n_aug
    elif use_table:
        n_table = n_aug
    else:
        n_noise = n_aug
    keep = np.ones(n, bool)
    n_ball = int(rng.random() * n_aug) if use_ball else 0
    if n_ball > 0:
        keep = _remove_balls(pcl, n_ball, cfg, rng)
    rest = n_aug - int((~keep).sum())
    if rest > 0:
        alive = np.flatnonzero(keep)
        keep[rng.choice(alive, rest, replace=False)] = False
    reduced = pcl[keep]
    added: list[np.ndarray] = []
    if n_obj > 0:
        if cfg.p_neighbour > 0 and rng.random() < cfg.p_neighbour:
            added.append(_neighbour_part(n_obj, obj, reduced, others, cfg, rng))
        else:
            added.append(_object_crops(n_obj, reduced, uni, others, cfg, rng))
    if n_table > 0:
        half = rng.uniform(*cfg.table_scale)
        c = rng.uniform(-0.2, 0.2, 2)
        uv = rng.uniform(-1.0, 1.0, (n_table, 2)) * half + c
        up = _support_direction(cfg, rng)
        height = float((obj.surface @ up).min())
        z = height + rng.normal(0.0, cfg.noise_std, n_table)
        patch = np.concatenate([uv, z[:, None]], axis=1)
        if up[2] != 1.0:
            patch = patch @ _frame_with_z(up).T
        added.append(patch)
    if n_noise > 0:
        added.append(rng.uniform(-0.5, 0.5, (n_noise, 3)))
    out = np.concatenate([*added, reduced], axis=0)
    if len(out) < n:  # crops can come up short: pad from the reduced cloud
        out = np.concatenate([out, reduced[rng.integers(0, len(reduced), n - len(out))]], axis=0)
    return out[:n].astype(np.float32)


def make_example(obj: ObjectData, cfg: SampleConfig, rng: np.random.Generator, *,
                 others: Sequence[ObjectData] = (), augment: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """One training example.

    Returns:
        ``pcl`` (n_pcl, 3) float32 input cloud and ``queries`` (Qu + Qn, 4) float32 (uniform first, then
        near-surface).
    """
    uni = obj.uni[rng.integers(0, len(obj.uni), cfg.n_query_uniform)]
    nss = obj.nss[rng.integers(0, len(obj.nss), cfg.n_query_near)]
    if cfg.sensor_p > 0 and rng.random() < cfg.sensor_p:
        pcl = sensor_cloud(obj, cfg, rng)
    else:
        pcl = input_cloud(obj, cfg, rng)
    if augment:
        pcl = augment_v1(pcl, obj, uni, others, cfg, rng)
    return pcl, np.concatenate([uni, nss], axis=0)


def make_batch(objs: Sequence[ObjectData], cfg: SampleConfig, rng: np.random.Generator, *,
               others: Sequence[ObjectData] = (), augment: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Stack ``make_example`` over ``objs``: (B, n_pcl, 3) and (B, Q, 4) float32."""
    ex = [make_example(o, cfg, rng, others=others, augment=augment) for o in objs]
    return np.stack([e[0] for e in ex]), np.stack([e[1] for e in ex])
