"""End to end with real processes: the service (`python -m fleetmap.server`) as a subprocess, robots
as separate processes publishing over Zenoh (tests/robot_process.py), the map read back over real
HTTP and compared cell by cell with the engine's map of the same scans built here."""

from __future__ import annotations

import io
import json
import math
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from robot_process import encode, scans_for
from service_process import RobotProcess, ServiceProcess, wait_for

from fleetmap import codec
from fleetmap.config import MapConfig
from fleetmap.grid_map import STATE_NAMES, GridMap

#: Layers compared exactly when one robot feeds a map (its scans are integrated in seq order).
ALL_LAYERS = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")
#: Layers that do not depend on the order in which several robots' scans were integrated.
COUNT_LAYERS = ("hits", "misses")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One service for the module's tests; each test uses its own map ids."""
    svc = ServiceProcess(tmp_path_factory.mktemp("service"))
    svc.start()
    yield svc
    code = svc.stop()
    assert code == 0, f"service did not shut down cleanly ({code}):\n{svc.logs()}"


@pytest.fixture
def http(service: ServiceProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=service.base_url, timeout=20.0) as client:
        yield client


# -- helpers ---------------------------------------------------------------------------------------


def expected_map(sources: list[dict[str, Any]], config: MapConfig | None = None) -> tuple[GridMap, int]:
    """The engine's map of what the robots described by `sources` (RobotProcess options) publish,
    each payload decoded as the service decodes it, robots one after the other, seq order. Returns
    the map and the number of scans."""
    gmap = GridMap(config or MapConfig())
    n = 0
    for opts in sources:
        scans = scans_for(
            sim=opts.get("sim"), plan_seed=opts.get("plan_seed", 0), beams=opts.get("beams", 361),
            dataset=opts.get("dataset"), start=opts.get("start", 0), count=opts.get("count", 10),
        )  # fmt: skip
        encoding = opts.get("encoding", "binary")
        wire_encoding = codec.JSON_ENCODING if encoding == "json" else codec.BINARY_ENCODING
        skip = set(opts.get("skip", []))
        for k, scan in enumerate(scans):
            seq = opts.get("seq_start", 0) + k
            if seq in skip:
                continue
            gmap.integrate(codec.decode(encode(scan, seq, encoding), wire_encoding).scan)
            n += 1
    return gmap, n


def map_stats(http: httpx.Client, map_id: str) -> dict[str, Any]:
    response = http.get(f"/maps/{map_id}")
    if response.status_code == 404:
        return {}
    response.raise_for_status()
    return response.json()["stats"]


def wait_integrated(http: httpx.Client, map_id: str, n: int, timeout: float = 60.0) -> dict[str, Any]:
    """The map's stats once at least `n` scans are integrated (AssertionError with the last stats)."""
    last: dict[str, Any] = {}

    def done() -> bool:
        nonlocal last
        last = map_stats(http, map_id)
        return bool(last) and last["scans_integrated"] >= n

    try:
        wait_for(done, timeout=timeout, what=f"{n} scans integrated on {map_id}")
    except AssertionError:
        raise AssertionError(f"{n} scans not integrated on {map_id} in {timeout} s; stats: {last}") from None
    return last


def region_npy(http: httpx.Client, map_id: str, layer: str, window: tuple[int, int, int, int],
               resolution: float) -> np.ndarray:  # fmt: skip
    """GET /region as npy for cells [i0, i1) x [j0, j1): bounds at cell centres so floor() is exact."""
    i0, j0, i1, j1 = window
    params = {
        "xmin": (i0 + 0.5) * resolution, "ymin": (j0 + 0.5) * resolution,
        "xmax": (i1 + 0.5) * resolution, "ymax": (j1 + 0.5) * resolution,
        "layer": layer, "format": "npy",
    }  # fmt: skip
    response = http.get(f"/maps/{map_id}/region", params=params)
    assert response.status_code == 200, response.text
    assert response.headers["x-fleetmap-window"] == f"{i0},{j0},{i1},{j1}"
    return np.load(io.BytesIO(response.content), allow_pickle=False)


def assert_region_equal(http: httpx.Client, map_id: str, want: GridMap, layers: tuple[str, ...]) -> None:
    """The served map observed exactly the engine's window of cells, and each layer over it is
    identical (NaN where unknown)."""
    window = want.known_bounds()
    assert window is not None
    res = want.resolution
    assert map_stats(http, map_id)["bounds"] == pytest.approx([v * res for v in window])
    for layer in layers:
        got = region_npy(http, map_id, layer, window, want.resolution)
        expected = want.region(layer, *window)
        assert got.shape == expected.shape and got.dtype == expected.dtype, layer
        np.testing.assert_array_equal(got, expected, err_msg=f"{map_id} {layer}")


