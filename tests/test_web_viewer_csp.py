"""The web viewer under the service's Content-Security-Policy, in headless Chromium: the page is served
with the policy, and every part of the viewer (the sign-in form, Leaflet and its tiles, the robots'
SVG markers and trails, the live event stream, a cell query) works without the policy blocking
anything, as a browser reports it both ways (`securitypolicyviolation` events and console reports).
A policy stricter than what the viewer loads shows up here, rather than as a broken viewer. Same
Chromium and skip rule as test_web_viewer.py. See fleetmap.api.security_headers.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from service_process import ServiceProcess
from test_auth import READ, WRITE, bearer
from test_web_viewer import _LOADED_TILES_JS, CHROMIUM, SHOW_MS, _tile_pixels, _wait
from test_web_viewer_recovery import _scan
from test_web_viewer_signin import (
    _CONNECTED_JS,
    _ROW,
    _SIGN_IN_GONE_JS,
    _SIGN_IN_SHOWN_JS,
    MAP_ID,
    ROBOT_ID,
    _map_with_a_robot,
    _sign_in,
    _tokens,
)

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)


def test_the_policy_blocks_nothing_the_viewer_needs(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    tokens = _tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    base = service_factory("--in-memory", "--auth-tokens", str(tokens), "--require-read-token").base_url
    _map_with_a_robot(base)
    tile_statuses: dict[str, int] = {}
    page.on("response", lambda r: tile_statuses.__setitem__(r.url, r.status) if "/tiles/" in r.url else None)

    # The page comes with its policy (the test would prove nothing without one).
    response = page.goto(f"{base}/#map={MAP_ID}&layer=probability")
    assert response is not None and "script-src 'self'" in response.headers["content-security-policy"]
    # Its scripts ran (Leaflet and app.js) and asked for a token.
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")
    _sign_in(page, READ)
    _wait(page, _SIGN_IN_GONE_JS, what="the form gone")
    _wait(page, _CONNECTED_JS, what="the event stream connected")

    # Tiles drawn, the robot's marker (inline SVG) and row, Leaflet's styles applied.
    _wait(page, f"() => {_LOADED_TILES_JS}.length > 0", what="loaded tiles")
    drawn = _tile_pixels(page, tile_statuses)
    assert sum(t["opaque"] for t in drawn) > 1000, drawn
    page.wait_for_selector(_ROW, timeout=SHOW_MS)
    assert page.locator(".robot-marker svg").count() == 1
    # leaflet.css positions the map's panes: without the style sheet they would be static.
    assert page.eval_on_selector(".leaflet-pane", "el => getComputedStyle(el).position") == "absolute"
    # style.css: the toolbar is laid out as the viewer's style sheet says (not the browser's default).
    assert page.eval_on_selector("#toolbar", "el => getComputedStyle(el).display") == "flex"

    # Live over the event stream, and a cell query (fetch).
    _scan(base, MAP_ID, ROBOT_ID, 2, 2.5, 2.0, headers=bearer(WRITE))
    _wait(page, f"() => document.querySelector('{_ROW} .scans')?.textContent === '2 scans'", what="2 scans")
    page.locator("#map").focus()
    page.keyboard.press("Enter")
    _wait(page, "() => document.querySelector('#cell-info table') !== null", what="the cell's values")

    # Nothing was blocked, as the page's events and the browser's console tell (the fixture checks
    # the console again once the test ends).
    assert page.evaluate("() => window.cspViolations") == []
    assert page.csp_reports == [] and page.page_errors == [], (page.csp_reports, page.page_errors)
