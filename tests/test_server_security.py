"""Server security of the viewer and the annotator (items 5-8), against the real apps on port 0.

5. Cross-site WebSocket hijacking: a foreign `Origin`, a missing or wrong token are refused with HTTP 403; the
   printed URL (token in the query) and the cookie its page load sets are accepted. Also on the full CLI process.
6. A 0.0.0.0 bind warns in one line and prints a URL other machines can use (with the token).
7. Values a client sends over the WebSocket (bypassing the GUI's limits) are clamped/validated on the server.
8. Exports from the GUI stay inside the output folder chosen at start.
"""

from __future__ import annotations

import http.client
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterator

import numpy as np
import pytest
import trimesh

sys.path.insert(0, str(Path(__file__).parent))
from helpers import ball_scan, server_signals  # noqa: E402
from viser_client import AnnotateProcess, RawClient, ViserClient, handshake_status, wait_for, ws_url  # noqa: E402

from annotator.app import TOOLS, AnnotatorApp  # noqa: E402
from annotator.io import LabelIOError  # noqa: E402
from efem_viz.serve import guard  # noqa: E402
from efem_viz.serve.inputs import (  # noqa: E402
    ClientValueError,
    confine_writes,
    read_choice,
    read_int,
    read_number,
    read_rgb,
    read_text,
    resolve_inside_root,
    uncastable_value,
)

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------- fixtures
@pytest.fixture()
def scan(tmp_path: Path) -> Path:
    return ball_scan(tmp_path)


