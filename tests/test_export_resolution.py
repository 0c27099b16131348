"""Exports at a coarser resolution than the map's (`GET /maps/{id}/export?resolution=`,
`fleetmap.export.most_occupied`): each exported cell is a block of k x k of the map's cells, aligned
on multiples of k, and shows the block's most occupied known cell.

The reference here reduces the map's whole probability window by strided views (`reference`), not by
blocks of a tile at a time as the export does, and the real service's files are checked against it."""

from __future__ import annotations

import dataclasses
import io
import math
import zipfile

import numpy as np
import pytest
from fleetmap_client import FleetmapClient, FleetmapError
from PIL import Image
from service_process import ServiceProcess
from test_api import post_scan
from test_api_support import fan_scan, running_api

from fleetmap.api.app import ApiSettings
from fleetmap.config import MapConfig
from fleetmap.export import (
    MAX_EXPORT_SCALE,
    Window,
    by_blocks,
    export_resolution,
    export_scale,
    known_window,
    map_image,
    map_probability,
    map_state,
    nav2_files,
    probability_to_gray,
)
from fleetmap.grid_map import GridMap
from fleetmap.nav2_import import map_from_nav2
from fleetmap.scan import Pose2D
from fleetmap.sim import SimulatedRobot, generate_floorplan


