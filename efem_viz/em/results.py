"""EFEM results: `Instances` (accepted objects) and `EMResult` (trace + instances + config), with IO.

`<scene>.efem.npz` holds the trace (`trace/...`), the instances (`instances/...`), the config as JSON, the
schema version, the scene name and its number of points. Exports: the ScanNet benchmark layout
(docs/design/efem-method.md §4.2) and a coloured PLY with the predicted instance as the per-vertex `instance` property.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from efem_viz.em.config import EMConfig
from efem_viz.data.io import RESULT_SUFFIX
from efem_viz.em.replay import TraceReplay
from efem_viz.em.rules import REVIEW_COLUMNS
from efem_viz.em.trace import EMTrace
from efem_viz.prior.config import CategorySettings

if TYPE_CHECKING:
    from efem_viz.geometry.transforms import Sim3
    from efem_viz.prior.config import PriorArg
    import trimesh

    from efem_viz.data.scene import Scene

logger = logging.getLogger(__name__)

RESULT_SCHEMA_VERSION = 1


def _offsets(lengths: list[int]) -> np.ndarray:
    out = np.zeros(len(lengths) + 1, np.int64)
    if lengths:
        np.cumsum(np.asarray(lengths, np.int64), out=out[1:])
    return out


def _split(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [values[int(offsets[i]) : int(offsets[i + 1])] for i in range(len(offsets) - 1)]


def confidence_mask(confidence: np.ndarray | Sequence[float], threshold: float) -> np.ndarray:
    """The one confidence-threshold rule of efem-viz: keep an instance when its confidence ≥ `threshold`.

    Args:
        confidence: (K,) confidences.
        threshold: the threshold (the viewer's slider, `--threshold` of the exports, AP's operating point).

    Returns:
        (K,) bool.
    """
    return np.asarray(confidence, np.float64).reshape(-1) >= float(threshold)


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
        return cls.from_rows([])

    @classmethod
    def from_rows(cls, rows: list[dict[str, Any]], *, category: str = "object") -> "Instances":
        """Build from the solver's accepted review records (`ReviewRecord` fields plus "confidence",
        "stationary", "center", "scale" and "category"; `category` is used for rows without one)."""
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
            category=(np.array([str(r.get("category", category)) for r in rows], dtype=object).astype(str) if k
                      else np.zeros(0, dtype="<U1")),
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

    def transformed(self, sim: "Sim3") -> "Instances":
        """The instances in another frame, `x ↦ s R x + t` (e.g. a scan's own frame: `ScanFrame.to_scene.inverse()`):
        meshes, poses (R, centre, scale Θ_s) and boxes move with it; masks (point indices), confidences and scores
        are unchanged. Positions (mesh vertices, centres) come out in float64, so a georeferenced frame
        (coordinates of 10⁵-10⁷ m, `data.formats.las`) keeps its millimetres."""
        import dataclasses

        Rf, s = sim.R.astype(np.float32), np.float32(sim.scale)
        move = lambda x: float(sim.scale) * np.asarray(x, np.float64) @ sim.R.T + sim.t  # noqa: E731
        return dataclasses.replace(
            self,
            mesh_vertices=[move(v) for v in self.mesh_vertices],
            R=np.einsum("ij,kjl->kil", Rf, self.R).astype(np.float32),
            center=move(self.center).reshape(-1, 3),
            scale=(self.scale * s).astype(np.float32),
            obb_center=move(self.obb_center).reshape(-1, 3),
            obb_axes=np.einsum("ij,kjl->kil", Rf, self.obb_axes).astype(np.float32),
            obb_half_extents=(self.obb_half_extents * s).astype(np.float32),
        )

    def to_json_objects(self) -> list[dict[str, Any]]:
        """One JSON object per instance: category, confidence, pose (R, centre, scale Θ_s), oriented box and
        mask size, in the instances' frame."""
        return [{"index": k, "proposal_id": int(self.ids[k]), "category": str(self.category[k]),
                 "confidence": round(float(self.confidence[k]), 6), "points": int(len(self.masks[k])),
                 "R": np.round(self.R[k].astype(np.float64), 7).tolist(),
                 "center": np.round(self.center[k].astype(np.float64), 7).tolist(),
                 "scale": round(float(self.scale[k]), 7),
                 "obb": {"center": np.round(self.obb_center[k].astype(np.float64), 7).tolist(),
                         "axes": np.round(self.obb_axes[k].astype(np.float64), 7).tolist(),
                         "half_extents": np.round(self.obb_half_extents[k].astype(np.float64), 7).tolist()}}
                for k in range(len(self))]

    def export_objects(self, folder: str | os.PathLike[str], *, fmt: str = "glb", frame: str = "scene",
                       extra: dict[str, Any] | None = None) -> Path:
        """Write every instance's completed mesh (`<k>_<category>.glb|obj|ply`) and `objects.json` (category,
        confidence, pose, box and mesh file per instance, plus `extra`) into `folder`; returns the JSON's path.

        Raises:
            ValueError: an unknown mesh format.
        """
        from efem_viz.data.io import atomic_write_bytes, atomic_write_text

        names = self.object_files(fmt)
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        objects = self.to_json_objects()
        for k, obj in enumerate(objects):
            name = names[k]
            data: Any = self.mesh(k).export(file_type=fmt)
            atomic_write_bytes(out / name, data if isinstance(data, bytes) else str(data).encode())
            obj["mesh"] = name
        return atomic_write_text(out / "objects.json", json.dumps(
            {**(extra or {}), "frame": frame, "instances": objects}, indent=1) + "\n")

    def object_files(self, fmt: str = "glb") -> list[str]:
        """The mesh file names `export_objects` writes, one per instance in order (`<k>_<category>.<fmt>`).

        Raises:
            ValueError: an unknown mesh format.
        """
        if fmt not in ("glb", "obj", "ply"):
            raise ValueError(f"unknown object mesh format {fmt!r}; use glb, obj or ply")
        return [f"{k:03d}_{''.join(c if c.isalnum() else '_' for c in str(self.category[k]))[:40]}.{fmt}"
                for k in range(len(self))]

    def above(self, threshold: float) -> "Instances":
        """Instances with confidence ≥ threshold (a view on the stored result; nothing is re-run)."""
        return self.select(confidence_mask(self.confidence, threshold))

    def kept(self, threshold: float) -> np.ndarray:
        """(K,) bool: which instances a confidence threshold keeps (see `confidence_mask`)."""
        return confidence_mask(self.confidence, threshold)

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
        """Write the ScanNet benchmark layout (docs/design/efem-method.md §4.2).

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
        from efem_viz.colors import result_colors
        from efem_viz.data.io import save_scene

        keep = self.kept(threshold)
        inst = self.select(keep)
        labels = inst.label_array(scene.num_points)
        pal = result_colors(self)[keep]  # the colours of the viewer and the annotator's import
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
    categories: tuple[CategorySettings, ...] = ()
    """The settings each prior of the solve ran with, in prior order (τ_out resolved); empty for results saved
    before multi-prior solves."""
    warnings: tuple[str, ...] = ()
    """What the run could not do as configured, in words (e.g. a recorded camera it could not use, so the
    free-space check was off); saved with the result, shown by the viewer."""
    replay: TraceReplay = field(default=cast("TraceReplay", None), repr=False, compare=False)
    """The trace bound to its scene and prior(s) (`run_em` and `load` bind what they have, `bind` the rest; not
    saved). Always set: a result built without one gets an unbound replay."""

    def __post_init__(self) -> None:
        if self.replay is None:
            self.replay = TraceReplay(self.trace)

    def bind(self, scene: "Scene | None" = None, prior: "PriorArg | None" = None) -> TraceReplay:
        """Bind the scene and/or prior(s) for replays (`result.replay.view(...)`); returns the replay.

        Raises:
            ValueError: the scene has another number of points than the run, or the wrong number of priors.
        """
        return self.replay.bind(scene, prior)

    def save(self, path: str | os.PathLike[str], *, compact: bool = False) -> Path:
        """Write `<scene>.efem.npz` (compressed, atomic). A directory path gets `<dir>/<scene>.efem.npz`.

        ``compact``: the trace's latents in float16 (`EMTrace.to_npz_dict`), for bundled or shared results."""
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
            "categories_json": np.array(json.dumps([c.to_dict() for c in self.categories])),
            "warnings_json": np.array(json.dumps(list(self.warnings))),
        }
        data.update(self.trace.to_npz_dict(compact=compact))
        data.update(self.instances.to_npz_dict())
        # cast: numpy's stub types savez's keywords as `allow_pickle: bool, **kwds: ArrayLike`, so it takes a
        # **dict[str, ndarray] to possibly fill `allow_pickle`; these keys are array names.
        kwds = cast("dict[str, Any]", data)
        return atomic_write(p, lambda t: np.savez_compressed(t, **kwds))

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, scene: "Scene | None" = None,
             prior: "PriorArg | None" = None) -> "EMResult":
        """Read a file written by `save`; optionally bind the scene and prior(s) for replays (`result.replay`).

        The file is checked before anything is built from it (`validate_result_arrays`): every key `save` writes is
        present, shapes and dtypes agree, confidences are finite and in [0, 1], and mask, face and proposal indices
        are in range.

        Args:
            path: a `<scene>.efem.npz` file.
            scene: the scene the result was computed on (its point count must equal the stored `num_points`).
            prior: the prior it ran with (for re-deriving weights and meshes).

        Raises:
            FileNotFoundError: missing file.
            ResultFileError: (a ValueError, naming the file) a directory, not an EFEM result, a corrupt archive
                (an array header that disagrees with its member's bytes is refused before numpy allocates), an
                unsupported schema version, a missing key or an inconsistent or out-of-range array; or `scene` has
                another number of points.
        """
        p = Path(path)
        data = _read_result_archive(p)
        num_points = validate_result_arrays(data, path=p)
        if scene is not None and scene.num_points != num_points:
            raise ResultFileError(f"{p} was computed on {num_points} points but scene {scene.name!r} has "
                                  f"{scene.num_points}")
        try:
            config = EMConfig.from_json(str(data["config_json"]))
        except (ValueError, TypeError, KeyError) as exc:  # JSONDecodeError is a ValueError
            raise ResultFileError(f"{p}: config_json is not a valid EMConfig: {exc}") from exc
        try:
            timings = json.loads(str(data["timings_json"]))
        except ValueError as exc:
            raise ResultFileError(f"{p}: timings_json is not valid JSON: {exc}") from exc
        if not isinstance(timings, dict):
            raise ResultFileError(f"{p}: timings_json must hold a JSON object, got {type(timings).__name__}")
        try:
            trace = EMTrace.from_npz_dict(data)
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            raise ResultFileError(f"{p}: unreadable trace: {_describe(exc)}") from exc
        n_props = int(len(trace.prop_episode))
        ids = np.asarray(data["instances/ids"])
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= n_props):
            raise ResultFileError(f"{p}: instance proposal ids span [{int(ids.min())}, {int(ids.max())}] but the "
                                  f"trace has {n_props} proposals")
        categories = _read_categories(data, p)
        warnings = _read_warnings(data, p)
        if not trace.prior_names and len(categories) == 1:  # a one-prior run saved before runs named their prior
            trace = dataclasses.replace(trace, prior_names=(categories[0].name,))
        return cls(
            trace=trace,
            instances=Instances.from_npz_dict(data),
            config=config,
            timings=timings,
            scene_name=str(data["scene_name"]),
            num_points=num_points,
            seed=_scalar_int(data["seed"], "seed", p),
            categories=categories,
            warnings=warnings,
            replay=TraceReplay(trace, scene, prior),
        )


