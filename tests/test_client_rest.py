"""`FleetmapClient` (the typed REST client) against the real service, started as a process
(`python -m fleetmap.server` on free ports, tests/service_process.py), over real HTTP; and the
robot-side clients (`ScanPublisher`, `fleetmap replay`) feeding that service over real Zenoh.

Where the service answers with map content, it is compared with the engine's own `GridMap` of the
same scans (decoded from the same payloads, so float32 wire rounding is the same on both sides).
"""

from __future__ import annotations

import contextlib
import copy
import io
import itertools
import json
import math
import multiprocessing
import os
import pickle
import re
import sqlite3
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fleetmap_client import cli, rest
from fleetmap_client.publisher import ScanPublisher
from fleetmap_client.rest import FleetmapClient, FleetmapError, MapChanged, parse_sse
from PIL import Image
from pydantic import ValidationError
from service_process import REPO_DIR, FreezableProxy, ServiceProcess, free_port, wait_for

from fleetmap.api_models import MapInfo, MapStats, ReplacedEvent
from fleetmap.codec import decode, encode_binary, encode_json
from fleetmap.config import MapConfig, OccupancyParams, TsdfParams
from fleetmap.database import DB_NAME
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import STATE_NAMES, GridMap
from fleetmap.scan import Scan
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING, PoseMessage, ScanMessage

CONFIG = MapConfig(resolution=0.1, tile_size=64)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One real service for the module (each test uses its own map ids)."""
    with ServiceProcess(tmp_path_factory.mktemp("service")) as svc:
        yield svc


@pytest.fixture
def client(service: ServiceProcess) -> Iterator[FleetmapClient]:
    with FleetmapClient(service.base_url, timeout=20.0) as c:
        yield c


@pytest.fixture(scope="module")
def scans() -> list[Scan]:
    plan = generate_floorplan(7, width_m=20.0, height_m=15.0)
    robot = SimulatedRobot(plan, seed=11, num_beams=271, range_max=10.0)
    return [robot.tick() for _ in range(8)]


def _engine_map(wire_scans: list[Scan]) -> GridMap:
    gmap = GridMap(CONFIG)
    for scan in wire_scans:
        gmap.integrate(scan)
    return gmap


def _assert_cells_equal(got: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    """The client's cells() arrays against GridMap.cells() of the same points."""
    np.testing.assert_array_equal(got["known"], expected["known"])
    for name in ("log_odds", "probability", "tsdf", "tsdf_weight"):
        np.testing.assert_allclose(got[name], expected[name].astype(np.float64), rtol=1e-6, equal_nan=True)
    for name in ("hits", "misses"):
        np.testing.assert_array_equal(got[name], expected[name].astype(np.int64))
    np.testing.assert_array_equal(got["state"], [STATE_NAMES[int(c)] for c in expected["state"]])


# -- maps ------------------------------------------------------------------------------------------


def test_health_and_map_lifecycle(client: FleetmapClient) -> None:
    health = client.health()
    assert health.status == "ok" and health.zenoh is not None and health.zenoh["mode"] == "router"

    created = client.create_map("life", {"resolution": 0.1})
    assert created.id == "life" and created.resolution == 0.1 and created.stats.scans_integrated == 0
    assert "life" in [m.id for m in client.list_maps()]
    assert client.create_map("life", {"resolution": 0.1}).id == "life"  # same config: a no-op
    with pytest.raises(FleetmapError) as conflict:
        client.create_map("life", {"resolution": 0.2})
    assert conflict.value.status == 409 and "different configuration" in conflict.value.detail

    typed = client.create_map("life-typed", CONFIG)
    assert typed.config == CONFIG and typed.tile_size == 64
    assert client.get_map("life-typed").config == CONFIG

    with pytest.raises(FleetmapError) as invalid:
        client.create_map("bad-config", {"resolution": -1})
    assert invalid.value.status == 422 and "resolution" in invalid.value.detail
    assert invalid.value.errors and invalid.value.errors[0]["loc"][-1] == "resolution"
    assert "bad-config" not in [m.id for m in client.list_maps()]  # bad input changed nothing

    client.delete_map("life")
    with pytest.raises(FleetmapError) as gone:
        client.get_map("life")
    assert gone.value.status == 404 and "life" in gone.value.detail
    with pytest.raises(FleetmapError) as again:
        client.delete_map("life")
    assert again.value.status == 404
    assert "fleetmap_queue_depth" in client.metrics()


def test_ids_are_checked_before_any_request(client: FleetmapClient) -> None:
    with pytest.raises(ValueError, match="map_id 'a/b' is invalid"):
        client.get_map("a/b")
    with pytest.raises(ValueError, match="robot_id 'r 1' is invalid"):
        client.post_scan("m", "r 1", {})
    with pytest.raises(ValueError, match="all of xmin"):
        client.region("m", 0, 0, 1)
    with pytest.raises(ValueError, match="finite"):
        client.cell("m", float("nan"), 0)


def test_a_coordinate_or_range_that_is_no_number_is_a_value_error_before_any_request() -> None:
    """`cell`'s point, a window's bounds and `raycast`'s `max_range` are numbers ("a bound that is
    not a finite number is a ValueError before any request", docs/clients.md): float() read text
    ("1.5"), True (1.0) and a NumPy date (its seconds since 1970), which went to the service as
    those numbers, where `cells`, `raycast`'s origin and the engine refuse them; None or a
    one-element array raised float()'s TypeError instead. The client points at a port where
    nothing listens: any request would be a ConnectError."""
    with FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=5) as nowhere:
        calls: list[Callable[[Any], object]] = [
            lambda wrong: nowhere.cell("m", wrong, 0.0),
            lambda wrong: nowhere.cell("m", 0.0, wrong),
            lambda wrong: nowhere.region("m", 0.0, 0.0, wrong, 1.0),
            lambda wrong: nowhere.region_png("m", wrong, 0.0, 1.0, 1.0),
            lambda wrong: nowhere.surface("m", 0.0, wrong, 1.0, 1.0),
            lambda wrong: nowhere.clear_region("m", 0.0, 0.0, 1.0, wrong),
            lambda wrong: nowhere.raycast("m", (0.0, 0.0), [0.0], wrong),
        ]
        for wrong in ("1.5", b"1", True, np.bool_(False), np.datetime64(5, "s"), np.array([1.0]), 1j):
            for call in calls:
                with pytest.raises(ValueError, match="must be finite numbers"):
                    call(wrong)
        for call in (calls[0], calls[-1]):  # None: no bound at all for a window (all four or none)
            with pytest.raises(ValueError, match="must be finite numbers"):
                call(None)
        with pytest.raises(httpx.ConnectError):  # numbers (NumPy's too) are asked for
            nowhere.cell("m", np.float32(1.5), 2)


def test_bad_arguments_are_refused_before_any_request(client: FleetmapClient, scans: list[Scan]) -> None:
    """Each of these went to the server before: (x, y, z) rows were sent as 3n/2 points, an unknown
    encoding posted the scan as JSON, and a bad id of `events` waited for the first `next()`."""
    client.create_map("args", CONFIG)
    with pytest.raises(ValueError, match=r"shape \(n, 2\); got shape \(2, 3\)"):
        client.cells("args", [[0.5, 0.5, 0.0], [1.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="encoding must be 'json' or 'binary', got 'msgpack'"):
        client.post_scan("args", "r1", scans[0], encoding="msgpack")  # type: ignore[arg-type]
    for wrong in ("scan.json", b"FMS1", 5):  # said "dictionary update sequence element #0 ..."
        with pytest.raises(TypeError, match=f"post_scan takes .* not {type(wrong).__name__}"):
            client.post_scan("args", "r1", wrong)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="map_id 'a/b' is invalid"):
        client.events("a/b")
    stats = client.get_map("args").stats
    assert stats.scans_integrated == 0 and stats.robots == {}
    assert client.cells("args", [0.5, 0.5])["known"].tolist() == [False]  # one pair: one point


def test_an_etag_no_header_carries_is_a_value_error_before_any_request() -> None:
    """A conditional write's `if_match` and `tile`'s `etag` go in a header: one with a line break
    (`'"x"\r\nX-Other: 1'`) went out as far as httpx, whose `LocalProtocolError`, a
    `TransportError`, read as a network failure "of the fleetmap service at ..."; one with a
    non-ASCII character raised a bare UnicodeEncodeError. Each is a ValueError naming the argument,
    before any request, as every other argument is checked; a tag read from a file with its line end
    is sent without it, as the token is. The client points at a port where nothing listens: any
    request would be a ConnectError."""
    with FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=5) as nowhere:
        conditional: list[tuple[str, Callable[[str], object]]] = [
            ("if_match", lambda tag: nowhere.delete_map("m", if_match=tag)),
            ("if_match", lambda tag: nowhere.create_map("m", if_match=tag)),
            ("if_match", lambda tag: nowhere.upload_snapshot("m", b"PK", if_match=tag)),
            ("if_match", lambda tag: nowhere.import_nav2("m", b"PK", if_match=tag)),
            ("if_match", lambda tag: nowhere.clear_region("m", 0, 0, 1, 1, if_match=tag)),
            ("etag", lambda tag: nowhere.tile("m", 0, 0, 0, etag=tag)),
        ]
        for name, call in conditional:
            for wrong in ('"x"\r\nX-Other: 1', '"x\ny"', '"\u00e9t\u00e9"', '"x"\x00'):
                with pytest.raises(ValueError, match=f"^{name} must be an ETag as the service sent it"):
                    call(wrong)
            with pytest.raises(httpx.ConnectError):  # sent, without its line end
                call('"map-1"\n')


def test_raycast_arguments_that_are_no_numbers_are_a_value_error_before_any_request() -> None:
    """`raycast` is documented to raise ValueError for a malformed argument before any request, as
    the engine's `cast_rays` does, but angles given as a generator (`(radians(d) for d in ...)`) or
    a dict, or an origin given as a dict, raised NumPy's bare TypeError "float() argument must be a
    string or a real number, not 'generator'", naming neither argument, and ragged angles NumPy's
    "setting an array element with a sequence". (Nothing listens at the address: a request would
    be a ConnectError.)"""
    nowhere = FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=2)
    cases: list[tuple[Any, Any, str]] = [
        ((0.0, 0.0), (math.radians(d) for d in range(0, 360, 10)), "angles"),
        ((0.0, 0.0), {"a": 0.1}, "angles"),
        ((0.0, 0.0), [[0.1], [0.2, 0.3]], "angles"),
        ({"x": 0.0, "y": 0.0}, [0.1], "origin"),
        ([[0.0, 0.0], [1.0]], [0.1, 0.2], "origin"),
    ]
    for origin, angles, what in cases:
        with pytest.raises(ValueError, match=f"^{what} must be"):
            nowhere.raycast("m", origin, angles, 1.0)
    nowhere.close()


def test_a_configuration_of_another_type_is_a_type_error_before_any_request() -> None:
    """`create_map` takes a `MapConfig`, a dict of its fields or None, as the engine's `GridMap`
    does; a configuration read from a file and passed as its JSON text raised dict()'s "dictionary
    update sequence element #0 has length 1; 2 is required", another type "'int' object is not
    iterable". Each is now a TypeError naming what the configuration must be. (Nothing listens at
    the address: a request would be a ConnectError.)"""
    nowhere = FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=2)
    for wrong in ('{"resolution": 0.1}', b"{}", 5, [("resolution", 0.1)]):
        with pytest.raises(TypeError, match="^config must be a MapConfig, a dict of its fields or None, not"):
            nowhere.create_map("m", wrong)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"json.loads"):
        nowhere.create_map("m", '{"resolution": 0.1}')  # type: ignore[arg-type]
    nowhere.close()


def test_a_snapshot_of_another_type_is_a_type_error_before_any_request() -> None:
    """`upload_snapshot` takes a snapshot's bytes, a file's path or a binary file; anything else
    (None from a variable never set, a list of chunks) went to the service as a request whose body
    then failed ("'NoneType' object has no attribute 'read'", an AttributeError, the upload cut off
    at the service). It is now a TypeError before any request. (Nothing listens at the address: a
    request would be a ConnectError.)"""
    nowhere = FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=2)
    for wrong in (None, 5, [b"PK"], {"snapshot": b"PK"}):
        with pytest.raises(TypeError, match="^snapshot must be"):
            nowhere.upload_snapshot("m", wrong)  # type: ignore[arg-type]
    nowhere.close()


