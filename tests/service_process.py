"""Real processes for end-to-end tests: the service (`python -m fleetmap.server`) and robots
(`tests/robot_process.py`), on free loopback ports, with their output kept for failure messages.

    with ServiceProcess(tmp_path) as svc:          # started, /healthz answered
        httpx.get(f"{svc.base_url}/maps")
        robot = RobotProcess(svc.zenoh_endpoint, "m", "r1", sim=1, count=20, log_dir=tmp_path)
        robot.start(); robot.wait()

`ServiceProcess.stop()` sends SIGTERM, waits, and only then kills; it returns the exit code so a test
can assert a clean shutdown.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import TypeVar

import httpx

TESTS_DIR = Path(__file__).resolve().parent
REPO_DIR = TESTS_DIR.parent
#: The shared recorded datasets (../shared/datasets from the repository); may be absent.
DATASETS_DIR = REPO_DIR.parent / "shared" / "datasets"
ROBOT_SCRIPT = TESTS_DIR / "robot_process.py"

T = TypeVar("T")


def fleetmap_command() -> list[str]:
    """The `fleetmap` console script `make` installs beside the interpreter (what users run), else
    the module."""
    script = Path(sys.executable).with_name("fleetmap")
    return [str(script)] if script.exists() else [sys.executable, "-m", "fleetmap"]


@contextlib.contextmanager
def reaped(proc: subprocess.Popen[str]) -> Iterator[subprocess.Popen[str]]:
    """Yield `proc`, and kill it on the way out if it still runs, so a failed test leaves no process."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


#: Where `free_port` picks: below Linux's ephemeral range (32768-60999 by default), from which every
#: outgoing connection takes its local port. A port the OS handed out from that range (`bind` to 0)
#: could be taken by some test's client connection before the service bound it: CI saw a service
#: fail to start with "Address already in use" while two test processes ran.
_PORTS = (20000, 32000)


#: Ports `free_port` gave out in this process: never given twice. Free again once released, a port
#: came back to the next call (1 in 12,000) and a service got the same one for HTTP and Zenoh; its
#: Zenoh listener then found its own HTTP socket there ("Address already in use", CI 2026-11-28).
_given_ports: set[int] = set()


def _port_range() -> tuple[int, int]:
    """The part of `_PORTS` this process picks from: under pytest-xdist, worker k of n takes the k-th
    of n equal parts, so that two workers never pick the same port. Picking from the whole range,
    two services starting at once in two workers could be given one port, free when each looked,
    and one of them failed to start ("Address already in use", CI 2026-11-29)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ... in xdist's workers
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not worker.startswith("gw") or count <= 1:
        return _PORTS
    k, span = int(worker[2:]), (_PORTS[1] - _PORTS[0]) // count
    return _PORTS[0] + k * span, _PORTS[0] + (k + 1) * span


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now, outside the ephemeral range, not given out before by
    this process, nor one another xdist worker of this run may give (`_port_range`). A small race
    remains until the child binds it, with other programs picking from the same range."""
    rng = random.Random()  # seeded from the OS
    low, high = _port_range()
    for _ in range(1000):
        port = rng.randrange(low, high)
        if port in _given_ports:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _given_ports.add(port)
        return port
    raise RuntimeError(f"no free TCP port in {low}-{high} on 127.0.0.1")


def _child_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


