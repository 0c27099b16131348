"""A map as the registry holds it, and a scan on its way into one.

`MapEntry` is one map of the service: its `GridMap`, its robots (`RobotState`), its change feed and
counters, and the flags a removal or an auto-creation sets. `Job` is a scan accepted by
`MapRegistry.submit` and waiting for integration. `IngestRejected` is a scan refused before
integration, and `REFUSAL_KINDS` names its kinds as the ingests count them. The registry
(`registry.py`) creates, changes and removes these under its lock; the REST API, the event streams,
the tile cache, the metrics and the ROS map publisher read them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

from fleetmap.change_feed import ChangeFeed
from fleetmap.codec import WireScan
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap, IntegrationResult
from fleetmap.robot_state import Receipt, RobotState
from fleetmap.tombstones import Tombstone


@dataclass
class MapEntry:
    """One map: its engine object, its robots, its change feed."""

    id: str
    gmap: GridMap
    generation: int
    robots: dict[str, RobotState] = field(default_factory=dict)
    scans_integrated: int = 0
    scans_rejected: int = 0
    #: Its change versions start at `generation` (see `MapRegistry._generations`): an event id from
    #: an earlier map of this id, or from before a restart, is below them.
    changes: ChangeFeed = field(init=False)
    created_at: float = field(default_factory=time.time)
    #: Set when the map is deleted or replaced, under its lock and the registry's (`_removing`): a
    #: worker holding the map's lock that finds it set neither applies nor journals a scan to it.
    retired: bool = False
    #: Created by a scan (auto-create) and claimed by nothing since: if every scan that reached it is
    #: refused, it is removed again (`_remove_unclaimed`), so a refused scan creates no map. Cleared
    #: once a scan of it is applied, and by `create` (PUT) or a robot's liveliness token
    #: (`set_online`), either of which would have created the map anyway.
    provisional: bool = False
    #: Scans accepted for this map (`submit`) that are neither counted as integrated nor refused yet:
    #: queued, in flight, or applied and waiting for their journal commit.
    unsettled: int = 0
    #: The entry `replace` installed in this one's place (under `MapRegistry.lock`), so an event
    #: stream can tell a map replaced under its id (it follows the new one) from a deleted one.
    replaced_by: MapEntry | None = field(default=None, repr=False)
    #: Bumped (under the registry's lock) whenever what a viewer shows of its robots changes: a robot
    #: created, forgotten, or changed in a field of `RobotState.changed`. An event stream that saw
    #: this version has nothing to send while it stays.
    live_version: int = 0
    #: The tombstones of robots it forgot (`Tombstones.forget`) that storage does not hold yet, by
    #: robot id: its next snapshot stores them in the transaction that drops those robots' rows
    #: (`MapRegistry.snapshot_all`). With a `DurableStore` only.
    unstored_stones: dict[str, Tombstone] = field(default_factory=dict)
    #: `unjournaled()` as its last snapshot stored it (or as restored at start): a change since makes
    #: a snapshot due (`MapRegistry.snapshot_all`).
    unjournaled_stored: int = 0
    #: The ids of the robots its last snapshot stored (or restored at start): a robot not among
    #: them makes a snapshot due. One made by a scan comes again from the journal, but one only a
    #: liveliness token made (`MapRegistry.set_online`) is stored by nothing else.
    robots_stored: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        self.changes = ChangeFeed(start=self.generation)

    @property
    def config(self) -> MapConfig:
        return self.gmap.config

    def robot(self, robot_id: str) -> RobotState:
        """Robot `robot_id`, created if the map has none of that id (call under the registry's lock)."""
        state = self.robots.get(robot_id)
        if state is None:
            state = self.robots[robot_id] = RobotState()
            self.touch(state)
        return state

    def touch(self, robot: RobotState) -> None:
        """Record that a field of `robot` that viewers show changed (call under the registry's lock)."""
        self.live_version += 1
        robot.changed = self.live_version

    def unjournaled(self) -> int:
        """How many scans it counted that left no journal row: refused (counted on the map, robots'
        refusals too), ignored as duplicates, or dropped by the full queue (call under the
        registry's lock). Only a snapshot stores their counts."""
        return self.scans_rejected + sum(robot.duplicates + robot.dropped for robot in self.robots.values())

    def forget(self, robot_id: str) -> None:
        """Remove robot `robot_id` and all the service knows of it (call under the registry's lock)."""
        del self.robots[robot_id]
        self.live_version += 1


#: A check a map change runs on the map it would change (None: no map of that id) under the registry's
#: lock, before it changes anything; it raises to refuse the change (the REST API's If-Match).
Expectation = Callable[[MapEntry | None], None]


@dataclass
class Job:
    """A scan waiting for integration, and who waits for its outcome (REST)."""

    map_id: str
    robot_id: str
    wire: WireScan
    generation: int
    #: time.monotonic() when the scan was queued, when it was applied to its map (readers see it
    #: from then on), and whether it was handed to the journal then (its row committed later).
    enqueued_at: float
    future: Future[IntegrationResult] | None = None
    applied_at: float | None = None
    journaled: bool = False
    #: Its entry in its publisher session's ledger, settled with the scan (`MapRegistry._settle`).
    receipt: Receipt | None = None


#: What each `IngestRejected` status means, as the ingests count their refusals (`kind`).
REFUSAL_KINDS = {200: "duplicate", 404: "no_map", 429: "too_many_robots", 503: "queue_full"}
#: The kind of the refusal of a scan submitted while the registry closes (`MapRegistry.close`).
SHUTTING_DOWN = "shutting_down"
#: The kind of the refusal of a scan the full queue deferred, taken nowhere: its caller fetches it
#: again once the queue has room (`MapRegistry.submit`'s `defer_when_full`).
DEFERRED = "deferred"


class IngestRejected(Exception):
    """A scan refused before integration: `reason` says why; `status` suggests an HTTP status."""

    def __init__(self, reason: str, status: int = 422, kind: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.status = status
        self._kind = kind

    @property
    def kind(self) -> str:
        """The refusal's kind for counters: the one given, else by status (`REFUSAL_KINDS`; `other`
        for any other status)."""
        return self._kind or REFUSAL_KINDS.get(self.status, "other")


__all__ = ["DEFERRED", "REFUSAL_KINDS", "SHUTTING_DOWN", "Expectation", "IngestRejected", "Job", "MapEntry"]