@pytest.fixture()
def annotator(scan: Path, tmp_path: Path) -> Iterator[AnnotatorApp]:
    a = AnnotatorApp(scan, out_dir=tmp_path / "out", port=0, autosave_delay=0)
    yield a
    a.close()


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A sphere scene with its saved EM result (analytic prior: exact, fast)."""
    import torch

    from efem_viz import em
    from efem_viz.data.io import save_scene
    from efem_viz.prior import analytic

    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("scenes")
    scene = analytic.make_sphere_scene(seed=0, spacing=0.012, name="spheres")
    save_scene(scene, d / "spheres.ply")
    cfg = em.preset("fast").with_proposals(8).replace(elimination={"min_size": 30})
    em.run_em(scene, analytic.make_sphere_prior(), cfg, seed=0).save(d / "spheres.efem.npz")
    return d


@pytest.fixture()
def viewer(scene_dir: Path, tmp_path: Path) -> Iterator[Any]:
    from efem_viz.prior import analytic
    from efem_viz.viewer.app import ViewerApp

    a = ViewerApp([scene_dir], port=0, prior=analytic.make_sphere_prior(), out_dir=tmp_path / "exports")
    assert a.wait_idle(60)
    yield a
    a.stop()


def _http_get(url: str, *, cookie: str | None = None, origin: str | None = None,
              host: str | None = None) -> tuple[int, dict[str, str], bytes]:
    m = re.match(r"http://([^/]+)(/.*)?$", url)
    assert m, url
    conn = http.client.HTTPConnection(m.group(1), timeout=10)
    headers = {}
    if cookie:
        headers["Cookie"] = cookie
    if origin:
        headers["Origin"] = origin
    if host:
        headers["Host"] = host
    conn.request("GET", m.group(2) or "/", headers=headers)
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, dict(r.getheaders()), body


def _base(url: str) -> str:
    return url.split("/?", 1)[0]


# ============================================================================ 5. origin + token (pure policy)
def _h(**kw: str) -> Any:
    data = {k.replace("_", "-").title(): v for k, v in kw.items()}
    return SimpleNamespace(get=lambda k, d=None: data.get(k, d),
                           get_all=lambda k: [data[k]] if k in data else [])


def test_policy_refuses_foreign_origin_rebinding_and_missing_token() -> None:
    tok = guard.new_token()
    pol = guard.AccessPolicy(token=tok, bind_host="127.0.0.1")
    ok = f"/?token={tok}"
    assert pol.refusal(path=ok, headers=_h(host="127.0.0.1:8080"), local_port=8080) is None
    # the printed origin, and localhost for a printed 127.0.0.1; the Host may be any loopback name
    assert pol.origin_hosts == {"127.0.0.1", "localhost"}
    assert pol.refusal(path=ok, headers=_h(host="127.0.0.1:8080", origin="http://localhost:8080"),
                       local_port=8080) is None
    assert pol.refusal(path=ok, headers=_h(host="[::1]:8080", origin="http://127.0.0.1:8080"), local_port=8080) is None
    # other loopback aliases are other origins: another local user's server can listen there
    for alias in ("http://127.0.0.2:8080", "http://[::1]:8080", "http://127.1.2.3:8080", "https://127.0.0.1:8080",
                  "http://127.0.0.1.:8081", "http://0.0.0.0:8080"):
        for host in ("127.0.0.1:8080", alias.split("//")[1]):
            why = pol.refusal(path=ok, headers=_h(host=host, origin=alias), local_port=8080)
            assert why is not None, (alias, host)
            assert "cross-origin" in why or "not a loopback name" in why, (alias, host, why)
    v6 = guard.AccessPolicy(token=tok, bind_host="::1")
    assert v6.origin_hosts == {"::1", "localhost"}
    assert v6.refusal(path=ok, headers=_h(host="[::1]:8080", origin="http://[::1]:8080"), local_port=8080) is None
    assert "cross-origin" in v6.refusal(path=ok, headers=_h(host="[::1]:8080", origin="http://127.0.0.1:8080"),
                                        local_port=8080)
    assert "cross-origin" in pol.refusal(path=ok, headers=_h(host="127.0.0.1:8080", origin="http://evil.example"),
                                         local_port=8080)
    assert "cross-origin" in pol.refusal(path=ok, headers=_h(host="127.0.0.1:8080", origin="http://localhost:9999"),
                                         local_port=8080)  # another local server's page
    assert "cross-origin" in pol.refusal(path=ok, headers=_h(host="127.0.0.1:8080", origin="null"), local_port=8080)
    assert "loopback" in pol.refusal(path=ok, headers=_h(host="evil.example:8080", origin="http://evil.example:8080"),
                                     local_port=8080)  # DNS rebinding
    assert "token" in pol.refusal(path="/", headers=_h(host="127.0.0.1:8080"), local_port=8080)
    # a port forward / SSH tunnel must keep the port: the printed origin is the only one accepted
    assert pol.refusal(path=ok, headers=_h(host="localhost:8080", origin="http://localhost:8080"),
                       local_port=8080) is None
    assert "cross-origin" in pol.refusal(path=ok, headers=_h(host="localhost:9000", origin="http://localhost:9000"),
                                         local_port=8080)
    assert "token" in pol.refusal(path="/?token=" + "x" * 32, headers=_h(host="127.0.0.1:8080"), local_port=8080)
    cookie = f"other=1; {pol.cookie_for(8080)}={tok}"
    assert pol.refusal(path="/", headers=_h(host="127.0.0.1:8080", cookie=cookie), local_port=8080) is None
    # the cookie of the server on another port does not open this one
    assert "token" in pol.refusal(path="/", headers=_h(host="127.0.0.1:8080", cookie=f"{pol.cookie_for(8081)}={tok}"),
                                  local_port=8080)
    with pytest.raises(ValueError):
        guard.AccessPolicy(token="short", bind_host="127.0.0.1")
    # a network bind accepts the machine's own name as Host, still only same-origin pages and the token
    net = guard.AccessPolicy(token=tok, bind_host="0.0.0.0", url_host="10.1.2.3")
    assert net.origin_hosts == {"10.1.2.3", "127.0.0.1", "localhost"}, "the URL and the 'on this machine' URL"
    assert net.refusal(path=ok, headers=_h(host="10.1.2.3:8080", origin="http://10.1.2.3:8080"),
                       local_port=8080) is None
    assert "cross-origin" in net.refusal(path=ok, headers=_h(host="myhost:8080", origin="http://myhost:8080"),
                                         local_port=8080), "a name that resolves here (DNS rebinding) is not printed"
    assert "cross-origin" in net.refusal(path=ok, headers=_h(host="10.1.2.3:8080", origin="http://evil.example"),
                                         local_port=8080)
    assert "token" in net.refusal(path="/", headers=_h(host="10.1.2.3:8080"), local_port=8080)


# ============================================================================ 5. against the real apps
_LOOPBACK_ALIASES = ("http://127.0.0.2:%d", "http://[::1]:%d", "http://127.0.0.1.:%d", "https://127.0.0.1:%d")
"""Origins that reach the same machine but are not the printed one."""


def _check_printed_origin_only(url: str) -> None:
    """Raw HTTP and WebSocket requests carrying loopback-alias origins, against a real server: refused (403) with
    the token; the printed origin and localhost pass."""
    port = int(re.search(r":(\d+)/", url).group(1))  # type: ignore[union-attr]
    assert url.startswith(f"http://127.0.0.1:{port}/?token=")
    for alias in _LOOPBACK_ALIASES:
        origin = alias % port
        assert handshake_status(ws_url(url), origin=origin) == 403, origin
        status, _, body = _http_get(url, origin=origin)
        assert status == 403 and b"cross-origin" in body, (origin, body[:200])
        # the alias also as the Host (a page of a server on 127.0.0.2 whose script connects there)
        assert _http_get(url, origin=origin, host=origin.split("//", 1)[1])[0] == 403, origin
    for ok in (f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
        assert handshake_status(ws_url(url), origin=ok) == 101, ok
        assert _http_get(url, origin=ok)[0] == 200, ok


def test_cli_servers_accept_only_the_printed_origin(view_cli: ViewCLI, scan: Path, tmp_path: Path) -> None:
    """Both CLIs, as started by a user: 127.0.0.2 and [::1] are not 127.0.0.1."""
    _check_printed_origin_only(view_cli.url)
    proc, lines = _start_cli(["-m", "annotator", str(scan), "--out", str(tmp_path / "o"), "--port", "0"])
    try:
        _check_printed_origin_only(re.search(r" at (http://\S+)", "".join(lines)).group(1))  # type: ignore[union-attr]
    finally:
        assert _stop_cli(proc) == 0


def _check_ws_guard(url: str, port: int, token: str) -> None:
    base = "ws://127.0.0.1:%d" % port
    own = f"http://127.0.0.1:{port}"
    assert handshake_status(base + "/", origin=own) == 403, "no token"
    assert handshake_status(base + "/?token=wrong-token-wrong-token-wrong", origin=own) == 403, "wrong token"
    assert handshake_status(ws_url(url), origin="http://evil.example") == 403, "foreign origin with the token"
    assert handshake_status(ws_url(url), origin=f"http://127.0.0.1:{port + 1}") == 403, "other local port"
    assert handshake_status(ws_url(url), origin=own) == 101, "the printed URL"
    assert handshake_status(ws_url(url), origin=f"http://localhost:{port}") == 101, "localhost = 127.0.0.1"
    for alias in _LOOPBACK_ALIASES:
        assert handshake_status(ws_url(url), origin=alias % port) == 403, alias
    assert handshake_status(ws_url(url)) == 101, "a script without Origin, with the token"
    # what the browser does: load the page (query token) → cookie → WebSocket on the bare URL with the cookie
    status, headers, body = _http_get(url)
    assert status == 200 and b"<html" in body[:400].lower()
    cookie = headers["Set-Cookie"].split(";", 1)[0]
    assert "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
    assert handshake_status(base, origin=own, cookie=cookie) == 101
    assert handshake_status(base, origin="http://evil.example", cookie=cookie) == 403
    # plain HTTP needs the token too (the page, any file)
    assert _http_get(_base(url) + "/")[0] == 403
    assert _http_get(_base(url) + "/index.html", cookie=cookie)[0] == 200
    assert _http_get(url, host=f"evil.example:{port}")[0] == 403


def test_viewer_refuses_foreign_origin_and_missing_token(viewer: Any) -> None:
    assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{32}", viewer.url), viewer.url
    _check_ws_guard(viewer.url, viewer.server.get_port(), viewer.access.token)


def test_annotator_refuses_foreign_origin_and_missing_token(annotator: AnnotatorApp) -> None:
    assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{32}", annotator.url), annotator.url
    _check_ws_guard(annotator.url, annotator.server.get_port(), annotator.access.token)


def test_a_refused_client_cannot_drive_the_annotator(annotator: AnnotatorApp) -> None:
    """Delete via a hostile page: refused at the handshake, the instance survives."""
    from websockets.exceptions import InvalidStatus

    iid = annotator.session.instances.new_instance(category="mug")
    with pytest.raises(InvalidStatus):
        RawClient(ws_url(annotator.url), origin="http://evil.example")
    assert iid in annotator.session.scan.store.labelset.instances
    with RawClient(annotator.url) as c:  # the token holder can
        assert wait_for(lambda: len(annotator.server.get_clients()) == 1)
        c.press(annotator.panels.gui_delete)
        assert wait_for(lambda: iid not in annotator.session.scan.store.labelset.instances)


def test_guard_fails_loudly_when_the_hook_point_is_gone(monkeypatch: pytest.MonkeyPatch) -> None:
    """If viser stops opening its socket through the hooked `serve`, nothing is served unguarded."""
    import websockets.asyncio.server as ws_server

    guard._install_serve_hook()
    assert guard._original_serve is not None
    monkeypatch.setattr(ws_server, "serve", guard._original_serve)  # viser now bypasses the wrapper
    monkeypatch.setattr(guard, "_install_serve_hook", lambda: None)
    with pytest.raises(guard.GuardUnavailableError, match="refusing to serve unguarded"):
        guard.start_server(host="127.0.0.1", port=0)


def test_a_busy_port_is_replaced_with_a_notice(caplog: pytest.LogCaptureFixture) -> None:
    """viser takes the next free port without a word; the server says which port it serves on instead."""
    import logging
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        with caplog.at_level(logging.WARNING, logger=guard.logger.name):
            server, access = guard.start_server(host="127.0.0.1", port=port)
        try:
            assert access.port != port and str(access.port) in access.url
            assert f"port {port} is busy" in caplog.text and f"serving on port {access.port} instead" in caplog.text
        finally:
            server.stop()


def test_client_cannot_rewrite_control_bounds(annotator: AnnotatorApp) -> None:
    """viser applies any property a client sends; the guard keeps only `value`, so bounds stay the server's."""
    with RawClient(annotator.url) as c:
        assert wait_for(lambda: len(annotator.server.get_clients()) == 1)
        c.set_gui(annotator.panels.gui_controls["radius"], max=1e9, min=-1e9, value=1e6)
        c.set_gui(annotator.panels.gui_tool, options=("brush", "rm"), value="rm")
        c.set_gui(annotator.panels.gui_delete, disabled=True)
        assert wait_for(lambda: abs(annotator.session.toolbox.settings.radius - 0.20) < 1e-9)
        radius = annotator.panels.gui_controls["radius"]
        assert radius.max == 20.0 and radius.min == pytest.approx(0.1)
        assert tuple(annotator.panels.gui_tool.options) == TOOLS
        assert annotator.panels.gui_delete.disabled is False
        assert annotator.session.toolbox.settings.tool == "brush"
        c.send({"type": "ShareUrlRequest"})  # would open a public tunnel to this server
        time.sleep(0.2)
        assert annotator.server._share_tunnel is None
    from viser import _messages

    assert _messages.ShareUrlRequest not in annotator.server._websock_server._incoming_handlers


