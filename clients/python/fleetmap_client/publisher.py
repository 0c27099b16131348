"""The robot side: publish laser scans to a fleetmap service over Zenoh.

    from fleetmap_client.publisher import ScanPublisher

    with ScanPublisher("warehouse", "robot-7", connect=["tcp/10.0.0.5:7447"]) as pub:
        pub.wait_connected(timeout=30)          # optional: until the service is reachable
        while running:
            pub.publish(scan)                   # a fleetmap.scan.Scan: SENSOR pose in the map frame

What it does on the wire (the schema is `fleetmap.wire`, the byte layout docs/protocol.md):

* one Zenoh session in CLIENT mode connecting to `connect` (the service's own Zenoh session is a
  router, so no zenohd is needed); multicast scouting is off;
* a liveliness token `fleetmap/<map_id>/<robot_id>/alive`, so the service shows the robot online
  while the session lives;
* scans on `fleetmap/<map_id>/<robot_id>/scan`, binary (`application/x-fleetmap-scan`) or JSON
  (`application/json`), RELIABLE, and by default with `CongestionControl.BLOCK` so that a busy link
  slows the robot down instead of dropping scans;
* in every scan, the publisher's session id (`session_id`): a random number picked when the
  publisher is made, and again whenever its seq starts again (an explicit seq below the last; the
  last seq again is a resend, e.g. of a scan dropped while disconnected, and keeps the session).
  The service tells by it a restarted robot (a new session: nothing of it is ignored as a duplicate,
  whatever its seq and stamp) from two robots misconfigured with one robot id (two sessions
  interleaving: the scans of both are integrated and the conflict reported). `send_session_id=False` sends
  none, for a service older than session ids (which refuses scans that carry one).

Connection behaviour. The constructor returns at once; the session is opened by a background thread
that keeps trying until the service answers (Zenoh's own `zenoh.open` in client mode either fails
at once or, with `connect/timeout_ms: -1`, blocks the caller until a router listens; a loop of
bounded attempts gives the same "wait for the service" behaviour while letting `close()` and Ctrl-C
stop it). At the program's exit (atexit), publishers left open are closed and the attempts still
in progress waited for: a thread that came back from Zenoh into a finalizing interpreter aborted
the process (SIGABRT, "FATAL: exception not rethrown"). Once connected, Zenoh itself reconnects
after the service restarts or the link drops, trying again every 0.1 s, then 0.2, 0.4, and every
0.5 s from then on (`RECONNECT_PERIOD_MAX_MS`; Zenoh's own default backs off to 4 s, and robots
missed services that came back only briefly).

Store and forward (`backlog`, default `DEFAULT_BACKLOG` = 1000 scans). Robots drive through Wi-Fi
dead zones, and the service restarts; no scan should be lost to either. The publisher is zenoh-ext's
ADVANCED publisher: it keeps its last `cache` scans (twice `backlog` by default, `CACHE_BACKLOGS`)
in a cache, announces its last sequence number by heartbeat (`HEARTBEAT_S`) and declares itself
(publisher detection), and the service's advanced subscriber fetches from that cache what it did
not receive: the scans in flight when a link died (the publisher cannot tell, until Zenoh notices,
that they went nowhere), those the service had not made durable when it was killed, and those its
full ingest queue deferred. They arrive in order, before newer ones, without duplicates
(docs/protocol.md, "Delivery guarantees"). Scans published while the publisher KNOWS it is
disconnected (no router or peer connected, or, behind a router, no subscriber of its key: the
service away), and those published before the session first opened, wait in the publisher's own
queue instead, of at most `backlog` scans (the oldest pushed out,
counted in `dropped`; the service counts them as `lost`), so `publish` still returns True for them
(counted in `backlogged`). After the session connects, and after every reconnection, scans wait in
that queue too (the hold): at least `RECONNECT_HOLD_S` (0.5 s), and, once Zenoh's cache holds a
scan, until the service's query for the cache reaches the publisher (and `FETCH_MARGIN_S` more), at
most `RECONNECT_HOLD_MAX_S`; then
the queue is sent, in order and before any newer scan. Why not hand them to Zenoh's cache while
disconnected: zenoh-ext's advanced subscriber takes the first sample of a publisher it does not know
yet (a service that just restarted) for that publisher's first, and drops as old what its history
query fetches from the cache a moment later. A scan put while the link was coming back (between the
publisher's look at the link and the put) went out live, was that first sample, and cost the service
the whole cache before it (70 to 600 scans of one robot in tests/test_crash_exactly_once.py). Held
back until the query has come, the cached scans (its replies) go out first and the held ones follow,
in order. A fixed hold of 0.5 s was not always enough: a restarted service busy with other robots'
caches queried one robot's 0.6 s after it connected, and lost the 3 scans only its cache held.
`wait_connected()` returns once that hold is over. `close()` gives up whatever was not delivered by
then.

Delivery confirmation (`flush`). Zenoh has no acknowledgement, so neither `publish` nor `close`
can tell whether a scan reached the map. `flush(timeout)` asks the service (a Zenoh query on
`fleetmap/<map_id>/<robot_id>/delivery`, docs/protocol.md, "Delivery confirmation") until it reports
every scan of this publisher's session settled, and says how many were integrated: a robot ending
its mission calls it before `close()`, and knows whether all its scans are in the map. A robot whose
process restarted mid-mission asks about the previous process's session with `flush_ended`.

`backlog=0` publishes with a plain publisher, for a service older than this one (whose plain
subscriber does not fetch anything): a scan published while no router is connected is then DROPPED
(Zenoh keeps nothing for a missing route), `publish` returns False and counts it in `dropped`. Call
`wait_connected()` before publishing anything that must arrive.
"""

from __future__ import annotations

import atexit
import contextlib
import math
import numbers
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Literal

import zenoh
import zenoh.ext

from fleetmap.cell_queries import Integer, Real, is_whole_number
from fleetmap.codec import encode_binary, encode_json
from fleetmap.scan import Scan
from fleetmap.shown_endpoint import shown_endpoints
from fleetmap.wire import (
    ALIVE_KEY,
    BINARY_ENCODING,
    DELIVERY_ERROR_ENCODING,
    DELIVERY_FIELDS,
    DELIVERY_FIELDS_PARAMETER,
    DELIVERY_KEY,
    DELIVERY_SESSION_PARAMETER,
    JSON_ENCODING,
    SCAN_KEY,
    SEQ_LIMIT,
    SESSION_LIMIT,
    DeliveryStatus,
    ScanMessage,
    is_valid_id,
    new_session_id,
    zenoh_error_text,
)

from .delivery import DeliveryReport, delivery_report, ended_session_report
from .scan_arguments import checked_seq, checked_stamp
from .zenoh_config import (
    CONNECT_ATTEMPT_MS,
    DEFAULT_CONNECT,
    RECONNECT_PERIOD_FACTOR,
    RECONNECT_PERIOD_INIT_MS,
    RECONNECT_PERIOD_MAX_MS,
    client_config,
    connect_endpoints,
)

