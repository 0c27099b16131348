"""Simulated robots publishing to a fleetmap service over Zenoh, in real time.

    fleetmap sim --robots 3 --map sim --seed 1 --rate 10

All robots explore one synthetic floor plan (`fleetmap.sim.generate_floorplan(seed)`, 40 x 30 m) as
`fleetmap.sim.SimulatedRobot`s with exact, noise-free lidars (1081 beams over 270 degrees, 30 m by
default). Each robot is its own `ScanPublisher` (its own Zenoh session and liveliness token, robot
ids `sim-1`, `sim-2`, ...) driven by its own thread: every 1/rate s it advances its simulation by
1/rate s and publishes the scan taken there, with seq 0, 1, 2, ... and the wall-clock stamp. A robot
that falls behind (a busy machine) does not burst to catch up: it resumes the schedule from now,
and counts the scans it skipped (`SimResult.skipped`; `fleetmap sim` warns of them).

The robots start once the service is reachable (they wait for it), run for `seconds` (None: until
stopped) and leave when stopped; scans published while the service is unreachable are kept in each
publisher's backlog (`ScanPublisher`) and delivered when it is back, as a real robot's would be,
while the robots keep moving.
"""

from __future__ import annotations

import math
import os
import resource
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from fleetmap.scan import MAX_BEAMS
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.sim.floorplan import FloorPlan
from fleetmap.wire import is_valid_id

from .delivery import DeliveryReport
from .publisher import (
    CLOSE_WAIT_S,
    DeliveryUnsupported,
    Encoding,
    ScanPublisher,
    check_period,
    check_timeouts,
)


class SimError(RuntimeError):
    """The simulation could not run (no service reachable in time), or a robot of it stopped on an
    error (the others were stopped with it)."""


@dataclass
class SimResult:
    robots: list[str]
    published: dict[str, int] = field(default_factory=dict)  # scans handed to a connected session
    #: Scans kept for re-delivery while disconnected (`ScanPublisher.backlogged`).
    backlogged: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)  # scans given up (`ScanPublisher.dropped`)
    #: Scans never taken because the robot fell behind its rate (a machine too busy for the fleet):
    #: their times passed while it was still busy with earlier ones, and it resumed from then.
    skipped: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    #: With `confirm_timeout`: what each robot's `ScanPublisher.flush` learned; a robot whose flush
    #: got an error answer is in `confirm_errors` instead, with it.
    delivery: dict[str, DeliveryReport] = field(default_factory=dict)
    confirm_errors: dict[str, str] = field(default_factory=dict)
    #: Why nothing could be confirmed: the service answers no delivery query (older than that).
    unconfirmable: str | None = None

    @property
    def confirmed(self) -> bool:
        """Whether every robot's scans were confirmed integrated (False when none was asked)."""
        reports = self.delivery.values()
        return bool(reports) and not self.confirm_errors and all(report.confirmed for report in reports)

    @property
    def total(self) -> int:
        """Scans published: sent, or kept for re-delivery."""
        return sum(self.published.values()) + sum(self.backlogged.values())


def robot_ids(count: int, prefix: str = "sim") -> list[str]:
    """The ids of `count` simulated robots: prefix-1, prefix-2, ..."""
    return [f"{prefix}-{k + 1}" for k in range(count)]


#: File descriptors one simulated robot holds: its Zenoh session's TCP socket and the POSIX
#: shared-memory segment zenoh-python makes for each session (measured: 2.1 per robot with 100).
FDS_PER_ROBOT = 2
#: Threads one simulated robot runs: its own (`_drive`), its publisher's opener and link watcher,
#: and its publisher's fetch watcher (measured: 3.1 per robot with 100).
THREADS_PER_ROBOT = 3
#: The fastest a simulated robot drives, m/s (180 km/h: past any robot that maps with a 2D laser).
#: Its route is planned again as it reaches each end, so a step's work grows with the metres it
#: drives: at 1e9 m/s a step took a second of re-planning, and the sim blamed a busy machine.
MAX_SPEED = 50.0
#: Robots a fleetmap service takes at once by default: Zenoh's `transport/unicast/max_sessions`.
SERVICE_SESSIONS = 1000
#: File descriptors and threads the rest of the process needs (interpreter, Zenoh's runtime).
PROCESS_RESERVE = 64


