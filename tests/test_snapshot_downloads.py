"""Big maps' snapshots, both ways, on the real service process.

Downloads (`GET /maps/{id}/snapshot`) are written to a spool in the temporary directory and sent
from there (`routes_snapshot.get_snapshot`), not built in memory: the compressed map was held there
three times over, besides the copy of its tiles. At most `ApiSettings.max_downloads` are in progress.

Uploads (`PUT /maps/{id}/snapshot`) may hold as many bytes of tiles as the memory budget for all
maps' tiles (`--max-memory`), not a fixed 4 GiB: the service downloaded, stored and restarted with
maps it could not take back. (A map past 4 GiB round trips in `scripts/big_snapshot_round_trip.py`:
too big for the tests' machines.)

As in test_upload_spool.py, a spool's file is unlinked as it is made, so the service's open
descriptors into its TMPDIR show it, and each test first sees one there, so that "none left" can fail.
"""

from __future__ import annotations

import io
import resource
import socket
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess, wait_for
from test_api_support import random_tiles_map, snapshot_body
from test_http_exhaustion import metric
from test_upload_spool import same_map, send_chunked, spool_files

from fleetmap.memory_budget import available_memory
from fleetmap.storage_format import snapshot_file
from fleetmap.upload_spool import SPOOL_MEMORY_BYTES

MEDIA = "application/zip"
#: What the service answers at once besides a stalled download (4, `ApiSettings.max_downloads`).
MAX_DOWNLOADS = 4


@pytest.fixture(scope="module")
def big_snapshot() -> bytes:
    """The snapshot of 24 tiles of every layer holding random values (they barely compress): a
    download past what a spool keeps in memory, so that it goes to a file of the temporary directory,
    and past what the sockets between the test and the service buffer, so that a client that stops
    reading holds the service at the download."""
    data = snapshot_file("big", random_tiles_map(24))
    assert len(data) > SPOOL_MEMORY_BYTES + (8 << 20)
    return data


@pytest.fixture(scope="module")
def service(
    tmp_path_factory: pytest.TempPathFactory, big_snapshot: bytes
) -> Iterator[tuple[ServiceProcess, Path]]:
    """A service whose TMPDIR is the test's, holding the map `big` (`big_snapshot`)."""
    tmpdir = tmp_path_factory.mktemp("spool")
    with ServiceProcess(tmp_path_factory.mktemp("logs"), ["--in-memory"], env={"TMPDIR": str(tmpdir)}) as svc:
        put = httpx.put(f"{svc.base_url}/maps/big/snapshot", content=big_snapshot, timeout=60)
        assert put.status_code == 201, put.text
        yield svc, tmpdir


def start_download(svc: ServiceProcess, path: str = "/maps/big/snapshot") -> tuple[socket.socket, bytes]:
    """A raw connection that asked for `path` and read the answer's head, and no more for now: the
    service then stalls sending the body. Returns the socket and what it read (the head, maybe more)."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=30)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)  # buffer little of the body
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n".encode())
    got = b""
    while b"\r\n\r\n" not in got:
        chunk = sock.recv(4096)
        assert chunk, got
        got += chunk
    return sock, got


def finish_download(sock: socket.socket, got: bytes) -> tuple[dict[str, str], bytes]:
    """The rest of a `start_download`'s answer: its headers (lower-case names) and its body."""
    with sock:
        while chunk := sock.recv(1 << 20):
            got += chunk
    head, _, body = got.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    assert lines[0].split()[1] == "200", lines[0]
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return headers, body


