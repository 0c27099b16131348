"""Resource exhaustion over HTTP, on the real service process: a client (no token needed, reads are
open by default) must not be able to pin the service's memory, CPU or connections without bound.

The service here runs with small limits so they are cheap to reach.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from service_process import RobotProcess, ServiceProcess, wait_for

from fleetmap.http_limits import ACCEPT_ERROR, LINGER, MAX_HEAD_BYTES, quiet_accept_errors
from fleetmap.rate_limited_log import LOG_INTERVAL

MAX_STREAMS = 3
MAX_CONNECTIONS = 16  # the smallest --max-http-connections allowed
HEAD_TIMEOUT, BODY_TIMEOUT = 1.0, 2.0


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    log_dir = tmp_path_factory.mktemp("exhaustion")
    args = [
        "--in-memory", "--max-event-streams", str(MAX_STREAMS),
        "--max-http-connections", str(MAX_CONNECTIONS),
        "--http-head-timeout", str(HEAD_TIMEOUT), "--http-body-timeout", str(BODY_TIMEOUT),
    ]  # fmt: skip
    with ServiceProcess(log_dir, args) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        yield svc


def open_event_stream(svc: ServiceProcess, map_id: str = "m") -> socket.socket:
    """A raw connection holding `GET /maps/{map_id}/events` open, once its first bytes arrived."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=10)
    sock.sendall(f"GET /maps/{map_id}/events HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
    head = b""
    while b"retry:" not in head:
        chunk = sock.recv(4096)
        assert chunk, f"the stream closed: {head!r}"
        head += chunk
    assert head.startswith(b"HTTP/1.1 200"), head
    return sock


def metric(svc: ServiceProcess, name: str) -> float:
    for line in httpx.get(f"{svc.base_url}/metrics").text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"no metric {name}")


def test_event_streams_are_capped_and_slots_come_back(service: ServiceProcess) -> None:
    url = f"{service.base_url}/maps/m/events"
    streams = [open_event_stream(service) for _ in range(MAX_STREAMS)]
    try:
        refused = httpx.get(url, timeout=5)
        assert refused.status_code == 503
        assert f"limit of {MAX_STREAMS} open event streams" in refused.json()["detail"]
        assert int(refused.headers["retry-after"]) > 0
        assert metric(service, "fleetmap_event_streams") == MAX_STREAMS
        assert metric(service, "fleetmap_event_streams_refused_total") >= 1
        # A client that goes away gives its slot back (detected at once, not at the next keepalive).
        streams.pop().close()
        streams.append(wait_for(lambda: _try_open(service), timeout=5, what="a freed stream slot"))
    finally:
        for sock in streams:
            sock.close()
    # All of them come back: the next client gets a stream at once.
    wait_for(lambda: metric(service, "fleetmap_event_streams") == 0, timeout=5, what="streams closed")
    open_event_stream(service).close()


def _try_open(svc: ServiceProcess) -> socket.socket | None:
    try:
        return open_event_stream(svc)
    except AssertionError:
        return None


def test_an_event_stream_of_a_deleted_map_gives_its_slot_back(service: ServiceProcess) -> None:
    assert httpx.put(f"{service.base_url}/maps/gone", json={}).status_code == 201
    sock = open_event_stream(service, "gone")
    try:
        assert httpx.delete(f"{service.base_url}/maps/gone").status_code == 204
        received = b""
        while b"event: deleted" not in received:
            chunk = sock.recv(4096)
            if not chunk:
                break
            received += chunk
        assert b"event: deleted" in received
        wait_for(lambda: metric(service, "fleetmap_event_streams") == 0, timeout=5, what="slot back")
    finally:
        sock.close()


def seconds_until_closed(sock: socket.socket, limit: float, dribble: bytes = b"") -> float:
    """Seconds until the server closes `sock` (reads b""), sending `dribble` every 0.2 s meanwhile;
    `limit` if it is still open then."""
    started = time.monotonic()
    sock.settimeout(0.2)
    while time.monotonic() - started < limit:
        try:
            if sock.recv(4096) == b"":
                return time.monotonic() - started
        except TimeoutError:
            pass
        if dribble:
            try:
                sock.sendall(dribble)
            except OSError:  # reset: closed by the server
                return time.monotonic() - started
    return limit


