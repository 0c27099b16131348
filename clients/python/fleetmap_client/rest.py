"""A typed client of the fleetmap REST API, for programs that read (or feed) maps over HTTP.

    from fleetmap_client.rest import FleetmapClient, FleetmapError

    with FleetmapClient("http://127.0.0.1:8000") as fm:
        fm.create_map("warehouse", {"resolution": 0.05})
        fm.post_scan("warehouse", "robot-7", scan, seq=0)   # a Scan, ScanMessage or dict
        p = fm.cell("warehouse", 1.0, 2.0).probability
        probs = fm.cells("warehouse", [[1.0, 2.0], [3.0, 4.0]])["probability"]   # numpy arrays
        hits = fm.raycast("warehouse", (1.0, 2.0), angles, max_range=10.0)["range"]  # first obstacles
        grid = fm.region("warehouse", 0, 0, 10, 10, layer="probability")      # (ny, nx), row 0 = lowest y
        for event, data in fm.events("warehouse"):                             # live changes
            ...

Answers are parsed into the models of `fleetmap.api_models` (the same classes the server answers
with), array answers into NumPy arrays. Every error answer of the server raises `FleetmapError` with
its HTTP status and the server's `detail` sentence, and so does a redirect (which the client does
not follow: give it the address it points to); network failures raise httpx's own
`httpx.TransportError` (e.g. `httpx.ConnectError` when nothing listens). A service started with
API tokens answers 401 / 403 without the right one: pass `token=` (or set $FLEETMAP_TOKEN).
Map and robot ids are checked before any request (ValueError), because an id with a `/` would
address another resource. The endpoint reference is the OpenAPI spec (openapi/openapi.json).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import numbers
import operator
import os
import re
import secrets
import socket
import threading
import zipfile
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal, TypeVar

import httpx
import numpy as np
import yaml
from pydantic import BaseModel, ValidationError

from fleetmap.api_models import (
    MAX_POINTS,
    CellsResponse,
    CellValue,
    ErrorResponse,
    Health,
    MapInfo,
    MapList,
    MapSummary,
    RaycastResponse,
    RegionCleared,
    RegionLayer,
    RobotsDeltaEvent,
    RobotsEvent,
    ScanResult,
    Surface,
)
from fleetmap.auth import TOKEN_CHARACTERS
from fleetmap.cell_queries import (
    MAX_RAY_WALK,
    MAX_RAYS,
    Integer,
    Points,
    Real,
    UnknownCells,
    as_points,
    float_array,
    real_number,
)
from fleetmap.codec import encode_binary, encode_json
from fleetmap.config import ANSWERED_CONFIG, STORED_CONFIG, MapConfig
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING, ScanMessage, is_valid_id
from fleetmap.yaml_whitespace import YamlCppWhitespace

from .scan_arguments import checked_seq, checked_stamp


class _TextLoader(YamlCppWhitespace, yaml.BaseLoader):
    """PyYAML's BaseLoader (every value its text), reading tabs between tokens as map_server's
    yaml-cpp and the server do: a map.yaml with one was "not valid YAML" here, and never sent."""


def nav2_files_zip(yaml_path: str | os.PathLike[str]) -> bytes:
    """A zip of a nav2 map_server `map.yaml` and the image it names (relative to the YAML's folder
    unless absolute), as `PUT /maps/{id}/import` reads it: the image beside the YAML under its own
    file name, the YAML's `image` rewritten to that name when it named a folder too. ValueError for
    a file that is not YAML, a YAML without an `image` file name, or, to be rewritten, with a field
    given twice (the server refuses such a YAML); OSError if a file cannot be read."""
    yaml_path = Path(yaml_path)
    text = yaml_path.read_bytes()
    # Every value as its text (BaseLoader: only str, list, dict), as the server and map_server's
    # yaml-cpp read them: written out again from PyYAML's types, `origin: [010, ...]` became octal
    # 8, and map_server reads 10. Text that looks like a number is written quoted, which both read
    # as that number. The first document only, as map_server's `YAML::LoadFile` reads it.
    loader: _TextLoader | None = None
    try:
        # Made inside the `try`: it decodes the start of the file at once, and raises its
        # ReaderError there for bytes that are not UTF-8 (Latin-1) or for a control character.
        loader = _TextLoader(text)
        node = loader.get_node() if loader.check_node() else None
        doc = None if node is None else loader.construct_document(node)
    except (yaml.YAMLError, RecursionError) as exc:
        # PyYAML's own error (ParserError, ScannerError) is no ValueError: it came out of
        # `import_nav2` as an exception its contract does not name, with a traceback.
        raise ValueError(f"{yaml_path} is not valid YAML: {exc}") from None
    finally:
        if loader is not None:
            loader.dispose()
    if not isinstance(doc, dict) or not isinstance(doc.get("image"), str) or not doc["image"]:
        raise ValueError(f"{yaml_path} names no image file ('image')")
    image = doc["image"]
    image_path = yaml_path.parent / image  # an absolute `image` stays itself
    name = image_path.name
    if name != image:  # the server reads only an image beside the YAML in the zip
        # Written out again from `doc`, a field given twice would keep its last value only, and
        # the server, which refuses such a YAML (map_server takes the first), would never see it.
        repeated = _repeated_field(node)
        if repeated is not None:
            raise ValueError(f"{yaml_path} gives the field {repeated!r} twice: which one is meant?")
        text = yaml.safe_dump({**doc, "image": name}, sort_keys=False).encode()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(yaml_path.name if yaml_path.suffix in (".yaml", ".yml") else "map.yaml", text)
        zf.writestr(name, image_path.read_bytes())
    return buf.getvalue()


def _repeated_field(node: yaml.Node | None) -> str | None:
    """The first top-level field a composed YAML document gives twice, or None."""
    seen: set[str] = set()
    for key, _ in node.value if isinstance(node, yaml.MappingNode) else ():
        if isinstance(key, yaml.ScalarNode) and key.value in seen:
            return str(key.value)
        seen.add(key.value)
    return None


#: Seconds `events` waits before it resumes a lost stream (the server's `retry:`, 1000 ms), unless a
#: 503's Retry-After asks for longer.
RECONNECT_DELAY = 1.0

#: The answers on which `events` waits and resumes a stream it had open, as an EventSource (the web
#: viewer) does: the service stopping or at its limit of streams (503), and a reverse proxy in front
#: of a restarting service (502: nothing listens; 504: no answer in time; 503 of its own).
_RESUMED_STATUSES = frozenset({502, 503, 504})

#: The longest wait a `Retry-After` is read as, seconds (the web viewer's `MAX_RETRY_AFTER_MS`). The
#: service asks for 1 or 5 s; a longer one comes from something else answering (a proxy in front of
#: it), and may be absurd: `1e999` is an infinite float, which a wait cannot take (OverflowError).
MAX_RETRY_AFTER = 60.0

#: Seconds `events` waits for anything from an open stream before it takes the connection for dead
#: and resumes the stream: three of the service's keepalive periods (`: keepalive` after 15 s of
#: silence, `fleetmap serve --events-keepalive`). A connection that dies without a FIN or RST (a
#: peer's power cut, a NAT or a proxy dropping state: half-open TCP) otherwise blocks the reader
#: for ever, as nothing ever arrives and the OS never tells.
EVENTS_READ_TIMEOUT = 45.0

#: The environment variable `FleetmapClient` reads its API token from when given none.
TOKEN_ENV = "FLEETMAP_TOKEN"

#: How long `post_scan` waits for the answer by default, seconds. The service holds a scan's answer
#: until the scan is integrated and answers 503 itself after its own wait (10 s by default,
#: `ApiSettings.scan_timeout`): the client must wait longer than that, or a slow integration would
#: end in httpx's bare ReadTimeout instead of the server's 503 saying what happened.
SCAN_TIMEOUT = 15.0

#: Seconds an idle connection is kept for the next request. The service closes one idle for 5 s
#: (uvicorn's keep-alive), and a request it gets on a connection it closed fails unanswered
#: ("Server disconnected without sending a response"): with httpx's own 5 s, a request sent a little
#: under 5 s after the last answer met that close whenever the link took longer than the rest of the
#: 5 s (the answer's way here, the request's there). Letting go well before leaves a link up to 3 s
#: round trip; a new connection costs a loopback or LAN handshake.
KEEPALIVE_EXPIRY = 2.0
#: Connections the client opens at once, and keeps idle, at most (httpx's defaults), for its requests.
_LIMITS = httpx.Limits(max_connections=100, max_keepalive_connections=20, keepalive_expiry=KEEPALIVE_EXPIRY)
#: The event streams' connections (`events`): a pool of their own, each held for as long as its
#: stream is followed, without a limit here (the service bounds them: `--max-event-streams`). Taken
#: from `_LIMITS`' pool, 100 streams left the client's requests none: each waited its timeout, then
#: failed with a PoolTimeout that read as the service's fault. None kept idle: a stream that ended
#: is resumed after a wait, on a new connection.
_STREAM_LIMITS = httpx.Limits(max_connections=None, max_keepalive_connections=0)

#: Bytes `save_snapshot` reads from the answer at a time.
_TRANSFER_CHUNK = 1 << 20
#: How long the whole-map transfers (`download_snapshot`, `upload_snapshot`, `import_nav2`,
#: `export`) wait for their answer by default, seconds: the service reads, checks and stores, or
#: packs, every tile of the map first, seconds for a big one, and a bare ReadTimeout would leave
#: the caller guessing whether an upload took effect.
TRANSFER_TIMEOUT = 300.0

#: The content types of the answers the client returns as bytes (`_bytes_of`), with what they are.
_SNAPSHOT = ("application/zip", "a snapshot of a map")
_NAV2_ZIP = ("application/zip", "a nav2 map zip")
_PNG = ("image/png", "a PNG image")

#: A model of `fleetmap.api_models` an answer is read as (`_read`).
_Model = TypeVar("_Model", bound=BaseModel)

#: The layers `region` and `region_png` read (the API's `RegionLayer`).
Layer = RegionLayer
#: What `FleetmapClient.events` returns: a generator (so `.close()` ends the stream early) of
#: (event name, data) pairs.
EventStream = Generator[tuple[str, dict[str, Any]], None, None]


class FleetmapError(Exception):
    """An error answer of the service: `status` (HTTP status code), `detail` (the server's sentence
    saying what is wrong), `errors` (the individual validation problems, when the server listed
    them), `retry_after` (the seconds its `Retry-After` header asks a client to wait before trying
    again, on a 503 or 429, at most `MAX_RETRY_AFTER`; None when it sent none)."""

    def __init__(
        self,
        status: int,
        detail: str,
        errors: list[dict[str, Any]] | None = None,
        retry_after: float | None = None,
    ) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail
        self.errors = errors or []
        self.retry_after = retry_after

    def __reduce__(self) -> tuple[Any, ...]:
        # Made again from its own arguments: Exception's pickling calls the class with `args`, the
        # one sentence, which this signature refused (TypeError), so a FleetmapError raised in a
        # worker process (multiprocessing, ProcessPoolExecutor) broke the whole pool, and
        # `copy.copy` of one raised.
        return type(self), self._arguments(), self.__dict__

    def _arguments(self) -> tuple[Any, ...]:
        """The constructor's arguments that make this error again (`__reduce__`)."""
        return self.status, self.detail, self.errors, self.retry_after


