"""The REST API end to end: a real uvicorn server on 127.0.0.1 (see test_api_support), real HTTP.

What the service answers is compared with an engine `GridMap` fed the same scans in the same order,
cell by cell and field by field, so the API adds nothing and loses nothing.
"""

from __future__ import annotations

import io
import json
import logging
import math
import queue
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from PIL import Image
from prometheus_client.parser import text_string_to_metric_families
from test_api_support import RunningApi, fan_scan, room_scans, running_api

from fleetmap import codec as codec_module
from fleetmap.api import ApiSettings, routes_maps
from fleetmap.api_models import cells_json, cells_response
from fleetmap.codec import decode, encode_binary, encode_json
from fleetmap.config import MapConfig
from fleetmap.export import PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN, state_to_pgm
from fleetmap.grid_map import REGION_LAYERS, STATE_NAMES, GridMap, cell_edge
from fleetmap.scan import Scan
from fleetmap.tiles import SLOT_OVERHEAD
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING

RES = 0.05
CONFIG = {"resolution": RES, "tile_size": 64}


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningApi]:
    web = tmp_path_factory.mktemp("web")
    (web / "index.html").write_text("<!doctype html><title>viewer under test</title>")
    (web / "app.js").write_text("console.log('app under test');")
    # A short keepalive so event readers (below) see a line at least every 0.3 s and can stop promptly.
    settings = ApiSettings(web_dir=web, zenoh_status=lambda: {"mode": "router", "test": True}, keepalive=0.3)
    with running_api(settings) as running:
        yield running


def post_scan(
    api: RunningApi, map_id: str, robot: str, scan: Scan, seq: int, binary: bool = False
) -> httpx.Response:
    body = encode_binary(scan, seq) if binary else encode_json(scan, seq)
    return api.client.post(
        f"/maps/{map_id}/scans",
        params={"robot_id": robot},
        content=body,
        headers={"content-type": BINARY_ENCODING if binary else JSON_ENCODING},
    )


def same_float(a: float | None, b: float) -> bool:
    """JSON null stands for NaN."""
    return (a is None and math.isnan(b)) or (a is not None and a == b)


# -- lifecycle ----------------------------------------------------------------------------------------


def test_map_lifecycle(api: RunningApi) -> None:
    c = api.client
    r = c.put("/maps/life", json={"resolution": 0.1, "layers": ["occupancy"]})
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["id"] == "life" and info["resolution"] == 0.1 and info["config"]["layers"] == ["occupancy"]
    stats = info["stats"]
    assert (stats["scans_integrated"], stats["scans_rejected"], stats["robots"]) == (0, 0, {})
    assert (stats["bounds"], stats["tiles"], stats["memory_bytes"]) == (None, 0, 0)
    # Change versions start above any an earlier map of this id, or an earlier process, gave out.
    assert stats["version"] > 10**15
    # Same configuration, written out differently (a preset named, defaults explicit): 200, unchanged.
    r = c.put(
        "/maps/life", json={"resolution": 0.1, "layers": ["occupancy"], "occupancy": {"preset": "octomap"}}
    )
    assert r.status_code == 200 and r.json()["config"] == info["config"]
    r = c.put("/maps/life", json={"resolution": 0.2})
    assert r.status_code == 409 and "different configuration" in r.json()["detail"]
    assert c.get("/maps/life").json()["config"]["resolution"] == 0.1  # the conflict changed nothing

    listed = {m["id"]: m for m in c.get("/maps").json()["maps"]}
    assert listed["life"]["layers"] == ["occupancy"] and listed["life"]["scans_integrated"] == 0

    r = c.delete("/maps/life")
    assert r.status_code == 204 and r.content == b""
    for method, path in [
        ("GET", "/maps/life"),
        ("DELETE", "/maps/life"),
        ("GET", "/maps/life/cell?x=0&y=0"),
        ("GET", "/maps/life/region?format=json"),
        ("GET", "/maps/life/tiles/0/0/0.png"),
        ("GET", "/maps/life/export"),
        ("GET", "/maps/life/events"),
        ("GET", "/maps/life/surface"),
    ]:
        r = c.request(method, path)
        assert r.status_code == 404, (method, path, r.text)
        assert r.json()["detail"] == "no map 'life'"
    r = c.post("/maps/life/cells", json={"points": [[0, 0]]})
    assert r.status_code == 404
    assert "life" not in {m["id"] for m in c.get("/maps").json()["maps"]}

    # No body: the server's default configuration.
    r = c.put("/maps/defaults")
    assert r.status_code == 201 and MapConfig.model_validate(r.json()["config"]) == MapConfig()


def test_a_configuration_with_its_layers_in_another_order_is_the_same(api: RunningApi) -> None:
    """`layers` is a set of layers (no layer twice): listed in another order they keep the same map.
    `PUT` with them so was a 409, "exists with a different configuration": a provisioning script that
    builds its list from a Python set (whose order changes from one process to the next) failed at
    random on its second run. The map keeps the order it was made with; other layers are a 409."""
    c = api.client
    made = c.put("/maps/order", json={"resolution": 0.1, "layers": ["tsdf", "occupancy"]})
    assert made.status_code == 201, made.text
    again = c.put("/maps/order", json={"resolution": 0.1, "layers": ["occupancy", "tsdf"]})
    assert again.status_code == 200, again.text
    assert again.json()["config"] == made.json()["config"]
    assert again.json()["config"]["layers"] == ["tsdf", "occupancy"]
    for layers in (["occupancy"], ["occupancy", "tsdf", "counts"], ["counts", "tsdf"]):
        r = c.put("/maps/order", json={"resolution": 0.1, "layers": layers})
        assert r.status_code == 409 and "different configuration" in r.json()["detail"], layers
    r = c.put("/maps/order", json={"resolution": 0.2, "layers": ["occupancy", "tsdf"]})
    assert r.status_code == 409


def test_a_preset_and_its_values_written_out_are_the_same_configuration(api: RunningApi) -> None:
    """Configurations compare after presets are resolved (docs/api.md, `PUT /maps/{map_id}`): a map
    made with the `int8` preset is the map of its four values written out, under any preset name
    (the values given override the preset's), and the other way round. The preset's name took part
    in the comparison, so such a `PUT` was a 409, "exists with a different configuration", for a map
    whose every cell it would have updated alike. Another value, or other thresholds, stay a 409."""
    c = api.client
    int8 = {"l_hit": 9.0, "l_miss": -9.0, "l_min": -128.0, "l_max": 127.0}
    made = c.put("/maps/preset", json={"resolution": 0.1, "occupancy": {"preset": "int8"}})
    assert made.status_code == 201, made.text
    for written in (int8, {**int8, "preset": "cartographer"}):
        again = c.put("/maps/preset", json={"resolution": 0.1, "occupancy": written})
        assert again.status_code == 200, (written, again.text)
        assert again.json()["config"] == made.json()["config"]  # the map as it was made
    written_out = c.put("/maps/written", json={"resolution": 0.1, "occupancy": int8})
    assert written_out.status_code == 201, written_out.text
    named = c.put("/maps/written", json={"resolution": 0.1, "occupancy": {"preset": "int8"}})
    assert named.status_code == 200, named.text
    assert named.json()["config"]["occupancy"]["preset"] == "octomap"  # as it was made
    for other in ({**int8, "l_hit": 8.0}, {"preset": "int8", "occupied_thresh": 0.7}, {"preset": "coursera"}):
        r = c.put("/maps/preset", json={"resolution": 0.1, "occupancy": other})
        assert r.status_code == 409 and "different configuration" in r.json()["detail"], other
    assert c.get("/maps/preset").json()["config"] == made.json()["config"]


def test_a_conflicting_configuration_is_refused_naming_what_differs(api: RunningApi) -> None:
    """A `PUT` of another configuration than the map's is a 409 that says which fields differ, and
    how: it said only "exists with a different configuration", and the difference may be invisible
    in the body sent (`{}` against a map a robot's scan made with the server's `--config`, a p_hit
    whose log-odds differ from the map's in the 16th digit). The preset's name and the order of the
    layers, which make no other map, are not differences."""
    c = api.client
    made = c.put(
        "/maps/differs",
        json={"resolution": 0.1, "layers": ["tsdf", "occupancy"], "occupancy": {"preset": "int8"}},
    )
    assert made.status_code == 201, made.text
    other = {
        "resolution": 0.2,
        "layers": ["occupancy", "tsdf"],
        "occupancy": {"preset": "coursera", "l_hit": 9.0, "l_miss": -9.0, "l_min": -128.0, "l_max": 100.0},
        "tsdf": {"max_weight": 5.0},
    }
    r = c.put("/maps/differs", json=other)
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert "different configuration" in detail
    for difference in (
        "resolution 0.1, not 0.2",
        "occupancy.l_max 127.0, not 100.0",
        "tsdf.max_weight 1000.0, not 5.0",
    ):
        assert difference in detail, (difference, detail)
    assert "layers" not in detail and "preset" not in detail and "l_hit" not in detail, detail
    r = c.put("/maps/differs", json={"resolution": 0.1, "layers": ["tsdf"], "occupancy": {"preset": "int8"}})
    assert r.status_code == 409 and "layers ['tsdf', 'occupancy'], not ['tsdf']" in r.json()["detail"], r.text


