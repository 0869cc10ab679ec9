"""Access guard for the viser servers of the viewer and the annotator (the one place that opens them).

A viser server is an HTTP + WebSocket endpoint that anyone who can reach the port can drive: a page on another
origin (cross-site WebSocket hijacking), another user of a shared machine, or anyone on the network for a 0.0.0.0
bind. `start_server` opens a `viser.ViserServer` whose every HTTP request and WebSocket handshake first passes
`AccessPolicy.refusal`:

* **Token.** A random per-server secret (`new_token`) must come with the request: as `?token=...` in the URL (the
  printed URL carries it, like a notebook server's) or as the cookie that the first page load with a valid token
  sets (viser's client opens its WebSocket on the page URL *without* the query string, so the cookie carries the
  token there). The token is required on every bind, loopback included: on a shared machine any local user can
  reach 127.0.0.1.
* **Origin.** A browser always sends `Origin` on a WebSocket handshake (and on cross-origin fetches). It must be
  exactly an origin the server printed: `http://<host>:<port>` of its URL or of its "on this machine" URL, with
  `localhost` counted as the same name as 127.0.0.1 (or ::1) when that is what was printed (`AccessPolicy.
  origin_hosts`). Nothing else counts: not another loopback alias (127.0.0.2, [::1] when 127.0.0.1 was printed:
  another local user's server can listen there), not another port, not a name that merely resolves here. A port
  forward or SSH tunnel works when it keeps the port (`ssh -L 8080:127.0.0.1:8080`). `Origin: null` (sandboxed
  frames, file:// pages) is refused. Requests without `Origin` come from non-browser clients and still need the
  token.
* **Host (loopback binds).** `Host` must be a loopback name, which defeats DNS rebinding (a foreign name that
  resolves to 127.0.0.1).

Refused requests get HTTP 403 with a one-line reason. The server also drops every client GUI update that touches
anything but a control's `value` (viser lets a client rewrite `min`, `max`, `options` or `disabled` of any control),
so the bounds that `efem_viz.serve.inputs` clamps to are the ones the server declared; drops a value viser could not
cast to its control's type (a NaN for an integer or colour control: `inputs.uncastable_value`) with one log line
instead of a traceback; and ignores clients' requests to open a public viser share tunnel.

Hook point (viser 1.1.1, websockets 16): viser opens its socket with `websockets.asyncio.server.serve(...,
process_request=<its static file server>)`. While `start_server` constructs a `ViserServer` (under a lock), the
`serve` wrapper installed here wraps that `process_request` with the policy; outside that window it passes every
call through unchanged. If the wrapper was not called (another viser, another websockets), the new server is
stopped and `GuardUnavailableError` raised: the apps never run unguarded.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import inspect
import ipaddress
import logging
import os
import secrets
import socket
import threading
from dataclasses import dataclass, field
from http.cookies import CookieError, SimpleCookie
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol
from urllib.parse import parse_qs, urlsplit

from efem_viz.serve.page import with_page_additions

if TYPE_CHECKING:
    import viser

logger = logging.getLogger(__name__)

TOKEN_PARAM = "token"
"""URL query parameter carrying the token."""
COOKIE_PREFIX = "efem_viz_token_"
"""Cookie name prefix; the port follows (cookies are per host, not per port)."""
WILDCARD_HOSTS = ("0.0.0.0", "", "::")
"""Bind addresses that listen on every interface."""
TESTED_VISER = ("1.1.",)
"""viser versions whose hook point was checked by hand (others are used when the hook still attaches)."""


class GuardUnavailableError(RuntimeError):
    """The access guard could not be attached to the viser server (the server is not started)."""


class _Headers(Protocol):
    def get(self, key: str, default: Any = None) -> Any: ...  # noqa: D102

    def get_all(self, key: str) -> list[str]: ...  # noqa: D102


def new_token() -> str:
    """A fresh random server token (URL-safe, 32 characters, 192 bits)."""
    return secrets.token_urlsafe(24)


TOKEN_FILE = "server.token"
"""Where a server that works in a folder of its own keeps its token (`saved_token`)."""


def saved_token(folder: str | os.PathLike[str]) -> tuple[str, bool]:
    """The token kept in `folder/server.token`, or a fresh one written there (readable by its owner only).

    A server restarted on the same folder (the annotator on the same scan and `--out`) keeps its URL, so a tab
    left open reconnects by itself instead of hanging on "Connecting…". A file that is not a plain file of one
    URL-safe token of 16-128 characters, or that others could read or write (any group/other permission bit) or
    that another user owns, is replaced by a fresh token (mode 0600, owned by this user) and a warning says why:
    a token others can read lets them in.

    Returns:
        (token, True when it was read back from the folder).

    Raises:
        OSError: the folder cannot be written.
    """
    path = Path(folder) / TOKEN_FILE
    try:
        if path.is_file() and not path.is_symlink() and path.stat().st_size <= 256:
            st = path.stat()
            if st.st_mode & 0o077 or st.st_uid != os.getuid():
                logger.warning("%s is readable or writable by others (mode %o, owner uid %d): not used; a fresh "
                            "token replaces it (mode 600)", path, st.st_mode & 0o777, st.st_uid)
            else:
                text = path.read_text(encoding="ascii").strip()
                if 16 <= len(text) <= 128 and all(c.isalnum() or c in "-_" for c in text):
                    return text, True
    except (OSError, UnicodeDecodeError):
        pass
    token = new_token()
    tmp = path.with_name(f".{TOKEN_FILE}.tmp-{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, (token + "\n").encode("ascii"))
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    return token, False


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses (127.0.0.0/8, ::1), brackets allowed ("[::1]")."""
    h = host.strip().strip("[]").lower().rstrip(".")
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    """True for binds on every interface (0.0.0.0, ::, empty)."""
    return host.strip().strip("[]") in WILDCARD_HOSTS


