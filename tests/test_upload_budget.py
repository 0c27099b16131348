"""Uploads (`PUT /maps/{id}/snapshot`, `PUT /maps/{id}/import`) reserve the memory budget
(`--max-memory`) for the map they build, on the real service over real HTTP: uploads read at once
that each fit but not together are installed as far as the budget goes and the others refused 507,
the budget's `used` never passing its limit; an upload refused, failed or cut off gives its room
back; an upload replacing a map counts the old map's bytes as free, once.

Before the reservation each upload checked the free bytes, built its map uncounted and had it
counted at install even past the limit: every upload read at once saw the same free bytes. The
uploads here are sent together, each body but its last byte first and then every last byte back to
back, so that their maps are read at the same time (a map of 24 tiles takes a few hundred
milliseconds to read, its reservation milliseconds)."""

from __future__ import annotations

import contextlib
import io
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess
from test_api_support import random_tiles_map, snapshot_parts
from test_upload_spool import read_answer, start_upload

from fleetmap.export import pgm_bytes
from fleetmap.storage_format import snapshot_file

#: Tiles of each uploaded map (every layer, 256 x 256 cells); the map's store
#: holds exactly its tiles (a store's first growth makes room for just those).
TILES = 24


@pytest.fixture(scope="module")
def snapshots() -> list[bytes]:
    """Four snapshots of maps of TILES tiles of random values, each telling itself apart by the
    log-odds of its first cell (k / 10, for snapshot k)."""
    gmap = random_tiles_map(TILES)
    found = []
    for k in range(4):
        gmap.store.pools["log_odds"][0, 0, 0] = k / 10
        found.append(snapshot_file(f"m{k}", gmap))
    return found


@pytest.fixture(scope="module")
def map_bytes() -> int:
    """The bytes a map of TILES tiles of every layer holds (what the budget counts for it)."""
    return random_tiles_map(TILES).memory_bytes()


def nav2_import() -> bytes:
    """A nav2 map (map.yaml and a PGM, zipped) whose known cells cover TILES tiles of 256 cells."""
    image = pgm_bytes(np.zeros((256, 256 * TILES), dtype=np.uint8))  # every cell occupied: known
    yaml_text = "image: map.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
    yaml_text += "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("map.yaml", yaml_text)
        zf.writestr("map.pgm", image)
    return buf.getvalue()


def memory(url: str) -> tuple[float, float]:
    """The service's `fleetmap_memory_used_bytes` and `fleetmap_memory_limit_bytes` (GET /metrics)."""
    text = httpx.get(f"{url}/metrics", timeout=10).text
    samples = dict(line.rsplit(" ", 1) for line in text.splitlines() if line.startswith("fleetmap_memory_"))
    return float(samples["fleetmap_memory_used_bytes"]), float(samples["fleetmap_memory_limit_bytes"])


@contextlib.contextmanager
def watching_memory(url: str) -> Iterator[list[float]]:
    """The budget's `used` sampled from /metrics every few milliseconds until the block ends."""
    seen: list[float] = []
    stop = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            seen.append(memory(url)[0])
            stop.wait(0.005)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    try:
        yield seen
    finally:
        stop.set()
        thread.join(10)
        seen.append(memory(url)[0])


def upload_together(svc: ServiceProcess, uploads: list[tuple[str, bytes]]) -> list[tuple[int, str]]:
    """PUT each `(path, body)`, every body but its last byte first, then every last byte back to
    back, so that the service reads them all at once; their answers (status, body), in order."""
    socks = [start_upload(svc, path, len(body)) for path, body in uploads]
    try:
        for sock, (_, body) in zip(socks, uploads, strict=True):
            sock.sendall(body[:-1])
        for sock, (_, body) in zip(socks, uploads, strict=True):
            sock.sendall(body[-1:])
        return [read_answer(sock) for sock in socks]
    finally:
        for sock in socks:
            sock.close()


def first_log_odds(url: str, map_id: str) -> float:
    """The log-odds of the first cell of map `map_id`'s snapshot: which of `snapshots` it holds."""
    _, arrays = snapshot_parts(httpx.get(f"{url}/maps/{map_id}/snapshot", timeout=30).content)
    return float(arrays["log_odds"][0, 0, 0])


def service(tmp_path: Path, limit: int) -> ServiceProcess:
    """A service holding its maps in memory, with a memory budget of `limit` bytes."""
    return ServiceProcess(tmp_path, ["--in-memory", "--max-memory", str(limit)])


