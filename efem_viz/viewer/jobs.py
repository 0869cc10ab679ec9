"""The viewer's worker threads and its playback timer (no viser, no GUI handle).

`Jobs` holds three single-thread pools, so that a long job of one kind never queues another kind behind it:
`worker` (loads, exports, mask bands), `decoder` (decoded shapes, proposal inspection) and `runner` (EM runs: opening
another scene or a trace does not wait for a run). A failed job is logged and reported through `on_error` (the app
shows it in the status line); the server stays up. `Player` calls a tick function at a given rate until stopped.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, ParamSpec, TypeVar

from efem_viz.serve.inputs import ClientValueError

logger = logging.getLogger(__name__)

P = ParamSpec("P")
T = TypeVar("T")


class Jobs:
    """Worker pools and the set of submitted jobs.

    Args:
        on_error: called with a one-line message when a job raises (a refused client value: its message; another
            error: "<job> failed: <error>").
    """

    def __init__(self, on_error: Callable[[str], None]) -> None:
        self.on_error = on_error
        self.worker = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-work")
        self.decoder = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-decode")
        self.runner = ThreadPoolExecutor(1, thread_name_prefix="efem-viewer-run")
        self._pending: set[Future[Any]] = set()  # futures of every result type
        self._pending_lock = threading.Lock()

    def submit(self, pool: ThreadPoolExecutor, fn: Callable[P, T], *args: P.args,
               **kw: P.kwargs) -> Future[T]:
        """Run `fn(*args, **kw)` on `pool`; an exception is reported through `on_error` and kept in the Future."""
        def guarded() -> T:
            try:
                return fn(*args, **kw)
            except ClientValueError as exc:  # a refused value or path: one line, no traceback
                self.on_error(str(exc))
                raise
            except Exception as exc:  # noqa: BLE001 - shown in the GUI, server stays up
                logger.exception("viewer job %s failed", getattr(fn, "__name__", fn))
                self.on_error(f"{getattr(fn, '__name__', 'job')} failed: {exc}")
                raise

        fut = pool.submit(guarded)
        with self._pending_lock:
            self._pending.add(fut)
        return fut

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every submitted job has finished. Returns False on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            with self._pending_lock:
                pending = [f for f in self._pending if not f.done()]
                self._pending = set(pending)
            if not pending:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)

    def shutdown(self) -> None:
        """Cancel queued jobs and wait for the running ones (runs first)."""
        for pool in (self.runner, self.worker, self.decoder):
            pool.shutdown(wait=True, cancel_futures=True)


class Player:
    """Calls `tick()` every `1 / rate()` seconds on its own thread until `tick` returns False or `stop()`.

    Args:
        tick: one playback step; returns whether to go on.
        rate: steps per second, read before each wait (at least 0.1).
    """

    def __init__(self, tick: Callable[[], bool], rate: Callable[[], float]) -> None:
        self.tick = tick
        self.rate = rate
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="efem-viewer-play", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _loop(self) -> None:
        while not self._stop.wait(1.0 / max(self.rate(), 0.1)):
            if not self.tick():
                return
