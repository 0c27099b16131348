"""The web viewer on a service that needs a token to read (`--require-read-token`), in headless
Chromium: the page loads, asks for a token, says when it is wrong, and with a read token shows the
map (tiles drawn, the robot, the live event stream) through the session cookie `POST /session` set;
a revoked token brings the form back, and signing out clears the cookie. With reads open the page
never asks. Same Chromium and skip rule as test_web_viewer.py; one in-memory service per test that
revokes a token, restarts it, fails a sign-in or needs other options, and one shared by the others.
"""

from __future__ import annotations

import contextlib
import hashlib
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_process import ServiceProcess, wait_for
from test_auth import READ, WRITE, bearer
from test_web_viewer import _LOADED_TILES_JS, CHROMIUM, SHOW_MS, _tile_pixels, _wait
from test_web_viewer_recovery import _scan
from test_web_viewer_usability import _CONTRAST_JS, _FOCUS_JS

from fleetmap.auth import SESSION_COOKIE

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: install Debian's chromium package (make system-deps)",
)

MAP_ID = "secured"
ROBOT_ID = "r1"
UNKNOWN = "unknown-token-0123456789"
_SIGN_IN_SHOWN_JS = "() => !document.getElementById('sign-in').hidden"
_SIGN_IN_GONE_JS = "() => document.getElementById('sign-in').hidden"
_CONNECTED_JS = "() => document.getElementById('status').dataset.state === 'connected'"
_ROW = f'#robot-list li[data-robot-id="{ROBOT_ID}"]'


def _tokens(path: Path, *lines: str) -> Path:
    path.write_text("".join(f"{line}\n" for line in lines))
    return path


