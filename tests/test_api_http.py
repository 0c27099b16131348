"""HTTP semantics of the real service as a client author, a tile client and a CDN in front see them:
HEAD on every GET route, no redirects for trailing slashes, gzip (never on the event stream), and the
caching headers (`Cache-Control`, `Vary`, weak ETags of compressed answers). See
fleetmap.api.http_semantics and docs/api.md, "HTTP conventions"."""

from __future__ import annotations

import gzip
import json
import math
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_process import ServiceProcess, wait_for

SCAN = {"seq": 1, "pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi,
        "angle_increment": math.pi / 180, "range_max": 10.0,
        "ranges": [3.0 + 0.5 * math.sin(k / 10) for k in range(361)]}  # fmt: skip
TILE = "/maps/m/tiles/0/0/-1.png"
IDENTITY = {"Accept-Encoding": "identity"}
GZIP = {"Accept-Encoding": "gzip"}


def integrate(client: httpx.Client, scan: dict[str, Any], headers: dict[str, str] | None = None) -> None:
    """POST `scan` to map `m` as robot `r` and wait until it is integrated. A 503 "not integrated
    within 10 s" (a loaded machine) still integrates it: wait for the count then."""
    r = client.post("/maps/m/scans", params={"robot_id": "r"}, json=scan, headers=headers)
    assert r.status_code in (200, 503), r.text
    seq = scan["seq"]  # the map's scans are seq 1, 2, ...: seq is also the count integrated
    wait_for(
        lambda: client.get("/maps/m", headers=headers).json()["stats"]["scans_integrated"] >= seq,
        what=f"scan {seq} integrated",
    )


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    """A client of one service for the module's tests (in memory: no test here is about storage)
    holding map `m` with one scan, which no test changes; the maps a test makes are its own."""
    with (
        ServiceProcess(tmp_path_factory.mktemp("api-http"), ["--in-memory"]) as service,
        httpx.Client(base_url=service.base_url, timeout=30) as client,
    ):
        assert client.put("/maps/m", json={"resolution": 0.05}).status_code == 201
        integrate(client, SCAN)
        yield client


def test_head_answers_every_get_route_with_its_headers_and_no_body(mapped: httpx.Client) -> None:
    paths = [TILE, "/maps", "/maps/m", "/healthz", "/metrics", "/maps/m/region?format=json",
             "/maps/m/cell?x=0&y=0", "/maps/m/export", "/maps/m/snapshot", "/", "/openapi.json"]  # fmt: skip
    for path in paths:
        got = mapped.get(path, headers=IDENTITY)
        head = mapped.head(path, headers=IDENTITY)
        assert head.status_code == got.status_code == 200, (path, head.status_code, head.text)
        assert head.content == b"", path
        assert head.headers["content-type"] == got.headers["content-type"], path
        if path == "/maps/m/snapshot":  # made only to be sent: its HEAD does not make it
            assert "content-length" not in head.headers
            assert head.headers["content-disposition"] == got.headers["content-disposition"]
        elif path not in ("/metrics", "/healthz"):  # those two change between requests
            assert head.headers["content-length"] == got.headers["content-length"], path
    tile = mapped.get(TILE)
    assert mapped.head(TILE).headers["etag"] == tile.headers["etag"]
    # A tile revalidated by HEAD: 304 as for GET.
    assert mapped.head(TILE, headers={"If-None-Match": tile.headers["etag"]}).status_code == 304
    # Errors too: the status and headers of the GET.
    missing = mapped.head("/maps/nope")
    assert missing.status_code == 404 and missing.headers["content-type"] == "application/json"
    # Where HEAD works, 405s say so; the event stream is the exception (its GET never ends).
    r = mapped.post("/maps/m/cell")
    assert r.status_code == 405 and r.headers["allow"] == "GET, HEAD", r.headers
    r = mapped.post("/maps/m/region")  # read, and cleared with DELETE
    assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET, HEAD", r.headers
    r = mapped.head("/maps/m/events")
    assert r.status_code == 405 and r.headers["allow"] == "GET"


