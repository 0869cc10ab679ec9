"""The parts of the annotator's headless session (`annotator.session.AnnotatorSession`): one job each.

`context` holds what the parts share (the GUI hooks, the tool table and its settings); `scan` opens the scan and
its label store (and warms up its ray caster); `cursor` is the brush cursor (`session.brush`); `instances` the
active tool and the instance table (create, update, delete, merge, undo, redo); `paint` paints (dabs, strokes,
region grow, fill, the active tool at a point; `session.painting`); `box_lasso` is box and lasso selection; `files`
exports and imports labels; `assist` is EFEM assistance (pre-labels and their review, click-to-segment and its
thread). No part imports viser or a drawing module (`tests/test_layering.py` checks it); docs/INTERFACES.md has the
table.
"""
