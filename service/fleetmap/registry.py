"""The map registry: every map the service holds, the robots that feed them, and the integration
workers. This is where the service's state lives.

Scans arrive from Zenoh callbacks and REST requests through `submit`, which never blocks: it checks
the robot's sequence number (duplicates are ignored, gaps counted as lost) and puts the scan on a
per-robot FIFO of a `FairQueue`. Worker threads take scans round-robin across robots, one scan of
a robot at a time (so each robot's scans are integrated in order), plan them without any lock and
apply them under the map's lock. When the robot's FIFO is full, the NEWEST scan is refused and
counted as `dropped` (REST callers get 503 and may retry); robots that must not lose scans publish
with Zenoh's blocking congestion control, and the service is sized to keep up.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field

from fleetmap.changes import ChangeFeed
from fleetmap.codec import WireScan
from fleetmap.config import MapConfig
from fleetmap.fair_queue import FairQueue, QueueClosed
from fleetmap.grid_map import GridMap, IntegrationResult
from fleetmap.scan import Pose2D, ScanError
from fleetmap.tiles import TileLimitError
from fleetmap.wire import is_valid_id

log = logging.getLogger("fleetmap.registry")

#: Poses kept per robot for viewers' trails.
TRAIL_LENGTH = 200


class MapNotFound(KeyError):
    def __str__(self) -> str:
        return f"no map {self.args[0]!r}"


class MapConflict(ValueError):
    """PUT of a configuration that differs from an existing map's."""


class InvalidId(ValueError):
    pass


@dataclass
class RobotState:
    """What the service knows of one robot on one map."""

    online: bool = False
    last_pose: Pose2D | None = None
    last_seq: int | None = None  # highest seq accepted (enqueued)
    last_stamp: float | None = None
    scans_integrated: int = 0
    scans_rejected: int = 0
    last_error: str | None = None
    lost: int = 0
    duplicates: int = 0
    dropped: int = 0
    trail: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_LENGTH))


@dataclass
class MapEntry:
    """One map: its engine object, its robots, its change feed."""

    id: str
    gmap: GridMap
    generation: int
    robots: dict[str, RobotState] = field(default_factory=dict)
    scans_integrated: int = 0
    scans_rejected: int = 0
    changes: ChangeFeed = field(default_factory=ChangeFeed)
    created_at: float = field(default_factory=time.time)

    @property
    def config(self) -> MapConfig:
        return self.gmap.config

    def robot(self, robot_id: str) -> RobotState:
        state = self.robots.get(robot_id)
        if state is None:
            state = self.robots[robot_id] = RobotState()
        return state


@dataclass
class Job:
    """A scan waiting for integration, and who waits for its outcome (REST)."""

    map_id: str
    robot_id: str
    wire: WireScan
    generation: int
    enqueued_at: float
    future: Future[IntegrationResult] | None = None


class IngestRejected(Exception):
    """A scan refused before integration: `reason` says why; `status` suggests an HTTP status."""

    def __init__(self, reason: str, status: int = 422) -> None:
        super().__init__(reason)
        self.reason = reason
        self.status = status


