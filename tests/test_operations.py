"""What the operator of a production service relies on, checked on the real service as a process:
`/metrics` is valid Prometheus text (read by prometheus_client's own parser) and shows what needs
watching; SIGHUP reloads the token file instead of killing the service; every `serve` option can be
given as a FLEETMAP_* environment variable, a bad one refused in one line; the start-up log says
where the service listens, where its data is, its auth mode and memory limit; and a running
service's data directory can be backed up (the documented SQLite online backup) and restored on
another machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from datetime import datetime, timedelta
from pathlib import Path

import httpx
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from fleetmap_client.rest import TOKEN_ENV as CLIENT_TOKEN_ENV
from prometheus_client.core import Metric
from prometheus_client.parser import text_string_to_metric_families
from service_process import ServiceProcess, free_port, reaped, wait_for

from fleetmap import cli, codec, serve_environment, server
from fleetmap.api.app import WEB_DIR_ENV
from fleetmap.auth import TOKENS_ENV
from fleetmap.database import DB_NAME
from fleetmap.http_limits import RESERVED_DESCRIPTORS
from fleetmap.journal import JournalWriter
from fleetmap.memory_budget import MemoryBudget
from fleetmap.registry import QUEUE_PER_ROBOT, QUEUE_TOTAL
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING
from fleetmap.zenoh_ingest import unauthenticated_endpoints

WRITE_A = "write-token-aaaaaaaaaaaaaaaa"
WRITE_B = "write-token-bbbbbbbbbbbbbbbb"


def scan_body(seq: int, x: float = 0.0) -> dict[str, object]:
    return {
        "seq": seq,
        "stamp": float(seq),
        "pose": {"x": x, "y": 0.5, "theta": 0.1 * seq},
        "angle_min": -1.5,
        "angle_increment": 0.05,
        "ranges": [2.0 + 0.01 * i for i in range(61)],
        "range_min": 0.1,
        "range_max": 10.0,
    }


def post_scans(base: str, map_id: str, robot: str, seqs: range, token: str | None = None) -> None:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    for seq in seqs:
        r = httpx.post(
            f"{base}/maps/{map_id}/scans", params={"robot_id": robot}, json=scan_body(seq), headers=headers
        )
        assert r.status_code == 200, r.text


# -- /metrics ----------------------------------------------------------------------------------------


def test_metrics_are_valid_prometheus_text_and_show_what_an_operator_watches(tmp_path: Path) -> None:
    with ServiceProcess(tmp_path) as svc:
        scraped = httpx.get(f"{svc.base_url}/metrics").text
        before = {f.name: f for f in text_string_to_metric_families(scraped)}
        post_scans(svc.base_url, "warehouse", "robot-1", range(1, 4))
        post_scans(svc.base_url, "yard_2", "r-2", range(1, 3))
        post_scans(svc.base_url, "yard_2", "r-2", range(5, 6))  # seqs 3 and 4 lost
        tile = httpx.get(f"{svc.base_url}/maps/warehouse/tiles/0/0/0.png")
        assert tile.status_code == 200
        revalidated = httpx.get(
            f"{svc.base_url}/maps/warehouse/tiles/0/0/0.png", headers={"If-None-Match": tile.headers["etag"]}
        )
        assert revalidated.status_code == 304
        assert httpx.get(f"{svc.base_url}/maps/nowhere/tiles/0/0/0.png").status_code == 404
        with httpx.Client() as held:  # a second connection, open during the scrape
            held.get(f"{svc.base_url}/healthz")
            r = httpx.get(f"{svc.base_url}/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = r.text
    families = {f.name: f for f in text_string_to_metric_families(text)}  # raises on invalid text

    # Strict exposition rules the parser lets through: one HELP and one TYPE per family, before its
    # samples; counters end in _total; no series twice.
    helps = Counter(line.split()[2] for line in text.splitlines() if line.startswith("# HELP "))
    types = Counter(line.split()[2] for line in text.splitlines() if line.startswith("# TYPE "))
    assert max(helps.values()) == 1 and max(types.values()) == 1
    series = Counter((s.name, tuple(sorted(s.labels.items()))) for f in families.values() for s in f.samples)
    assert [k for k, n in series.items() if n > 1] == []
    for line in text.splitlines():
        if line.startswith("# TYPE ") and line.endswith(" counter"):
            assert line.split()[2].endswith("_total"), line
    for family in families.values():
        if family.type != "histogram":
            continue
        for labels in {
            tuple(sorted((k, v) for k, v in s.labels.items() if k != "le")) for s in family.samples
        }:
            mine = [
                s
                for s in family.samples
                if tuple(sorted((k, v) for k, v in s.labels.items() if k != "le")) == labels
            ]
            buckets = [s for s in mine if s.name.endswith("_bucket")]
            assert buckets and buckets[-1].labels["le"] == "+Inf", family.name
            assert [b.value for b in buckets] == sorted(b.value for b in buckets), family.name
            count = next(s.value for s in mine if s.name.endswith("_count"))
            assert buckets[-1].value == count and any(s.name.endswith("_sum") for s in mine)

    def value(name: str, **labels: str) -> float:
        for family in families.values():
            for s in family.samples:
                if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()):
                    return s.value
        raise AssertionError(f"{name}{labels} is not in /metrics:\n{text}")

    # Per map and robot.
    assert value("fleetmap_scans_integrated_total", map="warehouse", robot="robot-1") == 3
    assert value("fleetmap_scans_integrated_total", map="yard_2", robot="r-2") == 3
    assert value("fleetmap_scans_lost", map="yard_2", robot="r-2") == 2
    assert value("fleetmap_scans_rejected_total", map="warehouse", robot="robot-1") == 0
    # Ingest, storage, memory, tiles, event streams.
    assert value("fleetmap_queue_depth") == 0
    assert value("fleetmap_storage_ok") == 1
    assert value("fleetmap_memory_used_bytes") > 0 and value("fleetmap_memory_limit_bytes") > 0
    assert value("fleetmap_tile_renders_total") >= 1
    assert value("fleetmap_event_streams") == 0
    assert value("fleetmap_ingest_latency_seconds_count") == 6
    # Latencies of durability and visibility, one observation per scan, none before the scans.
    for histogram in ("fleetmap_journal_latency_seconds", "fleetmap_ingest_visible_latency_seconds"):
        (count,) = [s.value for s in before[histogram].samples if s.name == f"{histogram}_count"]
        assert count == 0
        assert value(f"{histogram}_count") == 6
        assert 0 < value(f"{histogram}_sum") < value("fleetmap_ingest_latency_seconds_sum")
        assert value(f"{histogram}_bucket", le="+Inf") == 6
    # Tile answers by status: the revalidation (304) and the unknown map (404) count too.
    assert value("fleetmap_tile_requests_total", status="200") == 1
    assert value("fleetmap_tile_requests_total", status="304") == 1
    assert value("fleetmap_tile_requests_total", status="404") == 1
    # The journal: 6 scans committed, in at most 6 transactions (plus the maps' creations).
    assert value("fleetmap_journal_rows_total") == 6
    assert value("fleetmap_journal_commits_total") >= 1
    # HTTP connections: the scrape's and the one held open.
    assert value("fleetmap_http_connections") >= 2
    assert value("fleetmap_http_connections_limit") > 0
    # The process: memory, file descriptors (a service out of them cannot accept robots), restarts.
    assert value("process_resident_memory_bytes") > 0
    assert 0 < value("process_open_fds") < value("process_max_fds")
    assert math.isfinite(value("process_start_time_seconds"))
    # The version running, for upgrades.
    (build,) = families["fleetmap_build_info"].samples
    assert build.value == 1 and build.labels["version"]


# -- SIGHUP ----------------------------------------------------------------------------------------


def test_sighup_reloads_the_token_file_and_keeps_serving(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"write {WRITE_A}\n")
    with ServiceProcess(tmp_path, ["--auth-tokens", str(tokens)]) as svc:
        assert svc.proc is not None
        post_scans(svc.base_url, "m", "r", range(1, 2), token=WRITE_A)

        tokens.write_text(f"write {WRITE_B}\n")  # A revoked, B added
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the reload's log line")
        assert svc.alive(), svc.logs()
        post_scans(svc.base_url, "m", "r", range(2, 3), token=WRITE_B)
        refused = httpx.post(f"{svc.base_url}/maps/m/scans", params={"robot_id": "r"}, json=scan_body(3),
                             headers={"Authorization": f"Bearer {WRITE_A}"})  # fmt: skip
        assert refused.status_code == 401

        tokens.write_text("write short\n")  # a broken file keeps the tokens in force
        svc.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "SIGHUP: kept the tokens in force" in svc.logs(), 10, what="the refusal's log line")
        assert svc.alive()
        post_scans(svc.base_url, "m", "r", range(3, 4), token=WRITE_B)
        assert "short" not in svc.logs()
        assert svc.stop() == 0


def test_a_burst_of_sighups_is_served_off_the_signal_handler(tmp_path: Path) -> None:
    """SIGHUP's reload ran inside the signal handler, in the HTTP server's thread: a burst of them
    (a reload loop in a deployment script) nested handlers until a RecursionError, raised out of
    whatever that thread ran (asyncio logged tracebacks from a socket's read callback). Now the
    handler only wakes a thread: no traceback, the API keeps answering, and the file as it is after
    the burst is the one in force."""
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"write {WRITE_A}\n")
    with ServiceProcess(tmp_path, ["--auth-tokens", str(tokens)]) as svc:
        assert svc.proc is not None
        end = time.monotonic() + 3
        while time.monotonic() < end:
            for _ in range(1000):
                svc.proc.send_signal(signal.SIGHUP)
        tokens.write_text(f"write {WRITE_B}\n")  # A revoked, B added
        svc.proc.send_signal(signal.SIGHUP)
        assert httpx.get(f"{svc.base_url}/healthz", timeout=10).status_code == 200

        def b_in_force() -> bool:
            answer = httpx.post(f"{svc.base_url}/maps/m/scans", params={"robot_id": "r"}, json=scan_body(1),
                                headers={"Authorization": f"Bearer {WRITE_B}"})  # fmt: skip
            return answer.status_code != 401

        wait_for(b_in_force, 10, what="the token file as it is after the burst")
        assert svc.alive()
        assert "Traceback" not in svc.logs() and "RecursionError" not in svc.logs()
        assert svc.stop() == 0


#: A `sitecustomize` that sends its own process SIGHUP as each of `HANGUP_AT` starts to import,
#: so that a test hits the start's import window (seconds long, but not at a time a test can aim at).
SIGHUP_WHILE_IMPORTING = """
import os, signal, sys
_left = set(os.environ["HANGUP_AT"].split(","))
def _hang_up(event, args):
    if event == "import" and args[0] in _left:
        _left.discard(args[0])
        os.kill(os.getpid(), signal.SIGHUP)
sys.addaudithook(_hang_up)
"""


def hangups_while_importing(tmp_path: Path, modules: str) -> dict[str, str]:
    """The environment of a child process that is sent SIGHUP as each of `modules` (comma-separated)
    starts to import."""
    hook = tmp_path / "hangup-hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(SIGHUP_WHILE_IMPORTING)
    path = os.pathsep.join([str(hook), os.environ.get("PYTHONPATH", "")])
    return {"PYTHONPATH": path, "HANGUP_AT": modules}


def test_a_sighup_while_the_service_starts_is_held_not_its_end(tmp_path: Path) -> None:
    """SIGHUP's handler was installed once `serve` had imported its modules (pydantic, FastAPI,
    numba: seconds): a SIGHUP before, a service manager's reload right after the start, ended the
    process (exit 129). `fleetmap`'s entry point holds it from the first: the service starts, the held
    SIGHUP reads the token file once the tokens are read, and it stops cleanly."""
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"write {WRITE_A}\n")
    env = hangups_while_importing(tmp_path, "pydantic,fastapi,numba")
    service = ServiceProcess(tmp_path, ["--auth-tokens", str(tokens)], env=env)
    service.args[1:3] = ["-m", "fleetmap", "serve"]  # the entry point's way, not `-m fleetmap.server`
    with service as svc:
        assert svc.proc is not None
        wait_for(lambda: "SIGHUP: 1 API tokens read" in svc.logs(), 10, what="the held SIGHUP's reload")
        post_scans(svc.base_url, "m", "r", range(1, 2), token=WRITE_A)
        assert svc.stop() == 0, svc.logs()


def test_a_sighup_while_a_command_starts_ends_a_command_that_does_not_take_it(tmp_path: Path) -> None:
    """Held while the command line is read, SIGHUP keeps its default action for a command that does
    not take it (`fleetmap build`: a closed terminal ends it): delivered once the command is known."""
    env = {**os.environ, **hangups_while_importing(tmp_path, "pydantic")}
    result = subprocess.run([sys.executable, "-m", "fleetmap", "build", str(tmp_path / "none.log"), "--out",
                             str(tmp_path / "out")], env=env, capture_output=True, timeout=120)  # fmt: skip
    assert result.returncode == -signal.SIGHUP, result.stderr
    assert not (tmp_path / "out").exists()


# -- environment, start-up log, one-line errors ----------------------------------------------------


def test_every_option_can_come_from_the_environment(tmp_path: Path) -> None:
    port, zport = free_port(), free_port()
    data = tmp_path / "data"
    env = {
        **os.environ,
        "PYTHONUNBUFFERED": "1",
        "FLEETMAP_HTTP": f"127.0.0.1:{port}",
        "FLEETMAP_ZENOH_LISTEN": f"tcp/127.0.0.1:{zport}",
        "FLEETMAP_DATA_DIR": str(data),
        "FLEETMAP_MAX_MEMORY": "32MiB",  # the command line wins: --max-memory 64MiB below
        "FLEETMAP_NO_AUTO_CREATE": "yes",
        "FLEETMAP_DATADIR": str(tmp_path / "typo"),  # no option's: warned of, ignored
    }
    log_path = tmp_path / "service.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "fleetmap.server", "--max-memory", "64MiB"], env=env,
                                stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
    with reaped(proc):
        base = f"http://127.0.0.1:{port}"

        def up() -> bool:
            assert proc.poll() is None, log_path.read_text()
            try:
                return httpx.get(f"{base}/healthz").status_code == 200
            except httpx.TransportError:
                return False

        wait_for(up, 60, what="the service on FLEETMAP_HTTP")
        health = httpx.get(f"{base}/healthz").json()
        assert health["zenoh"]["listen"] == [f"tcp/127.0.0.1:{zport}"]
        assert (data / DB_NAME).exists()
        assert (
            httpx.post(f"{base}/maps/new/scans", params={"robot_id": "r"}, json=scan_body(1)).status_code
            == 404
        )
        metrics = httpx.get(f"{base}/metrics").text
        limit = next(
            f for f in text_string_to_metric_families(metrics) if f.name == "fleetmap_memory_limit_bytes"
        )
        assert limit.samples[0].value == 64 * 2**20
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    logs = log_path.read_text()
    # One line each: where it listens, where its data is, the auth mode, the memory limit.
    assert f"HTTP (REST API, viewer, /metrics, /healthz) on http://127.0.0.1:{port}" in logs
    assert f"listening on tcp/127.0.0.1:{zport}" in logs
    assert f"durable in {data.resolve()}" in logs and "64 MiB (--max-memory)" in logs
    assert "API tokens: NONE" in logs
    assert (
        "WARNING fleetmap.server: $FLEETMAP_DATADIR is not a variable of `fleetmap serve` (did you mean "
        "$FLEETMAP_DATA_DIR?): ignored" in logs
    ), logs
    assert not (tmp_path / "typo").exists()


def serve_error(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "fleetmap.server", *args], capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=60)  # fmt: skip


def test_bad_options_and_variables_are_refused_in_one_line(tmp_path: Path) -> None:
    not_text = tmp_path / "map-config.json"
    not_text.write_bytes(b'{"resolution": 0.1\xff}')  # not text: was a traceback and exit 1
    broken_zenoh = tmp_path / "zenoh.json5"
    broken_zenoh.write_text('{mode: "router",')
    cases = [
        (("--config", str(not_text)), {}, f"cannot read config {not_text}: not UTF-8 text (byte 18)"),
        (("--workers", "0"), {}, "argument --workers: must be between 1 and 64, got 0"),
        # Bounds were written as %g: "between 1 and 1e+06", "between 0 and 4.29497e+09".
        (("--max-failed-sign-ins", "0"), {}, "must be between 1 and 1000000, got 0"),
        (("--ros-domain", "4294967296"), {}, "must be between 0 and 4294967295, got 4294967296"),
        # With no token to check, reads were silently open to anyone.
        (("--require-read-token",), {}, "--require-read-token needs API tokens"),
        (("--max-memory", "lots"), {}, "argument --max-memory: expected a size"),
        ((), {"FLEETMAP_WORKERS": "many"}, "$FLEETMAP_WORKERS='many': expected a whole number"),
        ((), {"FLEETMAP_LOG_LEVEL": "loud"}, "$FLEETMAP_LOG_LEVEL='loud': invalid choice"),
        ((), {"FLEETMAP_IN_MEMORY": "maybe"}, "$FLEETMAP_IN_MEMORY='maybe': expected 1, true"),
        # An unset variable in a template: the maps went to the working directory, silently.
        ((), {"FLEETMAP_DATA_DIR": ""}, "$FLEETMAP_DATA_DIR='': expected a path, got an empty value"),
        (("--config", ""), {}, "argument --config: expected a path, got an empty value"),
        # Both were "--world-bound and --max-range must be positive": neither the one at fault,
        # nor its value, nor its variable.
        (("--max-range", "nan"), {}, "argument --max-range: must be a number of metres above 0, got nan"),
        ((), {"FLEETMAP_WORLD_BOUND": "-1"}, "$FLEETMAP_WORLD_BOUND='-1': must be a number of metres"),
        (("--world-bound", "far"), {}, "argument --world-bound: expected a number of metres, got 'far'"),
        # Checked only once parsed, a bad $FLEETMAP_HTTP was refused as "--http 'localhost': ...",
        # an option the command line did not hold (the Docker image sets the variable).
        ((), {"FLEETMAP_HTTP": "localhost"}, "$FLEETMAP_HTTP='localhost': expected HOST:PORT"),
        (("--http", "127.0.0.1:99999"), {}, "argument --http: port must be at most 65535, got"),
        # Zenoh's "invalid port value" named no endpoint, once every map was loaded.
        (
            ("--zenoh-listen", "tcp/127.0.0.1:99999"),
            {},
            "argument --zenoh-listen: 'tcp/127.0.0.1:99999' has port 99999: a port is at most 65535",
        ),
        # Both were found only once the kernels were loaded and every map restored (minutes for a
        # fleet's maps, a start for nothing), the data directory made meanwhile.
        (
            ("--zenoh-config", str(tmp_path / "absent.json5")),
            {},
            f"cannot load Zenoh config {tmp_path / 'absent.json5'}: No such file or directory",
        ),
        ((), {"FLEETMAP_ZENOH_CONFIG": str(broken_zenoh)}, f"cannot load Zenoh config {broken_zenoh}: "),
    ]
    for args, env, message in cases:
        done = serve_error(*args, "--data-dir", str(tmp_path / "d"), **env)
        assert done.returncode == 2, done
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("fleetmap serve: error: ") and message in lines[0], (
            done.stderr
        )
        assert not (tmp_path / "d").exists()


def serve_namespace(
    argv: list[str], environ: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> argparse.Namespace:
    """The options `fleetmap serve ARGV` runs with in `environ` (only FLEETMAP_* variables of it), as
    parsed by the real `serve` parser."""
    for name in os.environ:
        if name.startswith("FLEETMAP_"):
            monkeypatch.delenv(name)
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    parser = argparse.ArgumentParser(prog="fleetmap")
    server.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["serve", *argv])


def serve_options(
    argv: list[str], environ: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> dict[str, object]:
    """`serve_namespace` as a dict, a memory budget as its limit, to compare."""
    parsed = vars(serve_namespace(argv, environ, monkeypatch))
    return {k: v.limit if isinstance(v, MemoryBudget) else v for k, v in parsed.items()}


def serve_option_actions() -> list[argparse.Action]:
    parser = argparse.ArgumentParser(prog="fleetmap")
    serve = server.add_parser(parser.add_subparsers(dest="command"))
    return [action for action in serve._actions if action.dest != "help"]


def test_the_tests_free_ports_are_never_given_twice() -> None:
    """The tests' `free_port` (service_process.py) gives no port twice in a process: a service once
    got the same port for HTTP and Zenoh (1 chance in 12,000), and its Zenoh listener failed on its own
    HTTP socket. 300 ports from 12,000 at random repeat one with a probability of 98 %."""
    ports = [free_port() for _ in range(300)]
    assert len(set(ports)) == len(ports)


@pytest.fixture(scope="module")
def in_memory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One `--in-memory` service on loopback for the module's tests that need no other option: one
    reads its start-up log, one publishes a scan (robot `far` of map `m`); nothing else publishes to
    it."""
    with ServiceProcess(tmp_path_factory.mktemp("operations-memory"), ["--in-memory"]) as service:
        yield service


