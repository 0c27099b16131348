"""Uploads (`PUT /maps/{id}/snapshot`, `PUT /maps/{id}/import`) are spooled to the temporary
directory, not held in memory while they are read (`fleetmap.upload_spool`, `routes_snapshot.spooled_body`),
on the real service process with `TMPDIR` pointed at a directory of the test's.

A spool's file is unlinked as it is made, so the directory shows nothing: the service's open
descriptors into it (`/proc/<pid>/fd`) are what show a spool, and each test first sees one there
mid-upload (bodies past SPOOL_MEMORY_BYTES), so that its "none left" can fail.
"""

from __future__ import annotations

import errno
import io
import json
import logging
import os
import resource
import shutil
import signal
import socket
import tempfile
import threading
import time
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any
from unittest import mock

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess, wait_for
from test_api_support import random_tiles_map, running_api, snapshot_body, snapshot_parts
from test_http_exhaustion import metric

from fleetmap import upload_spool
from fleetmap.api.app import ApiSettings
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.http_server import GRACEFUL_HTTP_SECONDS
from fleetmap.storage_format import SNAPSHOT_FORMAT, snapshot_file
from fleetmap.upload_spool import (
    SPOOL_CHECK_EVERY,
    SPOOL_MEMORY_BYTES,
    SpoolFailed,
    close_spool,
    spooled_file,
)

BODY_TIMEOUT = 4.0
#: A body's bytes sent before the test looks for its spool: past what the spool keeps in memory.
FIRST_PART = SPOOL_MEMORY_BYTES + (4 << 20)
MEDIA = "application/zip"


@dataclass
class Spooling:
    service: ServiceProcess
    tmpdir: Path  # the service's TMPDIR


@pytest.fixture(scope="module")
def spooling(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Spooling]:
    tmpdir = tmp_path_factory.mktemp("spool")
    args = ["--in-memory", "--http-body-timeout", str(BODY_TIMEOUT)]
    with ServiceProcess(tmp_path_factory.mktemp("logs"), args, env={"TMPDIR": str(tmpdir)}) as svc:
        yield Spooling(svc, tmpdir)


@pytest.fixture(scope="module")
def big_snapshot() -> bytes:
    """The snapshot of a map of 24 tiles of every layer holding random values (they barely
    compress): a file over FIRST_PART, so that its upload goes to a file of the spool."""
    gmap = random_tiles_map(24)
    data = snapshot_file("big", gmap)
    assert len(data) > FIRST_PART + (1 << 20)
    return data


def spool_files(pid: int, directory: Path) -> list[str]:
    """The files of `directory` that process `pid` holds open (a spool's, unlinked: `... (deleted)`)."""
    held = []
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except FileNotFoundError:  # closed meanwhile
            continue
        if target.startswith(f"{directory}/"):
            held.append(target)
    return held


def start_upload(svc: ServiceProcess, path: str, length: int, headers: str = "") -> socket.socket:
    """A raw connection that has sent the head of `PUT path` with a body of `length` bytes."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=30)
    head = (
        f"PUT {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/zip\r\n"
        f"Content-Length: {length}\r\n"
        f"Connection: close\r\n{headers}\r\n"
    )
    sock.sendall(head.encode())
    return sock


def read_answer(sock: socket.socket) -> tuple[int, str]:
    """The status and the body of the answer on `sock`, read until the server closes it."""
    answer = b""
    while chunk := sock.recv(65536):
        answer += chunk
    head, _, body = answer.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode()


def upload_seen_spooled(spooling: Spooling, path: str, body: bytes, headers: str = "") -> tuple[int, str]:
    """Upload `body` to `path`, checking mid-body that the service holds a spool file in its TMPDIR;
    the answer's status and body."""
    pid = spooling.service.proc.pid  # type: ignore[union-attr]
    with start_upload(spooling.service, path, len(body), headers) as sock:
        sock.sendall(body[:FIRST_PART])
        wait_for(lambda: spool_files(pid, spooling.tmpdir), timeout=10, what="the upload's spool file")
        sock.sendall(body[FIRST_PART:])
        return read_answer(sock)


