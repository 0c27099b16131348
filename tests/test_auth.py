"""API tokens on the real service: roles, 401 / 403 with clear messages, open or protected reads,
loopback-only without tokens, and tokens never written to the logs."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fleetmap_client.zenoh_config import client_config
from service_process import ServiceProcess, free_port

from fleetmap.auth import TokenFileError, TokenSet, required_role
from fleetmap.registry import MapRegistry
from fleetmap.zenoh_ingest import IngestStartError, ZenohIngest

READ, WRITE, ADMIN = "read-token-0123456789", "write-token-0123456789", "admin-token-0123456789"
SCAN = {"seq": 0, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": -0.5, "angle_increment": 0.1,
        "range_max": 10.0, "ranges": [2.0] * 11}  # fmt: skip


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    path = tmp_path / "tokens.txt"
    path.write_text(f"# roles\nread {READ}\nwrite {WRITE}\nadmin {ADMIN}  # the operator\n")
    return path


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_roles_on_the_real_service(tmp_path: Path, token_file: Path) -> None:
    token_file.chmod(0o644)  # as written with the usual umask 022
    with ServiceProcess(tmp_path, ["--auth-tokens", str(token_file)]) as svc:
        url = svc.base_url
        # Anyone who can read the file holds its tokens: the start-up log says so, and what to do.
        warning = (
            f"WARNING fleetmap.server: the token file {token_file} is readable by every user of this "
            "machine (mode 0644): they can use its tokens; make it readable by the service's user "
            f"only (chmod 600 {token_file})"
        )
        assert warning in svc.logs()
        # Writing needs write or admin.
        r = httpx.put(f"{url}/maps/m", json={})
        assert r.status_code == 401 and "Bearer" in r.json()["detail"]
        assert r.headers["www-authenticate"].startswith("Bearer")
        r = httpx.put(f"{url}/maps/m", json={}, headers=bearer("not-a-token-at-all-xx"))
        assert r.status_code == 401 and r.json()["detail"] == "unknown token"
        r = httpx.put(f"{url}/maps/m", json={}, headers=bearer(READ))
        assert r.status_code == 403 and "'write'" in r.json()["detail"]
        assert httpx.get(f"{url}/maps/m").status_code == 404  # nothing was created
        assert httpx.put(f"{url}/maps/m", json={}, headers=bearer(WRITE)).status_code == 201
        r = httpx.post(f"{url}/maps/m/scans", params={"robot_id": "r"}, json=SCAN, headers=bearer(READ))
        assert r.status_code == 403
        r = httpx.post(f"{url}/maps/m/scans", params={"robot_id": "r"}, json=SCAN, headers=bearer(ADMIN))
        assert r.status_code == 200
        # Reading is open by default, including the read-only POST /cells.
        assert httpx.get(f"{url}/maps/m").status_code == 200
        assert httpx.post(f"{url}/maps/m/cells", json={"points": [[2.0, 0.0]]}).status_code == 200
        ray = {"origin": [0.0, 0.0], "angles": [0.0], "max_range": 5.0}
        assert httpx.post(f"{url}/maps/m/raycast", json=ray).status_code == 200
        assert httpx.delete(f"{url}/maps/m", headers=bearer(READ)).status_code == 403
        assert httpx.delete(f"{url}/maps/m", headers=bearer(ADMIN)).status_code == 204
        assert httpx.get(f"{url}/healthz").status_code == 200
        # With tokens, a request may name any host (a reverse proxy passes its own on).
        assert httpx.get(f"{url}/maps", headers={"Host": "fleetmap.example"}).status_code == 200
        logs = svc.logs()
    for token in (READ, WRITE, ADMIN, "not-a-token-at-all-xx"):
        assert token not in logs


@pytest.fixture(scope="module")
def reads_need_a_token(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One service of the read, write and admin tokens that requires a token to read, for the
    module's tests that only ask it (none changes its tokens or stops it, and none makes a map)."""
    tmp = tmp_path_factory.mktemp("reads-need-a-token")
    tokens = tmp / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\nadmin {ADMIN}\n")
    with ServiceProcess(tmp, ["--auth-tokens", str(tokens), "--require-read-token"]) as svc:
        yield svc


