"""What our servers add to viser's page (`efem_viz.serve.page`): the slider-keys script, in plain and gzip pages."""

from __future__ import annotations

import gzip

from websockets.datastructures import Headers
from websockets.http11 import Response

from efem_viz.serve.page import KEYS_SCRIPT, add_to_html, with_page_additions

PAGE = b"<!doctype html><html><head><title>viser</title></head><body><div id=root></div></body></html>"


def _response(body: bytes, *, ctype: str = "text/html; charset=utf-8", zipped: bool = False,
              status: int = 200) -> Response:
    payload = gzip.compress(body) if zipped else body
    return Response(status, "OK", Headers(**{"Content-Type": ctype, "Content-Length": str(len(payload)),
                                             "Content-Encoding": "gzip" if zipped else "identity"}), payload)


def test_script_goes_before_head_end_once() -> None:
    out = add_to_html(PAGE)
    assert out.count(KEYS_SCRIPT.encode()) == 1 and out.index(KEYS_SCRIPT.encode()) < out.index(b"</head>")
    assert add_to_html(out) == out  # idempotent
    assert add_to_html(b"<html>no head</html>") == b"<html>no head</html>"


def test_plain_and_gzip_pages_get_it_with_a_right_length() -> None:
    for zipped in (False, True):
        r = with_page_additions(_response(PAGE, zipped=zipped))
        body = gzip.decompress(r.body) if zipped else r.body
        assert KEYS_SCRIPT.encode() in body
        assert r.headers["Content-Length"] == str(len(r.body)) and len(r.headers.get_all("Content-Length")) == 1


def test_other_responses_pass_unchanged() -> None:
    js = _response(b"console.log('</head>')", ctype="application/javascript")
    assert with_page_additions(js).body == b"console.log('</head>')"
    refused = _response(PAGE, status=403)
    assert with_page_additions(refused).body == PAGE
    broken = _response(b"not gzip", zipped=False)
    del broken.headers["Content-Encoding"]
    broken.headers["Content-Encoding"] = "gzip"
    assert with_page_additions(broken).body == b"not gzip"  # says gzip, is not: served as it is
