"""efem-annotate: per-vertex instance labelling of scans in the browser.

Modules: `labels` (label store, pure), `selection` (brush / grow / fill / box, pure), `journal` (the append-only
journal's records and the atomic label file), `store` (`LabelStore`: journal first, autosaved checkpoint, recovery,
undo/redo), `io` (label formats, scan loading, path safety), `render` (chunks and
colours), `assist` (click-to-segment with EFEM), `tools` (the tool table, `ToolSettings`, the `ToolHost` contract),
`lasso` (the lasso outline), `session` (`AnnotatorSession`: every action, headless; the tools' host), `events` and
`panel_views` (the app's event checks and panel text, pure), `panels` (the GUI handles), `wiring` (GUI events →
actions), `scan_view` (drawing the scan, level of detail), `cheat_sheet`, `app` (the viser layer over the session;
the only module importing viser at run time).
"""
