"""Scans a full ingest queue deferred, fetched again from their publisher's cache once it has room.

Robots' backlogs come back as bursts at network speed (docs/protocol.md, "Delivery guarantees"):
after a restart of the service, or a dead zone, a fleet's robots send theirs at once, and the
ingest queue holds only so many (one map's robots share half of it). Dropped there, the newest
scans were lost to the map, though each was still in its robot's Zenoh cache (the advanced
publisher's, which holds the last scans it put, a `ScanPublisher`'s `cache`, and answers queries
for a range of its sequence numbers). So a scan of an advanced publisher (its samples carry their source, the
publisher's id, and their sequence number in it, `sn`) that the full queue would refuse is not
taken (`MapRegistry.submit`'s `defer_when_full`: its seq not recorded), and its publisher is
*behind* from that scan on (`Behind`): its later samples, as they arrive, are held back too
(submitting them would put them before the deferred one), until `BacklogRefetch`'s thread has
fetched them again, in order, from the publisher's cache (a Zenoh query on
`<key>/@adv/pub/<zid>/<eid>/**?_sn=<first>..<last>`, as zenoh-ext's own recovery asks), as many
as the queue has room for. A full queue costs a delay, not the scans.

`BacklogRefetch.admit` is the gate every sample of an advanced publisher passes, live or fetched
again: it lets through a publisher that is not behind, and of one that is only its next sample
(`Behind.next_sn`); `taken` moves that on (or makes the publisher behind when the queue deferred
the sample). It holds nothing but each behind publisher's two numbers (the first sn not taken,
the highest seen), so memory does not grow with the backlogs. A sample that comes twice (live and
fetched again) is taken once by the gate or, if both get through, ignored as a duplicate by the
registry's seq bookkeeping: each scan is integrated once.

Scans the cache no longer holds when they are fetched (the robot published more than its cache
holds meanwhile, or its publisher is gone) cannot be had. A fetch for as many as the queue has room
for that brings nothing is followed by one for every sample missing (the cache, which holds the
publisher's last samples, answers from where it begins now), and the samples before its first reply
are given up; so is a publisher when such fetches bring nothing `REFETCH_ATTEMPTS` times in a row.
Those are counted `unrecoverable`, as zenoh-ext's own misses are, and the registry counts them
`lost` on the robot once a later one is taken. A fetch that timed out brings nothing either, but it
is not one of those: the publisher's session did not answer (its link silent, within Zenoh's
lease), which says nothing of its cache, and the same is asked again; a robot gone for good is
given up once Zenoh ends its session, and its fetches end at once, empty (fetches that time out
count only after `REFETCH_SILENCE_S` of them in a row). Plain publishers' samples carry no source:
a full queue drops them, as before.

The thread asks several publishers' caches at once (`REFETCH_PARALLEL` fetches in flight, one a
publisher), and reads their replies as they arrive, without waiting on any one fetch: a robot whose
link died silently answers nothing until its fetch times out (`REFETCH_TIMEOUT_S`), and fetched one
at a time, every other robot's deferred scans waited for it meanwhile (2 s a fetch, about 6 s
before it was given up). A fetch is for as many as the queue has room for beside what the fetches
in flight were promised (`FairQueue.room`'s `promised`), so that fetches side by side do not ask
for the same room; the publisher with the most samples from its first not taken to its highest
seen, the nearest to pushing its first out of its cache, gets the room first. Each publisher's
replies are submitted in order, one fetch of it at a time, so its scans reach the registry in
order as before.

The thread only asks and submits: it never runs in a Zenoh callback, and the gate's lock is held
for one sample's decoding and submission at most.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import zenoh

log = logging.getLogger("fleetmap.zenoh")

#: Seconds between the thread's rounds while a publisher is behind. Each round starts a fetch for
#: every behind publisher without one in flight, for as many as the queue has room for then beside
#: what the fetches in flight were promised: while it stays full, about what the workers integrated
#: since the last round.
REFETCH_PERIOD_S = 0.05
#: Seconds one fetch may wait for its replies: a robot whose link died silently answers nothing. A
#: fetch cut short loses nothing: the next one asks from the first sample not taken, and it does
#: not count towards giving the robot up (`REFETCH_ATTEMPTS`).
REFETCH_TIMEOUT_S = 2.0
#: Fetches in flight at once at most, one a publisher: a robot whose link died silently holds its
#: own (and the room it was promised, its FIFO's at most) until `REFETCH_TIMEOUT_S`, and the others'
#: go on meanwhile. Fetched one at a time, every other robot's waited for it, 2 s a fetch, about 6 s
#: in all before it was given up.
REFETCH_PARALLEL = 16
#: Seconds the thread waits for replies between two looks at its fetches' channels, which it reads
#: without waiting (a fetch waited on blocks the others').
REFETCH_POLL_S = 0.005
#: Fetches in a row of every sample still missing that bring nothing of a behind publisher before
#: it is given up (its scans counted unrecoverable): its cache no longer holds them, or it is gone.
#: Answered, not timed out: a cache answers at once with what it holds.
REFETCH_ATTEMPTS = 3
#: Seconds of fetches of a publisher timing out in a row after which they count as empty ones (see
#: `REFETCH_ATTEMPTS`): three times Zenoh's default lease (10 s), by which a session whose link
#: died has long been ended; one that lives on and answers no query (a peer whose queryable is never
#: reached) would otherwise hold its publisher's later scans back for ever.
REFETCH_SILENCE_S = 30.0
#: Sequence numbers of zenoh-ext's samples are 32-bit and wrap.
_SN_MODULUS = 1 << 32


@dataclass(frozen=True)
class Origin:
    """Where a sample came from: its scan key, its advanced publisher (`zid`, `eid`) and its
    sequence number there (`sn`)."""

    key: str
    zid: str
    eid: int
    sn: int

    @property
    def publisher(self) -> tuple[str, int]:
        return self.zid, self.eid

    @classmethod
    def of(cls, key: str, sample: zenoh.Sample) -> Origin | None:
        """The origin of `sample` on `key`, None when it has no source (a plain publisher's)."""
        info = sample.source_info
        if info is None or info.source_sn is None or info.source_id is None:
            return None
        return cls(key, str(info.source_id.zid), int(info.source_id.eid), int(info.source_sn))


@dataclass
class Behind:
    """A publisher whose samples wait to be fetched again: from `next_sn` (the first not taken) to
    `seen_sn` (the highest that arrived and was deferred or held back), of scan key `key`."""

    key: str
    next_sn: int
    seen_sn: int
    #: Whether the next fetch asks for every sample from `next_sn` to `seen_sn`, whatever the
    #: queue's room: the last one, for as many as it had room for, brought nothing.
    widen: bool = False
    empty_fetches: int = 0
    #: When the first of the fetches timing out in a row was asked (`time.monotonic()`), or None.
    silent_since: float | None = None


@dataclass
class _Fetch:
    """A fetch in flight of `publisher`'s (`behind`) samples: its `replies` as they arrive, those
    taken so far (`got`), and the queue's room it was counted on that its replies have not taken
    yet (`promised`), which the other fetches leave to it."""

    publisher: tuple[str, int]
    behind: Behind
    replies: zenoh.Handler[zenoh.Reply]
    promised: int
    #: When it was asked (`time.monotonic()`).
    asked: float
    got: int = 0
    #: Whether it ended on its timeout: the publisher's session did not answer (see `_ended`).
    timed_out: bool = False


class BacklogRefetch:
    """The gate of advanced publishers' samples and the thread that fetches deferred ones again (see
    the module docstring).

    `room(key)` says how many scans of the scan key `key` the ingest queue takes now; `handle(key,
    sample, origin)` decodes and submits a fetched sample as the subscriber's callback does (it
    passes the gate). `on_unrecoverable(count, source)` counts `count` scans of the publisher
    `source` ("zid/eid") that could not be fetched again."""

    def __init__(
        self,
        room: Callable[[str, Mapping[str, int]], int],
        handle: Callable[[str, zenoh.Sample, Origin], None],
        on_unrecoverable: Callable[[int, str], None],
    ) -> None:
        self._room = room
        self._handle = handle
        self._on_unrecoverable = on_unrecoverable
        #: Held from a sample's `admit` to its `taken` (its decoding and submission): the gate's
        #: decision and the submission are one step, whichever thread a publisher's samples come on.
        self.lock = threading.RLock()
        self._behind: dict[tuple[str, int], Behind] = {}
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None
        #: Samples fetched again from publishers' caches.
        self.refetched = 0

    def start(self, session: zenoh.Session) -> None:
        """Start the fetching thread on `session`."""
        self._session = session
        self._thread = threading.Thread(target=self._run, name="fleetmap-refetch", daemon=True)
        self._thread.start()

    def close(self, timeout: float = REFETCH_TIMEOUT_S + 1.0) -> None:
        """Stop the thread (after the session closed, which ends its fetch in progress), waiting for
        it: a thread left inside a Zenoh call when the interpreter finalizes aborts the process.
        What is still behind is left in the robots' caches: the next process's history query
        fetches it (nothing of it was recorded)."""
        self._closed.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def behind(self) -> int:
        """Publishers behind now."""
        with self.lock:
            return len(self._behind)

    # -- the gate (call with `lock` held) -----------------------------------------------------------

    def admit(self, origin: Origin) -> bool:
        """Whether the sample of `origin` may be submitted now: its publisher is not behind, or this
        is its next sample (or one already taken, which the registry ignores as a duplicate). A
        sample held back is noted, so that it is fetched again."""
        behind = self._behind.get(origin.publisher)
        if behind is None:
            return True
        ahead = (origin.sn - behind.next_sn) % _SN_MODULUS
        if ahead == 0 or ahead >= _SN_MODULUS // 2:  # its next, or one before it
            return True
        if (origin.sn - behind.seen_sn) % _SN_MODULUS < _SN_MODULUS // 2:
            behind.seen_sn = origin.sn
        return False

    def taken(self, origin: Origin, deferred: bool) -> None:
        """The sample of `origin`, admitted, was submitted: `deferred` when the full queue deferred
        it (its publisher is behind from it), else taken (integrated, refused or a duplicate)."""
        publisher = origin.publisher
        behind = self._behind.get(publisher)
        if deferred:
            if behind is None:
                self._behind[publisher] = Behind(origin.key, origin.sn, origin.sn)
                self._wake.set()
            return
        if behind is None or origin.sn != behind.next_sn:
            return
        behind.next_sn = (origin.sn + 1) % _SN_MODULUS
        behind.empty_fetches = 0
        if (behind.seen_sn - behind.next_sn) % _SN_MODULUS >= _SN_MODULUS // 2:  # every one seen taken
            del self._behind[publisher]

    # -- the thread ---------------------------------------------------------------------------------

    def _run(self) -> None:
        fetches: dict[tuple[str, int], _Fetch] = {}
        launched = -REFETCH_PERIOD_S
        while not self._closed.is_set():
            if time.monotonic() - launched >= REFETCH_PERIOD_S:
                launched = time.monotonic()
                self._launch(fetches)
            if fetches:
                if not self._drain(fetches):
                    self._closed.wait(REFETCH_POLL_S)
                continue
            with self.lock:
                idle = not self._behind
            if idle:
                self._wake.wait()
                self._wake.clear()
                launched = -REFETCH_PERIOD_S
            else:
                self._closed.wait(REFETCH_PERIOD_S)

    def _launch(self, fetches: dict[tuple[str, int], _Fetch]) -> None:
        """Start a fetch for each behind publisher without one in flight that the queue has room for
        (`REFETCH_PARALLEL` in flight at most), the publisher nearest to overrunning its cache first."""
        with self.lock:
            # The most samples from the first not taken to the highest seen: its cache holds its
            # last samples, so it is the nearest to pushing out its first not taken (with caches
            # alike), and the first to get the queue's room.
            waiting = sorted(
                (item for item in self._behind.items() if item[0] not in fetches),
                key=lambda item: (item[1].seen_sn - item[1].next_sn) % _SN_MODULUS,
                reverse=True,
            )
        for publisher, behind in waiting:
            if len(fetches) >= REFETCH_PARALLEL or self._closed.is_set():
                return
            try:
                fetch = self._ask(publisher, behind, fetches)
            except Exception:  # the thread must go on: a bug is logged
                log.exception("unexpected error fetching deferred scans again")
                continue
            if fetch is not None:
                fetches[publisher] = fetch

    def _ask(
        self, publisher: tuple[str, int], behind: Behind, fetches: dict[tuple[str, int], _Fetch]
    ) -> _Fetch | None:
        """Ask `publisher`'s cache for its next deferred samples, as many as the queue takes now
        beside what the `fetches` in flight were promised; None when there is no room (or nothing
        to fetch any more)."""
        with self.lock:
            if self._behind.get(publisher) is not behind:
                return None  # caught up meanwhile
            first, missing = behind.next_sn, (behind.seen_sn - behind.next_sn) % _SN_MODULUS + 1
            widen = behind.widen
        promised: dict[str, int] = {}
        for fetch in fetches.values():
            promised[fetch.behind.key] = promised.get(fetch.behind.key, 0) + fetch.promised
        room = self._room(behind.key, promised)
        session = self._session
        if room <= 0 or session is None:
            return None  # the queue is full: the next round
        # Widened: the cache holds none of the first `room` (the robot published on and pushed
        # them out), and a range of it holds a sample only from where the cache begins now. The
        # replies past the room are deferred again, held back at the gate.
        count = missing if widen else min(missing, room)
        last = (first + count - 1) % _SN_MODULUS
        zid, eid = publisher
        selector = f"{behind.key}/@adv/pub/{zid}/{eid}/**?_sn={first}..{last}"
        # Its replies carry the scan key, not the query's: ANY; each is its own sample: no
        # consolidation (which kept only the last of a key). A channel as long as the replies, so
        # that Zenoh's thread never waits for this one, read without waiting (`_drain`).
        replies = session.get(
            selector,
            handler=zenoh.handlers.FifoChannel(count + 8),
            accept_replies=zenoh.ReplyKeyExpr.ANY,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=REFETCH_TIMEOUT_S,
        )
        return _Fetch(publisher, behind, replies, min(count, room), time.monotonic())

    def _drain(self, fetches: dict[tuple[str, int], _Fetch]) -> bool:
        """Hand the replies that arrived of every fetch in flight to `handle` (through the gate), and
        end the fetches whose replies are all in. Returns whether any reply or end was there."""
        progressed = False
        for publisher, fetch in list(fetches.items()):
            try:
                while True:
                    try:
                        reply = fetch.replies.try_recv()
                    except zenoh.ZError:  # the channel is closed: every reply is in (or timed out)
                        del fetches[publisher]
                        progressed = True
                        self._ended(fetch)
                        break
                    if reply is None:
                        break
                    progressed = True
                    self._take(fetch, reply)
            except Exception:  # the thread must go on: a bug is logged; the next fetch asks again
                fetches.pop(publisher, None)
                log.exception("unexpected error fetching deferred scans again")
        return progressed

    def _take(self, fetch: _Fetch, reply: zenoh.Reply) -> None:
        """One reply of `fetch`: its sample, if it is one of the publisher's, to `handle`."""
        sample = reply.ok
        if sample is None:  # an error reply (another queryable's, the timeout's): no scan
            fetch.timed_out |= _is_timeout(reply)
            return
        origin = Origin.of(fetch.behind.key, sample)
        if origin is None or origin.publisher != fetch.publisher:
            return
        if fetch.got == 0:
            self._skip_to(fetch.publisher, fetch.behind, origin.sn)
        fetch.got += 1
        fetch.promised = max(0, fetch.promised - 1)  # in the queue now, or deferred again
        self.refetched += 1
        self._handle(fetch.behind.key, sample, origin)

    def _ended(self, fetch: _Fetch) -> None:
        """`fetch` got every reply it will: one that brought nothing widens the next, or after
        `REFETCH_ATTEMPTS` widened ones gives the publisher up. Not one that timed out: the
        publisher's session did not answer at all (a cache answers at once, with what it holds), so
        it says nothing of the cache, and the next fetch asks the same again. A robot whose link
        went silent for a while, within Zenoh's lease, was given up after 4 of them (about 8 s),
        its deferred scans counted unrecoverable though its cache still held them; one gone for
        good is given up once Zenoh ends its session (the lease) and its cache's queryable with it:
        fetches then end at once, empty. Past `REFETCH_SILENCE_S` of them in a row, though, they
        count as empty ones: a session that lives on and answers nothing would hold its
        publisher's later scans back for ever."""
        publisher, behind = fetch.publisher, fetch.behind
        with self.lock:
            if fetch.timed_out and not fetch.got:
                if behind.silent_since is None:
                    behind.silent_since = fetch.asked
                if time.monotonic() - behind.silent_since < REFETCH_SILENCE_S:
                    return
            else:
                behind.silent_since = None
            if fetch.got:
                return
            if not behind.widen:
                behind.widen = True
                return
            behind.empty_fetches += 1
            if behind.empty_fetches < REFETCH_ATTEMPTS or self._behind.get(publisher) is not behind:
                return
            del self._behind[publisher]
            gone = (behind.seen_sn - behind.next_sn) % _SN_MODULUS + 1
        zid, eid = publisher
        self._on_unrecoverable(gone, f"{zid}/{eid}")

    def _skip_to(self, publisher: tuple[str, int], behind: Behind, sn: int) -> None:
        """A fetch's first reply is `sn`: those before it, from `next_sn`, are gone from the cache."""
        with self.lock:
            behind.widen = False
            if self._behind.get(publisher) is not behind:
                return
            gone = (sn - behind.next_sn) % _SN_MODULUS
            if gone == 0 or gone >= _SN_MODULUS // 2:
                return
            behind.next_sn = sn
        zid, eid = publisher
        self._on_unrecoverable(gone, f"{zid}/{eid}")


def _is_timeout(reply: zenoh.Reply) -> bool:
    """Whether `reply` is the error Zenoh gives a query when its timeout passed (payload "Timeout")."""
    error = reply.err
    return error is not None and error.payload.to_bytes() == b"Timeout"


__all__ = ["REFETCH_PARALLEL", "REFETCH_PERIOD_S", "REFETCH_SILENCE_S", "BacklogRefetch", "Behind", "Origin"]
