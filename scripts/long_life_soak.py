"""Long-life soak: does the service's memory stay flat, and /metrics bounded, under a steady
workload with churn?

    PYTHONPATH=service:clients/python:tests .venv/bin/python scripts/long_life_soak.py \\
        [--minutes 12] [--out /tmp/soak] [--max-robots-per-map 64]

Opt-in, never part of `pytest` (it takes minutes and most of a core). Against the real service
process (durable, on its own data directory), for `--minutes`, at once:

- `fleetmap sim` robots publishing to the map `sim` over Zenoh the whole time (steady load);
- robots under new ids coming and going over Zenoh on the map `roam` (a `ScanPublisher` each, a few
  scans, then closed: a liveliness token appears and goes each time);
- robots under new ids posting over REST to the map `rest` (its robots pass `--max-robots-per-map`,
  so the map forgets robots: tombstones);
- maps created under new ids, given scans by two robots and a tile read, then deleted;
- tile readers (random tiles and zooms of `sim`) and event-stream subscribers (opened, read for a
  moment and dropped, full and `?robots=delta`).

Every `--sample-every` seconds it writes one JSON line to `OUT/samples.jsonl` and prints it: the
service's RSS, `fleetmap_memory_used_bytes`, the size of `/metrics` in bytes and lines, the number
of robot series, tile cache entries, and the counts of churn done so far. The trend is what matters:
growth that follows the churn counts without levelling off is a leak; growth that stops at a cache's
bound, or a step at the start (numba's compilation, the allocator's arenas), is not.
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
from service_process import ServiceProcess, fleetmap_command  # noqa: E402

from fleetmap import codec  # noqa: E402
from fleetmap.scan import Pose2D, Scan  # noqa: E402

JSON = {"content-type": "application/json"}


def _fan(rng: random.Random) -> Scan:
    """A scan of 90 beams somewhere within 10 m of the origin."""
    pose = Pose2D(rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(-3, 3))
    return Scan.from_fan(pose, -2.3, 0.05, [rng.uniform(1.0, 8.0) for _ in range(90)], 0.0, 10.0)


def _scan(rng: random.Random) -> bytes:
    """`_fan` as a JSON body for POST /scans."""
    return codec.encode_json(_fan(rng), 0)


def _status(pid: int) -> dict[str, int]:
    """The process's RssAnon, RssFile (kB) and Threads, from /proc/PID/status."""
    found = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "RssAnon", "RssFile", "Threads"):
            found[name] = int(value.split()[0])
    return found


def _metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return -1.0