def _host_port(value: str, *, default_port: int | None) -> tuple[str, int | None]:
    """("localhost", 8080) from "localhost:8080", ("::1", 80) from "[::1]" with default_port=80.

    Raises:
        ValueError: not a host[:port].
    """
    parts = urlsplit("//" + value.strip())
    host = parts.hostname
    if not host or parts.path or parts.query or parts.username is not None:
        raise ValueError(f"bad host {value!r}")
    port = parts.port  # ValueError when out of range / not a number
    return host.lower().rstrip("."), port if port is not None else default_port


def _host_name(host: str) -> str:
    """A host as origins are compared: lower case, no brackets (a trailing dot makes another origin, as in
    browsers)."""
    return host.strip().strip("[]").lower()


LOCALHOST_SAME_AS = frozenset({"127.0.0.1", "::1", "localhost"})
"""Printed hosts for which the name `localhost` is the same origin (and 127.0.0.1 for a printed `localhost`): the
usual way to type the printed loopback URL. Other loopback aliases are other origins."""


@dataclass(frozen=True)
class AccessPolicy:
    """Who may talk to one server: the token, the bind address it listens on, and the origins it printed.

    Args:
        token: the server's secret (non-empty).
        bind_host: the address the server binds ("127.0.0.1", "0.0.0.0", ...).
        url_host: the host of the printed URL (default: `reachable_host(bind_host)`, what `ServerAccess.url`
            prints).
    """

    token: str
    """The per-server secret."""
    bind_host: str
    """The bind address; a loopback bind also requires a loopback `Host` header."""
    url_host: str = ""
    """The host of the URL printed at start (filled in from `bind_host` when empty)."""

    def __post_init__(self) -> None:
        if not self.token or len(self.token) < 16:
            raise ValueError("the server token must be at least 16 characters")
        if not self.url_host:
            object.__setattr__(self, "url_host", reachable_host(self.bind_host))

    @property
    def local_host(self) -> str:
        """The host of the "on this machine" URL (`ServerAccess.local_url`)."""
        return local_host(self.bind_host)

    @property
    def origin_hosts(self) -> frozenset[str]:
        """The hosts a browser `Origin` may name (with this server's port): those of the printed URLs, plus
        `localhost` for a printed 127.0.0.1 or ::1 (and 127.0.0.1 for a printed `localhost`)."""
        printed = {_host_name(self.url_host), _host_name(self.local_host)}
        same = set(printed)
        if printed & LOCALHOST_SAME_AS:
            same.add("localhost")
        if "localhost" in printed:
            same.add("127.0.0.1")
        return frozenset(same)

    def cookie_for(self, port: int) -> str:
        """The cookie name for the server on `port`."""
        return f"{COOKIE_PREFIX}{int(port)}"

    def refusal(self, *, path: str, headers: _Headers, local_port: int) -> str | None:
        """Why a request must be refused, or None when it may pass.

        Args:
            path: the request target, with its query ("/?token=...").
            headers: the request headers (`get`, `get_all`).
            local_port: the port the request arrived on.

        Returns:
            A one-line reason, or None.
        """
        host_header = headers.get("Host")
        if not host_header:
            return "no Host header"
        try:
            req_host, _ = _host_port(str(host_header), default_port=80)
        except ValueError:
            return f"bad Host header {host_header!r}"
        if is_loopback(self.bind_host) and not is_loopback(req_host):
            return f"Host {host_header!r} is not a loopback name (this server listens on {self.bind_host} only)"
        origin = headers.get("Origin")
        if origin is not None:
            why = self._origin_refusal(str(origin), local_port)
            if why is not None:
                return why
        if not self.token_ok(path, headers, local_port):
            return "missing or wrong token: open the URL printed at start (it ends in ?token=...)"
        return None

    def _origin_refusal(self, origin: str, local_port: int) -> str | None:
        """An `Origin` passes only when it is `http://<host>:<port>` with a host of `origin_hosts` and the port
        the server listens on (the printed port)."""
        parts = urlsplit(origin.strip())
        if parts.scheme != "http" or not parts.hostname:
            return f"cross-origin request (Origin {origin!r})"
        try:
            o_port = parts.port or 80
        except ValueError:
            return f"bad Origin {origin!r}"
        if o_port != local_port or _host_name(parts.hostname) not in self.origin_hosts or parts.path not in ("", "/"):
            return f"cross-origin request from {origin} (only the printed origin is accepted)"
        return None

    def token_ok(self, path: str, headers: _Headers, local_port: int) -> bool:
        """True when the query (`?token=`) or this server's cookie carries the token (constant-time compare)."""
        return any(hmac.compare_digest(c.encode(), self.token.encode())
                   for c in self._candidates(path, headers, local_port))

    def query_token_ok(self, path: str) -> bool:
        """True when the URL query itself carries the right token (the response then sets the cookie)."""
        return any(hmac.compare_digest(c.encode(), self.token.encode()) for c in _query_tokens(path))

    def _candidates(self, path: str, headers: _Headers, local_port: int) -> list[str]:
        found = _query_tokens(path)
        name = self.cookie_for(local_port)
        for raw in headers.get_all("Cookie"):
            jar: SimpleCookie = SimpleCookie()
            try:
                jar.load(raw)
            except CookieError:
                continue
            if name in jar:
                found.append(jar[name].value)
        return found

    def set_cookie_header(self, port: int) -> str:
        """The `Set-Cookie` value that lets the page's WebSocket (opened without the query) carry the token."""
        return f"{self.cookie_for(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"


