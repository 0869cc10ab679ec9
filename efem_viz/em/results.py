"""EFEM results: `Instances` (accepted objects) and `EMResult` (trace + instances + config), with IO.

`<scene>.efem.npz` holds the trace (`trace/...`), the instances (`instances/...`), the config as JSON, the
schema version, the scene name and its number of points. Exports: the ScanNet benchmark layout
(efem-method.md §4.2) and a coloured PLY with the predicted instance as the per-vertex `instance` property.
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from efem_viz.em.config import EMConfig
from efem_viz.em.trace import EMTrace

if TYPE_CHECKING:
    import trimesh

    from efem_viz.data.scene import Scene

logger = logging.getLogger(__name__)

RESULT_SCHEMA_VERSION = 1
RESULT_SUFFIX = ".efem.npz"


def _offsets(lengths: list[int]) -> np.ndarray:
    out = np.zeros(len(lengths) + 1, np.int64)
    if lengths:
        np.cumsum(np.asarray(lengths, np.int64), out=out[1:])
    return out


def _split(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [values[int(offsets[i]) : int(offsets[i + 1])] for i in range(len(offsets) - 1)]


def _palette(k: int) -> np.ndarray:
    """(k, 3) uint8 distinct colours (golden-ratio hues)."""
    import colorsys

    out = np.zeros((k, 3), np.uint8)
    for i in range(k):
        h = (0.13 + i * 0.618033988749895) % 1.0
        r, g, b = colorsys.hsv_to_rgb(h, 0.75, 0.95)
        out[i] = (int(r * 255), int(g * 255), int(b * 255))
    return out


@dataclass(frozen=True)
class Instances:
    """Accepted objects of one scene (possibly overlapping masks), in acceptance order.

    Attributes:
        ids: (K,) int64 proposal ids (keys into the trace).
        masks: K arrays (n_k,) int32 scene-point indices.
        confidence: (K,) float32 s_stat · min(coverage, 0.4) / 0.4.
        category: (K,) str category (the prior's name).
        mesh_vertices: K arrays (V_k, 3) float32, world frame.
        mesh_faces: K arrays (F_k, 3) int32.
        R: (K, 3, 3) float32 pose, columns = canonical x, y, z axes in the world frame (proper rotations).
        center: (K, 3) float32 Θ_c, world.
        scale: (K,) float32 Θ_s.
        obb_center: (K, 3) float32 box centre, world.
        obb_axes: (K, 3, 3) float32 box axes (columns).
        obb_half_extents: (K, 3) float32 half side lengths (m).
        coverage: (K,) float32 coverage score of the last review.
        stationary: (K,) float32 stationary score of the last step.
        db_sim: (K,) float32 codebook similarity (NaN without a codebook).
    """

    ids: np.ndarray
    masks: list[np.ndarray]
    confidence: np.ndarray
    category: np.ndarray
    mesh_vertices: list[np.ndarray]
    mesh_faces: list[np.ndarray]
    R: np.ndarray
    center: np.ndarray
    scale: np.ndarray
    obb_center: np.ndarray
    obb_axes: np.ndarray
    obb_half_extents: np.ndarray
    coverage: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    stationary: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    db_sim: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    def __len__(self) -> int:
        return int(len(self.ids))

    @classmethod
    def empty(cls) -> "Instances":
        return cls.from_rows([], category="object")

    @classmethod
    def from_rows(cls, rows: list[dict[str, Any]], *, category: str) -> "Instances":
        """Build from the solver's accepted review records."""
        k = len(rows)

        def arr(key: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
            if not k:
                return np.zeros((0, *shape), dtype)
            return np.stack([np.asarray(r[key], dtype).reshape(shape) for r in rows])

        verts = [np.asarray(r["mesh_vertices"], np.float32) + np.asarray(r["center"], np.float32)
                 for r in rows]
        return cls(
            ids=np.array([int(r["proposal_id"]) for r in rows], np.int64),
            masks=[np.asarray(r["mask"], np.int32) for r in rows],
            confidence=np.array([r["confidence"] for r in rows], np.float32),
            category=np.array([category] * k, dtype=object).astype(str) if k else np.zeros(0, dtype="<U1"),
            mesh_vertices=verts,
            mesh_faces=[np.asarray(r["mesh_faces"], np.int32).reshape(-1, 3) for r in rows],
            R=arr("R", (3, 3), np.float32),
            center=arr("center", (3,), np.float32),
            scale=np.array([float(r["scale"]) for r in rows], np.float32),
            obb_center=arr("obb_center", (3,), np.float32),
            obb_axes=arr("obb_axes", (3, 3), np.float32),
            obb_half_extents=arr("obb_half_extents", (3,), np.float32),
            coverage=np.array([r["coverage"] for r in rows], np.float32),
            stationary=np.array([r["stationary"] for r in rows], np.float32),
            db_sim=np.array([r["db_sim"] for r in rows], np.float32),
        )

    # ------------------------------------------------------------------ views
    def select(self, keep: np.ndarray) -> "Instances":
        """The instances at the given positions (int array) or where a (K,) bool mask holds."""
        keep = np.asarray(keep)
        idx = np.flatnonzero(keep) if keep.dtype == bool else keep.astype(np.int64)
        return Instances(
            ids=self.ids[idx],
            masks=[self.masks[i] for i in idx],
            confidence=self.confidence[idx],
            category=self.category[idx],
            mesh_vertices=[self.mesh_vertices[i] for i in idx],
            mesh_faces=[self.mesh_faces[i] for i in idx],
            R=self.R[idx],
            center=self.center[idx],
            scale=self.scale[idx],
            obb_center=self.obb_center[idx],
            obb_axes=self.obb_axes[idx],
            obb_half_extents=self.obb_half_extents[idx],
            coverage=self.coverage[idx] if len(self.coverage) == len(self) else self.coverage,
            stationary=self.stationary[idx] if len(self.stationary) == len(self) else self.stationary,
            db_sim=self.db_sim[idx] if len(self.db_sim) == len(self) else self.db_sim,
        )

    def above(self, threshold: float) -> "Instances":
        """Instances with confidence ≥ threshold (a view on the stored result; nothing is re-run)."""
        return self.select(self.confidence >= float(threshold))

    def label_array(self, n_points: int) -> np.ndarray:
        """(N,) int32 per-point label: k + 1 for the k-th instance, 0 = none; on overlap the higher confidence
        wins (ties: the earlier instance)."""
        labels = np.zeros(int(n_points), np.int32)
        best = np.full(int(n_points), -np.inf, np.float64)
        for k in range(len(self)):
            m = self.masks[k]
            if len(m) and int(m.max()) >= n_points:
                raise ValueError(f"instance {k} has point index {int(m.max())} >= n_points {n_points}")
            better = self.confidence[k] > best[m]
            labels[m[better]] = k + 1
            best[m[better]] = self.confidence[k]
        return labels

    def bool_masks(self, n_points: int) -> list[np.ndarray]:
        """K dense (N,) bool masks."""
        out = []
        for m in self.masks:
            b = np.zeros(int(n_points), bool)
            b[m] = True
            out.append(b)
        return out

    def obb(self, k: int) -> Any:
        """The k-th instance's oriented box as an `efem_viz.geometry.obb.OBB` (corners, edges, contains, ...)."""
        from efem_viz.geometry.obb import BOX_CORNER_SIGNS, BOX_EDGES, OBB

        c = np.asarray(self.obb_center[k], np.float64)
        ax = np.asarray(self.obb_axes[k], np.float64)
        e = np.asarray(self.obb_half_extents[k], np.float64)
        return OBB(center=c, axes=ax, half_extents=e, corners=c + (BOX_CORNER_SIGNS * e) @ ax.T,
                   edges=BOX_EDGES.copy())

    def mesh(self, k: int) -> "trimesh.Trimesh":
        """The k-th instance's mesh (world frame)."""
        import trimesh

        return trimesh.Trimesh(self.mesh_vertices[k], self.mesh_faces[k], process=False)

    # ------------------------------------------------------------------ persistence
    def to_npz_dict(self, prefix: str = "instances/") -> dict[str, np.ndarray]:
        def flat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> tuple[np.ndarray, np.ndarray]:
            offs = _offsets([len(p) for p in parts])
            if not parts:
                return np.zeros((0, *shape), dtype), offs
            return np.concatenate([np.asarray(p, dtype).reshape(-1, *shape) for p in parts]).astype(dtype), offs

        mv, mv_off = flat(self.mesh_vertices, (3,), np.float32)
        mf, mf_off = flat(self.mesh_faces, (3,), np.int32)
        mk, mk_off = flat(self.masks, (), np.int32)
        return {
            prefix + "ids": self.ids,
            prefix + "confidence": self.confidence,
            prefix + "category": np.asarray(self.category, dtype=str),
            prefix + "R": self.R,
            prefix + "center": self.center,
            prefix + "scale": self.scale,
            prefix + "obb_center": self.obb_center,
            prefix + "obb_axes": self.obb_axes,
            prefix + "obb_half_extents": self.obb_half_extents,
            prefix + "coverage": self.coverage,
            prefix + "stationary": self.stationary,
            prefix + "db_sim": self.db_sim,
            prefix + "masks": mk,
            prefix + "masks_offsets": mk_off,
            prefix + "mesh_vertices": mv,
            prefix + "mesh_vertices_offsets": mv_off,
            prefix + "mesh_faces": mf,
            prefix + "mesh_faces_offsets": mf_off,
        }

    @classmethod
    def from_npz_dict(cls, data: Any, prefix: str = "instances/") -> "Instances":
        g = lambda k: np.asarray(data[prefix + k])  # noqa: E731
        return cls(
            ids=g("ids").astype(np.int64),
            masks=_split(g("masks"), g("masks_offsets")),
            confidence=g("confidence").astype(np.float32),
            category=g("category").astype(str),
            mesh_vertices=_split(g("mesh_vertices"), g("mesh_vertices_offsets")),
            mesh_faces=_split(g("mesh_faces"), g("mesh_faces_offsets")),
            R=g("R"),
            center=g("center"),
            scale=g("scale"),
            obb_center=g("obb_center"),
            obb_axes=g("obb_axes"),
            obb_half_extents=g("obb_half_extents"),
            coverage=g("coverage"),
            stationary=g("stationary"),
            db_sim=g("db_sim"),
        )

    # ------------------------------------------------------------------ exports
    def to_scannet(self, out_dir: str | os.PathLike[str], scene_name: str, n_points: int, *,
                   label_id: int = 1) -> Path:
        """Write the ScanNet benchmark layout (efem-method.md §4.2).

        `<out_dir>/<scene>.txt` lists one line per instance, `pred_mask/<scene>_<kkk>.txt <label_id> <conf>`
        (confidence with 4 decimals); each mask file under `<out_dir>/pred_mask/` holds N lines of 0/1.

        Returns:
            The path of `<scene>.txt`.
        """
        from efem_viz.data.io import atomic_write_text

        out = Path(out_dir)
        lines = []
        for k in range(len(self)):
            rel = f"pred_mask/{scene_name}_{k:03d}.txt"
            m = np.zeros(int(n_points), np.uint8)
            m[self.masks[k]] = 1
            atomic_write_text(out / rel, "\n".join("1" if v else "0" for v in m) + "\n")
            lines.append(f"{rel} {int(label_id)} {float(self.confidence[k]):.4f}")
        return atomic_write_text(out / f"{scene_name}.txt", "".join(line + "\n" for line in lines))

    def to_colored_ply(self, scene: "Scene", path: str | os.PathLike[str], *, threshold: float = 0.0) -> Path:
        """Save the scene as a PLY coloured by predicted instance (grey = none) with `instance` = label.

        Args:
            scene: the scene the instances belong to.
            path: destination `.ply`.
            threshold: only instances with confidence ≥ threshold are coloured.
        """
        from efem_viz.data.io import save_scene

        inst = self.above(threshold)
        labels = inst.label_array(scene.num_points)
        pal = _palette(len(inst))
        colors = (np.asarray(scene.colors).astype(np.float32) * 0.35 + 90).astype(np.uint8)
        sel = labels > 0
        colors[sel] = pal[labels[sel] - 1]
        cats = {k + 1: str(inst.category[k]) for k in range(len(inst))}
        out = scene.replace(colors=colors.astype(np.uint8), instance=labels, categories=cats)
        return save_scene(out, Path(path))


@dataclass
class EMResult:
    """What `run_em` returns: the trace, the accepted instances, the config and per-stage timings (s)."""

    trace: EMTrace
    instances: Instances
    config: EMConfig
    timings: dict[str, float]
    scene_name: str
    num_points: int
    seed: int = 0

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write `<scene>.efem.npz` (compressed, atomic). A directory path gets `<dir>/<scene>.efem.npz`."""
        from efem_viz.data.io import atomic_write

        p = Path(path)
        if p.is_dir() or not p.name.endswith(".npz"):
            p = p / f"{self.scene_name}{RESULT_SUFFIX}"
        data: dict[str, np.ndarray] = {
            "schema_version": np.array(RESULT_SCHEMA_VERSION, np.int32),
            "kind": np.array("efem-result"),
            "scene_name": np.array(self.scene_name),
            "num_points": np.array(self.num_points, np.int64),
            "seed": np.array(self.seed, np.int64),
            "config_json": np.array(self.config.to_json()),
            "timings_json": np.array(json.dumps(self.timings)),
        }
        data.update(self.trace.to_npz_dict())
        data.update(self.instances.to_npz_dict())
        # cast: numpy's stub types savez's keywords as `allow_pickle: bool, **kwds: ArrayLike`, so it takes a
        # **dict[str, ndarray] to possibly fill `allow_pickle`; these keys are array names.
        kwds = cast("dict[str, Any]", data)
        return atomic_write(p, lambda t: np.savez_compressed(t, **kwds))

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, scene: "Scene | None" = None, prior: Any = None) -> "EMResult":
        """Read a file written by `save`; optionally bind the scene and prior for `trace.view` replays.

        Raises:
            FileNotFoundError: missing file.
            ValueError: not an EFEM result, or an unsupported schema version.
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"EFEM result not found: {p}")
        try:
            z = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{p} is not a readable EFEM result (corrupt or truncated .npz?): "
                             f"{type(exc).__name__}") from exc
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"{p} is not an EFEM result file (a single array, not an .npz archive)")
        with z:
            if "kind" not in z.files or str(z["kind"]) != "efem-result":
                raise ValueError(f"{p} is not an EFEM result file (keys: {sorted(z.files)[:8]}...)")
            ver = int(z["schema_version"])
            if ver != RESULT_SCHEMA_VERSION:
                raise ValueError(
                    f"{p}: unsupported result schema_version {ver} (expected {RESULT_SCHEMA_VERSION})")
            try:
                data = {k: z[k] for k in z.files}
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
                raise ValueError(f"{p}: a member of the result archive is unreadable (corrupt?): "
                                 f"{type(exc).__name__}") from exc
        if scene is not None and scene.num_points != int(data["num_points"]):
            raise ValueError(f"{p} was computed on {int(data['num_points'])} points but scene {scene.name!r} has "
                             f"{scene.num_points}")
        trace = EMTrace.from_npz_dict(data)
        trace.bind(scene, prior)
        return cls(
            trace=trace,
            instances=Instances.from_npz_dict(data),
            config=EMConfig.from_json(str(data["config_json"])),
            timings=json.loads(str(data["timings_json"])),
            scene_name=str(data["scene_name"]),
            num_points=int(data["num_points"]),
            seed=int(data["seed"]),
        )
