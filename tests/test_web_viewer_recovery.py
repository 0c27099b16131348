"""The web viewer (clients/web) when things change under it, in headless Chromium against a real service.

test_web_viewer.py walks through the normal life of a map; these tests cover what the viewer must
survive: a link to a map that does not exist, robot rows clicked while robots events keep coming, the
service restarting with another map under the same id, and the last map being deleted. Scans come
through `POST /maps/{id}/scans` (no Zenoh needed here). Same Chromium and skip rule as
test_web_viewer.py; one browser for the module, one page per test, and one in-memory service for
the tests that each show a map of their own (a test about which maps the service holds, or that
stops it, has one of its own).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
from service_process import FreezableProxy, ServiceProcess
from test_web_viewer import (
    _ALL_TILES_OF_LAYER_JS,
    _LAYER_OPTIONS_JS,
    _MARKER_JS,
    CHROMIUM,
    SHOW_MS,
    _wait,
)

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)

MAP_ID = "alpha"

#: The map's centre in the viewer is at the given robot's marker (within a few pixels).
_CENTRED_ON_JS = """
(id) => {
  const v = window.fleetmapViewer, r = v.state.robots.get(id);
  if (!r || !r.marker) return false;
  const m = v.map;
  const a = m.latLngToContainerPoint(m.getCenter()), b = m.latLngToContainerPoint(r.marker.getLatLng());
  return Math.hypot(a.x - b.x, a.y - b.y) < 5;
}
"""
#: Every tile image on the map is a loaded 256-pixel tile (a failed one is the 1-pixel error tile).
_TILES_LOADED_JS = """
() => {
  const imgs = [...document.querySelectorAll('#map img.leaflet-tile')];
  return imgs.length > 0 && imgs.every((i) => i.complete && i.naturalWidth === 256);
}
"""
#: The URL of every tile image on the map.
_TILE_URLS_JS = "() => [...document.querySelectorAll('#map img.leaflet-tile')].map((i) => i.src)"
_AWAY_JS = "() => window.fleetmapViewer.map.setView([-4000, -4000], 0, {animate: false})"
#: The error panel is shown and says `text`.
_ERROR_JS = (
    "(text) => { const e = document.getElementById('error');"
    " return !e.hidden && e.textContent.includes(text); }"
)
#: The row of a robot in the list.
_ROW = '#robot-list li[data-robot-id="{}"]'


def _scan(
    base: str,
    map_id: str,
    robot_id: str,
    seq: int,
    x: float,
    y: float,
    theta: float = 0.0,
    headers: dict[str, str] | None = None,
) -> None:
    """One JSON scan: a ring of walls 3 m around (x, y) (`headers`: e.g. a write token's)."""
    n = 180
    body = {
        "seq": seq,
        "stamp": float(seq),
        "pose": {"x": x, "y": y, "theta": theta},
        "angle_min": -math.pi,
        "angle_increment": 2 * math.pi / n,
        "range_min": 0.05,
        "range_max": 30.0,
        "ranges": [3.0] * n,
    }
    r = httpx.post(
        f"{base}/maps/{map_id}/scans", params={"robot_id": robot_id}, json=body, headers=headers, timeout=30.0
    )
    assert r.status_code == 200, r.text


def _make_map(
    base: str,
    robots: dict[str, tuple[float, float]],
    config: dict[str, Any] | None = None,
    map_id: str = MAP_ID,
) -> None:
    """PUT the map `map_id` (with `config`), and one scan from each robot at its (x, y)."""
    r = httpx.put(f"{base}/maps/{map_id}", json=config or {}, timeout=10.0)
    assert r.status_code in (200, 201), r.text
    for robot_id, (x, y) in robots.items():
        _scan(base, map_id, robot_id, 1, x, y)


@pytest.fixture
def svc(service_factory: Callable[..., ServiceProcess]) -> ServiceProcess:
    """An in-memory service of the test's own: for tests about the maps the service holds (which
    one a page shows, the list) or that stop it."""
    return service_factory("--in-memory")


@pytest.fixture(scope="module")
def shared_svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One in-memory service for the module's tests that each open a page on a map of their own
    (named in the link, an id no other test here uses) and neither stop the service nor care which
    other maps it holds."""
    with ServiceProcess(tmp_path_factory.mktemp("viewer-recovery"), ["--in-memory"]) as service:
        yield service


def _open(page: Any, base: str, hash_: str) -> None:
    page.goto(f"{base}/{hash_}")
    _wait(page, "() => document.getElementById('status').dataset.state === 'connected'", what="connected")


def test_link_to_a_missing_map(page: Any, svc: ServiceProcess) -> None:
    """A #map= link (on load, or edited by hand) to a map that does not exist says so, and the URL
    names the map that is shown instead."""
    base = svc.base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    _open(page, base, "#map=ghost&layer=probability")
    _wait(page, f"() => location.hash === '#map={MAP_ID}&layer=probability'", what="the shown map in the URL")
    _wait(page, _ERROR_JS, "map ghost not found", what="'map ghost not found'")
    assert page.eval_on_selector("#map-select", "el => el.value") == MAP_ID

    page.evaluate("() => { location.hash = '#map=ghost2&layer=probability'; }")
    _wait(page, _ERROR_JS, "map ghost2 not found", what="'map ghost2 not found'")
    _wait(
        page,
        f"() => location.hash === '#map={MAP_ID}&layer=probability'",
        what="the URL back on the shown map",
    )
    assert page.evaluate("() => window.fleetmapViewer.state.mapId") == MAP_ID
    assert not page.page_errors, page.page_errors


def test_an_edited_hash_names_what_is_shown(page: Any, shared_svc: ServiceProcess) -> None:
    """The hash edited by hand to leave out the layer, or to name a view out of range, is written
    again to name the layer and view shown (it kept the edit, so a link copied from the address bar
    showed another layer, or the map fitted, than the page the link was copied from)."""
    base, map_id = shared_svc.base_url, "edited"  # a map of its own on the shared service
    _make_map(base, {"r1": (2.0, 2.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}&layer=hits")
    page.evaluate(f"() => {{ location.hash = '#map={map_id}'; }}")
    _wait(page, f"() => location.hash === '#map={map_id}&layer=hits'", what="the layer shown in the URL")
    page.evaluate(f"() => {{ location.hash = '#map={map_id}&layer=hits&x=4&y=2&z=3'; }}")
    _wait(page, "() => window.fleetmapViewer.map.getZoom() === 3", what="the view of the link")
    page.evaluate(f"() => {{ location.hash = '#map={map_id}&layer=hits&x=1e400&y=2&z=1'; }}")
    _wait(
        page,
        f"() => location.hash === '#map={map_id}&layer=hits&x=4&y=2&z=3'",
        what="the view shown in the URL",
    )
    assert page.evaluate("() => window.fleetmapViewer.state.layer") == "hits"
    assert not page.page_errors, page.page_errors


def test_robot_rows_are_stable_buttons(page: Any, shared_svc: ServiceProcess) -> None:
    """Robot rows are updated in place while robots events come (so a slow click is not lost), in
    natural order, and are buttons: a click or Enter centres the map on the robot."""
    base, map_id = shared_svc.base_url, "rows"  # a map of its own on the shared service
    _make_map(base, {"sim-10": (6.0, 2.0), "sim-2": (2.0, 2.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}")
    page.wait_for_selector(_ROW.format("sim-10"), timeout=SHOW_MS)
    ids = page.eval_on_selector_all("#robot-list li", "els => els.map((li) => li.dataset.robotId)")
    assert ids == ["sim-2", "sim-10"], ids
    assert page.inner_text(f"{_ROW.format('sim-10')} .scans") == "1 scan"  # not '1 scans'
    assert page.eval_on_selector_all(
        "#robot-list li",
        "els => els.every((li) => li.querySelector('button') && li.querySelector('button').tabIndex === 0)",
    )

    # sim-2 keeps scanning (robots events several times a second) while its rows are clicked.
    stop = threading.Event()

    def feed() -> None:
        seq = 2
        while not stop.is_set():
            _scan(base, map_id, "sim-2", seq, 2.0, 2.0)
            seq += 1
            stop.wait(0.08)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        page.evaluate("(sel) => { window.__row = document.querySelector(sel); }", _ROW.format("sim-2"))
        _wait(
            page,
            "(sel) => parseInt(document.querySelector(sel).textContent) >= 8",
            f"{_ROW.format('sim-2')} .scans",
            what="sim-2's scans counted",
        )
        assert page.evaluate("(sel) => window.__row === document.querySelector(sel)", _ROW.format("sim-2")), (
            "the row was rebuilt instead of updated in place"
        )

        for robot_id in ("sim-2", "sim-10"):  # a slow click: press, 150 ms, release
            page.evaluate(_AWAY_JS)
            box = page.locator(_ROW.format(robot_id)).bounding_box()
            assert box is not None
            page.mouse.move(box["x"] + 30, box["y"] + box["height"] / 2)
            page.mouse.down()
            page.wait_for_timeout(150)
            page.mouse.up()
            _wait(page, _CENTRED_ON_JS, robot_id, what=f"the map centred on {robot_id} after a click")

        page.evaluate(_AWAY_JS)
        page.focus(f"{_ROW.format('sim-2')} button")
        page.keyboard.press("Enter")
        _wait(page, _CENTRED_ON_JS, "sim-2", what="the map centred on sim-2 after Enter")
    finally:
        stop.set()
        feeder.join(10)
    assert not page.page_errors, page.page_errors


def test_a_focused_robot_row_keeps_the_focus_as_robots_come(page: Any, shared_svc: ServiceProcess) -> None:
    """A keyboard user on a robot's row keeps their place when another robot joins the list: the
    list was rebuilt whole, every row taken out and put back, and the focused row lost the focus to
    the page, so the next Tab started again from the top of the page (robots leaving did the same)."""
    base, map_id = shared_svc.base_url, "focus"  # a map of its own on the shared service
    _make_map(base, {"sim-5": (2.0, 2.0), "sim-7": (6.0, 2.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}")
    page.wait_for_selector(_ROW.format("sim-7"), timeout=SHOW_MS)
    page.focus(f"{_ROW.format('sim-7')} button")
    focused = "() => document.activeElement.closest('#robot-list li')?.dataset.robotId ?? 'none'"
    assert page.evaluate(focused) == "sim-7"
    _scan(base, map_id, "sim-6", 1, 4.0, 2.0)  # a robot joins, before sim-7 in the list
    page.wait_for_selector(_ROW.format("sim-6"), timeout=SHOW_MS)
    assert page.evaluate(focused) == "sim-7", "the focus left the robot's row"
    assert not page.page_errors, page.page_errors


def test_restart_with_another_map(page: Any, service_factory: Callable[..., ServiceProcess]) -> None:
    """The service restarts and the map comes back with another resolution and other layers (its data
    directory restored from another backup): after the event stream reconnects the viewer shows the
    new map's layers, tiles and robot positions, without a new selection by the map list poll. While
    the service is down robots are not claimed online, and 'cannot reach' goes on reconnect."""
    # The backup: a data directory whose map has another resolution and keeps only counts.
    other = service_factory()
    _make_map(other.base_url, {"sim-1": (4.0, 3.0)}, {"resolution": 0.2, "layers": ["counts"]})
    other.stop()
    svc = service_factory()
    base = svc.base_url
    _make_map(base, {"sim-1": (2.0, 2.0)})
    _open(page, base, f"#map={MAP_ID}&layer=probability")
    row = _ROW.format("sim-1")
    page.wait_for_selector(row, timeout=SHOW_MS)
    token = page.evaluate("() => window.fleetmapViewer.state.selectToken")

    svc.stop()
    _wait(page, "() => document.getElementById('status').dataset.state !== 'connected'", what="the loss")
    page.wait_for_selector(f'{row}[data-online="unknown"]', timeout=SHOW_MS)
    svc.args[svc.args.index("--data-dir") + 1] = other.args[other.args.index("--data-dir") + 1]
    svc.start()

    _wait(page, "() => document.getElementById('status').dataset.state === 'connected'", what="reconnected")
    _wait(page, f"() => {_LAYER_OPTIONS_JS} === 'hits,misses'", what="the new map's layers")
    _wait(page, "() => window.fleetmapViewer.state.res === 0.2", what="the new resolution")
    _wait(page, f"() => location.hash === '#map={MAP_ID}&layer=hits'", what="the new layer in the URL")
    _wait(page, _ALL_TILES_OF_LAYER_JS, "hits", what="tiles of the hits layer")
    _wait(page, _TILES_LOADED_JS, what="every tile loaded (none failed)")
    marker = _wait(page, _MARKER_JS, ["sim-1", 4.0, 3.0, 0.2], what="sim-1's marker")
    assert math.dist(marker["expected"], marker["actual"]) < 3.0, marker
    _wait(
        page,
        "() => document.getElementById('error').hidden"
        " || !document.getElementById('error').textContent.includes('cannot reach')",
        what="'cannot reach the service' gone",
    )
    assert page.evaluate("() => window.fleetmapViewer.state.selectToken") == token
    assert not page.page_errors, page.page_errors


def test_last_map_deleted(page: Any, svc: ServiceProcess) -> None:
    """The shown map is deleted and none is left: no cell values, outline, cursor position or map
    name stay on the page or in the URL."""
    base = svc.base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    _open(page, base, f"#map={MAP_ID}")
    box = page.locator("#map").bounding_box()
    assert box is not None
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    _wait(page, "() => document.getElementById('cell-info').dataset.i !== undefined", what="the clicked cell")
    page.mouse.move(box["x"] + box["width"] / 2 + 10, box["y"] + box["height"] / 2)
    _wait(page, "() => document.getElementById('coords').textContent !== ''", what="the cursor position")

    assert httpx.delete(f"{base}/maps/{MAP_ID}", timeout=10.0).status_code in (200, 204)
    _wait(page, "() => document.getElementById('map-select').disabled", what="no maps")
    _wait(page, "() => location.hash === ''", what="an empty URL hash")
    assert page.evaluate("() => document.getElementById('cell-info').dataset.i") is None
    assert "Click the map" in page.inner_text("#cell-info")
    assert page.eval_on_selector_all(".leaflet-overlay-pane path", "ps => ps.length") == 0
    assert page.inner_text("#coords") == ""
    assert not page.page_errors, page.page_errors


def test_last_map_gone_over_a_restart_says_so(page: Any, svc: ServiceProcess) -> None:
    """The service restarts without the shown map, the only one (it kept its maps in memory; a
    restored backup may lack it too): no `deleted` event tells the page, whose stream was down, and
    the map-list poll finds the map gone. The page says so, as it does when another map is left or
    when the `deleted` event tells; it went to 'Waiting for robots' without a word."""
    base = svc.base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    _open(page, base, f"#map={MAP_ID}")
    svc.stop()
    _wait(page, "() => document.getElementById('status').dataset.state !== 'connected'", what="the loss")
    svc.start()  # --in-memory: without the map
    _wait(page, "() => document.getElementById('map-select').disabled", what="no maps")
    _wait(page, _ERROR_JS, f"map {MAP_ID} was deleted", what="that the map was deleted")
    assert page.is_visible("#empty")  # and it waits for robots
    assert page.evaluate("() => location.hash") == ""
    assert not page.page_errors, page.page_errors


#: The fill colour of every robot marker's arrow, by robot id.
_MARKER_COLOURS_JS = """
() => Object.fromEntries([...window.fleetmapViewer.state.robots.values()]
  .filter((r) => r.marker && r.marker.getElement())
  .map((r) => [r.id, r.marker.getElement().querySelector('path').getAttribute('fill')]))
"""


def test_twelve_robots_have_twelve_colours(page: Any, shared_svc: ServiceProcess) -> None:
    """Colours came from a hash of the id into 10 colours: with 12 robots two pairs shared one, and
    the map has no label to tell them apart. Each robot of a map now has its own, the same after a
    reload."""
    base, map_id = shared_svc.base_url, "twelve"  # a map of its own on the shared service
    _make_map(base, {f"sim-{k}": (3.0 * k, 0.0) for k in range(1, 13)}, map_id=map_id)
    _open(page, base, f"#map={map_id}")
    _wait(page, "() => window.fleetmapViewer.state.robots.size === 12", what="12 robots")
    _wait(page, "() => document.querySelectorAll('.robot-marker').length === 12", what="12 markers")
    colours = page.evaluate(_MARKER_COLOURS_JS)
    assert len(colours) == 12 and len(set(colours.values())) == 12, colours
    page.reload()
    _wait(page, "() => document.querySelectorAll('.robot-marker').length === 12", what="12 markers again")
    assert page.evaluate(_MARKER_COLOURS_JS) == colours
    assert not page.page_errors


#: How many tile images on the map failed (Leaflet shows its 1-pixel error tile instead).
_FAILED_TILES_JS = (
    "() => [...document.querySelectorAll('#map img.leaflet-tile')]"
    ".filter((i) => i.complete && i.naturalWidth !== 256).length"
)


def test_tiles_that_failed_are_asked_again(page: Any, shared_svc: ServiceProcess) -> None:
    """The network drops tile requests for a moment while the map changes, and the event stream stays
    up. The tiles that failed showed nothing (a hole in the map, the robot's trail running over
    unknown space) until their cells changed again, which on a finished map is never: each one is
    now asked for again, and the map is whole again without a reload or a pan, and without the
    message that a tile failed."""
    base, map_id = shared_svc.base_url, "failed"  # a map of its own on the shared service
    _make_map(base, {"r1": (2.0, 2.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}&layer=probability")
    _wait(page, _TILES_LOADED_JS, what="every tile loaded")

    page.route("**/tiles/**", lambda route: route.abort("internetdisconnected"))
    _scan(base, map_id, "r1", 2, 2.5, 2.0)  # changes the tiles in view: the page asks for them again
    _wait(page, f"() => ({_FAILED_TILES_JS})() > 0", what="tiles failing while the network drops them")
    _wait(page, _ERROR_JS, "failed to load", what="'tile ... failed to load'")
    page.unroute("**/tiles/**")

    # No scan comes any more: nothing but the viewer itself may ask for the failed tiles again.
    _wait(page, _TILES_LOADED_JS, what="every tile loaded again (no hole left)")
    assert page.evaluate(_FAILED_TILES_JS) == 0
    # Loaded, no tile failed any more: the message goes with the failure (it stayed 15 s).
    assert page.is_hidden("#error"), page.inner_text("#error")
    assert page.evaluate("() => document.getElementById('status').dataset.state") == "connected"
    assert not page.page_errors, page.page_errors


def test_a_change_before_the_first_stream_opened_is_shown(page: Any, shared_svc: ServiceProcess) -> None:
    """A scan lands after the page loaded the map's tiles but before its event stream opened (a
    slow network, or a browser whose 6 connections to the service were all loading tiles). The
    stream started from the map's version when it opened, after that change, so the page never
    heard of it: the changed tiles stayed stale until their cells changed again, on a finished
    map for good. The first stream now resumes from the version the map had when the page read it
    (`?since=`), before its tiles were asked for."""
    base, map_id = shared_svc.base_url, "late-stream"  # a map of its own on the shared service
    _make_map(base, {"r1": (2.0, 2.0)}, map_id=map_id)
    held: list[Any] = []
    page.route(f"**/maps/{map_id}/events**", lambda route: held.append(route))
    try:
        page.goto(f"{base}/#map={map_id}&layer=probability")
        _wait(page, _TILES_LOADED_JS, what="every tile loaded")
        for _ in range(100):  # the stream's request reaches the route
            if held:
                break
            page.wait_for_timeout(50)
        assert len(held) == 1, "the page opened no event stream"
        before = page.evaluate(_TILE_URLS_JS)
        _scan(base, map_id, "r2", 1, 2.5, 2.0)  # changes the tiles in view
        held[0].continue_()
    finally:
        page.unroute(f"**/maps/{map_id}/events**")
    _wait(
        page,
        "() => window.fleetmapViewer.state.robots.get('r2')?.data?.scans_integrated === 1",
        what="the robot of the scan, through the stream",
    )
    _wait(
        page,
        f"(before) => ({_TILES_LOADED_JS})() && ({_TILE_URLS_JS})().some((u) => !before.includes(u))",
        before,
        what="the tiles the scan changed asked for again",
    )
    assert page.evaluate("() => document.getElementById('status').dataset.state") == "connected"
    assert not page.page_errors, page.page_errors


def test_a_stream_that_died_silently_is_opened_again(
    page: Any, service_factory: Callable[..., ServiceProcess]
) -> None:
    """The event stream's connection dies without a FIN or RST (a NAT or proxy dropped it, a laptop
    slept): the browser holds it open for good, and the page showed a stale map as live, its robots
    never moving again. The stream's keepalive events (here every 0.5 s) bound every silence, so the
    page notices a stream silent for three of them, opens another, and catches up."""
    svc = service_factory("--in-memory", "--events-keepalive", "0.5")
    base = svc.base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    proxy = FreezableProxy(svc.port)  # the page's way to the service; scans go directly
    try:
        _open(page, f"http://127.0.0.1:{proxy.port}", f"#map={MAP_ID}&layer=probability")
        _wait(page, _TILES_LOADED_JS, what="every tile loaded")
        before = page.evaluate(_TILE_URLS_JS)
        assert proxy.freeze(sent=b"/events?") == 1  # the stream only: tiles still load
        _scan(base, MAP_ID, "r1", 2, 2.5, 2.0)
        _wait(
            page,
            "() => window.fleetmapViewer.state.robots.get('r1')?.data?.scans_integrated === 2",
            what="the robot's second scan, through a new stream",
        )
        # Caught up: every tile asked for again (the new stream says nothing of what changed before
        # it opened). Loaded tiles alone were no news: those of before the freeze were loaded too.
        _wait(
            page,
            f"(before) => ({_TILES_LOADED_JS})() && ({_TILE_URLS_JS})().every((u) => !before.includes(u))",
            before,
            what="every tile loaded again",
        )
        assert page.evaluate("() => document.getElementById('status').dataset.state") == "connected"
        assert not page.page_errors, page.page_errors
    finally:
        proxy.close()


def test_maps_are_listed_in_natural_order(page: Any, svc: ServiceProcess) -> None:
    """The map selector lists maps as the robot list lists robots, in natural order (floor-2 before
    floor-10, case aside), and a page opened without a link shows the first of them: the code-unit
    order put floor-10 first, and any capitalised id before every lower-case one."""
    base = svc.base_url
    for map_id in ("floor-10", "floor-2", "Zone"):
        assert httpx.put(f"{base}/maps/{map_id}", json={}, timeout=10.0).status_code == 201
    _open(page, base, "")
    assert page.eval_on_selector_all("#map-select option", "els => els.map((o) => o.value)") == [
        "floor-2",
        "floor-10",
        "Zone",
    ]
    assert page.evaluate("() => window.fleetmapViewer.state.mapId") == "floor-2"
    assert not page.page_errors, page.page_errors


def test_a_page_without_maps_says_when_the_service_is_unreachable(page: Any, svc: ServiceProcess) -> None:
    """With no map to show (so no event stream), the service stops: the status says it cannot be
    reached, not 'waiting for robots'. Back, the status waits again and 'cannot reach the service'
    goes at the next map-list poll (5 s), not only when it fades 15 s after the last failed poll."""
    base = svc.base_url
    page.goto(f"{base}/")
    _wait(page, "() => document.getElementById('status').dataset.state === 'waiting'", what="waiting")
    svc.stop()
    _wait(page, _ERROR_JS, "cannot reach the service", what="'cannot reach the service'")
    assert page.inner_text("#status-text") == "cannot reach the service; retrying…"
    svc.start()
    _wait(page, "() => document.getElementById('status').dataset.state === 'waiting'", what="waiting again")
    page.wait_for_function(
        "() => document.getElementById('error').hidden", timeout=7_500
    )  # the next poll, 5 s at most; the fade would come 10 s later at the earliest
    assert not page.page_errors, page.page_errors


def test_missing_map_that_appears_is_no_longer_not_found(page: Any, svc: ServiceProcess) -> None:
    """A link names a map that does not exist yet: the page says so and waits. When the map appears
    it is shown, and 'map NAME not found' goes with it (it stayed beside the map for up to 15 s)."""
    base = svc.base_url
    page.goto(f"{base}/#map={MAP_ID}")
    _wait(page, _ERROR_JS, f"map {MAP_ID} not found", what=f"'map {MAP_ID} not found'")
    _make_map(base, {"r1": (2.0, 2.0)})
    _wait(
        page,
        f"() => window.fleetmapViewer.state.mapId === '{MAP_ID}'"
        " && document.getElementById('status').dataset.state === 'connected'",
        what="the map, once it exists",
    )
    error = page.eval_on_selector("#error", "e => e.hidden ? '' : e.textContent")
    assert "not found" not in error, error
    assert not page.page_errors, page.page_errors


def test_refused_event_stream_says_why(browser: Any, service_factory: Callable[..., ServiceProcess]) -> None:
    """The service holds its limit of open event streams (here 1: another viewer has it) and answers
    503. The browser's EventSource gives up without saying why, and the page said only 'event
    stream lost; retrying…', for as long as the other viewer stayed. It now shows the service's
    reason, and once the stream opens the message goes."""
    base = service_factory("--in-memory", "--max-event-streams", "1").base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    first = browser.new_page()
    second = browser.new_page()
    second.page_errors = []
    second.on("pageerror", lambda e: second.page_errors.append(str(e)))
    try:
        _open(first, base, f"#map={MAP_ID}")
        second.goto(f"{base}/#map={MAP_ID}")
        _wait(second, _ERROR_JS, "limit of 1 open event streams", what="why the stream is refused")
        assert second.evaluate("() => document.getElementById('status').dataset.state") == "error"
        first.close()
        _wait(second, "() => document.getElementById('status').dataset.state === 'connected'", what="open")
        _wait(second, "() => document.getElementById('error').hidden", what="the message gone")
        assert not second.page_errors, second.page_errors
    finally:
        second.close()
        if not first.is_closed():
            first.close()


def test_a_refused_event_stream_is_retried_after_its_retry_after(
    browser: Any, service_factory: Callable[..., ServiceProcess]
) -> None:
    """A stream refused for the limit of open streams is answered 503 with `Retry-After: 5`, and
    docs/api.md says the viewer reopens it after that; it retried every 3 s whatever the service
    asked. It now waits as long as the service's Retry-After says."""
    base = service_factory("--in-memory", "--max-event-streams", "1").base_url
    _make_map(base, {"r1": (2.0, 2.0)})
    first = browser.new_page()
    second = browser.new_page()
    opened: list[float] = []  # when the second page's EventSource asked for a stream
    second.on(
        "request",
        lambda r: opened.append(time.monotonic()) if r.resource_type == "eventsource" else None,
    )
    try:
        _open(first, base, f"#map={MAP_ID}")
        second.goto(f"{base}/#map={MAP_ID}")
        _wait(second, _ERROR_JS, "limit of 1 open event streams", what="why the stream is refused")
        deadline = time.monotonic() + 20.0
        while len(opened) < 4 and time.monotonic() < deadline:
            second.wait_for_timeout(200)
        gaps = [b - a for a, b in itertools.pairwise(opened)]
        assert len(gaps) >= 2 and min(gaps) >= 4.5, f"the stream was asked for again after {gaps} s"
    finally:
        second.close()
        first.close()


