"""The robot-side Python clients over real Zenoh: `ScanPublisher`, `fleetmap replay`, `fleetmap sim`.

The service side here is a real Zenoh ROUTER session in the test process (what `fleetmap serve` runs)
listening on a free loopback port and subscribing to the scan and liveliness keys, so these tests
check exactly what goes over the wire; tests/test_client_rest.py drives the real service.
"""

from __future__ import annotations

import argparse
import math
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
import zenoh.ext
from fleetmap_client import cli
from fleetmap_client import sim as sim_module
from fleetmap_client.delivery import DeliveryReport
from fleetmap_client.publisher import RECONNECT_HOLD_MAX_S, PublisherClosed, ScanPublisher
from fleetmap_client.replay import NOMINAL_SCAN_RATE, ReplayError, replay
from fleetmap_client.sim import SimError, SimResult, check_fleet, robot_ids, run_sim
from fleetmap_client.zenoh_config import client_config, config_value, connect_endpoints
from service_process import DATASETS_DIR, FreezableProxy, ServiceProcess, free_port, reaped, wait_for

from fleetmap.codec import WireScan, decode, encode_json
from fleetmap.datasets import load_dataset
from fleetmap.scan import Scan, ScanError
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.wire import ALIVE_KEY_WILDCARD, BINARY_ENCODING, JSON_ENCODING, SCAN_KEY_WILDCARD, ScanMessage