def test_an_invalid_configuration_is_located_at_its_fields(api: RunningApi) -> None:
    """Each problem of a configuration is located (`errors[].loc`) at the field at fault, as pydantic
    locates a bad type or range, and all are listed: a tile size that is not a power of two, no or
    repeated layers and a band too wide for the resolution were located at the body as a whole,
    and listed only once every field was valid otherwise (a bad resolution hid them)."""
    c = api.client
    cases = [
        ({"tile_size": 100}, [["body", "tile_size"]], "body.tile_size: tile_size must be a power of two"),
        ({"layers": []}, [["body", "layers"]], "body.layers: a map needs at least one layer"),
        ({"layers": ["tsdf", "tsdf"]}, [["body", "layers"]], "body.layers: layers must not repeat"),
        ({"tsdf": {"truncation": 13.0}}, [["body", "tsdf"]], "body.tsdf: tsdf.truncation 13 m is more than"),
        ({"beam": {"alpha": 13.0}}, [["body", "beam"]], "body.beam: beam.alpha 13 m is more than"),
        (
            {"resolution": 0, "tile_size": 100, "layers": []},
            [["body", "resolution"], ["body", "tile_size"], ["body", "layers"]],
            "body.resolution: Input should be greater than 0.001 (and 2 more problems)",
        ),
    ]
    for body, locs, detail in cases:
        r = c.put("/maps/located", json=body)
        assert r.status_code == 422, (body, r.text)
        assert [e["loc"] for e in r.json()["errors"]] == locs, (body, r.text)
        assert r.json()["detail"].startswith(detail), (body, r.text)
    assert c.get("/maps/located").status_code == 404


def test_a_refused_configuration_logs_no_stored_map_loaded(
    api: RunningApi, caplog: pytest.LogCaptureFixture
) -> None:
    """A body with a null band width or weight cap is refused as a new configuration, then tried as
    a stored one (a map stored before today's limits: `fleetmap.api.config_body`), whose loading
    warned "stored map configuration: tsdf.max_weight was infinite (stored as null); loaded as
    1e+30": for each refused PUT, where no stored map was loaded at all. Nothing is logged so now;
    loading a stored map still warns (test_persistence.py)."""
    with caplog.at_level(logging.WARNING, logger="fleetmap.config"):
        for section, name in [("tsdf", "max_weight"), ("tsdf", "truncation"), ("beam", "alpha")]:
            r = api.client.put("/maps/quiet", json={section: {name: None}})
            assert r.status_code == 422 and f"{section}" in r.text, r.text
    assert api.client.get("/maps/quiet").status_code == 404
    assert "stored map configuration" not in caplog.text, caplog.text


def test_a_configuration_takes_numbers_as_json_numbers_only(api: RunningApi) -> None:
    """`{"max_tiles": true}` made a map of at most 1 tile (every scan past its first tile refused),
    `{"resolution": true}` one of 1 m cells and `{"max_tiles": "4096"}` passed as a number: the
    configuration took booleans and strings for numbers, where every other JSON body of the API
    (scans, points) refuses them. Now 422, naming the field, and no map is made. A null or a
    container for the resolution was a 500 (see the cases)."""
    c = api.client
    for config, field in [
        ({"max_tiles": True}, "max_tiles"),
        ({"max_tiles": "4096"}, "max_tiles"),
        ({"max_tiles": 64.0}, "max_tiles"),
        ({"resolution": True}, "resolution"),
        ({"resolution": "0.1"}, "resolution"),
        ({"tsdf": {"truncation": False}}, "truncation"),
        ({"occupancy": {"p_hit": "0.7"}}, "p_hit"),
        # Refused as a new configuration, each was tried as a stored one, whose band limit
        # multiplied the resolution unchecked: None * 256 was a 500.
        ({"resolution": None}, "resolution"),
        ({"resolution": {}}, "resolution"),
        ({"resolution": [0.1]}, "resolution"),
    ]:
        r = c.put("/maps/strict", json=config)
        assert r.status_code == 422 and field in r.text, (config, r.text)
        assert c.get("/maps/strict").status_code == 404
    r = c.put("/maps/strict", json={"resolution": 1, "max_tiles": 64, "tsdf": {"truncation": 2}})
    assert r.status_code == 201 and r.json()["config"]["resolution"] == 1.0, r.text  # an integer is a number
    assert c.delete("/maps/strict").status_code == 204


def test_scan_creates_map_unless_auto_create_is_off(api: RunningApi) -> None:
    scan = fan_scan(0, 0, 0, [1.0] * 31)
    r = post_scan(api, "autocreated", "r1", scan, 0)
    assert r.status_code == 200 and r.json()["status"] == "integrated"
    assert api.client.get("/maps/autocreated").json()["stats"]["scans_integrated"] == 1

    with running_api(auto_create=False) as strict:
        r = post_scan(strict, "nomap", "r1", scan, 0)
        assert r.status_code == 404 and "auto-create is off" in r.json()["detail"]
        assert strict.client.get("/maps").json()["maps"] == []
        assert strict.client.put("/maps/nomap", json={}).status_code == 201
        r = post_scan(strict, "nomap", "r1", scan, 0)
        assert r.status_code == 200 and r.json()["cell_updates"] > 0


def test_a_scan_from_before_its_map_was_deleted_is_a_duplicate_and_creates_no_map(api: RunningApi) -> None:
    """A robot's scan sent again after its map was deleted (a retry, a copy from its cache) is from
    before the deletion: 200 `duplicate`, no map made. Its next scan makes a new map."""
    scan = fan_scan(0, 0, 0, [1.0] * 31)

    def post(seq: int) -> httpx.Response:
        return api.client.post(
            "/maps/buried/scans", params={"robot_id": "r1"}, content=encode_binary(scan, seq, session=99),
            headers={"content-type": BINARY_ENCODING},
        )  # fmt: skip

    assert [post(seq).json()["status"] for seq in range(3)] == ["integrated"] * 3
    assert api.client.delete("/maps/buried").status_code == 204
    r = post(2)
    assert r.status_code == 200 and r.json()["status"] == "duplicate", r.text
    assert "from before map 'buried' was deleted" in r.json()["detail"]
    assert api.client.get("/maps/buried").status_code == 404
    assert post(3).json()["status"] == "integrated"
    assert api.client.get("/maps/buried").json()["stats"]["scans_integrated"] == 1


def test_a_negative_reading_is_ignored_and_the_scan_integrated(api: RunningApi) -> None:
    """Negative readings (error codes in some drivers) are below range_min: ignored, as NaN is,
    while the scan's other beams are integrated. They used to make the whole scan a 422."""
    body = {"seq": 1, "pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -0.2,
            "angle_increment": 0.1, "range_min": 0.05, "range_max": 30.0}  # fmt: skip
    with_negative = api.client.post("/maps/neg1/scans?robot_id=r", json={**body, "ranges": [1.0, -2.0, 1.5]})
    without = api.client.post("/maps/neg2/scans?robot_id=r", json={**body, "ranges": [1.0, 0.0, 1.5]})
    assert with_negative.status_code == without.status_code == 200, with_negative.text
    assert with_negative.json()["cell_updates"] == without.json()["cell_updates"] > 0


def test_a_scan_without_beams_sets_the_robot_s_pose_and_changes_no_cell(api: RunningApi) -> None:
    """docs/protocol.md: a scan of no beams is valid in both encodings, integrated, and moves the
    robot (a pose report from a robot whose laser is off)."""
    for seq, binary in enumerate([False, True]):
        scan = Scan.from_fan((1.5, -2.0 - seq, 0.25), 0.0, 0.01, [], 0.05, 30.0)
        r = post_scan(api, "nobeams", "r", scan, seq, binary=binary)
        assert r.status_code == 200 and r.json()["status"] == "integrated", r.text
        assert r.json()["cell_updates"] == 0 and r.json()["changed_tiles"] == []
        robot = api.client.get("/maps/nobeams").json()["stats"]["robots"]["r"]
        assert robot["last_pose"] == {"x": 1.5, "y": -2.0 - seq, "theta": 0.25}
        assert (robot["last_seq"], robot["scans_integrated"]) == (seq, seq + 1)


def test_healthz_and_static_files(api: RunningApi) -> None:
    c = api.client
    health = c.get("/healthz").json()
    assert health["status"] == "ok" and health["zenoh"] == {"mode": "router", "test": True}
    assert health["queue_depth"] == 0 and health["maps"] == len(c.get("/maps").json()["maps"])
    r = c.get("/")
    assert (
        r.status_code == 200
        and "viewer under test" in r.text
        and r.headers["content-type"].startswith("text/html")
    )
    assert "app under test" in c.get("/static/app.js").text
    r = c.get("/static/missing.js")
    assert r.status_code == 404 and r.json()["detail"]
    leaflet = c.get("/vendor/leaflet/leaflet.js")
    assert leaflet.status_code == 200 and "Leaflet" in leaflet.text[:2000]
    assert c.get("/vendor/leaflet/leaflet.css").status_code == 200
    assert c.get("/vendor/leaflet/images/marker-icon.png").content[:4] == b"\x89PNG"


