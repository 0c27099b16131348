"""Sequences of requests against the real service whose answers must stay right across them: what a
client that comes back after a map changed under it is told.
"""

from __future__ import annotations

import json

import httpx
from service_process import ServiceProcess

from fleetmap.codec import encode_json
from fleetmap.scan import Scan

JSON = {"content-type": "application/json"}


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
