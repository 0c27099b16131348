"""Delivery confirmation over real parts: the real service as a process, robots' `ScanPublisher`s
(real Zenoh client sessions), raw Zenoh queries, and `FreezableProxy` (real sockets) to cut or
silently kill a robot's link.

The service answers a query on `fleetmap/<map>/<robot>/delivery` with what became of the robot's
scans (`fleetmap.wire.DeliveryStatus`); `ScanPublisher.flush` asks it until every scan of its
session is settled, and `fleetmap replay` reports what was confirmed (docs/protocol.md, "Delivery
confirmation")."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from array import array
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh
from fleetmap_client.delivery import delivery_report
from fleetmap_client.publisher import (
    DeliveryReport,
    DeliveryUnsupported,
    PublisherClosed,
    ScanPublisher,
)
from registry_idle import wait_idle
from robot_process import scans_for
from service_process import FreezableProxy, RestartingService, ServiceProcess, reaped, wait_for
from test_client_zenoh import Router, _write_carmen
from test_e2e import assert_region_equal, map_stats, wait_integrated
from test_ingest import client_session, scan_publisher
from test_store_forward import LAYERS, engine_map, publish_then_cut

from fleetmap import codec
from fleetmap.codec import WireScan
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.map_entry import IngestRejected, Job
from fleetmap.memory_budget import MemoryBudget, MemoryBudgetError
from fleetmap.registry import MapRegistry
from fleetmap.robot_state import LEDGER_HISTORY, MAX_SESSIONS, Receipt, RobotState, SessionLedger, pairs
from fleetmap.scan import Scan
from fleetmap.unmapped_refusals import MAX_UNMAPPED_ROBOTS
from fleetmap.wire import (
    BINARY_ENCODING,
    DELIVERY_KEY,
    JSON_ENCODING,
    SCAN_KEY,
    DeliveryStatus,
    SessionDelivery,
)


def test_settled_passes_only_scans_settled_in_order() -> None:
    """With durable storage a scan counts as integrated when its journal row commits, after a later
    scan of the robot may have been refused: `settled` must not pass the earlier one meanwhile. A
    re-send of a refused seq (a REST retry) is unsettled again until it is settled."""
    ledger = SessionLedger()
    first, second, third = ledger.open(0), ledger.open(1), ledger.open(2)
    ledger.settle(second, integrated=False)  # refused while the first waits for its commit
    assert (ledger.settled, ledger.integrated, ledger.refused) == (None, 0, 1)
    ledger.settle(first, integrated=True)
    assert ledger.settled == 1
    ledger.settle(third, integrated=False)
    ledger.settle(third, integrated=False)  # settled once
    assert (ledger.settled, ledger.integrated, ledger.refused) == (2, 1, 2)
    again = ledger.open(2)
    assert ledger.settled is None
    ledger.settle(again, integrated=True)
    assert (ledger.settled, ledger.first_seq) == (2, 0)


def test_refused_seqs_and_lost_gaps_are_listed_compactly_until_the_cap() -> None:
    """A session's refused seqs and gaps of lost seqs are kept as machine integers (out-of-limits
    scans under made-up robot ids fill them, and robot state is not charged to the memory budget),
    read back as the delivery query lists them: seqs, and (seq, n) pairs; past LEDGER_HISTORY
    entries each is not known (None), and a flush falls back to the counts."""
    robot = RobotState()
    seq = 2**40  # not a small int Python shares
    for k in range(LEDGER_HISTORY):
        seq += 3  # 2 seqs lost before each
        robot.accept(seq, float(k), 7)
        ledger = robot.sessions[7].ledger
        ledger.settle(ledger.open(seq), integrated=k % 2 == 0)
    assert isinstance(ledger.refused_seqs, array) and isinstance(ledger.lost_gaps, array)
    assert list(ledger.refused_seqs) == [2**40 + 3 * k for k in range(2, LEDGER_HISTORY + 1, 2)]
    gaps = pairs(ledger.lost_gaps)
    assert gaps is not None and len(gaps) == LEDGER_HISTORY - 1  # none before the session's first scan
    assert gaps[0] == (2**40 + 6, 2) and gaps[-1] == (seq, 2)
    ledger.withdraw_refusal(seq)  # the last refused scan sent again and accepted
    assert ledger.refused_seqs[-1] == seq - 6 and ledger.refused == LEDGER_HISTORY // 2 - 1
    for _ in range(LEDGER_HISTORY // 2 + 2):
        seq += 3
        robot.accept(seq, 0.0, 7)
        ledger.settle(ledger.open(seq), integrated=False)
    assert ledger.refused_seqs is None and ledger.lost_gaps is None and pairs(ledger.lost_gaps) is None


@pytest.mark.parametrize("case", ["resent after the full queue refused it", "restart without session ids"])
def test_settled_does_not_pass_a_seq_accepted_again_while_it_waits(case: str) -> None:
    """A seq accepted again while the robot's earlier scans wait (the re-send of a scan the full
    queue refused; a robot without session ids restarted, its seqs from 0 again) is behind them in
    the ledger: once they are settled, `settled` must not say the seq is settled while it waits
    (flush confirmed it; a crash then lost it with the publisher closed)."""
    seen: list[DeliveryStatus] = []
    session = 7 if case.startswith("resent") else None

    def on_integrated(_entry: Any, job: Job, _result: Any, _elapsed: float) -> None:
        if job.robot_id == "r" and job.wire.stamp == 2.0:  # the last of the earlier scans
            seen.append(reg.delivery_status("m", "r", 7 if session else 0))

    reg = MapRegistry(workers=1, queue_bytes=3 * 30 * 16, on_integrated=on_integrated)  # three scans
    if session:
        reg.submit("o", "other", WireScan(0, 0.0, _scan()))
    reg.submit("m", "r", WireScan(0, 1.0, _scan(), session))
    reg.submit("m", "r", WireScan(1, 2.0, _scan(), session))
    if session:
        with pytest.raises(IngestRejected, match="queue full"):
            reg.submit("m", "r", WireScan(2, 3.0, _scan(), session))
        reg.delete("o")  # room again: the robot sends seq 2 again (a REST retry, or a re-publish)
        reg.submit("m", "r", WireScan(2, 3.0, _scan(), session))
    else:
        reg.submit("m", "r", WireScan(0, 10.0, _scan()))  # restarted: a later stamp
    last = 2 if session else 0
    reg.start()
    try:
        assert wait_idle(reg)
        early = seen[0].sessions[0]
        assert early.settled is None or early.settled < last, f"seq {last} waited, yet settled {early}"
        final = reg.delivery_status("m", "r", 7 if session else 0).sessions[0]
        # Every scan settled: the highest seq accepted (the earlier run's 1 after a restart).
        assert (final.settled, final.refused, final.integrated) == (2 if session else 1, 0, 3)
    finally:
        reg.close()


@pytest.mark.parametrize("case", ["resent after the memory budget refused it", "restart without session ids"])
def test_a_snapshot_does_not_save_a_seq_accepted_again_as_the_services_while_it_waits(case: str) -> None:
    """What a snapshot saves of a session (`SessionSeqs.saved`) stops before its first scan not
    settled: a seq accepted again behind waiting scans (the re-send of a scan refused 507 while
    later ones were queued; a restart without session ids) is that first one, though not at the
    front. Saved as the service's, a crash before its journal commit lost it for good: the robot's
    cache re-sending it was refused as a duplicate, and its flush confirmed the session."""
    resend = case.startswith("resent")
    session = 7 if resend else None
    first = 5 if resend else 0  # the seq accepted again
    reg = MapRegistry(workers=1)
    entry, _ = reg.create("m")
    waiting, release = threading.Event(), threading.Event()
    plan, refused = entry.gmap.plan, []

    def plan_slowly(scan: Scan) -> Any:
        if scan.pose.x == 1.0 and not refused:  # the first time: refused for the memory budget
            refused.append(scan)
            raise MemoryBudgetError("the memory budget is full")
        if scan.pose.x == 2.0:  # a later scan waits here while the robot sends again
            waiting.set()
            release.wait(10)
        return plan(scan)

    entry.gmap.plan = plan_slowly  # type: ignore[method-assign]
    if resend:
        for seq, x in ((5, 1.0), (6, 2.0), (7, 3.0)):
            reg.submit("m", "r", WireScan(seq, float(seq), _scan(x), session))
    else:
        reg.submit("m", "r", WireScan(0, 1.0, _scan()))
        reg.submit("m", "r", WireScan(1, 2.0, _scan(2.0)))
    reg.start()
    try:
        assert waiting.wait(10)  # the scans before it are settled (one refused 507 if `resend`)
        reg.submit("m", "r", WireScan(first, 10.0, _scan(), session))  # again (resend), or restarted
        with reg.lock:
            seqs = reg.get("m").robots["r"].sessions[7 if resend else 0]
            saved = seqs.settled_seq()
        assert saved < first, f"seq {first} waits, yet a snapshot would save seq {saved} as the service's"
        release.set()
        assert wait_idle(reg)
        final = reg.delivery_status("m", "r", 7 if resend else 0).sessions[0]
        # Every scan settled: the highest seq accepted (7, not the re-sent 5 settled last; the
        # earlier run's 1), the 507 no longer counted as refused once its re-send was accepted.
        expected = (7, 0, 3) if resend else (1, 0, 3)
        assert (final.settled, final.refused, final.integrated) == expected
    finally:
        release.set()
        reg.close()


@pytest.mark.parametrize("case", ["refused", "lost", "refused and sent again"])
def test_a_snapshot_saves_the_counts_only_as_far_as_the_sessions_seqs(case: str) -> None:
    """A snapshot saves a session's seqs only up to its first scan not settled (a scan waiting for
    its journal commit: `SessionSeqs.settled_seq`), so after a crash the scans after it come again
    (replayed from the journal, fetched again from the robot's cache) and are counted again. What
    was counted of them before must not be saved too: a scan refused meanwhile made every later
    flush of the wholly integrated session say "1 refused" (2 refusals of a scan refused again),
    the gap before a scan not received yet "lost"; the refusal of a scan sent again and accepted
    was taken off twice."""
    state, receipts = RobotState(), []

    def accept(robot: RobotState, seq: int) -> Receipt:
        robot.accept(seq, float(seq), 7)
        return robot.sessions[7].ledger.open(seq)

    receipts.append(accept(state, 5))  # waits for its journal commit
    if case == "lost":
        receipts.append(accept(state, 7))  # seq 6 not received yet
    else:
        receipts.append(accept(state, 6))
        state.sessions[7].ledger.settle(receipts[1], integrated=False)  # refused (the queue was full)
        state.note_refused(6, 7)
        if case == "refused and sent again":
            receipts.append(accept(state, 6))
    restored = RobotState.from_saved(json.loads(json.dumps(state.saved())))  # a snapshot, then a crash
    for seq in (5, 6, 7):  # replayed from the journal, or fetched again from the robot's cache
        assert not restored.is_duplicate(seq, float(seq), 7)
        restored.sessions[7].ledger.settle(accept(restored, seq), integrated=True)
    ledger = restored.sessions[7].ledger
    counts = (ledger.first_seq, ledger.settled, ledger.integrated, ledger.refused, ledger.lost)
    assert counts == (5, 7, 3, 0, 0)


def _scan(x: float = 0.0) -> Scan:
    """A scan of 30 beams (what the queue's byte limits above count) from (`x`, 0)."""
    return Scan.from_fan((x, 0.0, 0.0), -0.5, 1.0 / 30, [2.0] * 30, 0.0, 30.0)


def test_the_reply_docs_protocol_md_shows_is_the_services_model() -> None:
    """docs/protocol.md's example reply is a `DeliveryStatus` (the doc and `fleetmap.wire` agree)."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "protocol.md").read_text(encoding="utf-8")
    section = text.split("### Delivery confirmation", 1)[1]
    example = re.search(r"```text\n(.*?)```", section, re.S)
    assert example, "no example reply in docs/protocol.md, Delivery confirmation"
    status = DeliveryStatus.model_validate_json(example.group(1))
    entry = status.session(4711)
    assert entry is not None and entry.settled == 999
    # The model ignores fields it does not know (a newer service's): the example must use its own.
    shown = json.loads(example.group(1))
    assert set(shown) == set(DeliveryStatus.model_fields), set(shown) ^ set(DeliveryStatus.model_fields)
    assert set(shown["sessions"][0]) == set(SessionDelivery.model_fields)


@pytest.fixture(scope="module")
def memory_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One `--in-memory` service for the module's tests that need no option of their own: each uses
    maps of its own (ids no other test here uses), and none stops, restarts or reconfigures it.
    A test that does keeps a service of its own."""
    with ServiceProcess(tmp_path_factory.mktemp("delivery-memory"), ["--in-memory"]) as service:
        yield service


@pytest.fixture(scope="module")
def durable_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One durable service (its own data directory) for the module's tests that need it as it
    starts, on the same terms as `memory_service`."""
    with ServiceProcess(tmp_path_factory.mktemp("delivery-durable")) as service:
        yield service


def query(session: zenoh.Session, key: str) -> DeliveryStatus | str:
    """The service's answer to a delivery query on `key` (a selector): the status, or an error
    reply's text. AssertionError when nothing answers."""
    for reply in session.get(key, timeout=5.0):
        if reply.ok is not None:
            return DeliveryStatus.model_validate_json(reply.ok.payload.to_bytes())
        assert reply.err is not None
        return reply.err.payload.to_string()
    raise AssertionError(f"no answer to the delivery query {key}")


def test_flush_confirms_scans_integrated_and_durable(durable_service: ServiceProcess) -> None:
    """A robot publishes 40 scans and flushes: the service (durable: each scan counts once its
    journal row is committed) reports all 40 integrated, and the map holds exactly them."""
    scans = scans_for(sim=11, beams=181, count=40)
    with (
        ScanPublisher("fl", "r1", connect=[durable_service.zenoh_endpoint]) as pub,
    ):
        assert pub.wait_connected(20), pub.last_connect_error
        for seq, scan in enumerate(scans):
            pub.publish(scan, seq=seq, stamp=float(seq))
        report = pub.flush(30)
        assert report.confirmed and report, report
        assert (report.published, report.integrated, report.refused, report.lost) == (40, 40, 0, 0)
        assert report.summary() == "40 scans published, 40 integrated"
        with httpx.Client(base_url=durable_service.base_url, timeout=10) as http:
            # Confirmed means integrated already: no waiting for the map here.
            assert map_stats(http, "fl")["scans_integrated"] == 40
            assert_region_equal(http, "fl", engine_map(scans), LAYERS)


def test_flush_waits_through_a_dead_zone(memory_service: ServiceProcess) -> None:
    """Scans published into a dead zone (the link cut, new connections refused) are not confirmed
    while it lasts; flush waits, the link comes back 1.5 s later, the backlog delivers them and
    flush confirms all of them."""
    scans = scans_for(sim=12, beams=181, count=30)
    proxy = FreezableProxy(memory_service.zenoh_port)
    pub = ScanPublisher("dz", "r1", connect=[proxy.endpoint])
    try:
        with httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            publish_then_cut(pub, proxy, http, "dz", scans, 10)
            for seq in range(10, len(scans)):
                assert pub.publish(scans[seq], seq=seq, stamp=float(seq))
            assert not pub.flush(0.5)  # in the dead zone: not confirmed (yet)
            threading.Timer(1.5, proxy.restore).start()
            started = time.monotonic()
            report = pub.flush(30)
            assert report.confirmed, report
            assert time.monotonic() - started > 1.0  # it waited for the link
            assert (report.published, report.integrated) == (30, 30)
            assert map_stats(http, "dz")["scans_integrated"] == 30
    finally:
        pub.close()
        proxy.close()


def test_replay_whose_link_dies_silently_near_the_end_reports_unconfirmed_scans(
    memory_service: ServiceProcess, tmp_path: Path
) -> None:
    """`fleetmap replay` of 40 scans, its link frozen after some 25 were integrated and never back
    (new connections refused; to the robot the frozen one looks alive): the replay publishes the
    rest into it, as it always did, but then says they are not confirmed and exits with 1 (it said
    "replayed 40 scans" and exited 0)."""
    log = tmp_path / "corridor.log"
    _write_carmen(log, 40)
    proxy = FreezableProxy(memory_service.zenoh_port)
    command = [
        sys.executable, "-m", "fleetmap_client.cli", "replay", str(log), "--map", "rp", "--robot", "r1",
        "--rate", "1", "--connect", proxy.endpoint, "--quiet", "--wait-timeout", "20",
        "--confirm-timeout", "3",
    ]  # fmt: skip
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with reaped(proc), httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            wait_integrated(http, "rp", 25, timeout=60)
            proxy.freeze(refuse_new=True)
            out, err = proc.communicate(timeout=60)
            integrated = map_stats(http, "rp")["scans_integrated"]
    finally:
        proxy.close()
    assert proc.returncode == 1, (proc.returncode, out, err)
    assert "replayed 40 scans" in out, (out, err)
    assert 25 <= integrated < 40
    # Frozen before the replay's first delivery query: the service never answered it.
    assert "40 scans published, 0 integrated: the service did not answer, 40 unconfirmed" in err, err


def test_replay_whose_service_goes_for_good_midway_says_so(
    memory_service: ServiceProcess, tmp_path: Path
) -> None:
    """`fleetmap replay` whose service goes away after some scans and does not come back within
    `--wait-timeout`: it exits with 2 saying it lost the service after publishing k of the scans,
    where it said "no fleetmap service reachable", as if there had never been one."""
    log = tmp_path / "corridor.log"
    _write_carmen(log, 40)
    proxy = FreezableProxy(memory_service.zenoh_port)
    command = [
        sys.executable, "-m", "fleetmap_client.cli", "replay", str(log), "--map", "gone", "--robot", "r1",
        "--rate", "1", "--connect", proxy.endpoint, "--quiet", "--wait-timeout", "2",
    ]  # fmt: skip
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with reaped(proc), httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            wait_integrated(http, "gone", 10, timeout=60)
            proxy.cut()
            out, err = proc.communicate(timeout=60)
    finally:
        proxy.close()
    assert proc.returncode == 2, (proc.returncode, out, err)
    assert re.search(
        r"lost the fleetmap service after publishing \d+ of 40 scans, and it did not come back", err
    )
    assert "Traceback" not in err, err


def test_a_query_for_an_unknown_map_or_robot_says_so(memory_service: ServiceProcess) -> None:
    """The service answers a query about a map it does not hold, or a robot the map does not know,
    with a status that says so (not silence); one about several robots (a wildcard) or with a bad
    session id gets an error reply. A known robot's answer lists its session."""
    scans = scans_for(sim=13, beams=181, count=3)
    session = client_session(memory_service.zenoh_endpoint)
    try:
        answer = query(session, DELIVERY_KEY.format(map_id="nowhere", robot_id="r1"))
        assert isinstance(answer, DeliveryStatus)
        assert (answer.status, answer.map_id, answer.robot_id, answer.sessions) == (
            "no_map",
            "nowhere",
            "r1",
            [],
        )
        key = SCAN_KEY.format(map_id="qm", robot_id="r1")
        for seq, scan in enumerate(scans):
            payload = codec.encode_binary(scan, seq, stamp=float(seq), session=77)
            session.put(key, payload, encoding=zenoh.Encoding(BINARY_ENCODING))
        with httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            wait_integrated(http, "qm", 3, timeout=30)
        answer = query(session, DELIVERY_KEY.format(map_id="qm", robot_id="r2"))
        assert isinstance(answer, DeliveryStatus) and answer.status == "no_robot"
        answer = query(session, DELIVERY_KEY.format(map_id="qm", robot_id="r1"))
        assert isinstance(answer, DeliveryStatus) and answer.status == "ok"
        entry = answer.session(77)
        assert entry is not None and (entry.first_seq, entry.last_accepted, entry.settled) == (0, 2, 2)
        assert (answer.scans_integrated, answer.unsettled, entry.integrated) == (3, 0, 3)
        assert query(session, DELIVERY_KEY.format(map_id="qm", robot_id="r1") + "?session=5").sessions == []  # type: ignore[union-attr]
        wildcard = query(session, DELIVERY_KEY.format(map_id="qm", robot_id="*"))
        assert isinstance(wildcard, str) and "ask for one robot" in wildcard
        bad = query(session, DELIVERY_KEY.format(map_id="qm", robot_id="r1") + "?session=x")
        assert isinstance(bad, str) and "session must be an integer" in bad
    finally:
        session.close()


def test_a_query_without_fields_2_gets_the_first_versions_reply(memory_service: ServiceProcess) -> None:
    """Robots in the field run the client they were built with, which read the delivery reply
    strictly: a field it did not know made its flush fail ("not a fleetmap one"). A query without
    `fields=2` gets the reply's first fields only, which such a client reads; one with it (today's
    `flush`) gets `last_error` and the sessions' `refused_seqs` and `lost_gaps` too."""

    first_fields = set(DeliveryStatus.model_fields) - {"last_error"}
    scan = scans_for(sim=21, beams=181, count=1)[0]
    session = client_session(memory_service.zenoh_endpoint)
    try:
        payload = codec.encode_binary(scan, 0, stamp=0.0, session=78)
        session.put(
            SCAN_KEY.format(map_id="fv", robot_id="r1"), payload, encoding=zenoh.Encoding(BINARY_ENCODING)
        )
        with httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            wait_integrated(http, "fv", 1, timeout=30)
        key = DELIVERY_KEY.format(map_id="fv", robot_id="r1")
        replies = {}
        for selector in (key + "?session=78", key + "?session=78;fields=2"):
            got = [r.ok.payload.to_string() for r in session.get(selector, timeout=5.0) if r.ok is not None]
            assert len(got) == 1, (selector, got)
            replies[selector] = json.loads(got[0])
        first = replies[key + "?session=78"]
        assert set(first) == first_fields, set(first) ^ first_fields
        assert set(first["sessions"][0]) == set(SessionDelivery.model_fields) - {
            "refused_seqs",
            "lost_gaps",
        }
        newer = replies[key + "?session=78;fields=2"]
        assert "last_error" in newer and newer["sessions"][0]["refused_seqs"] == []
    finally:
        session.close()


def test_the_answer_counts_refused_and_duplicate_scans(memory_service: ServiceProcess) -> None:
    """Scans the service does not integrate are settled all the same, and counted: a duplicate seq
    (ignored) and a scan that needs more tiles than its map may have (refused at integration).
    The session is settled through its last seq, and flush reports it settled but not confirmed."""
    near = Scan.from_fan((5.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)  # inside one tile
    far = Scan.from_fan((500.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)  # a tile more
    httpx.put(f"{memory_service.base_url}/maps/rf", json={"max_tiles": 1}, timeout=10).raise_for_status()
    pub = ScanPublisher("rf", "r1", connect=[memory_service.zenoh_endpoint], backlog=0)
    try:
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(3):
            pub.publish(near, seq=seq, stamp=float(seq))
        pub.publish(near, seq=2, stamp=2.0)  # the last seq again: a resend, a duplicate
        pub.publish(far, seq=3, stamp=3.0)  # a second tile: refused
        pub.publish(near, seq=4, stamp=4.0)
        report = pub.flush(30)
        assert report.settled and not report.confirmed, report
        assert (report.published, report.integrated, report.refused, report.lost) == (5, 4, 1, 0)
        assert report.last_error is not None and "max_tiles" in report.last_error, report
        refused = f"1 refused or dropped by the service (the last: {report.last_error})"
        assert report.summary() == f"5 scans published, 4 integrated: {refused}"
        assert pub._session is not None
        answer = query(pub._session, DELIVERY_KEY.format(map_id="rf", robot_id="r1"))
        assert isinstance(answer, DeliveryStatus)
        entry = answer.session(pub.session_id)
        assert entry is not None and (entry.duplicates, entry.refused, entry.settled) == (1, 1, 4)
        assert answer.duplicates == 1 and answer.unsettled == 0
    finally:
        pub.close()


def test_scans_refused_at_the_input_limits_are_settled_as_refused_not_lost(tmp_path: Path) -> None:
    """A robot's well-formed scans that break the service's input limits (a pose outside the world
    bound: UTM eastings sent as map coordinates) are refused, and settled so: counted `refused` in
    their session, not `lost` (they reached the service), and the last scan of the session refused
    so no longer leaves it unsettled, where flush waited until its timeout (for ever without one).
    A flush asks again after a restart of the durable service: the robot's cache, fetched again, is
    counted as duplicates, and the answer is the same."""
    near = Scan.from_fan((5.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    utm = Scan.from_fan((500_000.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    # A lidar of more beams than the service takes (--max-beams, 16384), refused by the binary header.
    dense = Scan.from_fan((5.0, 5.0, 0.0), -3.0, 6.0 / 20_000, [1.0] * 20_000, 0.05, 10.0)
    with (
        ServiceProcess(tmp_path) as service,
        ScanPublisher("lim", "r1", connect=[service.zenoh_endpoint]) as pub,
    ):
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(7):
            pub.publish({2: utm, 3: dense, 6: utm}.get(seq, near), seq=seq, stamp=float(seq))
        started = time.monotonic()
        report = pub.flush(10)
        assert time.monotonic() - started < 5, report  # the last scan's refusal settled it
        assert report.settled and not report.confirmed, report
        assert (report.published, report.integrated, report.refused, report.lost) == (7, 4, 3, 0)
        assert report.last_error is not None and "scan seq 6 refused: pose (500000, 5)" in report.last_error
        refused = f"3 refused or dropped by the service (the last: {report.last_error})"
        assert report.summary() == f"7 scans published, 4 integrated: {refused}"
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            robot = map_stats(http, "lim")["robots"]["r1"]
        assert (robot["scans_integrated"], robot["scans_rejected"], robot["lost"]) == (4, 3, 0), robot
        assert robot["last_seq"] == 6, robot
        assert "scan seq 6 refused: pose (500000, 5) is outside the world bound" in robot["last_error"]
        service.stop()
        service.start()  # same ports and data
        assert pub.wait_connected(20), pub.last_connect_error
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            # The cache fetched again: each of its scans a duplicate, the refused ones too.
            wait_for(lambda: map_stats(http, "lim")["robots"]["r1"]["duplicates"] == 7, 10, what="the cache")
            robot = map_stats(http, "lim")["robots"]["r1"]
        assert (robot["scans_integrated"], robot["scans_rejected"], robot["lost"]) == (4, 3, 0), robot
        assert pub.flush(10) == report


def test_json_scans_of_far_too_many_beams_are_settled_as_refused_not_lost(tmp_path: Path) -> None:
    """A JSON scan of so many beams that `decode_json` refuses it unparsed (more items than twice
    the beam limit: its commas are counted first) is refused as the binary one is, with its seq:
    the service counted it as undecodable, its seq as `lost` when the next came (besides
    `scans_rejected`: one scan counted twice), and the last scan of a session refused so was never
    settled: the robot's flush waited for it until its timeout, saying nothing of the refusal."""
    near = Scan.from_fan((5.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    dense = Scan.from_fan((5.0, 5.0, 0.0), -3.0, 6.0 / 5000, [1.0] * 5000, 0.05, 10.0)
    with (
        ServiceProcess(tmp_path, ["--in-memory", "--max-beams", "1000"]) as service,
        ScanPublisher("lim", "r1", connect=[service.zenoh_endpoint], encoding="json") as pub,
    ):
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(6):
            pub.publish(dense if seq in (2, 5) else near, seq=seq, stamp=float(seq))
        started = time.monotonic()
        report = pub.flush(10)
        assert time.monotonic() - started < 5, report  # the last scan's refusal settled it
        assert (report.published, report.integrated, report.refused, report.lost) == (6, 4, 2, 0), report
        assert report.settled and report.last_error is not None, report
        assert "scan seq 5 refused: invalid JSON scan: more items than 1000 beams" in report.last_error
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            robot = map_stats(http, "lim")["robots"]["r1"]
        assert (robot["scans_integrated"], robot["scans_rejected"], robot["lost"]) == (4, 2, 0), robot


def test_scans_refused_for_their_body_are_settled_as_refused_not_lost(memory_service: ServiceProcess) -> None:
    """Scans of a robot written to docs/protocol.md (not `ScanPublisher`, which refuses them first)
    whose seq and session are fine but whose body the service refuses: JSON of 2 angles but 20
    ranges, JSON with a negative range_min, binary with a NaN range_min. Each is refused with its
    seq, as a scan past the input limits is: they were counted in `scans_rejected` and, as
    undecodable, their seqs as `lost` too (one scan counted twice), and the session's last scan
    refused so was never settled (a robot's flush waited for it until its timeout)."""
    body = {"pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": -1.0, "angle_increment": 0.1}

    def json_scan(seq: int, **changes: Any) -> bytes:
        message = {"seq": seq, "stamp": float(seq), "session": 77, **body, "ranges": [2.0] * 20} | changes
        return json.dumps({k: v for k, v in message.items() if v is not None}).encode()

    near = Scan.from_fan((0.0, 0.0, 0.0), -1.0, 0.1, [2.0] * 20, 0.05, 10.0)
    nan_range_min = bytearray(codec.encode_binary(near, 3, stamp=3.0, session=77))
    header = list(codec.HEADER_V2.unpack_from(nan_range_min))
    header[9] = float("nan")  # range_min
    codec.HEADER_V2.pack_into(nan_range_min, 0, *header)
    payloads = [
        (json_scan(0), JSON_ENCODING),
        (json_scan(1, angle_min=None, angle_increment=None, angles=[0.0, 0.1]), JSON_ENCODING),
        (json_scan(2), JSON_ENCODING),
        (bytes(nan_range_min), BINARY_ENCODING),
        (json_scan(4), JSON_ENCODING),
        (json_scan(5, range_min=-1.0), JSON_ENCODING),
    ]
    session = client_session(memory_service.zenoh_endpoint)
    try:
        publisher = scan_publisher(session, "body", "r1", JSON_ENCODING)
        for payload, encoding in payloads:
            publisher.put(payload, encoding=zenoh.Encoding(encoding))
        with httpx.Client(base_url=memory_service.base_url, timeout=10) as http:
            wait_for(lambda: map_stats(http, "body")["robots"]["r1"]["scans_rejected"] == 3, 20)
            robot = map_stats(http, "body")["robots"]["r1"]
        assert (robot["scans_integrated"], robot["lost"], robot["last_seq"]) == (3, 0, 5), robot
        assert robot["last_error"].startswith("scan seq 5 refused: invalid JSON scan: range_min"), robot
        answer = query(session, DELIVERY_KEY.format(map_id="body", robot_id="r1") + "?fields=2")
        assert isinstance(answer, DeliveryStatus)
        entry = answer.session(77)
        assert entry is not None, answer
        assert (entry.last_accepted, entry.settled, entry.integrated, entry.refused, entry.lost) == (
            5, 5, 3, 3, 0,
        ), entry  # fmt: skip
        assert entry.refused_seqs == [1, 3, 5], entry
    finally:
        session.close()


def test_flush_against_a_service_without_delivery_queries_is_an_error_not_a_hang() -> None:
    """A router that subscribes to scans as the service does but declares no delivery queryable
    (a service older than delivery confirmation): flush raises `DeliveryUnsupported` within a few
    seconds, whatever its timeout."""
    router = Router().start()
    try:
        with ScanPublisher("old", "r1", connect=[router.endpoint]) as pub:
            assert pub.wait_connected(20), pub.last_connect_error
            pub.publish(scans_for(sim=15, beams=181, count=1)[0])
            started = time.monotonic()
            with pytest.raises(DeliveryUnsupported, match="answers no delivery query"):
                pub.flush(60)
            assert time.monotonic() - started < 15
    finally:
        router.stop()


@pytest.mark.parametrize("stop", ["sigterm", "sigkill"])
def test_flush_confirms_scans_integrated_before_a_restart_of_the_service(tmp_path: Path, stop: str) -> None:
    """A robot publishes 20 scans, the durable service stops (cleanly, or killed) and a new one starts
    on the same data while the robot publishes 20 more into its backlog: flush confirms all 40. What
    became of each session's scans is stored with the map (snapshots, then the journal's replay), so a
    restart in the middle of a mission does not leave its first scans unconfirmable."""
    data = ["--data-dir", str(tmp_path / "data")]
    scans = scans_for(sim=14, beams=181, count=40)
    services = RestartingService(tmp_path, data)
    first, proxy = services.service, services.proxy
    pub = ScanPublisher("rs", "r1", connect=[proxy.endpoint])
    try:
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(20):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        assert pub.flush(30)
        if stop == "sigkill":
            services.kill()
        else:
            assert first.stop() == 0
        for seq in range(20, 40):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        second = services.restart()
        report = pub.flush(30)
        assert report.confirmed, report
        assert (report.published, report.integrated, report.refused, report.lost) == (40, 40, 0, 0)
        with httpx.Client(base_url=second.base_url, timeout=10) as http:
            assert map_stats(http, "rs")["scans_integrated"] == 40
            assert_region_equal(http, "rs", engine_map(scans), LAYERS)
    finally:
        pub.close()
        services.close()


def test_replay_whose_delivery_answer_is_not_fleetmaps_says_so_and_exits_1(tmp_path: Path) -> None:
    """A delivery query answered with something that is not a fleetmap `DeliveryStatus` (another
    program's queryable on the key, a broken service) makes `flush` raise RuntimeError. `fleetmap
    replay` let it escape as a traceback; it now says its scans are not confirmed, and why, and
    exits with 1 like any replay whose scans are not confirmed."""
    log = tmp_path / "corridor.log"
    _write_carmen(log, 5)
    router = Router().start()
    assert router.session is not None
    garbage = router.session.declare_queryable(
        "fleetmap/*/*/delivery", lambda query: query.reply(query.key_expr, "not a delivery status")
    )
    try:
        command = [
            sys.executable, "-m", "fleetmap_client.cli", "replay", str(log), "--map", "rq", "--robot", "r1",
            "--rate", "0", "--connect", router.endpoint, "--quiet", "--wait-timeout", "20",
            "--confirm-timeout", "5",
        ]  # fmt: skip
        proc = subprocess.run(command, capture_output=True, text=True, timeout=60)
    finally:
        garbage.undeclare()
        router.stop()
    assert proc.returncode == 1, (proc.returncode, proc.stdout, proc.stderr)
    assert "replayed 5 scans" in proc.stdout, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "fleetmap replay: warning: not confirmed: the delivery answer is not a fleetmap one" in proc.stderr


def test_the_scans_of_a_robot_without_a_map_refused_at_the_limits_are_settled(
    memory_service: ServiceProcess,
) -> None:
    """A robot that declares no liveliness token (one written in another language: docs/protocol.md
    says it need not) and whose every scan breaks the input limits (UTM eastings as map
    coordinates) makes no map: a refused scan creates none, so the service answered `no_map` and
    nothing of them, and a flush waited for ever. The answer now lists them settled and refused,
    and says why."""
    utm = Scan.from_fan((500_000.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    session = client_session(memory_service.zenoh_endpoint)
    try:
        key = SCAN_KEY.format(map_id="utm", robot_id="r1")
        for seq in range(3):
            payload = codec.encode_binary(utm, seq, stamp=float(seq), session=79)
            session.put(key, payload, encoding=zenoh.Encoding(BINARY_ENCODING))
        selector = DELIVERY_KEY.format(map_id="utm", robot_id="r1") + "?session=79;fields=2"

        def listed() -> DeliveryStatus | None:
            # All three: the scans are answered one by one, and the first may be listed alone.
            answer = query(session, selector)
            if not isinstance(answer, DeliveryStatus) or not answer.sessions:
                return None
            entry = answer.session(79)
            return answer if entry is not None and entry.refused + entry.integrated >= 3 else None

        answer = wait_for(listed, 10, what="the three refused scans listed")
        assert isinstance(answer, DeliveryStatus) and answer.status == "no_map", answer
        entry = answer.session(79)
        assert entry is not None and (entry.settled, entry.refused, entry.integrated) == (2, 3, 0), entry
        assert answer.last_error is not None and "outside the world bound" in answer.last_error
        assert httpx.get(f"{memory_service.base_url}/maps/utm", timeout=10).status_code == 404  # still no map
    finally:
        session.close()


def test_flush_reads_an_answer_with_fields_it_does_not_know() -> None:
    """A service newer than the robot's client may add fields to its delivery answer (and its
    entries): flush reads what it knows and confirms. It raised "the delivery answer is not a
    fleetmap one" for any field it did not know, so every robot in the field failed its flush
    once the service was upgraded."""
    router = Router().start()
    assert router.session is not None

    def answer(query: zenoh.Query) -> None:
        session = int(query.parameters.get("session") or 0)
        entry = {
            "session": session, "first_seq": 0, "last_accepted": 0, "settled": 0, "integrated": 1,
            "refused": 0, "lost": 0, "duplicates": 0, "a_later_field": [1, 2],
        }  # fmt: skip
        status = {"map_id": "nf", "robot_id": "r1", "status": "ok", "sessions": [entry], "later": {"x": 1}}
        query.reply(query.key_expr, json.dumps(status))

    queryable = router.session.declare_queryable("fleetmap/*/*/delivery", answer)
    try:
        with ScanPublisher("nf", "r1", connect=[router.endpoint]) as pub:
            assert pub.wait_connected(20), pub.last_connect_error
            pub.publish(_scan())
            report = pub.flush(10)
            assert report.confirmed, report
    finally:
        queryable.undeclare()
        router.stop()


@pytest.mark.parametrize("how", ["deleted", "replaced"])
def test_flush_after_the_map_went_says_so_at_once(memory_service: ServiceProcess, how: str) -> None:
    """A robot's 10 scans are integrated, then its map is deleted (or replaced by an upload) before it
    flushes: flush without a timeout returns at once, unconfirmed, saying the map went with its
    scans, where it waited forever for a session the service no longer counted. The service knows
    it from the tombstones it keeps of the map's robots."""
    scans = scans_for(sim=15, beams=181, count=10)
    map_id = f"went-{how}"  # each case a map of its own, on the module's service
    with (
        ScanPublisher(map_id, "r1", connect=[memory_service.zenoh_endpoint]) as pub,
        httpx.Client(base_url=memory_service.base_url, timeout=10) as http,
    ):
        assert pub.wait_connected(20), pub.last_connect_error
        for seq, scan in enumerate(scans):
            pub.publish(scan, seq=seq, stamp=float(seq))
        wait_integrated(http, map_id, 10, timeout=30)
        if how == "deleted":
            assert http.delete(f"/maps/{map_id}").status_code == 204
        else:
            snapshot = http.get(f"/maps/{map_id}/snapshot").content
            assert http.put(f"/maps/{map_id}/snapshot", content=snapshot).status_code == 200
        outcome: list[object] = []
        flusher = threading.Thread(target=lambda: outcome.append(pub.flush()), daemon=True)
        flusher.start()
        flusher.join(10)
        assert not flusher.is_alive(), "flush() still waits for scans of a map that is gone"
        report = outcome[0]
        assert isinstance(report, DeliveryReport) and not report.confirmed, report
        assert (report.settled, report.integrated, report.gone, report.unsettled) == (True, 0, 10, 0), report
        assert report.summary() == "10 scans published, 0 integrated: 10 went with a deleted or replaced map"


def test_flush_after_the_map_went_midway_counts_both_parts(memory_service: ServiceProcess) -> None:
    """The map is deleted after 10 of a robot's scans; it publishes 10 more, which make a new map of
    that id: flush says 10 integrated and 10 gone with the deleted map, not confirmed."""
    scans = scans_for(sim=16, beams=181, count=20)
    with (
        ScanPublisher("midway", "r1", connect=[memory_service.zenoh_endpoint]) as pub,
        httpx.Client(base_url=memory_service.base_url, timeout=10) as http,
    ):
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(10):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        wait_integrated(http, "midway", 10, timeout=30)
        assert http.delete("/maps/midway").status_code == 204
        for seq in range(10, 20):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        report = pub.flush(20)
        got = (report.settled, report.integrated, report.gone, report.counted_from, report.confirmed)
        assert got == (True, 10, 10, 10, False), report
        assert report.summary() == "20 scans published, 10 integrated: 10 went with a deleted or replaced map"


def test_flush_of_scans_refused_for_want_of_their_map_returns_saying_so(tmp_path: Path) -> None:
    """A service that creates no map from scans (`--no-auto-create`) refuses the scans of a robot
    whose map does not exist (a map id mistyped in its configuration), and, after its map is deleted
    midway, the scans it publishes on: flush without a timeout returns at once, the scans refused
    and why, where it waited for ever (the service answered `no_map` and nothing of them)."""
    scans = scans_for(sim=17, beams=181, count=10)

    def flush_within(pub: ScanPublisher, seconds: float) -> DeliveryReport:
        outcome: list[DeliveryReport] = []
        flusher = threading.Thread(target=lambda: outcome.append(pub.flush()), daemon=True)
        flusher.start()
        flusher.join(seconds)
        assert not flusher.is_alive(), "flush() still waits for scans the service refused"
        return outcome[0]

    with (
        ServiceProcess(tmp_path, ["--in-memory", "--no-auto-create"]) as service,
        httpx.Client(base_url=service.base_url, timeout=10) as http,
    ):
        with ScanPublisher("typo", "r1", connect=[service.zenoh_endpoint]) as pub:
            assert pub.wait_connected(20), pub.last_connect_error
            for seq, scan in enumerate(scans):
                pub.publish(scan, seq=seq, stamp=float(seq))
            report = flush_within(pub, 10)
        assert (report.settled, report.integrated, report.refused, report.unsettled) == (True, 0, 10, 0), (
            report
        )
        assert report.last_error is not None and "no map 'typo' (auto-create is off)" in report.last_error
        assert "10 refused or dropped by the service (the last: " in report.summary()

        assert http.put("/maps/went").status_code == 201
        with ScanPublisher("went", "r1", connect=[service.zenoh_endpoint]) as pub:
            assert pub.wait_connected(20), pub.last_connect_error
            for seq in range(5):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            wait_integrated(http, "went", 5, timeout=30)
            assert http.delete("/maps/went").status_code == 204
            for seq in range(5, 10):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            report = flush_within(pub, 10)
        assert (report.settled, report.integrated, report.gone, report.refused) == (True, 0, 5, 5), report


def test_flush_of_scans_refused_for_want_of_room_for_the_robot_returns_saying_so(tmp_path: Path) -> None:
    """A map holds as many robots as it may (`--max-robots-per-map 1`, its robot online): a second
    robot's scans are refused (429), and its flush without a timeout returns at once saying so and
    why, where it waited for ever (the service answered `no_robot` and nothing of them)."""
    scans = scans_for(sim=20, beams=181, count=5)
    with (
        ServiceProcess(tmp_path, ["--in-memory", "--max-robots-per-map", "1"]) as service,
        ScanPublisher("full", "r1", connect=[service.zenoh_endpoint]) as first,
    ):
        assert first.wait_connected(20), first.last_connect_error
        first.publish(scans[0])
        assert first.flush(10).confirmed  # the map's one robot, online
        # Only now: its liveliness token would make it the map's robot, online, before the first.
        second = ScanPublisher("full", "r2", connect=[service.zenoh_endpoint])
        try:
            assert second.wait_connected(20), second.last_connect_error
            for scan in scans:
                second.publish(scan)
            outcome: list[DeliveryReport] = []
            flusher = threading.Thread(target=lambda: outcome.append(second.flush()), daemon=True)
            flusher.start()
            flusher.join(10)
            assert not flusher.is_alive(), "flush() still waits for scans the service refused"
        finally:
            second.close()
        report = outcome[0]
        assert (report.settled, report.integrated, report.refused) == (True, 0, 5), report
        assert report.last_error is not None and "already has 1 robots, the most it" in report.last_error


def test_a_robot_restarted_midway_learns_what_became_of_its_previous_sessions_scans(
    durable_service: ServiceProcess,
) -> None:
    """A robot publishes 10 scans, drives into a dead zone, publishes 10 more into its backlog, and
    its process restarts there (the backlog goes with it). The new process's publisher confirms its
    own 5 scans; `flush_ended` on the previous session, whose id and seqs the robot saved, says
    without a timeout that 10 of its 20 are in the map and 10 lost: the robot knows to drive that
    part again. `flush` alone confirmed the new session and said nothing of the old one."""
    scans = scans_for(sim=18, beams=181, count=20)
    with (
        httpx.Client(base_url=durable_service.base_url, timeout=10) as http,
    ):
        proxy = FreezableProxy(durable_service.zenoh_port)
        before = ScanPublisher("reboot", "r1", connect=[proxy.endpoint])
        try:
            publish_then_cut(before, proxy, http, "reboot", scans, 10)
            for seq in range(10, 20):
                assert before.publish(scans[seq], seq=seq, stamp=float(seq))
            saved = (before.session_id, 0, before.last_seq)
        finally:
            before.close()  # the process died: its backlog with it
            proxy.close()
        assert saved[0] is not None and saved[2] == 19
        with ScanPublisher("reboot", "r1", connect=[durable_service.zenoh_endpoint]) as pub:
            assert pub.wait_connected(20), pub.last_connect_error
            for seq in range(5):
                pub.publish(scans[seq], seq=seq, stamp=100.0 + seq)
            assert pub.flush(10).confirmed
            outcome: list[DeliveryReport] = []
            asker = threading.Thread(target=lambda: outcome.append(pub.flush_ended(*saved)), daemon=True)
            asker.start()
            asker.join(10)
            assert not asker.is_alive(), "flush_ended waits for scans that went with the old process"
            report = outcome[0]
            assert (report.published, report.integrated, report.lost, report.settled) == (20, 10, 10, True)
            assert not report.confirmed and report.summary() == "20 scans published, 10 integrated: 10 lost"
            # A session the service never heard of: nothing to wait for, nothing confirmed.
            unknown = pub.flush_ended(12345, 0, 9, timeout=10)
            assert (unknown.answered, unknown.settled, unknown.unsettled) == (True, False, 10), unknown


def test_flush_ended_takes_the_session_id_a_publisher_without_one_saved(
    memory_service: ServiceProcess,
) -> None:
    """A robot whose publisher sends no session id (`send_session_id=False`, for a service older
    than session ids) saves `pub.session_id`, None, as docs/clients.md says, and asks about its
    previous process's scans with it: `flush_ended` refused None ("session_id must be an integer"),
    though it asks about scans without a session id when given 0, and its type said `int` where
    `session_id` is `int | None`. None now asks about them."""
    scans = scans_for(sim=18, beams=91, count=5)
    connect = [memory_service.zenoh_endpoint]
    with ScanPublisher("nosession", "r1", connect=connect, send_session_id=False) as before:
        assert before.wait_connected(20), before.last_connect_error
        for seq, scan in enumerate(scans):
            assert before.publish(scan, seq=seq, stamp=float(seq))
        assert before.flush(20).confirmed
        saved = (before.session_id, 0, before.last_seq)
    assert saved == (None, 0, 4)
    with ScanPublisher("nosession", "r1", connect=connect, send_session_id=False) as pub:
        assert pub.session_id is None
        report = pub.flush_ended(*saved, timeout=20)
    assert report.confirmed and (report.published, report.integrated, report.settled) == (5, 5, True), report


def test_flush_and_wait_connected_refuse_a_timeout_that_is_not_a_number() -> None:
    """A timeout of NaN (a robot's configuration read badly) made flush and wait_connected wait for
    ever, as no time is ever past NaN: now a ValueError at once, and a string a TypeError naming the
    timeout rather than Python's "unsupported operand type(s)"."""
    with ScanPublisher("to", "r1", connect=["tcp/127.0.0.1:9"]) as pub:  # nothing listens there
        pub.publish(_scan())
        for call in (pub.flush, pub.wait_connected):
            outcome: list[BaseException] = []

            def run(call: Any = call, outcome: list[BaseException] = outcome) -> None:
                try:
                    call(float("nan"))
                except ValueError as exc:
                    outcome.append(exc)

            waiter = threading.Thread(target=run, daemon=True)
            waiter.start()
            waiter.join(5)
            assert not waiter.is_alive(), f"{call.__name__}(nan) still waits"
            assert outcome and "NaN" in str(outcome[0]), outcome
            with pytest.raises(TypeError, match="timeout must be a number of seconds or None"):
                call("5")
        assert not pub.flush(0.2).answered  # a number still works


@pytest.mark.parametrize("backlog", [10, 0])
def test_scans_given_up_before_the_first_connection_are_reported_lost(tmp_path: Path, backlog: int) -> None:
    """A robot that starts before the service and publishes more than its backlog (or anything with
    backlog 0) gives up its first scans. The service counts from the first scan it gets, so it knew
    nothing of them and the flush, final (`settled`), called them "unconfirmed"; the publisher
    knows it never sent them: they are lost, as docs/clients.md says ("dropped on the robot, lost
    at the service")."""
    near = Scan.from_fan((5.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    service = ServiceProcess(tmp_path, ["--in-memory"])
    with ScanPublisher("early", "r1", connect=[service.zenoh_endpoint], backlog=backlog) as pub:
        for _ in range(15):
            pub.publish(near)
        with service:  # (starts it: `with service.start()` started a second one, and left the first)
            assert pub.wait_connected(20), pub.last_connect_error
            for _ in range(5):
                pub.publish(near)
            report = pub.flush(10)
    given_up = 5 if backlog else 15
    assert pub.dropped == given_up
    assert report.settled and (report.published, report.integrated) == (20, 20 - given_up), report
    assert (report.lost, report.unsettled, report.counted_from) == (given_up, 0, given_up), report
    assert report.summary() == f"20 scans published, {20 - given_up} integrated: {given_up} lost"


def test_flush_ended_refuses_ids_past_the_wires_bounds_at_once() -> None:
    """`flush_ended` of a session id at or past 2**53, or a seq at or past 2**63 (a saved value read
    back wrong), is a ValueError at once: a reachable service answered the first with an error reply
    (RuntimeError, "the delivery query failed"), the second made a report of 2**63 scans
    "unconfirmed", and with no service reachable both waited for the timeout."""
    with ScanPublisher("to", "r1", connect=["tcp/127.0.0.1:9"]) as pub:  # nothing listens there
        for args, words in [
            ((2**53, 0, 1), "session_id must be an integer in [0, 2**53)"),
            ((5, 0, 2**63), "last_seq must be an integer in [0, 2**63)"),
            ((5, 2**63, 2**63 + 1), "first_seq must be an integer in [0, 2**63)"),
            ((5, -1, 1), "first_seq must be an integer in [0, 2**63)"),
        ]:
            started = time.monotonic()
            with pytest.raises(ValueError, match=re.escape(words)):
                pub.flush_ended(*args, timeout=3)
            assert time.monotonic() - started < 1
        assert not pub.flush_ended(2**53 - 1, 0, 2**63 - 1, timeout=0.2).answered  # the bounds themselves


def test_flush_counts_the_scans_through_its_last_seq_only(memory_service: ServiceProcess) -> None:
    """A robot flushes in a dead zone (its scans through seq 19 published, seq 15 one the service
    refuses) and goes on publishing meanwhile (seq 25 refused too); the link comes back and the
    backlog arrives at once, so the service's counts take in scans published after the flush began.
    The report counts the scans through 19 only: 19 integrated, 1 refused. It said "20 scans
    published, 20 integrated: 2 refused", more than were published and one integrated too many."""
    scans = scans_for(sim=19, beams=181, count=30)
    utm = Scan.from_fan((500_000.0, 5.0, 0.0), -1.0, 0.1, [1.0] * 20, 0.05, 10.0)
    with (
        httpx.Client(base_url=memory_service.base_url, timeout=10) as http,
    ):
        proxy = FreezableProxy(memory_service.zenoh_port)
        pub = ScanPublisher("through", "r1", connect=[proxy.endpoint])
        try:
            publish_then_cut(pub, proxy, http, "through", scans, 10)
            for seq in range(10, 20):
                assert pub.publish(utm if seq == 15 else scans[seq], seq=seq, stamp=float(seq))
            outcome: list[DeliveryReport] = []
            flusher = threading.Thread(target=lambda: outcome.append(pub.flush(20)), daemon=True)
            flusher.start()
            time.sleep(0.3)  # flush asks about seqs 0 .. 19
            for seq in range(20, 30):
                assert pub.publish(utm if seq == 25 else scans[seq], seq=seq, stamp=float(seq))
            proxy.restore()
            flusher.join(25)
            report = outcome[0]
            assert (report.published, report.integrated, report.refused, report.lost) == (20, 19, 1, 0), (
                report
            )
            assert report.settled and not report.confirmed
            everything = pub.flush(20)
            assert (everything.published, everything.integrated, everything.refused) == (30, 28, 2), (
                everything
            )
        finally:
            pub.close()
            proxy.close()


def test_flush_after_close_says_to_flush_first() -> None:
    """A robot that closes its publisher (a `with` block ended) and then flushes learns that the
    order was wrong, and why it matters, not only that the publisher is closed."""
    pub = ScanPublisher("fc", "r1", connect=["tcp/127.0.0.1:9"])  # nothing listens there
    pub.publish(_scan())
    pub.close()
    with pytest.raises(
        PublisherClosed, match=r"flush before close\(\), which gives up the scans not delivered"
    ):
        pub.flush(1)


@pytest.mark.parametrize("how", ["deleted", "replaced"])
def test_refusals_from_before_a_robot_was_on_its_map_do_not_hold_up_its_flush_after_the_map_went(
    how: str,
) -> None:
    """A robot's scans refused for want of its map (`--no-auto-create`; likewise of room on it),
    then, once the map was created, 5 integrated, then the map deleted (or replaced by an upload):
    the refusals the service
    remembered from before the robot was on the map were its answer again (`no_map`), settled only
    through seq 4, and covered up the tombstone's "in no map now" (`buried`) for seqs 0 to 9: a
    flush of seqs 0 to 9 never settled, where it returned at once saying they went with the map."""
    reg = MapRegistry(auto_create=False)  # workers not started: nothing is integrated, nor needs to be
    for seq in range(5):
        with pytest.raises(IngestRejected, match="no map"):
            reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
    reg.create("m")
    for seq in range(5, 10):
        reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
    if how == "deleted":
        reg.delete("m")
    else:
        reg.replace("m", GridMap(MapConfig()))
    status = reg.delivery_status("m", "r", 7)
    assert [entry.last_seq for entry in status.buried] == [9], status
    report = delivery_report(status, 7, 0, 9)
    assert (report.settled, report.gone, report.confirmed) == (True, 10, False), (report, status)
    reg.close()


@pytest.mark.parametrize("want", ["map", "room"])
def test_scans_refused_before_a_robot_was_on_its_map_count_as_refused_once_it_is(want: str) -> None:
    """A robot started before its map was made (`--no-auto-create`), or while the map was full of
    online robots: its first scans are refused and remembered, its flush says so. Once the map
    was made (or had room) and took its next scans, the answer listed the session from its first
    scan on the map only, and the refused scans, which the service still remembered, vanished from
    it: "12 scans published, 6 integrated: 5 unconfirmed" with `settled` true and no `last_error`,
    where docs/clients.md promises they count as refused, saying why."""
    reg = MapRegistry(auto_create=want == "room", max_robots_per_map=1)
    reg.start()
    try:
        if want == "room":
            reg.set_online("m", "other", True)  # the map's one robot, online: no room for "r"
        for seq in range(5):
            with pytest.raises(IngestRejected, match="no map" if want == "map" else "already has 1 robots"):
                reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
        if want == "map":
            reg.create("m")
        else:
            reg.set_online("m", "other", False)  # gone: forgotten to make room for "r"
        futures = [reg.submit("m", "r", WireScan(s, float(s), _scan(), 7), wait=True) for s in range(6, 12)]
        for future in futures:
            assert future is not None
            future.result(timeout=30)
        status = reg.delivery_status("m", "r", 7)
        report = delivery_report(status, 7, 0, 11)  # seq 5 never came: lost
        assert (report.settled, report.integrated, report.refused, report.lost, report.unsettled) == (
            True, 6, 5, 1, 0,
        ), (report, status)  # fmt: skip
        assert report.counted_from == 0 and not report.confirmed, report
        reason = "no map 'm' (auto-create is off)" if want == "map" else "already has 1 robots"
        assert report.last_error is not None and reason in report.last_error, report
        # A flush of the first seqs only, while the robot publishes on: those, refused, one by one.
        early = delivery_report(status, 7, 0, 2)
        assert (early.settled, early.integrated, early.refused, early.lost) == (True, 0, 3, 0), early
    finally:
        reg.close()


def test_a_scan_of_a_deleted_maps_robot_refused_again_at_the_limits_does_not_hold_up_its_flush() -> None:
    """A deleted map's robot's cache fetched again (after a restart of the service, or of its link):
    its copies are ignored as from before the deletion (the tombstone), but a copy refused at the
    input limits (a pose outside the world bound) was remembered as a refused scan of a robot
    without a map, from that seq on: it covered up the tombstone's "in no map now" for the earlier
    seqs, and a flush of the session never settled, where it returned at once saying they went."""
    reg = MapRegistry()  # workers not started
    for seq in range(10):
        reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
    reg.delete("m")
    assert delivery_report(reg.delivery_status("m", "r", 7), 7, 0, 9).gone == 10
    reg.reject("m", "r", "scan seq 7 refused: pose (1e+06, 0) is outside the world bound", (7, 7.0, 7))
    status = reg.delivery_status("m", "r", 7)
    report = delivery_report(status, 7, 0, 9)
    assert (report.settled, report.gone, report.refused) == (True, 10, 0), (report, status)
    assert status.sessions == [] and status.last_error is None, status
    reg.close()


@pytest.mark.parametrize("refusal", ["the memory budget is used up", "the queue is full"])
def test_scans_refused_on_a_map_they_created_are_settled_once_the_map_is_removed_again(refusal: str) -> None:
    """A map created by a robot's scans (auto-create) is removed again when every scan that reached
    it was refused (the memory budget used up, 507; the full queue, 503): its robot's ledger went
    with it, and the delivery query answered `no_map` and nothing of them, so the robot's flush
    waited until its timeout, for ever without one, for scans the service had refused."""
    budget = refusal.startswith("the memory")
    if budget:
        reg = MapRegistry(workers=1, memory_budget=MemoryBudget(1))
        reg.start()
    else:
        reg = MapRegistry(queue_bytes=100)  # less than one scan of 30 beams
    try:
        futures = []
        for seq in range(3):
            try:
                futures.append(reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7), wait=True))
            except IngestRejected as exc:
                assert exc.status == 503 and "removed again" in exc.reason, exc
        for future in futures:
            with pytest.raises(IngestRejected):
                future.result(timeout=120)
        assert wait_idle(reg, 120)
        status = reg.delivery_status("m", "r", 7)
        assert status.status == "no_map", status
        report = delivery_report(status, 7, 0, 2)
        assert (report.settled, report.refused, report.integrated) == (True, 3, 0), (report, status)
        expected = "memory budget" if budget else "ingest queue full"
        assert report.last_error is not None and expected in report.last_error, report
    finally:
        reg.close()


def test_scans_of_more_robots_under_one_id_refused_on_a_map_they_created_are_all_settled() -> None:
    """As above, with more robots under one id than `MAX_SESSIONS`: only the robot's recent sessions
    were remembered when the map was removed again, and the flushes of those pushed out of them
    (`RobotState.pushed_out`), told a bare `no_map`, waited until their timeout."""
    reg = MapRegistry(workers=1, memory_budget=MemoryBudget(1))
    count = MAX_SESSIONS + 2
    try:
        futures = [  # all queued before a worker runs: one map holds every session
            reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 100 + k), wait=True)
            for seq in range(3)
            for k in range(count)
        ]
        reg.start()
        for future in futures:
            with pytest.raises(IngestRejected):
                future.result(timeout=120)
        assert wait_idle(reg, 120)
        for k in range(count):
            status = reg.delivery_status("m", "r", 100 + k)
            report = delivery_report(status, 100 + k, 0, 2)
            assert (status.status, report.settled, report.refused) == ("no_map", True, 3), (k, report, status)
    finally:
        reg.close()


def test_a_copy_refused_at_the_limits_of_a_scan_from_before_its_map_went_changes_nothing() -> None:
    """A deleted map's robot's cache, fetched again, holds a scan the input limits refuse: on the
    map created again under that id it is ignored as `submit` ignores the other copies (the
    tombstone), before anything else. It made the full map forget an idle robot to make room for
    the old robot, whose new state held nothing but that copy."""
    reg = MapRegistry(max_robots_per_map=1)  # workers not started
    for seq in range(10):
        reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
    reg.delete("m")
    reg.create("m")
    reg.reject("m", "x", "undecodable")  # an idle robot on the new map, which is full
    reg.reject("m", "r", "scan seq 7 refused: pose (1e+06, 0) is outside the world bound", (7, 7.0, 7))
    entry = reg.get("m")
    assert sorted(entry.robots) == ["x"] and entry.scans_rejected == 1
    reg.close()


def test_refusals_of_more_robots_under_one_id_than_its_recent_sessions_settle_every_flush() -> None:
    """More robots under one robot id than `MAX_SESSIONS` (a fleet started from one image with its
    default id), their map not created (`--no-auto-create`): the refusals of 8 sessions a robot were
    remembered, each new one pushed the oldest out, and those robots' flushes, told a bare `no_map`,
    waited until their timeout (seen on the real service: ten `ScanPublisher`s under one id, the
    first two flushes took their 8 s timeout). As many are remembered as the service tells apart on a
    map; the query lists the 8 refused most recently unless asked for one."""
    count = MAX_SESSIONS + 2
    reg = MapRegistry(auto_create=False)  # workers not started: nothing is integrated
    for seq in range(3):
        for k in range(count):
            with pytest.raises(IngestRejected, match="no map"):
                reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 100 + k))
    for k in range(count):
        status = reg.delivery_status("m", "r", 100 + k)
        report = delivery_report(status, 100 + k, 0, 2)
        assert (status.status, report.settled, report.refused) == ("no_map", True, 3), (k, report, status)
        assert status.last_error is not None and "auto-create is off" in status.last_error
    listed = reg.delivery_status("m", "r").sessions
    assert [entry.session for entry in listed] == [100 + k for k in range(2, count)]
    reg.close()


def test_refusals_under_made_up_ids_do_not_push_out_a_real_robots_refused_scans() -> None:
    """A robot with a liveliness token (a real `ScanPublisher` declares one) whose scans were
    refused for want of its map, then scans refused under more made-up map and robot ids than the
    service remembers robots so (out-of-limits scans, which create no map, from any Zenoh peer):
    the made-up ones without a token are forgotten first. The real robot's refusals were pushed
    out, the query answered a bare `no_map`, and its flush waited until its timeout."""
    reg = MapRegistry(auto_create=False)  # workers not started: nothing is integrated
    reg.set_online("m", "r", True)
    for seq in range(5):
        with pytest.raises(IngestRejected, match="no map"):
            reg.submit("m", "r", WireScan(seq, float(seq), _scan(), 7))
    for k in range(MAX_UNMAPPED_ROBOTS + 10):
        reg.reject(f"fake{k % 300}", f"x{k}", "scan seq 0 refused: 99999 beams", (0, 0.0, 1 + k))
    assert len(reg.unmapped) == MAX_UNMAPPED_ROBOTS  # the bound holds
    status = reg.delivery_status("m", "r", 7)
    report = delivery_report(status, 7, 0, 4)
    assert (status.status, report.settled, report.refused) == ("no_map", True, 5), (report, status)
    assert status.last_error is not None and "no map" in status.last_error, status
    # The made-up ones are forgotten oldest first; without tokens, a real robot's would be too.
    assert reg.delivery_status("fake0", "x0").sessions == []
    last = MAX_UNMAPPED_ROBOTS + 9
    assert reg.delivery_status(f"fake{last % 300}", f"x{last}").sessions != []
    reg.close()
