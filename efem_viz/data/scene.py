"""The `Scene` data object: a scanned scene as points (or mesh vertices) with normals, colours and labels.

Frames: world frame, metres, +Z up (see docs/design/ARCHITECTURE.md). A scene with `faces` is a triangle mesh whose
vertices are `points`; without `faces` it is a point cloud.
"""

from __future__ import annotations

import dataclasses
import json
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping, cast, overload

import numpy as np

if TYPE_CHECKING:
    from efem_viz.geometry.normals import NormalsProgress

SCENE_SCHEMA_VERSION = 1
DEFAULT_MAX_POINTS = 5_000_000
"""Default limit on the number of points a scene may hold (configurable per call)."""
MAX_FACES_PER_POINT = 4
"""A file may declare at most this many faces per allowed point (`max_points`): a closed triangle mesh has about
2 faces per vertex, so only a corrupt or hostile header goes past 4 (checked before anything is allocated)."""
LIMIT_FLAG_HINT = "raise the limit with --max-points"
"""How a user raises the point limit: the option of the commands that read scenes (efem-viz view / info,
efem-annotate). Ends every "more than the limit" message."""
TOO_MANY_POINTS_HINT = f"downsample it, or {LIMIT_FLAG_HINT}"
"""The end of every "more points than the limit" message."""


class SceneError(ValueError):
    """Raised for invalid scene data or files, with a message meant for the user."""


class PendingNormals:
    """Normals not estimated yet: the inputs of `estimate_normals` for a scene, computed on first use.

    A `Scene` built without normals holds one of these until `scene.normals` (or `scene.compute_normals`) is
    read; then the estimate replaces it. Commands that never look at normals (`efem-viz info`) never pay for
    them. Picklable; the arrays are the scene's own (no copies).
    """

    __slots__ = ("points", "faces")

    def __init__(self, points: np.ndarray, faces: np.ndarray | None) -> None:
        """Args: points: (N, 3) float32, world frame. faces: (M, 3) int32 or None."""
        self.points = points
        self.faces = faces

    def __getstate__(self) -> tuple[np.ndarray, np.ndarray | None]:
        return self.points, self.faces

    def __setstate__(self, state: tuple[np.ndarray, np.ndarray | None]) -> None:
        self.points, self.faces = state

    def compute(self, on_progress: "NormalsProgress | None" = None) -> np.ndarray:
        """(N, 3) float32 unit normals: mesh vertex normals, or oriented PCA normals for a point cloud."""
        from efem_viz.geometry.normals import estimate_normals

        nrm = estimate_normals(self.points, faces=self.faces, on_progress=on_progress)
        return np.ascontiguousarray(nrm, dtype=np.float32)


_NORMALS_LOCK = threading.Lock()  # one estimate at a time (a viewer thread and the EM worker may both ask)


class _LazyNormals:
    """Data descriptor for `Scene.normals`: stores an array or a `PendingNormals`, always returns an array.

    Class access raises AttributeError, so the dataclass sees no default and the field stays a required
    positional argument, as before. The frozen dataclass's `__init__` sets the value through `__set__`;
    `scene.normals = x` still raises `FrozenInstanceError`.
    """

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> "_LazyNormals": ...
    @overload
    def __get__(self, obj: object, owner: type | None = None) -> np.ndarray: ...
    def __get__(self, obj: object | None, owner: type | None = None) -> "np.ndarray | _LazyNormals":
        if obj is None:
            raise AttributeError(self._name)  # no class-level default for the dataclass
        value = obj.__dict__[self._name]
        if isinstance(value, PendingNormals):
            value = _resolve_normals(obj, self._name, None)
        return value

    def __set__(self, obj: object, value: "np.ndarray | PendingNormals") -> None:
        obj.__dict__[self._name] = value


def _resolve_normals(obj: object, name: str, on_progress: "NormalsProgress | None") -> np.ndarray:
    """Estimate pending normals once (under a lock), store them on `obj` and return them."""
    with _NORMALS_LOCK:
        value = obj.__dict__[name]
        if isinstance(value, PendingNormals):
            value = value.compute(on_progress)
            obj.__dict__[name] = value
        return value