# ============================================================================ 5./6. the CLI processes
def _start_cli(args: list[str], *, until: str = "  autosave:") -> tuple[subprocess.Popen[str], list[str]]:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in [str(REPO), os.environ.get("PYTHONPATH", "")] if p)
    proc = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env, preexec_fn=server_signals())
    lines: list[str] = []
    end = time.monotonic() + 90
    assert proc.stdout is not None
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if line.startswith(until):
            return proc, lines
    proc.kill()
    raise AssertionError("the CLI printed no URL:\n" + "".join(lines))


def _stop_cli(proc: subprocess.Popen[str]) -> int:
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait(10)


class ViewCLI(SimpleNamespace):
    """A running `efem-viz view` process: `proc`, `url` (as printed), `root` (its output root), `lines` (everything
    it printed, stdout and stderr, read on a thread), `client()` (a new connected `ViserClient`)."""

    def client(self) -> ViserClient:
        return ViserClient(self.url)

    def log(self) -> str:
        return "".join(self.lines)


@pytest.fixture(scope="module")
def view_cli(scene_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ViewCLI]:
    """The real `efem-viz view` CLI on the sphere scene (its saved result loads with it), on port 0."""
    root = tmp_path_factory.mktemp("view-out") / "root"
    proc, lines = _start_cli(["-m", "efem_viz.cli", "view", str(scene_dir / "spheres.ply"), "--port", "0",
                              "--out-dir", str(root)], until="  exports go to:")
    url = re.search(r"viewer: (http://\S+)", "".join(lines)).group(1)  # type: ignore[union-attr]
    assert proc.stdout is not None
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)  # type: ignore[arg-type]
    reader.start()
    try:
        yield ViewCLI(proc=proc, url=url, root=root.resolve(), lines=lines)
    finally:
        assert _stop_cli(proc) == 0
        reader.join(10)


