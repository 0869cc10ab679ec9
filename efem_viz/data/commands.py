"""`efem-viz info` and `efem-viz import-rgbd`. Imported lazily by the CLI dispatcher; heavy imports stay in `run`."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import tyro

from efem_viz.data.files import NO_SCENES_GIVEN
from efem_viz.data.scene import DEFAULT_MAX_POINTS, SceneError

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from efem_viz.data.scene import Scene

log = logging.getLogger(__name__)


@dataclass
class InfoArgs:
    """Print what scene files contain: points, faces, bounds, normals, ground-truth labels, categories, provenance.

    Reads each file once and never estimates normals (a file without them says so), so it stays fast on large
    bare point clouds."""

    scenes: Annotated[list[Path], tyro.conf.Positional]
    """Scene files (.ply/.pcd/.las/.laz/.obj/.off/.glb/.npz) and/or folders of them."""
    json: bool = False
    """Print one JSON object per scene instead of tables."""
    full: bool = False
    """Print every provenance entry (camera matrices, plane fit, ...) and every instance; by default long values
    are summarised and at most 12 instances are listed."""
    max_points: int = DEFAULT_MAX_POINTS
    """Refuse scenes with more points than this."""

    def run(self) -> int:
        """Describe every scene; returns 1 if any file could not be read, else 0."""
        from efem_viz.terminal import console

        from efem_viz.data.io import find_scenes, holds_predictions, load_scene
        from efem_viz.terminal import console_text

        console = console()
        paths = find_scenes(self.scenes)
        if not paths:
            raise SceneError(f"no scene files found in {', '.join(str(s) for s in self.scenes)}" if self.scenes else
                          NO_SCENES_GIVEN)
        failures = 0
        for path in paths:
            try:
                scene = load_scene(path, max_points=self.max_points)
            except SceneError as exc:
                console.print(f"[red]{console_text(exc)}[/]")
                failures += 1
                continue
            summary = scene.summary()
            summary["file"] = str(path)
            predicted = holds_predictions(path)
            labels_name = "predicted instances" if predicted else "ground truth"
            if predicted:  # a segment output: its labels are the predictions, never ground truth
                summary["has_ground_truth"] = False
                summary["labels"] = "predicted (efem-viz segment output)"
            # never estimate normals here: that is the slow part of loading a bare point cloud, and info needs none
            summary["normals"] = "estimated on use" if scene.normals_pending else "stored"
            if self.json:
                print(json.dumps(summary, default=str))
                continue
            console.print(self._scene_table(path, scene, summary, labels_name))
            if scene.instance is not None and summary.get("instances"):
                self._print_instances(console, summary, labels_name if predicted else "instances")
        return 1 if failures else 0


    def _scene_table(self, path: Path, scene: Scene, summary: dict[str, Any], labels_name: str) -> Table:
        """One scene's table: kind, sizes, bounds, colours, normals, labels, capture camera, provenance."""
        from rich.table import Table

        from efem_viz.terminal import console_text, count

        table = Table(title=console_text(path), show_header=False, title_justify="left")
        table.add_column("field", style="bold")
        table.add_column("value")
        table.add_row("kind", summary["kind"])
        table.add_row("points", f"{summary['points']:,}")
        table.add_row("faces", f"{summary['faces']:,}")
        table.add_row("bounds min (m)", _vec(summary["bounds_min"]))
        table.add_row("bounds max (m)", _vec(summary["bounds_max"]))
        table.add_row("extent (m)", _vec(summary["extent"]))
        colours = "grey (none)" if bool((scene.colors == 180).all()) else "per point"
        table.add_row("colours", colours)
        table.add_row("normals", "in the file" if summary["normals"] == "stored" else "none (estimated on use)")
        if scene.instance is None:
            table.add_row(labels_name, "none")
        else:
            table.add_row(
                labels_name,
                f"{count(len(summary.get('instances', {})), 'instance')}, "
                f"{summary.get('labelled_points', 0):,} labelled points",
            )
            cats = summary.get("categories", {})
            if cats:
                table.add_row("categories", console_text(", ".join(f"{k} x{v}" for k, v in sorted(cats.items()))))
        self._add_provenance_rows(table, dict(scene.provenance))
        return table

    def _add_provenance_rows(self, table: Table, prov: dict[str, Any]) -> None:
        """The capture camera (usable or why not) and the provenance entries (long or camera ones only with
        `--full`)."""
        from efem_viz.geometry.camera import Camera
        from efem_viz.terminal import console_text

        camera, problem = Camera.parse(prov)
        if camera is not None:
            table.add_row("capture camera", f"{camera.width}x{camera.height}, fx {camera.K[0, 0]:.1f}, "
                          "recorded (free-space check available)")
        elif problem is not None:
            table.add_row("capture camera", console_text(f"[unusable: {problem}]"))
        elif "cameras" in prov:
            cams, problems = Camera.parse_all({"cameras": prov["cameras"]})
            text = f"{len(cams)} recorded (free-space check: segment --free-space on)" if cams else "none usable"
            if problems:
                text += f"; {len(problems)} unusable: {problems[0]}"
            table.add_row("cameras", console_text(text))
        shown = 0
        for key, val in prov.items():
            if not self.full and key in ("K", "T_world_camera", "image_size", "plane_camera"):
                continue
            text = str(val)
            if not self.full and len(text) > 80:
                text = text[:77] + "..."
            table.add_row(console_text(f"provenance.{key}"), console_text(text))
            shown += 1
        if not self.full and shown < len(prov):
            table.add_row("provenance", f"{len(prov) - shown} more entries (--full shows them)")

    def _print_instances(self, console: Console, summary: dict[str, Any], title: str) -> None:
        """The instance table (id, category, points): the first 12 rows unless `--full`."""
        from rich.table import Table

        from efem_viz.terminal import console_text

        inst = Table(title=title, title_justify="left")
        inst.add_column("id", justify="right")
        inst.add_column("category")
        inst.add_column("points", justify="right")
        items = list(summary["instances"].items())
        for i, rec in items if self.full else items[:12]:
            inst.add_row(str(i), console_text(rec["category"]), f"{rec['points']:,}")
        console.print(inst)
        if not self.full and len(items) > 12:
            console.print(f"... and {len(items) - 12} more instances (--full lists them)")


