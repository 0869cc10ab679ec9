"""The annotator's tool registry: one `Tool` entry per tool, read by the toolbar, hotkeys, help text and GUI.

A tool is a name, a label, a hotkey, one line of help, the setting controls it shows while active, and what it
does: `apply_at` acts on the surface point under a Ctrl/Cmd+click (and at the start of a Ctrl/Cmd+drag, unless the
tool paints strokes), `on_click` takes the raw click instead (the lasso needs the screen position and camera),
and `commands` are buttons with optional hotkeys (the lasso's Apply and Clear). The app (`annotator.app`) builds
its GUI from `DEFAULT_TOOLS` (or the `tools=` it is given) and dispatches every gesture through the active entry;
it has no per-tool branches. Adding a tool is one `Tool` entry plus its functions:

```python
def paint_ball(host, hit):  # everything within 3 cm of the click becomes the active instance
    idx = np.asarray(host.scan.geom.tree.query_ball_point(hit.position, 0.03), np.int64)
    host.painting.paint(idx, client=hit.client)

AnnotatorApp(scan, tools=(*DEFAULT_TOOLS, Tool("ball", "Ball", "P", "click paints a 3 cm ball", apply_at=paint_ball)))
```

Box select (Shift + drag) is a gesture of every tool; `erase` tools erase with it instead of painting. The
controls in `GESTURE_CONTROLS` (box select's and painting's) are always shown.

Hotkeys are single keys that neither the app (`APP_KEYS`) nor viser's browser client uses: W/A/S/D/Q/E move
viser's camera whatever the page does with them (`efem_viz.serve.camera`), so erase is X and segment is C.

Pure: no viser import (the tests of the tool table run without a server).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Literal, Protocol, Sequence

import numpy as np

from annotator.lasso import LassoCamera
from efem_viz.prior.config import DEFAULT_PRIOR
from efem_viz.serve.camera import VISER_CAMERA_KEYS

if TYPE_CHECKING:
    from annotator.labels import Delta
    from annotator.selection import ScanGeometry


@dataclass
class ToolSettings:
    """What the tool controls say; read from the GUI, never read by compute code directly."""

    tool: str = "brush"
    """Name of the active tool (an entry of the tool table)."""
    category: str = "object"
    """Category of new instances (N, *New instance*): the one the user chose last (typed into *Category*), or of
    the scan's labels when it has some."""
    radius: float = 0.01
    """Brush radius, metres."""
    brush_max_angle_deg: float = 180.0
    """Brush paints only vertices whose normal is within this angle of the hit normal (180 = no limit)."""
    grow_angle_deg: float = 20.0
    """Region grow: maximum normal change across one edge, degrees."""
    grow_distance: float = 0.15
    """Region grow: maximum distance from the seed, metres."""
    grow_min_height: float = 0.0
    """Region grow and fill never enter points lower than this above z = 0 (the table plane of imported
    tabletop scans), metres; 0 = off."""
    only_unlabelled: bool = False
    """Paint/grow/box change only unlabelled vertices."""
    labels_only: bool = False
    """The labels-only view: unlabelled vertices drawn in a faint grey (`annotator.render.compose_colors`)."""
    box_facing: str = "visible"
    """Box and lasso select: "visible" (what the camera sees), "front" (everything facing the camera, hidden or
    not) or "all" (through the object)."""
    active_id: int = 0
    """Active instance id (0 = none yet)."""
    prior: str = DEFAULT_PRIOR
    """Shape prior of the click-to-segment tool (the *Prior for Segment tool* dropdown)."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Settings of added tools' controls that have no field here (`annotator.tools.Control.setting` → value)."""

    def value(self, name: str) -> Any:
        """A setting by name: a field, else an added tool's (`extra`)."""
        return getattr(self, name) if hasattr(self, name) else self.extra[name]

    def assign(self, name: str, value: Any) -> None:
        """Set a setting by name: a field, else an added tool's (`extra`)."""
        if hasattr(self, name):
            setattr(self, name, value)
        else:
            self.extra[name] = value

    def shown_initial(self, c: Control) -> float | bool | str:
        """The value a control starts at, in display units: its field's value, else `c.initial` (which becomes
        the setting's value in `extra`)."""
        if not hasattr(self, c.setting):
            self.extra.setdefault(c.setting, float(c.initial) / c.scale if c.kind == "slider" else c.initial)
            return c.initial
        initial = getattr(self, c.setting)
        if c.kind == "slider":
            digits = max(0, -int(np.floor(np.log10(c.step)))) if c.step < 1 else 0
            initial = round(float(initial) * c.scale, digits)
        return initial