def test_reads_can_require_a_token(reads_need_a_token: ServiceProcess) -> None:
    svc = reads_need_a_token
    assert httpx.get(f"{svc.base_url}/maps").status_code == 401
    assert httpx.get(f"{svc.base_url}/maps", headers=bearer(READ)).status_code == 200
    assert httpx.post(f"{svc.base_url}/maps/x/cells", json={"points": []}).status_code == 401
    ray = {"origin": [0.0, 0.0], "angles": [0.0], "max_range": 5.0}
    assert httpx.post(f"{svc.base_url}/maps/x/raycast", json=ray).status_code == 401
    r = httpx.post(f"{svc.base_url}/maps/x/raycast", json=ray, headers=bearer(READ))
    assert r.status_code == 404 and r.json()["detail"] == "no map 'x'"  # a read token gets through
    assert httpx.get(f"{svc.base_url}/healthz").status_code == 200  # probes carry no token


def test_tokens_from_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLEETMAP_TOKENS", f"write {WRITE}; read {READ}")
    with ServiceProcess(tmp_path) as svc:
        assert httpx.put(f"{svc.base_url}/maps/e", json={}).status_code == 401
        assert httpx.put(f"{svc.base_url}/maps/e", json={}, headers=bearer(WRITE)).status_code == 201


