"""Conditional writes on maps (docs/api.md, "Conditional writes"; fleetmap.api.conditional), against
the real service over real sockets: the map's strong `ETag`, `If-Match` (strong comparison) and
`If-None-Match: *` on `PUT` / `DELETE /maps/{id}` and the snapshot and nav2 uploads, 412 with the
usual JSON error and nothing changed, and two writers racing with one tag: exactly one wins."""

from __future__ import annotations

import io
import math
import threading
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from service_process import ServiceProcess
from test_auth import READ, WRITE, bearer

SCAN = {"pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi,
        "angle_increment": math.pi / 180, "range_max": 10.0,
        "ranges": [3.0 + 0.5 * math.sin(k / 10) for k in range(361)]}  # fmt: skip
GZIP = {"Accept-Encoding": "gzip"}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One durable service (the default) for the module: conditions are checked where a change is
    stored, so storage is part of what is tested."""
    with ServiceProcess(tmp_path_factory.mktemp("conditional")) as svc:
        yield svc


@pytest.fixture
def client(service: ServiceProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=service.base_url, timeout=60) as c:
        yield c


def scan(client: httpx.Client, map_id: str, robot: str, seq: int) -> None:
    r = client.post(f"/maps/{map_id}/scans", params={"robot_id": robot}, json={**SCAN, "seq": seq})
    assert r.status_code == 200 and r.json()["status"] == "integrated", r.text


def fresh(client: httpx.Client, map_id: str) -> str:
    """Make map `map_id` anew (deleting any left by an earlier test) and return its ETag."""
    client.delete(f"/maps/{map_id}")
    r = client.put(f"/maps/{map_id}", json={"resolution": 0.05})
    assert r.status_code == 201, r.text
    return r.headers["etag"]


def assert_refused(r: httpx.Response, status: int = 412) -> str:
    """The answer is the service's JSON error of `status`; returns its detail."""
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"] == "application/json"
    detail = r.json()["detail"]
    assert isinstance(detail, str) and detail
    return detail


def test_the_map_etag_is_strong_stays_through_scans_and_gzip_and_changes_with_the_map(
    client: httpx.Client,
) -> None:
    """GET, HEAD and PUT answer the same strong tag; scans do not change it (nor does gzip weaken
    it: it names the map, not the bytes), a new map of the id has another; the answer is no-store
    (its statistics move while the tag stays), and a GET sending the tag back gets 304."""
    etag = fresh(client, "tagged")
    assert etag.startswith('"') and not etag.startswith("W/")
    for robot in range(8):  # enough robots for an answer over 1 KiB, which is gzipped
        scan(client, "tagged", f"robot{robot}", 1)
    got = client.get("/maps/tagged", headers=GZIP)
    assert got.headers.get("content-encoding") == "gzip"
    assert got.headers["etag"] == etag
    assert got.headers["cache-control"] == "no-store"
    assert got.json()["stats"]["scans_integrated"] == 8
    assert client.head("/maps/tagged").headers["etag"] == etag
    assert client.put("/maps/tagged", json={"resolution": 0.05}).headers["etag"] == etag  # found as asked
    revalidated = client.get("/maps/tagged", headers={"If-None-Match": etag})
    assert revalidated.status_code == 304 and revalidated.headers["etag"] == etag
    assert client.get("/maps/tagged", headers={"If-None-Match": '"other"'}).status_code == 200
    # Several field lines are one list (RFC 9110, 5.3), as for the writes: the tag on the second counts.
    lines = [("If-None-Match", '"other"'), ("If-None-Match", etag)]
    assert client.get("/maps/tagged", headers=lines).status_code == 304
    # The same id made again is another map: another tag.
    assert client.delete("/maps/tagged").status_code == 204
    again = client.put("/maps/tagged", json={"resolution": 0.05})
    assert again.headers["etag"] != etag


