"""A fleet's life over time, with the real service as a process and robots as real Zenoh sessions:
robots that restart (and lose their first scan doing so), copies and stale scans, and the service
restarting under robots that keep publishing."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from service_process import ServiceProcess, wait_for

from fleetmap import codec
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING, SCAN_KEY


def scan_at(x: float) -> Scan:
    """A small fan of returns 3 m ahead of a sensor at (x, 0)."""
    return Scan.from_fan((x, 0.0, 0.0), -0.5, 0.01, np.full(100, 3.0), 0.05, 30.0)


def robot_stats(http: httpx.Client, map_id: str, robot_id: str) -> dict[str, Any]:
    answer = http.get(f"/maps/{map_id}")
    if answer.status_code == 404:
        return {}
    return answer.json()["stats"]["robots"].get(robot_id, {})


def wait_integrated(http: httpx.Client, map_id: str, robot_id: str, count: int) -> dict[str, Any]:
    return wait_for(
        lambda: (s := robot_stats(http, map_id, robot_id)).get("scans_integrated") == count and s,
        timeout=20, what=f"{count} scans of {map_id}/{robot_id} integrated",
    )  # fmt: skip


def counters(stats: dict[str, Any]) -> tuple[int, int, int, int, int]:
    """(scans_integrated, last_seq, lost, duplicates, restarts)."""
    return tuple(stats[k] for k in ("scans_integrated", "last_seq", "lost", "duplicates", "restarts"))  # type: ignore[return-value]


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One in-memory service for the tests that do not restart it; each uses its own map ids."""
    svc = ServiceProcess(tmp_path_factory.mktemp("service"), ["--in-memory"])
    svc.start()
    yield svc
    svc.stop()


@pytest.fixture
def http(service: ServiceProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=service.base_url, timeout=10.0) as client:
        yield client


def test_a_restarted_robot_whose_first_scan_was_lost_is_integrated_again(
    service: ServiceProcess, http: httpx.Client
) -> None:
    """A robot process that crashes starts counting from 0 again, but its seq 0 is easily lost (it
    was published before the new session reached the service; some robots count from 1). Its scans
    were then ignored as duplicates until the new seqs passed the old ones (9 of 9 here, for hours
    on a robot that had run for a day). Its stamps go on, which tells a restart from a copy."""
    with ScanPublisher("life-restart", "r", connect=service.zenoh_endpoint) as before:
        assert before.wait_connected(15)
        for k in range(5):
            assert before.publish(scan_at(0.1 * k))
    wait_integrated(http, "life-restart", "r", 5)
    with ScanPublisher("life-restart", "r", connect=service.zenoh_endpoint) as after:
        assert after.wait_connected(15)
        for k in range(1, 4):  # seq 0 of the new run never arrived
            assert after.publish(scan_at(1.0 + 0.1 * k), seq=k)
    stats = wait_integrated(http, "life-restart", "r", 8)
    assert counters(stats) == (8, 3, 1, 0, 1)  # the new run's seq 0 counts as lost
    assert stats["last_pose"]["x"] == pytest.approx(1.3)


def test_copies_and_stale_scans_are_duplicates_even_at_seq_0(
    service: ServiceProcess, http: httpx.Client
) -> None:
    """Seq 0 used to be a restart whatever it carried, so a copy of a robot's first scan (a retry,
    a second sender of the same recording) was integrated twice and moved the sequence back. Now a
    scan whose seq is not new is a restart only with a later stamp, or at seq 0 when it is not the
    very scan last accepted: robots that send no stamp (0), or stamps of a clock that starts again
    with the robot, still restart at seq 0."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([service.zenoh_endpoint]))
    session = zenoh.open(cfg)
    try:
        pubs = {
            robot: session.declare_publisher(
                SCAN_KEY.format(map_id="life-copies", robot_id=robot),
                encoding=zenoh.Encoding(BINARY_ENCODING),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for robot in ("stamped", "unstamped")
        }
        for pub in pubs.values():
            wait_for(lambda p=pub: p.matching_status.matching, timeout=10, interval=0.01, what="the service")
        # (seq, stamp): a copy of seq 0 at once, and a stale copy of seq 1 after seq 2.
        for seq, stamp in [(0, 100.0), (0, 100.0), (1, 101.0), (2, 102.0), (1, 101.0), (3, 103.0)]:
            pubs["stamped"].put(codec.encode_binary(scan_at(float(seq)), seq, stamp))
        # No stamps: seq 0 after seq 2 is a restart, as it always was.
        for seq in [0, 1, 2, 0, 1]:
            pubs["unstamped"].put(codec.encode_binary(scan_at(float(seq)), seq))
        # Copies are counted when they arrive, before the last scan is integrated.
        stamped = wait_integrated(http, "life-copies", "stamped", 4)
        assert counters(stamped) == (4, 3, 0, 2, 0)
        assert stamped["last_stamp"] == 103.0
        assert counters(wait_integrated(http, "life-copies", "unstamped", 5)) == (5, 1, 0, 0, 1)
    finally:
        session.close()


def test_robots_outlive_a_service_restart_and_a_robot_restart_after_it(tmp_path: Path) -> None:
    """The service restarts (SIGTERM, durable storage) under a robot that keeps its session: the
    robot reconnects by itself, shows online again, continues its sequence with nothing counted as
    lost or duplicate. Then the robot restarts without its seq 0: its scans are integrated, which
    needs the last stamp to survive the service's restart (it was not kept in the snapshot)."""
    svc = ServiceProcess(tmp_path)
    svc.start()
    try:
        with httpx.Client(base_url=svc.base_url, timeout=10.0) as http:
            with ScanPublisher("life-svc", "r", connect=svc.zenoh_endpoint) as robot:
                assert robot.wait_connected(15)
                for k in range(3):
                    assert robot.publish(scan_at(0.1 * k))
                wait_integrated(http, "life-svc", "r", 3)
                assert svc.stop() == 0
                svc.start()  # same ports, same data directory
                assert robot.wait_connected(20)  # Zenoh reconnected by itself
                wait_for(lambda: robot_stats(http, "life-svc", "r").get("online"), timeout=15, what="online")
                for k in range(3, 5):
                    assert robot.publish(scan_at(0.1 * k))
                assert counters(wait_integrated(http, "life-svc", "r", 5)) == (5, 4, 0, 0, 0)
            assert svc.stop() == 0
            svc.start()
            with ScanPublisher("life-svc", "r", connect=svc.zenoh_endpoint) as restarted:
                assert restarted.wait_connected(15)
                for k in range(1, 3):
                    assert restarted.publish(scan_at(1.0 + 0.1 * k), seq=k)
            assert counters(wait_integrated(http, "life-svc", "r", 7)) == (7, 2, 1, 0, 1)
    finally:
        svc.stop()