def _notified(c: ViserClient, needle: str, *, before: int = 0) -> str:
    """The first notification after the first `before` ones that contains `needle` (waits for it)."""
    found: list[str] = []

    def seen() -> bool:
        found[:] = [t for t in c.notification_texts()[before:] if needle in t]
        return bool(found)

    assert c.wait_for(seen, 60), f"no notification with {needle!r}: {c.notification_texts()}"
    return found[0]


def test_annotate_cli_prints_a_tokenised_url_and_guards_it(scan: Path, tmp_path: Path) -> None:
    proc, lines = _start_cli(["-m", "annotator", str(scan), "--out", str(tmp_path / "o"), "--port", "0"])
    try:
        url = re.search(r" at (http://\S+)", "".join(lines)).group(1)  # type: ignore[union-attr]
        port = int(re.search(r":(\d+)/", url).group(1))  # type: ignore[union-attr]
        assert "?token=" in url and url.startswith("http://127.0.0.1:")
        assert not any("warning" in ln.lower() for ln in lines), "a loopback bind needs no warning"
        assert handshake_status(f"ws://127.0.0.1:{port}/", origin=f"http://127.0.0.1:{port}") == 403
        assert handshake_status(ws_url(url), origin="http://evil.example") == 403
        assert handshake_status(ws_url(url), origin=f"http://127.0.0.1:{port}") == 101
    finally:
        assert _stop_cli(proc) == 0


def test_annotate_cli_on_all_interfaces_warns_and_prints_a_reachable_url(scan: Path, tmp_path: Path) -> None:
    proc, lines = _start_cli(["-m", "annotator", str(scan), "--out", str(tmp_path / "o"), "--port", "0",
                              "--host", "0.0.0.0"])
    try:
        text = "".join(lines)
        warnings = [ln for ln in lines if "warning" in ln.lower()]
        assert len(warnings) == 1 and "anyone on the network" in warnings[0], text
        url = re.search(r" at (http://\S+)", text).group(1)  # type: ignore[union-attr]
        host = re.match(r"http://([^:/]+):", url).group(1)  # type: ignore[union-attr]
        assert host == guard.reachable_host("0.0.0.0") and host not in ("0.0.0.0", ""), url
        assert "?token=" in url
        assert re.search(r"on this machine: http://127\.0\.0\.1:\d+/\?token=", text), text
        assert handshake_status(ws_url(url), origin=_base(url)) == 101, "reachable at the printed address"
        assert handshake_status(ws_url(_base(url)), origin=_base(url)) == 403, "still needs the token"
    finally:
        assert _stop_cli(proc) == 0