def test_delete_with_if_match(client: httpx.Client) -> None:
    """Only the map of the tag is deleted: another tag, the weak form of the right one (If-Match
    compares strongly), or a tag after the map was replaced: 412 with the current tag, the map kept."""
    etag = fresh(client, "del")
    scan(client, "del", "r", 1)
    for sent in ('"map-1"', f"W/{etag}", '"a", "b"'):
        r = client.delete("/maps/del", headers={"If-Match": sent})
        assert "del" in assert_refused(r)
        assert r.headers["etag"] == etag  # what the map is now: read it again, decide again
        assert client.get("/maps/del").json()["stats"]["scans_integrated"] == 1  # untouched
    assert "weak" in client.delete("/maps/del", headers={"If-Match": f"W/{etag}"}).json()["detail"]
    # Listed among others, or as two header lines, the right tag matches.
    r = client.request("DELETE", "/maps/del", headers=[("If-Match", '"x"'), ("If-Match", f'"y", {etag}')])
    assert r.status_code == 204, r.text
    assert client.get("/maps/del").status_code == 404
    # No map: the 404 comes first, as without a condition (RFC 9110, 13.2.1).
    assert "no map" in assert_refused(client.delete("/maps/del", headers={"If-Match": etag}), 404)
    assert "no map" in assert_refused(client.delete("/maps/del", headers={"If-Match": "*"}), 404)
    # A replaced map (deleted and made again) refuses the old tag.
    newer = fresh(client, "del")
    assert_refused(client.delete("/maps/del", headers={"If-Match": etag}))
    assert client.delete("/maps/del", headers={"If-Match": "*"}).status_code == 204
    assert newer != etag


def test_create_only_and_if_match_on_put(client: httpx.Client) -> None:
    """`If-None-Match: *` creates, never finds: 412 when the map exists, even with the same
    configuration. `If-Match` on a PUT needs the map, with that tag, before configurations are
    compared. A malformed header is a 422; none of these changes anything."""
    client.delete("/maps/put")
    created = client.put("/maps/put", json={"resolution": 0.05}, headers={"If-None-Match": "*"})
    assert created.status_code == 201, created.text
    etag = created.headers["etag"]
    r = client.put("/maps/put", json={"resolution": 0.05}, headers={"If-None-Match": "*"})
    assert "exists" in assert_refused(r)
    # The right tag: found as asked (200), or the usual 409 for another configuration.
    assert client.put("/maps/put", json={"resolution": 0.05}, headers={"If-Match": etag}).status_code == 200
    assert client.put("/maps/put", json={"resolution": 0.1}, headers={"If-Match": etag}).status_code == 409
    # A stale tag is a 412 first, whatever the configuration.
    assert_refused(client.put("/maps/put", json={"resolution": 0.1}, headers={"If-Match": '"map-0"'}))
    for bad in ("map-1", '"a" "b"', '"a", *', ""):
        detail = assert_refused(client.put("/maps/put", json={}, headers={"If-Match": bad}), 422)
        assert "If-Match" in detail
    assert client.get("/maps/put").headers["etag"] == etag
    # If-Match on a map that does not exist creates nothing.
    client.delete("/maps/put")
    assert_refused(client.put("/maps/put", json={}, headers={"If-Match": etag}))
    assert_refused(client.put("/maps/put", json={}, headers={"If-Match": "*"}))
    assert client.get("/maps/put").status_code == 404


def nav2_zip() -> bytes:
    """A 1 x 1 m nav2 map, all free, at 0.05 m."""
    image = io.BytesIO()
    Image.fromarray(np.full((20, 20), 254, np.uint8)).save(image, format="PNG")
    yaml_text = "image: m.png\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
    yaml_text += "occupied_thresh: 0.65\nfree_thresh: 0.25\n"
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("map.yaml", yaml_text)
        zf.writestr("m.png", image.getvalue())
    return buf.getvalue()


def test_uploads_replace_only_the_map_of_the_tag(client: httpx.Client) -> None:
    """`PUT .../snapshot` and `PUT .../import` replace a map: with `If-Match` only the map of that
    tag, with `If-None-Match: *` only when there is none. A refused upload leaves the map as it was."""
    zipped = {"content-type": "application/zip"}
    fresh(client, "src")
    scan(client, "src", "r", 1)
    snapshot = client.get("/maps/src/snapshot").content
    etag = fresh(client, "up")
    put = client.put("/maps/up/snapshot", content=snapshot, headers={**zipped, "If-Match": etag})
    assert put.status_code == 200, put.text
    replaced = put.headers["etag"]
    assert replaced != etag and client.get("/maps/up").headers["etag"] == replaced
    # The tag read before the replacement is stale now, for both uploads.
    stale = client.put("/maps/up/snapshot", content=snapshot, headers={**zipped, "If-Match": etag})
    assert_refused(stale)
    nav2 = client.put("/maps/up/import?format=ros", content=nav2_zip(), headers={**zipped, "If-Match": etag})
    assert_refused(nav2)
    assert_refused(client.put("/maps/up/import?format=ros", content=nav2_zip(),
                              headers={**zipped, "If-None-Match": "*"}))  # fmt: skip
    info = client.get("/maps/up")
    assert info.headers["etag"] == replaced and info.json()["stats"]["bounds"] is not None  # the snapshot's
    imported = client.put("/maps/up/import?format=ros", content=nav2_zip(),
                          headers={**zipped, "If-Match": replaced})  # fmt: skip
    assert imported.status_code == 200, imported.text
    # Create-only: a new id takes it.
    client.delete("/maps/up-new")
    new = client.put("/maps/up-new/snapshot", content=snapshot, headers={**zipped, "If-None-Match": "*"})
    assert new.status_code == 201, new.text
    assert client.get("/maps/up-new").headers["etag"] == new.headers["etag"]