class HostToolbox(Protocol):
    """The part of a tool's host that holds the tool settings (`annotator.parts.context.Toolbox`)."""

    @property
    def settings(self) -> ToolSettings:
        """What the tool controls say."""
        ...


class HostScan(Protocol):
    """The part of a tool's host that holds the scan (`annotator.parts.scan.ScanPart`)."""

    @property
    def geom(self) -> ScanGeometry:
        """The scan's selection geometry."""
        ...


class HostPainting(Protocol):
    """The painting part of a tool's host (`annotator.parts.paint.PaintPart`): one journalled edit per call."""

    def paint(self, idx: np.ndarray, *, erase: bool = False, group: str = "", client: str = "") -> Delta | None:
        """Paint vertices with the active instance (or erase them)."""
        ...

    def dab(self, vertex: int, position: np.ndarray, *, erase: bool, client: str = "") -> Delta | None:
        """One brush dab at a surface point."""
        ...

    def grow(self, seed: int, *, client: str = "") -> Delta | None:
        """Region grow from a vertex."""
        ...

    def fill(self, seed: int, *, client: str = "") -> Delta | None:
        """Bucket fill from a vertex."""
        ...

    def pick_instance(self, vertex: int) -> int:
        """Make the instance under a vertex active."""
        ...


class HostLasso(Protocol):
    """The box-and-lasso part of a tool's host (`annotator.parts.box_lasso.BoxLassoPart`)."""

    def add_lasso_point(self, screen_pos: Sequence[float] | Sequence[Sequence[float]], *,
                        ray_origin: Sequence[float] | np.ndarray, ray_direction: Sequence[float] | np.ndarray,
                        camera: LassoCamera) -> int:
        """Add a clicked screen point (and its camera) to the lasso outline."""
        ...

    def apply_lasso(self, *, client: str = "") -> Delta | None:
        """Select inside the lasso outline."""
        ...

    def clear_lasso(self) -> None:
        """Drop the lasso outline."""
        ...


class HostAssist(Protocol):
    """The EFEM-assist part of a tool's host (`annotator.parts.assist.AssistPart`)."""

    def segment_at(self, vertex: int, *, wait: bool = False) -> np.ndarray | None:
        """Click-to-segment with the shape prior (`ToolSettings.prior`)."""
        ...

    def accept_segment(self) -> Delta | None:
        """Paint the previewed segment as a new instance."""
        ...

    def discard_segment(self) -> None:
        """Drop the segment preview (or cancel the segmentation running)."""
        ...


class ToolHost(Protocol):
    """What a tool's functions may use of their host: parts of the session (`annotator.session.AnnotatorSession`
    provides it), e.g. `host.toolbox.settings`, `host.scan.geom`, `host.painting.grow(vertex)`."""

    @property
    def toolbox(self) -> HostToolbox:
        """The tool settings (`toolbox.settings`)."""
        ...

    @property
    def scan(self) -> HostScan:
        """The scan's selection geometry (`scan.geom`)."""
        ...

    @property
    def painting(self) -> HostPainting:
        """Paint, erase, dab, region grow, fill, pick."""
        ...

    @property
    def box_lasso(self) -> HostLasso:
        """The lasso outline: add a point, apply, clear."""
        ...

    @property
    def assist(self) -> HostAssist:
        """Click-to-segment: run, accept, discard."""
        ...


@dataclass(frozen=True)
class Hit:
    """Where a gesture met the scan."""

    vertex: int
    """The scan vertex at (nearest to) the hit."""
    position: np.ndarray
    """(3,) float, the hit point on the surface, world frame."""
    client: str = ""
    """Who did it (journal attribution), e.g. "client3"."""


