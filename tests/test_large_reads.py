"""Reads of big windows (`GET /maps/{id}/region`, `/surface`, `/export` of more than 1 Mi cells) are
limited in number at once (`ApiSettings.max_large_reads`, 4), on the real service process.

Each read was bounded, but not how many ran together: a region of 16 Mi cells held about 450 MB
while it was made and its 64 MB answer until the client read it, so eight clients at once held
3.2 GB more, and a few dozen more memory than the machine had. Smaller windows never wait.
"""

from __future__ import annotations

import io
import socket
import struct
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess, wait_for
from test_api_support import fan_scan
from test_http_exhaustion import metric
from test_snapshot_downloads import finish_download, start_download

from fleetmap.codec import encode_json

#: Big reads in progress at once (`ApiSettings.max_large_reads`).
MAX_LARGE_READS = 4
#: A region of 2048 x 2048 cells at 0.05 m (4 Mi cells, a big read), as npy: 16 MiB, far more than the
#: sockets between the test and the service buffer, so a client that stops reading holds it.
BIG = "/maps/m/region?xmin=-51.2&ymin=-51.2&xmax=51.2&ymax=51.2&layer=hits"


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    # A send timeout past the test's length: the stalled clients read nothing until the end, and on a
    # loaded machine (four big regions made at once) that took longer than the default 60 s,
    # after which the service dropped them and their answers came cut short.
    args = ["--in-memory", "--http-send-timeout", "600"]
    with ServiceProcess(tmp_path_factory.mktemp("logs"), args) as svc:
        scan = encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 61), 0)
        r = httpx.post(
            f"{svc.base_url}/maps/m/scans",
            params={"robot_id": "r"},
            content=scan,
            headers={"content-type": "application/json"},
            timeout=30,
        )
        assert r.status_code == 200, r.text
        yield svc


def test_big_window_reads_in_progress_are_limited_and_a_client_gone_gives_its_slot_back(
    service: ServiceProcess,
) -> None:
    """Four clients that asked for a 4 Mi-cell region and read nothing hold the four slots: the next
    big region, or surface, is answered 503 with `Retry-After`, counted, having read nothing; a small
    window is answered as ever. Clients that go away give their slots back, and the answers of those
    that read on are whole."""
    svc = service
    stalled = [start_download(svc, BIG) for _ in range(MAX_LARGE_READS)]
    try:
        # Each answer's head has come: its read took its slot before it read the map.
        for _, head in stalled:
            assert head.startswith(b"HTTP/1.1 200"), head[:200]
        refused = httpx.get(f"{svc.base_url}{BIG}", timeout=60)
        assert refused.status_code == 503, refused.status_code
        assert refused.headers["retry-after"] == "1"
        assert "limit of 4 windows of more than 1048576 cells" in refused.json()["detail"]
        window = {"xmin": -51.2, "ymin": -51.2, "xmax": 51.2, "ymax": 51.2}
        surface = httpx.get(f"{svc.base_url}/maps/m/surface", params=window, timeout=60)
        assert surface.status_code == 503, surface.text
        assert metric(svc, "fleetmap_large_reads") == MAX_LARGE_READS
        assert metric(svc, "fleetmap_large_reads_refused_total") == 2
        # A layer the map does not keep is said so (422), whatever the slots: it was a 503, to retry.
        created = httpx.put(f"{svc.base_url}/maps/tsdf-only", json={"layers": ["tsdf"]}, timeout=30)
        assert created.status_code == 201, created.text
        lacking = httpx.get(f"{svc.base_url}{BIG.replace('/maps/m/', '/maps/tsdf-only/')}", timeout=60)
        assert lacking.status_code == 422 and "does not keep" in lacking.json()["detail"], lacking.text
        small = httpx.get(f"{svc.base_url}/maps/m/region", params={"layer": "hits"}, timeout=30)
        assert small.status_code == 200 and np.load(io.BytesIO(small.content)).sum() > 0
        # Two clients go away before reading their answers.
        for sock, _ in stalled[:2]:
            sock.close()
        wait_for(lambda: metric(svc, "fleetmap_large_reads") == 2, timeout=30, what="2 slots back")
        again = httpx.get(f"{svc.base_url}{BIG}", timeout=60)
        assert again.status_code == 200
        assert np.load(io.BytesIO(again.content)).shape == (2048, 2048)
        for sock, head in stalled[2:]:
            headers, body = finish_download(sock, head)
            assert int(headers["content-length"]) == len(body)
            assert np.array_equal(np.load(io.BytesIO(body)), np.load(io.BytesIO(again.content)))
    finally:
        for sock, _ in stalled:
            sock.close()
    wait_for(lambda: metric(svc, "fleetmap_large_reads") == 0, timeout=30, what="every slot back")
    assert "Traceback" not in svc.logs(), svc.logs()


def test_a_big_read_whose_client_went_away_is_not_written_on_into_the_log(service: ServiceProcess) -> None:
    """A big answer is handed to the server a megabyte at a time, and the server takes a piece
    without waiting while its write buffer has room, so the answer went on without ever letting the
    event loop run: a client that reset its connection was noticed only once the whole answer had
    been written to the dead socket, and asyncio logged a warning, "socket.send() raised
    exception.", with nothing to say which answer or why, for each piece past the fifth: some 60
    lines for each 64 MB region a client gave up on (some 10 for these 16 MB). The answer now stops
    at the piece after."""
    svc = service
    for _ in range(3):
        sock, head = start_download(svc, BIG)
        assert head.startswith(b"HTTP/1.1 200"), head[:200]
        # Reset, as a client killed or a browser tab closed mid-download does, not closed cleanly.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()
        wait_for(lambda: metric(svc, "fleetmap_large_reads") == 0, timeout=30, what="the slot back")
    # The service is still answering: its log holds whatever the aborted answers made it write.
    assert httpx.get(f"{svc.base_url}/healthz", timeout=30).status_code == 200
    assert "socket.send() raised exception" not in svc.logs(), svc.logs()[-2000:]