def test_viewer_on_all_interfaces_warns_and_prints_a_reachable_url(
    scene_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from efem_viz.serve import lifecycle
    from efem_viz.viewer import commands

    def interrupt(_s: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(lifecycle.time, "sleep", interrupt)  # serve "until Ctrl+C": at once
    args = commands.ViewArgs(paths=(scene_dir / "spheres.ply",), host="0.0.0.0", port=0, prior=[],
                             out_dir=tmp_path / "o")
    assert args.run() == 0
    out = capsys.readouterr()
    warn = [ln for ln in out.err.splitlines() if "warning" in ln]
    assert len(warn) == 1 and "anyone on the network" in warn[0], out.err
    url = re.search(r"viewer: (http://\S+)", out.out).group(1)  # type: ignore[union-attr]
    assert url.startswith(f"http://{guard.reachable_host('0.0.0.0')}:") and "?token=" in url
    assert "127.0.0.1" not in url or guard.reachable_host("0.0.0.0") == "127.0.0.1"
    assert re.search(r"on this machine: http://127\.0\.0\.1:\d+/\?token=", out.out)


def test_loopback_app_urls_have_the_real_port_and_no_warning(annotator: AnnotatorApp) -> None:
    assert annotator.access.exposure_warning is None
    assert f":{annotator.server.get_port()}/" in annotator.url
    assert annotator.local_url == annotator.url


# ============================================================================ 7. values from clients
class _H(SimpleNamespace):
    pass


def test_read_helpers_clamp_and_reject() -> None:
    h = _H(label="Brush radius (cm)", value=1e6, min=0.1, max=20.0)
    fixed: list[Any] = []
    assert read_number(h, write_back=lambda _h, v: fixed.append(v)) == 20.0 and fixed == [20.0]
    h.value = -5.0
    assert read_number(h) == pytest.approx(0.1)
    for bad in (math.nan, math.inf, -math.inf, "abc", None, True):
        h.value = bad
        with pytest.raises(ClientValueError, match="Brush radius"):
            read_number(h)
    n = _H(label="Proposals", value=50_000_000, min=1, max=2000)
    assert read_int(n) == 2000
    n.value = 0
    assert read_int(n) == 1
    free = _H(label="x", value=1e300)  # no declared bounds: finite is enough
    assert read_number(free) == 1e300
    d = _H(label="Tool", value="rm -rf", options=("brush", "erase"))
    with pytest.raises(ClientValueError, match="not one of the options"):
        read_choice(d)
    d.value = "erase"
    assert read_choice(d) == "erase"
    t = _H(label="Name", value="x" * 5000)
    with pytest.raises(ClientValueError, match="longer"):
        read_text(t)
    t.value = "a\x00b"
    with pytest.raises(ClientValueError, match="NUL"):
        read_text(t)
    c = _H(label="Colour", value=(300, -4, 7))
    assert read_rgb(c) == (255, 0, 7)
    c.value = (1, 2)
    with pytest.raises(ClientValueError):
        read_rgb(c)


def test_annotator_clamps_a_raw_brush_radius_before_painting(annotator: AnnotatorApp) -> None:
    """The 1e6 cm brush: sent raw over the WebSocket, the click paints with the slider's maximum (20 cm)."""
    from annotator import selection as sel

    big = trimesh.creation.box(extents=(2.0, 2.0, 0.02)).subdivide().subdivide().subdivide()
    assert big is not None
    iid = annotator.session.instances.new_instance(category="mug")
    with RawClient(annotator.url) as c:
        assert wait_for(lambda: len(annotator.server.get_clients()) == 1)
        c.set_gui(annotator.panels.gui_controls["radius"], value=1e6)
        assert wait_for(lambda: annotator.session.toolbox.settings.radius == pytest.approx(0.20))
        assert wait_for(lambda: annotator.panels.gui_controls["radius"].value == 20.0), (
            "the clamped value is shown to all")
        # refused: the setting stays
        c.set_gui(annotator.panels.gui_controls["brush_max_angle_deg"], value=float("nan"))
        c.set_gui(annotator.panels.gui_controls["grow_distance"], value=-1e9)
        assert wait_for(lambda: annotator.session.toolbox.settings.grow_distance == pytest.approx(0.01))
        assert annotator.session.toolbox.settings.brush_max_angle_deg == 180.0
        c.set_gui(annotator.panels.gui_tool, value="no-such-tool")
        time.sleep(0.2)
        assert annotator.session.toolbox.settings.tool == "brush"
    # the computation sees the clamped radius: a click paints exactly the 20 cm ball
    hit = sel.pick(annotator.session.scan.geom, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))
    assert hit is not None
    annotator.session.painting.click(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))
    expect = sel.brush(annotator.session.scan.geom, hit[1], 0.20)
    assert np.array_equal(np.flatnonzero(annotator.session.scan.store.labels == iid), np.sort(expect))


def test_annotator_refuses_non_finite_scene_events(annotator: AnnotatorApp) -> None:
    annotator.session.instances.new_instance()
    ev = SimpleNamespace(ray_origin=(0.0, 0.0, math.nan), ray_direction=(0.0, 0.0, -1.0), client_id=1)
    with pytest.raises(ClientValueError):
        annotator.handle_event("click", ev)
    assert not (annotator.session.scan.store.labels > 0).any()


def test_annotator_text_fields_are_bounded(annotator: AnnotatorApp) -> None:
    iid = annotator.session.instances.new_instance(category="mug")
    with RawClient(annotator.url) as c:
        assert wait_for(lambda: len(annotator.server.get_clients()) == 1)
        c.set_gui(annotator.panels.gui_name, value="n" * 100_000)
        time.sleep(0.3)
        assert len(annotator.session.scan.store.labelset.info(iid).name) < 300
        c.set_gui(annotator.panels.gui_name, value="cup A")
        assert wait_for(lambda: annotator.session.scan.store.labelset.info(iid).name == "cup A")


def test_viewer_clamps_raw_proposals_and_rejects_nan(viewer: Any) -> None:
    """50,000,000 proposals sent raw (GUI max 2000): the run gets 2000; a NaN point size changes nothing."""
    calls: list[Any] = []
    viewer.start_run = lambda settings=None, **kw: calls.append(settings)  # looked up at call time
    p = viewer.panels
    size_before = viewer.state.point_size
    with RawClient(viewer.url) as c:
        assert wait_for(lambda: len(viewer.server.get_clients()) == 1)
        c.set_gui(p.gui_proposals, value=50_000_000)
        c.set_gui(p.gui_seed, value=-7)
        c.set_gui(p.gui_preset, value="../../etc")
        # The dropdown's own callback refuses the value first; only then is the press the one error source left
        # (callbacks run in a thread pool: on a busy machine a press's callback can run after later updates).
        assert wait_for(lambda: "not one of the options" in (viewer.state.error or ""))
        viewer.state.error = None
        c.press(p.gui_run)
        assert wait_for(lambda: "not one of the options" in (viewer.state.error or ""))
        assert not calls, "an unknown preset is refused before anything runs"
        viewer.state.error = None
        c.set_gui(p.gui_preset, value="fast")
        c.set_gui(p.gui_precision, value="float16")  # not one of the Precision options
        c.press(p.gui_run)
        assert wait_for(lambda: "not one of the options" in (viewer.state.error or ""))
        assert not calls, "an unknown precision is refused before anything runs"
        c.set_gui(p.gui_precision, value="bfloat16")
        viewer.state.error = None
        c.set_gui(p.gui_free_space, value="always")  # not one of the Free space options
        c.press(p.gui_run)
        assert wait_for(lambda: "not one of the options" in (viewer.state.error or ""))
        assert not calls, "an unknown free-space choice is refused before anything runs"
        c.set_gui(p.gui_free_space, value="on")
        time.sleep(0.1)
        c.press(p.gui_run)
        assert wait_for(lambda: bool(calls))
        got = calls[0]
        assert (got.preset, got.proposals, got.seed, got.matmul_dtype, got.free_space) == \
            ("fast", 2000, 0, "bfloat16", "on")
        assert wait_for(lambda: p.gui_proposals.value == 2000)
        c.set_gui(p.gui_point_size, value=float("nan"))
        assert wait_for(lambda: "finite" in (viewer.state.error or ""))
        assert viewer.state.point_size == size_before
        c.set_gui(p.gui_max_shapes, value=10**9)
        assert wait_for(lambda: viewer.state.max_shapes == 64)
        c.set_gui(p.gui_speed, value=1e9)
        assert wait_for(lambda: viewer.state.speed == 10.0)


