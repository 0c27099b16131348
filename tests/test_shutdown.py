"""Stopping the real service while work is in flight: signals that come twice or late, uploads cut
off by the stop, requests still running when the graceful wait ends. Each test starts `python -m
fleetmap.server` as a process, stops it with real signals, and checks the exit code and the log (and,
with durable storage, what a restart on the same data directory finds)."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import signal
import socket
import sqlite3
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
from service_process import RobotProcess, ServiceProcess, reaped, wait_for

from fleetmap.config import MapConfig
from fleetmap.database import DB_NAME
from fleetmap.grid_map import GridMap
from fleetmap.log_format import ShutdownCutoffLog
from fleetmap.persistence import DurableStore
from fleetmap.scan import Scan
from fleetmap.storage_format import scan_to_blob


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


def test_a_request_still_running_when_the_graceful_wait_ends_gets_503(tmp_path: Path) -> None:
    """An upload still trickling in when uvicorn's graceful shutdown runs out (3 s) is cancelled.
    uvicorn answered it 500 "Internal Server Error" in plain text and logged an ERROR with a
    CancelledError traceback, as for a bug, on a routine restart. It gets 503 JSON with Retry-After
    (retry it on the restarted service), and the log one WARNING line naming the request."""
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        sock = socket.create_connection(("127.0.0.1", svc.port), timeout=20)
        head = (
            b"PUT /maps/m/snapshot HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/octet-stream\r\n"
            b"Content-Length: 100000\r\n\r\n"
        )
        sock.sendall(head + b"x" * 1000)
        answered = threading.Event()

        def trickle() -> None:  # a slow client: 50 bytes a second, never the whole body
            while not answered.wait(0.2):
                try:
                    sock.sendall(b"x" * 10)
                except OSError:
                    return

        threading.Thread(target=trickle, daemon=True).start()
        time.sleep(0.5)
        assert svc.proc is not None
        svc.proc.send_signal(signal.SIGTERM)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
        answered.set()
        sock.close()
        assert svc.proc.wait(20) == 0, svc.logs()
    head_part, _, body = answer.partition(b"\r\n\r\n")
    assert head_part.startswith(b"HTTP/1.1 503 "), answer
    assert b"\r\nretry-after: 1" in head_part.lower(), answer
    assert "shutting down" in json.loads(body)["detail"]
    line = "WARNING fleetmap.api: shutdown: PUT /maps/m/snapshot was still running; answered 503"
    assert line in svc.logs()
    assert_clean_log(svc)


def test_uvicorns_lines_about_cancelled_requests_fit_a_routine_restart() -> None:
    """The lines uvicorn logs when its graceful shutdown runs out: its count of cancelled requests
    (an ERROR, even with none: a slow client still reading a finished answer) is a WARNING; its
    traceback of a request's cancellation is dropped (`ShutdownCutoff` logged the request); any other
    exception it logs is kept as it is."""
    cutoff = ShutdownCutoffLog()

    def record(msg: str, args: tuple[object, ...], exc: BaseException | None) -> logging.LogRecord:
        info = (type(exc), exc, None) if exc is not None else None
        return logging.LogRecord("uvicorn.error", logging.ERROR, __file__, 0, msg, args, info)

    count = record("Cancel %s running task(s), timeout graceful shutdown exceeded", (2,), None)
    assert cutoff.filter(count) and count.levelno == logging.WARNING and count.levelname == "WARNING"
    assert count.getMessage() == "shutdown: the HTTP connections still open are closed (2 request(s) cut off)"
    cancelled = record("Exception in ASGI application\n", (), asyncio.CancelledError("graceful shutdown"))
    assert not cutoff.filter(cancelled)
    bug = record("Exception in ASGI application\n", (), RuntimeError("a real bug"))
    assert cutoff.filter(bug) and bug.levelno == logging.ERROR


def test_a_signal_during_the_restore_opens_nothing_and_saves_the_restored_maps(tmp_path: Path) -> None:
    """SIGTERM while the stored maps are restored (a long journal takes 10-20 s a map): the service
    finished the restore and then went on starting, opened its Zenoh session (robots could connect
    and send scans for a moment) and logged where it served, before it stopped. Now it opens
    nothing once the restore is done, snapshots the maps as restored (the next start replays no
    journal) and exits 0."""
    data = tmp_path / "data"
    store = DurableStore(data)
    store.map_created("m", GridMap(MapConfig())).result()
    store.close()
    rng = np.random.default_rng(3)
    rows = []
    for seq in range(6000):  # journal rows as a crash leaves them: seconds to replay
        ranges = rng.uniform(0.5, 12.0, 1081)
        pose = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3))
        scan = Scan.from_fan(pose, -2.35, 4.7 / 1080, ranges, 0.05, 30.0)
        rows.append(("m", "r", seq, 0.0, scan_to_blob(scan)))
    with sqlite3.connect(data / DB_NAME) as conn:
        conn.executemany(
            "INSERT INTO journal (map_id, robot_id, seq, stamp, scan) VALUES (?, ?, ?, ?, ?)", rows
        )
    svc = ServiceProcess(tmp_path, ["--data-dir", str(data)])
    with open(svc.log_path, "wb") as log:
        proc = subprocess.Popen(svc.args, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    with reaped(proc):  # type: ignore[arg-type]  # (a bytes Popen; reaped only polls and kills)
        wait_for(lambda: "engine ready" in svc.logs(), timeout=120, what="the restore under way")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(120) == 0, svc.logs()
    logs = svc.logs()
    assert re.search(r"restored 1 map\(s\) in [0-9.]+ s: 16 tiles, 6000 journal scans replayed", logs), logs
    assert "stopped before serving" in logs, logs
    assert "zenoh" not in logs.lower() and "fleetmap serving" not in logs and "HTTP" not in logs, logs
    with sqlite3.connect(data / DB_NAME) as conn:
        assert conn.execute("SELECT COUNT(*) FROM journal").fetchone() == (0,)