def assert_no_spool(spooling: Spooling) -> None:
    pid = spooling.service.proc.pid  # type: ignore[union-attr]
    assert spool_files(pid, spooling.tmpdir) == []
    assert list(spooling.tmpdir.iterdir()) == []


def same_map(a: bytes, b: bytes) -> None:
    meta_a, arrays_a = snapshot_parts(a)
    meta_b, arrays_b = snapshot_parts(b)
    assert meta_a["config"] == meta_b["config"] and arrays_a.keys() == arrays_b.keys()
    for name, values in arrays_a.items():
        assert np.array_equal(values, arrays_b[name], equal_nan=True), name


def test_a_big_upload_goes_through_a_spool_file_and_round_trips(
    spooling: Spooling, big_snapshot: bytes
) -> None:
    """Download -> upload -> the same map, the upload spooled to a file of TMPDIR on the way, and that
    file closed (so removed) by the time the answer comes."""
    status, answer = upload_seen_spooled(spooling, "/maps/round-trip/snapshot", big_snapshot)
    assert status == 201, answer
    assert_no_spool(spooling)
    base = spooling.service.base_url
    downloaded = httpx.get(f"{base}/maps/round-trip/snapshot", timeout=60).content
    same_map(downloaded, big_snapshot)
    # ... and that download uploaded again (to another id) is that map once more.
    status, answer = upload_seen_spooled(spooling, "/maps/round-trip-2/snapshot", downloaded)
    assert status == 201, answer
    same_map(httpx.get(f"{base}/maps/round-trip-2/snapshot", timeout=60).content, big_snapshot)
    assert_no_spool(spooling)


@pytest.mark.parametrize("refusal", ["not a zip", "precondition"])
def test_a_refused_upload_leaves_no_spool_and_changes_nothing(
    spooling: Spooling, big_snapshot: bytes, refusal: str
) -> None:
    base = spooling.service.base_url
    assert httpx.put(f"{base}/maps/kept", json={}).status_code in (200, 201)
    etag = httpx.get(f"{base}/maps/kept").headers["etag"]
    if refusal == "not a zip":
        body, headers, expected = b"\x07" * len(big_snapshot), "", 422
        detail = "not a fleetmap snapshot: the body is not a zip file"
        status, answer = upload_seen_spooled(spooling, "/maps/kept/snapshot", body, headers)
    else:
        # A whole good snapshot for a map that did not exist when its head came: the map another
        # writer made while the body was read into the spool fails it once the body is in.
        pid = spooling.service.proc.pid  # type: ignore[union-attr]
        with start_upload(
            spooling.service, "/maps/late/snapshot", len(big_snapshot), "If-None-Match: *\r\n"
        ) as sock:
            sock.sendall(big_snapshot[:FIRST_PART])
            wait_for(lambda: spool_files(pid, spooling.tmpdir), timeout=10, what="the upload's spool file")
            assert httpx.put(f"{base}/maps/late", json={}).status_code == 201
            etag = httpx.get(f"{base}/maps/late").headers["etag"]
            sock.sendall(big_snapshot[FIRST_PART:])
            status, answer = read_answer(sock)
        expected, detail = 412, "If-None-Match"
    assert status == expected and detail in answer, answer
    assert_no_spool(spooling)
    assert httpx.get(f"{base}/maps/{'kept' if refusal == 'not a zip' else 'late'}").headers["etag"] == etag


