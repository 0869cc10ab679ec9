"""efem-annotate: per-vertex instance labelling of scans in the browser.

Modules: `labels` (label store, pure), `selection` (brush / grow / fill / box, pure), `journal` (append-only
journal, atomic checkpoint, `LabelStore`), `io` (label formats, scan loading, path safety), `render` (chunks and
colours), `assist` (click-to-segment with EFEM), `app` (the viser layer; the only module importing viser).
"""
