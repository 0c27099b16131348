"""Chaos run: the service's features at once, under stress, against the real service process.

    PYTHONPATH=service:clients/python:tests .venv/bin/python scripts/chaos_service.py \\
        [--minutes 3] [--robots 10] [--kills 2] [--out /tmp/chaos]

Opt-in, never part of `pytest` (it takes minutes and both CPU cores). For `--minutes`, at once:
robots publishing through real Zenoh sessions (`ScanPublisher`, each its own process; two pairs
share a robot id, some restart their publisher), maps deleted and created again, a map replaced
with `PUT /maps/{id}/snapshot`, small windows of the stable maps cleared (`DELETE
/maps/{id}/region`) while their robots publish, event streams opened and dropped (full and
`?robots=delta`, with `Last-Event-ID`), tiles read with conditional GETs and HEADs, bad requests
(bad JSON, duplicate keys, huge heads, long targets), `/metrics` scraped; the service runs with
`--log-format json` and is SIGKILLed and restarted `--kills` times on the same data directory.

Invariants, checked while it runs and at the end (the exit code is the number violated):
no 5xx answer (but the stream cap's 503); every log line JSON, no traceback, no sentence written
more than 30 times a minute; after a restart, a stream resumed with the old Last-Event-ID starts
with a reset, and an old tile ETag revalidates only an unchanged tile; `/metrics` parses;
a delta stream's folded robots equal a fresh `robots` event after quiescence; for the robots of
the last round, scans integrated = sent - dropped - rejected - duplicate; RSS and open descriptors
level off; a map read after a kill equals the map before it (its scans and cleared windows were
committed), the
churned and replaced maps too (snapshots run every second, racing their deletes and replacements).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import httpx
from prometheus_client.parser import text_string_to_metric_families

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
from service_process import ServiceProcess, wait_for  # noqa: E402

from fleetmap import codec  # noqa: E402
from fleetmap.scan import Pose2D, Scan  # noqa: E402
from fleetmap.signal_event import SignalEvent  # noqa: E402

STABLE_MAPS = ("stable-a", "stable-b")
CHURN_MAP = "churn"
REPLACED_MAP = "replaced"


class Violations:
    """Invariant violations, counted by name with a few examples each."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.examples: dict[str, list[str]] = {}

    def add(self, name: str, example: str) -> None:
        with self.lock:
            self.counts[name] += 1
            self.examples.setdefault(name, [])
            if len(self.examples[name]) < 5:
                self.examples[name].append(example[:600])


# -- robots: a child process each -------------------------------------------------------------------


def robot_main(args: argparse.Namespace) -> int:
    """One robot: publish `count` sim scans at `rate`, restarting the publisher at `restart_at`.
    Prints a JSON line {"sent", "not_sent"} at the end."""
    from fleetmap_client.publisher import ScanPublisher

    from fleetmap.sim import SimulatedRobot, generate_floorplan

    plan = generate_floorplan(args.seed % 3, width_m=20.0, height_m=15.0)
    sim = SimulatedRobot(plan, args.seed, num_beams=90, range_max=12.0, speed=1.0, scan_rate=5.0)
    stop = SignalEvent()
    signal.signal(signal.SIGTERM, lambda *_: stop.set_in_handler())
    sent = not_sent = 0
    pub = ScanPublisher(args.map, args.robot, connect=[args.connect])
    pub.wait_connected(timeout=60)
    for k in range(args.count):
        if stop.is_set():
            break
        if k == args.restart_at:
            pub.close()
            pub = ScanPublisher(args.map, args.robot, connect=[args.connect])
            pub.wait_connected(timeout=60)
        if pub.publish(sim.tick()):
            sent += 1
        else:
            not_sent += 1
        time.sleep(1.0 / args.rate)
    time.sleep(0.5)  # let the session flush
    pub.close()
    print(json.dumps({"sent": sent, "not_sent": not_sent}), flush=True)
    return 0