def test_the_same_upload_twice_replaces_the_map_again_as_the_docs_say(client: httpx.Client) -> None:
    """docs/api.md ("Content types") said of every `PUT` that the same one twice changes nothing the
    second time. So it is for `PUT /maps/{map_id}` (same map, same `ETag`); a snapshot sent twice
    replaces the map twice: the same cells, but another map (a new `ETag`, so the first answer's is
    stale, and its robots afresh). A retry sent with the `If-Match` read replaces nothing made
    since. The docs now say so."""
    zipped = {"content-type": "application/zip"}
    etag = fresh(client, "twice")
    assert client.put("/maps/twice", json={"resolution": 0.05}).headers["etag"] == etag
    scan(client, "twice", "r", 1)
    snapshot = client.get("/maps/twice/snapshot").content
    client.delete("/maps/twice-copy")
    first = client.put("/maps/twice-copy/snapshot", content=snapshot, headers=zipped)
    assert first.status_code == 201, first.text
    scan(client, "twice-copy", "r", 1)  # a robot maps on into the restored map
    second = client.put("/maps/twice-copy/snapshot", content=snapshot, headers=zipped)
    assert second.status_code == 200, second.text
    assert second.headers["etag"] != first.headers["etag"] and second.json()["stats"]["robots"] == {}
    assert_refused(client.put("/maps/twice-copy/snapshot", content=snapshot,
                              headers={**zipped, "If-Match": first.headers["etag"]}))  # fmt: skip
    window = {"xmin": -4, "ymin": -4, "xmax": 4, "ymax": 4, "layer": "log_odds"}
    regions = [client.get(f"/maps/{m}/region", params=window).content for m in ("twice", "twice-copy")]
    assert regions[0] == regions[1]  # the snapshot's cells, not the robot's scan since
    conventions = (Path(__file__).resolve().parent.parent / "docs" / "api.md").read_text(encoding="utf-8")
    conventions = " ".join(conventions.split("## HTTP conventions", 1)[1].split("## Endpoints", 1)[0].split())
    assert "the same PUT twice changes nothing" not in conventions
    assert "sent again replaces the map again" in conventions


def test_a_scan_sent_with_a_condition_goes_only_into_the_map_of_it(client: httpx.Client) -> None:
    """`POST /maps/{map_id}/scans` writes a map too: a client that reads a map's `ETag` and sends its
    scans with `If-Match` must not see them go into another map made or restored under the id
    meanwhile. The headers were ignored (RFC 9110, 13.1.1: an origin server MUST evaluate them), so
    such a scan went into whatever map was there, or made one. Now 412 with the map's `ETag`,
    nothing counted or created; `If-None-Match: *` sends a scan only to a map that does not exist
    yet (it makes it)."""
    etag = fresh(client, "guarded")
    body = {**SCAN, "seq": 1}

    def post(map_id: str, headers: dict[str, str]) -> httpx.Response:
        return client.post(f"/maps/{map_id}/scans", params={"robot_id": "r"}, json=body, headers=headers)

    r = post("guarded", {"If-Match": etag})
    assert r.status_code == 200 and r.json()["status"] == "integrated", r.text
    assert_refused(post("guarded", {"If-Match": '"map-1"'}))
    refused = post("guarded", {"If-None-Match": "*"})
    assert "exists" in assert_refused(refused) and refused.headers["etag"] == etag
    stats = client.get("/maps/guarded").json()["stats"]
    robot = stats["robots"]["r"]
    assert (stats["scans_integrated"], stats["scans_rejected"], robot["duplicates"]) == (1, 0, 0), stats
    client.delete("/maps/guarded-new")
    assert_refused(post("guarded-new", {"If-Match": etag}))  # it would make a map: not the one read
    assert client.get("/maps/guarded-new").status_code == 404
    made = post("guarded-new", {"If-None-Match": "*"})
    assert made.status_code == 200 and made.json()["status"] == "integrated", made.text
    assert_refused(post("guarded", {"If-Match": "map-1"}), 422)  # not a quoted tag


