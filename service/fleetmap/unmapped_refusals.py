"""What the service remembers of scans it refused because they had no map to go to, so that a robot's
delivery query can say they are settled.

A scan is refused without ever reaching a robot's ledger (`RobotState`) when its map does not exist
and the service may not create it (`--no-auto-create`, a mistyped map id), when its map holds
`--max-robots-per-map` robots and none can be forgotten for it, or when it broke the input limits on
such a map. Scans refused on a map they created, which was removed again at once
(`MapRegistry._remove_unclaimed`), lose their ledger with the map. Without a record of them the
delivery query answered only `no_map` (or `no_robot`), and a robot's `flush` waited for those scans
for ever: what became of them is final, and the answer must say so.

So each such refusal is remembered here per (map id, robot id) and publisher session
(`UnmappedRefusals.remember`): the first and last seq settled, how many of them were refused (the
rest never arrived: lost) and the last reason. Scans without a session id are not remembered: their
seqs may start again at any time, so no range of them could be settled.

Bounds: `MAX_UNMAPPED_ROBOTS` robots, each with at most `SESSIONS_TOLD_APART` sessions, as many as a
robot's bookkeeping on a map tells apart (more robots under one id than its `MAX_SESSIONS` recent
sessions): with `MAX_SESSIONS`, the sessions of the ninth and later robots under one id pushed the
first ones' out, and those robots' flushes, told only `no_map`, waited until their timeout. Kept as
rows of numbers (`PushedOutRows`), with the robot's last reason. Anyone who may publish can make up
map and robot ids, so past the bound the least recently refused robot without a liveliness token is
forgotten first (real publishers declare one), then the least recently refused.

A robot's record goes when its map is deleted or replaced, or forgets the robot (`forget`): its
tombstone tells the rest. Not saved: after a restart the robots' caches, fetched again, are refused
and remembered again. Plain data, no locks: the registry holds its lock around every use.
"""

from __future__ import annotations

from collections.abc import Container, Iterable
from dataclasses import dataclass, field

from fleetmap.pushed_out import PushedOutRows
from fleetmap.robot_state import MAX_SESSIONS, SESSIONS_TOLD_APART
from fleetmap.wire import SessionDelivery

#: Robots (map id, robot id) whose refused scans are remembered, the most recent. Each holds at most
#: SESSIONS_TOLD_APART sessions of 3 numbers (32 bytes each with its key) and its last reason:
#: 6.1 MB with 64-character ids, whatever ids senders make up (1.4 MB with MAX_SESSIONS each, where
#: a session as an object with its own reason took 3.2 MB; tracemalloc, 2026-11-29).
MAX_UNMAPPED_ROBOTS = 1024


@dataclass(slots=True)
class UnmappedRobot:
    """A robot's publisher sessions whose scans were refused for want of their map, or of room on it,
    least recently refused first: per session (key: its id) the row (`first_seq`, `last_seq`,
    `refused`): seqs `first_seq` to `last_seq` are settled, `refused` of them refused (the rest never
    arrived: lost). `reason`: why its last counted refusal was."""

    sessions: PushedOutRows = field(default_factory=lambda: PushedOutRows("qqq"))
    reason: str = ""


