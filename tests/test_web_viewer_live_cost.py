"""What the web viewer costs under a live fleet, in headless Chromium against a real service with
robots publishing through real Zenoh sessions (tests/robot_process.py).

The assertions are counts and identities, never timings: robot markers are moved in place (the same
DOM elements before and after many robots events, and no more elements), a tile that changes with
every event is requested at most once per TILE_REFRESH_MS of the elapsed time (requests counted with
`page.on("request")`), and a hidden tab requests no tile and holds no event stream. Same Chromium and
skip rule as test_web_viewer.py.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
from service_process import RobotProcess, ServiceProcess, wait_for
from test_web_viewer import CHROMIUM, SHOW_MS, _wait
from test_web_viewer_recovery import _scan

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)

#: The viewer's TILE_REFRESH_MS (clients/web/config.js): one tile is requested at most this often.
TILE_REFRESH_S = 0.5

#: Counts the page's `tiles` and robots (full or delta) events from now on (window.eventsSeen), on
#: the open stream.
_COUNT_EVENTS_JS = """
() => {
  window.eventsSeen = {tiles: 0, robots: 0};
  const es = window.fleetmapViewer.state.events;
  es.addEventListener('tiles', () => { window.eventsSeen.tiles += 1; });
  // The viewer asks for deltas: after the first full `robots` event, robots come as `robots_delta`.
  for (const kind of ['robots', 'robots_delta']) {
    es.addEventListener(kind, () => { window.eventsSeen.robots += 1; });
  }
}
"""
#: Hide or show the page as a minimised window or a background tab would. Headless Chromium has no
#: window to minimise and no CDP command that hides a page, so visibilityState is overridden and the
#: visibilitychange event the browser would send is dispatched; the viewer's code path is the real one.
_SET_VISIBILITY_JS = """
(hidden) => {
  const visibility = hidden ? 'hidden' : 'visible';
  Object.defineProperty(document, 'visibilityState', {configurable: true, get: () => visibility});
  Object.defineProperty(document, 'hidden', {configurable: true, get: () => hidden});
  document.dispatchEvent(new Event('visibilitychange'));
}
"""
#: The page is hidden from its start, as one opened in a background tab (added before its scripts run).
_HIDDEN_FROM_THE_START_JS = """
Object.defineProperty(document, 'visibilityState', {configurable: true, get: () => 'hidden'});
Object.defineProperty(document, 'hidden', {configurable: true, get: () => true});
"""
_STATUS_JS = "(s) => document.getElementById('status').dataset.state === s"
#: The viewer's period of asking for the map list (clients/web/config.js, MAPS_REFRESH_MS).
MAP_LIST_PERIOD_S = 5.0


@pytest.fixture
def counted_page(page: Any) -> Any:
    """conftest's page, counting its tile requests: `page.tile_requests`, tile path
    (no query) -> requests; and its requests of the map list, `page.map_list_requests`."""
    page.tile_requests = Counter()
    page.map_list_requests = 0

    def count(request: Any) -> None:
        path = urlsplit(request.url).path
        if "/tiles/" in path:
            page.tile_requests.update([path])
        elif path == "/maps":
            page.map_list_requests += 1

    page.on("request", count)
    return page


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One in-memory service for the module's tests: each shows a map of its own (`map_id`), and
    the robots of a test are stopped when it ends."""
    with ServiceProcess(tmp_path_factory.mktemp("viewer-live-cost"), ["--in-memory"]) as service:
        yield service


@pytest.fixture
def map_id(request: pytest.FixtureRequest) -> str:
    """The test's own map on the module's service: its name without `test_` (at most 64 characters)."""
    return request.node.originalname.removeprefix("test_")[:64]


@pytest.fixture
def robots(svc: ServiceProcess, map_id: str, tmp_path: Path) -> Iterator[Callable[..., RobotProcess]]:
    """Start robot processes on `svc` publishing to `map_id` (`robots("r1", sim=1, rate=20,
    count=400)`): they stay online until the test ends, when they are stopped."""
    started: list[RobotProcess] = []

    def start(robot_id: str, **options: object) -> RobotProcess:
        robot = RobotProcess(svc.zenoh_endpoint, map_id, robot_id, log_dir=tmp_path, linger=-1, **options)
        started.append(robot.start())
        return robot

    yield start
    for robot in started:
        robot.stop()


