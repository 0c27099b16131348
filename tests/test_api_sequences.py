"""Sequences of requests against the real service whose answers must stay right across them: a
client coming back after its map changed under it, a write racing another writer's.
"""

from __future__ import annotations

import io
import json
import threading
import time
import zipfile
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from PIL import Image
from service_process import ServiceProcess

from fleetmap.codec import encode_json
from fleetmap.scan import Scan

JSON = {"content-type": "application/json"}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One service (default options) for the module's tests, in place of conftest's one per test:
    each works on maps of its own (ids no other test here uses) and none stops or reconfigures it."""
    with ServiceProcess(tmp_path_factory.mktemp("api-sequences")) as svc:
        yield svc


def post_scan(client: httpx.Client, map_id: str, robot: str, seq: int, x: float, y: float) -> None:
    scan = Scan.from_fan((x, y, 0.0), -1.5, 0.05, [1.0] * 61, 0.0, 30.0)
    r = client.post(
        f"/maps/{map_id}/scans", params={"robot_id": robot}, content=encode_json(scan, seq), headers=JSON
    )
    assert r.status_code == 200 and r.json()["status"] == "integrated", r.text


def first_tiles_event(client: httpx.Client, map_id: str, last_event_id: int) -> dict:
    """The data of the first `tiles` event of a stream resumed with `Last-Event-ID`."""
    headers = {"Last-Event-ID": str(last_event_id)}
    with client.stream("GET", f"/maps/{map_id}/events", headers=headers, timeout=10) as r:
        assert r.status_code == 200
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line.removeprefix("event: ")
            elif line.startswith("data: ") and kind == "tiles":
                return json.loads(line.removeprefix("data: "))
    raise AssertionError("the stream ended without a tiles event")


def test_a_stream_resumed_after_its_map_was_made_again_is_reset(service: ServiceProcess) -> None:
    """docs/api.md, events: a client resuming with an event id of an earlier map of the id gets a
    reset, never the new map's changes after that number. Versions counted on from the service's
    start, so a map made again after its predecessor's 20 changes began below the old map's last id,
    and a resume with that id, once the new map had changed more, got only its latest tiles: the
    viewer kept the old map's tiles everywhere else."""
    with httpx.Client(base_url=service.base_url, timeout=30) as c:
        assert c.put("/maps/m", json={"tile_size": 16}).status_code == 201
        for seq in range(1, 21):
            post_scan(c, "m", "a", seq, 0.2 * seq, 0.0)
        old_last = c.get("/maps/m").json()["stats"]["version"]  # the id a viewer of it last got
        assert c.delete("/maps/m").status_code == 204
        assert c.put("/maps/m", json={"tile_size": 16}).status_code == 201
        for seq in range(1, 41):
            post_scan(c, "m", "b", seq, -10.0 if seq == 1 else 5.0, -10.0 if seq == 1 else 5.0)
        event = first_tiles_event(c, "m", old_last)
        assert event.get("reset") is True, event


def nav2_zip_of(side: int) -> bytes:
    """A nav2 map of `side` x `side` pixels at 0.05 m, free with a wall every 50 rows: big enough
    that the service takes a second or more to read it."""
    pixels = np.full((side, side), 254, np.uint8)
    pixels[::50] = 0
    image = io.BytesIO()
    Image.fromarray(pixels).save(image, format="PNG")
    body = io.BytesIO()
    with zipfile.ZipFile(body, "w") as zf:
        zf.writestr("m.yaml", "image: m.png\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
                    "occupied_thresh: 0.65\nfree_thresh: 0.25\n")  # fmt: skip
        zf.writestr("m.png", image.getvalue())
    return body.getvalue()


def test_an_import_read_while_its_map_was_made_again_changes_nothing(service: ServiceProcess) -> None:
    """A nav2 import takes the configuration of the map it replaces, and is refused (422) at another
    resolution. Read with the configuration of the map there when its body was in, it replaced the
    map another writer made meanwhile at 0.1 m with a 0.05 m map, answering 200: a map of a
    configuration no longer there, where the import sent after that writer is refused. Now 409,
    nothing changed; sent again, it meets the 0.1 m map (422)."""
    body = nav2_zip_of(6000)  # about 2 s to read on a shared 2-core machine
    zipped = {"content-type": "application/zip"}
    with httpx.Client(base_url=service.base_url, timeout=60) as c:
        assert c.put("/maps/imp", json={"resolution": 0.05, "max_tiles": 8192}).status_code == 201
        answers: list[httpx.Response] = []
        upload = threading.Thread(
            target=lambda: answers.append(c.put("/maps/imp/import", content=body, headers=zipped))
        )
        upload.start()
        time.sleep(0.4)  # its body (49 kB) is in, its image being read
        assert c.delete("/maps/imp").status_code == 204
        assert c.put("/maps/imp", json={"resolution": 0.1, "max_tiles": 8192}).status_code == 201
        upload.join(60)
        assert answers[0].status_code == 409, answers[0].text
        assert c.get("/maps/imp").json()["resolution"] == 0.1
        again = c.put("/maps/imp/import", content=body, headers=zipped)
        assert again.status_code == 422 and "resolution" in again.text, again.text


def test_a_tile_revalidated_with_its_tag_on_a_second_field_line_is_not_modified(
    service: ServiceProcess,
) -> None:
    """`If-None-Match` sent on two field lines is one list (RFC 9110, 5.3), as a proxy merging a
    client's tags may send it: the tile's tag on the second line is a 304, as on the first. The
    tile route read the first line alone and sent the whole tile again."""
    with httpx.Client(base_url=service.base_url, timeout=30) as c:
        post_scan(c, "t", "r", 1, 0.5, 0.5)
        etag = c.get("/maps/t/tiles/0/0/-1.png").headers["etag"]
        for method in ("GET", "HEAD"):
            r = c.request(
                method,
                "/maps/t/tiles/0/0/-1.png",
                headers=[("If-None-Match", '"other"'), ("If-None-Match", etag)],
            )
            assert r.status_code == 304 and r.headers["etag"] == etag, (method, r.status_code)