def test_an_upload_whose_precondition_fails_is_refused_before_its_body(
    spooling: Spooling, big_snapshot: bytes
) -> None:
    """`If-Match` with another tag, or `If-None-Match: *` on a map that exists, is answered 412
    from the request's head: the body (gigabytes, for a big map) is neither waited for nor
    spooled, and the map is unchanged. Checked only once the body was in, a doomed upload was
    sent whole and filled the temporary directory before its 412."""
    svc, pid = spooling.service, spooling.service.proc.pid  # type: ignore[union-attr]
    base = svc.base_url
    small = snapshot_file("s", GridMap(MapConfig()))
    assert httpx.put(f"{base}/maps/guarded/snapshot", content=small).status_code in (200, 201)
    etag = httpx.get(f"{base}/maps/guarded").headers["etag"]
    # (An import's body may hold 16 MiB at most: a longer Content-Length is refused first, 413.)
    for path, length in (("/maps/guarded/snapshot", len(big_snapshot)), ("/maps/guarded/import", 1 << 20)):
        for header in ('If-Match: "not-its-tag"', "If-None-Match: *"):
            with start_upload(svc, path, length, f"{header}\r\n") as sock:
                sock.settimeout(BODY_TIMEOUT / 2)  # sooner than the body's deadline would answer
                status, answer = read_answer(sock)  # none of the body sent
            assert status == 412, (path, header, answer)
            assert spool_files(pid, spooling.tmpdir) == []
    assert httpx.get(f"{base}/maps/guarded").headers["etag"] == etag
    # The same head with the map's own tag is taken, body and all.
    status, answer = upload_seen_spooled(
        spooling, "/maps/guarded/snapshot", big_snapshot, f"If-Match: {etag}\r\n"
    )
    assert status == 200, answer
    assert httpx.get(f"{base}/maps/guarded").headers["etag"] != etag
    assert_no_spool(spooling)


@pytest.mark.parametrize("how", ["client gone", "body deadline"])
def test_an_upload_cut_off_mid_body_leaves_no_spool(
    spooling: Spooling, big_snapshot: bytes, how: str
) -> None:
    """A client that goes away mid-body, or whose body misses its deadline (--http-body-timeout):
    the spool is closed, the service answers on, and no map was made."""
    svc, pid = spooling.service, spooling.service.proc.pid  # type: ignore[union-attr]
    with start_upload(svc, "/maps/cut/snapshot", len(big_snapshot)) as sock:
        sock.sendall(big_snapshot[:FIRST_PART])
        wait_for(lambda: spool_files(pid, spooling.tmpdir), timeout=10, what="the upload's spool file")
        if how == "body deadline":  # the service answers 408, then closes the connection
            sock.settimeout(BODY_TIMEOUT + 5)
            answer = b""
            while chunk := sock.recv(65536):
                answer += chunk
            assert answer.startswith(b"HTTP/1.1 408 ") and b"--http-body-timeout" in answer, answer
    wait_for(lambda: not spool_files(pid, spooling.tmpdir), timeout=5, what="the spool closed")
    assert_no_spool(spooling)
    assert httpx.get(f"{svc.base_url}/healthz").status_code == 200
    assert httpx.get(f"{svc.base_url}/maps/cut").status_code == 404
    assert "Traceback" not in svc.logs(), svc.logs()


def send_chunked(port: int, path: str, chunk: bytes, chunks: int) -> tuple[int, str, int]:
    """`PUT path` with a chunked body (no Content-Length: the limit is met only as the body arrives)
    of `chunks` copies of `chunk`, sent from a thread while the answer is read: (status, body, bytes
    of the body sent when the server stopped reading or answered)."""
    sent = 0
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)

    def send() -> None:
        nonlocal sent
        head = f"PUT {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/zip\r\n"
        head += "Transfer-Encoding: chunked\r\n\r\n"
        try:
            sock.sendall(head.encode())
            for _ in range(chunks):
                sock.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                sent += len(chunk)
            sock.sendall(b"0\r\n\r\n")
        except OSError:  # the server answered and closed
            pass

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        answer = b""
        while b"\r\n\r\n" not in answer or len(answer.partition(b"\r\n\r\n")[2]) < int(
            answer.lower().partition(b"content-length: ")[2].split(b"\r\n")[0] or 0
        ):
            data = sock.recv(65536)
            if not data:
                break
            answer += data
        at = sent
    finally:
        sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        sender.join(10)
    head, _, body = answer.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode(), at


