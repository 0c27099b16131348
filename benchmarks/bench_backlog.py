"""A fleet's recovered backlogs into one map, past the ingest queue: what is integrated, what the robots'
caches could no longer give back, and how long it takes (docs/protocol.md, "Delivery guarantees").

    PYTHONPATH=service:clients/python python benchmarks/bench_backlog.py --robots 40 --queued 1000 --extra 50
    ... --silent 1      # one robot's link dies silently once it sent its scans (SIGSTOP)
    ... --router        # robots and service all clients of a Zenoh router (a Python session)

Each robot is its own process with a `ScanPublisher` (`--backlog`, and `--cache`, by default the
client's): it queues `--queued` scans while no service runs (its backlog); then the service starts
(`fleetmap serve`, in memory) and every robot, once connected, publishes `--extra` more at once, then
flushes (`ScanPublisher.flush`) and reports. The service's queue defers what it has no room for and
fetches it again from the robots' caches (`fleetmap.backlog_refetch`); a robot's scans it gets to
after they left the robot's cache are unrecoverable. `--silent K` stops K robots (SIGSTOP: their
links stay up, their caches answer nothing) once they published everything, and measures how long the
others take to settle. Prints one line of results (and JSON with `--json`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parent.parent


def robot_main(argv: Sequence[str]) -> int:
    """A robot: queue `--queued` scans, wait for "go" on stdin, publish `--extra` once connected,
    flush, print the report as JSON, and wait for stdin to close."""
    from fleetmap_client.publisher import ScanPublisher

    from fleetmap.sim import SimulatedRobot, generate_floorplan

    p = argparse.ArgumentParser(prog="bench_backlog.py _robot")
    p.add_argument("--connect", required=True)
    p.add_argument("--map", required=True)
    p.add_argument("--robot", required=True)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--queued", type=int, required=True)
    p.add_argument("--extra", type=int, required=True)
    p.add_argument("--beams", type=int, required=True)
    p.add_argument("--backlog", type=int, required=True)
    p.add_argument("--cache", type=int, default=None)
    a = p.parse_args(argv)
    plan = generate_floorplan(0, width_m=20.0, height_m=15.0)
    sim = SimulatedRobot(plan, a.seed, num_beams=a.beams, range_max=12.0, speed=1.0, scan_rate=5.0)
    scans = [sim.tick() for _ in range(a.queued + a.extra)]
    options: dict[str, Any] = {} if a.cache is None else {"cache": a.cache}
    pub = ScanPublisher(a.map, a.robot, connect=[a.connect], backlog=a.backlog, **options)
    for scan in scans[: a.queued]:
        pub.publish(scan)
    print("queued", flush=True)
    sys.stdin.readline()  # go
    pub.wait_connected(300)
    for scan in scans[a.queued :]:
        pub.publish(scan)
    print("published", flush=True)
    report = pub.flush(600)
    print(json.dumps({"integrated": report.integrated, "lost": report.lost, "settled": report.settled,
                      "time": time.time()}), flush=True)  # fmt: skip
    sys.stdin.read()
    pub.close()
    return 0


def _line(proc: subprocess.Popen[str], timeout: float) -> str:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line:
            return line.strip()
        if proc.poll() is not None:
            raise RuntimeError(f"robot exited with {proc.returncode}")
    raise TimeoutError("robot said nothing")


@contextlib.contextmanager
def router(endpoint: str) -> Iterator[None]:
    """A Zenoh router listening on `endpoint` (a Python session standing in for zenohd)."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("timestamping/enabled", '{"router": false}')
    session = zenoh.open(cfg)
    try:
        yield
    finally:
        session.close()