class ResultFileError(ValueError):
    """A `<scene>.efem.npz` that cannot be used (not a result, missing keys, inconsistent or out-of-range arrays).

    The message names the file and the problem, and is meant for the user.
    """


def _read_result_archive(p: Path) -> dict[str, Any]:
    """The arrays of a result file that `EMResult.load` reads (required and optional keys), once the file is known
    to be an `.npz` EFEM result of this schema version with every required key; nothing else is checked yet.

    Raises:
        FileNotFoundError: missing file.
        ResultFileError: a directory, an unreadable or corrupt archive, not an EFEM result, another schema version,
            a missing key.
    """
    if not p.is_file():
        if p.is_dir():
            raise ResultFileError(f"{p} is a directory, not an EFEM result file")
        raise FileNotFoundError(f"EFEM result not found: {p}")
    _check_npz_headers(p)
    try:
        z = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ResultFileError(f"{p} is not a readable EFEM result (corrupt or truncated .npz?): "
                              f"{type(exc).__name__}") from exc
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ResultFileError(f"{p} is not an EFEM result file (a single array, not an .npz archive)")
    with z:
        try:
            kind = str(z["kind"]) if "kind" in z.files else None
            if kind != "efem-result":
                raise ResultFileError(f"{p} is not an EFEM result file (keys: {sorted(z.files)[:8]}...)")
            if "schema_version" not in z.files:
                raise ResultFileError(f"{p}: not a complete EFEM result: key 'schema_version' missing")
            ver = _scalar_int(z["schema_version"], "schema_version", p)
            if ver != RESULT_SCHEMA_VERSION:
                raise ResultFileError(
                    f"{p}: unsupported result schema_version {ver} (this build reads {RESULT_SCHEMA_VERSION})")
            missing = [k for k in REQUIRED_RESULT_KEYS if k not in z.files]
            if missing:
                raise ResultFileError(f"{p}: not a complete EFEM result: missing {', '.join(missing)}")
            wanted = set(REQUIRED_RESULT_KEYS) | set(OPTIONAL_RESULT_KEYS)
            return {k: z[k] for k in z.files if k in wanted}
        except ResultFileError:
            raise
        except MemoryError:
            raise
        except Exception as exc:  # zipfile, zlib and numpy raise many types on a corrupt member
            raise ResultFileError(f"{p}: a member of the result archive is unreadable (corrupt?): "
                                  f"{_describe(exc)[:300]} ({type(exc).__name__})") from exc