class MapChanged(FleetmapError):
    """A conditional write (`if_match=`, `create_only=`) refused with 412: the map is not the one the
    caller read (replaced, deleted and made again, or deleted; or, with `create_only`, it exists).
    Nothing changed. `etag` is the map's current ETag (None when there is no map): read the map
    again (`get_map_and_etag`), decide again, and write with the new tag."""

    def __init__(
        self,
        status: int,
        detail: str,
        errors: list[dict[str, Any]] | None = None,
        retry_after: float | None = None,
        etag: str | None = None,
    ) -> None:
        super().__init__(status, detail, errors, retry_after)
        self.etag = etag

    def _arguments(self) -> tuple[Any, ...]:
        return (*super()._arguments(), self.etag)


def _conditions(if_match: str | None, create_only: bool = False) -> dict[str, str]:
    """The headers of a conditional write: `If-Match` (the map's ETag as read: only if the map is
    still that one), `If-None-Match: *` (`create_only`: only if there is no map of the id)."""
    headers: dict[str, str] = {}
    if if_match is not None:
        headers["If-Match"] = _etag("if_match", if_match)
    if create_only:
        headers["If-None-Match"] = "*"
    return headers


#: What a header value the client is given (an ETag) may hold: printable ASCII, spaces and tabs.
#: A line break would end the header (httpx refused it as it sent the request, with a
#: `LocalProtocolError`, a `TransportError` read as a network failure), and httpx encodes header
#: values as ASCII (a bare UnicodeEncodeError otherwise).
_HEADER_VALUE = re.compile(r"[\x20-\x7e\t]+")


def _etag(name: str, value: str) -> str:
    """`value`, the argument `name` (an entity tag, as a response's `ETag` gave it), without the
    whitespace around it (a tag read from a file ends with a line end); ValueError before any
    request unless it is a non-empty string a header carries (`_HEADER_VALUE`)."""
    tag = value.strip() if isinstance(value, str) else ""
    if not _HEADER_VALUE.fullmatch(tag):
        raise ValueError(f"{name} must be an ETag as the service sent it, not {value!r}")
    return tag


def _authorization(token: str | None) -> dict[str, str]:
    """The `Authorization` header that carries the API token `token` (none for None or a blank one),
    its surrounding whitespace dropped as the service drops it: a token read whole from its file ends
    with a line end, one from an env file written on Windows with a carriage return. ValueError,
    naming no token, for one holding a character no header carries (tokens are printable ASCII
    without spaces, `fleetmap.auth.TOKEN_CHARACTERS`): httpx refused it only at each request, with
    the token itself in its message ("Illegal header value b'Bearer ...'"), for any log to keep."""
    token = (token or "").strip()
    if not token:
        return {}
    if not TOKEN_CHARACTERS.match(token):
        raise ValueError(
            f"the API token (token= or ${TOKEN_ENV}) holds a character no HTTP header carries: a "
            "token is printable ASCII characters without spaces"
        )
    return {"Authorization": f"Bearer {token}"}


def _service_url(base_url: str) -> str:
    """`base_url`, the service's address, as the client sends its requests there: without the
    whitespace around it (an address read from a file or the environment), a fragment (the viewer's
    link, `/#map=m`) or a trailing `/`. ValueError for one that is no http:// or https:// URL with a
    host, or that has a query: httpx took `localhost:8000` for a URL of the scheme `localhost`, and
    `http:/127.0.0.1:8000` for one without a host, and every request then failed with a
    `TransportError` ("unsupported protocol", "Name or service not known"), which a program takes
    for the service being down (and may retry for ever); a query went before every request's path
    (`/?map=m/healthz`). So was a port no TCP connection has (`:80000`, a typo of `:8000`; 0; -1),
    which httpx takes as well: "Connection refused" at every request."""
    text = str(base_url).strip().partition("#")[0]
    try:
        url = httpx.URL(text)
    except httpx.InvalidURL:
        url = None
    if (
        url is None
        or url.scheme not in ("http", "https")
        or not url.host
        or "?" in text
        or not (url.port is None or 1 <= url.port <= 65535)
    ):
        raise ValueError(
            f"base_url must be the service's http:// or https:// address, such as http://127.0.0.1:8000, "
            f"without a query, its port from 1 to 65535 if given; got {_shown_url(str(base_url))!r}"
        )
    return text.rstrip("/")


def _positive_seconds(name: str, value: object) -> float:
    """`value`, the argument `name`, as seconds: ValueError unless it is a positive number of at
    most `threading.TIMEOUT_MAX` (292 years on Linux), the longest wait of the platform: a longer
    one (1e10, meant as "for ever") made every request raise OverflowError ("timestamp out of range
    for platform time_t"), as the socket's timeout took it."""
    seconds = float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else math.nan
    if not 0 < seconds <= threading.TIMEOUT_MAX:  # NaN (and what is no number) too
        raise ValueError(
            f"{name} must be a positive number of seconds, at most {threading.TIMEOUT_MAX:.0f}, not {value!r}"
        )
    return seconds