@dataclass(frozen=True)
class Control:
    """A setting control of the Tools panel. Its value is read into `ToolSettings.<setting>` (or into
    `ToolSettings.extra[setting]` for a setting `ToolSettings` has no field for), checked as
    `efem_viz.serve.inputs` checks every client value."""

    setting: str
    """Name of the setting (and the key of the control in `annotator.panels.Panels.gui_controls`)."""
    label: str
    """Label in the panel."""
    kind: Literal["slider", "checkbox", "dropdown"]
    initial: float | bool | str
    """Initial value in display units, for a setting without a `ToolSettings` field (a field's value is shown
    instead)."""
    min: float = 0.0
    max: float = 1.0
    step: float = 1.0
    scale: float = 1.0
    """Display units per setting unit (100 for a setting in metres shown in cm)."""
    options: tuple[str, ...] = ()
    """Dropdown options."""
    hint: str | None = None


@dataclass(frozen=True)
class ToolCommand:
    """A button of a tool (in the Tools panel, with an optional hotkey in the Ctrl/Cmd+K palette)."""

    key: str
    """Key of the button in `annotator.panels.Panels.gui_tool_buttons`."""
    label: str
    run: Callable[[ToolHost], object]
    hotkey: str | None = None
    """Key of the palette command (e.g. "Enter"); None = button only. It acts for the active tool: two tools may
    give their commands the same key (Enter applies the lasso, and accepts a segment preview)."""
    hint: str | None = None
    disabled: bool = False
    """Initial state (the app enables it when it applies, e.g. once a lasso has 3 points)."""


@dataclass(frozen=True)
class Tool:
    """One annotator tool: what the toolbar, the hotkeys, the help and the gestures need to know."""

    name: str
    """Identifier: the Tool dropdown's option and `ToolSettings.tool`."""
    label: str
    """Human name (help text, palette command "Tool: <label>")."""
    hotkey: str
    """Single key that activates the tool."""
    help: str
    """One line: what a click (or drag) does with this tool."""
    controls: tuple[Control, ...] = ()
    """Setting controls shown while the tool is active (besides `GESTURE_CONTROLS`)."""
    apply_at: Callable[[ToolHost, Hit], object] | None = None
    """Ctrl/Cmd+click on the surface (and the start of a drag when not `stroke`); None = nothing."""
    on_click: Callable[[ToolHost, Any], object] | None = None
    """Takes the raw viser click event instead of `apply_at` (needs the screen position / camera)."""
    stroke: bool = False
    """Ctrl/Cmd+drag paints a stroke along the surface (one undo step)."""
    erase: bool = False
    """Strokes, box and lasso selections erase instead of painting the active instance."""
    commands: tuple[ToolCommand, ...] = field(default=())
    """Buttons (and hotkeys) of the tool."""


@dataclass(frozen=True)
class AppKey:
    """A hotkey of the app's own commands (not a tool's). The palette commands, the help line and the `?` cheat
    sheet are read from `APP_KEYS`; `annotator.app.AnnotatorApp` binds each `action` to one of its methods."""

    action: str
    """What the key does, as the app names it ("undo", "next_instance", ...)."""
    label: str
    """Palette command and cheat-sheet text."""
    shown: str
    """The key as the help shows it ("Ctrl+Z", "Tab")."""
    bindings: tuple[tuple[str, str | None], ...]
    """(viser hotkey, modifier) pairs that trigger it. Keys are matched on the character typed, so "?" is bound
    both with and without Shift (it takes Shift on most layouts)."""


APP_KEYS: tuple[AppKey, ...] = (
    AppKey("new_instance", "New instance", "N", (("N", None),)),
    AppKey("next_instance", "Next instance (make it active)", "Tab", (("tab", None),)),
    AppKey("previous_instance", "Previous instance (make it active)", "Shift+Tab", (("tab", "shift"),)),
    AppKey("toggle_visible", "Hide / show active instance", "H", (("H", None),)),
    AppKey("toggle_locked", "Lock / unlock active instance", "L", (("L", None),)),
    AppKey("brush_smaller", "Smaller brush", "[", (("[", None),)),
    AppKey("brush_larger", "Larger brush", "]", (("]", None),)),
    AppKey("undo", "Undo", "Ctrl+Z", (("Z", "cmd/ctrl"),)),
    AppKey("redo", "Redo", "Ctrl+Y", (("Y", "cmd/ctrl"),)),
    AppKey("reset_view", "Reset view (fit the scan)", "R", (("R", None),)),
    AppKey("cheat_sheet", "Keyboard shortcuts (this sheet)", "?", (("?", None), ("?", "shift"))),
)
"""The app's own hotkeys, in help order."""

