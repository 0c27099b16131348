"""Bounds that must hold over a service's long life, with the real service: what robots, maps and
clients that come and go leave behind must not grow without end, in memory or on disk, nor come back
after a restart."""

from __future__ import annotations

import json
import re
import sqlite3
import time
from pathlib import Path

import httpx
import zenoh
from prometheus_client.parser import text_string_to_metric_families
from service_process import ServiceProcess, wait_for

from fleetmap.database import DB_NAME


def _scan(seq: int = 0) -> dict:
    """A small JSON scan at the origin."""
    return {
        "seq": seq,
        "pose": {"x": 0.0, "y": 0.0, "theta": 0.0},
        "angle_min": -1.0,
        "angle_increment": 0.5,
        "range_max": 10.0,
        "ranges": [2.0] * 5,
    }


def _post_robots(svc: ServiceProcess, robot_ids: list[str]) -> None:
    for robot_id in robot_ids:
        url = f"{svc.base_url}/maps/m/scans"
        r = httpx.post(url, params={"robot_id": robot_id}, json=_scan(), timeout=30)
        assert r.status_code == 200, r.text


def _robots(svc: ServiceProcess) -> set[str]:
    return set(httpx.get(f"{svc.base_url}/maps/m", timeout=10).json()["stats"]["robots"])


def test_robots_a_full_map_forgot_are_not_stored_nor_back_after_a_restart(tmp_path: Path) -> None:
    """A map keeps at most --max-robots-per-map robots, forgetting the offline one heard from least
    recently for a new one. Robots that come and go under new ids (every day, for weeks) used to
    leave their rows in the database for good: the snapshot only added and updated rows, so after a
    restart the map held every robot id it had ever seen (58 with a cap of 8 in a probe), in GET
    /maps/{id}, /metrics and every robots event. Robots first heard since the last snapshot, replayed
    from the journal after a crash, also pushed the map past its cap."""
    data = tmp_path / "data"
    args = ["--data-dir", str(data), "--max-robots-per-map", "3"]
    with ServiceProcess(tmp_path, args) as svc:
        _post_robots(svc, ["a0", "a1", "a2"])
    with ServiceProcess(tmp_path, args) as svc:
        _post_robots(svc, ["b0", "b1", "b2"])  # each forgets an `a` robot
        assert _robots(svc) == {"b0", "b1", "b2"}
    # (stopped with SIGTERM: its final snapshot stores the robots the map holds, and only those)
    db = sqlite3.connect(data / DB_NAME)
    try:
        assert {row[0] for row in db.execute("SELECT robot_id FROM robots")} == {"b0", "b1", "b2"}
    finally:
        db.close()
    svc = ServiceProcess(tmp_path, args).start()
    try:
        assert _robots(svc) == {"b0", "b1", "b2"}
        _post_robots(svc, ["c0", "c1"])
    finally:
        svc.proc.kill()  # type: ignore[union-attr]  # no snapshot: c0 and c1 are in the journal only
        svc.stop()
    with ServiceProcess(tmp_path, args) as svc:
        # Replayed after the snapshot's robots, c0 and c1 were heard most recently; of the rest, b2.
        assert _robots(svc) == {"b2", "c0", "c1"}


def _memory_used(svc: ServiceProcess) -> float:
    metrics = httpx.get(f"{svc.base_url}/metrics", timeout=10).text
    found = re.search(r"^fleetmap_memory_used_bytes (\S+)$", metrics, re.MULTILINE)
    assert found is not None, metrics
    return float(found.group(1))


def test_a_map_deleted_after_a_viewer_showed_it_gives_its_memory_back(tmp_path: Path) -> None:
    """An event stream that ends because its client went away is cancelled, and the cancellation's
    traceback kept the stream's frame, with the map in its locals, in a reference cycle that only a
    full garbage collection frees; an idle service ran none within minutes. So a map deleted after
    a viewer had shown it kept its tiles in memory and charged to --max-memory (whose scans then got
    507), as long as no collection happened to come."""
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        _post_robots(svc, ["r"])
        assert _memory_used(svc) > 0
        with httpx.stream("GET", f"{svc.base_url}/maps/m/events", timeout=10) as stream:
            for line in stream.iter_lines():
                if line.startswith("event: robots"):
                    break
        time.sleep(0.5)  # the service sees the client go and ends the stream
        assert httpx.delete(f"{svc.base_url}/maps/m", timeout=10).status_code == 204
        # Looked at once: every scrape allocates, and enough of them bring on the collection.
        time.sleep(1.0)
        assert _memory_used(svc) == 0


def _robot_series(svc: ServiceProcess, family_name: str = "fleetmap_scans_integrated") -> dict[str, float]:
    """Robot id -> its sample of `family_name` on map m, as /metrics shows it now."""
    text = httpx.get(f"{svc.base_url}/metrics", timeout=10).text
    return {
        sample.labels["robot"]: sample.value
        for family in text_string_to_metric_families(text)
        if family.name == family_name
        for sample in family.samples
        if sample.labels.get("map") == "m"
    }


def test_robots_gone_a_while_leave_metrics_and_come_back_when_heard(tmp_path: Path) -> None:
    """A map forgets its robots only once it holds --max-robots-per-map (1024), so /metrics kept 8
    series for every robot id a map had ever heard (robots renamed, replaced, simulated, or ids made
    up by any Zenoh peer), growing every scrape by up to 8192 series a map, long after the robots
    were gone. A robot neither online nor heard for --metrics-robot-idle seconds now keeps only its
    online gauge (at 0, so that an alert on a robot gone goes on firing); the map still holds it,
    and its counters come back with its counts when it is heard."""
    idle = 4.0  # long enough for the posts and the scrape after them on a busy machine
    with ServiceProcess(tmp_path, ["--in-memory", "--metrics-robot-idle", str(idle)]) as svc:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", json.dumps([svc.zenoh_endpoint]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)
        try:
            # Online (its liveliness token alive) but silent: it stays, however long it is silent.
            token = session.liveliness().declare_token("fleetmap/m/present/alive")
            wait_for(lambda: "present" in _robot_series(svc), timeout=10, what="the online robot's series")
            _post_robots(svc, ["gone", "back"])
            assert _robot_series(svc) == {"gone": 1, "back": 1, "present": 0}
            time.sleep(idle + 0.5)
            assert _robot_series(svc) == {"present": 0}
            assert _robot_series(svc, "fleetmap_robot_online") == {"present": 1, "gone": 0, "back": 0}
            assert _robots(svc) == {"gone", "back", "present"}  # the map keeps them
            url = f"{svc.base_url}/maps/m/scans"
            r = httpx.post(url, params={"robot_id": "back"}, json=_scan(1), timeout=30)
            assert r.status_code == 200, r.text
            assert _robot_series(svc) == {"present": 0, "back": 2}
            token.undeclare()
        finally:
            session.close()