def _read_categories(data: Mapping[str, Any], p: Path) -> tuple[CategorySettings, ...]:
    """The per-category review settings a result was computed with (`categories_json`; none when absent).

    Raises:
        ResultFileError: not a JSON list of category settings.
    """
    if "categories_json" not in data:
        return ()
    try:
        raw = json.loads(str(data["categories_json"]))
        if not isinstance(raw, list):
            raise ValueError(f"a JSON list is expected, got {type(raw).__name__}")
        return tuple(CategorySettings.from_dict(c) for c in raw)
    except (ValueError, TypeError) as exc:
        raise ResultFileError(f"{p}: categories_json is not a list of category settings: {exc}") from exc


def _read_warnings(data: Mapping[str, Any], p: Path) -> tuple[str, ...]:
    """The run's warnings (`warnings_json`: at most 20 of at most 500 characters; results saved before it have
    none).

    Raises:
        ResultFileError: not a JSON list of strings.
    """
    if "warnings_json" not in data:  # results saved before it have none
        return ()
    try:
        raw_w = json.loads(str(data["warnings_json"]))
        if not isinstance(raw_w, list) or not all(isinstance(w, str) for w in raw_w):
            raise ValueError("a JSON list of strings is expected")
        return tuple(w[:500] for w in raw_w[:20])
    except ValueError as exc:
        raise ResultFileError(f"{p}: warnings_json is not a list of strings: {exc}") from exc