@dataclass(frozen=True)
class Scene:
    """A scanned scene: points (or mesh vertices) with normals, colours and optional ground truth.

    Construct through `Scene.create` (which validates and fills defaults) or `efem_viz.data.io.load_scene`.
    """

    name: str
    """Human-readable scene name (usually the file stem)."""
    points: np.ndarray
    """(N, 3) float32, world frame, metres, +Z up."""
    if TYPE_CHECKING:  # type checkers see a plain required field; at run time a descriptor fills it lazily
        normals: np.ndarray
    else:
        normals: np.ndarray = _LazyNormals()
    """(N, 3) float32 unit normals, oriented outward / toward the sensor. Estimated on first access when the
    scene was created without them (see `normals_pending`)."""
    colors: np.ndarray
    """(N, 3) uint8 RGB."""
    faces: np.ndarray | None = None
    """(M, 3) int32 triangle indices into `points`, or None for a point cloud."""
    instance: np.ndarray | None = None
    """(N,) int32 ground-truth instance id per point; 0 = unlabelled / background. None = no ground truth."""
    categories: Mapping[int, str] = field(default_factory=dict)
    """Instance id -> category name (e.g. {1: "mug"}), for the ids in `instance`."""
    up: str = "+z"
    """Up axis of the world frame; always "+z" after loading."""
    provenance: Mapping[str, Any] = field(default_factory=dict)
    """Where the scene came from (source file, generator config, seed, licence...). JSON-serialisable."""

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(
        cls,
        name: str,
        points: np.ndarray,
        *,
        normals: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        faces: np.ndarray | None = None,
        instance: np.ndarray | None = None,
        categories: Mapping[int, str] | None = None,
        provenance: Mapping[str, Any] | None = None,
        max_points: int = DEFAULT_MAX_POINTS,
    ) -> "Scene":
        """Validate arrays, convert dtypes, fill missing colours (grey); missing normals are estimated lazily.

        Args:
            name: scene name.
            points: (N, 3) float, world frame, metres.
            normals: (N, 3) float or None: then estimated on first access of `Scene.normals` (mesh vertex
                normals, or PCA normals oriented consistently; `efem_viz.geometry.normals.estimate_normals`).
            colors: (N, 3) uint8, or float in [0, 1], or None (grey).
            faces: (M, 3) int or None.
            instance: (N,) integer labels or None.
            categories: instance id -> category name.
            provenance: JSON-serialisable metadata.
            max_points: refuse scenes with more points than this.

        Raises:
            SceneError: empty, NaN/Inf, wrong shapes, mismatched lengths, non-integer labels, too many points.
        """
        pts = _as_points(points, "points")
        n = pts.shape[0]
        if n == 0:
            raise SceneError(f"scene {name!r} is empty (0 points)")
        if n > max_points:
            raise SceneError(
                f"scene {name!r} has {n:,} points, more than the limit of {max_points:,}; "
                f"{TOO_MANY_POINTS_HINT}"
            )
        if not np.isfinite(pts).all():
            bad = int((~np.isfinite(pts)).any(axis=1).sum())
            raise SceneError(f"scene {name!r}: {bad} of {n} points contain NaN or Inf coordinates")
        fcs = _as_faces(faces, n, name)
        pts32 = np.ascontiguousarray(pts, dtype=np.float32)
        nrm = PendingNormals(pts32, fcs) if normals is None else _as_normals(normals, n, name)
        col = _as_colors(colors, n, name)
        inst = None if instance is None else _as_instance(instance, n, name)
        if not isinstance(categories or {}, Mapping) or not isinstance(provenance or {}, Mapping):
            raise SceneError(f"scene {name!r}: categories and provenance must be mappings, got "
                             f"{type(categories).__name__} and {type(provenance).__name__}")
        cats = {int(k): str(v) for k, v in (categories or {}).items()}
        prov = dict(provenance or {})
        return cls(
            name=str(name),
            points=pts32,
            normals=cast(np.ndarray, nrm),  # a PendingNormals is resolved by the `normals` descriptor
            colors=col,
            faces=fcs,
            instance=inst,
            categories=cats,
            up="+z",
            provenance=prov,
        )

    # ------------------------------------------------------------------ normals
    @property
    def normals_pending(self) -> bool:
        """True while the normals are still to be estimated (the scene was created without them)."""
        return isinstance(self.__dict__["normals"], PendingNormals)

    def compute_normals(self, *, on_progress: "NormalsProgress | None" = None) -> np.ndarray:
        """The normals, estimating them now if pending, with progress reports (for a CLI progress line).

        Args:
            on_progress: called as `estimate_normals` documents: ("pca", points done, N), ("orient", step, 3).

        Returns:
            (N, 3) float32 unit normals, the same array `Scene.normals` returns from then on.
        """
        return _resolve_normals(self, "normals", on_progress)

    def _normals_or_none(self) -> np.ndarray | None:
        """The stored normals, or None while pending (copies then re-estimate them only if needed)."""
        value = self.__dict__["normals"]
        return None if isinstance(value, PendingNormals) else value

    # ------------------------------------------------------------------ properties
    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def is_mesh(self) -> bool:
        return self.faces is not None and len(self.faces) > 0

    @property
    def has_gt(self) -> bool:
        return self.instance is not None and bool((self.instance > 0).any())

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float32: min and max corner."""
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])

    def instance_ids(self) -> np.ndarray:
        """Sorted ground-truth instance ids > 0 (empty when unlabelled)."""
        if self.instance is None:
            return np.zeros(0, np.int32)
        ids = np.unique(self.instance)
        return ids[ids > 0]

    def with_labels(self, instance: np.ndarray | None, categories: Mapping[int, str] | None = None) -> "Scene":
        """A copy with other ground-truth labels (validated)."""
        return Scene.create(
            self.name,
            self.points,
            normals=self._normals_or_none(),  # same points and faces: pending normals stay pending
            colors=self.colors,
            faces=self.faces,
            instance=instance,
            categories=categories if categories is not None else self.categories,
            provenance=self.provenance,
            max_points=max(self.num_points, DEFAULT_MAX_POINTS),
        )

    def replace(self, **changes: Any) -> "Scene":
        """dataclasses.replace, re-validated."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "normals"}
        # pending normals stay pending: they are estimated from the (possibly new) points and faces on use
        d["normals"] = self._normals_or_none()
        d.update(changes)
        d.pop("up", None)
        name = d.pop("name")
        pts = d.pop("points")
        return Scene.create(name, pts, max_points=max(len(pts), DEFAULT_MAX_POINTS), **d)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly description: counts, bounds, labels, categories."""
        b = self.bounds
        out: dict[str, Any] = {
            "name": self.name,
            "kind": "mesh" if self.is_mesh else "points",
            "points": self.num_points,
            "faces": int(len(self.faces)) if self.faces is not None else 0,
            "bounds_min": [round(float(v), 4) for v in b[0]],
            "bounds_max": [round(float(v), 4) for v in b[1]],
            "extent": [round(float(v), 4) for v in (b[1] - b[0])],
            "has_ground_truth": self.has_gt,
        }
        if self.instance is not None:
            ids, counts = np.unique(self.instance, return_counts=True)
            out["labelled_points"] = int(counts[ids > 0].sum())
            out["instances"] = {
                int(i): {"points": int(c), "category": self.categories.get(int(i), "object")}
                for i, c in zip(ids, counts)
                if i > 0
            }
            cats: dict[str, int] = {}
            for i in ids[ids > 0]:
                cname = self.categories.get(int(i), "object")
                cats[cname] = cats.get(cname, 0) + 1
            out["categories"] = cats
        if self.provenance:
            out["provenance"] = dict(self.provenance)
        return out

    # ------------------------------------------------------------------ npz (native format)
    def to_npz_dict(self) -> dict[str, np.ndarray]:
        d: dict[str, np.ndarray] = {
            "schema_version": np.array(SCENE_SCHEMA_VERSION, np.int32),
            "name": np.array(self.name),
            "points": self.points,
            "normals": self.normals,
            "colors": self.colors,
            "up": np.array(self.up),
            "categories_json": np.array(json.dumps({str(k): v for k, v in self.categories.items()})),
            "provenance_json": np.array(json.dumps(self.provenance, default=str)),
        }
        if self.faces is not None:
            d["faces"] = self.faces
        if self.instance is not None:
            d["instance"] = self.instance
        return d


def _as_points(a: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise SceneError(f"{what} must have shape (N, 3), got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise SceneError(f"{what} must be numeric, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)


def _as_colors(colors: np.ndarray | None, n: int, name: str) -> np.ndarray:
    if colors is None:
        return np.full((n, 3), 180, np.uint8)
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape[0] != n or c.shape[1] not in (3, 4):
        raise SceneError(f"scene {name!r}: colours must have shape ({n}, 3), got {c.shape}")
    c = c[:, :3]
    if np.issubdtype(c.dtype, np.floating):
        if not np.isfinite(c).all():
            raise SceneError(f"scene {name!r}: colours contain NaN or Inf")
        if c.max() <= 1.0 + 1e-6:
            c = c * 255.0
        c = np.clip(np.round(c), 0, 255)
    elif np.issubdtype(c.dtype, np.integer) and c.dtype != np.uint8 and c.size and (c.min() < 0 or c.max() > 255):
        # e.g. 16-bit colours: casting would wrap around silently
        raise SceneError(
            f"scene {name!r}: integer colours must lie in 0..255, got [{int(c.min())}, {int(c.max())}] ({c.dtype})"
        )
    elif not (np.issubdtype(c.dtype, np.integer) or np.issubdtype(c.dtype, np.floating)):
        raise SceneError(f"scene {name!r}: colours must be numeric, got dtype {c.dtype}")
    return np.ascontiguousarray(c, dtype=np.uint8)


def _as_faces(faces: np.ndarray | None, n: int, name: str) -> np.ndarray | None:
    """(M, 3) int32 faces indexing `n` points, contiguous; None for None or no faces."""
    if faces is None:
        return None
    fcs = np.asarray(faces)
    if fcs.size == 0:
        return None
    if fcs.ndim != 2 or fcs.shape[1] != 3:
        raise SceneError(f"scene {name!r}: faces must have shape (M, 3), got {fcs.shape}")
    if not np.issubdtype(fcs.dtype, np.integer):
        raise SceneError(f"scene {name!r}: faces must be integers, got {fcs.dtype}")
    if fcs.min() < 0 or fcs.max() >= n:
        raise SceneError(
            f"scene {name!r}: face indices must lie in [0, {n}), got [{fcs.min()}, {fcs.max()}]"
        )
    return np.ascontiguousarray(fcs, dtype=np.int32)


def _as_normals(normals: np.ndarray, n: int, name: str) -> np.ndarray:
    """(n, 3) float32 unit normals, contiguous; a zero-length normal becomes +Z."""
    nrm = _as_points(normals, "normals")
    if nrm.shape[0] != n:
        raise SceneError(f"scene {name!r}: {n} points but {nrm.shape[0]} normals")
    if not np.isfinite(nrm).all():
        raise SceneError(f"scene {name!r}: normals contain NaN or Inf")
    lens = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(lens > 1e-12, nrm / np.maximum(lens, 1e-12), np.array([0, 0, 1], np.float32))
    return np.ascontiguousarray(nrm, dtype=np.float32)


def _as_instance(instance: np.ndarray, n: int, name: str) -> np.ndarray:
    """(n,) int32 instance labels >= 0 (0 = unlabelled), contiguous; whole-valued floats are accepted."""
    inst_raw = np.asarray(instance)
    if inst_raw.ndim != 1 or inst_raw.shape[0] != n:
        raise SceneError(f"scene {name!r}: {n} points but instance labels of shape {inst_raw.shape}")
    if not np.issubdtype(inst_raw.dtype, np.integer):
        if np.issubdtype(inst_raw.dtype, np.floating) and np.isfinite(inst_raw).all() and (
            np.round(inst_raw) == inst_raw
        ).all():
            inst_raw = inst_raw.astype(np.int64)
        else:
            raise SceneError(
                f"scene {name!r}: instance labels must be integers, got dtype {inst_raw.dtype}"
            )
    if inst_raw.min() < 0:
        raise SceneError(f"scene {name!r}: instance labels must be >= 0 (0 = unlabelled)")
    if inst_raw.max() > np.iinfo(np.int32).max:
        raise SceneError(f"scene {name!r}: instance label {inst_raw.max()} does not fit int32")
    return np.ascontiguousarray(inst_raw, dtype=np.int32)