def start_robot(endpoint: str, map_id: str, robot_id: str, seed: int, count: int, rate: float,
                restart_at: int, out: Path) -> tuple[subprocess.Popen[str], Path]:  # fmt: skip
    log = out / f"robot-{map_id}-{robot_id}-{seed}.log"
    cmd = [sys.executable, __file__, "robot", "--connect", endpoint, "--map", map_id, "--robot", robot_id,
           "--seed", str(seed), "--count", str(count), "--rate", str(rate),
           "--restart-at", str(restart_at)]  # fmt: skip
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, text=True)
    return proc, log


# -- the service, killed and restarted on one data dir ---------------------------------------------


class Service:
    def __init__(self, out: Path) -> None:
        self.out = out
        self.svc = ServiceProcess(
            out,
            ["--log-format", "json", "--data-dir", str(out / "data"), "--max-event-streams", "64",
             "--workers", "1", "--snapshot-interval", "1"],
        )  # fmt: skip
        self.generation = 0
        self.up = threading.Event()

    @property
    def base(self) -> str:
        return self.svc.base_url

    def start(self) -> None:
        self.svc.start()
        self.up.set()

    def kill_and_restart(self) -> None:
        self.up.clear()
        assert self.svc.proc is not None
        self.svc.proc.kill()
        self.svc.proc.wait()
        self.svc.log_path.rename(self.out / f"service-gen{self.generation}.log")
        self.generation += 1
        self.start()

    def pid(self) -> int:
        assert self.svc.proc is not None
        return self.svc.proc.pid

    def all_logs(self) -> Iterator[tuple[str, str]]:
        for p in sorted(self.out.glob("service-gen*.log")):
            yield p.name, p.read_text(errors="replace")
        yield "current", self.svc.logs()


# -- load generators (threads) ---------------------------------------------------------------------


