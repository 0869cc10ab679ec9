"""The annotator server's memory over whole-scan edits on a big scan (the whole app, not only its label store).

Opens `AnnotatorApp` (no browser) on an N-vertex height-field mesh (the one `bench.annotator_scale` builds, cached),
then imports a pre-label file K times (two files in turn, each relabelling every vertex: the worst edit) and
records the resident set and glibc's heap/mmap split after each. With `--allocator default` it runs without the
allocator setting `efem-annotate` starts with (`efem_viz.cpu.configure_allocator`), to show what it fixes.

Usage: python -m bench.annotator_memory [--n-side 3146] [--edits 25] [--allocator fixed|default]
Writes bench/results/annotator_memory/annotator_memory_<allocator>.json.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, result_path, rss_mb, write_result  # first: the OpenMP wait policy, before torch


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]


def _heap() -> dict[str, int]:
    """glibc's view (MB): heap size, its part in use and free, and memory in separate mappings."""
    try:
        f = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):
        return {}
    f.restype = _MallInfo2
    m = f()
    return {"heap_mb": m.arena >> 20, "heap_in_use_mb": m.uordblks >> 20, "heap_free_mb": m.fordblks >> 20,
            "mmap_mb": m.hblkhd >> 20}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-side", type=int, default=3146, help="vertices per side (3146: 9.9M vertices)")
    ap.add_argument("--edits", type=int, default=25)
    ap.add_argument("--allocator", choices=("fixed", "default"), default="fixed")
    a = ap.parse_args()
    from efem_viz.cpu import configure_allocator

    applied = configure_allocator() if a.allocator == "fixed" else False
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    from annotator.app import AnnotatorApp
    from annotator.io import save_labels_npz
    from annotator.labels import InstanceInfo
    from bench.annotator_scale import make_surface
    from efem_viz.data.io import save_scene

    n = a.n_side ** 2
    cached = Path.home() / ".cache" / "efem-viz" / "bench" / f"surface_{a.n_side}.ply"
    if not cached.is_file():
        cached.parent.mkdir(parents=True, exist_ok=True)
        save_scene(make_surface(a.n_side), cached)
    tmp = Path(tempfile.mkdtemp(prefix="bench_annotator_memory_"))
    try:
        scan = shutil.copy(cached, tmp / "surface.ply")
        rng = np.random.default_rng(0)
        files = []
        for k in range(2):
            p = tmp / f"prelabels_{k}.npz"
            save_labels_npz(rng.integers(0, 6, n).astype(np.int32),
                            {i: InstanceInfo(i, f"object {i}") for i in range(1, 6)}, p)
            files.append(p)
        t0 = time.perf_counter()
        app = AnnotatorApp(scan, out_dir=tmp / "out", port=0, autosave_delay=0.5, max_points=max(n, 2_000_000))
        app.wait_idle(600)
        rows = [{"edit": 0, "rss_mb": rss_mb(), **_heap()}]
        print(f"open: {time.perf_counter() - t0:.0f} s, RSS {rows[0]['rss_mb']} MB", flush=True)
        for e in range(a.edits):
            app.session.files.import_labels(str(files[e % 2]))
            app.wait_idle(600)
            time.sleep(1.0)  # the autosave (0.5 s after the edit) has run
            rows.append({"edit": e + 1, "rss_mb": rss_mb(), **_heap()})
            print(f"edit {e + 1}: RSS {rows[-1]['rss_mb']} MB {_heap()}", flush=True)
        app.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    after2 = [r["rss_mb"] for r in rows[2:]]
    out = {"machine": machine(1), "vertices": n, "edits": a.edits, "allocator": a.allocator,
           "allocator_setting_applied": applied, "rows": rows,
           "rss_growth_after_edit_2_mb": (max(after2) - after2[0]) if after2 else None}
    write_result(result_path("annotator_memory", a.allocator), out)
    print(f"RSS growth from edit 2 to {a.edits}: {out['rss_growth_after_edit_2_mb']} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