class MapRegistry:
    """All maps, their robots and the integration workers."""

    def __init__(
        self,
        default_config: MapConfig | None = None,
        auto_create: bool = True,
        workers: int = 2,
        queue_per_robot: int = 64,
        queue_total: int = 8192,
        on_integrated: Callable[[MapEntry, Job, IntegrationResult, float], None] | None = None,
    ) -> None:
        self.default_config = default_config or MapConfig()
        self.auto_create = auto_create
        self.maps: dict[str, MapEntry] = {}
        self.lock = threading.RLock()  # guards `maps` and every RobotState / counter
        self.queue: FairQueue[Job] = FairQueue(queue_per_robot, queue_total)
        self._generations = itertools.count(1)
        self._on_integrated = on_integrated
        self._workers = [
            threading.Thread(target=self._work, name=f"fleetmap-integrate-{k}", daemon=True)
            for k in range(workers)
        ]
        self._started = False

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> None:
        if not self._started:
            self._started = True
            for t in self._workers:
                t.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop taking scans, finish the queued ones, stop the workers."""
        self.queue.close()
        for t in self._workers:
            if t.is_alive():
                t.join(timeout)

    # -- maps ------------------------------------------------------------------------------------

    def create(self, map_id: str, config: MapConfig | None = None) -> tuple[MapEntry, bool]:
        """Create a map, or return the existing one if its configuration is the same.
        Returns (entry, created). Raises MapConflict for a different configuration."""
        _check_id("map id", map_id)
        config = config or self.default_config
        with self.lock:
            existing = self.maps.get(map_id)
            if existing is not None:
                if existing.config != config:
                    raise MapConflict(
                        f"map {map_id!r} exists with a different configuration; delete it first"
                    )
                return existing, False
            entry = MapEntry(map_id, GridMap(config), next(self._generations))
            self.maps[map_id] = entry
            log.info("created map %s", map_id)
            return entry, True

    def get(self, map_id: str) -> MapEntry:
        with self.lock:
            entry = self.maps.get(map_id)
        if entry is None:
            raise MapNotFound(map_id)
        return entry

    def delete(self, map_id: str) -> None:
        with self.lock:
            if self.maps.pop(map_id, None) is None:
                raise MapNotFound(map_id)
        self.queue.drop_source(lambda source: source[0] == map_id)
        log.info("deleted map %s", map_id)

    def list(self) -> list[MapEntry]:
        with self.lock:
            return list(self.maps.values())

    # -- ingest ----------------------------------------------------------------------------------

    def submit(self, map_id: str, robot_id: str, wire: WireScan, wait: bool = False) -> Future | None:
        """Queue a decoded scan for integration, never blocking.

        Returns a Future of the IntegrationResult when `wait`, else None. Raises IngestRejected for
        a duplicate (status 200: nothing to do), an unknown map without auto-create (404), or a full
        queue (503). Every refusal is counted on the robot.
        """
        _check_id("map id", map_id)
        _check_id("robot id", robot_id)
        with self.lock:
            entry = self.maps.get(map_id)
            if entry is None:
                if not self.auto_create:
                    raise IngestRejected(f"no map {map_id!r} (auto-create is off)", 404)
                entry, _ = self.create(map_id)
            robot = entry.robot(robot_id)
            seq = wire.seq
            if robot.last_seq is not None and seq <= robot.last_seq and seq != 0:
                robot.duplicates += 1
                raise IngestRejected(f"duplicate seq {seq} (last accepted {robot.last_seq})", 200)
            if robot.last_seq is not None and seq > robot.last_seq + 1:
                robot.lost += seq - robot.last_seq - 1
            # seq 0 restarts the sequence (a robot that restarted): accept it and go on from it.
            # Recorded before the queue is tried so a dropped scan is not also counted as lost.
            robot.last_seq = seq
            job = Job(map_id, robot_id, wire, entry.generation, time.monotonic())
            if wait:
                job.future = Future()
            if not self.queue.put((map_id, robot_id), job):
                robot.dropped += 1
                raise IngestRejected("ingest queue full: scan dropped", 503)
            return job.future

    def reject(self, map_id: str, robot_id: str, reason: str) -> None:
        """Count a message that could not even be decoded, on its robot if the ids are valid."""
        if not (is_valid_id(map_id) and is_valid_id(robot_id)):
            return
        with self.lock:
            entry = self.maps.get(map_id)
            if entry is None:
                return
            robot = entry.robot(robot_id)
            robot.scans_rejected += 1
            robot.last_error = reason
            entry.scans_rejected += 1

    def set_online(self, map_id: str, robot_id: str, online: bool) -> None:
        """A robot's liveliness token appeared or went away."""
        if not (is_valid_id(map_id) and is_valid_id(robot_id)):
            return
        with self.lock:
            entry = self.maps.get(map_id)
            if entry is None:
                if not (online and self.auto_create):
                    return
                entry, _ = self.create(map_id)
            entry.robot(robot_id).online = online

    def iter_robots(self) -> Iterator[tuple[str, str, RobotState]]:
        with self.lock:
            for entry in self.maps.values():
                for robot_id, state in entry.robots.items():
                    yield entry.id, robot_id, state

    # -- integration -----------------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            try:
                got = self.queue.get()
            except QueueClosed:
                return
            if got is None:
                continue
            source, job = got
            try:
                self._integrate(job)
            except Exception as exc:  # a bug must not kill the worker; it is logged and counted
                log.exception("integration of %s/%s seq %s failed", job.map_id, job.robot_id, job.wire.seq)
                self._finish_rejected(job, f"internal error: {exc}")
            finally:
                self.queue.done(source)

    def _integrate(self, job: Job) -> None:
        with self.lock:
            entry = self.maps.get(job.map_id)
        if entry is None or entry.generation != job.generation:
            if job.future:
                job.future.set_exception(IngestRejected(f"map {job.map_id!r} was deleted", 404))
            return
        started = time.perf_counter()
        try:
            plan = entry.gmap.plan(job.wire.scan)
            result = entry.gmap.apply(plan)
        except (ScanError, TileLimitError) as exc:
            self._finish_rejected(job, str(exc))
            return
        elapsed = time.perf_counter() - started
        entry.changes.record(result.changed_tiles)
        pose = job.wire.scan.pose
        with self.lock:
            entry.scans_integrated += 1
            robot = entry.robot(job.robot_id)
            robot.scans_integrated += 1
            robot.last_pose = pose
            robot.last_stamp = job.wire.stamp
            robot.trail.append((pose.x, pose.y, pose.theta))
        if self._on_integrated is not None:
            self._on_integrated(entry, job, result, elapsed)
        if job.future:
            job.future.set_result(result)

    def _finish_rejected(self, job: Job, reason: str) -> None:
        with self.lock:
            entry = self.maps.get(job.map_id)
            if entry is not None and entry.generation == job.generation:
                robot = entry.robot(job.robot_id)
                robot.scans_rejected += 1
                robot.last_error = reason
                entry.scans_rejected += 1
        if job.future and not job.future.done():
            job.future.set_exception(IngestRejected(reason, 422))

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Wait until the queue is empty and no scan is in flight (for tests and shutdown)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.queue.depth() == 0 and not self.queue._busy:  # noqa: SLF001
                return True
            time.sleep(0.005)
        return False


def _check_id(what: str, value: str) -> None:
    if not is_valid_id(value):
        raise InvalidId(f"{what} {value!r} must match [A-Za-z0-9_-]{{1,64}}")