def _tile_index(name: str, value: Integer) -> int:
    """`tile`'s `z`, `x` or `y` as an int; TypeError for anything but an integer (a NumPy one too).
    Cut to an int, a float named another tile: -0.5 (a point left of tile 0, divided by the tile
    size) asked for tile 0, not -1, and 0.9 for tile 0, with no word."""
    if isinstance(value, bool):
        raise TypeError(f"tile {name} must be an integer, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise TypeError(f"tile {name} must be an integer, got {value!r}") from None


def _check_id(name: str, value: str) -> str:
    if not isinstance(value, str) or not is_valid_id(value):
        raise ValueError(f"{name} {value!r} is invalid: use 1 to 64 characters from A-Z a-z 0-9 _ -")
    return value


def _check_since(since: Integer | None) -> int | None:
    """`events`' `since`: a change version (an integer >= 0) or None. Anything else, sent as
    `Last-Event-ID`, would be read by the server as no version at all, and the stream would start
    from now instead of resuming: a silent gap in what the program sees."""
    if since is None:
        return None
    try:
        version = operator.index(since) if not isinstance(since, bool) else -1
    except TypeError:
        version = -1
    if version < 0:
        raise ValueError(f"since must be a change version (an integer >= 0) or None, got {since!r}")
    return version


def _bounds(xmin: Real | None, ymin: Real | None, xmax: Real | None, ymax: Real | None) -> dict[str, float]:
    """Query parameters of a window: all four bounds, or none (the map's observed extent).
    ValueError for a bound that is not a finite number, before any request, as `cell` refuses a
    point (float() of an int past float's range raised OverflowError, no ValueError)."""
    if xmin is None or ymin is None or xmax is None or ymax is None:
        if any(b is not None for b in (xmin, ymin, xmax, ymax)):
            raise ValueError("give all of xmin, ymin, xmax and ymax, or none of them (the observed extent)")
        return {}
    return {"xmin": _finite(xmin), "ymin": _finite(ymin), "xmax": _finite(xmax), "ymax": _finite(ymax)}


def _read_chunks(fp: IO[bytes]) -> Iterator[bytes]:
    """What is left of the binary file `fp`, _TRANSFER_CHUNK bytes at a time."""
    while chunk := fp.read(_TRANSFER_CHUNK):
        yield chunk


class FleetmapClient:
    """A synchronous client of one fleetmap service at `base_url` (e.g. "http://127.0.0.1:8000"; its
    http:// or https:// address, ValueError here for anything else, see `_service_url`).

    `timeout` (seconds) applies to every request except these: `post_scan` waits for its answer up
    to `scan_timeout` (default `SCAN_TIMEOUT`, 15 s, or `timeout` if longer), because the server
    answers only once the scan is integrated; the whole-map transfers (`download_snapshot`,
    `upload_snapshot`, `import_nav2`, `export`) up to `transfer_timeout` (default
    `TRANSFER_TIMEOUT`, 300 s, or `timeout` if longer), since a big map takes the service seconds
    to store or pack; and the event stream's reads wait up to `events_read_timeout` (default
    `EVENTS_READ_TIMEOUT`, 45 s: three of the service's keepalive periods) for anything from the
    server before the stream is taken for dead and resumed (`events`); give a server run with a
    longer `--events-keepalive` a longer one (None: wait for ever). Each timeout is a positive number
    of seconds, at most `threading.TIMEOUT_MAX` (ValueError here otherwise). `token`: an API token of the
    service (`fleetmap serve --auth-tokens`), sent as `Authorization: Bearer <token>`; None takes it
    from the environment variable `FLEETMAP_TOKEN` if set (a service without tokens ignores it);
    surrounding whitespace (a line end) is dropped, and a token with a character no header carries
    is a ValueError here, naming no token, as is a token with an address that has a user and
    password (`http://user:password@host`: httpx sends those in the Authorization header, and
    dropped the token).
    Thread-safe (one httpx.Client for the requests, at most 100 connections at once, and one for
    the event streams, a connection each; `post_scan` sends one robot's scans one at a time, in
    call order, so threads sharing a robot's automatic seqs lose none); use as a context manager or
    call `close()`.
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        timeout: Real = 10.0,
        token: str | None = None,
        scan_timeout: Real = SCAN_TIMEOUT,
        transfer_timeout: Real = TRANSFER_TIMEOUT,
        events_read_timeout: Real | None = EVENTS_READ_TIMEOUT,
    ) -> None:
        # Checked here: a timeout of 0 failed each request as a ConnectError "Operation now in
        # progress" naming the service, as if it were down; a negative one, or NaN, at each request;
        # None (httpx's "no limit"), as a TypeError of `max` here.
        timeout = _positive_seconds("timeout", timeout)
        self.events_read_timeout = (
            None
            if events_read_timeout is None
            else _positive_seconds("events_read_timeout", events_read_timeout)
        )
        self.base_url = _service_url(base_url)
        self.timeout = timeout
        self.scan_timeout = max(_positive_seconds("scan_timeout", scan_timeout), timeout)
        self.transfer_timeout = max(_positive_seconds("transfer_timeout", transfer_timeout), timeout)
        headers = _authorization(token if token is not None else os.environ.get(TOKEN_ENV))
        if headers and httpx.URL(self.base_url).userinfo:
            # httpx puts the address's user and password in the Authorization header (Basic auth)
            # over the client's own: the token was dropped without a word, and the service said 401.
            raise ValueError(
                f"the address ({_shown_url(self.base_url)}) has a user and password, which httpx "
                "sends as Basic auth in the Authorization header, and an API token is given (token= "
                f"or ${TOKEN_ENV}), which needs that header too: give one of them"
            )
        self._http = httpx.Client(base_url=self.base_url, timeout=timeout, headers=headers, limits=_LIMITS)
        #: The event streams' connections (`_STREAM_LIMITS`).
        self._stream_http = httpx.Client(
            base_url=self.base_url, timeout=timeout, headers=headers, limits=_STREAM_LIMITS
        )
        #: Next automatic seq per (map_id, robot_id) for `post_scan` of a `Scan` without a seq.
        self._next_seq: dict[tuple[str, str], int] = {}
        #: Per (map_id, robot_id): held by `post_scan` while it sends one of that robot's scans.
        self._robot_locks: dict[tuple[str, str], threading.Lock] = {}
        self._robot_locks_lock = threading.Lock()
        #: The event streams being read (`events`), which `close` ends; guarded by `_streams_lock`.
        self._streams: set[httpx.Response] = set()
        self._streams_lock = threading.Lock()
        #: Set by `close`: the streams being read, or waiting to be resumed, end (`_events`).
        self._closed = threading.Event()

    # -- plumbing ----------------------------------------------------------------------------------

    def _request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        try:
            # Streamed, then read here (what `httpx.Client.request` does) so that a body its
            # Content-Encoding does not decode is refused with its answer's status (`_decoding`).
            with self._http.stream(method, url, **kwargs) as response, _decoding(response):
                response.read()
        except httpx.TransportError as exc:
            raise _naming_the_service(exc, self.base_url) from exc
        _raise_for_error(response)
        return response

    def _transfer(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        """`_request` for a whole-map transfer: its answer may take up to `transfer_timeout`."""
        timeout = httpx.Timeout(self.timeout, read=self.transfer_timeout)
        return self._request(method, url, timeout=timeout, **kwargs)

    def close(self) -> None:
        """Close the connection pools, and end the event streams being read (`events`, in other
        threads too: their iteration stops at once). Idempotent; a request afterwards raises
        RuntimeError."""
        with self._streams_lock:
            self._closed.set()
            streams = list(self._streams)
        # Closing the pool does not wake a thread blocked reading a stream: it read on until the
        # server's next keepalive (some 15 s), then failed on the closed pool with RuntimeError.
        # Shut down, its socket reads as ended now.
        for response in streams:
            _shut_down(response)
        self._http.close()
        self._stream_http.close()

    def __enter__(self) -> FleetmapClient:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FleetmapClient({_shown_url(self.base_url)!r})"

    # -- service -----------------------------------------------------------------------------------

    def health(self) -> Health:
        """`GET /healthz`: maps held, robots online, ingest queue depth, Zenoh status."""
        return _read(Health, self._request("GET", "/healthz"))

    def metrics(self) -> str:
        """`GET /metrics`: the Prometheus text exposition."""
        response = self._request("GET", "/metrics")
        _raise_unless_media_type(response, "text/plain", "Prometheus metrics")
        return response.text

    # -- maps --------------------------------------------------------------------------------------

    def list_maps(self) -> list[MapSummary]:
        """`GET /maps`: every map with its resolution, layers and counters, sorted by id."""
        return _read(MapList, self._request("GET", "/maps")).maps

    def create_map(
        self,
        map_id: str,
        config: MapConfig | Mapping[str, Any] | None = None,
        *,
        create_only: bool = False,
        if_match: str | None = None,
    ) -> MapInfo:
        """`PUT /maps/{map_id}`: create a map with `config` (None: the server's default). Creating a
        map that exists with the same configuration is a no-op; with a different one it raises
        `FleetmapError` 409. A bad configuration raises 422 with the server's reason, a `config` of
        another type (a JSON text) TypeError before any request. Returns once
        the server has stored the map (503: created, but the server could not store it).
        `create_only`: raise `MapChanged` (412) if the map exists at all, even with this
        configuration (`If-None-Match: *`); `if_match`: only if the map exists with that ETag
        (`get_map_and_etag`), else `MapChanged`."""
        _check_id("map_id", map_id)
        headers = _conditions(if_match, create_only)
        if config is None:
            kwargs: dict[str, Any] = {}
        elif isinstance(config, MapConfig):
            kwargs = {"content": config.model_dump_json()}
            headers["content-type"] = JSON_ENCODING
        elif isinstance(config, Mapping):
            kwargs = {"content": _json(dict(config))}
            headers["content-type"] = JSON_ENCODING
        else:
            # As the engine's GridMap refuses it: dict() of a configuration's JSON text (read from a
            # file) said "dictionary update sequence element #0 has length 1; 2 is required".
            text = " (a JSON text: json.loads it first)" if isinstance(config, str | bytes) else ""
            raise TypeError(
                f"config must be a MapConfig, a dict of its fields or None, not {type(config).__name__}{text}"
            )
        response = self._request("PUT", f"/maps/{map_id}", headers=headers, **kwargs)
        return _read(MapInfo, response)

    def get_map(self, map_id: str) -> MapInfo:
        """`GET /maps/{map_id}`: configuration and statistics (per-robot counters, bounds, tiles).
        Needs no ETag in the answer (a service older than conditional writes, a proxy that drops
        it): only `get_map_and_etag` does."""
        _check_id("map_id", map_id)
        return _read(MapInfo, self._request("GET", f"/maps/{map_id}"))

    def get_map_and_etag(self, map_id: str) -> tuple[MapInfo, str]:
        """`get_map`, and the map's ETag: pass it as `if_match=` to `delete_map`, `upload_snapshot`,
        `import_nav2` or `create_map` to have the write refused (`MapChanged`, nothing changed) if
        the map was replaced, or deleted and made again, since it was read. The tag names the map's
        incarnation and configuration, not its cells: scans do not change it (nor does a restart
        keep it: after one, read it again)."""
        _check_id("map_id", map_id)
        response = self._request("GET", f"/maps/{map_id}")
        etag = response.headers.get("ETag")
        if etag is None:  # a proxy that drops it: without it no conditional write can be made
            raise _not_fleetmap(response, "a map with its ETag", "no ETag header")
        return _read(MapInfo, response), etag

    def delete_map(self, map_id: str, *, if_match: str | None = None) -> None:
        """`DELETE /maps/{map_id}`, returning once the server has stored the deletion; `FleetmapError`
        404 if there is no such map, 503 if it was removed but the server could not store that.
        `if_match`: delete only the map of that ETag (`get_map_and_etag`); `MapChanged` (412, the
        map untouched) if the map is another one by now (no map at all is still the 404; a retry of
        a 503 whose deletion is still being stored is a `MapChanged`: the first attempt removed
        it)."""
        _check_id("map_id", map_id)
        response = self._request("DELETE", f"/maps/{map_id}", headers=_conditions(if_match))
        if response.status_code != 204:  # another web server's page: no map was deleted
            status = f"status {response.status_code}"
            raise _not_fleetmap(response, "an empty answer (204 No Content)", status)

    def download_snapshot(self, map_id: str) -> bytes:
        """`GET /maps/{map_id}/snapshot`: the whole map (configuration and every tile of every layer)
        as one zip file, taken between two scans; `upload_snapshot` restores it here or elsewhere.
        For a big map, `save_snapshot` writes it to a file instead of holding it in memory."""
        _check_id("map_id", map_id)
        return _bytes_of(self._transfer("GET", f"/maps/{map_id}/snapshot"), *_SNAPSHOT)

    def save_snapshot(self, map_id: str, path: str | os.PathLike[str]) -> int:
        """`download_snapshot` written to the file `path` as it arrives, never held in memory whole
        (a big map's file takes gigabytes); returns its size in bytes. It goes to a `.part` file
        beside `path` first (`<name>.<random>.part`, its own for each call), renamed to `path` once
        whole and on disk (fsync): an error (`FleetmapError`, a dropped connection, an `OSError` of
        the rename: `path` a folder, say) leaves no file, and an earlier one at `path` as it was; a
        power cut leaves the earlier file or the whole new one; saves to one `path` at once (threads,
        an overlapping backup job) each leave a whole file there, the last one renamed."""
        _check_id("map_id", map_id)
        target = Path(path)
        # Its own: with one `path.part` for every call, two saves to one path at once wrote into one
        # file (each truncating it at its start), one renamed it, possibly unfinished, and returned
        # the size it then had (0, say), and the other failed to rename what was gone.
        part = target.with_name(f"{target.name}.{secrets.token_hex(8)}.part")
        timeout = httpx.Timeout(self.timeout, read=self.transfer_timeout)
        size = 0
        try:
            with (
                self._http.stream("GET", f"/maps/{map_id}/snapshot", timeout=timeout) as response,
                _decoding(response),
            ):
                if _failed(response):
                    response.read()
                    _raise_for_error(response)
                _raise_unless_media_type(response, *_SNAPSHOT)  # before a file is made for it
                with open(part, "xb") as fp:
                    for chunk in response.iter_bytes(_TRANSFER_CHUNK):
                        size += fp.write(chunk)
                    # On disk before it takes the name: renamed while its data was still only in
                    # the page cache, a power cut (or a kernel crash) soon after could leave `path`
                    # empty or cut short on most file systems, the earlier backup there gone too.
                    fp.flush()
                    os.fsync(fp.fileno())
        except BaseException as exc:
            part.unlink(missing_ok=True)
            if isinstance(exc, httpx.TransportError):
                raise _naming_the_service(exc, self.base_url) from exc
            raise
        try:
            os.replace(part, target)
        except OSError:
            # (`path` a folder, or a name this user may not replace): the whole download, gigabytes
            # for a big map, was left behind as `.part` beside it.
            part.unlink(missing_ok=True)
            raise
        _sync_directory(target.parent)  # the rename itself
        return size

    def upload_snapshot(
        self,
        map_id: str,
        snapshot: bytes | bytearray | memoryview | str | os.PathLike[str] | IO[bytes],
        *,
        if_match: str | None = None,
        create_only: bool = False,
    ) -> MapInfo:
        """`PUT /maps/{map_id}/snapshot`: install a `download_snapshot` file as map `map_id`, replacing
        any map of that id, and return it once stored. `snapshot`: the file's bytes (or a bytearray or
        memoryview of them), its path (a
        `save_snapshot` file: sent from the file as it is read, never held in memory whole), or a
        binary file open for reading (sent from where it stands to its end; a pipe too); anything
        else is a TypeError before any request.
        `FleetmapError` 422 (or 413) for a file that is not a valid snapshot, naming the part at
        fault; nothing changes then. `if_match`: replace only the map of that ETag
        (`get_map_and_etag`), `create_only`: only if there is no map of the id; else `MapChanged`
        (412), nothing changed."""
        _check_id("map_id", map_id)
        headers = {"content-type": "application/zip", **_conditions(if_match, create_only)}
        with contextlib.ExitStack() as stack:
            body: bytes | IO[bytes] | Iterator[bytes]
            if isinstance(snapshot, (str, os.PathLike)):
                body = stack.enter_context(open(snapshot, "rb"))  # noqa: SIM115 - closed by the stack
            elif isinstance(snapshot, (bytes, bytearray, memoryview)):
                # As bytes: httpx takes a bytearray or memoryview for an iterable of chunks, and
                # failed on its first byte ("object of type 'int' has no len()").
                body = bytes(snapshot)
            elif callable(getattr(snapshot, "read", None)):
                # From where the caller's file stands, to its end, chunked: httpx would declare the
                # whole file's size (`os.fstat`) whatever its position, and 0 for a pipe, then fail
                # sending more or less than that ("Too much data for declared Content-Length").
                body = _read_chunks(snapshot)
            else:
                # Taken for a file, it failed as its body was sent ("'NoneType' object has no
                # attribute 'read'"), the upload cut off at the service.
                raise TypeError(
                    "snapshot must be the snapshot's bytes, the path of its file or a binary file open "
                    f"for reading, not {type(snapshot).__name__}"
                )
            response = self._transfer("PUT", f"/maps/{map_id}/snapshot", content=body, headers=headers)
        return _read(MapInfo, response)

    def import_nav2(
        self,
        map_id: str,
        source: str | os.PathLike[str] | bytes | bytearray | memoryview,
        snap_origin: bool = False,
        *,
        if_match: str | None = None,
        create_only: bool = False,
    ) -> MapInfo:
        """`PUT /maps/{map_id}/import?format=ros`: install a ROS nav2 map_server map as map `map_id`,
        replacing any map of that id (keeping its configuration), and return it once stored.

        `source`: the path of a `map.yaml` (it is zipped here with the image it names, which is
        read relative to the YAML's folder as map_server does), or a zip holding one YAML file and
        its image (what `GET /maps/{id}/export?format=ros` gives): its bytes (a bytearray or
        memoryview too), or the path of a file
        whose name ends in `.zip`, sent as it is. ValueError for a YAML file that is not YAML or
        names no image (nothing is sent). `FleetmapError` 422
        naming the field or image at fault (a rotated map, an origin off the cell grid, a colour
        image, ...), 413 past a size limit; nothing changes then. OSError if a file cannot be read.
        `snap_origin`: an origin off the map's cell grid (as SLAM tools and map_saver write them) is
        moved to the nearest cell edge, by at most half a cell, instead of refused. `if_match` /
        `create_only` as for `upload_snapshot`."""
        _check_id("map_id", map_id)
        headers = {"content-type": "application/zip", **_conditions(if_match, create_only)}
        if isinstance(source, (bytes, bytearray, memoryview)):  # (a bytearray was taken for a path)
            body = bytes(source)
        elif Path(source).suffix.lower() == ".zip":  # an export saved to a file: not a YAML to zip
            body = Path(source).read_bytes()
        else:
            body = nav2_files_zip(source)
        response = self._transfer(
            "PUT", f"/maps/{map_id}/import", params={"format": "ros", "snap_origin": snap_origin},
            content=body,
            headers=headers,
        )  # fmt: skip
        return _read(MapInfo, response)

    # -- scans -------------------------------------------------------------------------------------

    def post_scan(
        self,
        map_id: str,
        robot_id: str,
        scan: Scan | ScanMessage | Mapping[str, Any],
        seq: Integer | None = None,
        stamp: Real | None = None,
        encoding: Literal["json", "binary"] = "json",
    ) -> ScanResult:
        """`POST /maps/{map_id}/scans?robot_id=...`: integrate one scan and wait until it is in the map.

        `scan` is an engine `Scan` (sent with `seq`, default an automatic per-robot counter from 0 in
        this client, and `stamp`, default 0), a `ScanMessage`, or a dict in the JSON scan format
        (`seq` / `stamp`, when given, override theirs). `encoding` chooses the body for a `Scan`
        (JSON or the binary encoding of docs/protocol.md). Returns the `ScanResult` (status
        "integrated", or "duplicate" when the seq was not new). Raises TypeError before any request
        for a `scan` of another type, a `seq` that is not an integer or a `stamp` that is not a
        number, ValueError for a `seq` outside [0, 2**63) or a stamp that is not finite (as
        `ScanPublisher.publish`), `FleetmapError` 422 for an invalid scan, 404 for an unknown
        map when the server does not create maps on first use, 503 when the server could not
        integrate it in time (it still will) or its queue is full.
        Waits for the answer up to `scan_timeout` (see the class).

        The automatic counter moves past every seq sent that the map may hold: after an answer,
        and after a 503 or a lost answer (the scan may still be integrated: under its seq the next
        scan would be a duplicate; the service counts the skipped seq as `lost` if it was not). It
        stays after a refusal (4xx, 507) or a request that never left, whose seq is still free.
        """
        _check_id("map_id", map_id)
        _check_id("robot_id", robot_id)
        if encoding not in ("json", "binary"):
            raise ValueError(f"encoding must be 'json' or 'binary', got {encoding!r}")
        if not isinstance(scan, Scan | ScanMessage | Mapping):  # dict("text") said "update sequence element"
            raise TypeError(
                f"post_scan takes a fleetmap Scan, a ScanMessage or a dict, not {type(scan).__name__}"
            )
        # Checked here as the publisher checks them: a NumPy integer seq (from `np.arange`) failed
        # in the JSON encoder, and, sent in binary, became the automatic counter, which then failed
        # every later JSON scan of the robot; a float or negative one was sent, and its 422 counted
        # against the robot as a rejected scan.
        seq = None if seq is None else checked_seq(seq)
        stamp = None if stamp is None else checked_stamp(stamp)
        key = (map_id, robot_id)
        # One robot's scans are sent one at a time, in call order, each with its seq: two threads
        # that took seqs 0 and 1 could otherwise both take 0 (one ignored as a duplicate), or send 1
        # first (then 0 is a duplicate). The service integrates one robot's scans in order anyway.
        with self._robot_lock(key):
            if isinstance(scan, Scan) and seq is None:
                seq = self._next_seq.get(key, 0)
            body, content_type, sent_seq = _scan_body(scan, seq, stamp, encoding)
            try:
                response = self._request(
                    "POST", f"/maps/{map_id}/scans", params={"robot_id": robot_id}, content=body,
                    headers={"content-type": content_type},
                    timeout=httpx.Timeout(self.timeout, read=self.scan_timeout),
                )  # fmt: skip
            except BaseException as exc:
                # A scan the service may still integrate (a 503 "not integrated within 10 s, it will
                # be", an answer lost on the way) has used its seq: the next automatic scan under it
                # would be ignored as a duplicate. Skipping a seq costs only a `lost` count.
                if sent_seq is not None and not _scan_not_taken(exc):
                    self._next_seq[key] = sent_seq + 1
                raise
            if sent_seq is not None:
                self._next_seq[key] = sent_seq + 1
        return _read(ScanResult, response)

    def _robot_lock(self, key: tuple[str, str]) -> threading.Lock:
        """The lock `post_scan` holds while it sends a scan of robot `key` (map_id, robot_id)."""
        with self._robot_locks_lock:
            return self._robot_locks.setdefault(key, threading.Lock())

    # -- queries -----------------------------------------------------------------------------------

    def cell(self, map_id: str, x: Real, y: Real) -> CellValue:
        """`GET /maps/{map_id}/cell`: every layer's value in the cell containing the map point (x, y)."""
        _check_id("map_id", map_id)
        response = self._request("GET", f"/maps/{map_id}/cell", params={"x": _finite(x), "y": _finite(y)})
        return _read(CellValue, response)

    def cells(self, map_id: str, points: Points) -> dict[str, np.ndarray]:
        """`POST /maps/{map_id}/cells`: every layer at many map points at once.

        `points` is (n, 2) x, y in metres (one pair alone is one point; ValueError for another shape
        or a non-finite coordinate, before any request). Returns one NumPy array per field, one
        entry per point in order: `i`, `j` (int64 cell indices), `known` (bool), and for the layers
        the map keeps: `log_odds` (float64, NaN if unknown), `probability` (float64, 0.5 if
        unknown), `state` (str: "unknown" / "free" / "occupied"), `hits`, `misses` (int64), `tsdf`
        (float64, NaN if unknown), `tsdf_weight` (float64). Fields of layers the map does not keep
        are absent.

        Any number of points: past the service's limit of `MAX_POINTS` (100 000) a request, they
        are asked for in several requests, each read at its own moment (scans may land between
        them); `FleetmapError` 409 if the map was replaced meanwhile by one keeping other layers.
        """
        _check_id("map_id", map_id)
        pts = as_points(points)  # ValueError for another shape than (n, 2) or a non-finite value
        # The service answers at most MAX_POINTS points a request (413 past it): more go in several.
        return _in_parts(pts, MAX_POINTS, lambda chunk: self._cells(map_id, chunk), map_id, "points")

    def _cells(self, map_id: str, pts: np.ndarray) -> dict[str, np.ndarray]:
        """One `POST /maps/{map_id}/cells` of at most MAX_POINTS checked points, as `cells` answers."""
        response = self._request("POST", f"/maps/{map_id}/cells", json={"points": pts.tolist()})
        parsed = _read(CellsResponse, response)
        out: dict[str, np.ndarray] = {
            "i": np.array(parsed.i, dtype=np.int64),
            "j": np.array(parsed.j, dtype=np.int64),
            "known": np.array(parsed.known, dtype=bool),
        }
        floats = {"log_odds": parsed.log_odds, "probability": parsed.probability, "tsdf": parsed.tsdf,
                  "tsdf_weight": parsed.tsdf_weight}  # fmt: skip
        for name, values in floats.items():
            if values is not None:
                out[name] = np.array([math.nan if v is None else v for v in values], dtype=np.float64)
        for name, counts in (("hits", parsed.hits), ("misses", parsed.misses)):
            if counts is not None:
                out[name] = np.array(counts, dtype=np.int64)
        if parsed.state is not None:
            out["state"] = np.array(parsed.state, dtype=str)
        return out

    def raycast(
        self,
        map_id: str,
        origin: Sequence[float] | Sequence[Sequence[float]] | np.ndarray,
        angles: Real | Sequence[float] | np.ndarray,
        max_range: Real,
        unknown: UnknownCells = "stop",
    ) -> dict[str, np.ndarray]:
        """`POST /maps/{map_id}/raycast`: where rays from `origin` first meet an obstacle (OctoMap's
        castRay; the server runs `GridMap.cast_rays`).

        `origin` is (x, y) in metres, where every ray starts, or one (x, y) per ray (shape (n, 2)
        for n angles: rays from many poses at once, sent as `origins`), `angles` the rays' map-frame
        directions in radians (one number alone is one ray), `max_range` metres. A ray stops at the
        first occupied cell, or with `unknown="stop"` (the default) at the first never-observed one.
        Returns one NumPy array per field, one entry per angle in order: `status` (str: "occupied",
        "unknown", "max_range"), `range` (float64, metres to where the ray enters that cell: 0 for
        the origin's own cell, `max_range` when nothing stopped it), `x`, `y` (float64, that point),
        `i`, `j` (int64, the cell). ValueError for a non-finite or malformed argument (angles of more
        than one dimension among them, as the engine refuses them) or a `max_range` that is not
        positive, before any request.

        Any number of rays: past what the service casts in one request (`MAX_RAYS`, 10 000 rays,
        and `MAX_RAY_WALK`, 2**24 cells of rays x `max_range`), they are cast in several requests,
        in order, each at its own moment (scans may land between them); for the second limit the
        client reads the map's resolution first (one `GET /maps/{map_id}`), only when the rays
        might pass it. A `max_range` over 20 000 cells, a limit of each ray, answers 413 as
        `FleetmapError`: cast shorter rays. No angles at all answer empty arrays, as the engine
        does, without a request (the service casts 1 to 10 000 rays a request).
        """
        _check_id("map_id", map_id)
        # What is no numbers (a generator of angles, a dict, ragged rows) was NumPy's TypeError, or
        # its ValueError, naming no argument: a ValueError naming it, as the engine raises.
        try:
            starts = float_array(origin)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"origin must be an (x, y) pair of numbers, or one per angle: {exc}") from None
        if starts.shape != (2,) and not (starts.ndim == 2 and starts.shape[1] == 2):
            raise ValueError(f"origin must be an (x, y) pair, or one per angle, not {origin!r}")
        try:
            rays = float_array(angles)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"angles must be numbers (radians), one or a list or array: {exc}") from None
        # Refused as the engine refuses it: flattened, a (2, 3) array was cast as 6 rays, paired with
        # 6 origins in an order the caller never chose.
        if rays.ndim > 1:
            raise ValueError(f"angles must be a number or a one-dimensional sequence; got shape {rays.shape}")
        rays = rays.reshape(-1)
        if not np.isfinite(rays).all():
            raise ValueError("angles must be finite numbers (radians)")
        if starts.ndim == 2 and len(starts) != len(rays):
            raise ValueError(f"{len(starts)} origins for {len(rays)} angles: give one, or one per angle")
        if not np.isfinite(starts).all():
            raise ValueError(f"coordinates must be finite, got origin {origin!r}")
        max_range = _finite(max_range)
        if max_range <= 0:
            raise ValueError(f"max_range must be a positive number of metres, got {max_range!r}")
        if unknown not in ("stop", "pass"):
            raise ValueError(f"unknown must be 'stop' or 'pass', not {unknown!r}")
        if len(rays) == 0:
            # The engine answers no rays with empty arrays; the service casts 1 to MAX_RAYS a request
            # and refuses none (422), which a caller casting a filtered set of rays would meet.
            return _no_rays()
        per_request = MAX_RAYS
        # The service walks at most MAX_RAY_WALK cells a request, rays x max_range in cells, and the
        # client knows the cells only from the map's resolution: read it only when the rays could
        # pass the limit at the finest resolution a map may have (a 360-ray scan of 10 m never does).
        if len(rays) * max_range / _MIN_RESOLUTION > MAX_RAY_WALK:
            cells = max_range / self.get_map(map_id).resolution
            per_request = max(1, min(MAX_RAYS, math.floor(MAX_RAY_WALK / cells)))

        def cast(part: np.ndarray) -> dict[str, np.ndarray]:
            where = {"origin": starts.tolist()} if starts.ndim == 1 else {"origins": starts[part].tolist()}
            body = {**where, "angles": rays[part].tolist(), "max_range": max_range, "unknown": unknown}
            return self._raycast(map_id, body)

        return _in_parts(np.arange(len(rays)), per_request, cast, map_id, "rays")

    def _raycast(self, map_id: str, body: dict[str, Any]) -> dict[str, np.ndarray]:
        """One `POST /maps/{map_id}/raycast` of `body`, as `raycast` answers."""
        response = self._request("POST", f"/maps/{map_id}/raycast", json=body)
        parsed = _read(RaycastResponse, response)
        return {
            "status": np.array(parsed.status, dtype=str),
            "range": np.array(parsed.range, dtype=np.float64),
            "x": np.array(parsed.x, dtype=np.float64),
            "y": np.array(parsed.y, dtype=np.float64),
            "i": np.array(parsed.i, dtype=np.int64),
            "j": np.array(parsed.j, dtype=np.int64),
        }

    def region(
        self,
        map_id: str,
        xmin: Real | None = None,
        ymin: Real | None = None,
        xmax: Real | None = None,
        ymax: Real | None = None,
        layer: Layer = "probability",
    ) -> np.ndarray:
        """`GET /maps/{map_id}/region?format=npy`: a dense window of one layer.

        The cells with index in [floor(xmin/res), floor(xmax/res)) x [floor(ymin/res), floor(ymax/res)),
        a bound within a billionth of a cell, or a nanometre, of a cell edge being that edge (0.15 at
        0.05 m starts at cell 3, though 0.15 / 0.05 is 2.9999999999999996); no bounds at all: the
        map's observed extent. Shape (ny, nx), row 0 = the LOWEST y; float32
        with NaN for unknown (log_odds, probability, tsdf), uint32 counts (hits, misses), uint8 state
        codes (0 unknown, 1 free, 2 occupied). Use `region_window` for where the window lies.
        """
        return self.region_window(map_id, xmin, ymin, xmax, ymax, layer)[0]

    def region_window(
        self,
        map_id: str,
        xmin: Real | None = None,
        ymin: Real | None = None,
        xmax: Real | None = None,
        ymax: Real | None = None,
        layer: Layer = "probability",
    ) -> tuple[np.ndarray, tuple[int, int, int, int], tuple[float, float]]:
        """`region`, plus the cell window (i0, j0, i1, j1) and the map point (x, y) of its lower-left
        corner, from the answer's X-Fleetmap-Window / X-Fleetmap-Origin headers."""
        _check_id("map_id", map_id)
        params: dict[str, Any] = {**_bounds(xmin, ymin, xmax, ymax), "layer": layer, "format": "npy"}
        response = self._request("GET", f"/maps/{map_id}/region", params=params)
        try:
            array = np.load(io.BytesIO(response.content), allow_pickle=False)
            i0, j0, i1, j1 = (int(v) for v in response.headers["X-Fleetmap-Window"].split(","))
            ox, oy = (float(v) for v in response.headers["X-Fleetmap-Origin"].split(","))
        except (ValueError, KeyError, EOFError) as exc:  # said "... contains pickled (object) data"
            raise _not_fleetmap(response, "a window of a map", f"{type(exc).__name__}: {exc}") from None
        return array, (i0, j0, i1, j1), (ox, oy)

    def clear_region(
        self, map_id: str, xmin: Real, ymin: Real, xmax: Real, ymax: Real, *, if_match: str | None = None
    ) -> RegionCleared:
        """`DELETE /maps/{map_id}/region`: make the cells with index in [floor(xmin/res),
        floor(xmax/res)) x [floor(ymin/res), floor(ymax/res)) (a bound on a cell edge is that edge, as
        for `region`) unknown again in every layer, as before any scan, and return once the server
        has stored that. `FleetmapError` 404 for no such map,
        422 for an empty window, 503 if the cells were cleared but that could not be stored yet.
        `if_match`: clear only in the map of that ETag (`get_map_and_etag`); `MapChanged` (412,
        nothing cleared) if the map is another one by now, as for the other writes of a map."""
        _check_id("map_id", map_id)
        response = self._request(
            "DELETE",
            f"/maps/{map_id}/region",
            params=_bounds(xmin, ymin, xmax, ymax),
            headers=_conditions(if_match),
        )
        return _read(RegionCleared, response)

    def region_png(
        self,
        map_id: str,
        xmin: Real | None = None,
        ymin: Real | None = None,
        xmax: Real | None = None,
        ymax: Real | None = None,
        layer: Layer = "probability",
    ) -> bytes:
        """`GET /maps/{map_id}/region?format=png`: the window as a grayscale + alpha PNG (top row =
        highest y, unknown transparent)."""
        _check_id("map_id", map_id)
        params: dict[str, Any] = {**_bounds(xmin, ymin, xmax, ymax), "layer": layer, "format": "png"}
        return _bytes_of(self._request("GET", f"/maps/{map_id}/region", params=params), *_PNG)

    def tile(
        self,
        map_id: str,
        z: Integer,
        x: Integer,
        y: Integer,
        layer: Layer = "probability",
        etag: str | None = None,
    ) -> tuple[bytes | None, str]:
        """`GET /maps/{map_id}/tiles/{z}/{x}/{y}.png`: a 256 x 256 RGBA tile (Leaflet CRS.Simple,
        zoom 0 = one pixel per cell). With the `etag` of an earlier answer, returns (None, etag) while
        the tile is unchanged (the server answered 304), else (png bytes, new etag). TypeError before
        any request for a `z`, `x` or `y` that is not an integer, ValueError for an `etag` no header
        carries."""
        _check_id("map_id", map_id)
        z, x, y = (_tile_index(name, value) for name, value in (("z", z), ("x", x), ("y", y)))
        headers = {"If-None-Match": _etag("etag", etag)} if etag else {}
        response = self._request(
            "GET", f"/maps/{map_id}/tiles/{z}/{x}/{y}.png", params={"layer": layer}, headers=headers
        )
        new_etag = response.headers.get("ETag", "")
        if response.status_code == 304:
            return None, new_etag or (etag or "")
        return _bytes_of(response, *_PNG), new_etag

    def surface(
        self,
        map_id: str,
        xmin: Real | None = None,
        ymin: Real | None = None,
        xmax: Real | None = None,
        ymax: Real | None = None,
    ) -> np.ndarray:
        """`GET /maps/{map_id}/surface`: TSDF zero-crossing points, sub-cell interpolated, as an
        (n, 2) float64 array of x, y in metres: those that lie in the window (as for `region`), so
        that windows side by side share out the surface. `FleetmapError` 422 if the map keeps no
        TSDF layer."""
        _check_id("map_id", map_id)
        response = self._request("GET", f"/maps/{map_id}/surface", params=_bounds(xmin, ymin, xmax, ymax))
        parsed = _read(Surface, response)
        return np.array(parsed.points, dtype=np.float64).reshape(-1, 2)

    def export(
        self,
        map_id: str,
        format: Literal["ros", "png"] = "ros",
        margin: Integer | None = None,
        resolution: Real | None = None,
    ) -> bytes:
        """`GET /maps/{map_id}/export`: "ros" = a zip of map.yaml + map.pgm (nav2 map_server), "png"
        = one grayscale PNG; `margin` unknown cells around the observed extent (server default 2);
        `resolution` metres per exported cell, the map's times a whole number (each exported cell
        shows the most occupied known cell of its block; default the map's). `FleetmapError` 409 for
        a map with no observed cell, 422 for a resolution that is not such a multiple."""
        _check_id("map_id", map_id)
        params: dict[str, Any] = {"format": format}
        if margin is not None:
            params["margin"] = margin
        if resolution is not None:
            params["resolution"] = resolution
        response = self._transfer("GET", f"/maps/{map_id}/export", params=params)
        return _bytes_of(response, *(_PNG if format == "png" else _NAV2_ZIP))

    # -- live events -------------------------------------------------------------------------------

    def events(
        self, map_id: str, since: Integer | None = None, robots: Literal["full", "delta"] = "full"
    ) -> EventStream:
        """`GET /maps/{map_id}/events`: the map's server-sent events as (event, data) pairs, e.g.
        ("tiles", {"version": 7, "tiles": [[i0, j0, i1, j1], ...]}) or ("tiles", {"version": 9,
        "reset": True}), ("robots", {"robots": {...}}), ("replaced", {"id": ..., "version": v}) when
        the map was replaced by an upload, a snapshot or a nav2 import (reload its metadata and
        tiles; the stream goes on with the new map's events, its versions starting at v), ("deleted",
        {"id": ...}) after which the stream ends. Keepalive comments are skipped. `since`: resume
        after that change version.

        Robots: the stream is always asked for deltas (`?robots=delta`: only what changed travels).
        With `robots="full"` (the default) they are folded here (`RobotsEvent.apply`), and every
        ("robots", data) is every robot of the map with its trail, a `RobotsEvent` as a dict: what
        a program drawing or checking robots wants, with no bookkeeping of its own. With
        `robots="delta"` the events are yielded as sent: ("robots", ...) every robot, then
        ("robots_delta", data) with what changed since the previous robots event, a
        `RobotsDeltaEvent` as a dict (`RobotsDeltaEvent.model_validate(data)` types it), for a
        program that keeps its own state of a big fleet and wants only the changes.

        The generator is lazy: the request is made on the first `next()`. It ends after `deleted`,
        and when the client is closed (`close()`, from any thread: a thread reading the stream, or
        waiting to resume it, stops at once); close it early with `.close()` on the generator (or
        by leaving a `for` loop and dropping it). Raises `FleetmapError` (e.g. 404 unknown map) or
        httpx's `ConnectError` on the first `next()`; an invalid `map_id` raises ValueError here, at
        the call, as every other method does.

        Once a stream was open, it is followed as an EventSource follows it: when the server stops
        (a restart) or the connection is lost, or nothing at all (not even the server's keepalive)
        arrives for `events_read_timeout` seconds (a half-open connection, a frozen server), `next()`
        waits for the service (`RECONNECT_DELAY` between attempts, or a Retry-After's longer wait,
        at most `MAX_RETRY_AFTER`, through its 503s and a reverse proxy's 502, 503 and 504) and resumes
        with `Last-Event-ID`, so the tiles changed meanwhile come in the next `tiles` event (or a
        reset). It then yields ("reconnected", {"last_event_id": ...}) first: a restarted service
        may hold another map under the id, so reload `get_map` as after `replaced`. A 404 then (the
        map was deleted meanwhile) or 401 / 403 raises `FleetmapError`, and so does an answer that
        is no event stream (not `text/event-stream`: another web server at the address), at any
        time.
        """
        _check_id("map_id", map_id)
        if robots not in ("full", "delta"):
            raise ValueError(f"robots must be 'full' or 'delta', got {robots!r}")
        stream = self._events(map_id, _check_since(since))
        return stream if robots == "delta" else fold_robots(stream)

    @contextlib.contextmanager
    def _open_stream(self, response: httpx.Response) -> Iterator[None]:
        """`response`, an event stream, among those `close` ends while it is read; `_StreamClosed` if
        the client was closed already."""
        with self._streams_lock:
            if self._closed.is_set():
                raise _StreamClosed
            self._streams.add(response)
        try:
            yield
        finally:
            with self._streams_lock:
                self._streams.discard(response)

    def _events(self, map_id: str, since: int | None) -> EventStream:
        """The stream, resumed after a lost connection or a server restart (see `events`)."""
        params = {"robots": "delta"}
        # The stream may be idle for long, but the server's keepalives break every silence: one
        # longer than a few of them is a dead connection (httpx.ReadTimeout), resumed below.
        timeout = httpx.Timeout(self.timeout, read=self.events_read_timeout)
        # The last `id:` the server sent, as an EventSource keeps it; `since` is sent the same way
        # (the server reads `Last-Event-ID` as `?since=`; servers before 2026-11 let `?since=` win
        # over it on a resume).
        last_id = None if since is None else str(since)
        followed = False  # a stream was opened: from then on a lost one is resumed
        while True:
            # Resume where the last stream stopped, as an EventSource does: the server sends the
            # changes after `Last-Event-ID` (or a reset when it does not know that version).
            headers = {} if last_id is None else {"Last-Event-ID": last_id}
            delay = RECONNECT_DELAY
            try:
                with (
                    self._stream_http.stream(
                        "GET", f"/maps/{map_id}/events", params=params, headers=headers, timeout=timeout
                    ) as response,
                    self._open_stream(response),
                    _decoding(response),
                ):
                    if _failed(response):
                        response.read()
                        if not (followed and response.status_code in _RESUMED_STATUSES):
                            _raise_for_error(response)  # 404: the map is gone; 401 / 403: no access
                        delay = _retry_after(response, delay)  # the server, or its proxy, says when
                    else:
                        _raise_unless_event_stream(response)
                        if followed:
                            yield "reconnected", {"last_event_id": last_id}
                        followed = True
                        for event_id, event, data in _parse_sse_ids(response.iter_lines()):
                            last_id = event_id or last_id
                            yield event, data
                            if event == "deleted":
                                return
            except _StreamClosed:
                return
            except httpx.TransportError as exc:
                if self._closed.is_set():  # `close` ended it
                    return
                if not followed:  # nothing listens at all: say so, as every other method does
                    raise _naming_the_service(exc, self.base_url) from exc
            except RuntimeError:
                # The pool closed as a followed stream was resumed (httpx: "the client has been
                # closed"): `close` ends it, as it ends one it finds open. Before the first
                # connection it is the RuntimeError of any request after `close`.
                if followed and self._closed.is_set():
                    return
                raise
            # The stream ended without `deleted` (the server stopped: "the server is shutting
            # down"), the connection was lost, it stayed silent past the read timeout (a
            # ReadTimeout: leaving the `with` closed that connection), or the service (or its
            # proxy) is not back yet (`_RESUMED_STATUSES`): wait for the service, go on.
            # Woken by `close`: slept through, the wait (a 503's Retry-After may ask for minutes)
            # kept the reader after the program closed the client, which then failed the resume
            # with RuntimeError instead of ending the stream.
            if self._closed.wait(delay):
                return


class _StreamClosed(Exception):
    """The client was closed as an event stream opened (`FleetmapClient._open_stream`)."""


def _shut_down(response: httpx.Response) -> None:
    """Shut the socket of a streamed `response` down, so that a thread blocked reading it reads its
    end at once (closing the socket alone leaves such a read blocked, on Linux)."""
    stream = response.extensions.get("network_stream")
    sock = stream.get_extra_info("socket") if stream is not None else None
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)