class _FakeService(BaseHTTPRequestHandler):
    """A handler of the fake servers below (`_serving`): `reply` answers, `read_body` reads a
    request's body, and nothing is logged."""

    def read_body(self) -> bytes:
        return self.rfile.read(int(self.headers.get("content-length") or 0))

    def reply(
        self, status: int, body: bytes, content_type: str, headers: dict[str, str] | None = None
    ) -> None:
        """Answer `status` with `body` of `content_type`, and `headers` besides."""
        self.send_response(status)
        self.send_header("content-type", content_type)
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        pass


@contextlib.contextmanager
def _serving(handler: type[BaseHTTPRequestHandler]) -> Iterator[str]:
    """A real HTTP server on a free port answering with `handler`, on a thread; yields its URL."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@contextlib.contextmanager
def _late_service(status: int, detail: str, delay: float = 1.5) -> Iterator[str]:
    """A real HTTP server on a free port that answers every GET, POST and PUT `delay` seconds late
    with `status` and `{"detail": detail}`, as the service answers its slow requests; yields its URL."""

    class LateService(_FakeService):
        def _answer_late(self) -> None:
            self.read_body()
            time.sleep(delay)
            self.reply(status, json.dumps({"detail": detail}).encode(), "application/json")

        do_GET = do_POST = do_PUT = _answer_late

    with _serving(LateService) as url:
        yield url


@contextlib.contextmanager
def _redirect_to(target: str, status: int = 301) -> Iterator[str]:
    """A real HTTP server on a free port that answers every request with a redirect (`status`) to
    the same path at `target`, as a proxy sending http:// to https:// does; yields its URL."""

    class Redirect(_FakeService):
        def _redirect(self) -> None:
            self.read_body()
            self.reply(
                status, b"<html><body>Moved</body></html>", "text/html", {"location": target + self.path}
            )

        do_GET = do_POST = do_PUT = do_DELETE = _redirect

    with _serving(Redirect) as url:
        yield url


def test_a_redirect_is_no_answer(client: FleetmapClient, service: ServiceProcess, tmp_path: Path) -> None:
    """A redirect (a proxy in front of the service sending http:// to https://, a service moved) is
    an error naming where it points, and nothing was done: every status below 400 was taken for the
    answer, so `delete_map` returned as if the map were deleted, `save_snapshot` wrote the
    redirect's HTML page as the backup and returned its size, an event stream "reconnected" for
    ever, and the readers raised pydantic's ValidationError about invalid JSON."""
    client.create_map("moved", CONFIG)
    backup = tmp_path / "moved.zip"
    with _redirect_to(service.base_url) as old, FleetmapClient(old, timeout=20.0) as fm:
        calls: list[Callable[[], object]] = [
            lambda: fm.delete_map("moved"),
            lambda: fm.save_snapshot("moved", backup),
            lambda: fm.download_snapshot("moved"),
            lambda: fm.get_map("moved"),
            lambda: fm.metrics(),
            lambda: next(fm.events("moved")),
        ]
        for call in calls:
            with pytest.raises(FleetmapError) as moved:
                call()
            assert moved.value.status == 301
            assert f"redirect to {service.base_url}/" in moved.value.detail
    assert list(tmp_path.iterdir()) == []  # no backup, nor a part of one
    assert client.get_map("moved").id == "moved"  # not deleted


def test_post_scan_checks_seq_and_stamp_as_the_publisher_does(
    client: FleetmapClient, scans: list[Scan]
) -> None:
    """A NumPy integer seq (from `np.arange`) is a seq: it failed in the JSON encoder ("Object of
    type int64 is not JSON serializable"), and, sent in binary, became the robot's automatic
    counter, which then failed every later JSON scan of it. A seq or stamp no scan can carry is
    refused before any request, as `ScanPublisher.publish` refuses it: sent, its 422 counted against
    the robot as a rejected scan."""
    client.create_map("seqs", CONFIG)
    assert client.post_scan("seqs", "r1", scans[0], seq=np.int64(0)).status == "integrated"
    assert client.post_scan("seqs", "r1", scans[1], seq=np.uint8(1), encoding="binary").seq == 1
    assert client.post_scan("seqs", "r1", scans[2], stamp=np.float32(2.5)).seq == 2  # automatic
    assert client.post_scan("seqs", "r1", scans[3]).status == "integrated"
    refused: list[tuple[type[Exception], str, dict[str, Any]]] = [
        (TypeError, "seq must be an integer", {"seq": 4.0}),
        (TypeError, "seq must be an integer", {"seq": True}),
        (ValueError, r"seq must be in \[0, 2\*\*63\)", {"seq": -1}),
        (ValueError, r"seq must be in \[0, 2\*\*63\)", {"seq": 2**63}),
        (TypeError, "stamp must be a number", {"stamp": "now"}),
        (ValueError, "stamp must be finite", {"stamp": math.inf}),
    ]
    for error, message, arguments in refused:
        with pytest.raises(error, match=message):
            client.post_scan("seqs", "r1", scans[4], **arguments)
    robot = client.get_map("seqs").stats.robots["r1"]
    assert (robot.scans_integrated, robot.scans_rejected, robot.last_seq) == (4, 0, 3)


def test_timeouts_are_checked_when_the_client_is_made(service: ServiceProcess) -> None:
    """A timeout of 0 failed every request as a ConnectError ("Operation now in progress", naming
    the service as if it were down), a negative one or NaN at each request, and None (httpx's "no
    limit") as a TypeError of `max` ("'>' not supported between ..."). One longer than the platform
    waits (1e10 s, meant as "for ever") was taken, and every request raised OverflowError
    ("timestamp out of range for platform time_t"). Each is now refused at once, naming the
    argument; `events_read_timeout` alone takes None (wait for ever), and the longest wait the
    platform takes is taken."""
    for name in ("timeout", "scan_timeout", "transfer_timeout", "events_read_timeout"):
        for wrong in (
            0,
            -1.0,
            math.nan,
            math.inf,
            threading.TIMEOUT_MAX * 1.01,
            1e300,
            "10",
            True,
            *([None] if name != "events_read_timeout" else []),
        ):
            with pytest.raises(ValueError, match=f"^{name} must be a positive number of seconds"):
                FleetmapClient(service.base_url, **{name: wrong})
    with FleetmapClient(service.base_url, timeout=5, events_read_timeout=None) as fm:
        assert fm.health().status == "ok"
    longest = threading.TIMEOUT_MAX
    with FleetmapClient(service.base_url, longest, None, longest, longest, longest) as fm:
        assert fm.health().status == "ok" and fm.list_maps() is not None
    # The address as read from a file or the environment, with its line end, and the viewer's link.
    for address in (f" {service.base_url}\n", f"{service.base_url}/#map=m"):
        with FleetmapClient(address) as fm:
            assert fm.base_url == service.base_url
            assert fm.health().status == "ok"


@pytest.mark.parametrize(
    "address",
    ["localhost:8000", "127.0.0.1:8000", "ftp://127.0.0.1:8000", "http://", "http:/127.0.0.1:8000",
     "http://[::1:8000", "http://127.0.0.1:8000/?map=m", "http://127.0.0.1:8000/?", "",
     "http://127.0.0.1:80000", "http://127.0.0.1:65536", "http://127.0.0.1:0", "http://127.0.0.1:-1"],
)  # fmt: skip
def test_an_address_that_is_no_http_url_is_a_value_error_when_the_client_is_made(address: str) -> None:
    """A `base_url` without its scheme (`localhost:8000`: httpx took `localhost` for the scheme) or
    without a host (`http:/127.0.0.1:8000`) was taken, and every request failed with a
    `TransportError` ("unsupported protocol 'localhost://'", "Name or service not known"): the
    class a program takes for the service being down, and retries for ever. One httpx cannot parse
    raised its `InvalidURL`, no ValueError; one with a query sent every request to
    `/?map=m/healthz`. A port no TCP connection has (`:80000`, a typo of `:8000`; 0; -1), which
    httpx takes too, failed every request as "Connection refused". Each is now a ValueError at
    once, naming the address."""
    with pytest.raises(ValueError, match=r"base_url must be the service's http:// or https:// address"):
        FleetmapClient(address)


def test_an_answer_that_is_not_fleetmaps_is_a_fleetmap_error(scans: list[Scan]) -> None:
    """Another web server answering 200 at the address (a captive portal's page, a wrong port), or
    a service of another version: each reader raises `FleetmapError` naming the address, what came
    and what was expected. They raised pydantic's ValidationError ("Invalid JSON ..."), `region`
    NumPy's ValueError "This file contains pickled (object) data", `get_map_and_etag` a KeyError:
    none of the errors the client promises, nor a word of the address. A real HTTP server answers
    200 with JSON here."""
    with _late_service(200, "welcome", delay=0.0) as base, FleetmapClient(base) as other:
        readers: list[tuple[str, Callable[[], object]]] = [
            ("a Health", other.health),
            ("a MapList", other.list_maps),
            ("a MapInfo", lambda: other.create_map("m")),
            ("a map with its ETag", lambda: other.get_map_and_etag("m")),
            ("a ScanResult", lambda: other.post_scan("m", "r1", scans[0])),
            ("a CellValue", lambda: other.cell("m", 0.0, 0.0)),
            ("a CellsResponse", lambda: other.cells("m", [[0.0, 0.0]])),
            ("a RaycastResponse", lambda: other.raycast("m", (0.0, 0.0), [0.0], 1.0)),
            ("a window of a map", lambda: other.region("m")),
            ("a Surface", lambda: other.surface("m")),
        ]
        for expected, read in readers:
            with pytest.raises(FleetmapError) as exc:
                read()
            assert exc.value.status == 200
            assert exc.value.detail.startswith(f"{base}/")
            assert (
                f"answered application/json, not {expected} as a fleetmap service answers" in exc.value.detail
            )


@contextlib.contextmanager
def _web_page_server() -> Iterator[str]:
    """A real HTTP server on a free port answering every request 200 with an HTML page, as a captive
    portal or another web server on a wrong port does; yields its URL."""

    class WebPage(_FakeService):
        def _page(self) -> None:
            self.read_body()
            body = b"<html><body>Welcome to the guest Wi-Fi: sign in to go on.</body></html>"
            self.reply(200, body, "text/html; charset=utf-8")

        do_GET = do_POST = do_PUT = do_DELETE = _page

    with _serving(WebPage) as url:
        yield url


def test_an_answer_read_as_bytes_that_is_not_fleetmaps_is_a_fleetmap_error(tmp_path: Path) -> None:
    """The answers the client returns as bytes or text, and `delete_map`'s empty one, from another
    web server at the address (a captive portal's 200 page): `save_snapshot` wrote the page as the
    backup and returned its size, `download_snapshot`, `export`, `region_png`, `tile` and `metrics`
    returned it as the zip, PNG or metrics, and `delete_map` returned as if the map were deleted.
    Each raises `FleetmapError` naming the address, what came and what was expected, and leaves no
    file behind."""
    backup = tmp_path / "backup.zip"
    with _web_page_server() as base, FleetmapClient(base) as other:
        calls: list[tuple[str, Callable[[], object]]] = [
            ("a snapshot of a map", lambda: other.save_snapshot("m", backup)),
            ("a snapshot of a map", lambda: other.download_snapshot("m")),
            ("a nav2 map zip", lambda: other.export("m")),
            ("a PNG image", lambda: other.export("m", "png")),
            ("a PNG image", lambda: other.region_png("m")),
            ("a PNG image", lambda: other.tile("m", 0, 0, 0)),
            ("Prometheus metrics", other.metrics),
            ("an empty answer (204 No Content)", lambda: other.delete_map("m")),
        ]
        for expected, call in calls:
            with pytest.raises(FleetmapError) as exc:
                call()
            assert exc.value.status == 200
            assert exc.value.detail.startswith(f"{base}/")
            assert f"answered text/html, not {expected} as a fleetmap service answers" in exc.value.detail
    assert list(tmp_path.iterdir()) == []  # no backup, nor a part of one