#: Whether the view shows the whole of the map's bounds [xmin, ymin, xmax, ymax] (metres), as the
#: service reports them: CRS.Simple, one map unit a cell (lat = y / res, lng = x / res).
_SHOWS_BOUNDS_JS = """
(b) => {
  const v = window.fleetmapViewer;
  const res = v.state.res;
  return v.map.getBounds().contains(L.latLngBounds([b[1] / res, b[0] / res], [b[3] / res, b[2] / res]));
}
"""


def _bounds(base: str, map_id: str = MAP_ID) -> list[float]:
    return httpx.get(f"{base}/maps/{map_id}", timeout=10.0).json()["stats"]["bounds"]


#: Sets window.__dragDone once the next drag of the map has ended, its inertia included: Leaflet
#: fires `moveend` at once after `dragend` without inertia, else when the inertia's pan has ended.
_DRAG_DONE_JS = """
() => {
  window.__dragDone = false;
  const m = window.fleetmapViewer.map;
  m.once('dragend', () => m.once('moveend', () => { window.__dragDone = true; }));
}
"""


def test_the_view_follows_a_growing_map_until_the_user_moves_it(
    page: Any, shared_svc: ServiceProcess
) -> None:
    """The view was fitted to the map once, at the first scans: as a demo's robots explored on, the
    new rooms ran off screen and a newcomer had to zoom out to see them. Until the user moves the
    map, the view now follows it as it grows; once the user has moved it, it stays put."""
    base, map_id = shared_svc.base_url, "growing"  # a map of its own on the shared service
    _make_map(base, {"r1": (0.0, 0.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}")
    _wait(page, _SHOWS_BOUNDS_JS, _bounds(base, map_id), what="the first fit")
    for seq, x in enumerate((40.0, 80.0), start=2):  # far beyond the first fit, on that zoom
        _scan(base, map_id, "r1", seq, x, 0.0)
        _wait(page, _SHOWS_BOUNDS_JS, _bounds(base, map_id), what=f"the view following the map to x = {x} m")
    assert page.evaluate("() => window.fleetmapViewer.state.viewChosen") is False

    # The user pans: from now on the view is theirs.
    box = page.locator("#map").bounding_box()
    assert box is not None
    page.evaluate(_DRAG_DONE_JS)
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] / 2 + 80, box["y"] + box["height"] / 2 + 40, steps=5)
    page.mouse.up()
    _wait(page, "() => window.fleetmapViewer.state.viewChosen", what="the user's pan noticed")
    # The drag's inertia runs out: it lasts as long as the drag was fast, and starts a frame after
    # the button is released (a fixed 1.5 s, or a wait for Leaflet's pan animation, could end first).
    _wait(page, "() => window.__dragDone === true", what="the drag's end, inertia included")
    chosen = page.evaluate("() => window.fleetmapViewer.map.getCenter()")
    _scan(base, map_id, "r1", 4, -120.0, 0.0)  # answered once integrated: its tiles event is on its way
    page.wait_for_timeout(5000)  # past two follow periods: a follow would have refitted by now
    assert page.evaluate("() => window.fleetmapViewer.map.getCenter()") == chosen
    assert not page.evaluate(_SHOWS_BOUNDS_JS, _bounds(base, map_id))
    assert not page.page_errors, page.page_errors


