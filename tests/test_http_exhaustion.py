"""Resource exhaustion over HTTP, on the real service process: a client (no token needed, reads are
open by default) must not be able to pin the service's memory, CPU or connections without bound.

The service here runs with small limits so they are cheap to reach.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator

import httpx
import pytest
from service_process import ServiceProcess, wait_for

MAX_STREAMS = 3


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    log_dir = tmp_path_factory.mktemp("exhaustion")
    args = ["--in-memory", "--max-event-streams", str(MAX_STREAMS)]
    with ServiceProcess(log_dir, args) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        yield svc


def open_event_stream(svc: ServiceProcess, map_id: str = "m") -> socket.socket:
    """A raw connection holding `GET /maps/{map_id}/events` open, once its first bytes arrived."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=10)
    sock.sendall(f"GET /maps/{map_id}/events HTTP/1.1\r\nHost: t\r\n\r\n".encode())
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
