"""Scripted viser clients over a real WebSocket (what a browser, a hostile page or a script can send).

* `handshake_status(url, origin=..., cookie=...)`: 101 when the server accepts the WebSocket handshake, else the
  HTTP status it refused with.
* `RawClient(url)`: sends raw viser messages (GUI limits bypassed); a drain thread discards what the server sends.
* `ViserClient(url)`: also decodes the server's frames and keeps the GUI it describes (components by uuid with
  their props, notifications), with label-based helpers (`set_value`, `click`, `markdown`, `scene_click`).

The URL may be the printed http:// URL with its `?token=...`: it is turned into the ws:// URL of the same place.

Note: rebuilt on 2026-12-01 after an accidental overwrite, from how tests/test_annotator_cli_reliability.py uses
`ViserClient` (same public names); check against the original author's intent.
"""

from __future__ import annotations

import atexit
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any, Callable

import msgspec.msgpack
import viser
import zstandard
from websockets.exceptions import InvalidStatus
from helpers import server_signals
from websockets.sync.client import ClientConnection, connect

SUBPROTOCOL = f"viser-v{viser.__version__}"

HANG_GUARD_S = 200.0
"""Every wait of a scripted client on an app is a hang guard (10x what the slowest took beside a busy load)."""


def ws_url(url: str) -> str:
    """ws://host:port/?token=... from an http:// URL (ws:// URLs pass unchanged)."""
    if url.startswith("http://"):
        return "ws://" + url[len("http://"):]
    if url.startswith("https://"):
        return "wss://" + url[len("https://"):]
    return url


def _headers(cookie: str | None) -> dict[str, str]:
    return {"Cookie": cookie} if cookie else {}


def _connect(url: str, origin: str | None, cookie: str | None) -> ClientConnection:
    return connect(ws_url(url), origin=origin, additional_headers=_headers(cookie),  # type: ignore[arg-type]
                   subprotocols=[SUBPROTOCOL], open_timeout=10, max_size=None)  # type: ignore[list-item]


def handshake_status(url: str, *, origin: str | None = None, cookie: str | None = None) -> int:
    """101 when the server accepts the WebSocket handshake, else the HTTP status it answered with."""
    try:
        with _connect(url, origin, cookie):
            return 101
    except InvalidStatus as exc:
        return int(exc.response.status_code)


