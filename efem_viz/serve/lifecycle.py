"""How both servers (`efem-viz view`, `efem-annotate`) run until the user stops them: the one serve-until-Ctrl+C
loop, and the signal handlers that make Ctrl+C and SIGTERM stop a server however it was started.

Why the handlers: a process started in the background by a non-interactive shell (`cmd &`, nohup, many CI
runners and service scripts) inherits SIGINT as *ignored*, and Python then never installs its
KeyboardInterrupt handler, so Ctrl+C (or `kill -INT`) does nothing and the server runs on. `stop_signals`
installs its own handler for SIGINT and SIGTERM (`signal.signal` overrides an inherited SIG_IGN) for as long as
the server lives:

* the first signal raises KeyboardInterrupt in the main thread, wherever it is (loading the scan, or waiting in
  `wait_for_stop`), and the app's own clean-up runs (`finally: app.close()`);
* a further signal while that clean-up runs ends the process at once (`os._exit(EXIT_FORCED)`): a stuck
  shutdown can always be cut short (the annotator's journal is on disk before every edit is acknowledged).

Usage (what both CLIs do):

```python
with stop_signals("efem-annotate"):
    app = AnnotatorApp(...)  # Ctrl+C while loading stops too (KeyboardInterrupt)
    try:
        print(app.url)
        wait_for_stop()      # returns after SIGINT / SIGTERM
    finally:
        app.close()
```

Signal handlers can only be set from the main thread: elsewhere (a server embedded in another program's
thread) `stop_signals` leaves the process's handlers alone and the embedding program decides.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from types import FrameType
from typing import Iterator

from efem_viz.terminal import terminal_text

logger = logging.getLogger(__name__)

STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)
"""Signals that stop a server: Ctrl+C, and what service managers and `kill` send."""
EXIT_FORCED = 130
"""Exit status when a second signal cuts the shutdown short (128 + SIGINT, as after Ctrl+C)."""
POLL_S = 1.0
"""`wait_for_stop` wakes this often (a signal interrupts the wait at once; this only bounds how late a
`stop_event` set from another thread is seen)."""


class _Stopping:
    """Shared between the handler and the context: whether a stop was already asked for."""

    def __init__(self, prog: str) -> None:
        self.prog = prog
        self.asked = False

    def handle(self, signum: int, _frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.asked:
            # Still shutting down after the first signal: the user insists.
            print(f"{self.prog}: {name} again while stopping: exiting now", file=sys.stderr, flush=True)
            os._exit(EXIT_FORCED)
        self.asked = True
        logger.info("%s: stopping (%s)", self.prog, name)
        raise KeyboardInterrupt(name)


@contextlib.contextmanager
def stop_signals(prog: str) -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM stop the server: the first raises KeyboardInterrupt in the main thread
    (also when SIGINT was inherited as ignored), a second one during the clean-up exits at once. The handlers that
    were there before are restored when the block ends.

    Args:
        prog: the program name for the one-line message of a forced exit ("efem-annotate").

    Yields:
        Nothing; outside the main thread the block runs with the process's handlers unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    stopping = _Stopping(prog)
    previous = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    for s in STOP_SIGNALS:
        signal.signal(s, stopping.handle)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def announce(prog: str, headline: str, *, url: str, local_url: str, exposure_warning: str | None = None,
             details: tuple[str, ...] = ()) -> None:
    """What both servers print at start: the exposure warning (stderr), ``prog: headline at URL``, the local URL
    when it differs, and indented detail lines; control characters escaped (`efem_viz.terminal.terminal_text`).

    Args:
        prog: program name ("efem-annotate").
        headline: what is served, followed by the URL (e.g. "scan.ply (1,234 vertices) at <url>").
        url: the URL with the access token (already in ``headline``; compared with ``local_url``).
        local_url: the URL on this machine.
        exposure_warning: the access guard's warning when the server is reachable from other machines.
        details: further lines ("autosave: ...").
    """
    if exposure_warning:
        print(f"{prog}: {terminal_text(exposure_warning)}", file=sys.stderr, flush=True)
    print(f"{prog}: {terminal_text(headline)}", flush=True)  # the headline names the scan: any bytes
    if local_url != url:
        print(f"  on this machine: {local_url}", flush=True)
    for line in details:
        print(f"  {terminal_text(line)}", flush=True)


def wait_for_stop(*, stop_event: threading.Event | None = None) -> None:
    """Serve until Ctrl+C / SIGTERM (a KeyboardInterrupt; use inside `stop_signals`) or until `stop_event` is set;
    returns normally either way (the caller closes its app in `finally`).

    Args:
        stop_event: set it from another thread to stop without a signal (embedding, tests).
    """
    event = stop_event if stop_event is not None else threading.Event()
    try:
        while not event.is_set():
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        pass
