"""The EFEM assistance part: pre-labels from an EFEM result and their review, and click-to-segment with the
shape prior (its background thread, preview, accept, discard)."""

from __future__ import annotations

import dataclasses
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from annotator.efem_runs import SEGMENT_SETTINGS, get_prior
from annotator.io import LabelData, LabelIOError, load_labels, resolve_inside
from annotator.labels import Delta, prelabel_note, unreviewed_prelabels
from efem_viz.data.io import RESULT_SUFFIX
from efem_viz.em.solver import PROGRESSIVE_EVERY_S

EFEM_FULL_RESOLUTION_POINTS = 250_000
"""Scans with more vertices run EFEM on a thinned working set (`EFEM_BIG_SCAN_VOXEL`; masks stay full resolution):
a real frame has ~60k points, and EM's cost grows with the points it iterates on."""
EFEM_BIG_SCAN_VOXEL = 0.005
"""The working-set cell (m) of an EFEM run on a big scan (`SolveSettings.work_voxel`), unless its preset's own is
coarser (`chairs`: 2.5 cm)."""

if TYPE_CHECKING:
    from efem_viz.em.config import SolveSettings
    from annotator.parts.context import SessionHooks, Toolbox
    from annotator.parts.scan import ScanPart
    from annotator.parts.instances import InstancePart
    from annotator.parts.paint import PaintPart

PRELABEL_MIN_FREE = 0.5
"""A pre-label is added only when at least this fraction of its vertices is unlabelled (`AssistPart.add_prelabels`)."""
SEED_RADIUS = 0.02
"""Before its first step, a running EFEM's overlay marks the scan within this distance (m, EFEM's metric frame) of
each proposal's anchor."""


@dataclass(frozen=True)
class RunOverlay:
    """What a running EFEM on the scan has found so far (`AssistPart.run_overlay`), drawn over the vertices nobody
    has labelled, where its pre-labels would go (`annotator.render.compose_colors`): where its live proposals are
    looking and the instances it accepted so far."""

    codes: np.ndarray
    """(N,) uint16 per scan vertex: 0 nothing, 1 sampled by a live proposal at the newest step (before the first
    step: near a proposal's anchor), k + 2 the k-th instance accepted so far."""
    colors: np.ndarray
    """(A, 3) uint8 colour of each accepted instance (`efem_viz.colors.result_colors`: its pre-label's)."""
    step: int
    """The solver's step shown (0-based; −1: its proposals are drawn, no step done yet)."""

    @classmethod
    def of_result(cls, result: Any, points: np.ndarray) -> RunOverlay:
        """The overlay of a running solve's result so far (`StepInfo.partial()`, an `EMResult` on the scan's
        points as EFEM sees them, (N, 3) metres): its newest step's live samples, or before the first step the
        scan within `SEED_RADIUS` of its proposals' anchors, and its accepted instances (these win where both are).

        Raises:
            ValueError: the result belongs to another point count.
        """
        from efem_viz._typeshims import cKDTree
        from efem_viz.colors import result_colors

        n = len(points)
        if int(result.num_points) != n:
            raise ValueError(f"the running EFEM result has {result.num_points} points, the scan {n} vertices")
        codes = np.zeros(n, np.uint16)
        trace = result.trace
        step = trace.num_steps - 1
        if step >= 0:
            codes[trace.live_samples(step)] = 1
        elif trace.num_proposals:
            anchors = np.asarray(points, np.float64)[np.asarray(trace.prop_anchor, np.int64)]
            d, _ = cKDTree(anchors).query(np.asarray(points, np.float64), distance_upper_bound=SEED_RADIUS)
            codes[np.isfinite(d)] = 1
        inst = result.instances
        if len(inst):
            labels = np.asarray(inst.label_array(n), np.int64)
            codes[labels > 0] = (labels[labels > 0] + 1).astype(np.uint16)
        colors = result_colors(inst) if len(inst) else np.zeros((0, 3), np.uint8)
        return cls(codes=codes, colors=np.asarray(colors, np.uint8).reshape(-1, 3), step=step)

    @property
    def accepted(self) -> int:
        """Instances accepted so far."""
        return len(self.colors)

    def changed(self, before: RunOverlay | None) -> np.ndarray:
        """(K,) int64 vertices to draw again after `before` (None: no overlay was drawn): those whose code changed,
        and every accepted instance's."""
        if before is None:
            return np.flatnonzero(self.codes)
        return np.flatnonzero((self.codes != before.codes) | (self.codes >= 2))


