"""`efem-annotate SCAN [--labels FILE] [--out DIR] [--host 127.0.0.1] [--port 8081]`: label a scan in the browser."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from annotator.io import MAX_SCAN_POINTS
from annotator.scan_view import DISPLAY_POINTS


@dataclass
class AnnotateArgs:
    """Label per-vertex object instances of a scan in the browser (viser). Edits are journalled and autosaved."""

    scan: tyro.conf.Positional[Path]
    """Scan to label: PLY/OBJ/OFF/GLB/NPZ mesh or point cloud, or an RGB-D frame .npz. Never modified."""
    labels: Path | None = None
    """Labels to start from (PLY `instance`, NPZ, ScanNet .aggregation.json / .segs.json, EFEM .efem.npz).
    Ignored when the output folder already has a journal for this scan (the session resumes)."""
    out: Path | None = None
    """Output folder for the journal, autosave checkpoint and exports (default: the current directory). Exports
    are written only inside it."""
    host: str = "127.0.0.1"
    """Bind address. The default serves this machine only; 0.0.0.0 serves anyone on the network who has the
    printed URL (it carries the access token)."""
    port: int = 8081
    """TCP port (a busy port is replaced by the next free one; the real URL is printed)."""
    max_points: int = MAX_SCAN_POINTS
    """Refuse scans with more vertices than this (a 5M-vertex scan needs about 2.2 GB of memory at its peak)."""
    display_points: int = DISPLAY_POINTS
    """Draw at most this many vertices in the browser: a larger scan is shown as an evenly spread subset of them
    (every tool still labels all vertices)."""
    autosave_delay: float = 0.5
    """Seconds between an edit and the checkpoint rewrite (the journal is written before every edit returns)."""
    token: str | None = None
    """Access token to require (default: the one this scan's output folder keeps, `<scan>.annotate/server.token`,
    made on the first run: the URL stays the same across restarts). At least 16 characters."""
    device: str = "auto"
    """Where click-to-segment and EFEM runs solve: auto (CUDA when this machine has it, else the CPU), cpu or
    cuda."""
    accept_scan_mismatch: bool = False
    """Resume a session whose journal was written for other scan geometry with the same vertex count (e.g. the
    same scan re-exported). Without it such a session is refused, so labels never land on the wrong points."""

    def run(self) -> int:
        """Open the scan, print the URL, serve until Ctrl+C / SIGTERM (`efem_viz.serve.lifecycle`)."""
        from annotator.app import AnnotatorApp
        from efem_viz.cli import check_device, check_port
        from efem_viz.serve.lifecycle import announce, stop_signals, wait_for_stop

        check_port(self.port)  # before the scan is read (a bad port used to hang in viser's server thread)
        from annotator import efem_runs

        efem_runs.use_device(check_device(self.device))  # CUDA asked for without CUDA: one line, before the scan
        with stop_signals("efem-annotate"):  # before loading: Ctrl+C stops a long load too
            app = AnnotatorApp(
                self.scan,
                labels_path=self.labels,
                out_dir=self.out,
                host=self.host,
                port=self.port,
                max_points=self.max_points,
                display_points=self.display_points,
                autosave_delay=self.autosave_delay,
                accept_scan_mismatch=self.accept_scan_mismatch,
                token=self.token,
                on_stage=lambda what: print(f"efem-annotate: opening {Path(self.scan).name}: {what} …", flush=True),
            )
            try:
                ses = app.session
                if ses.scan.store.recovery is not None:
                    print("efem-annotate: " + ses.scan.store.recovery.summary().replace("\n", "\n  "), flush=True)
                details = [f"autosave: {ses.scan.work_dir}", f"EFEM assist runs on: {efem_runs.solve_device()}"]
                if ses.scan.store.resumed:
                    details.append(f"resumed from the journal: {ses.scan.store.journal.next_seq:,} records, "
                                   f"{len(ses.scan.store.labelset.undo_stack):,} undoable edits")
                if app.token_kept:
                    details.append("same URL as the last run on this scan: a tab left open reconnects by itself")
                announce("efem-annotate",
                         f"{ses.scan.scan_path.name} ({ses.scan.n:,} vertices) at {app.url}  — Ctrl+C to quit",
                         url=app.url, local_url=app.local_url, exposure_warning=app.access.exposure_warning,
                         details=tuple(details))
                wait_for_stop()
            finally:
                app.close()
        return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `efem-annotate` console script.

    Errors print one line `efem-annotate: error: ...` on stderr and exit 1 (LabelIOError and JournalError are
    ValueErrors); `--debug` (or EFEM_DEBUG=1) shows the traceback instead. `--version` prints the version.
    """
    from efem_viz.cli import package_version, pop_debug_flag, run_reporting_errors
    from efem_viz.cpu import configure_allocator, configure_openmp
    from efem_viz.terminal import log_to_terminal

    configure_openmp()  # before torch is imported: OpenMP threads sleep at barriers (sharing busy cores)
    configure_allocator()  # a long-lived server: large freed arrays go back to the system, not to the heap

    rest, debug = pop_debug_flag(list(sys.argv[1:] if argv is None else argv))
    if rest and rest[0] in ("--version", "-V"):
        print(f"efem-annotate {package_version()}")
        return 0
    log_to_terminal()
    args = tyro.cli(AnnotateArgs, args=rest, prog="efem-annotate")
    return run_reporting_errors("efem-annotate", args.run, debug=debug)


if __name__ == "__main__":
    sys.exit(main())
