"""Security headers on the real service: every answer is `nosniff`, unframeable and sends no
referrer, whatever made it (a route, an error handler, the auth middleware, the body limit), and the
web viewer's files carry a Content-Security-Policy allowing only what the viewer loads. See
fleetmap.api.security_headers and docs/security.md, "Browsers"; test_web_viewer_csp.py checks in a
real browser that the policy blocks nothing the viewer needs."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
from service_process import ServiceProcess
from test_auth import READ, WRITE, bearer
from test_operations import BROKEN_TILES_SERVICE, post_scans

#: The web viewer of this checkout, which the service under test serves at `/` and `/static/`.
WEB_DIR = Path(__file__).resolve().parents[1] / "clients" / "web"
#: A JavaScript file's `Content-Type`, without which a browser runs no module script (nor, as the
#: answer is `nosniff`, any script).
JAVASCRIPT_TYPES = {"text/javascript", "application/javascript"}


def viewer_modules() -> list[str]:
    """The viewer's ES modules as its page asks for them: `app.js` (index.html's module script), then
    every module an `import ... from './x.js'` names, followed from module to module."""
    found: list[str] = []
    todo = ["app.js"]
    while todo:
        name = todo.pop(0)
        if name not in found:
            found.append(name)
            source = (WEB_DIR / name).read_text(encoding="utf-8")
            todo += re.findall(r"^import [^;]*? from '\./([\w.-]+\.js)';$", source, re.M)
    return [f"/static/{name}" for name in found]


#: The viewer's files, as its page asks for them, and a Leaflet image its style sheet names.
VIEWER_FILES = ["/", *viewer_modules(), "/static/style.css", "/vendor/leaflet/leaflet.js",
                "/vendor/leaflet/leaflet.css", "/vendor/leaflet/images/layers.png"]  # fmt: skip
EVERY_ANSWER = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "no-referrer",
}
#: The policy's directives, as a browser reads them (order does not matter).
VIEWER_POLICY = {
    "default-src": "'none'",
    "script-src": "'self'",
    "style-src": "'self'",
    "img-src": "'self' data:",
    "connect-src": "'self'",
    "base-uri": "'none'",
    "form-action": "'none'",
    "frame-ancestors": "'none'",
}


def policy(response: httpx.Response) -> dict[str, str]:
    """The answer's Content-Security-Policy, directive -> sources."""
    header = response.headers["content-security-policy"]
    directives = (part.strip().partition(" ") for part in header.split(";"))
    return {name: sources.strip() for name, _, sources in directives}


def assert_every_answer_headers(response: httpx.Response, what: str) -> None:
    for name, value in EVERY_ANSWER.items():
        assert response.headers.get(name) == value, (what, response.status_code, name, response.headers)


@pytest.fixture(scope="module")
def in_memory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One `--in-memory` service for the module's tests that need no other option: they read its
    answers' headers, and make no map but their own."""
    with ServiceProcess(tmp_path_factory.mktemp("security-headers"), ["--in-memory"]) as service:
        yield service


def test_the_viewer_files_carry_a_policy_allowing_only_what_the_viewer_loads(
    in_memory: ServiceProcess,
) -> None:
    url = in_memory.base_url
    for path in VIEWER_FILES:
        for r in (httpx.get(f"{url}{path}"), httpx.head(f"{url}{path}")):
            assert r.status_code == 200, (path, r.status_code)
            assert policy(r) == VIEWER_POLICY, (path, r.headers)
            assert_every_answer_headers(r, path)
            if path.endswith(".js"):
                assert r.headers["content-type"].partition(";")[0] in JAVASCRIPT_TYPES, (path, r.headers)
    # Every script of the viewer is one its page loads (app.js imports it, or a module app.js imports).
    scripts = {f"/static/{p.name}" for p in WEB_DIR.glob("*.js")}
    assert scripts == {path for path in VIEWER_FILES if path.startswith("/static/") and path.endswith(".js")}
    # A file the viewer does not have is still under the viewer's folder: same headers on its 404.
    r = httpx.get(f"{url}/static/nothing.js")
    assert r.status_code == 404 and policy(r) == VIEWER_POLICY


def test_every_answer_is_nosniff_unframeable_and_sends_no_referrer(in_memory: ServiceProcess) -> None:
    url = in_memory.base_url
    assert httpx.put(f"{url}/maps/m", json={}).status_code == 201
    answers = {
        "map list": httpx.get(f"{url}/maps"),
        "tile": httpx.get(f"{url}/maps/m/tiles/0/0/-1.png"),
        "spec": httpx.get(f"{url}/openapi.json"),
        "metrics": httpx.get(f"{url}/metrics"),
        "404 of the error handler": httpx.get(f"{url}/maps/nothing"),
        "422 of validation": httpx.get(f"{url}/maps/m/cell", params={"x": "nan", "y": 0}),
        "405": httpx.delete(f"{url}/healthz"),
        "413 of the body limit": httpx.put(f"{url}/maps/m", content=b"x" * (17 * 1024 * 1024)),
    }
    with httpx.stream("GET", f"{url}/maps/m/events", timeout=10) as events:
        answers["event stream"] = events
    for what, r in answers.items():
        assert_every_answer_headers(r, what)
        # The policy is the viewer's: JSON, images and the API's own pages (Swagger UI) get none.
        assert "content-security-policy" not in r.headers, what
    assert answers["404 of the error handler"].status_code == 404
    assert answers["413 of the body limit"].status_code == 413


def test_the_auth_middlewares_answers_carry_them_too(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    url = service_factory("--in-memory", "--auth-tokens", str(tokens), "--require-read-token").base_url
    answers = {
        "401": httpx.get(f"{url}/maps"),
        "403": httpx.put(f"{url}/maps/m", json={}, headers=bearer(READ)),
        "sign-in": httpx.post(f"{url}/session", headers=bearer(READ)),
    }
    assert [r.status_code for r in answers.values()] == [401, 403, 200]
    for what, r in answers.items():
        assert_every_answer_headers(r, what)
    assert policy(httpx.get(f"{url}/")) == VIEWER_POLICY  # the page is open, and has its policy


def test_a_bugs_500_carries_them_too(tmp_path: Path) -> None:
    """An exception no handler expected is answered 500 by Starlette's `ServerErrorMiddleware`, which
    Starlette puts outside every middleware of the app: the 500 carried none of the headers (nor
    `Cache-Control`). The service is the real one, with a fault injected in the PNG encoder
    (test_operations.py's `BROKEN_TILES_SERVICE`): there is no bug to trigger on purpose."""
    svc = ServiceProcess(tmp_path, ["--in-memory"])
    svc.args[1:3] = ["-c", BROKEN_TILES_SERVICE]
    with svc:
        post_scans(svc.base_url, "m", "r", range(1, 3))  # cells to draw: the encoder is called
        r = httpx.get(f"{svc.base_url}/maps/m/tiles/0/0/0.png")
        assert r.status_code == 500 and r.json() == {"detail": "internal server error (logged on the server)"}
        assert_every_answer_headers(r, "500 of a bug")
        assert r.headers.get("cache-control") == "no-cache", r.headers
