"""Seeding a map from a ROS nav2 map (`fleetmap.nav2_import`, `PUT /maps/{id}/import`): map_server's
pixel rules per value and mode, the geometry, every refusal, and the REST route on the real service
(status codes, cells, auth, a restart) and the Python client."""

from __future__ import annotations

import functools
import io
import math
import struct
import threading
import zipfile
import zlib
from pathlib import Path

import httpx
import numpy as np
import pytest
from fleetmap_client.rest import FleetmapClient, FleetmapError, nav2_files_zip
from PIL import Image
from service_process import ServiceProcess
from test_api_support import hostile_zip, padded_zip

from fleetmap import nav2_import
from fleetmap.api.routes_snapshot import ANY_CONFIG, read_for_the_map_there
from fleetmap.config import MapConfig
from fleetmap.datasets import load_dataset
from fleetmap.export import Window, known_window, nav2_files, pgm_bytes
from fleetmap.grid_map import STATE_FREE, STATE_OCCUPIED, STATE_UNKNOWN, GridMap
from fleetmap.memory_budget import MemoryBudget, UploadReservation
from fleetmap.nav2_import import (
    MAX_IMAGE_SIDE,
    Nav2ImportError,
    map_from_nav2,
    map_from_nav2_zip,
)
from fleetmap.upload_spool import UploadStopped

CONFIG = MapConfig(resolution=0.05)
L_MIN, L_MAX = (float(np.float32(v)) for v in CONFIG.occupancy.resolved()[2:])
READ, WRITE = "read-token-0123456789", "write-token-0123456789"


def nav2_yaml(image: str = "map.pgm", **fields: object) -> str:
    """A map_server YAML: map_server's usual fields, overridden (or dropped, with None) by `fields`."""
    values: dict[str, object] = {
        "image": image, "mode": "trinary", "resolution": 0.05, "origin": "[0.0, 0.0, 0.0]", "negate": 0,
        "occupied_thresh": 0.65, "free_thresh": 0.196,
    }  # fmt: skip
    values.update(fields)
    return "".join(f"{key}: {value}\n" for key, value in values.items() if value is not None)


def png(pixels: np.ndarray) -> bytes:
    """A PNG of `pixels`, in the mode its shape and dtype say (uint16: 16-bit grey; 2 channels: LA)."""
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def nav2_zip(yaml_text: str | bytes, files: dict[str, bytes], yaml_name: str = "map.yaml") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(yaml_name, yaml_text)
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def row_map(values: list[int], **fields: object) -> GridMap:
    """A map of one image row of `values` (cells (0, 0), (1, 0), ...), as a PGM."""
    return map_from_nav2(nav2_yaml(**fields), pgm_bytes(np.array([values], dtype=np.uint8)), CONFIG)


def log_odds_row(gmap: GridMap, n: int) -> np.ndarray:
    return gmap.region("log_odds", 0, 0, n, 1)[0]


def logit_clamped(percent: float) -> float:
    p = percent / 100.0
    value = -math.inf if p == 0 else math.inf if p == 1 else math.log(p / (1 - p))
    return float(np.float32(min(max(value, L_MIN), L_MAX)))


# -- map_server's pixel rules ------------------------------------------------------------------------


def test_trinary_pixels_by_value_with_strict_thresholds_as_map_server_computes_them() -> None:
    """occ = 1.0 - v / 255 in double, occupied if occ > occupied_thresh, free if occ < free_thresh.
    0.6 and 0.2 are thresholds some pixels hit exactly: v = 102 gives occ == 0.6 (not occupied:
    strict), and v = 204 gives 1.0 - 0.8 = 0.19999999999999996 < 0.2, free (where (255 - v) / 255
    would say 0.2, unknown: map_server's arithmetic decides)."""
    values = [0, 101, 102, 150, 203, 204, 205, 254, 255]
    gmap = row_map(values, occupied_thresh=0.6, free_thresh=0.2)
    got = log_odds_row(gmap, len(values))
    nan = math.nan
    want = [L_MAX, L_MAX, nan, nan, nan, L_MIN, L_MIN, L_MIN, L_MIN]
    np.testing.assert_array_equal(got, np.array(want, dtype=np.float32))
    # With map_server's usual thresholds, 205 (map_saver's unknown) is unknown, 254 free, 0 occupied.
    usual = log_odds_row(row_map([0, 205, 254]), 3)
    np.testing.assert_array_equal(usual, np.array([L_MAX, nan, L_MIN], dtype=np.float32))
    state = gmap.region("state", 0, 0, len(values), 1)[0]
    assert list(state[:3]) == [STATE_OCCUPIED, STATE_OCCUPIED, STATE_UNKNOWN]
    assert state[-1] == STATE_FREE


def test_negate_reads_dark_pixels_as_free() -> None:
    got = log_odds_row(row_map([0, 205, 255, 100], negate=1), 4)
    # occ = v / 255: 0 free, 205 (0.80) and 255 occupied, 100 (0.39) in between: unknown.
    np.testing.assert_array_equal(got, np.array([L_MIN, L_MAX, L_MAX, math.nan], dtype=np.float32))
    assert np.array_equal(
        log_odds_row(row_map([0, 255], negate="true"), 2), log_odds_row(row_map([0, 255], negate=1), 2)
    )
    # Quoted, as yaml-cpp (map_server's parser) reads it: refused before ("must be an integer").
    for quoted, plain in (('"1"', 1), ("'0'", 0)):
        got = log_odds_row(row_map([0, 255], negate=quoted), 2)
        assert np.array_equal(got, log_odds_row(row_map([0, 255], negate=plain), 2))
    # Not an integer, map_server reads `negate` as yaml-cpp's boolean, whose words PyYAML leaves
    # strings when quoted, or always (y, n): refused before ("must be an integer or a boolean").
    for word, plain in (("y", 1), ("N", 0), ('"true"', 1), ("'Off'", 0), ('"YES"', 1), ("'No'", 0)):
        got = log_odds_row(row_map([0, 255], negate=word), 2)
        assert np.array_equal(got, log_odds_row(row_map([0, 255], negate=plain), 2)), word
    for word in ("yES", '"tRUE"', "si"):  # not in yaml-cpp's flexible case, or not a boolean
        with pytest.raises(Nav2ImportError, match="'negate' must be an integer or a boolean"):
            row_map([0, 255], negate=word)
    # yaml-cpp's integers take their base from the prefix (hex, octal), and fit in an int.
    for text, plain in (("0x1", 1), ('"0X0"', 0), ("010", 1), ("'-07'", 1), ("000", 0), ("+2147483647", 1)):
        got = log_odds_row(row_map([0, 255], negate=text), 2)
        assert np.array_equal(got, log_odds_row(row_map([0, 255], negate=plain), 2)), text
    for text in ("2147483648", '"-2147483649"', "0b1", '"09"', "0x123456789"):
        with pytest.raises(Nav2ImportError, match="'negate' must be an integer or a boolean"):
            row_map([0, 255], negate=text)


def test_scale_mode_publishes_the_rescaled_percentage_and_has_no_unknown_grey() -> None:
    """Between the thresholds, map_server publishes rint((occ - free) / (occ_t - free) * 100) percent;
    that probability, clamped, is the cell. 205 is a grey like any other (0 % here: free)."""
    values = [0, 80, 150, 180, 205, 254]
    got = log_odds_row(row_map(values, mode="scale"), len(values))
    want = []
    for v in values:
        occ = 1.0 - v / 255.0
        if occ > 0.65:
            want.append(L_MAX)
        elif occ < 0.196:
            want.append(L_MIN)
        else:
            want.append(logit_clamped(float(np.rint((occ - 0.196) / (0.65 - 0.196) * 100.0))))
    np.testing.assert_array_equal(got, np.array(want, dtype=np.float32))
    assert L_MIN < got[2] < L_MAX and got[2] != 0.0  # 150 is 48 %: a known cell in between
    assert got[4] == L_MIN  # 205 is 0 %: map_server publishes free
    assert log_odds_row(row_map([205], mode="SCALE"), 1)[0] == L_MIN  # mode names in any case


def test_scale_mode_reads_transparent_pixels_as_unknown() -> None:
    grey = np.array([[0, 0, 254, 128]], dtype=np.uint8)
    alpha = np.array([[255, 0, 254, 255]], dtype=np.uint8)
    image = png(np.dstack([grey, alpha]))
    gmap = map_from_nav2(nav2_yaml("map.png", mode="scale"), image, CONFIG)
    got = log_odds_row(gmap, 4)
    assert got[0] == L_MAX and math.isnan(got[1]) and math.isnan(got[2])
    assert got[3] == logit_clamped(float(np.rint(((1 - 128 / 255) - 0.196) / (0.65 - 0.196) * 100)))


