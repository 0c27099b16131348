"""End-to-end test of the web viewer (clients/web) in headless Chromium.

Everything is real: the service runs as a subprocess on free ports, a simulated robot publishes its
scans through a real Zenoh client session (with a liveliness token, as robots do), and Debian's
Chromium, driven by Playwright, loads the page the service serves at `/` with Leaflet from the
service's own /vendor/leaflet (no internet). The assertions are on what the page shows: "waiting
for robots" before any map, the map selector, tile images (HTTP 200, not transparent), live tile
refresh without a page reload, the robot in the list (online, then offline) and on the map at its
pose with its heading and trail, a clicked cell's values (equal to the engine's own map of the same
scans), the layer switch, a map keeping fewer layers, that map replaced by a snapshot (reloaded in
place), a deleted map, and the service going away.

Chromium comes from the Debian package `chromium` (`make system-deps` installs it); the test is
skipped, with that reason, only when /usr/bin/chromium is missing. `playwright install` is never used.
A screenshot of the page is saved to /tmp/viewer.png for a human to look at.
"""

from __future__ import annotations

import math
import re
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess

from fleetmap.codec import encode_binary
from fleetmap.config import MapConfig
from fleetmap.grid_map import STATE_OCCUPIED, GridMap
from fleetmap.scan import Scan
from fleetmap.sim.floorplan import FloorPlan, generate_floorplan
from fleetmap.sim.robot import SimulatedRobot
from fleetmap.wire import ALIVE_KEY, BINARY_ENCODING, SCAN_KEY

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SCREENSHOT = Path("/tmp/viewer.png")
MAP_ID = "viewer-e2e"
ROBOT_ID = "scout-1"
#: Scans in the first and the second batch the robot publishes.
FIRST_SCANS = 20
MORE_SCANS = 15
#: Functional bounds (not speed assertions): how long the page may take to show something.
SHOW_MS = 15_000

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)


# ---- the service and a robot ------------------------------------------------------------------------


