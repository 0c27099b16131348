"""Service benchmark: the real `fleetmap serve` process, robot processes publishing over Zenoh, real HTTP.

    make bench-service        # = .venv/bin/python benchmarks/bench_service.py   (about 2-3 minutes)
    .venv/bin/python benchmarks/bench_service.py --soak [--robots 25] [--rate 40] [--minutes 5] [--beams N]
    .venv/bin/python benchmarks/bench_service.py --ramp 16 24 32 40 [--robots 25] [--step-seconds 20]

Everything runs on loopback on this machine: the service (durable, its data directory in a temporary
directory), N robot processes (each a `fleetmap_client.ScanPublisher`: its own Zenoh client session,
binary encoding, `CongestionControl.BLOCK`), the latency checker and the HTTP load generator (`wrk`).
They share the machine's cores; the script prints how many there are.

The default run has two phases (see docs/benchmarks.md, "Service", for the method in full):

1. **Ingest, one shared map** (`--robots` robots at `--rate` Hz for `--seconds`; default 10 x 40 Hz
   for 30 s = 400 scans/s of 1081-beam 30 m scans): scans published vs integrated and the service's
   per-robot counters (lost, dropped, rejected, duplicates), the sustained integration rate, and the
   publish-to-visible latency of every scan. Robots stamp each scan with `time.time()` just before
   `publish`; a checker polls `GET /maps/{id}` every `--poll-ms` and records when each robot's
   `last_stamp` (the stamp of its last integrated scan) reaches each scan's stamp. The service sets it
   only after the scan was applied to the map (tiles and cells show it from then on) AND its journal
   row was committed, so the figure is publish -> visible and durable. It is an upper bound: the time
   the poll's answer arrived, i.e. at most one poll period plus one round trip late.
2. **Reads under ingest**: the same robots publish again, to a second shared map, while (c) `wrk`
   fetches cached PNG tiles of phase 1's map (z = 0, -1, -2, no If-None-Match, so 200s from the tile
   cache), then (d) a Python httpx client posts batch cell queries (`--points` points per request)
   on phase 1's map.

`--soak`: `--robots` robots at `--rate` Hz on one map for `--minutes`, sampling every
`--sample-seconds`: service RSS (/proc/<pid>/status), counters, and latency percentiles over each
window (service histograms from /metrics, and the checker's publish-to-visible figure).

`--ramp R ...`: the shared-map ingest phase at each per-robot rate R in turn (`--step-seconds` each),
to find the highest rate the service sustains with zero loss and with p99 under the aim.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import re
import select
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT / "tests"))
from service_process import ServiceProcess  # noqa: E402 - the tests' helper: the real service process

#: The issue's aims.
AIM_SCANS_PER_S = 400.0
AIM_P99_MS = 50.0
AIM_TILES_PER_S = 1000.0
#: Robots replay a precomputed stretch of their simulated route, forwards then backwards, so the
#: benchmark's own CPU use stays small (a 1081-beam simulated scan costs ~0.7 ms to ray-cast).
TRAJECTORY_CYCLE = 400
#: Seconds robots get to start and connect before they are told to go.
ROBOT_START_TIMEOUT = 120.0
#: Seconds of robots publishing alone before and between the read loads of phase 2.
SETTLE = 3.0
_LABELS = r'\{map="([^"]*)",robot="([^"]*)"\} (\S+)$'
COUNTER_RE = re.compile(r"^fleetmap_scans_(integrated|rejected|lost|duplicate|dropped)_total" + _LABELS, re.M)


# == the robot process ================================================================================


def robot_main(argv: Sequence[str]) -> int:
    """One robot (run as `bench_service.py _robot ...`): load a trajectory, connect, print `ready`,
    wait for `go T0 SECONDS` on stdin, then publish scan k at wall time T0 + (phase + k) / rate with
    seq k and stamp = time.time() taken just before `publish`, until T0 + SECONDS. Writes the stamps
    (.npy) to --out and prints one JSON line: published, dropped, lateness and publish-call times."""
    from fleetmap_client.publisher import ScanPublisher

    from fleetmap.scan import Scan

    p = argparse.ArgumentParser(prog="bench_service.py _robot")
    p.add_argument("--connect", required=True)
    p.add_argument("--map", required=True)
    p.add_argument("--robot", required=True)
    p.add_argument("--trajectory", required=True, type=Path)
    p.add_argument("--rate", required=True, type=float)
    p.add_argument("--phase", type=float, default=0.0, help="offset in periods, [0, 1)")
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args(argv)

    data = np.load(args.trajectory)
    poses, ranges = data["poses"], data["ranges"]
    amin, inc, rmin, rmax = (float(v) for v in data["fan"])
    scans = [
        Scan.from_fan(tuple(pose), amin, inc, r, rmin, rmax) for pose, r in zip(poses, ranges, strict=True)
    ]
    order = _ping_pong(len(scans))
    pub = ScanPublisher(args.map, args.robot, connect=[args.connect], encoding="binary", block=True)
    try:
        if not pub.wait_connected(60.0):
            print(f"robot {args.robot}: service not reachable", file=sys.stderr, flush=True)
            return 3
        print("ready", flush=True)
        words = sys.stdin.readline().split()
        if len(words) != 3 or words[0] != "go":
            return 2
        t0, seconds = float(words[1]), float(words[2])
        period = 1.0 / args.rate
        count = max(0, math.ceil(seconds * args.rate - args.phase))
        stamps = np.full(count, np.nan)
        lateness = np.zeros(count)
        call = np.zeros(count)
        published = 0
        for k in range(count):
            due = t0 + (args.phase + k) * period
            delay = due - time.time()
            if delay > 0:
                time.sleep(delay)
            stamp = time.time()
            pub.publish(scans[order[k % len(order)]], seq=k, stamp=stamp)
            done = time.time()
            stamps[k], lateness[k], call[k] = stamp, stamp - due, done - stamp
            published += 1
        np.save(args.out, stamps[:published])
        summary = {
            "published": pub.published,
            "dropped": pub.dropped,
            "late_p99_ms": float(np.percentile(lateness, 99) * 1e3) if count else 0.0,
            "late_max_ms": float(lateness.max() * 1e3) if count else 0.0,
            "publish_max_ms": float(call.max() * 1e3) if count else 0.0,
        }
        print(json.dumps(summary), flush=True)
    finally:
        pub.close()  # flushes what Zenoh still holds (reliable channel)
    return 0


def _ping_pong(n: int) -> list[int]:
    """Indices 0..n-1 then back n-2..1: a continuous route when repeated."""
    return list(range(n)) + list(range(n - 2, 0, -1)) if n > 2 else list(range(n))


# == trajectories =====================================================================================


def build_trajectories(count: int, robots: int, rate: float, beams: int, out_dir: Path) -> list[Path]:
    """Simulate `robots` robots on floor plan 1 (40 x 30 m) with 1081-beam-style 270 degree, 30 m
    lidars (`beams` beams) for `count` ticks at `rate` Hz each; save poses and ranges per robot."""
    from fleetmap.sim import SimulatedRobot, generate_floorplan

    plan = generate_floorplan(1)
    paths = []
    for k in range(robots):
        sim = SimulatedRobot(plan, seed=1000 + k, scan_rate=rate, num_beams=beams, range_max=30.0, speed=1.0)
        scans = [sim.tick() for _ in range(count)]
        first = scans[0]
        path = out_dir / f"trajectory-{beams}-{k}.npz"
        np.savez(
            path,
            poses=np.array([[s.pose.x, s.pose.y, s.pose.theta] for s in scans]),
            ranges=np.stack([s.ranges for s in scans]).astype(np.float32),
            fan=np.array(
                [first.angles[0], first.angles[1] - first.angles[0], first.range_min, first.range_max]
            ),
        )
        paths.append(path)
    return paths


# == robots as processes ==============================================================================


@dataclass
class RobotSpec:
    map_id: str
    robot_id: str
    trajectory: Path
    phase: float


class RobotWorker:
    """One robot process (`robot_main`), driven over its stdin / stdout."""

    def __init__(self, spec: RobotSpec, endpoint: str, rate: float, work_dir: Path) -> None:
        self.spec = spec
        self.out = work_dir / f"stamps-{spec.map_id}-{spec.robot_id}.npy"
        self.log_path = work_dir / f"robot-{spec.map_id}-{spec.robot_id}.log"
        log = open(self.log_path, "wb")  # noqa: SIM115 - the child writes to it until it exits
        self.proc = subprocess.Popen(
            [
                sys.executable, str(Path(__file__).resolve()), "_robot", "--connect", endpoint,
                "--map", spec.map_id, "--robot", spec.robot_id, "--trajectory", str(spec.trajectory),
                "--rate", str(rate), "--phase", str(spec.phase), "--out", str(self.out),
            ],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True,
        )  # fmt: skip
        log.close()
        self.summary: dict[str, Any] = {}

    def _line(self, deadline: float) -> str:
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.proc.stdout], [], [], 0.2)
            if ready:
                line = self.proc.stdout.readline()
                if not line:
                    break
                return line.strip()
            if self.proc.poll() is not None:
                break
        raise RuntimeError(f"robot {self.spec.robot_id} gave no answer:\n{self.log_path.read_text()[-2000:]}")

    def wait_ready(self, deadline: float) -> None:
        if self._line(deadline) != "ready":
            raise RuntimeError(f"robot {self.spec.robot_id} did not get ready")

    def go(self, t0: float, seconds: float) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"go {t0:.6f} {seconds}\n")
        self.proc.stdin.flush()

    def finish(self, deadline: float) -> tuple[dict[str, Any], np.ndarray]:
        self.summary = json.loads(self._line(deadline))
        self.proc.wait(max(1.0, deadline - time.monotonic()))
        return self.summary, np.load(self.out)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


# == reading the service ==============================================================================


def robot_counters(text: str) -> dict[tuple[str, str], dict[str, int]]:
    """{(map, robot): {integrated, rejected, lost, duplicate, dropped}} from a /metrics text."""
    out: dict[tuple[str, str], dict[str, int]] = {}
    for name, m, r, v in COUNTER_RE.findall(text):
        out.setdefault((m, r), {})[name] = int(float(v))
    return out


def histogram(text: str, name: str) -> tuple[list[float], np.ndarray]:
    """(upper bounds, cumulative counts) of a Prometheus histogram in a /metrics text."""
    pattern = re.compile(rf'^{name}_bucket\{{le="([^"]+)"\}} (\S+)$', re.M)
    pairs = [(float(le), float(v)) for le, v in pattern.findall(text)]
    return [le for le, _ in pairs], np.array([v for _, v in pairs])


def histogram_quantile(bounds: list[float], cumulative: np.ndarray, q: float) -> float:
    """Prometheus' histogram_quantile: linear interpolation inside the bucket holding rank q * n.
    NaN without observations; the last finite bound when the rank is in the +Inf bucket."""
    total = cumulative[-1] if len(cumulative) else 0.0
    if total <= 0:
        return math.nan
    rank = q * total
    k = int(np.searchsorted(cumulative, rank, side="left"))
    if k >= len(bounds) - 1 and math.isinf(bounds[-1]):
        return bounds[-2]
    lo = bounds[k - 1] if k > 0 else 0.0
    below = cumulative[k - 1] if k > 0 else 0.0
    inside = cumulative[k] - below
    return lo + (bounds[k] - lo) * ((rank - below) / inside if inside > 0 else 1.0)


def histogram_delta(before: str, after: str, name: str) -> tuple[list[float], np.ndarray]:
    b_bounds, b = histogram(before, name)
    a_bounds, a = histogram(after, name)
    if not a_bounds:
        return [], np.zeros(0)
    return a_bounds, a - (b if len(b) == len(a) else 0.0)


def proc_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_memory_mib(pid: int) -> dict[str, float]:
    """Resident memory of a process in MiB from /proc/<pid>/status: VmRSS (all resident pages) and its
    parts RssAnon (heap: what a leak grows), RssFile (mapped files: libraries, the database) and
    RssShmem."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
            out[name] = int(value.split()[0]) / 1024.0
    return out