def test_scale_mode_ignores_the_colour_of_pixels_it_reads_as_unknown() -> None:
    """In scale mode map_server reads every pixel that is not opaque as unknown, whatever its
    colour: an RGBA map whose transparent pixels keep a colour (GIMP can save them so) was refused
    as a colour image. Opaque colour is still refused, and in trinary mode, which averages alpha in
    with the colour, any colour."""
    rgba = np.array([[[10, 20, 30, 0], [0, 0, 0, 255], [200, 100, 50, 128]]], dtype=np.uint8)
    got = log_odds_row(map_from_nav2(nav2_yaml("map.png", mode="scale"), png(rgba), CONFIG), 3)
    assert math.isnan(got[0]) and got[1] == L_MAX and math.isnan(got[2])
    opaque = rgba.copy()
    opaque[0, 2, 3] = 255
    with pytest.raises(Nav2ImportError, match=r"colour image \(mode RGBA\): pixel \(2, 0\)"):
        map_from_nav2(nav2_yaml("map.png", mode="scale"), png(opaque), CONFIG)
    with pytest.raises(Nav2ImportError, match=r"colour image \(mode RGBA\): pixel \(0, 0\)"):
        map_from_nav2(nav2_yaml("map.png"), png(rgba), CONFIG)


def test_trinary_mode_averages_alpha_in_as_map_server_does() -> None:
    """With an alpha channel, trinary's shade is (r + g + b + alpha) / 4: an opaque 205 is free."""
    grey = np.array([[0, 205, 205, 254]], dtype=np.uint8)
    alpha = np.array([[255, 255, 0, 255]], dtype=np.uint8)
    for image in (png(np.dstack([grey, alpha])), png(np.dstack([grey, grey, grey, alpha]))):
        got = log_odds_row(map_from_nav2(nav2_yaml("map.png"), image, CONFIG), 4)
        # occ: 1 - (0 + 255) / 1020 = 0.75; 1 - 870 / 1020 = 0.147; 1 - 615 / 1020 = 0.397; 0.004.
        np.testing.assert_array_equal(got, np.array([L_MAX, L_MIN, math.nan, L_MIN], dtype=np.float32))


def test_raw_mode_takes_the_pixel_value_as_percent() -> None:
    got = log_odds_row(row_map([0, 50, 100, 101, 255], mode="raw", negate=1), 5)
    np.testing.assert_array_equal(got[:3], np.array([L_MIN, 0.0, L_MAX], dtype=np.float32))
    assert np.isnan(got[3:]).all()  # past 100: unknown; negate is ignored in raw mode


def test_raw_mode_reads_thresholds_it_does_not_use_whatever_they_are() -> None:
    """Raw mode uses neither threshold (map_server loads a raw map.yaml saved with both 0): such a
    map was refused by the check of their order, which only trinary and scale need. They must
    still be there, numbers, as map_server requires."""
    got = log_odds_row(row_map([0, 100], mode="raw", occupied_thresh=0, free_thresh=0), 2)
    np.testing.assert_array_equal(got, np.array([L_MIN, L_MAX], dtype=np.float32))
    with pytest.raises(Nav2ImportError, match="0 <= free_thresh < occupied_thresh <= 1"):
        row_map([0, 100], mode="scale", occupied_thresh=0, free_thresh=0)
    with pytest.raises(Nav2ImportError, match="map.yaml has no 'free_thresh'"):
        row_map([0, 100], mode="raw", free_thresh=None)


def test_geometry_row_order_negative_origin_png_and_pgm() -> None:
    """Row 0 of the image is the top (highest y); the origin is the lower-left corner of the
    bottom-left pixel, here on the grid at negative coordinates; PNG and PGM read alike."""
    pixels = np.full((3, 4), 205, dtype=np.uint8)
    pixels[0, 0] = 0  # top-left: occupied
    pixels[2, 3] = 254  # bottom-right: free
    yaml_text = nav2_yaml("map.png", origin="[-1.5, -0.75, 0.0]")
    from_png = map_from_nav2(yaml_text, png(pixels), CONFIG)
    from_pgm = map_from_nav2(yaml_text.replace("map.png", "map.pgm"), pgm_bytes(pixels), CONFIG)
    for gmap in (from_png, from_pgm):
        # Bottom-left cell is (-30, -15); the image spans i -30..-27, j -15..-13.
        assert gmap.known_bounds() == (-30, -15, -26, -12)
        cells = gmap.cells([[-1.5 + 0.025, -0.75 + 2 * 0.05 + 0.025], [-1.5 + 3 * 0.05 + 0.025, -0.725]])
        assert list(cells["state"]) == [STATE_OCCUPIED, STATE_FREE]
        assert int(np.isfinite(gmap.region("log_odds", -30, -15, -26, -12)).sum()) == 2
    assert np.array_equal(
        from_png.region("log_odds", -40, -20, 0, 0),
        from_pgm.region("log_odds", -40, -20, 0, 0),
        equal_nan=True,
    )


def test_tiles_only_where_a_cell_is_known_with_versions_and_other_layers_unknown() -> None:
    pixels = np.full((300, 600), 205, dtype=np.uint8)  # three tiles wide, two high at 256 cells
    pixels[-1, 0] = 0  # bottom-left: tile (0, 0)
    pixels[0, 599] = 254  # top-right: tile (2, 1)
    gmap = map_from_nav2(nav2_yaml(), pgm_bytes(pixels), CONFIG)
    assert sorted(gmap.store.keys) == [(0, 0), (2, 1)]
    versions = [gmap.store.version(key) for key in gmap.store.keys]
    assert all(v is not None and v > 0 for v in versions) and len(set(versions)) == 2
    for layer in ("hits", "misses", "tsdf_weight"):  # the configuration's other layers: unknown
        assert not gmap.region(layer, 0, 0, 600, 300).any()
    empty = map_from_nav2(nav2_yaml(), pgm_bytes(np.full((10, 10), 205, dtype=np.uint8)), CONFIG)
    assert len(empty.store) == 0


def test_without_a_configuration_the_default_takes_the_yaml_resolution() -> None:
    gmap = map_from_nav2(
        nav2_yaml(resolution=0.1, origin="[0.3, -0.2, 0]"), pgm_bytes(np.zeros((2, 2), np.uint8))
    )
    assert gmap.resolution == 0.1 and gmap.known_bounds() == (3, -2, 5, 0)
    base = MapConfig(layers=["occupancy"], max_tiles=7)
    gmap = map_from_nav2(nav2_yaml(resolution=0.1), pgm_bytes(np.zeros((2, 2), np.uint8)), defaults=base)
    assert gmap.config.layers == ("occupancy",) and gmap.config.max_tiles == 7 and gmap.resolution == 0.1


# -- the round trip of fleetmap's own export ---------------------------------------------------------


@pytest.fixture(scope="module")
def intel_map() -> GridMap:
    from service_process import DATASETS_DIR

    path = DATASETS_DIR / "intel-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"shared datasets not found: {path} is missing")
    gmap = GridMap(MapConfig(resolution=0.05, layers=["occupancy", "counts"]))
    for scan in load_dataset(path, range_max=8.0):
        gmap.integrate(scan)
    return gmap


def test_an_import_installs_over_a_map_of_its_very_configuration_listed_otherwise() -> None:
    """An import is read for the configuration of the map there when its body is in, and installed
    only over a map of that configuration (else 409: the map changed while it was read). Compared
    with `!=`, a map replaced meanwhile by one of the same configuration, its layers listed in another
    order or its occupancy preset written out as values, refused it. Another configuration still
    does, as does a map made where none was, or none left where one was."""
    read_with = MapConfig(layers=["occupancy", "counts"], occupancy={"preset": "int8"})
    made = read_with
    values = read_with.occupancy.model_dump(exclude={"preset"})
    same = MapConfig(layers=["counts", "occupancy"], occupancy=values)
    assert same != read_with and same.same_map_as(read_with)
    assert read_for_the_map_there(read_with, same, made)
    assert read_for_the_map_there(read_with, read_with, made)
    assert not read_for_the_map_there(read_with, MapConfig(resolution=0.1), made)
    assert not read_for_the_map_there(read_with, None, made)  # deleted meanwhile
    # Read for no map: over one another writer made meanwhile, if it is of what the import made.
    assert not read_for_the_map_there(None, MapConfig(resolution=0.1), made)
    assert read_for_the_map_there(None, same, made)
    assert read_for_the_map_there(None, None, made)
    assert read_for_the_map_there(ANY_CONFIG, MapConfig(resolution=0.1), made)  # a snapshot's own


def test_the_intel_map_exported_and_imported_has_the_same_state_cell_for_cell(intel_map: GridMap) -> None:
    window = known_window(intel_map, margin=2)
    assert window is not None
    files = nav2_files(intel_map, window)
    imported = map_from_nav2(files["map.yaml"], files["map.pgm"], intel_map.config)
    i0, j0, i1, j1 = window.i0, window.j0, window.i1, window.j1
    want = intel_map.region("state", i0, j0, i1, j1)
    got = imported.region("state", i0, j0, i1, j1)
    assert (want == STATE_OCCUPIED).sum() > 10_000 and (want == STATE_FREE).sum() > 100_000
    np.testing.assert_array_equal(got, want)
    # The same origin and extent: exported again, the files are the same bytes.
    assert nav2_files(imported, window) == files
    bounds = imported.known_bounds()
    assert bounds is not None and window.i0 <= bounds[0] and bounds[2] <= window.i1
    assert window.j0 <= bounds[1] and bounds[3] <= window.j1