def _query_tokens(path: str) -> list[str]:
    query = urlsplit(path).query
    return [t for t in parse_qs(query, keep_blank_values=True).get(TOKEN_PARAM, []) if t]


# ============================================================================================== hook into viser
@dataclass
class _Armed:
    policy: AccessPolicy
    attached: bool = False
    refused: set[str] = field(default_factory=set)


_LOCK = threading.RLock()
_armed: _Armed | None = None
_original_serve: Callable[..., Any] | None = None


def _local_port(connection: Any) -> int:
    addr = connection.local_address
    return int(addr[1])


def _guarded_process_request(armed: _Armed, inner: Callable[..., Any] | None) -> Callable[..., Any]:
    """Wrap viser's `process_request(connection, request)` with the access policy."""
    policy = armed.policy

    async def process_request(connection: Any, request: Any) -> Any:
        port = _local_port(connection)
        why = policy.refusal(path=request.path, headers=request.headers, local_port=port)
        if why is not None:
            kind = why.split(" ", 2)[0]
            log = logger.warning if kind not in armed.refused else logger.debug
            armed.refused.add(kind)
            log("refused %s from %s: %s", request.path.split("?", 1)[0], connection.remote_address, why)
            return connection.respond(http.HTTPStatus.FORBIDDEN, f"efem-viz: access refused: {why}\n")
        response = inner(connection, request) if inner is not None else None
        if inspect.isawaitable(response):
            response = await response
        if response is not None and policy.query_token_ok(request.path):
            response.headers["Set-Cookie"] = policy.set_cookie_header(port)
        return with_page_additions(response) if response is not None else None

    return process_request