class UnmappedRefusals:
    """Scans refused for want of their map, or of room for their robot on it, per (map id, robot id)
    and publisher session, for the delivery query. `alive` is the registry's set of (map id, robot
    id) with a liveliness token, read when a robot must be forgotten to keep the bound."""

    def __init__(self, alive: Container[tuple[str, str]]) -> None:
        self._alive = alive
        # (map id, robot id) -> its refused scans; least recently refused first.
        self._robots: dict[tuple[str, str], UnmappedRobot] = {}

    def __len__(self) -> int:
        return len(self._robots)

    def remember(
        self,
        map_id: str,
        robot_id: str,
        seq: int,
        session: int | None,
        reason: str,
        last: int | None = None,
        count: int = 1,
    ) -> None:
        """The scan `seq` of publisher session `session` was refused for `reason`: remember it as
        settled and refused, if it has a session id. A seq not above the session's last is a copy
        (the robot's cache fetched again): not counted twice. With `last` and `count`, `count` scans
        of seqs `seq` to `last` were (a removed map's ledger); overlapping what was counted, only
        its end is taken (the seqs after it not refused then count as lost)."""
        if session is None:
            return
        last = seq if last is None else last
        key = (map_id, robot_id)
        robot = self._robots.pop(key, None) or UnmappedRobot()
        self._robots[key] = robot  # the most recent last
        while len(self._robots) > MAX_UNMAPPED_ROBOTS:
            del self._robots[self._to_forget()]
        first_seq, last_seq, refused = robot.sessions.pop(session) or (seq, seq - 1, 0)
        assert isinstance(last_seq, int) and isinstance(refused, int)  # (numbers put below: no None)
        if seq > last_seq:
            last_seq, refused, robot.reason = last, refused + count, reason
        elif last > last_seq:
            last_seq, robot.reason = last, reason
        robot.sessions.put(session, (first_seq, last_seq, refused))  # the most recent last
        robot.sessions.drop_first(max(0, len(robot.sessions) - SESSIONS_TOLD_APART))

    def forget(self, map_id: str, robot_ids: Iterable[str]) -> None:
        """Robots `robot_ids` of map `map_id` were buried with it (deleted or replaced) or forgotten
        by it: forget their refused scans; their tombstones say the rest. Kept, they were the robot's
        answer again, older than its tombstone, and their session, settled only through its last
        refused seq, hid the tombstone's "in no map now" of its later scans: a flush of it never
        settled."""
        if self._robots:
            for robot_id in robot_ids:
                self._robots.pop((map_id, robot_id), None)

    def sessions_of(self, map_id: str) -> dict[str, list[tuple[int, int]]]:
        """Robot id -> (session id, last seq settled) of each of its sessions refused for want of
        map `map_id`, or of room on it, least recently refused first: the robots that waited for it
        when it is deleted or replaced (`Tombstones.bury`). Walks every robot remembered: at most
        MAX_UNMAPPED_ROBOTS."""
        return {
            robot_id: list(zip(robot.sessions.keys(), robot.sessions.columns(1), strict=True))
            for (refused_map, robot_id), robot in self._robots.items()
            if refused_map == map_id
        }

    def deliveries(
        self, map_id: str, robot_id: str, session: int | None = None
    ) -> tuple[list[SessionDelivery], str | None]:
        """The delivery query's sessions of a robot without a map, or without room on it, each
        settled through its last refused seq: the `MAX_SESSIONS` refused most recently, as the
        query lists a robot's sessions on a map, or only `session` if given (one of any it
        remembers: its flush asks); and the last reason any of its scans was refused for (None if
        none was)."""
        robot = self._robots.get((map_id, robot_id))
        if robot is None:
            return [], None
        if session is None:
            listed = list(robot.sessions.items())[-MAX_SESSIONS:]
        else:
            row = robot.sessions.get(session)
            listed = [] if row is None else [(session, row)]
        answer = [
            SessionDelivery(
                session=key, first_seq=first_seq, last_accepted=last_seq, settled=last_seq, integrated=0,
                refused=refused, lost=last_seq - first_seq + 1 - refused, duplicates=0,  # type: ignore[operator]
            )
            for key, (first_seq, last_seq, refused) in listed
        ]  # fmt: skip
        return answer, robot.reason

    def _to_forget(self) -> tuple[str, str]:
        """The robot to forget past MAX_UNMAPPED_ROBOTS: the least recently refused without a
        liveliness token, else the least recently refused. Real publishers declare a token;
        refusals under made-up ids (any Zenoh peer, with scans at the input limits or for made-up
        maps) pushed a real robot's out, and its flush, then told only `no_map`, waited until its
        timeout (for ever without one). Walks past the entries with a token only: at most
        MAX_UNMAPPED_ROBOTS."""
        oldest = next(iter(self._robots))
        return next((key for key in self._robots if key not in self._alive), oldest)