# ============================================================================ 8. exports stay in the output root
def test_viewer_gui_exports_stay_inside_the_output_root(viewer: Any, tmp_path: Path) -> None:
    root = viewer.out_root
    assert root == (tmp_path / "exports").resolve()
    assert viewer.open_scene("spheres") and viewer.state.result is not None
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    root.mkdir(parents=True, exist_ok=True)
    os.symlink(outside, root / "link")
    for bad in ("../escape", str(outside), "/etc", "link/sub", "sub/../../x"):
        viewer.gui_set(viewer.panels.gui_out_dir, bad)
        with pytest.raises(ClientValueError, match="refusing output folder|not allowed"):
            viewer.export_tab.export_from_gui("results")
        with pytest.raises(ClientValueError):
            viewer.export_tab.export_from_gui("static")
    assert not any(outside.iterdir())
    viewer.gui_set(viewer.panels.gui_out_dir, "run1")
    fut = viewer.export_tab.export_from_gui("results")
    assert fut is not None and fut.result(60) == root / "run1"
    assert (root / "run1" / "spheres_instances.ply").is_file()


def test_view_cli_export_refuses_links_inside_the_output_root(view_cli: ViewCLI, tmp_path: Path) -> None:
    """on the real CLI: the typed folder is inside the root, but a link below it leads out (a
    `pred_mask` folder link; a file link at the last file written). Refused before anything is written."""
    root = view_cli.root
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("keep me\n")
    (root / "trap").mkdir(parents=True)
    os.symlink(outside, root / "trap" / "pred_mask")  # a folder link
    (root / "trap2" / "pred_mask").mkdir(parents=True)
    os.symlink(outside / "victim.txt", root / "trap2" / "spheres.txt")  # a file link, written after the masks
    os.symlink(root / "trap", root / "trap3")  # a folder link that stays inside the root leads out further down
    c = view_cli.client()
    try:
        for folder, link in (("trap", "pred_mask"), ("trap2", "spheres.txt"), ("trap3", "pred_mask")):
            n = len(c.notification_texts())
            c.set_value("Output folder", folder)
            c.click("Export results")
            text = _notified(c, "refusing export", before=n)
            assert link in text and "nothing was written" in text, text
            assert "\n" not in text.split(": ", 1)[1].strip(), "one line"
        assert sorted(p.name for p in outside.iterdir()) == ["victim.txt"]
        assert (outside / "victim.txt").read_text() == "keep me\n"
        assert [p.name for p in (root / "trap2").rglob("*")] in (["pred_mask", "spheres.txt"],
                                                                 ["spheres.txt", "pred_mask"])
        assert not list((root / "trap2" / "pred_mask").iterdir()), "no mask written before the refusal"
        # the same export into a plain folder works (the refusals above were the links, not the harness)
        c.set_value("Output folder", "plain")
        c.click("Export results")
        assert c.wait_for(lambda: (root / "plain" / "spheres_instances.ply").is_file(), 60)
        assert list((root / "plain" / "pred_mask").glob("spheres_*.txt"))
    finally:
        c.close()
    assert "Traceback" not in view_cli.log()


def test_view_cli_refuses_control_characters_and_uncastable_values(view_cli: ViewCLI) -> None:
    """on the real CLI: a newline in the output-folder field, and NaN / infinity / text sent for
    integer controls, are refused with one-line notices and one log line each; no traceback in the server log."""
    root = view_cli.root
    c = view_cli.client()
    try:
        n = len(c.notification_texts())
        c.set_value("Output folder", "run\nx")
        c.click("Export results")
        text = _notified(c, "control character", before=n)
        assert "Output folder" in text and "\\n" in text, text
        assert not list(root.glob("run*"))
        for label, bad in (("Proposals", math.nan), ("Seed", math.inf), ("Proposals", "many"),
                           ("Max shapes drawn", math.nan)):
            n = len(c.notification_texts())
            c.set_value(label, bad)
            text = _notified(c, "Value refused", before=n)
            assert label in text and "expected a finite integer" in text, text
    finally:
        c.close()
    log = view_cli.log()
    assert "Traceback" not in log and "cannot convert" not in log, log[-3000:]
    assert log.count("refused a client's value") == 4


