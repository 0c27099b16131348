"""The service behind a reverse proxy: under a path prefix (`fleetmap serve --root-path /fleetmap`,
https://host/fleetmap/ proxied to the service's root, the prefix stripped as nginx's
`location /fleetmap/ { proxy_pass http://svc/; }` does), the real service through a real proxy; and
the proxies it trusts (`--forwarded-allow-ips`)."""

from __future__ import annotations

import http.client
import re
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest
from fleetmap_client import FleetmapClient
from service_process import ServiceProcess

from fleetmap import cli

PREFIX = "/fleetmap"
READ, WRITE = "r" * 32, "w" * 32
#: Headers of one hop, which a proxy does not pass on (RFC 9110, 7.6.1), and those it sets itself.
_HOP = {"connection", "keep-alive", "transfer-encoding", "te", "trailer", "upgrade", "host", "content-length"}


class StrippingProxy(ThreadingHTTPServer):
    """A reverse proxy on a free loopback port passing `PREFIX/...` on to `upstream` as `/...` (and
    nothing else: 404), with `X-Forwarded-Proto: https` as a TLS-terminating proxy adds it. Answers
    are read whole (no event streams)."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        super().__init__(("127.0.0.1", 0), _ProxyHandler)
        self.url = f"http://127.0.0.1:{self.server_address[1]}{PREFIX}"


class _ProxyHandler(BaseHTTPRequestHandler):
    server: StrippingProxy
    protocol_version = "HTTP/1.1"

    def _forward(self) -> None:
        if not (self.path == PREFIX or self.path.startswith(PREFIX + "/")):
            self.send_error(404)
            return
        body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
        headers = {k: v for k, v in self.headers.items() if k.lower() not in _HOP}
        headers |= {"X-Forwarded-Proto": "https", "X-Forwarded-For": "203.0.113.7"}
        upstream = http.client.HTTPConnection("127.0.0.1", self.server.upstream_port, timeout=30)
        try:
            path = self.path[len(PREFIX) :] or "/"
            upstream.request(self.command, path, body=body or None, headers=headers)
            answer = upstream.getresponse()
            content = answer.read()
        finally:
            upstream.close()
        self.send_response(answer.status)
        for name, value in answer.getheaders():
            if name.lower() not in _HOP:
                self.send_header(name, value)
        self.send_header("Content-Length", str(len(content)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(content)

    do_GET = do_HEAD = do_PUT = do_POST = do_DELETE = _forward

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the base class's name
        pass


@pytest.fixture(scope="module")
def proxied(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ServiceProcess, str]]:
    """The service with `--root-path /fleetmap` and tokens, and the proxy's URL (PREFIX included)."""
    tmp = tmp_path_factory.mktemp("root-path")
    tokens = tmp / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    tokens.chmod(0o600)
    with ServiceProcess(tmp, ["--auth-tokens", str(tokens), "--root-path", PREFIX + "/"]) as svc:
        proxy = StrippingProxy(svc.port)
        thread = threading.Thread(target=proxy.serve_forever, daemon=True)
        thread.start()
        try:
            yield svc, proxy.url
        finally:
            proxy.shutdown()
            proxy.server_close()