def _tile_requests(page: Any) -> int:
    """Tile requests the page made so far. Playwright hands events over only during its own calls:
    one first, so none made while the test slept is missed."""
    page.evaluate("() => 0")
    return sum(page.tile_requests.values())


def _map_version(base: str, map_id: str) -> int:
    r = httpx.get(f"{base}/maps/{map_id}", timeout=10.0)
    return int(r.json()["stats"]["version"]) if r.status_code == 200 else -1


def _open_live(page: Any, base: str, map_id: str) -> None:
    """Open the viewer on `map_id` once it exists, wait until it is connected and shows its tiles."""
    wait_for(lambda: _map_version(base, map_id) > 0, timeout=60, what="the robots' map")
    page.goto(f"{base}/#map={map_id}")
    _wait(page, _STATUS_JS, "connected", what="connected")
    _wait(page, "() => document.querySelectorAll('#map img.leaflet-tile-loaded').length > 0", what="tiles")
    _wait(page, "() => window.fleetmapViewer.state.fitted", what="the view fitted to the map")


def test_robot_markers_are_moved_in_place(
    counted_page: Any, svc: ServiceProcess, map_id: str, robots: Callable[..., Any]
) -> None:
    """Three robots moving and scanning: across many robots events each marker (its element and its
    arrow) stays the same DOM object, tagged with a JS property before, and the counted_page's element count
    does not grow. The viewer used to rebuild every marker's icon on every event."""
    for k in range(3):
        robots(f"r{k + 1}", sim=k + 1, rate=10, count=400, beams=91)
    _open_live(counted_page, svc.base_url, map_id)
    _wait(
        counted_page,
        "() => document.querySelectorAll('.robot-marker svg').length === 3",
        what="three markers",
    )
    tagged = counted_page.evaluate(
        """() => {
          for (const el of document.querySelectorAll('.robot-marker')) {
            el.identity = el.dataset.robotId;
            el.querySelector('svg').identity = el.dataset.robotId;
          }
          return {
            elements: document.getElementsByTagName('*').length,
            at: Object.fromEntries([...window.fleetmapViewer.state.robots].map(([id, r]) =>
              [id, r.marker.getLatLng().toString()])),
          };
        }"""
    )
    counted_page.evaluate(_COUNT_EVENTS_JS)
    # Many robots events, and every robot moved since the tagging.
    _wait(counted_page, "() => window.eventsSeen.robots >= 15", what="15 robots events")
    _wait(
        counted_page,
        """(at) => [...window.fleetmapViewer.state.robots].every(([id, r]) =>
             r.marker.getLatLng().toString() !== at[id])""",
        tagged["at"],
        what="every robot moved",
    )
    after = counted_page.evaluate(
        """() => [...document.querySelectorAll('.robot-marker')].map((el) => ({
             id: el.dataset.robotId, el: el.identity, svg: el.querySelector('svg').identity}))"""
    )
    assert sorted(m["id"] for m in after) == ["r1", "r2", "r3"]
    for m in after:
        assert m["el"] == m["id"], f"robot {m['id']}'s marker element was replaced: {after}"
        assert m["svg"] == m["id"], f"robot {m['id']}'s arrow was rebuilt: {after}"
    elements = counted_page.evaluate("() => document.getElementsByTagName('*').length")
    # Generous: nothing but tiles Leaflet may add at an edge; a marker per event would add dozens.
    assert elements <= tagged["elements"] + 10, (tagged["elements"], elements)
    assert not counted_page.page_errors, counted_page.page_errors


def test_hot_tile_requested_at_refresh_rate(
    counted_page: Any, svc: ServiceProcess, map_id: str, robots: Callable[..., Any]
) -> None:
    """A robot scanning 40 times a second changes the tiles around it with every tiles event (up to
    10 a second). Each tile is requested at most once per TILE_REFRESH_S of the elapsed time, plus
    slack, however many events came, and the hottest tile is still refreshed. Counts, not timings:
    the bound grows with the elapsed time, so a slow machine only makes it looser."""
    robots("hot", sim=1, rate=40, count=4000, beams=181)
    _open_live(counted_page, svc.base_url, map_id)
    counted_page.evaluate(_COUNT_EVENTS_JS)
    counted_page.tile_requests.clear()
    started = time.monotonic()
    _wait(counted_page, "() => window.eventsSeen.tiles >= 40", what="40 tiles events")
    elapsed = time.monotonic() - started
    events = counted_page.evaluate("() => window.eventsSeen.tiles")
    hottest, fetches = (
        counted_page.tile_requests.most_common(1)[0] if counted_page.tile_requests else ("none", 0)
    )
    bound = elapsed / TILE_REFRESH_S + 2
    assert fetches <= bound, (
        f"tile {hottest} was requested {fetches} times in {elapsed:.1f} s ({events} tiles events);"
        f" at most {bound:.0f} expected: {counted_page.tile_requests}"
    )
    assert fetches >= 2, f"the changing tiles were not refreshed: {counted_page.tile_requests}"
    assert not counted_page.page_errors, counted_page.page_errors