def test_a_body_past_the_limit_is_refused_as_it_arrives_and_leaves_no_spool(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, big_snapshot: bytes
) -> None:
    """The body limit counts what the route streams as it does what it read whole: a snapshot body
    past a (lowered) limit, sent without Content-Length, is answered 413 once the limit is passed,
    not after the rest, and its spool (on disk by then) is gone; the map is as it was. (In-process,
    for the lowered limit: the service has no option for it.)"""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    limit = FIRST_PART
    with running_api(ApiSettings(max_snapshot_body_bytes=limit)) as api:
        assert api.client.put("/maps/kept", json={}).status_code == 201
        etag = api.client.get("/maps/kept").headers["etag"]
        port = int(api.base_url.rsplit(":", 1)[1])
        chunk = big_snapshot[: 1 << 20]
        status, body, sent = send_chunked(port, "/maps/kept/snapshot", chunk, 4 * limit // len(chunk))
        assert status == 413 and f"larger than the limit of {limit} bytes" in body, body
        assert sent < 2 * limit  # answered as the limit was passed, not once all had been sent
        wait_for(lambda: not spool_files(os.getpid(), tmp_path), timeout=5, what="the spool closed")
        assert list(tmp_path.iterdir()) == []
        assert api.client.get("/maps/kept").headers["etag"] == etag
        # Under the limit, the same route takes a body (of a map's snapshot) as before.
        small = snapshot_file("s", GridMap(MapConfig()))
        assert api.client.put("/maps/kept/snapshot", content=small).status_code == 200


def test_a_nav2_import_past_the_body_limit_is_refused(spooling: Spooling) -> None:
    """`PUT .../import` streams its body through the same spool, and its limit (the 16 MiB of every
    body but a snapshot's) still holds as the body arrives."""
    svc = spooling.service
    status, body, sent = send_chunked(svc.port, "/maps/imported/import", b"\0" * (1 << 20), 64)
    assert status == 413 and "larger than the limit of 16777216 bytes" in body, body
    assert sent < 48 << 20
    wait_for(lambda: not spool_files(svc.proc.pid, spooling.tmpdir), timeout=5, what="no spool")  # type: ignore[union-attr]
    assert httpx.get(f"{svc.base_url}/maps/imported").status_code == 404


def _small_file_limit() -> None:
    """In the service's child process: files it writes may hold at most SPOOL_MEMORY_BYTES + 2 MiB,
    so a spool past that fails as on a full disk (EFBIG; Python ignores the SIGXFSZ it brings)."""
    size = SPOOL_MEMORY_BYTES + (2 << 20)
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))