def test_a_connection_that_sends_nothing_is_closed(service: ServiceProcess) -> None:
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        assert seconds_until_closed(sock, 10) < HEAD_TIMEOUT + 1.5


def test_a_request_head_sent_a_byte_at_a_time_is_cut_off(service: ServiceProcess) -> None:
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        sock.sendall(b"GET /maps HTTP/1.1\r\nHost: localhost\r\n")
        assert seconds_until_closed(sock, 10, dribble=b"X") < HEAD_TIMEOUT + 1.5


def test_a_request_body_that_stalls_is_cut_off(service: ServiceProcess) -> None:
    """A read route (open to anyone): the body it buffers would otherwise stay in memory for ever."""
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        head = b"POST /maps/m/cells HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        sock.sendall(head + b"Content-Length: 1000000\r\n\r\n" + b" " * 100_000)
        closed_after = seconds_until_closed(sock, 15, dribble=b" ")
        assert BODY_TIMEOUT - 0.5 < closed_after < BODY_TIMEOUT + 1.5


def test_an_upload_whose_body_misses_its_deadline_is_told_why(service: ServiceProcess) -> None:
    """A snapshot upload over a slow link that does not arrive within --http-body-timeout is cut off:
    the connection was closed without a word, and the client saw "empty reply" or "connection
    reset", nothing that said to raise the limit (as docs/api.md says to for big maps). It gets a
    JSON 408 naming the option, then the end of the stream; nothing is installed."""
    with socket.create_connection(("127.0.0.1", service.port), timeout=15) as sock:
        head = b"PUT /maps/slow/snapshot HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/zip\r\n"
        sock.sendall(head + b"Content-Length: 100000\r\n\r\n" + b"x" * 1000)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 408 "), answer
    detail = json.loads(answer.partition(b"\r\n\r\n")[2])["detail"]
    assert "--http-body-timeout" in detail and f"{BODY_TIMEOUT:g} s" in detail, detail
    assert httpx.get(f"{service.base_url}/maps/slow").status_code == 404


def test_an_upload_cut_off_mid_body_is_not_logged_as_a_bug(service: ServiceProcess) -> None:
    """A body cut off (its deadline, or a client that goes away mid-upload) is the client's doing:
    Starlette's ClientDisconnect from `request.body()` was answered as an internal error, logged at
    ERROR with two tracebacks (fleetmap's and uvicorn's) for each such request."""
    with socket.create_connection(("127.0.0.1", service.port)) as sock:
        head = b"PUT /maps/cut-off/snapshot HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/zip\r\n"
        sock.sendall(head + b"Content-Length: 100000\r\n\r\n" + b"x" * 1000)
        assert seconds_until_closed(sock, 10) < BODY_TIMEOUT + 1.5
    with socket.create_connection(("127.0.0.1", service.port)) as sock:  # gone before the deadline
        sock.sendall(head + b"Content-Length: 100000\r\n\r\n" + b"x" * 1000)
    time.sleep(0.5)
    logs = service.logs()
    assert "ClientDisconnect" not in logs and "/maps/cut-off/snapshot" not in logs, logs


def test_kept_alive_connections_and_long_responses_are_not_cut_off(service: ServiceProcess) -> None:
    """The deadlines are for receiving requests: an event stream outlives them, and a kept-alive
    connection serves a request sent after a pause longer than the head timeout allows."""
    stream = open_event_stream(service)
    try:
        with httpx.Client(base_url=service.base_url) as client:
            assert client.get("/maps").status_code == 200
            time.sleep(HEAD_TIMEOUT + 0.5)  # within uvicorn's 5 s keep-alive
            assert client.post("/maps/m/cells", json={"points": [[0.0, 0.0]]}).status_code == 200
        # Still open: it may send an event or nothing, but it is not closed.
        assert seconds_until_closed(stream, 1.0) == 1.0
    finally:
        stream.close()