#: The finest resolution a map may have (`MapConfig.resolution` is above it): with it, `raycast`
#: tells whether rays might pass the service's walk limit without asking the map's own.
_MIN_RESOLUTION: float = next(
    float(m.gt) for m in MapConfig.model_fields["resolution"].metadata if getattr(m, "gt", None) is not None
)


def _no_rays() -> dict[str, np.ndarray]:
    """What `FleetmapClient.raycast` answers for no rays: its fields, each empty, of their dtypes."""
    return {
        "status": np.array([], dtype=str),
        "range": np.array([], dtype=np.float64),
        "x": np.array([], dtype=np.float64),
        "y": np.array([], dtype=np.float64),
        "i": np.array([], dtype=np.int64),
        "j": np.array([], dtype=np.int64),
    }


def _in_parts(
    items: np.ndarray,
    size: int,
    ask: Callable[[np.ndarray], dict[str, np.ndarray]],
    map_id: str,
    what: str,
) -> dict[str, np.ndarray]:
    """`ask(part)` for each run of at most `size` of `items`, in order (one call for an empty
    `items`), and the answers' arrays joined in that order: what `cells` and `raycast` do past the
    service's limit per request. `FleetmapError` 409 if the parts came back with different fields
    (the map was replaced meanwhile by one keeping other layers)."""
    chunks = [items[k : k + size] for k in range(0, len(items), size)] or [items]
    parts = [ask(chunk) for chunk in chunks]
    if len(parts) == 1:
        return parts[0]
    if any(part.keys() != parts[0].keys() for part in parts):  # replaced by a map of other layers
        raise FleetmapError(
            409, f"map {map_id!r} changed its layers while its {len(items)} {what} were read in parts"
        )
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def fold_robots(events: EventStream) -> EventStream:
    """`events` with each `robots_delta` applied to the robots so far and yielded as the full
    ("robots", data) it amounts to (a `RobotsEvent` as a dict); other events pass unchanged. Closing
    the result closes `events`."""
    view: RobotsEvent | None = None
    try:
        for event, data in events:
            if event == "robots":
                view = RobotsEvent.model_validate(data)
            elif event == "robots_delta" and view is not None:
                view = view.apply(RobotsDeltaEvent.model_validate(data))
                event, data = "robots", view.model_dump()
            yield event, data
    finally:
        events.close()