class Chaos:
    def __init__(self, svc: Service, deadline: float, v: Violations) -> None:
        self.svc, self.deadline, self.v = svc, deadline, v
        self.stop = threading.Event()
        self.stats: Counter[str] = Counter()
        self.rng = random.Random(1)
        #: Held by `churn_maps` while it changes maps, and by the kill while it compares them.
        self.churn_lock = threading.Lock()

    def running(self) -> bool:
        return not self.stop.is_set() and time.monotonic() < self.deadline

    def check(self, r: httpx.Response, what: str) -> None:
        self.stats[f"status {r.status_code}"] += 1
        if r.status_code >= 500 and not (r.status_code == 503 and "events" in what):
            self.v.add("5xx", f"{what}: {r.status_code} {r.text[:300]}")

    def guarded(self, fn, *args) -> None:  # type: ignore[no-untyped-def]
        """Run `fn` in a loop until the end; transport errors while the service is down are expected."""
        # Streams idle up to the 15 s keepalive.
        with httpx.Client(timeout=20.0) as client:
            while self.running():
                if not self.svc.up.wait(1.0):
                    continue
                try:
                    fn(client, *args)
                except (httpx.TransportError, ConnectionError, OSError) as exc:
                    if self.svc.up.is_set() and self.svc.svc.alive():
                        self.stats[f"transport {type(exc).__name__} in {fn.__name__}"] += 1
                    time.sleep(0.2)

    def churn_maps(self, client: httpx.Client) -> None:
        base = self.svc.base
        with self.churn_lock:
            self.check(client.put(f"{base}/maps/{CHURN_MAP}", json={}), "put churn")
        time.sleep(self.rng.uniform(0.5, 2.0))
        with self.churn_lock:
            self.check(client.delete(f"{base}/maps/{CHURN_MAP}"), "delete churn")
            snap = client.get(f"{base}/maps/{STABLE_MAPS[0]}/snapshot")
            self.check(snap, "get snapshot")
            if snap.status_code == 200:
                r = client.put(f"{base}/maps/{REPLACED_MAP}/snapshot", content=snap.content,
                               headers={"content-type": snap.headers["content-type"]})  # fmt: skip
                self.check(r, "put snapshot")
        time.sleep(self.rng.uniform(0.5, 2.0))

    def clear_regions(self, client: httpx.Client) -> None:
        """Forget a small window of a stable map now and then, while its robots publish: under
        `churn_lock`, so that each clear answered before a kill is in the maps compared after it
        (the journal's row of it, replayed between the same scans)."""
        base = self.svc.base
        map_id = self.rng.choice(STABLE_MAPS)
        x, y = self.rng.uniform(0.0, 18.0), self.rng.uniform(0.0, 13.0)
        w, h = self.rng.uniform(0.2, 3.0), self.rng.uniform(0.2, 3.0)
        window = {"xmin": x, "ymin": y, "xmax": x + w, "ymax": y + h}
        with self.churn_lock:
            r = client.delete(f"{base}/maps/{map_id}/region", params=window)
        self.check(r, "clear region")
        if r.status_code == 200:
            self.stats["regions cleared"] += 1
            self.stats["cells cleared"] += r.json()["cells_cleared"]
        elif r.status_code != 404:  # (a stable map is made at the start; 404 only before that)
            self.v.add("clear region", f"{map_id} {window}: {r.status_code} {r.text[:300]}")
        time.sleep(self.rng.uniform(0.5, 1.5))

    def streams(self, client: httpx.Client) -> None:
        base = self.svc.base
        map_id = self.rng.choice([*STABLE_MAPS, CHURN_MAP, REPLACED_MAP])
        params = {"robots": "delta"} if self.rng.random() < 0.5 else {}
        headers = {"Last-Event-ID": str(self.rng.randint(0, 50))} if self.rng.random() < 0.5 else {}
        hold = self.rng.uniform(0.1, 2.0)
        with client.stream("GET", f"{base}/maps/{map_id}/events", params=params, headers=headers) as r:
            self.check(r, "events")
            if r.status_code != 200:
                r.read()
                return
            start = time.monotonic()
            for _ in r.iter_bytes():
                if time.monotonic() - start > hold:
                    break
        self.stats["streams"] += 1

    def tiles(self, client: httpx.Client) -> None:
        base = self.svc.base
        map_id = self.rng.choice([*STABLE_MAPS, REPLACED_MAP])
        z = self.rng.choice([-2, -1, 0])
        x, y = self.rng.randint(-2, 2), self.rng.randint(-2, 2)
        url = f"{base}/maps/{map_id}/tiles/{z}/{x}/{y}.png"
        r = client.get(url)
        self.check(r, "tile")
        etag = r.headers.get("etag")
        if etag:
            r2 = client.get(url, headers={"If-None-Match": etag})
            self.check(r2, "tile conditional")
            self.stats[f"tile conditional {r2.status_code}"] += 1
        h = client.head(url)
        self.check(h, "tile head")
        if h.content:
            self.v.add("head body", f"{url}: HEAD answered a body of {len(h.content)} bytes")
        for path in (f"/maps/{map_id}", "/maps", "/healthz"):
            r = client.get(f"{base}{path}", headers={"Accept-Encoding": "gzip"})
            self.check(r, path)
            if r.status_code == 200 and path != "/healthz" and r.headers.get("etag"):
                r3 = client.get(f"{base}{path}", headers={"If-None-Match": r.headers["etag"]})
                self.check(r3, f"{path} conditional")
        time.sleep(0.05)

    def bad_requests(self, client: httpx.Client) -> None:
        base = self.svc.base
        for body in (b"{not json", b'{"resolution": 0.05, "resolution": 0.1}', b"[]", b'{"x":' * 10000):
            r = client.put(f"{base}/maps/bad-{self.rng.randint(0, 3)}", content=body,
                           headers={"content-type": "application/json"})  # fmt: skip
            self.check(r, f"bad json {body[:30]!r}")
            if r.status_code < 400:
                self.v.add("bad accepted", f"PUT bad body {body[:40]!r} -> {r.status_code}")
        r = client.post(f"{base}/maps/{STABLE_MAPS[1]}/scans", params={"robot_id": "bad"},
                        content=b'{"seq": 1, "seq": 2}',
                        headers={"content-type": "application/json"})  # fmt: skip
        self.check(r, "bad scan")
        # A whole scan but for a key given twice: refused, not integrated with the last value.
        good = codec.encode_json(Scan.from_fan(Pose2D(0.5, 0.5, 0.0), -1.0, 0.5, [1.0] * 5, 0.0, 5.0), 1)
        r = client.post(f"{base}/maps/{STABLE_MAPS[1]}/scans", params={"robot_id": "bad"},
                        content=good.replace(b'"seq":1', b'"seq":1,"seq":2', 1),
                        headers={"content-type": "application/json"})  # fmt: skip
        self.check(r, "scan with a repeated key")
        if r.status_code < 400:
            self.v.add("bad accepted", f"a scan with a repeated key -> {r.status_code}")
        self.stats["bad scans posted"] += 1
        host, port = "127.0.0.1", self.svc.svc.port
        for raw in (
            b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Big: " + b"a" * 70000 + b"\r\n\r\n",
            b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\nHost: localhost\r\n\r\n",
            b"GARBAGE\r\n\r\n",
            b"GET /maps HTTP/1.1\r\nHost: localhost\r\nContent-Length: zz\r\n\r\n",
            b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\r\n",
        ):
            with socket.create_connection((host, port), timeout=5) as s:
                try:
                    s.sendall(raw)
                    data = s.recv(200)
                except (ConnectionResetError, BrokenPipeError):
                    data = b""
            status = data.split(b" ", 2)[1:2]
            self.stats[f"raw {status}"] += 1
            if status and status[0].startswith(b"5"):
                self.v.add("5xx", f"raw {raw[:40]!r}: {data[:200]!r}")
        time.sleep(0.3)

    def scrape(self, client: httpx.Client, samples: list[tuple[float, int, int]]) -> None:
        r = client.get(f"{self.svc.base}/metrics")
        self.check(r, "metrics")
        try:
            list(text_string_to_metric_families(r.text))
        except Exception as exc:  # noqa: BLE001 - any parse failure is the violation
            self.v.add("metrics parse", repr(exc))
        pid = self.svc.pid()
        try:
            rss = int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
            fds = len(os.listdir(f"/proc/{pid}/fd"))
            samples.append((time.monotonic(), rss, fds))
        except OSError:
            pass
        time.sleep(1.0)