# -- refusals ------------------------------------------------------------------------------------------

PIXELS = pgm_bytes(np.zeros((2, 2), dtype=np.uint8))


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        (nav2_yaml(resolution=None), "map.yaml has no 'resolution'"),
        (nav2_yaml(resolution="fine"), "'resolution' must be a finite number, got 'fine'"),
        (nav2_yaml(resolution=-0.05), "'resolution' must be positive"),
        (nav2_yaml(origin="[0.0, 0.0]"), "'origin' must be a list of 3 numbers"),
        (nav2_yaml(origin="[0.0, .nan, 0.0]"), "'origin' must be a finite number"),
        (nav2_yaml(origin="[0.0, 0.0, 0.1]"), "origin yaw is 0.1 rad: only maps with yaw 0"),
        (
            nav2_yaml(origin="[0.01, 0.0, 0.0]"),
            "origin x 0.01 is not on the map's cell grid: it is 0.2 cells",
        ),
        (nav2_yaml(origin="[0.0, -0.0726, 0.0]"), "origin y -0.0726 is not on the map's cell grid"),
        (nav2_yaml(occupied_thresh=0.1), "0 <= free_thresh < occupied_thresh <= 1"),
        (nav2_yaml(free_thresh=None), "map.yaml has no 'free_thresh'"),
        (nav2_yaml(negate=None), "map.yaml has no 'negate'"),
        (nav2_yaml(negate="maybe"), "'negate' must be an integer or a boolean"),
        (nav2_yaml(mode="fancy"), "'mode' must be trinary, scale or raw, got 'fancy'"),
        (nav2_yaml(image=None), "'image' must name the image file"),
        (nav2_yaml(resolution=0.1), "resolution 0.1 m differs from the map configuration's 0.05 m"),
        ("[1, 2]", "map.yaml must hold a mapping of fields, not a list"),
        # An empty file (a save cut short) said "not a NoneType", Python's word for nothing.
        ("", "map.yaml is empty: it must hold a mapping of fields"),
        ("# only a comment\n", "map.yaml is empty: it must hold a mapping of fields"),
        ("image: [unclosed", "map.yaml is not valid YAML"),
        # map_server (yaml-cpp) reads the first of two, PyYAML the last: refused, not guessed.
        (nav2_yaml() + "resolution: 0.1\n", "the field 'resolution' is given twice"),
    ],
)
def test_a_bad_yaml_is_refused_naming_the_field(yaml_text: str, message: str) -> None:
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(yaml_text, PIXELS, CONFIG)
    assert message in str(caught.value) and caught.value.status == 422


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        (b"image: map\xff.pgm\n" + nav2_yaml(image=None).encode(), "invalid start byte"),
        (b"\xfe\xff\x00i\x00", "truncated data"),  # a UTF-16 BOM, "i", half a character
        (nav2_yaml(image="map.pgm\x01").encode(), "special characters are not allowed"),
        (nav2_yaml(image="map.pgm\x01"), "special characters are not allowed"),
    ],
)
def test_a_yaml_that_is_not_utf8_text_is_refused_as_such_not_as_a_crash(
    yaml_text: str | bytes, message: str
) -> None:
    """PyYAML's loader decodes the start of its input (4 KB) as it is made: a map.yaml of other bytes
    than UTF-8 (Latin-1, a stray byte) or with a control character raised its ReaderError there,
    before the parse that turns YAML's errors into a refusal, and `PUT .../import` answered 500."""
    for parse in (
        lambda: map_from_nav2(yaml_text, PIXELS, CONFIG),
        lambda: map_from_nav2_zip(nav2_zip(yaml_text, {"map.pgm": PIXELS}), CONFIG),
    ):
        with pytest.raises(Nav2ImportError) as caught:
            parse()
        assert "map.yaml is not valid YAML" in str(caught.value) and message in str(caught.value)
        assert caught.value.status == 422


#: Six levels of ten aliases: a list of 10**6 strings in 250 bytes (nine levels, 10**9, took the
#: service's 18 GB; six fail fast without the fix).
LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{name}: &{name} [{', '.join([f'*{prev}'] * 10)}]\n" for prev, name in zip("abcde", "bcdef", strict=True)
)


@pytest.mark.parametrize("field", ["image", "resolution", "origin", "negate", "mode", "free_thresh"])
def test_aliases_of_lists_are_refused_before_anything_walks_them(field: str) -> None:
    """A billion laughs in any field: before, the error message's repr walked 10**9 strings (18 GB
    of the service's memory, then the OOM killer)."""
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(LAUGHS + nav2_yaml(**{field: "*f"}), PIXELS, CONFIG)
    assert "an alias (*a) of a list or a mapping is not read" in str(caught.value)
    assert caught.value.status == 422 and len(str(caught.value)) < 1000
    # An alias of a scalar is read as its value.
    gmap = map_from_nav2("r: &r 0.05\n" + nav2_yaml(resolution="*r"), PIXELS, CONFIG)
    assert gmap.resolution == 0.05


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        (nav2_yaml(resolution="1" + "0" * 5000), "map.yaml holds a number Python does not read"),
        (nav2_yaml(origin=f"[1{'0' * 400}, 0, 0]"), f"'origin' must be a finite number, got 1{'0' * 76}..."),
        (nav2_yaml(image="1" * 4000), f"'image' must name the image file, got {'1' * 77}..."),
        # Python's int() of more than 4300 decimal digits (a ValueError), quoted or with a zero first.
        (
            nav2_yaml(negate=f'"{"1" * 5000}"'),
            f"'negate' must be an integer or a boolean, got '{'1' * 76}...",
        ),
        (nav2_yaml(negate="0" + "1" * 5000), "'negate' must be an integer or a boolean, got '0111"),
        (nav2_yaml(origin="[1e999, 0, 0]"), "'origin' must be a finite number, got '1e999'"),
        # Finite, but infinite in cells (1.7e308 / 0.05): math.floor's OverflowError, and snapped too.
        (nav2_yaml(origin="[1.7e308, 0, 0]"), "the map reaches beyond the +-1e+07 m the service accepts"),
        (nav2_yaml(origin="[0, -1.7e308, 0]"), "the map reaches beyond the +-1e+07 m the service accepts"),
    ],
)
@pytest.mark.parametrize("snap_origin", [False, True])
def test_huge_numbers_are_refused_as_such_not_as_a_crash(
    yaml_text: str, message: str, snap_origin: bool
) -> None:
    """Before: PyYAML's int() of 5000 digits (a ValueError), float() of a 400-digit integer (an
    OverflowError), the repr of a 6000-digit hex image name (a ValueError; yaml-cpp reads hex as
    text, and so does the import now) and an origin that is infinite in cells (an OverflowError)
    were HTTP 500s."""
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(yaml_text, PIXELS, CONFIG, snap_origin=snap_origin)
    assert message in str(caught.value) and caught.value.status == 422


def test_numbers_are_read_as_yaml_cpp_reads_them() -> None:
    """map_server's yaml-cpp reads `1e-05` (as it writes a small origin) and `2.0e1` as numbers;
    PyYAML's YAML 1.1 resolver leaves both strings, which were refused."""
    gmap = map_from_nav2(nav2_yaml(resolution="5e-2", origin="[2.0e1, -1e-12, 0e0]"), PIXELS, CONFIG)
    assert gmap.resolution == 0.05 and gmap.known_bounds() == (400, 0, 402, 2)


def test_only_the_first_document_of_the_yaml_is_read_as_map_server_reads_it() -> None:
    """map_server's `YAML::LoadFile` reads the file's first document and no further: a map.yaml
    ending in `---` (another document, empty or not, even one that is not valid YAML) loads there,
    and was refused here ("expected a single document in the stream")."""
    want = map_from_nav2(nav2_yaml(), PIXELS, CONFIG).known_bounds()
    for rest in ("---\n", "---\nimage: other.pgm\nresolution: 0.1\n", "...\n---\nbroken: [\n"):
        assert map_from_nav2(nav2_yaml() + rest, PIXELS, CONFIG).known_bounds() == want, rest
    with pytest.raises(Nav2ImportError, match="map.yaml is empty"):  # the first document is empty
        map_from_nav2("---\n---\n" + nav2_yaml(), PIXELS, CONFIG)