def parse_sse(lines: Iterator[str]) -> Iterator[tuple[str, dict[str, Any]]]:
    """(event, data) pairs of a text/event-stream given as lines (without line ends), per the
    HTML server-sent events rules: `event:` names the event (default "message"), `data:` lines are
    joined by newlines and parsed as JSON (a non-JSON data becomes {"data": text}), a blank line
    dispatches, lines starting with ":" are comments; `id:` and `retry:` are ignored."""
    for _, event, data in _parse_sse_ids(lines):
        yield event, data


def _parse_sse_ids(lines: Iterator[str]) -> Iterator[tuple[str | None, str, dict[str, Any]]]:
    """`parse_sse`, each event with the stream's last event id when it was dispatched (an `id:`
    line sets it for this event and the following ones, as an EventSource's `lastEventId`)."""
    event = ""
    last_id: str | None = None
    data: list[str] = []
    for line in lines:
        if line == "":
            if data:
                text = "\n".join(data)
                try:
                    parsed = json.loads(text)
                except json.JSONDecodeError:
                    parsed = {"data": text}
                yield last_id, event or "message", parsed if isinstance(parsed, dict) else {"data": parsed}
            event, data = "", []
            continue
        if line.startswith(":"):
            continue
        field, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if field == "event":
            event = value
        elif field == "data":
            data.append(value)
        elif field == "id" and "\0" not in value:
            last_id = value


