"""How long after a service restart a robot's `ScanPublisher` is connected again.

    PYTHONPATH=service:clients/python:tests .venv/bin/python scripts/reconnect_timing.py \\
        [--downs 1 2 4 8] [--repeat 3] [--via proxy|direct] [--retry INIT,MAX,FACTOR] [--soak 10]

Opt-in, never part of `pytest` (a minute or more). One publisher connects to a real durable service
(`tests/service_process.py`) directly or, with `--via proxy`, through the `FreezableProxy` that
tests/test_crash_exactly_once.py uses. The service is SIGKILLed and started again on the same Zenoh
port after each down time of `--downs` (seconds), `--repeat` times in a row; for each restart it
prints how long after the new service LISTENED (its Zenoh port accepting TCP connections) the
robot's session was connected (`pub.connected`) and saw the scan subscriber (`pub.subscribed`).
`--soak N` instead restarts it N times as the soak does: up for its start plus 0.05-4 s, down for
0-4 s; it prints, for each service, whether the robot met it at all.

`--via service-client` / `--via service-peer` measure the SERVICE's session instead: the service runs
with `--zenoh-connect` to a Zenoh router (a separate process, as a zenohd would be), in client mode
(no listening) or as a peer (listening too); the router is SIGKILLed and started again, and it
prints how long after the router listened the service counted it again (`/healthz` zenoh.routers).

`--retry INIT,MAX,FACTOR` sets the robot's `connect/retry` (ms, ms, factor) instead of the
publisher's default, to compare; `--retry zenoh` leaves it unset in the configuration given to
`ScanPublisher` (Zenoh's own default applies unless `client_config` fills one in).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import zenoh
from fleetmap_client.publisher import ScanPublisher
from service_process import FreezableProxy, ServiceProcess, free_port


class Sampler:
    """Samples, every 10 ms, whether the service's Zenoh port listens and the publisher's state; keeps
    the first time each became true after `arm()`."""

    def __init__(self, pub: ScanPublisher, port: int) -> None:
        self.pub, self.port = pub, port
        self.first: dict[str, float] = {}
        #: (monotonic time, connected) at each change of `pub.connected`.
        self.changes: list[tuple[float, bool]] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def arm(self) -> None:
        with self._lock:
            self.first = {}

    def _listening(self) -> bool:
        with socket.socket() as s:
            s.settimeout(0.2)
            return s.connect_ex(("127.0.0.1", self.port)) == 0

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            now = time.monotonic()
            state = {"listening": self._listening(), "connected": self.pub.connected}
            state["subscribed"] = state["connected"] and self.pub.subscribed
            with self._lock:
                if not self.changes or self.changes[-1][1] != state["connected"]:
                    self.changes.append((now, state["connected"]))
                for name, value in state.items():
                    if value and name not in self.first:
                        self.first[name] = now

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(2)


def start_service(tmp: Path, data: Path, port: int) -> ServiceProcess:
    """A durable service on `data` whose Zenoh router listens on `port`, started (healthz answered)."""
    svc = ServiceProcess(tmp, ["--data-dir", str(data)])
    svc.zenoh_port, svc.zenoh_endpoint = port, f"tcp/127.0.0.1:{port}"
    svc.args[svc.args.index("--zenoh-listen") + 1] = svc.zenoh_endpoint
    return svc


def kill(svc: ServiceProcess) -> None:
    assert svc.proc is not None
    svc.proc.kill()
    svc.proc.wait(10)


def retry_config(spec: str | None) -> zenoh.Config | None:
    if spec is None:
        return None
    cfg = zenoh.Config()
    if spec != "zenoh":
        init, most, factor = spec.split(",")
        retry = {
            "period_init_ms": int(init),
            "period_max_ms": int(most),
            "period_increase_factor": float(factor),
        }
        cfg.insert_json5("connect/retry", json.dumps(retry))
    return cfg


def restarts(args: argparse.Namespace, tmp: Path) -> None:
    port = free_port()
    data = tmp / "data"
    svc = start_service(tmp, data, port).start()
    proxy = FreezableProxy(port) if args.via == "proxy" else None
    endpoint = proxy.endpoint if proxy else svc.zenoh_endpoint
    pub = ScanPublisher("timing", "r", connect=[endpoint], zenoh_config=retry_config(args.retry))
    sampler = Sampler(pub, port)
    rows: dict[float, list[tuple[float, float, float]]] = {}
    try:
        assert pub.wait_connected(30), pub.last_connect_error
        plan = [d for _ in range(args.repeat) for d in args.downs]
        for down in plan:
            time.sleep(1.0)
            kill(svc)
            killed = time.monotonic()
            while pub.connected and time.monotonic() - killed < 30:
                time.sleep(0.01)
            time.sleep(max(0.0, killed + down - time.monotonic()))
            sampler.arm()
            spawned = time.monotonic()
            svc = start_service(tmp, data, port).start()
            healthy = time.monotonic()
            deadline = healthy + 60
            while "subscribed" not in sampler.first and time.monotonic() < deadline:
                time.sleep(0.01)
            first = dict(sampler.first)
            listen = first.get("listening", spawned)
            conn = first.get("connected", float("nan")) - listen
            sub = first.get("subscribed", float("nan")) - listen
            rows.setdefault(down, []).append((conn, sub, healthy - listen))
            print(
                f"down {down:4.1f} s: listening {listen - spawned:5.2f} s after spawn,"
                f" healthz +{healthy - listen:5.2f} s;"
                f" robot connected +{conn:6.2f} s, subscribed +{sub:6.2f} s after listening",
                flush=True,
            )
        print("summary (seconds after the new service listened):")
        for down, values in sorted(rows.items()):
            conns = [v[0] for v in values]
            print(
                f"  down {down:4.1f} s: connected median {statistics.median(conns):5.2f},"
                f" max {max(conns):5.2f}"
                f" ({', '.join(f'{c:.2f}' for c in conns)})"
            )
    finally:
        sampler.stop()
        pub.close()
        if proxy:
            proxy.close()
        svc.stop()


ROUTER_SCRIPT = """
import sys, threading, zenoh
cfg = zenoh.Config()
cfg.insert_json5("mode", '"router"')
cfg.insert_json5("listen/endpoints", '["tcp/127.0.0.1:%s"]' % sys.argv[1])
cfg.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(cfg)
threading.Event().wait()
"""


def service_side(args: argparse.Namespace, tmp: Path) -> None:
    """The service's session connecting to a router that is killed and restarted (`--via service-*`)."""
    router_port = free_port()
    router_endpoint = f"tcp/127.0.0.1:{router_port}"

    def router() -> subprocess.Popen[bytes]:
        return subprocess.Popen([sys.executable, "-c", ROUTER_SCRIPT, str(router_port)])

    def listening() -> bool:
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", router_port)) == 0

    proc = router()
    while not listening():
        time.sleep(0.01)
    extra = ["--in-memory", "--zenoh-connect", router_endpoint]
    svc = ServiceProcess(tmp, extra)
    if args.via == "service-client":
        at = svc.args.index("--zenoh-listen")
        del svc.args[at : at + 2]
    if args.retry:
        config = tmp / "service-zenoh.json5"
        init, most, factor = args.retry.split(",")
        retry = {
            "period_init_ms": int(init),
            "period_max_ms": int(most),
            "period_increase_factor": float(factor),
        }
        config.write_text(json.dumps({"connect": {"retry": retry}}))
        svc.args += ["--zenoh-config", str(config)]
    svc.start()

    def routers() -> int:
        try:
            return int(httpx.get(f"{svc.base_url}/healthz", timeout=1).json()["zenoh"].get("routers", 0))
        except (httpx.HTTPError, ValueError, KeyError):
            return -1

    rows: list[float] = []
    try:
        deadline = time.monotonic() + 30
        while routers() < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        print(f"service ({args.via}) connected to the router: {routers()}", flush=True)
        for down in [d for _ in range(args.repeat) for d in args.downs]:
            time.sleep(1.0)
            proc.kill()
            proc.wait()
            while routers() != 0:
                time.sleep(0.01)
            time.sleep(down)
            proc = router()
            while not listening():
                time.sleep(0.005)
            listened = time.monotonic()
            while routers() < 1 and time.monotonic() - listened < 60:
                time.sleep(0.01)
            rows.append(time.monotonic() - listened)
            print(f"down {down:4.1f} s: service connected again +{rows[-1]:5.2f} s after the router listened")
        print(f"median {statistics.median(rows):.2f} s, max {max(rows):.2f} s")
    finally:
        svc.stop()
        proc.kill()
        proc.wait()


