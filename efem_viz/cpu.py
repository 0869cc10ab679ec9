"""How a process of efem-viz shares the machine: OpenMP threads that sleep instead of spinning, a torch thread
count taken from the cores that are free, and (for the long-lived annotator server) an allocator that gives large
freed arrays back to the system.

Torch's OpenMP threads spin at every barrier for a while before they sleep. On a machine whose cores are all busy
(two cores and a test suite or a training run beside the solve), a spinning thread holds a core that the thread it
waits for needs, and a solve took 10x its quiet time. Two remedies, both applied by the command-line entry points
before torch is imported:

* `configure_openmp`: ``OMP_WAIT_POLICY=PASSIVE`` (threads sleep at once at a barrier) unless the user set it;
* `free_cores`: the number of cores not busy with other work (from the 1-minute load average), which the
  commands use as their torch thread count when no ``--threads`` was given.

Memory (`configure_allocator`): glibc's malloc raises its mmap threshold each time a large block is freed (up to
32 MB), so later arrays of a few to 32 MB (a 10M-vertex scan's masks, colours and label copies) come from the heap,
and what an edit frees there stays with the process. On a 9.9M-vertex scan each whole-scan edit left 40-120 MB
behind (2.49 -> 2.81 GB over ten label imports, the heap's free part 92 -> 407 MB while what was in use stayed at
425 MB). A fixed threshold sends every array of 8 MB or more to mmap, which returns it at once: the same ten edits
stay flat after the second.

Torch-free at import.
"""

from __future__ import annotations

import math
import os
import sys

WAIT_POLICY_VAR = "OMP_WAIT_POLICY"


def cpu_count() -> int:
    """CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def configure_openmp() -> bool:
    """Ask OpenMP threads to sleep at barriers (``OMP_WAIT_POLICY=PASSIVE``) unless the environment already says
    otherwise. Effective only before torch is first imported (OpenMP reads it once); returns whether it took
    effect (False when torch was imported already or the user chose a policy)."""
    if WAIT_POLICY_VAR in os.environ or "torch" in sys.modules:
        return False
    os.environ[WAIT_POLICY_VAR] = "PASSIVE"
    return True


MMAP_THRESHOLD_BYTES = 8 << 20
"""Blocks of this size or more are mapped on their own (and returned to the system when freed); see the module doc."""
MMAP_THRESHOLD_VAR = "MALLOC_MMAP_THRESHOLD_"
"""The environment variable with which a user sets glibc's threshold instead (then `configure_allocator` keeps it)."""


def configure_allocator(threshold: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc malloc's mmap threshold at `threshold` bytes (no dynamic raise), so that freed large arrays go back
    to the system instead of staying in the heap. Returns whether it took effect: False off glibc, or when the user
    set ``MALLOC_MMAP_THRESHOLD_``."""
    if MMAP_THRESHOLD_VAR in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    m_mmap_threshold = -3  # glibc's M_MMAP_THRESHOLD
    return bool(mallopt(m_mmap_threshold, int(threshold)))


def free_cores(*, load: float | None = None, cpus: int | None = None) -> int:
    """Cores not busy with other work: the usable CPUs minus the 1-minute load average (rounded to the nearest
    whole core), at least 1.

    Args:
        load: the load to subtract (default: `os.getloadavg()[0]`, 0 where the platform has none).
        cpus: the usable CPUs (default: `cpu_count`).
    """
    n = cpu_count() if cpus is None else max(1, int(cpus))
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):
            load = 0.0
    if not math.isfinite(load) or load < 0:
        load = 0.0
    return max(1, min(n, n - int(math.floor(load + 0.5))))


def set_torch_threads(threads: int | None) -> int:
    """Set torch's intra-op threads: ``threads`` when given, else `free_cores`. Returns the count set."""
    import torch

    n = int(threads) if threads else free_cores()
    torch.set_num_threads(max(1, n))
    return max(1, n)