@pytest.fixture(scope="module")
def durable(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One durable service with the default options for the module's stalled-disk tests: each
    stalls the commits of its own scans to a map of its own, and lets them go before it ends; they
    count the service-wide counters from what they were when they began."""
    with ServiceProcess(tmp_path_factory.mktemp("operations-durable")) as service:
        yield service


def test_zenoh_beyond_loopback_without_credentials_is_warned_of(
    tmp_path: Path, in_memory: ServiceProcess
) -> None:
    """A plain Zenoh endpoint beyond loopback takes anyone's scans: a warning at start says so and
    names it (the REST API refuses such an address without tokens; Zenoh has no check of its own).
    Loopback, mutual TLS and a user / password configuration are not warned of; TLS alone is."""
    endpoint = f"tcp/0.0.0.0:{free_port()}"
    with ServiceProcess(tmp_path, ["--in-memory", "--zenoh-listen", endpoint]) as svc:
        open_logs = svc.logs()
    loopback_logs = in_memory.logs()
    warning = (
        "beyond loopback with neither mutual TLS nor a user / password: anyone who reaches it can "
        "publish scans"
    )
    assert f"zenoh listens on {endpoint} {warning}" in open_logs, open_logs
    assert warning not in loopback_logs
    plain = zenoh.Config()
    endpoints = ["tcp/0.0.0.0:1", "tcp/[::1]:2", "tls/0.0.0.0:3", "quic/[::1]:4"]
    # TLS without mutual TLS encrypts, but takes any robot: it was not warned of.
    assert unauthenticated_endpoints(endpoints, plain) == ["tcp/0.0.0.0:1", "tls/0.0.0.0:3"]
    mtls = zenoh.Config()
    mtls.insert_json5("transport/link/tls/enable_mtls", "true")
    assert unauthenticated_endpoints(endpoints, mtls) == ["tcp/0.0.0.0:1"]
    users = zenoh.Config()
    users.insert_json5("transport/auth/usrpwd/dictionary_file", '"/etc/fleetmap/users.txt"')
    assert unauthenticated_endpoints(["tcp/0.0.0.0:1"], users) == []


def test_an_empty_user_password_dictionary_is_warned_of(tmp_path: Path) -> None:
    """A `usrpwd` dictionary file that holds no user (empty, or blank lines only: one made before its
    users were added) turns Zenoh's user / password authentication off rather than refusing everyone:
    a robot without credentials opens a session. The endpoint was not warned of, as if every robot
    needed a password."""
    dictionary = tmp_path / "users.txt"
    dictionary.write_text("\n  \n")
    port = free_port()
    service = zenoh.Config()
    service.insert_json5("mode", '"router"')
    service.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    service.insert_json5("scouting/multicast/enabled", "false")
    service.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary)))
    robot = zenoh.Config()
    robot.insert_json5("mode", '"client"')
    robot.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    robot.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(service), zenoh.open(robot):  # no credentials, and let in (zenoh 1.10.2)
        pass
    assert unauthenticated_endpoints(["tcp/0.0.0.0:1"], service) == ["tcp/0.0.0.0:1"]
    dictionary.write_text("robot-7:correct-horse-battery-staple\n")
    assert unauthenticated_endpoints(["tcp/0.0.0.0:1"], service) == []
    # The service's own user alone (the robot's side of the exchange) asks every robot for one it
    # cannot check: none is let in, nothing to warn of.
    own_user = zenoh.Config()
    own_user.insert_json5("transport/auth/usrpwd", '{"user": "service", "password": "a-long-password"}')
    assert unauthenticated_endpoints(["tcp/0.0.0.0:1"], own_user) == []


def test_in_memory_with_a_data_dir_says_the_directory_is_not_used(tmp_path: Path) -> None:
    """--in-memory with --data-dir (the Docker image sets $FLEETMAP_DATA_DIR): a warning at start
    says the directory is not used, and nothing is written there."""
    unused = tmp_path / "unused"
    with ServiceProcess(tmp_path, ["--in-memory", "--data-dir", str(unused)]) as svc:
        assert httpx.get(f"{svc.base_url}/healthz").status_code == 200
        logs = svc.logs()
    assert f"--in-memory: --data-dir {unused} is not used; the maps are lost when the service stops" in logs
    assert not unused.exists()


def test_variables_that_name_no_option_are_warned_of(monkeypatch: pytest.MonkeyPatch) -> None:
    """A FLEETMAP_ variable of no option is ignored with a warning (the closest option's variable
    named when one is close), and the variables fleetmap reads elsewhere are not warned of."""
    for name in [v for v in os.environ if v.startswith("FLEETMAP_")]:
        monkeypatch.delenv(name)
    environ = {"FLEETMAP_DATADIR": "/x", "FLEETMAP_COLOUR": "red", "FLEETMAP_WEB_DIR": "/w"}
    warnings = serve_namespace([], environ, monkeypatch).environment_warnings
    assert warnings == [
        "$FLEETMAP_COLOUR is not a variable of `fleetmap serve`: ignored",
        "$FLEETMAP_DATADIR is not a variable of `fleetmap serve` (did you mean $FLEETMAP_DATA_DIR?): ignored",
    ]
    assert serve_namespace([], {"FLEETMAP_DATA_DIR": "/x"}, monkeypatch).environment_warnings == []
    assert {TOKENS_ENV, WEB_DIR_ENV} == serve_environment.OTHER_VARIABLES
    # The Python client's token, which docs/clients.md says to set: "did you mean $FLEETMAP_TOKENS?"
    # sent its user to give the service a token in the client's variable's place, of another format.
    assert serve_namespace([], {CLIENT_TOKEN_ENV: "t" * 16}, monkeypatch).environment_warnings == [
        f"${CLIENT_TOKEN_ENV} is the Python client's API token (fleetmap_client.rest), not a variable of "
        "`fleetmap serve`, whose tokens are --auth-tokens FILE or $FLEETMAP_TOKENS: ignored"
    ]


def test_each_variable_means_its_option_on_the_command_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every option, whatever its kind, has its variable, which means what the option says on the
    command line (with a value other than its default, so that a variable ignored shows)."""
    for action in serve_option_actions():
        option = action.option_strings[-1]
        if action.nargs == 0:
            argv, text = [option], "1"
        elif option == "--ros-domain":  # a number without a default (it falls back to $ROS_DOMAIN_ID)
            argv, text = [option, "5"], "5"
        elif action.nargs == "+":
            # Lists of anything but addresses and origins (Zenoh endpoints) take any text.
            items = {
                "--forwarded-allow-ips": ["10.0.0.1", "10.0.0.2"],
                "--cors-origin": ["http://a", "https://b:8443"],
                "--ros-publish-map": ["lab", "wh=/wh/map"],
            }.get(option, ["tcp/a:1", "tcp/b:2"])
            argv, text = [option, *items], "  ".join(items)
        elif action.choices:
            argv, text = [option, action.choices[-1]], action.choices[-1]
        elif isinstance(action.default, (int, float)):
            # Up from a default at the bottom of its range, else down.
            up = option == "--ros-map-period"
            value = action.default + 1 if up else action.default - 1
            argv, text = [option, str(value)], str(value)
        elif option == "--http":
            argv, text = [option, "127.0.0.1:9000"], "127.0.0.1:9000"
        elif option == "--root-path":
            argv, text = [option, "/fleetmap"], "/fleetmap"
        else:  # text, or a size (--max-memory)
            argv, text = [option, "1GiB"], "1GiB"
        defaults = serve_options([], {}, monkeypatch)
        from_variable = serve_options([], {serve_environment.env_name(action): text}, monkeypatch)
        assert from_variable == serve_options(argv, {}, monkeypatch) != defaults, option


def test_a_command_line_naming_its_command_adds_that_commands_parser_alone() -> None:
    """`fleetmap build` imported every command's module (the service's, the demo's: 0.7 s of its
    start) to build parsers it never used. A command line naming its command now gets that
    command's parser alone, from the module `cli.COMMAND_MODULES` names for it; the table must name
    every command's module and only those, or a command would be missing when named."""
    _, every = cli.command_line_parser()
    assert set(every.choices) == {"build", *cli.COMMAND_MODULES}
    table = cli.COMMAND_MODULES
    for command in every.choices:
        _, alone = cli.command_line_parser([command, "--help"])
        module = table.get(command)
        assert set(alone.choices) == {c for c in table if table[c] == module} if module else {command}
    for other in ([], ["--help", "build"], ["bulid"], ["--version"]):
        assert list(cli.command_line_parser(other)[1].choices) == list(every.choices), other


def test_a_list_option_given_twice_keeps_the_values_of_both() -> None:
    """`--zenoh-listen tcp/a --zenoh-listen tls/b` listened on tls/b alone, and `--cors-origin A
    --cors-origin B` allowed B alone: argparse's plain list option keeps its last occurrence, and
    nothing said the first was dropped. Every command's list options keep every value, in order, as
    `--ros-publish-map` already did: given twice, they mean what one occurrence of all the values
    means."""
    parser, sub = cli.command_line_parser()
    required = {"replay": ["data.log", "--map", "m", "--robot", "r"]}
    values = {
        "--forwarded-allow-ips": ["10.0.0.1", "10.0.0.2"],
        "--cors-origin": ["http://a", "https://b:8443"],
        "--ros-publish-map": ["lab", "wh=/wh/map"],
    }
    checked = []
    for command, p in sub.choices.items():
        for action in p._actions:
            if action.nargs != "+":
                continue
            option = action.option_strings[-1]
            first, second = values.get(option, ["tcp/a:1", "tcp/b:2"])
            base = [command, *required.get(command, [])]
            twice = parser.parse_args([*base, option, first, option, second])
            once = parser.parse_args([*base, option, first, second])
            assert getattr(twice, action.dest) == getattr(once, action.dest), f"fleetmap {command} {option}"
            checked.append(f"{command} {option}")
    expected = {"serve --zenoh-listen", "serve --cors-origin", "replay --connect", "sim --connect"}
    assert expected <= set(checked), checked


def test_on_off_variables_take_the_documented_words_and_the_command_line_wins(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for word in ["1", "true", "yes", "on", " TRUE ", "On"]:
        assert serve_options([], {"FLEETMAP_INSECURE": word}, monkeypatch)["insecure"] is True, word
    for word in ["0", "false", "no", "off", "", "OFF"]:
        assert serve_options([], {"FLEETMAP_INSECURE": word}, monkeypatch)["insecure"] is False, word
    # The command line wins over every kind of variable: a value, a list.
    environ = {"FLEETMAP_WORKERS": "3", "FLEETMAP_CORS_ORIGIN": "http://a http://b"}
    options = serve_options(["--workers", "5", "--cors-origin", "http://c"], environ, monkeypatch)
    assert options["workers"] == 5 and options["cors_origin"] == ["http://c"]
    # A value is the variable's whole text, even one that looks like an option.
    assert serve_options([], {"FLEETMAP_DATA_DIR": "--in-memory"}, monkeypatch)["data_dir"] == "--in-memory"


def test_a_bad_variable_is_one_json_line_with_json_logs(tmp_path: Path) -> None:
    """With JSON logs asked for by the command line or the environment, a bad variable of any kind
    (on/off, a choice, a number) is refused in one JSON object naming the variable."""
    cases = [
        (
            ("--log-format", "json"),
            {"FLEETMAP_IN_MEMORY": "maybe"},
            "$FLEETMAP_IN_MEMORY='maybe': expected 1",
        ),
        (
            (),
            {"FLEETMAP_LOG_FORMAT": "json", "FLEETMAP_WORKERS": "many"},
            "$FLEETMAP_WORKERS='many': expected",
        ),
        (
            (),
            {"FLEETMAP_LOG_FORMAT": "json", "FLEETMAP_LOG_LEVEL": "loud"},
            "$FLEETMAP_LOG_LEVEL='loud': invalid",
        ),
    ]
    for args, env, message in cases:
        done = serve_error(*args, "--data-dir", str(tmp_path / "d"), **env)
        assert done.returncode == 2, done
        (line,) = done.stderr.strip().splitlines()
        error = json.loads(line)
        assert error["level"] == "ERROR" and error["message"].startswith(f"fleetmap serve: error: {message}")
        assert not (tmp_path / "d").exists()


def test_log_level_warning_keeps_the_start_up_quiet(tmp_path: Path) -> None:
    with ServiceProcess(tmp_path, ["--log-level", "warning", "--in-memory"]) as svc:
        post_scans(svc.base_url, "m", "r", range(1, 3))
        assert svc.stop() == 0
    logs = svc.logs()
    assert " INFO " not in logs, logs
    assert "fleetmap serving http://" in logs  # the ready line is on stdout whatever the level


# -- JSON logs ----------------------------------------------------------------------------------

#: The service with a broken PNG encoder, so that a tile request meets an exception: the service has
#: no bug to trigger on purpose, and an exception's log line is what this test must see. Everything
#: else is the real `python -m fleetmap.server` with its real command line.
BROKEN_TILES_SERVICE = (
    "import runpy\n"
    "import fleetmap.tile_render\n"
    "def broken(rgba):\n"
    "    raise RuntimeError('injected fault: the PNG encoder is broken')\n"
    "fleetmap.tile_render.encode_png = broken\n"
    "runpy.run_module('fleetmap.server', run_name='__main__', alter_sys=True)\n"
)


def zenoh_client_config(endpoint: str) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


def test_json_log_is_one_object_per_line_with_uvicorn_and_the_ready_line(tmp_path: Path) -> None:
    svc = ServiceProcess(tmp_path, ["--log-format", "json", "--access-log"])
    assert svc.args[1:3] == ["-m", "fleetmap.server"]
    svc.args[1:3] = ["-c", BROKEN_TILES_SERVICE]
    with svc:
        assert svc.proc is not None
        post_scans(svc.base_url, "m", "r", range(1, 3))  # access lines; "created map m"
        assert httpx.get(f"{svc.base_url}/maps/m/tiles/0/0/0.png").status_code == 500  # the exception
        with socket.create_connection(("127.0.0.1", svc.port), timeout=10) as raw:  # uvicorn's warning
            raw.sendall(b"NOT HTTP\r\n\r\n")
            assert raw.recv(4096).startswith(b"HTTP/1.1 400")
        svc.proc.send_signal(signal.SIGHUP)  # fleetmap's own warning: no token file to reload
        session = zenoh.open(zenoh_client_config(svc.zenoh_endpoint))
        try:  # a robot's undecodable scan: a warning with its map and robot as fields
            publisher = session.declare_publisher(
                "fleetmap/m/robot-z/scan", encoding=zenoh.Encoding(BINARY_ENCODING)
            )
            wait_for(lambda: publisher.matching_status.matching, 10, what="the service's subscriber")
            publisher.put(b"not a scan")
            wait_for(lambda: "rejected a scan from m/robot-z" in svc.logs(), 10, what="the rejection")
        finally:
            session.close()
        wait_for(lambda: "SIGHUP: nothing to reload" in svc.logs(), 10, what="the SIGHUP warning")
        assert svc.stop() == 0
    lines = svc.logs().splitlines()
    assert lines
    objects = [json.loads(line) for line in lines]  # every line, stdout's and stderr's, alone
    for line in objects:
        assert isinstance(line, dict) and {"time", "level", "logger", "message"} <= line.keys(), line
        assert line["time"].endswith("Z") and datetime.fromisoformat(line["time"]).utcoffset() == timedelta(0)

    def find(**fields: object) -> dict[str, object]:
        found = [line for line in objects if all(line.get(k) == v for k, v in fields.items())]
        assert found, f"no log line with {fields}:\n{svc.logs()}"
        return found[0]

    # Start-up: where HTTP listens, and the ready line (stdout) with its address as fields.
    listening = f"HTTP (REST API, viewer, /metrics, /healthz) on {svc.base_url}"
    assert find(logger="fleetmap.server", level="INFO", message=listening)
    ready = find(url=svc.base_url)
    assert ready["message"] == f"fleetmap serving {svc.base_url}  zenoh: {svc.zenoh_endpoint}"
    assert ready["zenoh"] == [svc.zenoh_endpoint]
    assert find(logger="fleetmap.registry", message="created map m")["map_id"] == "m"
    # The access log, with the request as fields.
    access = find(logger="uvicorn.access", method="POST", status=200)
    assert str(access["path"]).startswith("/maps/m/scans") and access["client"]
    # Warnings: uvicorn's, fleetmap's, and a robot's rejected scan with its ids.
    assert find(logger="uvicorn.error", level="WARNING", message="Invalid HTTP request received.")
    assert find(logger="fleetmap.server", level="WARNING")["message"].startswith("SIGHUP: nothing to reload")
    assert find(logger="fleetmap.ingest", level="WARNING", map_id="m", robot_id="robot-z")
    # The exception: its traceback in one field of one line.
    failure = find(logger="fleetmap.api", level="ERROR", map_id="m")
    assert failure["message"] == "internal error on GET /maps/m/tiles/0/0/0.png"
    assert "Traceback" in failure["exception"] and "injected fault" in failure["exception"]
    assert "injected fault" in find(logger="uvicorn.error", level="ERROR")["exception"]  # uvicorn's own


def test_a_bad_option_is_one_json_line_with_json_logs() -> None:
    """With JSON logs asked for by the command line (before or after the bad value) or by the
    environment, a value its option's check refuses is one JSON object: argparse's refusal was a
    text line among the JSON a log pipeline reads."""
    cases = [
        (("--log-format", "json", "--http", "nowhere"), {}, "argument --http: expected HOST:PORT"),
        (("--workers", "0", "--log-format=json"), {}, "argument --workers: must be between 1 and 64"),
        (("--workers", "0"), {"FLEETMAP_LOG_FORMAT": "json"}, "argument --workers: must be between"),
    ]
    for args, env, message in cases:
        done = serve_error(*args, **env)
        assert done.returncode == 2
        (line,) = done.stderr.strip().splitlines()
        error = json.loads(line)
        assert error["level"] == "ERROR"
        assert error["message"].startswith(f"fleetmap serve: error: {message}"), error
    # The command line wins over the variable here too.
    done = serve_error("--workers", "0", "--log-format", "text", FLEETMAP_LOG_FORMAT="json")
    assert done.stderr.startswith("fleetmap serve: error: argument --workers: must be between"), done.stderr


# -- backup and restore ----------------------------------------------------------------------------


def test_online_backup_of_a_running_service_restores_on_another_machine(tmp_path: Path) -> None:
    """docs/durability.md's backup recipe: SQLite's online backup of the database while the service
    runs and journals, then a service started on a copy in another directory serves the same map."""
    data = tmp_path / "data"
    backup = tmp_path / "backup"
    with ServiceProcess(tmp_path, ["--data-dir", str(data), "--snapshot-interval", "0.5"]) as svc:
        post_scans(svc.base_url, "m", "r", range(1, 40))
        # The documented command (python3 -c ...), run as the operator would, while scans go on.
        backup.mkdir()
        command = (
            _documented_backup_command().replace("DATA_DIR", str(data)).replace("BACKUP_DIR", str(backup))
        )
        done = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        points = [[0.05 * i, 0.05 * j] for i in range(-50, 50, 3) for j in range(-30, 40, 3)]
        at_backup = httpx.post(f"{svc.base_url}/maps/m/cells", json={"points": points}).json()
        post_scans(svc.base_url, "m", "r", range(40, 45))  # after the backup: not in it
        assert svc.stop() == 0
    assert sqlite3.connect(backup / DB_NAME).execute("PRAGMA integrity_check").fetchone() == ("ok",)
    with ServiceProcess(tmp_path, ["--data-dir", str(backup)]) as restored:
        stats = httpx.get(f"{restored.base_url}/maps/m").json()["stats"]
        assert stats["scans_integrated"] == 39 and stats["robots"]["r"]["last_seq"] == 39, stats
        assert httpx.post(f"{restored.base_url}/maps/m/cells", json={"points": points}).json() == at_backup


def _documented_backup_command() -> str:
    text = (Path(__file__).resolve().parents[1] / "docs" / "durability.md").read_text()
    lines = [line.strip() for line in text.splitlines() if "DATA_DIR" in line and "python3" in line]
    assert len(lines) == 1, "docs/durability.md should give one backup command with DATA_DIR and BACKUP_DIR"
    return lines[0]


# -- what to alert on --------------------------------------------------------------------------------


def test_metrics_count_every_http_answer_by_status_and_show_the_zenoh_session(tmp_path: Path) -> None:
    """An operator alerts on 5xx and on robots gone from /metrics alone: before, only tile answers
    were counted by status, and the Zenoh session (up, routers, robots alive, undecodable messages)
    was only in /healthz, which a Prometheus scrape does not read."""
    svc = ServiceProcess(tmp_path)
    svc.args[1:3] = ["-c", BROKEN_TILES_SERVICE]
    with svc:
        post_scans(svc.base_url, "m", "r", range(1, 3))
        assert httpx.get(f"{svc.base_url}/maps/m/tiles/0/0/0.png").status_code == 500
        assert httpx.get(f"{svc.base_url}/maps/nowhere").status_code == 404
        session = zenoh.open(zenoh_client_config(svc.zenoh_endpoint))
        try:
            token = session.liveliness().declare_token("fleetmap/m/robot-z/alive")
            publisher = session.declare_publisher(
                "fleetmap/m/robot-z/scan", encoding=zenoh.Encoding(BINARY_ENCODING)
            )
            wait_for(lambda: publisher.matching_status.matching, 10, what="the service's subscriber")
            publisher.put(b"not a scan")

            def scrape() -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
                text = httpx.get(f"{svc.base_url}/metrics").text
                return {
                    (s.name, tuple(sorted(s.labels.items()))): s.value
                    for f in text_string_to_metric_families(text)
                    for s in f.samples
                }

            seen = wait_for(
                lambda: (
                    (m := scrape()).get(("fleetmap_zenoh_decode_errors_total", ())) == 1
                    and m.get(("fleetmap_zenoh_robots_alive", ())) == 1
                    and m
                ),
                10,
                what="the robot's token and its undecodable scan on /metrics",
            )
            token.undeclare()
        finally:
            session.close()
    assert seen[("fleetmap_http_responses_total", (("code", "500"),))] == 1
    assert seen[("fleetmap_http_responses_total", (("code", "503"),))] == 0  # there before the first
    assert seen[("fleetmap_http_responses_total", (("code", "404"),))] == 1
    assert seen[("fleetmap_http_responses_total", (("code", "200"),))] >= 2  # the scans, the scrapes
    assert seen[("fleetmap_zenoh_up", ())] == 1
    assert seen[("fleetmap_zenoh_routers", ())] == 0  # a router itself: robots connect as clients
    assert seen[("fleetmap_zenoh_messages_received_total", ())] == 1
    assert seen[("fleetmap_zenoh_scans_submitted_total", ())] == 0
    assert seen[("fleetmap_zenoh_invalid_keys_total", ())] == 0
    # Refusals by reason from the start, at 0: `increase()` sees the first one.
    assert seen[("fleetmap_zenoh_scans_refused_total", (("reason", "queue_full"),))] == 0
    assert seen[("fleetmap_zenoh_scans_unrecoverable_total", ())] == 0
    assert seen[("fleetmap_zenoh_scans_deferred_total", ())] == 0
    assert seen[("fleetmap_zenoh_scans_refetched_total", ())] == 0
    # How full the ingest queue may get, beside its depth.
    assert seen[("fleetmap_queue_limit", ())] == QUEUE_TOTAL
    assert seen[("fleetmap_queue_depth", ())] == 0
    # Storage failures by operation, at 0 on a healthy disk (tests/test_durability.py fails one).
    for operation in ("journal_commit", "snapshot", "map_change"):
        assert seen[("fleetmap_storage_failures_total", (("operation", operation),))] == 0


def test_a_stalled_disk_shows_on_metrics_as_scans_waiting_for_their_journal_commit(
    durable: ServiceProcess,
) -> None:
    """A disk that stalls (a journal commit that hangs) moved no metric: with durable storage a scan
    counts as integrated only once its row commits, so `fleetmap_journal_commits_total` and
    `fleetmap_scans_integrated_total` stopped together, and docs/api.md's alert for it (commits at 0
    while scans are integrated) could never fire; the workers go on applying scans, so the ingest
    queue stayed empty too. The journal's backlog now shows it: rows waiting and the oldest's age.
    Here another program holds the database's write lock, as a stalled disk holds the commit."""
    post_scans(durable.base_url, "stalled", "r", range(1, 3))

    def scrape() -> dict[str, float]:
        text = httpx.get(f"{durable.base_url}/metrics").text
        return {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples}

    before = scrape()
    assert before["fleetmap_journal_rows_waiting"] == 0
    assert before["fleetmap_journal_backlog_seconds"] == 0
    data_dir = Path(durable.args[durable.args.index("--data-dir") + 1])
    holder = sqlite3.connect(data_dir / DB_NAME, isolation_level=None, timeout=30)
    holder.execute("BEGIN EXCLUSIVE")
    answers: list[httpx.Response] = []
    sender = threading.Thread(
        target=lambda: answers.append(
            httpx.post(f"{durable.base_url}/maps/stalled/scans", params={"robot_id": "r"}, json=scan_body(3),
                       timeout=60)
        )
    )  # fmt: skip
    try:
        sender.start()
        stalled = wait_for(
            lambda: (m := scrape())["fleetmap_journal_backlog_seconds"] > 0.5 and m,
            20,
            what="the stalled commit on /metrics",
        )
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    sender.join(60)
    assert stalled["fleetmap_journal_rows_waiting"] == 1
    # What the alert used to watch did not move: neither would tell a stalled disk.
    assert stalled["fleetmap_journal_commits_total"] == before["fleetmap_journal_commits_total"]
    assert stalled["fleetmap_queue_depth"] == 0
    after = wait_for(
        lambda: (m := scrape())["fleetmap_journal_rows_waiting"] == 0 and m, 20, what="the commit"
    )
    assert after["fleetmap_journal_backlog_seconds"] == 0
    assert after["fleetmap_journal_rows_total"] == before["fleetmap_journal_rows_total"] + 1
    assert answers and answers[0].status_code in (200, 503)  # 503: not integrated within 10 s


def test_a_stalled_disk_holds_the_scans_in_the_bounded_ingest_queue_not_in_memory_without_end(
    durable: ServiceProcess,
) -> None:
    """While no journal commit came back (a stalled disk: a frozen file system, a hung network
    mount), the workers went on applying scans and appending them to the journal's queue, each
    holding its scan: memory grew without bound (1.2 MB/s for two robots at 20 Hz in a probe with
    the file system frozen by `fsfreeze`, and all of it lost in a crash). Now at most
    `JournalWriter.MAX_WAITING` rows wait; past that the workers wait too, the scans wait in the
    ingest queue, and past its bounds in the robot's Zenoh cache (deferred, as under any other
    overload: `backlog_refetch.py`; until 2026-11-29 the queue dropped them), and once the disk
    moves again every scan is integrated. Another program holding the database's write lock stalls
    the commits here, as in the test above."""
    limit = JournalWriter.MAX_WAITING
    count = limit + QUEUE_PER_ROBOT + 500  # past the rows waiting, one scan held and the robot's FIFO
    post_scans(durable.base_url, "bounded", "r", range(1))

    def scrape() -> dict[str, float]:
        text = httpx.get(f"{durable.base_url}/metrics").text
        return {s.name: s.value for f in text_string_to_metric_families(text) for s in f.samples}

    def robot() -> dict:
        return httpx.get(f"{durable.base_url}/maps/bounded").json()["stats"]["robots"]["r"]

    data_dir = Path(durable.args[durable.args.index("--data-dir") + 1])
    deferred = scrape()["fleetmap_zenoh_scans_deferred_total"]  # the module's earlier tests'
    # Open until every scan is in: the deferred ones wait in its cache, which close() gives up.
    with ScanPublisher("bounded", "r", connect=[durable.zenoh_endpoint], backlog=count) as pub:
        assert pub.wait_connected(20), pub.last_connect_error
        holder = sqlite3.connect(data_dir / DB_NAME, isolation_level=None, timeout=30)
        holder.execute("BEGIN EXCLUSIVE")
        try:
            for seq in range(1, count + 1):
                pub.publish(
                    Scan.from_fan((0.0, 0.5, 0.001 * seq), -1.5, 0.05, [2.0] * 61, 0.1, 10.0), seq=seq
                )
            # Until the service has seen every scan: waiting for its commit, queued, held by a
            # worker, or deferred (left in the robot's cache), or until more wait than the bound.
            stalled = wait_for(
                lambda: (
                    (
                        (m := scrape())["fleetmap_journal_rows_waiting"] > limit
                        or m["fleetmap_journal_rows_waiting"]
                        + m["fleetmap_queue_depth"]
                        + m["fleetmap_zenoh_scans_deferred_total"]
                        - deferred
                        >= count - 1
                    )
                    and m
                ),
                25,
                what="every scan taken in while the commits stall",
            )
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        assert stalled["fleetmap_journal_rows_waiting"] <= limit
        assert stalled["fleetmap_zenoh_scans_deferred_total"] > deferred
        # The disk moves again: every scan is integrated (none applied and lost, none dropped).
        report = pub.flush(60)
    assert report.confirmed, report
    final = robot()
    # lost 1: the publisher's session, a restart after the REST scan, began at seq 1, not 0.
    assert (final["not_durable"], final["dropped"], final["lost"]) == (0, 0, 1), final
    assert final["scans_integrated"] == count + 1


def test_a_scrape_holds_the_registry_lock_only_to_copy_the_counters() -> None:
    """Every scan's submit and integration take the registry's lock. A scrape built its 8 samples a
    robot under one hold of it: at 45,000 robots (40 maps of 1024) that held it for a second, and
    every scan waited that long (a scan's answer took 990 ms during a scrape, 6-14 ms otherwise).
    Now the counters are copied one map at a time and the samples built with the lock free."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    from fleetmap.metrics import RegistryCollector
    from fleetmap.registry import MapRegistry

    registry = MapRegistry()
    for map_id in ("a", "b"):
        entry, _ = registry.create(map_id)
        for k in range(3):
            entry.robot(f"r{k}")
    held_while_building = []
    collector = RegistryCollector(registry)
    original = {cls: cls.add_metric for cls in (CounterMetricFamily, GaugeMetricFamily)}

    def watching(cls: type) -> object:
        def add_metric(self: object, labels: list[str], value: float, *args: object, **kw: object) -> None:
            if registry.lock._is_owned():  # type: ignore[attr-defined]
                held_while_building.append(labels)
            original[cls](self, labels, value, *args, **kw)  # type: ignore[arg-type]

        return add_metric

    with pytest.MonkeyPatch.context() as patch:
        for cls in original:
            patch.setattr(cls, "add_metric", watching(cls))
        families = {f.name: f for f in collector.collect()}
    assert held_while_building == []
    online = families["fleetmap_robot_online"].samples
    assert [(s.labels["map"], s.labels["robot"]) for s in online] == [
        (m, f"r{k}") for m in ("a", "b") for k in range(3)
    ]


def test_the_zenoh_session_limit_is_reported_and_warned_of_when_reached(tmp_path: Path) -> None:
    """The service's router accepts `transport/unicast/max_sessions` robots (Zenoh's default 1000)
    and refuses the next ones at their handshake; they retry for ever, seeing what they see with no
    service at all. The service said nothing of it, nor how many sessions it held: an operator of
    1001 robots had no sign why one never showed. Now /healthz and /metrics give the sessions and
    the limit, and a warning says when the limit is reached (as the config file set it here)."""
    config = tmp_path / "zenoh.json5"
    config.write_text("{ transport: { unicast: { max_sessions: 2 } } }")
    with ServiceProcess(tmp_path, ["--in-memory", "--zenoh-config", str(config)]) as svc:
        status = httpx.get(f"{svc.base_url}/healthz").json()["zenoh"]
        assert status["sessions"] == 0 and status["max_sessions"] == 2
        robots = [zenoh.open(zenoh_client_config(svc.zenoh_endpoint)) for _ in range(2)]
        try:
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(zenoh_client_config(svc.zenoh_endpoint))  # the third: refused
            wait_for(
                lambda: httpx.get(f"{svc.base_url}/healthz").json()["zenoh"]["sessions"] == 2,
                10, what="two sessions in /healthz",
            )  # fmt: skip
            wait_for(
                lambda: "holds 2 Zenoh sessions, its limit (transport/unicast/max_sessions)" in svc.logs(),
                10, what="the warning",
            )  # fmt: skip
            metrics = {
                s.name: s.value
                for f in text_string_to_metric_families(httpx.get(f"{svc.base_url}/metrics").text)
                for s in f.samples
            }
            assert metrics["fleetmap_zenoh_sessions"] == 2 and metrics["fleetmap_zenoh_max_sessions"] == 2
            robots.pop().close()
            wait_for(
                lambda: httpx.get(f"{svc.base_url}/healthz").json()["zenoh"]["sessions"] == 1,
                10, what="one session left",
            )  # fmt: skip
            robots.append(zenoh.open(zenoh_client_config(svc.zenoh_endpoint)))  # room again
        finally:
            for robot in robots:
                robot.close()


def test_zenoh_sessions_are_held_to_what_the_descriptors_leave_http(tmp_path: Path) -> None:
    """Each robot's session holds one of the service's file descriptors, and Zenoh accepted its
    default 1000 whatever `ulimit -n` was: with 400 descriptors, 365 robots took all of them, and
    /healthz, the REST API and the viewer went unanswered ("cannot accept HTTP connections: Too many
    open files", 340 a second) for as long as the robots stayed. HTTP's limit was lowered to the
    descriptors, Zenoh's not. Now Zenoh's sessions are lowered too, with a warning, so that HTTP
    keeps its share: with 500 descriptors, 116 beyond the 384 kept for storage, half each."""
    descriptors = 500
    limit = (descriptors - RESERVED_DESCRIPTORS) // 2

    def low_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (descriptors, descriptors))

    with ServiceProcess(tmp_path, ["--in-memory"], preexec_fn=low_limit) as svc:
        status = httpx.get(f"{svc.base_url}/healthz").json()["zenoh"]
        assert status["max_sessions"] == limit
        assert f"at most {limit} Zenoh sessions (robots), not 1000" in svc.logs()
        metrics = {
            s.name: s.value
            for f in text_string_to_metric_families(httpx.get(f"{svc.base_url}/metrics").text)
            for s in f.samples
        }
        assert metrics["fleetmap_http_connections_limit"] == limit
        robots = []
        try:
            for _ in range(limit):
                robots.append(zenoh.open(zenoh_client_config(svc.zenoh_endpoint)))
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(zenoh_client_config(svc.zenoh_endpoint))
            # HTTP is still served, and says why no more robots connect.
            status = httpx.get(f"{svc.base_url}/healthz", timeout=10).json()["zenoh"]
            assert status["sessions"] == status["max_sessions"] == limit
            wait_for(lambda: "raise the service's hard ulimit -n" in svc.logs(), 10, what="the warning")
        finally:
            for robot in robots:
                robot.close()


def test_zenoh_decode_errors_say_they_count_scans_past_the_input_limits(in_memory: ServiceProcess) -> None:
    """`fleetmap_zenoh_decode_errors_total` counts well-formed scans refused at the input limits (a
    pose outside `--world-bound`, too many beams) as well as undecodable ones (docs/protocol.md,
    "Sequence numbers"), but its HELP text ("Zenoh scan messages not decoded") and the table of
    docs/api.md ("scans that could not be decoded (a robot's bug, or garbage)") said only the
    latter: an operator reading a rise of it as garbage on the network looked in the wrong place."""
    session = zenoh.open(zenoh_client_config(in_memory.zenoh_endpoint))
    try:
        publisher = session.declare_publisher("fleetmap/m/far/scan", encoding=zenoh.Encoding(BINARY_ENCODING))
        wait_for(lambda: publisher.matching_status.matching, 10, what="the service's subscriber")
        far = Scan.from_fan((1e9, 0.0, 0.0), -1.0, 0.01, [3.0] * 10, 0.05, 30.0)
        publisher.put(codec.encode_binary(far, 0, stamp=1.0, session=7))

        def family() -> Metric | None:
            text = httpx.get(f"{in_memory.base_url}/metrics").text
            found = [
                f for f in text_string_to_metric_families(text) if f.name == "fleetmap_zenoh_decode_errors"
            ]
            return found[0] if found and found[0].samples[0].value == 1 else None

        counted = wait_for(family, 10, what="the scan past the world bound counted")
    finally:
        session.close()
    assert "input limits" in counted.documentation, counted.documentation
    row = next(
        line
        for line in (Path(__file__).resolve().parent.parent / "docs" / "api.md").read_text().splitlines()
        if "decode_errors_total` |" in line
    )
    assert "input limits" in row and "world-bound" in row, row


def test_journal_rows_say_they_count_cleared_windows_too(tmp_path: Path) -> None:
    """A region cleared (`DELETE /maps/{id}/region`) is a journal row between the scans, and
    `fleetmap_journal_rows_total` counts it, but its HELP text ("Journal rows (scans) committed")
    and docs/api.md ("journal transactions and scans committed") said scans only: after a clear it
    no longer matched the scans integrated, with nothing to say why."""
    with ServiceProcess(tmp_path, ["--data-dir", str(tmp_path / "data")]) as svc:
        post_scans(svc.base_url, "m", "r", range(1, 3))

        def rows() -> Metric:
            text = httpx.get(f"{svc.base_url}/metrics").text
            return next(f for f in text_string_to_metric_families(text) if f.name == "fleetmap_journal_rows")

        assert rows().samples[0].value == 2
        window = {"xmin": -1, "ymin": -1, "xmax": 1, "ymax": 1}
        assert httpx.delete(f"{svc.base_url}/maps/m/region", params=window).status_code == 200
        counted = rows()
    assert counted.samples[0].value == 3  # the clear's row
    assert "cleared" in counted.documentation, counted.documentation
    api = (Path(__file__).resolve().parent.parent / "docs" / "api.md").read_text()
    row = next(line for line in api.splitlines() if "`fleetmap_journal_rows_total` |" in line)
    assert "cleared" in row, row