class Router:
    """A Zenoh router session recording every scan sample and liveliness change it sees. Its scan
    subscriber is zenoh-ext's advanced subscriber with the service's settings (`ingest.ZenohIngest`),
    so it fetches what advanced publishers kept for it (their backlog), as the service does.

    Callbacks only append raw samples (they run on Zenoh threads and must not block); decoding
    happens when a test reads them."""

    def __init__(self, port: int | None = None, plain: bool = False, upstream: str | None = None) -> None:
        #: `plain`: a plain subscriber instead, which never queries publishers' caches (a subscriber
        #: that is not a fleetmap service, or a router with no service behind it yet).
        self.plain = plain
        #: `upstream`: a router's endpoint to join as a peer, as `fleetmap serve --zenoh-connect`
        #: does, robots publishing through that router.
        self.upstream = upstream
        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self._lock = threading.Lock()
        self._samples: list[tuple[str, str, bytes]] = []
        self.misses = 0  # samples zenoh-ext reported as unrecoverable
        self._alive: list[tuple[str, zenoh.SampleKind]] = []
        self.session: zenoh.Session | None = None

    def start(self) -> Router:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"router"' if self.upstream is None else '"peer"')
        cfg.insert_json5("listen/endpoints", f'["{self.endpoint}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        if self.upstream is not None:
            cfg.insert_json5("connect/endpoints", f'["{self.upstream}"]')
        self.session = zenoh.open(cfg)
        if self.plain:
            self._subs = [self.session.declare_subscriber(SCAN_KEY_WILDCARD, self._on_scan)]
            return self
        scans = zenoh.ext.declare_advanced_subscriber(
            self.session,
            SCAN_KEY_WILDCARD,
            self._on_scan,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True,
        )
        self._subs: list[Any] = [
            scans.sample_miss_listener(self._on_miss),
            scans,
            self.session.liveliness().declare_subscriber(ALIVE_KEY_WILDCARD, self._on_alive, history=True),
        ]
        return self

    def stop(self) -> None:
        if self.session is not None:
            for sub in self._subs:
                sub.undeclare()
            self.session.close()
            self.session = None

    def _on_scan(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._samples.append((str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes()))

    def _on_miss(self, miss: zenoh.ext.Miss) -> None:
        with self._lock:
            self.misses += miss.nb

    def _on_alive(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._alive.append((str(sample.key_expr), sample.kind))

    def samples(self) -> list[tuple[str, str, bytes]]:
        with self._lock:
            return list(self._samples)

    def scans(self, key: str | None = None) -> list[tuple[str, str, WireScan]]:
        """(key, encoding, decoded scan) of every sample so far (of `key` only, if given)."""
        return [(k, e, decode(p, e)) for k, e, p in self.samples() if key is None or k == key]

    def wait_count(
        self, n: int, key: str | None = None, timeout: float = 10.0
    ) -> list[tuple[str, str, WireScan]]:
        wait_for(lambda: len(self.scans(key)) >= n, timeout, 0.02, f"{n} scans on {key or 'any key'}")
        return self.scans(key)

    def alive_events(self) -> list[tuple[str, zenoh.SampleKind]]:
        with self._lock:
            return list(self._alive)

    def online(self) -> set[str]:
        """Keys whose last liveliness event is PUT."""
        state: dict[str, bool] = {}
        for key, kind in self.alive_events():
            state[key] = kind == zenoh.SampleKind.PUT
        return {k for k, up in state.items() if up}


@pytest.fixture
def router() -> Iterator[Router]:
    r = Router().start()
    yield r
    r.stop()


@pytest.fixture(scope="module")
def sim_scans() -> list[Scan]:
    """Exact simulated scans (with "no return" beams as +inf) from a small floor plan."""
    plan = generate_floorplan(3, width_m=20.0, height_m=15.0)
    robot = SimulatedRobot(plan, seed=5, num_beams=361, range_max=8.0)
    return [robot.tick() for _ in range(6)]


def _assert_same_scan(got: WireScan, sent: Scan, seq: int, stamp: float, encoding: str) -> None:
    assert got.seq == seq
    assert got.stamp == stamp
    assert (got.scan.pose.x, got.scan.pose.y, got.scan.pose.theta) == (
        sent.pose.x,
        sent.pose.y,
        sent.pose.theta,
    )
    assert got.scan.range_min == pytest.approx(sent.range_min, rel=1e-7)
    assert got.scan.range_max == pytest.approx(sent.range_max, rel=1e-7)
    if encoding == "binary":
        # Ranges and the angle increment travel as float32 (docs/protocol.md).
        np.testing.assert_array_equal(got.scan.ranges, sent.ranges.astype(np.float32).astype(np.float64))
        np.testing.assert_allclose(got.scan.angles, sent.angles, rtol=0, atol=1e-5)
    else:
        np.testing.assert_array_equal(got.scan.ranges, sent.ranges)
        np.testing.assert_allclose(got.scan.angles, sent.angles, rtol=0, atol=1e-12)


# -- ScanPublisher ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("encoding", "zenoh_encoding"), [("binary", BINARY_ENCODING), ("json", JSON_ENCODING)]
)
def test_scans_arrive_decoded_identically(
    router: Router, sim_scans: list[Scan], encoding: str, zenoh_encoding: str
) -> None:
    assert any(np.isinf(s.ranges).any() for s in sim_scans), "the scans should include no-return beams"
    with ScanPublisher("lab", "r1", connect=[router.endpoint], encoding=encoding) as pub:  # type: ignore[arg-type]
        assert pub.wait_connected(10)
        stamps = [1000.0 + 0.1 * k for k in range(len(sim_scans))]
        for scan, stamp in zip(sim_scans, stamps, strict=True):
            assert pub.publish(scan, stamp=stamp) is True
        got = router.wait_count(len(sim_scans))
    assert [k for k, _, _ in got] == ["fleetmap/lab/r1/scan"] * len(sim_scans)
    assert {e for _, e, _ in got} == {zenoh_encoding}
    for k, ((_, _, wire), scan) in enumerate(zip(got, sim_scans, strict=True)):
        _assert_same_scan(wire, scan, k, stamps[k], encoding)
    assert pub.published == len(sim_scans) and pub.dropped == 0


def test_seq_auto_increments_and_follows_explicit_seq(router: Router, sim_scans: list[Scan]) -> None:
    with ScanPublisher("lab", "r2", connect=[router.endpoint]) as pub:
        assert pub.next_seq == 0 and pub.last_seq is None
        assert pub.wait_connected(10)
        pub.publish(sim_scans[0])
        pub.publish(sim_scans[1])
        pub.publish(sim_scans[2], seq=10)
        pub.publish(sim_scans[3])
        assert pub.last_seq == 11 and pub.next_seq == 12
        # A ScanMessage brings its own seq and stamp.
        pub.publish(ScanMessage.from_scan(sim_scans[4], seq=40, stamp=4.5))
        got = router.wait_count(5)
    assert [w.seq for _, _, w in got] == [0, 1, 10, 11, 40]
    assert got[-1][2].stamp == 4.5
    stamps = [w.stamp for _, _, w in got[:4]]
    assert all(abs(s - time.time()) < 60 for s in stamps), "default stamps are the wall-clock time"


@pytest.mark.parametrize("encoding", ["binary", "json"])
def test_each_publisher_sends_its_own_session_id_and_a_new_one_when_its_seq_starts_again(
    router: Router, sim_scans: list[Scan], encoding: str
) -> None:
    """Every scan carries the publisher's random session id; another publisher has another one;
    an explicit seq below the last one starts a new session (under the old one the service would
    ignore the scans as duplicates), while the last seq again is a resend (the replay command's, of
    a scan dropped while disconnected) in the same session; `send_session_id=False` sends none."""
    with (
        ScanPublisher("lab", "s1", connect=[router.endpoint], encoding=encoding) as pub,  # type: ignore[arg-type]
        ScanPublisher("lab", "s2", connect=[router.endpoint], encoding=encoding) as other,  # type: ignore[arg-type]
        ScanPublisher(
            "lab", "s3", connect=[router.endpoint], encoding=encoding, send_session_id=False
        ) as none,  # type: ignore[arg-type]
    ):
        first = pub.session_id
        assert first is not None and first != other.session_id and none.session_id is None
        for p in (pub, other, none):
            assert p.wait_connected(10)
        pub.publish(sim_scans[0])
        pub.publish(sim_scans[1], seq=5)  # forward: the same session
        pub.publish(sim_scans[1], seq=5)  # a resend: the same session
        assert pub.session_id == first
        pub.publish(sim_scans[2], seq=4)  # below the last: the seq starts again
        restarted = pub.session_id
        pub.publish(sim_scans[3])
        other.publish(sim_scans[0])
        none.publish(sim_scans[0])
        got = router.wait_count(5, "fleetmap/lab/s1/scan")
        assert [(w.seq, w.session) for _, _, w in got] == [
            (0, first), (5, first), (5, first), (4, restarted), (5, restarted),
        ]  # fmt: skip
        assert restarted not in (None, first)
        assert router.wait_count(1, "fleetmap/lab/s2/scan")[0][2].session == other.session_id
        assert router.wait_count(1, "fleetmap/lab/s3/scan")[0][2].session is None


def test_liveliness_token_follows_the_publisher(router: Router) -> None:
    pub = ScanPublisher("lab", "robot-7", connect=[router.endpoint])
    assert pub.wait_connected(10)
    wait_for(lambda: "fleetmap/lab/robot-7/alive" in router.online(), 5, 0.02, "the liveliness token")
    pub.close()
    wait_for(lambda: "fleetmap/lab/robot-7/alive" not in router.online(), 5, 0.02, "the token withdrawn")
    kinds = [kind for key, kind in router.alive_events() if key == "fleetmap/lab/robot-7/alive"]
    assert kinds == [zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE]


def test_publisher_started_before_the_router_keeps_its_scans_and_sends_them_first(
    sim_scans: list[Scan],
) -> None:
    """Scans published before the session opened wait in the pre-open queue (at most `backlog`: the
    oldest give way, counted as dropped) and leave first, in seq order, once it opens."""
    router = Router()  # not started: nothing listens on its port yet
    with ScanPublisher("lab", "early", connect=[router.endpoint], backlog=2) as pub:
        assert pub.wait_connected(0.5) is False
        assert not pub.connected
        for seq in range(3):  # kept, not sent: the third pushes the first out
            assert pub.publish(sim_scans[seq]) is True
        assert (pub.pending, pub.backlogged, pub.dropped, pub.published) == (2, 2, 1, 0)
        router.start()
        try:
            assert pub.wait_connected(15), f"no connection; last error {pub.last_connect_error}"
            assert pub.connected and pub.subscribed
            for scan in sim_scans[3:5]:
                assert pub.publish(scan)
            got = router.wait_count(4)
            assert [w.seq for _, _, w in got] == [1, 2, 3, 4]  # seq 0 was pushed out
            assert (pub.pending, pub.backlogged, pub.dropped, pub.published) == (0, 0, 1, 4)
            wait_for(lambda: "fleetmap/lab/early/alive" in router.online(), 5, 0.02, "the token")
        finally:
            router.stop()


def test_a_first_connection_holds_scans_briefly_where_no_one_fetches_the_cache(sim_scans: list[Scan]) -> None:
    """A publisher's first connection, to a router whose subscriber never queries caches: its
    queued scans leave after the short hold (`RECONNECT_HOLD_S`), not after the longest one, which
    waits for a service's fetch. Zenoh's cache holds nothing yet, so no fetch can be lost to them;
    waiting for one held the first scans 5 s, past `fleetmap replay`'s --wait-timeout of 2 s (seen
    in CI, where the first query of a loaded service came late)."""
    router = Router(plain=True).start()
    try:
        with ScanPublisher("lab", "first", connect=[router.endpoint]) as pub:
            assert pub.publish(sim_scans[0])  # queued until the session connects and the hold ends
            started = time.monotonic()
            assert pub.wait_connected(15), f"no connection; last error {pub.last_connect_error}"
            held = time.monotonic() - started
            assert held < RECONNECT_HOLD_MAX_S - 1.0, f"the first connection held scans {held:.2f} s"
            assert [w.seq for _, _, w in router.wait_count(1)] == [0]
    finally:
        router.stop()


def test_a_publisher_starts_no_zenoh_callback_thread_that_nothing_joins(
    router: Router, sim_scans: list[Scan]
) -> None:
    """zenoh-python runs a Python callback on a thread it starts, a daemon when the declaring thread
    is one (the publisher's opener is). Nothing joins such a thread: one that wakes as its
    declaration goes at exit comes back into a finalizing interpreter, and the process dies with
    "FATAL: exception not rethrown" (SIGABRT). CI saw `fleetmap replay` die so, one run in about
    thirty, after its last message. The publisher declares no callback: while it connects, fetches
    and is closed, no such thread appears."""

    def zenoh_daemon_threads() -> set[int | None]:
        return {t.ident for t in threading.enumerate() if t.daemon and "pyo3-closure" in t.name}

    def publisher_threads() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name.endswith("-lab-threads")]

    before = zenoh_daemon_threads()
    with ScanPublisher("lab", "threads", connect=[router.endpoint]) as pub:
        assert pub.wait_connected(15), f"no connection; last error {pub.last_connect_error}"
        for seq in range(3):
            assert pub.publish(sim_scans[seq])
        assert [w.seq for _, _, w in router.wait_count(3)] == [0, 1, 2]  # the router fetched the cache too
        assert zenoh_daemon_threads() - before == set()
        assert len(publisher_threads()) == 2  # the opener (then link watcher) and the fetch watcher
    assert publisher_threads() == []  # close() joined them


def test_a_publisher_left_open_is_closed_at_exit(router: Router, tmp_path: Path) -> None:
    """A program that ends without closing its publisher: the publisher is closed at exit, while the
    interpreter still runs its threads (which wait in Zenoh's calls: coming back from one during
    finalization aborts the process), and the program exits normally, its scan delivered."""
    program = tmp_path / "left_open.py"
    program.write_text(
        "import atexit, threading\n"
        "# Registered first, so it runs last: after the publisher module's own exit handler.\n"
        "atexit.register(lambda: print('closed', PUB.closed, 'threads', sorted(\n"
        "    t.name for t in threading.enumerate() if t.name.endswith('-lab-left'))))\n"
        "from fleetmap.sim import SimulatedRobot, generate_floorplan\n"
        "from fleetmap_client.publisher import ScanPublisher\n"
        f"PUB = ScanPublisher('lab', 'left', connect=['{router.endpoint}'])\n"
        "assert PUB.wait_connected(15), PUB.last_connect_error\n"
        "robot = SimulatedRobot(generate_floorplan(1), num_beams=91, seed=1)\n"
        "PUB.publish(robot.tick())\n"
    )
    done = subprocess.run([sys.executable, str(program)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, (done.returncode, done.stdout, done.stderr)
    assert done.stdout.strip() == "closed True threads []", done.stdout
    assert [w.seq for _, _, w in router.wait_count(1, "fleetmap/lab/left/scan")] == [0]


# A program that makes a publisher whose opener is inside a connection attempt when the program
# ends (a silent endpoint: each attempt lasts `CONNECT_ATTEMPT_MS`), closed first with `close`
# giving up on the attempt at once ("close"), or never closed ("open"). Its own atexit hook,
# registered before fleetmap_client's and so run after it, says what was left running.
_EXIT_PROGRAM = """
import atexit, sys, time
left = {}
atexit.register(lambda: print(f"opener alive {left['opener'].is_alive()} closed {left['pub'].closed}"))
from fleetmap_client import publisher
publisher.CLOSE_WAIT_S = 0.05
pub = publisher.ScanPublisher("lab", "exit", connect=[sys.argv[1]])
left["pub"], left["opener"] = pub, pub._opener
time.sleep(0.3)
if sys.argv[2] == "close":
    pub.close()
    print(f"after close: opener alive {pub._opener.is_alive()}")
"""


@pytest.mark.parametrize("how", ["close", "open"])
def test_a_program_ends_with_no_publisher_thread_left_inside_zenoh(how: str) -> None:
    """The opener is a daemon thread, which nothing joins: one that came back from `zenoh.open` (or
    any Zenoh call that lets the GIL go) while the interpreter finalized was ended inside Rust code,
    and the process died with "FATAL: exception not rethrown" (SIGABRT) instead of exiting: here 9
    runs in 16 whose attempt ended just after a `close()` that had given up waiting for it. At exit,
    publishers left open are closed and openers still in an attempt waited for."""
    silent = socket.create_server(("127.0.0.1", 0))  # accepts connections, never answers Zenoh's hello
    with silent:
        endpoint = f"tcp/127.0.0.1:{silent.getsockname()[1]}"
        done = subprocess.run(
            [sys.executable, "-c", _EXIT_PROGRAM, endpoint, how], capture_output=True, text=True, timeout=60
        )
    if how == "close":
        assert "after close: opener alive True" in done.stdout, done.stdout  # close gave up on it
    assert "opener alive False closed True" in done.stdout, done.stdout + done.stderr
    assert done.returncode == 0, done.stderr


def test_closing_gives_up_the_queued_scans_and_counts_them_as_dropped(sim_scans: list[Scan]) -> None:
    """Scans still in the publisher's queue when it is closed are never sent: `close()` moves them
    from `backlogged` (kept for re-delivery) to `dropped` (given up), so that the counters still say
    where every scan went."""
    router = Router()  # not started: nothing listens on its port yet
    pub = ScanPublisher("lab", "early", connect=[router.endpoint])
    for scan in sim_scans[:3]:
        assert pub.publish(scan) is True
    assert (pub.pending, pub.backlogged, pub.dropped, pub.published) == (3, 3, 0, 0)
    pub.close()
    assert (pub.pending, pub.backlogged, pub.dropped, pub.published) == (0, 0, 3, 0)


# A robot program whose SIGTERM handler closes its publisher ("close"), or publishes a scan
# ("publish"), the signal arriving while `publish` holds the publisher's locks (here: as it encodes
# the second scan, the moment a big JSON scan spends most of its time in). `close` must not wait for
# what the interrupted `publish` holds: that one goes on only once the handler returned. Its waits
# are made far longer than the subprocess's timeout, so a close that waits at all fails the test
# instead of passing slowly.
_SIGNAL_HANDLER_PROGRAM = """
import signal, sys
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap_client import publisher
publisher.CLOSE_WAIT_S = publisher.CLOSE_SEND_WAIT_S = 600.0
pub = publisher.ScanPublisher("lab", "sigterm", connect=[sys.argv[1]], encoding="json")
assert pub.wait_connected(15), pub.last_connect_error
robot = SimulatedRobot(generate_floorplan(1), num_beams=91, seed=1)
scans = [robot.tick() for _ in range(3)]
assert pub.publish(scans[0])
def on_sigterm(signum, frame):
    if sys.argv[2] == "close":
        pub.close()
        print("closed in the handler")
        return
    try:
        pub.publish(scans[2])
    except RuntimeError as exc:
        print("refused in the handler:", exc)
signal.signal(signal.SIGTERM, on_sigterm)
encode = pub._encode
def encode_and_get_sigterm(*args, **kwargs):
    pub._encode = encode
    signal.raise_signal(signal.SIGTERM)  # its handler runs here, inside publish
    return encode(*args, **kwargs)
pub._encode = encode_and_get_sigterm
print("second publish", pub.publish(scans[1]))
print("counters", pub.published, pub.backlogged, pub.dropped, pub.pending)
"""


def test_a_signal_handler_closes_a_publisher_interrupted_inside_publish(router: Router) -> None:
    """`close()` called by a signal handler that interrupted `publish` of the same thread: the
    publish held the publisher's (non-reentrant) locks, so the close hung for ever when the signal
    came while it encoded (2 runs in 3 of a loop of 20,000-beam JSON scans and a SIGALRM), and took
    9 s otherwise (6 s for the send lock, 3 s for the link watcher blocked on it). Now it closes at
    once, and the interrupted publish gives its scan up (`dropped`) as after any close."""
    program = [sys.executable, "-c", _SIGNAL_HANDLER_PROGRAM, router.endpoint, "close"]
    done = subprocess.run(program, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert done.stdout.splitlines() == ["closed in the handler", "second publish False", "counters 1 0 1 0"]
    assert [w.seq for _, _, w in router.wait_count(1, "fleetmap/lab/sigterm/scan")] == [0]


def test_a_signal_handler_may_not_publish_inside_an_interrupted_publish(router: Router) -> None:
    """A signal handler that publishes while it interrupted a `publish` of the same thread: with the
    locks reentrant (for a close there), its publish ran inside the interrupted one, took the same
    seq and sent its scan first, and the interrupted one's scan arrived as a duplicate (ignored).
    It is refused with a RuntimeError saying why; the interrupted publish goes on unharmed."""
    program = [sys.executable, "-c", _SIGNAL_HANDLER_PROGRAM, router.endpoint, "publish"]
    done = subprocess.run(program, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, (done.stdout, done.stderr)
    lines = done.stdout.splitlines()
    assert lines[0].startswith("refused in the handler: publish() was called by a signal handler"), lines
    assert lines[1:] == ["second publish True", "counters 2 0 0 0"]
    scans = router.wait_count(2, "fleetmap/lab/sigterm/scan")
    assert [w.seq for _, _, w in scans] == [0, 1]
    assert len(router.wait_count(2)) == 2  # nothing more was sent


@pytest.mark.parametrize("when", ["before the link check", "after the link check"])
def test_a_close_from_another_thread_during_a_publish_leaves_every_scan_counted_where_it_went(
    router: Router, sim_scans: list[Scan], when: str
) -> None:
    """A robot's shutdown handler closes the publisher while its publishing thread is inside
    `publish`. Before the link check, the scan was queued after close() had given up the queue:
    never sent, yet `publish` returned True and it stayed in `pending`, counted `backlogged` for
    ever. After it, the scan put over the live link (which the session's close flushes) was counted
    `backlogged`, as if kept for re-delivery, because the link looked down once close() had begun.
    Seen in 8 of 30 and 26 of 40 runs of a thread publishing in a loop against a close(); here
    the close is made to happen at that point: `_check_link` is wrapped to let a real close() of
    another thread begin there (it then waits for the publish, as always)."""
    pub = ScanPublisher("m", "closing", connect=[router.endpoint])
    assert pub.wait_connected(10)
    assert pub.publish(sim_scans[0])
    check_link = pub._check_link
    closer = threading.Thread(target=pub.close)

    def close_meanwhile() -> bool:
        if when == "after the link check":
            held = check_link()
        closer.start()
        wait_for(lambda: pub.closed, 5, 0.001, "close() to begin")
        return check_link() if when == "before the link check" else held

    pub._check_link = close_meanwhile  # type: ignore[method-assign]
    sent = pub.publish(sim_scans[1])
    closer.join(10)
    assert not closer.is_alive()
    if when == "before the link check":
        assert sent is False  # given up: the publisher closed meanwhile
        assert (pub.published, pub.backlogged, pub.dropped, pub.pending) == (1, 0, 1, 0)
    else:
        assert sent is True
        assert (pub.published, pub.backlogged, pub.dropped, pub.pending) == (2, 0, 0, 0)
        assert [w.seq for _, _, w in router.wait_count(2, "fleetmap/m/closing/scan")] == [0, 1]


def test_publisher_without_backlog_drops_what_it_publishes_before_the_router_appears(
    sim_scans: list[Scan],
) -> None:
    router = Router()  # not started: nothing listens on its port yet
    with ScanPublisher("lab", "early", connect=[router.endpoint], backlog=0) as pub:
        assert pub.wait_connected(0.5) is False
        # Published while disconnected: dropped, and said so.
        assert pub.publish(sim_scans[0]) is False
        assert pub.dropped == 1 and pub.published == 0 and pub.pending == 0
        router.start()
        try:
            assert pub.wait_connected(15), f"no connection; last error {pub.last_connect_error}"
            assert pub.connected and pub.subscribed
            for scan in sim_scans[1:4]:
                assert pub.publish(scan)
            got = router.wait_count(3)
            assert [w.seq for _, _, w in got] == [1, 2, 3]  # seq 0 was the dropped one
        finally:
            router.stop()


def test_a_service_restarted_behind_a_router_gets_a_cached_scan_first_not_a_live_one(
    sim_scans: list[Scan],
) -> None:
    """The robot connected to a Zenoh router that the service joins (`fleetmap serve
    --zenoh-connect`), the service restarted there: no link of the robot's changed, so it held
    nothing back and put its scans live as the new service subscribed. One reached the service
    before its fetch of the cache, and zenoh-ext then dropped the whole cache as old: every scan
    published while the service was away was lost, and those it had not made durable (seen against
    the real service killed and restarted: 171 to 272 scans lost in 1 of 3 restarts). Now the
    publisher keeps its scans while no subscriber of its key is known and holds them after one
    appears, as after a reconnection, so each new service's first scan is one published before it
    subscribed. (Not necessarily the cache's first: zenoh-ext, fetching the cache of a publisher
    connected before its subscriber was declared, sometimes skips a run of it, docs/protocol.md.)
    Here the service is a subscriber like the service's, opened again and again."""
    upstream = Router(plain=True)  # only its free port: the robots' router has no subscriber
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", f'["{upstream.endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(cfg)
    pub = ScanPublisher("lab", "behind", connect=upstream.endpoint)
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.002):
            pub.publish(sim_scans[0])

    robot = threading.Thread(target=publish)
    firsts: list[tuple[int, int]] = []  # (last seq published before it subscribed, its first seq)
    try:
        assert pub.wait_connected(10, require_subscriber=False)
        robot.start()
        wait_for(lambda: pub.last_seq is not None, 5, 0.01, "a first scan")
        for _ in range(10):  # without the keeping and the hold, 1 to 6 of 8 got a live scan first
            before = pub.last_seq
            assert before is not None
            service = Router(upstream=upstream.endpoint).start()
            try:
                firsts.append((before, service.wait_count(1, timeout=10)[0][2].seq))
                time.sleep(0.1)
            finally:
                service.stop()
            time.sleep(0.05)  # the service away: the robot publishes on
    finally:
        stop.set()
        robot.join(10)
        pub.close()
        router.close()
    assert all(first <= before for before, first in firsts), f"a live scan first: {firsts}"


@pytest.mark.parametrize("backlog", [1000, 0])
def test_publisher_reconnects_after_the_router_restarts(sim_scans: list[Scan], backlog: int) -> None:
    """With a backlog, the scan published while the service was away is delivered when it is back,
    before the newer ones (with the rest of the backlog); without, it is dropped."""
    router = Router().start()
    with ScanPublisher("lab", "rb", connect=[router.endpoint], backlog=backlog) as pub:
        try:
            assert pub.wait_connected(10)
            assert pub.publish(sim_scans[0])
            router.wait_count(1)
            router.stop()
            wait_for(lambda: not pub.connected, 10, 0.02, "the publisher to notice the router left")
            assert pub.publish(sim_scans[1]) is bool(backlog)  # kept, or dropped, while the service is away
            assert (pub.backlogged, pub.dropped) == ((1, 0) if backlog else (0, 1))
            router = Router(router.port).start()  # the service comes back on the same endpoint
            assert pub.wait_connected(20), "Zenoh did not reconnect"
            for scan in sim_scans[2:5]:
                assert pub.publish(scan)
            # The new router fetches the whole backlog, seq 0 too (the service ignores it as a duplicate).
            got = router.wait_count(5 if backlog else 3)
            assert [w.seq for _, _, w in got] == ([0, 1, 2, 3, 4] if backlog else [2, 3, 4])
            # The liveliness token is declared again to the new router.
            wait_for(
                lambda: "fleetmap/lab/rb/alive" in router.online(), 5, 0.02, "the token after reconnecting"
            )
        finally:
            router.stop()


def test_publisher_rejects_bad_arguments_and_use_after_close(router: Router, sim_scans: list[Scan]) -> None:
    with pytest.raises(ValueError, match="map_id 'a/b' is invalid"):
        ScanPublisher("a/b", "r")
    with pytest.raises(ValueError, match="robot_id '' is invalid"):
        ScanPublisher("m", "")
    with pytest.raises(ValueError, match="encoding must be"):
        ScanPublisher("m", "r", encoding="xml")  # type: ignore[arg-type]
    pub = ScanPublisher("m", "r", connect=[router.endpoint])
    with pytest.raises(ValueError, match="seq must be"):
        pub.publish(sim_scans[0], seq=-1)
    with pytest.raises(ValueError, match="stamp must be finite"):
        pub.publish(sim_scans[0], stamp=math.nan)
    pub.close()
    pub.close()  # idempotent
    with pytest.raises(PublisherClosed):
        pub.publish(sim_scans[0])
    assert pub.wait_connected(0.1) is False


def test_concurrent_publishes_leave_in_seq_order(router: Router, sim_scans: list[Scan]) -> None:
    """ScanPublisher is thread-safe, and threads of one robot publishing at once took distinct
    seqs but handed their scans to Zenoh after letting go of the lock: a later seq could leave
    first, and the service then took the earlier one for a duplicate and ignored it (seen against
    the real service: 4 to 10 of 120 scans from 8 threads counted as duplicates, as many as lost)."""
    threads, each = 8, 40
    with ScanPublisher("m", "threads", connect=[router.endpoint]) as pub:
        assert pub.wait_connected(10)
        start = threading.Barrier(threads)

        def publish_some() -> None:
            start.wait()
            for k in range(each):
                assert pub.publish(sim_scans[k % len(sim_scans)])

        workers = [threading.Thread(target=publish_some) for _ in range(threads)]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join()
        got = router.wait_count(threads * each, "fleetmap/m/threads/scan")
    assert [wire.seq for _, _, wire in got] == list(range(threads * each))


def test_a_refused_publish_leaves_no_gap_in_the_seqs(router: Router, sim_scans: list[Scan]) -> None:
    """A call that raises publishes nothing and keeps the seq counter: it used to take a seq (a
    dict failed while encoding, a float seq made the counter 3.5), which the service counts as a
    lost scan."""
    with ScanPublisher("m", "gapless", connect=[router.endpoint]) as pub:
        assert pub.wait_connected(10)
        assert pub.publish(sim_scans[0])
        with pytest.raises(TypeError, match="publish takes a fleetmap Scan or ScanMessage, not dict"):
            pub.publish({"pose": [0, 0, 0]})  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="seq must be an integer, got 2.5"):
            pub.publish(sim_scans[1], seq=2.5)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="stamp must be a number"):
            pub.publish(sim_scans[1], stamp="now")  # type: ignore[arg-type]
        assert (pub.last_seq, pub.next_seq, pub.published, pub.dropped) == (0, 1, 1, 0)
        assert pub.publish(sim_scans[1])
        got = router.wait_count(2, "fleetmap/m/gapless/scan")
    assert [wire.seq for _, _, wire in got] == [0, 1]


@pytest.mark.parametrize("where", ["in the link check", "in the put"])
def test_a_publish_interrupted_by_ctrl_c_leaves_no_gap_in_the_seqs(
    router: Router, sim_scans: list[Scan], where: str
) -> None:
    """Ctrl-C (or SIGTERM, which `fleetmap replay` turns into the same KeyboardInterrupt) while a
    publish is inside the link check or Zenoh's put, before the scan left: the seq counter had moved
    already, so that seq was never sent: the service counted a lost scan, and a robot that flushed
    after the Ctrl-C waited the flush's whole timeout for it ("1 unconfirmed", 2 runs in 8 of a
    loop publishing to a real service). Interrupted there, the call publishes nothing and keeps
    the counter, as every call that raises does."""
    with ScanPublisher("m", "ctrl-c", connect=[router.endpoint]) as pub:
        assert pub.wait_connected(10)
        assert pub.publish(sim_scans[0])

        def interrupted(*args: Any) -> Any:
            raise KeyboardInterrupt

        if where == "in the link check":
            pub._check_link = interrupted  # type: ignore[method-assign]
        else:
            assert pub._publisher is not None
            publisher, pub._publisher = pub._publisher, _Interrupting()  # type: ignore[assignment]
        with pytest.raises(KeyboardInterrupt):
            pub.publish(sim_scans[1])
        assert (pub.last_seq, pub.next_seq, pub.published, pub.backlogged, pub.dropped) == (0, 1, 1, 0, 0)
        if where == "in the link check":
            del pub._check_link
        else:
            pub._publisher = publisher
        assert pub.publish(sim_scans[1])
        got = router.wait_count(2, "fleetmap/m/ctrl-c/scan")
    assert [wire.seq for _, _, wire in got] == [0, 1]


class _Interrupting:
    """A stand-in for the publisher's Zenoh publisher whose put is interrupted by Ctrl-C before it
    sent anything."""

    def put(self, payload: bytes) -> None:
        raise KeyboardInterrupt


def test_binary_publishes_a_range_max_beyond_float32_as_no_maximum(router: Router) -> None:
    """A legal scan whose range_max is beyond float32 (sys.float_info.max, a common "no maximum")
    made `publish` raise struct's OverflowError in the binary encoding, which JSON sends as is. It
    now travels as +inf (no maximum), as readings beyond float32 travel as +inf (no return); a
    range_min beyond float32 (a scan the service refuses anyway) is a ScanError that sends nothing."""
    huge = Scan.from_fan((1.0, 2.0, 0.0), 0.0, 0.1, [1.5, 1e39, math.inf], 0.0, sys.float_info.max)
    with ScanPublisher("m", "wide", connect=[router.endpoint]) as pub:
        assert pub.wait_connected(10)
        assert pub.publish(huge, stamp=1.0)
        with pytest.raises(ScanError, match="does not fit the binary encoding's float32"):
            pub.publish(Scan.from_fan((0.0, 0.0, 0.0), 0.0, 0.1, [1.0], 1e39), stamp=2.0)
        assert pub.publish(huge, stamp=3.0)
        got = router.wait_count(2, "fleetmap/m/wide/scan")
    as_json = decode(encode_json(huge, 0, 1.0), JSON_ENCODING).scan  # the service's range_max: its cap
    assert [wire.seq for _, _, wire in got] == [0, 1]
    for _, _, wire in got:
        assert wire.scan.range_max == as_json.range_max
        np.testing.assert_array_equal(wire.scan.ranges, [1.5, math.inf, math.inf])


def test_client_config_takes_one_endpoint_as_a_string_and_says_what_is_wrong(tmp_path: Path) -> None:
    """A string was read as a list of one-character endpoints; Zenoh's error carried the Rust
    source path it was raised at, and an endpoint without its protocol (`127.0.0.1:7447`, the
    likeliest mistake) read `Json5Err(Message { msg: "Endpoints must be ...`, cut off mid-way."""
    import json

    assert json.loads(client_config("tcp/127.0.0.1:1").get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]
    with pytest.raises(ValueError) as bad:
        client_config("127.0.0.1:7447")
    assert str(bad.value) == (
        "invalid Zenoh endpoint in ['127.0.0.1:7447']: Endpoints must be of the form "
        "<protocol>/<address>[?<metadata>][#<config>]: 127.0.0.1:7447"
    )
    # Flags that are not bools: "no" was true, and the robot blocked on a full link it meant to drop on.
    for flags in ({"block": "no"}, {"send_session_id": "false"}):
        with pytest.raises(TypeError, match="must be True or False"):
            ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", **flags)  # type: ignore[arg-type]
    for backlog in (-1, True, 2.5, "5"):
        with pytest.raises(ValueError, match="backlog must be an integer >= 0"):
            ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", backlog=backlog)  # type: ignore[arg-type]
    # A NumPy integer is one, as for a seq (it was refused as "backlog must be an integer").
    with ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", backlog=np.int64(5)) as pub:  # type: ignore[arg-type]
        assert pub.backlog == 5 and type(pub.backlog) is int
        assert pub.cache == 10  # twice the backlog by default
    # A cache smaller than the backlog would lose the backlog's first scans as it goes out.
    for cache in (4, -1, True, 7.0):
        with pytest.raises(ValueError, match=r"cache must be an integer >= backlog \(5\)"):
            ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", backlog=5, cache=cache)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="a cache needs a backlog"):
        ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", backlog=0, cache=10)
    with ScanPublisher("m", "r", connect="tcp/127.0.0.1:1", backlog=5, cache=np.int64(5)) as pub:
        assert pub.cache == 5 and type(pub.cache) is int
    # As a URL, which Zenoh takes for the protocol `tcp:`: the robot waited for the service for ever.
    with pytest.raises(
        ValueError, match=r"^'tcp://h:7447' is written as a URL: .* PROTOCOL/ADDRESS, tcp/h:7447$"
    ):
        ScanPublisher("m", "r", connect=["tcp/127.0.0.1:1", "tcp://h:7447"])
    # Without its port: Zenoh's "invalid socket address" named no endpoint.
    with pytest.raises(
        ValueError, match=r"^'tcp/h' has no port: a Zenoh tcp endpoint is tcp/HOST:PORT, e.g. tcp/h:7447$"
    ):
        ScanPublisher("m", "r", connect="tcp/h")
    # A port past 65535: Zenoh's "invalid port value" named no endpoint either.
    with pytest.raises(ValueError, match=r"^'tcp/\[::1\]:70000' has port 70000: a port is at most 65535$"):
        ScanPublisher("m", "r", connect="tcp/[::1]:70000")
    config_file = tmp_path / "robot.json5"
    config_file.write_text('{mode: "client", connect: {endpoints: ["127.0.0.1:7447"]}}')
    with pytest.raises(ValueError) as bad:
        client_config(None, str(config_file))
    assert str(bad.value).startswith(f"cannot read Zenoh configuration {config_file}: ")
    assert str(bad.value).endswith(
        "Endpoints must be of the form <protocol>/<address>[?<metadata>][#<config>]: 127.0.0.1:7447"
    )
    assert " at /" not in str(bad.value) and "Message {" not in str(bad.value)


def test_a_zenoh_config_that_is_neither_a_config_nor_a_path_is_a_type_error_naming_it(tmp_path: Path) -> None:
    """A dict of settings, the likeliest wrong type, was taken for a file name: "cannot read Zenoh
    configuration {'mode': 'client'}: No such file or directory (os error 2)" sent the robot's
    author looking for a file. A `pathlib.Path` still names a file."""
    settings = {"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7447"]}}
    with pytest.raises(
        TypeError, match=r"zenoh_config must be a zenoh.Config or the path of a JSON5 file, not dict"
    ):
        ScanPublisher("m", "r", zenoh_config=settings)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="not bytes"):
        client_config(None, b"robot.json5")  # type: ignore[arg-type]
    config_file = tmp_path / "robot.json5"
    config_file.write_text('{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7"]}}')
    assert config_value(client_config(None, config_file), "connect/endpoints") == ["tcp/127.0.0.1:7"]


