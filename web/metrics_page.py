"""The Prometheus page, served over HTTP by the socket's server process (server/rpc_process.py).

The daemon sends two snapshots over its channel, as it sends `stats`: `metrics_strokes` (counts and
histograms of committed strokes, fleet/metrics.py, from the record writer's thread) and
`metrics_state` (state, fault, targets, record writer and shipper figures, from the loop's slack).
This module turns them, with the server's own count of socket clients, into prometheus_client
metric families and text (`choose_encoder`: the Prometheus text format, or OpenMetrics when the
scraper asks), and serves them with aiohttp's low-level server on the server process's event loop.
A scrape never reaches the loop's process. Why there: docs/fleet.md, "Where the page is served".
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import msgpack
from aiohttp import web
from prometheus_client.core import (
    CollectorRegistry,
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.exposition import choose_encoder

from usmswitch.fleet.metrics import DIRECTION_NAMES, FEEDS, HISTOGRAMS, OUTCOMES, STATE_FEED, STROKES_FEED
from usmswitch.web.budgets import HTTP_BACKLOG, METRICS_CONNECTIONS, METRICS_HEAD_S, METRICS_IDLE_S
from usmswitch.web.door import Door, QuietLog

log = logging.getLogger("usmswitch.rpc")
STATES = ("idle", "cycling", "fault", "stopped")
#: Histogram names on the page, with the unit in the name as Prometheus wants (base unit: seconds).
HISTOGRAM_NAMES = {
    "error": ("usmswitch_error_seconds", "Stroke error: total (command to arrival) minus the target T."),
    "operating": ("usmswitch_operating_seconds", "Operating time t: motor start to the far sensor."),
    "lateness": (
        "usmswitch_start_lateness_seconds",
        "Start lateness: motor start minus (command + delay), host-timed strokes.",
    ),
}
# HTTP (web/door.py): a request line or header longer than this is refused (aiohttp's parser, 400);
# a request head begun must be complete within HEAD_TIMEOUT_S (408, closed: each byte restarts
# nothing); a connection that sends nothing for IDLE_TIMEOUT_S, at its start or between scrapes, is
# closed (Prometheus keeps one open per target and scrapes every 5-60 s); past MAX_SCRAPERS at once
# the longest idle is shed for a newcomer, else the newcomer is answered 503 and closed. Pipelined
# requests wait in the kernel once aiohttp's queue is full.
MAX_LINE_BYTES = 8190
HEAD_TIMEOUT_S = METRICS_HEAD_S
IDLE_TIMEOUT_S = METRICS_IDLE_S
MAX_SCRAPERS = METRICS_CONNECTIONS
#: Answers go out at most this often, all connections together (50 a second: Prometheus scrapes
#: a target every few seconds). Scrapers hammering the page then wait for their turn instead of
#: keeping the server process, and the machine's second core, busy.
ANSWER_INTERVAL_NS = 20_000_000

Source = Callable[[], tuple[Mapping[str, bytes], Mapping[str, int]]]


def _s(ns: float | None) -> float:
    return float("nan") if ns is None else ns / 1e9


class PageCollector:
    """Metric families from the latest snapshots (prometheus_client's collector interface)."""

    def __init__(self, source: Source) -> None:
        self.source = source

    def collect(self) -> Iterator[Metric]:
        """Every family on the page, from the snapshots as they are now."""
        snaps, clients = self.source()
        strokes = _unpack(snaps.get(STROKES_FEED))
        state = _unpack(snaps.get(STATE_FEED))
        rig = str(state.get("rig", ""))
        info = GaugeMetricFamily(
            "usmswitch_info",
            "The daemon: rig, driver and version (always 1).",
            labels=["rig", "driver", "version"],
        )
        info.add_metric([rig, str(state.get("driver", "")), str(state.get("version", ""))], 1)
        yield info
        if strokes:
            yield from _stroke_families(rig, strokes)
        if state:
            yield from _state_families(rig, state)
        sock = GaugeMetricFamily(
            "usmswitch_socket_clients", "Connections open on the control socket.", labels=["rig", "transport"]
        )
        for transport, n in sorted(clients.items()):
            sock.add_metric([rig, transport], n)
        yield sock


def _unpack(packed: bytes | None) -> dict[str, Any]:
    return {} if packed is None else msgpack.unpackb(packed, raw=False)


def _stroke_families(rig: str, snap: dict[str, Any]) -> Iterator[Metric]:
    total = CounterMetricFamily(
        "usmswitch_strokes",
        "Strokes committed to the records since the daemon started, by direction and outcome.",
        labels=["rig", "direction", "outcome"],
    )
    for direction in DIRECTION_NAMES:
        for outcome in OUTCOMES:
            total.add_metric([rig, direction, outcome], snap["strokes"][direction][outcome])
    yield total
    for key, (_, bounds) in HISTOGRAMS.items():
        name, doc = HISTOGRAM_NAMES[key]
        fam = HistogramMetricFamily(name, doc, labels=["rig", "direction"])
        for direction in DIRECTION_NAMES:
            h = snap["histograms"][key][direction]
            cumulative, buckets = 0, []
            for bound, n in zip((*bounds, None), h["buckets"], strict=True):
                cumulative += n
                buckets.append(("+Inf" if bound is None else repr(bound / 1e9), cumulative))
            fam.add_metric([rig, direction], buckets, sum_value=h["sum_ns"] / 1e9)
        yield fam
    last = snap["last"]
    for name, key, doc in (
        ("usmswitch_predicted_seconds", "t_hat_ns", "The predicted operating time t_hat of the last stroke."),
        ("usmswitch_run_error_mean_seconds", "run_error_mean_ns", "Mean error of the current or last run."),
        ("usmswitch_run_error_std_seconds", "run_error_std_ns", "Error std of the current or last run."),
    ):
        fam = GaugeMetricFamily(name, doc, labels=["rig", "direction"])
        for direction in DIRECTION_NAMES:
            if last[direction][key] is not None:
                fam.add_metric([rig, direction], _s(last[direction][key]))
        yield fam
    newest = max(
        (last[d] for d in DIRECTION_NAMES if last[d]["cycle"] is not None),
        key=lambda x: x["cycle"],
        default=None,
    )
    temp = GaugeMetricFamily(
        "usmswitch_temperature_celsius", "Motor temperature at the last stroke (when the rig reports it).",
        labels=["rig"],
    )  # fmt: skip
    if newest is not None and newest["temperature_c"] is not None:
        temp.add_metric([rig], newest["temperature_c"])
    yield temp
    if snap.get("run_id") is not None:
        run = GaugeMetricFamily("usmswitch_run_id", "The current or last run's id.", labels=["rig"])
        run.add_metric([rig], snap["run_id"])
        yield run


def _state_families(rig: str, state: dict[str, Any]) -> Iterator[Metric]:
    st = GaugeMetricFamily(
        "usmswitch_state", "The loop's state (1 for the current one).", labels=["rig", "state"]
    )
    for name in STATES:
        st.add_metric([rig, name], 1 if state["state"] == name else 0)
    yield st
    fault = GaugeMetricFamily(
        "usmswitch_fault", "1 while a FAULT is latched (until reset_fault).", labels=["rig"]
    )
    fault.add_metric([rig], 1 if state["fault"] else 0)
    yield fault
    target = GaugeMetricFamily(
        "usmswitch_target_seconds", "The target T per direction.", labels=["rig", "direction"]
    )
    for d, direction in enumerate(DIRECTION_NAMES):
        target.add_metric([rig, direction], _s(state["targets_ns"][d]))
    yield target
    rec = state["records"]
    backlog = GaugeMetricFamily(
        "usmswitch_records_backlog", "Records submitted and not yet committed to SQLite.", labels=["rig"]
    )
    backlog.add_metric([rig], rec["backlog"])
    yield backlog
    ok = GaugeMetricFamily(
        "usmswitch_records_writer_ok", "1 while the records file is writable.", labels=["rig"]
    )
    ok.add_metric([rig], 0 if rec["writer_error"] else 1)
    yield ok
    pg = state.get("postgres")
    if pg is None:
        return
    for name, key, doc, kind in (
        ("usmswitch_postgres_up", "connected", "1 while the shipper is connected to PostgreSQL.", "g"),
        ("usmswitch_postgres_lag_strokes", "lag", "Strokes committed locally, not yet in PostgreSQL.", "g"),
        ("usmswitch_postgres_shipped_cycle", "shipped_cycle", "The highest cycle PostgreSQL holds.", "g"),
        ("usmswitch_postgres_shipped_strokes", "shipped", "Strokes inserted into PostgreSQL.", "c"),
        ("usmswitch_postgres_errors", "error_count", "Failed connects and batches (each retried).", "c"),
    ):
        fam = (CounterMetricFamily if kind == "c" else GaugeMetricFamily)(name, doc, labels=["rig"])
        fam.add_metric([rig], int(pg[key]))
        yield fam


class MetricsPage:
    """The page's bytes, rendered again only when a snapshot or the client count changed."""

    def __init__(self, source: Source) -> None:
        self.source = source
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(PageCollector(source))  # type: ignore[arg-type]
        self._cache: dict[str, tuple[tuple[Any, ...], bytes]] = {}
        self._next_answer_ns = 0

    def wait_for_turn_s(self) -> float:
        """Seconds until the next answer may go out, that slot taken (ANSWER_INTERVAL_NS apart)."""
        now = time.monotonic_ns()
        at = max(now, self._next_answer_ns)
        self._next_answer_ns = at + ANSWER_INTERVAL_NS
        return (at - now) / 1e9

    def render(self, accept: str) -> tuple[bytes, str]:
        """(body, content type) for a scrape with this Accept header."""
        encoder, content_type = choose_encoder(accept)
        snaps, clients = self.source()
        key = (*(snaps.get(f) for f in FEEDS), tuple(sorted(clients.items())))
        hit = self._cache.get(content_type)
        if hit is not None and hit[0] == key:
            return hit[1], content_type
        body = encoder(self.registry)
        self._cache[content_type] = (key, body)
        return body, content_type


async def _answer(page: MetricsPage, request: web.BaseRequest) -> web.StreamResponse:
    """One request, in its turn: GET or HEAD of /metrics (or of / for a link to it)."""
    delay = page.wait_for_turn_s()
    if delay > 0:
        await asyncio.sleep(delay)
    if request.method not in ("GET", "HEAD"):
        reply = web.Response(status=405, text="only GET and HEAD\n", headers={"Allow": "GET, HEAD"})
    elif request.path == "/metrics":
        try:
            body, content_type = page.render(request.headers.get("Accept", ""))
        except Exception as exc:  # a bug costs this scrape, not the server
            log.exception("metrics page failed")
            return web.Response(status=500, text=f"metrics page failed: {type(exc).__name__}: {exc}\n")
        reply = web.Response(body=body, headers={"Content-Type": content_type})
    elif request.path == "/":
        page_link = '<html><body><a href="/metrics">usmswitchd metrics</a></body></html>\n'
        reply = web.Response(text=page_link, content_type="text/html")
    else:
        reply = web.Response(status=404, text="not found: the page is /metrics\n")
    if request.keep_alive:  # HTTP/1.1 keeps it anyway; said, as the scraper's logs may show it
        reply.headers["Connection"] = "keep-alive"
    return reply


async def serve_metrics(sock: socket.socket, source: Source) -> asyncio.Server:
    """Serve the page on a listening TCP socket the daemon bound (the server process's event loop)."""
    page = MetricsPage(source)
    door = Door("metrics page", MAX_SCRAPERS, HEAD_TIMEOUT_S, IDLE_TIMEOUT_S)

    async def handler(request: web.BaseRequest) -> web.StreamResponse:
        return await door.handling(request, lambda r: _answer(page, r))

    server = web.Server(
        handler,
        keepalive_timeout=IDLE_TIMEOUT_S,
        max_line_size=MAX_LINE_BYTES,
        max_field_size=MAX_LINE_BYTES,
        access_log=None,
        logger=QuietLog("metrics page"),
    )
    return await asyncio.get_running_loop().create_server(
        door.protocol_factory(server), sock=sock, backlog=HTTP_BACKLOG
    )