def test_a_range_request_for_a_viewer_file_gets_the_whole_file(api: RunningApi) -> None:
    """The viewer's files answered a `Range` (Starlette's file responses) where no other answer of
    the service does, and refused a bad one with a plain-text 400 ("Range header: range must be
    requested") or an empty plain-text 416, where every error answer is JSON with a `detail`
    (docs/api.md); a range unit other than bytes (`items=0-1`) was a 400 too, where RFC 9110 (14.2)
    says to ignore it. A `Range` is ignored on them as everywhere else (RFC 9110 allows it): the
    whole file, 200, and no `Accept-Ranges: bytes` inviting one."""
    c = api.client
    for path in ("/", "/static/app.js", "/vendor/leaflet/leaflet.css"):
        whole = c.get(path)
        assert whole.status_code == 200 and whole.headers.get("accept-ranges", "none") == "none", path
        for value in (
            "bytes=0-3",
            "bytes=0-1,5-9",
            "bytes=999999-",
            "bytes=-0",
            "bytes=abc",
            "bytes=5-1",
            "items=0-1",
        ):
            r = c.get(path, headers={"Range": value})
            where = f"{path} Range: {value} -> {r.status_code} {r.headers.get('content-type')}"
            assert r.status_code == 200 and r.content == whole.content, where
            assert "content-range" not in r.headers, where


def test_a_write_to_a_viewer_file_is_a_405_naming_get_and_head(api: RunningApi) -> None:
    """A method the viewer's files do not take (a POST to `/static/app.js`) was a 405 whose `Allow`
    was empty and whose detail ended "allowed: ": the methods were looked for among the app's
    routes at the file's path as the mount sees it (`/app.js`), where none is. RFC 9110 (15.5.6)
    asks a 405 to list what the resource takes: GET and HEAD, as the API's own 405s list theirs."""
    c = api.client
    for path in ("/static/app.js", "/vendor/leaflet/leaflet.js", "/static/missing.js"):
        for method in ("POST", "PUT", "DELETE", "PATCH", "OPTIONS"):
            r = c.request(method, path)
            where = f"{method} {path} -> {r.status_code} {r.text}"
            assert r.status_code == 405 and r.headers["allow"] == "GET, HEAD", where
            assert r.json()["detail"] == f"method {method} is not allowed on {path}; allowed: GET, HEAD", (
                where
            )
    r = c.request("OPTIONS", "/maps/nowhere")  # the API's own, as before
    assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET, HEAD, PUT", r.text


def test_a_viewer_not_installed_is_a_404_for_each_of_its_files(tmp_path: Path) -> None:
    """With the viewer's folder missing ($FLEETMAP_WEB_DIR misspelt, an install without
    clients/web), `/` said so with a 404, but every `/static/...` file was a 500 with a traceback
    in the log (Starlette's check of the folder raised). Each says so now; a folder installed
    after start-up is served."""
    web = tmp_path / "viewer"
    with running_api(ApiSettings(web_dir=web)) as running:
        c = running.client
        for path in ("/", "/static/app.js", "/static/modules/map.js"):
            r = c.get(path)
            assert r.status_code == 404 and "web viewer is not installed" in r.json()["detail"], (
                path,
                r.text,
            )
        web.mkdir()
        (web / "app.js").write_text("console.log('installed later');")
        assert c.get("/static/app.js").text == "console.log('installed later');"
        assert c.get("/static/missing.js").status_code == 404


def test_a_viewer_not_installed_names_the_api_pages_under_the_root_path(tmp_path: Path) -> None:
    """Its 404 said "the API is at /docs", outside the path a proxy serves the service under."""
    with running_api(ApiSettings(web_dir=tmp_path / "viewer"), root_path="/fleetmap") as running:
        for path in ("/", "/static/app.js"):
            detail = running.client.get(path).json()["detail"]
            assert detail.endswith("not found); the API is at /fleetmap/docs"), (path, detail)


# -- scans, cells and regions against the engine -------------------------------------------------------


@pytest.fixture(scope="module")
def engine_map(api: RunningApi) -> GridMap:
    """Map "eng" on the service and the same map built by the engine from the same payloads, in the
    same order: two robots, JSON and binary encodings, scans with no-return beams."""
    assert api.client.put("/maps/eng", json=CONFIG).status_code == 201
    gmap = GridMap(MapConfig(**CONFIG))
    scans = room_scans(10, seed=3, beams=360)
    scans.append(fan_scan(0.5, 0.2, 0.3, [None, 2.0, 4.0, None, 1.5] * 20, fov=2 * math.pi * 0.99))
    for k, scan in enumerate(scans):
        robot, seq, binary = ("r1", k // 2, k % 4 == 0) if k % 2 == 0 else ("r2", k // 2, k % 3 == 0)
        payload = encode_binary(scan, seq) if binary else encode_json(scan, seq)
        r = post_scan(api, "eng", robot, scan, seq, binary)
        assert r.status_code == 200, r.text
        # The engine gets exactly what the service decoded (binary ranges are float32 on the wire).
        expected = gmap.integrate(decode(payload, BINARY_ENCODING if binary else JSON_ENCODING).scan)
        got = r.json()
        assert got["status"] == "integrated" and got["seq"] == seq
        assert got["cell_updates"] == expected.cell_updates and got["tsdf_updates"] == expected.tsdf_updates
        t = gmap.store.tile_size
        assert got["changed_tiles"] == [
            [i * t, j * t, (i + 1) * t, (j + 1) * t] for i, j in sorted(expected.changed_tiles)
        ]
    return gmap


def test_cells_match_engine_cell_by_cell(api: RunningApi, engine_map: GridMap) -> None:
    i0, j0, i1, j1 = engine_map.known_bounds()  # type: ignore[misc]
    info = api.client.get("/maps/eng").json()
    assert info["stats"]["bounds"] == [cell_edge(i, RES) for i in (i0, j0, i1, j1)]  # to the nanometre
    assert info["stats"]["scans_integrated"] == 11 and set(info["stats"]["robots"]) == {"r1", "r2"}
    # Every cell of the observed window and a margin of unknown cells, at cell centres.
    ii, jj = np.meshgrid(np.arange(i0 - 2, i1 + 2), np.arange(j0 - 2, j1 + 2))
    points = np.stack([(ii.ravel() + 0.5) * RES, (jj.ravel() + 0.5) * RES], axis=1)
    r = api.client.post("/maps/eng/cells", json={"points": points.tolist()})
    assert r.status_code == 200
    # Byte for byte what the response model serialises to (the answer is written without it).
    assert r.content == cells_response(engine_map, points).model_dump_json().encode()
    got = r.json()
    want = engine_map.cells(points)
    assert got["count"] == len(points) and got["i"] == ii.ravel().tolist() and got["j"] == jj.ravel().tolist()
    assert got["known"] == want["known"].tolist()
    assert 0 < sum(got["known"]) < len(points)  # both known and unknown cells are compared
    for name in ("log_odds", "tsdf"):
        assert all(same_float(a, b) for a, b in zip(got[name], want[name].tolist(), strict=True)), name
    for name in ("probability", "hits", "misses", "tsdf_weight"):
        assert got[name] == want[name].tolist(), name
    assert got["state"] == [STATE_NAMES[s] for s in want["state"].tolist()]
    unknown = [k for k, known in enumerate(got["known"]) if not known]
    assert {got["probability"][k] for k in unknown} == {0.5} and {got["state"][k] for k in unknown} == {
        "unknown"
    }

    # GET /cell agrees too, at arbitrary (not centred) points, negative ones, and far away.
    rng = np.random.default_rng(1)
    for x, y in [*rng.uniform(-3.3, 3.3, (25, 2)).tolist(), [2.999, -1.999], [-3.0, 2.0], [500.0, -500.0]]:
        cell = api.client.get("/maps/eng/cell", params={"x": x, "y": y}).json()
        one = engine_map.cells(np.array([[x, y]]))
        assert (cell["x"], cell["y"]) == (x, y)
        assert (cell["i"], cell["j"]) == (math.floor(x / RES), math.floor(y / RES))
        assert cell["known"] == bool(one["known"][0])
        assert same_float(cell["log_odds"], float(one["log_odds"][0]))
        assert same_float(cell["tsdf"], float(one["tsdf"][0]))
        assert cell["probability"] == float(one["probability"][0])
        assert cell["state"] == STATE_NAMES[int(one["state"][0])]
        assert (cell["hits"], cell["misses"]) == (int(one["hits"][0]), int(one["misses"][0]))
        assert cell["tsdf_weight"] == float(one["tsdf_weight"][0])


@pytest.mark.parametrize("layers", [["occupancy", "counts", "tsdf"], ["occupancy"], ["counts"], ["tsdf"]])
def test_cells_json_is_the_response_models_json_byte_for_byte(layers: list[str]) -> None:
    """POST /cells writes its answer straight from the arrays (cells_json); it must be exactly the JSON
    of the documented CellsResponse: the same float text, null for NaN, null for layers not kept."""
    gmap = GridMap(MapConfig(resolution=RES, tile_size=64, layers=layers))  # type: ignore[arg-type]
    for scan in room_scans(6, seed=4, beams=200):
        gmap.integrate(scan)
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.uniform(-4, 4, (3000, 2)), [[1e6, -1e6], [-0.0, 0.0]]])
    for pts in (points, points[:1], points[:0]):
        assert cells_json(gmap, pts) == cells_response(gmap, pts).model_dump_json().encode()


