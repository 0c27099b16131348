"""Robot updates of `GET /maps/{map_id}/events`: full `robots` events for old clients, and with
`?robots=delta` a full event first, then `robots_delta` events that carry only what changed.

Against the real service as a process: robots publish over real Zenoh sessions (online while their
liveliness token lives) or post over HTTP, the map is small enough in robots (`--max-robots-per-map`)
that the service forgets one, and the streams are read over real sockets.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import httpx
import numpy as np
from fleetmap_client.publisher import ScanPublisher
from fleetmap_client.rest import FleetmapClient, parse_sse
from service_process import ServiceProcess, wait_for

from fleetmap.api.robots_feed import RobotsFeed
from fleetmap.api_models import RobotsDeltaEvent, RobotsEvent
from fleetmap.codec import encode_json
from fleetmap.config import MapConfig
from fleetmap.registry import MapRegistry
from fleetmap.scan import Pose2D, Scan

MAP = "fleet"


def scan_at(x: float, y: float) -> Scan:
    """A small fan of returns 2 m ahead of a sensor at (x, y)."""
    return Scan.from_fan((x, y, 0.0), -0.5, 0.01, np.full(100, 2.0), 0.05, 30.0)


class StreamReader:
    """Reads one event stream in a thread: (event, data) pairs on a queue, None when it ended. It
    ends when the map is deleted (the test's last step), so no reader outlives its test."""

    def __init__(self, url: str, headers: dict[str, str] | None = None) -> None:
        self.events: queue.Queue[tuple[str, dict[str, Any]] | None] = queue.Queue()
        self.seen: list[tuple[str, dict[str, Any]]] = []
        self._thread = threading.Thread(target=self._run, args=(url, headers or {}), daemon=True)
        self._thread.start()

    def _run(self, url: str, headers: dict[str, str]) -> None:
        try:
            with httpx.stream("GET", url, headers=headers, timeout=httpx.Timeout(10, read=60)) as r:
                assert r.status_code == 200, r.read()
                for pair in parse_sse(r.iter_lines()):
                    self.events.put(pair)
        finally:
            self.events.put(None)

    def until(self, done: Callable[[str, dict[str, Any]], bool], timeout: float = 30.0) -> None:
        """Take events (into `seen`) until `done(event, data)` is true for one of them."""
        deadline = time.monotonic() + timeout
        while True:
            item = self.events.get(timeout=max(0.01, deadline - time.monotonic()))
            assert item is not None, f"the stream ended; it sent {[e for e, _ in self.seen]}"
            self.seen.append(item)
            if done(*item):
                return

    def ended(self) -> bool:
        self._thread.join(10)
        return not self._thread.is_alive()


def folded(events: list[tuple[str, dict[str, Any]]]) -> RobotsEvent:
    """The robots after applying a stream's robots events in order; the first must be full."""
    robot_events = [(e, d) for e, d in events if e in ("robots", "robots_delta")]
    assert robot_events and robot_events[0][0] == "robots", [e for e, _ in robot_events]
    view = RobotsEvent.model_validate(robot_events[0][1])
    for event, data in robot_events[1:]:
        if event == "robots":
            view = RobotsEvent.model_validate(data)
        else:
            view = view.apply(RobotsDeltaEvent.model_validate(data))
    return view


def current_robots(svc: ServiceProcess, map_id: str = MAP) -> RobotsEvent:
    """The map's robots now: the first event of a new stream without deltas (a full one)."""
    with httpx.stream("GET", f"{svc.base_url}/maps/{map_id}/events", timeout=10) as r:
        for event, data in parse_sse(r.iter_lines()):
            if event == "robots":
                return RobotsEvent.model_validate(data)  # leaving `with` closes the stream
    raise AssertionError("the stream ended before its robots event")


def post(http: httpx.Client, robot: str, seq: int, x: float, y: float, map_id: str = MAP) -> None:
    """Robot `robot`'s scan `seq`, taken at (x, y), over HTTP; returns once it is integrated."""
    r = http.post(
        f"/maps/{map_id}/scans",
        params={"robot_id": robot},
        content=encode_json(scan_at(x, y), seq),
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 200, r.text


def test_deltas_applied_in_order_equal_the_full_state(service_factory: Callable[..., ServiceProcess]) -> None:
    svc = service_factory("--max-robots-per-map", "3")
    http = httpx.Client(base_url=svc.base_url, timeout=30)
    assert http.put(f"/maps/{MAP}", json={"resolution": 0.05, "tile_size": 64}).status_code == 201
    deltas = StreamReader(f"{svc.base_url}/maps/{MAP}/events?robots=delta")
    plain = StreamReader(f"{svc.base_url}/maps/{MAP}/events")  # a client that knows no deltas
    folding = FleetmapClient(svc.base_url)
    client_events: list[tuple[str, dict[str, Any]]] = []
    client_thread = threading.Thread(
        target=lambda: client_events.extend(folding.events(MAP)), daemon=True
    )  # ends with the map's `deleted` event
    client_thread.start()
    deltas.until(lambda e, _d: e == "robots")  # connected: the full event comes first
    plain.until(lambda e, _d: e == "robots")

    # Two robots over Zenoh (online while they live), one over HTTP (never online); all move.
    with ScanPublisher(MAP, "z1", connect=svc.zenoh_endpoint) as z1:
        with ScanPublisher(MAP, "z2", connect=svc.zenoh_endpoint) as z2:
            assert z1.wait_connected(15) and z2.wait_connected(15)
            for k in range(6):
                assert z1.publish(scan_at(0.1 * k, 0.0)) and z2.publish(scan_at(0.0, 0.1 * k))
                post(http, "h3", k, 0.2 * k, 1.0)
            wait_for(
                lambda: {r.scans_integrated for r in current_robots(svc).robots.values()} == {6},
                timeout=30, what="every scan integrated",
            )  # fmt: skip
            assert z1.publish(scan_at(1.0, 0.0))
        # z2 went offline; its scans are in.
        wait_for(lambda: not current_robots(svc).robots["z2"].online, timeout=30, what="z2 offline")
    wait_for(lambda: not current_robots(svc).robots["z1"].online, timeout=30, what="z1 offline")
    # The delta stream must have shown h3 before it is forgotten, or there is nothing to remove: a
    # stream whose poll (every 100 ms) comes after all of the above sees only its result.
    if "h3" not in folded(deltas.seen).robots:
        deltas.until(lambda e, _d: e.startswith("robots") and "h3" in folded(deltas.seen).robots)
    # A fourth robot on a map that keeps three: the offline one heard from least recently goes.
    post(http, "h4", 0, 3.0, 3.0)

    def forgotten_one() -> RobotsEvent | None:
        now = current_robots(svc)
        return now if "h4" in now.robots and len(now.robots) == 3 else None

    final = wait_for(forgotten_one, timeout=30, what="a robot forgotten for h4")
    assert final.robots["z1"].scans_integrated == 7 and len(final.robots["z1"].trail) == 7
    assert final.robots["h4"].trail == [[3.0, 3.0]] and final.robots["h4"].online is False

    deltas.until(lambda e, _d: e == "robots_delta" and folded(deltas.seen) == final)
    plain.until(lambda e, d: e == "robots" and RobotsEvent.model_validate(d) == final)
    assert [e for e, _ in deltas.seen if e.startswith("robots")].count("robots") == 1
    assert {e for e, _ in plain.seen} <= {"robots", "tiles"}  # never a delta without asking
    assert any(d["removed"] for e, d in deltas.seen if e == "robots_delta")  # the forgotten robot

    # One scan of one robot: the next delta holds that robot and its one new trail point.
    post(http, "h4", 1, 3.5, 3.0)
    deltas.until(lambda e, _d: e == "robots_delta")
    delta = RobotsDeltaEvent.model_validate(deltas.seen[-1][1])
    assert list(delta.robots) == ["h4"] and delta.removed == []
    change = delta.robots["h4"]
    assert change.trail == [[3.5, 3.0]] and change.pose == [3.5, 3.0, 0.0] and change.scans_integrated == 2
    assert folded(deltas.seen) == current_robots(svc)

    # A reconnect (Last-Event-ID: the last tiles version seen) starts with a full robots event.
    version = max(d["version"] for e, d in deltas.seen if e == "tiles")
    again = StreamReader(f"{svc.base_url}/maps/{MAP}/events?robots=delta", {"Last-Event-ID": str(version)})
    again.until(lambda e, _d: e in ("robots", "robots_delta"))
    event, data = again.seen[-1]
    assert event == "robots" and RobotsEvent.model_validate(data) == folded(deltas.seen)

    # The Python client folds the deltas it asked for into full robots events.
    wait_for(
        lambda: [d for e, d in client_events if e == "robots"][-1:] == [current_robots(svc).model_dump()],
        timeout=30, what="the client's last robots event to be the full state",
    )  # fmt: skip
    assert all(e != "robots_delta" for e, _ in client_events)

    assert http.delete(f"/maps/{MAP}").status_code == 204
    for reader in (deltas, plain, again):
        assert reader.ended()
    client_thread.join(10)
    assert client_events[-1] == ("deleted", {"id": MAP})
    folding.close()
    http.close()


def test_a_robot_forgotten_and_back_under_its_id_is_removed_then_new() -> None:
    """Between two deltas a robot is forgotten and another takes its id: the delta removes it and
    gives the new one its whole (new) trail, not the old trail plus new points. In-process: the
    service's HTTP face cannot forget and re-create a robot between two polls of a stream."""
    registry = MapRegistry(MapConfig(), workers=0)
    entry, _ = registry.create("m")
    robot = entry.robot("r")
    for k in range(5):
        robot.add_pose(Pose2D(float(k), 0.0, 0.0))
        entry.touch(robot)
    feed = RobotsFeed(entry, registry.lock)
    base = feed.full()
    assert base is not None and len(base.robots["r"].trail) == 5
    assert feed.delta() is None  # nothing changed
    with registry.lock:
        entry.forget("r")
        again = entry.robot("r")
        again.add_pose(Pose2D(9.0, 9.0, 0.0))
        entry.touch(again)
    delta = feed.delta()
    assert delta is not None and delta.removed == ["r"] and delta.robots["r"].trail == [[9.0, 9.0]]
    assert base.apply(delta).robots["r"].trail == [[9.0, 9.0]]
    assert base.apply(delta) == RobotsFeed(entry, registry.lock).full()
    assert feed.delta() is None


def test_streams_of_one_map_make_each_robots_json_once(monkeypatch: Any) -> None:
    """Every stream of a map built the same robot models and JSON again: 100 streams of a map with
    200 robots moving took 120 ms of the event loop's core per 100 ms poll (16 ms now). Each robot's
    JSON is made by the first stream that sends it, and sent as is by the others: here 10 streams of
    20 robots make 20 robots' JSON per event, not 200, and all send the same, valid, events."""
    import fleetmap.api.robots_feed as robots_feed

    made: list[int] = []
    real = robots_feed.robot_live

    def counted(*args: Any, **kwargs: Any) -> Any:
        made.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(robots_feed, "robot_live", counted)
    registry = MapRegistry(MapConfig(), workers=0)
    entry, _ = registry.create("m")
    robots = [entry.robot(f"r{k:02d}") for k in range(20)]

    def move(step: int) -> None:
        with registry.lock:
            for k, robot in enumerate(robots):
                robot.add_pose(Pose2D(float(step), float(k), 0.0))
                robot.scans_integrated += 1
                entry.touch(robot)

    move(0)
    feeds = [RobotsFeed(entry, registry.lock) for _ in range(10)]
    bases = [feed.full() for feed in feeds]
    assert len(made) == 20 and all(other == bases[0] for other in bases)
    base = bases[0]
    assert base is not None
    for step in range(1, 4):
        made.clear()
        move(step)
        deltas = [feed.delta() for feed in feeds]
        assert len(made) == 20 and all(other == deltas[0] for other in deltas)
        delta = deltas[0]
        assert delta is not None
        base = base.apply(delta)
        assert base == RobotsFeed(entry, registry.lock).full()
    # The events are the models' own JSON, byte for byte.
    move(4)
    data = feeds[0].delta_json()
    assert data is not None and RobotsDeltaEvent.model_validate_json(data).model_dump_json() == data
    data = RobotsFeed(entry, registry.lock).full_json()
    assert data is not None and RobotsEvent.model_validate_json(data).model_dump_json() == data
    # A stream that fell behind gets its own (longer) trails, made for it, and the right ones.
    late = RobotsFeed(entry, registry.lock)
    late.full_json()
    move(5)
    move(6)
    made.clear()
    behind = late.delta()
    assert behind is not None and len(made) == 20
    assert all(len(change.trail) == 2 for change in behind.robots.values())
    assert behind.robots["r03"].trail == [[5.0, 3.0], [6.0, 3.0]]


def test_streams_of_one_map_share_their_tiles_events(monkeypatch: Any) -> None:
    """Each stream made its own tiles event from the change feed: 100 streams of a map that 200
    robots change took 73 ms of the event loop per 100 ms poll (0.6 ms now). A stream whose version
    lies within the last event made sends that one: here 10 streams in step make one event per poll,
    not 10, and every stream is told of every tile changed after its version, a lagging one too."""
    import fleetmap.api.events as events
    from fleetmap.change_feed import ChangeFeed

    made: list[int] = []
    real = events.tile_windows

    def counted(*args: Any, **kwargs: Any) -> Any:
        made.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(events, "tile_windows", counted)
    feed = ChangeFeed(start=100)
    versions = [feed.version] * 10
    for step in range(3):
        made.clear()
        for k in range(5):
            feed.record([(step, k)])
        sent = []
        for n, version in enumerate(versions):
            if n == 5:
                feed.record([(9, 9)])  # a scan between two streams' polls
            versions[n], data = events.tiles_event(feed, version, 16)
            assert data is not None
            sent.append(json.loads(data))
        assert len(made) == 1, made  # one event, shared by all ten
        windows = {tuple(w) for w in sent[0]["tiles"]}
        assert {(step * 16, k * 16, step * 16 + 16, k * 16 + 16) for k in range(5)} <= windows
        assert all(event == sent[0] for event in sent)
        assert len(set(versions)) == 1
        # Tile (9, 9), changed after the shared event was made, comes with the next poll.
        assert events.tiles_event(feed, versions[0], 16)[1] is not None
        versions = [feed.version] * 10
    # A stream behind the last event gets its own, with everything changed after its version.
    behind = feed.version
    feed.record([(1, 1)])
    feed.record([(2, 2)])
    events.tiles_event(feed, behind + 1, 16)  # the last event made: tile (2, 2) only
    _, data = events.tiles_event(feed, behind, 16)
    assert data is not None
    assert {tuple(w) for w in json.loads(data)["tiles"]} == {(16, 16, 32, 32), (32, 32, 48, 48)}


def test_a_stream_resumed_from_long_ago_does_not_share_its_event() -> None:
    """A viewer resuming with an old `Last-Event-ID` gets everything changed since; that event was
    left for the streams in step to share, which then told every other viewer of the map of all
    those tiles again (each refetched them all), not just of what changed since their last event."""
    from fleetmap.api.events import tiles_event
    from fleetmap.change_feed import ChangeFeed

    feed = ChangeFeed(start=100)
    live = feed.version
    for tile in [(0, 0), (1, 0), (2, 0)]:  # a live stream follows the map, poll by poll
        feed.record([tile])
        live, data = tiles_event(feed, live, 16)
        assert data is not None
    feed.record([(9, 9)])
    # A stream resumed from the start (the viewer slept): all four tiles, rightly.
    _, resumed = tiles_event(feed, 100, 16)
    assert resumed is not None and len(json.loads(resumed)["tiles"]) == 4
    # The live stream is told of the one tile changed since its last event.
    _, data = tiles_event(feed, live, 16)
    assert data is not None and json.loads(data)["tiles"] == [[144, 144, 160, 160]], data


def test_a_stream_resumed_after_the_map_went_unwatched_does_not_share_its_event(monkeypatch: Any) -> None:
    """The last event shared dates from when viewers last followed the map. A viewer that opens
    later, and one resuming from back then (a laptop woken after the night), poll: the resumed one's
    event of everything changed since started after that old shared one's start, so it was left
    for sharing, and the live viewer, in step, was told of every tile the night changed (which it
    had loaded fresh) instead of the one changed since it opened."""
    import fleetmap.api.events as events
    from fleetmap.change_feed import ChangeFeed

    clock = [1000.0]
    monkeypatch.setattr(events.time, "monotonic", lambda: clock[0])
    feed = ChangeFeed(start=100)
    evening = feed.version
    for tile in [(0, 0), (1, 0)]:  # the evening's viewer follows the map, poll by poll
        feed.record([tile])
        evening, data = events.tiles_event(feed, evening, 16)
        assert data is not None
    for tile in [(2, 0), (3, 0), (4, 0)]:  # the night: nobody watches
        feed.record([tile])
    clock[0] += 8 * 3600
    live, data = events.tiles_event(feed, feed.version, 16)  # a viewer opens in the morning
    assert data is None
    feed.record([(9, 9)])
    _, data = events.tiles_event(feed, evening, 16)  # the evening's viewer wakes up: the night
    assert data is not None and len(json.loads(data)["tiles"]) == 4
    _, data = events.tiles_event(feed, live, 16)
    assert data is not None and json.loads(data)["tiles"] == [[144, 144, 160, 160]], data