def test_a_window_of_any_size_is_cleared(service: ServiceProcess) -> None:
    """docs/api.md: `DELETE .../region`'s window may be of any size, only the stored tiles being
    visited. "Everything", 10 000 km each way, on a 5 mm map is 4e9 cells a side, 1.6e19 in all:
    past an int64, it was refused with 413 ("ask for smaller windows"), a status the route does not
    declare, and nothing was cleared."""
    with httpx.Client(base_url=service.base_url, timeout=30) as c:
        assert c.put("/maps/fine", json={"resolution": 0.005}).status_code == 201
        post_scan(c, "fine", "r", 1, 0.1, 0.1)
        assert c.get("/maps/fine").json()["stats"]["bounds"] is not None
        everything = {"xmin": -1e7, "ymin": -1e7, "xmax": 1e7, "ymax": 1e7}
        r = c.delete("/maps/fine/region", params=everything)
        assert r.status_code == 200 and r.json()["cells_cleared"] > 0, r.text
        assert c.get("/maps/fine").json()["stats"]["bounds"] is None


def resume_position(client: httpx.Client, map_id: str) -> str | None:
    """Open `map_id`'s event stream as an EventSource would, read what it sends on connect (up to its
    first `robots` event), leave, and return the last event id the EventSource then holds: what it
    sends back as `Last-Event-ID` when it reconnects (None: it sends none, and the stream starts from
    now). Follows the HTML rules: an `id:` line sets the id even in a block without data."""
    last_id: str | None = None
    with client.stream("GET", f"/maps/{map_id}/events", timeout=10) as r:
        assert r.status_code == 200
        kind = ""
        for line in r.iter_lines():
            if line.startswith("id: "):
                last_id = line.removeprefix("id: ")
            elif line.startswith("event: "):
                kind = line.removeprefix("event: ")
            elif line == "" and kind == "robots":
                return last_id
    raise AssertionError("the stream ended before its first robots event")


def test_a_stream_left_before_any_change_resumes_without_a_gap(service: ServiceProcess) -> None:
    """docs/api.md, events: a reconnecting EventSource sends the last id as `Last-Event-ID` and gets
    the changes since. A stream gave ids only with `tiles` events, so a viewer whose connection
    dropped before the map first changed under it (a quiet map, a proxy closing idle streams) held
    no id: it reconnected without one, the stream started from then, and the tiles changed while it
    was away were never announced (its tiles stayed stale for good)."""
    with httpx.Client(base_url=service.base_url, timeout=30) as c:
        assert c.put("/maps/quiet", json={"tile_size": 16}).status_code == 201
        last_id = resume_position(c, "quiet")
        # Away: the map changes.
        scan = Scan.from_fan((0.3, 0.1, 0.0), -1.5, 0.05, [1.0] * 61, 0.0, 30.0)
        r = c.post("/maps/quiet/scans", params={"robot_id": "a"}, content=encode_json(scan, 1), headers=JSON)
        assert r.status_code == 200 and r.json()["changed_tiles"], r.text
        changed = r.json()["changed_tiles"]
        assert last_id is not None, "the stream gave the client no event id to resume from"
        event = first_tiles_event(c, "quiet", int(last_id))
        assert "reset" not in event and all(w in event["tiles"] for w in changed), (event, changed)


def test_a_stream_resumed_from_long_ago_is_not_shared_with_streams_nearer_the_present(
    service: ServiceProcess,
) -> None:
    """docs/api.md, events: the streams of a map share their `tiles` events, so one may name "a few
    tiles the previous event named". A viewer resuming with an old `Last-Event-ID`, while the map's
    last shared event was older still (no stream had been in step since: a map followed live by a
    viewer that only opened after the last event), made an event of everything changed since its id
    and left it for the others to share: a viewer resuming from just before the latest scan was
    told of every tile changed since the first viewer's id too, and so was a live stream polling
    between them, and refetched them all."""
    with httpx.Client(base_url=service.base_url, timeout=30) as c:
        assert c.put("/maps/shared", json={"tile_size": 16}).status_code == 201
        long_ago = c.get("/maps/shared").json()["stats"]["version"]
        for seq in range(1, 4):  # away: three scans far from where the last one lands
            post_scan(c, "shared", "a", seq, -5.0 - seq, -5.0)
        just_before = c.get("/maps/shared").json()["stats"]["version"]
        scan = Scan.from_fan((5.0, 5.0, 0.0), -0.3, 0.05, [1.0] * 13, 0.0, 30.0)
        r = c.post("/maps/shared/scans", params={"robot_id": "a"}, content=encode_json(scan, 4), headers=JSON)
        assert r.status_code == 200 and r.json()["status"] == "integrated", r.text
        latest = sorted(r.json()["changed_tiles"])
        # A viewer follows the map live (its stream has polled once it sent the robots).
        with c.stream("GET", "/maps/shared/events", timeout=10) as live:
            lines = live.iter_lines()
            assert any(line == "event: robots" for line in lines)
            everything = first_tiles_event(c, "shared", long_ago)
            assert set(map(tuple, latest)) < set(map(tuple, everything["tiles"])), everything
            nearer = first_tiles_event(c, "shared", just_before)
        assert sorted(nearer["tiles"]) == latest, (len(nearer["tiles"]), len(latest))