class ZenohRobot:
    """A simulated robot publishing binary scans through its own Zenoh client session, with the
    liveliness token that tells the service it is online. Keeps its scans for a local reference map."""

    def __init__(self, endpoint: str, map_id: str, robot_id: str, plan: FloorPlan, seed: int) -> None:
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(cfg)
        self.token = self.session.liveliness().declare_token(
            ALIVE_KEY.format(map_id=map_id, robot_id=robot_id)
        )
        self.publisher = self.session.declare_publisher(
            SCAN_KEY.format(map_id=map_id, robot_id=robot_id),
            encoding=zenoh.Encoding(BINARY_ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self.sim = SimulatedRobot(plan, seed, speed=1.0, scan_rate=5.0)
        self.scans: list[Scan] = []

    def wait_matched(self, timeout: float = 10.0) -> None:
        """Samples published before the service's subscriber is known would be dropped: wait for it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = self.publisher.matching_status
            if getattr(status, "matching", status):
                return
            time.sleep(0.02)
        raise AssertionError("the service's scan subscriber never matched the robot's publisher")

    def publish(self, n: int) -> None:
        for _ in range(n):
            scan = self.sim.tick()
            self.publisher.put(encode_binary(scan, seq=len(self.scans), stamp=self.sim.time))
            self.scans.append(scan)

    def close(self) -> None:
        """Leave: undeclare the token (the service then reports the robot offline) and the session."""
        self.publisher.undeclare()
        self.token.undeclare()
        self.session.close()


def _wait_integrated(base: str, n: int, timeout: float = 30.0) -> dict[str, Any]:
    """GET /maps/{MAP_ID} until it has integrated `n` scans; returns that answer."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        r = httpx.get(f"{base}/maps/{MAP_ID}", timeout=5.0)
        if r.status_code == 200:
            last = r.json()
            if last["stats"]["scans_integrated"] >= n:
                return last
        time.sleep(0.05)
    raise AssertionError(f"the service did not integrate {n} scans within {timeout} s; last answer {last}")


def _occupied_cell(scans: list[Scan]) -> tuple[int, int, float]:
    """The most certainly occupied cell (i, j, probability) of the engine's own map of `scans`, built
    here with the service's default configuration: the reference for what the page must show."""
    gmap = GridMap(MapConfig())
    for scan in scans:
        gmap.integrate(scan)
    bounds = gmap.known_bounds()
    assert bounds is not None
    state = gmap.region("state", *bounds)
    prob = gmap.region("probability", *bounds)
    prob = np.where(state == STATE_OCCUPIED, np.nan_to_num(prob, nan=0.0), -1.0)
    row, col = np.unravel_index(int(np.argmax(prob)), prob.shape)
    assert prob[row, col] > 0.5, "the robot saw no wall"
    return bounds[0] + int(col), bounds[1] + int(row), float(prob[row, col])


# ---- page helpers ------------------------------------------------------------------------------------

#: The URLs of the tile images on the map that have loaded.
_LOADED_TILES_JS = "[...document.querySelectorAll('#map img.leaflet-tile-loaded')].map((img) => img.src)"

#: The layer selector's options, comma-separated.
_LAYER_OPTIONS_JS = "[...document.querySelectorAll('#layer-select option')].map((o) => o.value).join()"

#: Per loaded tile image: its URL, size and how many of its pixels are not fully transparent (drawn
#: to a canvas: the tiles are same-origin, so the canvas is readable). Null while one is loading
#: again: see `_tile_pixels`.
_TILE_PIXELS_JS = """
() => {
  const imgs = [...document.querySelectorAll('#map img.leaflet-tile-loaded')];
  // A tile whose src was set again (a refresh) keeps its class while its next image loads, with no
  // image to read: null, read again later.
  if (imgs.some((img) => !img.complete || img.naturalWidth === 0)) return null;
  return imgs.map((img) => {
  const c = document.createElement('canvas');
  c.width = img.naturalWidth;
  c.height = img.naturalHeight;
  const ctx = c.getContext('2d');
  ctx.drawImage(img, 0, 0);
  const d = ctx.getImageData(0, 0, c.width, c.height).data;
  let opaque = 0;
  for (let k = 3; k < d.length; k += 4) if (d[k] > 0) opaque++;
  return {src: img.src, width: c.width, height: c.height, opaque};
  });
}
"""

#: For a robot at map point (x, y) metres on a map of resolution `res`: where the page should draw it
#: (container pixels, by the Leaflet map's projection: one map unit per cell), the centre of its marker
#: element and the arrow's rotation in degrees; null while there is no marker.
_MARKER_JS = """
([robotId, x, y, res]) => {
  const p = window.fleetmapViewer.map.latLngToContainerPoint([y / res, x / res]);
  const el = document.querySelector(`.robot-marker[data-robot-id="${robotId}"]`);
  if (!el) return null;
  const box = el.getBoundingClientRect();
  const map = document.getElementById('map').getBoundingClientRect();
  const actual = [box.left + box.width / 2 - map.left, box.top + box.height / 2 - map.top];
  const rotation = /rotate\\(([-0-9.e]+)deg\\)/.exec(el.querySelector('svg').style.transform);
  return {expected: [p.x, p.y], actual, online: el.dataset.online, degrees: rotation && Number(rotation[1])};
}
"""

#: Whether every loaded tile comes from the given layer.
_ALL_TILES_OF_LAYER_JS = (
    f"(layer) => {{ const s = {_LOADED_TILES_JS};"
    " return s.length > 0 && s.every((u) => u.includes(`layer=${layer}&`)); }"
)

_CELL_POINT_JS = """
([i, j]) => {
  const p = window.fleetmapViewer.map.latLngToContainerPoint([j + 0.5, i + 0.5]);
  return [p.x, p.y];
}
"""

_GET_VIEW_JS = (
    "() => { const m = window.fleetmapViewer.map, c = m.getCenter(); return [c.lat, c.lng, m.getZoom()]; }"
)
_SET_VIEW_JS = "([lat, lng, z]) => window.fleetmapViewer.map.setView([lat, lng], z, {animate: false})"


def _wait(page: Any, js: str, arg: Any = None, what: str = "") -> Any:
    """page.wait_for_function, failing with a message that names what the page did not show."""
    try:
        return page.wait_for_function(js, arg=arg, timeout=SHOW_MS).json_value()
    except Exception as exc:  # playwright's TimeoutError
        raise AssertionError(f"the page did not show {what or js} within {SHOW_MS} ms") from exc


def _settled_tiles(page: Any, statuses: dict[str, int]) -> list[str]:
    """Wait until every tile image on the map has finished loading, each with an HTTP 200 answer
    seen by the browser; returns their URLs. (A tile refreshed just now may still be on its way.)"""
    deadline = time.monotonic() + SHOW_MS / 1000
    while True:
        tiles = page.evaluate(
            "() => [...document.querySelectorAll('#map img.leaflet-tile')].map((i) => [i.src, i.complete])"
        )
        srcs = [src for src, _ in tiles]
        if tiles and all(done and statuses.get(src) == 200 for src, done in tiles):
            return srcs
        if time.monotonic() > deadline:
            raise AssertionError(f"tiles did not all load with 200: {tiles} {statuses}")
        page.wait_for_timeout(50)


def _tile_pixels(page: Any, statuses: dict[str, int]) -> list[dict[str, Any]]:
    """Once every tile has loaded (`_settled_tiles`), what `_TILE_PIXELS_JS` reads of each. A tile
    refreshed between the two (robots keep scanning) has no image to read for a moment: read again
    then (getImageData refused its 0-pixel canvas, and a CI run failed so)."""
    deadline = time.monotonic() + SHOW_MS / 1000
    while True:
        _settled_tiles(page, statuses)
        pixels = page.evaluate(_TILE_PIXELS_JS)
        if pixels is not None:
            return list(pixels)
        if time.monotonic() > deadline:
            raise AssertionError("a tile kept loading again")
        page.wait_for_timeout(50)


def _scan_count_js(row: str, n: int) -> str:
    return f"() => document.querySelector('{row} .scans')?.textContent === '{n} scans'"


# ---- the test ----------------------------------------------------------------------------------------


def test_web_viewer_end_to_end(service: ServiceProcess) -> None:
    """`service` (tests/conftest.py): `python -m fleetmap.server` on free ports, stopped afterwards."""
    from playwright.sync_api import sync_playwright

    base, endpoint = service.base_url, service.zenoh_endpoint
    plan = generate_floorplan(7, width_m=16.0, height_m=12.0, resolution=0.05, n_obstacles=3)
    robot: ZenohRobot | None = None
    requests: list[str] = []
    tile_statuses: dict[str, int] = {}
    page_errors: list[str] = []

    def on_response(response: Any) -> None:
        if "/tiles/" in response.url:
            tile_statuses[response.url] = response.status

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.on("request", lambda r: requests.append(r.url))
            page.on("response", on_response)
            page.on("pageerror", lambda e: page_errors.append(str(e)))

            # No map yet: the page says it waits for robots instead of failing.
            page.goto(f"{base}/")
            _wait(page, "() => !document.getElementById('empty').hidden", what="'waiting for robots'")
            assert "Waiting for robots" in page.inner_text("#empty")
            assert page.get_attribute("#status", "data-state") == "waiting"
            assert page.eval_on_selector("#map-select", "el => el.disabled")

            # A robot comes and maps part of the floor; the page's periodic map list poll finds the map.
            robot = ZenohRobot(endpoint, MAP_ID, ROBOT_ID, plan, seed=11)
            robot.wait_matched()
            robot.publish(FIRST_SCANS)
            _wait_integrated(base, FIRST_SCANS)
            page.wait_for_selector(f'#map-select option[value="{MAP_ID}"]', state="attached", timeout=SHOW_MS)
            assert page.eval_on_selector("#map-select", "el => el.value") == MAP_ID
            assert page.is_hidden("#empty")
            _wait(
                page,
                f"() => location.hash === '#map={MAP_ID}&layer=probability'",
                what="the map and layer in the URL hash",
            )
            _wait(
                page,
                "() => document.getElementById('status').dataset.state === 'connected'",
                what="connected",
            )
            assert page.inner_text("#status").startswith("connected")

            # Only the layers the map keeps (the default configuration keeps them all) are offered.
            assert (
                page.evaluate(f"() => {_LAYER_OPTIONS_JS}")
                == "probability,state,log_odds,hits,misses,tsdf,tsdf_weight"
            )

            # Tiles: loaded with HTTP 200 from the tile endpoint, and showing the map (not transparent).
            _wait(page, f"() => {_LOADED_TILES_JS}.length > 0", what="loaded tiles")
            tiles = _tile_pixels(page, tile_statuses)
            for tile in tiles:
                assert f"/maps/{MAP_ID}/tiles/" in tile["src"] and "layer=probability" in tile["src"], tile
                assert (tile["width"], tile["height"]) == (256, 256), tile
                assert tile_statuses.get(tile["src"]) == 200, (tile, tile_statuses)
            assert sum(t["opaque"] for t in tiles) > 5000, tiles  # thousands of observed cells are drawn

            # The robot: listed online with its name and scan count, drawn at its pose, with a trail.
            row = f'#robot-list li[data-robot-id="{ROBOT_ID}"]'
            page.wait_for_selector(f'{row}[data-online="true"]', timeout=SHOW_MS)
            _wait(page, _scan_count_js(row, FIRST_SCANS), what="the robot's scan count")
            text = page.inner_text(row)
            assert ROBOT_ID in text and "online" in text
            pose = robot.sim.pose  # the pose of its last scan
            res = MapConfig().resolution  # the service's default configuration made the map
            marker = _wait(page, _MARKER_JS, [ROBOT_ID, pose.x, pose.y, res], what="the robot's marker")
            assert marker["online"] == "true"
            assert math.dist(marker["expected"], marker["actual"]) < 3.0, marker
            # The arrow points along the heading: CSS turns clockwise on a y-down screen, hence -theta.
            turn = (marker["degrees"] + math.degrees(pose.theta) + 180.0) % 360.0 - 180.0
            assert abs(turn) < 0.1, (marker, pose)
            trail = page.evaluate(
                "(id) => window.fleetmapViewer.state.robots.get(id).trail.getLatLngs().length", ROBOT_ID
            )
            assert trail >= FIRST_SCANS // 2
            assert page.eval_on_selector_all(".leaflet-overlay-pane path", "ps => ps.length") >= 1
            fitted_view = page.evaluate(_GET_VIEW_JS)  # for the screenshot below

            # Live refresh: more scans change the displayed tiles; their images get a new URL that is
            # requested and loads with 200, while the page itself is not reloaded.
            page.evaluate("() => { window.__sameDocument = true; }")
            before = [t["src"] for t in tiles]
            robot.publish(MORE_SCANS)
            _wait_integrated(base, FIRST_SCANS + MORE_SCANS)
            fresh = _wait(
                page,
                f"(before) => {{ const f = {_LOADED_TILES_JS}.filter((s) => !before.includes(s));"
                " return f.length > 0 ? f : null; }",
                before,
                what="refreshed tiles",
            )
            assert any(src in requests for src in fresh), "no request for a refreshed tile was seen"
            settled = _settled_tiles(page, tile_statuses)
            assert any(src not in before for src in settled), (before, settled)
            assert page.evaluate("() => window.__sameDocument === true"), "the page was reloaded"
            _wait(page, _scan_count_js(row, FIRST_SCANS + MORE_SCANS), what="the robot's new scan count")

            # Click the most certainly occupied cell of the engine's own map of the same scans
            # (zoomed in to 16 pixels per cell, so the click lands inside it).
            i, j, p_ref = _occupied_cell(robot.scans)
            page.evaluate(_SET_VIEW_JS, [j + 0.5, i + 0.5, 4])
            x, y = page.evaluate(_CELL_POINT_JS, [i, j])
            box = page.locator("#map").bounding_box()
            assert box is not None
            page.mouse.click(box["x"] + x, box["y"] + y)
            _wait(
                page,
                f"() => document.getElementById('cell-info').dataset.i === '{i}'"
                f" && document.getElementById('cell-info').dataset.j === '{j}'",
                what="the clicked cell",
            )
            assert page.inner_text('#cell-info td[data-field="state"]') == "occupied"
            assert page.inner_text('#cell-info td[data-field="known"]') == "yes"
            probability = float(page.inner_text('#cell-info td[data-field="probability"]'))
            assert probability > 0.5
            assert probability == pytest.approx(p_ref, abs=1e-3)
            assert int(page.inner_text('#cell-info td[data-field="hits"]')) >= 1

            # A screenshot for people: the fitted view with the robot, its trail and the clicked cell.
            page.evaluate(_SET_VIEW_JS, fitted_view)
            _settled_tiles(page, tile_statuses)
            page.screenshot(path=str(SCREENSHOT))

            # Switching the layer reloads the tiles from the other layer and records it in the hash.
            page.select_option("#layer-select", "hits")
            _wait(
                page,
                _ALL_TILES_OF_LAYER_JS,
                "hits",
                what="tiles of the hits layer",
            )
            assert any("/tiles/" in url and "layer=hits" in url for url in requests)
            # The view was moved above (setView), so the URL also names it: the centre and the zoom.
            assert re.fullmatch(
                rf"#map={MAP_ID}&layer=hits&x=[-0-9.]+&y=[-0-9.]+&z=-?\d+",
                page.evaluate("() => location.hash"),
            )
            hits_tiles = _tile_pixels(page, tile_statuses)
            assert all(tile_statuses.get(t["src"]) == 200 for t in hits_tiles), hits_tiles
            assert sum(t["opaque"] for t in hits_tiles) > 1000, hits_tiles

            # The robot leaves: its liveliness token goes, and the page shows it offline.
            robot.close()
            robot = None
            page.wait_for_selector(f'{row}[data-online="false"]', timeout=SHOW_MS)
            assert "offline" in page.inner_text(row)

            assert not page_errors, page_errors
            assert page.is_hidden("#error"), page.inner_text("#error")

            # Another map that keeps only counts: once the map list poll shows it, selecting it offers
            # only its layers (the wanted layer, hits, is kept) and loads its tiles.
            other = "counts-only"
            r = httpx.put(f"{base}/maps/{other}", json={"layers": ["counts"]}, timeout=10.0)
            assert r.status_code == 201, r.text
            page.wait_for_selector(f'#map-select option[value="{other}"]', state="attached", timeout=SHOW_MS)
            page.select_option("#map-select", other)
            _wait(
                page, f"() => location.hash === '#map={other}&layer=hits'", what="the other map in the hash"
            )
            _wait(
                page,
                f"() => {_LAYER_OPTIONS_JS} === 'hits,misses'",
                what="only the counts layers",
            )
            _wait(
                page,
                f"() => {_LOADED_TILES_JS}.some((s) => s.includes('/maps/{other}/tiles/'))",
                what="its tiles",
            )
            assert page.inner_text("#robot-list") == "no robots"

            # It is replaced by a snapshot of the first map (PUT /maps/{id}/snapshot): the page stays
            # on it with the same event stream, says nothing is wrong, offers the layers the new map
            # keeps (the wanted layer, hits, still) and reloads every tile, which now show cells.
            snapshot = httpx.get(f"{base}/maps/{MAP_ID}/snapshot", timeout=30.0)
            assert snapshot.status_code == 200, snapshot.text
            page.evaluate("() => { window.__stream = window.fleetmapViewer.state.events; }")
            before = page.evaluate(f"() => {_LOADED_TILES_JS}")
            r = httpx.put(
                f"{base}/maps/{other}/snapshot",
                content=snapshot.content,
                headers={"content-type": "application/zip"},
                timeout=30.0,
            )
            assert r.status_code == 200, r.text  # replaced, not created
            _wait(
                page,
                f"() => {_LAYER_OPTIONS_JS} === 'probability,state,log_odds,hits,misses,tsdf,tsdf_weight'",
                what="the replacing map's layers",
            )
            _wait(
                page,
                f"(before) => {{ const s = {_LOADED_TILES_JS}; return s.length > 0"
                f" && s.every((u) => !before.includes(u) && u.includes('/maps/{other}/tiles/')); }}",
                before,
                what="the replacing map's tiles",
            )
            replaced_tiles = _tile_pixels(page, tile_statuses)
            assert sum(t["opaque"] for t in replaced_tiles) > 1000, replaced_tiles
            assert page.eval_on_selector("#map-select", "el => el.value") == other
            assert page.evaluate("() => location.hash") == f"#map={other}&layer=hits"
            assert page.evaluate("() => window.fleetmapViewer.state.events === window.__stream")
            assert page.get_attribute("#status", "data-state") == "connected"
            assert page.is_hidden("#error"), page.inner_text("#error")
            assert not page_errors, page_errors

            # It is deleted: the page says so and goes back to the map that is left.
            assert httpx.delete(f"{base}/maps/{other}", timeout=10.0).status_code in (200, 204)
            _wait(
                page, f"() => document.getElementById('map-select').value === '{MAP_ID}'", what="map switch"
            )
            assert f"map {other} was deleted" in page.inner_text("#error")

            # The service goes away: the status line says the page is reconnecting, it does not break.
            service.stop()
            _wait(
                page, "() => document.getElementById('status').dataset.state !== 'connected'", what="the loss"
            )
            assert page.inner_text("#status").startswith(("reconnecting", "event stream lost"))
            assert not page_errors, page_errors
        finally:
            browser.close()
            if robot is not None:
                robot.close()