def test_a_trailing_slash_is_a_json_404_naming_the_resource(mapped: httpx.Client) -> None:
    for path, bare in (("/maps/", "/maps"), ("/maps/m/", "/maps/m"), ("/maps/m/scans/", "/maps/m/scans")):
        r = mapped.get(path)
        assert r.status_code == 404 and r.headers["content-type"] == "application/json", (path, r.headers)
        assert "location" not in r.headers
        assert r.json()["detail"] == f"no such resource: {path} (did you mean {bare}?)"
    assert mapped.get("/nothing/").json()["detail"] == "no such resource: /nothing/"
    r = mapped.put("/maps/new/", json={})
    assert r.status_code == 404 and mapped.get("/maps/new").status_code == 404  # nothing created


def test_large_answers_are_gzipped_for_clients_that_accept_it(mapped: httpx.Client) -> None:
    plain = mapped.get("/maps/m/region?format=json", headers=IDENTITY)
    assert "content-encoding" not in plain.headers
    with httpx.stream("GET", f"{mapped.base_url}/maps/m/region?format=json", headers=GZIP) as r:
        wire = b"".join(r.iter_raw())  # the bytes as sent, before httpx decodes them
        encoded = r.headers
    assert encoded["content-encoding"] == "gzip" and "accept-encoding" in encoded["vary"].lower()
    assert int(encoded["content-length"]) == len(wire) < len(plain.content) / 10
    assert gzip.decompress(wire) == plain.content
    assert mapped.get("/openapi.json", headers=GZIP).headers["content-encoding"] == "gzip"
    # Already compressed: sent as is.
    for path in (TILE, "/maps/m/export", "/maps/m/region?format=png"):
        assert "content-encoding" not in mapped.get(path, headers=GZIP).headers, path
    # Small answers are not worth it.
    assert "content-encoding" not in mapped.get("/maps/m/cell?x=0&y=0", headers=GZIP).headers
    # A compressed static file is another representation than the file: its ETag is weak.
    static = mapped.get("/static/app.js", headers=GZIP)
    assert static.headers["content-encoding"] == "gzip" and static.headers["etag"].startswith('W/"')
    assert not mapped.get("/static/app.js", headers=IDENTITY).headers["etag"].startswith("W/")
    again = mapped.get("/static/app.js", headers={**GZIP, "If-None-Match": static.headers["etag"]})
    assert again.status_code == 304
    # Its 304 says what the 200 would (RFC 9110, 15.4.5): the same weak tag, and the Vary on
    # Accept-Encoding; it said the strong tag with no Vary, and matched nothing a cache stored.
    assert again.headers["etag"] == static.headers["etag"], again.headers
    assert "accept-encoding" in again.headers.get("vary", "").lower()
    plain = mapped.get("/static/app.js", headers={**IDENTITY, "If-None-Match": static.headers["etag"]})
    assert plain.status_code == 304 and not plain.headers["etag"].startswith("W/")
    # Its 200 says `Vary: Accept-Encoding` uncompressed too (its encoding is negotiated), so its 304
    # does: it said none, unlike its 200.
    plain_200 = mapped.get("/static/app.js", headers=IDENTITY)
    assert "content-encoding" not in plain_200.headers
    assert plain.headers.get("vary") == plain_200.headers.get("vary") == "Accept-Encoding", plain.headers
    # A tag on a second field line (as a proxy merging tags sends it) matches, as for tiles:
    # Starlette read the first line alone, answering the whole file. `*` matches too.
    star = mapped.get("/static/app.js", headers={**GZIP, "If-None-Match": "*"})
    assert star.status_code == 304
    two_lines = [
        ("Accept-Encoding", "gzip"),
        ("If-None-Match", '"other"'),
        ("If-None-Match", static.headers["etag"]),
    ]
    assert mapped.get("/static/app.js", headers=two_lines).status_code == 304
    assert mapped.get("/static/app.js", headers={**GZIP, "If-None-Match": '"other"'}).status_code == 200
    # The viewer's page (`/`) revalidates the same way; it had an ETag but answered every
    # revalidation, each page load (`no-cache`), with the whole page.
    page = mapped.get("/", headers=GZIP)
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    again = mapped.get("/", headers={**GZIP, "If-None-Match": page.headers["etag"]})
    assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == page.headers["etag"]


