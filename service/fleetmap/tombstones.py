"""What the service remembers of a deleted (or replaced) map's robots, so that the map stays deleted,
and of the robots a full map forgot, so that their old scans are not integrated twice.

A robot's `ScanPublisher` keeps its last scans for re-delivery, and the service's advanced
subscriber fetches them whenever it meets a publisher it has not heard: after every restart of the
service, and after a robot's link was down past Zenoh's lease. Those copies carry the seqs of scans
the service had before a map was deleted, and the map's seq bookkeeping went with it: without a
record, they re-created the deleted map with its old scans. Likewise a robot's liveliness token,
seen again after a restart, re-created it empty.

So when a map is deleted or replaced by an upload, each of its robots is buried (`Tombstones.bury`):
the last seq of each of its publisher sessions, and when: of every session its bookkeeping knows, the
recent ones and those pushed out of them (`RobotState.pushed_out`: more robots under one id than
`MAX_SESSIONS`), kept compactly (`BuriedSessions`). With the recent ones only, the copies of a
pushed-out session's scans (its robot's cache fetched again after a restart of the service) made the
deleted map again with them. A scan of a buried session at or below
that seq is from before the deletion and is ignored as a duplicate (`covers`); a token of a buried
robot creates no map (`buried`). A new scan, or a new session (a robot process that restarted),
goes through as before and, with auto-create, makes a new map. The robots that waited for the map
(their scans refused for want of room on it: `MapRegistry._bury`) are buried with it too: the
token of one, seen again after a restart, made the deleted map again, and its cache put its refused
scans from before the deletion in it.

A map full of robots forgets an idle one to make room for a new one (`MapRegistry._room_for`), and
its seq bookkeeping goes with it: without a record, the same cache fetched again (the service
restarted, the robot's link came back) was integrated a second time into the map that already held
those scans. So a forgotten robot is buried too (`Tombstones.forget`), its stone marked `forgotten`:
its old scans are ignored as duplicates the same way, but its scans are in the live map, not gone,
so its token brings it back as before (`buried` is False) and the delivery query does not list its
sessions as gone with a map. When that map is deleted or replaced, its forgotten robots' stones
become ordinary ones (`bury`): their scans went with it.

Scans without a session id are covered by their last seq and their run's latest stamp
(`Tombstone.plain`, `SessionSeqs.stamp`): a copy carries its old stamp, so one at or below that seq
whose stamp is not later than that (and not 0: a robot without a clock, whose copies cannot be told
from a restart) is from before; a robot that started its sequence again, with a later stamp, goes
through. They are re-delivered too: a `ScanPublisher(send_session_id=False)` keeps its cache, and
after a restart of the service its old scans, not covered, made the deleted map again with them.
(A live map takes seq 0 of an earlier stamp for a restart unless it is the run's own seq 0 again,
`SessionSeqs.is_restart`; a stone keeps no run's seq 0, and its robot's copies are what it is for.)

Maps are created and deleted under new ids for the service's whole life, so tombstones are bounded:
kept `TOMBSTONE_DAYS`, and for at most `MAX_TOMBSTONES` robots (`prune`). Past that many, forgotten
robots' stones go first, the oldest first, and deleted maps' robots' only when none is left: any
peer that may publish can make a full map forget robot after robot under made-up ids, and must not
push the deleted maps' robots out so. A robot whose publisher stays open and idle longer than
`TOMBSTONE_DAYS`, with the old scans in its cache, could still bring a deleted map back.

The `DurableStore` keeps them across restarts (a forgotten robot's stone in the snapshot
transaction that drops the robot's rows). Plain data, no locks: the registry holds its lock around
every use.
"""

from __future__ import annotations

import json
from array import array
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

from fleetmap.robot_state import NO_SESSION, SESSIONS_TOLD_APART, RobotState, session_key

#: Days a deleted map's robots (and a map's forgotten robots) are remembered.
TOMBSTONE_DAYS = 30.0
#: Buried robots remembered at most, the most recently buried: about 64 MB of memory with one
#: publisher session a stone, 70 MB with `MAX_SESSIONS`, 293 MB with `MAX_BURIED_SESSIONS`
#: (tracemalloc, 2026-11-29; 126 MB with `MAX_SESSIONS` as a dict, before `BuriedSessions`). A
#: service whose maps are deleted or whose full maps forget robots fills it at that rate, then holds
#: it there.
MAX_TOMBSTONES = 100_000
#: Sessions a tombstone remembers at most, the most recently heard: as many as a robot's bookkeeping
#: tells apart (`MAX_SESSIONS` recent ones and `MAX_SESSIONS_PUSHED_OUT` pushed out of them).
MAX_BURIED_SESSIONS = SESSIONS_TOLD_APART