def test_connections_past_the_limit_are_refused_and_the_service_recovers(service: ServiceProcess) -> None:
    idle = [socket.create_connection(("127.0.0.1", service.port)) for _ in range(MAX_CONNECTIONS)]
    try:
        with socket.create_connection(("127.0.0.1", service.port), timeout=5) as extra:
            answer = b""
            while chunk := extra.recv(4096):
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 503"), answer
        assert b'"detail": "the server holds too many HTTP connections; retry later"' in answer
        assert (
            b"\r\ncache-control: no-cache\r\n" in answer
            and b"\r\nx-content-type-options: nosniff\r\n" in answer
        )
    finally:
        for sock in idle:
            sock.close()
    # The idle ones are gone (closed by their clients, or by the head timeout): served again.
    wait_for(lambda: _healthz_ok(service), timeout=HEAD_TIMEOUT + 5, what="/healthz answering again")


def raw_answer(svc: ServiceProcess, request: bytes, piece: int = 0) -> tuple[int, str, dict[str, object]]:
    """(status, content type, JSON body) of the answer to `request`, sent whole or in pieces of
    `piece` bytes (so the head arrives in many reads), read until the service closes."""
    status, headers, body = raw_answer_with_headers(svc, request, piece)
    return status, headers["content-type"], body


def raw_answer_with_headers(
    svc: ServiceProcess, request: bytes, piece: int = 0
) -> tuple[int, dict[str, str], dict[str, object]]:
    """`raw_answer`, with every header (names in lower case) instead of the content type."""
    with socket.create_connection(("127.0.0.1", svc.port), timeout=10) as sock:
        try:
            for start in range(0, len(request), piece or len(request)):
                sock.sendall(request[start : start + (piece or len(request))])
                if piece:
                    time.sleep(0.002)  # (not a timing condition: only so that the pieces arrive apart)
        except OSError:  # refused before the whole head was sent: closed by the service
            pass
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    head, _, body = answer.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = {name.lower(): value for name, _, value in (line.partition(": ") for line in lines[1:])}
    return int(lines[0].split()[1]), headers, json.loads(body)


def test_an_oversized_or_unparsable_request_head_gets_a_json_error(service: ServiceProcess) -> None:
    """Every answer of the API is JSON {"detail": ...}, also those httptools' parser and the head limit
    give before a request reaches the app; and a head over MAX_HEAD_BYTES is refused, not read into
    memory (neither uvicorn nor httptools bounds it: a 10 MB header was answered 200)."""
    long_url = b"GET /maps/" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: localhost\r\n\r\n"
    long_header = b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Big: " + b"b" * 100_000 + b"\r\n\r\n"
    # In pieces and never ended: refused once past the limit, not read on until the head timeout.
    url_detail = "the request line is longer than 65536 bytes"
    head_detail = "the request's head (request line and headers) is longer than 65536 bytes"
    cases = [
        (long_url, 0, 414, url_detail),
        (long_url[:-30], 8192, 414, url_detail),
        (long_header, 0, 431, head_detail),
        (long_header[:-4], 8192, 431, head_detail),
        # The big header first: httptools hands a header over only once the next one begins, so
        # no header was seen yet when the limit refused it; it is still not the request line.
        (long_header.replace(b"Host: localhost\r\n", b"")[:-4], 8192, 431, head_detail),
        (b"NOT HTTP AT ALL\r\n\r\n", 0, 400, "invalid HTTP request"),
    ]
    for request, piece, status, detail in cases:
        got = raw_answer(service, request, piece)
        assert got[:2] == (status, "application/json"), (request[:40], piece, got)
        assert str(got[2]["detail"]).startswith(detail), got
    # uvicorn's warning about it, in the log's text format (time, level, logger), not uvicorn's own.
    assert " WARNING uvicorn.error: Invalid HTTP request received." in service.logs()
    assert "WARNING:  Invalid HTTP request received." not in service.logs()
    # Within the limit: a long header, and a body far longer than the limit (not part of the head).
    assert httpx.get(f"{service.base_url}/healthz", headers={"X-Big": "b" * 60_000}).status_code == 200
    points = [[0.01 * i, 0.0] for i in range(10_000)]
    assert len(json.dumps({"points": points})) > 2 * MAX_HEAD_BYTES
    assert httpx.post(f"{service.base_url}/maps/m/cells", json={"points": points}).status_code == 200