def test_the_spec_declares_the_headers_that_locate_and_validate_reads(mapped: httpx.Client) -> None:
    """A region's npy or png answer says where it lies only in its `X-Fleetmap-*` headers (and
    without bounds the client cannot know), a tile's and a JSON answer's validator is its `ETag`:
    the committed spec declares each such header the service sends, and the 304 of a JSON GET, so
    a client generated from it can read and revalidate them."""
    spec = json.loads((Path(__file__).resolve().parents[1] / "openapi" / "openapi.json").read_text())
    region = spec["paths"]["/maps/{map_id}/region"]["get"]["responses"]
    tile = spec["paths"]["/maps/{map_id}/tiles/{z}/{x}/{y}.png"]["get"]["responses"]
    info = spec["paths"]["/maps/{map_id}"]["get"]["responses"]
    got = mapped.get(TILE)
    listed = mapped.get("/maps/m")
    answers = [
        *(
            (region["200"], mapped.get("/maps/m/region", params={"format": f}))
            for f in ("npy", "json", "png")
        ),
        (tile["200"], got),
        (tile["304"], mapped.get(TILE, headers={"If-None-Match": got.headers["etag"]})),
        (info["200"], listed),
    ]
    revalidated = mapped.get("/maps/m", headers={"If-None-Match": listed.headers["etag"]})
    assert revalidated.status_code == 304 and "304" in info
    for documented, r in answers:
        meant = (
            {"x-fleetmap-window", "x-fleetmap-origin", "x-fleetmap-resolution"}
            if "region" in r.url.path
            else {"etag"}
        )
        assert meant <= set(r.headers), (r.url, r.status_code)
        declared = {name.lower() for name in documented.get("headers", {})}
        assert meant <= declared, (r.url, r.status_code, meant - declared)


def test_a_client_refusing_gzip_gets_no_gzip(mapped: httpx.Client) -> None:
    """`Accept-Encoding` is read by its weights (RFC 9110, 12.5.3): `gzip;q=0` means "not
    acceptable", so the answer is sent as it is, however large; `*` accepts gzip unless gzip is
    named with a weight of 0."""
    path = f"{mapped.base_url}/maps/m/region?format=json"
    plain = mapped.get(path, headers=IDENTITY).content
    assert len(plain) > 10_000
    for offered, gzipped in [
        ("gzip;q=0", False),
        ("identity, gzip; q=0", False),
        ("br, GZIP;Q=0.0", False),
        ("*;q=1, gzip;q=0", False),
        ("gzip;q=0.5", True),
        ("*", True),
        ("deflate, x-gzip", True),
    ]:
        with httpx.stream("GET", path, headers={"Accept-Encoding": offered}) as r:
            wire = b"".join(r.iter_raw())  # the bytes as sent, before httpx decodes them
            assert (r.headers.get("content-encoding") == "gzip") is gzipped, offered
            assert "accept-encoding" in r.headers["vary"].lower(), offered  # caches keep both apart
        assert (gzip.decompress(wire) if gzipped else wire) == plain, offered


def test_the_event_stream_is_never_compressed_and_each_event_arrives_at_once(mapped: httpx.Client) -> None:
    """A client accepting gzip gets the stream uncompressed, and each event when it is sent. Small
    events gain little from gzip, and a compressor that does not flush after every event (older
    Starlette's did not; a proxy's may not) holds them back until its buffer fills."""
    events: list[str] = []
    started, seen = threading.Event(), threading.Event()
    headers: dict[str, str] = {}

    def listen() -> None:
        with httpx.stream("GET", f"{mapped.base_url}/maps/m/events", headers=GZIP, timeout=30) as r:
            headers.update(r.headers)
            for line in r.iter_lines():
                events.append(line)
                if line.startswith("event: robots"):  # sent once the stream follows the map
                    started.set()
                if line.startswith("event: tiles"):
                    seen.set()
                    return

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    assert started.wait(20), f"the stream did not start within 20 s; got {events!r}"
    second = {**SCAN, "seq": 2, "pose": {"x": 0.5, "y": 0.0, "theta": 0.0}}
    integrate(mapped, second)
    assert seen.wait(20), f"no tiles event within 20 s; got {events!r}"
    thread.join(5)
    assert "content-encoding" not in headers and headers["content-type"].startswith("text/event-stream")


