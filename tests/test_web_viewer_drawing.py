"""How the web viewer draws its robots, in headless Chromium against the real service as a process:
counts and identities from the page's `window.__fleetmapViewerStats`, never timings.

- A `robots_delta` that appends one point to a drawn trail extends that trail: the same polyline on
  the same SVG path takes the new point (101 drawn points after 100), no trail is drawn whole again,
  and the robot's list row is the same element. One more point past the 100 a
  stream keeps drops the oldest, and the drawn trail is still exactly the service's.
- Several events arriving before the next animation frame are drawn once, in that frame.

Robots post over HTTP (each answer waits for the scan's integration), so the test knows when the
map's robots changed. Same Chromium and skip rule as test_web_viewer.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from service_process import ServiceProcess
from test_events_robots import current_robots, post
from test_web_viewer import CHROMIUM, _wait

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)

ROBOT = "t1"
#: Trail points a stream keeps per robot (the service's trail length).
TRAIL_POINTS = 100

#: Robot t1's drawn trail in metres (its trail points, then its pose).
_DRAWN_JS = """
() => {
  const v = window.fleetmapViewer, r = v.state.robots.get('t1');
  if (!r) return [];
  return r.trail.getLatLngs().map((ll) => [Math.round(ll.lng * v.state.res * 1000) / 1000,
                                           Math.round(ll.lat * v.state.res * 1000) / 1000]);
}
"""
#: Tag what draws robot t1 (its polyline, the polyline's SVG path, its list row) with a JS property.
_TAG_JS = """
() => {
  const r = window.fleetmapViewer.state.robots.get('t1');
  r.trail.tagged = true;
  r.trail.getElement().tagged = true;
  document.querySelector('#robot-list li[data-robot-id="t1"]').tagged = true;
  return {...window.__fleetmapViewerStats};
}
"""
#: Whether what _TAG_JS tagged is still what draws robot t1.
_TAGGED_JS = """
() => {
  const r = window.fleetmapViewer.state.robots.get('t1');
  return {
    polyline: r.trail.tagged === true,
    path: r.trail.getElement().tagged === true && r.trail.getElement().isConnected,
    row: document.querySelector('#robot-list li[data-robot-id="t1"]').tagged === true,
    paths: document.querySelectorAll('.leaflet-overlay-pane path').length,
    stats: {...window.__fleetmapViewerStats},
  };
}
"""
#: Dispatch `deltas` (robots_delta event data) on the page's open event stream, all in this one
#: task (so before the next frame), then resolve after two frames, with the stats before and after.
#: The network cannot promise that several events land within one frame; dispatching on the page's
#: own EventSource runs the viewer's real handler on them.
_BURST_JS = """
async (deltas) => {
  const es = window.fleetmapViewer.state.events;
  const before = {...window.__fleetmapViewerStats};
  for (const d of deltas) es.dispatchEvent(new MessageEvent('robots_delta', {data: JSON.stringify(d)}));
  const drawnAtOnce = {...window.__fleetmapViewerStats};
  await new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)));
  return {before, drawnAtOnce, after: {...window.__fleetmapViewerStats}};
}
"""


@pytest.fixture(scope="module")
def in_memory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One in-memory service for the module's tests, each drawing robot t1 of a map of its own."""
    with ServiceProcess(tmp_path_factory.mktemp("viewer-drawing"), ["--in-memory"]) as service:
        yield service


def _drawn_as_service(svc: ServiceProcess, map_id: str) -> list[list[float]]:
    """Robot t1's trail on `map_id` as the page should draw it: the service's trail points, then
    its pose."""
    r = current_robots(svc, map_id).robots[ROBOT]
    assert r.pose is not None
    return [[round(x, 3), round(y, 3)] for x, y in [*r.trail, r.pose[:2]]]


