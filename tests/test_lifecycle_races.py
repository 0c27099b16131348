"""Map writes racing everything else, against the real service: robots publishing over Zenoh and
scans over HTTP into a map that is meanwhile deleted, created again, replaced by a snapshot upload
and by a nav2 import (with and without `If-Match`), while readers (region, tile, cells, raycast,
export, snapshot download, event streams) follow it and snapshots run every half second; then a
SIGKILL and a restart.

Invariants: no 5xx answer and no traceback in the service's log; of two conditional writes sent
with one tag at once, at most one wins; an event stream only ever ends with `deleted`; after the
kill, the restarted service holds exactly the maps it held (none resurrected, none lost), each cell
for cell as before the kill, with the same counters. The snapshot races of `test_registry.py`
(`test_a_snapshot_pass_never_stores_...`, `test_a_map_created_again_right_after_...`) broke the last
one; they force their interleavings in-process, while this test runs them as they come.
"""

from __future__ import annotations

import io
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
from service_process import RobotProcess, ServiceProcess, wait_for
from test_api_conditional import nav2_zip

from fleetmap.codec import encode_json
from fleetmap.scan import Scan

HOT = "hot"  # the map every write goes to
BIG = "big"  # many tiles: each snapshot pass takes a while, in which the hot map changes
#: Seconds of hammering: short, the machine has 2 cores shared with other tests.
SECONDS = 4.0
ZIPPED = {"content-type": "application/zip"}
#: Answers a racing request may get: the map went (404), was replaced under it (409), or a
#: condition failed (412); 503 only for an event stream past its cap (not reached here).
EXPECTED = {200, 201, 204, 304, 404, 409, 412}


def fan(x: float, y: float, reach: float = 20.0, beams: int = 181) -> Scan:
    return Scan.from_fan((x, y, 0.0), -3.1, 6.2 / beams, [reach] * beams, 0.0, 30.0)


class Hammer:
    """Runs request loops on threads until `SECONDS` are up; records every unexpected answer."""

    def __init__(self, base: str) -> None:
        self.base = base
        self.deadline = time.monotonic() + SECONDS
        self.problems: list[str] = []
        self.counts: dict[str, int] = {}
        self.lock = threading.Lock()
        self.threads: list[threading.Thread] = []

    def running(self) -> bool:
        return time.monotonic() < self.deadline

    def seen(self, what: str, r: httpx.Response, allowed: set[int] = EXPECTED) -> httpx.Response:
        with self.lock:
            key = f"{what} {r.status_code}"
            self.counts[key] = self.counts.get(key, 0) + 1
            if r.status_code not in allowed:
                self.problems.append(f"{what}: {r.status_code} {r.text[:300]}")
        return r

    def loop(self, body: Callable[[httpx.Client], None]) -> None:
        def run() -> None:
            with httpx.Client(base_url=self.base, timeout=60) as client:
                while self.running():
                    body(client)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        self.threads.append(thread)

    def join(self) -> None:
        for thread in self.threads:
            thread.join(120)
            assert not thread.is_alive(), "a request loop hangs"


def map_state(base: str) -> dict[str, dict]:
    """Every map the service holds: its counters, tiles and every layer's cells over its bounds."""
    out: dict[str, dict] = {}
    for summary in httpx.get(f"{base}/maps", timeout=30).json()["maps"]:
        map_id = summary["id"]
        info = httpx.get(f"{base}/maps/{map_id}", timeout=30).json()
        stats = info["stats"]
        robots = {rid: r["scans_integrated"] for rid, r in stats["robots"].items()}
        state = {
            "config": info["config"],
            "scans": stats["scans_integrated"],
            "tiles": stats["tiles"],
            "bounds": stats["bounds"],
            "robots": robots,
        }
        if stats["bounds"] is not None:
            xmin, ymin, xmax, ymax = stats["bounds"]
            for layer in ("log_odds", "hits", "misses"):
                r = httpx.get(
                    f"{base}/maps/{map_id}/region",
                    params={"xmin": xmin, "ymin": ymin, "xmax": xmax, "ymax": ymax, "layer": layer,
                            "format": "npy"},
                    timeout=30,
                )  # fmt: skip
                if r.status_code == 422:  # a layer this map does not keep (a nav2 import's)
                    continue
                r.raise_for_status()
                state[layer] = np.load(io.BytesIO(r.content)).tobytes()
        out[map_id] = state
    return out