def test_every_answer_says_how_to_cache_it(mapped: httpx.Client) -> None:
    for path in ("/maps", "/maps/m/region?format=json", "/maps/m/cell?x=0&y=0", "/healthz",
                 "/maps/nope"):  # fmt: skip
        assert mapped.get(path).headers["cache-control"] == "no-cache", path
    # A map's answer carries the map's own ETag, which stays while its statistics change: no cache
    # may keep it and revalidate with that tag (docs/api.md, "Conditional writes").
    assert mapped.get("/maps/m").headers["cache-control"] == "no-store"
    r = mapped.post("/maps/m/cells", json={"points": [[0.0, 0.0]]})
    assert r.headers["cache-control"] == "no-cache"
    assert mapped.get(TILE).headers["cache-control"] == "no-cache"  # public: a CDN may store it
    assert "vary" not in mapped.get("/maps/m").headers  # no CORS: nothing varies by origin


READ, WRITE = "read-token-0123456789", "write-token-0123456789"
PAGE = "http://viewer.example"


def test_tiles_are_private_when_reading_needs_a_token(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    """A CDN must not keep a tile that only token holders may read: `private` keeps it out of every
    shared cache (the browser still stores and revalidates it)."""
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    svc = service_factory("--auth-tokens", str(tokens), "--require-read-token")
    write, read = ({"Authorization": f"Bearer {t}"} for t in (WRITE, READ))
    with httpx.Client(base_url=svc.base_url, timeout=30) as client:
        assert client.put("/maps/m", json={"resolution": 0.05}, headers=write).status_code == 201
        integrate(client, SCAN, headers=write)
        tile = client.get(TILE, headers=read)
        assert tile.status_code == 200 and tile.headers["cache-control"] == "private, no-cache"
        again = client.get(TILE, headers={**read, "If-None-Match": tile.headers["etag"]})
        assert again.status_code == 304 and again.headers["cache-control"] == "private, no-cache"


def test_with_cors_every_answer_varies_by_origin(service_factory: Callable[..., ServiceProcess]) -> None:
    """Also the answers to requests without an `Origin` (Starlette's CORS middleware does it): else a
    CDN would cache one and serve it, without CORS headers, to the viewer's page, which then cannot
    read it."""
    svc = service_factory("--cors-origin", PAGE)
    with httpx.Client(base_url=svc.base_url, timeout=30) as client:
        assert client.put("/maps/m", json={}).status_code == 201
        for path in ("/maps/m", "/maps/m/tiles/0/0/-1.png", "/maps/nope"):
            plain = client.get(path, headers=IDENTITY)
            assert "origin" in plain.headers.get("vary", "").lower(), (path, plain.headers)
            cross = client.get(path, headers={**IDENTITY, "Origin": PAGE})
            assert cross.headers["access-control-allow-origin"] == PAGE
            # A page may read where a PUT put its map and when to retry a 503.
            exposed = cross.headers["access-control-expose-headers"].lower().replace(" ", "").split(",")
            assert {"etag", "location", "retry-after"} <= set(exposed), exposed
            assert [v.strip() for v in cross.headers["vary"].split(",")].count("Origin") == 1, cross.headers
        # Another origin is not allowed, and gets no CORS headers.
        other = client.get("/maps/m", headers={**IDENTITY, "Origin": "https://elsewhere.example"})
        assert "access-control-allow-origin" not in other.headers


def test_cors_origin_star_allows_every_origin_as_the_docs_say(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """`--cors-origin '*'` (docs/security.md): every origin, answered `*`, never the origin itself."""
    svc = service_factory("--cors-origin", "*")
    with httpx.Client(base_url=svc.base_url, timeout=30) as client:
        for origin in (PAGE, "https://elsewhere.example"):
            r = client.get("/maps", headers={**IDENTITY, "Origin": origin})
            assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "*", r.headers


JSON = {"content-type": "application/json"}


def test_json_bodies_are_read_strictly_and_a_refused_one_changes_nothing(mapped: httpx.Client) -> None:
    refused = [
        # (body, headers, status, words of the detail)
        (b'{"resolution": 0.05}', {"content-type": "text/plain"}, 415, "Content-Type: application/json"),
        (b'{"resolution": 0.05}', {"content-type": "application/x-www-form-urlencoded"}, 415, "not 'app"),
        (b'{"resolution": 0.05}', {}, 415, "none was given"),
        (b'{"resolution": 0.05, "resolution": 0.1}', JSON, 422, "the key 'resolution' appears twice"),
        (b'{"occupancy": {"l_hit": 1, "l_hit": 2}}', JSON, 422, "the key 'l_hit' appears twice"),
        (b'\xef\xbb\xbf{"resolution": 0.05}', JSON, 422, "byte order mark"),
        (b'{"resolution": ' + b"9" * 5000 + b"}", JSON, 422, "too many digits"),
        (b"[" * 100_000 + b"]" * 100_000, JSON, 422, "nested too deeply"),
        (b'{"resolution": 0.05', JSON, 422, "body is not valid JSON for this API: Expecting"),
        (b'{"resolution": 0.05}\xff', JSON, 422, "not UTF-8"),
        # A JSON null is a body, and no configuration: it made the map with the server's default
        # configuration, as no body does, while `[]` or `"x"` were refused.
        (b"null", JSON, 422, "body: a map configuration is a JSON object, not null; send no body"),
        (b"[]", JSON, 422, "body: Input should be a valid dictionary"),
    ]
    for body, headers, status, words in refused:
        r = mapped.put("/maps/refused", content=body, headers=headers)
        where = f"{body[:40]!r} {headers}: {r.status_code} {r.text[:200]}"
        assert r.status_code == status and r.headers["content-type"] == "application/json", where
        assert words in r.json()["detail"], where
    assert mapped.get("/maps/refused").status_code == 404  # none of them created it
    # The same rules for POST /cells.
    r = mapped.post("/maps/m/cells", content=b'{"points": [[0, 0]]}', headers={"content-type": "text/plain"})
    assert r.status_code == 415
    r = mapped.post("/maps/m/cells", content=b'{"points": [[0, 0]], "points": [[9, 9]]}', headers=JSON)
    assert r.status_code == 422 and "'points' appears twice" in r.json()["detail"]
    # And for a scan, whose JSON is that of Zenoh messages too (its codec used to keep the last seq).
    before = mapped.get("/maps/m").json()["stats"]
    body = json.dumps({**SCAN, "seq": 2}).replace('"seq": 2', '"seq": 2, "seq": 9')
    r = mapped.post("/maps/m/scans", params={"robot_id": "r"}, content=body, headers=JSON)
    assert r.status_code == 422 and "the key 'seq' appears twice" in r.json()["detail"], r.text
    after = mapped.get("/maps/m").json()["stats"]
    assert after["scans_integrated"] == before["scans_integrated"] and after["version"] == before["version"]
    assert after["robots"]["r"]["scans_rejected"] == before["robots"]["r"]["scans_rejected"] + 1
    # What stays allowed: JSON with a charset, an empty body of any type (the default configuration).
    assert (
        mapped.put(
            "/maps/a", content=b"{}", headers={"content-type": "application/json; charset=utf-8"}
        ).status_code
        == 201
    )
    assert mapped.put("/maps/b", content=b"", headers={"content-type": "text/plain"}).status_code == 201


def test_a_compressed_request_body_is_refused_saying_so(mapped: httpx.Client) -> None:
    """No route decodes a Content-Encoding: a gzipped JSON body was refused as "not UTF-8 text" and
    a gzipped snapshot as "not a zip file". 415 with Accept-Encoding: identity (RFC 9110, 15.5.16)
    says what to change, and changes nothing."""
    body = gzip.compress(json.dumps({"points": [[0.0, 0.0]]}).encode())
    spec = json.loads((Path(__file__).resolve().parents[1] / "openapi" / "openapi.json").read_text())
    for method, path, route, headers in [
        ("POST", "/maps/m/cells", "/maps/{map_id}/cells", JSON),
        ("PUT", "/maps/zipped", "/maps/{map_id}", JSON),
        ("PUT", "/maps/zipped/snapshot", "/maps/{map_id}/snapshot", {"content-type": "application/zip"}),
        ("POST", "/maps/m/scans?robot_id=r", "/maps/{map_id}/scans", JSON),
    ]:
        r = mapped.request(method, path, content=body, headers={**headers, "content-encoding": "gzip"})
        assert r.status_code == 415 and r.headers["accept-encoding"] == "identity", (path, r.text)
        assert "415" in spec["paths"][route][method.lower()]["responses"], f"{method} {route}: 415 undeclared"
        assert "Content-Encoding 'gzip'" in r.json()["detail"] and "uncompressed" in r.json()["detail"]
    assert mapped.get("/maps/zipped").status_code == 404
    # identity is no encoding at all.
    plain = json.dumps({"points": [[0.0, 0.0]]}).encode()
    r = mapped.post("/maps/m/cells", content=plain, headers={**JSON, "content-encoding": "identity"})
    assert r.status_code == 200, r.text


def test_a_body_with_a_transfer_coding_other_than_chunked_is_refused_saying_so(mapped: httpx.Client) -> None:
    """The HTTP server undoes `chunked` only: a body sent `Transfer-Encoding: gzip, chunked` reached
    the routes as the gzipped bytes, so a gzipped snapshot was refused as "not a zip file" and gzipped
    JSON as "not UTF-8 text", as a Content-Encoding once was. It is a 415 saying so, nothing changed;
    `chunked` alone (in any case) is read as before."""
    snapshot = mapped.get("/maps/m/snapshot").content

    def send(path: str, body: bytes, coding: str, content_type: str) -> tuple[int, dict[str, Any]]:
        chunked = b"%x\r\n%s\r\n0\r\n\r\n" % (len(body), body)
        head = (
            f"PUT {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: {content_type}\r\n"
            f"Transfer-Encoding: {coding}\r\nConnection: close\r\n\r\n"
        )
        with socket.create_connection(("127.0.0.1", mapped.base_url.port or 80), timeout=30) as sock:
            sock.sendall(head.encode() + chunked)
            answer = b""
            while chunk := sock.recv(65536):
                answer += chunk
        status_line, _, rest = answer.partition(b"\r\n")
        return int(status_line.split()[1]), json.loads(rest.partition(b"\r\n\r\n")[2])

    for path, body, content_type in [
        ("/maps/zipped/snapshot", snapshot, "application/zip"),
        ("/maps/zipped", b"{}", "application/json"),
    ]:
        for coding in ("gzip, chunked", "deflate,chunked"):
            status, answer = send(path, gzip.compress(body), coding, content_type)
            assert status == 415, (path, coding, answer)
            assert f"Transfer-Encoding {coding!r}" in answer["detail"] and "uncompressed" in answer["detail"]
        assert mapped.get("/maps/zipped").status_code == 404
    assert send("/maps/plain/snapshot", snapshot, "Chunked", "application/zip")[0] == 201


def test_a_content_encoding_without_a_body_refuses_nothing(mapped: httpx.Client) -> None:
    """A `Content-Encoding` says how a body is encoded: a request without one (a GET, a HEAD, a
    DELETE, `Content-Length: 0`) has nothing encoded. Every such request was refused 415 "a body
    with Content-Encoding 'gzip' is not read here", /healthz too (a monitor or a client library
    that sets the header on every request saw the service refuse all of it), with a status the spec
    gives none of those routes. A body sent so is still refused (above), chunked too."""
    gzipped = {"content-encoding": "gzip"}
    assert mapped.get("/healthz", headers=gzipped).status_code == 200
    assert mapped.get("/maps/m", headers=gzipped).status_code == 200
    assert mapped.head(TILE, headers=gzipped).status_code == 200
    empty = mapped.put("/maps/m", content=b"", headers={**gzipped, "content-length": "0"})
    assert empty.status_code == 200, empty.text  # no body: the defaults, as the map has them
    assert mapped.put("/maps/gone", headers=gzipped).status_code == 201
    assert mapped.delete("/maps/gone", headers=gzipped).status_code == 204
    body = gzip.compress(json.dumps({"points": [[0.0, 0.0]]}).encode())
    chunked = mapped.post("/maps/m/cells", content=iter([body]), headers={**JSON, **gzipped})
    assert chunked.status_code == 415 and "chunked" in chunked.request.headers["transfer-encoding"]


def test_query_parameters_once_each_unknown_ones_ignored(mapped: httpx.Client) -> None:
    for path in ("/maps/m/cell?x=0&x=5&y=0", f"{TILE}?layer=hits&layer=probability",
                 "/maps/m/region?xmin=0&xmin=1&ymin=0&xmax=1&ymax=1"):  # fmt: skip
        r = mapped.get(path)
        assert r.status_code == 422 and "is given more than once" in r.json()["detail"], (path, r.text)
        (item,) = r.json()["errors"]  # listed as a validation failure lists its problems
        assert item["loc"][0] == "query" and item["type"] == "repeated", r.text
    r = mapped.get("/maps/m/region?xmin=0&xmin=1&ymin=0&ymin=2&xmax=1&ymax=1")
    assert [e["loc"] for e in r.json()["errors"]] == [["query", "xmin"], ["query", "ymin"]], r.text
    assert "(and 1 more)" in r.json()["detail"], r.text
    plain = mapped.get("/maps/m/cell?x=0&y=0").json()
    assert mapped.get("/maps/m/cell?x=0&y=0&_=1700000000&v=2&v=3").json() == plain
    assert mapped.get(f"{TILE}?v=2").headers["etag"] == mapped.get(TILE).headers["etag"]
    for value in ("nan", "inf", "-inf", "1e400"):
        r = mapped.get(f"/maps/m/cell?x={value}&y=0")
        assert r.status_code == 422 and "finite" in r.json()["detail"], (value, r.text)


def test_a_number_with_an_underscore_is_refused_where_it_was_read_as_another(mapped: httpx.Client) -> None:
    """pydantic reads `1_0` as 10: a typo in a coordinate, a tile index or a resolution was answered
    for another place than asked. Numbers in the query and the path take no underscore; ids still do."""
    for path, where, name in (
        ("/maps/m/cell?x=1_0.5&y=0", "query", "x"),
        ("/maps/m/tiles/0/1_0/0.png", "path", "x"),
        ("/maps/m/export?resolution=0.1_0", "query", "resolution"),
    ):
        r = mapped.get(path)
        assert r.status_code == 422, (path, r.status_code, r.text)
        assert r.json()["detail"].startswith(f"{where} parameter {name!r}: "), r.text
        assert r.json()["errors"][0]["loc"] == [where, name], r.text
    assert mapped.get("/maps/m/cell?x=10.5&y=0").json()["x"] == 10.5  # written plainly, as before
    assert mapped.put("/maps/with_underscore", json={}).status_code == 201


def test_an_integer_not_in_plain_decimal_is_refused_so_a_tile_has_one_url(mapped: httpx.Client) -> None:
    """pydantic reads `01`, `+1`, `1.0` and ` 1` as 1: a tile had many URLs, each cached apart by
    browsers and proxies. Integers in the path and the query are plain decimal; floats keep their
    forms (`1e1` is a coordinate as good as `10`)."""
    assert mapped.get("/maps/m/tiles/0/-1/0.png").status_code != 422  # plain, negative
    for spelling in ("01", "+1", "1.0", "%201", "-0", "1e0"):
        r = mapped.get(f"/maps/m/tiles/0/{spelling}/0.png")
        assert r.status_code == 422, (spelling, r.status_code, r.text)
        assert r.json()["detail"].startswith("path parameter 'x': ") and "plain decimal" in r.text, r.text
        assert r.json()["errors"][0]["loc"] == ["path", "x"], r.text
    r = mapped.get("/maps/m/export?margin=+2")
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["query", "margin"], r.text
    assert mapped.get("/maps/m/cell?x=1e1&y=+0").json()["x"] == 10.0


def test_a_put_that_creates_answers_201_with_its_location_then_200(mapped: httpx.Client) -> None:
    created = mapped.put("/maps/p", json={"resolution": 0.1})
    assert created.status_code == 201 and created.headers["location"] == "/maps/p"
    again = mapped.put("/maps/p", json={"resolution": 0.1})
    assert again.status_code == 200 and "location" not in again.headers
    assert again.json()["config"] == created.json()["config"]
    snapshot = mapped.get("/maps/m/snapshot").content
    zipped = {"content-type": "application/zip"}
    restored = mapped.put("/maps/copy/snapshot", content=snapshot, headers=zipped)
    assert restored.status_code == 201 and restored.headers["location"] == "/maps/copy"
    replaced = mapped.put("/maps/copy/snapshot", content=snapshot, headers=zipped)
    assert replaced.status_code == 200 and "location" not in replaced.headers


def test_small_json_answers_carry_an_etag_and_revalidate_to_304(mapped: httpx.Client) -> None:
    """A viewer polling the map list downloads it only when it changed."""
    first = mapped.get("/maps")
    etag = first.headers["etag"]
    assert etag.startswith('W/"'), etag  # weak: the gzip form shares it
    same = mapped.get("/maps", headers={"If-None-Match": etag})
    assert same.status_code == 304 and same.content == b"" and same.headers["etag"] == etag
    assert same.headers["cache-control"] == "no-cache" and "content-type" not in same.headers
    assert mapped.get("/maps", headers={**GZIP, "If-None-Match": f'"other", {etag}'}).status_code == 304
    assert mapped.head("/maps", headers={"If-None-Match": etag}).status_code == 304
    # A 304 says the Vary its 200 would (RFC 9110, 15.4.5): the gzip middleware put `Accept-Encoding`
    # only on the 200 it compressed, so the 304 of a large answer left it out.
    zipped = mapped.get("/openapi.json", headers=GZIP)
    assert zipped.headers["content-encoding"] == "gzip" and "Accept-Encoding" in zipped.headers["vary"]
    spec_etag = {"If-None-Match": zipped.headers["etag"]}
    again = mapped.get("/openapi.json", headers={**GZIP, **spec_etag})
    assert again.status_code == 304 and "Accept-Encoding" in again.headers.get("vary", ""), again.headers
    # A client taking no gzip gets the 200 uncompressed, whose `Vary: Accept-Encoding` its 304 says
    # too: it said none, as if the answer were not negotiated.
    plain_200 = mapped.get("/openapi.json", headers=IDENTITY)
    assert "content-encoding" not in plain_200.headers and plain_200.headers["vary"] == "Accept-Encoding"
    plain = mapped.get("/openapi.json", headers={**IDENTITY, "If-None-Match": plain_200.headers["etag"]})
    assert plain.status_code == 304 and plain.headers.get("vary") == "Accept-Encoding", plain.headers
    assert mapped.put("/maps/another", json={}).status_code == 201
    changed = mapped.get("/maps", headers={"If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["etag"] != etag
    assert "another" in changed.text
    # Answers with their own validators keep them; errors and large answers get none.
    assert mapped.get(TILE).headers["etag"].startswith('"')
    assert "etag" not in mapped.get("/maps/nope").headers
    big = mapped.get(
        "/maps/m/region", params={"format": "json", "xmin": -25, "ymin": -25, "xmax": 25, "ymax": 25}
    )
    assert big.status_code == 200 and len(big.content) > 1024 * 1024 and "etag" not in big.headers