def assert_cells_equal(http: httpx.Client, map_id: str, want: GridMap, layers: tuple[str, ...],
                       n: int = 3000, seed: int = 0) -> None:  # fmt: skip
    """POST /cells at `n` random cell centres in (and a margin around) the known window; every
    field of every point equals the engine's."""
    i0, j0, i1, j1 = want.known_bounds()
    rng = np.random.default_rng(seed)
    res = want.resolution
    ci = rng.integers(i0 - 20, i1 + 20, n)
    cj = rng.integers(j0 - 20, j1 + 20, n)
    points = np.stack([(ci + 0.5) * res, (cj + 0.5) * res], axis=1)
    response = http.post(f"/maps/{map_id}/cells", json={"points": points.tolist()})
    assert response.status_code == 200, response.text
    got = response.json()
    ref = want.cells(points)
    assert got["i"] == ci.tolist() and got["j"] == cj.tolist()
    for name in ("hits", "misses", "tsdf_weight"):
        if name in layers:
            np.testing.assert_array_equal(np.asarray(got[name], dtype=ref[name].dtype), ref[name], name)
    if "tsdf" in layers:
        tsdf = np.array([math.nan if v is None else v for v in got["tsdf"]], dtype=np.float32)
        np.testing.assert_array_equal(tsdf, ref["tsdf"], "tsdf")
    if "log_odds" in layers:
        assert got["known"] == ref["known"].tolist()
        log_odds = np.array([math.nan if v is None else v for v in got["log_odds"]], dtype=np.float32)
        np.testing.assert_array_equal(log_odds, ref["log_odds"], "log_odds")
        np.testing.assert_array_equal(np.asarray(got["probability"], dtype=np.float32), ref["probability"])
        assert got["state"] == [STATE_NAMES[int(s)] for s in ref["state"]]


def run_robots(service: ServiceProcess, log_dir: Path, robots: list[tuple[str, str, dict[str, Any]]]
               ) -> list[RobotProcess]:  # fmt: skip
    """Start every robot at once (separate processes), then wait for all of them to finish."""
    procs = [
        RobotProcess(service.zenoh_endpoint, map_id, robot_id, log_dir=log_dir, **opts).start()
        for map_id, robot_id, opts in robots
    ]
    try:
        for proc in procs:
            proc.wait(timeout=120)
    finally:
        for proc in procs:
            proc.stop()
    return procs


# -- tests -----------------------------------------------------------------------------------------


