"""How a process of efem-viz shares the CPU: OpenMP threads that sleep instead of spinning, and
a torch thread count taken from the cores that are free.

Torch's OpenMP threads spin at every barrier for a while before they sleep. On a machine whose cores are all busy
(two cores and a test suite or a training run beside the solve), a spinning thread holds a core that the thread it
waits for needs, and a solve took 10x its quiet time. Two remedies, both applied by the command-line entry points
before torch is imported:

* `configure_openmp`: ``OMP_WAIT_POLICY=PASSIVE`` (threads sleep at once at a barrier) unless the user set it;
* `free_cores`: the number of cores not busy with other work (from the 1-minute load average), which the
  commands use as their torch thread count when no ``--threads`` was given.

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