def _read_int(path: str) -> int | None:
    """The integer in the file at `path` (a /proc/sys setting), None where there is none."""
    try:
        with open(path, encoding="ascii") as file:
            return int(file.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def check_capacity(robots: int) -> None:
    """ValueError unless this process may open the file descriptors and start the threads that
    `robots` simulated robots need (`FDS_PER_ROBOT`, `THREADS_PER_ROBOT` each, `PROCESS_RESERVE`
    besides); the message names the limit and what to change. Past them the robots beyond could not
    open their Zenoh sessions ("OS error 24", reported as no service reachable) and waited for ever,
    or could not start their threads."""
    fds = robots * FDS_PER_ROBOT + PROCESS_RESERVE
    threads = robots * THREADS_PER_ROBOT + PROCESS_RESERVE
    thread_limits = {
        "kernel.pid_max": _read_int("/proc/sys/kernel/pid_max"),
        "kernel.threads-max": _read_int("/proc/sys/kernel/threads-max"),
    }
    nproc, _ = resource.getrlimit(resource.RLIMIT_NPROC)
    if nproc != resource.RLIM_INFINITY and os.geteuid() != 0:  # root is not held to `ulimit -u`
        thread_limits["ulimit -u"] = nproc
    for name, limit in thread_limits.items():
        if limit is not None and threads > limit:
            most = max(0, limit - PROCESS_RESERVE) // THREADS_PER_ROBOT
            raise ValueError(
                f"{robots} robots need about {threads} threads ({THREADS_PER_ROBOT} per robot) but this "
                f"machine allows {limit} ({name}): run at most {most} robots per process (several "
                "processes on different maps, or machines), or raise it"
            )
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and fds > soft:
        hard_text = "unlimited" if hard == resource.RLIM_INFINITY else str(hard)
        raise ValueError(
            f"{robots} robots need about {fds} file descriptors ({FDS_PER_ROBOT} per robot: its Zenoh "
            f"session's socket and shared-memory segment) but this process may open {soft} (ulimit -n; "
            f"hard limit {hard_text}): raise it (ulimit -n {fds}, as root if past the hard limit) or run "
            f"at most {max(0, soft - PROCESS_RESERVE) // FDS_PER_ROBOT} robots per process"
        )


def check_fleet(
    robots: int,
    rate: float,
    seconds: float | None,
    beams: int = 1081,
    speed: float = 1.0,
    seed: int = 1,
    names: Mapping[str, str] | None = None,
) -> None:
    """ValueError unless `run_sim` can run `robots` robots at `rate` scans/s for `seconds` (None: no
    limit), with lidars of `beams` beams, at `speed` m/s, on the floor plan of `seed`: at least one
    robot, a finite rate above 0 whose period a thread can wait (`check_period`), seconds not
    negative, 1 to `MAX_BEAMS` beams (a scan holds no more), a speed from 0 to `MAX_SPEED`, a seed not
    negative (numpy's generators take no other), and no more robots than this process's file
    descriptors and threads allow (`check_capacity`). The message calls each value by its name in
    `names` (`fleetmap sim` passes its options', `SIM_OPTIONS`), else by its parameter's."""

    def name(parameter: str) -> str:
        return (names or {}).get(parameter, parameter)

    if seed < 0:  # was numpy's "expected non-negative integer", from inside the floor plan's draw
        raise ValueError(f"{name('seed')} must be >= 0, got {seed}")
    if robots < 1:
        raise ValueError(f"{name('robots')} must be >= 1, got {robots}")
    if not (rate > 0.0 and rate != float("inf")):
        raise ValueError(f"{name('rate')} must be a finite number > 0, got {rate}")
    check_period(1.0 / rate, f"{name('rate')} {rate:g}")
    if seconds is not None and not seconds >= 0.0:
        raise ValueError(f"{name('seconds')} must be >= 0, got {seconds}")
    # Checked here, not at the first scan: --beams 0 let every robot thread die with a traceback,
    # and the command still printed its summary ("published 0 scans") and exited 0.
    if not 1 <= beams <= MAX_BEAMS:
        raise ValueError(f"{name('beams')} must be 1 to {MAX_BEAMS}, got {beams}")
    if not (math.isfinite(speed) and speed >= 0.0):
        raise ValueError(f"{name('speed')} must be finite and >= 0, got {speed}")
    if speed > MAX_SPEED:
        raise ValueError(f"{name('speed')} must be at most {MAX_SPEED:g} m/s, got {speed:g}")
    check_capacity(robots)


def run_sim(
    robots: int,
    *,
    map_id: str = "sim",
    seed: int = 1,
    rate: float = 10.0,
    seconds: float | None = None,
    connect: Sequence[str] | None = None,
    zenoh_config: str | None = None,
    encoding: Encoding = "binary",
    beams: int = 1081,
    range_max: float = 30.0,
    speed: float = 1.0,
    prefix: str = "sim",
    wait_timeout: float | None = None,
    stop: threading.Event | None = None,
    on_waiting: Callable[[ScanPublisher], None] | None = None,
    plan: FloorPlan | None = None,
    confirm_timeout: float | None = None,
) -> SimResult:
    """Run `robots` simulated robots on `map_id` until `seconds` pass (from when they start moving;
    None or inf: no limit) or `stop` is set. Blocks; returns what each robot published.

    `seed` picks the floor plan (`generate_floorplan(seed)`, unless `plan` is given) and the robots'
    start poses and routes (robot k uses seed `seed * 1000 + k`). `rate` is scans per second per
    robot. `wait_timeout`: seconds to wait for the service before starting (None: forever; raises
    `SimError` when it passes); `on_waiting(publisher)` is called once if that takes over a second.
    `confirm_timeout`: once the robots stopped, wait at most that many seconds (the robots asked at
    once) for the service to confirm their scans (`ScanPublisher.flush`, into `SimResult.delivery`);
    None (default): ask nothing. Raises ValueError for bad arguments (e.g. a robot id that `prefix`
    makes invalid, a timeout below 0 or NaN).
    """
    check_fleet(robots, rate, seconds, beams, speed, seed)
    check_timeouts(wait_timeout=wait_timeout, confirm_timeout=confirm_timeout)
    stop = stop or threading.Event()
    ids = robot_ids(robots, prefix)
    # All of them before any robot connects: the last id is the longest, and one too long raised
    # only when its publisher was made, after the robots before it had joined the map.
    for rid in (ids[0], ids[-1]):
        if not is_valid_id(rid):
            raise ValueError(
                f"robot id {rid!r} (prefix {prefix!r}) is invalid: use 1 to 64 characters from "
                "A-Z a-z 0-9 _ -"
            )
    if not is_valid_id(map_id):
        raise ValueError(f"map_id {map_id!r} is invalid: use 1 to 64 characters from A-Z a-z 0-9 _ -")
    floor = plan if plan is not None else generate_floorplan(seed)

    def simulated(k: int) -> SimulatedRobot:
        return SimulatedRobot(floor, seed=seed * 1000 + k, scan_rate=rate, num_beams=beams,
                              range_max=range_max, speed=speed)  # fmt: skip

    sims = [simulated(k) for k in range(robots)]
    # The robots' compiled route planner and lidar load from numba's cache at their first call
    # (0.3 to 0.6 s): on the robots' clock, every run started that far behind its rate, and the demo
    # and `fleetmap sim` warned of scans skipped on "a machine too busy" for even one robot. A copy
    # of the first robot (the others keep their own motion) takes its first scan before the clock
    # starts, and before the robots' sessions take their file descriptors (numba opens files).
    simulated(0).tick()
    result = SimResult(robots=ids)
    publishers: list[ScanPublisher] = []
    try:
        for rid in ids:
            publishers.append(
                ScanPublisher(map_id, rid, connect=connect, encoding=encoding, zenoh_config=zenoh_config)
            )
        _wait_all(publishers, wait_timeout, stop, on_waiting)
        started = time.monotonic()
        # Infinite seconds are no limit, as None: a deadline of inf broke the count of the scans a
        # robot behind its rate skipped up to it (OverflowError: "cannot convert float infinity").
        deadline = None if seconds is None or math.isinf(seconds) else started + seconds
        failures: dict[str, BaseException] = {}
        threads = [
            threading.Thread(
                target=_drive_or_stop,
                args=(sim, pub, rate, deadline, stop, failures, result.skipped),
                name=f"fleetmap-{pub.robot_id}",
                daemon=True,
            )
            for sim, pub in zip(sims, publishers, strict=True)
        ]
        for t in threads:
            t.start()
        try:
            # The main thread only waits, in short steps so that Ctrl-C (KeyboardInterrupt) gets through.
            while any(t.is_alive() for t in threads):
                stop.wait(0.1)
                if stop.is_set():
                    break
        finally:
            stop.set()
            for t in threads:
                t.join()
        result.seconds = time.monotonic() - started
        if failures:
            # A robot's thread that died printed its traceback, and the command then said "published
            # N scans" and exited 0 as if all had gone well.
            robot, exc = next(iter(failures.items()))
            raise SimError(f"robot {robot} stopped: {type(exc).__name__}: {exc} (the others were stopped)")
        if confirm_timeout is not None:
            _confirm(publishers, confirm_timeout, result)
    finally:
        for pub in publishers:
            result.published[pub.robot_id] = pub.published
            result.backlogged[pub.robot_id] = pub.backlogged
            result.dropped[pub.robot_id] = pub.dropped
        _close_all(publishers)
    return result


def _close_all(publishers: list[ScanPublisher]) -> None:
    """Close every publisher, all at once. A publisher that never connected waits in `close` for
    its connection attempt to end (about a second): closed one after another, 300 robots that
    found no service took four minutes to give up after `--wait-timeout`."""
    closers = [
        threading.Thread(target=pub.close, name=f"fleetmap-close-{pub.robot_id}", daemon=True)
        for pub in publishers
    ]
    for closer in closers:
        closer.start()
    for closer in closers:
        closer.join()


def _confirm(publishers: list[ScanPublisher], timeout: float, result: SimResult) -> None:
    """Each robot's delivery report (`ScanPublisher.flush`), all robots asked at once, each for at
    most `timeout` seconds."""

    def ask(pub: ScanPublisher) -> None:
        try:
            result.delivery[pub.robot_id] = pub.flush(timeout)
        except DeliveryUnsupported as exc:
            result.unconfirmable = str(exc)
        except RuntimeError as exc:  # an error answer, or one that is not fleetmap's
            result.confirm_errors[pub.robot_id] = str(exc)

    askers = [threading.Thread(target=ask, args=(pub,), daemon=True) for pub in publishers]
    for asker in askers:
        asker.start()
    try:
        for asker in askers:
            asker.join()
    except BaseException:  # Ctrl-C: stop asking. Closed, a publisher's flush ends at once, and its
        # thread must not be left inside a Zenoh call as the program exits (that aborts it).
        for pub in publishers:
            pub.close()
        for asker in askers:
            asker.join(CLOSE_WAIT_S)
        raise


#: How Zenoh's errors end when the process has no file descriptor left (EMFILE), e.g. "Unable to
#: create POSIX shm segment: OS error 24".
_OUT_OF_DESCRIPTORS = "os error 24"


def _check_descriptors(publishers: list[ScanPublisher]) -> None:
    """SimError if a publisher could not open its session for want of file descriptors. Any of them,
    not only the one waited for: the first robots may wait for a service not up yet while the last
    ones failed. Not the service's doing, and not over by waiting: the sim retried for ever (without
    --wait-timeout), then said "no fleetmap service reachable" with the service up."""
    for pub in publishers:
        error = pub.last_connect_error or ""
        if _OUT_OF_DESCRIPTORS in error.lower():
            soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
            raise SimError(
                f"robot {pub.robot_id} could not open its Zenoh session: this process ran out of file "
                f"descriptors (ulimit -n {soft}; {error}): raise it, or run fewer robots"
            )


def _wait_all(
    publishers: list[ScanPublisher],
    timeout: float | None,
    stop: threading.Event,
    on_waiting: Callable[[ScanPublisher], None] | None,
) -> None:
    deadline = None if timeout is None else time.monotonic() + timeout
    told = False
    started = time.monotonic()
    for pub in publishers:
        while not pub.wait_connected(0.1):
            if stop.is_set():
                return
            now = time.monotonic()
            if not told and now - started >= 1.0 and on_waiting is not None:
                on_waiting(pub)
                told = True
            _check_descriptors(publishers)
            if deadline is not None and now >= deadline:
                reason = f" ({pub.last_connect_error})" if pub.last_connect_error else ""
                where = ", ".join(pub.shown_endpoints)
                connected = sum(other.connected for other in publishers)
                if 0 < connected < len(publishers):
                    # The service is up, but refuses the others' sessions just as an absent one
                    # would (a timeout): its Zenoh router takes only so many. (All connected: a
                    # router with no service behind it, whose subscriber is what they wait for.)
                    raise SimError(
                        f"only {connected} of {len(publishers)} robots could connect to the service at "
                        f"{where} within {timeout:g} s{reason}: its Zenoh router takes no more sessions? "
                        f"(at most {SERVICE_SESSIONS} unless its --zenoh-config raises "
                        "transport/unicast/max_sessions: docs/protocol.md)"
                    )
                raise SimError(f"no fleetmap service reachable at {where} within {timeout:g} s{reason}")


def _drive_or_stop(
    robot: SimulatedRobot,
    pub: ScanPublisher,
    rate: float,
    deadline: float | None,
    stop: threading.Event,
    failures: dict[str, BaseException],
    skipped: dict[str, int],
) -> None:
    """`_drive`; an error ends the whole simulation (`stop`), recorded in `failures` by robot id.
    The scans it skipped for falling behind go to `skipped`, by robot id."""
    try:
        skipped[pub.robot_id] = 0
        _drive(robot, pub, rate, deadline, stop, skipped)
    except Exception as exc:
        failures.setdefault(pub.robot_id, exc)
        stop.set()


def _drive(
    robot: SimulatedRobot,
    pub: ScanPublisher,
    rate: float,
    deadline: float | None,
    stop: threading.Event,
    skipped: dict[str, int],
) -> None:
    """One robot's loop: tick, publish, wait for the next period. Counts in `skipped[robot id]` the
    scans whose times passed while it was behind."""
    period = 1.0 / rate
    due = time.monotonic()
    while not stop.is_set():
        if deadline is not None and due >= deadline:
            return
        pub.publish(robot.tick())
        due += period
        now = time.monotonic()
        if due < now - period:
            # Fell behind by more than a period: don't burst, resume with the scan due now (the
            # schedule's slot in progress). The slots passed meanwhile (before the deadline) are
            # never taken: counted, or the summary's total looked like the rate was kept.
            behind = math.floor((now - due) / period)
            if deadline is not None:
                behind = min(behind, max(0, math.ceil((deadline - due) / period)))
            skipped[pub.robot_id] += behind
            due += behind * period
        # Not past the deadline: at --rate 0.1 a robot slept its whole 10 s period through it, so
        # --seconds 15 ran 20 s.
        stop.wait(max(0.0, (due if deadline is None else min(due, deadline)) - now))


__all__ = ["SimError", "SimResult", "check_capacity", "robot_ids", "run_sim"]