def _media_type(response: httpx.Response) -> str:
    """The media type of `response`'s `Content-Type`, without its parameters ("" without one)."""
    return response.headers.get("content-type", "").partition(";")[0].strip().lower()


def _raise_unless_event_stream(response: httpx.Response) -> None:
    """Raise `FleetmapError` for an answer to `events`' request that is no event stream (its
    content type not `text/event-stream`), as an EventSource fails such a connection instead of
    reconnecting: another web server at the address (a wrong port, a proxy's page) answered 200
    with HTML, which held no event, so the stream was taken as lost and resumed every second for
    ever, each time yielding a "reconnected" that never was."""
    _raise_unless_media_type(response, "text/event-stream", "an event stream")


def _raise_unless_media_type(response: httpx.Response, media_type: str, expected: str) -> None:
    """Raise `FleetmapError` (`_not_fleetmap`: `expected` was not what came) for a successful answer
    whose content type is not `media_type`: the answers the client hands on as bytes or text rather
    than parse (a snapshot, an export, a PNG, the metrics), where another web server's page at the
    address (a captive portal's, a wrong port's) went through unread: `save_snapshot` wrote it as
    the backup and returned its size."""
    if _media_type(response) != media_type:
        raise _not_fleetmap(response, expected, f"whose content type is {media_type}")


