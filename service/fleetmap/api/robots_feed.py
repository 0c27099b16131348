"""What one event stream has sent of a map's robots, and what it has not sent yet.

A `robots` event holds every robot with its trail: 100 robots x 100 points is ~150 kB of JSON, and
built 10 times a second per stream under the registry's lock, which ingest needs too. A
`RobotsFeed` builds one only when the map's robots changed since (`MapEntry.live_version`), and
`delta` copies only what changed: the robots whose `RobotState.changed` is newer than the last event,
of their trails only the points appended since (`RobotState.appended`), and the ids of robots
forgotten since. The copies are made under the lock, the models (and their JSON) after it, once for
all the streams of a map (`RobotsFeed`).
"""

from __future__ import annotations

import json
import threading
from itertools import islice

from fleetmap.api_models import RobotChange, RobotLive, RobotsDeltaEvent, RobotsEvent, robot_live
from fleetmap.map_entry import MapEntry
from fleetmap.robot_state import RobotState
from fleetmap.scan import Pose2D

#: Trail points a stream sends per robot (the registry keeps TRAIL_LENGTH).
TRAIL_POINTS = 100
#: JSON fragments a robot keeps for the streams (`RobotState.viewer_json`); past it they start over.
#: Streams in step with each other ask for one or two (a delta's points since the previous poll, and
#: a full event's trail).
FRAGMENTS_PER_ROBOT = 8

#: What identifies a robot's JSON in an event: the model (a delta's `RobotChange` or a full event's
#: `RobotLive`), the fields a viewer sees, its `appended` count and how many trail points it sends
#: (the trail only grows, so the last `count` points as of `appended` never change).
_Key = tuple[bool, bool, Pose2D | None, int, int, int]
#: A robot of an event being built: its id, its state, its key, and its JSON if some stream made it,
#: else the trail points it sends.
_Part = tuple[str, RobotState, _Key, str | None, list[tuple[float, float, float]] | None]


class RobotsFeed:
    """The robots events of map `entry` for one stream. Not thread-safe: one stream's task uses it.

    Every stream of a map sends each robot's change as the same JSON (its fields, and the points
    appended since the stream's previous event: one or two when the streams poll in step), so the
    first stream to send it leaves it on the robot (`RobotState.viewer_json`) and the others send
    that: building the events of 100 streams of a map with 200 robots moving took more than the
    event loop's whole core, most of it spent making the same models again."""

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
        """`full_json` as a model."""
        data = self.full_json()
        return None if data is None else RobotsEvent.model_validate_json(data)

    def delta(self) -> RobotsDeltaEvent | None:
        """`delta_json` as a model."""
        data = self.delta_json()
        return None if data is None else RobotsDeltaEvent.model_validate_json(data)

    def full_json(self) -> str | None:
        """Every robot of the map (a `RobotsEvent`'s JSON), or None when nothing of them changed
        since this feed's last event."""
        with self.lock:
            robots = self.entry.robots
            if self.entry.live_version == self.version:
                return None
            self.version = self.entry.live_version
            self.sent = {rid: (state, state.appended) for rid, state in robots.items()}
            parts = [self._part(rid, state, state.appended, False) for rid, state in robots.items()]
        return '{"robots":' + self._robots_json(parts, False) + "}"

    def delta_json(self) -> str | None:
        """What changed since this feed's last event (a `RobotsDeltaEvent`'s JSON; `RobotsEvent.apply`
        applies it), or None when nothing did. Call `full_json` first: a delta is relative to what
        this feed sent."""
        removed: list[str] = []
        parts: list[_Part] = []
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
                parts.append(self._part(rid, state, new_points, True))
                self.sent[rid] = (state, state.appended)
            # Every robot of the map is in `sent` now (one unchanged since was sent before): more
            # ids there means robots were forgotten.
            if len(self.sent) > len(entry.robots):
                gone = self.sent.keys() - entry.robots.keys()
                for rid in gone:
                    del self.sent[rid]
                removed.extend(gone)
            self.version = entry.live_version
        if not parts and not removed:
            return None
        return (
            f'{{"trail_length":{self.trail_points},"robots":{self._robots_json(parts, True)},'
            f'"removed":{json.dumps(sorted(removed), separators=(",", ":"))}}}'
        )

    def _part(self, rid: str, state: RobotState, new_points: int, change: bool) -> _Part:
        """A robot of an event (under the lock): its key, and its JSON if a stream made it already,
        else its last `count` trail points, copied here (the journal thread appends to the trail)."""
        count = min(new_points, self.trail_points, len(state.trail))
        key = (change, state.online, state.last_pose, state.scans_integrated, state.appended, count)
        made = state.viewer_json.get(key)
        points = None if made is not None else list(islice(reversed(state.trail), count))[::-1]
        return rid, state, key, made, points

    @staticmethod
    def _robots_json(parts: list[_Part], change: bool) -> str:
        """The event's `robots` object, each robot's JSON made once for every stream (after the
        lock: a key holds what its JSON shows, so what is left on the robot is right for any stream
        that asks for that key)."""
        model: type[RobotLive] = RobotChange if change else RobotLive
        items = []
        for rid, state, key, made, points in sorted(parts, key=lambda part: part[0]):
            if made is None:
                _, online, pose, scans, _, _ = key
                made = robot_live(online, pose, points or [], scans, model=model).model_dump_json()
                cache = state.viewer_json
                if len(cache) >= FRAGMENTS_PER_ROBOT:
                    cache.clear()
                cache[key] = made
            items.append(f"{json.dumps(rid)}:{made}")
        return "{" + ",".join(items) + "}"