RESERVED_HOTKEYS: tuple[str, ...] = tuple(dict.fromkeys(
    key.upper() for k in APP_KEYS for key, modifier in k.bindings if modifier in (None, "shift")))
"""Keys the app's own commands take (tools and tool commands may not use them); Ctrl+Z / Ctrl+Y take a modifier."""
BRUSH_STEP = 1.25
"""`[` / `]` divide / multiply the brush radius by this (at least one slider step, within the slider's range)."""


# ---------------------------------------------------------------------------------------------- controls
RADIUS = Control("radius", "Brush radius (cm)", "slider", 1.0, min=0.1, max=20.0, step=0.1, scale=100.0)
NORMAL_LIMIT = Control("brush_max_angle_deg", "Brush normal limit (deg)", "slider", 180, min=5, max=180, step=5,
                       hint="paint only surface facing like the hit point; 180 = off")
GROW_ANGLE = Control("grow_angle_deg", "Grow: max normal change (deg)", "slider", 20.0, min=1, max=90, step=1)
GROW_DISTANCE = Control("grow_distance", "Grow: max distance (cm)", "slider", 15, min=1, max=200, step=1, scale=100.0)
MIN_HEIGHT = Control("grow_min_height", "Grow: min height (cm)", "slider", 0.0, min=0.0, max=10.0, step=0.1,
                     scale=100.0, hint="keep fills above the table (z = 0 in imported tabletop scans); 0 = off")
ONLY_UNLABELLED = Control("only_unlabelled", "Only unlabelled vertices", "checkbox", False)
BOX_FACING = Control("box_facing", "Box / lasso take", "dropdown", "visible", options=("visible", "front", "all"),
                     hint="visible = what the camera sees; front = all surface facing it, hidden or not; "
                          "all = through the object")
GESTURE_CONTROLS: tuple[Control, ...] = (ONLY_UNLABELLED, BOX_FACING)
"""Shown whatever the tool: box select (Shift+drag) works with every tool, and any tool's paint may be limited to
unlabelled vertices."""


# ---------------------------------------------------------------------------------------------- tool functions
def _brush(host: ToolHost, hit: Hit) -> object:
    return host.painting.dab(hit.vertex, hit.position, erase=False, client=hit.client)


def _erase(host: ToolHost, hit: Hit) -> object:
    return host.painting.dab(hit.vertex, hit.position, erase=True, client=hit.client)


def _grow(host: ToolHost, hit: Hit) -> object:
    return host.painting.grow(hit.vertex, client=hit.client)


def _fill(host: ToolHost, hit: Hit) -> object:
    return host.painting.fill(hit.vertex, client=hit.client)


def _pick(host: ToolHost, hit: Hit) -> object:
    return host.painting.pick_instance(hit.vertex)


def _segment(host: ToolHost, hit: Hit) -> object:
    return host.assist.segment_at(hit.vertex)


def lasso_click(host: ToolHost, event: Any) -> int:
    """The lasso tool's click: the event's screen point, ray and client camera go to `ToolHost.add_lasso_point`."""
    cam = event.client.camera
    camera = LassoCamera(np.asarray(cam.position, np.float64), np.asarray(cam.wxyz, np.float64), float(cam.fov),
                         float(cam.aspect))
    return host.box_lasso.add_lasso_point(event.screen_pos, ray_origin=event.ray_origin,
                                          ray_direction=event.ray_direction, camera=camera)