def test_region_npy_json_png_match_engine(api: RunningApi, engine_map: GridMap) -> None:
    i0, j0, i1, j1 = engine_map.known_bounds()  # type: ignore[misc]
    i0, j0, i1, j1 = i0 - 3, j0 - 2, i1 + 1, j1 + 4  # unknown margins, uneven
    # Bounds at cell centres: floor(x / res) is then exactly the intended index.
    bounds = {
        "xmin": (i0 + 0.5) * RES,
        "ymin": (j0 + 0.5) * RES,
        "xmax": (i1 + 0.5) * RES,
        "ymax": (j1 + 0.5) * RES,
    }
    for layer in REGION_LAYERS:
        want = engine_map.region(layer, i0, j0, i1, j1)
        r = api.client.get("/maps/eng/region", params={**bounds, "layer": layer, "format": "npy"})
        assert r.status_code == 200 and r.headers["x-fleetmap-window"] == f"{i0},{j0},{i1},{j1}"
        got = np.load(io.BytesIO(r.content), allow_pickle=False)
        assert got.shape == (j1 - j0, i1 - i0) and got.dtype == want.dtype
        assert np.array_equal(got, want, equal_nan=True), layer

        r = api.client.get("/maps/eng/region", params={**bounds, "layer": layer, "format": "json"})
        body = r.json()
        assert body["window"] == [i0, j0, i1, j1] and body["shape"] == [j1 - j0, i1 - i0]
        # The corner as a decimal (-3.8, not the product's -3.8000000000000003).
        assert body["origin"] == [float(f"{i0 * RES:.2f}"), float(f"{j0 * RES:.2f}")]
        assert body["layer"] == layer
        flat = [v for row in body["values"] for v in row]
        if want.dtype.kind in "ui":  # counts and state codes are JSON integers
            assert all(type(v) is int for v in flat), layer
        assert all(same_float(a, float(b)) for a, b in zip(flat, want.ravel().tolist(), strict=True)), layer

        r = api.client.get("/maps/eng/region", params={**bounds, "layer": layer, "format": "png"})
        assert r.headers["content-type"] == "image/png"
        image = Image.open(io.BytesIO(r.content))
        assert image.mode == "LA" and image.size == (i1 - i0, j1 - j0)
        pixels = np.asarray(image)[::-1]  # back to row 0 = lowest y
        known = ~np.isnan(want) if want.dtype.kind == "f" and layer != "tsdf_weight" else want > 0
        assert np.array_equal(pixels[..., 1] == 255, known), layer
        assert known.any() and (~known).any()
        if layer == "probability":
            # 255 (1 - p) of the reported (float32) p, rounded exactly: not in float32 arithmetic,
            # which drew a cell hit once (76.500003) as 76.
            grey = np.round(255 * (1 - want[known].astype(np.float64))).astype(np.uint8)
            assert np.array_equal(pixels[..., 0][known], grey)
        if layer == "tsdf":  # the layer is in [-1, 1] already: -1 black, 0 mid-grey, 1 white
            grey = np.round(127.5 * (1 + want[known].astype(np.float64))).astype(np.uint8)
            assert np.array_equal(pixels[..., 0][known], grey)

    # No bounds: the observed extent.
    r = api.client.get("/maps/eng/region", params={"layer": "hits"})
    b = engine_map.known_bounds()
    assert r.headers["x-fleetmap-window"] == ",".join(map(str, b))
    assert np.array_equal(np.load(io.BytesIO(r.content)), engine_map.region("hits", *b))  # type: ignore[misc]


def test_region_bounds_on_cell_edges_in_decimal_are_those_edges(api: RunningApi, engine_map: GridMap) -> None:
    """Bounds on cell edges written in decimal: 0.15 / 0.05 is 2.9999999999999996, so `xmin=0.15`
    started the window at cell 2, and the origin a region answer reports did not give its own window
    back (the window moved by a cell for about a sixth of the edges at 0.05 m). Such a bound is now
    that edge; one a little way inside a cell (a millionth of a cell) is still floored."""
    edges = [round(k * RES, 10) for k in range(-40, 41)]  # -2.0 ... 2.0 as a person writes them
    assert any(math.floor(x / RES) != k for k, x in zip(range(-40, 41), edges, strict=True))
    for k, x in zip(range(-40, 41), edges, strict=True):
        params = {"xmin": x, "ymin": x, "xmax": x + 0.5, "ymax": x + 0.5, "layer": "hits", "format": "json"}
        body = api.client.get("/maps/eng/region", params=params).json()
        assert body["window"][:2] == [k, k], (x, body["window"])
        again = {**params, "xmin": body["origin"][0], "ymin": body["origin"][1]}
        assert api.client.get("/maps/eng/region", params=again).json()["window"] == body["window"]
    inside = {
        "xmin": 0.15 - 1e-6 * RES,
        "ymin": 0.0,
        "xmax": 0.5,
        "ymax": 0.5,
        "layer": "hits",
        "format": "json",
    }
    assert api.client.get("/maps/eng/region", params=inside).json()["window"][0] == 2


def test_region_bounds_far_from_the_origin_are_floored_unless_on_an_edge(api: RunningApi) -> None:
    """The tolerance that makes a decimal edge that edge grew with the cell index (a billionth of
    it): at 0.01 m, 5,300 km north (UTM northings, a georeferenced nav2 map) it was half a cell, so
    every bound in the upper half of a cell moved to the next edge. `ymin=5300000.006` started the
    window, and a cleared region, at row 530000001 while its point lies in row 530000000 (`/cell`).
    A bound is the edge only within the rounding of the division there; decimal edges still are."""
    res = 0.01
    r = api.client.put("/maps/utm", json={"resolution": res, "layers": ["counts"]})
    assert r.status_code in (200, 201), r.text
    x, y = 500000.006, 5300000.006
    cell = api.client.get("/maps/utm/cell", params={"x": x, "y": y}).json()
    assert (cell["i"], cell["j"]) == (50000000, 530000000)
    bounds = {"xmin": x, "ymin": y, "xmax": x + 0.1, "ymax": y + 0.1}
    r = api.client.get("/maps/utm/region", params={**bounds, "layer": "hits"})
    assert r.status_code == 200, r.text
    assert r.headers["x-fleetmap-window"] == "50000000,530000000,50000010,530000010"
    r = api.client.delete("/maps/utm/region", params=bounds)
    assert r.status_code == 200, r.text
    assert r.json()["window"] == [50000000, 530000000, 50000010, 530000010]
    # Edges written in decimal there are still those edges, and an answer's origin gives its window.
    for k in range(530000000, 530000020):
        edge = round(k * res, 10)
        params = {"xmin": 0.0, "ymin": edge, "xmax": 0.05, "ymax": edge + 0.05}
        params |= {"layer": "hits", "format": "json"}
        body = api.client.get("/maps/utm/region", params=params).json()
        assert body["window"][1] == k, (edge, body["window"])
        again = {**params, "ymin": body["origin"][1]}
        assert api.client.get("/maps/utm/region", params=again).json()["window"] == body["window"]


def test_a_region_s_origin_gives_its_window_back_at_a_resolution_of_more_than_nine_decimals(
    api: RunningApi,
) -> None:
    """An answer's origin is rounded to the nanometre (`cell_edge`), and a bound was that edge only
    within a billionth of a cell of it: at the float32 of 0.05 m (0.05000000074505806, what a map
    copied from a published nav2 map is configured at), the origin of half the windows starting
    right of 0 lay up to 10 billionths of a cell below their edge, and asked for again it started
    the window a cell lower (0.550000008 for cell 11 gave cell 10). A bound within a nanometre of
    an edge is that edge now; one a millionth of a cell inside it is still floored."""
    res = float(np.float32(0.05))
    r = api.client.put("/maps/f32res", json={"resolution": res, "layers": ["counts"]})
    assert r.status_code in (200, 201), r.text
    for k in range(-40, 41):
        params = {"xmin": k * res, "ymin": -k * res, "xmax": (k + 3) * res, "ymax": (3 - k) * res}
        params |= {"layer": "hits", "format": "json"}
        r = api.client.get("/maps/f32res/region", params=params)
        body = r.json()
        assert body["window"][:2] == [k, -k], (k, body["window"])
        assert r.headers["x-fleetmap-origin"] == ",".join(map(repr, body["origin"]))
        again = {**params, "xmin": body["origin"][0], "ymin": body["origin"][1]}
        assert api.client.get("/maps/f32res/region", params=again).json()["window"] == body["window"], k
    inside = {"xmin": 11 * res - 1e-6 * res, "ymin": 0.0, "xmax": 1.0, "ymax": 1.0, "format": "json"}
    assert api.client.get("/maps/f32res/region", params={**inside, "layer": "hits"}).json()["window"][0] == 10


