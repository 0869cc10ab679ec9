"""Ctrl+C and SIGTERM stop both servers however they were started (`efem_viz.serve.lifecycle`).

A background job of a non-interactive shell (`cmd &`, nohup, CI runners) inherits SIGINT as ignored, and Python then
installs no KeyboardInterrupt handler: the servers must install their own. The CLI tests start the real servers that
way (SIGINT ignored, a client connected), send the signal, and expect a clean exit. The issue asks for an exit within
2 s; the waits here are ten times that, so they only catch a server that ignores the signal, never a slow machine.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from helpers import ball_scan, server_signals  # noqa: E402
from viser_client import AnnotateProcess, ViserClient  # noqa: E402

from efem_viz.serve.lifecycle import EXIT_FORCED, stop_signals, wait_for_stop  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STOP_TIMEOUT_S = 20.0
"""Ten times the 2 s a server may take to stop: only a hang exceeds it."""
START_TIMEOUT_S = 180.0
"""Generous: the viewer imports torch, on a loaded 2-core machine."""


@pytest.fixture()
def restore_handlers() -> Iterator[None]:
    """Put this process's SIGINT / SIGTERM handlers back after a test that changes them."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in before.items():
        signal.signal(s, h)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stop_signals_override_an_ignored_disposition(sig: signal.Signals, restore_handlers: None) -> None:
    """With the signal ignored before (as a background start leaves SIGINT), the signal still ends
    `wait_for_stop`; the ignored disposition is back after the block."""
    signal.signal(sig, signal.SIG_IGN)
    timer = threading.Timer(0.2, os.kill, (os.getpid(), sig))
    with stop_signals("test"):
        timer.start()
        wait_for_stop()  # returns only through the signal
    timer.join()
    assert signal.getsignal(sig) is signal.SIG_IGN


def test_wait_for_stop_returns_when_its_event_is_set() -> None:
    event = threading.Event()
    threading.Timer(0.1, event.set).start()
    wait_for_stop(stop_event=event)
    assert event.is_set()


def _env() -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in [str(REPO), os.environ.get("PYTHONPATH", "")] if p)
    return env


def test_a_second_signal_during_a_stuck_shutdown_exits_at_once(tmp_path: Path) -> None:
    """The first SIGINT starts the clean-up; if that hangs, a second one ends the process (exit 130)."""
    script = tmp_path / "stuck.py"
    script.write_text(textwrap.dedent("""
        import time
        from efem_viz.serve.lifecycle import stop_signals, wait_for_stop
        with stop_signals("stuck"):
            try:
                print("serving", flush=True)
                wait_for_stop()
            finally:
                print("closing", flush=True)
                time.sleep(600)  # a shutdown that hangs
    """))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=_env(), preexec_fn=server_signals(sigint_ignored=True))
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "serving"
        proc.send_signal(signal.SIGINT)
        assert proc.stdout.readline().strip() == "closing"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(STOP_TIMEOUT_S) == EXIT_FORCED
        assert "SIGINT again while stopping" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.fixture()
def ball(tmp_path: Path) -> Path:
    return ball_scan(tmp_path)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_annotate_cli_stops_when_started_with_sigint_ignored(ball: Path, tmp_path: Path, sig: signal.Signals) -> None:
    """`efem-annotate` started as a background job (SIGINT ignored), a client connected: the signal stops it,
    cleanly (exit 0, the journal lock released: a second session opens the same output folder)."""
    proc = AnnotateProcess(ball, tmp_path / "out", sigint_ignored=True, timeout=START_TIMEOUT_S)
    try:
        proc.edit(("new",))  # the client is connected and served
        t0 = time.monotonic()
        rc = proc.stop(STOP_TIMEOUT_S, sig=sig, keep_client=True)
        took = time.monotonic() - t0
    finally:
        proc.client.close()
    assert rc == 0, "".join(proc.lines[-20:])
    print(f"efem-annotate stopped {took:.2f} s after {sig.name}")
    again = AnnotateProcess(ball, tmp_path / "out", timeout=START_TIMEOUT_S)  # the journal lock was released
    assert again.stop(STOP_TIMEOUT_S) == 0


def test_view_cli_stops_when_started_with_sigint_ignored(tmp_path: Path) -> None:
    """`efem-viz view` started as a background job (SIGINT ignored), a client connected: SIGINT stops it (exit 0)."""
    from efem_viz.data.io import save_scene
    from efem_viz.data.scene import Scene

    p = np.random.default_rng(0).normal(size=(2000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    scene = tmp_path / "ball.ply"
    save_scene(Scene.create("ball", (0.1 * p).astype(np.float32), normals=p.astype(np.float32)), scene)
    proc = subprocess.Popen(
        [sys.executable, "-m", "efem_viz.cli", "view", str(scene), "--port", "0", "--out-dir", str(tmp_path / "o")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env(),
        preexec_fn=server_signals(sigint_ignored=True),
    )
    lines: list[str] = []
    client: ViserClient | None = None
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + START_TIMEOUT_S
        url = ""
        while not url and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.search(r"viewer: (http://\S+)", line)
            url = m.group(1) if m else ""
        assert url, "efem-viz view printed no URL:\n" + "".join(lines)
        threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()  # type: ignore[arg-type]
        client = ViserClient(url)  # connected: the server sent it the GUI
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"efem-viz view ignored SIGINT for {STOP_TIMEOUT_S:.0f} s:\n"
                                 + "".join(lines[-20:])) from None
        assert rc == 0, "".join(lines[-20:])
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