def test_hidden_tab_fetches_nothing(
    counted_page: Any, svc: ServiceProcess, map_id: str, robots: Callable[..., Any]
) -> None:
    """Hidden, the counted_page closes its event stream and requests no tile while the map keeps changing;
    shown again, it reconnects and reloads its tiles."""
    robots("busy", sim=2, rate=20, count=4000, beams=181)
    _open_live(counted_page, svc.base_url, map_id)
    counted_page.evaluate(_SET_VISIBILITY_JS, True)
    _wait(counted_page, _STATUS_JS, "paused", what="the paused status")
    assert counted_page.evaluate("() => window.fleetmapViewer.state.events") is None
    # Let any request already under way finish, then watch the map change a good deal.
    _wait(
        counted_page, "() => [...document.querySelectorAll('#map img.leaflet-tile')].every((i) => i.complete)"
    )
    counted_page.tile_requests.clear()
    counted_page.map_list_requests = 0
    hidden_at = time.monotonic()
    version = _map_version(svc.base_url, map_id)
    wait_for(
        lambda: _map_version(svc.base_url, map_id) >= version + 40, timeout=60, what="40 more map changes"
    )
    # Longer than the map list's period (5 s), which it polled while hidden too.
    time.sleep(max(0.0, hidden_at + MAP_LIST_PERIOD_S + 1.0 - time.monotonic()))
    assert _tile_requests(counted_page) == 0, (
        f"a hidden counted_page requested tiles: {counted_page.tile_requests}"
    )
    assert counted_page.map_list_requests == 0, "a hidden page asked for the map list"

    counted_page.evaluate(_SET_VISIBILITY_JS, False)
    _wait(counted_page, _STATUS_JS, "connected", what="connected again")
    wait_for(lambda: _tile_requests(counted_page) > 0, timeout=SHOW_MS / 1000, what="tiles reloaded")
    assert counted_page.map_list_requests >= 1  # asked for at once when shown, not at the next period
    assert not counted_page.page_errors, counted_page.page_errors


def test_a_tab_opened_hidden_catches_up_when_shown(
    counted_page: Any, svc: ServiceProcess, map_id: str
) -> None:
    """A viewer opened in a background tab loads the map but opens no event stream; the map changes
    before the tab is shown, and the stream opened then reports only later changes. Shown, the page
    catches up as after a reconnect: its tiles are asked for again (they kept the map as it was
    when the page loaded)."""
    base = svc.base_url
    assert httpx.put(f"{base}/maps/{map_id}", json={}, timeout=10.0).status_code == 201
    _scan(base, map_id, "r1", 1, 2.0, 2.0)
    counted_page.add_init_script(_HIDDEN_FROM_THE_START_JS)
    counted_page.goto(f"{base}/#map={map_id}")
    _wait(counted_page, _STATUS_JS, "paused", what="the paused status")
    _wait(
        counted_page,
        "() => document.querySelectorAll('#map img.leaflet-tile-loaded').length > 0",
        what="tiles",
    )
    counted_page.tile_requests.clear()
    for seq in range(2, 5):  # the robot moves on: its ring of walls too, in view
        _scan(base, map_id, "r1", seq, 2.0 + 0.5 * seq, 2.0)

    counted_page.evaluate(_SET_VISIBILITY_JS, False)
    _wait(counted_page, _STATUS_JS, "connected", what="connected")
    wait_for(
        lambda: _tile_requests(counted_page) > 0, timeout=SHOW_MS / 1000, what="the tiles asked for again"
    )
    assert not counted_page.page_errors, counted_page.page_errors