#: Tiles the viewer keeps (to refresh them) whose image is no longer on the page.
_DETACHED_TILES_JS = """
() => [...window.fleetmapViewer.state.shownTiles.values()].filter((t) => !t.el.isConnected).length
"""


def test_tiles_aborted_by_a_zoom_are_forgotten(page: Any, shared_svc: ServiceProcess) -> None:
    """Tiles still loading when the user zooms again (an animated zoom, as the buttons and the wheel
    do) are aborted: Leaflet takes them off the map and fires 'tileabort', not 'tileunload'. The
    viewer kept them in its list of shown tiles, and every reset after (a reconnect, a replaced map)
    asked the service for each of them again, for nothing. Tile answers are held back here so that
    the second zoom catches the first one's tiles loading."""
    base, map_id = shared_svc.base_url, "aborted"  # a map of its own on the shared service
    _make_map(base, {"r1": (2.0, 2.0)}, map_id=map_id)
    _open(page, base, f"#map={map_id}&layer=probability")
    _wait(page, _TILES_LOADED_JS, what="every tile loaded")
    page.evaluate(
        "() => { const v = window.fleetmapViewer; v.aborted = 0; v.tiles.on('tileabort', () => v.aborted++);"
        " v.zooms = 0; v.map.on('zoomend', () => v.zooms++); }"
    )
    held: list[Any] = []
    page.route("**/tiles/**", lambda route: held.append(route))  # no answer: they stay under way
    try:
        zoom = page.evaluate("() => window.fleetmapViewer.map.getZoom()")
        page.evaluate("(z) => window.fleetmapViewer.map.setZoom(z)", zoom + 1)
        _wait(page, "() => window.fleetmapViewer.zooms === 1", what="the first zoom done")
        for _ in range(50):  # the new level's requests reach the route
            if held:
                break
            page.wait_for_timeout(20)
        assert held, "no tile request was held back"
        page.evaluate("(z) => window.fleetmapViewer.map.setZoom(z)", zoom + 2)
        _wait(page, "() => window.fleetmapViewer.zooms === 2", what="the second zoom done")
        assert page.evaluate("() => window.fleetmapViewer.aborted") > 0, "no tile was aborted"
        assert page.evaluate(_DETACHED_TILES_JS) == 0
        assert not page.page_errors, page.page_errors
    finally:
        page.unroute("**/tiles/**")
        for route in held:
            with contextlib.suppress(Exception):  # one the browser cancelled itself is handled
                route.abort()