def machine_busy() -> tuple[float, float]:
    """(busy, total) jiffies of all CPUs (/proc/stat), for the machine's utilisation over a span."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = values[3] + values[4]
    return float(sum(values) - idle), float(sum(values))


class Poller(threading.Thread):
    """The latency checker: polls GET /maps/{map_id} of every map in `keys` each `period` s and records,
    per (map, robot) of `keys`, the robot's `last_stamp` (stamp of its last integrated AND durable
    scan: the registry sets it when the scan's journal row is committed, after the scan was applied to
    the map) and `scans_integrated`, with the time each answer arrived."""

    def __init__(self, base_url: str, keys: list[tuple[str, str]], period: float) -> None:
        super().__init__(name="latency-checker", daemon=True)
        self.client = httpx.Client(base_url=base_url, timeout=10.0)
        self.keys = keys
        self.maps = sorted({m for m, _ in keys})
        self.period = period
        self.received: list[float] = []
        self.stamps: list[list[float]] = []
        self.counts: list[list[int]] = []
        self.latest: dict[tuple[str, str], int] = {}
        self.errors = 0
        self._halt = threading.Event()

    def poll(self) -> None:
        """One poll of every map; an answer that fails is counted in `errors` and skipped."""
        try:
            robots = {m: self.client.get(f"/maps/{m}").json()["stats"]["robots"] for m in self.maps}
        except (httpx.HTTPError, ValueError, KeyError):
            self.errors += 1
            return
        received = time.time()
        stamps, counts = [], []
        for m, r in self.keys:
            state = robots[m].get(r) or {}
            stamp = state.get("last_stamp")
            stamps.append(-math.inf if stamp is None else float(stamp))
            counts.append(int(state.get("scans_integrated", 0)))
        self.latest = dict(zip(self.keys, counts, strict=True))
        self.received.append(received)
        self.stamps.append(stamps)
        self.counts.append(counts)

    def run(self) -> None:
        next_at = time.monotonic()
        while not self._halt.is_set():
            self.poll()
            next_at += self.period
            delay = next_at - time.monotonic()
            if delay > 0:
                self._halt.wait(delay)
            else:
                next_at = time.monotonic()

    def stop(self) -> None:
        self._halt.set()
        self.join(10)
        self.client.close()

    def visible_times(self, key_index: int, published: np.ndarray) -> np.ndarray:
        """For the scans a robot published at wall times `published` (its stamps, increasing): when
        the first poll that showed each one integrated arrived; NaN for scans never integrated.

        A robot's scans are integrated in order, so scan k is integrated once the robot's last_stamp
        reaches its stamp. Scans refused on the way (a full queue) never move last_stamp themselves;
        they are found by counting: if n scans passed last_stamp between two polls but
        `scans_integrated` grew by fewer, the difference are scans that were not integrated, and the
        newest ones of that span (a full queue refuses the newest) are marked NaN."""
        last = np.array([row[key_index] for row in self.stamps])
        counts = np.array([row[key_index] for row in self.counts], dtype=np.int64)
        received = np.array(self.received)
        idx = np.searchsorted(last, published, side="left")  # first poll with last_stamp >= stamp
        out = np.full(len(published), np.nan)
        seen = idx < len(received)
        out[seen] = received[idx[seen]]
        for poll in np.unique(idx[seen]):
            members = np.flatnonzero(idx == poll)
            grew = counts[poll] - (counts[poll - 1] if poll > 0 else 0)
            missing = len(members) - grew
            if missing > 0:
                out[members[len(members) - missing :]] = np.nan
        return out

    def poll_period_ms(self) -> float:
        return float(np.median(np.diff(self.received)) * 1e3) if len(self.received) > 1 else math.nan


# == one ingest phase =================================================================================


@dataclass
class IngestResult:
    label: str
    robots: int
    rate: float
    seconds: float
    published: int = 0
    publisher_dropped: int = 0
    integrated: int = 0
    lost: int = 0
    dropped: int = 0
    rejected: int = 0
    duplicates: int = 0
    integrated_in_window: int = 0
    drain_seconds: float = math.nan
    t0: float = 0.0
    #: Per published scan: wall time of its publish, and its publish -> visible latency in ms (NaN:
    #: never seen integrated).
    published_at: np.ndarray = field(default_factory=lambda: np.zeros(0))
    latency_all: np.ndarray = field(default_factory=lambda: np.zeros(0))
    poll_ms: float = math.nan
    service_ingest_p50_ms: float = math.nan
    service_ingest_p99_ms: float = math.nan
    service_integration_mean_ms: float = math.nan
    service_cores: float = math.nan
    machine_busy: float = math.nan
    late_p99_ms: float = 0.0
    publish_max_ms: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def loss(self) -> int:
        """Scans the robots tried to publish that were not integrated, whatever the reason (dropped by
        the publisher or the service's queue, lost on the way, rejected)."""
        return max(0, self.published + self.publisher_dropped - self.integrated)

    @property
    def sustained(self) -> float:
        return self.integrated_in_window / self.seconds

    @property
    def latency_ms(self) -> np.ndarray:
        """Latencies of the scans that became visible."""
        return self.latency_all[~np.isnan(self.latency_all)]

    @property
    def not_visible(self) -> int:
        return int(np.isnan(self.latency_all).sum())

    def pct(self, q: float) -> float:
        lat = self.latency_ms
        return float(np.percentile(lat, q)) if lat.size else math.nan

    def segment(self, start: float, end: float) -> tuple[int, int, float, float]:
        """(scans published in [start, end) wall time, of which never visible, p50 ms, p99 ms)."""
        inside = (self.published_at >= start) & (self.published_at < end)
        lat = self.latency_all[inside]
        seen = lat[~np.isnan(lat)]
        if not seen.size:
            return int(inside.sum()), int(lat.size), math.nan, math.nan
        return int(inside.sum()), int(lat.size - seen.size), *np.percentile(seen, [50, 99]).tolist()

    def windows(self, length: float) -> list[tuple[float, int, int, float, float]]:
        """`segment` over consecutive windows of `length` s from t0: (start - t0, *segment)."""
        return [
            (float(t - self.t0), *self.segment(t, t + length))
            for t in np.arange(self.t0, self.t0 + self.seconds, length)
        ]


def run_ingest(
    svc: ServiceProcess,
    specs: list[RobotSpec],
    rate: float,
    seconds: float,
    poll_ms: float,
    work_dir: Path,
    label: str,
    during: Callable[[float, float], dict[str, Any]] | None = None,
    sampler: Callable[[float, float], None] | None = None,
) -> IngestResult:
    """Run the robots of `specs` at `rate` Hz for `seconds` against the service; measure everything.

    `during(t0, seconds)` runs in this thread while the robots publish (its result lands in
    `extra`); `sampler(t0, seconds)` likewise (the soak's periodic sampling)."""
    result = IngestResult(label, len(specs), rate, seconds)
    started = time.monotonic()
    workers = [RobotWorker(spec, svc.zenoh_endpoint, rate, work_dir) for spec in specs]
    client = httpx.Client(base_url=svc.base_url, timeout=30.0)
    assert svc.proc is not None
    pid = svc.proc.pid
    try:
        deadline = time.monotonic() + ROBOT_START_TIMEOUT
        for w in workers:
            w.wait_ready(deadline)
        print(f"  {len(workers)} robot processes connected in {time.monotonic() - started:.1f} s", flush=True)
        keys = [(s.map_id, s.robot_id) for s in specs]
        poller = Poller(svc.base_url, keys, poll_ms / 1e3)
        before = client.get("/metrics").text
        cpu_before, busy_before = proc_cpu_seconds(pid), machine_busy()
        poller.start()
        t0 = time.time() + 1.0
        for w in workers:
            w.go(t0, seconds)
        if during is not None:
            result.extra = during(t0, seconds)
        if sampler is not None:
            sampler(t0, seconds)
        time.sleep(max(0.0, t0 + seconds - time.time()))
        window_end = t0 + seconds
        cpu_after, busy_after = proc_cpu_seconds(pid), machine_busy()
        finish_deadline = time.monotonic() + 60.0
        stamps: list[np.ndarray] = []
        for w in workers:
            summary, s = w.finish(finish_deadline)
            stamps.append(s)
            result.published += int(summary["published"])
            result.publisher_dropped += int(summary["dropped"])
            result.late_p99_ms = max(result.late_p99_ms, summary["late_p99_ms"])
            result.publish_max_ms = max(result.publish_max_ms, summary["publish_max_ms"])
        # Drain: wait (up to 30 s) until every published scan is counted as integrated, or, when some
        # were dropped, until the service's queue is empty and the counts stood still for a second.
        drain_deadline = time.monotonic() + 30.0
        last_change, last_counts = time.monotonic(), dict(poller.latest)
        while time.monotonic() < drain_deadline:
            latest = poller.latest
            if all(latest.get(k, 0) >= len(s) for k, s in zip(keys, stamps, strict=True)):
                break
            if latest != last_counts:
                last_change, last_counts = time.monotonic(), dict(latest)
            elif time.monotonic() - last_change > 1.0 and client.get("/healthz").json()["queue_depth"] == 0:
                break
            time.sleep(0.05)
        time.sleep(3 * poll_ms / 1e3)
        poller.stop()
        after = client.get("/metrics").text
    finally:
        for w in workers:
            w.kill()
        client.close()

    counters = robot_counters(after)
    for key in keys:
        c = counters.get(key, {})
        result.integrated += c.get("integrated", 0)
        result.lost += c.get("lost", 0)
        result.dropped += c.get("dropped", 0)
        result.rejected += c.get("rejected", 0)
        result.duplicates += c.get("duplicate", 0)
    # Sustained rate: scans integrated between t0 and the end of the publishing window.
    received = np.array(poller.received)
    totals = np.array([sum(c) for c in poller.counts])
    at = np.searchsorted(received, [t0, window_end], side="right") - 1
    if len(totals) and at[1] >= 0:
        result.integrated_in_window = int(totals[at[1]] - (totals[at[0]] if at[0] >= 0 else 0))
    # Drain: from the end of the window to the first poll that saw every published scan integrated.
    complete = np.flatnonzero(totals >= sum(len(s) for s in stamps)) if len(totals) else np.zeros(0, int)
    if complete.size:
        result.drain_seconds = max(0.0, float(received[complete[0]]) - window_end)
    # Publish-to-visible latency of every scan.
    latencies, published_at = [], []
    for k, s in enumerate(stamps):
        visible = poller.visible_times(k, s)
        latencies.append((visible - s) * 1e3)
        published_at.append(s)
    result.t0 = t0
    result.latency_all = np.concatenate(latencies) if latencies else np.zeros(0)
    result.published_at = np.concatenate(published_at) if published_at else np.zeros(0)
    result.poll_ms = poller.poll_period_ms()
    bounds, delta = histogram_delta(before, after, "fleetmap_ingest_latency_seconds")
    result.service_ingest_p50_ms = histogram_quantile(bounds, delta, 0.5) * 1e3
    result.service_ingest_p99_ms = histogram_quantile(bounds, delta, 0.99) * 1e3
    n_int = _scalar(after, "fleetmap_integration_seconds_count") - _scalar(
        before, "fleetmap_integration_seconds_count"
    )
    s_int = _scalar(after, "fleetmap_integration_seconds_sum") - _scalar(
        before, "fleetmap_integration_seconds_sum"
    )
    result.service_integration_mean_ms = s_int / n_int * 1e3 if n_int > 0 else math.nan
    result.service_cores = (cpu_after - cpu_before) / seconds
    busy = busy_after[0] - busy_before[0]
    total = busy_after[1] - busy_before[1]
    result.machine_busy = busy / total if total > 0 else math.nan
    return result


def service_view(before: str, after: str) -> str:
    """What the service's /metrics say happened between two scrapes: its own queued -> durable
    latency (histogram buckets, so coarse), plan + apply time, scans dropped, and the HTTP requests
    held back for ingest (docs/api.md, "Ingest before reads"), including the checker's polls."""

    def delta(name: str) -> float:
        return _scalar(after, name) - _scalar(before, name)

    bounds, counts = histogram_delta(before, after, "fleetmap_ingest_latency_seconds")
    n = delta("fleetmap_integration_seconds_count")
    plan_apply = delta("fleetmap_integration_seconds_sum") / n * 1e3 if n > 0 else math.nan
    dropped = sum(c.get("dropped", 0) for c in robot_counters(after).values()) - sum(
        c.get("dropped", 0) for c in robot_counters(before).values()
    )
    delayed = delta("fleetmap_http_delayed_requests_total")
    waited = delta("fleetmap_http_delay_seconds_total")
    full_gc = _scalar(after, 'fleetmap_gc_collections_total{generation="2"}') - _scalar(
        before, 'fleetmap_gc_collections_total{generation="2"}'
    )
    return (
        f"queued -> durable p50 {histogram_quantile(bounds, counts, 0.5) * 1e3:.1f} ms, p99 "
        f"{histogram_quantile(bounds, counts, 0.99) * 1e3:.1f} ms; plan+apply mean {plan_apply:.2f} ms; "
        f"dropped {dropped}; HTTP requests held back for ingest {delayed:.0f}"
        + (f" (mean wait {waited / delayed * 1e3:.1f} ms)" if delayed else "")
        + f", served at the longest wait {delta('fleetmap_http_delay_timeouts_total'):.0f}; "
        f"full GCs {full_gc:.0f}"
    )


def _scalar(text: str, name: str) -> float:
    match = re.search(rf"^{re.escape(name)} (\S+)$", text, re.M)
    return float(match.group(1)) if match else 0.0


def print_ingest(r: IngestResult, window: float | None = None) -> None:
    """The figures of one ingest phase (and its latency per `window` seconds, if given)."""
    target = r.robots * r.rate
    print(
        f"  published {r.published} scans in {r.seconds:.0f} s = {r.published / r.seconds:.1f}/s (target "
        f"{target:.0f}/s; robots' schedule lateness p99 {r.late_p99_ms:.1f} ms, longest publish call "
        f"{r.publish_max_ms:.1f} ms)"
    )
    print(
        f"  integrated {r.integrated}: sustained {r.sustained:.1f} scans/s inside the window, "
        + (
            f"the rest within {r.drain_seconds:.2f} s after it"
            if r.drain_seconds >= 0
            else "NOT all in the end"
        )
    )
    print(
        f"  loss {r.loss} (service counters: lost {r.lost}, dropped on a full queue {r.dropped}, rejected "
        f"{r.rejected}, duplicates {r.duplicates}; publisher dropped {r.publisher_dropped})"
    )
    lat = r.latency_ms
    print(
        f"  publish -> visible+durable (checker, {lat.size} scans, poll every {r.poll_ms:.1f} ms): "
        f"p50 {r.pct(50):.1f} ms, p90 {r.pct(90):.1f} ms, p99 {r.pct(99):.1f} ms, max "
        f"{lat.max() if lat.size else math.nan:.1f} ms"
        + (f"; {r.not_visible} never seen" if r.not_visible else "")
    )
    if window:
        parts = [f"{t:.0f}s: {p50:.0f}/{p99:.0f}" + (f" ({lost} never visible)" if lost else "")
                 for t, _, lost, p50, p99 in r.windows(window)]  # fmt: skip
        print(f"  per {window:g} s window, p50/p99 ms: " + ", ".join(parts))
    print(
        f"  service histograms: queued -> integrated+durable p50 {r.service_ingest_p50_ms:.1f} ms, "
        f"p99 {r.service_ingest_p99_ms:.1f} ms; plan+apply mean {r.service_integration_mean_ms:.2f} ms"
    )
    print(f"  service CPU {r.service_cores:.2f} cores; whole machine {r.machine_busy * 100:.0f} % busy")


def dump(path: Path | None, results: dict[str, IngestResult]) -> None:
    """Save every phase's per-scan publish times and latencies (`--dump FILE.npz`), for analysis."""
    if path is None:
        return
    arrays: dict[str, np.ndarray] = {}
    for name, r in results.items():
        arrays[f"{name}_published_at"] = r.published_at
        arrays[f"{name}_latency_ms"] = r.latency_all
        arrays[f"{name}_t0"] = np.array([r.t0])
    np.savez(path, **arrays)
    print(f"per-scan data saved to {path}")


# == reads: tiles with wrk, cells with httpx ==========================================================


def tile_paths(info: dict[str, Any], map_id: str, zooms: Sequence[int] = (0, -1, -2)) -> list[str]:
    """Every tile URL path of the map's observed bounds at the given zooms (Leaflet CRS.Simple:
    tile (z, x, y) covers cells i in [x*S, (x+1)*S), j in [-(y+1)*S, -y*S), S = 256 / 2**z)."""
    res = info["resolution"]
    xmin, ymin, xmax, ymax = info["stats"]["bounds"]
    i0, j0 = math.floor(xmin / res), math.floor(ymin / res)
    i1, j1 = math.ceil(xmax / res), math.ceil(ymax / res)
    paths = []
    for z in zooms:
        s = int(256 / 2**z)
        for x in range(i0 // s, (i1 - 1) // s + 1):
            for y in range(-((j1 - 1) // s) - 1, -(j0 // s) - 1 + 1):
                paths.append(f"/maps/{map_id}/tiles/{z}/{x}/{y}.png")
    return paths


WRK_LUA = """
paths = {%s}
counter = 0
request = function()
  counter = counter + 1
  return wrk.format("GET", paths[(counter %% #paths) + 1])
end
"""


def ensure_wrk() -> str | None:
    """The wrk executable, installing Debian's package if missing (needs root); None if unavailable."""
    found = shutil.which("wrk")
    if found:
        return found
    script = REPO_ROOT / "scripts" / "system-deps.sh"
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        subprocess.run(["bash", str(script), "wrk"], check=False, timeout=300)
    return shutil.which("wrk")


def _wrk_ms(value: str, unit: str) -> float:
    return float(value) * {"us": 1e-3, "ms": 1.0, "s": 1e3}[unit]


def run_wrk(wrk: str, base_url: str, paths: list[str], seconds: float, threads: int, connections: int,
            work_dir: Path) -> dict[str, Any]:  # fmt: skip
    """wrk over `paths` in rotation; returns requests/s, latency percentiles and errors."""
    script = work_dir / "tiles.lua"
    script.write_text(WRK_LUA % ", ".join(json.dumps(p) for p in paths))
    cmd = [wrk, f"-t{threads}", f"-c{connections}", f"-d{seconds:.0f}s", "--latency", "--timeout", "5s",
           "-s", str(script), base_url]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 60, check=False).stdout
    result: dict[str, Any] = {"command": " ".join(cmd[:-3] + ["tiles.lua", base_url]), "raw": out}
    m = re.search(r"Requests/sec:\s+([\d.]+)", out)
    result["rps"] = float(m.group(1)) if m else math.nan
    m = re.search(r"(\d+) requests in ([\d.]+)(\w+)", out)
    result["requests"] = int(m.group(1)) if m else 0
    for pct in ("50", "75", "90", "99"):
        m = re.search(rf"^\s+{pct}%\s+([\d.]+)(us|ms|s)\s*$", out, re.M)
        result[f"p{pct}_ms"] = _wrk_ms(m.group(1), m.group(2)) if m else math.nan
    m = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
    result["non2xx"] = int(m.group(1)) if m else 0
    m = re.search(r"Socket errors: connect (\d+), read (\d+), write (\d+), timeout (\d+)", out)
    result["socket_errors"] = sum(int(g) for g in m.groups()) if m else 0
    return result


def run_cells(base_url: str, map_id: str, bounds: list[float], points: int, seconds: float) -> dict[str, Any]:
    """POST /maps/{map_id}/cells with `points` random points inside `bounds` in a loop for `seconds`."""
    rng = np.random.default_rng(3)
    xmin, ymin, xmax, ymax = bounds
    pts = np.column_stack([rng.uniform(xmin, xmax, points), rng.uniform(ymin, ymax, points)])
    body = json.dumps({"points": pts.round(3).tolist()}).encode()
    times = []
    sizes = 0
    with httpx.Client(base_url=base_url, timeout=30.0) as client:
        url = f"/maps/{map_id}/cells"
        headers = {"content-type": "application/json"}
        first = client.post(url, content=body, headers=headers)
        first.raise_for_status()
        answer = first.json()
        if answer["count"] != points or len(answer["probability"]) != points:
            raise RuntimeError(f"cells answered {answer['count']} values for {points} points")
        known = float(np.mean(answer["known"]))
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t = time.perf_counter()
            r = client.post(url, content=body, headers=headers)
            times.append(time.perf_counter() - t)
            r.raise_for_status()
            sizes += len(r.content)
    total = sum(times)
    return {
        "requests": len(times),
        "rps": len(times) / total if total else math.nan,
        "points_per_s": len(times) * points / total if total else math.nan,
        "p50_ms": float(np.percentile(times, 50) * 1e3) if times else math.nan,
        "p99_ms": float(np.percentile(times, 99) * 1e3) if times else math.nan,
        "response_kib": sizes / max(1, len(times)) / 1024,
        "known_fraction": known,
        "body_kib": len(body) / 1024,
    }


# == machine ==========================================================================================


def machine_lines() -> list[str]:
    model, mhz = "unknown", ""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model == "unknown":
                model = line.split(":", 1)[1].strip()
            elif line.startswith("cpu MHz") and not mhz:
                mhz = f", {float(line.split(':', 1)[1]):.0f} MHz"
    try:
        git = ["git", "-C", str(REPO_ROOT), "rev-parse", "--short", "HEAD"]
        commit = subprocess.run(git, capture_output=True, text=True, check=False, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = "?"
    wrk = shutil.which("wrk")
    wrk_version = "not installed"
    if wrk:
        text = subprocess.run([wrk, "--version"], capture_output=True, text=True, check=False).stdout
        wrk_version = text.split("[")[0].replace("wrk", "").strip() or "?"

    def v(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "?"

    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return [
        f"date: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; git {commit or '?'}",
        f"CPU: {model}{mhz}; {os.cpu_count()} logical cores, SHARED by the service, the robot processes, "
        f"the checker and the load generator (and anything else running); load average before: {load}",
        f"Python {platform.python_version()}, fleetmap {v('fleetmap')}, numpy {np.__version__}, "
        f"numba {v('numba')}, eclipse-zenoh {v('eclipse-zenoh')}, fastapi {v('fastapi')}, "
        f"uvicorn {v('uvicorn')}, httpx {v('httpx')}, wrk {wrk_version}",
    ]


def verdict(ok: bool) -> str:
    return "MET" if ok else "NOT MET"


# == the default benchmark ============================================================================


def start_service(work_dir: Path, workers: int | None, extra: Sequence[str] = ()) -> ServiceProcess:
    """The real service on free loopback ports, durable in `work_dir`/data unless `extra` says
    --in-memory; waits for /healthz."""
    args = list(extra)
    if "--in-memory" not in args:
        args += ["--data-dir", str(work_dir / "data")]
    if workers:
        args += ["--workers", str(workers)]
    svc = ServiceProcess(work_dir, extra_args=args).start()
    assert svc.proc is not None
    storage = "IN MEMORY" if "--in-memory" in args else f"durable in {work_dir / 'data'}"
    print(
        f"service: pid {svc.proc.pid}, {svc.base_url}, zenoh {svc.zenoh_endpoint}, {storage}, "
        + (f"{workers} integration workers" if workers else "default workers")
        + (f", extra arguments {' '.join(extra)}" if extra else "")
    )
    return svc


@dataclass
class Reads:
    """Phase 2's read figures."""

    wrk: dict[str, Any] | None
    cells: dict[str, Any]
    tile_hits: float
    tile_renders: float


def bench(args: argparse.Namespace) -> int:
    """The default run: phase 1 (ingest on one shared map) and phase 2 (reads under ingest)."""
    overall = time.monotonic()
    print("fleetmap service benchmark (loopback, one run)")
    for line in machine_lines():
        print("  " + line)
    wrk = None if args.no_wrk or args.no_reads else ensure_wrk()
    p2: IngestResult | None = None
    reads: Reads | None = None
    with tempfile.TemporaryDirectory(prefix="fleetmap-bench-") as tmp:
        work_dir = Path(tmp)
        count = min(TRAJECTORY_CYCLE, int(args.seconds * args.rate) + 1)
        t = time.monotonic()
        trajectories = build_trajectories(count, args.robots, args.rate, args.beams, work_dir)
        print(
            f"simulated {args.robots} trajectories x {count} scans of {args.beams} beams, 270 deg, 30 m in "
            f"{time.monotonic() - t:.1f} s (robots replay them forwards then backwards)"
        )
        svc = start_service(work_dir, args.workers, args.service_arg)
        try:
            p1 = phase_ingest(svc, args, trajectories, work_dir)
            if not args.no_reads:
                p2, reads = phase_reads(svc, args, trajectories, work_dir, wrk)
        finally:
            code = svc.stop()
            print(f"\nservice stopped (exit code {code})")
    dump(args.dump, {"shared": p1} | ({"busy": p2} if p2 else {}))
    summary(args, p1, p2, reads)
    print(
        f"  total time {time.monotonic() - overall:.0f} s; the machine's {os.cpu_count()} cores are shared "
        "by all the processes above"
    )
    return 0


def phase_ingest(
    svc: ServiceProcess, args: argparse.Namespace, trajectories: list[Path], work_dir: Path
) -> IngestResult:
    """Phase 1: the robots on one shared map."""
    print(
        f"\n[1] ingest: {args.robots} robot processes -> ONE shared map, {args.rate:g} Hz each, "
        f"{args.seconds:g} s, binary, CongestionControl.BLOCK"
    )
    with httpx.Client(base_url=svc.base_url, timeout=30.0) as client:
        client.put("/maps/shared").raise_for_status()
    specs = [RobotSpec("shared", f"r{k:02d}", trajectories[k], k / args.robots) for k in range(args.robots)]
    p1 = run_ingest(svc, specs, args.rate, args.seconds, args.poll_ms, work_dir, "shared map")
    print_ingest(p1, 5.0)
    return p1


def phase_reads(
    svc: ServiceProcess, args: argparse.Namespace, trajectories: list[Path], work_dir: Path, wrk: str | None
) -> tuple[IngestResult, Reads]:
    """Phase 2: the robots again, on a second map, while wrk fetches cached tiles of the first map and
    then a client posts batch cell queries on it."""
    client = httpx.Client(base_url=svc.base_url, timeout=30.0)
    info = client.get("/maps/shared").json()
    paths = tile_paths(info, "shared")
    for path in paths:  # render every tile once, so that wrk's requests are cache hits
        r = client.get(path)
        if r.status_code != 200 or r.headers.get("content-type") != "image/png":
            raise RuntimeError(f"GET {path}: {r.status_code}")
    print(
        f"\n[2] reads under ingest: {args.robots} robots -> a second map 'busy', {args.rate:g} Hz; meanwhile "
        f"(c) wrk on the {len(paths)} cached tiles of map 'shared' at z = 0, -1, -2, then (d) batch cell "
        f"queries of {args.points} points"
    )
    client.put("/maps/busy").raise_for_status()
    specs = [RobotSpec("busy", f"q{k:02d}", trajectories[k], k / args.robots) for k in range(args.robots)]
    before = client.get("/metrics").text

    def loads(t0: float, seconds: float) -> dict[str, Any]:
        """Robots alone for SETTLE s, wrk, robots alone for SETTLE s, cell queries, the rest."""
        out: dict[str, Any] = {"wrk": None}
        time.sleep(max(0.0, t0 + SETTLE - time.time()))
        if wrk is not None:
            start, metrics_before = time.time(), client.get("/metrics").text
            out["wrk"] = run_wrk(
                wrk, svc.base_url, paths, args.wrk_seconds, args.wrk_threads, args.wrk_connections, work_dir
            )
            out["wrk_span"] = (start, time.time())
            out["wrk_metrics"] = (metrics_before, client.get("/metrics").text)
            time.sleep(SETTLE)
        start, metrics_before = time.time(), client.get("/metrics").text
        out["cells"] = run_cells(
            svc.base_url, "shared", info["stats"]["bounds"], args.points, args.cells_seconds
        )
        out["cells_span"] = (start, time.time())
        out["cells_metrics"] = (metrics_before, client.get("/metrics").text)
        out["overran"] = time.time() > t0 + seconds
        return out

    seconds = (args.wrk_seconds + SETTLE if wrk else 0.0) + args.cells_seconds + 2 * SETTLE
    p2 = run_ingest(svc, specs, args.rate, seconds, args.poll_ms, work_dir, "busy map", loads)
    after = client.get("/metrics").text
    client.close()
    print_ingest(p2)
    spans = [("robots alone", p2.t0, p2.t0 + SETTLE, None)]
    if wrk is not None:
        spans.append(("during wrk", *p2.extra["wrk_span"], p2.extra["wrk_metrics"]))
    spans.append(("during cell queries", *p2.extra["cells_span"], p2.extra["cells_metrics"]))
    for name, a, b, texts in spans:
        n, unseen, p50, p99 = p2.segment(a, b)
        print(
            f"  scans published {name} ({b - a:.0f} s): {n}, never visible {unseen}, p50 {p50:.1f} ms, "
            f"p99 {p99:.1f} ms"
        )
        if texts is not None:
            print("    service side: " + service_view(*texts))
    if p2.extra.get("overran"):
        print("  note: the reads outlasted the robots' publishing window")
    reads = Reads(
        p2.extra["wrk"],
        p2.extra["cells"],
        _scalar(after, "fleetmap_tile_cache_hits_total") - _scalar(before, "fleetmap_tile_cache_hits_total"),
        _scalar(after, "fleetmap_tile_renders_total") - _scalar(before, "fleetmap_tile_renders_total"),
    )
    w, c = reads.wrk, reads.cells
    if w is None:
        print(
            "  (c) tiles: SKIPPED: wrk is not installed and could not be installed "
            "(bash scripts/system-deps.sh wrk needs root and apt)"
        )
    else:
        print(
            f"  (c) {w['command']}: {w['requests']} requests, {w['rps']:.0f} tiles/s; latency p50 "
            f"{w['p50_ms']:.2f} ms, p90 {w['p90_ms']:.2f} ms, p99 {w['p99_ms']:.2f} ms; non-2xx "
            f"{w['non2xx']}, socket errors {w['socket_errors']}; tile cache hits +{reads.tile_hits:.0f}, "
            f"renders +{reads.tile_renders:.0f}"
        )
    print(
        f"  (d) cells: {c['requests']} requests of {args.points} points in {args.cells_seconds:g} s: "
        f"{c['rps']:.1f} requests/s = {c['points_per_s'] / 1e3:.0f} k points/s; per request p50 "
        f"{c['p50_ms']:.1f} ms, p99 {c['p99_ms']:.1f} ms; request {c['body_kib']:.0f} KiB, answer "
        f"{c['response_kib']:.0f} KiB; {c['known_fraction'] * 100:.0f} % of the points in known cells"
    )
    return p2, reads


def summary(args: argparse.Namespace, p1: IngestResult, p2: IngestResult | None, reads: Reads | None) -> None:
    """The figures against the issue's aims."""
    print("\n== summary (aims of the issue) ==")
    target = args.robots * args.rate
    ok_rate = target >= AIM_SCANS_PER_S and p1.sustained >= 0.98 * target and p1.loss == 0
    print(
        f"  (a) sustained ingest, one shared map: {p1.sustained:.1f} scans/s integrated of {target:.0f}/s "
        f"offered, loss {p1.loss}; aim >= {AIM_SCANS_PER_S:.0f} scans/s with zero loss: {verdict(ok_rate)}"
    )
    print(
        f"  (b) publish -> visible+durable, shared map: p50 {p1.pct(50):.1f} ms, p99 {p1.pct(99):.1f} ms; "
        f"aim p99 < {AIM_P99_MS:.0f} ms: {verdict(p1.pct(99) < AIM_P99_MS)}"
    )
    if p2 is not None:
        print(
            f"      same robots, second map, under the read load of (c) and (d): {p2.sustained:.1f} "
            f"scans/s, loss {p2.loss}, p50 {p2.pct(50):.1f} ms, p99 {p2.pct(99):.1f} ms"
        )
    ratios = [
        f"ingest {p1.sustained / AIM_SCANS_PER_S:.2f}",
        f"p99 {p1.pct(99) / AIM_P99_MS:.2f} of the limit",
    ]
    if reads is not None:
        w, c = reads.wrk, reads.cells
        if w is None:
            print("  (c) cached tiles/s: SKIPPED (no wrk)")
        else:
            print(
                f"  (c) cached PNG tiles under ingest (wrk): {w['rps']:.0f}/s, p99 {w['p99_ms']:.1f} ms; "
                f"aim >= {AIM_TILES_PER_S:.0f}/s: {verdict(w['rps'] >= AIM_TILES_PER_S and w['non2xx'] == 0)}"
            )
            ratios.append(f"tiles {w['rps'] / AIM_TILES_PER_S:.2f}")
        print(
            f"  (d) batch cell queries under ingest: {c['rps']:.1f} requests/s x {args.points} points = "
            f"{c['points_per_s'] / 1e6:.2f} M points/s (no aim)"
        )
    print("  ratio to the aims: " + ", ".join(ratios))


# == soak =============================================================================================


@dataclass
class Sample:
    t: float
    rss_mib: float
    anon_mib: float
    integrated: int
    lost: int
    dropped: int
    rejected: int
    queue: int
    ingest_p50_ms: float
    ingest_p99_ms: float
    cores: float
    machine: float

    def line(self) -> str:
        """One row under SAMPLE_HEADER."""
        return (
            f"  {self.t:7.1f} {self.rss_mib:9.1f} {self.anon_mib:7.1f} {self.integrated:11d} {self.lost:5d} "
            f"{self.dropped:7d} {self.rejected:8d} {self.queue:5d} {self.ingest_p50_ms:8.1f} / "
            f"{self.ingest_p99_ms:6.1f} {self.cores:6.2f} {self.machine * 100:6.0f} %"
        )


SAMPLE_HEADER = (
    "      t s   RSS MiB  (anon)  integrated  lost dropped rejected queue  ingest p50/p99 ms  cores  machine"
)


def soak(args: argparse.Namespace) -> int:
    """`--soak`: many robots for minutes; memory, counters and latency every `--sample-seconds`."""
    seconds = args.minutes * 60.0
    print(
        f"fleetmap service soak: {args.robots} robots x {args.rate:g} Hz = {args.robots * args.rate:.0f} "
        f"scans/s of {args.beams} beams on one map, {args.minutes:g} min, sampling every "
        f"{args.sample_seconds:g} s"
    )
    for line in machine_lines():
        print("  " + line)
    with tempfile.TemporaryDirectory(prefix="fleetmap-soak-") as tmp:
        work_dir = Path(tmp)
        trajectories = build_trajectories(TRAJECTORY_CYCLE, args.robots, args.rate, args.beams, work_dir)
        svc = start_service(work_dir, args.workers, args.service_arg)
        assert svc.proc is not None
        pid = svc.proc.pid
        samples: list[Sample] = []
        try:
            client = httpx.Client(base_url=svc.base_url, timeout=30.0)
            client.put("/maps/soak").raise_for_status()
            idle = proc_memory_mib(pid)
            print(
                f"service memory before any robot connects: RSS {idle['VmRSS']:.0f} MiB (anonymous "
                f"{idle['RssAnon']:.0f}, files {idle['RssFile']:.0f}, shared memory {idle['RssShmem']:.0f})"
            )
            specs = [
                RobotSpec("soak", f"s{k:02d}", trajectories[k], k / args.robots) for k in range(args.robots)
            ]
            keys = [(s.map_id, s.robot_id) for s in specs]

            def sampler(t0: float, total: float) -> None:
                time.sleep(max(0.0, t0 - time.time()))
                prev_text, prev_cpu, prev_t = client.get("/metrics").text, proc_cpu_seconds(pid), time.time()
                prev_busy = machine_busy()
                print(SAMPLE_HEADER)
                while time.time() < t0 + total + 0.5:
                    time.sleep(max(0.0, prev_t + args.sample_seconds - time.time()))
                    text, cpu, now = client.get("/metrics").text, proc_cpu_seconds(pid), time.time()
                    busy = machine_busy()
                    memory = proc_memory_mib(pid)
                    counters = robot_counters(text)
                    mine = [counters.get(k, {}) for k in keys]
                    bounds, delta = histogram_delta(prev_text, text, "fleetmap_ingest_latency_seconds")
                    s = Sample(
                        t=now - t0,
                        rss_mib=memory["VmRSS"],
                        anon_mib=memory["RssAnon"],
                        integrated=sum(c.get("integrated", 0) for c in mine),
                        lost=sum(c.get("lost", 0) for c in mine),
                        dropped=sum(c.get("dropped", 0) for c in mine),
                        rejected=sum(c.get("rejected", 0) for c in mine),
                        queue=int(_scalar(text, "fleetmap_queue_depth")),
                        ingest_p50_ms=histogram_quantile(bounds, delta, 0.5) * 1e3,
                        ingest_p99_ms=histogram_quantile(bounds, delta, 0.99) * 1e3,
                        cores=(cpu - prev_cpu) / (now - prev_t),
                        machine=(busy[0] - prev_busy[0]) / max(1.0, busy[1] - prev_busy[1]),
                    )
                    samples.append(s)
                    print(s.line(), flush=True)
                    prev_text, prev_cpu, prev_t, prev_busy = text, cpu, now, busy

            r = run_ingest(svc, specs, args.rate, seconds, args.poll_ms, work_dir, "soak", sampler=sampler)
            client.close()
            print_ingest(r)
        finally:
            code = svc.stop()
            print(f"service stopped (exit code {code})")

    print("\n== soak summary ==")
    post = [s for s in samples if s.t >= args.warmup_seconds]
    if len(post) >= 2:
        first, last = post[0], post[-1]
        growth = (last.rss_mib - first.rss_mib) / first.rss_mib
        peak = max(s.rss_mib for s in post)
        print(
            f"  memory: RSS {first.rss_mib:.0f} MiB at {first.t:.0f} s (after a {args.warmup_seconds:g} s "
            f"warm-up), {last.rss_mib:.0f} MiB at {last.t:.0f} s ({growth * 100:+.1f} %), peak "
            f"{peak:.0f} MiB; flat within 10 %: {verdict(abs(growth) <= 0.10)}"
        )
        print(
            f"  anonymous memory (heap): {first.anon_mib:.0f} MiB -> {last.anon_mib:.0f} MiB "
            f"({(last.anon_mib - first.anon_mib) / first.anon_mib * 100:+.1f} %)"
        )
    print(
        f"  scans: published {r.published}, integrated {r.integrated}, loss {r.loss} (lost {r.lost}, "
        f"dropped {r.dropped}, rejected {r.rejected}); zero loss: {verdict(r.loss == 0)}"
    )
    print(f"  sustained {r.sustained:.1f} scans/s of {args.robots * args.rate:.0f}/s offered")
    windows = [w for w in r.windows(args.sample_seconds) if w[1] > w[2]]
    if windows:
        p50s, p99s = [w[3] for w in windows], [w[4] for w in windows]
        print(
            f"  publish -> visible+durable per {args.sample_seconds:g} s window (checker): p50 "
            f"{min(p50s):.1f}..{max(p50s):.1f} ms, p99 {min(p99s):.1f}..{max(p99s):.1f} ms (median window "
            f"p99 {float(np.median(p99s)):.1f} ms); whole run p50 {r.pct(50):.1f} ms, p99 {r.pct(99):.1f} ms"
        )
        print(f"  p99 < {AIM_P99_MS:.0f} ms in every window: {verdict(max(p99s) < AIM_P99_MS)}")
    dump(args.dump, {"soak": r})
    return 0


# == ramp =============================================================================================


def ramp(args: argparse.Namespace) -> int:
    """`--ramp R ...`: the shared-map ingest at each per-robot rate; the highest sustained one."""
    print(f"fleetmap service ramp: {args.robots} robots, {args.beams} beams, one shared map, "
          f"{args.step_seconds:g} s per rate")  # fmt: skip
    for line in machine_lines():
        print("  " + line)
    rows = []
    with tempfile.TemporaryDirectory(prefix="fleetmap-ramp-") as tmp:
        work_dir = Path(tmp)
        svc = start_service(work_dir, args.workers, args.service_arg)
        try:
            with httpx.Client(base_url=svc.base_url, timeout=30.0) as client:
                client.put("/maps/ramp").raise_for_status()
            for rate in args.ramp:
                count = min(TRAJECTORY_CYCLE, int(args.step_seconds * rate) + 1)
                step_dir = work_dir / f"rate-{rate:g}"
                step_dir.mkdir()
                trajectories = build_trajectories(count, args.robots, rate, args.beams, step_dir)
                print(f"\n{args.robots} x {rate:g} Hz = {args.robots * rate:.0f} scans/s offered")
                prefix = f"r{rate:g}".replace(".", "_")
                specs = [
                    RobotSpec("ramp", f"{prefix}-{k:02d}", trajectories[k], k / args.robots)
                    for k in range(args.robots)
                ]
                r = run_ingest(svc, specs, rate, args.step_seconds, args.poll_ms, step_dir, f"{rate:g} Hz")
                print_ingest(r)
                rows.append(r)
        finally:
            svc.stop()
    print("\n== ramp summary ==")
    print("  offered/s  integrated/s  loss  p50 ms  p99 ms  drain s  service cores  machine busy")
    for r in rows:
        print(f"  {r.robots * r.rate:9.0f} {r.sustained:13.1f} {r.loss:5d} {r.pct(50):7.1f} {r.pct(99):7.1f} "
              f"{r.drain_seconds:8.2f} {r.service_cores:14.2f} {r.machine_busy * 100:12.0f} %")  # fmt: skip
    keeps_up = [
        r for r in rows if r.loss == 0 and r.pct(99) < 1000.0 and r.sustained >= 0.98 * r.robots * r.rate
    ]
    meets = [r for r in keeps_up if r.pct(99) < AIM_P99_MS]
    best = max((r.robots * r.rate for r in keeps_up), default=0.0)
    best_aim = max((r.robots * r.rate for r in meets), default=0.0)
    print(
        f"  highest rate kept up with (zero loss, >= 98 % integrated in the window, p99 < 1 s): {best:.0f}/s"
    )
    print(f"  highest rate with zero loss and p99 < {AIM_P99_MS:.0f} ms: {best_aim:.0f} scans/s")
    return 0


# == command line =====================================================================================


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["_robot"]:
        return robot_main(argv[1:])
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--soak", action="store_true", help="the soak run (defaults: 25 robots, 40 Hz, 5 min)")
    p.add_argument("--ramp", type=float, nargs="+", metavar="HZ", help="per-robot rates to step through")
    p.add_argument("--robots", type=int, help="robot processes (default 10; soak and ramp 25)")
    p.add_argument("--rate", type=float, default=40.0, help="scans per second per robot (default 40)")
    p.add_argument("--beams", type=int, default=1081, help="beams per scan over 270 degrees (default 1081)")
    p.add_argument("--seconds", type=float, default=30.0, help="phase 1 publishing time (default 30)")
    p.add_argument("--minutes", type=float, default=5.0, help="soak duration (default 5)")
    p.add_argument("--sample-seconds", type=float, default=10.0, help="soak sampling period (default 10)")
    p.add_argument(
        "--warmup-seconds", type=float, default=60.0, help="soak warm-up before memory is compared"
    )
    p.add_argument("--step-seconds", type=float, default=20.0, help="ramp: seconds per rate (default 20)")
    p.add_argument("--poll-ms", type=float, help="latency checker's period (default 5; soak and ramp 10)")
    p.add_argument("--workers", type=int, help="the service's --workers (default: the service's default)")
    p.add_argument("--points", type=int, default=10_000, help="points per batch cell query (default 10000)")
    p.add_argument("--cells-seconds", type=float, default=10.0)
    p.add_argument("--wrk-seconds", type=float, default=15.0)
    p.add_argument("--wrk-threads", type=int, default=2)
    p.add_argument("--wrk-connections", type=int, default=32)
    p.add_argument("--no-wrk", action="store_true", help="skip the tile load test")
    p.add_argument("--no-reads", action="store_true", help="phase 1 only (no tiles / cells phase)")
    p.add_argument(
        "--service-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="extra argument for `fleetmap serve` (repeat; e.g. --service-arg=--in-memory to see what "
        "durability costs); the figures are then not those of the default configuration",
    )
    p.add_argument("--dump", type=Path, metavar="FILE.npz", help="save per-scan publish times and latencies")
    args = p.parse_args(argv)
    long_run = args.soak or args.ramp
    args.robots = args.robots or (25 if long_run else 10)
    args.poll_ms = args.poll_ms or (10.0 if long_run else 5.0)
    if args.robots < 1 or args.rate <= 0 or args.beams < 2:
        p.error("--robots, --rate and --beams must be positive (beams >= 2)")
    if args.soak:
        return soak(args)
    if args.ramp:
        return ramp(args)
    return bench(args)


if __name__ == "__main__":
    sys.exit(main())