class Soak:
    """The load threads, sharing a stop flag and a counter of what they did."""

    def __init__(self, svc: ServiceProcess, deadline: float) -> None:
        self.svc, self.deadline = svc, deadline
        self.done: Counter[str] = Counter()
        self.lock = threading.Lock()
        self.stop = threading.Event()

    def running(self) -> bool:
        return not self.stop.is_set() and time.monotonic() < self.deadline

    def count(self, what: str, n: int = 1) -> None:
        with self.lock:
            self.done[what] += n

    def loop(self, fn, period: float) -> None:  # type: ignore[no-untyped-def]
        """Call `fn(client)` every `period` seconds until the end; errors are counted, not fatal."""
        with httpx.Client(timeout=30.0) as client:
            while self.running():
                try:
                    fn(client)
                except Exception as exc:  # noqa: BLE001 - counted: the soak goes on
                    self.count(f"error {type(exc).__name__} in {fn.__name__}")
                time.sleep(period)

    def roaming_robot(self, _client: httpx.Client) -> None:
        from fleetmap_client.publisher import ScanPublisher

        k = self.done["zenoh robots"]
        rng = random.Random(k)
        with ScanPublisher("roam", f"roam-{k}", connect=[self.svc.zenoh_endpoint]) as pub:
            pub.wait_connected(timeout=30)
            for _ in range(5):
                pub.publish(_fan(rng))
            pub.flush(timeout=10)
        self.count("zenoh robots")

    def rest_robot(self, client: httpx.Client) -> None:
        k = self.done["rest robots"]
        r = client.post(f"{self.svc.base_url}/maps/rest/scans", params={"robot_id": f"rest-{k}"},
                        content=_scan(random.Random(k)), headers=JSON)  # fmt: skip
        self.count("rest robots" if r.status_code == 200 else f"rest robot {r.status_code}")

    def churn_map(self, client: httpx.Client) -> None:
        k = self.done["maps churned"]
        base = f"{self.svc.base_url}/maps/churn-{k}"
        client.put(base, json={}).raise_for_status()
        rng = random.Random(k)
        for robot in ("a", "b"):
            client.post(f"{base}/scans", params={"robot_id": f"{robot}-{k}"}, content=_scan(rng),
                        headers=JSON).raise_for_status()  # fmt: skip
        client.get(f"{base}/tiles/0/0/0.png")
        client.delete(base).raise_for_status()
        self.count("maps churned")

    def tiles(self, client: httpx.Client) -> None:
        rng = random.Random()
        z = rng.choice([-2, -1, 0, 0, 0])
        x, y = rng.randint(-3, 3), rng.randint(-3, 3)
        r = client.get(f"{self.svc.base_url}/maps/sim/tiles/{z}/{x}/{y}.png")
        self.count(f"tile {r.status_code}")

    def stream(self, client: httpx.Client) -> None:
        params = {"robots": "delta"} if random.random() < 0.5 else {}
        hold = random.uniform(0.5, 3.0)
        with client.stream("GET", f"{self.svc.base_url}/maps/sim/events", params=params) as r:
            start = time.monotonic()
            for _ in r.iter_bytes():
                if time.monotonic() - start > hold:
                    break
        self.count("streams")

    def sample(self, t0: float) -> dict:
        text = httpx.get(f"{self.svc.base_url}/metrics", timeout=30).text
        assert self.svc.proc is not None
        with self.lock:
            done = dict(self.done)
        status = _status(self.svc.proc.pid)
        return {
            "t": round(time.monotonic() - t0),
            "rss_mb": round(status["VmRSS"] / 1e3, 1),
            "anon_mb": round(status["RssAnon"] / 1e3, 1),
            "file_mb": round(status["RssFile"] / 1e3, 1),
            "threads": status["Threads"],
            "memory_used_mb": round(_metric(text, "fleetmap_memory_used_bytes") / 1e6, 2),
            "metrics_bytes": len(text),
            "metrics_lines": text.count("\n"),
            "robot_series": sum(1 for line in text.splitlines() if line.startswith("fleetmap_robot_online{")),
            "tile_cache": _metric(text, "fleetmap_tile_cache_entries"),
            "maps": _metric(text, "fleetmap_maps"),
            "gc_full": _metric(text, 'fleetmap_gc_collections_total{generation="2"}'),
            **done,
        }


#: The loads by name (`Soak`'s methods): the seconds between two calls of each thread running it.
LOADS = {
    "roaming_robot": (2.0,), "rest_robot": (0.2,), "churn_map": (0.5,), "tiles": (0.05,),
    "stream": (0.1, 0.3),
}  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=12.0)
    p.add_argument("--out", type=Path, default=Path("/tmp/fleetmap-soak"))
    p.add_argument("--sample-every", type=float, default=20.0)
    p.add_argument("--max-robots-per-map", type=int, default=64)
    p.add_argument(
        "--serve-arg", action="append", default=[], metavar="ARG",
        help="one more argument for the service, repeated: --serve-arg=--metrics-robot-idle --serve-arg=120",
    )  # fmt: skip
    p.add_argument("--sim-robots", type=int, default=2, help="0: no `fleetmap sim`")
    p.add_argument(
        "--loads", nargs="*", default=list(LOADS), choices=LOADS,
        help="which churn and read loads run (default all), to tell which one grows the memory",
    )  # fmt: skip
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    svc = ServiceProcess(
        args.out,
        ["--data-dir", str(args.out / "data"), "--max-robots-per-map", str(args.max_robots_per_map),
         *args.serve_arg],
    ).start()  # fmt: skip
    seconds = args.minutes * 60
    sim = None if args.sim_robots == 0 else subprocess.Popen(
        [*fleetmap_command(), "sim", "--robots", str(args.sim_robots), "--map", "sim", "--rate", "5",
         "--beams", "360", "--seconds", str(seconds), "--no-confirm", "--connect", svc.zenoh_endpoint],
        stdout=open(args.out / "sim.log", "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
    )  # fmt: skip
    t0 = time.monotonic()
    soak = Soak(svc, t0 + seconds)
    threads = [
        threading.Thread(target=soak.loop, args=(getattr(soak, name), period), daemon=True)
        for name in args.loads
        for period in LOADS[name]
    ]
    for thread in threads:
        thread.start()
    samples = args.out / "samples.jsonl"
    try:
        with samples.open("w") as f:
            while soak.running():
                row = soak.sample(t0)
                f.write(json.dumps(row) + "\n")
                f.flush()
                print(json.dumps(row), flush=True)
                time.sleep(args.sample_every)
    finally:
        soak.stop.set()
        for thread in threads:
            thread.join(timeout=30)
        if sim is not None:
            sim.terminate()
            sim.wait(timeout=30)
        print(json.dumps(soak.sample(t0)), flush=True)
        svc.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