def forgotten_before(now: float) -> float:
    """Robots buried before this time are forgotten at `now`."""
    return now - TOMBSTONE_DAYS * 86400.0


class BuriedSessions(Mapping[int, int]):
    """A tombstone's sessions, session id -> the last seq the service had of it, least recently
    heard first, as two arrays of machine integers: 16 bytes a session where a dict took about 100,
    for up to `MAX_BURIED_SESSIONS` sessions of each of `MAX_TOMBSTONES` robots. Finding an id scans
    the ids, at C speed (136 at most)."""

    __slots__ = ("_keys", "_seqs")

    def __init__(self, items: Iterable[tuple[int, int]] = ()) -> None:
        """The sessions `items`, (session id, last seq) least recently heard first, each id once."""
        listed = list(items)
        self._keys = array("q", [key for key, _ in listed])
        self._seqs = array("q", [seq for _, seq in listed])

    def __getitem__(self, key: int) -> int:
        try:
            return self._seqs[self._keys.index(key)]
        except ValueError:
            raise KeyError(key) from None

    def __iter__(self) -> Iterator[int]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __repr__(self) -> str:
        return f"BuriedSessions({self.pairs()!r})"

    def pairs(self) -> list[tuple[int, int]]:
        """(session id, last seq) of each, least recently heard first (what `items` gives, without
        a look-up of each id)."""
        return list(zip(self._keys, self._seqs, strict=True))


@dataclass(frozen=True)
class Tombstone:
    """One robot of a deleted or replaced map: the last seq the service had of each of its publisher
    sessions (session id -> seq; sessions without an id left out), and when it was buried.

    `forgotten`: the robot was forgotten by its map, which lives on (`Tombstones.forget`), and
    `deleted_at` is when: its scans through those seqs are in that map, not gone with it.

    `refused_scans` are the robot's `RobotState.refused_scans` then, (session key, seq) of its scans
    refused for the service's sake (a full queue: 503; the memory budget: 507): their seqs are
    recorded, yet the service never had the scans, and their sender is told to send them again,
    which must be integrated, not ignored as from before the deletion. Not stored (a live map's
    snapshot saves its robots' `RobotState.refused_scans`; a tombstone's row has no room for them):
    after a restart they are covered.

    `plain`: the last seq and the run's latest stamp (None: unknown) the service had of the robot's
    scans without a session id, None if it had none."""

    map_id: str
    robot_id: str
    deleted_at: float
    sessions: BuriedSessions
    refused_scans: frozenset[tuple[int, int]] = frozenset()
    forgotten: bool = False
    plain: tuple[int, float | None] | None = None

    def plain_row(self) -> tuple[int | None, float | None]:
        """`plain` as stored (`plain_seq`, `plain_stamp`; NULL: none)."""
        return (None, None) if self.plain is None else self.plain

    def last_seq(self, session: int | None) -> int | None:
        """The last seq the service had of publisher session `session` (None: scans without one)."""
        if session is None:
            return None if self.plain is None else self.plain[0]
        return self.sessions.get(session)

    def sessions_json(self) -> str:
        """`sessions` as stored (a JSON object of decimal strings: session ids need 64 bits)."""
        return json.dumps({str(k): v for k, v in self.sessions.pairs()})

    @classmethod
    def from_row(
        cls, map_id: str, robot_id: str, deleted_at: float, sessions_json: str, forgotten: int = 0,
        plain_seq: int | None = None, plain_stamp: float | None = None,
    ) -> Tombstone:  # fmt: skip
        """The tombstone of a stored row; ValueError if its time is not a number, its sessions are
        not a JSON object of session ids and seqs, or its `plain` seq and stamp are not numbers (a
        damaged database)."""
        # SQLite keeps any type in any column (a damaged page, a row edited by hand): a time stored
        # as text stopped the start with a traceback where the stones are sorted by it.
        if type(deleted_at) not in (int, float):
            raise ValueError(f"tombstone of {map_id}/{robot_id}: its time of deletion is not a number")
        if not (
            (plain_seq is None and plain_stamp is None)
            or (type(plain_seq) is int and (plain_stamp is None or type(plain_stamp) in (int, float)))
        ):
            raise ValueError(
                f"tombstone of {map_id}/{robot_id}: its scans without a session id are not numbers"
            )
        stored = json.loads(sessions_json)
        if not isinstance(stored, dict):
            raise ValueError(f"tombstone of {map_id}/{robot_id}: sessions are not a JSON object")
        try:
            sessions = BuriedSessions(zip(map(int, stored), map(int, stored.values()), strict=True))
        except TypeError:  # a seq that is a list or an object (int() of a wrong string: ValueError)
            raise ValueError(f"tombstone of {map_id}/{robot_id}: a session's seq is not a number") from None
        except OverflowError:  # past the 64 bits of `BuriedSessions`' machine integers
            raise ValueError(
                f"tombstone of {map_id}/{robot_id}: a session's id or seq is past 64 bits"
            ) from None
        plain = None if plain_seq is None else (plain_seq, plain_stamp)
        return cls(map_id, robot_id, deleted_at, sessions, forgotten=bool(forgotten), plain=plain)


