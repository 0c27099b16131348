"""Bad requests get a clear 4xx JSON error `{"detail": "..."}`, never a 500, and change nothing.

The server here has small limits (points, cells, body bytes) so the limits are cheap to exceed.
"""

from __future__ import annotations

import io
import json
import math
import string
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service_process import ServiceProcess
from test_api_support import (
    RunningApi,
    declare_size,
    fan_scan,
    room_scans,
    running_api,
    small_snapshot_map,
    snapshot_body,
    snapshot_parts,
)

from fleetmap.api import ApiSettings
from fleetmap.codec import encode_binary, encode_json
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan
from fleetmap.storage_format import MAX_SNAPSHOT_META_BYTES, snapshot_file
from fleetmap.wire import BINARY_ENCODING

LIMITS = ApiSettings(max_points=1000, max_region_cells=10_000, max_json_cells=1000, max_body_bytes=200_000)


@pytest.fixture(scope="module")
def api() -> Iterator[RunningApi]:
    with running_api(LIMITS) as running:
        c = running.client
        assert c.put("/maps/e", json={"resolution": 0.05}).status_code == 201
        assert c.put("/maps/occ", json={"resolution": 0.05, "layers": ["occupancy"]}).status_code == 201
        assert c.put("/maps/tsdf", json={"resolution": 0.05, "layers": ["tsdf"]}).status_code == 201
        assert c.put("/maps/empty", json={}).status_code == 201
        scan = encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 61), 0)
        for map_id in ("e", "occ", "tsdf"):
            r = c.post(
                f"/maps/{map_id}/scans",
                params={"robot_id": "r"},
                content=scan,
                headers={"content-type": "application/json"},
            )
            assert r.status_code == 200
        yield running


def good_scan(seq: int = 1) -> dict[str, Any]:
    return json.loads(encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 5), seq))


SCAN = "/maps/e/scans?robot_id=r"
SNAP = "/maps/e/snapshot"  # a refused upload must leave map e as it was
META, ARRAYS = snapshot_parts(snapshot_file("s", small_snapshot_map()))
TILES = len(ARRAYS["keys"])


def snap(meta: Any = None, **arrays: np.ndarray) -> dict[str, Any]:
    """httpx arguments of a PUT of the small snapshot with `map.json` and arrays replaced."""
    return {"content": snapshot_body(META if meta is None else meta, {**ARRAYS, **arrays})}


def cells(name: str, value: float) -> np.ndarray:
    """Array `name` of the small snapshot with its first cell set to `value`."""
    out = ARRAYS[name].copy()
    out[0, 0, 0] = value
    return out


def corrupt_deflate() -> bytes:
    """The small snapshot, deflated, with bytes in the middle of the deflate data of tiles.npz flipped."""
    body = bytearray(snapshot_body(META, ARRAYS, deflate=True))
    start = body.index(b"tiles.npz") + 60
    body[start : start + 30] = bytes(b ^ 0x55 for b in body[start : start + 30])
    return bytes(body)