class ServiceProcess:
    """`python -m fleetmap.server` on free ports: HTTP on 127.0.0.1:<port>, Zenoh listening on
    tcp/127.0.0.1:<zport>, plus `extra_args`. Output goes to `log_dir/service-<port>.log`. `env`
    adds to (or overrides) the test's environment variables, `preexec_fn` runs in the child before
    it starts (e.g. to set a resource limit), as `subprocess.Popen`'s."""

    def __init__(
        self, log_dir: Path, extra_args: Sequence[str] = (), startup_timeout: float = 60.0,
        env: Mapping[str, str] | None = None, preexec_fn: Callable[[], None] | None = None,
    ) -> None:  # fmt: skip
        self.port = free_port()
        self.zenoh_port = free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.zenoh_endpoint = f"tcp/127.0.0.1:{self.zenoh_port}"
        # Durable storage is on by default: each service gets its own data directory unless the test
        # names one (or asks for --in-memory), so services running side by side never share one.
        storage = (
            []
            if {"--data-dir", "--in-memory"} & set(extra_args)
            else ["--data-dir", str(Path(log_dir) / f"data-{self.port}")]
        )
        self.args = [
            sys.executable, "-m", "fleetmap.server",
            "--http", f"127.0.0.1:{self.port}",
            "--zenoh-listen", self.zenoh_endpoint,
            *storage,
            *extra_args,
        ]  # fmt: skip
        self.log_path = Path(log_dir) / f"service-{self.port}.log"
        self.startup_timeout = startup_timeout
        self.env, self.preexec_fn = env, preexec_fn
        self.proc: subprocess.Popen[bytes] | None = None
        self.returncode: int | None = None

    def start(self) -> ServiceProcess:
        """Start the service and wait until /healthz answers 200. Raises RuntimeError (with the
        service's output) if it exits or does not answer within `startup_timeout`."""
        log = open(self.log_path, "wb")  # noqa: SIM115 - the child writes to it until stop()
        self.proc = subprocess.Popen(
            self.args, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=_child_env(self.env), preexec_fn=self.preexec_fn,
        )  # fmt: skip
        log.close()
        deadline = time.monotonic() + self.startup_timeout
        with httpx.Client(timeout=2.0) as client:
            while time.monotonic() < deadline:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"service exited with {self.proc.returncode}:\n{self.logs()}")
                try:
                    if client.get(f"{self.base_url}/healthz").status_code == 200:
                        return self
                except httpx.TransportError:
                    pass
                time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"service did not answer /healthz within {self.startup_timeout} s:\n{self.logs()}")

    def logs(self) -> str:
        """Everything the service printed so far (stdout and stderr)."""
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = 20.0) -> int | None:
        """SIGTERM, wait up to `timeout`, then SIGKILL. Returns the exit code. Idempotent."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.returncode = self.proc.returncode
        return self.returncode

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:  # fmt: skip
        self.stop()


class RobotProcess:
    """`tests/robot_process.py` as a child process publishing to `endpoint` as robot
    `map_id`/`robot_id`. Keyword arguments become its options (`sim=3` -> `--sim 3`,
    `skip=[4, 5]` -> `--skip 4 5`); see robot_process.py for their meaning."""

    def __init__(
        self, endpoint: str, map_id: str, robot_id: str, *, log_dir: Path, **options: object
    ) -> None:
        self.map_id, self.robot_id = map_id, robot_id
        self.options = options
        self.args = [
            sys.executable, str(ROBOT_SCRIPT), "--connect", endpoint, "--map", map_id, "--robot", robot_id,
        ]  # fmt: skip
        for name, value in options.items():
            flag = "--" + name.replace("_", "-")
            if isinstance(value, list | tuple):
                self.args += [flag, *(str(v) for v in value)]
            else:
                self.args += [flag, str(value)]
        self.log_path = Path(log_dir) / f"robot-{map_id}-{robot_id}-{os.getpid()}-{id(self)}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> RobotProcess:
        log = open(self.log_path, "wb")  # noqa: SIM115 - the child writes to it until it exits
        # stdin is a pipe so that `--linger -1` robots stay online until we close it (or SIGTERM).
        self.proc = subprocess.Popen(
            self.args, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.PIPE, env=_child_env()
        )
        log.close()
        return self

    def logs(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def wait(self, timeout: float = 60.0) -> int:
        """Wait for the robot to exit; raises RuntimeError with its output unless it exits 0."""
        assert self.proc is not None, "start() first"
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            message = f"robot {self.robot_id} did not finish in {timeout} s:\n{self.logs()}"
            raise RuntimeError(message) from None
        if code != 0:
            raise RuntimeError(f"robot {self.robot_id} exited with {code}:\n{self.logs()}")
        return code

    def wait_published(self, timeout: float = 60.0) -> None:
        """Wait until the robot printed `published N` (it may still be lingering, online)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if "published" in self.logs():
                return
            if self.proc is not None and self.proc.poll() is not None:
                code = self.proc.returncode
                raise RuntimeError(f"robot {self.robot_id} exited with {code}:\n{self.logs()}")
            time.sleep(0.05)
        raise RuntimeError(f"robot {self.robot_id} did not publish in {timeout} s:\n{self.logs()}")

    def stop(self, timeout: float = 10.0) -> int | None:
        """Close stdin (a `--linger -1` robot then leaves), SIGTERM if needed, then SIGKILL."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            try:
                if self.proc.stdin:
                    self.proc.stdin.close()
                self.proc.wait(timeout / 2)
            except (subprocess.TimeoutExpired, BrokenPipeError):
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(timeout / 2)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(10)
        return self.proc.returncode


def _frames_end(data: bytes | bytearray, count: int) -> int | None:
    """Where the first `count` length-prefixed Zenoh frames of a TCP stream's `data` end, None while
    they are not all there."""
    end = 0
    for _ in range(count):
        if end + 2 > len(data):
            return None
        end += 2 + int.from_bytes(data[end : end + 2], "little")
    return end if end <= len(data) else None


#: How many of a connection's last client bytes `FreezableProxy` keeps (`freeze(sent=...)`).
_TAIL_BYTES = 4096


class FreezableProxy:
    """A TCP proxy on a free loopback port to `target_port`, each connection forwarded by two
    threads. `freeze()` stops forwarding on every connection open now, both ways, while leaving its
    sockets open: to the client the connection is alive (no FIN, no RST) and silent, as a half-open
    connection is after a peer's power cut or a NAT or proxy dropped its state. Connections made
    later are forwarded, unless `freeze(refuse_new=True)`: then they are closed at once until
    `restore()`, and the frozen ones stay silent (a link that died without anyone noticing and never
    comes back). `cut()` closes every connection and refuses new ones (closed at once) until
    `restore()`: a robot in a Wi-Fi dead zone. `target_port` may be changed at any time (a service
    restarted on another port); a connection the target refuses is closed. `refused` lists when
    (`time.monotonic()`) each connection refused by a cut or freeze came: a client's attempts.
    `delay_after_handshake(s)`: the next connection's client's bytes after its Zenoh handshake reach
    the target `s` seconds late (a service slow to take in a robot that just connected).
    `freeze(sent=b"...")` freezes only the connections whose client's last bytes hold `sent`: over
    HTTP, the one whose last request was that (a browser's event stream, its other connections left
    working). `lag`: what the target sends, its close too, reaches the client `lag` seconds late (at
    least), as over a slow link."""

    def __init__(self, target_port: int, lag: float = 0.0) -> None:
        self.target_port = target_port
        self.lag = lag
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.connections: list[tuple[socket.socket, socket.socket, threading.Event]] = []
        self.lock = threading.Lock()
        self.refusing = False
        self.refused: list[float] = []
        self._next_delay = 0.0
        #: The last `_TAIL_BYTES` each connection's client sent, by its `frozen` event.
        self.tails: dict[threading.Event, bytearray] = {}
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                if self.listener.fileno() == -1:  # close()d
                    return
                # Any other error (a connection aborted before it was accepted, EMFILE under
                # load) must not end the proxy: its listener would then only queue connections.
                time.sleep(0.01)
                continue
            try:
                if self.refusing:
                    self.refused.append(time.monotonic())
                    raise ConnectionRefusedError
                upstream = socket.create_connection(("127.0.0.1", self.target_port))
            except OSError:
                client.close()
                continue
            frozen = threading.Event()
            with self.lock:
                # A cut() or freeze(refuse_new=True) that came while the upstream was connected
                # refuses this one too: kept, it would have outlived the cut, and a client in the
                # middle of its handshake would wait for its open timeout (10 s) before trying again.
                refused = self.refusing
                if not refused:
                    self.connections.append((client, upstream, frozen))
                    tail = self.tails[frozen] = bytearray()
                    delay, self._next_delay = self._next_delay, 0.0
            if refused:
                self.refused.append(time.monotonic())
                upstream.close()
                client.close()
                continue
            for source, sink, wait, seen, lag in (
                (client, upstream, delay, tail, 0.0),
                (upstream, client, 0.0, None, self.lag),
            ):
                pump_args = (source, sink, frozen, wait, seen, lag)
                threading.Thread(target=self._pump, args=pump_args, daemon=True).start()

    @staticmethod
    def _pump(
        source: socket.socket,
        sink: socket.socket,
        frozen: threading.Event,
        delay: float = 0.0,
        tail: bytearray | None = None,
        lag: float = 0.0,
    ) -> None:
        """Forward `source` to `sink` until either closes or `frozen` is set. With `delay`, what
        follows the first two Zenoh frames (a client's InitSyn and OpenSyn, the handshake; over TCP
        each batch is prefixed with its length, 2 bytes little-endian) is sent `delay` s late.
        `tail` keeps the last `_TAIL_BYTES` forwarded. `lag`: each read, and the close, is passed
        on `lag` s after it came."""
        source.settimeout(0.05)
        handshake: bytearray | None = bytearray() if delay else None  # the client's bytes so far
        while not frozen.is_set():
            try:
                data = source.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                with contextlib.suppress(OSError):
                    sink.shutdown(socket.SHUT_RDWR)
                return
            time.sleep(lag)
            if not data or frozen.is_set():  # frozen: what arrives now is dropped, never forwarded
                if not data:
                    with contextlib.suppress(OSError):
                        sink.shutdown(socket.SHUT_WR)
                    return
                continue
            if tail is not None:
                tail += data
                del tail[:-_TAIL_BYTES]
            if handshake is not None:
                handshake += data
                end = _frames_end(handshake, 2)
                if end is not None:
                    beyond = len(handshake) - end  # the tail of `data` past the handshake
                    try:
                        sink.sendall(data[: len(data) - beyond])
                    except OSError:
                        return
                    data, handshake = data[len(data) - beyond :], None
                    time.sleep(delay)  # what the client sends meanwhile waits in the socket
            try:
                sink.sendall(data)
            except OSError:
                return

    def freeze(self, refuse_new: bool = False, sent: bytes | None = None) -> int:
        """Stop forwarding on every connection open now, or with `sent` on those whose client's last
        bytes hold it (and, with `refuse_new`, refuse new ones until `restore()`); returns how many."""
        with self.lock:
            if refuse_new:
                self.refusing = True
            chosen = [f for _, _, f in self.connections if sent is None or sent in self.tails[f]]
            for frozen in chosen:
                frozen.set()
            return len(chosen)

    def cut(self) -> int:
        """Close every connection open now, both ways, and refuse new ones until `restore()`;
        returns how many were closed."""
        with self.lock:
            self.refusing = True
            connections, self.connections = self.connections, []
            self.tails = {}
        for client, upstream, frozen in connections:
            frozen.set()
            for sock in (client, upstream):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
        return len(connections)

    def delay_after_handshake(self, seconds: float) -> None:
        """The next connection made: what its client sends after the Zenoh handshake reaches the
        target `seconds` late (its liveliness tokens, its scans), while the target's replies flow:
        the client's link is up at once, and the service hears of the robot only then."""
        with self.lock:
            self._next_delay = seconds

    def restore(self) -> None:
        """Forward new connections again (after `cut()` or `freeze(refuse_new=True)`)."""
        self.refusing = False

    def close(self) -> None:
        self.listener.close()
        self.cut()