def test_several_robots_on_one_map_and_on_different_maps_at_once(
    service: ServiceProcess, http: httpx.Client, tmp_path: Path
) -> None:
    """Four robot processes at once: two share a map, two have a map each (one JSON, one binary).
    Single-robot maps equal the engine's map in every layer; the shared map's counts (and its
    occupancy, unclamped integer log-odds, where order cannot matter) equal the engine's."""
    # Integer log-odds, no clamping within reach: the shared map's occupancy is order-independent.
    unclamped = MapConfig.model_validate(
        {"occupancy": {"l_hit": 2.0, "l_miss": -1.0, "l_min": -1e6, "l_max": 1e6}}
    )
    response = http.put("/maps/e2e-shared", json=unclamped.model_dump(mode="json"))
    assert response.status_code in (200, 201), response.text
    shared_a = {"sim": 11, "count": 40, "skip": [5, 6], "duplicate": [10]}
    shared_b = {"sim": 12, "count": 40, "encoding": "json", "rate": 50}
    solo_json = {"sim": 13, "count": 40, "encoding": "json"}
    solo_binary = {"sim": 14, "count": 40, "beams": 1081, "rate": 40}
    run_robots(service, tmp_path, [
        ("e2e-shared", "a", shared_a), ("e2e-shared", "b", shared_b),
        ("e2e-solo-json", "c", solo_json), ("e2e-solo-bin", "d", solo_binary),
    ])  # fmt: skip

    for map_id, robot_id, opts in (("e2e-solo-json", "c", solo_json), ("e2e-solo-bin", "d", solo_binary)):
        want, n = expected_map([opts])
        stats = wait_integrated(http, map_id, n)
        assert stats["scans_integrated"] == n == 40 and stats["scans_rejected"] == 0
        robot = stats["robots"][robot_id]
        counters = (robot["last_seq"], robot["lost"], robot["duplicates"], robot["scans_integrated"])
        assert counters == (39, 0, 0, 40)
        assert_region_equal(http, map_id, want, ALL_LAYERS)
        assert_cells_equal(http, map_id, want, ALL_LAYERS)
        last = scans_for(sim=opts["sim"], beams=opts.get("beams", 361), count=40)[-1].pose
        assert robot["last_pose"] == pytest.approx({"x": last.x, "y": last.y, "theta": last.theta})

    want, n = expected_map([shared_a, shared_b], unclamped)
    stats = wait_integrated(http, "e2e-shared", n)
    assert stats["scans_integrated"] == n == 78
    a, b = stats["robots"]["a"], stats["robots"]["b"]
    assert (a["scans_integrated"], a["lost"], a["duplicates"], a["last_seq"]) == (38, 2, 1, 39)
    assert (b["scans_integrated"], b["lost"], b["duplicates"], b["last_seq"]) == (40, 0, 0, 39)
    assert_region_equal(http, "e2e-shared", want, (*COUNT_LAYERS, "log_odds"))
    assert_cells_equal(http, "e2e-shared", want, (*COUNT_LAYERS, "log_odds"))

    # The server wired the integration-latency hook: /metrics has observations and per-robot counts.
    metrics = http.get("/metrics").text
    assert 'fleetmap_scans_integrated_total{map="e2e-solo-json",robot="c"} 40.0' in metrics
    lines = metrics.splitlines()
    count = next(line for line in lines if line.startswith("fleetmap_integration_seconds_count"))
    assert float(count.split()[-1]) >= 40 + 40 + 78

    # Every robot process has exited: every robot is reported offline.
    for map_id, robot_ids in (("e2e-shared", "ab"), ("e2e-solo-json", "c"), ("e2e-solo-bin", "d")):
        wait_for(
            lambda m=map_id, r=robot_ids: not any(map_stats(http, m)["robots"][x]["online"] for x in r),
            timeout=15, what=f"robots of {map_id} offline",
        )  # fmt: skip


def test_robot_is_online_while_its_process_runs_and_offline_when_it_exits(
    service: ServiceProcess, http: httpx.Client, tmp_path: Path
) -> None:
    """A clean exit and a SIGKILL both take the robot offline (its Zenoh session goes away)."""
    clean = RobotProcess(service.zenoh_endpoint, "e2e-live", "clean", log_dir=tmp_path,
                         sim=21, count=3, linger=-1).start()  # fmt: skip
    killed = RobotProcess(service.zenoh_endpoint, "e2e-live", "killed", log_dir=tmp_path,
                          sim=22, count=3, linger=-1).start()  # fmt: skip
    try:
        clean.wait_published()
        killed.wait_published()

        def online() -> dict[str, bool]:
            return {r: s["online"] for r, s in map_stats(http, "e2e-live").get("robots", {}).items()}

        wait_for(lambda: online() == {"clean": True, "killed": True}, timeout=15, what="both online")
        stats = wait_integrated(http, "e2e-live", 6)
        assert stats["robots"]["clean"]["scans_integrated"] == 3
        assert clean.stop() == 0  # closes its stdin: the robot leaves cleanly
        wait_for(lambda: online() == {"clean": False, "killed": True}, timeout=15, what="clean offline")
        assert killed.proc is not None
        killed.proc.send_signal(signal.SIGKILL)
        killed.proc.wait(10)
        wait_for(lambda: online() == {"clean": False, "killed": False}, timeout=20, what="killed offline")
    finally:
        clean.stop()
        killed.stop()


def test_real_dataset_replayed_through_zenoh_matches_the_engine(
    service: ServiceProcess, http: httpx.Client, tmp_path: Path, datasets_dir: Path
) -> None:
    """The Intel Research Lab log (first 300 scans) published by a robot process at 100 Hz (BLOCK
    congestion control keeps Zenoh from dropping; the rate keeps the service's per-robot queue from
    filling, which would refuse the newest scans): every layer of the served map equals the
    engine's map of the same scans."""
    path = datasets_dir / "intel-corrected.log.gz"
    if not path.exists():
        pytest.skip(f"{path} not found")
    opts = {"dataset": str(path), "start": 0, "count": 300, "rate": 100}
    run_robots(service, tmp_path, [("e2e-intel", "replay", opts)])
    want, n = expected_map([opts])
    assert n == 300
    stats = wait_integrated(http, "e2e-intel", n, timeout=120)
    robot = stats["robots"]["replay"]
    assert (robot["scans_integrated"], robot["lost"], robot["scans_rejected"]) == (300, 0, 0)
    assert_region_equal(http, "e2e-intel", want, ALL_LAYERS)
    assert_cells_equal(http, "e2e-intel", want, ALL_LAYERS, n=5000)