def _serve_wrapper(*args: Any, **kwargs: Any) -> Any:
    """Stand-in for `websockets.asyncio.server.serve`: guards the call made while a guarded server starts."""
    armed = _armed
    assert _original_serve is not None
    if armed is not None:
        kwargs["process_request"] = _guarded_process_request(armed, kwargs.get("process_request"))
        armed.attached = True
    return _original_serve(*args, **kwargs)


def _install_serve_hook() -> None:
    """Put `_serve_wrapper` in place of `websockets.asyncio.server.serve` (idempotent)."""
    global _original_serve
    try:
        import websockets.asyncio.server as ws_server
    except ImportError as exc:  # pragma: no cover - viser depends on websockets
        raise GuardUnavailableError(f"websockets.asyncio.server is missing ({exc}); cannot guard the server") from exc
    current = getattr(ws_server, "serve", None)
    if current is None:
        raise GuardUnavailableError("websockets.asyncio.server.serve is missing; cannot guard the viser server")
    if current is _serve_wrapper:
        return
    _original_serve = current
    ws_server.serve = _serve_wrapper  # type: ignore[assignment]


def _only_value_updates(_client_id: Any, message: Any) -> None:
    """Drop client updates to anything but a control's value (viser would apply `max`, `options`, ...)."""
    updates = getattr(message, "updates", None)
    if isinstance(updates, dict):
        dropped = [k for k in updates if k != "value"]
        for k in dropped:
            del updates[k]
        if dropped:
            logger.warning("dropped a client's update of GUI properties %s (only values may change)", dropped)


def _castable_values(server: viser.ViserServer, handles: dict[Any, Any]) -> Callable[[Any, Any], None]:
    """A GuiUpdateMessage filter that drops a value viser could not cast to its control's type
    (`efem_viz.serve.inputs.uncastable_value`: a NaN for an integer or colour control), with one log line and a
    notification to the client that sent it, instead of viser's traceback."""
    from efem_viz.serve.inputs import uncastable_value

    def drop_uncastable(client_id: Any, message: Any) -> None:
        updates = getattr(message, "updates", None)
        handle = handles.get(getattr(message, "uuid", None))
        if not isinstance(updates, dict) or "value" not in updates or handle is None:
            return
        impl = getattr(handle, "_impl", None)
        why = uncastable_value(getattr(impl, "value", None), updates["value"])
        if why is None:
            return
        del updates["value"]
        label = str(getattr(handle, "label", "") or "control")
        logger.warning("refused a client's value for %r: %s", label, why)
        client = server.get_clients().get(client_id)
        if client is not None:
            try:
                client.add_notification("Value refused", f"{label}: {why}", color="red", auto_close_seconds=8.0)
            except Exception:  # noqa: BLE001 - the client may be gone
                pass

    return drop_uncastable


def _install_update_filter(server: viser.ViserServer) -> None:
    """Run `_only_value_updates` and `_castable_values` before viser's own GuiUpdateMessage handler; drop the
    share-tunnel handlers."""
    from viser import _messages

    handlers = getattr(getattr(server, "_websock_server", None), "_incoming_handlers", None)
    if not isinstance(handlers, dict) or _messages.GuiUpdateMessage not in handlers:
        raise GuardUnavailableError("viser's GUI update handler was not found; cannot filter client updates")
    inputs = getattr(getattr(server, "gui", None), "_gui_input_handle_from_uuid", None)
    if not isinstance(inputs, dict):
        raise GuardUnavailableError("viser's GUI handle table was not found; cannot check client values")
    handlers[_messages.GuiUpdateMessage][0:0] = [_only_value_updates, _castable_values(server, inputs)]
    # viser lets any client ask the server to open a public share tunnel (share.viser.studio): never.
    for cls in (getattr(_messages, "ShareUrlRequest", None), getattr(_messages, "ShareUrlDisconnect", None)):
        if cls is not None:
            handlers.pop(cls, None)