def test_urls_the_service_names_are_under_the_prefix(proxied: tuple[ServiceProcess, str]) -> None:
    svc, url = proxied
    write = {"Authorization": f"Bearer {WRITE}"}
    with httpx.Client(timeout=30) as http:
        # A made map's Location is under the prefix, and following it (through the proxy) finds it.
        made = http.put(f"{url}/maps/a", json={"resolution": 0.1}, headers=write)
        assert made.status_code == 201, made.text
        assert made.headers["location"] == f"{PREFIX}/maps/a"
        origin = url.removesuffix(PREFIX)
        found = http.get(origin + made.headers["location"], headers=write)
        assert found.status_code == 200 and found.json()["id"] == "a", found.text
        # So is a snapshot upload's, which made map `b`.
        snapshot = http.get(f"{url}/maps/a/snapshot", headers=write)
        assert snapshot.status_code == 200, snapshot.text
        put = http.put(f"{url}/maps/b/snapshot", content=snapshot.content, headers=write)
        assert put.status_code == 201 and put.headers["location"] == f"{PREFIX}/maps/b", put.text

        # The API's pages load the spec from under the prefix, which names it as the API's server.
        for page in ("docs", "redoc"):
            html = http.get(f"{url}/{page}").text
            assert re.findall(r"""['"](/[^'"]*openapi\.json)['"]""", html) == [f"{PREFIX}/openapi.json"], page
        spec = http.get(f"{url}/openapi.json")
        assert spec.status_code == 200 and spec.json()["servers"] == [{"url": PREFIX}]

        # The viewer's files need no token under the prefix either, and carry the viewer's policy.
        for file in ("/", "/static/app.js", "/vendor/leaflet/leaflet.js"):
            got = http.get(url + file)
            assert got.status_code == 200, (file, got.text)
            assert "content-security-policy" in got.headers, file
        assert http.get(f"{url}/maps").status_code == 200  # reads need no token (no --require-read-token)
        assert http.put(f"{url}/maps/c").status_code == 401  # writes do

        # A 404's hint and a 405's Allow are the routes' under the prefix too.
        for path, hint in [("/maps/a/", f"{PREFIX}/maps/a"), ("//", f"{PREFIX}/")]:
            detail = http.get(url + path).json()["detail"]
            assert detail == f"no such resource: {PREFIX}{path} (did you mean {hint}?)", detail
        assert http.post(f"{url}/static/app.js", headers=write).headers["allow"] == "GET, HEAD"
        # A proxy that passes the prefix on (nginx's `proxy_pass http://svc;`, no `/`) is told so.
        kept = http.get(f"{url}{PREFIX}/maps").json()["detail"]
        assert kept.endswith(
            f"(the service was started with --root-path {PREFIX}, for a reverse proxy that "
            "strips that prefix from the requests it passes on; this one still had it)"
        ), kept

        # The session cookie is the prefix's (Secure: the proxy said https), and reads with it.
        signed = http.post(f"{url}/session", headers={"Authorization": f"Bearer {READ}"})
        assert signed.status_code == 200, signed.text
        attributes = {part.strip() for part in signed.headers["set-cookie"].split(";")[1:]}
        assert {f"Path={PREFIX}", "Secure", "HttpOnly"} <= attributes, signed.headers["set-cookie"]
        out = http.delete(f"{url}/session")
        assert f"Path={PREFIX}" in out.headers["set-cookie"], out.headers["set-cookie"]

        # Straight to the service (no proxy) the paths are the routes', and it names them the same.
        direct = http.put(f"{svc.base_url}/maps/d", headers=write)
        assert direct.status_code == 201 and direct.headers["location"] == f"{PREFIX}/maps/d", direct.text
        assert http.get(f"{svc.base_url}/static/app.js").status_code == 200


def test_the_python_client_works_under_the_prefix(proxied: tuple[ServiceProcess, str]) -> None:
    _, url = proxied
    with FleetmapClient(url, token=WRITE) as fm:
        fm.create_map("client", {"resolution": 0.1})
        assert fm.get_map("client").id == "client"
        assert fm.cell("client", 0.0, 0.0).known is False


def test_root_path_takes_a_url_path_and_names_what_is_wrong(capsys: pytest.CaptureFixture[str]) -> None:
    """uvicorn encodes the root path as ASCII for every request (one outside ASCII failed each), and
    puts it before each request's path as it is: `fleetmap` (no `/`) made paths such as
    `fleetmap/maps`, which no route matches."""
    _, sub = cli.command_line_parser()
    serve = sub.choices["serve"]
    taken_as = [("/fleetmap/", "/fleetmap"), ("/", ""), ("", ""), ("/a/b-c.d~e%20f", "/a/b-c.d~e%20f")]
    for given, taken in taken_as:
        assert serve.parse_args(["--root-path", given]).root_path == taken, given
    assert serve.parse_args([]).root_path == ""
    for given, hint in [
        ("fleetmap", "(a path starts with '/')"),
        ("/a//b", "(no empty segment: '//')"),
        ("/a?b=1", "(a path only: no query or fragment)"),
        ("/flëetmap", "are percent-encoded)"),
        ("/a b", "are percent-encoded)"),
    ]:
        with pytest.raises(SystemExit):
            serve.parse_args(["--root-path", given])
        said = capsys.readouterr().err
        assert f"--root-path: expected a URL path such as /fleetmap, got {given!r} (" in said, said
        assert said.endswith(f"{hint} (see fleetmap serve --help)\n"), said


def test_forwarded_allow_ips_help_gives_uvicorns_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--forwarded-allow-ips`' help said its default was 127.0.0.1, where uvicorn, which applies it,
    trusts ::1 as well (a proxy on this machine connecting over IPv6 is trusted too)."""
    import uvicorn

    monkeypatch.delenv("FORWARDED_ALLOW_IPS", raising=False)
    default = uvicorn.Config(app=None).forwarded_allow_ips
    assert isinstance(default, str)
    _, sub = cli.command_line_parser()
    (action,) = [a for a in sub.choices["serve"]._actions if "--forwarded-allow-ips" in a.option_strings]
    assert f"default {' and '.join(default.split(','))}," in (action.help or ""), (default, action.help)