#: How long `close` waits for the opener's attempt in progress to end (one attempt and a margin; a
#: configuration whose own `connect/timeout_ms` is longer, or -1, may leave it running: it is waited
#: for again at the program's exit, `EXIT_WAIT_S`).
CLOSE_WAIT_S = CONNECT_ATTEMPT_MS / 1000 + 2.0
#: How long `close` waits for a `publish` inside Zenoh's put (congestion control BLOCK on a congested
#: or frozen link) to return before it undeclares the publisher: Zenoh closes a link it could not
#: send on for `transport/link/tx/queue/congestion_control/block/wait_before_close` (5 s by
#: default), which ends the put.
CLOSE_SEND_WAIT_S = 6.0
#: How long, at the program's exit, each publisher thread still inside a Zenoh call (an opener's
#: connection attempt) is waited for (`_settle_at_exit`): one that comes back from Zenoh while the
#: interpreter finalizes aborts the process. A `connect/timeout_ms` longer than this (or -1) may
#: outlast it.
EXIT_WAIT_S = CONNECT_ATTEMPT_MS / 1000 + 10.0
#: Scans a publisher keeps for re-delivery by default (`backlog`): at 10 scans/s, 100 s of dead zone,
#: about 4.5 MB of binary 1081-beam scans. The service's ingest queue holds as many per robot.
DEFAULT_BACKLOG = 1000
#: The advanced publisher's cache, by default, in backlogs (`cache`): twice the backlog, so that a
#: robot whose whole backlog went out at a reconnection may publish as many scans again before the
#: first of them leaves the cache, while the service, its queue full with a fleet's backlogs, has yet
#: to fetch them again (docs/protocol.md, "Delivery guarantees"). As large as the backlog, a robot
#: that published on pushed its backlog's first scans out of the cache one per scan (40 robots x
#: 1050 scans on one map lost 50 to 740 of them).
CACHE_BACKLOGS = 2
#: Seconds between the advanced publisher's heartbeats: how soon after a reconnection the service
#: learns of scans it missed in flight (scans published while the publisher knew it was disconnected
#: are not in Zenoh's cache: they wait in its own queue and are sent after the reconnection's hold).
HEARTBEAT_S = 0.5
#: After the session (re)connects, `publish` keeps scans in the publisher's own queue instead of
#: sending them live (the hold, `ScanPublisher._check_link`) until the service's query for the
#: cache has reached the publisher: zenoh-ext's advanced subscriber takes a live sample of a
#: publisher it does not know yet (a service just restarted) for that publisher's first, and then
#: drops as old the cached scans its history query brings after it. The query's replies leave
#: before any scan sent after it, so the service takes the cache first. Seconds the hold lasts
#: after the query came (the cache's own queryable answers the same query: its first reply must
#: be on its way first).
FETCH_MARGIN_S = 0.1
#: Seconds the hold lasts at least, a query or not: as long as before the hold waited for the query
#: (2026-11-27). With the query alone, holds of 0.1-0.3 s sent five robots' queued scans into the
#: fetches of their caches, and 2 of 43 heavy soak runs then got part of a robot's cache only (see
#: docs/protocol.md, "Delivery guarantees"); kept until that is understood.
RECONNECT_HOLD_S = 0.5
#: Seconds the hold lasts at most, when no query comes: a service that does not fetch caches (a
#: plain subscriber, an older service) or one busier than that. A restarted service queried 0.01 to
#: 0.6 s after a robot connected in tests/test_crash_exactly_once.py, where 5 robots' caches of 1000
#: scans each went through its scan callback at once.
RECONNECT_HOLD_MAX_S = 5.0
#: Seconds between the link checks of the publisher's background thread (reconnections, the hold).
WATCH_INTERVAL_S = 0.05
#: Queries for the cache the fetch watch's channel holds until its thread takes them (it takes each
#: as it comes: more wait only while the GIL is busy). A fuller channel lets the oldest go, so that
#: Zenoh's thread never waits for ours; only when the last came matters.
FETCH_WATCH_DEPTH = 64
#: Seconds between the delivery queries of `flush`.
FLUSH_POLL_S = 0.1
#: Seconds one delivery query may wait for its answer (a frozen link answers nothing), at most: less
#: when the flush's timeout comes sooner.
DELIVERY_QUERY_TIMEOUT_S = 2.0
#: Seconds during which `flush` gets only empty answers to its delivery queries, while the service's
#: scan subscriber is reachable, before it concludes that the service does not answer them (older
#: than delivery confirmation). Empty: the query ended at once without a reply, as Zenoh ends one
#: that no queryable matches; a query over a link that died silently ends at its timeout instead
#: (not yet). Not at the first: a service that just (re)started may declare its queryable a
#: moment after its subscriber.
NO_ANSWER_S = 3.0

Encoding = Literal["binary", "json"]


class PublisherClosed(RuntimeError):
    """`publish` on a publisher that was closed."""


class DeliveryUnsupported(RuntimeError):
    """`flush` got no answer to its delivery queries from a reachable service (its scan subscriber
    matched for `NO_ANSWER_S`): the service is older than delivery confirmation, or a Zenoh access
    control rule keeps the query from it (docs/security.md)."""


#: Publishers not closed yet, and threads of closed ones (openers, fetch watchers) `close` stopped
#: waiting for while they were still inside a Zenoh call: `_settle_at_exit` closes the ones and
#: waits for the others before the interpreter finalizes. Guarded by `_exit_lock`, reentrant as the
#: publisher's own locks are: a signal handler may close a publisher while its thread holds it.
_unclosed: set[ScanPublisher] = set()
_threads_in_zenoh: set[threading.Thread] = set()
_exit_lock = threading.RLock()


def _settle_at_exit() -> None:
    """At the program's exit (atexit: after its non-daemon threads ended, before the interpreter
    finalizes), leave no publisher's thread inside a Zenoh call: close the publishers the program
    left open, then wait for the threads still in a Zenoh call (up to `EXIT_WAIT_S` each).

    The opener and the fetch watcher are daemon threads (a program must be able to end without
    `close()`), which nothing joins. One that came back from `zenoh.open`, or from any Zenoh call
    that lets the GIL go, while the interpreter finalized was ended by Python inside Rust code, and
    the process died with "FATAL: exception not rethrown" (SIGABRT) instead of exiting: after a
    `close()` that gave up waiting for the attempt in progress (a `connect/timeout_ms` above
    `CLOSE_WAIT_S`, or a starved machine), or with a publisher never closed."""
    with _exit_lock:
        unclosed = list(_unclosed)
    for pub in unclosed:
        pub.close()
    with _exit_lock:
        threads = list(_threads_in_zenoh)
        _threads_in_zenoh.clear()
    for thread in threads:
        thread.join(EXIT_WAIT_S)


atexit.register(_settle_at_exit)