# -- stream folding ---------------------------------------------------------------------------------


def sse_events(
    url: str, headers: dict[str, str] | None = None, timeout: float | None = 10.0
) -> Iterator[tuple[str, str]]:
    """(event name, data) of a server-sent event stream, until it ends or the caller stops."""
    with httpx.Client(timeout=timeout) as c, c.stream("GET", url, headers=headers) as r:
        kind = "message"
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: "):
                yield kind, line[6:]


class DeltaFolder:
    """A `?robots=delta` stream of a map, folded: robots as a full event would say."""

    def __init__(self, base: str, map_id: str) -> None:
        self.robots: dict | None = None
        self.events = 0
        self.error: str | None = None
        self.thread = threading.Thread(target=self._run, args=(base, map_id), daemon=True)
        self.thread.start()

    def _run(self, base: str, map_id: str) -> None:
        from fleetmap.api_models import RobotsDeltaEvent, RobotsEvent

        try:
            for kind, data in sse_events(f"{base}/maps/{map_id}/events?robots=delta", timeout=None):
                if kind == "robots":
                    self.robots = RobotsEvent.model_validate_json(data).model_dump()
                elif kind == "robots_delta":
                    assert self.robots is not None, "a delta before any robots event"
                    delta = RobotsDeltaEvent.model_validate_json(data)
                    self.robots = RobotsEvent.model_validate(self.robots).apply(delta).model_dump()
                self.events += 1
        except Exception as exc:  # noqa: BLE001 - ends with the service; reported when relevant
            self.error = repr(exc)


