"""A fleet's life over time, with the real service as a process and robots as real Zenoh sessions:
robots that restart (and lose their first scan doing so, or restart their clock), copies and stale
scans, two robots under one robot id, and the service restarting under robots that keep publishing."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from prometheus_client.parser import text_string_to_metric_families
from service_process import ServiceProcess, wait_for

from fleetmap import codec
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING, SCAN_KEY, new_session_id


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


@contextlib.contextmanager
def raw_publishers(
    endpoint: str, map_id: str, robots: Sequence[str], encoding: str = BINARY_ENCODING
) -> Iterator[dict[str, zenoh.Publisher]]:
    """One Zenoh client session with a publisher of each robot's scans (matched by the service), for
    tests that write each message's fields (seq, stamp, session) themselves."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    session = zenoh.open(cfg)
    try:
        pubs = {
            robot: session.declare_publisher(
                SCAN_KEY.format(map_id=map_id, robot_id=robot),
                encoding=zenoh.Encoding(encoding),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for robot in robots
        }
        for pub in pubs.values():
            wait_for(lambda p=pub: p.matching_status.matching, timeout=10, interval=0.01, what="the service")
        yield pubs
    finally:
        session.close()


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
    with raw_publishers(service.zenoh_endpoint, "life-copies", ["stamped", "unstamped"]) as pubs:
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


def test_a_copy_from_before_a_robots_clock_stepped_back_is_a_duplicate(
    service: ServiceProcess, http: httpx.Client
) -> None:
    """A robot without session ids whose clock NTP steps back an hour mid-run: its seqs go on, so
    its scans are integrated. A copy of a scan from before the step (a retry, its cache fetched
    again) carries a stamp later than the last scan's: it was taken for a restart, integrated a
    second time, moved `last_seq` back and counted the seqs before it as lost. The run's latest
    stamp, not the last one's, tells a restart now; so does seq 0 of a real restart."""
    t0 = 1_800_000_000.0
    with raw_publishers(service.zenoh_endpoint, "life-ntp", ["r"]) as pubs:
        for seq in range(10):  # the clock steps back 3600 s between seq 4 and seq 5
            stamp = t0 + seq - (3600.0 if seq >= 5 else 0.0)
            pubs["r"].put(codec.encode_binary(scan_at(float(seq)), seq, stamp))
        wait_integrated(http, "life-ntp", "r", 10)
        for seq in (2, 0):  # late copies from before the step
            pubs["r"].put(codec.encode_binary(scan_at(float(seq)), seq, t0 + seq))
        pubs["r"].put(codec.encode_binary(scan_at(10.0), 10, t0 - 3600.0 + 10))
        stats = wait_for(
            lambda: (s := robot_stats(http, "life-ntp", "r")).get("scans_integrated", 0) >= 11 and s,
            timeout=20, what="seq 10 integrated",
        )  # fmt: skip
        assert counters(stats) == (11, 10, 0, 2, 0)  # was (13, 10, 11, 0, 2): both copies integrated
        pubs["r"].put(codec.encode_binary(scan_at(0.5), 0, t0 - 3000.0))  # a real restart: seq 0
        stats = wait_integrated(http, "life-ntp", "r", 12)
    assert counters(stats) == (12, 0, 0, 2, 1)


def test_robots_outlive_a_service_restart_and_a_robot_restart_after_it(tmp_path: Path) -> None:
    """The service restarts (SIGTERM, durable storage) under a robot that keeps its session: the
    robot reconnects by itself, shows online again, continues its sequence with nothing counted as
    lost; the restarted service fetches the robot's backlog (store and forward), whose 3 scans it had
    integrated before the restart: those count as duplicates, not integrated twice. Then the robot
    restarts without its seq 0: its scans are integrated, which needs the last stamp to survive the
    service's restart (it was not kept in the snapshot)."""
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
                assert counters(wait_integrated(http, "life-svc", "r", 5)) == (5, 4, 0, 3, 0)
            assert svc.stop() == 0
            svc.start()
            with ScanPublisher("life-svc", "r", connect=svc.zenoh_endpoint) as restarted:
                assert restarted.wait_connected(15)
                for k in range(1, 3):
                    assert restarted.publish(scan_at(1.0 + 0.1 * k), seq=k)
            assert counters(wait_integrated(http, "life-svc", "r", 7)) == (7, 2, 1, 3, 1)
    finally:
        svc.stop()


# -- publisher sessions ---------------------------------------------------------------------------------


def robot_metric(http: httpx.Client, name: str, map_id: str, robot_id: str) -> float | None:
    """The value of the Prometheus sample `name{map=map_id, robot=robot_id}`, None if absent."""
    for family in text_string_to_metric_families(http.get("/metrics").text):
        for sample in family.samples:
            if sample.name == name and sample.labels == {"map": map_id, "robot": robot_id}:
                return sample.value
    return None


def test_two_robots_under_one_robot_id_are_both_integrated_and_the_conflict_reported(
    service: ServiceProcess, http: httpx.Client
) -> None:
    """Two robots misconfigured with one robot id: their seqs interleave. Told apart by nothing but
    stamps, the second one's seq 0 looked like a restart of the first, and then, its clock being
    behind the other's, its scans were dropped as duplicates of the other's (and the counters said
    restart after restart). Each publisher sends its own session id: the service keeps each one's
    seqs apart, integrates every scan of both and reports the conflict (robot listing, metric, log)."""
    with (
        ScanPublisher("life-twins", "r", connect=service.zenoh_endpoint) as first,
        ScanPublisher("life-twins", "r", connect=service.zenoh_endpoint, encoding="json") as second,
    ):
        assert first.session_id != second.session_id
        assert first.wait_connected(15) and second.wait_connected(15)
        for k in range(10):
            assert first.publish(scan_at(0.1 * k))
            wait_integrated(http, "life-twins", "r", 2 * k + 1)  # so that the two interleave
            assert second.publish(scan_at(5.0 + 0.1 * k), stamp=time.time() - 1000.0)  # its clock is behind
            stats = wait_integrated(http, "life-twins", "r", 2 * k + 2)
    assert counters(stats) == (20, 9, 0, 0, 0)
    assert stats["id_conflict"] is True and stats["id_conflicts"] == 1
    assert robot_metric(http, "fleetmap_robot_id_conflicts_total", "life-twins", "r") == 1.0
    wait_for(
        lambda: "robot id conflict on map 'life-twins'" in service.logs() and "'r'" in service.logs(),
        timeout=10, what="the conflict's log line",
    )  # fmt: skip
    lines = [line for line in service.logs().splitlines() if "robot id conflict on map 'life-twins'" in line]
    assert all("GET /maps/life-twins" in line for line in lines), lines
    assert len(lines) == 1  # one line for the ongoing conflict, not one per scan
    # A robot alone under its id is in no conflict.
    assert robot_stats(http, "life-restart", "r").get("id_conflict") in (False, None)


def test_three_robots_under_one_robot_id_count_two_conflicts_however_they_are_found(
    http: httpx.Client,
) -> None:
    """Three robots under one id count 2 in `id_conflicts` (docs/protocol.md, "Sessions": two robots
    1, a third one more), whether the third is found after the first two or all three at once (a
    fleet booted together with one configuration): found at once, they counted 1, as two robots do."""

    def post(map_id: str, session: int, seq: int) -> None:
        body = codec.encode_json(scan_at(0.1 * seq), seq, float(seq), session=session)
        answer = http.post(
            f"/maps/{map_id}/scans", params={"robot_id": "r"}, content=body,
            headers={"content-type": JSON_ENCODING},
        )  # fmt: skip
        assert answer.status_code == 200 and answer.json()["status"] == "integrated", answer.text

    # One after the other: two interleave (1), then a third joins them (2).
    for session, seq in ((11, 0), (12, 0), (11, 1), (12, 1), (13, 0), (11, 2), (12, 2), (13, 1)):
        post("life-three-later", session, seq)
    # At once: three first scans, then each one's second.
    for session, seq in ((21, 0), (22, 0), (23, 0), (21, 1), (22, 1), (23, 1)):
        post("life-three-at-once", session, seq)
    for map_id in ("life-three-later", "life-three-at-once"):
        stats = robot_stats(http, map_id, "r")
        assert (stats["id_conflicts"], stats["restarts"], stats["lost"]) == (2, 0, 0), (map_id, stats)
        assert robot_metric(http, "fleetmap_robot_id_conflicts_total", map_id, "r") == 2.0


def test_more_robots_under_one_robot_id_than_sessions_remembered_are_still_a_conflict(
    service: ServiceProcess,
) -> None:
    """Ten robots under one id (a fleet started from one image with its default id), more than the 8
    sessions a robot's bookkeeping holds: each session was pushed out before it came back, so each
    of its scans looked like a new session, a restart whose seqs before it were lost. The service
    counted 180 restarts and a `lost` of 20,000 scans, and showed no conflict at all. A session
    pushed out is still known when it comes back: the ten count 9 conflicts, nothing lost or
    restarted, every scan integrated, and a copy of a scan of theirs is a duplicate."""
    robots = 10
    with raw_publishers(service.zenoh_endpoint, "life-ten", ["r"]) as pubs:
        for seq in range(1000, 1020):
            for session in range(1, robots + 1):
                pubs["r"].put(codec.encode_binary(scan_at(0.01 * seq), seq, float(seq), session=session))
        pubs["r"].put(codec.encode_binary(scan_at(0.0), 1010, 1010.0, session=1))  # a copy
        with httpx.Client(base_url=service.base_url, timeout=10.0) as http:
            stats = wait_for(
                lambda: (s := robot_stats(http, "life-ten", "r"))
                and s["scans_integrated"] + s["duplicates"] == 20 * robots + 1 and s,
                timeout=20, what="every scan and the copy counted",
            )  # fmt: skip
            assert counters(stats) == (20 * robots, 1019, 0, 1, 0)
            assert stats["id_conflict"] is True and stats["id_conflicts"] == robots - 1


def test_each_of_more_robots_under_one_robot_id_than_sessions_listed_has_its_scans_confirmed(
    service: ServiceProcess,
) -> None:
    """Ten robots under one id flush: the delivery query lists a robot's 8 recent sessions, and the
    two pushed out of those by the others were not found when asked for by their session id, so
    those robots' flushes said none of their scans was counted. Asked for by its id, a session
    pushed out is answered too."""
    robots = [ScanPublisher("life-ten-flush", "r", connect=service.zenoh_endpoint) for _ in range(10)]
    try:
        for pub in robots:
            assert pub.wait_connected(15)
        for k in range(5):
            for pub in robots:
                assert pub.publish(scan_at(0.1 * k))
        reports = [pub.flush(30) for pub in robots]
        assert [report.summary() for report in reports] == ["5 scans published, 5 integrated"] * 10
        assert all(report.confirmed for report in reports)
    finally:
        for pub in robots:
            pub.close()


def test_lost_goes_down_when_a_gap_was_another_robots_so_it_is_a_gauge(http: httpx.Client) -> None:
    """A robot's `lost` counts a gap once a later seq arrives, and takes it back when the "gap" turns
    out to be another robot publishing under the id. It was the counter fleetmap_scans_lost_total,
    which fell: Prometheus reads that as a reset, and `increase()` reported the whole value again."""

    def post(session: int, seq: int) -> None:
        body = codec.encode_json(scan_at(0.01 * seq), seq, float(seq), session=session)
        answer = http.post(
            "/maps/life-lost/scans", params={"robot_id": "r"}, content=body,
            headers={"content-type": JSON_ENCODING},
        )  # fmt: skip
        assert answer.status_code == 200 and answer.json()["status"] == "integrated", answer.text

    for seq in (0, 1, 2, 3, 4, 9):  # 5 to 8 lost
        post(11, seq)
    assert robot_stats(http, "life-lost", "r")["lost"] == 4
    post(22, 500)  # another session far ahead: the robot's scans 10 to 499 look lost
    assert robot_stats(http, "life-lost", "r")["lost"] == 504
    post(11, 10)  # the first session goes on: 22 was another robot under the id, not a restart
    assert robot_stats(http, "life-lost", "r")["lost"] == 4
    assert robot_metric(http, "fleetmap_scans_lost", "life-lost", "r") == 4.0
    families = {f.name: f.type for f in text_string_to_metric_families(http.get("/metrics").text)}
    assert families["fleetmap_scans_lost"] == "gauge"


def test_a_robot_restarting_with_its_clock_and_seq_at_0_is_a_new_session_not_duplicates(
    service: ServiceProcess, http: httpx.Client
) -> None:
    """A robot whose clock starts again at 0 with it (or that sends stamp 0) and counts from 0 again:
    by its stamps, its new scans were duplicates (stamp 0) or each one another restart (stamps
    below the old ones, but rising). Its new session id says "restarted": nothing is dropped, one
    restart is counted. Copies within a session (also a late copy from before the restart) are
    still duplicates, and no id conflict."""
    with raw_publishers(service.zenoh_endpoint, "life-sessions", ["unstamped", "clock"]) as pubs:
        before, after = new_session_id(), new_session_id()
        # (session, seq): stamp 0 throughout; a copy of seq 4, and a late copy of the old run's seq 3.
        for sid, seq in [(before, 0), (before, 1), (before, 2), (before, 3), (before, 4), (before, 4),
                         (after, 0), (after, 1), (before, 3), (after, 2)]:  # fmt: skip
            pubs["unstamped"].put(codec.encode_binary(scan_at(float(seq)), seq, 0.0, session=sid))
        # A clock at 500 s, then at 0 again after the restart.
        for sid, seq, stamp in [
            *((before, k, 500.0 + k) for k in range(5)),
            *((after, k, 0.1 * k) for k in range(4)),
        ]:
            pubs["clock"].put(codec.encode_binary(scan_at(float(seq)), seq, stamp, session=sid))
        unstamped = wait_integrated(http, "life-sessions", "unstamped", 8)
        assert counters(unstamped) == (8, 2, 0, 2, 1)
        clock = wait_integrated(http, "life-sessions", "clock", 9)
        assert counters(clock) == (9, 3, 0, 0, 1)
        assert clock["last_stamp"] == pytest.approx(0.3)
        assert not unstamped["id_conflict"] and not clock["id_conflict"]


def test_a_service_restart_gives_the_session_bookkeeping_it_had(tmp_path: Path) -> None:
    """The journal keeps each scan's session id, the snapshot each robot's sessions: after a crash
    (the journal replayed) and after a clean restart (the snapshot) a map's robots have the
    counters they had: interleaved sessions (an id conflict, with a third session joining), a
    restarted robot, and one of an old publisher that sends no session id."""
    svc = ServiceProcess(tmp_path, ["--snapshot-interval", "3600"])
    svc.start()
    a, b, c, s1, s2 = (new_session_id() for _ in range(5))
    twins = [(a, 0), (b, 0), (a, 1), (b, 1), (a, 2), (b, 2), (a, 4), (b, 3), (c, 0), (a, 5), (b, 4), (c, 1)]
    solo = [(s1, k) for k in range(4)] + [(s2, k) for k in range(3)]
    old = [(None, k) for k in (0, 1, 2, 0, 1)]
    try:
        robots = {"twins": twins, "solo": solo, "old": old}
        with raw_publishers(svc.zenoh_endpoint, "life-replay", list(robots), JSON_ENCODING) as pubs:
            for robot, messages in robots.items():
                for sid, seq in messages:
                    pubs[robot].put(codec.encode_json(scan_at(0.1 * seq), seq, 0.0, session=sid))
        with httpx.Client(base_url=svc.base_url, timeout=10.0) as http:
            live = {robot: wait_integrated(http, "life-replay", robot, n) for robot, n in
                    (("twins", 12), ("solo", 7), ("old", 5))}  # fmt: skip
            assert counters(live["twins"]) == (12, 1, 1, 0, 0)  # seq 3 of `a` lost; `c` no restart
            assert (live["twins"]["id_conflict"], live["twins"]["id_conflicts"]) == (True, 2)
            assert counters(live["solo"]) == (7, 2, 0, 0, 1)
            assert counters(live["old"]) == (5, 1, 0, 0, 1)
            svc.proc.kill()  # type: ignore[union-attr]  # SIGKILL: no snapshot, only the journal
            svc.proc.wait(10)  # type: ignore[union-attr]
            for how in ("journal", "snapshot"):
                svc.start()
                if how == "journal":  # (no snapshot was made before the kill: all 24 replayed)
                    assert "24 journal scans replayed" in svc.logs()
                again = {robot: robot_stats(http, "life-replay", robot) for robot in live}
                assert again == live, how
                if how == "journal":
                    assert svc.stop() == 0  # a clean stop: snapshotted
            # The snapshot kept each session's seqs: `c` and `a` go on, neither restarted nor lost.
            with raw_publishers(svc.zenoh_endpoint, "life-replay", ["twins"]) as pubs:
                for sid, seq in [(c, 2), (a, 6)]:
                    pubs["twins"].put(codec.encode_binary(scan_at(0.1 * seq), seq, 0.0, session=sid))
                twins_now = wait_integrated(http, "life-replay", "twins", 14)
            assert counters(twins_now) == (14, 6, 1, 0, 0)
            assert twins_now["id_conflicts"] == 2
    finally:
        svc.stop()


def test_twenty_robots_under_one_robot_id_are_told_apart_also_after_a_service_restart(
    tmp_path: Path,
) -> None:
    """Twenty robots under one id (a fleet started from one image with its default id), more than
    the 16 sessions a robot's bookkeeping held: each session was pushed out of them before it came
    back, so each of its scans looked like a new session (a restart, its seqs before it lost, and
    one conflict more each time). And the sessions pushed out were not saved: after a restart of
    the service the robots' caches, fetched again, were integrated a second time for those (with
    ten robots under one id, two of them). Now every session is known: 19 conflicts, nothing lost
    or restarted, and after a clean restart copies of every scan are duplicates, each session's
    next scan goes on from its own seq, and the delivery query answers for a session pushed out."""
    svc = ServiceProcess(tmp_path, ["--snapshot-interval", "3600"])
    svc.start()
    robots, scans = 20, 3
    sessions = [new_session_id() for _ in range(robots)]

    def put_round(pub: zenoh.Publisher, seqs: range) -> None:
        for seq in seqs:
            for sid in sessions:
                pub.put(codec.encode_binary(scan_at(0.01 * seq), seq, 100.0 + seq, session=sid))

    try:
        with httpx.Client(base_url=svc.base_url, timeout=10.0) as http:
            with raw_publishers(svc.zenoh_endpoint, "life-crowd", ["r"]) as pubs:
                put_round(pubs["r"], range(scans))
                live = wait_integrated(http, "life-crowd", "r", robots * scans)
            assert counters(live) == (robots * scans, scans - 1, 0, 0, 0)
            assert (live["id_conflict"], live["id_conflicts"]) == (True, robots - 1)
            assert svc.stop() == 0  # a clean stop: snapshotted, the journal empty
            svc.start()
            assert robot_stats(http, "life-crowd", "r") == live
            with raw_publishers(svc.zenoh_endpoint, "life-crowd", ["r"]) as pubs:
                put_round(pubs["r"], range(scans))  # the caches fetched again: copies
                put_round(pubs["r"], range(scans, scans + 1))  # and each robot's next scan
                now = wait_for(
                    lambda: (s := robot_stats(http, "life-crowd", "r"))
                    and s["scans_integrated"] + s["duplicates"] == robots * (2 * scans + 1) and s,
                    timeout=20, what="every copy and next scan counted",
                )  # fmt: skip
            assert counters(now) == (robots * (scans + 1), scans, 0, robots * scans, 0)
            assert now["id_conflicts"] == robots - 1
            cfg = zenoh.Config()
            cfg.insert_json5("mode", '"client"')
            cfg.insert_json5("connect/endpoints", json.dumps([svc.zenoh_endpoint]))
            with zenoh.open(cfg) as session:
                key = f"fleetmap/life-crowd/r/delivery?session={sessions[0]}"
                replies = list(session.get(key, timeout=10))
            answer = json.loads(replies[0].ok.payload.to_string())  # type: ignore[union-attr]
            assert [(s["session"], s["integrated"], s["settled"]) for s in answer["sessions"]] == [
                (sessions[0], scans + 1, scans)
            ]
    finally:
        svc.stop()