def npz_member(name: str = "", data: bytes = b"") -> bytes:
    """A tiles.npz of the small snapshot's arrays (stored, not compressed), with member `name`
    replaced by `data` if given."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for key, array in ARRAYS.items():
            buf = io.BytesIO()
            np.save(buf, array)
            zf.writestr(f"{key}.npy", data if f"{key}.npy" == name else buf.getvalue())
    return out.getvalue()


def npy_with_header(header: bytes) -> bytes:
    """A version 1.0 .npy file whose header is `header` (padded as numpy pads it), and no data."""
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


#: A header such as a flipped bit of a deflated tiles.npz makes: numpy's fallback parser, which it
#: runs when `literal_eval` fails, raises tokenize.TokenError for it.
UNTERMINATED = b"{'descr': '" + b"''<u4', 'fortran_order': False, 'shape': (2, 16, 16), }"

TILE = "/maps/e/tiles"
R = "/maps/e/region?xmin=0&ymin=0&xmax=1&ymax=1"

#: (method, path, keyword arguments for httpx, expected status, a word the detail must contain)
CASES: list[tuple[str, str, dict[str, Any], int, str]] = [
    # ids
    ("GET", "/maps/bad%20id", {}, 422, "not a valid id"),
    ("GET", "/maps/" + "a" * 65, {}, 422, "not a valid id"),
    ("GET", "/maps/caf%C3%A9", {}, 422, "not a valid id"),
    ("PUT", "/maps/bad.id", {"json": {}}, 422, "not a valid id"),
    ("GET", "/maps/bad.id/tiles/0/0/0.png", {}, 422, "not a valid id"),
    ("GET", "/maps/nope", {}, 404, "no map 'nope'"),
    ("POST", "/maps/e/scans", {"json": good_scan()}, 422, "robot_id"),
    ("POST", "/maps/e/scans?robot_id=bad%20robot", {"json": good_scan()}, 422, "not a valid id"),
    ("POST", "/maps/e/scans?robot_id=" + "r" * 65, {"json": good_scan()}, 422, "not a valid id"),
    # map configurations
    ("PUT", "/maps/new1", {"json": {"resolution": -1}}, 422, "resolution"),
    ("PUT", "/maps/new1", {"json": {"tile_size": 100}}, 422, "power of two"),
    ("PUT", "/maps/new1", {"json": {"bogus": 1}}, 422, "bogus"),
    ("PUT", "/maps/new1", {"json": {"layers": "occupancy"}}, 422, "layers"),
    ("PUT", "/maps/new1", {"json": {"layers": ["volume"]}}, 422, "layers"),
    ("PUT", "/maps/new1", {"json": {"occupancy": {"preset": "nope"}}}, 422, "preset"),
    ("PUT", "/maps/new1", {"json": {"tsdf": {"truncation": 1e9}}}, 422, "more than 256 cells"),
    ("PUT", "/maps/new1", {"json": {"beam": {"alpha": 1e9}}}, 422, "more than 256 cells"),
    (
        "PUT",
        "/maps/new1",
        {"content": b'{"tsdf": {"truncation": Infinity}}', "headers": {"content-type": "application/json"}},
        422,
        "finite",
    ),
    ("PUT", "/maps/new1", {"json": [1, 2]}, 422, "body"),
    (
        "PUT",
        "/maps/new1",
        {"content": b"{not json", "headers": {"content-type": "application/json"}},
        422,
        "JSON",
    ),
    (
        "PUT",
        "/maps/new1",
        {"content": b"x" * 300_000, "headers": {"content-type": "application/json"}},
        413,
        "",
    ),
    # snapshot uploads: what is not a snapshot, and what the service could not have written
    ("PUT", SNAP, {"content": snapshot_body([1, 2], ARRAYS)}, 422, "map.json holds a JSON list"),
    ("PUT", SNAP, {"content": snapshot_body('"x"', ARRAYS)}, 422, "map.json holds a JSON str"),
    ("PUT", SNAP, {"content": snapshot_body(b"\xff\xfe{", ARRAYS)}, 422, "map.json is not valid JSON"),
    ("PUT", SNAP, snap(keys=np.array([1, 2, 3])), 422, "keys.npy has shape (3,)"),
    ("PUT", SNAP, snap(keys=np.array(5)), 422, "keys.npy has shape ()"),
    ("PUT", SNAP, {"content": corrupt_deflate()}, 422, "corrupt"),
    ("PUT", SNAP, snap(keys=ARRAYS["keys"] + 2**40), 422, "world bound"),
    ("PUT", SNAP, snap(keys=ARRAYS["keys"] + 0.5), 422, "expected integers"),
    ("PUT", SNAP, snap(keys=np.repeat(ARRAYS["keys"][:1], TILES, axis=0)), 422, "twice"),
    ("PUT", SNAP, snap(log_odds=cells("log_odds", np.inf)), 422, "log_odds must be NaN (unknown) or within"),
    ("PUT", SNAP, snap(log_odds=cells("log_odds", 50.0)), 422, "the map's clamp"),
    ("PUT", SNAP, snap(tsdf_weight=cells("tsdf_weight", -5.0)), 422, "tsdf_weight must be finite and >= 0"),
    ("PUT", SNAP, snap(tsdf_weight=cells("tsdf_weight", np.nan)), 422, "tsdf_weight must be"),
    ("PUT", SNAP, snap(tsdf=cells("tsdf", 1.5)), 422, "tsdf must be within [-1, 1]"),
    (
        "PUT",
        SNAP,
        snap(hits=ARRAYS["hits"].astype(np.float64)),
        422,
        "hits.npy has dtype float64, expected uint32",
    ),
    (
        "PUT",
        SNAP,
        snap(hits=ARRAYS["hits"][:1]),
        422,
        f"hits.npy has shape (1, 16, 16), expected ({TILES}, 16, 16)",
    ),
    ("PUT", SNAP, {"content": snapshot_body(META, npz=b"garbage")}, 422, "tiles.npz is not a valid .npz"),
    (
        "PUT",
        SNAP,
        {"content": snapshot_body(META, npz=npz_member("hits.npy", b"garbage"))},
        422,
        "not a valid .npy",
    ),
    (
        "PUT",
        SNAP,
        {"content": snapshot_body(META, npz=npz_member("hits.npy", npy_with_header(UNTERMINATED)))},
        422,
        "not a valid .npy",
    ),
    (
        "PUT",
        SNAP,
        {"content": snapshot_body(META, npz=declare_size(npz_member(), "tsdf.npy", 2**32 - 2))},
        422,
        "bytes of data, its shape and dtype need",
    ),
    (
        "PUT",
        SNAP,
        {"content": snapshot_body(json.dumps(META) + " " * MAX_SNAPSHOT_META_BYTES, ARRAYS, deflate=True)},
        413,
        f"map.json is {len(json.dumps(META)) + MAX_SNAPSHOT_META_BYTES} bytes decompressed, more than",
    ),
    # scans
    ("POST", SCAN, {"content": b"{not json", "headers": {"content-type": "application/json"}}, 422, "JSON"),
    ("POST", SCAN, {"json": {"seq": "one"}}, 422, "seq"),
    ("POST", SCAN, {"json": {**good_scan(), "ranges": "far"}}, 422, "ranges"),
    ("POST", SCAN, {"json": {**good_scan(), "seq": -1}}, 422, "seq"),
    ("POST", SCAN, {"json": {**good_scan(), "pose": {"x": 0, "y": 0}}}, 422, "theta"),
    ("POST", SCAN, {"json": {**good_scan(), "angles": [0.0]}}, 422, "angles"),
    (
        "POST",
        SCAN,
        {
            "content": b'{"seq": 1, "pose": {"x": NaN, "y": 0, "theta": 0}, "angle_min": 0, '
            b'"angle_increment": 0.1, "ranges": [1]}',
            "headers": {"content-type": "application/json"},
        },
        422,
        "finite",
    ),
    ("POST", SCAN, {"content": b"FMS1garbage", "headers": {"content-type": BINARY_ENCODING}}, 422, "binary"),
    # A media type the route does not read (it was a 422 "unknown encoding", as for a bad scan).
    (
        "POST",
        SCAN,
        {"content": b"hello", "headers": {"content-type": "text/plain"}},
        415,
        "unknown encoding 'text/plain'; use application/json or application/x-fleetmap-scan",
    ),
    ("POST", SCAN, {"content": b"", "headers": {"content-type": "application/json"}}, 422, "JSON"),
    ("POST", SCAN, {"content": b"x" * 300_000, "headers": {"content-type": "application/json"}}, 413, ""),
    # one cell
    ("GET", "/maps/e/cell?x=nan&y=0", {}, 422, "'x'"),
    ("GET", "/maps/e/cell?x=0&y=inf", {}, 422, "'y'"),
    ("GET", "/maps/e/cell?x=-Infinity&y=0", {}, 422, "'x'"),
    ("GET", "/maps/e/cell?x=abc&y=0", {}, 422, "'x'"),
    ("GET", "/maps/e/cell?x=1e300&y=0", {}, 422, "'x'"),
    ("GET", "/maps/e/cell?y=0", {}, 422, "'x' is required"),
    # many cells
    (
        "POST",
        "/maps/e/cells",
        {"content": b"[[1, 2]", "headers": {"content-type": "application/json"}},
        422,
        "JSON",
    ),
    ("POST", "/maps/e/cells", {"json": {"points": "abc"}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [[1]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [[1, 2, 3]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [["a", "b"]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [[0, None]]}}, 422, "points"),
    (
        "POST",
        "/maps/e/cells",
        {"content": b'{"points": [[NaN, 0]]}', "headers": {"content-type": "application/json"}},
        422,
        "points",
    ),
    ("POST", "/maps/e/cells", {"json": {"points": [[1e12, 0]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"pts": [[0, 0]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [[0.0, False]]}}, 422, "points"),
    ("POST", "/maps/e/cells", {"json": {"points": [["1", "2"]]}}, 422, "points"),
    (
        "POST",
        "/maps/e/cells",
        {"content": b"\xff\xfe{", "headers": {"content-type": "application/json"}},
        422,
        "JSON",
    ),
    ("POST", "/maps/e/cells", {"json": {"points": [[0.5, 0.5]] * 1001}}, 413, "1000"),
    ("POST", "/maps/e/cells", {"json": {"points": [[0.5, 0.5]] * 20_000}}, 413, ""),  # > max_body_bytes
    # regions
    ("GET", R + "&layer=volume", {}, 422, "volume"),
    ("GET", R + "&format=tiff", {}, 422, "tiff"),
    ("GET", "/maps/e/region?xmin=0&ymin=0&xmax=1", {}, 422, "all of xmin"),
    ("GET", "/maps/e/region?xmin=1&ymin=0&xmax=1&ymax=1", {}, 422, "no cell"),
    ("GET", "/maps/e/region?xmin=2&ymin=0&xmax=1&ymax=1", {}, 422, "no cell"),
    ("GET", "/maps/e/region?xmin=nan&ymin=0&xmax=1&ymax=1", {}, 422, "xmin"),
    ("GET", "/maps/e/region?xmin=-100&ymin=-100&xmax=100&ymax=100", {}, 413, "limit"),
    ("GET", "/maps/e/region?xmin=0&ymin=0&xmax=10&ymax=10&format=json", {}, 413, "limit"),
    ("GET", "/maps/tsdf/region?layer=probability", {}, 422, "occupancy"),
    ("GET", "/maps/occ/region?layer=tsdf", {}, 422, "tsdf"),
    ("GET", "/maps/empty/region", {}, 409, "no observed cell"),
    ("GET", "/maps/occ/surface", {}, 422, "tsdf"),
    ("GET", "/maps/e/surface?xmin=0", {}, 422, "all of xmin"),
    # tiles
    ("GET", TILE + "/99/0/0.png", {}, 422, "'z'"),
    ("GET", TILE + "/-9/0/0.png", {}, 422, "'z'"),
    ("GET", TILE + "/abc/0/0.png", {}, 422, "'z'"),
    ("GET", TILE + "/0/1.5/0.png", {}, 422, "'x'"),
    ("GET", TILE + "/0/0/" + str(2**60) + ".png", {}, 422, "cell range"),
    ("GET", TILE + "/0/0/0.png?layer=volume", {}, 422, "volume"),
    ("GET", "/maps/occ/tiles/0/0/0.png?layer=tsdf", {}, 422, "tsdf"),
    ("GET", TILE + "/0/0/0.jpg", {}, 404, ""),
    # export, events
    ("GET", "/maps/e/export?format=tiff", {}, 422, "tiff"),
    ("GET", "/maps/e/export?margin=-1", {}, 422, "margin"),
    # Not finite, as every number parameter says (nan was "Input should be greater than 0").
    ("GET", "/maps/e/export?resolution=nan", {}, 422, "resolution': Input should be a finite number"),
    ("GET", "/maps/e/export?resolution=inf", {}, 422, "resolution': Input should be a finite number"),
    ("GET", "/maps/e/export?resolution=1e400", {}, 422, "resolution': Input should be a finite number"),
    ("GET", "/maps/tsdf/export", {}, 422, "occupancy"),
    ("GET", "/maps/empty/export", {}, 409, "no observed cell"),
    ("GET", "/maps/e/events?since=-1", {}, 422, "since"),
    ("GET", "/maps/bad!/events", {}, 422, "not a valid id"),
    # routing
    ("GET", "/nowhere", {}, 404, "/nowhere"),
    ("POST", "/healthz", {}, 405, "method POST is not allowed on /healthz"),
    ("DELETE", "/maps", {}, 405, ""),
    ("OPTIONS", "/maps/e", {}, 405, "allowed: DELETE, GET, HEAD, PUT"),
]


def maps_without_rejections(c: httpx.Client) -> list[dict[str, Any]]:
    """GET /maps minus the rejection counters (which refused scans legitimately raise)."""
    return [{k: v for k, v in m.items() if k != "scans_rejected"} for m in c.get("/maps").json()["maps"]]


def test_every_bad_request_is_a_clear_4xx_and_changes_nothing(api: RunningApi) -> None:
    c = api.client
    before_maps = maps_without_rejections(c)
    before_cells = c.get("/maps/e/region", params={"layer": "log_odds"}).content
    before_robot = c.get("/maps/e").json()["stats"]["robots"]["r"]
    rejected_scans = 0
    for method, path, kwargs, status, word in CASES:
        r = c.request(method, path, **kwargs)
        where = f"{method} {path[:80]} -> {r.status_code} {r.text[:300]}"
        assert r.status_code == status, where
        assert r.headers["content-type"] == "application/json", where
        detail = r.json()["detail"]
        assert isinstance(detail, str) and detail, where
        assert word.lower() in detail.lower(), where
        if path == SCAN and status in (415, 422):  # refused by the codec: counted on robot "r"
            rejected_scans += 1
    # Nothing changed: the same maps (none created by a refused PUT), the same cells; the refused
    # scans are only counted (and the last reason kept) on the robot, as Zenoh messages would be.
    assert maps_without_rejections(c) == before_maps
    assert c.get("/maps/e/region", params={"layer": "log_odds"}).content == before_cells
    robot = c.get("/maps/e").json()["stats"]["robots"]["r"]
    assert robot["scans_integrated"] == before_robot["scans_integrated"]
    assert robot["last_seq"] == before_robot["last_seq"]
    assert robot["scans_rejected"] == before_robot["scans_rejected"] + rejected_scans
    assert robot["last_error"]


def test_an_empty_window_is_refused_naming_the_cells_its_bounds_make(api: RunningApi) -> None:
    """A window is `[floor(xmin/res), floor(xmax/res))`: at 0.05 m, bounds 0.045 m apart (0.04 and
    0.085) make a window of one column, and bounds 0.039 m apart (0.01 and 0.049) none. The refusal
    said "xmax must be at least one cell beyond xmin", wrong both ways; it names the cells the bounds
    make, for GET and DELETE alike."""
    c = api.client
    one = c.get(
        "/maps/e/region", params={"xmin": 0.04, "ymin": 0.0, "xmax": 0.085, "ymax": 1.0, "layer": "hits"}
    )
    assert one.status_code == 200 and one.headers["x-fleetmap-window"] == "0,0,1,20"
    none = {"xmin": 0.01, "ymin": 0.0, "xmax": 0.049, "ymax": 1.0}
    for r in (
        c.get("/maps/e/region", params={**none, "layer": "hits"}),
        c.delete("/maps/e/region", params=none),
    ):
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert "the window holds no cell" in detail and "[0, 0) x [0, 20)" in detail, detail
        assert "at least one cell beyond" not in detail


def test_a_region_of_a_layer_the_map_does_not_keep_is_refused_saying_so_whatever_its_window(
    api: RunningApi,
) -> None:
    """A region of a layer the map does not keep is a 422 saying so, whatever the window: the window
    was judged first, so a TSDF-only map's `state` was a 409 telling the client to give bounds (on an
    empty map), a 413 to ask for smaller windows, or a 422 naming the window's cells, and the client
    who followed that advice got another refusal for the same reason it had not been told."""
    c = api.client
    assert c.put("/maps/tsdf-empty", json={"layers": ["tsdf"]}).status_code == 201
    try:
        for path, params in (
            ("/maps/tsdf-empty/region", {}),  # no bounds on a map with no observed cell
            ("/maps/tsdf/region", {"xmin": -100, "ymin": -100, "xmax": 100, "ymax": 100}),  # past the limit
            ("/maps/tsdf/region", {"xmin": 1, "ymin": 0, "xmax": 1, "ymax": 1}),  # no cell
        ):
            r = c.get(path, params={**params, "layer": "state"})
            assert r.status_code == 422, (path, params, r.text)
            assert "needs the 'occupancy' layer" in r.json()["detail"], (path, params, r.text)
    finally:
        assert c.delete("/maps/tsdf-empty").status_code == 204


def test_validation_errors_list_every_problem(api: RunningApi) -> None:
    r = api.client.get(
        "/maps/e/region", params={"xmin": "a", "ymin": "b", "xmax": 1, "ymax": 1, "layer": "x"}
    )
    body = r.json()
    assert r.status_code == 422 and "(and 2 more problems)" in body["detail"]
    assert [e["loc"] for e in body["errors"]] == [["query", "xmin"], ["query", "ymin"], ["query", "layer"]]


def test_a_snapshot_with_an_invalid_configuration_lists_every_problem(api: RunningApi) -> None:
    """As for PUT /maps: one line naming the first problem, and every problem in `errors` (not
    pydantic's text, with its URLs), located in the file."""
    meta = {**META, "config": {**META["config"], "resolution": -1, "max_tiles": 0}}
    r = api.client.put(SNAP, content=snapshot_body(meta, ARRAYS))
    body = r.json()
    assert r.status_code == 422, body
    assert body["detail"] == (
        "snapshot map.json.config.resolution: Input should be greater than 0.001 (and 1 more problem)"
    )
    assert [e["loc"] for e in body["errors"]] == [
        ["map.json", "config", "resolution"],
        ["map.json", "config", "max_tiles"],
    ]
    assert api.client.get("/maps/e").json()["stats"]["robots"]  # map e is still the one it was


def test_binary_scan_and_duplicates_over_http(api: RunningApi) -> None:
    scan = fan_scan(0.0, 0.0, 0.0, [1.0] * 61)
    body = encode_binary(scan, 7)
    url = "/maps/e/scans?robot_id=bin"
    r = api.client.post(url, content=body, headers={"content-type": BINARY_ENCODING})
    assert r.status_code == 200 and r.json()["status"] == "integrated" and r.json()["seq"] == 7
    r = api.client.post(url, content=body, headers={"content-type": BINARY_ENCODING})
    assert (
        r.status_code == 200 and r.json()["status"] == "duplicate" and "duplicate seq 7" in r.json()["detail"]
    )
    # Without a content type, the payload is recognised by its content.
    r = api.client.post(url, content=encode_binary(scan, 8))
    assert r.status_code == 200 and r.json()["status"] == "integrated"


def test_full_queue_is_503() -> None:
    """A robot whose FIFO is full gets 503 (the scan is dropped and counted). No worker runs here,
    so the FIFO of one slot stays full; the queued POST itself times out with 503 too."""
    with running_api(ApiSettings(scan_timeout=0.5), workers=0, queue_per_robot=1) as api:
        scan = encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 5), 0)
        url = f"{api.base_url}/maps/q/scans?robot_id=r"
        with httpx.Client(timeout=10) as c1:
            first = c1.post(url, content=scan, headers={"content-type": "application/json"})
            assert first.status_code == 503 and "not integrated within 0.5 s" in first.json()["detail"]
            second = c1.post(
                url,
                content=encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 5), 1),
                headers={"content-type": "application/json"},
            )
            assert second.status_code == 503 and "queue full" in second.json()["detail"]
            # Every 503 says when to retry, as proxies and HTTP clients (urllib3's Retry) read it.
            assert first.headers["retry-after"] == second.headers["retry-after"] == "1"
        robot = api.client.get("/maps/q").json()["stats"]["robots"]["r"]
        assert robot["dropped"] == 1 and robot["scans_integrated"] == 0