@dataclass(frozen=True)
class ServerAccess:
    """How to reach a guarded server: its token and the URLs to print.

    Args:
        token: the server's secret.
        bind_host: the address it binds.
        port: the port it really listens on.
    """

    token: str
    """The per-server secret (in `url`)."""
    bind_host: str
    """The bind address."""
    port: int
    """The real port (viser moves to the next free one when the asked port is busy)."""
    url_host: str = ""
    """The host of `url` (the access policy's `url_host`: the origin browsers must come from); empty =
    `reachable_host(bind_host)`."""

    @property
    def url(self) -> str:
        """The URL to open, with the token: the machine's address for a wildcard bind, else the bind address."""
        return self._url(self.url_host or reachable_host(self.bind_host))

    @property
    def local_url(self) -> str:
        """The URL from this machine (127.0.0.1 for wildcard and loopback binds)."""
        return self._url(local_host(self.bind_host))

    def _url(self, host: str) -> str:
        shown = f"[{host}]" if ":" in host and not host.startswith("[") else host
        return f"http://{shown}:{self.port}/?{TOKEN_PARAM}={self.token}"

    @property
    def exposure_warning(self) -> str | None:
        """One warning line when the server is reachable from other machines, else None."""
        if is_loopback(self.bind_host):
            return None
        where = "every interface" if is_wildcard(self.bind_host) else self.bind_host
        return (
            f"warning: listening on {where} (port {self.port}): anyone on the network who has the URL with its "
            "token can view and edit here; bind 127.0.0.1 (the default) to keep it private"
        )


def local_host(bind_host: str) -> str:
    """The host of the URL to use from this machine: 127.0.0.1 for a wildcard bind, else the bind address."""
    return "127.0.0.1" if is_wildcard(bind_host) else bind_host


def reachable_host(bind_host: str) -> str:
    """The address other machines use for a wildcard bind (the primary interface's IP, else the hostname);
    the bind address itself otherwise."""
    if not is_wildcard(bind_host):
        return bind_host
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: picks the outgoing interface, sends nothing
            ip = str(s.getsockname()[0])
        if ip and not ip.startswith("0."):
            return ip
    except OSError:
        pass
    return socket.gethostname() or "127.0.0.1"


class ServedApp:
    """What both browser apps say about where they are served (`ViewerApp` and `AnnotatorApp` inherit it): they
    set `access` (the `ServerAccess` of `start_server`) when their server starts."""

    access: ServerAccess

    @property
    def url(self) -> str:
        """The URL to open, with the access token (the machine's address for a 0.0.0.0 bind; the real port)."""
        return self.access.url

    @property
    def local_url(self) -> str:
        """The URL from this machine (127.0.0.1 for loopback and 0.0.0.0 binds), with the token."""
        return self.access.local_url


def start_server(*, host: str = "127.0.0.1", port: int = 8080,
                 token: str | None = None) -> tuple[viser.ViserServer, ServerAccess]:
    """Start a `viser.ViserServer` behind the access guard.

    Args:
        host: bind address (127.0.0.1 unless told otherwise).
        port: port (0 = any free port; a busy port is replaced by the next free one).
        token: the secret; None draws a fresh one (`new_token`).

    Returns:
        The running server and how to reach it (`ServerAccess.url`).

    Raises:
        GuardUnavailableError: the guard could not be attached (the server is stopped, never left running).
        ValueError: a token shorter than 16 characters.
    """
    import viser

    global _armed
    policy = AccessPolicy(token=token if token is not None else new_token(), bind_host=host)
    version = str(getattr(viser, "__version__", "?"))
    if not version.startswith(TESTED_VISER):
        logger.warning("viser %s is untested with the efem-viz access guard (tested: %s)", version, TESTED_VISER)
    with _LOCK:
        _install_serve_hook()
        armed = _Armed(policy)
        _armed = armed
        console = _rich_console()
        quiet = getattr(console, "quiet", False)
        try:
            if console is not None:
                console.quiet = True  # viser prints its URL without the token: it would only be refused
            server = viser.ViserServer(host=host, port=port, verbose=False)
        finally:
            _armed = None
            if console is not None:
                console.quiet = quiet
    if not armed.attached:
        server.stop()
        raise GuardUnavailableError(
            f"could not attach the access guard to viser {version}: its server no longer opens its socket through "
            "websockets.asyncio.server.serve; refusing to serve unguarded"
        )
    try:
        _install_update_filter(server)
    except GuardUnavailableError:
        server.stop()
        raise
    actual = int(server.get_port())
    if port and actual != port:  # viser takes the next free port without a word: say so
        logger.warning("port %d is busy (another server?): serving on port %d instead", port, actual)
    return server, ServerAccess(token=policy.token, bind_host=host, port=actual, url_host=policy.url_host)


def _rich_console() -> Any:
    try:
        import rich

        return rich.get_console()
    except Exception:  # noqa: BLE001 - rich is optional here: without it there is nothing to silence
        return None
