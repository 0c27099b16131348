"""Stopping the real service while work is in flight: signals that come twice or late, uploads cut
off by the stop. Each test starts `python -m fleetmap.server` as a process (durable storage), stops
it with real signals, and checks the exit code, the log and what a restart on the same data
directory finds."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import httpx
from service_process import RobotProcess, ServiceProcess, wait_for


def integrated(base_url: str, map_id: str) -> dict[str, int]:
    """Each robot's scans the service reports integrated on `map_id` ({} while the map does not exist)."""
    r = httpx.get(f"{base_url}/maps/{map_id}", timeout=10)
    if r.status_code == 404:
        return {}
    return {robot: s["scans_integrated"] for robot, s in r.json()["stats"]["robots"].items()}


def assert_clean_log(svc: ServiceProcess) -> None:
    logs = svc.logs()
    assert "Traceback" not in logs and " ERROR " not in logs, logs


def publishing_service(tmp_path: Path, data_dir: Path) -> tuple[ServiceProcess, list[RobotProcess]]:
    """A service on `data_dir` with two robots publishing to map `m` (both already integrated)."""
    svc = ServiceProcess(tmp_path, ["--data-dir", str(data_dir)]).start()
    robots = [
        RobotProcess(
            svc.zenoh_endpoint, "m", f"r{k}", log_dir=tmp_path, sim=k, count=3000, rate=100, linger=-1
        )
        for k in range(2)
    ]
    for robot in robots:
        robot.start()
    wait_for(lambda: len(integrated(svc.base_url, "m")) == 2, timeout=60, what="both robots integrated")
    return svc, robots


def assert_kept(tmp_path: Path, data_dir: Path, before: dict[str, int]) -> None:
    """A restart on `data_dir` holds every scan reported integrated in `before`."""
    with ServiceProcess(tmp_path, ["--data-dir", str(data_dir)]) as restarted:
        after = integrated(restarted.base_url, "m")
        assert all(after.get(robot, 0) >= n for robot, n in before.items()), (before, after)
        assert restarted.stop() == 0


def stop_and_check(tmp_path: Path, data_dir: Path, send: Callable[[subprocess.Popen[bytes]], None]) -> None:
    """Start a service with robots publishing, `send` it its signals, and check that it exited 0
    with a clean log and that a restart holds every scan reported integrated before."""
    svc, robots = publishing_service(tmp_path, data_dir)
    try:
        before = integrated(svc.base_url, "m")
        assert svc.proc is not None
        send(svc.proc)
        assert svc.proc.wait(20) == 0, svc.logs()
        assert_clean_log(svc)
    finally:
        for robot in robots:
            robot.stop()
        svc.stop()
    assert_kept(tmp_path, data_dir, before)


def test_a_second_ctrl_c_does_not_cut_the_shutdown_short(tmp_path: Path) -> None:
    """Ctrl-C twice (and SIGTERM then Ctrl-C): uvicorn takes a second SIGINT during its shutdown as
    "force quit", which skipped the ASGI lifespan shutdown and had the event loop cancel it, logging
    an ERROR with a CancelledError traceback. The graceful shutdown is bounded (3 s) anyway: the
    second signal must change nothing, and the process exits 0 with nothing lost."""
    for first in (signal.SIGINT, signal.SIGTERM):

        def twice(proc: subprocess.Popen[bytes], first: signal.Signals = first) -> None:
            proc.send_signal(first)
            time.sleep(0.05)
            proc.send_signal(signal.SIGINT)

        stop_and_check(tmp_path, tmp_path / "data", twice)


def test_signals_arriving_while_the_service_stops_do_not_kill_it(tmp_path: Path) -> None:
    """SIGTERM, then SIGTERM or SIGHUP again and again until the process is gone (a user's repeated
    `kill`, systemd's SendSIGHUP=, a log rotation's HUP): each must be harmless to the end. `run`
    restored the default handlers once it had stopped, and a signal in the ~50 ms before the process
    exited killed it (exit -15 / -1 instead of 0)."""
    for late in (signal.SIGTERM, signal.SIGHUP):

        def repeatedly(proc: subprocess.Popen[bytes], late: signal.Signals = late) -> None:
            proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + 20
            while proc.poll() is None and time.monotonic() < deadline:
                try:
                    proc.send_signal(late)
                except ProcessLookupError:  # exited between poll and kill
                    break
                time.sleep(0.005)

        stop_and_check(tmp_path, tmp_path / "data", repeatedly)
