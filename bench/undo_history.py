"""Undo history on a big scan: memory per whole-scan edit, reopening, undoing an old edit.

Drives `LabelStore` directly (the annotator's one store) on N vertices: two instances, then K edits that each
repaint every vertex (the worst case: a whole-scan import or fill). Prints and records the resident set after each
edit, then closes (final checkpoint), reopens and reports the reopening seconds and its memory, and the seconds of
undoing all K edits after the reopen (each is read back from the journal).

Usage: python -m bench.undo_history [--n 9900000] [--edits 10] [--history-mb 256]
Writes bench/results/undo_history/latest.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import result_path, rss_mb, write_result  # first: the OpenMP wait policy, before torch



def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=9_900_000)
    ap.add_argument("--edits", type=int, default=10)
    ap.add_argument("--history-mb", type=int, default=256)
    a = ap.parse_args()
    from annotator.store import LabelStore

    out: dict[str, object] = {"machine": f"{platform.machine()}, {platform.processor() or 'cpu'}", "n": a.n,
                              "edits": a.edits, "history_mb": a.history_mb}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {"journal_path": Path(tmp) / "s.journal", "label_path": Path(tmp) / "s.labels.npz"}
        rss0 = rss_mb()
        s = LabelStore(a.n, autosave_delay=0, history_bytes=a.history_mb << 20, **paths)
        s.do(lambda ls: ls.create_instance(category="mug"))
        s.do(lambda ls: ls.create_instance(category="bowl"))
        after_open = rss_mb()
        rss = []
        for i in range(a.edits):
            s.do(lambda ls, i=i: ls.paint(np.arange(ls.n), 1 + i % 2))
            rss.append(rss_mb())
        final = s.labels.copy()
        s.close()
        del s
        t0 = time.perf_counter()
        before_reopen = rss_mb()
        s2 = LabelStore(a.n, autosave_delay=0, history_bytes=a.history_mb << 20, **paths)
        reopen_s = time.perf_counter() - t0
        reopen_mb = rss_mb() - before_reopen
        assert np.array_equal(s2.labels, final)
        t0 = time.perf_counter()
        for _ in range(a.edits):
            s2.undo()
        undo_s = (time.perf_counter() - t0) / a.edits
        journal_mb = paths["journal_path"].stat().st_size / 2**20
        s2.close()
    growth = np.diff([after_open, *rss])
    out.update({"rss_mb_start": rss0, "rss_mb_after_open": after_open, "rss_mb_after_each_edit": rss,
                "median_growth_mb_per_edit": float(np.median(growth)), "journal_mb": round(journal_mb),
                "reopen_s": round(reopen_s, 2), "reopen_rss_growth_mb": reopen_mb,
                "undo_s_per_edit_after_reopen": round(undo_s, 3)})
    print(json.dumps(out, indent=1))
    write_result(result_path("undo_history"), out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
