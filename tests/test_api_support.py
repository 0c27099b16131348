"""Helpers for the REST API tests: the real app in a real uvicorn server on 127.0.0.1, in a thread.

The API tests talk HTTP over a socket to a server started here (port 0: the kernel picks a free port,
so test files can run in parallel), with a registry whose integration workers run. This module holds
no tests itself.
"""

from __future__ import annotations

import io
import json
import math
import socket
import struct
import threading
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import uvicorn

from fleetmap.api import ApiSettings, create_app
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.metrics import IntegrationMetrics
from fleetmap.registry import MapRegistry
from fleetmap.scan import Pose2D, Scan


@dataclass
class RunningApi:
    registry: MapRegistry
    metrics: IntegrationMetrics
    base_url: str
    client: httpx.Client


@contextmanager
def running_api(
    settings: ApiSettings | None = None, root_path: str = "", **registry_args: object
) -> Iterator[RunningApi]:
    """Start registry workers and a uvicorn server for `create_app(registry, settings=settings)`
    (served under `root_path`, as `fleetmap serve --root-path` serves it); stop both on exit."""
    metrics = IntegrationMetrics()
    registry = MapRegistry(on_integrated=metrics.on_integrated, **registry_args)  # type: ignore[arg-type]
    registry.start()
    app = create_app(registry, settings=settings)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(
        app, log_level="warning", timeout_graceful_shutdown=1, lifespan="off", root_path=root_path
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.01)
    base_url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base_url, timeout=30) as client:
            yield RunningApi(registry, metrics, base_url, client)
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()
        registry.close()


def fan_scan(
    x: float,
    y: float,
    theta: float,
    ranges: list[float | None],
    fov: float = math.pi,
    range_max: float = 10.0,
) -> Scan:
    """A scan of len(ranges) beams spread evenly over `fov`, centred on the heading."""
    n = len(ranges)
    inc = fov / (n - 1) if n > 1 else 0.0
    return Scan.from_fan(Pose2D(x, y, theta), -fov / 2, inc, ranges, 0.0, range_max)


def room_scans(count: int, seed: int = 0, beams: int = 181) -> list[Scan]:
    """Scans from random poses inside a 6 m x 4 m box room (walls at x = -3, 3 and y = -2, 2), exact
    ranges: a map with occupied walls, free inside and unknown outside."""
    rng = np.random.default_rng(seed)
    scans = []
    for _ in range(count):
        x, y = rng.uniform(-2.0, 2.0), rng.uniform(-1.2, 1.2)
        theta = rng.uniform(-math.pi, math.pi)
        angles = -math.pi + 2 * math.pi * np.arange(beams) / beams
        world = theta + angles
        c, s = np.cos(world), np.sin(world)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (3 - x) / c, np.where(c < 0, (-3 - x) / c, np.inf))
            ty = np.where(s > 0, (2 - y) / s, np.where(s < 0, (-2 - y) / s, np.inf))
        ranges = np.minimum(tx, ty)
        scans.append(Scan.from_angles(Pose2D(x, y, theta), angles, ranges, 0.0, 10.0))
    return scans


# -- snapshot files, whole or altered ------------------------------------------------------------------


def small_snapshot_map() -> GridMap:
    """A map of 16-cell tiles with every layer and a few tiles observed: its snapshot file is small."""
    gmap = GridMap(MapConfig(resolution=0.05, tile_size=16))
    gmap.integrate(fan_scan(0.0, 0.0, 0.0, [1.0] * 61))
    return gmap


