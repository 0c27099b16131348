"""`fleetmap demo`: the main job. For now it maps a synthetic floor plan with simulated robots in
process and writes the exports; the service issue turns it into the live service plus robots."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from fleetmap.config import MapConfig


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="map a synthetic floor plan with simulated robots")
    p.add_argument("--out", default="out/demo", help="output directory")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--seconds", type=float, default=60.0, help="simulated time")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from fleetmap.export import write_build_outputs
    from fleetmap.grid_map import GridMap
    from fleetmap.sim import SimulatedRobot, generate_floorplan

    plan = generate_floorplan(args.seed)
    robots = [SimulatedRobot(plan, seed=args.seed * 100 + k) for k in range(args.robots)]
    gmap = GridMap(MapConfig())
    scans = 0
    started = time.perf_counter()
    dt = 0.1
    for _ in range(math.ceil(args.seconds / dt)):
        for robot in robots:
            robot.step(dt)
            gmap.integrate(robot.scan())
            scans += 1
    elapsed = time.perf_counter() - started
    written = write_build_outputs(gmap, Path(args.out))
    print(f"{len(robots)} simulated robots, {scans} scans mapped in {elapsed:.1f} s")
    print(f"map image: {next(p for p in written if p.name == 'map.png')}")
    return 0