def run(args: argparse.Namespace) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": f"{REPO / 'service'}:{REPO / 'clients' / 'python'}"}
    zport, hport = args.port, args.port + 1
    endpoint = f"tcp/127.0.0.1:{zport}"
    base = f"http://127.0.0.1:{hport}"
    stack = contextlib.ExitStack()
    with stack:
        if args.router:
            stack.enter_context(router(endpoint))
        robots = []
        for k in range(args.robots):
            cmd = [sys.executable, __file__, "_robot", "--connect", endpoint, "--map", "m",
                   "--robot", f"r{k}", "--seed", str(k), "--queued", str(args.queued),
                   "--extra", str(args.extra), "--beams", str(args.beams),
                   "--backlog", str(args.backlog)]  # fmt: skip
            if args.cache is not None:
                cmd += ["--cache", str(args.cache)]
            robots.append(
                subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
            )
        try:
            for robot in robots:
                if _line(robot, 300) != "queued":
                    raise RuntimeError("robot did not queue")
            zenoh_args = ["--zenoh-connect", endpoint] if args.router else ["--zenoh-listen", endpoint]
            service = subprocess.Popen(
                [sys.executable, "-m", "fleetmap", "serve", "--http", f"127.0.0.1:{hport}", *zenoh_args,
                 "--in-memory", "--log-level", "warning"],
                env=env, stdout=subprocess.DEVNULL, stderr=open(args.log, "w"),  # noqa: SIM115
            )  # fmt: skip
            stack.callback(lambda: (service.terminate(), service.wait(30)))
            deadline = time.monotonic() + 60
            while True:
                with contextlib.suppress(httpx.TransportError):
                    if httpx.get(f"{base}/healthz").status_code == 200:
                        break
                if time.monotonic() > deadline or service.poll() is not None:
                    raise RuntimeError("service did not start")
                time.sleep(0.1)
            t0 = time.time()
            for robot in robots:
                assert robot.stdin is not None
                robot.stdin.write("go\n")
                robot.stdin.flush()
            for robot in robots:
                if _line(robot, 300) != "published":
                    raise RuntimeError("robot did not publish")
            silent = robots[: args.silent]
            for robot in silent:
                robot.send_signal(signal.SIGSTOP)
            reports = [json.loads(_line(robot, 900)) for robot in robots[args.silent :]]
            for robot in silent:
                robot.send_signal(signal.SIGCONT)
            for robot in silent:
                reports.append(json.loads(_line(robot, 900)))
            health = httpx.get(f"{base}/healthz").json()["zenoh"]
            m = httpx.get(f"{base}/maps/m").json()
        finally:
            for robot in robots:
                with contextlib.suppress(OSError):
                    robot.send_signal(signal.SIGCONT)
                    assert robot.stdin is not None
                    robot.stdin.close()
            for robot in robots:
                try:
                    robot.wait(30)
                except subprocess.TimeoutExpired:
                    robot.kill()
    others = reports[: args.robots - args.silent]
    return {
        "robots": args.robots, "queued": args.queued, "extra": args.extra, "backlog": args.backlog,
        "cache": args.cache, "silent": args.silent, "router": args.router,
        "scans": args.robots * (args.queued + args.extra),
        "integrated": m["stats"]["scans_integrated"],
        "lost": sum(r["lost"] for r in m["stats"]["robots"].values()),
        "unrecoverable": health["unrecoverable"], "deferred": health["deferred"],
        "refetched": health["refetched"], "dropped": health["rejected"].get("queue_full", 0),
        "others_settled_s": round(max(r["time"] for r in others) - t0, 2) if others else None,
        "all_settled_s": round(max(r["time"] for r in reports) - t0, 2),
    }  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["_robot"]:
        return robot_main(argv[1:])
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=40)
    p.add_argument(
        "--queued", type=int, default=1000, help="scans each robot queues before the service starts"
    )
    p.add_argument("--extra", type=int, default=50, help="scans each robot publishes at once when connected")
    p.add_argument("--beams", type=int, default=361)
    p.add_argument("--backlog", type=int, default=1000, help="each ScanPublisher's backlog")
    p.add_argument(
        "--cache", type=int, default=None, help="each ScanPublisher's cache (default: the client's)"
    )
    p.add_argument("--silent", type=int, default=0, help="robots stopped (SIGSTOP) once they published")
    p.add_argument("--router", action="store_true", help="robots and service clients of a Zenoh router")
    p.add_argument("--port", type=int, default=18400, help="Zenoh port; HTTP the next one")
    p.add_argument("--log", default="/tmp/bench_backlog_service.log", help="the service's log")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    result = run(args)
    print(json.dumps(result) if args.json else " ".join(f"{k}={v}" for k, v in result.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