def test_a_big_download_is_sent_from_a_spool_file_and_round_trips(
    service: tuple[ServiceProcess, Path], big_snapshot: bytes
) -> None:
    """The download is written to a file of the temporary directory (seen held open while the client
    has not read it) and sent from there whole: its Content-Length is its size, it is not
    compressed again, and it holds the map uploaded, bit for bit. Nothing is left after it."""
    svc, tmpdir = service
    pid = svc.proc.pid  # type: ignore[union-attr]
    sock, got = start_download(svc)
    wait_for(lambda: spool_files(pid, tmpdir), timeout=10, what="the download's spool file")
    headers, body = finish_download(sock, got)
    assert int(headers["content-length"]) == len(body)
    assert "content-encoding" not in headers and headers["content-type"] == MEDIA
    assert headers["content-disposition"] == 'attachment; filename="big.fleetmap.zip"'
    same_map(big_snapshot, body)
    with zipfile.ZipFile(io.BytesIO(body)) as zf:  # tiles.npz stored, so that an upload reads it in place
        assert zf.getinfo("tiles.npz").compress_type == zipfile.ZIP_STORED
    wait_for(lambda: not spool_files(pid, tmpdir), timeout=5, what="no spool")
    assert list(tmpdir.iterdir()) == []
    # Taken back by the service as it is (a round trip through the API).
    put = httpx.put(f"{svc.base_url}/maps/again/snapshot", content=body, timeout=60)
    assert put.status_code == 201, put.text
    same_map(big_snapshot, httpx.get(f"{svc.base_url}/maps/again/snapshot", timeout=60).content)
    assert httpx.delete(f"{svc.base_url}/maps/again").status_code == 204


def test_downloads_in_progress_are_limited_and_a_client_gone_gives_its_slot_back(
    service: tuple[ServiceProcess, Path], big_snapshot: bytes
) -> None:
    """At most 4 downloads at once (each holds a copy of its map's tiles while its file is written,
    then the file): the next is answered 503 with `Retry-After`, counted. A client that goes away
    mid-download gives its slot and its spool back; later downloads are served as before."""
    svc, tmpdir = service
    pid = svc.proc.pid  # type: ignore[union-attr]
    stalled = [start_download(svc) for _ in range(MAX_DOWNLOADS)]
    try:
        wait_for(lambda: len(spool_files(pid, tmpdir)) == MAX_DOWNLOADS, timeout=20, what="4 spools")
        assert metric(svc, "fleetmap_downloads") == MAX_DOWNLOADS
        refused = httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=30)
        assert refused.status_code == 503, refused.text
        assert refused.headers["retry-after"] == "5"
        assert "limit of 4 snapshot downloads" in refused.json()["detail"]
        assert metric(svc, "fleetmap_downloads_refused_total") >= 1
        # Two clients go away mid-download.
        for sock, _ in stalled[:2]:
            sock.close()
        wait_for(
            lambda: metric(svc, "fleetmap_downloads") == MAX_DOWNLOADS - 2, timeout=10, what="2 slots back"
        )
        wait_for(
            lambda: len(spool_files(pid, tmpdir)) == MAX_DOWNLOADS - 2, timeout=10, what="2 spools closed"
        )
        got = httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=60)
        assert got.status_code == 200
        same_map(big_snapshot, got.content)
        for sock, head in stalled[2:]:
            same_map(big_snapshot, finish_download(sock, head)[1])
    finally:
        for sock, _ in stalled:
            sock.close()
    wait_for(lambda: metric(svc, "fleetmap_downloads") == 0, timeout=10, what="every slot back")
    wait_for(lambda: not spool_files(pid, tmpdir), timeout=5, what="no spool")
    assert "Traceback" not in svc.logs(), svc.logs()


def test_a_head_on_a_snapshot_writes_nothing_and_takes_no_slot(
    service: tuple[ServiceProcess, Path], big_snapshot: bytes
) -> None:
    """A HEAD answers the download's headers without writing the file (it wrote the whole map and
    held a download slot, to send nothing): with every slot held it is still 200 at once, with no
    `Content-Length` (unknown until written) and no spool of its own; a map that is not there is a
    404, as the GET's."""
    svc, tmpdir = service
    pid = svc.proc.pid  # type: ignore[union-attr]
    refused = metric(svc, "fleetmap_downloads_refused_total")
    stalled = [start_download(svc) for _ in range(MAX_DOWNLOADS)]
    try:
        wait_for(lambda: len(spool_files(pid, tmpdir)) == MAX_DOWNLOADS, timeout=20, what="4 spools")
        head = httpx.head(f"{svc.base_url}/maps/big/snapshot", timeout=30)
        assert head.status_code == 200, head.headers
        assert head.headers["content-type"] == MEDIA
        assert head.headers["content-disposition"] == 'attachment; filename="big.fleetmap.zip"'
        assert "content-length" not in head.headers and head.content == b""
        assert len(spool_files(pid, tmpdir)) == MAX_DOWNLOADS
        assert metric(svc, "fleetmap_downloads") == MAX_DOWNLOADS
        assert metric(svc, "fleetmap_downloads_refused_total") == refused
        assert httpx.head(f"{svc.base_url}/maps/nothing/snapshot").status_code == 404
    finally:
        for sock, _ in stalled:
            sock.close()
    wait_for(lambda: metric(svc, "fleetmap_downloads") == 0, timeout=10, what="every slot back")
    # The GET after it is whole.
    same_map(big_snapshot, httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=60).content)