def soak_like(args: argparse.Namespace, tmp: Path) -> None:
    rng = random.Random(args.seed)
    port = free_port()
    data = tmp / "data"
    svc = start_service(tmp, data, port).start()
    proxy = FreezableProxy(port) if args.via == "proxy" else None
    endpoint = proxy.endpoint if proxy else svc.zenoh_endpoint
    pub = ScanPublisher("timing", "r", connect=[endpoint], zenoh_config=retry_config(args.retry))
    sampler = Sampler(pub, port)
    met = 0
    try:
        assert pub.wait_connected(30), pub.last_connect_error
        began = time.monotonic()
        for number in range(args.soak + 1):
            time.sleep(rng.uniform(0.05, 4.0))
            seen = dict(sampler.first)
            kill(svc)
            if number:
                met += "connected" in seen
                when = seen.get("connected", 0) - seen.get("listening", 0)
                print(
                    f"service #{number}: up {time.monotonic() - seen.get('listening', 0):.2f} s, robot "
                    + (
                        f"connected +{when:.2f} s after it listened"
                        if "connected" in seen
                        else "NEVER connected"
                    ),
                    flush=True,
                )
            time.sleep(rng.uniform(0.0, 4.0))
            if number < args.soak:
                sampler.arm()
                svc = start_service(tmp, data, port).start()
        changes = [c for c in sampler.changes if c[0] >= began]
        gaps = [b[0] - a[0] for a, b in zip(changes, changes[1:], strict=False) if not a[1]]
        print(
            f"met {met} of {args.soak} services; longest time unconnected between services {max(gaps):.1f} s"
        )
    finally:
        sampler.stop()
        pub.close()
        if proxy:
            proxy.close()
        with contextlib.suppress(Exception):
            svc.stop()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--downs", type=float, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--via", choices=["proxy", "direct", "service-client", "service-peer"], default="proxy"
    )
    parser.add_argument("--retry", default=None)
    parser.add_argument("--soak", type=int, default=0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="reconnect-timing-") as tmp:
        if args.via.startswith("service-"):
            service_side(args, Path(tmp))
        elif args.soak:
            soak_like(args, Path(tmp))
        else:
            restarts(args, Path(tmp))


if __name__ == "__main__":
    main()