def test_endpoints_set_per_mode_in_a_config_file_are_read_for_the_session_s_mode(
    router: Router, tmp_path: Path
) -> None:
    """Zenoh takes `connect/endpoints` per mode too (`{client: [...], peer: [...]}`, in a file shared
    by several kinds of nodes). The publisher connected, but took the keys for its endpoints: it
    said "waiting for the fleetmap service at peer, client"; and a file with endpoints for other
    modes only left the client none ("No peer specified and multicast scouting deactivated!")
    where docs/clients.md promises the default endpoint."""
    shared = tmp_path / "shared.json5"
    shared.write_text(
        f'{{connect: {{endpoints: {{peer: ["tcp/127.0.0.1:1"], client: ["{router.endpoint}"]}}}}}}'
    )
    with ScanPublisher("m", "per-mode", zenoh_config=shared) as pub:
        assert pub.endpoints == [router.endpoint]
        assert f"endpoints=['{router.endpoint}']" in repr(pub)
        assert pub.wait_connected(10)
    routers_only = tmp_path / "routers.json5"
    routers_only.write_text('{connect: {endpoints: {router: ["tcp/127.0.0.1:1"]}}}')
    assert connect_endpoints(client_config(None, routers_only)) == ["tcp/127.0.0.1:7447"]
    assert connect_endpoints(client_config(router.endpoint, routers_only)) == [router.endpoint]