def _vec(v: list[float]) -> str:
    return "  ".join(f"{x:+.3f}" for x in v)


@dataclass
class ImportRgbdArgs:
    """Import a real RGB-D frame as a tabletop scene (table at z = 0, +Z up), written as a binary PLY (or any
    scene format, by the suffix of --out); or a posed RGB-D sequence fused into one scan (--sequence).

    Either give FRAME.npz (arrays rgb, depth_mm or depth, K), or --depth with the intrinsics --fx --fy --cx --cy,
    or --sequence DIR: a 7-Scenes style folder (frame-*.depth.png / .color.png / .pose.txt), ScanNet's exported
    frames (depth/, color/, pose/, intrinsic/), a TUM RGB-D folder (depth.txt, rgb.txt, groundtruth.txt: associated
    by time), or depth (and color) images with --poses FILE. Every frame is
    fused (TSDF), the support plane put at z = 0 and every camera recorded (docs/OWN_DATA.md).
    """

    frame: Annotated[Path | None, tyro.conf.Positional] = None
    """An .npz frame with `rgb` (H,W,3) uint8, `depth_mm` (H,W) uint16 (or `depth` float metres) and `K` (3,3)."""
    out: Path = Path("scene.ply")
    """Output scene file (.ply, .pcd, .las, .laz, .npz, .glb, .obj, .off)."""
    depth: Path | None = None
    """Depth image instead of FRAME: .npy in metres, or a 16-bit .png in millimetres."""
    rgb: Path | None = None
    """Colour image registered to --depth (any format PIL reads)."""
    fx: float | None = None
    """Focal length x in pixels (with --depth)."""
    fy: float | None = None
    """Focal length y in pixels (with --depth)."""
    cx: float | None = None
    """Principal point x in pixels (with --depth)."""
    cy: float | None = None
    """Principal point y in pixels (with --depth)."""
    name: str | None = None
    """Scene name (default: the output file's stem)."""
    voxel: float = 0.004
    """Voxel size of the output point cloud, metres."""
    max_depth: float = 2.5
    """Ignore depth readings farther than this, metres."""
    max_height: float = 0.4
    """Keep points up to this height above the table, metres."""
    seed: int = 0
    """RANSAC seed."""
    licence: str | None = None
    """The frame's licence, recorded in the scene's provenance (e.g. "CC-BY-4.0, (c) 2025 A. Person"); default:
    none is recorded."""
    sequence: Path | None = None
    """A folder of posed RGB-D frames to fuse into one scan (instead of FRAME or --depth)."""
    poses: Path | None = None
    """With --sequence: a poses file, one camera-to-world 4x4 per depth image (16 numbers per line or 4 lines)."""
    every: int = 1
    """With --sequence: fuse every N-th frame."""
    depth_scale: float | None = None
    """With --sequence: depth PNG units per metre (default: the layout's, 5000 for TUM RGB-D folders, else 1000:
    millimetres)."""

    def run(self) -> int:
        """Import the frame and save it; returns 0."""
        from efem_viz.terminal import console

        from efem_viz.data.io import save_scene
        from efem_viz.data.rgbd import import_rgbd, load_rgbd_npz

        console = console()
        t0 = time.perf_counter()
        if self.sequence is not None:
            return self._run_sequence(console, t0)
        if (self.frame is None) == (self.depth is None):
            raise SceneError("give either FRAME.npz or --depth (with --fx --fy --cx --cy), not both or neither")
        if self.frame is not None:
            rgb, depth_m, K = load_rgbd_npz(self.frame)
            source = self.frame
        else:
            assert self.depth is not None
            intr = (self.fx, self.fy, self.cx, self.cy)
            if any(v is None for v in intr):
                raise SceneError("--depth needs the intrinsics --fx --fy --cx --cy")
            K = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)
            from efem_viz.data.rgbd import read_depth_image, read_rgb_image

            depth_m = read_depth_image(self.depth)
            rgb = read_rgb_image(self.rgb) if self.rgb is not None else None
            source = self.depth
        name = self.name or self.out.name.split(".")[0]
        scene = import_rgbd(
            depth_m,
            K,
            rgb,
            name=name,
            voxel=self.voxel,
            max_depth=self.max_depth,
            max_height=self.max_height,
            seed=self.seed,
            licence=self.licence,
            provenance={"source_file": source.name},
        )
        save_scene(scene, self.out)
        b = scene.bounds
        console.print(
            f"[green]wrote[/] {self.out}: {scene.num_points:,} points, "
            f"extent {[round(float(v), 3) for v in b[1] - b[0]]} m, "
            f"plane rms {scene.provenance['plane_residual_rms_m'] * 1000:.1f} mm, "
            f"{time.perf_counter() - t0:.1f} s"
        )
        return 0

    def _run_sequence(self, console: Any, t0: float) -> int:
        """--sequence: fuse the folder's posed frames into one scene and save it; returns 0."""
        from efem_viz.data.io import save_scene
        from efem_viz.data.sequence import import_sequence

        if self.frame is not None or self.depth is not None:
            raise SceneError("give FRAME.npz, --depth or --sequence, not several")
        if self.every < 1 or (self.depth_scale is not None and not self.depth_scale > 0):
            raise SceneError(f"--every must be >= 1 and --depth-scale > 0, got {self.every} and {self.depth_scale}")
        assert self.sequence is not None
        name = self.name or self.out.name.split(".")[0]
        scene = import_sequence(self.sequence, name=name, poses=self.poses, K=_intrinsics_given(self),
                                every=self.every, voxel=self.voxel, max_depth=self.max_depth,
                                depth_scale=self.depth_scale, seed=self.seed)
        if self.licence is not None:
            scene = scene.replace(provenance={**dict(scene.provenance), "licence": self.licence})
        save_scene(scene, self.out)
        b = scene.bounds
        console.print(f"[green]wrote[/] {self.out}: {scene.provenance['frames']} frames ({scene.provenance['layout']}) "
                      f"fused into {scene.num_points:,} points, extent {[round(float(v), 3) for v in b[1] - b[0]]} m, "
                      f"{time.perf_counter() - t0:.1f} s")
        return 0