DEFAULT_TOOLS: tuple[Tool, ...] = (
    Tool("brush", "Brush", "B", "drag paints the active instance; click paints a dab",
         controls=(RADIUS, NORMAL_LIMIT), apply_at=_brush, stroke=True),
    Tool("erase", "Erase", "X", "drag (or click) clears labels; box and lasso erase too",
         controls=(RADIUS, NORMAL_LIMIT), apply_at=_erase, stroke=True, erase=True),
    Tool("grow", "Region grow", "G", "click grows the active instance over smooth surface from the point",
         controls=(GROW_ANGLE, GROW_DISTANCE, MIN_HEIGHT), apply_at=_grow),
    Tool("fill", "Fill", "F", "click gives the connected region of the clicked label to the active instance",
         controls=(MIN_HEIGHT,), apply_at=_fill),
    Tool("pick", "Pick instance", "I", "click makes the instance under the cursor active", apply_at=_pick),
    Tool("segment", "Click to segment", "C", "click runs EFEM with the shape prior (EFEM assist) and previews the "
         "object; Enter accepts it, Esc discards it (or cancels the run)", apply_at=_segment,
         commands=(
             ToolCommand("segment_accept", "Accept segment", lambda h: h.assist.accept_segment(), hotkey="Enter",
                         hint="paint the previewed object as a new instance", disabled=True),
             ToolCommand("segment_discard", "Discard segment", lambda h: h.assist.discard_segment(), hotkey="Escape",
                         hint="drop the preview, or cancel the segmentation running", disabled=True),
         )),
    Tool("lasso", "Lasso", "O", "each click adds an outline point; Enter applies (paints, or erases)",
         on_click=lasso_click,
         commands=(
             ToolCommand("lasso_apply", "Apply lasso", lambda h: h.box_lasso.apply_lasso(), hotkey="Enter",
                         hint="Lasso tool: Ctrl/Cmd+click the outline, then apply", disabled=True),
             ToolCommand("lasso_clear", "Clear lasso", lambda h: h.box_lasso.clear_lasso(), disabled=True),
         )),
)
"""The annotator's tools, in toolbar order."""

TOOLS: tuple[str, ...] = tuple(t.name for t in DEFAULT_TOOLS)
"""Names of the default tools (the Tool dropdown's options)."""


def check_tools(tools: Sequence[Tool]) -> dict[str, Tool]:
    """The tools by name, after checking the table: unique names, hotkeys and command keys; a control per
    setting name (two tools sharing a setting share the `Control`).

    Raises:
        ValueError: a duplicate, an empty table, a hotkey the app uses itself (`RESERVED_HOTKEYS`), or one of
            the keys that move viser's camera in the browser (`efem_viz.serve.camera.VISER_CAMERA_KEYS`).
    """
    if not tools:
        raise ValueError("the annotator needs at least one tool")
    by_name: dict[str, Tool] = {}
    keys: dict[str, str] = {k: "the app" for k in RESERVED_HOTKEYS}
    keys.update({k: "viser's camera (the browser client moves the camera with W/A/S/D/Q/E)"
                 for k in VISER_CAMERA_KEYS})
    command_keys: dict[str, str] = {}
    """Command hotkeys → the first command that uses it (commands of different tools may share one)."""
    controls: dict[str, Control] = {c.setting: c for c in GESTURE_CONTROLS}
    commands: set[str] = set()
    for t in tools:
        if t.name in by_name:
            raise ValueError(f"two tools are named {t.name!r}")
        if t.hotkey.upper() in keys or t.hotkey.upper() in command_keys:
            taken = keys.get(t.hotkey.upper()) or command_keys[t.hotkey.upper()]
            raise ValueError(f"tool {t.name!r}: hotkey {t.hotkey!r} is taken by {taken!r}")
        keys[t.hotkey.upper()] = t.name
        for c in t.controls:
            if controls.setdefault(c.setting, c) != c:
                raise ValueError(f"tool {t.name!r}: setting {c.setting!r} has two different controls")
        own: set[str] = set()
        for cmd in t.commands:
            if cmd.key in commands:
                raise ValueError(f"tool {t.name!r}: command key {cmd.key!r} is used twice")
            commands.add(cmd.key)
            if cmd.hotkey is not None:
                key = cmd.hotkey.upper()
                if key in keys:
                    raise ValueError(f"tool {t.name!r}: hotkey {cmd.hotkey!r} is taken by {keys[key]!r}")
                if key in own:
                    raise ValueError(f"tool {t.name!r}: two commands have the hotkey {cmd.hotkey!r}")
                own.add(key)
                command_keys.setdefault(key, f"{t.name}: {cmd.label}")
        by_name[t.name] = t
    return by_name