def test_client_config_defaults_and_overrides() -> None:
    import json

    cfg = client_config()
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    # Reconnection bounded at 0.5 s between attempts, unless the configuration says otherwise.
    assert json.loads(cfg.get_json("connect/retry")) == {
        "period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2.0
    }  # fmt: skip
    own = zenoh.Config.from_json5("{connect: {retry: {period_max_ms: 8000}}}")
    assert json.loads(client_config(None, own).get_json("connect/retry")) == {
        "period_init_ms": None, "period_max_ms": 8000, "period_increase_factor": None
    }  # fmt: skip
    base = zenoh.Config()
    base.insert_json5("connect/endpoints", '["tcp/10.1.2.3:7447"]')
    assert json.loads(client_config(None, base).get_json("connect/endpoints")) == ["tcp/10.1.2.3:7447"]
    assert json.loads(client_config(["tcp/127.0.0.1:1"], base).get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:1"
    ]
    with pytest.raises(ValueError, match="non-empty list"):
        client_config([])


# -- replay ----------------------------------------------------------------------------------------


def _write_carmen(path: Path, n: int) -> None:
    """A small CARMEN log: n FLASER scans of 180 beams along a corridor, with a PARAM and comments."""
    lines = ["# synthetic log for the client tests", "PARAM robot_frontlaser_offset 0.0"]
    for k in range(n):
        ranges = " ".join(f"{2.0 + 0.01 * ((i + k) % 50):.3f}" for i in range(180))
        x, y, th = 0.1 * k, 0.05 * k, 0.01 * k
        lines.append(
            f"FLASER 180 {ranges} {x:.4f} {y:.4f} {th:.4f} {x:.4f} {y:.4f} {th:.4f} {k * 0.1:.3f} h 0"
        )
        lines.append(f"ODOM {x} {y} {th} 0 0 0 {k * 0.1:.3f} h 0")
    path.write_text("\n".join(lines) + "\n")