class ScanPublisher:
    """Publishes one robot's scans to one map over Zenoh. Thread-safe: concurrent `publish` calls
    take distinct seqs and their scans leave in seq order (one at a time).

    Args:
        map_id, robot_id: ids matching `fleetmap.wire.ID_PATTERN` (`[A-Za-z0-9_-]{1,64}`); anything
            else raises ValueError at construction.
        connect: Zenoh endpoints of the service, a list or one string (default: those of
            `zenoh_config`, else `tcp/127.0.0.1:7447`, where `fleetmap serve` listens by default).
        encoding: "binary" (compact, for high rates) or "json".
        zenoh_config: a `zenoh.Config` or JSON5 file to start from (see `client_config`).
        block: True (default) publishes with `CongestionControl.BLOCK` (a full link blocks `publish`,
            no scan is dropped); False uses `DROP` (best effort: never blocks, may drop under load).
        send_session_id: True (default) sends a random session id in every scan (see the module docstring);
            False sends none (then the service recognises restarts by the stamps only). Both flags must
            be bools (TypeError otherwise: `block="no"` was taken for True).
        backlog: scans kept for re-delivery after a lost connection (default `DEFAULT_BACKLOG`; see the
            module docstring); 0: none, with a plain Zenoh publisher, for a service older than
            store and forward (scans published while disconnected are then dropped).
        cache: scans the advanced publisher's Zenoh cache keeps for the service to fetch again, at
            least `backlog` (default `CACHE_BACKLOGS` times it, 2000: about 9 MB of binary 1081-beam
            scans; see `CACHE_BACKLOGS`). Not with `backlog=0`, which has no cache.

    Counters (each successful `publish` counts in exactly one of the first three):

    * `published`: scans handed to Zenoh while a router (or peer) was connected, including those of
      the queue when the session opened or a hold ended, and those put while a link was dying
      unnoticed (Zenoh still counts it connected until its lease runs out; the service fetches them
      from the advanced publisher's cache);
    * `backlogged`: scans kept for re-delivery: waiting in the queue (`pending`) while disconnected
      or in a hold, or put in the advanced publisher's cache because Zenoh noticed the link down
      between the publisher's look at it and the put. A dead zone that outlasts `backlog` scans
      loses the oldest of them all the same (`dropped`; the service counts them as lost);
    * `dropped`: scans given up here: published while disconnected with `backlog=0`, pushed out of
      the full queue (moved from `backlogged`), still in that queue at `close()` (moved too), or
      refused by a session closing meanwhile.

    The session opens in the background (see the module docstring): use `wait_connected`.
    """

    def __init__(
        self,
        map_id: str,
        robot_id: str,
        connect: Sequence[str] | str | None = None,
        encoding: Encoding = "binary",
        zenoh_config: zenoh.Config | str | Path | None = None,
        block: bool = True,
        send_session_id: bool = True,
        backlog: Integer = DEFAULT_BACKLOG,
        cache: Integer | None = None,
    ) -> None:
        for name, value in (("map_id", map_id), ("robot_id", robot_id)):
            if not isinstance(value, str) or not is_valid_id(value):
                raise ValueError(f"{name} {value!r} is invalid: use 1 to 64 characters from A-Z a-z 0-9 _ -")
        if not is_whole_number(backlog) or backlog < 0:  # a NumPy integer too, as a seq may be
            raise ValueError(f"backlog must be an integer >= 0, got {backlog!r}")
        if cache is not None and not backlog and cache != 0:
            raise ValueError(
                "a cache needs a backlog: backlog=0 publishes with a plain publisher, which keeps none"
            )
        if cache is not None and (not is_whole_number(cache) or cache < backlog):
            raise ValueError(f"cache must be an integer >= backlog ({backlog}), got {cache!r}")
        if encoding not in ("binary", "json"):
            raise ValueError(f"encoding must be 'binary' or 'json', got {encoding!r}")
        for name, flag in (("block", block), ("send_session_id", send_session_id)):
            if not isinstance(flag, bool):  # block="no" (or "false" read from a file) was taken for True
                raise TypeError(f"{name} must be True or False, got {flag!r}")
        self.map_id = map_id
        self.robot_id = robot_id
        self.encoding: Encoding = encoding
        self.block = block
        self.backlog = int(backlog)
        #: Scans the advanced publisher's Zenoh cache keeps (0 with `backlog=0`).
        self.cache = int(cache) if cache is not None else CACHE_BACKLOGS * self.backlog
        self.scan_key = SCAN_KEY.format(map_id=map_id, robot_id=robot_id)
        self.alive_key = ALIVE_KEY.format(map_id=map_id, robot_id=robot_id)
        self._config = client_config(connect, zenoh_config)
        self.endpoints: list[str] = connect_endpoints(self._config)
        self._encode = encode_binary if encoding == "binary" else encode_json
        self._zenoh_encoding = zenoh.Encoding(BINARY_ENCODING if encoding == "binary" else JSON_ENCODING)
        # _lock guards the session objects and the counters; the opener thread sets them.
        # Both locks are reentrant for `close()` from a signal handler (a robot's SIGTERM handler):
        # it runs in the thread it interrupted, inside `publish` perhaps, whose locks stay held
        # until the handler returns. With plain locks that close() waited for itself: for ever
        # for `_lock` (held while a scan is encoded), 6 s (`CLOSE_SEND_WAIT_S`) for `_send_lock`.
        # Taken again so, close() finds the interrupted publish between two bytecodes, never
        # inside a Zenoh call; once the handler returns, that publish finds the publisher closed.
        self._lock = threading.RLock()
        # _send_lock is held by `publish` from taking a seq to handing the scan to Zenoh, so that
        # scans leave in seq order: the service takes a scan whose seq arrives after a higher one for
        # a duplicate and ignores it. Not `_lock`, which `close` and the counters need meanwhile.
        self._send_lock = threading.RLock()
        self._opened = threading.Event()
        self._closed = threading.Event()
        self._session: zenoh.Session | None = None
        self._publisher: zenoh.Publisher | zenoh.ext.AdvancedPublisher | None = None
        # Only for `subscribed`: an advanced publisher has no matching status, a plain one on the same
        # key (never put to) has. With backlog 0 it is the publisher itself.
        self._matching: zenoh.Publisher | None = None
        # Scans published before the session opened, or during a reconnection's hold (seq, session id
        # and payload, in seq order), sent when it opens or the hold ends.
        self._pending: deque[tuple[int, int | None, bytes]] = deque()
        # Whether the link was up at the last look (publish or the watcher), and the routers and
        # peers it went to: a change to up, or a router or peer not there at the last look (a
        # restarted service has a new Zenoh id), is a (re)connection, which starts a hold
        # (monotonic times it ends at the earliest in `_hold_least`, at the latest in `_hold_until`).
        # The link came up after the look before (`_looked_at` then, kept in `_hold_since`): a query
        # for the cache that reached the publisher since (`_fetched_at`, set by `_watch_fetches`) is
        # the new service's, and ends the hold.
        self._link_up = False
        # Whether a subscriber of the scan key (the service's) was known at the last look: one that
        # appears over a link that stayed up starts a hold too (`_check_link`).
        self._listened = False
        self._neighbours: frozenset[str] = frozenset()
        self._hold_until: float | None = None
        self._hold_least = 0.0
        self._hold_since = 0.0
        self._looked_at = 0.0
        self._fetched_at: float | None = None
        # Whether a scan was ever handed to Zenoh (so its cache holds one): until then no service
        # can lose cached scans to a live one, and a hold waits for no query (`_check_link`).
        self._cached = False
        self._fetch_watch: zenoh.Queryable[zenoh.Handler[zenoh.Query]] | None = None
        self._fetch_thread: threading.Thread | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._next_seq = 0
        self._last_seq: int | None = None
        # True while `publish` runs (under `_send_lock`): a publish of the same thread meanwhile is
        # one of a signal handler, refused.
        self._publishing = False
        # The seq of the first scan of the current session (`session_id`): `flush` covers from it.
        self._session_first_seq: int | None = None
        # The seq of the first scan of the current session handed to Zenoh (None: none yet). Those
        # before it were given up here (`_with_given_up`).
        self._session_first_sent: int | None = None
        self._session_id = new_session_id() if send_session_id else None
        #: Scans handed to Zenoh while a router (or peer) was connected (see the class docstring).
        self.published = 0
        #: Scans kept for re-delivery while disconnected (see the class docstring).
        self.backlogged = 0
        #: Scans given up (see the class docstring).
        self.dropped = 0
        #: The last error of a connection attempt (e.g. "Unable to connect ..."), for diagnostics.
        self.last_connect_error: str | None = None
        self._opener = threading.Thread(
            target=self._open_loop, name=f"fleetmap-publisher-{map_id}-{robot_id}", daemon=True
        )
        self._opener.start()
        with _exit_lock:  # once there is an opener to stop
            _unclosed.add(self)

    # -- connection --------------------------------------------------------------------------------

    def _open_loop(self) -> None:
        """Open the session, retrying until it works or the publisher is closed; then watch the link
        (`_watch`) until `close()`."""
        while not self._closed.is_set():
            started = time.monotonic()
            try:
                session = zenoh.open(self._config)
            except zenoh.ZError as exc:
                self.last_connect_error = zenoh_error_text(exc)
                # An attempt that failed fast (e.g. connection refused with a zero timeout) must not spin.
                self._closed.wait(max(0.0, 0.2 - (time.monotonic() - started)))
                continue
            congestion = zenoh.CongestionControl.BLOCK if self.block else zenoh.CongestionControl.DROP
            # _send_lock first (as `publish` takes it): no scan may overtake the pre-open queue's.
            with self._send_lock, self._lock:
                if self._closed.is_set():
                    session.close()
                    return
                self._token = session.liveliness().declare_token(self.alive_key)
                self._matching = session.declare_publisher(
                    self.scan_key,
                    encoding=self._zenoh_encoding,
                    congestion_control=congestion,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                if self.backlog:
                    self._publisher = zenoh.ext.declare_advanced_publisher(
                        session,
                        self.scan_key,
                        encoding=self._zenoh_encoding,
                        congestion_control=congestion,
                        reliability=zenoh.Reliability.RELIABLE,
                        cache=zenoh.ext.CacheConfig(self.cache),
                        sample_miss_detection=zenoh.ext.MissDetectionConfig(
                            heartbeat=HEARTBEAT_S, sporadic_heartbeat=None
                        ),
                        publisher_detection=True,
                    )
                    # Every query for this publisher's cache (a subscriber's history fetch, a
                    # heartbeat's or a miss's recovery) reaches this queryable too: it answers
                    # nothing, it only tells the hold that the service is fetching. Its queries go
                    # to a channel that a thread of ours waits on (`_watch_fetches`) and `close()`
                    # joins. Not a Python callback: zenoh-python runs one on a thread of its own, a
                    # daemon when declared here (the opener is one), which nothing joins; waking as
                    # the queryable went at exit, it came back into a finalizing interpreter and the
                    # process died with "FATAL: exception not rethrown" (SIGABRT), as `fleetmap
                    # replay` did in CI after its last message. Nor a callback on Zenoh's own thread
                    # (`indirect=False`): that thread would wait for the GIL, and the session's
                    # traffic with it. Nor a channel the link check drains: it saw a query only at
                    # its next look, late, and the service's fetch ended no sooner.
                    source = self._publisher.id
                    self._fetch_watch = session.declare_queryable(
                        f"{self.scan_key}/@adv/pub/{source.zid}/{source.eid}/**",
                        zenoh.handlers.RingChannel(FETCH_WATCH_DEPTH),
                    )
                    self._fetch_thread = threading.Thread(
                        target=self._watch_fetches,
                        args=(self._fetch_watch.handler,),
                        name=f"fleetmap-fetch-watch-{self.map_id}-{self.robot_id}",
                        daemon=True,
                    )
                    self._fetch_thread.start()
                else:
                    self._publisher = self._matching
                self._session = session
                self.last_connect_error = None
                if not self.backlog:
                    self._link_up = True
            self._opened.set()
            self._watch()
            return

    def _watch_fetches(self, queries: zenoh.Handler[zenoh.Query]) -> None:
        """Until the fetch watch is undeclared (`close()`): note when each query for the advanced
        publisher's cache reaches the session, for the hold (`_check_link`). Answers nothing: the
        cache's own queryable does."""
        while True:
            try:
                query = queries.recv()
            except zenoh.ZError:  # undeclared: the channel is closed
                return
            self._fetched_at = time.monotonic()
            # Dropped at once, not when Python collects it: the querier's query ends only once
            # every queryable it reached let go of it.
            query.drop()

    def _watch(self) -> None:
        """Until `close()`: notice (re)connections and end their holds (`_check_link`)."""
        while not self._closed.wait(WATCH_INTERVAL_S):
            # Not a wait without end: a `publish` interrupted by a signal handler that closes the
            # publisher holds the lock until the handler returns, and close() joins this thread
            # meanwhile (it waited `CLOSE_WAIT_S` for it).
            if not self._send_lock.acquire(timeout=WATCH_INTERVAL_S):
                continue
            try:
                if self._closed.is_set():
                    return
                self._check_link()
            finally:
                self._send_lock.release()

    def _check_link(self) -> bool:
        """With `_send_lock` held, the session open: while the link is down, and during the hold
        after it came up, scans wait in the queue; when the hold is over, send the queued scans.
        Returns whether scans are being held, so a scan published now must wait in the queue behind
        them. With backlog 0 there is no hold and no queue.

        Nothing goes to Zenoh while the link is down (see the module docstring): a put racing with
        the link coming back could reach a restarted service live, ahead of the cache it had yet to
        fetch, and zenoh-ext would then drop that cache as old. Queued, the scan can only leave
        after the hold: `RECONNECT_HOLD_S` after the (re)connection was noticed and `FETCH_MARGIN_S`
        after a query for the cache reached the publisher since the link came up (the service is
        fetching it: its replies leave first), or `RECONNECT_HOLD_MAX_S` after it when none came. A
        session that opened without a link (a peer's) keeps its scans queued until it has one.

        The same holds for the service's scan subscriber behind a router (`fleetmap serve
        --zenoh-connect`, robots connected to that router): a service that restarts there changes
        no link of the robot's, only whether a subscriber of its key is known. While none is, scans
        wait in the queue too, and one that appears starts a hold (unless one runs): put live as
        the restarted service subscribed, a scan reached it before its fetch of the cache, and
        zenoh-ext dropped the whole cache as old (1 of 3 kill -9 restarts lost every scan published
        while the service was away, and those it had not made durable)."""
        if not self.backlog:
            return False
        neighbours = self._connected_to()
        up = bool(neighbours)
        listened = up and self.subscribed
        now = time.monotonic()
        with self._lock:
            looked, self._looked_at = self._looked_at, now
            # A new router or peer too: a service killed and restarted between two looks (a robot
            # publishing rarely, a starved watcher) was never seen down, and its new process must
            # get the cache before any live scan all the same.
            reconnected = up and (not self._link_up or not neighbours <= self._neighbours)
            # A subscriber again over the same link: the service (re)started behind a router. A
            # hold already running (the link itself came back) is not started again: the query it
            # waits for may have come already, and a new hold would wait for another.
            resubscribed = listened and not self._listened and self._hold_until is None
            self._listened = listened
            if reconnected or resubscribed:
                # With nothing in the cache yet (the first connection), there is no fetch to wait
                # for: a router or peer that never queries (no fleetmap service behind it yet, a
                # plain subscriber) held the first scans RECONNECT_HOLD_MAX_S, past `fleetmap
                # replay`'s --wait-timeout of 2 s.
                self._hold_until = now + (RECONNECT_HOLD_MAX_S if self._cached else RECONNECT_HOLD_S)
                self._hold_least = now + RECONNECT_HOLD_S
                self._hold_since = looked  # the link came up after that look
            self._link_up = up
            self._neighbours = neighbours
            if not up:
                return True
            if self._hold_until is not None:
                fetched = self._fetched_at  # the last query for the cache, if it came since the link did
                fetched = fetched if fetched is not None and fetched > self._hold_since else None
                fetching = fetched is None or now < fetched + FETCH_MARGIN_S
                if now < self._hold_until and (now < self._hold_least or fetching):
                    return True
                self._hold_until = None
            if not listened:
                # After the hold, so that a hold ends (`wait_connected(require_subscriber=False)`)
                # where no service subscribes yet; its scans wait for one (and for its hold).
                return True
            if not self._pending:
                return False
            held = list(self._pending)
            self._pending.clear()
            publisher = self._publisher
        assert publisher is not None  # the session opened
        sent = 0
        with contextlib.suppress(zenoh.ZError):  # close() raced: the rest are given up
            for seq, session, payload in held:
                self._cached = True  # before the put: a put that raises may have reached the cache
                publisher.put(payload)  # Zenoh's cache keeps it too, should the link die again
                sent += 1
                if self._session_first_sent is None:
                    self._note_sent(seq, session)
        given_up = len(held) - sent
        with self._lock:
            self.backlogged -= sent + given_up
            self.published += sent
            self.dropped += given_up
        return False

    @property
    def connected(self) -> bool:
        """True while the session is connected to at least one router or peer."""
        return bool(self._connected_to())

    def _connected_to(self) -> frozenset[str]:
        """The Zenoh ids of the routers and peers the session is connected to (none: not connected,
        or closed)."""
        session = self._session
        if session is None or self._closed.is_set():
            return frozenset()
        return _neighbours_of(session)

    @property
    def subscribed(self) -> bool:
        """True when Zenoh knows a subscriber for this robot's scan key (the service is listening)."""
        pub = self._matching
        if pub is None or self._closed.is_set():
            return False
        # zenoh's stub types matching_status a bool; it is a MatchingStatus (zenoh 1.x).
        return bool(pub.matching_status.matching)  # type: ignore[attr-defined]

    def wait_connected(self, timeout: Real | None = None, *, require_subscriber: bool = True) -> bool:
        """Wait until the session is connected and, with `require_subscriber` (default), until a
        subscriber of the scan key is known, i.e. the service's ingest is reachable and listening.

        Returns True when that happened, False when `timeout` seconds (None: no limit) passed first
        or the publisher was closed. Polls every 10 ms, so Ctrl-C interrupts it.
        """
        deadline = _deadline(timeout)
        while not self._closed.is_set():
            ready = self._hold_until is None and self._link_up
            if ready and self.connected and (not require_subscriber or self.subscribed):
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return False

    # -- publishing --------------------------------------------------------------------------------

    @property
    def last_seq(self) -> int | None:
        """The seq of the last published (or dropped) scan, None before the first."""
        return self._last_seq

    @property
    def session_id(self) -> int | None:
        """The session id its scans carry (None with `send_session_id=False`): picked at random when the
        publisher is made, and again when an explicit seq is below the last one."""
        return self._session_id

    @property
    def pending(self) -> int:
        """Scans in the publisher's own queue: published before the session opened, while it knew it
        was disconnected, or during the hold after a (re)connection; sent when the hold ends (counted
        in `backlogged` meanwhile)."""
        return len(self._pending)

    @property
    def next_seq(self) -> int:
        """The seq the next `publish` without an explicit seq will use."""
        return self._next_seq

    def publish(
        self, scan: Scan | ScanMessage, seq: Integer | None = None, stamp: Real | None = None
    ) -> bool:
        """Encode and publish one scan.

        `scan` is an engine `Scan` (or a `ScanMessage`, converted with `to_scan`; its seq and stamp
        are the defaults then). `seq` defaults to an automatic counter starting at 0; an explicit
        seq also moves the counter to seq + 1; one below the last seq starts a new session
        (`session_id`), so the service takes it for a restart, not a duplicate (the last seq again
        is a resend, in the same session: a duplicate if the first one arrived). A `ScanMessage`'s own
        session is not sent: the publisher's is. `stamp` defaults to the current time (seconds since
        the epoch). With `block=True` this may block while the link is congested.

        Returns True when the scan was handed to a connected session (counted in `published`) or
        kept for re-delivery while disconnected (`backlogged`: delivered when the connection is back,
        unless more than `backlog` newer scans push it out first), False when it was dropped
        (`dropped`: no router connected with `backlog=0`, or the publisher closing meanwhile).
        Raises `PublisherClosed` after `close()`, TypeError for a `scan` that is neither, a seq that
        is not an integer or a stamp that is not a number, ValueError for a negative or too large seq
        or a non-finite stamp, and `fleetmap.scan.ScanError` for a `ScanMessage` the engine refuses
        or, in binary, a scan whose range_min or angles float32 cannot hold (`codec.encode_binary`),
        RuntimeError when a signal handler calls it while it interrupted a publish of the same
        thread (`close()` may be called there). A call that raises publishes nothing and leaves the
        seq counter as it was (the service would count a skipped seq as a lost scan).
        """
        if isinstance(scan, ScanMessage):
            seq = scan.seq if seq is None else seq
            stamp = scan.stamp if stamp is None else stamp
            scan = scan.to_scan()
        elif not isinstance(scan, Scan):
            raise TypeError(f"publish takes a fleetmap Scan or ScanMessage, not {type(scan).__name__}")
        if seq is not None:
            seq = checked_seq(seq)
        stamp = checked_stamp(time.time() if stamp is None else stamp)
        with self._send_lock:
            # A signal handler publishing while it interrupted a publish of this thread: the locks
            # are reentrant (for `close()` there), so its publish would run inside the interrupted
            # one and send its scan before that one's lower seq, which the service then ignores as
            # a duplicate, or send the queue while the interrupted one was sending it.
            if self._publishing:
                raise RuntimeError(
                    "publish() was called by a signal handler that interrupted a publish() of the same "
                    "thread: set a flag in the handler and publish from the program's loop"
                )
            self._publishing = True
            try:
                return self._send(scan, seq, stamp)
            finally:
                self._publishing = False

    def _send(self, scan: Scan, seq: int | None, stamp: float) -> bool:
        """`publish`, its arguments checked, with `_send_lock` held: take the seq, encode, and queue
        the scan or hand it to Zenoh."""
        with self._lock:
            if self._closed.is_set():
                raise PublisherClosed(f"publisher {self.map_id}/{self.robot_id} is closed")
            session = self._session_id
            if seq is None:
                seq = self._next_seq
                if seq >= SEQ_LIMIT:
                    raise ValueError("the automatic seq passed 2**63 - 1: publish with seq=0 to restart")
            elif session is not None and self._last_seq is not None and seq < self._last_seq:
                session = new_session_id()  # the seq starts again: under the old session, duplicates
            # The counter moves only once the scan is handed on (`_take_seq`: sent, queued or given
            # up), so that a call that raises leaves no gap: one that cannot be encoded, and a
            # KeyboardInterrupt (Ctrl-C, or SIGTERM as `fleetmap replay` maps it) raised during the
            # link check or the put. Moved first, such a seq was never sent: the service counted it
            # lost, and a `flush` after the Ctrl-C waited its whole timeout for it (2 runs in 8).
            payload = self._encode(scan, seq, stamp, session=session)
            publisher, zenoh_session = self._publisher, self._session
            if publisher is None and not self.backlog:  # no session yet, nothing kept
                self._take_seq(seq, session)
                self.dropped += 1
                return False
        if publisher is None or self._check_link():  # no session yet, no link, or a hold: queue it
            with self._lock:
                self._take_seq(seq, session)
                if self._closed.is_set():
                    # close() ran since the check above (from another thread) and gave up the
                    # queue: queued now, the scan would stay there unsent, counted `backlogged`.
                    self.dropped += 1
                    return False
                if len(self._pending) == self.backlog:
                    self._pending.popleft()  # the oldest gives way
                    self.backlogged -= 1
                    self.dropped += 1
                self._pending.append((seq, session, payload))
                self.backlogged += 1
            return True
        # The session's link, not `self.connected`, which is False once close() has begun: a
        # close() of another thread waits for this put (`_send_lock`), and the session's close
        # then flushes it over the live link, so it is `published`, not `backlogged`.
        connected = zenoh_session is not None and bool(_neighbours_of(zenoh_session))
        if not connected and not self.backlog:
            with self._lock:
                self._take_seq(seq, session)
                self.dropped += 1
            return False
        try:
            # The link died since `_check_link` looked: the cache keeps it for the service to fetch.
            self._cached = True
            publisher.put(payload)
        except zenoh.ZError:
            # Only possible when close() raced with this call: report it like a disconnection.
            with self._lock:
                self._take_seq(seq, session)
                self.dropped += 1
            return False
        with self._lock:
            self._take_seq(seq, session)
        self._note_sent(seq, session)
        with self._lock:
            if connected:
                self.published += 1
            else:
                self.backlogged += 1
        return True

    def _take_seq(self, seq: int, session: int | None) -> None:
        """With `_lock` held: the scan `seq` of session `session` was handed on (sent, queued or
        given up), so the seq counter moves past it (and the session is this publisher's now)."""
        if self._session_first_seq is None or session != self._session_id:
            self._session_first_seq = seq
            self._session_first_sent = None
        self._session_id = session
        self._next_seq = seq + 1
        self._last_seq = seq

    def _note_sent(self, seq: int, session: int | None) -> None:
        """The scan `seq` of session `session` was handed to Zenoh: the first of the current
        session's so is `_session_first_sent`."""
        with self._lock:
            if self._session_first_sent is None and session == self._session_id:
                self._session_first_sent = seq

    # -- delivery confirmation ---------------------------------------------------------------------

    def flush(self, timeout: Real | None = None) -> DeliveryReport:
        """Wait until the service reports every scan of this publisher's session (its scans since
        the publisher was made, or since an explicit seq started its seq again) settled, and say
        what became of them: a `DeliveryReport`, true when all of them are integrated.

        Asks the service every `FLUSH_POLL_S` (a Zenoh query on `fleetmap/<map>/<robot>/delivery`)
        until it reports the session settled through the last seq published when `flush` was called
        (scans published meanwhile are not waited for), or until `timeout` seconds (None: no limit)
        pass: then the report says what was known last (`unsettled` > 0, or `answered` False when the
        service never answered). Waits through disconnections: the backlog re-delivers what the
        service missed. A scan dropped here (`backlog=0` while disconnected) never arrives: it shows
        as lost, or, the last one, as unsettled until the timeout. Returns at once with nothing
        published. Raises `DeliveryUnsupported` when the service's scan subscriber is reachable but
        no delivery query is answered for `NO_ANSWER_S` (an older service), RuntimeError for an error
        reply or an answer that is not a fleetmap `DeliveryStatus`, `PublisherClosed` after `close()`
        (which gives up what was not delivered: flush first) or when it is called meanwhile,
        TypeError for a timeout that is not a number, ValueError for NaN (which never passed).
        """
        _deadline(timeout)  # a bad timeout raises, whether or not there is anything to wait for
        with self._lock:
            if self._closed.is_set():
                raise PublisherClosed(
                    f"publisher {self.map_id}/{self.robot_id} is closed: flush before close(), which gives "
                    "up the scans not delivered yet"
                )
            first, last, session = self._session_first_seq, self._last_seq, self._session_id
        if first is None or last is None:
            return DeliveryReport(published=0, answered=True)
        return self._await_delivery(session, first, last, timeout, ended=False)

    def flush_ended(
        self, session_id: Integer | None, first_seq: Integer, last_seq: Integer, timeout: Real | None = None
    ) -> DeliveryReport:
        """What became of the scans `first_seq` .. `last_seq` of an ENDED publisher session of this
        robot: one whose publisher no longer runs, typically the robot's process before it restarted
        mid-mission (`flush` covers only this publisher's own session). Save `session_id` (None for
        a publisher made with `send_session_id=False`: its scans without a session id) and
        `last_seq` as the robot publishes (and the first seq) to ask about them after a restart.

        Its scans the service had not received went with that publisher's backlog, so the answer is
        final once the service has settled every scan of the session it accepted: the seqs after
        the last one it accepted count as `lost`, and the report is `settled`. It returns at once,
        unsettled, when the service counts nothing of the session (none of its scans arrived, or the
        service forgot it: an in-memory service restarted since, the robot's 136 more recent
        sessions, 8 and 128 pushed out of them, or a map full of robots forgot the robot), and on the
        timeout otherwise (None: no limit). Asks and raises as `flush` does, and
        ValueError for a session id outside [0, 2**53) or a seq outside [0, 2**63), or a last_seq
        below first_seq.
        Do not call it for a session whose publisher still runs (it may deliver more): `flush` that
        one."""
        # Within the wire's bounds too: a session id past 2**53 came back as the service's error reply
        # (a RuntimeError, "the delivery query failed"), a seq past 2**63 as a report of that many
        # scans "unconfirmed", and with no service reachable either waited for the timeout.
        # None: the scans sent without a session id, as `session_id` says of a publisher made with
        # send_session_id=False (it was refused, though 0, the query's "none", asked about them).
        limits = (
            ("session_id", 0 if session_id is None else session_id, SESSION_LIMIT, "2**53"),
            ("first_seq", first_seq, SEQ_LIMIT, "2**63"),
            ("last_seq", last_seq, SEQ_LIMIT, "2**63"),
        )
        for name, value, limit, text in limits:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= value < limit:
                raise ValueError(f"{name} must be an integer in [0, {text}), got {value!r}")
        if last_seq < first_seq:
            raise ValueError(f"last_seq {last_seq} is below first_seq {first_seq}")
        if self._closed.is_set():
            raise PublisherClosed(f"publisher {self.map_id}/{self.robot_id} is closed")
        return self._await_delivery(
            int(session_id or 0) or None, int(first_seq), int(last_seq), timeout, ended=True
        )

    def _await_delivery(
        self, session: int | None, first: int, last: int, timeout: Real | None, ended: bool
    ) -> DeliveryReport:
        """Ask the service until the scans `first` .. `last` of `session` are settled (or, `ended`,
        final: `ended_session_report`), or `timeout` passes; `flush` and `flush_ended`."""
        deadline = _deadline(timeout)
        report = DeliveryReport(published=last - first + 1, first_seq=first, last_seq=last)
        unanswered_since: float | None = None  # since when the queries end at once without a reply
        while True:
            started = time.monotonic()
            # Within the flush's timeout: a query over a dead link waits for its own.
            wait_at_most = DELIVERY_QUERY_TIMEOUT_S if deadline is None else deadline - started
            wait_at_most = max(FLUSH_POLL_S, min(DELIVERY_QUERY_TIMEOUT_S, wait_at_most))
            status = self._query_delivery(session, wait_at_most)
            now = time.monotonic()
            # Ended well before its timeout without a reply: no queryable matched (not a dead link).
            unanswered = status is None and now - started < wait_at_most / 2
            if status is not None:
                unanswered_since = None
                report = delivery_report(status, session, first, last)
                if not ended:
                    report = self._with_given_up(report, session)
                if report.settled:
                    return report
                if ended:
                    final = ended_session_report(status, session, report)
                    if final is not None:
                        return final
            elif unanswered and self.connected and self.subscribed:
                unanswered_since = now if unanswered_since is None else unanswered_since
                if now - unanswered_since >= NO_ANSWER_S:
                    raise DeliveryUnsupported(
                        f"the fleetmap service at {', '.join(self.shown_endpoints)} answers no delivery "
                        f"query ({DELIVERY_KEY.format(map_id=self.map_id, robot_id=self.robot_id)}): it is "
                        "older than delivery confirmation, or access control keeps the query from it"
                    )
            else:
                unanswered_since = None  # not reachable, or silent: not yet
            if deadline is not None and now >= deadline:
                return report
            wait = FLUSH_POLL_S if deadline is None else min(FLUSH_POLL_S, deadline - now)
            if self._closed.wait(max(0.0, wait)):
                raise PublisherClosed(f"publisher {self.map_id}/{self.robot_id} was closed during flush")

    def _with_given_up(self, report: DeliveryReport, session: int | None) -> DeliveryReport:
        """`report` (of this publisher's session `session`) with the seqs before the first scan of
        the session handed to Zenoh counted as `lost`: given up here before the service could see
        them (pushed out of the full queue before the first connection, dropped with backlog 0).
        The service counts from the first scan it got (`counted_from`) and knew nothing of them:
        they were "unconfirmed" in a report already final (`settled`)."""
        with self._lock:
            first_sent = self._session_first_sent if session == self._session_id else None
        first, counted = report.first_seq, report.counted_from
        if first_sent is None or first is None or counted is None or counted <= first:
            return report
        return replace(report, lost=report.lost + min(first_sent, counted) - first)

    def _query_delivery(self, session_id: int | None, timeout: float) -> DeliveryStatus | None:
        """One delivery query: the service's answer, None when none came (no session or link yet,
        no queryable, or none answered in `timeout` seconds). Raises RuntimeError for an error
        reply or an answer that is not a `DeliveryStatus` (not a fleetmap service answering)."""
        session = self._session
        if session is None:
            return None
        key = DELIVERY_KEY.format(map_id=self.map_id, robot_id=self.robot_id)
        selector = (
            f"{key}?{DELIVERY_SESSION_PARAMETER}={0 if session_id is None else session_id}"
            f";{DELIVERY_FIELDS_PARAMETER}={DELIVERY_FIELDS}"
        )
        try:
            replies = session.get(selector, timeout=timeout)
            for reply in replies:
                if reply.ok is not None:
                    try:
                        return DeliveryStatus.model_validate_json(reply.ok.payload.to_bytes())
                    except ValueError as exc:
                        raise RuntimeError(f"the delivery answer is not a fleetmap one: {exc}") from None
                # Zenoh's own errors (the query's timeout: a silent link) are no answer; the service's are.
                if reply.err is not None and reply.err.encoding == zenoh.Encoding(DELIVERY_ERROR_ENCODING):
                    raise RuntimeError(f"the delivery query failed: {reply.err.payload.to_string()}")
        except zenoh.ZError:  # closed meanwhile
            return None
        return None

    # -- lifetime ----------------------------------------------------------------------------------

    def close(self) -> None:
        """Withdraw the liveliness token, undeclare the publisher and close the session. Idempotent.

        Scans already handed to Zenoh over a live link are flushed by the session close (reliable
        channel); scans still waiting for re-delivery (`backlogged`, `pending`) are given up, and so
        are those put on a link dying unnoticed (counted `published`: Zenoh's cache goes with the
        session). On such a link the session's close waits about 10 s (Zenoh's close timeout). A
        `publish` of another thread blocked in Zenoh (BLOCK on a congested or frozen link) is waited
        for, at most `CLOSE_SEND_WAIT_S`. While
        no connection was made, it waits for the attempt in progress to end (at most `CLOSE_WAIT_S`;
        an attempt still running then is waited for at the program's exit, at most `EXIT_WAIT_S`).
        A publisher the program leaves open is closed at its exit (atexit)."""
        with self._lock:
            if self._closed.is_set():
                return
            self._closed.set()
            session, self._session = self._session, None
            publisher, self._publisher = self._publisher, None
            matching, self._matching = self._matching, None
            token, self._token = self._token, None
            fetch_watch, self._fetch_watch = self._fetch_watch, None
            # Never sent now: given up (`dropped`), no longer kept for re-delivery (`backlogged`).
            self.backlogged -= len(self._pending)
            self.dropped += len(self._pending)
            self._pending.clear()
        # A `publish` may be inside the publisher's put (BLOCK: a congested or frozen link), during
        # which zenoh-python holds the publisher borrowed: its undeclare raised RuntimeError
        # ("Already borrowed") out of close(), which left the session open, and the session's
        # close waits for such a put until its own timeout (10 s). Wait for the put instead: it
        # returns once the link drains, or once Zenoh closes a link it could not send on.
        sending = self._send_lock.acquire(timeout=CLOSE_SEND_WAIT_S)
        try:
            for thing in (token, fetch_watch, publisher, None if matching is publisher else matching):
                if thing is not None:
                    # RuntimeError: a put still borrows it past the wait; the session's close undeclares it.
                    with contextlib.suppress(zenoh.ZError, RuntimeError):
                        thing.undeclare()
        finally:
            if sending:
                self._send_lock.release()
        if session is not None:
            with contextlib.suppress(zenoh.ZError):
                session.close()
        # The opener exits after its current attempt, the fetch watcher with its undeclared channel:
        # wait for them. A thread still inside `zenoh.open` or the channel's wait when the program
        # exits comes back into a finalizing interpreter, and the process dies with "FATAL:
        # exception not rethrown" (SIGABRT, exit 134) instead of exiting normally: one still in a
        # Zenoh call after CLOSE_WAIT_S is waited for at exit (`_settle_at_exit`).
        self._opener.join(timeout=CLOSE_WAIT_S)
        if self._fetch_thread is not None:
            self._fetch_thread.join(timeout=CLOSE_WAIT_S)
        with _exit_lock:
            _unclosed.discard(self)
            _threads_in_zenoh.update(
                t for t in (self._opener, self._fetch_thread) if t is not None and t.is_alive()
            )

    @property
    def closed(self) -> bool:
        """True once `close()` was called: `publish` then raises `PublisherClosed`."""
        return self._closed.is_set()

    def __enter__(self) -> ScanPublisher:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def shown_endpoints(self) -> list[str]:
        """`endpoints` as they may be shown, in logs and messages: the configuration an endpoint
        carries after `#` (a TLS private key given inline, `#connect_private_key_base64=...`) with
        its values left out (`fleetmap.shown_endpoint`), as the service shows its own."""
        return shown_endpoints(self.endpoints)

    def __repr__(self) -> str:
        state = "closed" if self.closed else "connected" if self.connected else "connecting"
        return (
            f"ScanPublisher(map_id={self.map_id!r}, robot_id={self.robot_id!r}, encoding={self.encoding!r}, "
            f"{state}, endpoints={self.shown_endpoints})"
        )


def _neighbours_of(session: zenoh.Session) -> frozenset[str]:
    """The Zenoh ids of the routers and peers `session` is connected to (none: not connected, or
    the session closed)."""
    try:
        info = session.info
        return frozenset(str(zid) for zid in (*info.routers_zid(), *info.peers_zid()))
    except zenoh.ZError:  # closed meanwhile
        return frozenset()


def check_timeouts(**timeouts: float | None) -> None:
    """ValueError naming the first of `timeouts` (seconds; None: no limit) that is below 0 or NaN:
    the commands' checks of their arguments (`replay.replay`, `sim.run_sim`), before they publish or
    wait. NaN passed every check downstream: a wait for it never ended, a flush raised only after
    the whole run, and a negative one gave up "within -1 s"."""
    for name, value in timeouts.items():
        if value is not None and not value >= 0.0:
            raise ValueError(f"{name} must be a number of seconds >= 0, got {value}")


def check_period(period: float, what: str) -> None:
    """ValueError unless a thread can wait `period` seconds (the time between two scans of
    `replay.replay` and `sim.run_sim` at their rate, `what`, which the message names) at once: at
    most `threading.TIMEOUT_MAX`, about 292 years, which `time.sleep` and `Event.wait` take.
    Past it the replay published its first scan, then ended in an OverflowError traceback, and the
    sim's robots stopped on "OverflowError: timestamp out of range for platform time_t"."""
    if period > threading.TIMEOUT_MAX:
        raise ValueError(
            f"{what} is too slow: a scan every {period:.3g} s, longer than a thread can wait "
            f"({threading.TIMEOUT_MAX:.4g} s, about 292 years)"
        )


def _deadline(timeout: Real | None) -> float | None:
    """The monotonic time at which a wait of `timeout` seconds ends (None: no limit; a negative
    timeout has ended already). Raises TypeError for a timeout that is not a number and ValueError
    for NaN, which no time ever passed, so a wait for it never ended."""
    if timeout is None:
        return None
    if isinstance(timeout, bool) or not isinstance(timeout, numbers.Real):
        raise TypeError(f"timeout must be a number of seconds or None, got {timeout!r}")
    if math.isnan(timeout):
        raise ValueError("timeout must be a number of seconds or None, got NaN")
    return time.monotonic() + float(timeout)


__all__ = [
    "CACHE_BACKLOGS", "CLOSE_SEND_WAIT_S", "CLOSE_WAIT_S", "CONNECT_ATTEMPT_MS", "DEFAULT_BACKLOG",
    "DEFAULT_CONNECT", "EXIT_WAIT_S",
    "FETCH_MARGIN_S", "HEARTBEAT_S", "RECONNECT_HOLD_MAX_S", "RECONNECT_HOLD_S", "RECONNECT_PERIOD_FACTOR",
    "RECONNECT_PERIOD_INIT_MS", "RECONNECT_PERIOD_MAX_MS",
    "DeliveryReport", "DeliveryUnsupported", "PublisherClosed", "ScanPublisher", "check_period",
    "check_timeouts", "client_config",
]  # fmt: skip
