"""A map past 4 GiB, downloaded from and uploaded to the real service: what the tests' machines cannot
hold (tests/test_snapshot_downloads.py checks the same paths with small maps and small limits).

    PYTHONPATH=service:clients/python:tests .venv/bin/python scripts/big_snapshot_round_trip.py \\
        [--tiles 3400] [--out /tmp/big-snapshot]

Opt-in, never part of `pytest`: it needs about three times the map's size in memory (the map made
here, the service's, and the download's copy of its tiles) and as much disk in `--out` (the
service's TMPDIR). It makes a map of `--tiles` tiles of 256 x 256 cells with every layer (20 bytes
a cell: 3,400 tiles are 4.46 GB of arrays, past the 4 GiB an upload once could hold), a twentieth
of each tile observed, and then, against a service started with `--in-memory --max-memory none`:

1. uploads its snapshot (`PUT /maps/big/snapshot`), timed;
2. downloads it (`GET /maps/big/snapshot`) to a file, timed, with the service's peak resident memory
   before and after (`VmHWM`);
3. reads the downloaded file back and compares every array with the map made here, bit for bit
   (by digests: the script does not keep its map meanwhile);
4. deletes the map and uploads the downloaded file again under another id (a backup's restore).

It prints each step's figures and exits 1 if a step fails or a cell differs.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
from service_process import ServiceProcess  # noqa: E402

from fleetmap.config import MapConfig  # noqa: E402
from fleetmap.grid_map import GridMap  # noqa: E402
from fleetmap.storage_format import map_from_snapshot_file, write_snapshot_file  # noqa: E402

CHUNK = 1 << 20


def big_map(tiles: int) -> GridMap:
    """`tiles` tiles of every layer in a row, each with its first 13 rows of cells observed (values the
    engine could store, different from tile to tile), the rest unknown: a map that compresses as
    mapped ones do, not as random data (which would take minutes to compress)."""
    gmap = GridMap(MapConfig(resolution=0.05, max_tiles=tiles))
    gmap.store.create([(i, 0) for i in range(tiles)])
    rng = np.random.default_rng(1)
    _, _, l_min, l_max = gmap.config.occupancy.resolved()
    rows = 13
    shift = (np.arange(tiles) % 97).reshape(-1, 1, 1)
    for name, pool in gmap.store.pools.items():
        observed = pool[:tiles, :rows, :]
        if name == "log_odds":
            observed[...] = rng.uniform(l_min, l_max, (rows, 256)) * (1 - shift / 200)
        elif name == "tsdf":
            observed[...] = rng.uniform(-1, 1, (rows, 256)) * (1 - shift / 200)
        else:  # hits, misses, tsdf_weight: any value >= 0
            observed[...] = rng.integers(1, 1 << 10, (rows, 256)) + shift
    return gmap


def digests(gmap: GridMap) -> dict[str, str]:
    """A BLAKE2 digest of each stored array's bits, tile by tile in slot order."""
    out = {}
    for name, pool in gmap.store.pools.items():
        h = hashlib.blake2b()
        for slot in range(len(gmap.store.keys)):
            h.update(pool[slot].tobytes())
        out[name] = h.hexdigest()
    return out


def vm_hwm(pid: int) -> int:
    """Peak resident memory of process `pid`, bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiles", type=int, default=3400)
    p.add_argument("--out", type=Path, default=Path("/tmp/big-snapshot"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    tmpdir = args.out / "tmp"
    tmpdir.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    gmap = big_map(args.tiles)
    arrays_bytes = gmap.store.bytes_for(args.tiles) - 8 * args.tiles
    upload = args.out / "upload.fleetmap.zip"
    with open(upload, "wb") as fp:
        write_snapshot_file("big", gmap, fp)
    made = digests(gmap)
    keys = list(gmap.store.keys)
    del gmap  # the script's copy, so that the machine holds the service's and its download's
    print(
        f"map: {args.tiles} tiles, {arrays_bytes / 1e9:.2f} GB of arrays (4 GiB = {4 * 2**30 / 1e9:.2f} GB); "
        f"snapshot {upload.stat().st_size / 1e6:.0f} MB, made in {time.perf_counter() - t0:.1f} s"
    )
    ok = True
    serve = ["--in-memory", "--max-memory", "none", "--http-body-timeout", "600"]
    with (
        ServiceProcess(args.out, serve, env={"TMPDIR": str(tmpdir)}) as svc,
        httpx.Client(timeout=1200) as http,
    ):
        pid = svc.proc.pid  # type: ignore[union-attr]
        t0 = time.perf_counter()
        with open(upload, "rb") as fp:
            put = http.put(f"{svc.base_url}/maps/big/snapshot", content=fp)
        print(f"upload: {put.status_code} in {time.perf_counter() - t0:.1f} s")
        ok &= put.status_code == 201
        before = vm_hwm(pid)
        download = args.out / "download.fleetmap.zip"
        t0 = time.perf_counter()
        with http.stream("GET", f"{svc.base_url}/maps/big/snapshot") as got, open(download, "wb") as fp:
            for chunk in got.iter_bytes(CHUNK):
                fp.write(chunk)
            length = int(got.headers["content-length"])
        took = time.perf_counter() - t0
        after = vm_hwm(pid)
        size = download.stat().st_size
        print(
            f"download: {got.status_code}, {size / 1e6:.0f} MB (Content-Length {length}) in {took:.1f} s; "
            f"service's peak resident memory {before / 1e9:.2f} GB before, {after / 1e9:.2f} GB after "
            f"(+{(after - before) / 1e9:.2f} GB for {arrays_bytes / 1e9:.2f} GB of tiles)"
        )
        ok &= got.status_code == 200 and size == length
        t0 = time.perf_counter()
        with open(download, "rb") as fp:
            back = map_from_snapshot_file(fp, max_bytes=2 * arrays_bytes)
        same = back.store.keys == keys and digests(back) == made
        print(
            f"read back and compared in {time.perf_counter() - t0:.1f} s: "
            f"{'the same, bit for bit' if same else 'DIFFERENT'}"
        )
        ok &= same
        del back
        assert http.delete(f"{svc.base_url}/maps/big").status_code == 204  # room for the next
        t0 = time.perf_counter()
        with open(download, "rb") as fp:
            put = http.put(f"{svc.base_url}/maps/again/snapshot", content=fp)
        print(f"the download uploaded again: {put.status_code} in {time.perf_counter() - t0:.1f} s")
        ok &= put.status_code == 201
    for path in (upload, download):
        path.unlink()
    print("ok" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