def test_replay_of_a_carmen_log_arrives_complete_and_in_order(router: Router, tmp_path: Path) -> None:
    log = tmp_path / "corridor.log"
    _write_carmen(log, 40)
    ds = load_dataset(log)
    result = replay(log, "corr", "r1", rate=0, connect=[router.endpoint], progress=False, wait_timeout=20)
    assert result.scans == 40 and result.pauses == 0
    got = router.wait_count(40)
    assert [w.seq for _, _, w in got] == list(range(40))
    for (_, enc, wire), k in zip(got, range(40), strict=True):
        assert enc == BINARY_ENCODING
        _assert_same_scan(wire, ds[k], k, wire.stamp, "binary")


def test_replay_waits_for_the_service_then_paces_scans(tmp_path: Path) -> None:
    log = tmp_path / "short.log"
    _write_carmen(log, 6)
    router = Router()
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["result"] = replay(
                log, "m", "late", rate=1.0, connect=[router.endpoint], encoding="json", progress=False
            )
        except BaseException as exc:  # report it to the test thread
            outcome["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    try:
        time.sleep(1.5)  # the replay is waiting: nothing listens yet
        assert thread.is_alive() and not outcome
        router.start()
        thread.join(30)
        assert not thread.is_alive(), "the replay did not finish"
        assert "error" not in outcome, outcome.get("error")
        got = router.wait_count(6)
    finally:
        router.stop()
    assert [w.seq for _, _, w in got] == list(range(6))
    assert {e for _, e, _ in got} == {JSON_ENCODING}
    # rate 1 = NOMINAL_SCAN_RATE scans per second: scan k leaves k / 10 s after the first.
    result = outcome["result"]
    assert result.seconds >= 5 / NOMINAL_SCAN_RATE - 0.02  # type: ignore[attr-defined]
    stamps = [w.stamp for _, _, w in got]
    assert stamps[-1] - stamps[0] >= 5 / NOMINAL_SCAN_RATE - 0.02


def test_replay_command_stops_on_sigterm_as_on_ctrl_c(router: Router, tmp_path: Path) -> None:
    """SIGTERM (`kill`, `docker stop`, a job's deadline) ends the replay as Ctrl-C does: "replay
    interrupted", exit 130. It killed the replay without a word (exit -15); as a container's PID 1,
    which receives no signal it does not handle, it went on replaying until Docker killed it."""
    log = tmp_path / "long.log"
    _write_carmen(log, 400)  # 40 s at the nominal rate
    code, _, err = _sigterm_after_first_scans(
        router, ["replay", str(log), "--robot", "r", "--wait-timeout", "20", "--quiet"]
    )
    assert code == 130, (code, err)
    assert "replay interrupted" in err and "Traceback" not in err, err


def _sigterm_after_first_scans(router: Router, args: list[str]) -> tuple[int, str, str]:
    """Run `fleetmap_client.cli` with `args` on map "term" through `router`, send it SIGTERM once its
    first scans came, and return its exit code, stdout and stderr."""
    command = [sys.executable, "-m", "fleetmap_client.cli", *args]
    command += ["--map", "term", "--connect", router.endpoint]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(process):
        wait_for(lambda: any(k.startswith("fleetmap/term/") for k, _, _ in router.samples()), 30, 0.05,
                 "the first scans")  # fmt: skip
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=30)
    return process.returncode, out, err


def test_replay_of_the_intel_log_first_50_scans(router: Router) -> None:
    path = DATASETS_DIR / "intel-corrected.log.gz"
    if not path.exists():
        pytest.skip(f"shared dataset not found: {path}")
    ds = load_dataset(path)
    code = cli.main(["replay", str(path), "--map", "intel", "--robot", "r1", "--rate", "0", "--limit", "50",
                     "--connect", router.endpoint, "--quiet", "--wait-timeout", "20"])  # fmt: skip
    assert code == 0
    got = router.wait_count(50)
    assert len(got) == 50
    assert {k for k, _, _ in got} == {"fleetmap/intel/r1/scan"}
    for k, (_, _, wire) in enumerate(got):
        _assert_same_scan(wire, ds[k], k, wire.stamp, "binary")


def test_replay_command_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.log"
    assert cli.main(["replay", str(missing), "--map", "m", "--robot", "r", "--quiet"]) == 2
    assert "nope.log" in capsys.readouterr().err
    log = tmp_path / "ok.log"
    _write_carmen(log, 2)
    nobody = f"tcp/127.0.0.1:{free_port()}"
    args = [
        "replay",
        str(log),
        "--map",
        "m",
        "--robot",
        "r",
        "--connect",
        nobody,
        "--wait-timeout",
        "1.5",
        "--quiet",
    ]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "fleetmap replay: error: no fleetmap service reachable at" in err and nobody in err
    assert cli.main(["replay", str(log), "--map", "bad/id", "--robot", "r", "--quiet"]) == 2
    assert "map_id 'bad/id' is invalid" in capsys.readouterr().err
    with pytest.raises(ReplayError):
        replay(log, "m", "r", connect=[nobody], wait_timeout=0.5, progress=False)
    # A timeout of NaN is refused before anything is published: --confirm-timeout nan made the
    # replay publish every scan and then flush for ever (or fail then, with no word on the scans).
    for options in (["--confirm-timeout", "nan", "--wait-timeout", "2"], ["--wait-timeout", "nan"]):
        started = time.monotonic()
        assert (
            cli.main(["replay", str(log), "--map", "m", "--robot", "r", "--connect", nobody, *options]) == 2
        )
        assert time.monotonic() - started < 5
        assert "must be a number of seconds >= 0, got nan" in capsys.readouterr().err