def test_tabs_between_the_tokens_are_whitespace_as_yaml_cpp_reads_them() -> None:
    """yaml-cpp (map_server's reader) skips tabs between tokens as it skips spaces: a hand-edited
    map.yaml with a tab after a colon, a tab before a comment, a trailing tab or a tab in the origin's
    list loads in map_server. PyYAML skips only spaces there, and such a file was refused ("found
    character '\\t' that cannot start any token")."""
    want = map_from_nav2(nav2_yaml(origin="[-1.0, 2.0, 0.0]"), PIXELS, CONFIG)
    tabbed = (
        "image:\tmap.pgm\n"
        "mode: trinary\t# the default\n"
        "resolution:\t0.05\t\n"
        "origin: [-1.0,\t2.0, 0.0]\t\n"
        "negate: 0\t\t\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )
    gmap = map_from_nav2(tabbed, PIXELS, CONFIG)
    assert gmap.known_bounds() == want.known_bounds() == (-20, 40, -18, 42)


def test_the_client_zips_a_yaml_with_tabs_between_its_tokens(tmp_path: Path) -> None:
    """The client reads such a map.yaml as the server does (it was "not valid YAML" to it), also to
    write it out again for an image in a folder."""
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "map.pgm").write_bytes(PIXELS)
    (tmp_path / "map.pgm").write_bytes(PIXELS)
    for image in ("map.pgm", "img/map.pgm"):
        yaml_path = tmp_path / "map.yaml"
        yaml_path.write_text(
            f"image:\t{image}\t# the image\n" + nav2_yaml(origin="[-1.0,\t2.0, 0.0]", image=None)
        )
        gmap = map_from_nav2_zip(nav2_files_zip(yaml_path), CONFIG)
        assert gmap.known_bounds() == (-20, 40, -18, 42), image


def test_integers_with_a_leading_zero_are_decimal_as_yaml_cpp_reads_them() -> None:
    """PyYAML's YAML 1.1 reads `010` as octal 8, yaml-cpp's `as<double>()` as 10: `origin: [-010,
    020, 0]` was imported 2 m and 4 m away from where map_server puts it, without a word. Forms
    yaml-cpp reads as no number at all (hex, underscores, sexagesimal: map_server fails to load
    the YAML) are refused, where PyYAML made numbers of them."""
    gmap = map_from_nav2(nav2_yaml(origin="[-010, 020, 00]"), PIXELS, CONFIG)
    assert gmap.known_bounds() == (-200, 400, -198, 402)  # -10 m, 20 m
    on = log_odds_row(row_map([0, 255], negate="01"), 2)  # an integer still: non-zero, true
    assert np.array_equal(on, log_odds_row(row_map([0, 255], negate=1), 2))
    for text in ("0x10", "1_000", "1:30"):
        with pytest.raises(Nav2ImportError, match=f"'origin' must be a finite number, got '{text}'"):
            map_from_nav2(nav2_yaml(origin=f"[0, {text}, 0]"), PIXELS, CONFIG)
    for text in ("0_.05", "0:0.05"):
        with pytest.raises(Nav2ImportError, match=f"'resolution' must be a finite number, got '{text}'"):
            map_from_nav2(nav2_yaml(resolution=text), PIXELS, CONFIG)
    # An image named 0x10 is that file, for yaml-cpp's `as<std::string>()` too: not "an integer".
    with pytest.raises(Nav2ImportError, match="names the image '0x10', which is not in the zip"):
        map_from_nav2_zip(nav2_zip(nav2_yaml(image="0x10"), {"map.pgm": PIXELS}), CONFIG)


def test_a_float32_resolution_printed_in_full_is_the_map_s_resolution() -> None:
    """map_server publishes its resolution as a float32, and a map.yaml written from a published
    0.05 m map (rclpy, `ros2 topic echo /map`) says 0.05000000074505806: that map is a 0.05 m map.
    It was refused against a 0.05 m configuration, and a new map made at 0.05000000074505806 put
    the origin -10.0 2.98e-06 cells off its grid."""
    full = float(np.float32(0.05))
    assert repr(full) == "0.05000000074505806"
    yaml_text = nav2_yaml(resolution=repr(full), origin="[-10.0, -10.0, 0]")
    for config in (CONFIG, None):
        gmap = map_from_nav2(yaml_text, PIXELS, config)
        assert gmap.resolution == 0.05 and gmap.known_bounds() == (-200, -200, -198, -198)
    # A value that is not exactly a float32 is the YAML's own, even within a float32's rounding.
    assert map_from_nav2(nav2_yaml(resolution="0.0500000001"), PIXELS).resolution == 0.0500000001
    assert map_from_nav2(nav2_yaml(resolution="0.03125"), PIXELS).resolution == 0.03125


def test_a_float32_resolution_printed_to_a_float_s_nine_digits_is_the_map_s_resolution() -> None:
    """yaml-cpp's emitter writes a float with 9 significant digits (`max_digits10`): a tool that
    writes map.yaml from a published map's float32 `info.resolution` says 0.0500000007 for a 0.05 m
    map, 0.0250000004 for 0.025 m. map_server publishes such a map at the float32 of 0.05, as it
    does a map.yaml saying 0.05; the import took it for another resolution: refused against a 0.05
    m map, and a new map made at 0.0500000007 put an origin of -10.0 2.8e-06 cells off its grid."""
    for written, resolution in (("0.0500000007", 0.05), ("0.0250000004", 0.025), ("0.100000001", 0.1)):
        assert f"{np.float32(resolution):.9g}" == written
        yaml_text = nav2_yaml(resolution=written, origin="[-10.0, -10.0, 0]")
        for config in (MapConfig(resolution=resolution), None):
            gmap = map_from_nav2(yaml_text, PIXELS, config)
            edge = round(-10.0 / resolution)
            assert gmap.resolution == resolution and gmap.known_bounds() == (edge, edge, edge + 2, edge + 2)
    # A value of 9 digits that is no float32's is the YAML's own.
    assert map_from_nav2(nav2_yaml(resolution="0.0500000008"), PIXELS).resolution == 0.0500000008


def test_a_map_configured_at_a_float32_resolution_printed_in_full_takes_its_own_export_back() -> None:
    """A map made at 0.05000000074505806 m (the resolution copied from a published OccupancyGrid)
    exports it as is; its import read the YAML's value as 0.05 (the float32's shortest decimal),
    and refused it against the map's own configuration: `PUT /maps/{id}/import` of the map's own
    export gave 422. For map_server, whose resolution is a float32, the two are one resolution."""
    config = MapConfig(resolution=float(np.float32(0.05)))
    gmap = GridMap(config)
    gmap.store.create([(-1, -1)])
    gmap.store.pools["log_odds"][gmap.store.slots[(-1, -1)], -3:, -5:] = L_MAX  # cells -5..-1, -3..-1
    files = nav2_files(gmap, Window(-5, -3, 0, 0))
    assert "resolution: 0.05000000074505806\n" in files["map.yaml"].decode()
    again = map_from_nav2(files["map.yaml"], files["map.pgm"], config)
    assert again.resolution == config.resolution and again.known_bounds() == (-5, -3, 0, 0)
    assert nav2_files(again, Window(-5, -3, 0, 0)) == files
    # A value within a part in 10^9 of the configuration's own (no float32) is still its resolution.
    near = map_from_nav2(nav2_yaml(resolution="0.0500000007", origin="[0.0, 0.0, 0]"), PIXELS, config)
    assert near.resolution == config.resolution
    # Another resolution is still refused, saying which.
    with pytest.raises(Nav2ImportError, match="resolution 0.1 m differs from the map configuration's"):
        map_from_nav2(nav2_yaml(resolution="0.1"), PIXELS, config)


def test_an_origin_on_the_grid_of_the_float32_or_the_shortest_resolution_is_on_the_map_s_grid() -> None:
    """0.05 and 0.05000000074505806 are one resolution to the import (map_server publishes a
    float32), but the origin was checked on the map's grid only: the export of a map configured at
    0.05000000074505806, whose origin is -400 of its cells (-20.000000298), was refused by a new
    map, made at 0.05, as 6e-06 cells off its grid (and a 0.05 map's export by a map configured at
    the float32): a copy of any map reaching 3.4 m from the origin was refused."""
    full = float(np.float32(0.05))
    for exported_at, imported_at in ((full, None), (full, CONFIG), (0.05, MapConfig(resolution=full))):
        gmap = GridMap(MapConfig(resolution=exported_at))
        gmap.store.create([(-2, -2)])
        gmap.store.pools["log_odds"][gmap.store.slots[(-2, -2)], 112:115, 112:118] = L_MAX
        files = nav2_files(gmap, Window(-400, -400, -394, -397))
        again = map_from_nav2(files["map.yaml"], files["map.pgm"], imported_at)
        assert again.known_bounds() == (-400, -400, -394, -397)
        assert np.array_equal(again.region("log_odds", -400, -400, -394, -397), np.full((3, 6), L_MAX))


def test_the_off_grid_message_says_by_how_much() -> None:
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(nav2_yaml(origin="[0.0, 1.001, 0.0]"), PIXELS, CONFIG)
    assert "20.02 cells of 0.05 m from 0, 0.02 cells off the nearest cell edge (1 m)" in str(caught.value)
    # Within 1e-6 cells of an edge is on it: a float's rounding.
    assert map_from_nav2(
        nav2_yaml(origin="[-20.200000000000003, 0.1, 0]"), PIXELS, CONFIG
    ).known_bounds() == (-404, 2, -402, 4)


