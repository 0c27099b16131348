"""What one event stream has sent of a map's robots, and what it has not sent yet.

A `robots` event holds every robot with its trail: 100 robots x 100 points is ~150 kB of JSON, and
built 10 times a second per stream under the registry's lock, which ingest needs too. A
`RobotsFeed` builds one only when the map's robots changed since (`MapEntry.live_version`), and
`delta` copies only what changed: the robots whose `RobotState.changed` is newer than the last event,
of their trails only the points appended since (`RobotState.appended`), and the ids of robots
forgotten since. The copies are made under the lock, the models (and their JSON) after it.
"""

from __future__ import annotations

import threading
from itertools import islice

from fleetmap.api_models import RobotChange, RobotsDeltaEvent, RobotsEvent, robot_live
from fleetmap.registry import MapEntry
from fleetmap.robot_state import RobotState
from fleetmap.scan import Pose2D

#: What `RobotsFeed._copy` takes of a robot under the lock: its id, and `robot_live`'s arguments.
_Copy = tuple[str, tuple[bool, Pose2D | None, list[tuple[float, float, float]], int]]

#: Trail points a stream sends per robot (the registry keeps TRAIL_LENGTH).
TRAIL_POINTS = 100


class RobotsFeed:
    """The robots events of map `entry` for one stream. Not thread-safe: one stream's task uses it."""

    def __init__(
        self, entry: MapEntry, registry_lock: threading.RLock, trail_points: int = TRAIL_POINTS
    ) -> None:
        self.entry = entry
        self.lock = registry_lock
        self.trail_points = trail_points
        #: `entry.live_version` when this feed last sent (-1: never).
        self.version = -1
        #: Per robot id sent: the robot object sent (another one under that id is a new robot: the
        #: old one was forgotten) and its `appended` count then.
        self.sent: dict[str, tuple[RobotState, int]] = {}

    def full(self) -> RobotsEvent | None:
        """Every robot of the map, or None when nothing of them changed since this feed's last event."""
        with self.lock:
            robots = self.entry.robots
            if self.entry.live_version == self.version:
                return None
            self.version = self.entry.live_version
            self.sent = {rid: (state, state.appended) for rid, state in robots.items()}
            copies = [self._copy(rid, state, state.appended) for rid, state in robots.items()]
        return RobotsEvent(robots={rid: robot_live(*fields) for rid, fields in sorted(copies)})

    def delta(self) -> RobotsDeltaEvent | None:
        """What changed since this feed's last event (`RobotsEvent.apply` applies it), or None when
        nothing did. Call `full` first: a delta is relative to what this feed sent."""
        removed: list[str] = []
        copies: list[_Copy] = []
        with self.lock:
            entry = self.entry
            if entry.live_version == self.version:
                return None
            for rid, state in entry.robots.items():
                if state.changed <= self.version:
                    continue
                sent = self.sent.get(rid)
                if sent is not None and sent[0] is state:
                    new_points = state.appended - sent[1]
                else:
                    if sent is not None:  # forgotten, and created again under its id since
                        removed.append(rid)
                    new_points = state.appended
                copies.append(self._copy(rid, state, new_points))
                self.sent[rid] = (state, state.appended)
            # Every robot of the map is in `sent` now (one unchanged since was sent before): more
            # ids there means robots were forgotten.
            if len(self.sent) > len(entry.robots):
                gone = self.sent.keys() - entry.robots.keys()
                for rid in gone:
                    del self.sent[rid]
                removed.extend(gone)
            self.version = entry.live_version
        if not copies and not removed:
            return None
        robots = {rid: robot_live(*fields, model=RobotChange) for rid, fields in sorted(copies)}
        return RobotsDeltaEvent(trail_length=self.trail_points, robots=robots, removed=sorted(removed))

    def _copy(self, rid: str, state: RobotState, new_points: int) -> _Copy:
        """What a robot event needs of `state` (under the lock): its live fields and the last
        `new_points` of its trail (at most `trail_points`)."""
        count = min(new_points, self.trail_points, len(state.trail))
        trail = list(islice(reversed(state.trail), count))[::-1]
        return rid, (state.online, state.last_pose, trail, state.scans_integrated)