def reference(probability: np.ndarray, k: int) -> np.ndarray:
    """`most_occupied` another way: the largest of the k * k strided views of the window, NaN only
    where every cell of a block is NaN."""
    ny, nx = probability.shape
    out = np.full((ny // k, nx // k), np.nan, dtype=probability.dtype)
    for dj in range(k):
        for di in range(k):
            out = np.fmax(out, probability[dj::k, di::k])
    return out


def mapped(tile_size: int, seed: int) -> GridMap:
    """A floor plan mapped by a simulated robot, a few metres either side of 0 (negative cells too)."""
    plan = generate_floorplan(seed, width_m=16.0, height_m=12.0)
    robot = SimulatedRobot(plan, seed=seed, num_beams=181, range_max=8.0)
    gmap = GridMap(MapConfig(resolution=0.05, tile_size=tile_size))
    for _ in range(12):
        scan = robot.tick()
        # The plan spans [0, 16] x [0, 12]: moved across 0, the whole scan with its pose.
        pose = Pose2D(scan.pose.x - 8.0, scan.pose.y - 6.0, scan.pose.theta)
        gmap.integrate(dataclasses.replace(scan, pose=pose))
    return gmap


@pytest.mark.parametrize(("tile_size", "k"), [(256, 2), (256, 3), (64, 5), (16, 20), (32, 1)])
def test_a_coarse_export_shows_each_blocks_most_occupied_cell(tile_size: int, k: int) -> None:
    """Images and nav2 states at k times the resolution, read a few tiles at a time, against the
    reference over the whole window: for block sides that divide the tile size, that do not, and
    that are larger than a tile, on windows across 0."""
    gmap = mapped(tile_size, seed=3)
    window = known_window(gmap, margin=2)
    assert window is not None and window.i0 < 0
    aligned = window.aligned(k)
    assert aligned.i0 % k == 0 and aligned.j1 % k == 0 and aligned.i0 <= window.i0 and aligned.j1 >= window.j1
    expected = reference(gmap.region("probability", aligned.i0, aligned.j0, aligned.i1, aligned.j1), k)
    state = map_state(gmap, aligned, k)
    np.testing.assert_array_equal(state, gmap.classify_probability(expected))
    image = map_image(gmap, aligned, probability_to_gray, k)
    np.testing.assert_array_equal(image, probability_to_gray(expected)[::-1])
    # An obstacle is kept: every block holding an occupied cell is occupied.
    fine = map_state(gmap, aligned)
    occupied_blocks = reference(np.where(fine == 2, 1.0, np.nan), k) == 1.0
    assert occupied_blocks.any() and (state[occupied_blocks] == 2).all()


@pytest.mark.parametrize(
    ("layers", "k"), [(("occupancy",), 1), (("occupancy",), 3), (("counts",), 1), (("counts",), 20)]
)
def test_an_export_of_a_map_written_while_it_is_read_is_of_one_moment(
    layers: tuple[str, ...], k: int
) -> None:
    """An export is read a storage tile at a time (integration never waits long for it), so scans
    land between its reads. Each tile read before a scan that changed it showed the map before it,
    each read after it the map after: 34 of 93 exports of a map one robot wrote matched the map after
    no number of its scans. Here a scan lands after every read of the export (from the `convert` it
    calls on each block read), through all its passes: the image must be the map as it was at one
    of those moments, read afresh."""
    plan = generate_floorplan(5, width_m=16.0, height_m=12.0)
    robot = SimulatedRobot(plan, seed=5, num_beams=181, range_max=8.0)
    gmap = GridMap(MapConfig(resolution=0.05, tile_size=16, layers=layers))
    for _ in range(20):
        gmap.integrate(robot.tick())
    window = known_window(gmap, margin=2)
    assert window is not None
    window = window.aligned(k)

    def now() -> np.ndarray:
        return gmap.classify_probability(reference(map_probability(gmap, window), k))

    moments = [now()]

    def classify_while_a_robot_writes(probability: np.ndarray) -> np.ndarray:
        gmap.integrate(robot.tick())
        moments.append(now())
        return gmap.classify_probability(probability)

    state = by_blocks(gmap, window, k, classify_while_a_robot_writes)
    assert len(moments) > 100 and not np.array_equal(moments[0], moments[-1])
    assert any(np.array_equal(state, moment) for moment in moments)


def test_the_resolution_must_be_a_whole_multiple_of_the_maps() -> None:
    assert export_scale(0.05, 0.05) == 1 and export_scale(0.05, 0.1) == 2 and export_scale(0.05, 0.15) == 3
    assert export_scale(0.05, 0.05 * MAX_EXPORT_SCALE) == MAX_EXPORT_SCALE
    for bad in (0.07, 0.025, 0.05 * (MAX_EXPORT_SCALE + 1), 0.0, -0.1, math.nan, math.inf, 1.65e308, 5e-324):
        with pytest.raises(ValueError, match="resolution"):
            export_scale(0.05, bad)
    assert export_resolution(0.05, 3) == 0.15 and export_resolution(0.05, 1) == 0.05
    assert Window(-5, -1, 7, 9).aligned(4) == Window(-8, -4, 8, 12)


@pytest.mark.parametrize("scale", [0, -1, 2.5, True, "2"])
def test_an_export_scale_that_is_not_a_whole_number_of_cells_is_refused(scale: object) -> None:
    """`map_state`, `map_image`, `nav2_files`, `map_png` (`fleetmap.export`, the library's exports)
    took any scale: 0 was a ZeroDivisionError, -1 numpy's 'negative dimensions are not allowed',
    2.5 "'float' object cannot be interpreted as an integer"."""
    gmap = mapped(64, seed=3)
    window = known_window(gmap)
    assert window is not None
    with pytest.raises(ValueError, match=f"scale must be a whole number of cells >= 1, got {scale!r}"):
        map_state(gmap, window, scale)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="scale must be a whole number"):
        nav2_files(gmap, window, scale=scale)  # type: ignore[arg-type]


def test_a_coarse_export_of_a_window_not_aligned_to_its_blocks_is_refused() -> None:
    """A coarse export reads blocks aligned on multiples of the scale (`Window.aligned`); a window
    that was not failed in numpy ('cannot reshape array of size ... into shape ...'). It is refused,
    saying what to pass; the aligned window exports as before."""
    gmap = mapped(64, seed=3)
    window = known_window(gmap, margin=1)
    assert window is not None and window != window.aligned(4)
    with pytest.raises(ValueError, match=r"not aligned to blocks of 4 cells: pass window.aligned\(4\)"):
        map_state(gmap, window, 4)
    with pytest.raises(ValueError, match="not aligned"):
        map_image(gmap, window, probability_to_gray, 4)
    aligned = window.aligned(4)
    assert map_state(gmap, aligned, 4).shape == (aligned.shape[0] // 4, aligned.shape[1] // 4)
    assert map_state(gmap, window).shape == window.shape  # scale 1: any window


def test_a_coarse_export_states_its_cells_resolution_to_a_float_s_precision() -> None:
    """The resolution of a coarse export was rounded to the nanometre, as the origins are: for a map
    at 0.05000000074505806 (a float32's 0.05, copied from a published map), 3 x is
    0.15000000223517418, and the YAML said 0.150000002, a grid that parts from the exported cells'
    by 1.5e-9 cells a cell: the export of the map 200 m from the origin did not import (its origin
    4e-06 cells off that grid), nor did a 0.0123456789012 m map's 5 m away."""
    for map_resolution in (float(np.float32(0.05)), 0.0123456789012):
        stated = export_resolution(map_resolution, 3)
        assert stated == pytest.approx(3 * map_resolution, rel=1e-14, abs=0)
        gmap = GridMap(MapConfig(resolution=map_resolution, layers=["occupancy"]))
        gmap.store.create([(-16, 0)])
        gmap.store.pools["log_odds"][gmap.store.slots[(-16, 0)], 0:3, 96:102] = 3.0  # cells -4000..-3994
        files = nav2_files(gmap, Window(-4002, 0, -3993, 3), scale=3)
        assert f"resolution: {stated!r}\n" in files["map.yaml"].decode()
        again = map_from_nav2(files["map.yaml"], files["map.pgm"])
        assert again.resolution == stated and again.known_bounds() == (-1334, 0, -1331, 1)


def test_the_service_exports_a_map_at_a_coarser_resolution(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The real service's nav2 files and PNG at 0.15 m from a 0.05 m map: the YAML says 0.15 and an
    origin on the block grid, and every pixel is the reference's over the service's own probability
    window (read with /region); a resolution that is not a whole multiple is refused with 422."""
    plan = generate_floorplan(5, width_m=14.0, height_m=10.0)
    robot = SimulatedRobot(plan, seed=5, num_beams=271, range_max=8.0)
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc, FleetmapClient(svc.base_url) as client:
        client.create_map("m", MapConfig(resolution=0.05))
        for seq in range(10):
            client.post_scan("m", "r", robot.tick(), seq=seq)
        k, res = 3, 0.05
        with zipfile.ZipFile(io.BytesIO(client.export("m", "ros", resolution=0.15))) as zf:
            yaml_text = zf.read("map.yaml").decode()
            pgm = Image.open(io.BytesIO(zf.read("map.pgm")))
        assert "resolution: 0.15\n" in yaml_text
        origin = yaml_text.split("origin: [")[1].split("]")[0].split(", ")
        i0, j0 = round(float(origin[0]) / res), round(float(origin[1]) / res)
        assert i0 % k == 0 and j0 % k == 0
        width, height = pgm.size
        x0, y0 = i0 * res, j0 * res
        x1, y1 = x0 + width * k * res, y0 + height * k * res
        # Cells [floor(xmin / res), floor(xmax / res)): a quarter cell in, whatever the rounding.
        q = res / 4
        probability = client.region("m", x0 + q, y0 + q, x1 + q, y1 + q, layer="probability")
        assert probability.shape == (height * k, width * k)
        expected = reference(probability, k)
        pixels = np.asarray(pgm)[::-1]
        state = np.full(expected.shape, 205)
        with np.errstate(invalid="ignore"):
            state[expected > 0.65] = 0
            state[expected < 0.196] = 254
        np.testing.assert_array_equal(pixels, state)
        assert (pixels == 0).any() and (pixels == 254).any() and (pixels == 205).any()
        png = np.asarray(Image.open(io.BytesIO(client.export("m", "png", resolution=0.15))))
        np.testing.assert_array_equal(png, probability_to_gray(expected)[::-1])
        with pytest.raises(FleetmapError) as refused:
            client.export("m", "ros", resolution=0.07)
        assert refused.value.status == 422 and "times a whole number" in str(refused.value)


def test_the_export_limit_counts_exported_cells() -> None:
    """A map past `max_export_cells` at its own resolution is exported at twice it (a quarter of the
    cells), and the refusal says so."""
    scan = fan_scan(0.0, 0.0, 0.0, [3.0] * 61)
    engine = GridMap(MapConfig())
    engine.integrate(scan)
    i0, j0, i1, j1 = engine.known_bounds()  # type: ignore[misc]
    cells = (i1 - i0 + 4) * (j1 - j0 + 4)  # the export's default margin: 2 cells
    with running_api(ApiSettings(max_export_cells=cells // 2)) as api:
        assert post_scan(api, "big", "r", scan, 0).status_code == 200
        refused = api.client.get("/maps/big/export")
        assert refused.status_code == 413 and "coarser resolution" in refused.json()["detail"]
        coarse = api.client.get("/maps/big/export", params={"resolution": 0.1})
        assert coarse.status_code == 200, coarse.text
    # What an export reads is bounded too: k * k of the map's cells for each it writes.
    with running_api(ApiSettings(max_export_read_cells=cells - 1)) as api:
        assert post_scan(api, "big", "r", scan, 0).status_code == 200
        refused = api.client.get("/maps/big/export", params={"resolution": 0.1})
        assert refused.status_code == 413 and "max_export_read_cells" in refused.json()["detail"]
