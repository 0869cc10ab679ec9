"""What every bench shares: the checkout on `sys.path`, the CLIs' OpenMP wait policy, the record of the machine a
number was measured on, and where results are written.

Import it first (`from bench.common import ROOT, machine`), before anything imports torch: OpenMP reads its wait
policy once, and the CLIs make waiting threads sleep (`efem_viz.cpu.configure_openmp`), so a bench measures what a
user runs, and two threads cost no more than one on a shared machine. `rss_mb` is the resident set the memory
benches record. A bench writes `result_path(NAME)` (``bench/results/NAME/latest.json``) or, for a named candidate,
`result_path(NAME, tag)` (``bench/results/NAME/NAME_<tag>.json``), through `write_result`.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import argparse

ROOT = Path(__file__).resolve().parents[1]
"""The checkout (first on `sys.path`: a bench measures this tree, not an installed copy)."""
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))

from efem_viz.cpu import configure_openmp  # noqa: E402 - after the path: this checkout's efem_viz

configure_openmp()

RESULTS = ROOT / "bench" / "results"
"""One folder per bench under it."""


def result_path(bench: str, tag: str | None = None) -> Path:
    """Where bench ``bench`` writes: its ``latest.json``, or ``<bench>_<tag>.json`` for a named run."""
    return RESULTS / bench / ("latest.json" if not tag else f"{bench}_{tag}.json")


def write_result(path: Path, out: Any, *, indent: int = 1, archive: bool = True) -> Path:
    """Write a result atomically (JSON; numpy scalars and arrays as numbers and lists) and say where. A new
    ``latest.json`` first moves the one it replaces aside as ``<bench>_<date>.json`` (its file date; ``_2``, ``_3``
    ... when that name is taken), unless ``archive`` is False (a bench that updates sections of its record, or
    writes its record again after each part). Returns ``path``."""
    from efem_viz.data.io import atomic_write_text

    path.parent.mkdir(parents=True, exist_ok=True)
    if archive and path.name == "latest.json" and path.exists():
        day = time.strftime("%Y-%m-%d", time.gmtime(path.stat().st_mtime))
        kept = path.with_name(f"{path.parent.name}_{day}.json")
        n = 1
        # taken: a second run of the day, a tag that reads like a date, or a record gzipped since
        while kept.exists() or kept.with_name(kept.name + ".gz").exists():
            n += 1
            kept = path.with_name(f"{path.parent.name}_{day}_{n}.json")
        path.replace(kept)
    text = json.dumps(out, indent=indent, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    atomic_write_text(path, text)
    print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")
    return path


def replay_parser(doc: str | None) -> "argparse.ArgumentParser":
    """The options of the kernel replay benches (`bench.decoder_kernel`, `bench.encoder_kernel`): the scenes whose
    solve is recorded, repeats, torch threads and the record's tag; the bench adds its own."""
    import argparse

    ap = argparse.ArgumentParser(description=(doc or "").split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["real_tabletop_0", "z_7000"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--tag", default=None)
    return ap


def kernels_or_say(threads: int) -> bool:
    """Set the torch threads and load the fused kernels; False, said in one line, where they are unavailable."""
    import torch

    from efem_viz.prior import fused

    torch.set_num_threads(threads)
    if fused.load():
        return True
    print("the fused kernels are unavailable on this machine: nothing to compare")
    return False


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