def fresh_robots(base: str, map_id: str) -> dict:
    from fleetmap.api_models import RobotsEvent

    for kind, data in sse_events(f"{base}/maps/{map_id}/events"):
        if kind == "robots":
            return RobotsEvent.model_validate_json(data).model_dump()
    raise AssertionError("no robots event")


def robot_counters(base: str) -> dict[tuple[str, str], dict[str, float]]:
    text = httpx.get(f"{base}/metrics", timeout=10).text
    out: dict[tuple[str, str], dict[str, float]] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if "robot" in s.labels and s.name.endswith("_total"):
                out.setdefault((s.labels["map"], s.labels["robot"]), {})[s.name] = s.value
    return out


def quiescent(base: str) -> bool:
    text = httpx.get(f"{base}/metrics", timeout=10).text
    for fam in text_string_to_metric_families(text):
        if fam.name == "fleetmap_queue_depth":
            return all(s.value == 0 for s in fam.samples)
    return False


def map_image(base: str, map_id: str) -> bytes | None:
    r = httpx.get(f"{base}/maps/{map_id}/export", params={"format": "png"}, timeout=30)
    return r.content if r.status_code == 200 else None


def cache_validators(base: str, map_id: str) -> tuple[int, dict[str, tuple[str, bytes]]]:
    """What a client holds of a map: its change version (an event stream's last id) and some tiles'
    ETags and PNGs."""
    version = httpx.get(f"{base}/maps/{map_id}", timeout=10).json()["stats"]["version"]
    tiles = {}
    for x in (-1, 0):
        for y in (-1, 0):
            url = f"{base}/maps/{map_id}/tiles/0/{x}/{y}.png"
            r = httpx.get(url, timeout=10)
            if r.status_code == 200:
                tiles[f"/maps/{map_id}/tiles/0/{x}/{y}.png"] = (r.headers["etag"], r.content)
    return version, tiles


def check_validators_after_restart(
    base: str, map_id: str, version: int, tiles: dict[str, tuple[str, bytes]], v: Violations
) -> None:
    """After a restart: a stream resumed from the old last id starts with a reset, and a tile
    revalidated with its old ETag gets 304 only if its PNG is the same."""
    for kind, data in sse_events(f"{base}/maps/{map_id}/events", {"Last-Event-ID": str(version)}):
        if kind == "tiles":
            if not json.loads(data).get("reset"):
                v.add("resume after restart", f"{map_id}: Last-Event-ID {version} resumed: {data[:200]}")
            break
        if kind == "robots":
            # No tiles event before the first robots event: the old id passed for current.
            v.add("resume after restart", f"{map_id}: Last-Event-ID {version}: no reset")
            break
    for path, (etag, png) in tiles.items():
        fresh = httpx.get(base + path, timeout=10)
        again = httpx.get(base + path, headers={"If-None-Match": etag}, timeout=10)
        if again.status_code == 304 and fresh.content != png:
            v.add("etag after restart", f"{path}: 304 for the old ETag {etag}, but the tile changed")


# -- the run ----------------------------------------------------------------------------------------