def test_a_download_the_temporary_directory_has_no_room_for_is_refused_with_507(
    tmp_path: Path, big_snapshot: bytes
) -> None:
    """A download whose file cannot be written (its disk full: here a limit on the size of the files
    the service writes, set once the map is in) is answered 507 naming the temporary directory and
    the download, never 500, and leaves nothing; the map is unchanged and a small map's download is
    served."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    with ServiceProcess(tmp_path, ["--in-memory"], env={"TMPDIR": str(tmpdir)}) as svc:
        pid = svc.proc.pid  # type: ignore[union-attr]
        assert (
            httpx.put(f"{svc.base_url}/maps/big/snapshot", content=big_snapshot, timeout=60).status_code
            == 201
        )
        small = snapshot_file("small", random_tiles_map(2))
        assert httpx.put(f"{svc.base_url}/maps/small/snapshot", content=small).status_code == 201
        stats = httpx.get(f"{svc.base_url}/maps/big").json()["stats"]
        # Files past SPOOL_MEMORY_BYTES + 2 MiB now fail as on a full disk (EFBIG; Python ignores
        # the SIGXFSZ that comes with it).
        limit = SPOOL_MEMORY_BYTES + (2 << 20)
        resource.prlimit(pid, resource.RLIMIT_FSIZE, (limit, limit))
        got = httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=60)
        assert got.status_code == 507, got.text
        assert f"the temporary directory {tmpdir} has no room for the download" in got.json()["detail"]
        assert list(tmpdir.iterdir()) == [] and not spool_files(pid, tmpdir)
        assert httpx.get(f"{svc.base_url}/maps/big").json()["stats"] == stats
        assert metric(svc, "fleetmap_downloads") == 0
        same_map(small, httpx.get(f"{svc.base_url}/maps/small/snapshot").content)
        assert "Traceback" not in svc.logs(), svc.logs()


def crafted_upload(tiles: int, tile_size: int = 1024) -> tuple[bytes, int]:
    """A small snapshot file whose tiles.npz says it holds `tiles` tiles of every layer of
    `tile_size` cells (each array of the shape that needs) though it holds none: the service refuses
    it for its size (413) before anything is decompressed when that is past its limit, else for the
    arrays' shapes (422). And the bytes its tiles would hold."""
    config = {"resolution": 0.05, "tile_size": tile_size, "max_tiles": 100_000}
    meta = {"format": "fleetmap-snapshot-1", "id": "c", "config": config}
    empty = {a: np.zeros(0, np.float32) for a in ("log_odds", "tsdf", "tsdf_weight")}
    empty |= {a: np.zeros(0, np.uint32) for a in ("hits", "misses")}
    keys = np.array([[k, 0] for k in range(tiles)], dtype=np.int64)
    return snapshot_body(meta, {"keys": keys, **empty}), tiles * tile_size * tile_size * 20


def test_the_upload_limit_is_the_memory_budget(tmp_path: Path) -> None:
    """A snapshot's tiles may hold what the memory budget (`--max-memory`) holds: with 64 MiB, tiles of
    80 MiB are refused with 413 before anything is read, as is a body past 64 MiB + 2 MiB; with no
    budget, the memory the service may use, so tiles of 5 GiB (past the fixed 4 GiB there was) pass
    the size check and are refused for what the file holds (422), not for their size."""
    body, size = crafted_upload(4)
    assert 64 << 20 < size < 96 << 20
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "64MiB"]) as svc:
        put = httpx.put(f"{svc.base_url}/maps/c/snapshot", content=body)
        assert put.status_code == 413, put.text
        assert f"hold {size} bytes" in put.json()["detail"] and "67108864" in put.json()["detail"]
        # Refused as it arrives: what was sent past the limit is at most what the sockets buffer.
        status, answer, sent = send_chunked(svc.port, "/maps/c/snapshot", b"\0" * (1 << 20), 160)
        assert status == 413 and f"larger than the limit of {(64 << 20) + (2 << 20)} bytes" in answer, answer
        assert sent < 128 << 20
        small = snapshot_file("s", random_tiles_map(2, tile_size=64))
        assert httpx.put(f"{svc.base_url}/maps/c/snapshot", content=small).status_code == 201
    body, size = crafted_upload(256)
    assert size == 5 << 30
    if available_memory() < size:
        pytest.skip(f"this machine's {available_memory()} bytes of memory are under the 5 GiB map checked")
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "none"]) as svc:
        put = httpx.put(f"{svc.base_url}/maps/c/snapshot", content=body)
        assert put.status_code == 422, put.text
        assert "has shape" in put.json()["detail"], put.text