def scaled_to_scan(tools: Sequence[Tool], diagonal: float) -> tuple[Tool, ...]:
    """The tools with their length sliders reaching as far as the scan needs: the brush radius up to 10 % of the
    scan's diagonal (at least its 20 cm), the grow distance up to the diagonal (at least its 2 m). A room-sized
    scan (9 x 6 x 3 m) gets a brush that covers a chair; a tabletop scan keeps the shipped ranges."""
    reach = {"radius": 0.10 * diagonal, "grow_distance": diagonal}

    def scaled(c: Control) -> Control:
        if c.kind != "slider" or c.setting not in reach or not np.isfinite(reach[c.setting]):
            return c
        top = round(reach[c.setting] * c.scale / c.step) * c.step
        return dataclasses.replace(c, max=float(max(c.max, top)))

    return tuple(dataclasses.replace(t, controls=tuple(scaled(c) for c in t.controls)) for t in tools)


def all_controls(tools: Sequence[Tool]) -> tuple[Control, ...]:
    """Every control of the tools (each once, in order of first use), then `GESTURE_CONTROLS`."""
    seen: dict[str, Control] = {}
    for t in tools:
        for c in t.controls:
            seen.setdefault(c.setting, c)
    for c in GESTURE_CONTROLS:
        seen.setdefault(c.setting, c)
    return tuple(seen.values())


def shown_settings(tool: Tool) -> frozenset[str]:
    """Settings whose controls are shown while `tool` is active."""
    return frozenset(c.setting for c in (*tool.controls, *GESTURE_CONTROLS))


def help_markdown(tools: Sequence[Tool], active: str | None = None) -> str:
    """The tools' help: one line per tool with its hotkey, the active one in bold, then the gestures.

    Args:
        tools: the tool table.
        active: name of the active tool (marked), or None.
    """
    lines = []
    for t in tools:
        text = f"**{t.hotkey}** {t.label}: {t.help}"
        lines.append(f"- ▶ {text}" if t.name == active else f"- {text}")
    lines.append("")
    lines.append("Ctrl/Cmd+click applies the tool, Ctrl/Cmd+drag paints with brush/erase, Shift+drag box-selects. "
                 + " · ".join(f"{k.shown} {_short(k.label)}" for k in APP_KEYS))
    return "\n".join(lines)


GESTURES: tuple[tuple[str, str], ...] = (
    ("Ctrl/Cmd + click", "apply the active tool at the point (the lasso adds an outline point)"),
    ("Ctrl/Cmd + drag", "paint a stroke (brush, erase); other tools act where the drag starts"),
    ("Shift + drag", "box select (paints the active instance; erases with an erasing tool)"),
    ("Ctrl/Cmd + K", "command palette: every command and its key"),
)
"""Mouse gestures and the palette, for the cheat sheet."""


def cheat_sheet_markdown(tools: Sequence[Tool]) -> str:
    """The `?` overlay: every key of the tools, their commands and the app (`APP_KEYS`), then the gestures.

    Args:
        tools: the tool table.
    """
    rows = [f"| **{t.hotkey}** | {t.label} tool: {t.help} |" for t in tools]
    rows += [f"| **{c.hotkey}** | {c.label.removesuffix(f' ({c.hotkey})')} ({t.label} tool) |"
             for t in tools for c in t.commands if c.hotkey]
    rows += [f"| **{k.shown}** | {k.label} |" for k in APP_KEYS]
    rows += [f"| **{g}** | {what} |" for g, what in GESTURES]
    return "\n".join(["| key | does |", "|---|---|", *rows,
                      "", "Keys act when no text field has the focus (click the 3-D view first)."])


def _short(label: str) -> str:
    """A palette label shortened for the one-line help ("Hide / show active instance" → "hide / show")."""
    return label.split(" (", 1)[0].replace(" active instance", "").lower()