def _intrinsics_given(args: ImportRgbdArgs) -> np.ndarray | None:
    """--fx --fy --cx --cy as a K matrix (None when none is given).

    Raises:
        SceneError: some given and not all, or a focal length that is not positive.
    """
    intr = (args.fx, args.fy, args.cx, args.cy)
    if all(v is None for v in intr):
        return None
    if any(v is None for v in intr):
        raise SceneError("give all four intrinsics --fx --fy --cx --cy")
    fx, fy, cx, cy = (float(v) for v in intr)  # type: ignore[arg-type]
    if not (fx > 0 and fy > 0):
        raise SceneError(f"focal lengths must be positive, got fx={fx}, fy={fy}")
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


@dataclass
class ImportScanArgs:
    """Import your own scan (a point cloud or mesh from a phone or tablet LiDAR app, a robot, another tool) into
    the scene frame EFEM works in: metres, +Z up, the support plane at z = 0.

    Units (metres, centimetres, millimetres) are told by the scan's extent and point spacing, the up axis by its
    dominant support plane; --units and --up override a wrong guess, and a scan that cannot be decided is refused
    with the flag to pass. The transform is recorded in the scene (`efem-viz info` shows it), so that
    `efem-viz segment --frame original` writes results back in the file's own frame and units; the point order is
    kept, so per-point masks and labels line up with the file's vertices. See docs/OWN_DATA.md."""

    scan: Annotated[Path, tyro.conf.Positional]
    """The scan: .ply, .pcd, .las, .laz, .obj, .off, .glb or .npz."""
    out: Path | None = None
    """Output scene file (any scene format by its suffix); default: SCAN's folder, <stem>.scene.ply."""
    units: str = "auto"
    """The scan's length unit: auto, m, cm or mm."""
    up: str = "auto"
    """The scan's up axis: auto, +z, -z, +y, -y, +x or -x (glTF files and many phone apps: +y)."""
    seed: int = 0
    """Seed of the plane search (the same seed gives the same frame)."""
    max_points: int = DEFAULT_MAX_POINTS
    """Refuse scans with more points than this."""

    def run(self) -> int:
        """Import the scan and save it; returns 0."""
        from efem_viz.terminal import console

        from efem_viz.data.io import load_scene, save_scene
        from efem_viz.data.scan import import_scan

        console = console()
        t0 = time.perf_counter()
        out = self.out if self.out is not None else self.scan.with_name(self.scan.name.split(".")[0] + ".scene.ply")
        if out.resolve() == self.scan.resolve():
            raise SceneError(f"--out {out} is the scan itself; choose another file")
        scene = load_scene(self.scan, max_points=self.max_points)
        imported, frame = import_scan(scene, units=self.units, up=self.up, seed=self.seed)  # type: ignore[arg-type]
        imported = imported.replace(name=out.name.split(".")[0],
                                    provenance={**dict(imported.provenance), "source_file": self.scan.name})
        save_scene(imported, out)
        b = imported.bounds
        console.print(f"[green]wrote[/] {out}: {imported.num_points:,} points, {frame.describe()}"
                      + ("; already in the scene frame, unchanged" if frame.is_identity else
                         f" -> metres, +Z up, extent {[round(float(v), 3) for v in b[1] - b[0]]} m")
                      + f", {time.perf_counter() - t0:.1f} s")
        return 0