def test_a_new_robot_on_a_full_map_is_429_and_the_spec_says_so() -> None:
    """A map whose every robot is online has no room for a new one: its scan is refused with 429
    (docs/protocol.md, "Sessions"). The spec of `POST /scans` listed no 429, and the only 429 it
    described was a sign-in's ("too many failed attempts from this client address")."""
    with running_api(max_robots_per_map=1) as api:
        api.registry.set_online("full", "a", True)
        url = "/maps/full/scans?robot_id=b"
        r = api.client.post(url, content=encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 5), 0))
        assert r.status_code == 429 and "already has 1 robots" in r.json()["detail"]
        spec = api.client.get("/openapi.json").json()
        answers = spec["paths"]["/maps/{map_id}/scans"]["post"]["responses"]
        assert "429" in answers and "robot" in answers["429"]["description"]
        assert "sign-in" not in answers["429"]["description"]


def test_a_snapshot_upload_may_be_larger_than_other_bodies() -> None:
    """The snapshot of a map of a few hundred tiles is over 16 MiB (the Freiburg campus log: 342
    tiles, 17.8 MB): every body, snapshots included, was held to `max_body_bytes`, so the service
    refused with 413 a file it had written itself, whose arrays were far under the upload's limit
    (docs/api.md). Snapshot uploads have their own limit; other bodies keep theirs. (What the limits
    are by default: test_snapshot_downloads.py.)"""
    gmap = GridMap(MapConfig(resolution=0.05))
    for scan in room_scans(5):
        gmap.integrate(scan)
    meta, arrays = snapshot_parts(snapshot_file("s", gmap))
    stored = io.BytesIO()
    np.savez(stored, **arrays)  # not compressed: a file bigger than max_body_bytes
    body = snapshot_body(meta, npz=stored.getvalue())
    settings = ApiSettings(max_body_bytes=200_000, max_snapshot_body_bytes=len(body) + 1000)
    assert len(body) > settings.max_body_bytes
    with running_api(settings) as api:
        put = api.client.put("/maps/big/snapshot", content=body, headers={"content-type": "application/zip"})
        assert put.status_code == 201, put.text
        assert api.client.get("/maps/big").json()["stats"]["tiles"] == len(arrays["keys"])
        over = body + b"\0" * 2000  # past the snapshot limit: refused before it is read
        put = api.client.put("/maps/big/snapshot", content=over, headers={"content-type": "application/zip"})
        assert put.status_code == 413 and str(len(body) + 1000) in put.json()["detail"]
        # Another body as big as the snapshot is still held to max_body_bytes.
        r = api.client.put("/maps/other", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 413 and "200000" in r.json()["detail"]


# -- fuzzing: whatever the query, never a 500 ---------------------------------------------------------

_TEXT = st.text(alphabet=string.printable + "é∞", max_size=12)
_NUMBERISH = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(2**70), max_value=2**70).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e309", "", " ", "0x10", "1_000", "--1"]),
    _TEXT,
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    endpoint=st.sampled_from(["cell", "region", "surface", "tile", "export", "events"]),
    values=st.lists(_NUMBERISH, min_size=6, max_size=6),
    layer=st.one_of(st.sampled_from(["probability", "state", "hits", "tsdf"]), _TEXT),
)
def test_fuzzed_queries_never_500(api: RunningApi, endpoint: str, values: list[str], layer: str) -> None:
    a, b, cc, d, e, f = values
    params: dict[str, str] = {}
    if endpoint == "cell":
        path, params = "/maps/e/cell", {"x": a, "y": b}
    elif endpoint in ("region", "surface"):
        path, params = (
            f"/maps/e/{endpoint}",
            {"xmin": a, "ymin": b, "xmax": cc, "ymax": d, "layer": layer, "format": e},
        )
    elif endpoint == "tile":
        path, params = (
            f"/maps/e/tiles/{a}/{b}/{cc}.png".replace("#", "%23").replace("?", "%3F"),
            {"layer": layer},
        )
    elif endpoint == "export":
        path, params = "/maps/e/export", {"format": layer, "margin": a}
    else:
        path, params = "/maps/e/events", {"since": a}
    try:
        # Streamed, and closed after the first bytes: a valid event stream never ends by itself.
        with api.client.stream("GET", path, params=params) as r:
            if r.status_code == 200 and endpoint == "events":
                assert next(r.iter_text()).startswith("retry:")
                return
            r.read()
    except httpx.InvalidURL:
        return  # httpx refuses to send it: nothing reached the server
    assert r.status_code < 500, (path, params, r.text)
    if r.status_code >= 400:
        assert isinstance(r.json()["detail"], str)
    elif endpoint == "region" and r.headers["content-type"] == "application/octet-stream":
        assert np.load(io.BytesIO(r.content)).ndim == 2