def test_an_origin_off_the_grid_is_moved_to_the_nearest_cell_edge_when_asked() -> None:
    """SLAM tools put a map's origin anywhere (gmapping half a cell off: -51.225 at 0.05 m), and
    map_saver writes it to 3 significant digits (-4.81): such a map was always refused. With
    `snap_origin` it moves to the nearest cell edge, at most half a cell on each axis (half a cell
    off: the edge above), each pixel keeping its place in the image."""
    pixels = np.full((3, 4), 205, dtype=np.uint8)
    pixels[0, 0] = 0  # top-left: occupied
    pixels[2, 3] = 254  # bottom-right: free
    yaml_text = nav2_yaml("map.png", origin="[-51.225, -4.81, 0.0]")
    with pytest.raises(Nav2ImportError, match="unless snap_origin moves it"):
        map_from_nav2(yaml_text, png(pixels), CONFIG)
    gmap = map_from_nav2(yaml_text, png(pixels), CONFIG, snap_origin=True)
    # -1024.5 cells -> -1024 (half a cell: the edge above); -96.2 cells -> -96.
    assert gmap.known_bounds() == (-1024, -96, -1020, -93)
    top_left = (-1024 * 0.05 + 0.025, (-96 + 2) * 0.05 + 0.025)
    bottom_right = ((-1024 + 3) * 0.05 + 0.025, -96 * 0.05 + 0.025)
    assert list(gmap.cells([top_left, bottom_right])["state"]) == [STATE_OCCUPIED, STATE_FREE]
    # An origin on the grid is not moved, snapped or not.
    on_grid = nav2_yaml("map.png", origin="[-1.5, -0.75, 0.0]")
    unmoved = map_from_nav2(on_grid, png(pixels), CONFIG, snap_origin=True)
    assert unmoved.known_bounds() == (-30, -15, -26, -12)


@pytest.mark.parametrize(
    ("image", "message", "status"),
    [
        (png(np.zeros((2, 2), np.uint16)), "is a 16-bit grey image (mode I;16)", 422),
        (
            png(np.array([[[0, 0, 0], [10, 20, 10]]], np.uint8)),
            "colour image (mode RGB): pixel (1, 0) is (10, 20, 10)",
            422,
        ),
        (b"P6\n1 1\n255\n\x00\x10\x00", "colour image (mode RGB): pixel (0, 0) is (0, 16, 0)", 422),
        (b"GIF89a not an image", "is not a PGM or PNG image", 422),
        (png(np.zeros((1, MAX_IMAGE_SIDE + 1), np.uint8)), f"is {MAX_IMAGE_SIDE + 1} x 1 pixels", 413),
    ],
)
def test_images_that_are_not_8_bit_grey_or_too_big_are_refused(
    image: bytes, message: str, status: int
) -> None:
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(nav2_yaml(), image, CONFIG)
    assert message in str(caught.value) and caught.value.status == status


def test_refusals_of_unreadable_images_say_what_the_file_is_and_nothing_of_the_process() -> None:
    """A 16-bit PGM (maxval 65535) opens as Pillow's mode I: the message says a 16-bit PGM reads so.
    Bytes Pillow cannot identify are refused without Pillow's own message, which names the
    in-memory buffer object and its address."""
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(nav2_yaml(), b"P5\n1 1\n65535\n\x01\x00", CONFIG)
    assert "16- or 32-bit integer (a 16-bit PGM reads so) image (mode I" in str(caught.value)
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(nav2_yaml(), b"GIF89a not an image", CONFIG)
    assert str(caught.value) == "map.pgm is not a PGM or PNG image"


