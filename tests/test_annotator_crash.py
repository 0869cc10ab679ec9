"""Crash safety: a process making edits is killed with SIGKILL mid-edit; reopening recovers every acknowledged edit.

The child applies a deterministic edit sequence through `LabelStore` (journal fsync before acknowledging) with a
fast autosave (so checkpoint rewrites are also in flight) and prints "ACK k" after edit k returns. The parent
kills it at a random moment, reopens the store and checks that the recovered state equals the state after the
last acknowledged edit, or after the one in flight (it may have reached the disk before the ack was printed).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from annotator.store import LabelStore
from annotator.labels import LabelSet

N = 120_000
CHILD = textwrap.dedent(
    """
    import sys, numpy as np
    from annotator.store import LabelStore
    from annotator.labels import LabelSet
    sys.path.insert(0, {here!r})
    from test_annotator_crash import edit, N
    d = sys.argv[1]
    s = LabelStore(N, journal_path=d + "/c.journal", label_path=d + "/c.labels.npz", autosave_delay=0.01)
    print("READY", flush=True)
    for k in range(10_000):
        edit(k, s)
        print("ACK", k, flush=True)
    """
)


def edit(k: int, target) -> None:
    """Edit number k of the deterministic sequence; `target` is a LabelStore (child) or LabelSet (reference)."""
    if isinstance(target, LabelSet):
        def do(build):
            target.apply(build(target))

        undo = target.undo
    else:
        do = target.do
        undo = target.undo
    if k < 3:
        do(lambda ls: ls.create_instance(category="mug"))
    elif k % 7 == 0:
        undo()
    else:
        start = (k * 7919) % N
        idx = (np.arange(start, start + 30_000) % N).astype(np.int32)
        do(lambda ls: ls.paint(idx, 1 + k % 3))


def _reference(n_edits: int) -> list[np.ndarray]:
    ls = LabelSet(N)
    states = [ls.labels.copy()]
    for k in range(n_edits):
        edit(k, ls)
        states.append(ls.labels.copy())
    return states


@pytest.mark.parametrize("kill_after_acks", [4, 11, 23])
def test_sigkill_mid_edit_loses_nothing_acknowledged(tmp_path: Path, kill_after_acks: int) -> None:
    here = str(Path(__file__).parent)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(here).parent), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(here=here), str(tmp_path)],
        stdout=subprocess.PIPE, text=True, env=env,
    )
    acked = -1
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "READY"
        while acked < kill_after_acks:
            line = proc.stdout.readline()
            assert line.startswith("ACK"), line
            acked = int(line.split()[1])
        # Land the kill at an arbitrary point inside the next edits (journal write, apply or checkpoint).
        time.sleep(float(np.random.default_rng(kill_after_acks).uniform(0.0, 0.05)))
        os.kill(proc.pid, signal.SIGKILL)
        for line in proc.stdout:  # acks printed before the kill landed count too
            if line.startswith("ACK"):
                acked = int(line.split()[1])
    finally:
        proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    ref = _reference(acked + 3)
    s = LabelStore(N, journal_path=tmp_path / "c.journal", label_path=tmp_path / "c.labels.npz", autosave_delay=0)
    try:
        got = s.labels
        ok_after = [k for k in (acked + 1, acked + 2) if np.array_equal(got, ref[k])]
        assert ok_after, f"recovered labels match neither edit {acked} (acknowledged) nor the one in flight"
        # the recovered history undoes exactly like the reference history
        ls = LabelSet(N)
        for k in range(ok_after[0]):
            edit(k, ls)
        s.undo()
        ls.undo()
        assert np.array_equal(s.labels, ls.labels)
    finally:
        s.close()
