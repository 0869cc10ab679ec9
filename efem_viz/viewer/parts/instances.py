"""The instance table's part: choose, show or hide, fly to and step through the final instances of the result."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from efem_viz.serve.table import option_id, step_row
from efem_viz.viewer.texts import instance_options

if TYPE_CHECKING:
    from efem_viz.viewer.parts.core import ViewerCore
    from efem_viz.viewer.parts.results import ResultPart


class FlyTarget(NamedTuple):
    """Where to point a camera for one final instance."""

    pid: int
    lo: np.ndarray
    """(3,) world-frame minimum of the instance's points (of its box when it has none)."""
    hi: np.ndarray
    """(3,) world-frame maximum."""
    scene_diagonal: float
    below_threshold: bool
    """The instance is below the confidence threshold (not drawn)."""
    confidence: float


class InstancePart:
    """The Results tab's instance table over the shown result (rows most confident first)."""

    def __init__(self, core: ViewerCore, results: ResultPart) -> None:
        self.core = core
        """The session's shared parts."""
        self.results = results
        """The results part (the drawn instances)."""

    def instance_index(self, pid: int | None) -> int:
        """Position in the result's instances of proposal id `pid`.

        Raises:
            ValueError: no result, no instance chosen, or no instance with that id.
        """
        res = self.core.state.result
        if res is None:
            raise ValueError("no result: load or run one first")
        if pid is None:
            raise ValueError("no instance chosen: pick one in the Instance dropdown")
        hit = np.flatnonzero(np.asarray(res.instances.ids).reshape(-1) == int(pid))
        if hit.size == 0:
            raise ValueError(f"the result has no instance #{int(pid)}")
        return int(hit[0])

    def table_options(self) -> tuple[str, ...]:
        """The instance table's rows (most confident first) as dropdown options; keeps `state.table_row` on one
        of them (the first when none or a stale one is chosen). Empty without instances."""
        s = self.core.state
        if s.result is None or len(s.result.instances) == 0:
            return ()
        opts = instance_options(s.result.instances)
        if s.table_row is not None and s.table_row not in {option_id(o) for o in opts}:
            s.table_row = None
        if s.table_row is None:  # the dropdown shows the first row: that is the one chosen
            s.table_row = option_id(opts[0])
        return opts

    def choose_instance(self, pid: int | None) -> None:
        """Choose a row of the instance table (None: none). Raises ValueError for an unknown id."""
        with self.core.lock:
            if pid is not None:
                self.instance_index(pid)
            self.core.state.table_row = None if pid is None else int(pid)

    def set_instance_visible(self, pid: int | None, visible: bool) -> None:
        """Show or hide one final instance (a view like the threshold). Raises ValueError for an unknown id."""
        with self.core.lock:
            self.instance_index(pid)
            assert pid is not None
            s = self.core.state
            s.table_row = int(pid)
            if visible:
                s.hidden.discard(int(pid))
            else:
                s.hidden.add(int(pid))

    def fly_target(self, pid: int | None) -> FlyTarget:
        """Choose instance `pid` in the table and say where a camera should look at it (the status line says so
        when it is below the threshold).

        Raises:
            ValueError: no such instance.
        """
        with self.core.lock:
            k = self.instance_index(pid)
            s = self.core.state
            inst, scene = s.require_result().instances, s.require_scene()
            mask = np.asarray(inst.masks[k], np.int64)
            pts = scene.points[mask] if mask.size else np.asarray(inst.obb(k).corners, np.float64)
            lo_s, hi_s = scene.bounds
            s.table_row = int(inst.ids[k])
            target = FlyTarget(pid=int(inst.ids[k]), lo=pts.min(axis=0), hi=pts.max(axis=0),
                               scene_diagonal=float(np.linalg.norm(np.subtract(hi_s, lo_s))),
                               below_threshold=not bool(inst.kept(s.threshold)[k]),
                               confidence=float(inst.confidence[k]))
        if target.below_threshold:
            self.core.set_status(f"Instance #{target.pid} (confidence {target.confidence:.2f}) is below the "
                                 f"confidence threshold {s.threshold:.2f}: lower it to see the instance.")
        return target

    def next_instance(self, step: int) -> int:
        """The proposal id of the next (`step` = 1) or previous (-1) row of the instance table (most confident
        first, wrapping around).

        Raises:
            ValueError: no result or no instance.
        """
        with self.core.lock:
            res = self.core.state.result
            if res is None or len(res.instances) == 0:
                raise ValueError("no instances: load or run a result first")
            ids = [option_id(o) for o in instance_options(res.instances)]
            return step_row(ids, self.core.state.table_row, step)