_INSTANCE_KEYS: tuple[str, ...] = (
    "ids", "confidence", "category", "R", "center", "scale", "obb_center", "obb_axes", "obb_half_extents",
    "coverage", "stationary", "db_sim", "masks", "masks_offsets", "mesh_vertices", "mesh_vertices_offsets",
    "mesh_faces", "mesh_faces_offsets",
)
_TRACE_SCALAR_KEYS: tuple[str, ...] = (
    "schema_version", "config_json", "num_points", "timings_json", "work_idx", "has_work_idx", "work_min_size",
)
REQUIRED_RESULT_KEYS: tuple[str, ...] = (
    "schema_version", "kind", "scene_name", "num_points", "seed", "config_json", "timings_json",
    *(f"instances/{k}" for k in _INSTANCE_KEYS),
    *(f"trace/{k}" for k in _TRACE_SCALAR_KEYS),
    *(f"trace/{k}" for k in EMTrace._ARRAY_FIELDS),
)
"""Every key `EMResult.save` writes (schema 1); `EMResult.load` refuses a file without one of them."""
OPTIONAL_RESULT_KEYS: tuple[str, ...] = (
    "categories_json", "warnings_json", "trace/reason_names_json", "trace/prior_names_json", "trace/prop_prior",
    *(f"trace/{col.trace}" for col in REVIEW_COLUMNS if col.optional),
)
"""Keys `EMResult.save` writes that older results lack. `load` reads these and the required keys only: any other
member of the archive is never inflated (a 5 MB result with an extra 2 GiB deflated member cost 2.2 GB)."""


