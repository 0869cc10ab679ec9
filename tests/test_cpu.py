"""How a process shares the machine (`efem_viz.cpu`): the allocator setting the annotator server starts with gives
freed large arrays back to the system (the CPU settings are tested with the batch runner)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# A long-lived server's pattern on a big scan: a large array freed (glibc then raises its mmap threshold), then
# arrays of 10-30 MB made and dropped while small blocks that stay are made in between (as an edit's temporaries
# and the label table, history entries or messages it keeps). Prints the resident-set growth in MB.
PATTERN = """
import sys
import numpy as np
sys.path.insert(0, {root!r})
{setup}
def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) >> 10
big = np.ones(30 << 20, np.uint8)
del big
kept = []
r0 = rss_mb()
for i in range(20):
    a = np.ones((10 << 20) + i * (1 << 20), np.uint8)
    kept.append(np.ones(64 << 10, np.uint8))
    del a
print(rss_mb() - r0)
"""


def _growth_mb(setup: str) -> int:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}  # no MALLOC_* variable from the caller
    run = subprocess.run([sys.executable, "-c", PATTERN.format(root=str(ROOT), setup=setup)], capture_output=True,
                         text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    return int(run.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_the_annotator_gives_freed_large_arrays_back_to_the_system() -> None:
    """Without the setting, the freed arrays stay with the process (the heap keeps them: tens of MB here, 40-120 MB
    per whole-scan edit on a 9.9M-vertex scan); `efem-annotate`'s entry point sets it, and then only the small
    blocks kept (1.3 MB) remain."""
    assert _growth_mb("") >= 20  # the pattern shows the retention this guards against
    entry = "from annotator.__main__ import main\nassert main(['--version']) == 0"
    assert _growth_mb(entry) <= 5


def test_a_users_own_threshold_is_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    from efem_viz.cpu import MMAP_THRESHOLD_VAR, configure_allocator

    monkeypatch.setenv(MMAP_THRESHOLD_VAR, "65536")
    assert configure_allocator() is False