def test_map_writes_racing_scans_reads_and_snapshots_then_a_kill(tmp_path: Path) -> None:
    data = tmp_path / "data"
    args = ["--data-dir", str(data), "--snapshot-interval", "0.5"]
    svc = ServiceProcess(tmp_path, args).start()
    try:
        base = svc.base_url
        with httpx.Client(base_url=base, timeout=60) as setup:
            # The big map: dozens of tiles, so a snapshot pass that stores it takes a while.
            assert setup.put(f"/maps/{BIG}", json={}).status_code == 201
            for k in range(6):
                scan = json.loads(encode_json(fan(25.0 * k, 0.0, reach=29.0), k))
                assert (
                    setup.post(f"/maps/{BIG}/scans", params={"robot_id": "b"}, json=scan).status_code == 200
                )
            assert setup.put(f"/maps/{HOT}", json={}).status_code == 201
            scan = json.loads(encode_json(fan(0.0, 0.0), 0))
            assert setup.post(f"/maps/{HOT}/scans", params={"robot_id": "h"}, json=scan).status_code == 200
            snapshot = setup.get(f"/maps/{HOT}/snapshot").content
        nav2 = nav2_zip()
        robots = [
            RobotProcess(svc.zenoh_endpoint, HOT, f"z{k}", sim=k + 1, count=int(SECONDS * 25), rate=25,
                         log_dir=tmp_path).start()
            for k in range(2)
        ]  # fmt: skip
        hammer = Hammer(base)
        seqs = iter(range(1, 1_000_000))
        tag_wins: list[tuple[int, int]] = []

        def big_scans(c: httpx.Client) -> None:  # keeps the big map changing: snapshotted every pass
            seq = next(seqs)
            scan = json.loads(encode_json(fan(25.0 * (seq % 6), 0.5, reach=29.0), seq))
            hammer.seen("big scan", c.post(f"/maps/{BIG}/scans", params={"robot_id": "b"}, json=scan))

        def hot_scans(c: httpx.Client) -> None:
            seq = next(seqs)
            scan = json.loads(encode_json(fan(0.3 * (seq % 40), -5.0), seq))
            hammer.seen("hot scan", c.post(f"/maps/{HOT}/scans", params={"robot_id": "h"}, json=scan))

        def writes(c: httpx.Client) -> None:
            hammer.seen("delete", c.delete(f"/maps/{HOT}"))
            hammer.seen("put", c.put(f"/maps/{HOT}", json={}))
            hammer.seen("upload", c.put(f"/maps/{HOT}/snapshot", content=snapshot, headers=ZIPPED))
            time.sleep(0.05)
            hammer.seen("import", c.put(f"/maps/{HOT}/import", content=nav2, headers=ZIPPED))
            time.sleep(0.05)

        def tagged_writes(c: httpx.Client) -> None:
            # Two writers with one tag at once: at most one may win.
            etag = c.get(f"/maps/{HOT}").headers.get("etag")
            if etag is None:
                hammer.seen("put", c.put(f"/maps/{HOT}", json={}, headers={"If-None-Match": "*"}))
                return
            answers: list[int] = []
            with httpx.Client(base_url=base, timeout=60) as other:
                go = threading.Barrier(2)

                def upload() -> None:
                    go.wait()
                    r = other.put(
                        f"/maps/{HOT}/snapshot", content=snapshot, headers={**ZIPPED, "If-Match": etag}
                    )
                    answers.append(hammer.seen("tagged upload", r).status_code)

                racer = threading.Thread(target=upload)
                racer.start()
                go.wait()
                answers.append(
                    hammer.seen(
                        "tagged delete", c.delete(f"/maps/{HOT}", headers={"If-Match": etag})
                    ).status_code
                )
                racer.join(60)
            tag_wins.append((sum(1 for s in answers if s in (200, 201, 204)), len(answers)))

        def reads(c: httpx.Client) -> None:
            for path, params in (
                ("region", {"xmin": -5, "ymin": -5, "xmax": 5, "ymax": 5, "format": "npy"}),
                ("cell", {"x": 0.5, "y": 0.5}),
                ("tiles/0/0/-1.png", {}),
                ("export", {"format": "png"}),
            ):
                hammer.seen(f"read {path}", c.get(f"/maps/{HOT}/{path}", params=params))
            hammer.seen("cells", c.post(f"/maps/{HOT}/cells", json={"points": [[0.1, 0.2], [3.0, -1.0]]}))
            hammer.seen(
                "raycast",
                c.post(
                    f"/maps/{HOT}/raycast", json={"origin": [0, 0], "angles": [0.0, 1.5], "max_range": 10.0}
                ),
            )
            hammer.seen("snapshot", c.get(f"/maps/{HOT}/snapshot"))

        def events(c: httpx.Client) -> None:
            try:
                with c.stream("GET", f"/maps/{HOT}/events", timeout=5) as r:
                    hammer.seen("events", r)
                    if r.status_code != 200:
                        return
                    kinds = []
                    for line in r.iter_lines():
                        if line.startswith("event: "):
                            kinds.append(line[7:])
                            if kinds[-1] == "deleted":
                                return
                        if not hammer.running():
                            return
            except httpx.ReadTimeout:  # the map stayed quiet: fine
                pass

        for body in (big_scans, hot_scans, writes, tagged_writes, reads, reads, events, events):
            hammer.loop(body)
        hammer.join()
        for robot in robots:
            robot.proc.wait(60)  # type: ignore[union-attr]
        assert not hammer.problems, (hammer.problems[:10], hammer.counts)
        assert tag_wins and all(won <= 1 for won, _ in tag_wins), tag_wins
        # Quiet now: every scan answered, its journal row committed; then a snapshot pass or two.
        wait_for(
            lambda: "fleetmap_queue_depth 0.0" in httpx.get(f"{base}/metrics", timeout=10).text,
            what="the ingest queue drained",
        )
        time.sleep(1.5)
        before = map_state(base)
        assert BIG in before
        log = svc.logs()
        assert "Traceback" not in log, log[-3000:]
        svc.proc.kill()  # type: ignore[union-attr]
        svc.proc.wait()  # type: ignore[union-attr]
    finally:
        svc.stop()
    restarted = ServiceProcess(tmp_path, args).start()
    try:
        after = map_state(restarted.base_url)
    finally:
        restarted.stop()
    assert set(after) == set(before)  # none resurrected, none lost
    for map_id in before:
        assert after[map_id] == before[map_id], map_id