def test_a_last_event_id_that_int_refuses_opens_the_stream(api: RunningApi) -> None:
    """`Last-Event-ID` is whatever the client sends: a superscript digit (latin-1 byte 0xB2, which
    `str.isdigit` takes and `int` refuses) is no id this service sent, so the stream starts from now
    (its first event is `robots`); a number of 5000 digits (past `int`'s 4300) is beyond every
    version, so the stream starts with a reset. Neither is a 500."""
    version = api.client.get("/maps/e").json()["stats"]["version"]
    for header, first in [(b"\xb2", "robots"), (b"9" * 5000, "tiles")]:
        with api.client.stream("GET", "/maps/e/events", headers={"Last-Event-ID": header}) as r:
            assert r.status_code == 200, r.read()
            lines = r.iter_lines()
            event = next(line for line in lines if line.startswith("event:"))
            assert event == f"event: {first}"
            if first == "tiles":
                assert json.loads(next(lines).removeprefix("data: ")) == {"version": version, "reset": True}


def test_the_services_input_limits_hold_over_rest_as_over_zenoh(tmp_path: Path) -> None:
    """`serve --max-beams / --world-bound / --max-range` are the registry's (`MapRegistry.input_limits`),
    which POST /maps/{id}/scans decodes with, as Zenoh ingest does: a scan past them is a 422 naming
    the limit in force, not the default's, and a return at or past --max-range is no return."""
    args = ["--in-memory", "--max-beams", "10", "--world-bound", "100", "--max-range", "5"]
    with ServiceProcess(tmp_path, args) as service, httpx.Client(base_url=service.base_url) as client:
        assert client.put("/maps/lim", json={"resolution": 0.05}).status_code == 201

        seqs = iter(range(100))

        def post(scan: Scan) -> httpx.Response:
            return client.post(
                "/maps/lim/scans", params={"robot_id": "r"}, content=encode_binary(scan, next(seqs)),
                headers={"content-type": BINARY_ENCODING},
            )  # fmt: skip

        r = post(fan_scan(0.0, 0.0, 0.0, [1.0] * 11, range_max=30.0))
        assert r.status_code == 422 and "11 beams is more than the limit of 10" in r.json()["detail"], r.text
        r = post(fan_scan(150.0, 0.0, 0.0, [1.0], range_max=30.0))
        assert r.status_code == 422 and "world bound of +-100 m" in r.json()["detail"], r.text
        # Two beams along +x and +y: a return at 3 m, and one at 8 m, past --max-range 5.
        r = post(Scan.from_angles((0.0, 0.0, 0.0), [0.0, math.pi / 2], [3.0, 8.0], 0.0, 30.0))
        assert r.status_code == 200, r.text
        points = [[3.01, 0.01], [0.01, 8.01], [0.01, 4.0]]
        cells = client.post("/maps/lim/cells", json={"points": points}).json()
        # The 3 m return is a hit; the 8 m one is ignored whole (no return, no clearing by default).
        assert cells["state"] == ["occupied", "unknown", "unknown"], cells
