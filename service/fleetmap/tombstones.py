"""What the service remembers of a deleted (or replaced) map's robots, so that the map stays deleted.

A robot's `ScanPublisher` keeps its last scans for re-delivery, and the service's advanced
subscriber fetches them whenever it meets a publisher it has not heard: after every restart of the
service, and after a robot's link was down past Zenoh's lease. Those copies carry the seqs of scans
the service had before a map was deleted, and the map's seq bookkeeping went with it: without a
record, they re-created the deleted map with its old scans. Likewise a robot's liveliness token,
seen again after a restart, re-created it empty.

So when a map is deleted or replaced by an upload, each of its robots is buried (`Tombstones.bury`):
the last seq of each of its publisher sessions, and when. A scan of a buried session at or below
that seq is from before the deletion and is ignored as a duplicate (`covers`); a token of a buried
robot creates no map (`buried`). A new scan, or a new session (a robot process that restarted),
goes through as before and, with auto-create, makes a new map.

Scans without a session id (plain publishers) are never covered: they are not re-delivered, and
their seqs may start again at any time. Tombstones are kept `TOMBSTONE_DAYS` and at most
`MAX_TOMBSTONES` robots (the oldest go first), since maps are created and deleted under new ids for
the service's whole life; a robot whose publisher stays open and idle longer than that, with the
old scans in its cache, could still bring a deleted map back. The `DurableStore` keeps them across
restarts. Plain data, no locks: the registry holds its lock around every use.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from fleetmap.robot_state import MAX_SESSIONS, NO_SESSION, RobotState

#: Days a deleted map's robots are remembered.
TOMBSTONE_DAYS = 30.0
#: Buried robots remembered at most, the most recently buried.
MAX_TOMBSTONES = 100_000


def forgotten_before(now: float) -> float:
    """Robots buried before this time are forgotten at `now`."""
    return now - TOMBSTONE_DAYS * 86400.0


@dataclass(frozen=True)
class Tombstone:
    """One robot of a deleted or replaced map: the last seq the service had of each of its publisher
    sessions (session id -> seq; sessions without an id left out), and when it was buried.

    `refused` is the robot's `RobotState.refused` then, (session id, seq) of its last scan refused
    for the service's sake (a full queue: 503; the memory budget: 507): its seq is recorded, yet the
    service never had the scan, and its sender is told to send it again, which must be integrated,
    not ignored as from before the deletion. Not stored, as `RobotState.refused` is not: after a
    restart it is covered, as the map's own bookkeeping would have it."""

    map_id: str
    robot_id: str
    deleted_at: float
    sessions: Mapping[int, int]
    refused: tuple[int, int] | None = None

    def sessions_json(self) -> str:
        """`sessions` as stored (a JSON object of decimal strings: session ids need 64 bits)."""
        return json.dumps({str(k): v for k, v in self.sessions.items()})

    @classmethod
    def from_row(cls, map_id: str, robot_id: str, deleted_at: float, sessions_json: str) -> Tombstone:
        """The tombstone of a stored row; ValueError if its sessions are not a JSON object of
        session ids and seqs (a damaged database)."""
        stored = json.loads(sessions_json)
        if not isinstance(stored, dict):
            raise ValueError(f"tombstone of {map_id}/{robot_id}: sessions are not a JSON object")
        return cls(map_id, robot_id, deleted_at, {int(k): int(v) for k, v in stored.items()})


class Tombstones:
    """Buried robots by (map id, robot id), oldest first."""

    def __init__(self, stones: Iterable[Tombstone] = (), now: float | None = None) -> None:
        self._stones: dict[tuple[str, str], Tombstone] = {}
        for stone in sorted(stones, key=lambda s: s.deleted_at):
            self._stones[stone.map_id, stone.robot_id] = stone
        if now is not None:
            self.prune(now)

    def __len__(self) -> int:
        return len(self._stones)

    def bury(self, map_id: str, robots: Mapping[str, RobotState], now: float) -> list[Tombstone]:
        """Remember every robot of map `map_id`, being deleted or replaced at `now`; return the
        tombstones to store. A robot buried before (the map was deleted, made again and deleted)
        keeps the sessions it had then, and each session the higher of its two seqs, up to the
        `MAX_SESSIONS` heard most recently: each burial renews the tombstone's time, so without
        that bound a map deleted every day grew its robots' tombstones by a session a day for good.
        (The live bookkeeping keeps no more: an older session's scans were new to it too.)"""
        made = []
        for robot_id, state in robots.items():
            old = self._stones.pop((map_id, robot_id), None)
            sessions = dict(old.sessions) if old is not None else {}  # least recently heard first
            for key, rec in state.sessions.items():
                if key != NO_SESSION:
                    sessions[key] = max(rec.last_seq, sessions.pop(key, rec.last_seq))
            while len(sessions) > MAX_SESSIONS:
                del sessions[next(iter(sessions))]
            refused = state.refused if state.refused is not None and state.refused[0] != NO_SESSION else None
            stone = Tombstone(map_id, robot_id, now, sessions, refused)
            self._stones[map_id, robot_id] = stone
            made.append(stone)
        self.prune(now)
        return made

    def covers(self, map_id: str, robot_id: str, session: int | None, seq: int) -> Tombstone | None:
        """The tombstone that makes scan `seq` of publisher session `session` one from before its map
        was deleted, or None: the scan is not known to be old (or is the one its robot was told to
        send again: `Tombstone.refused`)."""
        stone = self._stones.get((map_id, robot_id))
        if stone is None or session is None or stone.refused == (session, seq):
            return None
        last = stone.sessions.get(session)
        return stone if last is not None and seq <= last else None

    def get(self, map_id: str, robot_id: str) -> Tombstone | None:
        """The tombstone of robot `robot_id` of a deleted or replaced map `map_id`, if it has one."""
        return self._stones.get((map_id, robot_id))

    def buried(self, map_id: str, robot_id: str) -> bool:
        """Whether robot `robot_id` was buried with map `map_id` (its token must not bring it back)."""
        return (map_id, robot_id) in self._stones

    def prune(self, now: float) -> None:
        """Forget the robots buried more than `TOMBSTONE_DAYS` ago, and the oldest past
        `MAX_TOMBSTONES`."""
        horizon = forgotten_before(now)
        while self._stones:
            key, oldest = next(iter(self._stones.items()))
            if oldest.deleted_at >= horizon and len(self._stones) <= MAX_TOMBSTONES:
                break
            del self._stones[key]