def test_an_upload_the_temporary_directory_has_no_room_for_is_refused_with_507(
    tmp_path: Path, big_snapshot: bytes
) -> None:
    """A spool that cannot be written (its disk full: here a file size limit on the service) is
    answered 507 naming the temporary directory, never 500; nothing changes, nothing is left, and
    an upload that fits is taken afterwards."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    args = ["--in-memory"]
    env = {"TMPDIR": str(tmpdir)}
    with ServiceProcess(tmp_path, args, env=env, preexec_fn=_small_file_limit) as svc:
        spooling = Spooling(svc, tmpdir)
        # Answered before the body is all sent: sent from a thread, the answer read meanwhile.
        status, answer, _ = send_chunked(svc.port, "/maps/full/snapshot", big_snapshot[: 1 << 20], 32)
        assert status == 507, answer
        assert f"the temporary directory {tmpdir} has no room for the upload" in answer, answer
        assert_no_spool(spooling)
        assert httpx.get(f"{svc.base_url}/maps/full").status_code == 404
        small = snapshot_file("s", GridMap(MapConfig()))
        put = httpx.put(f"{svc.base_url}/maps/full/snapshot", content=small)
        assert put.status_code == 201, put.text
        time.sleep(0.2)
        assert "Traceback" not in svc.logs(), svc.logs()


def test_uploads_in_progress_are_limited_and_the_next_is_refused_before_its_body(
    spooling: Spooling, big_snapshot: bytes
) -> None:
    """At most `ApiSettings.max_uploads` (4) uploads hold a spool at once: the next is answered 503
    with `Retry-After` before its body is read, changing nothing, and a slot is given back as an
    upload ends, answered or cut off. Without the limit as many uploads as HTTP connections (1024)
    each held 16 MiB of memory (their spool before it goes to disk) or disk of their size: 16 slow
    uploads of 16 MiB held 262 MiB for the whole body deadline."""
    svc, pid = spooling.service, spooling.service.proc.pid  # type: ignore[union-attr]
    limit = ApiSettings().max_uploads
    small = snapshot_file("s", GridMap(MapConfig()))
    stalled = []
    try:
        for k in range(limit):
            sock = start_upload(svc, f"/maps/busy-{k}/snapshot", len(big_snapshot))
            stalled.append(sock)
            sock.sendall(big_snapshot[:FIRST_PART])
            wait_for(lambda n=k + 1: len(spool_files(pid, spooling.tmpdir)) == n, timeout=10, what="a spool")
        for path in ("/maps/busy-more/snapshot", "/maps/busy-more/import"):
            refused = httpx.put(f"{svc.base_url}{path}", content=small, headers={"Content-Type": MEDIA})
            assert refused.status_code == 503, refused.text
            assert f"its limit of {limit} uploads in progress" in refused.json()["detail"]
            assert refused.headers["retry-after"] == "5"
        assert httpx.get(f"{svc.base_url}/maps/busy-more").status_code == 404
        assert metric(svc, "fleetmap_uploads") == limit
        assert metric(svc, "fleetmap_uploads_refused_total") >= 2
        # One answered: its slot is free again.
        stalled[0].sendall(big_snapshot[FIRST_PART:])
        assert read_answer(stalled[0])[0] == 201
        put = httpx.put(f"{svc.base_url}/maps/busy-more/snapshot", content=small)
        assert put.status_code == 201, put.text
    finally:
        for sock in stalled:  # the others cut off: their slots too are given back
            sock.close()
    wait_for(lambda: not spool_files(pid, spooling.tmpdir), timeout=5, what="the spools closed")
    # Every slot is free again: `limit` uploads are taken (a slot is held from the head on, before
    # any of the body), and only the next is refused.
    heads = [start_upload(svc, f"/maps/again-{k}/snapshot", len(small)) for k in range(limit)]
    try:
        for sock in heads:
            sock.settimeout(0.5)
            with pytest.raises(TimeoutError):
                sock.recv(1)  # not answered: waiting for its body
        refused = httpx.put(f"{svc.base_url}/maps/busy-more/snapshot", content=small)
        assert refused.status_code == 503, refused.text
    finally:
        for sock in heads:
            sock.close()
    wait_for(
        lambda: httpx.put(f"{svc.base_url}/maps/busy-more/snapshot", content=small).status_code == 200,
        timeout=5,
        what="a slot free",
    )
    assert_no_spool(spooling)
    assert metric(svc, "fleetmap_uploads") == 0
    assert "Traceback" not in svc.logs(), svc.logs()


class _FailingDisk(io.RawIOBase):
    """A file of the temporary directory (`real`, unbuffered) whose disk fails: with `fail` "read",
    every read raises EIO; with "write", every write once `after` bytes have been written."""

    def __init__(self, real: IO[bytes], fail: str, after: int) -> None:
        super().__init__()
        self._real, self._fail, self._after, self._written = real, fail, after, 0

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._real.fileno()

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._real.seek(offset, whence)

    def tell(self) -> int:
        return self._real.tell()

    def readinto(self, buffer: Any) -> int:
        if self._fail == "read":
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return self._real.readinto(buffer)  # type: ignore[attr-defined]

    def write(self, data: Any) -> int:
        self._written += len(data)
        if self._fail == "write" and self._written > self._after:
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return self._real.write(data)

    def close(self) -> None:
        self._real.close()
        super().close()


@pytest.mark.parametrize("fail", ["read", "write"])
@pytest.mark.parametrize("spool", ["body", "decompressed tiles.npz"])
def test_an_io_error_of_the_temporary_directory_is_the_servers_503_not_the_uploads_422(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, big_snapshot: bytes,
    fail: str, spool: str,
) -> None:  # fmt: skip
    """An EIO reading a spool back (the body's, or the copy of a compressed tiles.npz) was answered
    422 "the body is not a zip file" / "tiles.npz is not a valid .npz file", the client blamed for
    the server's disk. Any error of the spool's disk but no room is now 503 naming the directory,
    logged as an ERROR; nothing changes and the spool is gone. (In-process, the failure injected at
    the spool file's raw reads and writes, under Python's buffering: a real EIO needs a failing
    device, dm-error or a FUSE file system, which a test cannot set up without privileges.)"""
    real_temporary_file = tempfile.TemporaryFile

    def failing_file(*args: Any, **kwargs: Any) -> io.BufferedRandom:
        real = real_temporary_file(buffering=0, dir=kwargs.get("dir"), prefix=kwargs.get("prefix", "tmp"))
        return io.BufferedRandom(_FailingDisk(real, fail, SPOOL_MEMORY_BYTES + (4 << 20)))

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(tempfile, "TemporaryFile", failing_file)  # what SpooledTemporaryFile rolls to
    if spool == "body":  # past what the spool keeps in memory
        body = big_snapshot
    else:  # a small body (kept in memory) whose tiles.npz, deflated, holds 31 MB of arrays
        gmap = GridMap(MapConfig())
        gmap.store.create([(i, 0) for i in range(24)], fill=True)
        meta, arrays = snapshot_parts(snapshot_file("z", gmap))
        npz = io.BytesIO()
        np.savez(npz, **arrays)  # type: ignore[arg-type]
        body = snapshot_body(meta, npz=npz.getvalue(), deflate=True)
        assert len(body) < SPOOL_MEMORY_BYTES < len(npz.getvalue()) - (4 << 20)
    with running_api() as api:
        assert api.client.put("/maps/kept", json={}).status_code == 201
        etag = api.client.get("/maps/kept").headers["etag"]
        with caplog.at_level(logging.ERROR, logger="fleetmap.api"):
            put = api.client.put("/maps/kept/snapshot", content=body, headers={"Content-Type": MEDIA})
        action = "read back from" if fail == "read" else "written to"
        assert put.status_code == 503, put.text
        assert put.json()["detail"] == (
            f"the upload could not be {action} the temporary directory {tmp_path} (Input/output error)"
        )
        logged = [r for r in caplog.records if r.levelno == logging.ERROR and str(tmp_path) in r.getMessage()]
        assert logged, caplog.text
        assert api.client.get("/maps/kept").headers["etag"] == etag
        wait_for(lambda: not spool_files(os.getpid(), tmp_path), timeout=5, what="the spool closed")
        assert list(tmp_path.iterdir()) == []


def zeros_snapshot(chunks: int) -> bytes:
    """A snapshot whose tiles.npz is deflated and holds `chunks` x 16 MiB of zeros (not an npz: it is
    refused only once decompressed whole), made in a moment: 16 MiB of zeros deflated once, after a
    full flush (which resets the compressor's state), gives the same bytes every time, so the
    member is those bytes `chunks` times (zipfile's compressor replaced by one that repeats them)."""
    chunk = bytes(16 << 20)
    deflate = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = deflate.compress(chunk) + deflate.flush(zlib.Z_FULL_FLUSH)
    assert deflate.compress(chunk) + deflate.flush(zlib.Z_FULL_FLUSH) == block
    end = deflate.flush()

    class Repeat:
        def compress(self, data: bytes) -> bytes:
            assert len(data) == len(chunk)
            return block

        def flush(self) -> bytes:
            return end

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("map.json", json.dumps({"format": SNAPSHOT_FORMAT, "config": {}}))
        info = zipfile.ZipInfo("tiles.npz")
        info.compress_type = zipfile.ZIP_DEFLATED
        with (
            mock.patch.object(zipfile, "_get_compressor", lambda *_args, **_kwargs: Repeat()),
            zf.open(info, "w", force_zip64=True) as member,
        ):
            for _ in range(chunks):
                member.write(chunk)  # zipfile sums its CRC, as for a real one
    return out.getvalue()


def held_open(pid: int, directory: Path) -> list[str]:
    """`spool_files`, none once process `pid` has exited."""
    try:
        return spool_files(pid, directory)
    except FileNotFoundError:  # /proc/<pid>/fd: gone with the process
        return []


def test_an_upload_still_being_decompressed_at_shutdown_stops_with_its_request(tmp_path: Path) -> None:
    """SIGTERM while an upload's reader decompresses a compressed tiles.npz into the temporary
    directory: the request is answered 503 at the graceful shutdown's cutoff, and its reader, on a
    worker thread, stops then too. It ran on to the end (4 GiB of zeros written to TMPDIR, here some
    13 s after the cutoff), and the process's exit waited for it: asyncio joins its executor's
    threads. The spool's file is unlinked as it is made, so TMPDIR shows nothing either way; the
    service's descriptor into it (`spool_files`) shows the reader still at work."""
    body = zeros_snapshot(255)  # 4080 MiB, within the 4 GiB limit; a 4 MB body, kept in memory
    assert len(body) < SPOOL_MEMORY_BYTES
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    svc = ServiceProcess(tmp_path, ["--in-memory"], env={"TMPDIR": str(tmpdir)}).start()
    try:
        pid = svc.proc.pid  # type: ignore[union-attr]
        with start_upload(svc, "/maps/zeros/snapshot", len(body)) as sock:
            sock.sendall(body)
            # The only spool on disk is the decompressed tiles.npz's: the reader is at work.
            wait_for(lambda: spool_files(pid, tmpdir), timeout=20, what="the decompressed copy's spool")
            sent = time.monotonic()
            svc.proc.send_signal(signal.SIGTERM)  # type: ignore[union-attr]
            sock.settimeout(GRACEFUL_HTTP_SECONDS + 10)
            status, answer = read_answer(sock)
        assert status == 503 and "shutting down" in answer, answer
        # The reader stops with its request: its spool is closed at once, not when it is done.
        wait_for(lambda: not held_open(pid, tmpdir), timeout=1.5, what="the reader stopped")
        assert svc.stop(timeout=30) == 0, svc.logs()
        assert time.monotonic() - sent < GRACEFUL_HTTP_SECONDS + 3, svc.logs()
    finally:
        svc.stop()
    assert list(tmpdir.iterdir()) == []
    assert "Traceback" not in svc.logs(), svc.logs()


def test_a_spool_leaves_its_disk_room_for_the_maps_storage(monkeypatch: pytest.MonkeyPatch) -> None:
    """A spool on disk (past SPOOL_MEMORY_BYTES) never fills its disk: once its next SPOOL_CHECK_EVERY
    bytes would leave less than SPOOL_DISK_RESERVE free, it fails as on a full disk (507), saying
    why. A snapshot upload may be as big as the memory budget, and the temporary directory may share
    its disk with the journal. (The disk is real; the reserve is raised past its free space here.)"""
    chunk = b"\0" * (1 << 20)
    spool = spooled_file("download")
    try:
        free = shutil.disk_usage(tempfile.gettempdir()).free
        monkeypatch.setattr(upload_spool, "SPOOL_DISK_RESERVE", free + (1 << 40))
        for _ in range(SPOOL_MEMORY_BYTES >> 20):  # in memory: no disk to look at
            spool.write(chunk)
        with pytest.raises(SpoolFailed) as failed:
            for _ in range(SPOOL_CHECK_EVERY >> 20):
                spool.write(chunk)
        assert failed.value.status == 507
        assert "has no room for the download (it would leave less than" in str(failed.value), failed.value
    finally:
        close_spool(spool)
    monkeypatch.undo()  # the real reserve: with more than that free, the spool grows
    if shutil.disk_usage(tempfile.gettempdir()).free < upload_spool.SPOOL_DISK_RESERVE + (64 << 20):
        pytest.skip(f"{tempfile.gettempdir()} has less than the reserve and 64 MiB free")
    spool = spooled_file()
    try:
        for _ in range((SPOOL_MEMORY_BYTES + 2 * SPOOL_CHECK_EVERY) >> 20):
            spool.write(chunk)
        assert spool.tell() == SPOOL_MEMORY_BYTES + 2 * SPOOL_CHECK_EVERY
    finally:
        close_spool(spool)