def chaos_main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    # A fresh data directory too: the service would restore an earlier run's maps and robots' counters,
    # and every robot of the last round (the same ids each run) then counted twice its scans.
    shutil.rmtree(out / "data", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    for p in out.glob("*"):
        if p.is_file():
            p.unlink()
    v = Violations()
    svc = Service(out)
    svc.start()
    for m in STABLE_MAPS:
        httpx.put(f"{svc.base}/maps/{m}", json={}, timeout=10)
    endpoint = svc.svc.zenoh_endpoint
    duration = args.minutes * 60
    chaos = Chaos(svc, time.monotonic() + duration, v)
    samples: list[tuple[float, int, int]] = []
    threads = [
        threading.Thread(target=chaos.guarded, args=(chaos.churn_maps,), daemon=True),
        threading.Thread(target=chaos.guarded, args=(chaos.clear_regions,), daemon=True),
        threading.Thread(target=chaos.guarded, args=(chaos.bad_requests,), daemon=True),
        threading.Thread(target=chaos.guarded, args=(chaos.scrape, samples), daemon=True),
        *(threading.Thread(target=chaos.guarded, args=(chaos.streams,), daemon=True) for _ in range(4)),
        *(threading.Thread(target=chaos.guarded, args=(chaos.tiles,), daemon=True) for _ in range(2)),
    ]
    for t in threads:
        t.start()

    # Robots in rounds: each round runs until the next kill. Pairs share an id (conflicts), some
    # restart their publisher mid-way.
    rounds = args.kills + 1
    round_seconds = duration / rounds
    robots: list[tuple[subprocess.Popen[str], Path, str, str, int]] = []
    for rnd in range(rounds):
        started: list[tuple[subprocess.Popen[str], Path, str, str, int]] = []
        for k in range(args.robots):
            # k = 0, 1 share an id on stable-a, k = 2, 3 one on stable-b: id conflicts.
            map_id = STABLE_MAPS[(k // 2) % 2] if k < args.robots - 2 else CHURN_MAP
            robot_id = f"r{rnd}-{k // 2 if k < 4 else k}"
            rate = 4.0
            count = int(rate * (round_seconds - 15))
            restart_at = count // 2 if k % 3 == 0 else -1
            proc, log = start_robot(endpoint, map_id, robot_id, 100 * rnd + k, count, rate, restart_at, out)
            started.append((proc, log, map_id, robot_id, rnd))
        robots += started
        end = time.monotonic() + round_seconds
        if rnd < rounds - 1:
            # Quiesce the stable maps once before the kill, to compare them after it.
            for proc, *_ in started:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(max(1.0, end - time.monotonic()))
            wait_for(lambda: quiescent(svc.base), timeout=60, what="queue empty before kill")
            # The churned and replaced maps too (deleted, created again and replaced while the
            # snapshots, every second, store them): no change between the two looks.
            with chaos.churn_lock:
                time.sleep(1.5)  # the journal's group commit (committed before their answer/ack)
                compared = (*STABLE_MAPS, CHURN_MAP, REPLACED_MAP)
                before = {m: map_image(svc.base, m) for m in compared}
                validators = {m: cache_validators(svc.base, m) for m in STABLE_MAPS}
                print(f"[chaos] SIGKILL the service (round {rnd})", flush=True)
                svc.kill_and_restart()
                after = {m: map_image(svc.base, m) for m in compared}
            for m in compared:
                if before[m] != after[m]:
                    v.add("map after kill", f"{m}: export differs after restart (round {rnd})")
                chaos.stats["maps compared after kill"] += 1
            for m in STABLE_MAPS:
                check_validators_after_restart(svc.base, m, *validators[m], v)
        else:
            folders = {m: DeltaFolder(svc.base, m) for m in STABLE_MAPS}
            for proc, *_ in started:
                proc.wait(round_seconds + 120)

    chaos.stop.set()
    for t in threads:
        t.join(30)

    # -- end invariants
    wait_for(lambda: quiescent(svc.base), timeout=60, what="queue empty at the end")
    time.sleep(1.0)
    for m, folder in folders.items():
        try:
            wait_for(lambda f=folder: f.robots is not None, timeout=10, what="a robots event")
            fresh = fresh_robots(svc.base, m)
            wait_for(lambda f=folder, fr=fresh: f.robots == fr, timeout=5, what="folded == fresh")
            chaos.stats["folded streams equal"] += 1
        except AssertionError as exc:
            v.add("folded robots", f"{m}: {exc}; error {folder.error}")

    counters = robot_counters(svc.base)
    sent: Counter[tuple[str, str]] = Counter()
    for _proc, log, map_id, robot_id, rnd in robots:
        if rnd == rounds - 1 and map_id in STABLE_MAPS:
            lines = [ln for ln in log.read_text().splitlines() if ln.startswith("{")]
            if not lines:
                v.add("robot failed", f"{robot_id}: {log.read_text()[-500:]}")
                continue
            sent[(map_id, robot_id)] += json.loads(lines[-1])["sent"]
    for key, n in sent.items():
        c = counters.get(key, {})

        def get(name: str, c: dict[str, float] = c) -> float:
            return c.get(f"fleetmap_{name}_total", 0.0)

        accounted = (
            get("scans_integrated") + get("scans_dropped") + get("scans_rejected") + get("scans_duplicate")
        )
        chaos.stats["robots accounted"] += 1
        if accounted != n:
            v.add(
                "scan accounting", f"{key}: sent {n}, integrated+dropped+rejected+duplicate {accounted} ({c})"
            )

    repeated: Counter[str] = Counter()
    for name, text in svc.all_logs():
        for i, line in enumerate(text.splitlines()):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except ValueError:
                v.add("log not json", f"{name}:{i}: {line[:300]}")
                continue
            if "Traceback" in line or record.get("exc_info") or record.get("exception"):
                v.add("traceback", f"{name}:{i}: {line[:500]}")
            if record.get("logger") != "fleetmap.registry":  # maps created/deleted/restored: ours
                repeated[str(record.get("message"))[:120]] += 1
    # A flood: a sentence written more than 30 times a minute (strangers must not fill the log).
    for message, n in repeated.items():
        if n > 30 * args.minutes:
            v.add("log flood", f"{n} x {message}")

    # Memory and descriptors: the last third of the samples of the last generation must not stand
    # far above its first third.
    if len(samples) >= 9:
        third = len(samples) // 3
        rss0 = max(s[1] for s in samples[third : 2 * third])
        rss1 = max(s[1] for s in samples[-third:])
        fd0 = max(s[2] for s in samples[third : 2 * third])
        fd1 = max(s[2] for s in samples[-third:])
        chaos.stats["rss MB middle/end"] = f"{rss0 / 2**20:.0f}/{rss1 / 2**20:.0f}"  # type: ignore[assignment]
        chaos.stats["fds middle/end"] = f"{fd0}/{fd1}"  # type: ignore[assignment]
        if rss1 > 1.5 * rss0 + 50 * 2**20:
            v.add("memory growth", f"rss {rss0} -> {rss1}")
        if fd1 > fd0 + 50:
            v.add("fd growth", f"fds {fd0} -> {fd1}")
    code = svc.svc.stop()
    chaos.stats[f"service exit {code}"] += 1

    print(
        json.dumps(
            {"stats": chaos.stats, "violations": v.counts, "examples": v.examples}, indent=1, default=str
        )
    )
    return len(v.counts)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="mode")
    r = sub.add_parser("robot")
    r.add_argument("--connect", required=True)
    r.add_argument("--map", required=True)
    r.add_argument("--robot", required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--count", type=int, default=50)
    r.add_argument("--rate", type=float, default=5.0)
    r.add_argument("--restart-at", type=int, default=-1)
    p.add_argument("--minutes", type=float, default=3.0)
    p.add_argument("--robots", type=int, default=10)
    p.add_argument("--kills", type=int, default=2)
    p.add_argument("--out", default="/tmp/fleetmap-chaos")
    args = p.parse_args()
    if args.mode == "robot":
        return robot_main(args)
    return chaos_main(args)


if __name__ == "__main__":
    sys.exit(main())