def test_bad_messages_over_zenoh_are_reported_per_robot(
    service: ServiceProcess, http: httpx.Client, tmp_path: Path
) -> None:
    """A garbage payload from a real robot process: counted on the robot with its reason, and the
    service's Zenoh status (in /healthz) counts it."""
    run_robots(service, tmp_path, [("e2e-bad", "r", {"sim": 31, "count": 2})])
    wait_integrated(http, "e2e-bad", 2)
    before = http.get("/healthz").json()["zenoh"]["decode_errors"]
    script = (
        "import sys, zenoh\n"
        "c = zenoh.Config(); c.insert_json5('mode', '\"client\"')\n"
        f"c.insert_json5('connect/endpoints', '[\"{service.zenoh_endpoint}\"]')\n"
        "s = zenoh.open(c)\n"
        "p = s.declare_publisher('fleetmap/e2e-bad/r/scan')\n"
        "import time\n"
        "while not p.matching_status.matching: time.sleep(0.01)\n"
        "p.put(b'{\"seq\": 5}', encoding=zenoh.Encoding.APPLICATION_JSON)\n"
        "time.sleep(0.3); s.close()\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    stats = wait_for(lambda: (s := map_stats(http, "e2e-bad")) and s["scans_rejected"] == 1 and s,
                     timeout=15, what="the rejected scan")  # fmt: skip
    robot = stats["robots"]["r"]
    assert robot["scans_rejected"] == 1 and "pose" in robot["last_error"]
    assert robot["scans_integrated"] == 2 and robot["last_seq"] == 1
    assert http.get("/healthz").json()["zenoh"]["decode_errors"] == before + 1


def test_serve_options_config_and_no_auto_create(service_factory, tmp_path: Path) -> None:  # noqa: ANN001
    """--config sets auto-created maps' configuration; --no-auto-create refuses unknown maps until
    PUT creates them; --workers is accepted."""
    config = tmp_path / "map.json"
    config.write_text(json.dumps({"resolution": 0.1, "tile_size": 64}))
    svc = service_factory("--config", str(config), "--workers", "1")
    with httpx.Client(base_url=svc.base_url, timeout=20.0) as http:
        run_robots(svc, tmp_path, [("auto", "r", {"sim": 41, "count": 3})])
        stats = wait_integrated(http, "auto", 3)
        assert stats["scans_integrated"] == 3
        info = http.get("/maps/auto").json()
        assert info["config"]["resolution"] == 0.1 and info["config"]["tile_size"] == 64
    assert "fleetmap serving http://127.0.0.1:" in svc.logs()
    assert svc.stop() == 0

    strict = service_factory("--no-auto-create")
    with httpx.Client(base_url=strict.base_url, timeout=20.0) as http:
        run_robots(strict, tmp_path, [("manual", "r", {"sim": 42, "count": 3})])
        assert http.get("/maps/manual").status_code == 404
        status = wait_for(lambda: (z := http.get("/healthz").json()["zenoh"])["rejected"] and z,
                          timeout=10, what="the refusals counted")  # fmt: skip
        assert status["rejected"] == {"no_map": 3}
        assert http.put("/maps/manual", json={}).status_code in (200, 201)
        run_robots(strict, tmp_path, [("manual", "r", {"sim": 42, "count": 3})])
        assert wait_integrated(http, "manual", 3)["scans_integrated"] == 3
    assert strict.proc is not None
    strict.proc.send_signal(signal.SIGINT)  # Ctrl-C shuts down as cleanly as SIGTERM
    assert strict.proc.wait(20) == 0, strict.logs()
    assert "Traceback" not in strict.logs()