class RestartingService:
    """A service that robots reach through a `FreezableProxy`, stopped or killed and started again
    on the same arguments (its data directory): `restart()` starts the next process and points the
    proxy at it, so robots connected to `proxy.endpoint` meet the new one. `service` is the one
    started last; `close()` (or leaving a `with` block) closes the proxy and stops every process."""

    def __init__(self, log_dir: Path, extra_args: Sequence[str]) -> None:
        self.log_dir = log_dir
        self.extra_args = list(extra_args)
        self.service = ServiceProcess(log_dir, self.extra_args).start()
        self.proxy = FreezableProxy(self.service.zenoh_port)
        self._started = [self.service]

    def kill(self) -> None:
        """SIGKILL the current process (no snapshot, no goodbye) and wait for it to be gone."""
        assert self.service.proc is not None
        self.service.proc.kill()
        self.service.proc.wait(10)

    def restart(self) -> ServiceProcess:
        """Start the next process (the current one must be stopped or killed) with the proxy pointed
        at it before it listens, and return it."""
        self.service = ServiceProcess(self.log_dir, self.extra_args)
        self._started.append(self.service)
        self.proxy.target_port = self.service.zenoh_port
        return self.service.start()

    def close(self) -> None:
        """Close the proxy and stop every process started (idempotent)."""
        self.proxy.close()
        for service in self._started:
            service.stop()

    def __enter__(self) -> RestartingService:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:  # fmt: skip
        self.close()


def wait_for(
    predicate: Callable[[], T], timeout: float = 30.0, interval: float = 0.1, what: str = "condition"
) -> T:
    """Poll `predicate()` until it returns something truthy (returned) or `timeout` passes
    (AssertionError naming `what` and the last value)."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}; last value: {last!r}")
