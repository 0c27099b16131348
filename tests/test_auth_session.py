"""Browser sessions on the real service (`POST /session`, `DELETE /session`): with
`--require-read-token` the web viewer's files are open, a valid token buys a session cookie that
unlocks reads (the map list, tiles, the event stream) and never a write, revoking the token ends it,
and every answer a cookie could unlock is kept out of shared caches. See fleetmap.auth and
docs/security.md, "REST API"."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_process import ServiceProcess, wait_for
from test_api_security_headers import viewer_modules
from test_auth import ADMIN, READ, SCAN, WRITE, bearer
from test_http_exhaustion import metric

from fleetmap.api import ApiSettings, create_app
from fleetmap.auth import (
    MAX_SESSION_VALUES,
    SESSION_COOKIE,
    UNKNOWN_SESSION,
    TokenSet,
    is_read_request,
    required_role,
)
from fleetmap.registry import MapRegistry

TILE = "/maps/m/tiles/0/0/-1.png"
UNKNOWN = "unknown-token-0123456789"
#: The viewer's files, as its page asks for them (its ES modules: before the user can sign in).
VIEWER_FILES = ["/", *viewer_modules(), "/static/style.css", "/vendor/leaflet/leaflet.js",
                "/vendor/leaflet/leaflet.css"]  # fmt: skip
#: What a request that needs `write` answers without a token, cookie or not.
WRITE_401 = "this request needs a token with the 'write' role: send 'Authorization: Bearer <token>'"


def session_of(token: str) -> str:
    """The session cookie's value for `token`, as docs/security.md describes it."""
    return hashlib.sha256(token.encode()).hexdigest()


def cookie(value: str) -> dict[str, str]:
    """A request header carrying the session cookie `value` (and another cookie, as browsers send)."""
    return {"Cookie": f"theme=dark; {SESSION_COOKIE}={value}"}


def set_cookie(response: httpx.Response) -> tuple[str, set[str]]:
    """The session cookie a response sets: its value, and its attributes (`HttpOnly`, `Path=/`,
    ..., names as sent)."""
    (header,) = response.headers.get_list("set-cookie")
    pair, *attributes = (part.strip() for part in header.split(";"))
    name, _, value = pair.partition("=")
    assert name == SESSION_COOKIE, header
    return value, set(attributes)


