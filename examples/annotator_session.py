"""Label a scan from a script with the annotator's headless session: no viser, no browser, the same journal.

`annotator.session.AnnotatorSession` is everything the annotator does, without its GUI (the viser app,
`annotator.app.AnnotatorApp`, is a thin layer over it). Every edit goes through the crash-safe journal, so a
script's labels open in `efem-annotate` afterwards and survive a crash like a person's. This example

1. opens a bundled real scan (`sample_scenes/real_tabletop_6.ply`; the scan itself is never written) with its
   journal under `--out`;
2. imports the scan's precomputed EFEM result as pre-labels and accepts those above a confidence cut;
3. adds an instance by region growing from a vertex, undoes it and redoes it;
4. exports the labels (PLY), closes, and reopens the session: the journal gives back the same labels.

Run (a few seconds)::

    python examples/annotator_session.py
    python examples/annotator_session.py --cut 0.3 --out /tmp/labels
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="real_tabletop_6", help="a scan of sample_scenes/ with its .efem.npz")
    ap.add_argument("--cut", type=float, default=0.2, help="accept pre-labels at or above this confidence")
    ap.add_argument("--out", type=Path, default=None, help="journal and export folder (default: a temp dir)")
    args = ap.parse_args(argv)

    from annotator.session import AnnotatorSession

    out = args.out or Path(tempfile.mkdtemp(prefix="efem_annotate_example_"))
    scan = REPO / "sample_scenes" / f"{args.scene}.ply"

    # ---- 1. open: the journal and checkpoint go to <out>/<scan>.annotate/
    s = AnnotatorSession(scan, out_dir=out, autosave_delay=0.0)
    s.notify = lambda title, body: print(f"  [{title}] {body}")
    labels = s.scan.store.labelset
    print(f"opened {scan.name}: {s.scan.n} vertices, {len(labels.instances)} instances to start with")

    # ---- 2. EFEM pre-labels, reviewed by a confidence cut
    pre = s.assist.import_efem(str(scan.with_suffix("").with_suffix(".efem.npz")))
    print(f"imported {len(pre)} pre-labels")
    accepted = s.assist.review_prelabels(args.cut, "accept")
    rejected = s.assist.review_prelabels(args.cut, "reject")
    print(f"accepted {len(accepted)} at confidence >= {args.cut}, rejected {len(rejected)} below it")

    # ---- 3. a new instance by region growing from the highest unlabelled vertex, with undo / redo
    free = np.flatnonzero(s.scan.store.labels == 0)
    seed = int(free[np.argmax(s.scan.scene.points[free, 2])])
    new_id = s.instances.new_instance(category="object")
    s.painting.grow(seed)
    grown = int((s.scan.store.labels == new_id).sum())
    s.instances.undo()
    after_undo = int((s.scan.store.labels == new_id).sum())
    s.instances.redo()
    print(f"region grow from vertex {seed}: {grown} vertices; after undo {after_undo}; after redo "
          f"{int((s.scan.store.labels == new_id).sum())}")

    # ---- 4. export, close, reopen from the journal
    written = s.files.export("ply")
    snapshot = s.scan.store.labels.copy()
    s.close()
    print(f"exported {[p.name for p in written]}")
    again = AnnotatorSession(scan, out_dir=out, autosave_delay=0.0)
    same = bool(np.array_equal(again.scan.store.labels, snapshot))
    print(f"reopened from the journal: labels identical {same}, "
          f"{len(again.scan.store.labelset.instances)} instances")
    again.close()
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
