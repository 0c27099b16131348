"""`fleetmap demo`, the main job (`make demo` runs it), as a user runs it: the installed command in
a subprocess, on free ports, stopped with Ctrl-C (SIGINT). It must print the viewer's address, map
with its simulated robots over Zenoh, stop the robots and the service cleanly, and keep the map.
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from service_process import REPO_DIR, ServiceProcess, fleetmap_command, free_port, reaped

from fleetmap import cli_demo
from fleetmap.database import DataDirLock


def port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def run_demo(
    tmp_path: Path, *args: str, env: dict[str, str] | None = None
) -> tuple[subprocess.CompletedProcess[str], int]:
    """`fleetmap demo ARGS` on free loopback ports with its data in `tmp_path / "data"`, run to its
    end (60 s at most): what it did, and its HTTP port."""
    http, zenoh = free_port(), free_port()
    done = subprocess.run(
        [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
         "--data-dir", str(tmp_path / "data"), *args],
        capture_output=True, text=True, timeout=60, env=env,
    )  # fmt: skip
    return done, http


class Demo:
    """`fleetmap demo` started on free ports with `args`, what it and its service print in a file."""

    def __init__(self, tmp_path: Path, *args: str) -> None:
        self.http, self.zenoh = free_port(), free_port()
        self.data = tmp_path / "data"
        self.log = open(tmp_path / "demo.log", "w+")  # noqa: SIM115 - read back by `output`
        self.proc = subprocess.Popen(
            [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{self.http}", "--zenoh",
             f"tcp/127.0.0.1:{self.zenoh}", "--data-dir", str(self.data), *args],
            stdout=self.log, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip

    def output(self) -> str:
        self.log.seek(0)
        return self.log.read()

    def wait_until(self, done: Callable[[], bool], timeout: float, what: str) -> None:
        """Wait for `done`, failing with the output if it takes longer than `timeout` s."""
        deadline = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < deadline, f"no {what} within {timeout} s:\n{self.output()}"
            time.sleep(0.2)

    def wait_for_address(self) -> None:
        """Until it prints the viewer's address, which it does once the service answers."""
        address = f"open http://127.0.0.1:{self.http}/#map=demo"
        self.wait_until(lambda: address in self.output(), 120, "address")
        assert self.proc.poll() is None, self.output()


def test_demo_maps_until_ctrl_c_then_stops_everything_and_keeps_the_map(tmp_path: Path) -> None:
    demo = Demo(tmp_path, "--robots", "2", "--rate", "10")
    with reaped(demo.proc):
        # It prints the viewer's address once the service answers, then the robots map.
        demo.wait_for_address()
        viewer = httpx.get(f"http://127.0.0.1:{demo.http}/", timeout=5)
        assert viewer.status_code == 200 and "leaflet" in viewer.text.lower()

        def integrated() -> int:
            assert demo.proc.poll() is None, demo.output()
            r = httpx.get(f"http://127.0.0.1:{demo.http}/maps/demo", timeout=5)
            robots = r.json()["stats"]["robots"] if r.status_code == 200 else {}
            return sum(robot["scans_integrated"] for robot in robots.values())

        demo.wait_until(lambda: integrated() >= 30, 120, "30 scans integrated")
        demo.proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert demo.proc.wait(60) == 0, demo.output()
    text = demo.output()
    assert "Traceback" not in text, text
    # Before the address, the engine's kernels: loaded here (the tests' cache is warm). A first start
    # after an install compiles them for up to minutes and says how long (tests/test_compiled_cache.py).
    assert "loading the engine's compiled kernels" in text and "engine ready in" in text, text
    summary = re.search(r"fleetmap demo: 2 robots published (\d+) scans \((\d+) dropped\)", text)
    assert summary is not None, text
    published, dropped = int(summary[1]), int(summary[2])
    assert published >= 30 and dropped == 0
    # Its last line, below the service's own shutdown lines, says where the map is kept.
    assert text.rstrip().splitlines()[-1] == f"fleetmap demo: stopped; the map is kept in {demo.data}", text

    # The service is gone: both of its ports are free again.
    assert port_is_free(demo.http) and port_is_free(demo.zenoh)

    # The map was kept: a service restarted on the demo's data directory holds every scan published.
    with ServiceProcess(tmp_path, ["--data-dir", str(demo.data)]) as service:
        robots = httpx.get(f"{service.base_url}/maps/demo", timeout=5).json()["stats"]["robots"]
        assert sum(robot["scans_integrated"] for robot in robots.values()) == published
        assert len(robots) == 2