def test_a_rate_too_slow_for_a_thread_to_wait_out_is_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`fleetmap replay --rate 1e-300` published its first scan, then ended in an OverflowError
    traceback from `time.sleep` (exit 1), and `fleetmap sim --rate 1e-12` said "robot sim-1 stopped:
    OverflowError: timestamp out of range for platform time_t": no thread waits past
    `threading.TIMEOUT_MAX` (about 292 years) at once. Such a rate is refused at once now, before
    the replay waits for its service or the sim announces its robots."""
    log = tmp_path / "ok.log"
    _write_carmen(log, 2)
    nobody = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(ValueError, match=r"rate 1e-300 is too slow: a scan every 1e\+299 s"):
        replay(log, "m", "r", rate=1e-300, connect=[nobody], wait_timeout=0.5, progress=False)
    command = ["replay", str(log), "--map", "m", "--robot", "r", "--connect", nobody, "--quiet"]
    assert cli.main([*command, "--rate", "1e-300"]) == 2
    assert "fleetmap replay: error: --rate 1e-300 is too slow" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"rate 1e-12 is too slow: a scan every 1e\+12 s"):
        check_fleet(1, rate=1e-12, seconds=None)
    assert cli.main(["sim", "--robots", "1", "--rate", "1e-12", "--connect", nobody]) == 2
    out, err = capsys.readouterr()
    assert "fleetmap sim: error: --rate 1e-12 is too slow" in err and "robots on map" not in out, (out, err)
    check_fleet(1, rate=1e-9, seconds=None)  # a scan every 31 years: slow, but a thread can wait it


def test_replay_goes_on_at_its_rate_after_a_pause_for_a_lost_connection(
    router: Router, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A replay paused for a lost connection goes on at its rate when the service is back: it kept
    its schedule, so every scan due during the pause went out at once after it (at --rate 20, 2760
    scans in a second after 12 s away, and the service's ingest queue of 1024 dropped hundreds)."""
    log = tmp_path / "corridor.log"
    _write_carmen(log, 120)
    proxy = FreezableProxy(router.port)
    sent: list[float] = []
    publish = ScanPublisher.publish

    def timed(pub: ScanPublisher, *args: Any, **kwargs: Any) -> bool:
        sent.append(time.monotonic())
        return publish(pub, *args, **kwargs)

    monkeypatch.setattr(ScanPublisher, "publish", timed)
    done: list[Any] = []
    runner = threading.Thread(
        target=lambda: done.append(
            replay(
                log,
                "pace",
                "r1",
                rate=4.0,
                connect=[proxy.endpoint],
                progress=False,
                wait_timeout=20,
                confirm=False,
            )
        )
    )
    try:
        runner.start()
        wait_for(lambda: len(sent) >= 10, 20, 0.01, "the first scans")
        proxy.cut()
        time.sleep(2.0)  # 80 scans due meanwhile at 40 a second
        proxy.restore()
        back = time.monotonic()
        runner.join(30)
    finally:
        proxy.close()
    assert done and done[0].scans == 120 and done[0].pauses == 1, done
    after = [t for t in sent if t > back]
    in_first_second = sum(1 for t in after if t < after[0] + 1.0)
    assert in_first_second <= 55, f"{in_first_second} scans in the second after the pause, at 40 a second"