def decode_frame(data: bytes) -> list[dict[str, Any]]:
    """The messages of one server frame (zstd-compressed msgpack; binary buffers after it are ignored)."""
    n_inner = int.from_bytes(data[0:8], "little")
    n_comp = int.from_bytes(data[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(data[16:16 + n_comp], max_output_size=n_inner)
    payload = msgspec.msgpack.decode(inner)
    return list(payload.get("messages", ()))


def wait_for(cond: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Poll `cond` until true or the timeout; returns its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return bool(cond())


class RawClient:
    """A connected client that sends raw viser messages.

    Args:
        url: the server URL (http:// with `?token=` as printed, or ws://).
        origin: the `Origin` header to send (None = none, like a script).
        cookie: a `Cookie` header to send.
        announce: send a first camera message (viser fires GUI callbacks only for clients that sent one).
    """

    def __init__(self, url: str, *, origin: str | None = None, cookie: str | None = None,
                 announce: bool = True) -> None:
        self.ws = _connect(url, origin, cookie)
        self._reader = threading.Thread(target=self._read, name="viser-test-client", daemon=True)
        self._reader.start()
        if announce:
            self.announce_camera()

    def _read(self) -> None:
        try:
            for frame in self.ws:
                if isinstance(frame, (bytes, bytearray)):
                    self._on_frame(bytes(frame))
        except Exception:  # noqa: BLE001 - closed
            pass

    def _on_frame(self, frame: bytes) -> None:
        """Raw frames are discarded (see `ViserClient`)."""

    def send(self, message: dict[str, Any]) -> None:
        """Send one message dict (with its "type")."""
        self.ws.send(msgspec.msgpack.encode(message))

    def announce_camera(self) -> None:
        """The first camera message: viser treats the client as connected (callbacks fire) only after it."""
        self.send({"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 1.0),
                   "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
                   "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)})

    def update_gui(self, uuid: str, **updates: Any) -> None:
        """A GuiUpdateMessage for the control `uuid` (any property, as any client can send)."""
        self.send({"type": "GuiUpdateMessage", "uuid": uuid, "updates": updates})

    def set_gui(self, handle: Any, **updates: Any) -> None:
        """`update_gui` for a server-side handle, e.g. `set_gui(app.panels.gui_radius, value=1e6)`."""
        self.update_gui(handle._impl.uuid, **updates)

    def press(self, button: Any) -> None:
        """Press a button given by its server-side handle."""
        self.set_gui(button, value=True)

    def scene_click(self, origin: tuple[float, float, float], direction: tuple[float, float, float], *,
                    modifier: str | None = "cmd/ctrl") -> None:
        """A scene click along a ray (world frame), with a modifier (the annotator's tools need Ctrl/Cmd)."""
        self.send({"type": "ScenePointerMessage", "event_type": "click", "ray_origin": tuple(origin),
                   "ray_direction": tuple(direction), "screen_pos": ((0.5, 0.5),), "modifier": modifier})

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> RawClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ViserClient(RawClient):
    """A client that also keeps the GUI the server describes (what a user would see).

    Attributes:
        components: uuid → {"type": message type, "props": props dict}, in creation order.
        notifications: props of every notification shown or updated, in arrival order.
    """

    def __init__(self, url: str, *, origin: str | None = None, cookie: str | None = None,
                 timeout: float = 30.0) -> None:
        self.components: dict[str, dict[str, Any]] = {}
        self.notifications: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        super().__init__(url, origin=origin, cookie=cookie, announce=True)
        if not self.wait_for(lambda: any(c["type"] == "GuiButtonMessage" for c in self._snapshot()), timeout):
            raise AssertionError("the server sent no GUI")

    # ---- state from the server
    def _on_frame(self, frame: bytes) -> None:
        try:
            messages = decode_frame(frame)
        except Exception:  # noqa: BLE001 - not a frame we understand
            return
        with self._lock:
            for m in messages:
                kind = m.get("type", "")
                if kind == "GuiUpdateMessage" and m.get("uuid") in self.components:
                    self.components[m["uuid"]]["props"].update(m.get("updates", {}))
                elif kind == "GuiRemoveMessage":
                    self.components.pop(m.get("uuid"), None)
                elif kind in ("NotificationShowMessage", "NotificationUpdateMessage"):
                    self.notifications.append(dict(m.get("props", {})))
                elif kind.startswith("Gui") and "uuid" in m and isinstance(m.get("props"), dict):
                    self.components[m["uuid"]] = {"type": kind, "props": dict(m["props"])}

    def _snapshot(self) -> list[dict[str, Any]]:
        with self._lock:
            return [{"uuid": u, "type": c["type"], "props": dict(c["props"])} for u, c in self.components.items()]

    def find(self, label: str, *, kind: str | None = None) -> dict[str, Any]:
        """The first component whose label is `label` (else the first whose label starts with it).

        Raises:
            KeyError: no such component.
        """
        comps = [c for c in self._snapshot() if kind is None or c["type"] == kind]
        for match in (lambda s: s == label, lambda s: s.startswith(label)):
            for c in comps:
                if match(str(c["props"].get("label", ""))):
                    return c
        raise KeyError(f"no GUI component labelled {label!r}")

    def value(self, label: str) -> Any:
        """The current value of a control, as the server last sent it."""
        return self.find(label)["props"].get("value")

    def markdowns(self) -> list[str]:
        """The content of every markdown component, in creation order."""
        return [str(c["props"].get("_markdown", "")) for c in self._snapshot() if c["type"] == "GuiMarkdownMessage"]

    def markdown(self, prefix: str) -> str:
        """The content of the first markdown component that starts with `prefix` (else contains it), or ""."""
        texts = self.markdowns()
        for t in texts:
            if t.startswith(prefix):
                return t
        for t in texts:
            if prefix in t:
                return t
        return ""

    def notification_texts(self) -> list[str]:
        """"title: body" of every notification, in arrival order."""
        with self._lock:
            return [f"{n.get('title', '')}: {n.get('body', '')}" for n in self.notifications]

    # ---- actions by label
    def set_value(self, label: str, value: Any) -> None:
        """Set a control's value, as a browser would."""
        self.update_gui(self.find(label)["uuid"], value=value)

    def click(self, label: str) -> None:
        """Press the button labelled `label` (or starting with it: "Undo" presses "Undo (Ctrl+Z)")."""
        self.update_gui(self.find(label, kind="GuiButtonMessage")["uuid"], value=True)

    def wait_for(self, cond: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Poll `cond` until true or the timeout; returns its last value."""
        return wait_for(cond, timeout)


REPO = Path(__file__).resolve().parents[1]

JOURNAL_FAULTS_SITECUSTOMIZE = textwrap.dedent(
    """
    # Test-only fault injection: while $EFEM_TEST_FAULT_FILE exists, writes to *.journal files get half a record
    # through and then fail with ENOSPC (a disk that fills up mid-write).
    import errno, os
    _flag = os.environ.get("EFEM_TEST_FAULT_FILE")
    _real_write = os.write
    def _write(fd, data):
        if _flag and os.path.exists(_flag):
            try:
                target = os.readlink(f"/proc/self/fd/{fd}")
            except OSError:
                target = ""
            if target.endswith(".journal"):
                _real_write(fd, bytes(data[: len(data) // 2]))
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return _real_write(fd, data)
    os.write = _write
    """
)
"""A sitecustomize.py for fault injection into a CLI process (put its folder in PYTHONPATH_FIRST)."""


class AnnotateProcess:
    """One `efem-annotate` CLI process and a `ViserClient` connected to it (the printed URL, token included).

    Args:
        scan: the scan to open.
        out: the --out folder.
        env_extra: extra environment; PYTHONPATH_FIRST is put in front of PYTHONPATH (e.g. a fault-injecting
            sitecustomize).
        args: extra CLI arguments.
        sigint_ignored: start it with SIGINT ignored, as a background job of a non-interactive shell is (by
            default SIGINT and SIGTERM are reset to their defaults, whatever this test run inherited).
    """

    def __init__(self, scan: Path, out: Path, env_extra: dict[str, str] | None = None,
                 args: tuple[str, ...] = (), timeout: float = 120.0, *, sigint_ignored: bool = False) -> None:
        self.t_start = time.monotonic()
        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1", **(env_extra or {}))
        env["PYTHONPATH"] = os.pathsep.join(p for p in [env.get("PYTHONPATH_FIRST", ""), str(REPO),
                                                          os.environ.get("PYTHONPATH", "")] if p)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "annotator", str(scan), "--out", str(out), "--port", "0",
             "--autosave-delay", "0.05", *args],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
            preexec_fn=server_signals(sigint_ignored=sigint_ignored),
        )
        self.lines: list[str] = []
        self.url = ""
        atexit.register(self._kill_if_running)  # a failing test must not leave servers behind
        end = time.monotonic() + timeout
        assert self.proc.stdout is not None
        while time.monotonic() < end:
            line = self.proc.stdout.readline()
            if not line:
                raise AssertionError("efem-annotate exited:\n" + "".join(self.lines))
            self.lines.append(line)
            m = re.search(r" at (http://\S+)", line)
            if m:
                self.url = m.group(1)
                break
        assert self.url, "".join(self.lines)
        self.t_url = time.monotonic() - self.t_start
        """Seconds from process start to the printed URL (scan loaded, journal recovered, GUI built)."""
        # keep reading the output: a full pipe would block the server's logging (and then the server)
        self._drain = threading.Thread(target=self._read_rest, daemon=True)
        self._drain.start()
        self.client = ViserClient(self.url)
        self.client.set_value("Brush radius (cm)", 2.0)

    def _kill_if_running(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()

    def _read_rest(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    def table(self) -> str:
        """The instance table as the server last sent it (the markdown that says how much is labelled)."""
        return next((m for m in self.client.markdowns() if "vertices labelled" in m), "")

    def must(self, cond: Callable[[], bool], timeout: float = HANG_GUARD_S, what: str = "the expected update") -> None:
        """Wait for `cond`; raise TimeoutError if it does not come (`timeout` is a hang guard: a restarted CLI on a
        machine with four busy threads took over 20 s to send its first table)."""
        if not self.client.wait_for(cond, timeout):
            raise TimeoutError(f"efem-annotate did not send {what} within {timeout:.0f} s")

    def counts(self) -> dict[int, int]:
        return {int(m.group(1)): int(m.group(2).replace(",", ""))
                for m in re.finditer(r"^\| (\d+)[^|]*\|[^|]*\|[^|]*\| ([\d,]+) \|", self.table(), re.M)}

    def edit(self, step: tuple, *, expect_change: bool = True, timeout: float = HANG_GUARD_S) -> str:
        """Run one edit and wait for the table that shows it; returns that table."""
        c = self.client
        before = self.table()
        n_notes = len(c.notifications)
        if step[0] == "new":
            c.click("New instance")
        elif step[0] == "undo":
            c.click("Undo")
        elif step[0] == "redo":
            c.click("Redo")
        elif step[0] == "press":  # any button whose edit shows in the table (pre-label import, merge, delete)
            c.click(step[1])
        elif step[0] == "click":  # any button acknowledged by a notification (exports)
            c.click(step[1])
            if expect_change:
                self.must(lambda: len(c.notifications) > n_notes, timeout, "a notification")
            return self.table()
        else:
            # ("paint", direction) clicks from 0.5 m out toward the centre; ("paint", origin, direction) any ray
            o, d = (0.5 * step[1], -step[1]) if len(step) == 2 else (step[1], step[2])
            c.scene_click(tuple(float(x) for x in o), tuple(float(x) for x in d))
        if expect_change:
            self.must(lambda: self.table() != before, timeout, "a new instance table")
        return self.table()

    def kill(self) -> None:
        self.client.close()
        self.proc.kill()
        self.proc.wait(10)

    def stop(self, timeout: float = 90.0, *, sig: signal.Signals = signal.SIGINT, keep_client: bool = False) -> int:
        """Ctrl+C (or `sig`), as a user stops it; returns the exit status.

        Args:
            timeout: seconds to wait for the exit (only catches a hang).
            sig: the signal to send (SIGTERM: what a service manager sends).
            keep_client: leave the client connected while the server stops (as a browser tab stays open).

        Raises:
            AssertionError: it did not exit within `timeout` (killed then; its last output is in the message).
        """
        if not keep_client:
            self.client.close()
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            stacks = ""
            try:  # where it hangs, when py-spy is installed
                stacks = subprocess.run(["py-spy", "dump", "--pid", str(self.proc.pid)], capture_output=True,
                                        text=True, timeout=30).stdout
            except (OSError, subprocess.SubprocessError):
                pass
            self.lines.append(stacks)
            self.proc.kill()
            self.proc.wait(10)
            raise AssertionError(f"efem-annotate ignored {sig.name} for {timeout:.0f} s:\n"
                                 + "".join(self.lines[-30:])) from None