def _check_npz_headers(p: Path) -> None:
    """Every array header of the archive agrees with the bytes its member holds, before numpy allocates for it
    (the scene reader's check, `efem_viz.data.npz_guard.check_npz_headers`, without its scene size limits)."""
    from efem_viz.data.npz_guard import check_npz_headers
    from efem_viz.data.scene import SceneError

    try:
        check_npz_headers(p, 1 << 40)
    except SceneError as exc:
        msg = str(exc)
        if "not a valid .npz" in msg:
            raise ResultFileError(f"{p} is not a readable EFEM result (corrupt or truncated .npz?): "
                                  f"{msg.split(': ', 1)[-1]}") from exc
        raise ResultFileError(msg) from exc


def _describe(exc: BaseException) -> str:
    """One line for an exception (a KeyError's repr'd key becomes "missing key 'k'")."""
    if isinstance(exc, KeyError) and exc.args:
        return f"missing key {exc.args[0]!r}"
    return " ".join(str(exc).split()) or type(exc).__name__


def _scalar_int(value: Any, key: str, path: Path) -> int:
    """The integer held by a 0-d (or 1-element) integer array; ResultFileError otherwise."""
    a = np.asarray(value)
    if a.size != 1 or a.dtype.kind not in "iu":
        raise ResultFileError(f"{path}: {key} must be one integer, got {a.dtype} array of shape {a.shape}")
    return int(a.reshape(()))


def validate_result_arrays(data: Mapping[str, Any], *, path: str | os.PathLike[str]) -> int:
    """Check the arrays of a `<scene>.efem.npz` (as read by `np.load`) before they are used.

    Checks the top-level scalars (`num_points` a non-negative integer equal to `trace/num_points`; the names and
    JSON texts strings) and the instances: every per-instance array has K rows and the documented trailing shape
    and dtype kind, the ragged offsets are (K+1,) non-decreasing from 0 to the length of their values, confidences
    are finite and in [0, 1], mask indices lie in [0, num_points), mesh faces index their own instance's vertices;
    and the trace's point indices (`rev_mask`, `episode_unavailable`, `work_idx`) lie in [0, num_points).

    Args:
        data: key -> array, with every key of `REQUIRED_RESULT_KEYS`.
        path: the file, for the messages.

    Returns:
        num_points.

    Raises:
        ResultFileError: (a ValueError) naming the file and the first problem found.
    """
    p = Path(path)
    num_points = _check_scalars(data, p)
    _check_instances(data, p, num_points)
    for key in ("rev_mask", "episode_unavailable", "work_idx"):
        a = np.asarray(data["trace/" + key])
        if a.size and (a.dtype.kind not in "iu" or int(a.min()) < 0 or int(a.max()) >= num_points):
            raise _fail(p, f"trace/{key} must hold point indices in [0, num_points = {num_points}), got "
                        f"{a.dtype} in [{a.min()}, {a.max()}]")
    return num_points


def _fail(p: Path, msg: str) -> ResultFileError:
    """The error for a result file `p` with problem `msg`."""
    return ResultFileError(f"{p}: {msg}")


def _check_scalars(data: Mapping[str, Any], p: Path) -> int:
    """Every required key present; names and JSON texts single strings; `num_points` (returned) a non-negative
    integer equal to `trace/num_points` (`validate_result_arrays`)."""
    missing = [k for k in REQUIRED_RESULT_KEYS if k not in data]
    if missing:
        raise _fail(p, f"not a complete EFEM result: missing {', '.join(missing)}")
    for key in ("scene_name", "config_json", "timings_json", "trace/config_json", "trace/timings_json"):
        a = np.asarray(data[key])
        if a.size != 1 or a.dtype.kind not in "US":
            raise _fail(p, f"{key} must be one string, got {a.dtype} array of shape {a.shape}")
    num_points = _scalar_int(data["num_points"], "num_points", p)
    if num_points < 0:
        raise _fail(p, f"num_points must be >= 0, got {num_points}")
    trace_n = _scalar_int(data["trace/num_points"], "trace/num_points", p)
    if trace_n != num_points:
        raise _fail(p, f"num_points {num_points} disagrees with trace/num_points {trace_n}")
    return num_points