def _map_with_a_robot(base: str, map_id: str = MAP_ID) -> None:
    """Map `map_id` with a scan of ROBOT_ID (a ring of walls around (2, 2)), written with the write
    token."""
    r = httpx.put(f"{base}/maps/{map_id}", json={}, headers=bearer(WRITE), timeout=10.0)
    assert r.status_code == 201, r.text
    _scan(base, map_id, ROBOT_ID, 1, 2.0, 2.0, headers=bearer(WRITE))


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One in-memory service needing a token to read (the read and the write token) for the module's
    tests that each show a map of their own, if any, and neither revoke a token, restart the
    service, nor fail a sign-in (the failures a client address may make are counted service-wide);
    those tests have a service of their own."""
    tmp = tmp_path_factory.mktemp("viewer-signin")
    tokens = _tokens(tmp / "tokens.txt", f"read {READ}", f"write {WRITE}")
    with ServiceProcess(tmp, ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]) as svc:
        yield svc


def _sign_in(page: Any, token: str) -> None:
    page.fill("#sign-in-token", token)
    page.press("#sign-in-token", "Enter")


def _session_cookies(page: Any) -> list[dict[str, Any]]:
    return [c for c in page.context.cookies() if c["name"] == SESSION_COOKIE]


def test_the_viewer_signs_in_with_a_read_token(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    tokens = _tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    svc = service_factory("--in-memory", "--auth-tokens", str(tokens), "--require-read-token")
    assert svc.proc is not None
    base = svc.base_url
    _map_with_a_robot(base)
    tile_statuses: dict[str, int] = {}
    page.on("response", lambda r: tile_statuses.__setitem__(r.url, r.status) if "/tiles/" in r.url else None)

    # The page itself loads (its files are open); its first read is refused, and it asks for a token.
    page.goto(f"{base}/#map={MAP_ID}&layer=probability")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")
    assert page.inner_text("#status-text") == "sign in to see the maps"
    assert page.evaluate("() => document.activeElement.id") == "sign-in-token"
    assert page.get_attribute("#sign-in-token", "type") == "password"
    assert page.is_hidden("#sign-out") and page.is_hidden("#error")  # a 401 is no error to report
    assert page.eval_on_selector("#map-select", "el => el.disabled")
    assert page.get_by_label("API token").count() == 1
    low = [c for c in page.evaluate(_CONTRAST_JS) if c["ratio"] < c["need"]]
    assert low == [], low
    for _ in range(2):  # the token field, then the button: each shows a focus outline
        focus = page.evaluate(_FOCUS_JS)
        assert focus["style"] not in ("none", "auto") and focus["width"] >= 2, focus
        page.keyboard.press("Tab")

    # A wrong token: said under the form, no cookie, the form stays.
    _sign_in(page, UNKNOWN)
    _wait(
        page,
        "() => { const e = document.getElementById('sign-in-error');"
        " return !e.hidden && e.textContent.includes('unknown token'); }",
        what="'unknown token' under the form",
    )
    assert page.is_visible("#sign-in") and _session_cookies(page) == []

    # The read token: the map, its tiles drawn, its robot, the live stream, all through the cookie.
    _sign_in(page, READ)
    _wait(page, _SIGN_IN_GONE_JS, what="the form gone")
    _wait(page, _CONNECTED_JS, what="the event stream connected")
    (cookie,) = _session_cookies(page)
    assert cookie["value"] == hashlib.sha256(READ.encode()).hexdigest()
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and cookie["path"] == "/"
    assert page.evaluate("() => document.cookie") == ""  # out of the page's scripts' reach
    assert page.input_value("#sign-in-token") == ""  # the page keeps no token
    assert page.eval_on_selector("#map-select", "el => el.value") == MAP_ID
    assert page.evaluate("() => location.hash") == f"#map={MAP_ID}&layer=probability"
    _wait(page, f"() => {_LOADED_TILES_JS}.length > 0", what="loaded tiles")
    drawn = _tile_pixels(page, tile_statuses)
    assert sum(t["opaque"] for t in drawn) > 1000, drawn  # the ring of walls and the free space in it
    page.wait_for_selector(_ROW, timeout=SHOW_MS)
    assert page.is_visible("#sign-out")

    # Live: a new scan reaches the page over the event stream (the robot's count goes up).
    _scan(base, MAP_ID, ROBOT_ID, 2, 2.5, 2.0, headers=bearer(WRITE))
    _wait(page, f"() => document.querySelector('{_ROW} .scans')?.textContent === '2 scans'", what="2 scans")
    assert page.is_hidden("#error"), page.inner_text("#error")

    # The token is revoked: the next map-list poll is refused, and the form is back, the map gone.
    _tokens(tokens, f"write {WRITE}")
    svc.proc.send_signal(signal.SIGHUP)
    wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form again after the token was revoked")
    assert page.inner_text("#status") == "sign in to see the maps"  # no 'last update' of a map not shown
    assert page.evaluate("() => document.querySelectorAll('#map img.leaflet-tile').length") == 0
    assert page.evaluate("() => document.querySelectorAll('#robot-list li[data-robot-id]').length") == 0
    assert page.evaluate(
        "() => [...document.querySelectorAll('#map-select option')].map((o) => o.value)"
    ) == [""]
    assert page.is_hidden("#sign-out")

    # Another token signs in again, back on the map the URL still names; signing out clears the cookie.
    _sign_in(page, WRITE)
    _wait(page, _CONNECTED_JS, what="connected again")
    assert page.eval_on_selector("#map-select", "el => el.value") == MAP_ID
    page.click("#sign-out")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form after signing out")
    assert _session_cookies(page) == []
    assert not page.page_errors, page.page_errors


def test_with_reads_open_the_viewer_never_asks(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    """Tokens for writing only: the page shows the map as it always has, with no form and no
    'Sign out'."""
    tokens = _tokens(tmp_path / "tokens.txt", f"write {WRITE}")
    base = service_factory("--in-memory", "--auth-tokens", str(tokens)).base_url
    _map_with_a_robot(base)
    page.goto(f"{base}/#map={MAP_ID}")
    _wait(page, _CONNECTED_JS, what="connected")
    page.wait_for_selector(_ROW, timeout=SHOW_MS)
    assert page.is_hidden("#sign-in") and page.is_hidden("#sign-out")
    assert _session_cookies(page) == []
    assert not page.page_errors, page.page_errors


def test_the_viewer_says_when_sign_ins_are_refused_for_a_while(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    """Past the failed sign-ins allowed (here one), the form says why it cannot sign in and when to
    try again (the 429's detail), rather than calling the right token unknown, nor marking it wrong
    (a screen reader said the field was invalid, as after an unknown token)."""
    tokens = _tokens(tmp_path / "tokens.txt", f"read {READ}")
    svc = service_factory(
        "--in-memory", "--auth-tokens", str(tokens), "--require-read-token", "--max-failed-sign-ins", "1"
    )
    page.goto(f"{svc.base_url}/")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")
    _sign_in(page, UNKNOWN)
    _wait(page, "() => document.getElementById('sign-in-error').textContent.includes('unknown token')")
    assert page.get_attribute("#sign-in-token", "aria-invalid") == "true"
    _sign_in(page, READ)
    _wait(
        page,
        "() => document.getElementById('sign-in-error').textContent.includes('too many failed sign-ins')",
        what="the 429's detail under the form",
    )
    assert "try again in" in page.inner_text("#sign-in-error")
    assert page.get_attribute("#sign-in-token", "aria-invalid") is None
    assert page.is_visible("#sign-in") and _session_cookies(page) == []
    assert not page.page_errors, page.page_errors


def test_a_sign_out_that_failed_can_be_tried_again(page: Any, secured: ServiceProcess) -> None:
    """The network drops the sign-out (DELETE session): the page says it could not sign out and keeps
    'Sign out', since the browser still holds its session; the next click signs out. ('Sign out' went
    at the first click, and with it the only way to end the session, over reloads too.)"""
    map_id = "sign-out"  # a map of its own on the module's service
    _map_with_a_robot(secured.base_url, map_id)
    page.goto(f"{secured.base_url}/#map={map_id}")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")
    _sign_in(page, READ)
    _wait(page, _CONNECTED_JS, what="connected")

    def drop_sign_outs(route: Any) -> None:
        if route.request.method == "DELETE":
            route.abort()
        else:
            route.continue_()

    page.route("**/session", drop_sign_outs)
    page.click("#sign-out")
    _wait(
        page,
        "() => { const e = document.getElementById('error');"
        " return !e.hidden && e.textContent.includes('cannot sign out'); }",
        what="'cannot sign out'",
    )
    assert page.is_visible("#sign-out") and len(_session_cookies(page)) == 1
    assert page.evaluate("() => localStorage.getItem('fleetmap.signedIn')") == "1"  # for a reload

    page.unroute("**/session")
    page.click("#sign-out")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form after signing out")
    assert _session_cookies(page) == [] and page.is_hidden("#sign-out")
    assert not page.page_errors, page.page_errors


@contextlib.contextmanager
def _two_tabs(
    browser: Any, svc: ServiceProcess, map_id: str, second_script: str | None = None
) -> Iterator[tuple[Any, Any, list[str]]]:
    """Two tabs of one browser on `svc` (a service that needs a token to read), holding map `map_id`
    with a robot, each showing its sign-in form: yields (first tab, second tab, the pages' errors).
    The second runs `second_script` before its page's own."""
    _map_with_a_robot(svc.base_url, map_id)
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        first, second = context.new_page(), context.new_page()
        if second_script is not None:
            second.add_init_script(second_script)
        errors: list[str] = []
        for tab in (first, second):
            tab.on("pageerror", lambda e: errors.append(str(e)))
            tab.goto(f"{svc.base_url}/#map={map_id}")
            _wait(tab, _SIGN_IN_SHOWN_JS, what="the sign-in form")
        yield first, second, errors
    finally:
        context.close()


def test_signing_in_in_one_tab_signs_in_the_others(browser: Any, secured: ServiceProcess) -> None:
    """Two tabs of one browser ask for a token; the user signs in in one. The session cookie is the
    browser's, so the other tab shows the map too, without its form (it kept asking for the token,
    with no request that could find out, until it was reloaded)."""
    with _two_tabs(browser, secured, "tabs-in") as (first, second, errors):
        _sign_in(first, READ)
        _wait(first, _CONNECTED_JS, what="the first tab connected")
        _wait(second, _SIGN_IN_GONE_JS, what="the second tab's form gone")
        _wait(second, _CONNECTED_JS, what="the second tab connected")
        second.wait_for_selector(_ROW, timeout=SHOW_MS)
        assert second.is_visible("#sign-out")
        assert errors == [], errors


def test_signing_out_in_one_tab_signs_out_the_others(browser: Any, secured: ServiceProcess) -> None:
    """Two tabs show the map, signed in; the user signs out in one. The other shows the form at once,
    saying the session ended: its map and its event stream, opened with the cookie, went on until
    its next poll of the map list (5 s), which is turned off here so that only the sign-out can end
    them (the other tab's reaction to signing in was handled, to signing out not)."""
    # The second tab polls no map list (MAPS_REFRESH_MS): only what signing out does can reach it.
    no_polls = (
        "{ const every = window.setInterval;"
        " window.setInterval = (f, ms, ...a) => (ms === 5000 ? 0 : every(f, ms, ...a)); }"
    )
    with _two_tabs(browser, secured, "tabs-out", second_script=no_polls) as (first, second, errors):
        _sign_in(first, READ)
        for tab in (first, second):
            _wait(tab, _CONNECTED_JS, what="connected")
        second.wait_for_selector(_ROW, timeout=SHOW_MS)

        first.click("#sign-out")
        _wait(first, _SIGN_IN_SHOWN_JS, what="the form in the tab that signed out")
        _wait(second, _SIGN_IN_SHOWN_JS, what="the form in the other tab")
        assert "session has ended" in second.inner_text("#sign-in-error")
        assert second.is_hidden("#sign-out") and second.query_selector(_ROW) is None
        assert second.evaluate("() => document.getElementById('status').dataset.state") == "signin"
        assert errors == [], errors


@pytest.mark.parametrize("tokens_after", ["none", "for writes only"])
def test_a_service_back_with_reads_open_lets_the_form_show_the_maps(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path, tokens_after: str
) -> None:
    """The page asks for a token; the service restarts with reads open to anyone: without tokens, or
    with tokens for writes only. Signing in, whatever it answers (404: nothing to sign in to; 401
    for a token no longer listed), shows the maps, the form gone. The form said 'there is nothing
    to sign in to (reads need no token)', or 'unknown token', and stayed, with no way to the maps
    but a reload."""
    tokens = _tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    svc = service_factory("--auth-tokens", str(tokens), "--require-read-token")
    page.goto(f"{svc.base_url}/#map={MAP_ID}")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")

    svc.stop()
    dropped = (
        ("--require-read-token",)
        if tokens_after != "none"
        else (str(tokens), "--auth-tokens", "--require-read-token")
    )
    svc.args = [a for a in svc.args if a not in dropped]
    _tokens(tokens, f"write {WRITE}")
    svc.start()
    _map_with_a_robot(svc.base_url)

    _sign_in(page, READ)
    _wait(page, _SIGN_IN_GONE_JS, what="the form gone")
    _wait(page, _CONNECTED_JS, what="the event stream connected")
    page.wait_for_selector(_ROW, timeout=SHOW_MS)
    assert page.eval_on_selector("#map-select", "el => el.value") == MAP_ID
    assert page.is_hidden("#sign-out") and _session_cookies(page) == []  # no session: none is needed
    assert page.input_value("#sign-in-token") == ""
    assert not page.page_errors, page.page_errors


def test_the_form_says_when_the_browser_does_not_keep_the_session_cookie(
    page: Any, secured: ServiceProcess
) -> None:
    """The service accepts the token but the browser keeps no cookie (cookies blocked for the site, or
    a `Secure` cookie, a proxy having said https, on a page served over http: simulated here by an
    answer without the cookie). The form says so, not an unknown token, and the token field is not
    marked wrong. (It went and came back at once, emptied, saying nothing: the user could only
    retype the right token, to the same end.)"""
    page.goto(f"{secured.base_url}/")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")

    def accept_without_a_cookie(route: Any) -> None:
        if route.request.method == "POST":
            route.fulfill(status=200, json={"role": "read"})
        else:
            route.continue_()

    page.route("**/session", accept_without_a_cookie)
    _sign_in(page, READ)
    _wait(
        page,
        "() => document.getElementById('sign-in-error').textContent"
        ".includes('did not keep the session cookie')",
        what="why the sign-in did not take",
    )
    assert page.is_visible("#sign-in") and page.is_hidden("#sign-out")
    assert page.get_attribute("#sign-in-token", "aria-invalid") is None  # the token is right
    assert page.inner_text("#status-text") == "sign in to see the maps"
    assert not page.page_errors, page.page_errors


def test_the_form_says_why_it_asks_again_when_a_session_ends(
    page: Any, service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    """The token of the page's session is revoked while its map is shown: the form that replaces the
    map says the session ended and why it may have (it said only what it says to a first visitor,
    that the service needs a token, and the map the user was watching was simply gone). Signing out,
    which the user asked for, and a first visit say nothing of the kind."""
    tokens = _tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    svc = service_factory("--in-memory", "--auth-tokens", str(tokens), "--require-read-token")
    assert svc.proc is not None
    _map_with_a_robot(svc.base_url)
    page.goto(f"{svc.base_url}/#map={MAP_ID}")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form")
    assert page.is_hidden("#sign-in-error")  # a first visit: nothing ended
    _sign_in(page, READ)
    _wait(page, _CONNECTED_JS, what="connected")

    _tokens(tokens, f"write {WRITE}")
    svc.proc.send_signal(signal.SIGHUP)
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form after the token was revoked")
    _wait(page, "() => !document.getElementById('sign-in-error').hidden", what="why the form is back")
    said = page.inner_text("#sign-in-error")
    assert "session has ended" in said and "revoked" in said, said
    assert page.get_attribute("#sign-in-token", "aria-invalid") is None  # nothing typed was wrong

    _sign_in(page, WRITE)
    _wait(page, _CONNECTED_JS, what="connected again")
    page.click("#sign-out")
    _wait(page, _SIGN_IN_SHOWN_JS, what="the sign-in form after signing out")
    assert page.is_hidden("#sign-in-error"), page.inner_text("#sign-in-error")
    assert not page.page_errors, page.page_errors