def write_tokens(path: Path, *lines: str) -> Path:
    path.write_text("".join(f"{line}\n" for line in lines))
    return path


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A service requiring a read token, holding map `m` with one scan (posted with the write token)."""
    tmp = tmp_path_factory.mktemp("secured")
    tokens = write_tokens(tmp / "tokens.txt", f"read {READ}", f"write {WRITE}", f"admin {ADMIN}")
    with ServiceProcess(tmp, ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]) as svc:
        url = svc.base_url
        assert httpx.put(f"{url}/maps/m", json={}, headers=bearer(WRITE)).status_code == 201
        r = httpx.post(f"{url}/maps/m/scans", params={"robot_id": "r"}, json=SCAN, headers=bearer(WRITE))
        assert r.status_code == 200, r.text
        yield svc


def test_which_requests_a_session_may_stand_for() -> None:
    for path in ("/", "/static/app.js", "/vendor/leaflet/images/marker-icon.png"):
        assert required_role("GET", path, True) is None, path
        assert required_role("HEAD", path, True) is None, path
    assert required_role("GET", "/static", True) == "read"  # not a file of the viewer
    assert required_role("GET", "/staticx/app.js", True) == "read"
    assert required_role("PUT", "/static/app.js", True) == "write"  # only reading them is open
    assert required_role("POST", "/session", False) == "read"  # any valid token, reads open or not
    assert required_role("DELETE", "/session", True) is None
    assert is_read_request("GET", "/maps") and is_read_request("HEAD", "/maps/m/events")
    assert is_read_request("POST", "/maps/m/cells") and is_read_request("POST", "/maps/m/raycast")
    writes = [("POST", "/maps/m/scans"), ("PUT", "/maps/m"), ("DELETE", "/maps/m"),
              ("PUT", "/maps/m/snapshot"), ("PUT", "/maps/m/import"), ("POST", "/session")]  # fmt: skip
    for method, path in writes:
        assert not is_read_request(method, path), (method, path)


def test_the_viewer_files_are_open_when_reads_need_a_token(secured: ServiceProcess) -> None:
    url = secured.base_url
    for path in VIEWER_FILES:
        r = httpx.get(f"{url}{path}")
        assert r.status_code == 200 and r.content, (path, r.status_code, r.text)
        assert httpx.head(f"{url}{path}").status_code == 200, path
    # Everything else keeps its rule: map data, the spec, a file outside the viewer's folders.
    for path in ("/maps", "/maps/m", TILE, "/openapi.json", "/static", "/docs"):
        assert httpx.get(f"{url}{path}").status_code == 401, path


def test_signing_in_sets_a_cookie_that_holds_no_token(secured: ServiceProcess) -> None:
    url = secured.base_url
    for token, role in ((READ, "read"), (WRITE, "write"), (ADMIN, "admin")):
        r = httpx.post(f"{url}/session", headers=bearer(token))
        assert r.status_code == 200 and r.json() == {"role": role}, r.text
        value, attributes = set_cookie(r)
        assert value == session_of(token) and token not in r.headers["set-cookie"]
        assert attributes == {"HttpOnly", "SameSite=Strict", "Path=/"}  # not Secure: plain http
        assert r.headers["cache-control"] == "no-store"
    # Behind a TLS proxy on the same machine (uvicorn trusts loopback's X-Forwarded-Proto): Secure.
    r = httpx.post(f"{url}/session", headers={**bearer(READ), "X-Forwarded-Proto": "https"})
    assert r.status_code == 200 and set_cookie(r)[1] == {"HttpOnly", "SameSite=Strict", "Path=/", "Secure"}


def test_the_trusted_proxies_are_an_option(tmp_path: Path) -> None:
    """`--forwarded-allow-ips` names the proxies whose X-Forwarded-Proto is believed: naming another
    address than this test's 127.0.0.1, its `https` no longer makes the cookie Secure (before, only
    uvicorn's own environment variable could say which proxies to trust, not an option of `fleetmap
    serve` as every other setting is)."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}")
    forwarded = {**bearer(READ), "X-Forwarded-Proto": "https"}
    args = ["--in-memory", "--auth-tokens", str(tokens), "--forwarded-allow-ips", "10.1.2.3"]
    with ServiceProcess(tmp_path, args) as svc:
        r = httpx.post(f"{svc.base_url}/session", headers=forwarded)
        assert r.status_code == 200 and "Secure" not in set_cookie(r)[1], r.headers


def test_trusted_proxies_that_uvicorn_would_never_match_are_refused(tmp_path: Path) -> None:
    """uvicorn takes an entry of `--forwarded-allow-ips` that is no address, network or `*` as a name
    that no connection's address equals: `10.1.2.3,127.0.0.1` (uvicorn's own variable's separator),
    `127.0.0.1,` (a variable's list split at spaces), a host name. The proxy was silently not trusted,
    and the cookie set behind it lacked `Secure`: found by giving the loopback proxy with a comma."""
    cases = [
        (
            ["--forwarded-allow-ips", "10.1.2.3,127.0.0.1"],
            {},
            "'10.1.2.3,127.0.0.1' (separate addresses with spaces",
        ),
        (["--forwarded-allow-ips", "proxy.internal"], {}, "'proxy.internal' (host names are not looked up)"),
        (
            ["--forwarded-allow-ips", "127.0.0.300"],
            {},
            "expected an IP address, a network (10.0.0.0/8) or '*'",
        ),
        ([], {"FLEETMAP_FORWARDED_ALLOW_IPS": "127.0.0.1, 10.1.2.3"}, "$FLEETMAP_FORWARDED_ALLOW_IPS="),
        # uvicorn's own variable (docs/api.md names it), read without the option: checked alike.
        ([], {"FORWARDED_ALLOW_IPS": "127.0.0.1, proxy.internal"}, "$FORWARDED_ALLOW_IPS='127.0.0.1, "),
    ]
    for args, env, message in cases:
        done = subprocess.run(
            [sys.executable, "-m", "fleetmap.server", "--in-memory", *args],
            capture_output=True, text=True, env={**os.environ, **env}, timeout=60,
        )  # fmt: skip
        assert done.returncode == 2 and message in done.stderr, (args, env, done.stderr)
    # What is accepted is what uvicorn matches: a network holding 127.0.0.1 (host bits cleared), and
    # `*` among other addresses (uvicorn trusts all only for `*` alone: in a list it was ignored).
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}")
    forwarded = {**bearer(READ), "X-Forwarded-Proto": "https"}
    # So is uvicorn's variable's: it went to uvicorn as it was, whose strict parse took the network
    # for a name no address equals, and the proxy was silently not trusted.
    for trusted, env in (
        (["--forwarded-allow-ips", "127.0.0.5/8"], {}),
        (["--forwarded-allow-ips", "10.1.2.3", "*"], {}),
        ([], {"FORWARDED_ALLOW_IPS": "10.1.2.3, 127.0.0.5/8"}),
    ):
        args = ["--in-memory", "--auth-tokens", str(tokens), *trusted]
        with ServiceProcess(tmp_path, args, env=env) as svc:
            r = httpx.post(f"{svc.base_url}/session", headers=forwarded)
            assert r.status_code == 200 and "Secure" in set_cookie(r)[1], (trusted, env, r.headers)


def test_signing_in_needs_a_valid_token_in_the_header(secured: ServiceProcess) -> None:
    url = secured.base_url
    for headers in ({}, bearer(UNKNOWN), cookie(session_of(READ)), {"Authorization": f"Basic {READ}"}):
        r = httpx.post(f"{url}/session", headers=headers)
        assert r.status_code == 401, (headers, r.text)
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert "set-cookie" not in r.headers, headers
    assert httpx.post(f"{url}/session", headers=bearer(UNKNOWN)).json()["detail"] == "unknown token"


def test_a_session_cookie_unlocks_reads(secured: ServiceProcess) -> None:
    url = secured.base_url
    session = cookie(session_of(READ))
    maps = httpx.get(f"{url}/maps", headers=session)
    assert maps.status_code == 200 and [m["id"] for m in maps.json()["maps"]] == ["m"]
    assert httpx.get(f"{url}/maps/m", headers=session).json()["stats"]["scans_integrated"] == 1
    tile = httpx.get(f"{url}{TILE}", headers=session)
    assert tile.status_code == 200 and tile.headers["content-type"] == "image/png"
    assert httpx.get(f"{url}/maps/m/cell", params={"x": 0, "y": 0}, headers=session).status_code == 200
    assert (
        httpx.post(f"{url}/maps/m/cells", json={"points": [[2.0, 0.0]]}, headers=session).status_code == 200
    )
    ray = {"origin": [0.0, 0.0], "angles": [0.0], "max_range": 5.0}
    assert httpx.post(f"{url}/maps/m/raycast", json=ray, headers=session).status_code == 200
    with httpx.stream("GET", f"{url}/maps/m/events", headers=session, timeout=10) as events:
        assert events.status_code == 200 and events.headers["content-type"].startswith("text/event-stream")
        assert "event: robots" in next(line for line in events.iter_lines() if line.startswith("event:"))
    # A session of a higher role unlocks reads as well; an Authorization header wins over the cookie.
    assert httpx.get(f"{url}/maps", headers=cookie(session_of(ADMIN))).status_code == 200
    r = httpx.get(f"{url}/maps", headers={**session, **bearer(UNKNOWN)})
    assert r.status_code == 401 and r.json()["detail"] == "unknown token"
    assert httpx.get(f"{url}/maps", headers={**cookie("0" * 64), **bearer(READ)}).status_code == 200

    # As a browser does it: the cookie a sign-in set goes with every request after.
    with httpx.Client(base_url=url, timeout=10) as browser:
        assert browser.get("/maps").status_code == 401
        assert browser.post("/session", headers=bearer(READ)).status_code == 200
        assert browser.get("/maps").status_code == 200 and browser.get(TILE).status_code == 200
        signed_out = browser.delete("/session")
        assert signed_out.status_code == 204
        assert browser.get("/maps").status_code == 401


def test_an_unknown_session_is_an_unknown_token(secured: ServiceProcess) -> None:
    url = secured.base_url
    for value in (session_of(UNKNOWN), "0" * 64, session_of(READ).upper(), "not-a-digest", READ):
        r = httpx.get(f"{url}/maps", headers=cookie(value))
        assert r.status_code == 401, value
        assert r.json()["detail"].startswith("unknown token") and "sign in again" in r.json()["detail"]
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert READ not in r.text


def test_another_session_cookie_does_not_hide_the_viewers_own(secured: ServiceProcess) -> None:
    """A browser sends every `fleetmap_session` it holds for the host and path, longest path first
    (RFC 6265, 5.4): one set by another page of the site (another service on the host, any port; a
    sibling subdomain, for the parent domain) came first, and only the first was read, so every read
    was a 401 and signing in again did not help. Found by sending two values, the unknown one first."""
    url = secured.base_url
    mine = session_of(READ)
    for other in (session_of(UNKNOWN), "not-a-digest", mine.upper()):
        one_header = {"Cookie": f"{SESSION_COOKIE}={other}; theme=dark; {SESSION_COOKIE}={mine}"}
        r = httpx.get(f"{url}/maps", headers=one_header)
        assert r.status_code == 200, (other, r.text)
        # Two Cookie headers (what an HTTP/2 proxy may forward as it got them).
        two_headers = [("Cookie", f"{SESSION_COOKIE}={other}"), ("Cookie", f"{SESSION_COOKIE}={mine}")]
        assert httpx.get(f"{url}{TILE}", headers=two_headers).status_code == 200, other
    # None known: the unknown token's 401, as for one.
    r = httpx.get(f"{url}/maps", headers={"Cookie": f"{SESSION_COOKIE}=0; {SESSION_COOKIE}={'0' * 64}"})
    assert r.status_code == 401 and r.json()["detail"] == UNKNOWN_SESSION
    # At most MAX_SESSION_VALUES are looked up: a header of them costs the service a bounded time.
    unknown = "; ".join(f"{SESSION_COOKIE}={n:064x}" for n in range(MAX_SESSION_VALUES))
    r = httpx.get(f"{url}/maps", headers={"Cookie": f"{unknown}; {SESSION_COOKIE}={mine}"})
    assert r.status_code == 401 and r.json()["detail"] == UNKNOWN_SESSION
    # The cookies are still no use for a write, whichever comes first.
    r = httpx.put(
        f"{url}/maps/m3", json={}, headers={"Cookie": f"{SESSION_COOKIE}=0; {SESSION_COOKIE}={mine}"}
    )
    assert r.status_code == 401 and r.json() == {"detail": WRITE_401}


def test_a_session_cookie_never_authorises_a_write(secured: ServiceProcess) -> None:
    """Even an admin's session: a page that gets the browser to send a request with its cookie (CSRF)
    can change no map. Every write answers as it would without the cookie."""
    url = secured.base_url
    scan = {**SCAN, "seq": 1}
    zipped = {"content": b"PK", "headers": {"content-type": "application/zip"}}
    writes: list[tuple[str, str, dict[str, Any]]] = [
        ("POST", "/maps/m/scans?robot_id=r", {"json": scan}),
        ("PUT", "/maps/m2", {"json": {}}),
        ("DELETE", "/maps/m", {}),
        ("PUT", "/maps/m/snapshot", zipped),
        ("PUT", "/maps/m/import?format=ros", zipped),
    ]
    for token in (READ, WRITE, ADMIN):
        session = cookie(session_of(token))
        for method, path, request in writes:
            body = {k: v for k, v in request.items() if k != "headers"}
            headers = request.get("headers", {})
            plain = httpx.request(method, f"{url}{path}", headers=headers, **body)
            with_cookie = httpx.request(method, f"{url}{path}", headers={**headers, **session}, **body)
            assert with_cookie.status_code == plain.status_code == 401, (
                token,
                method,
                path,
                with_cookie.text,
            )
            assert with_cookie.json() == plain.json() == {"detail": WRITE_401}
        # With a read token in the header the answer is the header's 403, whatever the cookie.
        r = httpx.delete(f"{url}/maps/m", headers={**session, **bearer(READ)})
        assert r.status_code == 403, r.text
    r = httpx.get(f"{url}/maps/m", headers=bearer(READ)).json()
    assert r["stats"]["scans_integrated"] == 1  # unchanged: still there, no scan added
    assert httpx.get(f"{url}/maps/m2", headers=bearer(READ)).status_code == 404


def test_every_answer_is_private_when_reads_need_a_token(secured: ServiceProcess) -> None:
    """A shared cache stores no answer to a request with `Authorization` (RFC 9111, 3.5), but it
    would store one a cookie unlocked, and serve it to anyone: every answer is `private` here."""
    url = secured.base_url
    session = cookie(session_of(READ))
    paths = ["/maps", "/maps/m", "/maps/m/cell?x=0&y=0", "/maps/m/region?format=json", TILE, "/healthz",
             "/maps/nope", *VIEWER_FILES]  # fmt: skip
    revalidated = []
    for path in paths:
        # A map's answer is no-store (docs/api.md, "Conditional writes"): no cache keeps it at all.
        meant = "no-store" if path == "/maps/m" else "private, no-cache"
        r = httpx.get(f"{url}{path}", headers=session)
        assert r.headers["cache-control"] == meant, (path, r.headers["cache-control"])
        if "etag" in r.headers:  # a revalidation's answer too
            again = httpx.get(f"{url}{path}", headers={**session, "If-None-Match": r.headers["etag"]})
            assert again.headers["cache-control"] == meant, path
            revalidated += [path] if again.status_code == 304 else []
    assert {"/maps", "/maps/m", TILE} <= set(revalidated)
    r = httpx.post(f"{url}/maps/m/cells", json={"points": [[0.0, 0.0]]}, headers=session)
    assert r.headers["cache-control"] == "private, no-cache"
    with httpx.stream("GET", f"{url}/maps/m/events", headers=session, timeout=10) as events:
        assert events.headers["cache-control"] == "private, no-cache"
    assert httpx.get(f"{url}/maps").headers["cache-control"] == "private, no-cache"  # the 401 too


def test_signing_out_clears_the_cookie_without_a_token(secured: ServiceProcess) -> None:
    r = httpx.delete(f"{secured.base_url}/session")
    assert r.status_code == 204 and r.content == b""
    value, attributes = set_cookie(r)
    assert value == "" and attributes == {"Max-Age=0", "HttpOnly", "SameSite=Strict", "Path=/"}
    assert r.headers["cache-control"] == "no-store"


def test_revoking_the_token_ends_its_sessions(tmp_path: Path) -> None:
    """The cookie is matched against the tokens in force on every request: rewriting the token file
    and SIGHUP end the session at once, with no session store to clear."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    tokens.chmod(0o600)
    with ServiceProcess(
        tmp_path, ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]
    ) as svc:
        assert svc.proc is not None
        assert "token file" not in svc.logs()  # readable by its owner only: nothing to warn of
        url = svc.base_url
        session = cookie(set_cookie(httpx.post(f"{url}/session", headers=bearer(READ)))[0])
        kept = cookie(set_cookie(httpx.post(f"{url}/session", headers=bearer(WRITE)))[0])
        assert httpx.get(f"{url}/maps", headers=session).status_code == 200

        write_tokens(tokens, f"write {WRITE}")  # the read token revoked
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
        r = httpx.get(f"{url}/maps", headers=session)
        assert r.status_code == 401 and r.json()["detail"].startswith("unknown token")
        assert httpx.get(f"{url}/maps/m/events", headers=session).status_code == 401
        assert httpx.post(f"{url}/session", headers=bearer(READ)).status_code == 401
        assert httpx.get(f"{url}/maps", headers=kept).status_code == 200  # other sessions go on
        # Given back, the token's old cookie works again: it stands for the token, nothing else.
        write_tokens(tokens, f"read {READ}", f"write {WRITE}")
        tokens.chmod(0o640)  # its group may read it now: the reload says so
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 2 API tokens read" in svc.logs(), 10, what="the second reload")
        assert httpx.get(f"{url}/maps", headers=session).status_code == 200
        warning = f"the token file {tokens} is readable by the users of its group (mode 0640)"
        wait_for(lambda: warning in svc.logs(), 10, what="the reload's warning")
        logs = svc.logs()
    for secret in (READ, WRITE, session_of(READ), session_of(WRITE)):
        assert secret not in logs


def test_an_upload_whose_token_is_revoked_while_it_arrives_changes_nothing(tmp_path: Path) -> None:
    """A snapshot upload takes minutes over a slow link, and a token may be revoked meanwhile (token
    file and SIGHUP): the map was replaced all the same, by a token no longer let in. It is now a 401
    saying so, nothing changed; an upload of a token kept is installed."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"write {WRITE}", f"admin {ADMIN}")
    with ServiceProcess(tmp_path, ["--in-memory", "--auth-tokens", str(tokens)]) as svc:
        assert svc.proc is not None
        url = svc.base_url
        r = httpx.post(f"{url}/maps/m/scans", params={"robot_id": "r"}, json=SCAN, headers=bearer(ADMIN))
        assert r.status_code == 200, r.text
        snapshot = httpx.get(f"{url}/maps/m/snapshot", headers=bearer(ADMIN)).content
        revoked = threading.Event()

        def body() -> Iterator[bytes]:
            yield snapshot[: len(snapshot) // 2]
            assert revoked.wait(30)
            yield snapshot[len(snapshot) // 2 :]

        answer: list[httpx.Response] = []
        headers = {**bearer(WRITE), "Content-Type": "application/zip"}
        upload = threading.Thread(
            target=lambda: answer.append(
                httpx.put(f"{url}/maps/copy/snapshot", content=body(), headers=headers, timeout=30)
            )
        )
        upload.start()
        wait_for(lambda: metric(svc, "fleetmap_uploads") == 1, 10, what="the upload under way")
        write_tokens(tokens, f"admin {ADMIN}")  # the write token revoked
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
        revoked.set()
        upload.join(30)
        assert answer and answer[0].status_code == 401, answer
        assert "revoked" in answer[0].json()["detail"] and "nothing changed" in answer[0].json()["detail"]
        assert answer[0].headers["www-authenticate"] == 'Bearer realm="fleetmap"'
        assert httpx.get(f"{url}/maps/copy", headers=bearer(ADMIN)).status_code == 404
        # The same upload with a token still in force is installed.
        r = httpx.put(f"{url}/maps/copy/snapshot", content=snapshot, headers={**headers, **bearer(ADMIN)})
        assert r.status_code == 201, r.text


def test_a_scan_or_map_whose_token_is_revoked_while_its_body_arrives_changes_nothing(
    tmp_path: Path,
) -> None:
    """A request's body may follow its head by up to a minute (`--http-body-timeout`), and its token
    be revoked meanwhile: the scan was integrated all the same (its map made), and `PUT /maps/{id}`
    made the map, by a token no longer let in. Both are now a 401 saying so, nothing changed."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"write {WRITE}", f"admin {ADMIN}")
    with ServiceProcess(tmp_path, ["--in-memory", "--auth-tokens", str(tokens)]) as svc:
        assert svc.proc is not None
        url = svc.base_url
        revoked = threading.Event()

        def body(whole: bytes) -> Iterator[bytes]:
            yield whole[:10]
            assert revoked.wait(30)
            yield whole[10:]

        answers: dict[str, httpx.Response] = {}
        scan = json.dumps(SCAN).encode()
        config = json.dumps({"resolution": 0.1}).encode()
        json_headers = {**bearer(WRITE), "Content-Type": "application/json"}
        requests = [
            threading.Thread(
                target=lambda: answers.setdefault(
                    "scan",
                    httpx.post(
                        f"{url}/maps/s/scans?robot_id=r", content=body(scan), headers=json_headers, timeout=30
                    ),
                )
            ),
            threading.Thread(
                target=lambda: answers.setdefault(
                    "map", httpx.put(f"{url}/maps/p", content=body(config), headers=json_headers, timeout=30)
                )
            ),
        ]
        for request in requests:
            request.start()
        wait_for(lambda: metric(svc, "fleetmap_http_connections") >= 3, 10, what="both requests under way")
        write_tokens(tokens, f"admin {ADMIN}")  # the write token revoked
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
        revoked.set()
        for request in requests:
            request.join(30)
        for name in ("scan", "map"):
            answer = answers[name]
            assert answer.status_code == 401, (name, answer.text)
            assert "revoked" in answer.json()["detail"] and "nothing changed" in answer.json()["detail"]
            assert answer.headers["www-authenticate"] == 'Bearer realm="fleetmap"'
        assert httpx.get(f"{url}/maps", headers=bearer(ADMIN)).json()["maps"] == []


class StreamReader:
    """An event stream read on a thread: its lines as they come, and whether the server ended it."""

    def __init__(self, url: str, headers: dict[str, str]) -> None:
        self.lines: list[str] = []
        self.status: int | None = None
        self.ended = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(url, headers), daemon=True)
        self._thread.start()

    def _read(self, url: str, headers: dict[str, str]) -> None:
        try:
            with httpx.stream("GET", url, headers=headers, timeout=httpx.Timeout(10, read=None)) as r:
                self.status = r.status_code
                for line in r.iter_lines():
                    self.lines.append(line)
        except httpx.HTTPError as exc:
            self.lines.append(f"(client: {exc!r})")
        finally:
            self.ended.set()

    def saw(self, text: str) -> bool:
        return any(text in line for line in self.lines)


def test_revoking_a_token_ends_its_event_streams(tmp_path: Path) -> None:
    """An event stream lasts hours: one opened with a token, or with a session cookie standing for
    it, ends within a poll once the token is revoked (token file and SIGHUP), saying why; before, it
    went on streaming the map to a client that could no longer open it. Streams of a token that
    stays valid go on (and get the next change)."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    with ServiceProcess(
        tmp_path, ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]
    ) as svc:
        assert svc.proc is not None
        url = svc.base_url
        assert httpx.put(f"{url}/maps/m", json={}, headers=bearer(WRITE)).status_code == 201
        events = f"{url}/maps/m/events"
        read_session = cookie(set_cookie(httpx.post(f"{url}/session", headers=bearer(READ)))[0])
        write_session = cookie(set_cookie(httpx.post(f"{url}/session", headers=bearer(WRITE)))[0])
        revoked = [StreamReader(events, bearer(READ)), StreamReader(events, read_session)]
        kept = [StreamReader(events, bearer(WRITE)), StreamReader(events, write_session)]
        streams = revoked + kept
        # Every stream is open: each got its first robots event.
        wait_for(lambda: all(s.saw("event: robots") for s in streams), 10, what="every stream open")
        assert [s.status for s in streams] == [200] * 4

        write_tokens(tokens, f"write {WRITE}")  # the read token revoked
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
        for stream in revoked:
            assert stream.ended.wait(5), f"a revoked token's stream still runs: {stream.lines}"
            assert stream.lines[-2:] == [": the token of this stream was revoked", ""], stream.lines
        # The others go on, and stream the next change.
        assert not any(s.ended.is_set() for s in kept), [s.lines for s in kept]
        r = httpx.post(f"{url}/maps/m/scans", params={"robot_id": "r"}, json=SCAN, headers=bearer(WRITE))
        assert r.status_code == 200, r.text
        wait_for(
            lambda: all(s.saw("event: tiles") for s in kept), 10, what="the scan's tiles on kept streams"
        )
        assert not any(s.ended.is_set() for s in kept), [s.lines for s in kept]
        assert not any(s.saw("revoked") for s in kept)
    for stream in kept:  # the service stopped: they end as every stream does then
        assert stream.ended.wait(10) and stream.saw(": the server is shutting down"), stream.lines


def test_failed_sign_ins_are_limited_per_client_address(tmp_path: Path) -> None:
    """After --max-failed-sign-ins failures from one address within --failed-sign-in-window, every
    sign-in from it is a 429 with Retry-After, a right token's too (else 200 against 429 would say
    which guess was right), until the window has passed. Successful sign-ins never count. Other
    addresses (uvicorn believes loopback's X-Forwarded-For, as a proxy's) keep their own count, an
    IPv6 client by its /64. Before, a client could try tokens as fast as it could send them."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}")
    args = ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token",
            "--max-failed-sign-ins", "3", "--failed-sign-in-window", "3"]  # fmt: skip
    with ServiceProcess(tmp_path, args) as svc, httpx.Client(base_url=svc.base_url) as client:

        def sign_in(token: str | None, address: str = "10.0.0.1") -> httpx.Response:
            headers = {"X-Forwarded-For": address, **(bearer(token) if token else {})}
            return client.post("/session", headers=headers)

        assert [sign_in(UNKNOWN).status_code for _ in range(2)] == [401, 401]
        # Right tokens in between are not penalised: they neither count nor get refused.
        assert [sign_in(READ).status_code for _ in range(5)] == [200] * 5
        assert sign_in(None).status_code == 401  # the third failure (no token is a failure too)
        started = time.monotonic()
        for token in (UNKNOWN, READ):  # refused without looking at the token
            r = sign_in(token)
            assert r.status_code == 429 and "set-cookie" not in r.headers, r.text
            assert 1 <= int(r.headers["retry-after"]) <= 3, r.headers
            assert list(r.json()) == ["detail"] and r.json()["detail"].startswith(
                "too many failed sign-ins from this address (3 within 3 s): try again in "
            ), r.text
            assert r.headers["content-type"] == "application/json"
        # Only signing in is refused: the address's reads with a token go on.
        r = client.get("/maps", headers={"X-Forwarded-For": "10.0.0.1", **bearer(READ)})
        assert r.status_code == 200
        # Other addresses have their own count; an IPv6 host counts by its /64.
        assert sign_in(UNKNOWN, "10.0.0.2").status_code == 401
        assert [sign_in(UNKNOWN, "2001:db8::1").status_code for _ in range(3)] == [401] * 3
        assert sign_in(READ, "2001:db8::2:5").status_code == 429  # same /64
        assert sign_in(READ, "2001:db8:0:1::1").status_code == 200  # another /64
        # Once the window has passed, the address starts again.
        time.sleep(max(0.0, started + 3.2 - time.monotonic()))
        assert sign_in(UNKNOWN).status_code == 401
        assert sign_in(READ).status_code == 200


def test_sign_ins_whose_refusals_wait_on_their_client_are_counted_at_once() -> None:
    """A failed sign-in counts as its 401 starts, not once the client has taken it: sending waits
    while a client reads nothing (its connection's write buffer full, as behind a large answer it
    asked for first on that connection), and the sign-ins that arrived meanwhile passed the check.
    On the real service 25 connections, each asking for a 5 MB region (reads are open by default)
    and then signing in, had 25 guesses answered 401 under a limit of 10. Driven here through the
    app and all its middleware, with a client that holds its first answer back."""
    settings = ApiSettings(tokens=TokenSet.parse(f"read {READ}"), signin_max_failures=1)
    app = create_app(MapRegistry(), settings=settings)

    async def sign_in(token: str, started: asyncio.Event, taken: asyncio.Event) -> int:
        """POST /session with `token` from one address; its answer waits for `taken` once it started
        (`started` set then). Returns its status."""
        headers = [(b"host", b"localhost"), (b"authorization", f"Bearer {token}".encode())]
        scope = {
            "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
            "scheme": "http", "path": "/session", "raw_path": b"/session", "query_string": b"",
            "root_path": "", "headers": headers, "client": ("10.0.0.1", 40000),
            "server": ("127.0.0.1", 8000),
        }  # fmt: skip
        status = 0

        async def receive() -> dict[str, Any]:
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message: dict[str, Any]) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                started.set()
                await taken.wait()

        await app(scope, receive, send)
        return status

    async def guesses() -> list[int]:
        waiting, taken = asyncio.Event(), asyncio.Event()
        first = asyncio.create_task(sign_in(UNKNOWN, waiting, taken))
        await asyncio.wait_for(waiting.wait(), 30)  # its 401 has started; the client reads nothing
        read_at_once = asyncio.Event()
        read_at_once.set()
        # Another guess meanwhile, and a right token (refused too while the address is: docs).
        later = [await sign_in(token, asyncio.Event(), read_at_once) for token in (UNKNOWN + "-2", READ)]
        taken.set()
        return [await first, *later]

    assert asyncio.run(guesses()) == [401, 429, 429]


def test_signing_in_where_reads_are_open(tmp_path: Path) -> None:
    """Without --require-read-token signing in still needs a valid token (the cookie then unlocks
    nothing that is not open), and answers stay shareable by caches as before."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}")
    with ServiceProcess(tmp_path, ["--in-memory", "--auth-tokens", str(tokens)]) as svc:
        url = svc.base_url
        assert httpx.post(f"{url}/session").status_code == 401
        assert httpx.post(f"{url}/session", headers=bearer(UNKNOWN)).status_code == 401
        r = httpx.post(f"{url}/session", headers=bearer(READ))
        assert r.status_code == 200 and set_cookie(r)[0] == session_of(READ)
        assert httpx.get(f"{url}/maps").headers["cache-control"] == "no-cache"


def test_without_tokens_there_is_nothing_to_sign_in_to(tmp_path: Path) -> None:
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        r = httpx.post(f"{svc.base_url}/session", headers=bearer(READ))
        assert r.status_code == 404 and "set-cookie" not in r.headers
        assert "without API tokens" in r.json()["detail"] and "nothing to sign in to" in r.json()["detail"]
        assert httpx.delete(f"{svc.base_url}/session").status_code == 204  # signing out is harmless


def test_healthz_tells_no_map_ids_or_files_to_a_client_that_may_not_read(tmp_path: Path) -> None:
    """`/healthz` is open to liveness probes, and lists the maps storage failed for and the failure's
    text, which names them and the data directory's files: with reads needing a token, a client
    without one read there the map ids `GET /maps` refused it. It is told that storage failed, when,
    and how many scans are not durable; a reader, by token or session cookie, is told all of it."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}", f"write {WRITE}")
    data = tmp_path / "data"
    args = ["--data-dir", str(data), "--auth-tokens", str(tokens), "--require-read-token"]
    with ServiceProcess(tmp_path, args) as svc:
        url = svc.base_url

        def scan(seq: int) -> int:
            body = {**SCAN, "seq": seq}
            params = {"robot_id": "r"}
            return httpx.post(
                f"{url}/maps/site-7/scans", params=params, json=body, headers=bearer(WRITE)
            ).status_code

        assert scan(1) == 200
        shutil.rmtree(data)  # storage fails from here on (see test_durability.py)
        assert scan(2) == 503
        assert httpx.get(f"{url}/maps").status_code == 401

        anyone = httpx.get(f"{url}/healthz")
        assert anyone.status_code == 200 and anyone.json()["status"] == "degraded"
        storage = anyone.json()["storage"]
        assert storage["ok"] is False and storage["scans_not_durable"] == 1 and storage["last_error_at"]
        assert storage["maps_awaiting_snapshot"] == [] and storage["map_changes_not_stored"] == []
        assert storage["last_error"].startswith("storage failed (what failed, and the maps it concerns")
        assert "site-7" not in anyone.text and str(data) not in anyone.text, anyone.text
        # An unknown token, or a cookie of none, is anyone.
        for headers in (bearer("not-a-token-at-all-xx"), cookie(session_of("not-a-token-at-all-xx"))):
            assert httpx.get(f"{url}/healthz", headers=headers).json()["storage"] == storage

        for headers in (bearer(READ), cookie(session_of(READ))):
            told = httpx.get(f"{url}/healthz", headers=headers).json()["storage"]
            assert told["maps_awaiting_snapshot"] == ["site-7"], told
            assert str(data) in told["last_error"] and "deleted or replaced" in told["last_error"]


def test_healthz_names_no_ros_map_or_topic_to_a_client_that_may_not_read(tmp_path: Path) -> None:
    """With the ROS side on (`--ros-scans`, `--ros-publish-map`), `/healthz`'s `zenoh` held the ROS
    ingest's and publisher's status: the map each builds or publishes, its topics and keys, the
    robots' namespaces. With reads needing a token, a client without one read there the map ids
    `GET /maps` refused it. It is told the session's own status; a reader is told the ROS parts too."""
    tokens = write_tokens(tmp_path / "tokens.txt", f"read {READ}")
    args = ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]
    args += ["--ros-scans", "site-7", "--ros-publish-map", "site-7=/site_7_grid"]
    with ServiceProcess(tmp_path, args) as svc:
        anyone = httpx.get(f"{svc.base_url}/healthz")
        assert anyone.status_code == 200 and anyone.json()["zenoh"]["running"] is True
        assert "site-7" not in anyone.text and "site_7" not in anyone.text, anyone.text
        assert "ros" not in anyone.json()["zenoh"] and "ros_maps" not in anyone.json()["zenoh"]
        for headers in (bearer(READ), cookie(session_of(READ))):
            told = httpx.get(f"{svc.base_url}/healthz", headers=headers).json()["zenoh"]
            assert told["ros"]["map_id"] == "site-7", told
            assert told["ros_maps"]["topics"]["/site_7_grid"]["map_id"] == "site-7", told
