"""What the service knows of one robot on one map (`RobotState`): its counters, its pose and trail
for viewers, the seq bookkeeping of its publisher sessions (`SessionSeqs`) that tells new scans
from duplicates, restarts and two robots misconfigured with one id, and what became of each
session's scans (`SessionLedger`) for delivery confirmation. Plain data, no locks: the registry
holds its lock around every use."""

from __future__ import annotations

import struct
from array import array
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Any

from fleetmap.pushed_out import STORED_NONE, PushedOutRows, Value
from fleetmap.scan import Pose2D

#: Poses kept per robot for viewers' trails.
TRAIL_LENGTH = 200
#: Publisher sessions a robot's bookkeeping remembers, the most recently heard: enough for a few
#: robots that share one id, and bounded whatever session ids a sender makes up.
MAX_SESSIONS = 8
#: Sessions pushed out of those MAX_SESSIONS that a robot's bookkeeping still knows
#: (`RobotState.pushed_out`), so that more robots than MAX_SESSIONS under one id (a fleet started
#: from one image with its default id) are an id conflict: each session was pushed out by the others
#: before it came back, and taken for a new session each time (a restart, its seqs before it lost:
#: nine robots counted 180 restarts and 180,000 lost in 20 scans each, and no conflict), and its
#: copies (its cache fetched again after a restart of the service) for new scans, integrated twice.
#: So up to 136 robots under one id are told apart. Saved with the robot, and listed by the delivery
#: query only when asked for by its id (a flush). Each keeps its seqs and its ledger's counts, not
#: its lists, as a row of numbers (`PushedOutRows`): 105 bytes, about 14 kB for all 128 with the
#: buffer's slack (tracemalloc; as objects, 8 of them took 13 kB).
MAX_SESSIONS_PUSHED_OUT = 128
#: Publisher sessions of one robot id that the service tells apart: its recent ones and those pushed
#: out of them. What is remembered of a robot's sessions elsewhere keeps as many (a deleted map's
#: tombstone, `fleetmap.tombstones`; its scans refused for want of a map, `fleetmap.unmapped_refusals`).
SESSIONS_TOLD_APART = MAX_SESSIONS + MAX_SESSIONS_PUSHED_OUT
#: A session pushed out is forgotten once the robot has accepted this many scans of its other
#: sessions since its last (a day and more of a robot's 10 scans a second): a robot that restarts
#: every hour does not keep 128 sessions of processes long gone in its bookkeeping and its saved
#: state. Counted in scans, not seconds: while the service is down, or the robot's sessions all
#: silent, none is forgotten, so a robot's cache fetched again after a long stop of the service is
#: still told from new scans. A session that comes back after it was forgotten is a new one (a
#: restart, its seqs before it lost), as one pushed out of MAX_SESSIONS_PUSHED_OUT is.
PUSHED_OUT_EXPIRY = 1_000_000
#: Seconds a robot is shown in an id conflict (`RobotState.in_conflict`) after its last scan that
#: interleaved with another session's.
CONFLICT_SHOWN = 60.0
#: The session key of scans that carry no session id (publishers that send none).
NO_SESSION = 0
#: Refused seqs, and gaps of lost seqs, a session's ledger lists one by one (`SessionLedger.
#: refused_seqs`, `lost_gaps`), so that a flush counts the scans through its own last seq only;
#: past as many it lists none (the counts alone remain, and a flush under-confirms: it counts the
#: session's refusals and losses after its last seq too). Kept as machine integers (`array`), not
#: lists of int objects and tuples: out-of-limits scans under made-up robot ids (any Zenoh peer)
#: fill them for up to `--max-robots-per-map` robots on each map, and robot state is not charged to
#: the memory budget. A robot's worst case (MAX_SESSIONS sessions, each with as many refused seqs
#: and gaps, seqs too large to be shared small ints) measured 83.1 kB as lists and tuples, 25.8 kB
#: as arrays, 12.0 kB without the lists (tracemalloc); 1024 robots on each of 256 maps: 21.8 GB,
#: 6.8 GB, 3.1 GB. A cap of 32 would give 19.3 kB, 16 gives 16.2 kB, but flushes under-confirm sooner.
LEDGER_HISTORY = 64
#: A session's refused seqs that its next journaled scan names (`SessionLedger.unjournaled`): the
#: journal holds integrated scans only, and after a crash the seqs refused before a journaled scan
#: were taken for scans that never came (lost), and the re-send of one refused 507 for a duplicate.
#: Past as many between two of its journaled scans, the oldest are so still (128 bytes a session).
UNJOURNALED_REFUSALS = 16
#: Scans refused for the service's sake that a robot may send again under their seqs
#: (`RobotState.refused_scans`): a REST client answered 507 for several scans while the memory
#: budget was full retries each once memory is freed. The oldest are forgotten past this many (a
#: robot's worst case about 2 kB; robot state is not charged to the memory budget).
MAX_REFUSED_RETRIES = 16


#: The saved counters (`RobotState.SAVED`) that are not integers: what else each may hold.
_SAVED_NOT_INT: dict[str, type | tuple[type, ...]] = {
    "last_stamp": (int, float, type(None)),
    "last_error": (str, type(None)),
    "last_heard": (int, float),
    "conflict_at": (int, float, type(None)),
}


def _check_saved(name: str, value: object, kind: type | tuple[type, ...]) -> Any:
    """`value`, saved as field `name`, if it is a `kind` (a bool is no integer); else ValueError."""
    if isinstance(value, bool) or not isinstance(value, kind):
        raise ValueError(f"a saved robot's {name} is {value!r}")
    return value


