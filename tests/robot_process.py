"""A robot as its own process: publishes scans to the service through a real Zenoh client session.

    python tests/robot_process.py --connect tcp/127.0.0.1:7447 --map M --robot R \\
        (--sim SEED [--plan-seed P] [--beams N] | --dataset PATH [--start I] [--stop J]) \\
        [--encoding binary|json] [--count N] [--rate HZ] [--seq-start S] [--skip SEQ ...] \\
        [--duplicate SEQ ...] [--linger SECONDS]

The scans are exactly those `scans_for(...)` returns for the same arguments, so a test can build the
engine's map of the same scans in-process. Scan k (k = 0..count-1) gets seq `seq_start + k`; seqs in
`--skip` are not published (the service counts them as lost) and seqs in `--duplicate` are published
twice (the service ignores the second copy).

The robot declares its liveliness token `fleetmap/<map>/<robot>/alive`, waits (up to 20 s) until the
service's subscriber matches its publisher, publishes with `CongestionControl.BLOCK` (nothing is
dropped under load), prints `published N` and then lingers: `--linger S` seconds (default 0.5, so
the session flushes before it closes), or until stdin closes or SIGTERM arrives when S < 0. Either
of those also stops a robot that is still publishing (a test that ends before its robots do).
Exit codes: 0 done, 3 no matching subscriber in time, 2 bad arguments.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from fleetmap import codec
from fleetmap.scan import Scan
from fleetmap.wire import ALIVE_KEY, BINARY_ENCODING, JSON_ENCODING, SCAN_KEY


def scans_for(
    *,
    sim: int | None = None,
    plan_seed: int = 0,
    beams: int = 361,
    dataset: str | Path | None = None,
    start: int = 0,
    count: int = 10,
) -> list[Scan]:
    """The scans a robot process publishes for these arguments (deterministic).

    `sim`: a `SimulatedRobot(generate_floorplan(plan_seed, 20 x 15 m), seed=sim)` ticked `count`
    times (noise-free, `beams` beams over 270 degrees, 12 m range). `dataset`: scans
    `[start, start + count)` of the recorded log."""
    if (sim is None) == (dataset is None):
        raise ValueError("give exactly one of sim and dataset")
    if dataset is not None:
        from fleetmap.datasets import load_dataset

        ds = load_dataset(dataset)
        return [ds[i] for i in range(start, min(start + count, len(ds)))]
    from fleetmap.sim import SimulatedRobot, generate_floorplan

    plan = generate_floorplan(plan_seed, width_m=20.0, height_m=15.0)
    robot = SimulatedRobot(plan, sim, num_beams=beams, range_max=12.0, speed=1.0, scan_rate=5.0)
    return [robot.tick() for _ in range(count)]


def encode(scan: Scan, seq: int, encoding: str) -> bytes:
    """The payload for one scan (stamp = seq / 10 s)."""
    if encoding == "json":
        return codec.encode_json(scan, seq, stamp=seq / 10.0)
    return codec.encode_binary(scan, seq, stamp=seq / 10.0)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", required=True, nargs="+")
    p.add_argument("--map", required=True)
    p.add_argument("--robot", required=True)
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--sim", type=int, help="simulated robot seed")
    source.add_argument("--dataset", help="recorded log (CARMEN / .mat)")
    p.add_argument("--plan-seed", type=int, default=0)
    p.add_argument("--beams", type=int, default=361)
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--count", type=int, default=10)
    p.add_argument("--encoding", choices=("binary", "json"), default="binary")
    p.add_argument("--rate", type=float, default=0.0, help="scans per second; 0 = as fast as possible")
    p.add_argument("--seq-start", type=int, default=0)
    p.add_argument("--skip", type=int, nargs="*", default=[])
    p.add_argument("--duplicate", type=int, nargs="*", default=[])
    p.add_argument("--linger", type=float, default=0.5)
    args = p.parse_args(argv)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.linger < 0:  # online until the parent closes our stdin (or sends SIGTERM)
        threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    scans = scans_for(
        sim=args.sim, plan_seed=args.plan_seed, beams=args.beams, dataset=args.dataset,
        start=args.start, count=args.count,
    )  # fmt: skip

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", str(list(args.connect)).replace("'", '"'))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    try:
        token = session.liveliness().declare_token(ALIVE_KEY.format(map_id=args.map, robot_id=args.robot))
        encoding = zenoh.Encoding(JSON_ENCODING if args.encoding == "json" else BINARY_ENCODING)
        pub = session.declare_publisher(
            SCAN_KEY.format(map_id=args.map, robot_id=args.robot),
            encoding=encoding,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        deadline = time.monotonic() + 20.0
        while not pub.matching_status.matching:
            if time.monotonic() > deadline:
                print("no matching subscriber", file=sys.stderr, flush=True)
                return 3
            time.sleep(0.02)
        skip, duplicate = set(args.skip), set(args.duplicate)
        published = 0
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        next_at = time.monotonic()
        for k, scan in enumerate(scans):
            if stop.is_set():
                break
            seq = args.seq_start + k
            if seq in skip:
                continue
            payload = encode(scan, seq, args.encoding)
            for _ in range(2 if seq in duplicate else 1):
                pub.put(payload)
                published += 1
            if period:
                next_at += period
                time.sleep(max(0.0, next_at - time.monotonic()))
        print(f"published {published}", flush=True)
        stop.wait(args.linger if args.linger >= 0 else None)
        pub.undeclare()
        token.undeclare()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