def test_a_request_to_switch_protocols_with_a_body_is_refused_not_run_without_it(
    service: ServiceProcess,
) -> None:
    """`curl --http2` over http:// asks to switch to HTTP/2 (`Upgrade: h2c`). httptools takes what
    follows such a head for the other protocol's bytes, and uvicorn ran the request without its body:
    `PUT /maps/{id}` with `{"resolution": 0.1}` made a map of the default 0.05 m, answered 201. Such a
    request is refused now, nothing changed; one without a body is answered as any other."""
    upgrade = (
        "Upgrade: h2c\r\nConnection: Upgrade, HTTP2-Settings\r\nHTTP2-Settings: AAMAAABkAAQCAAAAAAIAAAAA\r\n"
    )
    config = b'{"resolution": 0.1}'
    requests = [
        f"PUT /maps/h2c HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(config)}\r\n{upgrade}\r\n".encode()
        + config,
        f"PUT /maps/h2c HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        f"Transfer-Encoding: chunked\r\n{upgrade}\r\n".encode()
        + b"%x\r\n%s\r\n0\r\n\r\n" % (len(config), config),
    ]
    for request in requests:
        status, content_type, body = raw_answer(service, request)
        assert (status, content_type) == (400, "application/json"), body
        assert "switch protocols" in str(body["detail"]) and "--http1.1" in str(body["detail"])
    assert httpx.get(f"{service.base_url}/maps/h2c").status_code == 404
    r = httpx.get(f"{service.base_url}/maps/m", headers={"Upgrade": "h2c", "Connection": "Upgrade"})
    assert r.status_code == 200 and r.json()["id"] == "m"


def test_a_request_to_switch_protocols_without_a_body_is_answered_quietly_and_so_is_the_next(
    service: ServiceProcess,
) -> None:
    """A request with `Upgrade` (h2c, or websocket: the service serves neither) and no body is
    answered over HTTP/1.1, as RFC 9110 lets a server ignore the `Upgrade`. uvicorn dropped what the
    client sent after it (a pipelined request was never answered) and logged two warnings for each,
    one telling the operator to install a WebSocket library."""
    already = len(service.logs())
    for protocol in ("h2c", "websocket"):
        upgrading = (
            f"GET /maps/m HTTP/1.1\r\nHost: localhost\r\nUpgrade: {protocol}\r\nConnection: Upgrade\r\n\r\n"
        )
        closing = "GET /healthz HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
        with socket.create_connection(("127.0.0.1", service.port), timeout=10) as sock:
            sock.sendall((upgrading + closing).encode())  # one piece: pipelined
            answer = b""
            while chunk := sock.recv(65536):
                answer += chunk
        assert answer.count(b"HTTP/1.1 200 OK\r\n") == 2, answer[:300]
        assert b'"id":"m"' in answer and b'"status":"ok"' in answer
    # Many in one read: each is answered (the rest after each was parsed in a call of its own, a
    # recursion that a thousand took past Python's limit: no answer, and a fatal error logged).
    upgrading = "GET /healthz HTTP/1.1\r\nHost: localhost\r\nUpgrade: h2c\r\nConnection: Upgrade\r\n\r\n"
    with socket.create_connection(("127.0.0.1", service.port), timeout=30) as sock:
        sock.sendall((upgrading * 1000 + closing).encode())
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.count(b"HTTP/1.1 200 OK\r\n") == 1001
    assert httpx.get(f"{service.base_url}/healthz").status_code == 200  # its log line is written
    logged = service.logs()[already:]
    assert "upgrade" not in logged.lower() and "WebSocket" not in logged, logged