def test_a_client_that_stops_reading_its_download_is_dropped(tmp_path: Path, big_snapshot: bytes) -> None:
    """A client that asks for a download and then reads nothing, its connection left open, is
    dropped once it has read nothing for `--http-send-timeout` seconds, as if it had gone: its slot
    and its spool come back. Four such clients held every download slot for ever (nothing timed an
    answer out), and every other download was refused with 503."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    args = ["--in-memory", "--http-send-timeout", "5"]
    with ServiceProcess(tmp_path, args, env={"TMPDIR": str(tmpdir)}) as svc:
        pid = svc.proc.pid  # type: ignore[union-attr]
        put = httpx.put(f"{svc.base_url}/maps/big/snapshot", content=big_snapshot, timeout=60)
        assert put.status_code == 201, put.text
        stalled = [start_download(svc) for _ in range(MAX_DOWNLOADS)]
        try:
            assert metric(svc, "fleetmap_downloads") > 0  # (the first may be dropped already)
            wait_for(lambda: metric(svc, "fleetmap_downloads") == 0, timeout=20, what="the slots back")
            wait_for(lambda: not spool_files(pid, tmpdir), timeout=5, what="no spool")
            got = httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=60)
            assert got.status_code == 200, got.text
            same_map(big_snapshot, got.content)
        finally:
            for sock, _ in stalled:
                sock.close()
        assert "Traceback" not in svc.logs() and "ERROR" not in svc.logs(), svc.logs()


def test_a_download_whose_client_goes_away_stops_being_written(tmp_path: Path) -> None:
    """A client that goes away while its download's file is being written stops the writing (its
    slot, its spool and the copy of the map come back at once, logged): it ran to the end, half a
    minute for a 4.46 GB map, so a client dropping 4 downloads as often as they were written kept
    everyone else's at 503. The map: 64 tiles of random values, about a second to compress.

    Nor is it a failure of the service: it was counted as a 503 in `fleetmap_http_responses_total`,
    the series docs/api.md alerts on as "the API fails", though nothing failed and nothing was sent.
    It counts under 499 (nginx's "client closed request"), and the 5xx stay at 0."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    with ServiceProcess(tmp_path, ["--in-memory"], env={"TMPDIR": str(tmpdir)}) as svc:
        pid = svc.proc.pid  # type: ignore[union-attr]
        body = snapshot_file("big", random_tiles_map(64))
        assert httpx.put(f"{svc.base_url}/maps/big/snapshot", content=body, timeout=60).status_code == 201
        with socket.create_connection(("127.0.0.1", svc.port), timeout=30) as sock:
            sock.sendall(b"GET /maps/big/snapshot HTTP/1.1\r\nHost: localhost\r\n\r\n")
            wait_for(lambda: metric(svc, "fleetmap_downloads") == 1, timeout=10, what="a download")
        stopped = "the download of map big stopped as it was written: its client went away"
        wait_for(lambda: stopped in svc.logs(), timeout=20, what="the writing stopped")
        wait_for(lambda: metric(svc, "fleetmap_downloads") == 0, timeout=10, what="the slot back")
        wait_for(lambda: not spool_files(pid, tmpdir), timeout=10, what="no spool")
        answers = 'fleetmap_http_responses_total{code="499"}'
        wait_for(lambda: metric(svc, answers) == 1, timeout=10, what="the dropped download counted")
        assert metric(svc, 'fleetmap_http_responses_total{code="503"}') == 0
        assert metric(svc, 'fleetmap_http_responses_total{code="500"}') == 0
        same_map(body, httpx.get(f"{svc.base_url}/maps/big/snapshot", timeout=60).content)
        assert "Traceback" not in svc.logs(), svc.logs()
