"""A user's own scan in the scene frame: units and up axis detected, the support plane put at z = 0, the transform
recorded so that every output can go back to the file's own frame.

EFEM works in metres with +Z up and the support plane at z = 0 (the spec's scene frame). Scans from phones, tablets,
robots and other tools arrive in millimetres or centimetres, Y-up (glTF's convention and many apps'), or tilted.
`detect_scan_frame` decides:

* **units** by two independent scales, the scan's extent (robust bounding-box diagonal) and its point spacing
  (median nearest-neighbour distance): a tabletop or room scan is 0.05-100 m across with points 0.1-50 mm apart; of
  metres, centimetres and millimetres the reading closest to a 3 mm spacing and a 1.5 m extent wins, and two
  readings that fit about equally well are refused ("pass --units").
* **up** as the normal of the dominant support plane: seeded RANSAC planes (`rgbd.ransac_plane`) on a subsample,
  each oriented toward the side most off-plane points lie on; a support plane has almost nothing below it. A plane
  within 10° of a coordinate axis snaps to that axis exactly (so that round trips are exact), else the plane's
  own normal is up (a tilted scan). The plane's height, rounded to whole millimetres, becomes z = 0.

The result is a `ScanFrame`: the `Sim3` taking the file's coordinates to the scene frame (`p_scene = s R p + t`),
with the units and up axis it was decided from. `import_scan` records it in the scene's provenance
(``provenance["scan_frame"]``); `ScanFrame.from_provenance` reads it back, and its `inverse` takes points, meshes,
poses and boxes back to the file's frame (`Instances.transformed`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from efem_viz.data.scene import Scene, SceneError
from efem_viz.geometry.transforms import Sim3

log = logging.getLogger(__name__)

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
"""Metres per unit of each length unit a scan may come in."""
UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}
UP_AXES: dict[str, tuple[float, float, float]] = {
    "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
    "+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0),
}
"""The axis choices of `--up` (the file's axis that points up)."""
_UP_ROTATIONS: dict[str, np.ndarray] = {  # exact proper rotations taking the named axis to +Z
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "+y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # glTF Y-up -> Z-up: (x, y, z) -> (x, -z, y)
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "+x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}
SNAP_DEG = 10.0
"""A support plane within this angle of a coordinate axis is taken as exactly that axis."""
_SPACING_M, _EXTENT_M = 0.003, 1.5
_EXTENT_RANGE, _SPACING_RANGE = (0.05, 100.0), (1e-4, 0.05)
_SUBSAMPLE = 20000
_PLANE_DISTANCE_M = 0.01

UnitsChoice = Literal["auto", "m", "cm", "mm"]
UpChoice = Literal["auto", "+z", "-z", "+y", "-y", "+x", "-x"]


@dataclass(frozen=True)
class ScanFrame:
    """How a scan file's coordinates map to the scene frame (metres, +Z up, support plane at z = 0)."""

    to_scene: Sim3
    """`p_scene = scale · R p_file + t`."""
    units: str
    """The file's length unit ("m", "cm", "mm")."""
    up: str
    """The file's up direction: an axis name ("+y", ...) or "plane" (a tilted scan: the support plane's normal)."""
    decided: str = "detected"
    """"detected", "given" (--up/--units) or "mixed"."""

    @property
    def is_identity(self) -> bool:
        """Whether the file is already in the scene frame (no change at all)."""
        return (self.to_scene.scale == 1.0 and np.array_equal(self.to_scene.R, np.eye(3))
                and not self.to_scene.t.any())

    def describe(self) -> str:
        """One line: what was decided, e.g. "millimetres, +Y up (detected)"."""
        up = "tilted (the support plane's normal is up)" if self.up == "plane" else f"{self.up.upper()} up"
        return f"{UNIT_NAMES[self.units]}, {up} ({self.decided})"

    def to_provenance(self) -> dict[str, Any]:
        """The JSON record kept in ``provenance["scan_frame"]``."""
        return {"units": self.units, "up": self.up, "decided": self.decided,
                "T_scene_file": self.to_scene.matrix().tolist()}

    @classmethod
    def from_provenance(cls, provenance: Any) -> ScanFrame | None:
        """The frame recorded by `import_scan`, or None (a scene made in the scene frame).

        Raises:
            SceneError: a damaged record.
        """
        rec = provenance.get("scan_frame") if hasattr(provenance, "get") else None
        if rec is None:
            return None
        try:
            T = np.asarray(rec["T_scene_file"], dtype=np.float64)
            sim = Sim3.from_matrix(T)
            if not np.isfinite(T).all() or not np.allclose(sim.R @ sim.R.T, np.eye(3), atol=1e-6):
                raise ValueError("not a similarity transform")
            return cls(sim, str(rec["units"]), str(rec["up"]), str(rec.get("decided", "detected")))
        except (KeyError, TypeError, ValueError) as exc:
            raise SceneError(f"the scene's recorded scan frame is damaged ({exc})") from None


def _robust_extent(points: np.ndarray) -> float:
    lo, hi = np.percentile(points, [1, 99], axis=0)
    return float(np.linalg.norm(hi - lo))


def _spacing(points: np.ndarray, rng: np.random.Generator) -> float:
    """Median distance from 2,000 random points to their nearest neighbour in the whole cloud."""
    from efem_viz._typeshims import cKDTree

    probe = points[rng.choice(len(points), size=min(len(points), 2000), replace=False)]
    d, _ = cKDTree(points).query(probe, k=2)
    nn = d[:, 1]
    nn = nn[nn > 0]
    if not len(nn):
        raise SceneError("cannot decide the units: every point is a duplicate of another; pass --units")
    return float(np.median(nn))


def detect_units(points: np.ndarray, *, seed: int = 0) -> str:
    """The length unit of a scan ("m", "cm" or "mm"), from its extent and point spacing (module docstring).

    Raises:
        SceneError: no unit gives a plausible scan, or two fit about equally well.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 10:
        raise SceneError(f"cannot decide the units of a scan with {len(pts)} points; pass --units")
    extent, spacing = _robust_extent(pts), _spacing(pts, np.random.default_rng(seed))
    scores = {}
    for unit, s in UNITS.items():
        e, d = extent * s, spacing * s
        if _EXTENT_RANGE[0] <= e <= _EXTENT_RANGE[1] and _SPACING_RANGE[0] <= d <= _SPACING_RANGE[1]:
            scores[unit] = abs(np.log(d / _SPACING_M)) + 0.5 * abs(np.log(e / _EXTENT_M))
    if not scores:
        raise SceneError(f"cannot decide the units: the scan is {extent:.4g} units across with points "
                         f"{spacing:.3g} units apart, which fits no scan in metres, centimetres or millimetres; "
                         "pass --units")
    ranked = sorted(scores, key=scores.__getitem__)
    if len(ranked) > 1 and scores[ranked[1]] - scores[ranked[0]] < 0.5:
        raise SceneError(f"cannot decide the units: {extent:.4g} units across, points {spacing:.3g} apart fit "
                         f"{UNIT_NAMES[ranked[0]]} and {UNIT_NAMES[ranked[1]]} about equally; pass --units")
    return ranked[0]


def _support_normal(points_m: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal pointing up, inlier points) of the dominant support plane of a metric cloud.

    Raises:
        SceneError: no plane with (almost) nothing below it.
    """
    from efem_viz.data.rgbd import ransac_plane

    rng = np.random.default_rng(seed)
    pts = points_m[rng.choice(len(points_m), size=min(len(points_m), _SUBSAMPLE), replace=False)]
    remaining = np.arange(len(pts))
    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for _ in range(4):
        if len(remaining) < 50:
            break
        model, inl = ransac_plane(pts[remaining], rng=rng, distance=_PLANE_DISTANCE_M, iterations=500)
        if len(inl) < max(30, 0.05 * len(pts)):
            break
        n, d = model[:3], float(model[3])
        side = pts @ n + d
        off = np.abs(side) > 2 * _PLANE_DISTANCE_M
        above, below = int((side[off] > 0).sum()), int((side[off] < 0).sum())
        if below > above:
            n, above, below = -n, below, above
        if above < 0.01 * len(pts):  # a flat scan: nothing tells the side; the file's +Z (else +Y) side is up
            ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) > 0.1 else np.array([0.0, 1.0, 0.0])
            n = n if n @ ref >= 0 else -n
        if below <= 0.05 * max(1, above + below) and (best is None or len(inl) > best[0]):
            best = (len(inl), n, pts[remaining[inl]])
        remaining = np.delete(remaining, inl)
    if best is None:
        raise SceneError("cannot decide the up axis: no support plane with the scan standing on it was found; "
                         "pass --up")
    return best[1] / np.linalg.norm(best[1]), best[2]


def detect_scan_frame(points: np.ndarray, *, units: UnitsChoice = "auto", up: UpChoice = "auto",
                      seed: int = 0) -> ScanFrame:
    """The `ScanFrame` of a scan's points (module docstring); `units`/`up` override the detection.

    A scan already in metres with +Z up and its support plane within 1 cm of z = 0 is left exactly as it is
    (the identity).

    Raises:
        SceneError: the units or the up axis cannot be decided (the message says which flag to pass), or an
            unknown choice.
    """
    if units not in ("auto", *UNITS):
        raise SceneError(f"unknown units {units!r}; expected auto, {', '.join(UNITS)}")
    if up not in ("auto", *UP_AXES):
        raise SceneError(f"unknown up axis {up!r}; expected auto, {', '.join(UP_AXES)}")
    pts = np.asarray(points, dtype=np.float64)
    unit = detect_units(pts, seed=seed) if units == "auto" else units
    s = UNITS[unit]
    metric = pts * s
    inliers: np.ndarray | None = None
    if up == "auto":
        normal, inliers = _support_normal(metric, seed)
        axis = min(UP_AXES, key=lambda a: float(np.arccos(np.clip(normal @ np.array(UP_AXES[a]), -1, 1))))
        angle = np.degrees(np.arccos(np.clip(normal @ np.array(UP_AXES[axis]), -1, 1)))
        up_name = axis if angle <= SNAP_DEG else "plane"
        if up_name == "plane":
            from efem_viz.data.rgbd import table_frame

            R, _ = table_frame(normal, np.zeros(3))
        else:
            R = _UP_ROTATIONS[up_name]
    else:
        up_name, R = up, _UP_ROTATIONS[up]
    decided = "detected" if units == up == "auto" else ("given" if "auto" not in (units, up) else "mixed")
    rotated = metric @ R.T
    if inliers is None:  # up was given: the support plane's height is the lowest dense layer
        height = float(np.percentile(rotated[:, 2], 2))
    else:
        height = float(np.median((inliers @ R.T)[:, 2]))
    if unit == "m" and up_name == "+z" and abs(height) < 0.01:  # already in the scene frame: not a bit changes
        return ScanFrame(Sim3.identity(), unit, up_name, decided)
    height = round(height, 3)  # whole millimetres: finer than any sensor's noise, and a scan exported from the
    # scene frame comes back to the same coordinates
    return ScanFrame(Sim3(s, R, np.array([0.0, 0.0, -height])), unit, up_name, decided)


def import_scan(scene: Scene, *, units: UnitsChoice = "auto", up: UpChoice = "auto",
                seed: int = 0) -> tuple[Scene, ScanFrame]:
    """A scene of a user's scan in the scene frame, its `ScanFrame` recorded in ``provenance["scan_frame"]``.

    Points, normals and faces are transformed (the point order is kept, so per-point labels and masks line up
    with the file's vertices); colours and labels are unchanged. A scan already in the scene frame comes back
    unchanged, with the identity recorded.

    Raises:
        SceneError: as `detect_scan_frame`; a scan whose frame is already recorded.
    """
    if "scan_frame" in scene.provenance:
        raise SceneError(f"{scene.name} was imported already (its scan frame is recorded); open it directly")
    frame = detect_scan_frame(scene.points, units=units, up=up, seed=seed)
    origin = file_origin(scene.provenance)
    sim = frame.to_scene  # of the points as loaded
    if origin.any():  # a georeferenced file loaded minus its origin: the recorded frame maps the file's coordinates
        frame = ScanFrame(Sim3(sim.scale, sim.R, sim.t - sim.scale * (sim.R @ origin)), frame.units, frame.up,
                          frame.decided)
    prov = {**dict(scene.provenance), "scan_frame": frame.to_provenance()}
    if sim.scale == 1.0 and np.array_equal(sim.R, np.eye(3)) and not sim.t.any():
        return scene.replace(provenance=prov), frame
    changes: dict[str, Any] = {"points": sim.apply(scene.points), "provenance": prov}
    if not scene.normals_pending:
        changes["normals"] = scene.normals @ sim.R.T
    return scene.replace(**changes), frame


def file_origin(provenance: Any) -> np.ndarray:
    """(3,) float64 the loader subtracted from a georeferenced file's coordinates (``provenance["file_origin"]``,
    e.g. `data.formats.las`), zeros when none.

    Raises:
        SceneError: a damaged record.
    """
    rec = provenance.get("file_origin") if hasattr(provenance, "get") else None
    if rec is None:
        return np.zeros(3)
    try:
        origin = np.asarray(rec, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise SceneError("the scene's recorded file origin is damaged (not three numbers)") from None
    if not np.isfinite(origin).all():
        raise SceneError("the scene's recorded file origin is damaged (not finite)")
    return origin


def scene_in_scene_frame(scene: Scene, *, seed: int = 0) -> tuple[Scene, str | None]:
    """A scan opened directly (`view`, `segment`): brought into the scene frame when it is clearly not in it.

    A scene with provenance (made by efem-viz: generated, imported, annotated; a loader's ``file_origin`` alone
    does not count) is used as it is. A bare file is
    checked with `detect_scan_frame`; when both the units and the up axis are decided and the scan is not already
    in metres with +Z up, it is transformed as `import_scan` would (the frame recorded in its provenance) and a
    one-line notice says so. A scan whose frame cannot be decided is used as it is (no notice: `import-scan` says
    why).

    Returns:
        (the scene to use, the notice or None).
    """
    if set(scene.provenance) - {"file_origin"}:  # a loader's own record does not make a scene efem-viz's
        return scene, None
    try:
        imported, frame = import_scan(scene, seed=seed)
    except SceneError as exc:
        log.debug("%s: scan frame not decided (%s); used as it is", scene.name, exc)
        return scene, None
    if frame.is_identity:
        return scene, None
    origin = file_origin(scene.provenance)
    geo = f"; its georeferenced origin {origin.tolist()} subtracted" if origin.any() else ""
    return imported, (f"{scene.name}: read as {frame.describe()} and brought to metres, +Z up, the support plane "
                      f"at z = 0{geo} (efem-viz import-scan --units/--up to override)")


def scene_in_file_frame(scene: Scene) -> tuple[Scene, ScanFrame | None]:
    """The scene back on its scan file's own coordinates and units (`import_scan`'s recorded frame undone: points,
    normals), so that what is written from it lines up with the user's file; the frame record is dropped from
    the provenance (the points are no longer in the scene frame) and ``frame`` says which they are in. A scene
    without a recorded frame, or with an identity one, is returned as it is.

    Returns:
        (the scene in its file's frame, the frame undone or None).

    Raises:
        SceneError: a damaged frame record.
    """
    frame = ScanFrame.from_provenance(scene.provenance)
    if frame is None or frame.is_identity:
        return scene, None
    back = frame.to_scene.inverse()
    prov = {k: v for k, v in dict(scene.provenance).items() if k != "scan_frame"}
    prov["frame"] = f"original ({frame.units}), {frame.describe()}"
    return scene.replace(points=back.apply(scene.points).astype(np.float32),
                         normals=None if scene.normals_pending else scene.normals @ back.R.T,
                         provenance=prov), frame