_PER_INSTANCE: dict[str, tuple[tuple[int, ...], str, bool]] = {
    "confidence": ((), "f", False), "category": ((), "US", False), "R": ((3, 3), "f", False),
    "center": ((3,), "f", False), "scale": ((), "f", False), "obb_center": ((3,), "f", False),
    "obb_axes": ((3, 3), "f", False), "obb_half_extents": ((3,), "f", False),
    "coverage": ((), "f", True), "stationary": ((), "f", True), "db_sim": ((), "f", True),
}
"""The per-instance arrays of a result file: key -> (trailing shape, dtype kinds, may be empty instead of K rows)."""


def _check_instances(data: Mapping[str, Any], p: Path, num_points: int) -> None:
    """The instances of a result file: K rows of every per-instance array (`_PER_INSTANCE`), confidences finite
    and in [0, 1], mask indices in [0, num_points), mesh faces indexing their own instance's vertices
    (`validate_result_arrays`)."""
    g = lambda k: np.asarray(data["instances/" + k])  # noqa: E731
    ids = g("ids")
    if ids.ndim != 1 or ids.dtype.kind not in "iu":
        raise _fail(p, f"instances/ids must be (K,) integers, got {ids.dtype} {ids.shape}")
    k = int(len(ids))
    for key, (tail, kinds, may_be_empty) in _PER_INSTANCE.items():
        a = g(key)
        shapes = [(k, *tail)] + ([(0, *tail)] if may_be_empty else [])
        if a.shape not in shapes or a.dtype.kind not in kinds:
            raise _fail(p, f"instances/{key} must be {' or '.join(map(str, shapes))} ({kinds!r} dtype kind) for "
                        f"{k} instances, got {a.dtype} {a.shape}")
    conf = g("confidence").astype(np.float64)
    bad = np.flatnonzero(~(np.isfinite(conf) & (conf >= 0.0) & (conf <= 1.0)))
    if len(bad):
        raise _fail(p, f"instance {int(bad[0])} has confidence {conf[bad[0]]} (must be finite and in [0, 1]; "
                    f"{len(bad)} bad of {k})")
    masks, _ = _ragged(data, p, "masks", (), "iu", k=k)
    if len(masks) and (int(masks.min()) < 0 or int(masks.max()) >= num_points):
        raise _fail(p, f"mask point indices span [{int(masks.min())}, {int(masks.max())}], outside "
                    f"[0, num_points = {num_points})")
    _, v_off = _ragged(data, p, "mesh_vertices", (3,), "f", k=k)
    faces, f_off = _ragged(data, p, "mesh_faces", (3,), "iu", k=k)
    if len(faces):
        n_verts = np.repeat(np.diff(v_off), np.diff(f_off))[:, None]
        if (faces < 0).any() or (faces >= n_verts).any():
            raise _fail(p, "instances/mesh_faces index vertices outside their own instance's mesh")


def _ragged(data: Mapping[str, Any], p: Path, key: str, tail: tuple[int, ...], kinds: str, *,
            k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ragged per-instance array `instances/<key>` and its (k+1,) offsets, checked: values of trailing shape
    `tail` and a dtype kind in `kinds`, offsets non-decreasing from 0 to the number of values."""
    values, offs = np.asarray(data[f"instances/{key}"]), np.asarray(data[f"instances/{key}_offsets"])
    if values.shape[1:] != tail or values.ndim != 1 + len(tail) or values.dtype.kind not in kinds:
        want = "(n,)" if not tail else f"(n, {', '.join(map(str, tail))})"
        raise _fail(p, f"instances/{key} must be {want} ({kinds!r} dtype kind), got {values.dtype} {values.shape}")
    if offs.shape != (k + 1,) or offs.dtype.kind not in "iu":
        raise _fail(p, f"instances/{key}_offsets must be ({k + 1},) integers for {k} instances, got "
                    f"{offs.dtype} {offs.shape}")
    if int(offs[0]) != 0 or (np.diff(offs) < 0).any() or int(offs[-1]) != len(values):
        raise _fail(p, f"instances/{key}_offsets must rise from 0 to {len(values)} (the length of "
                    f"instances/{key}), got [{int(offs[0])} ... {int(offs[-1])}]")
    return values, offs