def snapshot_parts(body: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The `map.json` and the arrays of `tiles.npz` of a snapshot file."""
    with zipfile.ZipFile(io.BytesIO(body)) as zf:
        meta = json.loads(zf.read("map.json"))
        with np.load(io.BytesIO(zf.read("tiles.npz"))) as npz:
            return meta, {name: npz[name] for name in npz.files}


def snapshot_body(
    meta: Any, arrays: dict[str, np.ndarray] | None = None, npz: bytes | None = None, deflate: bool = False
) -> bytes:
    """A snapshot file of `map.json` = `meta` (JSON-encoded unless bytes or str) and `tiles.npz` =
    `npz`, or those `arrays` compressed as `snapshot_file` does; the zip deflated if asked."""
    if npz is None:
        buf = io.BytesIO()
        np.savez_compressed(buf, **(arrays or {}))
        npz = buf.getvalue()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED) as zf:
        zf.writestr("map.json", meta if isinstance(meta, (bytes, str)) else json.dumps(meta))
        zf.writestr("tiles.npz", npz)
    return out.getvalue()


def random_tiles_map(n: int, tile_size: int = 256) -> GridMap:
    """A map of `n` tiles of every layer holding random values the engine could store: its snapshot
    barely compresses, so the file is about as big as the map (tests of big uploads)."""
    gmap = GridMap(MapConfig(resolution=0.05, tile_size=tile_size))
    gmap.store.create([(i, 0) for i in range(n)], fill=True)
    rng = np.random.default_rng(7)
    _, _, l_min, l_max = gmap.config.occupancy.resolved()
    for name, pool in gmap.store.pools.items():
        values = pool[:n]
        if name == "log_odds":
            values[...] = rng.uniform(l_min, l_max, values.shape)
        elif name == "tsdf":
            values[...] = rng.uniform(-1, 1, values.shape)
        else:  # hits, misses, tsdf_weight: any value >= 0
            values[...] = rng.integers(0, 1 << 20, values.shape)
    return gmap


def declare_size(archive: bytes, name: str, size: int) -> bytes:
    """`archive` (a zip) with member `name`'s uncompressed size in the central directory, which is
    what `zipfile.ZipInfo.file_size` reads, set to `size` (< 4 GiB): a lying header."""
    at = 0
    while True:
        at = archive.index(b"PK\x01\x02", at)  # a central directory entry
        (length,) = struct.unpack_from("<H", archive, at + 28)
        if archive[at + 46 : at + 46 + length] == name.encode():
            return archive[: at + 24] + struct.pack("<I", size) + archive[at + 28 :]
        at += 4


def padded_zip(archive: bytes, entries: int) -> bytes:
    """`archive` (a zip) with `entries` more, empty, members: a central directory of about 52 bytes
    each, which zipfile reads whole and makes an object of each when the zip is opened."""
    out = io.BytesIO(archive)
    with zipfile.ZipFile(out, "a") as zf:
        for k in range(entries):
            zf.writestr(f"x{k:05d}", b"")
    return out.getvalue()


def hostile_zip(archive: bytes, name: str, how: str) -> bytes:
    """`archive` (a zip, as zipfile writes it: no comment, no zip64) with member `name` made hostile
    in a way zipfile only notices when the member is opened, if at all:

    - "utf-8 name": its local header's name flagged UTF-8 (bit 11) and not UTF-8 (its last byte 0xff);
    - "before the start": the end record's directory offset raised by 64, so that zipfile, taking
      the 64 bytes for a prefix's, shifts every member's offset 64 bytes before where it is, and
      the first member's before the file's start;
    - "zip64 offset": its directory entry's offset 0xffffffff with a zip64 extra field that gives
      2**64 - 1, more than a seek takes."""
    eocd = archive.rindex(b"PK\x05\x06")
    cd_size, cd_offset = struct.unpack_from("<II", archive, eocd + 12)
    if how == "before the start":
        return archive[: eocd + 16] + struct.pack("<I", cd_offset + 64) + archive[eocd + 20 :]
    entries, at = [], cd_offset
    while at < cd_offset + cd_size:  # each central directory entry, to find `name`'s
        name_length, extra_length, comment_length = struct.unpack_from("<HHH", archive, at + 28)
        end = at + 46 + name_length + extra_length + comment_length
        entries.append((at, archive[at + 46 : at + 46 + name_length], archive[at:end]))
        at = end
    ((at, _, entry),) = [e for e in entries if e[1] == name.encode()]
    if how == "utf-8 name":
        (local,) = struct.unpack_from("<I", entry, 42)
        flags, name_length = struct.unpack_from("<H", archive, local + 6)[0], len(name)
        head = archive[:local] + archive[local : local + 6] + struct.pack("<H", flags | 0x800)
        head += archive[local + 8 : local + 30 + name_length - 1] + b"\xff"
        return head + archive[local + 30 + name_length :]
    assert how == "zip64 offset", how
    name_length, extra_length = struct.unpack_from("<HH", entry, 28)
    extra = struct.pack("<HHQ", 1, 8, 2**64 - 1)
    hostile = (
        entry[:30] + struct.pack("<H", extra_length + len(extra)) + entry[32:42] + b"\xff" * 4
        + entry[46 : 46 + name_length + extra_length] + extra + entry[46 + name_length + extra_length :]
    )  # fmt: skip
    directory = b"".join(hostile if e[0] == at else e[2] for e in entries)
    tail = archive[eocd : eocd + 12] + struct.pack("<II", len(directory), cd_offset) + archive[eocd + 20 :]
    return archive[:cd_offset] + directory + tail
