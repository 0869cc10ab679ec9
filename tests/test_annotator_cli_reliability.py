"""Reliability of the full `efem-annotate` CLI, driven by a scripted WebSocket client (tests/viser_client.py).

An edit counts as acknowledged when the server has sent the instance table that shows it: that is all a user
ever sees. Checked here, on the real process:
- kill -9 at random moments during painting and undo: the restarted CLI shows the last acknowledged table, or the
  one after it (the edit in flight may have reached the journal before its table was sent);
- injected ENOSPC on the journal write path (a `sitecustomize` wrapping `os.write` for `*.journal` files while a
  flag file exists): each refused edit says "Not done" in the GUI and changes nothing; after space comes back,
  later edits land and survive a clean Ctrl+C and restart.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

sys.path.insert(0, str(Path(__file__).parent))
from viser_client import JOURNAL_FAULTS_SITECUSTOMIZE as FAULTS  # noqa: E402
from viser_client import AnnotateProcess as Cli  # noqa: E402


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("scan") / "ball.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=0.1).export(p)  # 2562 vertices
    return p


def _spots(scan: Path, n: int) -> list[np.ndarray]:
    """n well-separated vertex directions of the ball (farthest-point order, deterministic)."""
    v = np.asarray(trimesh.load(scan, process=False).vertices)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    chosen = [0]
    d = np.linalg.norm(v - v[0], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(v - v[k], axis=1))
    return [v[k] for k in chosen]


def _script(scan: Path, n: int) -> list[tuple]:
    spots = _spots(scan, n)
    steps: list[tuple] = [("new",)]
    for k in range(n):
        steps.append(("paint", spots[k]))
        if k % 4 == 3:
            steps.append(("undo",))
    return steps


@pytest.mark.slow  # several CLI starts and kills: 15-20 s
def test_kill_9_at_random_moments_loses_no_acknowledged_edit(scan: Path, tmp_path: Path) -> None:
    steps = _script(scan, 14)
    ref = Cli(scan, tmp_path / "ref")
    tables = [ref.table()] + [ref.edit(s) for s in steps]
    assert ref.stop() == 0
    rng = np.random.default_rng(13)
    for trial in range(3):
        out = tmp_path / f"kill{trial}"
        cli = Cli(scan, out)
        stop_after = int(rng.integers(3, len(steps) - 1))
        acked = 0
        for s in steps[:stop_after]:
            assert cli.edit(s) == tables[acked + 1], "the scripted run must be deterministic"
            acked += 1
        # one more edit goes out, and the process dies at a random moment while it is handled
        cli.edit(steps[stop_after], expect_change=False)
        time.sleep(float(rng.uniform(0.0, 0.05)))
        cli.kill()
        again = Cli(scan, out)
        seen = again.table()
        assert seen in (tables[acked], tables[acked + 1]), f"trial {trial}: acked {acked}, recovered:\n{seen}"
        # and the session goes on: the next edits land
        assert again.stop() == 0


def test_disk_full_on_the_journal_refuses_edits_then_later_edits_survive(scan: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(FAULTS)
    flag = tmp_path / "disk-full"
    env = {"PYTHONPATH_FIRST": str(site), "EFEM_TEST_FAULT_FILE": str(flag)}
    spots = _spots(scan, 9)
    out = tmp_path / "out"
    cli = Cli(scan, out, env)
    cli.edit(("new",))
    for k in range(3):
        cli.edit(("paint", spots[k]))
    good = cli.table()
    flag.write_text("full")
    for k in range(3, 6):
        n_notes = len(cli.client.notifications)
        cli.edit(("paint", spots[k]), expect_change=False)
        cli.must(lambda n=n_notes: len(cli.client.notifications) > n)
        assert any("No space left" in t for t in cli.client.notification_texts()[n_notes:])
        time.sleep(0.2)
        assert cli.table() == good, "a refused edit must not show as applied"
    flag.unlink()
    for k in range(6, 9):
        cli.edit(("paint", spots[k]))
    final = cli.table()
    journal = next(out.glob("*.annotate/*.journal"))
    assert cli.stop() == 0
    again = Cli(scan, out)
    assert again.table() == final
    assert not list(journal.parent.glob("*.damaged-*")) and not list(journal.parent.glob("*.torn-*")), \
        "a failed append must leave no partial record behind"
    assert "Recovered" not in again.client.markdown("Autosave") + "".join(again.lines)
    assert again.stop() == 0


def test_damaged_journal_is_reported_in_the_gui(scan: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    cli = Cli(scan, out)
    spots = _spots(scan, 6)
    cli.edit(("new",))
    for k in range(6):
        cli.edit(("paint", spots[k]))
    final = cli.table()
    assert cli.stop() == 0
    journal = next(out.glob("*.annotate/*.journal"))
    data = bytearray(journal.read_bytes())
    offs = [m.start() for m in re.finditer(b"EFJ1", bytes(data))]
    data[offs[3] + 40] ^= 0xFF
    journal.write_bytes(bytes(data))
    again = Cli(scan, out)
    assert again.table() == final, "the checkpoint covers the damaged record: nothing is lost"
    again.must(lambda: any("recovered" in t.lower() for t in again.client.notification_texts()))
    status = next((c["props"].get("_markdown", "") for c in again.client.components.values()
                   if "Recovered" in str(c["props"].get("_markdown", ""))), "")
    assert "no edit recorded in the journal or the checkpoint is missing" in status and "damaged" in status
    assert "nothing was lost" not in status
    assert again.stop() == 0


def test_a_journal_cut_short_without_checkpoint_is_not_called_lossless(scan: Path, tmp_path: Path) -> None:
    """on the real CLI: after a session, the journal is cut to half its bytes and the checkpoint
    deleted. Fewer vertices come back, and the GUI says what was verified and what cannot be, never that nothing
    was lost."""
    out = tmp_path / "out"
    cli = Cli(scan, out)
    cli.edit(("new",))
    for spot in _spots(scan, 8):
        cli.edit(("paint", spot))
    labelled = sum(cli.counts().values())
    assert cli.stop() == 0
    journal = next(out.glob("*.annotate/*.journal"))
    next(out.glob("*.annotate/*.labels.npz")).unlink()
    data = journal.read_bytes()
    offs = [m.start() for m in re.finditer(b"EFJ1", data)]
    half = len(data) // 2 + (7 if len(data) // 2 in offs else 0)
    torn_at = max(o for o in offs if o < half)
    journal.write_bytes(data[:half])
    again = Cli(scan, out)
    try:
        assert sum(again.counts().values()) < labelled, "the cut really lost edits"
        again.must(lambda: any("not everything verifiable" in t for t in again.client.notification_texts()))
        status = again.client.markdown("**⚠ Recovered")
        for text in (status, next(t for t in again.client.notification_texts() if "verifiable" in t)):
            assert "nothing was lost" not in text and "no edit recorded" not in text
            assert f"incomplete record at byte {torn_at:,}" in text and "checkpoint: missing" in text
            assert "cannot be verified" in text and "journal cut short" in text
    finally:
        assert again.stop() == 0


@pytest.fixture()
def small_disk(tmp_path: Path):
    """A real 2 MiB tmpfs (skipped where mounting is not allowed)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here: " + r.stderr.decode(errors="replace").strip())
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _fill(disk: Path) -> Path:
    filler = disk / "filler"
    try:
        with open(filler, "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * 4096)
    except OSError:
        pass
    return filler


def test_real_full_disk_shows_in_the_gui_and_loses_nothing(scan: Path, small_disk: Path) -> None:
    """No injection: the output folder is on a real filesystem that fills up. Appends that still fit in the
    journal's last page land (and are kept); the checkpoint rewrite fails at once, which the GUI must say."""
    spots = _spots(scan, 14)
    out = small_disk / "out"
    cli = Cli(scan, out)
    cli.edit(("new",))
    for k in range(2):
        cli.edit(("paint", spots[k]))
    filler = _fill(small_disk)
    n_notes = len(cli.client.notifications)
    for k in range(2, 10):
        cli.edit(("paint", spots[k]), expect_change=False)
        time.sleep(0.3)
    cli.must(lambda: any("Autosave failed" in t for t in cli.client.notification_texts()[n_notes:]))
    assert "No space left" in " ".join(cli.client.notification_texts()[n_notes:])
    assert "⚠" in cli.client.markdown("**⚠"), "the status panel shows the standing problem"
    filler.unlink()
    for k in range(10, 14):
        cli.edit(("paint", spots[k]))
    cli.must(lambda: any("works again" in t for t in cli.client.notification_texts()))
    final = cli.table()
    assert cli.stop() == 0
    again = Cli(scan, out)
    assert again.table() == final, "every edit the GUI showed survives"
    assert again.stop() == 0


def test_a_restart_keeps_the_url_and_says_it_resumed(scan: Path, tmp_path: Path) -> None:
    """after a restart the old tab hung on "Connecting…" because the new server drew a new token.
    The scan's folder now keeps the token: killed (-9) and restarted on the same scan and --out, the CLI prints the
    same token, says it resumed from the journal and that the URL is the same, and a client using the old URL gets
    in (the old tab reconnecting). The kept token is readable by its owner only."""
    import socket
    import stat
    from urllib.parse import parse_qs, urlsplit

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    first = Cli(scan, tmp_path / "out", args=("--port", str(port)))
    token = parse_qs(urlsplit(first.url).query)["token"][0]
    first.edit(_script(scan, 1)[0])
    first.kill()
    again = Cli(scan, tmp_path / "out", args=("--port", str(port)))
    try:
        assert parse_qs(urlsplit(again.url).query)["token"][0] == token
        text = "".join(again.lines)
        assert "resumed from the journal" in text and "same URL as the last run" in text, text
        # before its URL, the CLI says what the opening does (seconds on a big scan)
        stages = [ln.split(": ", 2)[-1] for ln in again.lines if ln.startswith(f"efem-annotate: opening {scan.name}: ")
                  and "estimating normals" not in ln]  # (normals: when the file has none)
        assert [x.split(" ", 2)[:2] for x in stages] == [["reading", "the"], ["opening", "the"], ["starting", "the"],
                                                          ["preparing", "the"]], text
        assert text.index("preparing the drawing") < text.index(again.url)
        if urlsplit(again.url).port == port:  # (the port was free again: the very same URL)
            assert again.url == first.url
        kept = next((tmp_path / "out").glob("*.annotate/server.token"))
        assert stat.S_IMODE(kept.stat().st_mode) == 0o600 and kept.read_text().strip() == token
        assert "vertices labelled" in again.table()  # the client on the old token is served
    finally:
        assert again.stop() == 0


def test_a_name_typed_just_before_a_kill_is_kept(scan: Path, tmp_path: Path) -> None:
    """A name typed into the Name field and killed (-9) before its commit (the field waits for the typing to
    pause) is not lost: each keystroke's value is kept in the work folder, and the restarted CLI saves it to the
    instance and says so."""
    out = tmp_path / "out"
    cli = Cli(scan, out)
    cli.edit(("new",))
    cli.client.set_value("Name", "blue mug with a chip")
    pending = out / f"{scan.stem}.annotate" / "typing.json"
    cli.must(pending.is_file, what="the typed value to the work folder")
    cli.kill()
    again = Cli(scan, out)
    try:
        again.must(lambda: "blue mug with a chip" in again.table(), what="the restored name in the table")
        again.must(lambda: any("typed just before" in t for t in again.client.notification_texts()),
                   what="the notice that the name was restored")
        assert not pending.exists()
    finally:
        assert again.stop() == 0