def test_surface(api: RunningApi, engine_map: GridMap) -> None:
    got = api.client.get("/maps/eng/surface").json()
    b = engine_map.known_bounds()
    want = engine_map.surface(*b)  # type: ignore[misc]
    assert got["window"] == list(b) and got["count"] == len(want) > 50  # type: ignore[arg-type]
    assert np.array_equal(np.array(got["points"]), want)
    # Zero crossings of the room lie near its walls (x = +-3 or y = +-2).
    pts = want
    near_wall = np.minimum(np.abs(np.abs(pts[:, 0]) - 3), np.abs(np.abs(pts[:, 1]) - 2))
    assert np.median(near_wall) < 2 * RES
    # Read in two windows that meet on the wall x = 3 m (a cell edge), it is the same points: the
    # crossings between the cells either side of the edge were in neither window.
    i0, j0, i1, j1 = b  # type: ignore[misc]
    parts = [
        api.client.get(
            "/maps/eng/surface", params={"xmin": x0, "ymin": j0 * RES, "xmax": x1, "ymax": j1 * RES}
        )
        for x0, x1 in ((i0 * RES, 3.0), (3.0, i1 * RES))
    ]
    points = np.array(parts[0].json()["points"] + parts[1].json()["points"])
    assert len(points) == len(want)
    np.testing.assert_allclose(points[np.lexsort(points.T[::-1])], want[np.lexsort(want.T[::-1])], atol=1e-9)


def test_too_many_points_at_the_default_cap(api: RunningApi) -> None:
    """At the default limit the request model's own cap catches the list first; it must still be the
    413 docs/api.md promises, with the route's sentence, not a 422 "invalid body"."""
    assert api.client.put("/maps/pts", json=CONFIG).status_code in (200, 201)
    r = api.client.post("/maps/pts/cells", json={"points": [[0.0, 0.0]] * 100_001})
    assert r.status_code == 413, r.text
    assert r.json()["detail"] == "100001 points is more than the limit of 100000 per request"
    assert "errors" not in r.json()
    r = api.client.post("/maps/pts/cells", json={"points": [[0.0, 0.0]] * 100_000})
    assert r.status_code == 200 and r.json()["count"] == 100_000


