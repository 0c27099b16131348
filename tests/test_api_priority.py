"""Ingest before reads (`fleetmap.api.ingest_priority`): HTTP requests wait while scans wait.

A real registry with running workers behind a real uvicorn server (test_api_support): the backlog is
made real by holding the map's lock, so the workers block in apply and the robot's later scans queue
up and age, exactly as when the workers cannot keep up.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import pytest
import uvicorn
from prometheus_client.parser import text_string_to_metric_families
from registry_idle import wait_idle
from test_api_support import RunningApi, fan_scan, running_api

from fleetmap.api import ApiSettings, create_app
from fleetmap.api.ingest_priority import IngestGate, is_exempt
from fleetmap.codec import WireScan
from fleetmap.registry import MapRegistry


def metric(api: RunningApi, name: str) -> float:
    for family in text_string_to_metric_families(api.client.get("/metrics").text):
        for sample in family.samples:
            if sample.name == name:
                return sample.value
    raise KeyError(name)


@contextmanager
def backlog(api: RunningApi, map_id: str, scans: int = 5, age: float = 0.15) -> Iterator[None]:
    """Scans queued for `map_id` and not integrated while the block runs: the map's lock is held, so
    the worker that takes the first scan blocks in apply and the rest wait in the queue. Entered once
    the oldest queued scan is `age` seconds old. The scans are integrated after the block."""
    registry = api.registry
    entry, _ = registry.create(map_id)
    with entry.gmap.lock:
        for seq in range(scans):
            registry.submit(map_id, "r1", WireScan(seq, 0.0, fan_scan(0.0, 0.0, 0.0, [1.0] * 31)))
        deadline = time.monotonic() + 10
        while registry.backlog()[1] < age:
            assert time.monotonic() < deadline, registry.backlog()
            time.sleep(0.01)
        yield
    assert wait_idle(registry, 10)


def timed_get(api: RunningApi, path: str, out: dict[str, object]) -> threading.Thread:
    """GET `path` on its own connection in a thread; `out` gets the response and when it arrived."""

    def run() -> None:
        with httpx.Client(base_url=api.base_url, timeout=30) as client:
            out["response"] = client.get(path)
        out["at"] = time.monotonic()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


@pytest.fixture
def api() -> Iterator[RunningApi]:
    with running_api(ApiSettings(ingest_backlog=0.05, max_read_delay=20.0)) as running:
        yield running


def test_a_read_waits_while_scans_wait_and_is_served_once_they_are_integrated(api: RunningApi) -> None:
    api.client.put("/maps/other")
    assert api.client.get("/maps/other").status_code == 200
    assert metric(api, "fleetmap_http_delayed_requests_total") == 0  # no backlog: nothing waits
    out: dict[str, object] = {}
    with backlog(api, "busy"):
        thread = timed_get(api, "/maps/other", out)
        time.sleep(0.5)
        assert "response" not in out  # held back, not served
        # Health is never held back, and shows why. (/metrics is not held back either, but it reads
        # each map's tile count under the map's lock, which this test holds.)
        health = api.client.get("/healthz", timeout=2)
        assert health.status_code == 200 and health.json()["queue_depth"] >= 1
        assert api.registry.backlog()[1] >= 0.5
        released = time.monotonic()
    thread.join(10)
    response = out["response"]
    assert isinstance(response, httpx.Response) and response.status_code == 200
    assert response.json()["id"] == "other"
    # Served promptly once the scans were integrated, long before the 20 s limit.
    assert out["at"] - released < 2.0  # type: ignore[operator]
    assert metric(api, "fleetmap_http_delayed_requests_total") == 1
    assert metric(api, "fleetmap_http_delay_seconds_total") >= 0.3
    assert metric(api, "fleetmap_http_delay_timeouts_total") == 0
    assert metric(api, "fleetmap_http_requests_waiting") == 0
    assert metric(api, "fleetmap_ingest_backlog_seconds") == 0
    assert api.client.get("/maps/busy").json()["stats"]["scans_integrated"] == 5


def test_a_read_is_served_after_the_longest_wait_if_the_backlog_stays() -> None:
    with running_api(ApiSettings(ingest_backlog=0.05, max_read_delay=0.4)) as api:
        api.client.put("/maps/other")
        with backlog(api, "busy"):
            started = time.monotonic()
            response = api.client.get("/maps/other")
            waited = time.monotonic() - started
            assert response.status_code == 200
            assert 0.35 <= waited < 3.0
        assert metric(api, "fleetmap_http_delay_timeouts_total") == 1
        assert metric(api, "fleetmap_http_delayed_requests_total") == 1


def test_the_gate_can_be_switched_off() -> None:
    with running_api(ApiSettings(ingest_backlog=0.0)) as api:
        api.client.put("/maps/other")
        with backlog(api, "busy"):
            started = time.monotonic()
            assert api.client.get("/maps/other").status_code == 200
            assert time.monotonic() - started < 0.3
        assert metric(api, "fleetmap_http_delayed_requests_total") == 0


def test_exempt_requests() -> None:
    def scope(method: str, path: str) -> dict[str, object]:
        return {"type": "http", "method": method, "path": path}

    assert is_exempt(scope("GET", "/healthz")) and is_exempt(scope("GET", "/metrics"))
    assert is_exempt(scope("POST", "/maps/m/scans"))
    assert not is_exempt(scope("GET", "/maps/m/scans"))
    assert not is_exempt(scope("GET", "/maps/m/tiles/0/0/0.png"))
    assert not is_exempt(scope("POST", "/maps/m/cells"))


def test_waiting_requests_go_on_in_arrival_order_as_soon_as_the_backlog_clears() -> None:
    """The gate on its own, with a backlog the test sets: nobody waits while it is low; arrivals
    during a backlog wait, also those that come while it is already low again but others still wait
    (no overtaking); all go on, first come first, at the first check after it clears."""
    level = {"backlog": 0.0}
    gate = IngestGate(lambda: level["backlog"], threshold=0.01, max_wait=10.0, poll=0.005)
    order: list[int] = []

    async def request(k: int) -> None:
        await gate.admit()
        order.append(k)

    async def main() -> None:
        assert await gate.admit() == 0.0
        level["backlog"] = 0.5
        tasks = [asyncio.create_task(request(k)) for k in range(3)]
        await asyncio.sleep(0.05)
        assert order == [] and gate.waiting == 3
        tasks.append(asyncio.create_task(request(3)))
        await asyncio.sleep(0.05)
        assert order == []
        level["backlog"] = 0.0
        await asyncio.wait_for(asyncio.gather(*tasks), 2.0)

    asyncio.run(main())
    assert order == [0, 1, 2, 3]
    assert gate.delayed == 4 and gate.timeouts == 0 and gate.waiting == 0
    assert gate.delay_seconds >= 4 * 0.05


def test_the_service_takes_the_gate_options_and_reports_it(service_factory) -> None:  # noqa: ANN001
    svc = service_factory("--in-memory", "--ingest-backlog-ms", "5", "--max-read-delay-ms", "200")
    text = httpx.get(f"{svc.base_url}/metrics", timeout=10).text
    for name in ("fleetmap_ingest_backlog_seconds", "fleetmap_http_delayed_requests_total",
                 "fleetmap_http_delay_seconds_total", "fleetmap_http_delay_timeouts_total"):  # fmt: skip
        assert f"\n{name} 0.0\n" in text, name


def test_the_service_freezes_its_start_up_objects(service_factory) -> None:  # noqa: ANN001
    """`fleetmap serve` moves what lives as long as the process out of the collector's walks, so a
    full collection (set off by requests that allocate many objects) does not stall ingest."""
    svc = service_factory("--in-memory")
    samples = {
        s.name: s.value
        for family in text_string_to_metric_families(httpx.get(f"{svc.base_url}/metrics", timeout=10).text)
        for s in family.samples
    }
    assert samples["fleetmap_gc_frozen_objects"] > 50_000


def test_http_is_parsed_in_c() -> None:
    """uvicorn's automatic choice (what `fleetmap serve` uses) is httptools, a dependency: each request
    costs the service a quarter less CPU and GIL time than with the pure-Python h11."""
    config = uvicorn.Config(create_app(MapRegistry()), http="auto")
    config.load()
    assert config.http_protocol_class.__name__ == "HttpToolsProtocol"
