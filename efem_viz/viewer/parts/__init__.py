"""The parts of the viewer's headless session (`efem_viz.viewer.session.ViewerSession`): one job each.

`core` holds what every part shares (the `ViewerState`, the lock, the status line, the priors, the scene
generation); `scenes` opens scenes and sets the display; `results` loads and shows results, the confidence cut, the
mask band, the ground-truth comparison and the point colours; `instances` is the instance table; `runs` runs EFEM
(thread-safe start, progress, cancel); `timeline` steps through the EM iterations; `inspect` replays one proposal
(the Fig. S9 views; `session.inspection`); `exporting` writes results and the static demo (`session.export`). No
part imports viser or a drawing module (`tests/test_layering.py` checks it); docs/INTERFACES.md has the table.
"""