def merged_sessions(old: BuriedSessions, heard: Iterable[tuple[int, int]]) -> BuriedSessions:
    """The sessions of a tombstone that had `old` (least recently heard first) and buries the
    sessions `heard` now ((session key, last seq), least recently heard first: a robot's
    `RobotState.last_seqs`): each session the higher of its two seqs, sessions without an id left
    out, at most the `MAX_BURIED_SESSIONS` heard most recently (`heard`, in its order, count as
    heard last)."""
    sessions = dict(old.pairs())
    for key, seq in heard:
        if key != NO_SESSION:
            sessions[key] = max(seq, sessions.pop(key, seq))
    return BuriedSessions(list(sessions.items())[-MAX_BURIED_SESSIONS:])


def merged_plain(old: Tombstone | None, state: RobotState) -> tuple[int, float | None] | None:
    """The `Tombstone.plain` of a robot that had the stone `old` and buries `state` now: the seq and
    stamp of its last scan without a session id, `state`'s if it had one (its newest), else the old."""
    rec = state.sessions.get(NO_SESSION)
    if rec is not None:
        return rec.last_seq, rec.stamp
    return None if old is None else old.plain


class Tombstones:
    """Buried robots by (map id, robot id), oldest first."""

    def __init__(self, stones: Iterable[Tombstone] = (), now: float | None = None) -> None:
        self._stones: dict[tuple[str, str], Tombstone] = {}
        #: map id -> the robots it forgot that have a (`forgotten`) stone: what `bury` turns into
        #: ordinary stones when the map goes, without a look at every stone.
        self._forgotten: dict[str, set[str]] = {}
        #: The (map id, robot id) of every `forgotten` stone, oldest first: what `prune` lets go
        #: first past `MAX_TOMBSTONES`.
        self._forgotten_order: dict[tuple[str, str], None] = {}
        for stone in sorted(stones, key=lambda s: s.deleted_at):
            self._put(stone)
        if now is not None:
            self.prune(now)

    def _put(self, stone: Tombstone) -> None:
        """Keep `stone` as its robot's, the newest (replacing the robot's earlier one)."""
        self._drop(stone.map_id, stone.robot_id)
        self._stones[stone.map_id, stone.robot_id] = stone
        if stone.forgotten:
            self._forgotten.setdefault(stone.map_id, set()).add(stone.robot_id)
            self._forgotten_order[stone.map_id, stone.robot_id] = None

    def _drop(self, map_id: str, robot_id: str) -> Tombstone | None:
        """Remove the robot's stone, if it has one, and return it."""
        stone = self._stones.pop((map_id, robot_id), None)
        if stone is not None and stone.forgotten:
            del self._forgotten_order[map_id, robot_id]
            robots = self._forgotten[map_id]
            robots.discard(robot_id)
            if not robots:
                del self._forgotten[map_id]
        return stone

    def __len__(self) -> int:
        return len(self._stones)

    def bury(
        self,
        map_id: str,
        robots: Mapping[str, RobotState],
        now: float,
        waiting: Mapping[str, Iterable[tuple[int, int]]] | None = None,
    ) -> list[Tombstone]:
        """Remember every robot of map `map_id`, being deleted or replaced at `now`; return the
        tombstones to store. A robot buried before (the map was deleted, made again and deleted)
        keeps the sessions it had then, and each session the higher of its two seqs, up to the
        `MAX_BURIED_SESSIONS` heard most recently: each burial renews the tombstone's time, so without
        that bound a map deleted every day grew its robots' tombstones by a session a day for good.
        (The live bookkeeping keeps no more: an older session's scans were new to it too.)

        The robots the map forgot (`forget`) are buried with it: their stones become ordinary ones
        of this time, returned too (their scans went with the map). So are the robots `waiting`
        for room on it, or for it (robot id -> the (session key, last seq) of its scans refused so:
        `UnmappedRefusals.sessions_of`), not among `robots`: their scans from before are not the
        map's, nor their tokens a reason to make it again."""
        made = []
        for robot_id, state in robots.items():
            old = self._drop(map_id, robot_id)
            sessions = merged_sessions(BuriedSessions() if old is None else old.sessions, state.last_seqs())
            stone = Tombstone(
                map_id, robot_id, now, sessions, frozenset(state.refused_scans),
                plain=merged_plain(old, state),
            )  # fmt: skip
            self._put(stone)
            made.append(stone)
        for robot_id, heard in (waiting or {}).items():
            if robot_id not in robots:
                old = self._drop(map_id, robot_id)
                sessions = merged_sessions(BuriedSessions() if old is None else old.sessions, heard)
                stone = Tombstone(map_id, robot_id, now, sessions, plain=None if old is None else old.plain)
                self._put(stone)
                made.append(stone)
        for robot_id in sorted(self._forgotten.get(map_id, ())):  # (a copy: `_put` changes it)
            old = self._stones[map_id, robot_id]
            stone = Tombstone(map_id, robot_id, now, old.sessions, old.refused_scans, plain=old.plain)
            self._put(stone)
            made.append(stone)
        self.prune(now)
        return made

    def forget(self, map_id: str, robot_id: str, state: RobotState, now: float) -> Tombstone | None:
        """Remember robot `robot_id`, forgotten at `now` by map `map_id`, which lives on: its
        sessions' seqs, merged with its earlier stone as `bury` merges them, in a `forgotten` stone.
        Returns it, to store, or None if there is nothing to remember (no scan's seq, or none of
        its scans in the map, `RobotState.in_map`: nothing to integrate twice, and scans refused at
        the input limits under made-up robot ids took stones): its earlier stone, if any, then
        stays as it was. A robot that had an ordinary stone (its map was
        deleted before, and the robot fed the new one) gets a forgotten one: its scans since are in
        the live map, which the delivery query must not call gone; the older ones stay covered."""
        if not state.in_map or not state.sessions:
            return None
        old = self._drop(map_id, robot_id)
        stone = Tombstone(
            map_id, robot_id, now,
            merged_sessions(BuriedSessions() if old is None else old.sessions, state.last_seqs()),
            frozenset(state.refused_scans), forgotten=True, plain=merged_plain(old, state),
        )  # fmt: skip
        self._put(stone)
        self.prune(now)
        return stone

    def covers(
        self, map_id: str, robot_id: str, session: int | None, seq: int, stamp: float = 0.0
    ) -> Tombstone | None:
        """The tombstone that makes scan `seq` (of stamp `stamp`) of publisher session `session`
        (None: it sent none) one from before its map was deleted (or its robot forgotten by it:
        `Tombstone.forgotten`), or None: the scan is not known to be old (or is one its robot was
        told to send again: `Tombstone.refused_scans`; or, without a session id, one of a later
        stamp than the last, or of none (0): see the module's docstring)."""
        stone = self._stones.get((map_id, robot_id))
        if stone is None or (session_key(session), seq) in stone.refused_scans:
            return None
        last = stone.last_seq(session)
        if last is None or seq > last:
            return None
        if session is None:
            last_stamp = None if stone.plain is None else stone.plain[1]
            # Stamps are of any epoch, negative ones too: only 0 says "no clock" (as `is_restart`).
            if last_stamp is None or stamp == 0 or stamp > last_stamp:
                return None
        return stone

    def get(self, map_id: str, robot_id: str) -> Tombstone | None:
        """The tombstone of robot `robot_id` of a deleted or replaced map `map_id`, or of one map
        `map_id` forgot (`Tombstone.forgotten`), if it has one."""
        return self._stones.get((map_id, robot_id))

    def buried(self, map_id: str, robot_id: str) -> bool:
        """Whether robot `robot_id` was buried with map `map_id` (its token must not bring it back);
        not for a robot the map merely forgot."""
        stone = self._stones.get((map_id, robot_id))
        return stone is not None and not stone.forgotten

    def prune(self, now: float) -> None:
        """Forget the robots buried more than `TOMBSTONE_DAYS` ago, and the oldest past
        `MAX_TOMBSTONES`: the robots live maps forgot first, then deleted maps' (as
        `DurableStore.load_tombstones` cuts the table). Evicted oldest first among all, a sender
        cycling through robot ids with valid scans into a full map pushed every deleted map's
        robots out within minutes, and their cached scans brought the deleted maps back."""
        horizon = forgotten_before(now)
        while self._stones:
            oldest = next(iter(self._stones.values()))
            if oldest.deleted_at >= horizon:
                break
            self._drop(oldest.map_id, oldest.robot_id)
        while len(self._stones) > MAX_TOMBSTONES:
            map_id, robot_id = next(iter(self._forgotten_order or self._stones))
            self._drop(map_id, robot_id)