def test_annotate_cli_refuses_a_nan_colour_without_a_traceback(scan: Path, tmp_path: Path) -> None:
    """a NaN (or text, or an overflow) sent for the colour control: one-line notice, one log line
    each, no traceback."""
    proc = AnnotateProcess(scan, tmp_path / "o")
    try:
        proc.edit(("new",))
        c = proc.client
        for bad in ([math.nan, 0, 0], "red", [1e400, 0, 0]):
            n = len(c.notification_texts())
            c.set_value("Colour", bad)
            text = _notified(c, "Value refused", before=n)
            assert text.count("\n") == 0 and "Colour" in text, text
    finally:
        assert proc.stop() == 0
    log = "".join(proc.lines)
    assert "Traceback" not in log and "cannot convert" not in log, log[-3000:]
    assert log.count("refused a client's value for 'Colour'") == 3


def test_an_uncastable_value_leaves_the_control_as_it_was(viewer: Any) -> None:
    p = viewer.panels
    before = p.gui_proposals.value
    with RawClient(viewer.url) as c:
        assert wait_for(lambda: len(viewer.server.get_clients()) == 1)
        c.set_gui(p.gui_seed, value=math.nan)
        c.set_gui(p.gui_proposals, value=math.inf)
        c.set_gui(p.gui_seed, value=5)  # a later good value still lands
        assert wait_for(lambda: p.gui_seed.value == 5)
    assert p.gui_proposals.value == before


def test_read_text_refuses_control_characters() -> None:
    for bad, shown in (("run\nx", "\\n"), ("a\x1b[2J", "\\x1b"), ("a\x00b", "NUL"), ("a\rb", "\\r")):
        with pytest.raises(ClientValueError, match="control character") as err:
            read_text(_H(label="Output folder", value=bad))
        assert shown in str(err.value) and "\n" not in str(err.value)
    assert read_text(_H(label="Name", value="cup A — café 杯")) == "cup A — café 杯"


def test_uncastable_values_are_named() -> None:
    assert uncastable_value(100, 5.0) is None and uncastable_value(100, "12") is None
    assert uncastable_value(1.0, math.nan) is None, "a float control casts NaN; read_number refuses it"
    assert uncastable_value((255, 0, 0), [1, 2, 3]) is None
    for current, bad in ((100, math.nan), (100, math.inf), (100, "many"), (100, None), ((255, 0, 0), [math.nan, 0, 0]),
                         ((255, 0, 0), "red"), ((255, 0, 0), 7)):
        assert uncastable_value(current, bad), (current, bad)


def test_export_writes_exactly_the_files_it_checks(viewer: Any, tmp_path: Path) -> None:
    """`results_files` (what the confinement check looks at) is what `export_results` writes."""
    from efem_viz.viewer.export import export_results, results_files

    assert viewer.open_scene("spheres") and viewer.state.result is not None
    s = viewer.state
    out = tmp_path / "exp"
    export_results(s.result, s.scene, out, threshold=s.threshold, root=tmp_path)
    planned = results_files(s.result, s.scene, out, threshold=s.threshold)
    assert len(planned) > 4, "some masks"
    assert sorted(planned) == sorted([out, *out.rglob("*")])


def test_confine_writes_follows_every_link(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "d").mkdir(parents=True)
    os.symlink(tmp_path, root / "up")
    os.symlink(root / "d", root / "inner")  # a folder link inside the root: fine
    (root / "d" / "f.txt").write_text("x")
    os.symlink(root / "d" / "f.txt", root / "d" / "flink.txt")  # a file link: atomic writes would stop at it
    assert confine_writes(["d", root / "inner" / "new.txt", root / "d" / "f.txt"], root) == [
        (root / "d").resolve(), (root / "d" / "new.txt").resolve(), (root / "d" / "f.txt").resolve()]
    for bad in (root / "up" / "x.txt", root / "up", root / "d" / "flink.txt", root / ".." / "x", tmp_path / "x"):
        with pytest.raises(ClientValueError, match="nothing was written"):
            confine_writes([root / "d" / "ok.txt", bad], root)


def test_viewer_static_demo_defaults_into_the_output_root(viewer: Any, tmp_path: Path) -> None:
    """"Export static demo" writes <output folder>/static/<scene>/, never into the checkout or the package."""
    assert viewer.open_scene("spheres")
    before = ({p: p.stat().st_mtime for p in (REPO / "static").rglob("*") if p.is_file()}
              if (REPO / "static").exists() else {})
    fut = viewer.export_tab.export_from_gui("static")  # the field holds the root itself
    assert fut is not None
    index = fut.result(120)
    assert index == viewer.out_root / "static" / "spheres" / "index.html" and index.is_file()
    after = ({p: p.stat().st_mtime for p in (REPO / "static").rglob("*") if p.is_file()}
             if (REPO / "static").exists() else {})
    assert before == after, "nothing in the checkout's static/ changed"


def test_resolve_inside_root_refuses_escapes(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "a").mkdir(parents=True)
    os.symlink(tmp_path, root / "up")
    assert resolve_inside_root("a", root) == (root / "a").resolve()
    assert resolve_inside_root(str(root), root) == root.resolve()
    assert resolve_inside_root("new/dir", root) == (root / "new" / "dir").resolve()
    for bad in ("..", "a/../..", "/tmp", "up", "up/x", "", "a\x00b"):
        with pytest.raises(ClientValueError):
            resolve_inside_root(bad, root)