def test_an_answer_its_content_encoding_does_not_decode_is_a_fleetmap_error(
    tmp_path: Path, scans: list[Scan]
) -> None:
    """A proxy that breaks what it passes on (labels a plain body `Content-Encoding: gzip`, cuts a
    compressed one): httpx's own `DecodingError` came out of the client, neither of the errors it
    promises (a `FleetmapError` for an answer no fleetmap service gives, an `httpx.TransportError`
    for the network). Each answer, a JSON one, a snapshot saved to a file, an event stream and an
    error answer, is now a `FleetmapError` of its status naming the address and the encoding, and
    leaves no file behind. A scan answered so (200) is in the map: the next automatic seq moves on,
    as after any answer, not kept as after a refusal."""
    kinds = {"snapshot": "application/zip", "events": "text/event-stream"}
    seqs: list[int] = []

    class Garbling(_FakeService):
        def do_GET(self) -> None:
            last = self.path.partition("?")[0].rsplit("/", 1)[1]
            status = 503 if last == "busy" else 200
            kind = kinds.get(last, "application/json")
            self.reply(status, b"not gzip at all", kind, {"content-encoding": "gzip"})

        def do_POST(self) -> None:
            seqs.append(json.loads(self.read_body())["seq"])
            self.reply(200, b"not gzip at all", "application/json", {"content-encoding": "gzip"})

    backup = tmp_path / "backup.zip"
    with _serving(Garbling) as base, FleetmapClient(base) as fm:
        calls: list[tuple[int, Callable[[], object]]] = [
            (200, lambda: fm.get_map("m")),
            (503, lambda: fm.get_map("busy")),
            (200, lambda: fm.save_snapshot("m", backup)),
            (200, lambda: next(fm.events("m"))),
            (200, lambda: fm.post_scan("m", "r1", scans[0])),
            (200, lambda: fm.post_scan("m", "r1", scans[1])),
        ]
        for status, call in calls:
            with pytest.raises(FleetmapError) as exc:
                call()
            assert exc.value.status == status
            assert exc.value.detail.startswith(f"{base}/maps/")
            assert "does not decode as its Content-Encoding ('gzip') says" in exc.value.detail
    assert list(tmp_path.iterdir()) == []  # no backup, nor a part of one
    assert seqs == [0, 1]


def test_post_scan_waits_for_the_servers_own_answer(scans: list[Scan]) -> None:
    """The service answers a scan once it is integrated, or 503 after its own wait (10 s by
    default): a client whose timeout is not longer than that got httpx's bare ReadTimeout instead
    of the 503 saying the scan will still be integrated. A real HTTP server answers here as the
    service does, 1.5 s late; the client's timeout is 1 s, which still bounds other requests."""
    detail = "the scan was not integrated within 1.5 s; it will be"
    with _late_service(503, detail) as base, FleetmapClient(base, timeout=1.0) as slow:
        with pytest.raises(FleetmapError) as exc:
            slow.post_scan("late", "r1", scans[0])
        assert exc.value.status == 503 and exc.value.detail == detail
        with pytest.raises(httpx.ReadTimeout):
            slow.health()


def test_whole_map_transfers_wait_longer_than_other_requests() -> None:
    """A big map takes the service seconds to store (an upload) or to pack (a download, an export):
    with the general 10 s timeout a client got httpx's bare ReadTimeout, not knowing whether its
    upload took effect. A real HTTP server answers each transfer 1.5 s late here; the client's
    timeout is 1 s, its `transfer_timeout` the default, then 1 s too."""
    transfers: list[Callable[[FleetmapClient], object]] = [
        lambda c: c.upload_snapshot("big", b"PK"),
        lambda c: c.download_snapshot("big"),
        lambda c: c.import_nav2("big", b"PK"),
        lambda c: c.export("big"),
    ]
    with _late_service(422, "not a snapshot") as base:
        with FleetmapClient(base, timeout=1.0) as patient:
            for transfer in transfers:
                with pytest.raises(FleetmapError) as exc:
                    transfer(patient)
                assert exc.value.status == 422 and exc.value.detail == "not a snapshot"
        hasty = FleetmapClient(base, timeout=1.0, transfer_timeout=1.0)
        with hasty, pytest.raises(httpx.ReadTimeout):
            hasty.upload_snapshot("big", b"PK")


def test_errors_say_how_long_the_service_asks_to_wait(tmp_path: Path) -> None:
    """A 503's `Retry-After` (here the service's limit of open event streams, reached) is the
    error's `retry_after`; an answer without one has None. The client dropped the header, so a
    program could not back off as the service asked."""
    with (
        ServiceProcess(tmp_path, extra_args=["--max-event-streams", "1"]) as svc,
        FleetmapClient(svc.base_url, timeout=20.0) as fm,
    ):
        fm.create_map("waits", CONFIG)
        first = fm.events("waits")
        assert next(first)[0] == "robots"
        with pytest.raises(FleetmapError) as full:
            next(fm.events("waits"))
        assert full.value.status == 503 and full.value.retry_after is not None
        assert full.value.retry_after > 0
        first.close()
        with pytest.raises(FleetmapError) as missing:
            fm.get_map("no-such-map")
        assert missing.value.status == 404 and missing.value.retry_after is None


def test_automatic_seq_moves_past_a_scan_the_service_may_still_integrate(scans: list[Scan]) -> None:
    """After a 503 "not integrated within 10 s; it will be integrated" (or an answer lost to a read
    timeout) the scan is, or will be, in the map; the client kept its seq, so the next automatic
    scan went out under it and the service ignored it as a duplicate. A refused scan (422) leaves
    its seq free. A real HTTP server answers as the service does, in turn, and records the seqs."""
    answers: list[tuple[int, dict[str, Any], float]] = [
        (503, {"detail": "the scan was queued but not integrated within 10 s; it will be integrated"}, 0),
        (422, {"detail": "scan: pose.x must be a finite number"}, 0),
        (200, {"seq": 1, "status": "integrated"}, 0),
        (200, {"seq": 2, "status": "integrated"}, 1.5),  # later than the client waits: ReadTimeout
        (200, {"seq": 3, "status": "integrated"}, 0),
    ]
    seqs: list[int] = []

    class Service(_FakeService):
        def do_POST(self) -> None:
            seqs.append(json.loads(self.read_body())["seq"])
            status, answer, delay = answers[len(seqs) - 1]
            time.sleep(delay)
            self.reply(status, json.dumps(answer).encode(), "application/json")

    with _serving(Service) as url:
        with FleetmapClient(url, timeout=1.0, scan_timeout=1.0) as fm:
            with pytest.raises(FleetmapError, match="it will be integrated"):
                fm.post_scan("m", "r1", scans[0])
            with pytest.raises(FleetmapError, match="pose.x"):
                fm.post_scan("m", "r1", scans[1])
            assert fm.post_scan("m", "r1", scans[1]).seq == 1
            with pytest.raises(httpx.ReadTimeout):
                fm.post_scan("m", "r1", scans[2])
            assert fm.post_scan("m", "r1", scans[3]).status == "integrated"
        with FleetmapClient(f"http://127.0.0.1:{free_port()}", timeout=2.0) as nowhere:
            with pytest.raises(httpx.ConnectError):
                nowhere.post_scan("m", "r1", scans[0])
            assert nowhere._next_seq.get(("m", "r1"), 0) == 0  # nothing left: seq 0 is still free
    assert seqs == [0, 1, 1, 2, 3]


# -- scans and queries -----------------------------------------------------------------------------