class AssistPart:
    """EFEM's help: unreviewed pre-label instances, their review, and the click-to-segment run and preview."""

    def __init__(self, scan: ScanPart, toolbox: Toolbox, hooks: SessionHooks, instances: InstancePart,
                 painting: PaintPart) -> None:
        self.scan, self.toolbox, self.hooks = scan, toolbox, hooks
        self.instances, self.painting = instances, painting
        self.preview: np.ndarray | None = None
        """(N,) bool mask drawn highlighted (click-to-segment preview), or None."""
        self.pending_segment: np.ndarray | None = None
        """(K,) int32 vertices of the previewed segment, or None."""
        self.prelabel_cursor: int | None = None
        """The pre-label Next / Previous went to last (None: not used yet)."""
        self.solve: SolveSettings = SEGMENT_SETTINGS
        """The solver knobs of click-to-segment (preset, proposals, work_voxel, tau_out, matmul_dtype); the prior
        is the tool's (`settings.prior`)."""
        self._segment_lock = threading.Lock()
        self._segment_cancel: threading.Event | None = None
        self._job: str | None = None
        """The EFEM job running: "segment" (click-to-segment), "efem" (a run on the scan) or None."""
        self._thread: threading.Thread | None = None
        """The last EFEM job's thread (joined on close)."""
        self.last_run_path: Path | None = None
        """Where the last EFEM run on the scan saved its result (None: none yet)."""
        self._efem_scene: Any = None
        self.skipped_prelabels = 0
        """How many proposals the last `add_prelabels` left out (mostly on labelled vertices)."""
        self.run_overlay: RunOverlay | None = None
        """What a running EFEM on the scan has found so far, drawn over the unlabelled vertices (None: no run)."""
        self.progressive_every_s: float | None = PROGRESSIVE_EVERY_S
        """A running EFEM is drawn as it goes at most this often, from its first step (None: only its end; 0:
        every step)."""

    def efem_scene(self) -> Any:
        """The scan as EFEM sees it: brought to metres with +Z up when it is a bare scan in other units or axes
        (`efem_viz.data.scan.scene_in_scene_frame`, said once). The vertices keep their order, so every mask EFEM
        returns is a set of the scan's own vertex indices; the annotator shows and saves the scan as it is."""
        if self._efem_scene is None:
            from efem_viz.data.scan import scene_in_scene_frame

            scene, notice = scene_in_scene_frame(self.scan.scene)
            if notice:
                self.hooks.notify("Scan frame for EFEM", f"{notice}; the labels stay on the scan's own vertices")
            self._efem_scene = scene
        return self._efem_scene

    def import_efem(self, path: str) -> list[int]:
        """Import an EFEM result as unreviewed pre-label instances on unlabelled vertices; returns their ids."""
        p = resolve_inside(path, self.scan.roots, what="EFEM result")
        data = load_labels(p, self.scan.n)
        if not p.name.endswith(RESULT_SUFFIX):
            raise LabelIOError(f"{p.name} is not an EFEM result (*{RESULT_SUFFIX})")
        return self.add_prelabels(data, source=p.name)

    def add_prelabels(self, data: LabelData, *, source: str) -> list[int]:
        """Add proposals (labels + rows) as new unreviewed instances, painted only where nothing is labelled.

        A proposal that would keep less than `PRELABEL_MIN_FREE` of its vertices (they are labelled already, by
        hand or by a more confident pre-label), or none, is not added: a second run over a labelled scan would
        otherwise leave fragments of its objects (and empty rows) to review.
        `skipped_prelabels` says how many were left out."""
        group = uuid.uuid4().hex[:12]
        conf = data.confidence or {}
        order = sorted((r for r in data.instances if (data.labels == r.id).any()),
                       key=lambda r: -conf.get(r.id, 0.0))
        with self.scan.store.lock:  # one undo step: no other edit (another browser, an undo) between its parts
            new_ids = self._add_rows(data, order, conf, source, group)
        self.skipped_prelabels = len(order) - len(new_ids)
        self.hooks.on_change()
        return new_ids

    def _add_rows(self, data: LabelData, order: list[Any], conf: dict[int, float], source: str,
                  group: str) -> list[int]:
        new_ids: list[int] = []
        for row in order:
            idx = np.flatnonzero(data.labels == row.id)
            free = int((self.scan.store.labels[idx] == 0).sum())  # includes this batch's more confident ones
            if free == 0 or free < PRELABEL_MIN_FREE * len(idx):
                continue
            note = prelabel_note(source, conf.get(row.id))
            d = self.scan.store.do(lambda ls, row=row, note=note: ls.create_instance(category=row.category,
                                                                                name=f"{row.category} (EFEM)"),
                              group=group)
            assert d is not None
            iid = int(next(iter(d.table_after)))
            self.scan.store.do(lambda ls, iid=iid, note=note: ls.update_instance(iid, note=note), group=group)
            self.scan.store.do(lambda ls, iid=iid, idx=idx: ls.paint(idx, iid, overwrite=False), group=group)
            new_ids.append(iid)
        return new_ids

    def review_prelabel(self, instance_id: int, action: Literal["accept", "reject", "merge"], *,
                        group: str = "") -> None:
        """Accept (keep as a real instance), reject (delete) or merge (into the active instance) a pre-label.

        Args:
            instance_id: the pre-label.
            action: what to do with it.
            group: undo group (reviews of one group undo together).
        """
        info = self.scan.store.labelset.info(instance_id)
        if action == "accept":
            note, name = info.note.replace("unreviewed", "accepted"), info.name.replace(" (EFEM)", "")
            self.scan.store.do(lambda ls: ls.update_instance(instance_id, note=note, name=name), group=group)
        elif action == "reject":
            self.scan.store.do(lambda ls: ls.delete_instance(instance_id), group=group)
        elif action == "merge":
            target = self.instances.require_active()
            if target == instance_id:
                raise ValueError("choose another active instance to merge this pre-label into")
            self.scan.store.do(lambda ls: ls.merge([instance_id], target), group=group)
        else:
            raise ValueError(f"unknown review action {action!r}")
        self.hooks.on_change()

    def prelabel_cut(self, default: float = 0.5) -> float:
        """The pre-label cut that suits the unreviewed pre-labels: `default`, lowered to the best one's confidence
        when every one is below it (a real frame's pre-labels all under 0.5 made "Accept all ≥ cut"
        accept nothing)."""
        table = self.scan.store.labelset.instances
        conf = [float(table[k].confidence) for k in unreviewed_prelabels(table)]
        if not conf:
            return float(default)
        return float(min(default, np.floor(max(conf) * 100.0) / 100.0))

    def review_prelabels(self, cut: float, action: Literal["accept", "reject"]) -> list[int]:
        """Bulk review: accept every unreviewed pre-label with confidence ≥ `cut`, or reject every one below it;
        one undo step. Returns the instance ids reviewed."""
        if action not in ("accept", "reject"):
            raise ValueError(f"unknown bulk review action {action!r}")
        table = self.scan.store.labelset.instances
        ids = [k for k in unreviewed_prelabels(table)
               if (table[k].confidence >= cut) == (action == "accept")]
        group = uuid.uuid4().hex[:12]
        for iid in ids:
            self.review_prelabel(iid, action, group=group)
        self.hooks.on_change()
        self.hooks.notify("Pre-labels", f"{'accepted' if action == 'accept' else 'rejected'} {len(ids)} pre-label(s) "
                    f"with confidence {'≥' if action == 'accept' else '<'} {cut:.2f} (one undo step)")
        return ids

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment: run EFEM seeded near a vertex with the chosen prior (`settings.prior`) and preview the
        mask.

        The solver runs in a background thread (edits stay responsive); the mask is highlighted when it is ready
        and becomes labels only through `accept_segment`.

        Args:
            vertex: the clicked vertex.
            wait: run in the calling thread and return the mask (tests, scripts).

        Returns:
            With `wait`, (K,) int32 vertex indices of the proposed mask (also kept in `pending_segment`); else None.
        """
        prior_name = self.toolbox.settings.prior
        cancel = self._claim("segment")
        self.hooks.on_segment(0.0)
        if wait:
            return self._segment_job(int(vertex), prior_name, cancel)
        self.hooks.notify("Segmenting", f"EFEM with prior {prior_name!r} around vertex {vertex}... (Esc cancels)")
        self._thread = threading.Thread(
            target=lambda: self.hooks.report(lambda: self._segment_job(int(vertex), prior_name, cancel)),
            name="annotator-segment", daemon=True)
        self._thread.start()
        return None

    def _segment_job(self, vertex: int, prior_name: str, cancel: threading.Event) -> np.ndarray | None:
        from annotator import efem_runs
        from efem_viz.em.solver import EMCancelled

        def on_step(info: Any) -> None:
            self.hooks.on_segment(round(100.0 * (info.step + 1) / max(info.num_steps, 1), 1))

        t0 = time.perf_counter()
        try:
            from efem_viz.prior import fused

            fused.prepare(lambda notice: self.hooks.notify("Segmenting", notice))  # a first click builds them
            mask_idx = efem_runs.segment_at_point(self.efem_scene(), vertex, prior_name=prior_name, settings=self.solve,
                                               on_step=on_step, cancel=cancel)
        except EMCancelled:
            self.hooks.notify("Segmenting cancelled", f"the segmentation around vertex {vertex} was stopped")
            return None
        finally:
            self._release()
            self.hooks.on_segment(None)
        self.set_preview(mask_idx)
        if len(mask_idx) == 0:
            self.hooks.notify("No object found", f"EFEM with prior {prior_name!r} accepted no proposal around vertex "
                        f"{vertex} ({time.perf_counter() - t0:.1f} s): click nearer the object's centre, or "
                        "label it with the brush / region grow")
        else:
            self.hooks.notify("Segment preview", f"{len(mask_idx):,} vertices in {time.perf_counter() - t0:.1f} s: "
                        "Enter (Accept segment) paints it as a new instance, Esc discards it")
        return mask_idx

    @property
    def segmenting(self) -> bool:
        """Whether a click-to-segment run is in progress (Esc / Discard cancels it)."""
        with self._segment_lock:
            return self._job == "segment"

    @property
    def efem_running(self) -> bool:
        """Whether an EFEM run on the whole scan is in progress."""
        with self._segment_lock:
            return self._job == "efem"

    def _claim(self, job: str) -> threading.Event:
        """Start EFEM job `job` (one at a time); returns its cancel event.

        Raises:
            ValueError: another EFEM job is running (says which, and that Esc cancels it).
        """
        with self._segment_lock:
            if self._segment_cancel is not None:
                what = "segmenting the last click" if self._job == "segment" else "running EFEM on the scan"
                raise ValueError(f"still {what}: wait for it to finish, or cancel it")
            self._job = job
            self._segment_cancel = threading.Event()
            return self._segment_cancel

    def _release(self) -> None:
        with self._segment_lock:
            self._segment_cancel, self._job = None, None

    def result_path(self) -> Path:
        """Where a run's result goes, `<scan>.annotate/<scan>.efem.npz`, checked to stay inside the output folder
        (a link there to a folder or a file elsewhere is refused, as for every other output).

        Raises:
            LabelIOError: the path resolves outside the output folder, is a link or a folder.
        """
        from efem_viz.serve.inputs import confine_writes

        path = self.scan.work_dir / f"{self.scan.stem}{RESULT_SUFFIX}"
        confine_writes([path], self.scan.out_dir, what="EFEM result", error=LabelIOError)
        if path.is_symlink() or path.is_dir():
            raise LabelIOError(f"refusing EFEM result: {path} is a {'link' if path.is_symlink() else 'folder'}; "
                               "nothing was written")
        return path

    def suggested_preset(self, prior: str | None = None) -> str:
        """The EFEM preset that fits the scan solved with a shipped prior (``prior``: its name; None: the chosen
        one, `settings.prior`): `efem_viz.em.config.suggested_preset`, where the chair prior runs "chairs" on a scan
        that is not a single-view capture. A prior that cannot be loaded leaves the scan to decide alone (the run
        then says what is wrong with it)."""
        from efem_viz.em.config import suggested_preset
        from efem_viz.prior.config import prior_category

        try:
            category: str | None = prior_category(get_prior(prior or self.toolbox.settings.prior)).name
        except (ValueError, RuntimeError, OSError):
            category = None
        return suggested_preset(self.efem_scene(), category)

    def run_efem(self, *, preset: str | None = None, proposals: int | None = None, free_space: str = "auto",
                 seed: int = 0, wait: bool = False) -> list[int] | None:
        """Run EFEM on the whole scan with the chosen prior (`settings.prior`); its instances become unreviewed
        pre-labels (painted only where nothing is labelled), and the result is saved beside the journal
        (`<scan>.annotate/<scan>.efem.npz`, the last run) so that it can be imported again.

        The solver runs in a background thread; `hooks.on_efem` reports what it does and its progress, and
        `cancel_efem` (the Cancel EFEM run button) stops it at its next step.

        Args:
            preset: solver preset (None: the one that fits the scan and the chosen prior, `suggested_preset`).
            proposals: first-episode proposals (None: the preset's).
            free_space: the free-space check against the scan's recorded cameras, auto | on | off
                (`SolveSettings.free_space`: auto is the preset's; on adds the check for fused scans).
            seed: EM seed.
            wait: run in the calling thread and return the new pre-label ids (tests, scripts).

        Returns:
            With `wait`, the new pre-label instance ids ([] when cancelled or nothing was found); else None.

        Raises:
            ValueError: another EFEM job is running, or a bad preset / proposal count / free-space mode.
        """
        from efem_viz.em.config import SolveSettings

        settings = SolveSettings(preset=preset or self.suggested_preset(),  # type: ignore[arg-type]
                                 proposals=None if not proposals else int(proposals),
                                 free_space=free_space)  # type: ignore[arg-type]  # checked by config()
        own_voxel = settings.config().compute.work_voxel  # a bad preset, count or mode: one clear error first
        if self.scan.n > EFEM_FULL_RESOLUTION_POINTS and (own_voxel or 0.0) < EFEM_BIG_SCAN_VOXEL:
            settings = dataclasses.replace(settings, work_voxel=EFEM_BIG_SCAN_VOXEL)  # a preset's coarser one stays
        self.result_path()  # and an output that would land outside the output folder
        prior_name = self.toolbox.settings.prior
        cancel = self._claim("efem")
        try:
            self.hooks.on_efem(f"EFEM ({settings.preset}, prior {prior_name!r}): starting …", 0.0)
            self.hooks.on_segment(None)  # the segment buttons: a click-to-segment now waits
        except BaseException:
            self._release()
            raise
        if wait:
            return self._efem_job(settings, prior_name, seed, cancel)
        self._thread = threading.Thread(
            target=lambda: self.hooks.report(lambda: self._efem_job(settings, prior_name, seed, cancel)),
            name="annotator-efem", daemon=True)
        self._thread.start()
        return None

    def _efem_job(self, settings: SolveSettings, prior_name: str, seed: int, cancel: threading.Event) -> list[int]:
        from annotator import efem_runs
        from annotator.io import labels_from_result
        from efem_viz.em.solver import EMCancelled

        voxel = settings.config().compute.work_voxel  # forced here, or the preset's own
        what = f"EFEM ({settings.preset}, prior {prior_name!r}" + (
            f", on a {1000 * voxel:g} mm working set" if voxel else "") + (
            f", free space {settings.free_space}" if settings.free_space != "auto" else "") + ")"

        last_drawn = [-float("inf")]
        found = [""]  # the newest drawn state's count, said on every step's line

        def on_step(info: Any) -> None:
            every, now = self.progressive_every_s, time.monotonic()
            if every is not None and info.partial is not None and (info.step <= 0 or now - last_drawn[0] >= every):
                last_drawn[0] = now
                overlay = RunOverlay.of_result(info.partial(), self.efem_scene().points)
                self._draw_run_overlay(overlay)
                found[0] = f" · {overlay.accepted} found so far" if overlay.accepted else ""
            self.hooks.on_efem(f"{what}: step {info.step + 1} of {info.num_steps} · {info.status()}{found[0]} "
                               "(Cancel stops it)", round(100.0 * (info.step + 1) / max(info.num_steps, 1), 1))

        t0 = time.perf_counter()
        try:
            from efem_viz.prior import fused

            fused.prepare(lambda notice: self.hooks.on_efem(f"{what}: {notice}", 0.0))  # a first run builds them
            result = efem_runs.solve_scan(self.efem_scene(), prior_name=prior_name, settings=settings, seed=seed,
                                       on_step=on_step, cancel=cancel)
            if cancel.is_set():  # pressed after the last step: still nothing is added
                raise EMCancelled("cancelled after the last step")
            self.hooks.on_efem(f"{what}: saving the result and adding pre-labels …", 100.0)
            path = self.result_path()  # checked again: the folder may have changed during the run
            result.save(path)
            self.last_run_path = path
            ids = self.add_prelabels(labels_from_result(result, self.scan.n, where=path.name), source=path.name)
        except EMCancelled:
            self.hooks.notify("EFEM run cancelled", f"{what} was stopped; nothing was added")
            return []
        finally:
            try:
                self._draw_run_overlay(None)  # the pre-labels (if any) are painted: the run's overlay goes
                self.hooks.on_efem(None, None)  # the panel first: once the job is released, it shows the end
            finally:
                self._release()
                self.hooks.on_segment(None)
        self.hooks.notify("EFEM pre-labels", f"{what} found {len(result.instances)} instance(s) in "
                          f"{time.perf_counter() - t0:.0f} s: {len(ids)} pre-label(s) to review"
                          + (f", {self.skipped_prelabels} left out (mostly on labelled vertices)"
                             if self.skipped_prelabels else "")
                          + f" (result saved as {path.name} beside the journal)")
        return ids

    def _draw_run_overlay(self, overlay: RunOverlay | None) -> None:
        """Show a running EFEM's progress over the scan (None: remove it); redraws the vertices it changed."""
        before, self.run_overlay = self.run_overlay, overlay
        if overlay is not None:
            touched = overlay.changed(before)
        else:
            touched = np.zeros(0, np.int64) if before is None else np.flatnonzero(before.codes)
        if len(touched):
            self.hooks.on_preview(touched)

    def set_preview(self, idx: np.ndarray | None) -> None:
        """Highlight a proposed mask (None clears it) without touching the labels."""
        old = self.preview
        if idx is None or len(idx) == 0:
            self.preview, self.pending_segment = None, None
        else:
            preview = np.zeros(self.scan.n, bool)
            preview[idx] = True
            self.preview = preview
            self.pending_segment = np.asarray(idx, np.int32)
        touched = np.zeros(0, np.int64)
        for m in (old, self.preview):
            if m is not None:
                touched = np.union1d(touched, np.flatnonzero(m))
        self.hooks.on_preview(touched)
        self.hooks.on_segment(None)

    def accept_segment(self) -> Delta | None:
        """Paint the previewed segment as a new instance (category from the prior name)."""
        if self.pending_segment is None:
            raise ValueError("no segment preview to accept: Ctrl+click with the segment tool first")
        idx = self.pending_segment
        self.set_preview(None)
        self.instances.new_instance(category=self.toolbox.settings.prior or "object")
        return self.painting.paint(idx)

    def cancel_efem(self) -> bool:
        """Stop an EFEM run on the scan at its next step (the Cancel EFEM run button); a click-to-segment job or
        its preview is left alone. Returns whether a run was asked to stop."""
        with self._segment_lock:
            running = self._segment_cancel if self._job == "efem" else None
        if running is not None:
            running.set()
        return running is not None

    def join_jobs(self, timeout: float = 60.0) -> None:
        """Cancel a running EFEM job and wait for its thread (closing the app)."""
        with self._segment_lock:
            running, thread = self._segment_cancel, self._thread
        if running is not None:
            running.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)

    def discard_segment(self) -> None:
        """Drop the segment preview; while a click-to-segment run is in progress, cancel it (Esc). An EFEM run on
        the scan is left alone (`cancel_efem`: minutes of work are not lost to an Esc meant for a preview)."""
        with self._segment_lock:
            running = self._segment_cancel if self._job == "segment" else None
        if running is not None:
            running.set()
            return
        self.set_preview(None)