def _bytes_of(response: httpx.Response, media_type: str, expected: str) -> bytes:
    """`response`'s body, once `_raise_unless_media_type` found it of `media_type`."""
    _raise_unless_media_type(response, media_type, expected)
    return response.content


def _read(model: type[_Model], response: httpx.Response) -> _Model:
    """`response`'s JSON body as `model`; `FleetmapError` (of the answer's status) when it is not
    one, naming what came instead. A map configuration in it is read as a stored one
    (`STORED_CONFIG`): it is that of a map the service holds, perhaps since before one of today's
    limits, which the service keeps loading and answering; validated as a new configuration, such a
    map could not be read ("not a MapInfo ...: is it a fleetmap service, of this version?"). And as
    an answer (`ANSWERED_CONFIG`): the fields of a newer service's configuration that this version
    does not know are left out, as every answer's unknown fields are."""
    try:
        return model.model_validate_json(
            response.content, context={STORED_CONFIG: True, ANSWERED_CONFIG: True}
        )
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        raise _not_fleetmap(
            response, f"a {model.__name__}", f"{where}: {first['msg']}" if where else first["msg"]
        ) from None


def _not_fleetmap(response: httpx.Response, expected: str, reason: str) -> FleetmapError:
    """The `FleetmapError` for a successful answer that is not the one a fleetmap service gives:
    another web server answering at the address (a captive portal's or a proxy's page, a wrong
    port), or a service of another version. Raised as pydantic's ValidationError ("Invalid JSON:
    expected value at line 1 column 1"), or for a window NumPy's "contains pickled (object) data",
    it was neither of the errors the client promises, and said nothing of the address."""
    came = _media_type(response) or "without a content type"
    return FleetmapError(
        response.status_code,
        f"{_shown_url(response.request.url)} answered {came}, not "
        f"{expected} as a fleetmap service answers ({reason}): is it a fleetmap service, of this version?",
    )