def png16(samples: np.ndarray, colour_type: int) -> bytes:
    """A 16-bit PNG (which Pillow does not write) of `samples`, uint16 (height, width, channels),
    in PNG colour type `colour_type`: 2 RGB, 4 grey with alpha, 6 RGBA."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    h, w, _ = samples.shape
    header = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([16, colour_type, 0, 0, 0])
    rows = b"".join(b"\0" + row.astype(">u2").tobytes() for row in samples)  # filter 0 each row
    chunks = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + chunks


@pytest.mark.parametrize(("colour_type", "channels"), [(2, 3), (4, 2), (6, 4)])
def test_a_16_bit_png_with_colour_or_alpha_is_refused_not_read_at_8_bits(
    colour_type: int, channels: int
) -> None:
    """Pillow opens a 16-bit RGB, grey-with-alpha or RGBA PNG as 8-bit RGB / RGBA, the high byte of
    each sample: 52700 / 65535, free for map_server with free_thresh 0.196 (occ 0.19585), was read
    as 205, unknown. Refused, as a 16-bit grey PNG is."""
    samples = np.full((1, 2, channels), 65535, np.uint16)
    samples[0, 0, : 3 if channels >= 3 else 1] = 52700
    with pytest.raises(Nav2ImportError, match="map.png is a 16-bit PNG .* only 8-bit grey images are read"):
        map_from_nav2(nav2_yaml("map.png"), png16(samples, colour_type), CONFIG)


def test_a_pgm_whose_maxval_is_not_255_is_refused() -> None:
    """Pillow rounds a maxval-100 PGM's 50 to 128 (0.502), where map_server has 0.5: in scale mode
    (thresholds 0.65 / 0.196) 39 of 100 was published as 92 % instead of 91 %, and at a threshold a
    pixel changed class. Such a PGM (binary or plain, grey or colour) is refused, as a 16-bit one
    is; maxval 255 is read, plain (P2) as binary (P5)."""
    for image in (b"P5\n3 1\n100\n\x00\x27\x64", b"P2\n3 1\n100\n0 39 100\n"):
        with pytest.raises(Nav2ImportError, match="map.pgm is a PGM whose maxval is 100, not 255"):
            map_from_nav2(nav2_yaml(mode="scale"), image, CONFIG)
    with pytest.raises(Nav2ImportError, match="is a PPM whose maxval is 15, not 255"):
        map_from_nav2(nav2_yaml(), b"P6 1 1 15 \x00\x00\x00", CONFIG)
    plain = map_from_nav2(nav2_yaml(), b"P2\n# hand-made\n3 1\n255\n0 205 254\n", CONFIG)
    np.testing.assert_array_equal(log_odds_row(plain, 3), log_odds_row(row_map([0, 205, 254]), 3))


def png_claiming(width: int, height: int) -> bytes:
    """A 1 x 1 grey PNG whose header (IHDR, with a valid CRC) says `width` x `height`."""
    data = bytearray(png(np.zeros((1, 1), np.uint8)))
    at = data.index(b"IHDR")
    data[at + 4 : at + 12] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[at + 17 : at + 21] = zlib.crc32(bytes(data[at : at + 17])).to_bytes(4, "big")
    return bytes(data)


def test_an_image_past_the_pixel_bound_is_refused_from_its_header() -> None:
    """8193 x 8193 is within the side bound but past 2**26 pixels: refused before any pixel is
    decoded (the file holds one)."""
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2(nav2_yaml("map.png"), png_claiming(8193, 8193), CONFIG)
    assert "is 8193 x 8193 pixels" in str(caught.value) and caught.value.status == 413


def saved(im: Image.Image, image_format: str = "PNG", **options: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format=image_format, **options)
    return buf.getvalue()


def test_a_grey_palette_png_and_a_1_bit_png_read_as_map_server_reads_them() -> None:
    """A PNG optimiser (optipng, oxipng, pngquant) stores a trinary map's three greys as a palette of
    three colours at 2 bits a pixel, and a map of only walls and free space drawn by hand is often a
    1-bit PNG: map_server reads each pixel's colour (its palette entry's; a 1-bit sample at full
    scale, 1 as white) and loads both as it loads the 8-bit grey PNG, pixel for pixel. Both were
    refused ("only 8-bit grey images are read"), though 2- and 4-bit grey PNGs were read."""
    grey = np.array([[0, 205, 254, 205], [254, 254, 0, 205]], dtype=np.uint8)
    want = map_from_nav2(nav2_yaml("map.png"), png(grey), CONFIG)
    window = (-1, -1, 5, 3)
    palette = Image.fromarray(grey).convert("P", palette=Image.Palette.ADAPTIVE, colors=3)
    assert palette.mode == "P" and len(palette.getcolors() or ()) == 3
    got = map_from_nav2(nav2_yaml("map.png"), saved(palette, bits=2), CONFIG)
    assert np.array_equal(got.region("log_odds", *window), want.region("log_odds", *window), equal_nan=True)
    walls = np.array([[0, 255, 255], [255, 0, 255]], dtype=np.uint8)
    bilevel = Image.fromarray(walls).convert("1")
    got = map_from_nav2(nav2_yaml("map.png"), saved(bilevel), CONFIG)
    want = map_from_nav2(nav2_yaml("map.png"), png(walls), CONFIG)
    assert np.array_equal(got.region("log_odds", *window), want.region("log_odds", *window), equal_nan=True)
    assert list(got.cells([[0.025, 0.075], [0.075, 0.075]])["state"]) == [STATE_OCCUPIED, STATE_FREE]


def test_palette_images_with_colour_and_other_formats_bilevel_images_are_refused_saying_what_they_are() -> (
    None
):
    """A palette PNG is read only where the colours its pixels use are grey (the message names the
    first pixel that is not, and the mode); one with a transparent colour, as a grey PNG with one, and
    a 1-bit PBM (not a PGM or a PNG) are refused."""
    coloured = Image.fromarray(np.array([[[0, 0, 0], [10, 20, 10]]], np.uint8)).convert(
        "P", palette=Image.Palette.ADAPTIVE
    )
    for image, words in (
        (saved(coloured), "colour image (mode P): pixel (1, 0) is (10, 20, 10)"),
        (saved(coloured, transparency=0), "marks a transparent colour (a tRNS chunk)"),
        (saved(Image.new("1", (2, 2)), "PPM"), "1-bit black and white"),
    ):
        with pytest.raises(Nav2ImportError) as caught:
            map_from_nav2(nav2_yaml(), image, CONFIG)
        assert words in str(caught.value)


def test_more_tiles_than_max_tiles_or_than_the_memory_budget_is_refused_before_allocating() -> None:
    pixels = pgm_bytes(np.zeros((1, 300), dtype=np.uint8))  # two tiles of 256
    with pytest.raises(
        Nav2ImportError, match="needs 2 tiles of 256 x 256 cells, more than the configuration's max_tiles 1"
    ):
        map_from_nav2(nav2_yaml(), pixels, MapConfig(resolution=0.05, max_tiles=1))
    budget = MemoryBudget(1000)
    with pytest.raises(
        Nav2ImportError,
        match=r"the map's 2 tiles need 2\.5 MiB, and the service's memory budget .* has 1000 bytes free",
    ) as caught:
        map_from_nav2(nav2_yaml(), pixels, CONFIG, reservation=UploadReservation(budget, None))
    assert caught.value.status == 507 and budget.used == 0
    with pytest.raises(Nav2ImportError, match="keeps no occupancy layer"):
        map_from_nav2(nav2_yaml(), pixels, MapConfig(resolution=0.05, layers=["counts"]))


def test_a_default_configuration_without_occupancy_is_named_as_the_servers_default() -> None:
    """A nav2 map imported under a new id takes the server's default configuration (`--config`,
    docs/api.md): when that keeps no occupancy layer, the refusal said "the map configuration keeps
    no occupancy layer", of a map that does not exist, and not how to import it. It names the
    default, and the way: make the map with `PUT /maps/{map_id}` first."""
    pixels = pgm_bytes(np.zeros((2, 2), dtype=np.uint8))
    with pytest.raises(Nav2ImportError) as refused:
        map_from_nav2(nav2_yaml(), pixels, defaults=MapConfig(layers=["tsdf"]))
    reason = str(refused.value)
    assert "server's default configuration (--config)" in reason and "keeps no occupancy layer" in reason
    assert "PUT /maps/{map_id}" in reason, reason
    with pytest.raises(Nav2ImportError) as of_the_map:
        map_from_nav2(nav2_yaml(), pixels, MapConfig(resolution=0.05, layers=["counts"]))
    assert "the map's configuration keeps no occupancy layer (layers counts)" in str(of_the_map.value)
    with pytest.raises(Nav2ImportError) as too_fine:  # its TSDF band of 5 m is 500 cells of 0.01 m
        map_from_nav2(nav2_yaml(resolution=0.01), pixels, defaults=MapConfig(tsdf={"truncation": 5.0}))
    reason = str(too_fine.value)
    assert reason.startswith("map.yaml resolution 0.01 does not suit the server's default configuration")
    assert "tsdf.truncation 5 m is more than 256 cells" in reason and "Value error" not in reason, reason


def transparent_png(width: int, height: int) -> bytes:
    """An RGBA PNG of `width` x `height` fully transparent pixels, made a row at a time (260 KB for
    64 Mpixels: every pixel is unknown in scale mode, so its map has no tile)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row = bytes(1 + 4 * width)  # filter 0, then every channel 0
    packer = zlib.compressobj(9)
    idat = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    head = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)  # 8 bits, RGBA, not interlaced
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def peak_rss_mib(pid: int) -> float:
    """The peak resident memory of process `pid` since it started or since `reset_peak_rss`, in MiB."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith("VmHWM:")).split()[1]) / 1024


def reset_peak_rss(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM back to the present resident memory


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's /proc/PID/clear_refs")
def test_imports_sent_together_decode_one_image_at_a_time(tmp_path: Path) -> None:
    """Decoding an image takes memory outside the tiles' budget (`--max-memory`): a 64-Mpixel image
    with alpha takes 256 MiB decoded. Four zips of 260 KB each, a transparent 64-Mpixel PNG (no
    known cell, so no tile and nothing reserved), sent at once, took the service 2.8 GB past a
    budget of 64 MiB, each decoding at once and copying its image whole into numpy; one image is
    now read at a time, a strip at a time, and the peak stays within what one decode takes."""
    body = nav2_zip(nav2_yaml("map.png", mode="scale"), {"map.png": transparent_png(8192, 8192)})
    assert len(body) < 1 << 20
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "64MiB"]) as svc:
        pid = svc.proc.pid  # type: ignore[union-attr]
        reset_peak_rss(pid)
        before = peak_rss_mib(pid)
        answers: list[httpx.Response] = []
        put = functools.partial(httpx.put, headers={"content-type": "application/zip"}, timeout=300)
        threads = [
            threading.Thread(
                target=lambda k=k: answers.append(put(f"{svc.base_url}/maps/m{k}/import", content=body))
            )
            for k in range(4)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(300)
        assert sorted(r.status_code for r in answers) == [201] * 4, [r.text for r in answers]
        assert all(r.json()["stats"]["tiles"] == 0 for r in answers)
        grown = peak_rss_mib(pid) - before
        assert grown < 600, f"the service's peak grew by {grown:.0f} MiB for four imports of no tile"
        assert "Traceback" not in svc.logs(), svc.logs()


def test_a_reader_waits_for_the_decoding_turn_and_stops_waiting_when_told() -> None:
    """A reader waits for the image being read before its own (the process's one decoding turn),
    then reads; told to stop while it waits (its upload's request ended), it stops there, so the
    process's exit does not wait for its turn."""
    stop = threading.Event()
    stop.set()
    with nav2_import._DECODING:  # another image is being read
        with pytest.raises(UploadStopped):
            map_from_nav2(nav2_yaml(), PIXELS, CONFIG, stop=stop)
        with pytest.raises(UploadStopped):
            map_from_nav2_zip(nav2_zip(nav2_yaml(), {"map.pgm": PIXELS}), CONFIG, stop=stop)
        done: list[GridMap] = []
        waiting = threading.Thread(target=lambda: done.append(map_from_nav2(nav2_yaml(), PIXELS, CONFIG)))
        waiting.start()
        waiting.join(0.3)
        assert not done  # still waiting: the turn is held
    waiting.join(30)
    assert len(done) == 1 and len(done[0].store) == 1


@pytest.mark.parametrize(
    ("body", "message", "status"),
    [
        (b"not a zip", "the body is not a zip file", 415),
        (
            nav2_zip(nav2_yaml(), {"map.pgm": PIXELS, "other.yaml": b"image: x"}),
            "exactly one .yaml file, it holds 2",
            422,
        ),
        (nav2_zip(nav2_yaml(), {}, yaml_name="map.txt"), "exactly one .yaml file, it holds 0 (none)", 422),
        (
            nav2_zip(nav2_yaml("../map.pgm"), {"map.pgm": PIXELS}),
            "'image' '../map.pgm' is not a plain file name",
            422,
        ),
        (
            nav2_zip(nav2_yaml("/etc/map.pgm"), {"map.pgm": PIXELS}),
            "'/etc/map.pgm' is not a plain file name",
            422,
        ),
        (nav2_zip(nav2_yaml("sub/map.pgm"), {"sub/map.pgm": PIXELS}), "is not a plain file name", 422),
        (nav2_zip(nav2_yaml(".."), {}), "'..' is not a plain file name", 422),
        (
            nav2_zip(nav2_yaml("floor.pgm"), {"map.pgm": PIXELS}),
            "names the image 'floor.pgm', which is not in the zip",
            422,
        ),
    ],
)
def test_a_bad_zip_is_refused(body: bytes, message: str, status: int) -> None:
    with pytest.raises(Nav2ImportError) as caught:
        map_from_nav2_zip(body, CONFIG)
    assert message in str(caught.value) and caught.value.status == status


@pytest.mark.parametrize("how", ["utf-8 name", "before the start", "zip64 offset"])
@pytest.mark.parametrize("member", ["map.yaml", "map.pgm"])
def test_a_zip_whose_headers_zipfile_reads_only_when_opening_a_member_is_refused_not_a_500(
    how: str, member: str
) -> None:
    """A local name flagged UTF-8 that is not, an offset before the file's start or past what a seek
    takes: zipfile raises UnicodeDecodeError, ValueError, OverflowError when the member is opened,
    which were 500s. Refused as a corrupt member (422), or offsets as no zip at all (415)."""
    body = hostile_zip(nav2_zip(nav2_yaml(), {"map.pgm": PIXELS}), member, how)
    with pytest.raises(ValueError) as refused:
        map_from_nav2_zip(body, CONFIG)
    assert isinstance(refused.value, Nav2ImportError), repr(refused.value)
    assert refused.value.status == (422 if how == "utf-8 name" else 415), refused.value


def test_a_zip_of_too_many_entries_is_refused_before_zipfile_lists_them() -> None:
    """A central directory over 1 MiB (zipfile makes an object of every entry when it opens a zip) is
    refused as no zip this service reads; within it, entries beside the YAML and its image are not
    read."""
    body = nav2_zip(nav2_yaml(), {"map.pgm": PIXELS})
    with pytest.raises(Nav2ImportError, match="its central directory is [0-9]+ bytes") as refused:
        map_from_nav2_zip(padded_zip(body, 21_000), CONFIG)
    assert refused.value.status == 415
    assert map_from_nav2_zip(padded_zip(body, 100), CONFIG).known_bounds() == (0, 0, 2, 2)


def test_a_zip_entry_with_an_empty_name_is_not_read() -> None:
    """An entry whose name is empty (a damaged or hand-made zip): zipfile's `is_dir` raised
    IndexError for it, a 500 from PUT /maps/{id}/import. It is neither the YAML nor its image."""
    buf = io.BytesIO(nav2_zip(nav2_yaml(), {"map.pgm": PIXELS}))
    with zipfile.ZipFile(buf, "a") as zf:
        zf.writestr(zipfile.ZipInfo(""), b"nameless")  # (a str name "" fails in zipfile itself)
    assert "" in zipfile.ZipFile(buf).namelist()
    assert map_from_nav2_zip(buf.getvalue(), CONFIG).known_bounds() == (0, 0, 2, 2)


def test_a_zip_with_the_yaml_in_a_folder_reads_the_image_beside_it() -> None:
    body = nav2_zip(
        nav2_yaml("map.pgm"), {"maps/map.pgm": PIXELS, "map.pgm": b"decoy"}, yaml_name="maps/site.yml"
    )
    assert map_from_nav2_zip(body, CONFIG).known_bounds() == (0, 0, 2, 2)


def test_a_zip_holding_its_image_twice_is_refused_not_read_from_the_first() -> None:
    """A zip may hold two entries of one name: Python's zipfile appending a file to a zip adds one
    (with a warning), as some tools updating a zip do. unzip and zipfile itself read the last; the
    import read the first, so a map.pgm updated so was imported as it was before, without a word."""
    buf = io.BytesIO(nav2_zip(nav2_yaml(), {"map.pgm": pgm_bytes(np.full((1, 2), 254, np.uint8))}))
    with zipfile.ZipFile(buf, "a") as zf, pytest.warns(UserWarning, match="Duplicate name"):
        zf.writestr("map.pgm", pgm_bytes(np.zeros((1, 2), np.uint8)))  # the map updated: occupied
    with pytest.raises(Nav2ImportError, match=r"the zip holds the image 'map\.pgm' 2 times") as caught:
        map_from_nav2_zip(buf.getvalue(), CONFIG)
    assert caught.value.status == 422


def test_an_image_name_zipped_as_utf_8_without_the_zip_s_utf_8_flag_is_found() -> None:
    """Info-ZIP's `zip`, the usual zip of Linux, stores a name as its UTF-8 bytes without the flag
    that says so, and zipfile reads such a name as code page 437 ('B├╝ro.pgm'): `image: Büro.pgm`
    was refused as not in the zip, though unzip gives map_server that very file."""
    body = nav2_zip(nav2_yaml("Büro.pgm"), {"mxx/Bxxro.pgm": PIXELS}, yaml_name="mxx/site.yaml")
    # As Info-ZIP writes them: the names' UTF-8 bytes (as long), in the local headers and the directory.
    body = body.replace(b"Bxxro.pgm", "Büro.pgm".encode()).replace(b"mxx/", "mä/".encode())
    with zipfile.ZipFile(io.BytesIO(body)) as zf:
        assert [i.filename for i in zf.infolist()] == ["m├ñ/site.yaml", "m├ñ/B├╝ro.pgm"]
    assert map_from_nav2_zip(body, CONFIG).known_bounds() == (0, 0, 2, 2)


def test_a_zip_whose_folders_are_written_with_backslashes_reads_the_image_beside_the_yaml() -> None:
    """Windows PowerShell's Compress-Archive writes `maps\\site.yaml`, a backslash between folder and
    file, which unzip reads as a folder in a zip made on Windows: the image beside the YAML was
    looked for as `map.pgm`, at the top, and refused as not in the zip."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in (("maps\\site.yaml", nav2_yaml("map.pgm")), ("maps\\map.pgm", PIXELS)):
            info = zipfile.ZipInfo(name)
            info.create_system = 0  # made on Windows (MS-DOS, FAT): unzip reads a backslash as a '/'
            zf.writestr(info, data)
    assert map_from_nav2_zip(buf.getvalue(), CONFIG).known_bounds() == (0, 0, 2, 2)


def test_an_image_written_dot_slash_name_is_the_file_beside_the_yaml() -> None:
    """`image: ./map.pgm`, as hand-written map.yaml files often say, is map.pgm beside the YAML to
    map_server (the YAML's folder + '/' + the name): it was refused as not a plain file name."""
    for image in ("./map.pgm", "././map.pgm"):
        body = nav2_zip(nav2_yaml(image), {"maps/map.pgm": PIXELS}, yaml_name="maps/site.yaml")
        assert map_from_nav2_zip(body, CONFIG).known_bounds() == (0, 0, 2, 2)
    for image, shown in (("./sub/map.pgm", "'./sub/map.pgm'"), ("./", "'./'"), ("./..", "'./..'")):
        with pytest.raises(Nav2ImportError, match=f"'image' {shown} is not a plain file name"):
            map_from_nav2_zip(nav2_zip(nav2_yaml(image), {"sub/map.pgm": PIXELS}), CONFIG)


def test_the_apple_double_files_of_a_zip_made_by_macos_are_not_read() -> None:
    """macOS's Finder zips a folder `maps` with `__MACOSX/maps/._site.yaml` beside `maps/site.yaml`
    (AppleDouble attributes, not YAML): the zip was refused as holding two .yaml files."""
    apple_double = b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        "
    body = nav2_zip(
        nav2_yaml("map.pgm"),
        {"maps/map.pgm": PIXELS, "__MACOSX/maps/._site.yaml": apple_double, "__MACOSX/maps/._map.pgm": b""},
        yaml_name="maps/site.yaml",
    )
    assert map_from_nav2_zip(body, CONFIG).known_bounds() == (0, 0, 2, 2)


# -- over HTTP ---------------------------------------------------------------------------------------


def put_import(url: str, body: bytes, headers: dict[str, str] | None = None) -> httpx.Response:
    return httpx.put(
        f"{url}/import", params={"format": "ros"}, content=body,
        headers={"content-type": "application/zip", **(headers or {})}, timeout=60,
    )  # fmt: skip


def cell_states(url: str, points: list[tuple[float, float]]) -> list[tuple[str, float | None]]:
    out = []
    for x, y in points:
        r = httpx.get(f"{url}/cell", params={"x": x, "y": y}, timeout=10)
        assert r.status_code == 200, r.text
        out.append((r.json()["state"], r.json()["log_odds"]))
    return out


def test_import_over_http_creates_replaces_refuses_and_survives_a_restart(tmp_path: Path) -> None:
    pixels = np.full((40, 30), 205, dtype=np.uint8)
    pixels[5:10, 3:20] = 0
    pixels[20:35, 2:28] = 254
    pixels[12, 12] = 150
    body = nav2_zip(
        nav2_yaml("map.pgm", origin="[-0.5, -1.0, 0]", mode="scale"), {"map.pgm": pgm_bytes(pixels)}
    )
    engine = map_from_nav2_zip(body, defaults=MapConfig())
    points = [
        (-0.5 + (i + 0.5) * 0.05, -1.0 + (j + 0.5) * 0.05) for i in range(0, 30, 3) for j in range(0, 40, 3)
    ]
    points.append((-0.5 + 12.5 * 0.05, -1.0 + (40 - 12 - 0.5) * 0.05))  # the 48 % pixel
    want = engine.cells(points)
    svc = ServiceProcess(tmp_path).start()
    data_dir = tmp_path / f"data-{svc.port}"
    try:
        url = f"{svc.base_url}/maps/site"
        r = put_import(url, body)
        assert r.status_code == 201, r.text
        assert r.headers["location"] == "/maps/site" and r.json()["id"] == "site"
        assert r.json()["stats"]["tiles"] == len(engine.store)
        got = cell_states(url, points)
        names = {STATE_UNKNOWN: "unknown", STATE_FREE: "free", STATE_OCCUPIED: "occupied"}
        assert [s for s, _ in got] == [names[int(s)] for s in want["state"]]
        for (_, log_odds), expected in zip(got, want["log_odds"], strict=True):
            assert (log_odds is None and np.isnan(expected)) or log_odds == pytest.approx(
                float(expected), abs=1e-6
            )
        assert {"occupied", "free", "unknown"} <= {s for s, _ in got}
        assert put_import(url, body).status_code == 200  # replaced
        # Refusals change nothing and create nothing.
        r = put_import(
            f"{svc.base_url}/maps/bad", nav2_zip(nav2_yaml(origin="[0, 0, 1.57]"), {"map.pgm": PIXELS})
        )
        assert r.status_code == 422 and "origin yaw is 1.57 rad" in r.json()["detail"], r.text
        r = put_import(f"{svc.base_url}/maps/bad", b"not a zip")
        assert r.status_code == 415 and "not a zip file" in r.json()["detail"]
        r = httpx.put(f"{svc.base_url}/maps/bad/import", content=body, headers={"content-type": "text/plain"})
        assert r.status_code == 415 and "Content-Type: application/zip" in r.json()["detail"]
        r = put_import(f"{svc.base_url}/maps/bad", b"\0" * (17 << 20))
        assert r.status_code == 413
        r = httpx.put(
            f"{svc.base_url}/maps/bad/import?format=png",
            content=body,
            headers={"content-type": "application/zip"},
        )
        assert r.status_code == 422
        assert httpx.get(f"{svc.base_url}/maps/bad").status_code == 404
        # A map replaced keeps its configuration: another resolution is refused, the map unchanged.
        assert (
            httpx.put(
                f"{svc.base_url}/maps/fine", json={"resolution": 0.1, "layers": ["occupancy"]}
            ).status_code
            == 201
        )
        r = put_import(f"{svc.base_url}/maps/fine", body)
        assert (
            r.status_code == 422 and "resolution 0.05 m differs from the map configuration's 0.1 m" in r.text
        )
        r = put_import(f"{svc.base_url}/maps/fine", nav2_zip(nav2_yaml(resolution=0.1), {"map.pgm": PIXELS}))
        assert r.status_code == 200 and r.json()["config"]["layers"] == ["occupancy"]
        # fleetmap's own export goes back in as it came out.
        exported = httpx.get(f"{url}/export", params={"format": "ros", "margin": 0}, timeout=30)
        assert exported.status_code == 200
        assert put_import(f"{svc.base_url}/maps/copy", exported.content).status_code == 201
        again = httpx.get(
            f"{svc.base_url}/maps/copy/export", params={"format": "ros", "margin": 0}, timeout=30
        )
        with (
            zipfile.ZipFile(io.BytesIO(exported.content)) as a,
            zipfile.ZipFile(io.BytesIO(again.content)) as b,
        ):
            assert {n: a.read(n) for n in a.namelist()} == {n: b.read(n) for n in b.namelist()}
    finally:
        assert svc.stop() == 0
    restarted = ServiceProcess(tmp_path, ["--data-dir", str(data_dir)]).start()
    try:
        assert cell_states(f"{restarted.base_url}/maps/site", points) == got
    finally:
        restarted.stop()


def test_import_needs_the_write_role(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    body = nav2_zip(nav2_yaml(), {"map.pgm": PIXELS})
    with ServiceProcess(tmp_path, ["--auth-tokens", str(tokens)]) as svc:
        url = f"{svc.base_url}/maps/m"
        assert put_import(url, body).status_code == 401
        r = put_import(url, body, {"Authorization": f"Bearer {READ}"})
        assert r.status_code == 403 and "'write'" in r.json()["detail"]
        assert httpx.get(url).status_code == 404
        assert put_import(url, body, {"Authorization": f"Bearer {WRITE}"}).status_code == 201


def test_the_client_uploads_a_yaml_path_with_its_image_or_zip_bytes(tmp_path: Path) -> None:
    (tmp_path / "maps" / "img").mkdir(parents=True)
    pixels = np.full((4, 6), 254, dtype=np.uint8)
    pixels[0, :] = 0
    (tmp_path / "maps" / "img" / "floor.png").write_bytes(png(pixels))
    yaml_path = tmp_path / "maps" / "floor.yaml"
    yaml_path.write_text(nav2_yaml("img/floor.png", origin="[1.0, 2.0, 0.0]"))
    with ServiceProcess(tmp_path) as svc, FleetmapClient(svc.base_url) as fm:
        info = fm.import_nav2("floor", yaml_path)
        assert info.id == "floor" and info.stats.tiles == 1
        assert fm.cell("floor", 1.0 + 0.025, 2.0 + 3 * 0.05 + 0.025).state == "occupied"  # the top row
        assert fm.cell("floor", 1.0 + 0.025, 2.0 + 0.025).state == "free"
        assert fm.import_nav2("floor", str(yaml_path)).id == "floor"  # replaced
        # The path of a zip (an export saved to a file) is sent as it is: it was read as a YAML
        # ("not valid YAML: unacceptable character").
        zip_path = tmp_path / "floor.ZIP"
        zip_path.write_bytes(fm.export("floor", "ros"))
        assert fm.import_nav2("from-zip", zip_path).stats.bounds == fm.get_map("floor").stats.bounds
        info = fm.import_nav2("zipped", nav2_zip(nav2_yaml(), {"map.pgm": PIXELS}))
        assert info.stats.bounds == [0.0, 0.0, 0.1, 0.1]
        off_grid = nav2_zip(nav2_yaml(origin="[0.01, 0, 0]"), {"map.pgm": PIXELS})
        with pytest.raises(FleetmapError) as caught:
            fm.import_nav2("bad", off_grid)
        assert caught.value.status == 422 and "not on the map's cell grid" in str(caught.value)
        # Asked to, the service moves it to the nearest cell edge (0.01 m: 0.2 cells, to 0).
        assert fm.import_nav2("snapped", off_grid, snap_origin=True).stats.bounds == [0.0, 0.0, 0.1, 0.1]
        # A YAML giving a field twice is refused (map_server takes the first, PyYAML the last) by
        # the server, and by the client when it writes the YAML out again for an image in a folder,
        # which kept the last value only and hid the repetition from the server.
        yaml_path.write_text(nav2_yaml("img/floor.png", origin="[1.0, 2.0, 0.0]") + "resolution: 0.1\n")
        with pytest.raises(ValueError, match="gives the field 'resolution' twice"):
            fm.import_nav2("twice", yaml_path)
        assert "twice" not in {m.id for m in fm.list_maps()}
        # Written out again (the image is in a folder), the YAML keeps what map_server reads: its
        # `010` is 10 (PyYAML's octal 8 put the map 2 m off), its `true` a boolean to yaml-cpp too.
        yaml_path.write_text(nav2_yaml("img/floor.png", origin="[010, 2.0, 0.0]", negate="false"))
        assert fm.import_nav2("decimal", yaml_path).stats.bounds == pytest.approx([10.0, 2.0, 10.3, 2.2])
        # Its first document only, as map_server reads it (a second one was "not valid YAML").
        yaml_path.write_text(nav2_yaml("img/floor.png", origin="[1.0, 2.0, 0.0]") + "---\nimage: x.png\n")
        assert fm.import_nav2("first", yaml_path).stats.bounds == pytest.approx([1.0, 2.0, 1.3, 2.2])
        # A file that is not YAML (an unclosed list) is the ValueError its contract names, not
        # PyYAML's ParserError; nothing is sent.
        yaml_path.write_text("image: img/floor.png\nresolution: 0.05\norigin: [1.0, 2.0, 0.0\nnegate: 0\n")
        with pytest.raises(ValueError, match=r"floor.yaml is not valid YAML: while parsing a flow sequence"):
            fm.import_nav2("broken", yaml_path)
        assert "broken" not in {m.id for m in fm.list_maps()}


@pytest.mark.parametrize(
    "text", [b"image: map\xff.pgm\nresolution: 0.05\n", b"image: map.pgm\x01\nresolution: 0.05\n"]
)
def test_the_client_refuses_a_yaml_file_that_is_not_utf8_text_as_its_contract_says(
    tmp_path: Path, text: bytes
) -> None:
    """`nav2_files_zip` (`import_nav2` of a YAML path) promises ValueError for a file that is not
    YAML: a map.yaml of Latin-1 bytes, or with a control character, raised PyYAML's ReaderError
    instead, from the loader's constructor, before the try that turned YAML's errors into it."""
    yaml_path = tmp_path / "map.yaml"
    yaml_path.write_bytes(text)
    (tmp_path / "map.pgm").write_bytes(PIXELS)
    with pytest.raises(ValueError, match="map.yaml is not valid YAML: unacceptable character"):
        nav2_files_zip(yaml_path)
