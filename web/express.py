"""The panel's express lane: a fresh connection's first read, when it is one whole simple request,
parsed at the door (web/door.py) so that a few answers need nothing of aiohttp.

A fresh request through aiohttp costs ~0.5 ms on the bench's VM before any handler of ours runs
(its protocol, request and response objects, a task per connection: aiohttp's hello world against a
bare asyncio protocol, fresh connections, 200 each): the panel POST's estop paid it on every press,
and a burst of 200 read-only live feeds paid it 176 times for the 503s past the cap, with the
estop's connection queued behind them. The lane is a filter, never a
second server: `parse` takes only the plain case (HTTP/1.1, one complete request that ends the read,
a Content-Length body or none, no header the checks read given twice) and anything else is None,
left to aiohttp, which judges it as it always has. The panel (web/panel.py, `Panel.express`) answers
from it with the same checks and the same bodies as its aiohttp routes.

The parser is llhttp (Node's, through httptools, as uvicorn uses it): the same rules as aiohttp's C
parser, none written here.
"""

from __future__ import annotations

import http
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import httptools
from multidict import CIMultiDict, CIMultiDictProxy

#: A first read longer than this is left to aiohttp (its own limits on lines and fields judge it).
MAX_READ_BYTES = 8192
#: Headers a check reads: given twice, the request is aiohttp's to judge.
_ONCE = frozenset({b"host", b"origin", b"cookie", b"content-length", b"x-usmswitch-token"})


@dataclass(frozen=True)
class Request:
    """One whole request from a connection's first read."""

    method: str
    path: str
    headers: CIMultiDictProxy[str]
    body: bytes

    @property
    def cookies(self) -> Mapping[str, str]:
        """The Cookie header's pairs read as aiohttp reads them: `;`-separated, a value maybe in
        double quotes, a name without `=` an empty value, the last of a name kept. Browsers send
        every cookie of the host, other applications' among them: http.cookies would drop the
        whole header at the first it dislikes."""
        jar: dict[str, str] = {}
        for pair in self.headers.get("Cookie", "").split(";"):
            name, _, value = pair.strip().partition("=")
            value = value.strip()
            if len(value) >= 2 and value[0] == value[-1] == '"':
                value = value[1:-1]
            if name.strip():
                jar[name.strip()] = value
        return jar


class _Collect:
    """httptools' callbacks: what one request is made of, and how many began."""

    def __init__(self) -> None:
        self.begun = 0
        self.complete = False
        self.url = b""
        self.fields: list[tuple[bytes, bytes]] = []
        self.body = b""

    def on_message_begin(self) -> None:
        self.begun += 1

    def on_url(self, url: bytes) -> None:
        self.url += url

    def on_header(self, name: bytes, value: bytes) -> None:
        self.fields.append((name.lower(), value))

    def on_body(self, body: bytes) -> None:
        self.body += body

    def on_message_complete(self) -> None:
        self.complete = True


def parse(data: bytes, max_body: int) -> Request | None:
    """The request `data` is, when it is one whole plain request; None: aiohttp's to judge."""
    if len(data) > MAX_READ_BYTES:
        return None
    got = _Collect()
    parser = httptools.HttpRequestParser(got)
    try:
        parser.feed_data(data)
    except httptools.HttpParserUpgrade as upgrade:  # a WebSocket's GET: the head is whole
        if upgrade.args[0] != len(data):
            return None
    except httptools.HttpParserError:
        return None
    if got.begun != 1 or not got.complete or parser.get_http_version() != "1.1":
        return None
    names = [name for name, _ in got.fields]
    if b"transfer-encoding" in names or any(names.count(name) > 1 for name in _ONCE if name in names):
        return None
    if len(got.body) > max_body:
        return None
    try:
        url = httptools.parse_url(got.url)
        headers = CIMultiDict((name.decode("ascii"), value.decode("latin-1")) for name, value in got.fields)
        path = url.path.decode("ascii")
    except (httptools.HttpParserInvalidURLError, UnicodeDecodeError):
        return None
    if url.query is not None or url.fragment is not None or url.schema is not None:
        return None
    return Request(parser.get_method().decode("ascii"), path, CIMultiDictProxy(headers), got.body)


def json_answer(status: int, payload: Any) -> bytes:
    """A whole HTTP answer with a JSON body (as aiohttp's `json_response` writes it), then a close."""
    body = json.dumps(payload).encode()
    head = (
        f"HTTP/1.1 {status} {http.HTTPStatus(status).phrase}\r\n"
        "Content-Type: application/json; charset=utf-8\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    return head.encode("ascii") + body
