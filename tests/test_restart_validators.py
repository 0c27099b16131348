"""What a client cached before the service restarted must not pass for current after it.

Found by the chaos run (scripts/chaos_service.py), which deletes and re-creates maps and restarts the
service on its data directory while clients revalidate tiles with `If-None-Match`. A tile's ETag
named the map's generation, a counter each process started at 1: a map deleted and created again
under its id before a restart could come back with the generation and tile versions the old map had,
and a browser revalidating its cached tile of the OLD map got 304 and kept showing it.
"""

from __future__ import annotations

import json
from pathlib import Path

import httpx
from service_process import ServiceProcess
from test_api_support import fan_scan

from fleetmap.codec import encode_json
from fleetmap.wire import JSON_ENCODING

TILE = "/maps/m/tiles/0/0/-1.png"


def post_scan(base: str, ranges: list[float | None], seq: int = 0) -> None:
    """One scan of map `m` (robot `r`) from near the origin, integrated when this returns."""
    body = encode_json(fan_scan(0.5, 0.5, 0.0, ranges, range_max=3.0), seq)
    headers = {"content-type": JSON_ENCODING}
    r = httpx.post(f"{base}/maps/m/scans", params={"robot_id": "r"}, content=body, headers=headers)
    assert r.status_code == 200, r.text


def test_a_tile_cached_from_a_deleted_map_is_not_revalidated_after_a_restart(tmp_path: Path) -> None:
    data = ["--data-dir", str(tmp_path / "data")]
    with ServiceProcess(tmp_path, data) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        post_scan(svc.base_url, [1.0] * 31)
        old = httpx.get(svc.base_url + TILE)
        assert old.status_code == 200 and old.headers["etag"]
        # The same id, another map: the same number of changes, so the same tile versions.
        assert httpx.delete(f"{svc.base_url}/maps/m").status_code == 204
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        post_scan(svc.base_url, [2.0] * 31)
        assert httpx.get(svc.base_url + TILE).content != old.content
    with ServiceProcess(tmp_path, data) as svc:
        now = httpx.get(svc.base_url + TILE)
        assert now.status_code == 200 and now.content != old.content
        again = httpx.get(svc.base_url + TILE, headers={"If-None-Match": old.headers["etag"]})
        assert again.status_code == 200, "the old map's tile revalidated as current"
        assert again.content == now.content


def first_tiles_event(base: str, last_event_id: str) -> dict:
    """The first `tiles` event of map `m`'s stream resumed from `last_event_id`."""
    with httpx.stream("GET", f"{base}/maps/m/events", headers={"Last-Event-ID": last_event_id}) as r:
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "tiles":
                return json.loads(line[6:])
    raise AssertionError("the stream ended without a tiles event")


def test_an_event_id_from_before_a_restart_resumes_with_a_reset(tmp_path: Path) -> None:
    """An EventSource reconnecting after the service restarted sends the last id it got from the old
    process. Change versions counted from 0 again in the new one: once it had made as many changes,
    the old id looked current, and the client was sent only the changes after it in the NEW
    numbering, missing the first ones (their tiles stayed stale). It must get a reset."""
    data = ["--data-dir", str(tmp_path / "data")]
    with ServiceProcess(tmp_path, data) as svc:
        assert httpx.put(f"{svc.base_url}/maps/m", json={}).status_code == 201
        post_scan(svc.base_url, [1.0] * 31)
        old_version = httpx.get(f"{svc.base_url}/maps/m").json()["stats"]["version"]
    with ServiceProcess(tmp_path, data) as svc:
        post_scan(svc.base_url, [2.0] * 31, seq=1)
        post_scan(svc.base_url, [2.5] * 31, seq=2)
        event = first_tiles_event(svc.base_url, str(old_version))
        assert event.get("reset") is True, event
