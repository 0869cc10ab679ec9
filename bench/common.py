"""What every bench script shares: the checkout on `sys.path`, the CLIs' OpenMP wait policy, and the record of the
machine a number was measured on.

Import it first (`from common import ROOT, machine`), before anything imports torch: OpenMP reads its wait policy
once, and the CLIs make waiting threads sleep (`efem_viz.cpu.configure_openmp`), so a bench measures what a user
runs, and two threads cost no more than one on a shared machine. `rss_mb` is the resident set the memory benches
record.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
"""The checkout (first on `sys.path`: a bench measures this tree, not an installed copy)."""
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))

from efem_viz.cpu import configure_openmp  # noqa: E402 - after the path: this checkout's efem_viz

configure_openmp()


def rss_mb() -> int:
    """Resident set of this process now, MB (Linux; -1 elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024)
    except OSError:
        pass
    return -1


def cpu_model() -> str:
    """The CPU's model name (Linux), else the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine(threads: int | None = None) -> dict[str, Any]:
    """What a number was measured on: platform, CPU model and capability (torch's AVX2 / AVX512 / ...), whether
    bf16 matrix work is native, CPUs, torch threads, the wait policy and the 1-minute load."""
    import torch

    from efem_viz.prior.config import fast_cpu_bf16

    return {"platform": platform.platform(), "cpu": cpu_model(), "cpus": os.cpu_count(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(), "native_bf16": bool(fast_cpu_bf16()),
            "torch_threads": threads if threads is not None else torch.get_num_threads(), "torch": torch.__version__,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", ""), "load_1min": os.getloadavg()[0]}