def _number(value: object, where: str) -> float:
    """`value`, a JSON number saved in `where`; else ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"a saved robot's {where} holds {value!r}, not a number")
    return value


def _numbers(row: list, where: str) -> list:
    """`row`, a saved list of numbers, None and booleans (a session's seqs, a ledger's counts)."""
    for value in row:
        if value is not None and not isinstance(value, (bool, int, float)):
            raise ValueError(f"a saved robot's {where} holds {value!r}, not a number")
    return row


def _refused_scans(rows: object) -> dict[tuple[int, int], None]:
    """`RobotState.refused_scans` as `RobotState.saved` saved them, [session key, seq] pairs oldest
    first (a robot saved before they were has none); ValueError for anything else."""
    if not isinstance(rows, list):
        raise ValueError(f"a saved robot's refused_scans is {rows!r}, not a list")
    refused: dict[tuple[int, int], None] = {}
    for row in rows[-MAX_REFUSED_RETRIES:]:
        if not (isinstance(row, list) and len(row) == 2):
            raise ValueError(f"a saved robot's refused_scans holds {row!r}, not a [session, seq] pair")
        key, seq = (_check_saved("refused_scans", value, int) for value in row)
        refused[(key, seq)] = None
    return refused


def session_key(session: int | None) -> int:
    """The key in `RobotState.sessions` of the scans of publisher session `session` (None: none sent)."""
    return NO_SESSION if session is None else session


def pairs(flat: array[int] | None) -> list[tuple[int, int]] | None:
    """A flat array of pairs (`SessionLedger.lost_gaps`) as a list of pairs; None stays None."""
    if flat is None:
        return None
    items = iter(flat)
    return list(zip(items, items, strict=False))  # one iterator twice: no copies of the array


@dataclass(slots=True)
class Receipt:
    """One accepted scan of a session until it is settled (`SessionLedger.settle`)."""

    ledger: SessionLedger
    seq: int
    settled: bool = False
    integrated: bool = False  # how it was settled
    withdrawn: bool = False  # its refusal was taken back: the scan was sent again and accepted
    lost: int = 0  # seqs its session skipped just before it (`SessionLedger.count_lost`)


@dataclass
class SessionLedger:
    """What became of one publisher session's scans, for its delivery confirmation
    (`fleetmap.wire.SessionDelivery`). A snapshot saves it (`saved`: what was settled then, as far as
    `SessionSeqs.settled_seq`) and the journal's replay at start settles the scans integrated after
    it, so a robot's flush after a restart of the service confirms its scans from before the
    restart too. A session saved before ledgers were (or by an in-memory service) is counted afresh
    from its next scan (`first_seq` says from which).

    Each accepted scan gets a `Receipt` (`open`), in the order the robot's scans were accepted,
    which is the order they are integrated in; `settle` ends it. `settled` moves only over a run of
    settled receipts at the front: with durable storage a scan counts as integrated when its journal
    row commits, and a later scan refused meanwhile must not let `settled` pass the earlier one. A
    seq accepted again (a re-send, a restart without session ids) is not in seq order among them:
    `settled` is None until it is settled, then the highest seq accepted before it."""

    first_seq: int | None = None
    settled: int | None = None
    integrated: int = 0
    refused: int = 0
    lost: int = 0
    duplicates: int = 0
    open_receipts: deque[Receipt] = field(default_factory=deque, repr=False)
    #: The highest seq accepted (`open`) in this process; `settled` stands for it before the first.
    _top: int | None = field(default=None, repr=False)
    #: The last receipt of a seq accepted again (`open`), and the highest seq accepted before it:
    #: `settled` stays None until that receipt is settled, and is then that seq.
    _reopened: Receipt | None = field(default=None, repr=False)
    _reopened_top: int = field(default=0, repr=False)
    _gap: int = field(default=0, repr=False)  # seqs lost before the scan `open` is called for next
    #: The seqs of its scans settled as refused (less those whose refusal was withdrawn), and
    #: seq, n (flat, in pairs: see `pairs`) for the n seqs lost just before seq, in this process: the
    #: delivery query lists them so that a flush counts only the scans through its last seq, not
    #: those published after it began (`fleetmap_client.delivery.delivery_report`). None when not known: a
    #: ledger restored from a snapshot, or past LEDGER_HISTORY entries. Int64 (seqs are below 2**63).
    refused_seqs: array[int] | None = field(default_factory=lambda: array("q"), repr=False)
    lost_gaps: array[int] | None = field(default_factory=lambda: array("q"), repr=False)
    #: The seqs of its scans settled as refused in this process that no journal row names yet, at
    #: most UNJOURNALED_REFUSALS (None: none): the row of its next scan journaled names those
    #: below its seq (`take_unjournaled`), and the replay after a crash counts them refused again.
    unjournaled: array[int] | None = field(default=None, repr=False)

    def open(self, seq: int) -> Receipt:
        """A receipt for the scan `seq`, accepted now."""
        if self.first_seq is None:
            self.first_seq = seq
        receipt = Receipt(self, seq)
        top = self.settled if self._top is None else self._top
        if top is not None and seq <= top:
            # Its seq again (a re-send of a refused scan) or lower (a restart without session ids):
            # `settled` no longer says "this and every earlier seq" until this one is settled. Also
            # when scans accepted before it still wait: settling them must not move `settled` to
            # their seqs, at or past this one, while it waits (a flush took it for settled).
            self.settled = None
            self._reopened, self._reopened_top = receipt, top
        self._top = seq if top is None else max(top, seq)
        receipt.lost, self._gap = self._gap, 0
        if receipt.lost and self.lost_gaps is not None:
            self.lost_gaps.extend((seq, receipt.lost))
            if len(self.lost_gaps) > 2 * LEDGER_HISTORY:
                self.lost_gaps = None
        self.open_receipts.append(receipt)
        return receipt

    def settle(self, receipt: Receipt, integrated: bool) -> None:
        """The scan of `receipt` is integrated (`integrated`), or will never be. Idempotent."""
        if receipt.settled:
            return
        receipt.settled, receipt.integrated = True, integrated
        if integrated:
            self.integrated += 1
        else:
            self.refused += 1
            if self.refused_seqs is not None:
                self.refused_seqs.append(receipt.seq)
                if len(self.refused_seqs) > LEDGER_HISTORY:
                    self.refused_seqs = None
            if self.unjournaled is None:
                self.unjournaled = array("q")
            self.unjournaled.append(receipt.seq)
            if len(self.unjournaled) > UNJOURNALED_REFUSALS:
                del self.unjournaled[0]
        receipts = self.open_receipts
        while receipts and receipts[0].settled:
            done = receipts.popleft()
            if done is self._reopened:
                # Every scan accepted before it is settled too, the highest seq among them the last:
                # `settled` is that one (its own seq, lower, left a flush waiting for it).
                self._reopened = None
                self.settled = self._reopened_top
            elif self._reopened is None:  # else a seq accepted again waits behind `done`
                self.settled = done.seq

    def saved(self) -> list:
        """Its counts in order (`SessionLedger.from_saved` reads them), without the open receipts
        and what was counted of their scans: a snapshot saves the session's seqs only up to its
        first scan not settled (`SessionSeqs.settled_seq`), so after a crash those scans come again
        (from the journal, or the robot's cache) and are counted then."""
        integrated, refused, lost = self.integrated, self.refused, self.lost
        for receipt in self.open_receipts:
            lost -= receipt.lost
            if receipt.settled and not receipt.withdrawn:
                integrated -= receipt.integrated
                refused -= not receipt.integrated
        return [self.first_seq, self.settled, integrated, refused, lost, self.duplicates]

    @classmethod
    def from_saved(cls, row: list) -> SessionLedger:
        first_seq, settled, integrated, refused, lost, duplicates = row
        # Its refusals and losses so far are counted, not listed: not known one by one.
        return cls(
            first_seq, settled, integrated, refused, lost, duplicates, refused_seqs=None, lost_gaps=None
        )

    def first_unsettled(self) -> int | None:
        """The lowest seq of its scans not settled yet, None if every one is. Not always the front
        receipt's: a seq accepted again (`open`) waits behind scans with higher seqs."""
        if self._reopened is None:  # seqs rise along the receipts: the front one's is the lowest
            return self.open_receipts[0].seq if self.open_receipts else None
        return min(receipt.seq for receipt in self.open_receipts if not receipt.settled)

    def count_lost(self, count: int) -> None:
        """`count` seqs of the session were skipped (before the scan accepted now, whose receipt
        keeps the count: `saved`): lost, if after its first scan here."""
        if self.first_seq is not None:
            self.lost += count
            self._gap += count

    def take_unjournaled(self, below: int) -> list[int]:
        """The seqs of its refused scans that no journal row names yet and are below `below` (the
        seq of its scan journaled now, whose row names them), in order; they are named then."""
        if not self.unjournaled:
            return []
        taken = sorted(seq for seq in self.unjournaled if seq < below)
        if taken:
            rest = [seq for seq in self.unjournaled if seq >= below]
            self.unjournaled = array("q", rest) if rest else None
        return taken

    def withdraw_refusal(self, seq: int) -> None:
        """The scan `seq`, settled as refused, was sent again and accepted: not refused after all."""
        if self.unjournaled and seq in self.unjournaled:
            self.unjournaled.remove(seq)
        self.refused -= 1
        if self.refused_seqs is not None and seq in self.refused_seqs:
            self.refused_seqs.reverse()
            self.refused_seqs.remove(seq)  # its last refusal
            self.refused_seqs.reverse()
        for receipt in reversed(self.open_receipts):  # not counted again by `saved` if still here
            if receipt.seq == seq and receipt.settled and not receipt.integrated and not receipt.withdrawn:
                receipt.withdrawn = True
                break


@dataclass
class SessionSeqs:
    """The seq bookkeeping of one publisher session of a robot (`ScanMessage.session`): each session
    counts its own seqs, so scans of two publishers under one robot id are neither duplicates nor
    restarts of each other."""

    last_seq: int  # seq of its last accepted scan
    #: The latest stamp among its scans accepted since its last restart (None: unknown, in an old
    #: snapshot), not the last one's: a robot whose clock stepped back (NTP) has stamps below it
    #: after the step, and a copy of a scan from before the step was taken for a restart by its
    #: stamp, later than the last scan's, and integrated again (`is_restart`).
    stamp: float | None
    #: The robot's `accepted` count at its first scan and at its last: which sessions were heard
    #: since which (a logical clock, not a time).
    first_scan_no: int
    last_scan_no: int
    #: What its first scan added to `lost` when it was counted as a restart (None: it was not, or no
    #: longer is): withdrawn if it turns out to have run beside the session it seemed to restart.
    start_lost: int | None = None
    conflict: bool = False  # found running beside another session of the robot
    #: What became of its scans: saved apart (`RobotState.saved`'s `ledgers`, which an older service
    #: ignores), so not a constructor argument.
    ledger: SessionLedger = field(default_factory=SessionLedger, init=False, compare=False)
    #: The stamp of its scan of seq 0 since its last restart (None: none, or unknown), for scans
    #: without a session id (`is_restart`): saved apart too (`RobotState.saved`'s `start_stamps`).
    start_stamp: float | None = field(default=None, init=False, compare=False)

    def saved(self) -> list:
        """Its constructor's fields in order (`SessionSeqs(*saved)` gives it back), not the ledger,
        and `last_seq` only as far as the session's scans are settled (`settled_seq`)."""
        return [
            self.settled_seq() if f.name == "last_seq" else getattr(self, f.name)
            for f in fields(self)
            if f.init
        ]

    def settled_seq(self) -> int:
        """`last_seq`, or if a scan of the session is still unsettled (queued, or applied and its
        journal row not committed yet) the seq before the first such scan: what a snapshot may
        record as the service's. A snapshot (`MapRegistry._saved_counters`) is taken while scans
        wait; had it saved them as accepted, a crash before their journal commit lost them for good,
        since the new process refused the robot's cache re-sending them as duplicates. The scans it
        integrates after the snapshot are replayed from the journal, which advances `last_seq`."""
        pending = self.ledger.first_unsettled()
        return self.last_seq if pending is None else min(self.last_seq, pending - 1)

    def is_restart(self, seq: int, stamp: float) -> bool:
        """For scans WITHOUT a session id: whether a scan whose `seq` is not above `last_seq` starts
        the robot's sequence again (else it is a duplicate).

        A robot process that restarts counts from 0 again, but its first scans can be lost (published
        before its session reached the service) or it may count from 1; either way its scans must
        not be ignored as duplicates until it passes its old seq. Its stamps go on, so a later stamp
        than any of the run's accepted scans (`stamp`) says "restarted". A repeated message (a retry,
        a copy) carries its old stamp, a stale one an earlier stamp: both stay duplicates, also when
        the robot's clock stepped back since (its later scans' stamps are below the copy's). Seq 0 is
        also a restart with an equal or earlier stamp (robots without stamps send 0; a robot without
        a real-time clock may boot in 1970), unless it repeats the last accepted scan, seq 0 with the
        same stamp, or is a copy of the scan of seq 0 of the current run: the same stamp as that
        one's (`start_stamp`), not 0. A `ScanPublisher(send_session_id=False)`'s cache, fetched again after
        a restart of the service, starts with that copy while it holds the robot's first scans: taken
        for a restart, it and every copy after it were integrated a second time.
        A publisher that sends a session id needs none of this: a new session is a restart."""
        if self.stamp is not None and stamp > self.stamp:
            return True
        if seq != 0 or (self.last_seq == 0 and stamp == self.stamp):
            return False
        return not (stamp != 0 and stamp == self.start_stamp)


#: A pushed-out session's row (`RobotState.pushed_out`, `PushedOutRows`'s kinds of column): its
#: seqs (`SessionSeqs.saved`: last_seq, stamp, first_scan_no, last_scan_no, start_lost, conflict),
#: its ledger's counts (`SessionLedger.saved`) and its `start_stamp`.
_PUSHED_OUT_LAYOUT = "qdqqq?" + "qqqqqq" + "d"
_LAST_SEQ = 0  # its column that a tombstone reads (`RobotState.last_seqs`)
_LAST_SCAN_NO, _START_LOST, _CONFLICT = 3, 4, 5  # its columns that a conflict found reads


def _pushed_out_row(rec: SessionSeqs) -> list[Value]:
    """The row of session `rec` (`_PUSHED_OUT_LAYOUT`), as far as its scans are settled: as a
    snapshot saves a session (`SessionSeqs.saved`, `SessionLedger.saved`). Its ledger's counts at
    most 2**63 - 1, what a row holds: seqs are below it, but scans without a session id that
    restart at seqs near it add each seq to `lost` (two such made it too large for the row, and
    the scan that pushed their session out an error under the registry's lock)."""
    first_seq, settled, *counts = rec.ledger.saved()
    return [*rec.saved(), first_seq, settled, *(min(count, 2**63 - 1) for count in counts), rec.start_stamp]


def _pushed_out_seqs(row: tuple[Value, ...]) -> SessionSeqs:
    """The session of `row` (`_pushed_out_row`), its ledger's counts without their lists."""
    rec = SessionSeqs(*row[:6])  # type: ignore[arg-type]
    rec.ledger = SessionLedger.from_saved(list(row[6:12]))
    rec.start_stamp = row[12]  # (a float or None: its column's kind)
    return rec


@dataclass
class RobotState:
    """What the service knows of one robot on one map."""

    online: bool = False
    last_pose: Pose2D | None = None
    last_stamp: float | None = None
    scans_integrated: int = 0
    scans_rejected: int = 0
    last_error: str | None = None
    lost: int = 0
    duplicates: int = 0
    dropped: int = 0
    not_durable: int = 0  # applied, but the journal commit meant to make them durable failed
    restarts: int = 0  # times its seq started again (`accept`)
    #: Wall-clock time of its last message or liveliness change: a map full of robots forgets the
    #: offline robot heard from least recently to make room for a new one (`_room_for`).
    last_heard: float = 0.0
    #: Its scans accepted but not yet counted as integrated or refused: such a robot is not forgotten.
    unsettled: int = 0
    trail: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_LENGTH))
    #: Poses ever appended to `trail` (`add_pose`), which keeps only the last TRAIL_LENGTH: an event
    #: stream that sent the trail when this was n sends only the last `appended - n` points next.
    appended: int = 0
    #: `MapEntry.live_version` when a field a viewer shows (online, pose, trail, scans_integrated)
    #: last changed, or the robot was created (`MapEntry.touch`).
    changed: int = 0
    #: Its recent publisher sessions (key `session_key`), least recently heard first: the last one
    #: is the current one, whose last seq is the robot's (`last_seq`).
    sessions: dict[int, SessionSeqs] = field(default_factory=dict)
    #: Sessions pushed out of `sessions` by newer ones (key `session_key`), least recently pushed
    #: out first, at most MAX_SESSIONS_PUSHED_OUT (and forgotten after PUSHED_OUT_EXPIRY), as rows
    #: of numbers (`_pushed_out_row`): one that comes back ran beside those heard since (an id
    #: conflict), it did not restart, and a copy of one of its scans is a duplicate. Saved: after a
    #: restart of the service they were taken for new sessions, and the robots' caches fetched
    #: again integrated a second time. The delivery query answers for one asked for by its id
    #: (`delivery.delivery_status`). `session_seqs` reads one.
    pushed_out: PushedOutRows = field(default_factory=lambda: PushedOutRows(_PUSHED_OUT_LAYOUT), repr=False)
    #: Sessions pushed out while scans of theirs still wait (their receipts settle in their
    #: ledgers, so not a row yet): each becomes a row of `pushed_out` once they are settled. As
    #: many at most as the robot has scans queued.
    settling: dict[int, SessionSeqs] = field(default_factory=dict, repr=False)
    accepted: int = 0  # scans accepted (the clock of the sessions' `first_scan_no`, `last_scan_no`)
    #: Sessions found interleaved with another session's, the first two of a conflict counting once
    #: (two robots publishing under one id: 1; three: 2, found at once or one after the other; one of
    #: them restarted: +1).
    id_conflicts: int = 0
    conflict_at: float | None = None  # wall-clock time of the last interleaved scan
    #: (session key, seq) of its scans refused for the service's sake, oldest first: the full ingest
    #: queue's (counted in `dropped`, answered 503) or the memory budget's (answered 507), or one
    #: without a session id refused at integration (422: the map's max_tiles). Their seqs were
    #: recorded (so they are not also counted as lost), yet they were never integrated: a re-send of
    #: one, which a REST client answered 503 or 507 is told to make, or the next scan under a seq a
    #: 422 left free, is accepted rather than ignored as a duplicate (`note_refused`). One without a
    #: session id only until another of its scans is accepted (a seq of its own is then a restart's,
    #: not a re-send); one with a session id until it is sent again, of at most MAX_REFUSED_RETRIES
    #: (several scans refused while the budget was full are each sent again). Saved with the other
    #: counters (`saved`): an operator frees memory for 507s by restarting the service with a larger
    #: `--max-memory`, and the re-sends that followed were answered "duplicate", never integrated
    #: (the snapshot had saved their seqs as accepted).
    refused_scans: dict[tuple[int, int], None] = field(default_factory=dict, repr=False)
    #: Its JSON in live viewers' robots events, made by the first event stream that sent it and sent
    #: as is by the others (`api.robots_feed`): key (what the JSON shows) -> JSON. Not saved.
    viewer_json: dict[tuple, str] = field(default_factory=dict, repr=False, compare=False)

    #: The counters that survive a restart (and `sessions`, saved as lists).
    SAVED = (
        "last_stamp", "scans_integrated", "scans_rejected", "last_error", "lost", "duplicates",
        "dropped", "not_durable", "restarts", "last_heard", "accepted", "id_conflicts", "conflict_at",
    )  # fmt: skip

    @property
    def in_map(self) -> bool:
        """Whether any of its scans is in the map: integrated (`scans_integrated`, durable with
        durable storage), or applied though its journal commit failed (`not_durable`). A robot
        whose every scan was refused holds only its refusals."""
        return self.scans_integrated > 0 or self.not_durable > 0

    @property
    def last_seq(self) -> int | None:
        """The seq of the last scan accepted (enqueued), None before the first."""
        return next(reversed(self.sessions.values())).last_seq if self.sessions else None

    def saved(self) -> dict:
        # `last_seq` for a service from before sessions, which reads only that (same database layout).
        last = next(reversed(self.sessions.values())).settled_seq() if self.sessions else None
        out = {name: getattr(self, name) for name in self.SAVED} | {"last_seq": last}
        out["last_pose"] = (
            None if self.last_pose is None else [self.last_pose.x, self.last_pose.y, self.last_pose.theta]
        )
        # JSON objects have only string keys: a list keeps the ids integers and the order.
        out["sessions"] = [[key, *rec.saved()] for key, rec in self.sessions.items()]
        # Apart from the sessions: a service from before ledgers reads each session row as
        # `SessionSeqs` arguments, and ignores keys it does not know.
        out["ledgers"] = [[key, *rec.ledger.saved()] for key, rec in self.sessions.items()]
        out["start_stamps"] = [
            [key, rec.start_stamp] for key, rec in self.sessions.items() if rec.start_stamp is not None
        ]
        # Apart from the sessions too: a service from before it ignores it.
        out["pushed_out"] = [
            *([key, *row] for key, row in self.pushed_out.items()),
            *([key, *_pushed_out_row(rec)] for key, rec in self.settling.items()),
        ]
        # Oldest first; only those whose refusal the saved ledgers count: a re-send withdraws it.
        out["refused_scans"] = [[k, seq] for k, seq in self.refused_scans if self._refusal_saved(k, seq)]
        return out

    def _refusal_saved(self, key: int, seq: int) -> bool:
        """Whether `saved` counts the refusal of scan `seq` of session `key`: its seq is within the
        session's saved seqs (`SessionSeqs.settled_seq`), and its receipt is not still open behind a
        scan not settled (`SessionLedger.saved` leaves those to be counted again after a crash, when
        they come again: then its seq is new as it is)."""
        rec = self.session_seqs(key)
        if rec is None or seq > rec.settled_seq():
            return False
        return all(receipt.seq != seq for receipt in rec.ledger.open_receipts)

    @classmethod
    def from_saved(cls, data: object) -> RobotState:
        """The robot `saved` gave (read back from JSON). ValueError if `data` is not such a robot (a
        damaged database): the service then refuses to start with one line naming the map, where a
        row of the wrong shape was a traceback, and a counter that is not a number a 500 from every
        later GET of its map."""
        if not isinstance(data, dict):
            raise ValueError(f"a saved robot is a JSON object, not {type(data).__name__}")
        for name in cls.SAVED:
            if name in data:  # (a robot saved by an older version may lack the newer counters)
                _check_saved(name, data[name], _SAVED_NOT_INT.get(name, int))
        try:
            saved: dict[str, Any] = {name: data.get(name, getattr(cls, name, None)) for name in cls.SAVED}
            state = cls(**saved)
            if data.get("last_pose"):
                state.add_pose(Pose2D(*(_number(v, "last_pose") for v in data["last_pose"])))
            if "sessions" in data:
                state.sessions = {
                    int(row[0]): SessionSeqs(*_numbers(row[1:], "sessions")) for row in data["sessions"]
                }
                for row in data.get("ledgers", ()):
                    if int(row[0]) in state.sessions:
                        state.sessions[int(row[0])].ledger = SessionLedger.from_saved(
                            _numbers(row[1:], "ledgers")
                        )
                for key, start_stamp in data.get("start_stamps", ()):
                    if int(key) in state.sessions:
                        state.sessions[int(key)].start_stamp = _number(start_stamp, "start_stamps")
                for row in data.get("pushed_out", ()):
                    if not (
                        isinstance(row, list)
                        and len(row) == 1 + len(_PUSHED_OUT_LAYOUT)
                        and all(value is None or value >= 0 for value in _numbers(row, "pushed_out"))
                    ):  # (a row stores None as -1)
                        raise ValueError(f"a saved robot's pushed_out holds {row!r}, not a session's row")
                    key, *values = row
                    state.pushed_out.put(_check_saved("pushed_out", key, int), values)
                state.refused_scans = _refused_scans(data.get("refused_scans", []))
            elif data.get("last_seq") is not None:
                # Saved before sessions existed: every scan so far came without one.
                last_seq = _check_saved("last_seq", data["last_seq"], int)
                state.sessions = {NO_SESSION: SessionSeqs(last_seq, state.last_stamp, 0, 0)}
        # (ValueError: as it is; struct.error, OverflowError: a pushed-out session's row of the
        # wrong kinds, or numbers past 64 bits)
        except (TypeError, KeyError, IndexError, AttributeError, struct.error, OverflowError) as exc:
            raise ValueError(f"a saved robot of the wrong shape: {exc}") from None
        return state

    def add_pose(self, pose: Pose2D) -> None:
        """Its last integrated scan was taken at `pose`: its position now, and the trail's newest."""
        self.last_pose = pose
        self.trail.append((pose.x, pose.y, pose.theta))
        self.appended += 1

    def unjournaled_refusals(self, seq: int, session: int) -> list[tuple[int, bool]]:
        """What the journal row of scan `seq` of session `session` names (`take_unjournaled`): the
        seqs of the session refused before it that no row names yet, each with whether it may be
        sent again (`refused_scans`: refused for the service's sake)."""
        rec = self.session_seqs(session)
        if rec is None:
            return []
        taken = rec.ledger.take_unjournaled(seq)
        if taken:
            self._keep(session, rec)
        return [(refused, (session, refused) in self.refused_scans) for refused in taken]

    def replay_refusal(self, seq: int, stamp: float, session: int, resend: bool, now: float) -> None:
        """A journal row, replayed, names scan `seq` of session `session` as refused before it
        (`unjournaled_refusals`; `resend`: it may be sent again): count it so, as when it came, if
        the robot's saved bookkeeping does not hold it already. Its `stamp` is the row's."""
        rec = self.session_seqs(session)
        if rec is not None and seq <= rec.last_seq:
            return  # accepted before the snapshot: counted in it
        self.accept(seq, stamp, session, now)
        ledger = self.sessions[session].ledger
        ledger.settle(ledger.open(seq), integrated=False)
        ledger.unjournaled = None  # named by the row that is replayed now
        if resend:
            self.note_refused(seq, session)

    def note_refused(self, seq: int, session: int | None) -> None:
        """The scan `seq` of session `session`, accepted, was refused for the service's sake: a
        re-send of it is new (`refused_scans`)."""
        key = (session_key(session), seq)
        self.refused_scans.pop(key, None)
        self.refused_scans[key] = None
        while len(self.refused_scans) > MAX_REFUSED_RETRIES:
            del self.refused_scans[next(iter(self.refused_scans))]

    def is_duplicate(self, seq: int, stamp: float, session: int | None) -> bool:
        """Whether the scan `seq` of publisher session `session` (None: it sent none) is not new:
        its session's seq is past it (a copy, a retry, a stale message). A session not heard
        before is never a duplicate: its publisher (re)started, or another robot shares this id.
        Without a session, a seq not new is a restart if its stamp says so (`SessionSeqs.is_restart`).
        A re-send of a scan refused for the service's sake (`refused_scans`) is new: it was never
        integrated."""
        if (session_key(session), seq) in self.refused_scans:
            return False  # a re-send of a scan the full queue or the memory budget refused
        rec = self.session_seqs(session)
        if rec is None or seq > rec.last_seq:
            return False
        return session is not None or not rec.is_restart(seq, stamp)

    def session_seqs(self, session: int | None) -> SessionSeqs | None:
        """The bookkeeping of publisher session `session` (None: scans without one), one of the
        recent `sessions` or one pushed out (`settling`, or `pushed_out`: then a copy of its row,
        which `_keep` writes back once changed); None if the robot knows no such session."""
        key = session_key(session)
        rec = self.sessions.get(key) or self.settling.get(key)
        if rec is None and (row := self.pushed_out.get(key)) is not None:
            rec = _pushed_out_seqs(row)
        return rec

    def last_seqs(self) -> list[tuple[int, int]]:
        """(session key, last seq) of every session the robot knows, least recently heard first:
        those pushed out (`pushed_out`, least recently pushed out first, then `settling`), then the
        recent `sessions` (what a tombstone remembers: `fleetmap.tombstones.merged_sessions`)."""
        return [
            *zip(self.pushed_out.keys(), self.pushed_out.columns(_LAST_SEQ), strict=True),
            *((key, rec.last_seq) for key, rec in self.settling.items()),
            *((key, rec.last_seq) for key, rec in self.sessions.items()),
        ]

    def every_session(self) -> list[tuple[int, SessionSeqs]]:
        """(session key, bookkeeping) of every session the robot knows, in `last_seqs`'s order: those
        of `pushed_out` as copies of their rows, to read, not to change."""
        return [
            *((key, _pushed_out_seqs(row)) for key, row in self.pushed_out.items()),
            *self.settling.items(),
            *self.sessions.items(),
        ]

    def _keep(self, key: int, rec: SessionSeqs) -> None:
        """Session `key`'s bookkeeping `rec`, from `session_seqs` and changed since, is kept: a
        pushed-out one's row is written again (the others `rec` is)."""
        if key in self.pushed_out:
            self.pushed_out.put(key, _pushed_out_row(rec))

    def count_duplicate(self, session: int | None) -> SessionSeqs:
        """Count a scan of session `session` that `is_duplicate` found not new, on the robot and in
        its session's ledger (perhaps a pushed-out one's); returns the session's bookkeeping."""
        rec = self.session_seqs(session)
        assert rec is not None  # a duplicate of a session it knows (perhaps pushed out)
        self.duplicates += 1
        rec.ledger.duplicates += 1
        self._keep(session_key(session), rec)
        return rec

    def accept(self, seq: int, stamp: float, session: int | None = None, now: float = 0.0) -> bool:
        """Record the scan `seq` of publisher session `session` as accepted (by `submit`, or replayed
        from the journal); the caller has ruled out duplicates (`is_duplicate`).

        Per session: the seqs skipped since its last scan count as lost, and without a session id a
        seq not new is a restart whose new run's seqs before this one never arrived. A new session
        of a known robot is a restart too (its seqs before this one count as lost). A session that
        comes back after another one was heard is an id conflict (two publishers under one robot
        id): `conflict_at` becomes `now` (wall-clock), `id_conflicts` counts it if a session among
        them was not known to be in one, and a restart counted when the other one started is
        withdrawn (it ran beside this one). A re-send of a scan refused for the service's sake
        (`refused_scans`) changes none of this: its seq was recorded when it first came. Returns
        whether this scan interleaved with another session's so."""
        key = session_key(session)
        resent = (key, seq) in self.refused_scans
        if resent:
            del self.refused_scans[(key, seq)]
        # Another scan accepted: a refused seq without a session id that comes next is a restart's.
        for refused in [k for k in self.refused_scans if k[0] == NO_SESSION]:
            del self.refused_scans[refused]
        recent = key in self.sessions
        rec = self._take_session(key)
        if resent and rec is not None:
            rec.ledger.withdraw_refusal(seq)  # settled as refused, now accepted after all
            if rec.last_seq == seq:
                # The scan accepted under its seq now (a REST client's next scan after a 422, of a
                # later stamp) is the last: without a session id a copy of it, its stamp later than
                # the refused one's, was taken for a restart and integrated twice.
                rec.stamp = stamp if rec.stamp is None else max(rec.stamp, stamp)
            # Among the recent sessions, where the caller opens its receipt (`SessionLedger.open`):
            # one pushed out of them (other robots under its id heard since) failed with a KeyError.
            self._recent(key, rec)
            return False  # a re-send of a scan refused for the service's sake: its seq is recorded already
        # (A re-send of a session forgotten since is a new session's scan.)
        self.accepted += 1
        interleaved = False
        if rec is None:
            rec = SessionSeqs(seq, stamp, self.accepted, self.accepted)
            if self.sessions:
                self.restarts += 1
                self.lost += seq
                rec.start_lost = seq
        else:
            if seq <= rec.last_seq:  # without a session id (`is_duplicate` ruled out the rest): a restart
                self.restarts += 1
                self.lost += seq
                rec.ledger.count_lost(seq)
                rec.start_stamp = None  # its new run's seq 0, unless this is it (below)
            elif seq > rec.last_seq + 1:
                self.lost += seq - rec.last_seq - 1
                rec.ledger.count_lost(seq - rec.last_seq - 1)
            # Those pushed out meanwhile too: one that started after `rec`'s last scan was taken
            # for a restart, withdrawn only if found here. None if `rec` was a recent one: each
            # was pushed out as the least recently heard of them, `rec` among them or heard since.
            # (Looked at all the same, a robot with 128 sessions of its past restarts pushed out
            # took 0.7 ms a scan, under the registry's lock.)
            others = (*self.sessions.values(), *(() if recent else self.settling.values()))
            beside = [other for other in others if other.last_scan_no > rec.last_scan_no]
            rows, unchanged = ({}, 0) if recent else self._rows_heard_since(rec.last_scan_no)
            interleaved = bool(beside or rows or unchanged)
            if interleaved:
                self._conflict(rec, [*beside, *rows.values()], unchanged, now)
                for row_key, row_rec in rows.items():
                    self._keep(row_key, row_rec)
            # The run's latest stamp (`SessionSeqs.stamp`); a restart's own starts its run.
            latest = max(rec.stamp, stamp) if seq > rec.last_seq and rec.stamp is not None else stamp
            rec.last_seq, rec.stamp, rec.last_scan_no = seq, latest, self.accepted
        if seq == 0:
            rec.start_stamp = stamp
        self._recent(key, rec)
        return interleaved

    def _take_session(self, key: int) -> SessionSeqs | None:
        """The bookkeeping of session `key` (`session_key`), taken out of the recent `sessions` or
        those pushed out (`settling`, `pushed_out`) to be changed and put back (`_recent`); None if
        the robot knows no such session."""
        rec = self.sessions.pop(key, None) or self.settling.pop(key, None)
        if rec is None and (row := self.pushed_out.pop(key)) is not None:
            rec = _pushed_out_seqs(row)
        return rec

    def _recent(self, key: int, rec: SessionSeqs) -> None:
        """Session `key`'s bookkeeping `rec` (`_take_session`) is heard now: the last of the recent
        `sessions`, which pushes the least recently heard past MAX_SESSIONS out."""
        self.sessions[key] = rec
        if len(self.sessions) > MAX_SESSIONS or self.settling:
            self._push_out()

    def _push_out(self) -> None:
        """Push the least recently heard of `sessions` past MAX_SESSIONS out (`settling` while
        scans of theirs wait, else `pushed_out`), and forget those pushed out past
        MAX_SESSIONS_PUSHED_OUT or PUSHED_OUT_EXPIRY (the least recently pushed out first)."""
        while len(self.sessions) > MAX_SESSIONS:
            oldest = next(iter(self.sessions))
            pushed = self.settling[oldest] = self.sessions.pop(oldest)
            # Its counts stay (its scans still queued settle in them); not its lists, which made a
            # robot's pushed-out sessions hold 4 times as much as its recent ones (robot ids and
            # session ids made up by any Zenoh peer: docs/security.md). A flush then counts its
            # refusals and losses after its last seq too, as past LEDGER_HISTORY of them.
            pushed.ledger.refused_seqs = pushed.ledger.lost_gaps = None
        settled = [key for key, rec in self.settling.items() if not rec.ledger.open_receipts]
        if not settled:
            return
        for key in settled:
            self.pushed_out.put(key, _pushed_out_row(self.settling.pop(key)))
        heard = self.pushed_out.columns(_LAST_SCAN_NO)
        forget = max(0, len(heard) - MAX_SESSIONS_PUSHED_OUT)
        while forget < len(heard) and heard[forget] <= self.accepted - PUSHED_OUT_EXPIRY:
            forget += 1
        self.pushed_out.drop_first(forget)

    def _rows_heard_since(self, scan_no: int) -> tuple[dict[int, SessionSeqs], int]:
        """The sessions of `pushed_out` heard after the robot's scan `scan_no` that a conflict
        found now changes (not known to be in one yet, or counted as a restart: `_conflict`), as
        copies of their rows by key, and how many others were heard after it."""
        changed: dict[int, SessionSeqs] = {}
        unchanged = 0
        rows = self.pushed_out.columns(_LAST_SCAN_NO, _CONFLICT, _START_LOST)
        for key, (last, conflict, start_lost) in zip(self.pushed_out.keys(), rows, strict=True):
            if last <= scan_no:
                continue
            if conflict and start_lost == STORED_NONE:
                unchanged += 1
            else:
                row = self.pushed_out.get(key)
                assert row is not None  # (one of its keys)
                changed[key] = _pushed_out_seqs(row)
        return changed, unchanged

    def _conflict(self, back: SessionSeqs, beside: list[SessionSeqs], unchanged: int, now: float) -> None:
        """Session `back` came back after the sessions `beside` and `unchanged` others (known to be
        in a conflict, and not counted as restarts) were heard: they ran at once."""
        self.conflict_at = now
        for other in beside:
            if other.start_lost is not None and other.first_scan_no > back.last_scan_no:
                # It started while `back` still ran: not a restart of it.
                self.restarts -= 1
                self.lost -= other.start_lost
                other.start_lost = None
        newly = [rec for rec in (back, *beside) if not rec.conflict]
        for rec in newly:
            rec.conflict = True
        # Each session found counts, but the first two of a conflict count once between them (two
        # robots under one id: 1): three found at once are 2, as a third found later adds 1. Counted
        # once per finding, three robots started together showed 1, as two robots do.
        first_found = not unchanged and len(newly) == len(beside) + 1
        self.id_conflicts += len(newly) - 1 if first_found else len(newly)

    def in_conflict(self, now: float) -> bool:
        """Whether scans of two sessions interleaved within the last CONFLICT_SHOWN seconds (`now`
        and `conflict_at` are wall-clock time, which a snapshot keeps across restarts). A
        `conflict_at` after `now` is from before the service's clock stepped back: how long ago is
        not known, and taken for "just now" the conflict showed for as long as the step (hours)
        plus a minute; one that goes on shows again with its next interleaved scan."""
        return self.conflict_at is not None and 0.0 <= now - self.conflict_at < CONFLICT_SHOWN