def test_a_body_of_far_more_points_or_rays_than_allowed_is_refused_before_it_is_parsed(
    api: RunningApi,
) -> None:
    """A `POST .../cells` body of 16 MiB (the body limit) holds 2.8 million points: it was parsed
    whole (1.3 s and 300 MB, holding the GIL: nothing else was served meanwhile) before the model
    refused it as more than 100,000. Such a body is now refused (413) by counting its commas, and a
    valid body of the most points or rays a request may have is still read."""
    assert api.client.put("/maps/pts", json=CONFIG).status_code in (200, 201)
    points = b",".join([b"[0,0]"] * ((16 * 2**20 - 20) // 6))
    rays = b",".join([b"0"] * 3_000_000)
    for path, body, what in [
        ("cells", b'{"points":[' + points + b"]}", "100000 points"),
        ("raycast", b'{"origin":[0,0],"max_range":1,"angles":[' + rays + b"]}", "10000 rays"),
        (
            "raycast",
            b'{"angles":[0],"max_range":1,"origins":[' + points[: 6 * 2_000_000 - 1] + b"]}",
            "10000 rays",
        ),
        # A map's configuration holds a few dozen values: a body of millions under a key it does
        # not have was parsed whole too, before `extra="forbid"` refused the key.
        ("", b'{"x":[' + points[: 6 * 2_000_000 - 1] + b"]}", "the values of a map configuration"),
    ]:
        started = time.monotonic()
        headers = {"content-type": "application/json"}
        if path:
            r = api.client.post(f"/maps/pts/{path}", content=body, headers=headers)
        else:
            r = api.client.put("/maps/pts-new", content=body, headers=headers)
        assert r.status_code == 413, r.text
        assert (
            r.json()["detail"] == f"the body holds more than {what} (the limit per request); it was not read"
        )
        assert time.monotonic() - started < 1.0  # not parsed: 1.3 s and more when it was
    assert api.client.get("/maps/pts-new").status_code == 404
    angles = [0.001 * k for k in range(10_000)]
    r = api.client.post(
        "/maps/pts/raycast",
        json={"origins": [[0.5, 0.5]] * 10_000, "angles": angles, "max_range": 1.0, "unknown": "pass"},
    )
    assert r.status_code == 200, r.text


# -- tiles --------------------------------------------------------------------------------------------


def test_tiles_etag_304_and_visible_change(api: RunningApi) -> None:
    c = api.client
    c.put("/maps/tiles", json={"resolution": RES})
    assert post_scan(api, "tiles", "r", fan_scan(1.0, 1.0, 0.0, [2.0] * 91), 0).status_code == 200
    url = "/maps/tiles/tiles/0/0/-1.png"  # cells i, j in [0, 256): x, y in [0, 12.8) m
    r = c.get(url)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.headers["cache-control"] == "no-cache"
    etag = r.headers["etag"]
    image = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGBA"))
    assert image.shape == (256, 256, 4)
    # The pixel of cell (i, j) is row 255 - j, column i; its grey is 255 (1 - p) of that cell.
    for x, y in [(3.0 - 0.01, 1.0), (2.0, 1.0), (1.0, 1.0), (5.0, 5.0)]:
        cell = c.get("/maps/tiles/cell", params={"x": x, "y": y}).json()
        px = image[255 - cell["j"], cell["i"]]
        if cell["known"]:
            assert px[3] == 255 and px[0] == round(255 * (1 - cell["probability"]))
        else:
            assert px[3] == 0

    r = c.get(url, headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    assert c.get(url, headers={"If-None-Match": f'W/{etag}, "other"'}).status_code == 304
    # An unexplored tile: 200, fully transparent.
    far = c.get("/maps/tiles/tiles/0/100/100.png")
    assert (
        far.status_code == 200
        and not np.asarray(Image.open(io.BytesIO(far.content)).convert("RGBA"))[..., 3].any()
    )

    # A scan elsewhere (another storage tile) leaves this tile's ETag alone...
    assert post_scan(api, "tiles", "r", fan_scan(-20.0, -20.0, 0.0, [1.0] * 31), 1).status_code == 200
    assert c.get(url, headers={"If-None-Match": etag}).status_code == 304
    # ... a scan under it changes it, visible to the very first request after the POST returns
    # (the POST answers after integration, so no wait at all is needed, far less than 100 ms).
    assert post_scan(api, "tiles", "r", fan_scan(4.0, 2.0, 1.0, [1.5] * 91), 2).status_code == 200
    r = c.get(url, headers={"If-None-Match": etag})
    assert r.status_code == 200 and r.headers["etag"] != etag
    cell = c.get("/maps/tiles/cell", params={"x": 4.0, "y": 2.0}).json()
    assert (
        cell["known"]
        and np.asarray(Image.open(io.BytesIO(r.content)).convert("RGBA"))[255 - cell["j"], cell["i"], 3]
        == 255
    )

    # Other zooms and layers.
    zoomed_out = c.get("/maps/tiles/tiles/-3/0/-1.png", params={"layer": "hits"})
    assert zoomed_out.status_code == 200 and zoomed_out.headers["etag"] != r.headers["etag"]
    assert c.get("/maps/tiles/tiles/4/4/-3.png", params={"layer": "state"}).status_code == 200
    r = c.get("/maps/tiles/tiles/0/0/-1.png", params={"layer": "volume"})
    assert r.status_code == 422 and "volume" in r.json()["detail"]
    # Re-creating the map gives new ETags even where the tile versions coincide.
    c.delete("/maps/tiles")
    c.put("/maps/tiles", json={"resolution": RES})
    assert post_scan(api, "tiles", "r", fan_scan(1.0, 1.0, 0.0, [2.0] * 91), 0).status_code == 200
    assert c.get(url).headers["etag"] != etag


# -- export -------------------------------------------------------------------------------------------


def test_export_ros_zip_and_png(api: RunningApi, engine_map: GridMap) -> None:
    r = api.client.get("/maps/eng/export", params={"format": "ros"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    assert 'filename="eng.zip"' in r.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert sorted(zf.namelist()) == ["map.pgm", "map.yaml"]
        meta = yaml.safe_load(zf.read("map.yaml"))
        pgm = zf.read("map.pgm")
        # The same bytes for the same map: each entry carried the time of the request, so two
        # downloads of an unchanged map differed. Unzipped, the files are rw-r--r--.
        assert {info.date_time for info in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
        assert {info.external_attr >> 16 for info in zf.infolist()} == {0o644}
    assert api.client.get("/maps/eng/export", params={"format": "ros"}).content == r.content
    i0, j0, i1, j1 = engine_map.known_bounds()  # type: ignore[misc]
    i0, j0, i1, j1 = i0 - 2, j0 - 2, i1 + 2, j1 + 2  # the default margin, as `fleetmap build`
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["resolution"] == RES
    assert meta["origin"] == [float(f"{i0 * RES:.2f}"), float(f"{j0 * RES:.2f}"), 0.0] and meta["negate"] == 0
    assert (meta["occupied_thresh"], meta["free_thresh"]) == (0.65, 0.196)
    magic, size, maxval, data = pgm.split(b"\n", 3)
    width, height = map(int, size.split())
    assert (magic, maxval, width, height) == (b"P5", b"255", i1 - i0, j1 - j0)
    pixels = np.frombuffer(data, dtype=np.uint8).reshape(height, width)
    assert set(np.unique(pixels).tolist()) == {PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN}
    assert np.array_equal(pixels, state_to_pgm(engine_map.region("state", i0, j0, i1, j1)))

    r = api.client.get("/maps/eng/export", params={"format": "png", "margin": 0})
    image = Image.open(io.BytesIO(r.content))
    assert r.headers["content-type"] == "image/png" and image.size == (i1 - i0 - 4, j1 - j0 - 4)

    api.client.put("/maps/empty", json={})
    r = api.client.get("/maps/empty/export")
    assert r.status_code == 409 and "no observed cell" in r.json()["detail"]


# -- events -------------------------------------------------------------------------------------------


class EventReader:
    """Reads a server-sent event stream in a thread: (event, data, id) tuples on a queue."""

    def __init__(self, url: str, headers: dict[str, str] | None = None) -> None:
        self.events: queue.Queue[tuple[str, dict, str | None] | None] = queue.Queue()
        self.status: int | None = None
        self.content_type = ""
        self.keepalives = 0
        self._stop = threading.Event()
        self._client = httpx.Client(timeout=httpx.Timeout(30, read=60))
        self._thread = threading.Thread(target=self._run, args=(url, headers or {}), daemon=True)
        self._thread.start()

    def _run(self, url: str, headers: dict[str, str]) -> None:
        try:
            with self._client.stream("GET", url, headers=headers) as r:
                self.status, self.content_type = r.status_code, r.headers.get("content-type", "")
                kind, data, event_id = "message", "", None
                for line in r.iter_lines():
                    if self._stop.is_set():
                        break  # leaving the `with` closes the connection
                    if line.startswith(": keepalive"):
                        self.keepalives += 1
                    elif line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        data += line[6:]
                    elif line.startswith("id: "):
                        event_id = line[4:]
                    elif line == "" and data:
                        self.events.put((kind, json.loads(data), event_id))
                        kind, data, event_id = "message", "", None
        except (httpx.HTTPError, RuntimeError):
            pass  # closed by close()
        finally:
            self.events.put(None)

    def next(self, kind: str, timeout: float = 5.0) -> tuple[dict, str | None]:
        """The next event of `kind` (skipping others) within `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            item = self.events.get(timeout=max(0.01, deadline - time.monotonic()))
            if item is None:
                raise AssertionError(f"stream ended before a {kind!r} event")
            if item[0] == kind:
                return item[1], item[2]

    def ended(self, timeout: float = 5.0) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def close(self) -> None:
        self._stop.set()
        assert self.ended(), "the reader did not stop (no keepalive?)"
        self._client.close()


def test_exports_have_their_own_limit_above_the_regions() -> None:
    """A map too big for one region is exported whole up to `max_export_cells`, and refused past it
    (413 naming the setting) with nothing allocated."""
    scans = [fan_scan(0.0, 0.0, 0.0, [3.0] * 61)]
    engine = GridMap(MapConfig())
    engine.integrate(scans[0])
    i0, j0, i1, j1 = engine.known_bounds()  # type: ignore[misc]
    cells = (i1 - i0 + 4) * (j1 - j0 + 4)  # the export's default margin: 2 cells
    for limit, status in ((cells, 200), (cells - 1, 413)):
        settings = ApiSettings(max_region_cells=cells // 4, max_export_cells=limit)
        with running_api(settings) as api:
            assert post_scan(api, "big", "r", scans[0], 0).status_code == 200
            region = api.client.get("/maps/big/region", params={"layer": "state", "format": "npy"})
            assert region.status_code == 413, region.text
            export = api.client.get("/maps/big/export")
            assert export.status_code == status, export.text
            if status == 413:
                assert "max_export_cells" in export.json()["detail"]


def test_the_freiburg_campus_map_exports_whole(datasets_dir: Path) -> None:
    """The biggest recorded map here (6,039 x 6,059 cells at 0.05 m, over the region limit) is
    exported whole by the service with the default settings, cell for cell the map's state."""
    from fleetmap.datasets import load_dataset

    ds = load_dataset(datasets_dir / "freiburg-campus-corrected.log.gz")
    engine = GridMap(MapConfig())
    for k in range(len(ds)):
        engine.integrate(ds[k])
    i0, j0, i1, j1 = engine.known_bounds()  # type: ignore[misc]
    i0, j0, i1, j1 = i0 - 2, j0 - 2, i1 + 2, j1 + 2
    assert (i1 - i0) * (j1 - j0) > ApiSettings().max_region_cells
    with running_api() as api:
        api.registry.replace("campus", engine, wait=True)
        r = api.client.get("/maps/campus/export")
        assert r.status_code == 200, r.text
        with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
            magic, size, maxval, data = zf.read("map.pgm").split(b"\n", 3)
    width, height = map(int, size.split())
    assert (magic, maxval, width, height) == (b"P5", b"255", i1 - i0, j1 - j0)
    pixels = np.frombuffer(data, dtype=np.uint8).reshape(height, width)
    assert np.array_equal(pixels, state_to_pgm(engine.region("state", i0, j0, i1, j1)))


def test_a_counts_only_map_exports_its_count_models_occupancy(api: RunningApi) -> None:
    """As `fleetmap build` does: the nav2 map and the PNG show hits / (hits + misses) by the map's
    thresholds when the map keeps no occupancy layer."""
    assert api.client.put("/maps/cnt", json={"layers": ["counts"]}).status_code == 201
    scans = [fan_scan(0.1, 0.1, 0.3 * k, [1.0 + 0.2 * k] * 31) for k in range(6)]
    for seq, scan in enumerate(scans):
        assert post_scan(api, "cnt", "r", scan, seq).status_code == 200
    engine = GridMap(MapConfig(layers=["counts"]))
    for scan in scans:
        engine.integrate(scan)
    bounds = engine.known_bounds()
    assert bounds is not None
    i0, j0, i1, j1 = bounds[0] - 2, bounds[1] - 2, bounds[2] + 2, bounds[3] + 2
    hits = engine.region("hits", i0, j0, i1, j1).astype(np.float64)
    total = hits + engine.region("misses", i0, j0, i1, j1)
    with np.errstate(invalid="ignore"):
        p = hits / total
    want = np.full(p.shape, PGM_UNKNOWN, dtype=np.uint8)
    want[(total > 0) & (p < 0.196)] = PGM_FREE
    want[(total > 0) & (p > 0.65)] = PGM_OCCUPIED
    r = api.client.get("/maps/cnt/export")
    assert r.status_code == 200
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        _magic, _size, _maxval, data = zf.read("map.pgm").split(b"\n", 3)
    pgm = np.frombuffer(data, dtype=np.uint8).reshape(want.shape)
    np.testing.assert_array_equal(pgm, want[::-1])
    assert (want == PGM_OCCUPIED).any() and (want == PGM_FREE).any()
    png = np.asarray(Image.open(io.BytesIO(api.client.get("/maps/cnt/export?format=png").content)))
    assert png.shape == want.shape and png[::-1][want == PGM_OCCUPIED].max() < 60


def covered(window: list[int], windows: list[list[int]]) -> bool:
    return list(window) in [list(w) for w in windows]


def test_events_tiles_robots_resume_and_delete(api: RunningApi) -> None:
    c = api.client
    c.put("/maps/ev", json=CONFIG)
    reader = EventReader(f"{api.base_url}/maps/ev/events")
    try:
        first, _ = reader.next("robots")  # sent on connect: the stream is up
        assert reader.status == 200 and reader.content_type.startswith("text/event-stream")
        assert first == {"robots": {}}
        scan = fan_scan(0.7, -0.4, 0.25, [1.2] * 121)
        result = post_scan(api, "ev", "rA", scan, 0).json()
        assert result["changed_tiles"]
        seen: list[list[int]] = []
        while not all(covered(w, seen) for w in result["changed_tiles"]):
            data, event_id = reader.next("tiles")
            assert "reset" not in data and event_id == str(data["version"])
            seen += data["tiles"]
        while True:  # robots events come whenever something changed; wait for this scan's
            robots, _ = reader.next("robots")
            if robots["robots"].get("rA", {}).get("scans_integrated") == 1:
                break
        robot = robots["robots"]["rA"]
        assert (
            robot["pose"] == [0.7, -0.4, 0.25]
            and robot["trail"] == [[0.7, -0.4]]
            and robot["online"] is False
        )
        deadline = time.monotonic() + 5
        while reader.keepalives == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert reader.keepalives > 0  # comment lines keep an idle stream open

        # Deleting the map ends the stream with a `deleted` event.
        c.delete("/maps/ev")
        assert reader.next("deleted")[0] == {"id": "ev"}
        assert reader.ended()
    finally:
        reader.close()

    # Resuming: changes after `since` (or Last-Event-ID) are sent at once.
    c.put("/maps/ev2", json=CONFIG)
    start = c.get("/maps/ev2").json()["stats"]["version"]
    windows = []
    for seq, x in enumerate([0.5, 5.0]):
        windows += post_scan(api, "ev2", "rB", fan_scan(x, 0.0, 0.0, [1.0] * 61), seq).json()["changed_tiles"]
    for url, headers in [
        (f"{api.base_url}/maps/ev2/events?since={start}", None),
        (f"{api.base_url}/maps/ev2/events", {"Last-Event-ID": str(start)}),
    ]:
        reader = EventReader(url, headers)
        try:
            data, _ = reader.next("tiles")
            assert data["version"] == start + 2 and all(covered(w, data["tiles"]) for w in windows)
        finally:
            reader.close()
    # An EventSource opened with `?since=` reconnects to the same URL with `Last-Event-ID`, the later
    # id: the stream resumes from the header. Read `since` first, it replayed from there every time,
    # here a reset (a version before this map).
    resumed = {"Last-Event-ID": str(start + 1)}
    reader = EventReader(f"{api.base_url}/maps/ev2/events?since={start - 1}", resumed)
    try:
        data, _ = reader.next("tiles")
        assert "reset" not in data and data["version"] == start + 2 and data["tiles"]
    finally:
        reader.close()
    # An id from before the map was re-created (newer, or older, than anything this map had): reset.
    for since in (start + 99, start - 1):
        reader = EventReader(f"{api.base_url}/maps/ev2/events?since={since}")
        try:
            assert reader.next("tiles")[0] == {"version": start + 2, "reset": True}
        finally:
            reader.close()


def test_keepalive_events_for_pages(api: RunningApi) -> None:
    """A browser's EventSource never shows comments to the page, so a web page could not tell a
    quiet map from a stream that died silently. `?keepalive=event` sends the keepalives as
    `keepalive` events carrying the period, the first at once (the page knows the period before any
    silence), and no comment; without it, comments as before."""
    api.client.put("/maps/ka", json=CONFIG)
    reader = EventReader(f"{api.base_url}/maps/ka/events?keepalive=event")
    try:
        opened = time.monotonic()
        assert reader.next("keepalive", timeout=5.0)[0] == {"interval": 0.3}
        assert time.monotonic() - opened < 0.25  # at once, not after the first 0.3 s of silence
        reader.next("robots")
        # The map stays quiet: keepalive events, about every 0.3 s, and no comment.
        started = time.monotonic()
        for _ in range(3):
            assert reader.next("keepalive", timeout=2.0)[0] == {"interval": 0.3}
        assert 0.6 < time.monotonic() - started < 3.0
        assert reader.keepalives == 0
    finally:
        reader.close()
    plain = EventReader(f"{api.base_url}/maps/ka/events")
    try:
        deadline = time.monotonic() + 5
        while plain.keepalives == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert plain.keepalives > 0
        plain.close()
        kinds = []
        while (item := plain.events.get(timeout=1)) is not None:
            kinds.append(item[0])
        assert "keepalive" not in kinds
    finally:
        plain.close()
    assert api.client.get("/maps/ka/events", params={"keepalive": "often"}).status_code == 422


def test_events_follow_a_map_replaced_by_a_snapshot(api: RunningApi) -> None:
    """`PUT /maps/{id}/snapshot` replaces the map under its id (200 on GET afterwards): the stream says
    `replaced`, not `deleted`, with the new map's change version as its id, and goes on with the new
    map's events. `PUT /maps/{id}` never replaces a map (the same configuration changes nothing,
    another is 409), so it sends nothing."""
    c = api.client
    c.put("/maps/rep-src", json=CONFIG)
    assert post_scan(api, "rep-src", "rS", fan_scan(3.0, 3.0, 0.0, [1.0] * 61), 0).status_code == 200
    snapshot = c.get("/maps/rep-src/snapshot").content
    c.put("/maps/rep", json=CONFIG)
    assert post_scan(api, "rep", "rA", fan_scan(0.0, 0.0, 0.0, [1.2] * 61), 0).status_code == 200
    reader = EventReader(f"{api.base_url}/maps/rep/events")
    try:
        robots, _ = reader.next("robots")
        assert "rA" in robots["robots"]
        assert c.put("/maps/rep", json=CONFIG).status_code == 200
        assert c.put("/maps/rep", json={**CONFIG, "resolution": 0.1}).status_code == 409
        r = c.put("/maps/rep/snapshot", content=snapshot, headers={"content-type": "application/zip"})
        assert r.status_code == 200, r.text  # replaced, not created
        data, event_id = reader.next("replaced")  # fails if the stream said `deleted` and ended
        start = c.get("/maps/rep").json()["stats"]["version"]  # the new map's first version
        assert data == {"id": "rep", "version": start} and event_id == str(start)
        assert reader.next("robots")[0] == {"robots": {}}  # the new map's robots start afresh
        # The stream goes on with the new map: a scan's tiles arrive, with the new map's versions.
        result = post_scan(api, "rep", "rB", fan_scan(0.5, 0.0, 0.0, [1.0] * 61), 0).json()
        seen: list[list[int]] = []
        while not all(covered(w, seen) for w in result["changed_tiles"]):
            tiles, event_id = reader.next("tiles")
            assert event_id == str(tiles["version"]) == str(start + 1)
            seen += tiles["tiles"]
        assert c.get("/maps/rep").status_code == 200
        c.delete("/maps/rep")
        assert reader.next("deleted")[0] == {"id": "rep"}
        assert reader.ended()
    finally:
        reader.close()


def test_a_large_scan_body_is_decoded_off_the_event_loop(
    api: RunningApi, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Decoding a few MB of JSON takes tens of ms; other requests must not wait for it. The real
    decoder is wrapped so that it holds on until the test has seen /healthz answered meanwhile."""
    entered, release = threading.Event(), threading.Event()
    real = codec_module.decode

    def held(body: bytes, content_type: str, limits: codec_module.InputLimits) -> object:
        if len(body) > routes_maps.DECODE_ON_LOOP_BYTES:
            entered.set()
            release.wait(10)
        return real(body, content_type, limits)

    monkeypatch.setattr(codec_module, "decode", held)
    scan = fan_scan(0.0, 0.0, 0.0, [1.0] * 16000)
    body = encode_json(scan, 0).replace(b",", b",         ")  # the same scan, padded past the threshold
    assert len(body) > routes_maps.DECODE_ON_LOOP_BYTES
    answers: queue.Queue[httpx.Response] = queue.Queue()
    poster = threading.Thread(
        target=lambda: answers.put(
            api.client.post(
                "/maps/big/scans",
                params={"robot_id": "r"},
                content=body,
                headers={"content-type": JSON_ENCODING},
            )  # fmt: skip
        )
    )
    poster.start()
    try:
        assert entered.wait(10)
        assert api.client.get("/healthz", timeout=5).status_code == 200  # while the body decodes
    finally:
        release.set()
        poster.join(30)
    answer = answers.get(timeout=1)
    assert answer.status_code == 200 and answer.json()["status"] == "integrated", answer.text


def test_a_scan_over_the_payload_limit_is_413_and_counted(api: RunningApi) -> None:
    """A scan payload over the decoder's 4 MiB (the limit of every scan, as over Zenoh) is "too much
    at once", 413 as docs/api.md says, though far below the 16 MiB body limit; and it is counted on
    the robot as rejected, as the same payload over Zenoh would be."""
    limit = codec_module.DEFAULT_LIMITS.max_payload_bytes
    body = encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 2000), 0).replace(b",", b"," + b" " * 1500)
    assert limit < len(body) < ApiSettings().max_body_bytes
    assert api.client.put("/maps/huge", json=CONFIG).status_code in (200, 201)
    r = api.client.post(
        "/maps/huge/scans", params={"robot_id": "r"}, content=body, headers={"content-type": JSON_ENCODING}
    )
    assert r.status_code == 413, r.text
    assert r.json()["detail"] == f"payload of {len(body)} bytes exceeds the limit of {limit}"
    robot = api.client.get("/maps/huge").json()["stats"]["robots"]["r"]
    assert robot["scans_rejected"] == 1 and robot["scans_integrated"] == 0
    assert robot["last_error"] == r.json()["detail"]


def test_a_scan_with_a_session_refused_at_the_input_limits_is_rejected_not_also_lost(api: RunningApi) -> None:
    """A scan with a session id that breaks the input limits (a pose outside the world bound) is a
    422, counted as rejected with its seq recorded, as over Zenoh (docs/protocol.md, "Limits"): the
    robot's next seq is no gap. The REST ingest dropped its seq, so the next scan counted it as lost
    too: three scans, two integrated, one rejected and one lost. A copy of it is a duplicate."""
    assert api.client.put("/maps/lim-rest", json=CONFIG).status_code in (200, 201)

    def post(seq: int, x: float) -> httpx.Response:
        body = encode_json(fan_scan(x, 0.0, 0.0, [1.0] * 31), seq, float(seq), session=77)
        return api.client.post(
            "/maps/lim-rest/scans", params={"robot_id": "r"}, content=body,
            headers={"content-type": JSON_ENCODING},
        )  # fmt: skip

    assert post(0, 0.0).json()["status"] == "integrated"
    r = post(1, 5e6)
    assert r.status_code == 422 and "world bound" in r.json()["detail"], r.text
    assert post(1, 5e6).status_code == 422  # its copy: refused again, counted once
    assert post(2, 0.0).json()["status"] == "integrated"
    robot = api.client.get("/maps/lim-rest").json()["stats"]["robots"]["r"]
    counts = {k: robot[k] for k in ("scans_integrated", "scans_rejected", "lost", "duplicates", "last_seq")}
    assert counts == {"scans_integrated": 2, "scans_rejected": 1, "lost": 0, "duplicates": 1, "last_seq": 2}
    assert robot["last_error"].startswith("scan seq 1 refused: pose (5e+06, 0) is outside the world bound")


def test_a_scans_media_type_is_read_whatever_its_case(api: RunningApi) -> None:
    """`Content-Type: Application/JSON` is JSON (media types are case-insensitive, RFC 9110, 8.3.1),
    as for every other JSON body of the API: a scan sent so was refused as of an unknown encoding,
    and counted as rejected."""
    assert api.client.put("/maps/case", json=CONFIG).status_code in (200, 201)
    scan = fan_scan(0.0, 0.0, 0.0, [1.0] * 31)
    for seq, (body, content_type) in enumerate(
        [
            (encode_json(scan, 0), "Application/JSON; charset=UTF-8"),
            (encode_binary(scan, 1), BINARY_ENCODING.upper()),
        ]
    ):
        r = api.client.post(
            "/maps/case/scans", params={"robot_id": "r"}, content=body, headers={"content-type": content_type}
        )
        assert r.status_code == 200 and r.json()["status"] == "integrated", (seq, r.text)
    robot = api.client.get("/maps/case").json()["stats"]["robots"]["r"]
    assert (robot["scans_integrated"], robot["scans_rejected"]) == (2, 0)


def test_a_seq_refused_at_integration_without_a_session_is_free_for_the_next_scan(api: RunningApi) -> None:
    """A scan without a session id refused when it is integrated (it needs more tiles than the map's
    max_tiles: 422) leaves its seq free, as one the decoder refuses does: the next scan sent under
    it is integrated, and a copy of that one is a duplicate. Its seq was recorded when it was
    queued, so that scan was answered "duplicate" and never integrated (`FleetmapClient.post_scan`,
    whose automatic seq stays after a 422, lost the robot's next scan so, silently); and once it
    was, a copy of it, its stamp later than the refused scan's, was taken for a restart."""
    assert api.client.put("/maps/cap", json={**CONFIG, "max_tiles": 1}).status_code in (200, 201)
    near = fan_scan(1.6, 1.6, 0.0, [0.5] * 31)  # within one tile of 64 cells (3.2 m)
    far = fan_scan(50.0, 50.0, 0.0, [0.5] * 31)  # in another tile: past max_tiles

    def post(scan: Scan, seq: int, stamp: float) -> httpx.Response:
        return api.client.post(
            "/maps/cap/scans", params={"robot_id": "r"}, content=encode_json(scan, seq, stamp),
            headers={"content-type": JSON_ENCODING},
        )  # fmt: skip

    assert post(near, 0, 0.0).json()["status"] == "integrated"
    # Seq 1 refused, then taken by a scan of the same stamp (FleetmapClient sends 0); seq 2 refused,
    # then taken by a scan of a later stamp.
    for seq, stamp in ((1, 0.0), (2, 5.0)):
        r = post(far, seq, 0.0)
        assert r.status_code == 422 and "max_tiles" in r.json()["detail"], r.text
        r = post(near, seq, stamp)
        assert r.status_code == 200 and r.json()["status"] == "integrated", r.text
        assert post(near, seq, stamp).json()["status"] == "duplicate"  # its copy, once integrated
    robot = api.client.get("/maps/cap").json()["stats"]["robots"]["r"]
    names = ("scans_integrated", "scans_rejected", "lost", "duplicates", "restarts", "last_seq")
    assert {k: robot[k] for k in names} == {
        "scans_integrated": 3, "scans_rejected": 2, "lost": 0, "duplicates": 2, "restarts": 0, "last_seq": 2,
    }  # fmt: skip


# -- metrics ------------------------------------------------------------------------------------------


def test_metrics_count_per_robot(api: RunningApi) -> None:
    c = api.client
    c.put("/maps/met", json=CONFIG)
    scan = fan_scan(0.0, 0.0, 0.0, [1.0] * 31)
    for seq in (0, 1, 2):
        assert post_scan(api, "met", "m1", scan, seq).json()["status"] == "integrated"
    assert post_scan(api, "met", "m1", scan, 1).json()["status"] == "duplicate"
    assert post_scan(api, "met", "m1", scan, 5).json()["status"] == "integrated"  # 3 and 4 lost
    bad = encode_json(scan, 6).replace(b'"range_min":0.0', b'"range_min":-1.0')
    r = c.post(
        "/maps/met/scans", params={"robot_id": "m1"}, content=bad, headers={"content-type": JSON_ENCODING}
    )
    assert r.status_code == 422 and "range_min" in r.json()["detail"]
    assert post_scan(api, "met", "m2", scan, 0, binary=True).json()["status"] == "integrated"
    c.get("/maps/met/tiles/0/0/-1.png")

    samples = {}
    for family in text_string_to_metric_families(c.get("/metrics").text):
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    m1 = (("map", "met"), ("robot", "m1"))
    m2 = (("map", "met"), ("robot", "m2"))
    assert samples[("fleetmap_scans_integrated_total", m1)] == 4
    assert samples[("fleetmap_scans_duplicate_total", m1)] == 1
    assert samples[("fleetmap_scans_lost", m1)] == 2
    assert samples[("fleetmap_scans_rejected_total", m1)] == 1
    assert samples[("fleetmap_scans_dropped_total", m1)] == 0
    assert samples[("fleetmap_scans_integrated_total", m2)] == 1
    assert samples[("fleetmap_robot_online", m2)] == 0
    assert samples[("fleetmap_queue_depth", ())] == 0
    assert samples[("fleetmap_map_tiles", (("map", "met"),))] >= 1
    assert samples[("fleetmap_integration_seconds_count", ())] >= 5
    assert samples[("fleetmap_ingest_latency_seconds_count", ())] >= 5
    assert samples[("fleetmap_tile_render_seconds_count", (("layer", "probability"),))] >= 1
    # The same numbers as GET /maps/{id}: one truth.
    robot = c.get("/maps/met").json()["stats"]["robots"]["m1"]
    assert (robot["scans_integrated"], robot["duplicates"], robot["lost"], robot["scans_rejected"]) == (
        4,
        1,
        2,
        1,
    )
    assert "range_min" in robot["last_error"] and robot["last_seq"] == 5


def test_statistics_do_not_wait_for_the_map_lock(api: RunningApi) -> None:
    """`/metrics` and `GET /maps` answer while a scan or a snapshot's copy holds the map's lock (a
    Prometheus scrape must not stall behind them), with the tile count and pool bytes of the map."""
    c = api.client
    c.put("/maps/busy", json=CONFIG)
    scan = fan_scan(0.0, 0.0, 0.0, [3.0] * 31)
    assert post_scan(api, "busy", "r", scan, 0).json()["status"] == "integrated"
    gmap = api.registry.get("busy").gmap
    store = gmap.store
    pool_bytes = (
        sum(p.nbytes for p in store.pools.values())
        + store.versions.nbytes
        + SLOT_OVERHEAD * len(store.versions)
    )
    with gmap.lock:  # as the ingest worker or the snapshot writer would hold it
        metrics = c.get("/metrics", timeout=5).text
        listed = c.get("/maps", timeout=5).json()["maps"]
    samples = {
        (s.name, tuple(s.labels.values())): s.value
        for family in text_string_to_metric_families(metrics)
        for s in family.samples
    }
    assert samples[("fleetmap_map_tiles", ("busy",))] == len(store) > 0
    assert samples[("fleetmap_map_memory_bytes", ("busy",))] == pool_bytes
    summary = next(m for m in listed if m["id"] == "busy")
    assert (summary["tiles"], summary["memory_bytes"]) == (len(store), pool_bytes)


def test_web_dir_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from fleetmap.api.app import DEFAULT_WEB_DIR, default_web_dir

    checkout = Path(__file__).resolve().parents[1] / "clients" / "web"
    assert checkout == DEFAULT_WEB_DIR
    assert default_web_dir() == checkout  # the viewer is in this checkout
    monkeypatch.setenv("FLEETMAP_WEB_DIR", str(tmp_path))
    assert default_web_dir() == tmp_path


def test_an_upload_says_whether_it_replaced_a_map_as_of_when_it_installed_it(
    api: RunningApi, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`PUT .../snapshot` answers 201 (and `Location`) when it created the map, 200 when it replaced
    one. It looked the map up before reading the upload (seconds, for a big file): a map another
    writer created or deleted meanwhile made the answer wrong, 201 Created for an upload that had
    replaced that writer's map. Here the other writer acts while the upload is read."""
    from fleetmap.api import routes_snapshot
    from fleetmap.storage_format import snapshot_file

    body = snapshot_file("src", GridMap(MapConfig()))
    read = routes_snapshot.map_from_snapshot_file
    meanwhile: list[str] = []

    def read_while_another_writer_acts(data: bytes, **kwargs: object) -> GridMap:
        action = meanwhile.pop()
        if action == "create":
            api.registry.create("racing-upload")
        else:
            api.registry.delete("racing-upload")
        return read(data, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(routes_snapshot, "map_from_snapshot_file", read_while_another_writer_acts)
    zipped = {"content-type": "application/zip"}
    meanwhile.append("create")  # no map when the upload came, one when it was installed: replaced
    r = api.client.put("/maps/racing-upload/snapshot", content=body, headers=zipped)
    assert r.status_code == 200 and "location" not in r.headers, (r.status_code, r.headers)
    meanwhile.append("delete")  # a map when the upload came, none when it was installed: created
    r = api.client.put("/maps/racing-upload/snapshot", content=body, headers=zipped)
    assert r.status_code == 201 and r.headers["location"].endswith("/maps/racing-upload"), r.text
    api.registry.delete("racing-upload")