def test_uploads_read_at_once_are_installed_only_as_far_as_the_budget_goes(
    tmp_path: Path, snapshots: list[bytes], map_bytes: int
) -> None:
    """Three uploads of a map each (two snapshots and a nav2 import: both routes reserve alike) into
    a budget of two and a half: exactly two are installed, the third is refused 507 with nothing
    installed, and the budget's used bytes never pass its limit. Before the reservation all three
    were installed, 3 maps counted in a budget of 2.5."""
    limit = map_bytes * 5 // 2
    with service(tmp_path, limit) as svc:
        url = svc.base_url
        with watching_memory(url) as seen:
            answers = upload_together(
                svc,
                [("/maps/m0/snapshot", snapshots[0]), ("/maps/m1/snapshot", snapshots[1]),
                 ("/maps/m2/import", nav2_import())],
            )  # fmt: skip
        assert sorted(status for status, _ in answers) == [201, 201, 507], answers
        for k, (status, body) in enumerate(answers):
            found = httpx.get(f"{url}/maps/m{k}", timeout=10).status_code
            assert found == (200 if status == 201 else 404), (k, status, body)
            if status == 507:
                assert "memory budget" in body and "--max-memory" in body, body
        assert memory(url) == (2 * map_bytes, limit)
        assert max(seen) <= limit, (max(seen), limit)
        assert "Traceback" not in svc.logs(), svc.logs()


def test_an_upload_replacing_a_map_counts_its_bytes_as_free_once(
    tmp_path: Path, snapshots: list[bytes], map_bytes: int
) -> None:
    """In a budget of one map and a half, a map is replaced by another of its size (the old map's
    bytes count as free for the upload that replaces it), but not joined by one. Two uploads
    replacing it at once cannot both count its bytes: one is installed and the other refused 507,
    where before both were installed (each counted the old map's bytes as its own)."""
    limit = map_bytes * 3 // 2
    with service(tmp_path, limit) as svc:
        url = svc.base_url
        put = {"headers": {"content-type": "application/zip"}, "timeout": 60}
        r = httpx.put(f"{url}/maps/x/snapshot", content=snapshots[0], **put)  # type: ignore[arg-type]
        assert r.status_code == 201, r.text
        r = httpx.put(f"{url}/maps/x/snapshot", content=snapshots[1], **put)  # type: ignore[arg-type]
        assert r.status_code == 200, r.text  # half a map free, and the old map's bytes
        assert first_log_odds(url, "x") == pytest.approx(0.1)
        r = httpx.put(f"{url}/maps/y/snapshot", content=snapshots[2], **put)  # type: ignore[arg-type]
        assert r.status_code == 507 and "memory budget" in r.json()["detail"], r.text
        assert memory(url) == (map_bytes, limit)
        with watching_memory(url) as seen:
            answers = upload_together(
                svc, [("/maps/x/snapshot", snapshots[2]), ("/maps/x/snapshot", snapshots[3])]
            )
        assert sorted(status for status, _ in answers) == [200, 507], answers
        winner = 2 if answers[0][0] == 200 else 3
        assert first_log_odds(url, "x") == pytest.approx(winner / 10)
        assert memory(url) == (map_bytes, limit)
        # The old map and the new one are both held until the new one is installed: the budget
        # counts both, past its limit by at most the old map's bytes (the loan), never a third map.
        assert max(seen) <= limit + map_bytes, (max(seen), limit)
        assert "Traceback" not in svc.logs(), svc.logs()


def test_an_upload_refused_or_cut_off_gives_its_room_back(
    tmp_path: Path, snapshots: list[bytes], map_bytes: int
) -> None:
    """An upload refused after its map's tiles were reserved and allocated (a cell value the engine
    cannot store, found as the tiles are read), one cut off mid-body and one refused 507 leave the
    budget's used bytes where they were, and an upload that fits only in the whole budget is then
    installed. (A reservation left behind by the first took a map of the budget of one and a half.)"""
    limit = map_bytes * 3 // 2
    bad = random_tiles_map(TILES)
    bad.store.pools["tsdf"][TILES - 1, 255, 255] = 5.0  # the last cell read: outside [-1, 1]
    with service(tmp_path, limit) as svc:
        url = svc.base_url
        put = {"headers": {"content-type": "application/zip"}, "timeout": 60}
        r = httpx.put(f"{url}/maps/x/snapshot", content=snapshot_file("x", bad), **put)  # type: ignore[arg-type]
        assert r.status_code == 422 and "tsdf must be within [-1, 1]" in r.json()["detail"], r.text
        assert memory(url) == (0, limit)
        with start_upload(svc, "/maps/x/snapshot", len(snapshots[0])) as sock:
            sock.sendall(snapshots[0][: len(snapshots[0]) // 2])
        assert memory(url) == (0, limit)
        r = httpx.put(f"{url}/maps/x/snapshot", content=snapshots[0], **put)  # type: ignore[arg-type]
        assert r.status_code == 201, r.text
        r = httpx.put(f"{url}/maps/y/snapshot", content=snapshots[1], **put)  # type: ignore[arg-type]
        assert r.status_code == 507, r.text
        assert memory(url) == (map_bytes, limit)
        assert httpx.delete(f"{url}/maps/x", timeout=10).status_code == 204
        assert memory(url) == (0, limit)
        r = httpx.put(f"{url}/maps/y/snapshot", content=snapshots[1], **put)  # type: ignore[arg-type]
        assert r.status_code == 201, r.text
        assert memory(url) == (map_bytes, limit)
        assert "Traceback" not in svc.logs(), svc.logs()