def race(writers: list[Callable[[], httpx.Response]]) -> list[int]:
    """Run `writers` at once (each on its thread, released together) and return their statuses."""
    barrier = threading.Barrier(len(writers))
    statuses: list[int] = [0] * len(writers)

    def run(k: int) -> None:
        barrier.wait()
        statuses[k] = writers[k]().status_code

    threads = [threading.Thread(target=run, args=(k,)) for k in range(len(writers))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    return statuses


def test_two_writers_with_one_tag_exactly_one_wins(service: ServiceProcess) -> None:
    """Two operators read the same map and write with its tag at once (or both create it): the
    condition is checked where the write takes effect, so exactly one wins and the other gets 412,
    for uploads, for creates, and for a delete racing an upload. Two deletes: one deletes, the other
    finds no map (404, as without a condition: RFC 9110, 13.2.1). Each race on a fresh map, twice."""
    zipped = {"content-type": "application/zip"}
    with httpx.Client(base_url=service.base_url, timeout=120) as setup:
        fresh(setup, "race-src")
        scan(setup, "race-src", "r", 1)
        snapshot = setup.get("/maps/race-src/snapshot").content
        a, b = (httpx.Client(base_url=service.base_url, timeout=120) for _ in range(2))
        try:
            for _ in range(2):
                etag = fresh(setup, "race")
                uploads = race([
                    lambda c=c, t=etag: c.put("/maps/race/snapshot", content=snapshot,
                                              headers={**zipped, "If-Match": t})
                    for c in (a, b)
                ])  # fmt: skip
                assert sorted(uploads) == [200, 412], uploads
                setup.delete("/maps/race")
                creates = race([
                    lambda c=c: c.put("/maps/race", json={"resolution": 0.05}, headers={"If-None-Match": "*"})
                    for c in (a, b)
                ])  # fmt: skip
                assert sorted(creates) == [201, 412], creates
                etag = setup.get("/maps/race").headers["etag"]
                mixed = race([
                    lambda t=etag: a.delete("/maps/race", headers={"If-Match": t}),
                    lambda t=etag: b.put("/maps/race/snapshot", content=snapshot,
                                         headers={**zipped, "If-Match": t}),
                ])  # fmt: skip
                assert sorted(mixed) in ([200, 412], [204, 412]), mixed
                assert (setup.get("/maps/race").status_code == 404) == (mixed[0] == 204)
                etag = fresh(setup, "race")
                deletes = race(
                    [lambda c=c, t=etag: c.delete("/maps/race", headers={"If-Match": t}) for c in (a, b)]
                )
                assert sorted(deletes) == [204, 404], deletes
        finally:
            a.close()
            b.close()


def test_writes_without_conditions_are_as_before(client: httpx.Client) -> None:
    """No header, no change of behaviour: PUT finds or creates, DELETE deletes whatever map is there."""
    etag = fresh(client, "plain")
    assert client.put("/maps/plain", json={"resolution": 0.05}).status_code == 200
    assert client.delete("/maps/plain").status_code == 204
    assert client.put("/maps/plain", json={}).headers["etag"] != etag
    assert client.delete("/maps/plain").status_code == 204
    assert client.delete("/maps/plain").status_code == 404


def test_authentication_comes_before_the_conditions(tmp_path: Path) -> None:
    """401 and 403 come before anything about the conditions (a malformed one's 422, a failed one's
    412): a client without the right token learns nothing of the map, not even whether it exists
    or what its tag is (a 412 carries the map's ETag)."""
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    args = ["--in-memory", "--auth-tokens", str(tokens), "--require-read-token"]
    with ServiceProcess(tmp_path, args) as svc, httpx.Client(base_url=svc.base_url) as c:
        assert c.put("/maps/m", json={}, headers=bearer(WRITE)).status_code == 201
        upload = {"content": b"PK", "headers": {"content-type": "application/zip"}}
        writes = [("PUT", "/maps/m", {"json": {}}), ("DELETE", "/maps/m", {}),
                  ("PUT", "/maps/m/snapshot", upload), ("PUT", "/maps/m/import", upload)]  # fmt: skip
        for method, path, kwargs in writes:
            for condition in ({"If-Match": '"map-1"'}, {"If-None-Match": "*"}, {"If-Match": "map-1"}):
                for token, status in ((None, 401), ("wrong-token-0123456789", 401), (READ, 403)):
                    headers = {**kwargs.get("headers", {}), **condition, **(bearer(token) if token else {})}
                    r = c.request(method, path, **{**kwargs, "headers": headers})
                    assert_refused(r, status)
                    assert "etag" not in r.headers, (method, path, condition, r.headers)
        # With the write token the conditions are checked: the map is still there, untouched.
        r = c.delete("/maps/m", headers={"If-Match": '"map-1"', **bearer(WRITE)})
        assert_refused(r, 412)
        assert r.headers["etag"] == c.get("/maps/m", headers=bearer(READ)).headers["etag"]
