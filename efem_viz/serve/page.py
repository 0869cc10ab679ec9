"""What our servers add to viser's page: a focused GUI control keeps its keys.

viser's client moves the camera on WASD/QE and the arrow keys from a `document` listener that only steps aside for
text fields; a focused slider (Mantine's thumb, a `div` with `role="slider"`) is not one, so the arrow keys that step
the EM-step slider also orbited the camera. `KEYS_SCRIPT` stops those keys at the page's root element *after* the
control has handled them (React listens at its root container, below `<html>`), so the camera never sees them.

`with_page_additions` puts the script into the client's `index.html` as it is served (gzip or not); every other
response passes unchanged. The guarded `process_request` (`efem_viz.serve.guard`) calls it, so every server this
project starts (viewer, annotator) serves the same page.
"""

from __future__ import annotations

import functools
import gzip
from typing import Any

KEYS_SCRIPT = (
    "<script>/* efem-viz: a focused slider keeps its keys (the camera does not move with them) */"
    "document.documentElement.addEventListener('keydown',function(e){var t=e.target;"
    "if(t&&t.closest&&t.closest('[role=\"slider\"]')&&/^(Arrow|Page|Home$|End$)/.test(e.key)){e.stopPropagation();}"
    "});</script>"
)
"""Stops the keys a focused slider uses (arrows, Page Up/Down, Home, End) from reaching viser's camera listener."""

_MARKER = b"</head>"


def add_to_html(page: bytes) -> bytes:
    """`page` with `KEYS_SCRIPT` before its `</head>` (unchanged when it has none or already holds it)."""
    script = KEYS_SCRIPT.encode("utf-8")
    if script in page or _MARKER not in page:
        return page
    return page.replace(_MARKER, script + _MARKER, 1)


@functools.lru_cache(maxsize=4)
def _patched(body: bytes, zipped: bool) -> bytes | None:
    """The served page with the additions (re-compressed when `zipped`), or None to serve it unchanged. Cached:
    viser serves the same cached page bytes on every load, so the (de)compression runs once per page."""
    try:
        page = gzip.decompress(body) if zipped else body
    except (OSError, EOFError):  # not what the header says: serve it as it is
        return None
    new = add_to_html(page)
    if new is page:
        return None
    return gzip.compress(new) if zipped else new


def with_page_additions(response: Any) -> Any:
    """The response with `KEYS_SCRIPT` in it when it carries the client's HTML page (status 200, `text/html`),
    re-compressed and with its Content-Length updated; any other response unchanged."""
    headers = getattr(response, "headers", None)
    body = getattr(response, "body", None)
    if headers is None or not isinstance(body, (bytes, bytearray)) or getattr(response, "status_code", 0) != 200:
        return response
    if not str(headers.get("Content-Type", "")).startswith("text/html"):
        return response
    payload = _patched(bytes(body), headers.get("Content-Encoding", "identity") == "gzip")
    if payload is None:
        return response
    response.body = payload
    if "Content-Length" in headers:
        del headers["Content-Length"]
    headers["Content-Length"] = str(len(payload))
    return response