def serve(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetmap.server", "--in-memory", *args],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip


def test_an_empty_token_variable_is_refused_not_taken_for_none(monkeypatch: pytest.MonkeyPatch) -> None:
    """`FLEETMAP_TOKENS=` (a template's unset variable: `FLEETMAP_TOKENS=${API_TOKENS}`) was taken
    for no tokens at all: on loopback, behind a reverse proxy on the same machine (which names its
    upstream `127.0.0.1` in `Host`, as nginx does by default), the service served everyone without
    a token, and only the start-up log's `API tokens: NONE` told. It stops at start instead, as an
    empty $FLEETMAP_AUTH_TOKENS does."""
    for empty in ("", "  "):
        monkeypatch.setenv("FLEETMAP_TOKENS", empty)
        out = serve("--http", f"127.0.0.1:{free_port()}", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}")
        assert out.returncode == 2, out.stderr
        assert "$FLEETMAP_TOKENS is set but holds no tokens" in out.stderr, out.stderr


def test_no_tokens_means_loopback_only(tmp_path: Path) -> None:
    out = serve("--http", f"0.0.0.0:{free_port()}", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}")
    assert out.returncode == 2
    assert "without API tokens" in out.stderr and "--insecure" in out.stderr


def test_insecure_allows_all_interfaces() -> None:
    """With --insecure the service binds 0.0.0.0 without tokens; reached here through loopback only."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetmap.server", "--in-memory", "--insecure", "--http", f"0.0.0.0:{port}",
         "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if "fleetmap serving" in line:
                break
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5).status_code == 200
        # --insecure accepts requests for any host, as it accepts any address.
        r = httpx.get(f"http://127.0.0.1:{port}/maps", headers={"Host": "fleetmap.example"}, timeout=5)
        assert r.status_code == 200, r.text
    finally:
        proc.terminate()
        proc.wait(30)


def test_token_files_are_checked_without_echoing_tokens(tmp_path: Path) -> None:
    with pytest.raises(TokenFileError, match="tokens.txt:2") as bad:
        TokenSet.parse("read aaaaaaaaaaaaaaaaaaaa\nsuper bbbbbbbbbbbbbbbbbbbbb\n", "tokens.txt")
    assert "bbbb" not in str(bad.value)
    with pytest.raises(TokenFileError, match="at least 16"):
        TokenSet.parse("write short\n")
    # A token listed again with another role (a demotion that left the old line behind?) is
    # refused, naming both lines; listed again with the same role, it is harmless.
    with pytest.raises(
        TokenFileError, match=r"tokens.txt:3: this token is already listed on line 1 with the role 'admin'"
    ) as bad:
        TokenSet.parse(f"admin {READ}\nwrite {'c' * 20}\nread {READ}\n", "tokens.txt")
    assert READ not in str(bad.value)
    tokens = TokenSet.parse(f"read {READ}\nread {READ}\n")
    assert tokens.role_of(READ) == "read" and len(tokens.digests) == 1
    assert tokens.role_of(READ + "x") is None
    assert required_role("OPTIONS", "/maps", True) is None
    assert required_role("POST", "/maps/a/cells", False) is None
    assert required_role("POST", "/maps/a/raycast", False) is None
    assert required_role("POST", "/maps/a/raycast", True) == "read"
    assert required_role("POST", "/maps/a/raycast/x", False) == "write"
    assert required_role("POST", "/maps/a/scans", False) == "write"
    out = serve("--auth-tokens", str(tmp_path / "missing.txt"))
    assert out.returncode == 2 and "cannot read token file" in out.stderr


def test_tokens_given_where_the_token_file_goes_are_not_echoed() -> None:
    """`--auth-tokens` (`$FLEETMAP_AUTH_TOKENS`) takes a file's path, and a value that holds the
    tokens themselves (`write <token>`, as $FLEETMAP_TOKENS would) was quoted whole as the file that
    could not be read: the token written to the log, journald's or the container's. Such a value is
    now named as tokens and not quoted; a path is still quoted."""
    for value in (f"write {WRITE}", f"  admin\t{ADMIN}; read {READ}", f"read {READ}\n"):
        with pytest.raises(TokenFileError) as refused:
            TokenSet.load(value)
        message = str(refused.value)
        assert "ROLE TOKEN" in message and "$FLEETMAP_TOKENS" in message, message
        for secret in (READ, WRITE, ADMIN):
            assert secret not in message
    with pytest.raises(TokenFileError, match="cannot read token file /nowhere/writers.txt: No such file"):
        TokenSet.load("/nowhere/writers.txt")


def test_a_zenoh_configuration_it_cannot_read_is_reported_without_its_values(tmp_path: Path) -> None:
    """A Zenoh configuration file may hold a robot's password (`transport/auth/usrpwd`) or a private
    key inline (`*_base64`), and its errors go to the log (`fleetmap serve`) or to the robot's
    error (`ScanPublisher`, `fleetmap replay`): Zenoh's error quoted the file's line at fault, the
    password in it (an unquoted value, a quote left open), or the value of the wrong type (a
    password written as a number). They now say where the fault is and what was expected, as Zenoh
    did, but quote nothing of the file."""
    password = "correct-horse-battery-staple"
    faults = {
        "unquoted": f"password: {password},",  # a syntax error: Zenoh printed the line
        "open quote": f'password: "{password},',
        "a number": "password: 424242424242,",  # the wrong type: Zenoh printed the value
        "a boolean": "password: true,",
    }
    expected = {
        "unquoted": "line 5, column 15: expected array, boolean, null, number, object, or string",
        "a number": "invalid type: integer, expected a string",
        "a boolean": "invalid type: boolean, expected a string",
    }
    for fault, line in faults.items():
        config = tmp_path / f"{fault}.json5"
        config.write_text(
            "{\n  mode: 'router',\n  transport: { auth: { usrpwd: {\n"
            f"    user: 'robot-7',\n    {line}\n  }} }} }},\n}}\n"
        )
        secret = line.removeprefix("password: ").strip('",')
        out = serve("--zenoh-config", str(config), "--http", f"127.0.0.1:{free_port()}")
        assert out.returncode == 2, (fault, out.stderr)
        assert f"cannot load Zenoh config {config}: " in out.stderr, (fault, out.stderr)
        assert secret not in out.stderr, (fault, out.stderr)
        assert expected.get(fault, "line 5, column ") in out.stderr, (fault, out.stderr)
        with pytest.raises(ValueError, match="cannot read Zenoh configuration") as robot:
            client_config(zenoh_config=config)
        assert secret not in str(robot.value) and expected.get(fault, "line 5") in str(robot.value)


def test_a_zenoh_configuration_given_where_its_file_goes_is_not_echoed() -> None:
    """`--zenoh-config` (`$FLEETMAP_ZENOH_CONFIG`) and a robot's `zenoh_config=` take a file's path,
    and a configuration given inline instead (as a container's environment tends to be filled) was
    quoted whole as the file that could not be read, the robot's password in it. It is now named as
    a configuration and not quoted; a path still is."""
    password = "correct-horse-battery-staple"
    inline = f'{{transport: {{auth: {{usrpwd: {{user: "svc", password: "{password}"}}}}}}}}'
    for given in (inline, f"\n  {inline}\n", "mode: 'router'\ntransport: {}"):
        with pytest.raises(IngestStartError) as service:
            ZenohIngest(MapRegistry(), config_file=given).build_config()
        with pytest.raises(ValueError) as robot:
            client_config(zenoh_config=given)
        for refusal in (str(service.value), str(robot.value)):
            assert "not shown" in refusal and password not in refusal and "mode:" not in refusal, refusal
    with pytest.raises(IngestStartError, match="cannot load Zenoh config /nowhere/service.json5: No such"):
        ZenohIngest(MapRegistry(), config_file="/nowhere/service.json5").build_config()


def test_a_token_holding_a_hash_is_the_whole_token(tmp_path: Path) -> None:
    """`#` starts a comment only at a line's start or after a space: a token with `#` in it was cut
    there, so the configured token was refused and its first half alone let anyone in."""
    token = "0123456789abcdef#ghijklmnopqrstuv"
    path = tmp_path / "tokens.txt"
    path.write_text(f"# the line below holds a '#'\nwrite {token} # and a comment\n")
    with ServiceProcess(tmp_path, ["--auth-tokens", str(path)]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/h", json={}, headers=bearer(token)).status_code == 201
        prefix = token.split("#")[0]
        assert httpx.delete(f"{svc.base_url}/maps/h", headers=bearer(prefix)).status_code == 401


def test_a_token_file_saved_with_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    """Notepad's UTF-8 starts with a byte order mark, and Windows ends lines with CRLF: the mark was
    read as part of the first role, so the file was refused at start with "expected 'ROLE TOKEN'"."""
    path = tmp_path / "tokens.txt"
    path.write_bytes(f"write {WRITE}\r\nread {READ}\r\n".encode("utf-8-sig"))
    with ServiceProcess(tmp_path, ["--auth-tokens", str(path)]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/b", json={}, headers=bearer(WRITE)).status_code == 201
        assert httpx.delete(f"{svc.base_url}/maps/b", headers=bearer(READ)).status_code == 403


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"write \xff\xfe0123456789abcdefgh\n", "tokens.txt:1: not UTF-8 text"),
        (
            "read 0123456789abcdefghij\nwrite caf\u00e9-0123456789abcdef\n".encode(),
            "tokens.txt:2: tokens may hold only printable ASCII",
        ),
    ],
)  # fmt: skip
def test_token_files_no_client_could_use_are_refused_in_one_line(
    tmp_path: Path, content: bytes, message: str
) -> None:
    path = tmp_path / "tokens.txt"
    path.write_bytes(content)
    out = serve("--auth-tokens", str(path), "--http", f"127.0.0.1:{free_port()}")
    assert out.returncode == 2, out.stderr
    assert f"fleetmap serve: error: {path.parent}/{message}" in out.stderr
    assert "Traceback" not in out.stderr and "0123456789abcdef" not in out.stderr


def test_the_spec_declares_the_tokens_and_refusals_of_every_operation(
    reads_need_a_token: ServiceProcess,
) -> None:
    """Each operation of openapi/openapi.json that a token server guards lists the token's schemes
    (optional: a server without tokens needs none) and the 401 / 403 the real service answers it
    with. The schemes were declared in the components only, applied to no operation: Swagger UI's
    Authorize sent the token with no request (every write tried from /docs was a 401), and a
    client checking answers against the spec found the 401 and 403 undocumented (signing in's 401
    without the `WWW-Authenticate` it carries)."""
    spec = json.loads((Path(__file__).resolve().parents[1] / "openapi" / "openapi.json").read_text())
    with httpx.Client(base_url=reads_need_a_token.base_url) as client:
        for path, operations in spec["paths"].items():
            url = path.format(map_id="m", z=0, x=0, y=0)
            for method, operation in operations.items():
                where = f"{method.upper()} {path}"
                schemes = [name for scheme in operation.get("security", []) for name in scheme]
                r = client.request(method, url)
                if r.status_code != 401:  # open to anyone
                    assert path in ("/healthz", "/session"), (where, r.status_code)
                    continue
                assert "401" in operation["responses"] and "bearerToken" in schemes, where
                # The challenge of RFC 9110 (11.6.1) that every 401 carries, declared where it is.
                assert r.headers["www-authenticate"] == 'Bearer realm="fleetmap"', where
                assert "WWW-Authenticate" in operation["responses"]["401"].get("headers", {}), where
                if path == "/session":  # signing in: a token of any role, never a cookie
                    continue
                assert {} in operation["security"], where  # a tokenless server needs none
                r = client.request(method, url, headers=bearer(READ))
                if r.status_code == 403:
                    assert "403" in operation["responses"], where
                else:  # a read: a browser's session cookie may stand for the token
                    assert "sessionCookie" in schemes, where


PAGE = "https://viewer.example"  # an origin allowed by --cors-origin
STRANGER = "https://elsewhere.example"


def test_cors_is_off_by_default(tmp_path: Path) -> None:
    with ServiceProcess(tmp_path) as svc:
        r = httpx.get(f"{svc.base_url}/maps", headers={"Origin": PAGE})
        assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
        r = httpx.options(
            f"{svc.base_url}/maps/m",
            headers={"Origin": PAGE, "Access-Control-Request-Method": "PUT"},
        )
        assert "access-control-allow-origin" not in r.headers


def test_cors_allows_exactly_the_configured_origins_and_covers_auth_errors(
    tmp_path: Path, token_file: Path
) -> None:
    """A page on an allowed origin may call the API, sees its own errors (a 401 or 403 without CORS
    headers is an opaque network error to the page: the auth middleware answered outside CORS), and
    reads the exposed headers; no other origin is let in or reflected."""
    args = ["--auth-tokens", str(token_file), "--cors-origin", PAGE]
    with ServiceProcess(tmp_path, args) as svc:
        url = svc.base_url
        preflight = {
            "Origin": PAGE,
            "Access-Control-Request-Method": "PUT",
            "Access-Control-Request-Headers": "authorization, content-type",
        }
        r = httpx.options(f"{url}/maps/m", headers=preflight)
        assert r.status_code == 200, r.text
        assert r.headers["access-control-allow-origin"] == PAGE
        assert "PUT" in r.headers["access-control-allow-methods"]
        assert "authorization" in r.headers["access-control-allow-headers"].lower()
        r = httpx.options(f"{url}/maps/m", headers={**preflight, "Origin": STRANGER})
        assert r.status_code == 400 and "access-control-allow-origin" not in r.headers

        # The page's own errors carry the CORS headers, so it can read their detail.
        r = httpx.put(f"{url}/maps/m", json={}, headers={"Origin": PAGE})
        assert r.status_code == 401 and r.headers.get("access-control-allow-origin") == PAGE, r.headers
        r = httpx.put(f"{url}/maps/m", json={}, headers={"Origin": PAGE, **bearer(READ)})
        assert r.status_code == 403 and r.headers.get("access-control-allow-origin") == PAGE
        r = httpx.put(f"{url}/maps/m", json={}, headers={"Origin": PAGE, **bearer(WRITE)})
        assert r.status_code == 201 and r.headers["access-control-allow-origin"] == PAGE
        r = httpx.get(f"{url}/maps/m/tiles/0/0/0.png", headers={"Origin": PAGE})
        assert "etag" in r.headers["access-control-expose-headers"].lower()
        # HEAD works wherever GET does, from a page too: with a token (not a simple request's
        # header) it is preflighted, and the preflight refused it ('HEAD' is not allowed), so the
        # page's HEAD failed as a network error.
        head = {**preflight, "Access-Control-Request-Method": "HEAD"}
        r = httpx.options(f"{url}/maps/m/tiles/0/0/0.png", headers=head)
        assert r.status_code == 200 and "HEAD" in r.headers["access-control-allow-methods"], r.text
        r = httpx.head(f"{url}/maps/m/tiles/0/0/0.png", headers={"Origin": PAGE, **bearer(READ)})
        assert r.status_code == 200 and r.headers["access-control-allow-origin"] == PAGE

        # Another origin gets no CORS header on any answer, success or error.
        for r in (
            httpx.get(f"{url}/maps/m", headers={"Origin": STRANGER}),
            httpx.put(f"{url}/maps/m", json={}, headers={"Origin": STRANGER}),
        ):
            assert "access-control-allow-origin" not in r.headers


def test_cors_origins_no_browser_sends_are_refused_at_start(tmp_path: Path) -> None:
    """The CORS middleware compares a request's `Origin` with each `--cors-origin` as it is: a value no
    browser sends (with the trailing slash an address bar shows, without its scheme, in capitals, with
    the default port) let no page in, and the service started without a word."""
    cases = [
        ("https://viewer.example/", "(an origin has nothing after its host and port, not even a '/')"),
        ("viewer.example", "(an origin starts with its scheme: https://...)"),
        ("https://Viewer.example", "(browsers send it in lower case)"),
        ("https://viewer.example:443", "(browsers leave the default port 443 of https out)"),
        # Any site can make a page whose origin is `null` (a sandboxed frame): it would let all in.
        ("null", "(the origin of sandboxed frames, data: pages and local files, which any site can make"),
    ]
    for origin, hint in cases:
        done = subprocess.run(
            [sys.executable, "-m", "fleetmap.server", "--in-memory", "--cors-origin", PAGE, origin],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 2 and f"got {origin!r} {hint}" in done.stderr, (origin, done.stderr)
    # As browsers send them: a port that is not the default, an IPv6 address in brackets.
    with ServiceProcess(
        tmp_path, ["--cors-origin", "http://localhost:5173", "http://[::1]:8080", PAGE]
    ) as svc:
        for origin in ("http://localhost:5173", "http://[::1]:8080", PAGE):
            r = httpx.get(f"{svc.base_url}/healthz", headers={"Origin": origin})
            assert r.headers.get("access-control-allow-origin") == origin, origin


@pytest.fixture(scope="module")
def cors_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """A service without tokens (the default) that lets the page `PAGE` call it (`--cors-origin`)."""
    with ServiceProcess(tmp_path_factory.mktemp("cors"), ["--cors-origin", PAGE]) as svc:
        yield svc


def test_a_refused_cors_preflight_is_a_json_error_naming_what_was_refused(
    cors_service: ServiceProcess,
) -> None:
    """docs/api.md: every error answer is JSON with a `detail`. A preflight the CORS settings refuse
    was Starlette's plain text `Disallowed CORS origin`, the one error a client could not parse."""
    url = f"{cors_service.base_url}/maps/m"
    r = httpx.options(url, headers={"Origin": STRANGER, "Access-Control-Request-Method": "PUT"})
    assert r.status_code == 400 and r.headers["content-type"] == "application/json", r.text
    assert STRANGER in r.json()["detail"] and "--cors-origin" in r.json()["detail"]
    assert "access-control-allow-origin" not in r.headers and "Origin" in r.headers["vary"]
    r = httpx.options(url, headers={"Origin": PAGE, "Access-Control-Request-Method": "PATCH"})
    assert r.status_code == 400 and r.headers["access-control-allow-origin"] == PAGE
    assert "'PATCH' is not allowed" in r.json()["detail"], r.text
    # An allowed preflight is answered as before.
    r = httpx.options(url, headers={"Origin": PAGE, "Access-Control-Request-Method": "PUT"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == PAGE


def test_a_page_on_another_site_cannot_write_through_its_visitors_browser(
    cors_service: ServiceProcess,
) -> None:
    """Any page may make a browser send a POST without a `Content-Type` anywhere, with no preflight
    (`fetch(url, {method: 'POST', mode: 'no-cors', body: bytes})`); the scans route sniffs such a
    body, so every site a user of a service without tokens visited could create maps on it and
    integrate scans into them. The requests are sent here with the headers such a browser sends
    (Chromium's `Sec-Fetch-*` and `Origin`), not from a browser: which requests a browser sends
    without a preflight is the browser's, what the service does with them is what is tested."""
    url = cors_service.base_url
    body = json.dumps(SCAN).encode()  # no Content-Type: sniffed as JSON

    def scan(map_id: str, headers: dict[str, str]) -> httpx.Response:
        return httpx.post(
            f"{url}/maps/{map_id}/scans", params={"robot_id": "r"}, content=body, headers=headers
        )

    no_cors = {"Sec-Fetch-Mode": "no-cors", "Sec-Fetch-Dest": "empty"}

    def map_ids() -> list[str]:
        return [m["id"] for m in httpx.get(f"{url}/maps").json()["maps"]]

    maps_before = map_ids()  # the module's other tests' maps, if any
    refused = [
        ("cross-site", {**no_cors, "Origin": STRANGER, "Sec-Fetch-Site": "cross-site"}),
        # A sandboxed frame's or a file's page: its origin is `null`.
        ("null origin", {**no_cors, "Origin": "null", "Sec-Fetch-Site": "cross-site"}),
        # Another port of the same host is the same site, not the same origin.
        ("same-site", {**no_cors, "Origin": "http://127.0.0.1:1", "Sec-Fetch-Site": "same-site"}),
        # A browser without `Sec-Fetch-Site`: its `Origin` names another host than the request's.
        ("old browser", {"Origin": STRANGER}),
    ]
    for what, headers in refused:
        r = scan("forged", headers)
        assert r.status_code == 403 and r.headers["content-type"] == "application/json", (what, r.text)
        assert "cross-site request refused" in r.json()["detail"] and "--cors-origin" in r.json()["detail"]
        assert r.headers["x-content-type-options"] == "nosniff", r.headers  # the API's own answer
    r = httpx.delete(f"{url}/maps/forged", headers={"Origin": STRANGER, "Sec-Fetch-Site": "cross-site"})
    assert r.status_code == 403, r.text
    assert httpx.get(f"{url}/maps/forged").status_code == 404  # nothing was created
    assert map_ids() == maps_before

    # Written as before: by a client that is no browser's page, by the service's own pages, by a
    # request the user made, by a page `--cors-origin` allows, by an older browser's same-origin page.
    host = url.removeprefix("http://")
    allowed = [
        ("no browser", {}),
        ("same-origin", {"Origin": url, "Sec-Fetch-Site": "same-origin"}),
        ("the user's own", {"Sec-Fetch-Site": "none"}),
        ("allowed page", {"Origin": PAGE, "Sec-Fetch-Site": "cross-site"}),
        ("old browser, same origin", {"Origin": url, "Host": host}),
    ]
    for i, (what, headers) in enumerate(allowed):
        r = scan(f"ok-{i}", headers)
        assert r.status_code == 200 and r.json()["status"] == "integrated", (what, r.text)
    # Reads are not checked: they change nothing, and CORS keeps their answers from other pages.
    r = httpx.get(f"{url}/maps/ok-0", headers={"Origin": STRANGER, "Sec-Fetch-Site": "cross-site"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers


def test_a_page_rebound_to_loopback_cannot_reach_a_service_without_tokens(
    cors_service: ServiceProcess,
) -> None:
    """DNS rebinding: a page of `http://attacker.example:PORT` whose name the attacker then points at
    127.0.0.1 is the service's own origin to the browser (`Sec-Fetch-Site: same-origin`, no CORS in
    the way), so its script could read, delete and overwrite every map of a service without tokens.
    Its requests name the attacker's host in `Host`: they are refused. Sent here with the headers
    such a browser sends, over loopback as the rebound page's would come."""
    url = cors_service.base_url
    port = url.rpartition(":")[2]
    assert httpx.put(f"{url}/maps/kept", json={}).status_code == 201
    page = f"http://attacker.example:{port}"
    rebound = {"Host": f"attacker.example:{port}", "Origin": page, "Sec-Fetch-Site": "same-origin"}
    for method, path in [("GET", "/maps"), ("GET", "/maps/kept/tiles/0/0/0.png"), ("DELETE", "/maps/kept"),
                         ("PUT", "/maps/kept"), ("GET", "/healthz")]:  # fmt: skip
        r = httpx.request(method, f"{url}{path}", headers=rebound, json={} if method == "PUT" else None)
        assert r.status_code == 403 and r.headers["content-type"] == "application/json", (
            method,
            path,
            r.text,
        )
        assert "'attacker.example:" in r.json()["detail"] and "DNS rebinding" in r.json()["detail"]
        assert r.headers["x-frame-options"] == "DENY"  # the API's own answer
    assert httpx.get(f"{url}/maps/kept").status_code == 200  # still there
    # A name of this machine, as a browser or client sends it, with or without the port.
    for host in (
        f"127.0.0.1:{port}",
        f"localhost:{port}",
        "LocalHost.",
        "127.0.0.2",
        "[::1]:80",
        "localhost",
    ):
        r = httpx.get(f"{url}/maps/kept", headers={"Host": host})
        assert r.status_code == 200, (host, r.text)
    # Not a name of this machine, though it resembles one.
    for host in ("localhost.attacker.example", "127.0.0.1.nip.io", "[::2]:80", "0.0.0.0"):
        assert httpx.get(f"{url}/maps", headers={"Host": host}).status_code == 403, host