@contextlib.contextmanager
def _decoding(response: httpx.Response) -> Iterator[None]:
    """Read `response`'s body within: one its `Content-Encoding` does not decode (a proxy that
    labels a plain body gzip, or cuts a compressed one) raises `FleetmapError` of the answer's
    status, naming the address and the encoding, where httpx's own `DecodingError` came out of the
    client, neither of the errors it promises."""
    try:
        yield
    except httpx.DecodingError as exc:
        encoding = response.headers.get("content-encoding", "")
        raise FleetmapError(
            response.status_code,
            f"{_shown_url(response.request.url)} answered a body that does not decode as its "
            f"Content-Encoding ({encoding!r}) says ({exc}), which a fleetmap service never sends: "
            "does something between here and the service (a proxy) alter its answers?",
        ) from None


def _retry_after(response: httpx.Response, default: float) -> float:
    """The seconds to wait before asking again after `response` (a 503): what its `Retry-After`
    asks, but never less than `default`. A `Retry-After: 0` (a proxy's, on each of its answers)
    made a stream waiting to resume ask again at once, a busy loop against the proxy."""
    seconds = _retry_after_seconds(response)
    return default if seconds is None else max(default, seconds)


def _retry_after_seconds(response: httpx.Response) -> float | None:
    """The seconds an answer's `Retry-After` asks a client to wait, within [0, `MAX_RETRY_AFTER`];
    None without a number of seconds there (the service sends seconds; an HTTP date is not read,
    nor NaN). An infinite one (`1e999`, `inf`: what else answered may send anything) is the most."""
    try:
        seconds = float(response.headers.get("Retry-After", ""))
    except ValueError:
        return None
    if math.isnan(seconds):
        return None
    return min(max(0.0, seconds), MAX_RETRY_AFTER)


def _scan_body(
    scan: Scan | ScanMessage | Mapping[str, Any], seq: int | None, stamp: float | None, encoding: str
) -> tuple[bytes, str, int | None]:
    """`post_scan`'s request body for `scan`, its content type, and the seq it carries (None when a
    dict carries none, or not an integer: the server refuses it). `seq` is required for a `Scan`."""
    if isinstance(scan, Scan):
        assert seq is not None
        stamp = 0.0 if stamp is None else stamp
        if encoding == "binary":
            return encode_binary(scan, seq, stamp), BINARY_ENCODING, seq
        return encode_json(scan, seq, stamp), JSON_ENCODING, seq
    message: dict[str, Any] = (
        scan.model_dump(mode="json", exclude_none=True) if isinstance(scan, ScanMessage) else dict(scan)
    )
    if seq is not None:
        message["seq"] = seq
    if stamp is not None:
        message["stamp"] = stamp
    # NaN and infinities as the literals NaN, Infinity and -Infinity, which the service reads as a
    # JSON scan's invalid reading, no return, and no maximum (docs/protocol.md): a ScanMessage's
    # range_max is infinite unless given, and its NaN ranges stay invalid.
    sent = message.get("seq")
    sent_seq = int(sent) if isinstance(sent, numbers.Integral) and not isinstance(sent, bool) else None
    return _json(message), JSON_ENCODING, sent_seq


def _json(value: Any) -> bytes:
    """`value` as compact JSON, NumPy scalars and arrays in it as the numbers and lists they hold
    (a configuration's `np.int64` tile size, a dict scan's ranges as an array), which json refused
    ("Object of type int64 is not JSON serializable"), and pydantic models in it as the values they
    hold (a configuration dict's `OccupancyParams`, as `MapConfig` takes it); NaN and infinities as
    the literals the service reads."""
    return json.dumps(value, separators=(",", ":"), default=_plain).encode()


def _plain(value: Any) -> Any:
    """`json.dumps`' `default` for `_json`: a NumPy scalar or array as its Python value, a pydantic
    model as its JSON form (a `MapConfig` section's resolved values, as the model itself is sent)."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def _naming_the_service(exc: httpx.TransportError, base_url: str) -> httpx.TransportError:
    """`exc` again, of its own type, its sentence followed by the service's address: httpx's alone
    ("All connection attempts failed", "[Errno 111] Connection refused") names none, and a wrong
    host or port read as a mystery."""
    try:
        request: httpx.Request | None = exc.request
    except RuntimeError:  # raised before a request was made
        request = None
    return type(exc)(f"{exc} (the fleetmap service at {_shown_url(base_url)})", request=request)


def _shown_url(url: str | httpx.URL) -> str:
    """`url` as it may be shown, in an error's sentence or a repr (which logs keep): the password
    of its user info (`http://user:password@host/`, which httpx sends as Basic auth, e.g. to a proxy
    in front of the service) left out, the user kept, as the API token is never shown."""
    text = str(url)
    scheme, slashes, rest = text.partition("//")
    if not slashes:  # no scheme (an address refused for that): the user info starts it
        scheme, rest = "", text
    authority, slash, path = rest.partition("/")
    user_info, at, host = authority.rpartition("@")
    if not at:
        return text
    return f"{scheme}{slashes}{user_info.partition(':')[0]}@{host}{slash}{path}"


def _scan_not_taken(exc: BaseException) -> bool:
    """Whether a `post_scan` request that raised `exc` certainly left its scan out of the map, so
    that its seq is still free: the service refused it (a 4xx, or 507 for memory), or the request
    never left (no connection, or the client was closed). Otherwise (a 503, a read timeout, a
    dropped connection, or a success whose body could not be read: `_decoding`) the scan may be
    integrated."""
    if isinstance(exc, FleetmapError):
        answered = 200 <= exc.status < 300  # integrated: its answer's body is what failed
        return not answered and (exc.status < 500 or exc.status == 507)
    return isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout | httpx.PoolTimeout | RuntimeError)


def _finite(value: Real) -> float:
    """`value` as a float; ValueError unless it is a finite number (an int beyond float's range too,
    which float() refuses with OverflowError). A number as the engine takes one (`real_number`):
    float() read text ("1.5"), True and a NumPy date as numbers, sent as those, where `cells` and the
    engine refuse them; None or an array raised its TypeError."""
    try:
        v = real_number(value)
    except OverflowError:
        raise ValueError("coordinates must be finite numbers, got an int past a float's range") from None
    except TypeError as exc:  # what is no number at all: `real_number` says what it got
        raise ValueError(f"coordinates must be finite numbers: {exc}") from None
    if not math.isfinite(v):
        raise ValueError(f"coordinates must be finite numbers, got {value!r}")
    return v


def _failed(response: httpx.Response) -> bool:
    """Whether `response` is no answer to the request: a 4xx / 5xx, or a redirect (3xx) the client
    does not follow. Not a 304: what `tile` asked for with the ETag it has."""
    return response.status_code >= 300 and response.status_code != 304


def _raise_for_error(response: httpx.Response) -> None:
    """Raise `FleetmapError` for a 4xx / 5xx answer, with the server's detail, and for a redirect
    (3xx but 304), naming where it points.

    A redirect is no answer: a proxy in front of the service sending http:// to https:// (301), a
    service moved. Taken for one, as every status below 400 was, `delete_map` returned as if the map
    were deleted, `save_snapshot` wrote the redirect's HTML page as the backup and returned its
    size, and an event stream resumed it for ever. The client follows none: httpx would drop the
    API token on the way to another host, and send a write redirected by a 301 or 302 as a GET."""
    if not _failed(response):
        return
    if response.status_code < 400:
        location = response.headers.get("Location")
        to = f" to {location}" if location else ""
        raise FleetmapError(
            response.status_code,
            f"{_shown_url(response.request.url)} answered with a redirect{to} ({response.status_code} "
            f"{response.reason_phrase}), which the client does not follow: give it the service's "
            "address there",
            retry_after=_retry_after_seconds(response),
        )
    detail = response.text.strip() or response.reason_phrase
    errors: list[dict[str, Any]] = []
    try:
        parsed = ErrorResponse.model_validate_json(response.content)
    except ValidationError:
        pass
    else:
        detail = parsed.detail
        errors = [e.model_dump() for e in parsed.errors or []]
    if response.status_code == 412:  # a conditional write found another map (or none)
        raise MapChanged(412, detail, errors, _retry_after_seconds(response), response.headers.get("ETag"))
    raise FleetmapError(response.status_code, detail, errors, _retry_after_seconds(response))


__all__ = [
    "MAX_RETRY_AFTER",
    "RECONNECT_DELAY",
    "SCAN_TIMEOUT",
    "TOKEN_ENV",
    "TRANSFER_TIMEOUT",
    "EVENTS_READ_TIMEOUT",
    "KEEPALIVE_EXPIRY",
    "EventStream",
    "FleetmapClient",
    "FleetmapError",
    "Layer",
    "MapChanged",
    "fold_robots",
    "parse_sse",
]


def _sync_directory(directory: Path) -> None:
    """Make the names in `directory` durable (a rename into it), where the system can: a directory
    cannot be opened for that on some (Windows), nor synced on some file systems; the file's own
    data is synced already, so at worst a power cut keeps the earlier name's file."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)