def test_annotator_exports_only_into_the_output_folder(annotator: AnnotatorApp, scan: Path, tmp_path: Path) -> None:
    annotator.session.instances.new_instance()
    annotator.session.painting.paint(np.arange(10))
    out = annotator.session.scan.out_dir
    (out / "sub").mkdir()
    os.symlink(tmp_path, out / "escape")
    for bad in (str(scan.parent), "../scans", str(tmp_path), "escape", "/tmp"):
        with pytest.raises(LabelIOError):
            annotator.session.files.export("ply", directory=bad)
    assert [p.name for p in annotator.session.files.export("npz", directory="sub")] == ["ball.labels.npz"]
    assert (out / "sub" / "ball.labels.npz").is_file()
    assert sorted(p.name for p in scan.parent.iterdir()) == ["ball.ply"], "nothing written next to the scan"


def test_saved_token_is_kept_private_and_bad_files_are_replaced(tmp_path: Path) -> None:
    """`saved_token`: the first call writes a fresh token (mode 0600), later calls read it back; a file that is not
    one URL-safe token (too short, other characters, too big, a symbolic link) is replaced, never trusted."""
    import os
    import stat

    from efem_viz.serve.guard import TOKEN_FILE, saved_token

    tok, kept = saved_token(tmp_path)
    path = tmp_path / TOKEN_FILE
    assert not kept and len(tok) >= 16 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert saved_token(tmp_path) == (tok, True)
    for bad in ("short", "x" * 20 + "<script>", "y" * 300):
        path.write_text(bad)
        new, kept = saved_token(tmp_path)
        assert not kept and new != bad and path.read_text().strip() == new
    path.unlink()
    (tmp_path / "elsewhere").write_text("z" * 32)
    os.symlink(tmp_path / "elsewhere", path)
    new, kept = saved_token(tmp_path)
    assert not kept and new != "z" * 32 and not path.is_symlink()


@pytest.mark.parametrize("mode", [0o644, 0o666, 0o640, 0o602])
def test_a_saved_token_others_can_read_or_write_is_replaced_with_a_warning(
        tmp_path: Path, mode: int, caplog: pytest.LogCaptureFixture) -> None:
    """A `server.token` that others could read (and so enter with) or write (and so choose) is never printed in a
    URL again: a fresh token, mode 0600, replaces it, and one warning says why."""
    import stat

    from efem_viz.serve.guard import TOKEN_FILE, saved_token

    old, _ = saved_token(tmp_path)
    path = tmp_path / TOKEN_FILE
    path.chmod(mode)
    with caplog.at_level("WARNING"):
        new, kept = saved_token(tmp_path)
    assert not kept and new != old and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert any("readable or writable by others" in r.getMessage() for r in caplog.records)
    assert saved_token(tmp_path) == (new, True)


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to give the file to another user")
def test_a_saved_token_owned_by_another_user_is_replaced(tmp_path: Path) -> None:
    from efem_viz.serve.guard import TOKEN_FILE, saved_token

    old, _ = saved_token(tmp_path)
    os.chown(tmp_path / TOKEN_FILE, 65534, 65534)
    new, kept = saved_token(tmp_path)
    assert not kept and new != old and (tmp_path / TOKEN_FILE).stat().st_uid == os.getuid()


def test_view_results_alone_opens_the_scenes_its_batch_names_and_says_which_are_gone(tmp_path: Path) -> None:
    """`efem-viz view --results DIR` on a `segment --out DIR` folder alone (as USER_GUIDE.md and BATCH.md tell
    people to browse a batch): the viewer opens the scenes DIR's batch.json names, a line names the one whose scene
    file is gone, and with no scene left it is one error line. Full CLI, sphere prior (exact, fast)."""
    from efem_viz.data.io import save_scene
    from efem_viz.prior import analytic

    scenes = tmp_path / "scans"
    scenes.mkdir()
    for k in (0, 1):
        save_scene(analytic.make_sphere_scene(seed=k, spacing=0.014, name=f"balls_{k}"), scenes / f"balls_{k}.ply")
    out = tmp_path / "results"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    seg = subprocess.run([sys.executable, "-m", "efem_viz.cli", "segment", str(scenes), "--prior", "sphere",
                          "--preset", "fast", "--proposals", "8", "--out", str(out), "--no-scannet"],
                         capture_output=True, text=True, timeout=600, env=env)
    assert seg.returncode == 0, seg.stderr[-2000:]
    assert (out / "balls_0.efem.npz").is_file() and (out / "balls_1.efem.npz").is_file()
    (scenes / "balls_1.ply").unlink()
    proc, lines = _start_cli(["-m", "efem_viz.cli", "view", "--results", str(out), "--port", "0", "--prior", "sphere",
                              "--out-dir", str(tmp_path / "o")], until="  exports go to:")
    try:
        log = "".join(lines)
        assert "(1 scene;" in log, log
        assert "scene file not found for 1 result(s): balls_1" in log, log
    finally:
        assert _stop_cli(proc) in (0, 130)  # (stopping is test_server_stop's subject)
    (scenes / "balls_0.ply").unlink()
    gone = subprocess.run([sys.executable, "-m", "efem_viz.cli", "view", "--results", str(out), "--port", "0"],
                          capture_output=True, text=True, timeout=600, env=env)
    errors = [ln for ln in gone.stderr.splitlines() if "error" in ln]
    assert gone.returncode == 1 and len(errors) == 1 and "no scene to show" in errors[0], gone.stderr[-2000:]