def test_a_refused_head_s_answer_is_not_lost_to_a_reset(service: ServiceProcess) -> None:
    """A head refused while its client is still sending (a 100 kB URL followed by 4 MB more): the
    service read only the start of it. Closing at once, with the rest unread, made the kernel reset
    the connection, and the reset could destroy the 414 before the client read it (CI saw
    "connection reset by peer" under load). The service now half-closes after its answer and drops
    what still arrives, so the client reads the answer, then the end of the stream."""
    request = b"GET /maps/" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: localhost\r\n\r\n" + b"x" * 4_000_000
    for _ in range(5):
        with socket.create_connection(("127.0.0.1", service.port), timeout=10) as sock:
            sock.sendall(request)  # all of it: the service reads and drops what follows its answer
            answer = b""
            while chunk := sock.recv(65536):
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 414 "), answer[:100]
        assert b"the request line is longer than 65536 bytes" in answer


def test_a_request_refused_with_its_body_in_the_same_read_is_not_logged_as_a_bug(
    service: ServiceProcess,
) -> None:
    """A request httptools cannot parse (here a snapshot upload naming both Transfer-Encoding and
    Content-Length, and plain garbage) that arrives in one read with more than MAX_HEAD_BYTES after
    it (its body: an upload sent whole) is answered 400 and lingered over like any refusal. The
    bytes of that read were still counted as its head once it was refused, so the head limit refused
    it a second time, writing after the end of the stream: asyncio logged "Fatal error:
    protocol.data_received() call failed" with a traceback, an ERROR for anyone's malformed bytes,
    and reset the connection."""
    already = len(service.logs())
    upload = (
        b"PUT /maps/m/snapshot HTTP/1.1\r\nHost: localhost\r\nContent-Length: 5\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n" + b"x" * (4 * MAX_HEAD_BYTES)
    )
    garbage = b"NOT HTTP AT ALL\r\n\r\n" + b"x" * (4 * MAX_HEAD_BYTES)
    for request in (upload, garbage) * 3:
        status, _, body = raw_answer(service, request)
        assert status == 400 and str(body["detail"]).startswith("invalid HTTP request"), body
    assert httpx.get(f"{service.base_url}/healthz").status_code == 200  # its log line is written
    logs = service.logs()[already:]
    assert "Traceback" not in logs and "Fatal error" not in logs, logs


#: Headers every answer of the app carries (without tokens), whatever made it.
COMMON = ("cache-control", "x-content-type-options", "x-frame-options", "referrer-policy")


def test_answers_given_before_the_app_carry_the_apps_common_headers(service: ServiceProcess) -> None:
    """The 400, 414 and 431 the HTTP protocol gives by itself carry the Cache-Control and security
    headers every answer of the app does (here an error handler's 404). They carried neither: a
    cache in front could keep a 414 for its URL (cacheable by default, RFC 9110 15.5.15)."""
    app_error = httpx.get(f"{service.base_url}/nothing")
    assert app_error.status_code == 404
    expected = {name: app_error.headers[name] for name in COMMON}
    assert expected["cache-control"] == "no-cache" and expected["x-content-type-options"] == "nosniff"
    requests = {
        400: b"NOT HTTP AT ALL\r\n\r\n",
        414: b"GET /maps/" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: localhost\r\n\r\n",
        431: b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Big: " + b"b" * 100_000 + b"\r\n\r\n",
    }
    for status, request in requests.items():
        got, headers, _ = raw_answer_with_headers(service, request)
        assert got == status and {name: headers.get(name) for name in COMMON} == expected, (status, headers)


def test_refused_request_heads_are_logged_once_not_once_each(service: ServiceProcess) -> None:
    """uvicorn warns about every request it refuses before the app (400, and the 414 and 431 of a
    head that arrived whole), and anyone can send them: a client looping on bad heads wrote 10
    warnings a second. They are rate-limited: the sentence at most once per LOG_INTERVAL."""
    already = len(service.logs())
    started = time.monotonic()
    for k in range(60):
        request = b"NOT HTTP AT ALL\r\n\r\n" if k % 2 else b"GET /healthz HTTP/1.1\r\nX: " + b"b" * 70_000
        assert raw_answer(service, request)[0] in (400, 431)
    elapsed = time.monotonic() - started
    assert httpx.get(f"{service.base_url}/healthz").status_code == 200  # its log line is written
    warnings = service.logs()[already:].count("Invalid HTTP request received.")
    assert warnings <= 1 + elapsed / LOG_INTERVAL, (warnings, elapsed)