def test_replay_command_says_one_pause_in_the_singular(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A replay that paused once for a lost connection said "paused 1 times"."""
    import fleetmap_client.replay as replay_module

    log = tmp_path / "ok.log"
    _write_carmen(log, 2)
    pauses = iter([1, 2])

    def replayed(*args: Any, **kwargs: Any) -> replay_module.ReplayResult:
        return replay_module.ReplayResult(scans=2, pauses=next(pauses), seconds=1.0)

    monkeypatch.setattr(replay_module, "replay", replayed)
    args = ["replay", str(log), "--map", "m", "--robot", "r", "--quiet", "--no-confirm"]
    assert cli.main(args) == 0
    assert ", paused 1 time for a lost connection" in capsys.readouterr().out
    assert cli.main(args) == 0
    assert ", paused 2 times for a lost connection" in capsys.readouterr().out


def test_replay_help_says_that_rate_0_lets_the_service_drop_scans() -> None:
    """`fleetmap replay --help` said "--rate X ... (0: as fast as possible, nothing dropped)": a
    3000-scan log of 1081 beams replayed so over loopback had 2695 scans dropped by the service's
    ingest queue (then 64 per robot; 1024 now, as docs/clients.md says). Zenoh's BLOCK loses nothing;
    the queue does."""
    parser = argparse.ArgumentParser(prog="fleetmap")
    text = " ".join(cli.add_replay_parser(parser.add_subparsers()).format_help().split())
    assert "nothing dropped" not in text, text
    assert "0: as fast as Zenoh takes them, and the service drops" in text, text
    assert "0 = as fast as possible, and the service drops what it cannot integrate in time" in text, text


# -- sim -------------------------------------------------------------------------------------------


def test_sim_publishes_from_every_robot(router: Router) -> None:
    plan = generate_floorplan(2, width_m=20.0, height_m=15.0)
    result = run_sim(3, map_id="fleet", seed=2, rate=10.0, seconds=1.5, connect=[router.endpoint], beams=181,
                     wait_timeout=20, plan=plan)  # fmt: skip
    assert result.robots == robot_ids(3) == ["sim-1", "sim-2", "sim-3"]
    assert sum(result.dropped.values()) == 0
    for rid in result.robots:
        sent = result.published[rid]
        assert 1 <= sent <= 15  # at most seconds * rate
        got = router.wait_count(sent, f"fleetmap/fleet/{rid}/scan")
        assert [w.seq for _, _, w in got] == list(range(sent))
        assert all(w.scan.num_beams == 181 for _, _, w in got)
    events = router.alive_events()
    for rid in result.robots:
        key = f"fleetmap/fleet/{rid}/alive"
        assert (key, zenoh.SampleKind.PUT) in events
    wait_for(lambda: not router.online(), 5, 0.02, "every robot's token withdrawn after the run")
    # Robots drive apart: their scans come from different poses.
    first = {k: w.scan.pose for k, _, w in router.scans() if w.seq == 0}
    assert len({(p.x, p.y) for p in first.values()}) == 3


def test_sim_command_runs_and_reports(router: Router, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--seconds", "1", "--rate", "5", "--beams", "91", "--connect", router.endpoint]
    code = cli.main(["sim", "--robots", "2", "--map", "simcli", "--wait-timeout", "20", *args])
    assert code == 0
    out, err = capsys.readouterr()
    assert "sim: 2 robots published" in out
    # This router is no fleetmap service: it answers no delivery query, so nothing is confirmed,
    # said as a warning (as `fleetmap replay` does), not as a failure.
    assert "fleetmap sim: warning: not confirmed:" in err and "confirmed integrated" not in out
    keys = {k for k, _, _ in router.samples()}
    assert keys == {"fleetmap/simcli/sim-1/scan", "fleetmap/simcli/sim-2/scan"}


def test_sim_stopped_before_it_reached_a_service_claims_no_confirmation(tmp_path: Path) -> None:
    """Ctrl-C while the robots still wait for a service that is not there: nothing went out, and the
    command said "sim: all 0 scans confirmed integrated", as if a service had answered."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "fleetmap_client.cli", "sim", "--robots", "1", "--map", "m", "--connect",
         f"tcp/127.0.0.1:{free_port()}", "--wait-timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    with reaped(sim):
        assert sim.stdout is not None
        assert sim.stdout.readline().startswith("sim: 1 robot on map 'm'")
        time.sleep(1)  # waiting for the service now
        sim.send_signal(signal.SIGINT)
        out, _ = sim.communicate(timeout=60)
    assert sim.returncode == 0, out
    assert "sim: 1 robot published 0 scans" in out and "confirmed integrated" not in out, out
    assert "sim: nothing published, nothing to confirm" in out, out


def test_sim_command_stops_on_ctrl_c_with_its_summary_and_checks_the_map_id_first(
    router: Router, tmp_path: Path
) -> None:
    """Ctrl-C (SIGINT) stops the robots and the summary is still printed, even when the command
    was started with SIGINT ignored (as `cmd &` from a script does); a bad map id is refused before
    the banner claims robots on it."""
    command = [sys.executable, "-m", "fleetmap_client.cli", "sim", "--robots", "1", "--rate", "20",
               "--beams", "91", "--connect", router.endpoint, "--wait-timeout", "20",
               "--no-confirm"]  # fmt: skip
    sim = subprocess.Popen(
        [*command, "--map", "ctrlc"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )  # fmt: skip
    with reaped(sim):
        wait_for(lambda: any(k.startswith("fleetmap/ctrlc/") for k, _, _ in router.samples()), 30, 0.05,
                 "the robot's first scans")  # fmt: skip
        sim.send_signal(signal.SIGINT)
        out, _ = sim.communicate(timeout=30)
    assert sim.returncode == 0 and "sim: 1 robot published" in out, out
    bad = subprocess.run([*command, "--map", "bad id"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "map id 'bad id' must match" in bad.stderr
    # " on map ", not "robots on map": the command runs 1 robot, whose banner says "1 robot on map".
    assert " on map " not in bad.stdout
    # So is a fleet that cannot run (it announced "0 robots on map ..." first).
    # --beams 0 (or past a scan's limit) let every robot's thread die with a traceback, then said
    # "sim: 3 robots published 0 scans" and exited 0; --speed -1 came after the banner. Each error
    # names the option given ("robots must be >= 1" named run_sim's parameter).
    for option, value, words in [
        ("--robots", "0", "error: --robots must be >= 1"),
        ("--rate", "0", "error: --rate must be"),
        ("--seconds", "-1", "error: --seconds must be >= 0, got -1.0"),
        ("--beams", "0", "error: --beams must be 1 to 100000, got 0"),
        ("--beams", "100001", "--beams must be 1 to 100000, got 100001"),
        ("--speed", "-1", "error: --speed must be finite and >= 0, got -1.0"),
        # Taken, and each step re-planned routes for a second: "this machine is too busy".
        ("--speed", "1e9", "error: --speed must be at most 50 m/s, got 1e+09"),
        # numpy's "expected non-negative integer", after the banner, naming no option.
        ("--seed", "-1", "error: --seed must be >= 0, got -1"),
        # Refused once the banner had announced the robots, as their sessions opened.
        ("--connect", "foo", "'foo']: Endpoints must be of the form"),
        ("--zenoh-config", str(tmp_path / "none.json5"), "error: cannot read Zenoh configuration"),
    ]:
        args = [*command, "--map", "m", option, value]
        bad = subprocess.run(args, capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr
        assert "Traceback" not in bad.stderr, bad.stderr
        assert " on map " not in bad.stdout, bad.stdout


def test_sim_command_stops_on_sigterm_as_on_ctrl_c(router: Router) -> None:
    """SIGTERM (`kill`, `docker stop`) stops the robots and prints the summary, exit 0, as Ctrl-C
    does. It killed the sim without a word (exit -15); as PID 1 of compose.yaml's robots container,
    which receives no signal it does not handle, `docker compose stop` waited 10 s, then killed it."""
    code, out, err = _sigterm_after_first_scans(
        router,
        ["sim", "--robots", "1", "--rate", "20", "--beams", "91", "--wait-timeout", "20", "--no-confirm"],
    )
    assert code == 0, (code, out, err)
    assert "sim: 1 robot published" in out and "Traceback" not in out + err, (out, err)


def test_sim_refuses_a_timeout_of_nan_or_below_0_before_it_waits() -> None:
    """`fleetmap sim --wait-timeout nan` waited for an absent service for ever (replay's refuses it),
    and -1 gave up "within -1 s"; `run_sim(confirm_timeout=nan)` ran, then raised in every robot's
    flush thread. Refused at once now, as replay's are."""
    nobody = f"tcp/127.0.0.1:{free_port()}"
    command = [sys.executable, "-m", "fleetmap_client.cli", "sim", "--robots", "1", "--connect", nobody]
    for value in ("nan", "-1"):
        bad = subprocess.run([*command, "--wait-timeout", value], capture_output=True, text=True, timeout=30)
        assert bad.returncode == 2, bad.stderr
        assert f"--wait-timeout must be a number of seconds >= 0, got {float(value)}" in bad.stderr
        assert "robots on map" not in bad.stdout, bad.stdout
    for name in ("wait_timeout", "confirm_timeout"):
        options = {"wait_timeout": 0.5, name: math.nan}
        with pytest.raises(ValueError, match=f"{name} must be a number of seconds >= 0, got nan"):
            run_sim(1, connect=[nobody], seconds=0.1, **options)


def test_a_sim_that_finds_no_service_gives_up_soon_after_its_wait_timeout() -> None:
    """Closing a publisher that never connected waits for its connection attempt (about a second):
    the sim closed its robots one after another, so 300 robots took four minutes to give up after
    a 5 s `--wait-timeout`. They are closed together now: 20 robots in about 1 s, not 10-16."""
    started = time.monotonic()
    with pytest.raises(SimError, match="no fleetmap service reachable"):
        run_sim(20, connect=[f"tcp/127.0.0.1:{free_port()}"], seconds=0.1, wait_timeout=0.5, beams=91,
                plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    assert time.monotonic() - started < 6.0


def test_a_second_ctrl_c_stops_the_sims_wait_for_confirmation(router: Router) -> None:
    """The first Ctrl-C stops the robots and starts the wait for confirmation (this router answers
    no delivery query: a few seconds); a second one ends it at once, exit 130, no traceback."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "fleetmap_client.cli", "sim", "--robots", "2", "--rate", "20", "--beams", "91",
         "--map", "twice", "--connect", router.endpoint, "--wait-timeout", "20", "--confirm-timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    with reaped(sim):
        wait_for(lambda: any(k.startswith("fleetmap/twice/") for k, _, _ in router.samples()), 30, 0.05,
                 "the robots' first scans")  # fmt: skip
        sim.send_signal(signal.SIGINT)
        time.sleep(0.5)
        sim.send_signal(signal.SIGINT)
        out, err = sim.communicate(timeout=30)
    assert sim.returncode == 130, (sim.returncode, out, err)
    assert "sim interrupted" in err and "Traceback" not in err and "FATAL" not in err, err


@pytest.mark.parametrize("max_beams", [None, 50])
def test_sim_confirms_its_scans_with_the_service(tmp_path: Path, max_beams: int | None) -> None:
    """Once its robots stop, `fleetmap sim` asks the service whether every scan is integrated (as
    `fleetmap replay` does): it says so, or, for scans the service refused (more beams than its
    --max-beams), warns with each robot's report and exits 1, where it said "published" alone."""
    args = ["--in-memory"] if max_beams is None else ["--in-memory", "--max-beams", str(max_beams)]
    with ServiceProcess(tmp_path, args) as service:
        done = subprocess.run(
            [sys.executable, "-m", "fleetmap_client.cli", "sim", "--robots", "2", "--rate", "10",
             "--seconds", "1", "--beams", "91", "--map", "confirm", "--connect", service.zenoh_endpoint,
             "--wait-timeout", "30"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    if max_beams is None:
        assert done.returncode == 0, (done.stdout, done.stderr)
        integrated = re.search(r"sim: all (\d+) scans confirmed integrated", done.stdout)
        assert integrated and int(integrated.group(1)) >= 2, done.stdout
    else:
        assert done.returncode == 1, (done.stdout, done.stderr)
        for robot in ("sim-1", "sim-2"):  # a robot of a slow machine may have published only 1 scan
            assert re.search(
                rf"fleetmap sim: warning: {robot}: \d+ scans? published, 0 integrated", done.stderr
            )
        assert "refused" in done.stderr and "confirmed integrated" not in done.stdout


def test_a_sim_robot_that_fails_stops_the_sim_with_its_error(
    router: Router, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot whose loop raises stops the whole simulation, which raises SimError naming the robot
    and the error (the command exits 2 with it), where the thread printed a traceback and the sim
    went on to report success. Its publishers are closed all the same."""
    ticks: dict[int, int] = {}
    real_tick = SimulatedRobot.tick

    def tick(self: SimulatedRobot) -> Scan:
        ticks[id(self)] = ticks.get(id(self), 0) + 1
        if ticks[id(self)] == 3:  # a robot's third scan (whichever robot comes first)
            raise RuntimeError("lidar unplugged")
        return real_tick(self)

    monkeypatch.setattr(SimulatedRobot, "tick", tick)
    started = time.monotonic()
    with pytest.raises(SimError, match=r"robot sim-[12] stopped: RuntimeError: lidar unplugged"):
        run_sim(2, map_id="f", seed=0, rate=20, seconds=None, connect=[router.endpoint], beams=91,
                wait_timeout=20, plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    assert time.monotonic() - started < 15  # stopped, not left to run forever (seconds=None)
    assert [t for t in threading.enumerate() if t.name.startswith("fleetmap-") and "-f-sim-" in t.name] == []


def test_sim_stops_on_request(router: Router) -> None:
    stop = threading.Event()
    # The robot publishes once connected and past the 0.5 s hold after the connection: on a busy
    # machine that took most of a 1 s timer, and the sim stopped before its first scan.
    timer = threading.Timer(3.0, stop.set)
    timer.start()
    started = time.monotonic()
    result = run_sim(1, map_id="s", rate=20, seconds=None, connect=[router.endpoint], beams=91, stop=stop,
                     wait_timeout=20, plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    assert time.monotonic() - started < 15
    assert result.published["sim-1"] >= 1
    with pytest.raises(ValueError, match="robots must be"):
        run_sim(0)


def test_sim_refuses_more_robots_than_its_file_descriptors_allow_naming_the_limit() -> None:
    """Each robot holds two file descriptors (its Zenoh session's socket and shared-memory segment):
    at `ulimit -n 1024` (a common default) 520 robots ran out of them, and the robots beyond waited
    for ever (with --wait-timeout: "no fleetmap service reachable ... (Unable to create POSIX shm
    segment: OS error 24)", though the service was up). Refused at once now, naming the limit; the
    command first raises its soft limit to the hard one, so here both are lowered."""
    import resource

    def low_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))

    nobody = f"tcp/127.0.0.1:{free_port()}"
    command = [sys.executable, "-m", "fleetmap_client.cli", "sim", "--connect", nobody, "--wait-timeout", "5"]
    bad = subprocess.run(
        [*command, "--robots", "200"], capture_output=True, text=True, timeout=30, preexec_fn=low_limit
    )
    assert bad.returncode == 2, bad.stderr
    assert "200 robots need about 464 file descriptors" in bad.stderr, bad.stderr
    assert "this process may open 256 (ulimit -n; hard limit 256)" in bad.stderr, bad.stderr
    assert "at most 96 robots per process" in bad.stderr, bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1, bad.stderr  # one line, no traceback
    assert "robots on map" not in bad.stdout, bad.stdout

    def low_soft_limit() -> None:  # a soft limit the hard one allows raising: the command raises it
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 1024))

    quick = [*command[:-1], "0.5", "--robots", "200", "--beams", "9"]
    done = subprocess.run(quick, capture_output=True, text=True, timeout=60, preexec_fn=low_soft_limit)
    assert done.returncode == 2, done.stderr
    assert "no fleetmap service reachable" in done.stderr, done.stderr
    assert "file descriptors" not in done.stderr and "OS error 24" not in done.stderr, done.stderr


def test_sim_refuses_more_robots_than_the_machine_has_threads_for() -> None:
    """`fleetmap sim --robots 100000` needs 300,000 threads (three per robot) where a machine allows
    some tens of thousands (kernel.pid_max is 32768 by default): it spent a minute building the
    robots, then failed at their threads or waited for ever. Refused at once now, naming the limit.
    A million robots need 3 million threads, more than any machine this runs on allows."""
    with pytest.raises(ValueError, match=r"1000000 robots need about 3000064 threads \(3 per robot\)"):
        check_fleet(1_000_000, rate=10.0, seconds=None)  # as run_sim and the command check first


def test_a_sim_out_of_file_descriptors_says_so_at_once_not_that_no_service_answers(router: Router) -> None:
    """A program whose other files leave too few descriptors for its robots (the fleet check counts
    only the robots' own): the robots beyond could not open their sessions ("OS error 24"), retried
    for ever without a wait timeout, and with one the sim said "no fleetmap service reachable". It
    stops at once now, saying the process ran out of file descriptors. A router is needed: the
    sessions of the first robots must hold their descriptors, as connected ones do."""
    program = f"""
import os, resource, sys
from fleetmap_client.sim import SimError, run_sim
from fleetmap.sim import generate_floorplan
resource.setrlimit(resource.RLIMIT_NOFILE, (300, 300))
held = [os.open(os.devnull, os.O_RDONLY) for _ in range(150)]  # the program's other files
try:
    run_sim(60, connect=["{router.endpoint}"], seconds=0.1, beams=9,
            plan=generate_floorplan(4, width_m=20.0, height_m=15.0))
except SimError as exc:
    print(exc)
    sys.exit(3)
"""
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, (done.stdout, done.stderr)
    assert "could not open its Zenoh session: this process ran out of file descriptors" in done.stdout
    assert "ulimit -n 300" in done.stdout, done.stdout


def test_a_sim_whose_service_takes_no_more_sessions_says_so_not_that_none_is_reachable() -> None:
    """A fleetmap service's Zenoh router takes at most 1000 sessions (`max_sessions`) and refuses
    the others with the timeout of an absent service: a sim of 1100 robots said "no fleetmap
    service reachable" with 1000 of them connected. A router taking 3 stands in for it here."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg.insert_json5("listen/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("transport/unicast/max_sessions", "3")
    with zenoh.open(cfg), pytest.raises(SimError) as raised:
        run_sim(5, connect=[endpoint], seconds=0.1, wait_timeout=2.0, beams=9, confirm_timeout=None,
                plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    message = str(raised.value)
    expected = f"only 3 of 5 robots could connect to the service at {endpoint} within 2 s"
    assert message.startswith(expected), message
    assert "transport/unicast/max_sessions" in message, message


def test_a_slow_sim_stops_at_its_seconds_not_at_the_end_of_a_period(router: Router) -> None:
    """A robot slept until its next scan was due even when that was past the end: at --rate 0.1,
    --seconds 15 ran 20 s (a period of 10 s). Now it stops at the end: a scan at 0 s, at 0.5
    scans/s none more, and the run lasts its 0.6 s, not 2 s."""
    result = run_sim(2, rate=0.5, seconds=0.6, connect=[router.endpoint], beams=9, wait_timeout=20,
                     plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    assert result.total == 2, result
    assert 0.6 <= result.seconds < 1.5, result.seconds


def test_a_sim_too_busy_for_its_rate_counts_the_scans_it_skipped_and_says_so(
    router: Router, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot that fell behind its rate resumed from now, silently: 400 robots at 1 scan/s for 10 s
    on a busy machine published 2757 scans, and the summary read as if the rate had been kept. The
    scans skipped are counted now, and the command warns. 50000 scans/s is more than one robot's
    ray casting and encoding keep up with (some 3000/s here)."""
    code = cli.main(["sim", "--robots", "1", "--rate", "50000", "--seconds", "1",
                     "--connect", router.endpoint, "--wait-timeout", "20", "--no-confirm"])  # fmt: skip
    assert code == 0
    out, err = capsys.readouterr()
    # One robot, in the singular: "the robots fell behind ..., too busy for 1 robots" was printed.
    match = re.search(
        r"warning: (\d+) scans skipped: the robot fell behind 50000 scans/s, this machine is too busy for 1 "
        r"robot at that rate",
        err,
    )
    assert match is not None, err
    published = re.search(r"published (\d+) scans", out)
    assert published is not None, out
    skipped, sent = int(match.group(1)), int(published.group(1))
    assert skipped > sent > 0
    assert 49_000 <= skipped + sent <= 50_100  # every scan due in the second: taken or skipped


def test_a_sim_of_infinite_seconds_runs_until_stopped_also_when_it_falls_behind(router: Router) -> None:
    """`fleetmap sim --seconds inf` (and `fleetmap demo --seconds inf`) is taken as no limit, but a
    robot that fell behind its rate then counted its skipped scans up to an infinite deadline:
    "robot sim-1 stopped: OverflowError: cannot convert float infinity to integer", exit 2 (the
    demo: SimError's traceback). 50000 scans/s is more than one robot keeps up with (see above)."""
    stop = threading.Event()
    timer = threading.Timer(1.0, stop.set)  # a stop, not a measure: the robot runs until then
    timer.start()
    try:
        result = run_sim(1, rate=50000.0, seconds=math.inf, connect=[router.endpoint], beams=9,
                         wait_timeout=20, stop=stop)  # fmt: skip
    finally:
        timer.cancel()
    assert result.total > 0 and sum(result.skipped.values()) > 0, result


def test_a_sim_of_more_robots_than_a_service_takes_says_so_first() -> None:
    """A fleetmap service takes 1000 Zenoh sessions at once by default and refuses the others as an
    absent service would, logging nothing: `fleetmap sim --robots 1001` left its last robot waiting
    for ever, without a word of why. It warns first now (here with no service: it then gives up)."""
    nobody = f"tcp/127.0.0.1:{free_port()}"
    command = [sys.executable, "-m", "fleetmap_client.cli", "sim", "--connect", nobody, "--wait-timeout", "0",
               "--beams", "9"]  # fmt: skip
    done = subprocess.run([*command, "--robots", "1001"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "warning: a fleetmap service takes at most 1000 robots at once" in done.stderr, done.stderr
    assert "transport/unicast/max_sessions" in done.stderr, done.stderr
    done = subprocess.run([*command, "--robots", "2"], capture_output=True, text=True, timeout=60)
    assert "warning" not in done.stderr, done.stderr


def test_a_sim_prefix_too_long_for_its_last_robot_is_refused_before_any_robot_joins(router: Router) -> None:
    """Robot ids grow with their number: with a 61-character prefix `p...-1` to `p...-99` are valid
    and `p...-100` (65 characters) is not, and it was refused only when its publisher was made, after
    the 99 robots before it had connected and declared their tokens (which create the map on a
    fleetmap service). Refused before any robot is made now."""
    with pytest.raises(ValueError, match=r"robot id 'p{61}-100' \(prefix 'p{61}'\) is invalid"):
        run_sim(100, prefix="p" * 61, connect=[router.endpoint], seconds=0.1, wait_timeout=5, beams=9,
                plan=generate_floorplan(4, width_m=20.0, height_m=15.0))  # fmt: skip
    time.sleep(0.5)  # a robot's token reaches the router within milliseconds
    assert router.alive_events() == []


def test_sim_robots_start_on_time_with_their_compiled_code_loaded(router: Router) -> None:
    """The robots' compiled route planner and lidar loaded from numba's cache at their first call,
    0.3-0.6 s on the robots' clock: every demo and `fleetmap sim` began behind its rate and warned
    of scans skipped on a machine "too busy" for even one robot. They are loaded before the robots'
    clock starts. (A fresh process: this one may have loaded them already.)"""
    program = f"""
from fleetmap_client import sim
from fleetmap.sim import lidar, robot

loaded = []
drive = sim._drive


def spy(*args, **kwargs):
    loaded.append(bool(lidar._cast_rays.signatures) and bool(robot._bfs_path.signatures))
    return drive(*args, **kwargs)


sim._drive = spy
sim.run_sim(1, map_id="warm", rate=10.0, seconds=0.2, connect=[{router.endpoint!r}], wait_timeout=60)
print(loaded)
"""
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[True]", done.stdout + done.stderr


def test_sim_says_a_single_confirmed_scan_in_the_singular(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A sim that published one scan said "sim: all 1 scans confirmed integrated", where its other
    lines count as `counted` does ("1 robot published 1 scan")."""
    report = DeliveryReport(1, 1, 1, integrated=1, settled=True, answered=True, counted_from=1)
    result = SimResult(["sim-1"], published={"sim-1": 1}, seconds=0.5, delivery={"sim-1": report})
    monkeypatch.setattr(sim_module, "run_sim", lambda *args, **kwargs: result)
    assert cli.main(["sim", "--robots", "1", "--seconds", "0.5", "--connect", "tcp/127.0.0.1:1"]) == 0
    out = capsys.readouterr().out
    assert "sim: 1 robot published 1 scan in 0.5 s\n" in out, out
    assert "sim: the 1 scan confirmed integrated\n" in out, out
    result.published["sim-1"] = 2
    result.delivery["sim-1"] = DeliveryReport(
        2, 1, 2, integrated=2, settled=True, answered=True, counted_from=1
    )
    assert cli.main(["sim", "--robots", "1", "--seconds", "0.5", "--connect", "tcp/127.0.0.1:1"]) == 0
    assert "sim: all 2 scans confirmed integrated\n" in capsys.readouterr().out


def test_replay_errors_name_the_option_given(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`fleetmap replay`'s errors named `replay`'s parameters ("limit must be >= 0" for --limit -1,
    "wait_timeout must be ..." for --wait-timeout -1), as `fleetmap sim`'s once did: each names the
    option given now, and is said before the log is read."""
    command = ["replay", str(tmp_path / "absent.log"), "--map", "m", "--robot", "r", "--quiet"]
    for option, value, says in [
        ("--rate", "-1", "--rate must be a finite number >= 0, got -1.0"),
        ("--limit", "-1", "--limit must be >= 0, got -1"),
        ("--wait-timeout", "-1", "--wait-timeout must be a number of seconds >= 0, got -1.0"),
        ("--confirm-timeout", "nan", "--confirm-timeout must be a number of seconds >= 0, got nan"),
    ]:
        assert cli.main([*command, option, value]) == 2
        assert f"fleetmap replay: error: {says}\n" == capsys.readouterr().err


def test_sim_announces_infinite_seconds_as_no_limit(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--seconds inf` is no limit to `run_sim`, as leaving it out is; the banner said "for inf s"."""
    result = SimResult(["sim-1"])
    monkeypatch.setattr(sim_module, "run_sim", lambda *args, **kwargs: result)
    assert cli.main(["sim", "--robots", "1", "--seconds", "inf", "--connect", "tcp/127.0.0.1:1"]) == 0
    assert "sim: 1 robot on map 'sim' (floor plan seed 1), 10 scans/s each\n" in capsys.readouterr().out