def test_demo_refuses_addresses_another_service_holds(tmp_path: Path) -> None:
    """With another service on its HTTP port, the demo's own service would die while the other one
    answered its health checks, and the robots would map into that one: it refuses at once."""
    http, zenoh = free_port(), free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as other:
        other.bind(("127.0.0.1", http))
        other.listen()
        done = subprocess.run(
            [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
             "--data-dir", str(tmp_path / "data"), "--seconds", "5"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"cannot listen on 127.0.0.1:{http}: Address already in use" in done.stderr
    # The README starts the demo with `make demo`, which takes the options in DEMO_ARGS. The other
    # service is most likely a demo or `fleetmap serve` started in the same folder, which holds
    # ./fleetmap-data: the advice names another data directory too, or following it failed in turn.
    assert (
        'make demo DEMO_ARGS="--http 127.0.0.1:8001 --zenoh tcp/127.0.0.1:7448 --data-dir ./fleetmap-data-2"'
        in done.stderr
    )
    assert "Traceback" not in done.stderr
    assert "open http" not in done.stdout and not (tmp_path / "data").exists()
    assert port_is_free(zenoh)


def test_demo_whose_service_cannot_start_says_so_without_blaming_the_ports(tmp_path: Path) -> None:
    """Free ports, but the data directory held by another service (a `fleetmap serve` started in the
    same folder): the service says so, and the demo's own line said "is http://... or the Zenoh port
    in use?", which sent the user after the wrong cause."""
    http, zenoh = free_port(), free_port()
    data = tmp_path / "data"
    data.mkdir()
    held = DataDirLock(data)  # another process's lock, as the demo's service sees it
    try:
        done = subprocess.run(
            [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
             "--data-dir", str(data), "--seconds", "5"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        held.release()
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"data directory {data} is in use by another fleetmap service" in done.stderr, done.stderr
    assert "fleetmap demo: error: the service exited with code 2 before it was ready" in done.stderr
    assert "port in use" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert "open http" not in done.stdout


@pytest.mark.parametrize(
    ("option", "says"),
    [
        (["--robots", "0"], "--robots must be at least 1, got 0"),
        (["--rate", "0"], "--rate must be a number of scans per second above 0, got 0"),
        # Slower than a thread can wait for: the service started, and the robots' first waits
        # ended the demo in SimError's traceback ("OverflowError: timestamp out of range"). Named as
        # the option, as the demo's other errors are.
        (["--rate", "1e-300"], "--rate 1e-300 is too slow: a scan every 1e+300 s"),
        (["--seconds", "-1"], "--seconds must be 0 or more (or left out: until Ctrl-C), got -1"),
        (["--map", "bad/id"], "--map 'bad/id' is no map id: use 1 to 64 characters from A-Z a-z 0-9 _ -"),
        # Started the service, waited for it, then ended in numpy's traceback.
        (["--seed", "-1"], "--seed must be 0 or more, got -1"),
        # More robots than any machine has threads for (3 per robot): a ValueError traceback from
        # the simulation once the service was up.
        (["--robots", "1000000"], "1000000 robots need about 3000064 threads (3 per robot)"),
        # Port 0 (`serve`'s "any free port"): the demo waited 120 s for an answer on port 0 while
        # its service ran on another one, or its robots waited for ever to connect to port 0.
        (["--http", "127.0.0.1:0"], "--http 127.0.0.1:0: the demo needs a fixed port, not 0"),
        (["--zenoh", "tcp/127.0.0.1:0"], "--zenoh tcp/127.0.0.1:0: the demo needs a fixed port, not 0"),
        # An OverflowError traceback from the demo's check of the port.
        (["--zenoh", "tcp/127.0.0.1:99999"], "--zenoh tcp/127.0.0.1:99999: port must be at most 65535"),
        # Not this machine's address (TEST-NET-1): "is another fleetmap service running?" sent the
        # user after a service that was not there.
        (
            ["--http", "192.0.2.1:8000"],
            "cannot listen on 192.0.2.1:8000: Cannot assign requested address (the demo's service runs on "
            "this machine: give --http one of its addresses and a port it may use, e.g. 127.0.0.1:8001)",
        ),
        # Refused by the demo itself, not by its service after the demo started it.
        (["--http", "8000"], "--http '8000': expected HOST:PORT, e.g. 127.0.0.1:8000"),
    ],
)
def test_demo_refuses_a_fleet_it_cannot_run_before_starting_anything(
    tmp_path: Path, option: list[str], says: str
) -> None:
    """`fleetmap demo --robots 0` (or a rate of 0, a bad map id) started the service, waited for it,
    then ended in a ValueError traceback from the simulation."""
    done, _ = run_demo(tmp_path, *option)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith(f"fleetmap demo: error: {says}") and done.stderr.count("\n") == 1
    assert done.stdout == "" and not (tmp_path / "data").exists()


def test_demo_serves_beyond_loopback_with_insecure_as_the_refusal_says(tmp_path: Path) -> None:
    """Without API tokens the service refuses a non-loopback --http and says to give --insecure,
    which the demo had no option for: a demo shown to another machine (or run in a VM and watched
    from its host) could not be started at all."""
    http, zenoh = free_port(), free_port()
    command = [*fleetmap_command(), "demo", "--http", f"0.0.0.0:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
               "--data-dir", str(tmp_path / "data"), "--robots", "1", "--seconds", "0"]  # fmt: skip
    refused = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "give --insecure to accept that" in refused.stderr, refused.stderr
    # Said by the demo, before its service starts, in one line: the service's refusal named
    # --auth-tokens FILE and $FLEETMAP_TOKENS, neither of which the demo takes (it leaves out every
    # FLEETMAP_ variable), beside --insecure.
    assert refused.stderr.startswith("fleetmap demo: error: ") and refused.stderr.count("\n") == 1
    assert "--auth-tokens" not in refused.stderr and "FLEETMAP_TOKENS" not in refused.stderr
    assert not (tmp_path / "data").exists()
    # `:PORT`, all interfaces as `serve --http` takes it: the demo polled and printed `http://:PORT/`,
    # which nothing answers, and waited for its service until it gave up.
    command[command.index("--http") + 1] = f":{http}"
    done = subprocess.run([*command, "--insecure"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"open http://0.0.0.0:{http}/#map=demo" in done.stdout, done.stdout
    assert "Traceback" not in done.stderr, done.stderr


def test_demo_finds_its_service_whatever_proxy_the_environment_names(tmp_path: Path) -> None:
    """With HTTP_PROXY set (a company network) and 127.0.0.1 not in NO_PROXY, the demo asked the
    proxy for its own service's /healthz (a dead one here), and gave up after 120 s on a service
    that ran."""
    proxy = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    env = {key: value for key, value in os.environ.items() if key.lower() != "no_proxy"}
    env |= {"HTTP_PROXY": proxy, "http_proxy": proxy, "ALL_PROXY": proxy, "all_proxy": proxy}
    done, http = run_demo(tmp_path, "--robots", "1", "--seconds", "0", env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"open http://127.0.0.1:{http}/#map=demo" in done.stdout, done.stdout
    # One robot, in the singular ("to watch 1 robots", "1 robots published 0 scans").
    assert "to watch 1 robot map a floor plan" in done.stdout, done.stdout
    assert "fleetmap demo: 1 robot published 0 scans (0 dropped)" in done.stdout, done.stdout


def test_demo_warns_of_the_scans_its_robots_skipped_falling_behind_their_rate(tmp_path: Path) -> None:
    """Robots that fall behind their rate skip scans: `fleetmap sim` warns of them, the demo said
    nothing, its summary counting only what was sent. 50000 scans/s is more than one robot's
    simulation can make on any machine."""
    done, _http = run_demo(tmp_path, "--robots", "1", "--rate", "50000", "--seconds", "1")
    assert done.returncode == 0, done.stdout + done.stderr
    warning = re.search(
        r"fleetmap demo: warning: (\d+) scans skipped: the robot fell behind 50000 scans/s, this machine is "
        r"too busy for 1 robot at that rate \(run fewer, or a lower --rate\)",
        done.stderr,
    )
    assert warning is not None and int(warning[1]) > 0, done.stderr


def test_demo_sets_its_service_up_with_its_own_options_not_the_environments(tmp_path: Path) -> None:
    """FLEETMAP_* variables meant for `fleetmap serve` reached the demo's service: FLEETMAP_IN_MEMORY
    kept no map while the demo said where it was kept, and a FLEETMAP_ZENOH_CONFIG (a TLS router's,
    here one that is missing) stopped the service or left the demo's robots waiting. The demo now
    leaves them out and says so. The Python client's $FLEETMAP_TOKEN (docs/clients.md) is no
    setting of the service: it is left out unnamed, where the demo said "fleetmap serve reads them"."""
    env = os.environ | {"FLEETMAP_IN_MEMORY": "1", "FLEETMAP_ZENOH_CONFIG": str(tmp_path / "tls.json5")}
    env["FLEETMAP_TOKEN"] = "client-token-aaaaaaaaaaaaaaaa"
    done, _ = run_demo(tmp_path, "--robots", "1", "--seconds", "0", env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    ignored = "fleetmap demo: its service ignores FLEETMAP_IN_MEMORY, FLEETMAP_ZENOH_CONFIG (the demo's"
    assert ignored in done.stdout and "FLEETMAP_TOKEN" not in done.stdout, done.stdout
    assert done.stdout.rstrip().endswith(f"the map is kept in {tmp_path / 'data'}"), done.stdout
    assert (tmp_path / "data" / "fleetmap.db").is_file()  # kept where it says


def test_demo_whose_service_cannot_store_the_map_at_stop_says_so_and_fails(tmp_path: Path) -> None:
    """Stopped while its disk fails, the service's last snapshot fails and it exits 1, saying which
    maps a restart finds as they were stored last; the demo exited 0 all the same (only its "stopped;
    the map is kept" line went missing). It now ends with an error, exit 2 as its other errors. The
    failing disk is the service's RLIMIT_FSIZE lowered to 1 byte, as in test_durability.py (a full
    file system would need a mount, which tests cannot make; the service's own last lines go to a
    file here, so they fail to be written too)."""
    resource = pytest.importorskip("resource")
    demo = Demo(tmp_path, "--robots", "1", "--rate", "10")
    with reaped(demo.proc):
        demo.wait_for_address()
        (service,) = (
            int(pid)
            for pid in Path(f"/proc/{demo.proc.pid}/task/{demo.proc.pid}/children").read_text().split()
        )
        _, hard = resource.prlimit(service, resource.RLIMIT_FSIZE)
        resource.prlimit(service, resource.RLIMIT_FSIZE, (1, hard))

        def scans_not_durable() -> int:
            storage = httpx.get(f"http://127.0.0.1:{demo.http}/healthz", timeout=5).json()["storage"]
            return storage["scans_not_durable"]

        demo.wait_until(lambda: scans_not_durable() > 0, 60, "scans whose journal commit failed")
        demo.proc.send_signal(signal.SIGINT)  # Ctrl-C
        code = demo.proc.wait(60)
    text = demo.output()
    assert code == 2, text
    assert "fleetmap demo: error: the service did not stop cleanly (exit code 1)" in text, text
    assert "the map is kept in" not in text.rstrip().splitlines()[-1], text


def test_demo_waits_for_a_slow_first_start_as_long_as_its_service_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A first start compiles the kernels, a minute or two on a busy machine and several on a small
    board: the demo gave up after a fixed 120 s, and killed the service with its compile. It now
    waits while the service runs, saying so now and then. The service here is a stand-in that
    answers `/healthz` after 1.5 s, and the demo's clock runs 100 s per look (with the stand-in,
    what a real slow start would take minutes to show, which the test run cannot spend)."""
    (tmp_path / "healthz").write_text("ok")
    port = free_port()
    server = subprocess.Popen(
        [
            sys.executable, "-c",
            "import functools, http.server, sys, time; time.sleep(1.5); http.server.ThreadingHTTPServer("
            "('127.0.0.1', int(sys.argv[1])), functools.partial(http.server.SimpleHTTPRequestHandler, "
            "directory=sys.argv[2])).serve_forever()",
            str(port), str(tmp_path),
        ],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    clock = itertools.count(0.0, 100.0)
    fast = types.SimpleNamespace(monotonic=lambda: next(clock), sleep=time.sleep)
    monkeypatch.setattr(cli_demo, "time", fast)
    try:
        cli_demo._wait_for_service(server, f"http://127.0.0.1:{port}/", threading.Event())
        assert server.poll() is None  # it answered, and runs on
    finally:
        server.kill()
        server.wait()
    out = capsys.readouterr().out
    assert "fleetmap demo: still waiting for the service to answer" in out, out


def test_demo_stops_when_its_service_dies(tmp_path: Path) -> None:
    http, zenoh = free_port(), free_port()
    demo = subprocess.Popen(
        [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
         "--data-dir", str(tmp_path / "data"), "--robots", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    with reaped(demo):
        assert demo.stdout is not None
        for line in demo.stdout:
            if "open http" in line:
                break
        service = subprocess.run(
            ["pgrep", "-f", f"fleetmap.server --http 127.0.0.1:{http} "], capture_output=True, text=True
        ).stdout.split()
        assert len(service) == 1
        os.kill(int(service[0]), signal.SIGKILL)
        out, _ = demo.communicate(timeout=30)
    assert demo.returncode == 2 and "the service stopped unexpectedly" in out, out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_demo_stopped_by_kill_or_a_closed_terminal_stops_its_service_too(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """`kill`, `timeout` or `docker stop` (SIGTERM), or the terminal closed (SIGHUP), ended the demo
    at once and left its service running, holding the ports and the data directory: the next `make
    demo` found them in use. Now they stop it as Ctrl-C does."""
    demo = Demo(tmp_path, "--robots", "1")
    with reaped(demo.proc):
        demo.wait_for_address()
        demo.proc.send_signal(sig)
        assert demo.proc.wait(60) == 0, demo.output()
    out = demo.output()
    assert out.rstrip().splitlines()[-1] == f"fleetmap demo: stopped; the map is kept in {demo.data}", out
    assert port_is_free(demo.http) and port_is_free(demo.zenoh)
    DataDirLock(demo.data).release()  # no service holds the data directory (StorageError otherwise)


def test_a_killed_demo_takes_its_service_down_with_it(tmp_path: Path) -> None:
    """A demo killed outright (SIGKILL, a crash) cannot stop its service itself: the kernel sends
    the service SIGTERM when the demo dies (prctl's death signal), and it stops cleanly."""
    demo = Demo(tmp_path, "--robots", "1")
    with reaped(demo.proc):
        demo.wait_for_address()
        demo.proc.kill()
        demo.proc.wait(10)
    demo.wait_until(lambda: port_is_free(demo.http) and port_is_free(demo.zenoh), 60, "ports freed")
    # A clean stop, its map saved.
    demo.wait_until(lambda: "fleetmap.server: stopped" in demo.output(), 30, "clean stop of the service")


def test_make_demo_on_a_fresh_clone_says_what_it_installs_and_how_long_it_takes(tmp_path: Path) -> None:
    """A fresh clone's first `make demo` installs from PyPI for minutes with pip quiet: it says so
    first, rather than leaving a newcomer before a silent `pip install --quiet -e .`. (`make -n`
    shows what it would run, without running it.)"""
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(REPO_DIR / name, tmp_path / name)
    for target, says, install in (
        ("demo", "fleetmap: installing fleetmap and its dependencies into .venv/ (from PyPI: a few minutes",
         "pip install --quiet -e ."),
        ("lint", "fleetmap: adding the test and benchmark tools to .venv/ (a few minutes",
         "pip install --quiet -e '.[test]'"),
    ):  # fmt: skip
        plan = subprocess.run(
            ["make", "-n", target], cwd=tmp_path, capture_output=True, text=True, timeout=30
        )
        assert plan.returncode == 0, plan.stderr
        lines = plan.stdout.splitlines()
        said = next(k for k, line in enumerate(lines) if says in line)
        installs = next(k for k, line in enumerate(lines) if line.endswith(install))
        assert said < installs, plan.stdout  # said before pip starts


def test_make_demo_after_a_first_install_interrupted_in_venv_makes_the_venv_again(tmp_path: Path) -> None:
    """Ctrl-C while the first `make demo` ran `python3 -m venv` (its ensurepip) left a .venv/ whose
    python has no pip: every later `make demo` stopped at "No module named pip" until the user
    deleted .venv/ by hand. The next run makes it again. (Offline: pip's index is turned off, so the
    install itself stops later, at fleetmap's dependencies, once pip runs.)"""
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(REPO_DIR / name, tmp_path / name)
    venv = tmp_path / ".venv"
    # What the interrupted venv left: its interpreter, no pip.
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    assert subprocess.run([venv / "bin" / "python", "-m", "pip", "--version"], capture_output=True).returncode
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_FIND_LINKS": str(tmp_path / "no-wheels")}
    run = subprocess.run(
        ["make", "demo", f"PYTHON={sys.executable}"], cwd=tmp_path, capture_output=True, text=True,
        timeout=300, env=env,
    )  # fmt: skip
    assert "No module named pip" not in run.stdout + run.stderr, run.stdout + run.stderr
    pip = subprocess.run([venv / "bin" / "python", "-m", "pip", "--version"], capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr


def _python_older_than_3_11() -> str | None:
    """An interpreter of this machine older than fleetmap's Python 3.11 (on the PATH or pyenv's),
    or None."""
    candidates = [shutil.which(f"python3.{minor}") for minor in range(10, 7, -1)]
    candidates += sorted(str(p) for p in Path.home().glob(".pyenv/versions/3.*/bin/python3"))
    for candidate in filter(None, candidates):
        version = subprocess.run(
            [candidate, "-c", "import sys; print(sys.version_info[1])"], capture_output=True, text=True
        )
        if version.returncode == 0 and int(version.stdout) < 11:
            return candidate
    return None


def test_make_demo_refuses_a_python_too_old_and_replaces_the_venv_made_of_one(tmp_path: Path) -> None:
    """fleetmap needs Python 3.11: with an older `python3`, `make demo` made .venv/ of it, upgraded
    pip, and only then pip refused ("requires a different Python"); that .venv/ stayed, so the next
    `make demo PYTHON=python3.12` went on using it and failed the same way until the user deleted it.
    Now the old Python is refused first, saying how to give another, and a .venv/ of one is made
    again with the one given. (Offline: pip's index is off, so the install stops later.)"""
    old = _python_older_than_3_11()
    if old is None:
        pytest.skip("no Python older than 3.11 on this machine (python3.8-3.10 or pyenv's)")
    for name in ("Makefile", "pyproject.toml"):
        shutil.copy(REPO_DIR / name, tmp_path / name)
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_FIND_LINKS": str(tmp_path / "no-wheels")}
    refused = subprocess.run(
        ["make", "demo", f"PYTHON={old}"], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert refused.returncode != 0
    assert f"fleetmap: needs Python 3.11 or newer, and {old} is Python 3." in refused.stderr, refused.stderr
    assert "make demo PYTHON=python3.12" in refused.stderr
    assert not (tmp_path / ".venv").exists()  # nothing made of it
    # A .venv/ of the old Python (made before this check, or by hand) is made again with the new.
    subprocess.run([old, "-m", "venv", str(tmp_path / ".venv")], check=True, timeout=300)
    subprocess.run(
        ["make", "demo", f"PYTHON={sys.executable}"], cwd=tmp_path, capture_output=True, timeout=300, env=env
    )
    version = subprocess.run(
        [tmp_path / ".venv" / "bin" / "python", "-c", "import sys; print(sys.version_info[:2] >= (3, 11))"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert version.stdout.strip() == "True", version


def test_the_data_directories_the_demo_names_are_not_left_untracked_in_git() -> None:
    """A demo refused for addresses in use says to give it `--data-dir ./fleetmap-data-2`: git
    ignored ./fleetmap-data only, so that one showed in `git status` as untracked, its SQLite
    files one `git add -A` away from a commit."""
    if not (REPO_DIR / ".git").exists():
        pytest.skip("not a git checkout")
    for directory in (cli_demo.DEFAULT_DATA_DIR, "./fleetmap-data-2"):
        path = Path(directory) / "maps.sqlite"  # a file in it
        ignored = subprocess.run(
            ["git", "check-ignore", "--no-index", "-q", str(path)], cwd=REPO_DIR, timeout=30
        )
        assert ignored.returncode == 0, f"{directory} is not ignored by .gitignore"


def test_make_clean_removes_the_tools_and_keeps_the_maps(tmp_path: Path) -> None:
    """`make clean` removed out/ too, a leftover of a demo that once built its map there: out/ now
    holds only what the README's `fleetmap build ... --out out/intel` wrote, which `make clean`
    deleted without a word. It removes the installed tools and their caches, and keeps the maps."""
    shutil.copy(REPO_DIR / "Makefile", tmp_path / "Makefile")
    kept = [tmp_path / "out" / "intel" / "map.yaml", tmp_path / "fleetmap-data" / "maps.sqlite"]
    removed = [tmp_path / name / "x" for name in (".venv", ".pytest_cache", ".ruff_cache", ".mypy_cache")]
    for path in kept + removed:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x")
    done = subprocess.run(["make", "clean"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert all(path.exists() for path in kept), done.stdout
    assert not any(path.parent.exists() for path in removed), done.stdout


def test_a_second_demo_says_its_map_holds_an_earlier_runs_scans(tmp_path: Path) -> None:
    """The map is kept in the data directory, and a second demo's robots map into it: with another
    --seed, another floor plan drawn over the first, silently, which looked like a broken map. The
    second run says what the map holds already and how to start a new one."""
    http, zenoh = free_port(), free_port()
    data = tmp_path / "data"

    def demo(seed: int) -> str:
        done = subprocess.run(
            [*fleetmap_command(), "demo", "--http", f"127.0.0.1:{http}", "--zenoh", f"tcp/127.0.0.1:{zenoh}",
             "--data-dir", str(data), "--robots", "1", "--seconds", "1", "--seed", str(seed)],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout

    first = demo(1)
    assert "already holds" not in first
    published = int(re.search(r"1 robot published (\d+) scans?", first)[1])  # type: ignore[index]
    second = demo(2)
    note = re.search(
        rf"fleetmap demo: map demo in {re.escape(str(data))} already holds (\d+) scans? of an earlier run, "
        r"which the robots add to \(another --seed draws another floor plan over it\): --map NAME starts "
        r"a new map\n",
        second,
    )
    assert note is not None, second
    assert 0 < int(note[1]) <= published
    assert second.index(note[0]) < second.index("fleetmap demo: open http")  # said before the robots start