def test_delta_extends_the_drawn_trail(page: Any, in_memory: ServiceProcess) -> None:
    svc, map_id = in_memory, "delta"  # a map of its own on the module's service
    http = httpx.Client(base_url=svc.base_url, timeout=30)
    assert http.put(f"/maps/{map_id}", json={"resolution": 0.05, "tile_size": 64}).status_code == 201
    for k in range(TRAIL_POINTS - 1):
        post(http, ROBOT, k, 0.05 * k, 1.0, map_id)
    page.goto(f"{svc.base_url}/#map={map_id}")
    _wait(page, "() => document.getElementById('status').dataset.state === 'connected'", what="connected")
    want = _drawn_as_service(svc, map_id)
    assert len(want) == TRAIL_POINTS  # 99 trail points and the pose
    _wait(page, f"(want) => JSON.stringify(({_DRAWN_JS})()) === JSON.stringify(want)", want, what="the trail")
    before = page.evaluate(_TAG_JS)

    post(http, ROBOT, TRAIL_POINTS - 1, 0.05 * (TRAIL_POINTS - 1), 1.0, map_id)
    want = _drawn_as_service(svc, map_id)
    assert len(want) == TRAIL_POINTS + 1
    _wait(
        page, f"(want) => JSON.stringify(({_DRAWN_JS})()) === JSON.stringify(want)", want, what="101 points"
    )
    now = page.evaluate(_TAGGED_JS)
    assert now["polyline"] and now["path"] and now["row"], f"redrawn from scratch: {now}"
    assert now["paths"] == 1, f"one robot, one trail path: {now}"
    assert now["stats"]["trailsBuilt"] == before["trailsBuilt"], (before, now)
    assert now["stats"]["trailsExtended"] > before["trailsExtended"], (before, now)
    assert now["stats"]["rowsBuilt"] == before["rowsBuilt"], (before, now)

    # One point past what a stream keeps: the oldest goes, and the page still draws the service's trail.
    post(http, ROBOT, TRAIL_POINTS, 0.05 * TRAIL_POINTS, 1.5, map_id)
    want = _drawn_as_service(svc, map_id)
    assert len(want) == TRAIL_POINTS + 1 and want[0] == [0.05, 1.0], want[:2]
    _wait(
        page,
        f"(want) => JSON.stringify(({_DRAWN_JS})()) === JSON.stringify(want)",
        want,
        what="the cut trail",
    )
    final = page.evaluate(_TAGGED_JS)
    assert final["polyline"] and final["path"] and final["row"], final
    assert final["stats"]["trailsBuilt"] == before["trailsBuilt"], (before, final)
    assert not page.page_errors, page.page_errors
    http.close()


def test_events_within_one_frame_are_drawn_once(page: Any, in_memory: ServiceProcess) -> None:
    svc, map_id = in_memory, "burst"  # a map of its own on the module's service
    http = httpx.Client(base_url=svc.base_url, timeout=30)
    assert http.put(f"/maps/{map_id}", json={"resolution": 0.05, "tile_size": 64}).status_code == 201
    for k in range(3):
        post(http, ROBOT, k, 0.05 * k, 1.0, map_id)
    page.goto(f"{svc.base_url}/#map={map_id}")
    _wait(page, "() => document.getElementById('status').dataset.state === 'connected'", what="connected")
    want = _drawn_as_service(svc, map_id)
    _wait(page, f"(want) => JSON.stringify(({_DRAWN_JS})()) === JSON.stringify(want)", want, what="the trail")

    burst = 5
    deltas = [
        {
            "trail_length": TRAIL_POINTS,
            "robots": {ROBOT: {"online": False, "pose": [1.0 + 0.1 * k, 2.0, 0.0],
                               "scans_integrated": 3 + k + 1, "trail": [[1.0 + 0.1 * k, 2.0]]}},
            "removed": [],
        }
        for k in range(burst)
    ]  # fmt: skip
    got = page.evaluate(_BURST_JS, deltas)
    before, at_once, after = got["before"], got["drawnAtOnce"], got["after"]
    assert at_once == before, f"drawn while the events came in, not in the next frame: {got}"
    assert after["frames"] - before["frames"] == 1, got
    assert after["robotsDrawn"] - before["robotsDrawn"] == 1, got
    assert after["trailsExtended"] - before["trailsExtended"] == 1, got
    assert after["rowsUpdated"] - before["rowsUpdated"] == 1, got
    drawn = page.evaluate(_DRAWN_JS)
    assert drawn[-burst - 1 :] == [[round(1.0 + 0.1 * k, 3), 2.0] for k in range(burst)] + [[1.4, 2.0]], drawn
    assert len(drawn) == len(want) + burst
    assert page.evaluate(
        "() => document.querySelector('#robot-list li[data-robot-id=\"t1\"] .scans').textContent"
    ) == (f"{3 + burst} scans")
    assert not page.page_errors, page.page_errors
    http.close()