def test_posted_scans_and_every_query_match_the_engine(client: FleetmapClient, scans: list[Scan]) -> None:
    client.create_map("q", CONFIG)
    # Four scans in the four forms post_scan takes; the engine gets what the server decodes.
    r0 = client.post_scan("q", "r1", scans[0], stamp=1.0)  # Scan as JSON, automatic seq 0
    r1 = client.post_scan("q", "r1", scans[1], encoding="binary")  # automatic seq 1
    r2 = client.post_scan("q", "r1", ScanMessage.from_scan(scans[2], seq=2, stamp=3.0))
    message = ScanMessage.from_scan(scans[3], seq=0).model_dump(mode="json", exclude_none=True)
    r3 = client.post_scan("q", "r1", message, seq=3)
    assert [r.seq for r in (r0, r1, r2, r3)] == [0, 1, 2, 3]
    assert all(r.status == "integrated" and r.cell_updates > 0 and r.changed_tiles for r in (r0, r1, r2, r3))
    duplicate = client.post_scan("q", "r1", scans[4], seq=1)
    assert duplicate.status == "duplicate"
    wire = [
        decode(encode_json(scans[0], 0, 1.0), JSON_ENCODING).scan,
        decode(encode_binary(scans[1], 1, 0.0), BINARY_ENCODING).scan,
        ScanMessage.from_scan(scans[2], seq=2).to_scan(),
        ScanMessage.from_scan(scans[3], seq=3).to_scan(),
    ]
    gmap = _engine_map(wire)

    info = client.get_map("q")
    robot = info.stats.robots["r1"]
    assert (robot.scans_integrated, robot.duplicates, robot.last_seq) == (4, 1, 3)
    bounds = gmap.known_bounds()
    assert bounds is not None
    res = CONFIG.resolution
    assert info.stats.bounds == pytest.approx(tuple(b * res for b in bounds))

    # cells / cell: random points over the observed extent and beyond it.
    rng = np.random.default_rng(0)
    i0, j0, i1, j1 = bounds
    points = rng.uniform([(i0 - 5) * res, (j0 - 5) * res], [(i1 + 5) * res, (j1 + 5) * res], size=(500, 2))
    got = client.cells("q", points)
    expected = gmap.cells(points)
    assert got["known"].any() and not got["known"].all()
    _assert_cells_equal(got, expected)
    np.testing.assert_array_equal(got["i"], np.floor(points[:, 0] / res).astype(np.int64))
    one = client.cell("q", *points[0])
    assert (one.i, one.j, one.known) == (got["i"][0], got["j"][0], got["known"][0])
    assert one.probability == pytest.approx(got["probability"][0])

    # region: explicit bounds, every layer; then no bounds = the observed extent.
    x0, y0, x1, y1 = i0 * res + 0.05, j0 * res + 0.05, (i0 + 40) * res + 0.05, (j0 + 30) * res + 0.05
    for layer in ("probability", "log_odds", "state", "hits", "misses", "tsdf", "tsdf_weight"):
        array = client.region("q", x0, y0, x1, y1, layer=layer)  # type: ignore[arg-type]
        np.testing.assert_array_equal(array, gmap.region(layer, i0, j0, i0 + 40, j0 + 30), err_msg=layer)
    whole, window, origin = client.region_window("q")
    assert window == bounds and origin == pytest.approx((i0 * res, j0 * res))
    np.testing.assert_array_equal(whole, gmap.region("probability", *bounds))
    png = Image.open(io.BytesIO(client.region_png("q", layer="state")))
    assert png.size == (i1 - i0, j1 - j0)

    # surface: the engine's zero crossings of the same window.
    surface = client.surface("q", x0, y0, x1, y1)
    np.testing.assert_allclose(surface, gmap.surface(i0, j0, i0 + 40, j0 + 30), rtol=0, atol=1e-9)
    assert surface.shape[0] > 0

    # export: the nav2 zip and the PNG.
    with zipfile.ZipFile(io.BytesIO(client.export("q"))) as zf:
        assert sorted(zf.namelist()) == ["map.pgm", "map.yaml"]
        assert b"resolution: 0.1" in zf.read("map.yaml")
    assert Image.open(io.BytesIO(client.export("q", "png", margin=0))).size == (i1 - i0, j1 - j0)

    # snapshot: downloaded, then restored under another id, every layer equal; a bad file changes nothing.
    snapshot = client.download_snapshot("q")
    restored = client.upload_snapshot("q-copy", snapshot)
    assert restored.id == "q-copy" and restored.config == CONFIG and restored.stats.tiles == info.stats.tiles
    for layer in ("log_odds", "hits", "tsdf"):
        copy = client.region("q-copy", x0, y0, x1, y1, layer=layer)  # type: ignore[arg-type]
        np.testing.assert_array_equal(copy, client.region("q", x0, y0, x1, y1, layer=layer))  # type: ignore[arg-type]
    with pytest.raises(FleetmapError) as bad:
        client.upload_snapshot("q-copy", snapshot[: len(snapshot) // 2])
    assert bad.value.status == 422 and client.get_map("q-copy").stats.tiles == info.stats.tiles


def test_a_window_bound_on_a_cell_edge_is_that_edge_as_clients_md_says(
    client: FleetmapClient, scans: list[Scan]
) -> None:
    """docs/clients.md gave `region`'s window as `[floor(xmin/res), ...)` alone, which puts 0.3 at
    0.1 m in cell 2 (0.3 / 0.1 is 2.9999999999999996); the service (and the methods' docstrings)
    take a bound on a cell edge for that edge: cell 3. The page now says so."""
    client.create_map("edge", CONFIG)
    client.post_scan("edge", "rob", scans[0], seq=0)
    assert math.floor(0.3 / CONFIG.resolution) == 2
    _, window, origin = client.region_window("edge", 0.3, 0.3, 0.6, 0.6)
    assert (window, origin) == ((3, 3, 6, 6), (0.3, 0.3))
    assert client.clear_region("edge", 0.3, 0.3, 0.6, 0.6).window == [3, 3, 6, 6]
    page = (REPO_DIR / "docs" / "clients.md").read_text(encoding="utf-8")
    bullet = re.search(r"^- `region` / `surface` take.*?(?=^- )", page, re.M | re.S)
    assert bullet is not None and "edge" in bullet.group(0), bullet


def test_snapshots_saved_to_a_file_and_uploaded_from_one(
    client: FleetmapClient, scans: list[Scan], tmp_path: Path
) -> None:
    """`save_snapshot` writes the download to a file as it arrives (a big map's takes gigabytes) and
    `upload_snapshot` sends a file from its path or an open file: the same map comes back. A failed
    download leaves no file, and an earlier one where it was."""
    client.create_map("files", CONFIG)
    for k, scan in enumerate(scans[:4]):
        client.post_scan("files", "r1", scan, seq=k)
    path = tmp_path / "files.fleetmap.zip"
    size = client.save_snapshot("files", path)
    assert size == path.stat().st_size > 0 and [p.name for p in tmp_path.iterdir()] == [path.name]
    x0, y0, x1, y1 = -5.0, -5.0, 15.0, 12.0
    for target, source in (("files-a", path), ("files-b", open(path, "rb"))):  # noqa: SIM115
        with contextlib.ExitStack() as stack:
            if not isinstance(source, Path):
                stack.enter_context(source)
            restored = client.upload_snapshot(target, source)
        assert restored.stats.tiles == client.get_map("files").stats.tiles
        for layer in ("log_odds", "hits", "tsdf"):
            np.testing.assert_array_equal(
                client.region(target, x0, y0, x1, y1, layer=layer),  # type: ignore[arg-type]
                client.region("files", x0, y0, x1, y1, layer=layer),  # type: ignore[arg-type]
            )
    kept = path.read_bytes()
    with pytest.raises(FleetmapError) as missing:
        client.save_snapshot("no-such-map", path)
    assert missing.value.status == 404
    assert path.read_bytes() == kept and sorted(p.name for p in tmp_path.iterdir()) == [path.name]
    # A path the download cannot take (a folder): the error, and no `.part` left behind (it was:
    # the whole download, gigabytes for a big map).
    folder = tmp_path / "a-folder"
    folder.mkdir()
    with pytest.raises(IsADirectoryError):
        client.save_snapshot("files", folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, folder.name])


def test_a_saved_snapshot_is_on_disk_before_it_takes_its_name(
    client: FleetmapClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`save_snapshot` syncs the `.part` file to disk before renaming it to `path`, and then the
    folder (the rename): renamed with its data still in the page cache, a power cut soon after could
    leave a backup empty or cut short, the earlier one at `path` gone too. A power cut cannot be made
    here, so the test watches the calls that prevent that (the real ones, recorded in order)."""
    client.create_map("synced", CONFIG)
    path = tmp_path / "synced.fleetmap.zip"
    path.write_bytes(b"an earlier backup")
    calls: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        calls.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        calls.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    client.save_snapshot("synced", path)
    monkeypatch.undo()
    folder = os.path.realpath(tmp_path)  # (what /proc names the descriptors by)
    assert [c[0] for c in calls] == ["fsync", "replace", "fsync"], calls
    part = calls[0][1]  # the call's own part file, beside the backup
    assert os.path.dirname(part) == folder and re.fullmatch(
        rf"{re.escape(path.name)}\.[0-9a-f]{{16}}\.part", os.path.basename(part)
    )
    assert calls[1:] == [("replace", str(path)), ("fsync", folder)], calls
    assert path.read_bytes()[:2] == b"PK"


def test_snapshots_saved_to_one_path_at_once_each_leave_a_whole_file(
    client: FleetmapClient, scans: list[Scan], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two saves to one path at once (threads sharing the client, as it allows, or an overlapping
    backup job) each write their own part file and rename it whole. Both went to `path.part`: each
    truncated the other's, one renamed it, possibly unfinished, and returned the size it then had
    (0 was seen), the other failed renaming what was gone (FileNotFoundError). Here both downloads
    are written before either is renamed (each waits for the other at its fsync), as happens when
    they overlap."""
    client.create_map("twice", CONFIG)
    for k, scan in enumerate(scans[:3]):
        client.post_scan("twice", "r1", scan, seq=k)
    expected = client.download_snapshot("twice")
    path = tmp_path / "twice.fleetmap.zip"
    both_written = threading.Barrier(2, timeout=60)
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        real_fsync(fd)
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".part"):
            both_written.wait()

    monkeypatch.setattr(os, "fsync", fsync)
    outcomes: list[object] = []

    def save() -> None:
        try:
            outcomes.append(client.save_snapshot("twice", path))
        except Exception as exc:  # noqa: BLE001 - the outcome to check
            outcomes.append(exc)

    savers = [threading.Thread(target=save) for _ in range(2)]
    for saver in savers:
        saver.start()
    for saver in savers:
        saver.join(120)
    monkeypatch.undo()
    assert outcomes == [len(expected), len(expected)]
    assert path.read_bytes() == expected and [p.name for p in tmp_path.iterdir()] == [path.name]


def test_a_snapshot_uploaded_from_an_open_file_is_sent_from_where_it_stands(
    client: FleetmapClient, scans: list[Scan], tmp_path: Path
) -> None:
    """`upload_snapshot` sends an open file from its position to its end, whatever file it is: one
    whose first bytes the caller has read past (a snapshot after a header of its own) and a pipe
    (standard input). httpx declared the whole file's size whatever its position, and a pipe's 0,
    then failed mid-request with h11's "Too little (much) data for declared Content-Length"."""
    client.create_map("piped", CONFIG)
    for k, scan in enumerate(scans[:2]):
        client.post_scan("piped", "r1", scan, seq=k)
    snapshot = client.download_snapshot("piped")
    tiles = client.get_map("piped").stats.tiles
    path = tmp_path / "with-header.bin"
    path.write_bytes(b"HEADER" + snapshot)
    with open(path, "rb") as fp:
        assert fp.read(6) == b"HEADER"
        assert client.upload_snapshot("piped-offset", fp).stats.tiles == tiles
    read, write = os.pipe()

    def feed() -> None:
        with open(write, "wb") as out:
            out.write(snapshot)

    feeder = threading.Thread(target=feed)
    feeder.start()
    with open(read, "rb") as pipe:
        assert client.upload_snapshot("piped-pipe", pipe).stats.tiles == tiles
    feeder.join()
    x0, y0, x1, y1 = -5.0, -5.0, 15.0, 12.0
    for target in ("piped-offset", "piped-pipe"):
        np.testing.assert_array_equal(
            client.region(target, x0, y0, x1, y1), client.region("piped", x0, y0, x1, y1)
        )


def test_snapshots_and_nav2_maps_sent_from_a_bytearray_or_a_memoryview(
    client: FleetmapClient, scans: list[Scan]
) -> None:
    """`upload_snapshot` said it takes a bytearray or a memoryview of the file, and handed it to
    httpx as it was, which took it for an iterable of chunks and failed on its first byte ("object
    of type 'int' has no len()"); `import_nav2` took a bytearray for a path ("expected str, bytes or
    os.PathLike object")."""
    client.create_map("views", CONFIG)
    client.post_scan("views", "r1", scans[0])
    snapshot, ros = client.download_snapshot("views"), client.export("views")
    tiles = client.get_map("views").stats.tiles
    assert client.upload_snapshot("views-bytearray", bytearray(snapshot)).stats.tiles == tiles
    assert client.upload_snapshot("views-memoryview", memoryview(snapshot)).stats.tiles == tiles
    for target, source in (("nav2-bytearray", bytearray(ros)), ("nav2-memoryview", memoryview(ros))):
        assert client.import_nav2(target, source).stats.tiles > 0
        np.testing.assert_array_equal(client.region(target), client.region("nav2-bytearray"))


def test_threads_posting_one_robots_scans_lose_none(client: FleetmapClient, scans: list[Scan]) -> None:
    """The client is thread-safe, but threads posting one robot's scans with automatic seqs read
    the counter before any answer moved it: 4 threads posting 40 scans sent most seqs twice (or a
    higher one first), and the service ignored 30 of them as duplicates."""
    client.create_map("threads", CONFIG)
    threads, each = 4, 10
    start = threading.Barrier(threads)
    failures: list[BaseException] = []

    def post_some(k: int) -> None:
        start.wait()
        try:
            for n in range(each):
                assert client.post_scan("threads", "r1", scans[(k + n) % len(scans)]).status == "integrated"
        except BaseException as exc:  # reported below: an assert in a thread fails no test
            failures.append(exc)

    workers = [threading.Thread(target=post_some, args=(k,)) for k in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    assert not failures, failures
    robot = client.get_map("threads").stats.robots["r1"]
    assert (robot.scans_integrated, robot.duplicates, robot.lost) == (threads * each, 0, 0)
    assert robot.last_seq == threads * each - 1


def test_cells_past_the_services_limit_per_request(client: FleetmapClient, scans: list[Scan]) -> None:
    """The service answers at most 100 000 points a request; the client sent any number in one, and
    a planner asking for 250 000 got a 413. It now splits them and joins the answers in order."""
    client.create_map("many-cells", CONFIG)
    client.post_scan("many-cells", "r1", scans[0])
    pose = scans[0].pose
    some = np.random.default_rng(1).uniform([pose.x - 6, pose.y - 6], [pose.x + 6, pose.y + 6], (1000, 2))
    few = client.cells("many-cells", some)
    assert few["known"].any() and not few["known"].all()
    many = client.cells("many-cells", np.tile(some, (250, 1)))  # 250 000 points: three requests
    assert many.keys() == few.keys()
    for name, values in few.items():
        np.testing.assert_array_equal(many[name], np.tile(values, 250), err_msg=name)


def test_conditional_writes_refuse_a_map_that_changed(client: FleetmapClient, scans: list[Scan]) -> None:
    """`if_match=` (the tag `get_map_and_etag` read) and `create_only=` make a write happen only on
    the map the caller read, or only when there is none; otherwise `MapChanged` (a 412
    `FleetmapError`) with the map's current tag, and nothing changed."""
    with contextlib.suppress(FleetmapError):
        client.delete_map("cond")
    client.create_map("cond", CONFIG, create_only=True)
    with pytest.raises(MapChanged) as exists:
        client.create_map("cond", CONFIG, create_only=True)  # same configuration: still not created
    info, etag = client.get_map_and_etag("cond")
    assert exists.value.status == 412 and exists.value.etag == etag and info.id == "cond"
    client.post_scan("cond", "r1", scans[0], seq=0)
    assert client.get_map_and_etag("cond")[1] == etag  # scans do not change the map's tag
    snapshot = client.download_snapshot("cond")
    replaced = client.upload_snapshot("cond", snapshot, if_match=etag)
    new_etag = client.get_map_and_etag("cond")[1]
    assert new_etag != etag and replaced.stats.tiles > 0
    # The tag read before the replacement: every write refuses it, and the map stays.
    writes: list[Callable[[], object]] = [
        lambda: client.delete_map("cond", if_match=etag),
        lambda: client.upload_snapshot("cond", snapshot, if_match=etag),
        lambda: client.import_nav2("cond", client.export("cond", "ros"), if_match=etag),
        lambda: client.create_map("cond", CONFIG, if_match=etag),
        lambda: client.upload_snapshot("cond", snapshot, create_only=True),
    ]
    for write in writes:
        with pytest.raises(MapChanged) as changed:
            write()
        assert changed.value.etag == new_etag and "cond" in changed.value.detail
    assert client.get_map_and_etag("cond")[1] == new_etag
    client.delete_map("cond", if_match=new_etag)
    with pytest.raises(MapChanged) as gone:  # a PUT that would need the map finds none
        client.create_map("cond", CONFIG, if_match=new_etag)
    assert gone.value.etag is None
    with pytest.raises(FleetmapError) as missing:
        client.delete_map("cond", if_match=new_etag)
    assert missing.value.status == 404 and not isinstance(missing.value, MapChanged)
    with pytest.raises(ValueError, match="if_match"):
        client.delete_map("cond", if_match="")


def test_post_scan_sends_nan_and_infinities_as_the_protocol_reads_them(client: FleetmapClient) -> None:
    """A ScanMessage without range_max (no maximum: infinite) or with a NaN range (an invalid
    reading), and a dict in the JSON scan format holding NaN or infinities, all legal scans of
    docs/protocol.md, raised ValueError ("Out of range float values are not JSON compliant")."""
    pose = PoseMessage(x=0.5, y=0.5, theta=0.0)
    message = ScanMessage(seq=0, pose=pose, angle_min=-0.2, angle_increment=0.1, ranges=[1.0, None, math.nan])
    assert math.isinf(message.range_max)
    as_dict = {**message.model_dump(), "seq": 1, "ranges": [2.0, math.inf, math.nan, -math.inf]}
    results = [client.post_scan("non-finite", "r1", scan) for scan in (message, as_dict)]
    assert [(r.seq, r.status) for r in results] == [(0, "integrated"), (1, "integrated")]
    assert all(r.cell_updates > 0 for r in results)
    robot = client.get_map("non-finite").stats.robots["r1"]
    assert (robot.scans_integrated, robot.scans_rejected) == (2, 0)


def test_numpy_values_in_a_configuration_or_a_dict_scan(client: FleetmapClient, scans: list[Scan]) -> None:
    """A configuration dict or a dict scan holding NumPy values (a computed `np.int64` tile size, a
    `np.float32` resolution, ranges as an array, a seq from `np.arange`) is sent as the numbers and
    lists they hold: json refused them ("Object of type int64 is not JSON serializable"). The
    automatic seq goes on after a dict's NumPy seq, as after a Python one."""
    config = {"resolution": np.float32(0.125), "tile_size": np.int64(64), "layers": np.array(["occupancy"])}
    info = client.create_map("numpy-values", config)
    assert (info.resolution, info.config.tile_size, info.config.layers) == (0.125, 64, ("occupancy",))
    fan = scans[0]
    as_dict = {
        "seq": np.arange(5)[3],
        "stamp": np.float32(1.5),
        "pose": {"x": np.float64(fan.pose.x), "y": fan.pose.y, "theta": np.float32(fan.pose.theta)},
        "angle_min": fan.angles[0],
        "angle_increment": (fan.angles[1] - fan.angles[0]),
        "range_min": fan.range_min,
        "range_max": fan.range_max,
        "ranges": fan.ranges.astype(np.float32),
    }
    assert client.post_scan("numpy-values", "r1", as_dict).seq == 3
    assert client.post_scan("numpy-values", "r1", scans[1]).seq == 4  # the automatic seq went on
    robot = client.get_map("numpy-values").stats.robots["r1"]
    assert (robot.scans_integrated, robot.scans_rejected, robot.lost) == (2, 0, 0)


def test_a_configuration_dict_holding_the_engines_parameter_models(client: FleetmapClient) -> None:
    """`create_map` takes a configuration as a `MapConfig` or a dict, and `MapConfig` takes its
    sections as the engine's models (`{"occupancy": OccupancyParams(preset="int8")}`): such a dict
    raised json's "Object of type OccupancyParams is not JSON serializable". Each is sent as the
    values it holds, and the map is the one the same dict makes in the engine."""
    config = {
        "resolution": 0.1,
        "occupancy": OccupancyParams(preset="int8"),
        "tsdf": TsdfParams(truncation=0.3),
    }
    info = client.create_map("engine-sections", config)
    assert info.config == MapConfig.model_validate(config)
    assert client.create_map("engine-sections", config).config == info.config  # the same: 200


def test_tiles_with_etags(client: FleetmapClient, scans: list[Scan]) -> None:
    client.create_map("tiles", CONFIG)
    client.post_scan("tiles", "r1", scans[0], seq=0)
    x0, y0 = scans[0].pose.x / CONFIG.resolution, scans[0].pose.y / CONFIG.resolution
    # Zoom 0: one pixel per cell; tile (x, y) covers i in [256x, 256(x+1)), j in [-256(y+1), -256y).
    tx, ty = int(x0 // 256), int(-(y0 // 256) - 1)
    png, etag = client.tile("tiles", 0, tx, ty)
    assert png is not None and etag
    image = Image.open(io.BytesIO(png))
    assert image.size == (256, 256) and image.mode == "RGBA"
    assert np.asarray(image)[..., 3].any(), "the robot's surroundings are drawn"
    assert client.tile("tiles", 0, tx, ty, etag=etag) == (None, etag)  # 304: unchanged
    client.post_scan("tiles", "r1", scans[5], seq=1)
    png2, etag2 = client.tile("tiles", 0, tx, ty, etag=etag)
    assert png2 is not None and etag2 != etag
    with pytest.raises(FleetmapError) as bad_zoom:
        client.tile("tiles", 99, 0, 0)
    assert bad_zoom.value.status == 422 and "z" in bad_zoom.value.detail
    # NumPy integers are tile indices; a float is refused, before any request: cut to an int, -0.5
    # (a point left of tile 0, divided by the tile size) asked for tile 0, not -1, with no word.
    assert client.tile("tiles", np.int64(0), np.int32(tx), np.uint16(ty) if ty >= 0 else ty)[0] == png2
    for z, x, y in ((0, tx - 0.5, ty), (0, tx, float(ty)), (0.0, tx, ty), (0, True, ty)):
        with pytest.raises(TypeError, match="tile . must be an integer"):
            client.tile("tiles", z, x, y)  # type: ignore[arg-type]


def test_errors_carry_the_server_detail(client: FleetmapClient, scans: list[Scan]) -> None:
    with pytest.raises(FleetmapError) as unknown:
        client.cell("no-such-map", 0, 0)
    assert unknown.value.status == 404 and "no-such-map" in unknown.value.detail
    client.create_map("errs", {"resolution": 0.1, "layers": ["occupancy"]})
    with pytest.raises(FleetmapError) as empty:
        client.region("errs")
    assert empty.value.status == 409 and "no observed cell" in empty.value.detail
    with pytest.raises(FleetmapError) as export_empty:
        client.export("errs")
    assert export_empty.value.status == 409
    with pytest.raises(FleetmapError) as no_tsdf:
        client.surface("errs", 0, 0, 1, 1)
    assert no_tsdf.value.status == 422 and "tsdf" in no_tsdf.value.detail
    with pytest.raises(FleetmapError) as no_layer:
        client.region("errs", 0, 0, 1, 1, layer="hits")
    assert no_layer.value.status == 422 and "hits" in no_layer.value.detail
    with pytest.raises(FleetmapError) as bad_layer:
        client.region("errs", 0, 0, 1, 1, layer="colour")  # type: ignore[arg-type]
    assert bad_layer.value.status == 422 and "colour" in bad_layer.value.detail
    bad_scan: dict[str, Any] = {"seq": 0, "pose": {"x": 0, "y": 0, "theta": 0}, "ranges": [1.0]}
    with pytest.raises(FleetmapError) as invalid:
        client.post_scan("errs", "r1", bad_scan)
    assert invalid.value.status == 422 and "angle_min" in invalid.value.detail
    assert client.get_map("errs").stats.robots["r1"].scans_rejected == 1
    # httpx's own type, its sentence naming the address tried (httpx's alone names none).
    nowhere = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(httpx.ConnectError, match=f"the fleetmap service at {nowhere}"):
        FleetmapClient(nowhere, timeout=2).health()
    with pytest.raises(httpx.ConnectError, match=f"the fleetmap service at {nowhere}"):
        next(iter(FleetmapClient(nowhere, timeout=2).events("errs")))


def test_errors_do_not_show_the_password_of_the_address() -> None:
    """An address with a user and password (`http://user:password@proxy/`: httpx sends them as Basic
    auth, to a proxy in front of the service) showed the password in every error's sentence, which
    logs keep (a `ConnectError`'s "the fleetmap service at http://robot:s3cret@..."; another web
    server's page and a redirect named the request's URL whole), and in the client's repr: they show
    the user, never the password, as the API token is never shown."""
    secret = "s3cret-Pa55"

    def with_password(url: str) -> str:
        return url.replace("http://", f"http://robot:{secret}@")

    def shown(error: BaseException) -> str:
        return f"{error} {error!r}"

    nowhere = with_password(f"http://127.0.0.1:{free_port()}")
    with FleetmapClient(nowhere, timeout=2) as fm:
        assert secret not in repr(fm) and "robot@127.0.0.1" in repr(fm)
        with pytest.raises(httpx.ConnectError) as refused:
            fm.health()
        assert secret not in shown(refused.value)
        assert "the fleetmap service at http://robot@" in str(refused.value)
        with pytest.raises(httpx.ConnectError) as no_stream:
            next(iter(fm.events("m")))
        assert secret not in shown(no_stream.value)
    with _web_page_server() as page, FleetmapClient(with_password(page)) as fm:
        with pytest.raises(FleetmapError) as portal:
            fm.health()
        assert secret not in shown(portal.value) and "robot@127.0.0.1" in portal.value.detail
    with _redirect_to("https://elsewhere.example") as moved, FleetmapClient(with_password(moved)) as fm:
        with pytest.raises(FleetmapError) as redirect:
            fm.get_map("m")
        assert secret not in shown(redirect.value)
        assert "redirect to https://elsewhere.example" in redirect.value.detail
    with pytest.raises(ValueError) as no_url:
        FleetmapClient(f"robot:{secret}@127.0.0.1:8000")
    assert secret not in shown(no_url.value)


def _get_map_id(base_url: str, map_id: str) -> str:
    """A worker process's job in the test below: the id `get_map` answers."""
    with FleetmapClient(base_url, timeout=20.0) as fm:
        return fm.get_map(map_id).id


def test_errors_reach_another_process_whole(service: ServiceProcess, client: FleetmapClient) -> None:
    """A program spreading its queries over processes (ProcessPoolExecutor, multiprocessing) gets
    a worker's `FleetmapError` back as it was raised: pickled with its one sentence as `args`, it
    could not be made again (its constructor wants the status and the detail), and the pool broke,
    failing every other query of it as well (BrokenProcessPool)."""
    client.create_map("pickled", {"resolution": 0.1})
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        missing = pool.submit(_get_map_id, service.base_url, "no-such-map")
        with pytest.raises(FleetmapError) as raised:
            missing.result(timeout=120)
        assert pool.submit(_get_map_id, service.base_url, "pickled").result(timeout=120) == "pickled"
    assert (raised.value.status, raised.value.detail) == (404, "no map 'no-such-map'")
    # Every field, and a MapChanged's ETag, through pickle and copy.
    _, etag = client.get_map_and_etag("pickled")
    client.delete_map("pickled")
    client.create_map("pickled", {"resolution": 0.1})
    with pytest.raises(MapChanged) as changed:
        client.delete_map("pickled", if_match=etag)
    for again in (pickle.loads(pickle.dumps(changed.value)), copy.copy(changed.value)):
        assert type(again) is MapChanged and str(again) == str(changed.value)
        fields = ("status", "detail", "errors", "retry_after", "etag")
        assert [getattr(again, f) for f in fields] == [getattr(changed.value, f) for f in fields]
    assert changed.value.etag is not None and changed.value.etag != etag


def test_a_connection_the_service_closes_as_idle_is_not_used_again(service: ServiceProcess) -> None:
    """The service closes a kept-alive connection after 5 s idle (uvicorn's keep-alive), and httpx
    kept one for 5 s too: over a slow link, a request sent a little under 5 s after the last answer
    reached the service after it had closed the connection, and failed ("Server disconnected without
    sending a response", a RemoteProtocolError; a post_scan's seq then skipped as maybe taken). The
    client lets its connections go well before the service's do. The idle wait here is the case
    itself; a busy machine could only hide the failure (a service late to close), never cause one."""
    proxy = FreezableProxy(service.port, lag=0.6)  # 0.6 s from the service to the client
    try:
        with FleetmapClient(f"http://127.0.0.1:{proxy.port}", timeout=20.0) as fm:
            fm.health()
            time.sleep(4.7)  # idle: the service's close is 0.6 s behind, its 5 s passed on arrival
            assert fm.health().status == "ok"
    finally:
        proxy.close()


def test_api_tokens(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fleetmap.serve_options

    if "--auth-tokens" not in Path(fleetmap.serve_options.__file__).read_text():
        pytest.skip("this fleetmap serve has no --auth-tokens option")
    writer, reader = "w" * 8 + "-secret-token-1", "r" * 8 + "-secret-token-2"
    tokens = tmp_path / "tokens"
    tokens.write_text(f"write {writer}\nread {reader}\n")
    monkeypatch.delenv("FLEETMAP_TOKEN", raising=False)
    with ServiceProcess(tmp_path, ["--in-memory", "--auth-tokens", str(tokens)]) as svc:
        with FleetmapClient(svc.base_url) as anonymous:
            assert anonymous.list_maps() == []  # reading is open by default
            with pytest.raises(FleetmapError) as no_token:
                anonymous.create_map("locked")
            assert no_token.value.status == 401 and "Bearer" in no_token.value.detail
        with FleetmapClient(svc.base_url, token=reader) as read_only:
            with pytest.raises(FleetmapError) as too_low:
                read_only.create_map("locked")
            assert too_low.value.status == 403 and "'write'" in too_low.value.detail
        monkeypatch.setenv("FLEETMAP_TOKEN", writer)
        with FleetmapClient(svc.base_url) as from_env:
            assert from_env.create_map("locked").id == "locked"
        # A token read whole from its file (its line end), or from an env file written on Windows
        # (\r\n), is the token: the service drops the whitespace around it too. httpx refused it
        # at every request, the token itself in its message ("Illegal header value b'Bearer ...'").
        (tmp_path / "my-token").write_text(writer + "\n")
        with FleetmapClient(svc.base_url, token=(tmp_path / "my-token").read_text()) as from_file:
            assert from_file.create_map("from-file").id == "from-file"
        monkeypatch.setenv("FLEETMAP_TOKEN", writer + "\r\n")
        with FleetmapClient(svc.base_url) as from_env_file:
            from_env_file.delete_map("from-file")
        # One that no header can carry is refused at once, naming no token.
        for unsendable in ("w" * 8 + "-secret-tökén", writer[:8] + " " + writer[8:]):
            with pytest.raises(ValueError, match="printable ASCII") as refused:
                FleetmapClient(svc.base_url, token=unsendable)
            assert "secret" not in str(refused.value)


def test_an_api_token_and_an_address_with_a_password_are_not_both_taken(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """httpx sends the user and password of an address (`http://user:password@proxy/`) as Basic
    auth in the `Authorization` header, the header the API token goes in: given both, it sent the
    Basic auth and dropped the token without a word, and the service answered 401 ("no token") to
    a client made with one. Both given (the token as `token=` or `$FLEETMAP_TOKEN`) is now a
    ValueError when the client is made, naming neither secret; the address alone still sends its
    user and password."""
    seen: list[str | None] = []

    class Recorder(_FakeService):
        def do_GET(self) -> None:
            seen.append(self.headers.get("authorization"))
            self.reply(200, b'{"maps": []}', "application/json")

    monkeypatch.delenv("FLEETMAP_TOKEN", raising=False)
    with _serving(Recorder) as url:
        address = url.replace("http://", "http://robot:pa55word@")
        with FleetmapClient(address) as basic:
            assert basic.list_maps() == []
        assert seen == ["Basic cm9ib3Q6cGE1NXdvcmQ="]
        with pytest.raises(ValueError, match="Authorization header") as both:
            FleetmapClient(address, token="secret-token-1")
        monkeypatch.setenv("FLEETMAP_TOKEN", "secret-token-1")
        with pytest.raises(ValueError, match="Authorization header") as both_from_env:
            FleetmapClient(address)
        with FleetmapClient(url) as bearer:  # the token alone is sent
            assert bearer.list_maps() == []
        assert seen[-1] == "Bearer secret-token-1"
    for error in (both.value, both_from_env.value):
        assert "pa55word" not in str(error) and "secret-token" not in str(error)


# -- events ----------------------------------------------------------------------------------------


def test_events_stream_tiles_robots_and_deletion(client: FleetmapClient, scans: list[Scan]) -> None:
    client.create_map("ev", CONFIG)
    received: list[tuple[str, dict[str, Any]]] = []
    finished = threading.Event()

    def listen() -> None:
        with FleetmapClient(client.base_url) as own:
            for event in own.events("ev"):
                received.append(event)
        finished.set()  # the stream ended: the map was deleted

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    wait_for(lambda: any(e == "robots" for e, _ in received), 10, 0.02, "the initial robots event")
    result = client.post_scan("ev", "rob", scans[0], seq=0)

    def tiles_seen() -> set[tuple[int, ...]]:
        return {tuple(w) for e, d in received if e == "tiles" for w in d.get("tiles", [])}

    wait_for(lambda: {tuple(w) for w in result.changed_tiles} <= tiles_seen(), 10, 0.02, "the tiles event")
    # The robot is in the map from its scan's acceptance, before the scan is integrated: a robots
    # event of that moment shows it with no scan and no pose, and the next one with both (a
    # loaded machine let this test read the first and fail).
    wait_for(
        lambda: any(
            e == "robots" and d["robots"].get("rob", {}).get("scans_integrated") for e, d in received
        ),
        10,
        0.02,
        "robot 'rob' with its scan",
    )
    robots = next(d for e, d in reversed(received) if e == "robots")["robots"]["rob"]
    assert robots["scans_integrated"] == 1 and robots["pose"] == pytest.approx(
        [scans[0].pose.x, scans[0].pose.y, scans[0].pose.theta]
    )
    client.delete_map("ev")
    assert finished.wait(10), "the event stream did not end after the map was deleted"
    assert received[-1] == ("deleted", {"id": "ev"})


def _reader(client: FleetmapClient, map_id: str) -> tuple[threading.Thread, list[str], list[BaseException]]:
    """A thread, started, reading `client.events(map_id)`: it, the events it received and what it
    raised (the reader's view, to assert on)."""
    received: list[str] = []
    failures: list[BaseException] = []

    def listen() -> None:
        try:
            for event, _data in client.events(map_id):
                received.append(event)
        except BaseException as exc:
            failures.append(exc)

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    return thread, received, failures


def test_closing_the_client_ends_its_event_streams_read_in_other_threads(client: FleetmapClient) -> None:
    """A program that reads a map's events in a thread and closes its client to stop: the reader
    stayed blocked until the server's next keepalive (some 15 s), then failed with RuntimeError on
    the closed pool. Its iteration now just stops, at once."""
    client.create_map("ev-close", CONFIG)
    own = FleetmapClient(client.base_url)
    thread, received, failures = _reader(own, "ev-close")
    wait_for(lambda: "robots" in received, 10, 0.02, "the initial robots event")
    own.close()
    thread.join(60)
    assert not thread.is_alive() and not failures, failures
    with pytest.raises(RuntimeError, match="closed"):  # a request afterwards, as every other
        next(own.events("ev-close"))
    own.close()  # idempotent


def test_event_streams_leave_the_clients_requests_their_connections(
    client: FleetmapClient, service: ServiceProcess
) -> None:
    """Each event stream holds a connection for as long as it is followed. They came from the pool
    every request takes from (100 connections): with 100 streams open (a dashboard following many
    maps, or many threads one), every other request of the client, a `get_map` or another stream,
    waited `timeout`, then failed with a `PoolTimeout` reading " (the fleetmap service at ...)", as
    if the service were at fault. Streams have connections of their own (the service bounds
    them: `--max-event-streams`)."""
    client.create_map("many-streams", CONFIG)
    with FleetmapClient(service.base_url, timeout=5.0) as fm:
        streams = [fm.events("many-streams") for _ in range(rest._LIMITS.max_connections or 0)]
        for stream in streams:
            assert next(stream)[0] == "robots"
        assert fm.get_map("many-streams").id == "many-streams"
        assert next(fm.events("many-streams"))[0] == "robots"


def test_closing_the_client_ends_an_event_stream_waiting_to_resume() -> None:
    """A reader whose stream ended (the service restarting) waits before it resumes: 1 s, or what a
    503's Retry-After asks. A client closed meanwhile (the program stopping) let that wait run out,
    then its reader raised RuntimeError ("the client has been closed") instead of ending as a
    stream the close finds open does. It now ends at once, without an error."""
    requests: list[str] = []

    class EndsThenBusy(_FakeService):
        def do_GET(self) -> None:
            requests.append(self.path)
            if len(requests) == 1:  # a stream of one event, which then ends
                self.reply(
                    200, b'id: 1\nevent: tiles\ndata: {"version": 1, "tiles": []}\n\n', "text/event-stream"
                )
            else:  # the service is busy: come back in a minute
                body = b'{"detail": "the server holds its limit of event streams; retry later"}'
                self.reply(503, body, "application/json", {"retry-after": "60"})

    with _serving(EndsThenBusy) as url:
        own = FleetmapClient(url)
        thread, received, failures = _reader(own, "m")
        wait_for(lambda: len(requests) == 2, 10, 0.02, "the reader's attempt to resume")
        own.close()
        thread.join(20)  # well within the 60 s the service asked for
        assert not thread.is_alive() and not failures, failures
    assert received == ["tiles"]


@contextlib.contextmanager
def _stream_then(answers: list[tuple[int, str, dict[str, str]]]) -> Iterator[tuple[str, list[str]]]:
    """A real HTTP server on a free port, as a reverse proxy in front of a restarting service: the
    first GET is a stream of one `tiles` event (id 1) that then ends, each next one the next of
    `answers` (status, body, headers; a 200 is another such stream), and 404 after them (the map
    gone, which ends the client's stream). Yields its URL and the paths asked, in order, each
    followed by `&t=` and the `time.monotonic()` it came at."""
    requests: list[str] = []
    stream = b'id: 1\nevent: tiles\ndata: {"version": 1, "tiles": []}\n\n'

    class Proxy(_FakeService):
        def do_GET(self) -> None:
            requests.append(f"{self.path}&t={time.monotonic()}")  # when it came, too
            k = len(requests) - 2
            if k < 0 or (k < len(answers) and answers[k][0] == 200):
                self.reply(200, stream, "text/event-stream")
            elif k < len(answers):
                status, body, headers = answers[k]
                self.reply(status, body.encode(), "text/html", headers)
            else:
                self.reply(404, b'{"detail": "no map \'m\'"}', "application/json")

    with _serving(Proxy) as url:
        yield url, requests


def test_an_absurd_retry_after_is_read_safely_and_capped(monkeypatch: pytest.MonkeyPatch) -> None:
    """A `Retry-After` comes from whatever answers, a foreign proxy's too, and may say anything:
    `1e999` (an infinite float) made the error's `retry_after` infinite and a resumed event
    stream's wait raise OverflowError ("timeout value is too large") out of `next()`. It is read as
    at most `MAX_RETRY_AFTER` seconds, at least 0, and what is no number of seconds (NaN, an HTTP
    date) as none; the stream waits that long and goes on."""
    values = ["1e999", "-1e999", "nan", "-5", "120", "2.5", "Wed, 21 Oct 2026 07:28:00 GMT", "inf"]

    class Busy(_FakeService):
        def do_GET(self) -> None:
            value = values[int(self.path.rsplit("-", 1)[1])]
            self.reply(503, b'{"detail": "busy"}', "application/json", {"retry-after": value})

    with _serving(Busy) as url, FleetmapClient(url) as fm:
        waits = []
        for k in range(len(values)):
            with pytest.raises(FleetmapError) as busy:
                fm.get_map(f"busy-{k}")
            waits.append(busy.value.retry_after)
    most = rest.MAX_RETRY_AFTER
    assert waits == [most, 0.0, None, 0.0, most, 2.5, None, most]
    monkeypatch.setattr(rest, "MAX_RETRY_AFTER", 0.05)  # not a minute: the test goes on past it
    monkeypatch.setattr(rest, "RECONNECT_DELAY", 0.05)
    absurd = [(503, "busy", {"retry-after": "1e999"})]
    with _stream_then(absurd) as (url, requests), FleetmapClient(url) as fm:
        stream = fm.events("m")
        assert next(stream)[0] == "tiles"
        with pytest.raises(FleetmapError) as gone:  # the 404 after the wait, not an OverflowError
            next(stream)
    assert gone.value.status == 404 and len(requests) == 3


def test_events_resume_through_a_proxys_gateway_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    """Behind a reverse proxy (nginx, a load balancer), a restarting service is a 502 (nothing
    listens yet), a 504 (no answer in time) or a 503 of the proxy's own, without a Retry-After:
    each ended a followed stream with a `FleetmapError`, where the web viewer's EventSource (and
    the client itself, for the service's own 503) waits and resumes. They are resumed the same way."""
    monkeypatch.setattr(rest, "RECONNECT_DELAY", 0.05)
    page = "<html><body><h1>{}</h1>nginx</body></html>"
    gateway = [
        (502, page.format("502 Bad Gateway"), {}),
        (504, page.format("504 Gateway Time-out"), {}),
        (503, page.format("503 Service Temporarily Unavailable"), {}),
        (200, "", {}),
    ]
    received: list[str] = []
    with (
        _stream_then(gateway) as (url, requests),
        FleetmapClient(url) as fm,
        pytest.raises(FleetmapError) as gone,  # the 404 at last: the map is gone
    ):
        received.extend(event for event, _ in fm.events("m"))
    assert received == ["tiles", "reconnected", "tiles"]
    assert gone.value.status == 404 and len(requests) == 6


def test_a_retry_after_shorter_than_the_reconnect_delay_does_not_hurry_a_resume(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A proxy (or anything else answering) that says `Retry-After: 0` on each 503 made a stream
    waiting to resume ask again at once, as fast as the answers came, a busy loop hammering the
    proxy and the service behind it; the web viewer waits its own delay at least. The client waits
    `RECONNECT_DELAY` at least too, however short the Retry-After (only a lower bound is timed: a
    busy machine makes the gaps longer, never shorter)."""
    monkeypatch.setattr(rest, "RECONNECT_DELAY", 0.3)
    now = [(503, "busy", {"retry-after": wait}) for wait in ("0", "0.001", "-1")]
    times: list[float] = []
    with _stream_then(now) as (url, requests), FleetmapClient(url) as fm:
        stream = fm.events("m")
        assert next(stream)[0] == "tiles"
        with pytest.raises(FleetmapError) as gone:
            next(stream)
        times = [float(path.rpartition("&t=")[2]) for path in requests]
    assert gone.value.status == 404 and len(requests) == 5
    gaps = [later - earlier for earlier, later in itertools.pairwise(times)]
    assert min(gaps) >= 0.3 * 0.9, gaps


def test_events_go_on_through_a_snapshot_replacement(client: FleetmapClient, scans: list[Scan]) -> None:
    """A map replaced by `PUT /maps/{id}/snapshot` still exists: `events` yields `replaced` and goes
    on with the new map's events; only a deletion ends it."""
    client.create_map("ev-src", CONFIG)
    client.post_scan("ev-src", "rob", scans[0], seq=0)
    snapshot = httpx.get(f"{client.base_url}/maps/ev-src/snapshot", timeout=30).content
    client.create_map("ev-rep", CONFIG)
    received: list[tuple[str, dict[str, Any]]] = []
    finished = threading.Event()

    def listen() -> None:
        with FleetmapClient(client.base_url) as own:
            for event in own.events("ev-rep"):
                received.append(event)
        finished.set()

    threading.Thread(target=listen, daemon=True).start()
    wait_for(lambda: any(e == "robots" for e, _ in received), 10, 0.02, "the initial robots event")
    r = httpx.put(
        f"{client.base_url}/maps/ev-rep/snapshot",
        content=snapshot,
        headers={"content-type": "application/zip"},
        timeout=30,
    )
    assert r.status_code == 200, r.text  # replaced, not created
    start = httpx.get(f"{client.base_url}/maps/ev-rep", timeout=10).json()["stats"]["version"]
    replaced = ("replaced", {"id": "ev-rep", "version": start})
    wait_for(lambda: replaced in received, 10, 0.02, "replaced")
    assert not finished.is_set() and ("deleted", {"id": "ev-rep"}) not in received
    result = client.post_scan("ev-rep", "rob", scans[1], seq=0)  # the stream follows the new map
    changed = {tuple(w) for w in result.changed_tiles}

    def tiles_since_replaced() -> set[tuple[int, ...]]:
        after = received[received.index(replaced) :]
        return {tuple(w) for e, d in after if e == "tiles" for w in d.get("tiles", [])}

    wait_for(lambda: changed <= tiles_since_replaced(), 10, 0.02, "the new map's tiles event")
    client.delete_map("ev-rep")
    assert finished.wait(10), "the event stream did not end after the map was deleted"
    assert received[-1] == ("deleted", {"id": "ev-rep"})


def test_a_nav2_import_replacing_a_map_sends_replaced(client: FleetmapClient, scans: list[Scan]) -> None:
    """`PUT /maps/{id}/import` replaces a map as a snapshot upload does, and its streams get `replaced`
    too; the docs of the event (docs/api.md, docs/clients.md, the spec, `ReplacedEvent`) named the
    snapshot upload alone, so a client following an imported map was told to expect `deleted`."""
    client.create_map("ev-imp", CONFIG)
    client.post_scan("ev-imp", "rob", scans[0], seq=0)
    nav2 = client.export("ev-imp", "ros")
    received: list[tuple[str, dict[str, Any]]] = []

    def listen() -> None:
        with FleetmapClient(client.base_url) as own:
            for event in own.events("ev-imp"):
                received.append(event)
                if event[0] in ("replaced", "deleted"):
                    return

    threading.Thread(target=listen, daemon=True).start()
    wait_for(lambda: any(e == "robots" for e, _ in received), 10, 0.02, "the initial robots event")
    assert client.import_nav2("ev-imp", nav2).id == "ev-imp"
    start = client.get_map("ev-imp").stats.version
    wait_for(lambda: ("replaced", {"id": "ev-imp", "version": start}) in received, 10, 0.02, "replaced")
    api = (REPO_DIR / "docs" / "api.md").read_text(encoding="utf-8")
    clients = (REPO_DIR / "docs" / "clients.md").read_text(encoding="utf-8")
    spec = (REPO_DIR / "openapi" / "openapi.json").read_text(encoding="utf-8")
    descriptions = {
        "docs/api.md": re.search(r"^- `replaced`:.*?(?=^- )", api, re.M | re.S),
        "docs/clients.md": re.search(r'\("replaced", \{"id",.*?\(reload', clients, re.S),
        "openapi.json": re.search(r"event: replaced`, `id: <version>`.*?;", spec, re.S),
    }
    for where, found in descriptions.items():
        assert found is not None, f"{where} no longer describes the replaced event where it did"
        assert "/import" in found.group(0), f"{where} does not say an import sends replaced: {found.group(0)}"
    assert "/import" in (ReplacedEvent.__doc__ or "")


def test_events_resume_after_the_service_restarts(tmp_path: Path, scans: list[Scan]) -> None:
    """A dashboard following a map: the service restarts (SIGTERM ends every stream cleanly with
    ": the server is shutting down"). `events` took that end for the end of the map's events and
    stopped, where an EventSource reconnects with Last-Event-ID; it now waits for the service, says
    ("reconnected", ...), and goes on with the changes made since."""
    received: list[tuple[str, dict[str, Any]]] = []
    finished = threading.Event()
    with ServiceProcess(tmp_path) as svc, FleetmapClient(svc.base_url, timeout=20.0) as fm:
        fm.create_map("follow", CONFIG)
        fm.post_scan("follow", "r1", scans[0])

        def listen() -> None:
            with FleetmapClient(svc.base_url) as own:
                received.extend(own.events("follow"))
            finished.set()

        threading.Thread(target=listen, daemon=True).start()
        wait_for(lambda: any(e == "robots" for e, _ in received), 10, 0.02, "the initial robots event")
        assert svc.stop() == 0
        svc.start()  # the same ports and data directory: the map is restored
        wait_for(lambda: any(e == "reconnected" for e, _ in received), 30, 0.05, "the stream resumed")
        assert not finished.is_set()
        changed = {tuple(w) for w in fm.post_scan("follow", "r1", scans[1]).changed_tiles}

        def tiles_since_resumed() -> set[tuple[int, ...]]:
            after = received[[e for e, _ in received].index("reconnected") :]
            return {tuple(w) for e, d in after if e == "tiles" for w in d.get("tiles", [])}

        wait_for(lambda: changed <= tiles_since_resumed(), 10, 0.02, "the tiles changed after the restart")
        fm.delete_map("follow")
        assert finished.wait(10), "the event stream did not end after the map was deleted"
    assert received[-1] == ("deleted", {"id": "follow"})


def test_events_resume_a_stream_that_went_silent(tmp_path: Path, scans: list[Scan]) -> None:
    """A connection that dies without a FIN or RST (half-open TCP) sent nothing more, and `events`,
    which read without a timeout, waited for ever. The service breaks every silence with a keepalive
    (here every 0.3 s, `--events-keepalive`), so a stream silent for a few of them is dead: the client
    gives it up after `events_read_timeout` and resumes, saying ("reconnected", ...), with the
    changes made since. An idle stream that gets its keepalives is kept."""
    received: list[tuple[str, dict[str, Any]]] = []
    finished = threading.Event()
    with ServiceProcess(tmp_path, ["--in-memory", "--events-keepalive", "0.3"]) as svc:
        proxy = FreezableProxy(svc.port)
        try:
            with FleetmapClient(svc.base_url, timeout=20.0) as fm:
                fm.create_map("silent", CONFIG)
                fm.post_scan("silent", "r1", scans[0])

                def listen() -> None:
                    url = f"http://127.0.0.1:{proxy.port}"
                    with FleetmapClient(url, events_read_timeout=1.5) as own:
                        received.extend(own.events("silent"))
                    finished.set()

                threading.Thread(target=listen, daemon=True).start()
                wait_for(
                    lambda: any(e == "robots" for e, _ in received), 10, 0.02, "the initial robots event"
                )
                time.sleep(3.0)  # idle for twice the read timeout: the keepalives hold the stream
                assert [e for e, _ in received if e == "reconnected"] == [], received
                assert proxy.freeze() == 1  # the stream's connection: silent from now on
                wait_for(lambda: any(e == "reconnected" for e, _ in received), 15, 0.05, "the stream resumed")
                changed = {tuple(w) for w in fm.post_scan("silent", "r1", scans[1]).changed_tiles}

                def tiles_since_resumed() -> set[tuple[int, ...]]:
                    after = received[[e for e, _ in received].index("reconnected") :]
                    return {tuple(w) for e, d in after if e == "tiles" for w in d.get("tiles", [])}

                wait_for(
                    lambda: changed <= tiles_since_resumed(), 10, 0.02, "the tiles changed after the resume"
                )
                fm.delete_map("silent")
                assert finished.wait(10), "the event stream did not end after the map was deleted"
        finally:
            proxy.close()
    assert received[-1] == ("deleted", {"id": "silent"})
    with pytest.raises(ValueError, match="events_read_timeout"):
        FleetmapClient(svc.base_url, events_read_timeout=0)


def test_events_of_an_unknown_map(client: FleetmapClient) -> None:
    with pytest.raises(FleetmapError) as exc:
        next(client.events("nothing-here"))
    assert exc.value.status == 404


def test_events_from_a_server_that_sends_no_event_stream() -> None:
    """Another web server at the address (a wrong port, a proxy's page) answering 200 with no event
    stream fails the stream, as an EventSource fails such a connection: its answer held no event,
    so the stream was taken as lost and resumed every second for ever, each time yielding a
    "reconnected" that never was. A real HTTP server answers 200 with JSON here."""
    with _late_service(200, "welcome to another app", delay=0.0) as base, FleetmapClient(base) as fm:
        stream = fm.events("somewhere")
        with pytest.raises(FleetmapError, match="application/json, not an event stream") as exc:
            next(stream)
        assert exc.value.status == 200


@pytest.mark.parametrize("since", [-1, "7", 2.0, True])
def test_events_refuse_a_since_that_is_no_change_version(client: FleetmapClient, since: object) -> None:
    # Sent as it is, the server reads such a Last-Event-ID as none at all and starts from now.
    with pytest.raises(ValueError, match="since must be a change version"):
        client.events("any", since=since)  # type: ignore[arg-type]


def test_parse_sse_follows_the_event_stream_format() -> None:
    lines = [
        *["retry: 1000", "", "id: 4", "event: tiles", 'data: {"version": 4,', 'data: "tiles": []}', ""],
        *[": keepalive", "", "data: plain text", "", "event: robots", 'data: {"robots": {}}', ""],
    ]
    assert list(parse_sse(iter(lines))) == [
        ("tiles", {"version": 4, "tiles": []}),
        ("message", {"data": "plain text"}),
        ("robots", {"robots": {}}),
    ]


# -- robots over Zenoh into the real service -------------------------------------------------------


def test_publisher_scans_are_integrated_and_served(
    service: ServiceProcess, client: FleetmapClient, scans: list[Scan]
) -> None:
    client.create_map("zen", CONFIG)
    with ScanPublisher("zen", "z1", connect=[service.zenoh_endpoint]) as pub:
        assert pub.wait_connected(20), pub.last_connect_error
        for scan in scans:
            assert pub.publish(scan)

        def robot() -> Any:
            return client.get_map("zen").stats.robots.get("z1")

        wait_for(lambda: robot() and robot().scans_integrated == len(scans), 20, 0.05, "all scans integrated")
        state = robot()
        assert state.online and state.lost == 0 and state.dropped == 0 and state.last_seq == len(scans) - 1
    wait_for(lambda: not robot().online, 10, 0.05, "the robot offline after close()")
    # The whole pipeline (binary over Zenoh, service, REST) against the engine on the same payloads.
    gmap = _engine_map([decode(encode_binary(s, k, 0.0), BINARY_ENCODING).scan for k, s in enumerate(scans)])
    bounds = gmap.known_bounds()
    assert bounds is not None
    res = CONFIG.resolution
    ii, jj = np.meshgrid(np.arange(bounds[0], bounds[2]), np.arange(bounds[1], bounds[3]))
    points = np.stack([(ii.ravel() + 0.5) * res, (jj.ravel() + 0.5) * res], axis=1)
    _assert_cells_equal(client.cells("zen", points), gmap.cells(points))


def test_replay_command_into_the_service(
    service: ServiceProcess, client: FleetmapClient, tmp_path: Path
) -> None:
    from test_client_zenoh import _write_carmen

    log = tmp_path / "hall.log"
    _write_carmen(log, 30)
    args = ["replay", str(log), "--map", "hall", "--robot", "rp", "--rate", "5", "--quiet"]
    assert cli.main([*args, "--connect", service.zenoh_endpoint, "--wait-timeout", "20"]) == 0

    def robot() -> Any:
        info = client.list_maps()
        return "hall" in [m.id for m in info] and client.get_map("hall").stats.robots.get("rp")

    wait_for(lambda: robot() and robot().scans_integrated == 30, 20, 0.05, "the replayed scans integrated")
    state = robot()
    assert (state.last_seq, state.lost, state.dropped, state.scans_rejected) == (29, 0, 0, 0)
    ds = load_dataset(log)
    last = ds[29].pose
    assert (state.last_pose.x, state.last_pose.y, state.last_pose.theta) == pytest.approx(
        (last.x, last.y, last.theta)
    )


def service_with_a_map_past_todays_limits(tmp_path: Path, scans: list[Scan]) -> ServiceProcess:
    """A stopped service whose data directory holds map `old` (one scan) with a configuration an
    older version could store, past two of today's limits (`OLD_LIMITS`), as it stores it."""
    data_dir = tmp_path / "data"
    svc = ServiceProcess(tmp_path, ["--data-dir", str(data_dir)])
    with svc, FleetmapClient(svc.base_url, timeout=20.0) as fm:
        fm.create_map("old", {**CONFIG.model_dump(), "tsdf": {"truncation": 0.3}})
        fm.post_scan("old", "r1", scans[0])
    with sqlite3.connect(data_dir / DB_NAME) as conn:
        stored = json.loads(conn.execute("SELECT config FROM maps WHERE id = 'old'").fetchone()[0])
        stored["tsdf"]["truncation"] = 40.0  # more than 256 cells of 0.1 m: refused since
        stored["occupancy"]["occupied_thresh"] = 0.99  # past the clamp (p_max 0.97): refused since
        conn.execute("UPDATE maps SET config = ? WHERE id = 'old'", (json.dumps(stored),))
    return svc


def test_a_map_stored_before_todays_configuration_limits_is_read(tmp_path: Path, scans: list[Scan]) -> None:
    """A map stored before a configuration limit existed keeps loading in the service, with its
    configuration as it was (test_persistence.test_a_stored_configuration_past_todays_limits_still_loads),
    and `GET /maps/{id}` answers it. The client validated that configuration as a new one, and so
    raised for such a map "answered application/json, not a MapInfo ...: is it a fleetmap service,
    of this version?": an upgraded service's maps could no longer be read with the client."""
    svc = service_with_a_map_past_todays_limits(tmp_path, scans)
    with svc, FleetmapClient(svc.base_url, timeout=20.0) as fm:
        info = fm.get_map("old")
        assert info.config.tsdf.truncation == 40.0 and info.config.occupancy.occupied_thresh == 0.99
        assert info.stats.scans_integrated == 1
        assert fm.get_map_and_etag("old")[0] == info


@contextlib.contextmanager
def _answering(answer: dict[str, Any], etag: str | None = '"map-1"') -> Iterator[str]:
    """A real HTTP server on a free port answering every GET and PUT 200 with the JSON `answer` and
    `etag` (none for None), as a fleetmap service answers `GET` and `PUT /maps/{id}`; yields its URL."""

    class Answering(_FakeService):
        def _answer(self) -> None:
            self.read_body()
            self.reply(
                200, json.dumps(answer).encode(), "application/json", {} if etag is None else {"etag": etag}
            )

        do_GET = do_PUT = _answer

    with _serving(Answering) as url:
        yield url


def _map_info(config: MapConfig) -> dict[str, Any]:
    """The JSON of a `MapInfo` of map "m" with `config`, as `GET /maps/m` answers it."""
    stats = MapStats(scans_integrated=3, scans_rejected=0, robots={}, bounds=None, tiles=1, memory_bytes=1)
    info = MapInfo(
        id="m", config=config, resolution=config.resolution, tile_size=config.tile_size, stats=stats
    )
    return info.model_dump(mode="json")


def test_get_map_needs_no_etag() -> None:
    """`get_map` read the map through `get_map_and_etag`, which refuses an answer without the map's
    ETag (no conditional write can be made without it): a service older than conditional writes,
    or a proxy that drops the header, made `get_map` fail ("not a map with its ETag ... no ETag
    header"), though it returns no tag. Only `get_map_and_etag` needs one."""
    with _answering(_map_info(MapConfig()), etag=None) as url, FleetmapClient(url) as fm:
        assert fm.get_map("m").stats.scans_integrated == 3
        with pytest.raises(FleetmapError, match="no ETag header"):
            fm.get_map_and_etag("m")


def test_a_newer_services_map_configuration_is_read_without_its_new_fields() -> None:
    """Every answer's unknown fields are left out when read, so that an older client reads a newer
    service's answers (`fleetmap.api_models`), but a map's configuration refused them: one new
    setting of a newer service (a top-level field, or one in a section such as `occupancy`) made
    `get_map`, `create_map` and an upload's answer fail in every older client ("not a MapInfo ...
    (config.new_setting: Extra inputs are not permitted)"). They are now left out there too; a
    request's configuration still refuses them."""
    config = MapConfig(
        resolution=0.1, layers=("occupancy", "counts"), occupancy=OccupancyParams(preset="int8")
    )
    answer = _map_info(config)
    answer["config"]["new_setting"] = "on"
    answer["config"]["occupancy"]["new_parameter"] = 0.5
    answer["config"]["tsdf"]["new_parameter"] = [1, 2]
    answer["stats"]["new_count"] = 7
    with _answering(answer) as url, FleetmapClient(url) as fm:
        assert fm.get_map("m").config == config
        assert fm.get_map_and_etag("m") == (fm.get_map("m"), '"map-1"')
        assert fm.create_map("m", config).stats.scans_integrated == 3
    with pytest.raises(ValidationError, match="new_setting"):
        MapConfig.model_validate(answer["config"])
    with pytest.raises(ValidationError, match="new_parameter"):
        OccupancyParams.model_validate(answer["config"]["occupancy"])


def test_a_put_of_a_stored_maps_own_configuration_past_todays_limits_is_the_same_map(
    tmp_path: Path, scans: list[Scan]
) -> None:
    """`PUT /maps/{id}` with the configuration the map has is a 200, nothing changed (docs/api.md),
    which a provisioning script sends at every start. For a map stored before one of today's limits
    that was a 422, the configuration refused as a new one though it is the map's: the script
    failed after every upgrade, for a map the service keeps. Such a configuration for any other map
    (none there, or another configuration) is still refused with 422 and the reason."""
    svc = service_with_a_map_past_todays_limits(tmp_path, scans)
    with svc, httpx.Client(base_url=svc.base_url, timeout=20.0) as http:
        got = http.get("/maps/old")
        config, etag = got.json()["config"], got.headers["etag"]
        again = http.put("/maps/old", json=config)
        assert again.status_code == 200, again.text
        assert again.json()["config"] == config and again.headers["etag"] == etag
        assert again.json()["stats"]["scans_integrated"] == 1
        assert http.put("/maps/old", json=config, headers={"If-None-Match": "*"}).status_code == 412
        for map_id, body in [("new", config), ("old", {**config, "max_tiles": 100})]:
            refused = http.put(f"/maps/{map_id}", json=body)
            assert refused.status_code == 422, (map_id, refused.text)
            assert any("more than 256 cells" in e["msg"] for e in refused.json()["errors"]), refused.text
            locs = {tuple(e["loc"]) for e in refused.json()["errors"]}
            assert locs == {("body", "tsdf"), ("body", "occupancy")}, locs
        assert http.get("/maps/new").status_code == 404
        assert http.get("/maps/old").json()["config"] == config