def _healthz_ok(svc: ServiceProcess) -> bool:
    try:
        return httpx.get(f"{svc.base_url}/healthz", timeout=2).status_code == 200
    except httpx.TransportError:
        return False


def test_a_connection_flood_leaves_robots_and_the_log_alone(tmp_path: Path) -> None:
    """With the 512 descriptors of a tight `ulimit -n`, hundreds of idle HTTP connections (no token
    needed) must not use them all: robots still connect over Zenoh, HTTP refuses what it cannot hold
    with a 503, and the log does not fill with a traceback per refused accept."""
    svc = ServiceProcess(tmp_path, ["--in-memory"])
    svc.args = ["sh", "-c", 'ulimit -n 512 && exec "$@"', "sh", *svc.args]
    with svc:
        flood = []
        try:
            # All at once, not one after another: the kernel completes the handshakes and queues them,
            # and the service must not take more of them at a time than it has descriptors for.
            for _ in range(700):
                sock = socket.socket()
                sock.setblocking(False)
                sock.connect_ex(("127.0.0.1", svc.port))
                flood.append(sock)
            time.sleep(1.0)
            robot = RobotProcess(svc.zenoh_endpoint, "flooded", "r1", sim=1, count=5, log_dir=tmp_path)
            robot.start()
            robot.wait(60)
            with socket.create_connection(("127.0.0.1", svc.port), timeout=5) as extra:
                extra.sendall(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\n\r\n")
                assert extra.recv(4096).startswith(b"HTTP/1.1 503"), "refused with an answer, at once"
        finally:
            for sock in flood:
                sock.close()
        wait_for(lambda: _healthz_ok(svc), timeout=15, what="/healthz answering again")
        stats = httpx.get(f"{svc.base_url}/maps/flooded").json()["stats"]
        assert stats["robots"]["r1"]["scans_integrated"] == 5
        logs = svc.logs()
    assert "Too many open files" not in logs and "cannot accept" not in logs
    assert len(logs) < 20_000, logs[-2000:]


def test_failed_accepts_are_logged_once_not_once_each(caplog: pytest.LogCaptureFixture) -> None:
    """Python 3.11's loop reports every connection it could not accept for want of descriptors with
    a traceback (46,000 in 8 s of a flood); the service logs them as one rate-limited warning, and
    other loop errors as before."""
    loop = asyncio.new_event_loop()
    try:
        quiet_accept_errors(loop)
        with caplog.at_level(logging.WARNING):
            for _ in range(1000):
                loop.call_exception_handler(
                    {"message": ACCEPT_ERROR, "exception": OSError(errno.EMFILE, "Too many open files")}
                )
            loop.call_exception_handler({"message": "something else broke"})
    finally:
        loop.close()
    accept_lines = [r for r in caplog.records if "accept" in r.getMessage()]
    assert len(accept_lines) == 1, len(accept_lines)
    assert accept_lines[0].name == "fleetmap.http" and "Too many open files" in accept_lines[0].getMessage()
    assert any("something else broke" in r.getMessage() for r in caplog.records)


def test_a_refused_head_behind_an_event_stream_ends_the_stream_not_as_a_bug(tmp_path: Path) -> None:
    """Garbage pipelined behind an open event stream: its refusal half-closes the connection, and
    the stream's next write (a keepalive, here every 0.1 s) came after the end of the stream, where
    the transport raises: logged as an internal error with two tracebacks (fleetmap's and
    uvicorn's), for any client's bytes, and the 400 was written into the middle of the stream. The
    stream now ends as if its client had gone, its slot comes back, and nothing is logged as a bug."""
    with ServiceProcess(tmp_path, ["--in-memory", "--events-keepalive", "0.1"]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        with open_event_stream(svc) as sock:
            sock.sendall(b"NOT HTTP\r\n\r\n")  # the next request of the connection
            received = b""
            started = time.monotonic()
            while chunk := sock.recv(65536):  # until the service ends its side
                received += chunk
            assert time.monotonic() - started < LINGER + 1
            time.sleep(1.0)  # this side stays open (the service lingers): the keepalives are due
        wait_for(lambda: metric(svc, "fleetmap_event_streams") == 0, timeout=5, what="the slot back")
        time.sleep(0.3)  # the stream's task has seen it
        logs = svc.logs()
        assert "Traceback" not in logs and "internal error" not in logs, logs
        assert b"HTTP/1.1 400" not in received, received  # not inside the stream's bytes


def _unsent_bytes_of_closed_sockets(port: int) -> list[int]:
    """The bytes still queued to send by each socket on local port `port` that its process has closed
    and the kernel still holds (FIN_WAIT1, CLOSING or LAST_ACK), from /proc/net/tcp and tcp6."""
    held = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(FileNotFoundError), open(table) as rows:
            next(rows)  # the header
            for row in rows:
                fields = row.split()
                local, state, queues = fields[1], fields[3], fields[4]
                if int(local.rsplit(":", 1)[1], 16) == port and state in ("04", "0B", "09"):
                    held.append(int(queues.split(":")[0], 16))
    return held


def test_a_client_dropped_for_reading_nothing_leaves_no_unsent_answer_in_the_kernel(tmp_path: Path) -> None:
    """A client that asks for a big answer and reads none of it is dropped after --http-send-timeout
    seconds. The drop closed the socket, and the kernel went on holding what the answer had queued
    (2.8 MB of a region seen in `ss`: FIN-WAIT-1, offered to a client whose window was shut) for as
    long as that client kept its end open: the connection was gone from the service, not the memory,
    and a client repeating it pinned a few MB of the machine's memory a time. The drop resets the
    connection instead, which frees that queue at once."""
    with ServiceProcess(tmp_path, ["--in-memory", "--http-send-timeout", "1"]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        with socket.socket() as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connect: a small window
            sock.connect(("127.0.0.1", svc.port))
            window = "xmin=0&ymin=0&xmax=100&ymax=100&layer=log_odds&format=npy"  # 4 million cells
            sock.sendall(f"GET /maps/m/region?{window} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
            wait_for(lambda: metric(svc, "fleetmap_http_connections") == 1, timeout=30, what="the drop")
            held = _unsent_bytes_of_closed_sockets(svc.port)
            assert not any(held), f"the kernel still holds {held} bytes of the dropped answer"
            with pytest.raises(ConnectionResetError):
                while sock.recv(1 << 16):
                    pass


def test_an_answer_its_client_never_reads_is_not_held_by_the_kernel_after_the_connection_ends(
    tmp_path: Path,
) -> None:
    """An answer that fits whole in the socket's buffers (a 1.8 MB region) is written at once, and the
    service closes the idle connection a few seconds later (keep-alive, head timeout). Its client
    reading nothing and keeping its end open, the kernel held those unsent bytes for as long (seen:
    minutes, until the client closed), FIN-WAIT-1 with a shut window, a connection the service no
    longer counted: a client could pin the machine's memory 1.8 MB a request, past
    --max-http-connections. The kernel now drops them after --http-send-timeout seconds of the
    client reading nothing, as the service drops an open connection."""
    with ServiceProcess(tmp_path, ["--in-memory", "--http-send-timeout", "1"]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        with socket.socket() as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connect: a small window
            sock.connect(("127.0.0.1", svc.port))
            window = "xmin=0&ymin=0&xmax=34&ymax=34&layer=log_odds&format=npy"  # 462 400 cells
            sock.sendall(f"GET /maps/m/region?{window} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
            wait_for(lambda: metric(svc, "fleetmap_http_connections") == 1, timeout=60, what="closed")
            wait_for(
                lambda: not any(_unsent_bytes_of_closed_sockets(svc.port)),
                timeout=30,
                what="the unsent answer dropped by the kernel",
            )