def test_open_event_streams_end_cleanly_at_shutdown(service_factory, tmp_path: Path) -> None:  # noqa: ANN001
    """SIGTERM with viewers connected: each event stream ends with a last comment and a clean end of
    the body, and the service stops without waiting out its graceful-shutdown timeout (which would
    cancel the streams and log an error with a traceback for each)."""
    svc = service_factory("--in-memory")
    with httpx.Client(base_url=svc.base_url, timeout=20.0) as http:
        assert http.put("/maps/m", json={}).status_code == 201
    received: list[list[str]] = [[], []]
    ended: list[BaseException | None] = [None, None]
    opened = [threading.Event(), threading.Event()]

    def read(k: int) -> None:
        try:
            with httpx.stream("GET", f"{svc.base_url}/maps/m/events", timeout=30) as r:
                for line in r.iter_lines():
                    received[k].append(line)
                    if line.startswith("data:"):
                        opened[k].set()
        except BaseException as exc:  # noqa: BLE001 - reported by the assertions below
            ended[k] = exc

    readers = [threading.Thread(target=read, args=(k,), daemon=True) for k in range(2)]
    for reader in readers:
        reader.start()
    assert all(event.wait(20) for event in opened), received
    assert svc.stop() == 0, svc.logs()
    for reader in readers:
        reader.join(10)
        assert not reader.is_alive()
    for k in range(2):
        assert ended[k] is None, f"stream {k} did not end cleanly: {ended[k]!r}"
        assert received[k][-2:] == [": the server is shutting down", ""], received[k]
    logs = svc.logs()
    assert "timeout graceful shutdown exceeded" not in logs and "Traceback" not in logs, logs
    assert " ERROR " not in logs, logs


def test_serve_errors_exit_2_without_a_traceback(service: ServiceProcess, tmp_path: Path) -> None:
    """An HTTP port in use, a Zenoh port in use, a bad --http, a bad --config and a Zenoh endpoint
    without its protocol: one clear line, exit code 2."""
    bad_config = tmp_path / "bad.json"
    bad_config.write_text('{"resolution": -1}')
    http_in_use = ["--http", f"127.0.0.1:{service.port}", "--zenoh-listen", "tcp/127.0.0.1:0"]
    cases = [
        (http_in_use, "address already in use"),
        (["--http", "127.0.0.1:0", "--zenoh-listen", service.zenoh_endpoint], "Address already in use"),
        (["--http", "nonsense"], "HOST:PORT"),
        (["--http", "127.0.0.1:0", "--config", str(bad_config)], "invalid map configuration"),
        # Without its protocol: Zenoh's own words, not Rust's debug form of them (`Json5Err(Message {`).
        (
            ["--http", "127.0.0.1:0", "--zenoh-listen", "127.0.0.1:7447"],
            "error: invalid Zenoh endpoint: Endpoints must be of the form "
            "<protocol>/<address>[?<metadata>][#<config>]: 127.0.0.1:7447\n",
        ),
        # As a URL: Zenoh took `tcp:` for its protocol ("Unicast not supported for tcp: protocol").
        # Checked as the option is parsed, before maps are loaded.
        (
            ["--http", "127.0.0.1:0", "--zenoh-connect", "tcp://127.0.0.1:7447"],
            "error: argument --zenoh-connect: 'tcp://127.0.0.1:7447' is written as a URL: a Zenoh endpoint "
            "is PROTOCOL/ADDRESS, tcp/127.0.0.1:7447 (see fleetmap serve --help)\n",
        ),
        # Without a port: Zenoh's "invalid socket address" named no endpoint, once every map was loaded.
        (
            ["--http", "127.0.0.1:0", "--zenoh-listen", "tcp/127.0.0.1"],
            "error: argument --zenoh-listen: 'tcp/127.0.0.1' has no port: a Zenoh tcp endpoint is "
            "tcp/HOST:PORT, e.g. tcp/127.0.0.1:7447 (see fleetmap serve --help)\n",
        ),
    ]
    for args, message in cases:
        # --in-memory: these runs must not open (or create) ./fleetmap-data in the working directory.
        command = [sys.executable, "-m", "fleetmap.server", "--in-memory", *args]
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, (args, result.stdout, result.stderr)
        assert message in result.stderr and "fleetmap serve: error:" in result.stderr, result.stderr
        assert "Traceback" not in result.stderr, result.stderr
        assert "fleetmap serving" not in result.stdout


def test_serve_help_documents_the_options() -> None:
    result = subprocess.run([sys.executable, "-m", "fleetmap.server", "--help"], capture_output=True,
                            text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    for option in ("--http", "--zenoh-listen", "--zenoh-connect", "--zenoh-config", "--data-dir", "--config",
                   "--no-auto-create", "--workers"):  # fmt: skip
        assert option in text
