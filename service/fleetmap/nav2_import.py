"""Seed a map from a ROS nav2 map: `map.yaml` and its image, as map_server loads them.

The inverse of `export.nav2_files`: a fleet moving to fleetmap starts its shared map from the map
it navigates with, and robots' scans then refine it. Every pixel gets the value nav2's map_server
would publish for it in its `nav_msgs/OccupancyGrid`, and that value becomes the cell's log-odds.

What map_server does (navigation2, nav2_map_server/src/map_io.cpp, `loadMapYaml` and
`loadMapFromFile`; the mode names from map_mode.cpp's `map_mode_from_string`):

- The YAML needs `image`, `resolution`, `origin` (three numbers: x, y, yaw of the image's lower-left
  pixel corner), `occupied_thresh`, `free_thresh` and `negate` (an integer, quoted or not, in C++'s
  notation: `0x1f` hex, `017` octal, at most 32 bits, non-zero is true; or a boolean as yaml-cpp
  reads one, quoted or not: y / yes / true / on and n / no / false / off); `mode` is `trinary` (the
  default when absent), `scale` or `raw`, in any case.
- The resolution is published as a float32 (`nav_msgs/MapMetaData`): a YAML resolution that is
  a float32 printed in full, as a file written from a published map holds it (exactly, or to the 9
  digits yaml-cpp writes a float with), is read as that float32's shortest decimal
  (0.05000000074505806 and 0.0500000007 are 0.05).
- Row 0 of the image is its top: pixel `(x, y)` is written to `data[width * (height - y - 1) + x]`,
  so the top row is the highest y.
- A pixel's `shade` is the mean of its red, green and blue channels on a 0..1 scale (for a grey
  pixel of value v, v / 255); in trinary mode, an image with an alpha channel also averages in its
  alpha (255 opaque), "to preserve existing behaviour": shade = (3 v + alpha) / 1020.
  `occ = shade` if negate, else `1.0 - shade` (computed so, in double: not `(255 - v) / 255`,
  which rounds differently exactly at a threshold such as 0.2 for v = 204).
- trinary: `occupied_thresh < occ` is occupied (100), else `occ < free_thresh` is free (0), else
  unknown (-1). Both comparisons are strict: a pixel exactly at a threshold is unknown.
- scale: a pixel that is not fully opaque is unknown; else occupied and free as in trinary, and in
  between `rint((occ - free_thresh) / (occupied_thresh - free_thresh) * 100)`. There is no special
  grey value: 205, trinary's unknown, is a value like any other (0 with the usual thresholds).
- raw: `round(shade * 255)`, the pixel value itself, if it is 0..100, else unknown; negate and the
  thresholds are read but not used.

The published value m (0..100, or unknown) is an occupancy probability in percent
(`nav_msgs/OccupancyGrid`): the cell's log-odds is `logit(m / 100)` clamped to the map's
`[l_min, l_max]`, so occupied (100) is `l_max`, free (0) `l_min`, and unknown stays unknown (NaN).
In trinary mode that is all there is; in scale mode it is the published percentage, not the
pixel's own `occ`, that becomes the probability: the map robots navigated with is what is seeded.

Limits (`Nav2ImportError` names what is wrong; nothing is created): a yaw other than 0 (a rotated
image is not on the map's axis-aligned cells), an origin that is not on the map's cell grid (within
1e-6 of a cell edge of the map's resolution or of the YAML's, read or as a float32; with
`snap_origin` it is moved to the nearest one instead, by at most half a cell: SLAM tools put the
origin anywhere, and map_saver writes it rounded), a resolution other
than the configuration's, images that are not 8-bit grey (grey with alpha, and RGB / RGBA whose
channels are equal everywhere, as map_saver writes scale maps, are grey, and in scale mode where
a pixel is opaque: map_server reads the others as unknown; so are a PNG's samples of 1, 2 or 4
bits, at full scale, and a palette PNG's pixels whose colours are grey, as PNG optimisers store a
map's few greys; a PGM's maxval must be 255, a PNG's samples 8 bits at most), images over
MAX_IMAGE_SIDE on a side or MAX_IMAGE_PIXELS in all, more tiles than the map's `max_tiles`. Tiles
are created only where a cell is known; every layer but occupancy stays unknown.

Memory: an image is decoded by Pillow whole (1 byte a pixel for grey, 4 with alpha or colour), then
turned into map_server's values (one byte a pixel) a strip of rows at a time, through a table of
the 256 (or 256 x 256 with alpha) possible pixels, and the decoded image is freed before the tiles
are made; each tile's log-odds is one numpy gather of those values. That working memory is not the
maps' (`--max-memory` bounds the tiles), so one image at a time is read in the process
(`_decoding_turn`), from the image file's bytes to the map's tiles: a 3 KB zip holds a transparent
64-Mpixel PNG, about 350 MB to decode (800 MB when numpy copied it whole), and four such uploads
at once took the service 2.8 GB past a budget of 256 MiB. Others wait their turn.
"""

from __future__ import annotations

import contextlib
import io
import math
import posixpath
import re
import sys
import threading
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, Any, Literal

import numpy as np
import yaml
from PIL import Image, ImageFile, UnidentifiedImageError
from pydantic import ValidationError

from fleetmap.config import MAX_COORDINATE, MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.tiles import TileKey, TileLimitError
from fleetmap.upload_spool import check_stop, upload_zip
from fleetmap.yaml_whitespace import YamlCppWhitespace

if TYPE_CHECKING:
    from fleetmap.memory_budget import UploadReservation

#: Bounds of an imported image: its sides, and its pixels in all (64 Mi: 1024 tiles of 256 x 256).
#: The total stays under Pillow's own decompression-bomb bound (89 Mi pixels), past which it warns:
#: silencing that warning would change the process's warning filters from a worker thread.
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 26
#: The most bytes the YAML file and the image file may hold (decompressed, in a zip).
MAX_YAML_BYTES = 64 * 1024
MAX_IMAGE_FILE_BYTES = MAX_IMAGE_PIXELS * 4 + (1 << 20)
#: How far `origin / resolution` may be from an integer and still be on the cell grid, in cells.
GRID_TOLERANCE = 1e-6
#: How far the YAML's resolution may be from the configuration's, relative.
RESOLUTION_TOLERANCE = 1e-9
#: Rows of a decoded image turned into map_server's values at a time (`image_values`): a strip's
#: copies take at most 16 MiB (16384 pixels of 4 bytes, 256 rows) beside the image.
STRIP_ROWS = 256
#: Seconds between two looks at whether an upload waiting for its turn to decode was cut off.
_TURN_POLL_S = 0.1
#: Held while an image is read into a map, from its file's bytes to the map's tiles: one at a time
#: in the process (see the module's docstring).
_DECODING = threading.Lock()

Nav2Mode = Literal["trinary", "scale", "raw"]
NAV2_MODES: tuple[Nav2Mode, ...] = ("trinary", "scale", "raw")
#: map_server's OccupancyGrid values (nav2_util/occ_grid_values.hpp).
OCC_GRID_UNKNOWN, OCC_GRID_FREE, OCC_GRID_OCCUPIED = -1, 0, 100

#: What each of Pillow's modes of a PNG that are not 8-bit grey, colour or alpha is read as, a strip
#: at a time: a 1-bit grey PNG's samples as 8-bit grey at full scale (1 is 255), and a palette
#: PNG's pixels as their entries' colours (then grey where those are), as map_server reads them
#: (GraphicsMagick hands it every pixel's colour). PNG optimisers (optipng, oxipng, pngquant) store
#: a map's few greys as a palette; hand-drawn maps of walls and free space are often 1-bit.
_PNG_READ_AS = {"1": "L", "P": "RGB"}
#: Pillow's image modes that are not 8-bit grey, in words.
_MODE_WORDS = {
    "1": "a 1-bit black and white", "P": "a palette (indexed colour)", "PA": "a palette with alpha",
    "I;16": "a 16-bit grey", "I;16B": "a 16-bit grey", "F": "a floating-point",
    "I": "a 16- or 32-bit integer (a 16-bit PGM reads so)", "CMYK": "a CMYK", "LAB": "a Lab colour",
}  # fmt: skip

#: As storage_format's: a corrupt member's errors, and a local header's name that is not the UTF-8
#: its flag says (UnicodeDecodeError, when the member is opened).
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, UnicodeDecodeError)


class Nav2ImportError(ValueError):
    """Why a nav2 map cannot be imported; nothing was created. `status` is 413 for a file or an
    image past a size limit, 415 for bytes that are not a zip at all, 507 for tiles the memory
    budget has no room for, else 422."""

    def __init__(self, message: str, status: int = 422) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Nav2Meta:
    """The fields of a map_server YAML file that a load uses (see the module's docstring)."""

    image: str
    resolution: float
    origin: tuple[float, float, float]
    occupied_thresh: float
    free_thresh: float
    negate: bool
    mode: Nav2Mode


class _MapYamlLoader(YamlCppWhitespace, yaml.SafeLoader):
    """PyYAML's safe loader, refusing an alias (`*name`) of a list or a mapping. PyYAML shares the
    aliased object, so nested aliases ("billion laughs") build in a few bytes a structure whose
    every walk (a `repr` in an error message, a comparison) visits 10**9 elements: it took a 600-byte
    map.yaml and 18 GB of the service's memory. An alias of a scalar costs nothing; map_server's
    files have no aliases at all. Tabs between tokens are whitespace, as map_server's yaml-cpp reads
    them (`YamlCppWhitespace`)."""

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            aliased = self.anchors.get(event.anchor)
            if aliased is not None and not isinstance(aliased, yaml.ScalarNode):
                raise yaml.composer.ComposerError(
                    None,
                    None,
                    f"an alias (*{event.anchor}) of a list or a mapping is not read",
                    event.start_mark,
                )
        return super().compose_node(parent, index)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        """A mapping, refusing a key written twice: PyYAML keeps the last value, map_server's
        yaml-cpp the first, so a map.yaml saying `resolution` twice was imported at another
        resolution (or origin, or thresholds) than nav2 loads it with."""
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, str) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the field {key!r} is given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> Any:  # int, or str (not PyYAML's int)
        """An integer written in plain decimal (`0`, `-12`), else its text: PyYAML's YAML 1.1 reads
        `010` as octal 8 where yaml-cpp's `as<double>()`, map_server's reader, reads 10 (an origin
        of `[-010, 020, 0]` was imported 2 m and 4 m off), and makes numbers of hex, underscores
        and sexagesimal, which yaml-cpp does not read as numbers at all. The text goes to
        `_number`, which reads it as yaml-cpp does (`010` is 10) or refuses it."""
        text = self.construct_scalar(node)
        if isinstance(text, str) and not _DECIMAL_INTEGER_TEXT.fullmatch(text):
            return text
        return super().construct_yaml_int(node)

    def construct_yaml_float(self, node: yaml.ScalarNode) -> Any:  # float, or str
        """A float as yaml-cpp reads one (`_NUMBER_TEXT`), or infinity or NaN (refused later, as not
        finite, saying so), else its text: PyYAML's YAML 1.1 also reads underscores (`0_.05`) and
        sexagesimal (`1:30.5`), which yaml-cpp does not, and map_server fails to load."""
        text = self.construct_scalar(node)
        if isinstance(text, str) and not (_NUMBER_TEXT.fullmatch(text) or _NON_FINITE_TEXT.fullmatch(text)):
            return text
        return super().construct_yaml_float(node)


#: A number as yaml-cpp's `as<double>()` (map_server's reader) reads it where PyYAML's YAML 1.1
#: resolver leaves a string: an exponent without a dot or a sign, as in `1e-05`, which yaml-cpp
#: itself writes for a small origin.
_NUMBER_TEXT = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
#: An integer as yaml-cpp's `as<int>()` reads one (`_yaml_cpp_int`), with no more digits than a
#: value in an int's 32 bits may have (so it is never a long conversion).
_YAML_CPP_INTEGER_TEXT = re.compile(r"[-+]?(?:0[xX][0-9a-fA-F]{1,8}|0[0-7]{0,11}|[1-9][0-9]{0,9})")
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
#: An integer PyYAML reads as yaml-cpp does: plain decimal, no leading zero (octal to PyYAML).
_DECIMAL_INTEGER_TEXT = re.compile(r"[-+]?(?:0|[1-9][0-9]*)")
#: PyYAML's infinities and NaN (its YAML 1.1 resolver's own forms).
_NON_FINITE_TEXT = re.compile(r"[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)")
_MapYamlLoader.add_constructor("tag:yaml.org,2002:int", _MapYamlLoader.construct_yaml_int)
_MapYamlLoader.add_constructor("tag:yaml.org,2002:float", _MapYamlLoader.construct_yaml_float)
#: yaml-cpp's booleans (`convert<bool>`, which map_server's `negate` falls back to when it is no
#: integer): these words, quoted or not, all lower case, all upper case or capitalised. PyYAML reads
#: only the unquoted yes / no / true / false / on / off as booleans, not `y`, `n` or a quoted word.
_YAML_CPP_BOOLS = {
    "y": True, "n": False, "yes": True, "no": False, "true": True, "false": False, "on": True, "off": False,
}  # fmt: skip
#: The most characters of a YAML value an error message quotes.
_SHOWN_CHARS = 80


def _shown(value: object) -> str:
    """`repr(value)` for an error message, cut to `_SHOWN_CHARS` (an integer past Python's 4300
    digits has no repr at all)."""
    try:
        text = repr(value)
    except ValueError:
        return f"an integer of more than {sys.get_int_max_str_digits()} digits"
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 3] + "..."


def _negate(value: object) -> bool:
    """map.yaml's `negate` as map_server reads it: yaml-cpp's `as<int>()` (non-zero is true), and
    failing that its `as<bool>()`; `Nav2ImportError` when both fail, as map_server's load does."""
    if isinstance(value, bool):
        return value
    number = value if isinstance(value, int) else _yaml_cpp_int(value) if isinstance(value, str) else None
    if number is not None and _INT32_MIN <= number <= _INT32_MAX:
        return number != 0
    # Not an integer, map_server reads it as a boolean, as yaml-cpp does: `negate: y`, or
    # `negate: "true"`, which PyYAML leaves strings, were refused though map_server loads them.
    flag = _yaml_cpp_bool(value) if isinstance(value, str) else None
    if flag is None:
        raise Nav2ImportError(f"map.yaml 'negate' must be an integer or a boolean, got {_shown(value)}")
    return flag


def _yaml_cpp_int(text: str) -> int | None:
    """`text` as yaml-cpp's `as<int>()` reads it (C++'s stream extraction with the base from the
    prefix, as strtol's base 0: `0x1f` hex, `017` octal, else decimal; `negate: "0"` quoted too),
    None for any other text or one past an int's 32 bits. Counted by its digits, never converted
    whole: Python refuses to convert more than 4300 decimal digits (a ValueError, an HTTP 500)."""
    if not _YAML_CPP_INTEGER_TEXT.fullmatch(text):
        return None
    digits = text.lstrip("+-")
    base = 16 if digits[:2] in ("0x", "0X") else 8 if len(digits) > 1 and digits[0] == "0" else 10
    number = int(digits, base)
    return -number if text.startswith("-") else number


def _yaml_cpp_bool(text: str) -> bool | None:
    """`text` as yaml-cpp's `as<bool>()` reads it (`_YAML_CPP_BOOLS`, in its "flexible case": all
    lower, all upper, or an upper first letter and the rest all lower or all upper), else None."""
    rest = text[1:]
    flexible = text.islower() or (text[:1].isupper() and (not rest or rest.islower() or rest.isupper()))
    return _YAML_CPP_BOOLS.get(text.lower()) if flexible else None


def _number(doc: dict[str, Any], key: str) -> float:
    if key not in doc:
        raise Nav2ImportError(f"map.yaml has no {key!r}")
    value = doc[key]
    number = math.nan
    if isinstance(value, str) and _NUMBER_TEXT.fullmatch(value):
        number = float(value)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):  # an integer past a double's range
            number = float(value)
    if not math.isfinite(number):
        raise Nav2ImportError(f"map.yaml {key!r} must be a finite number, got {_shown(value)}")
    return number


#: The significant digits that print a float32 in full (C++'s `max_digits10` for a float): what
#: yaml-cpp's emitter writes a float with, and C++ streams set to that precision.
FLOAT32_DIGITS = 9


def _published_resolution(value: float) -> float:
    """The YAML's resolution as the map it describes has it: a value that is a float32 printed in
    full, exactly (0.05000000074505806) or to FLOAT32_DIGITS significant digits (0.0500000007), is
    the shortest decimal of that float32 (0.05); any other value is itself.

    Why: `nav_msgs/MapMetaData.resolution` is a float32, so map_server publishes float32(resolution)
    and every ROS consumer (AMCL, costmaps) uses that; a map.yaml written from a published map holds
    that float32 printed in full: 0.05000000074505806 for a 0.05 m map by rclpy (or from `ros2 topic
    echo /map`), 0.0500000007 by a C++ tool through yaml-cpp's emitter, which writes a float with 9
    digits. Taken as is, it differed from a 0.05 m map's configuration, and a new map made at it put
    an origin such as -10.0 2.98e-06 cells off its grid: both refused, though map_server publishes
    it as it publishes 0.05. A resolution written by hand is a float32 in full only as a short
    binary fraction (0.5, 0.03125), which is its own shortest decimal: those, and every other value,
    are unchanged."""
    with np.errstate(over="ignore", under="ignore"):
        single = np.float32(value)
    if value not in (float(single), float(f"{float(single):.{FLOAT32_DIGITS}g}")):
        return value
    return float(str(single))  # numpy prints a float32 as its shortest round-tripping decimal


def parse_nav2_yaml(text: str | bytes) -> Nav2Meta:
    """The fields of a map_server YAML file, checked; `Nav2ImportError` naming the field at fault."""
    if len(text) > MAX_YAML_BYTES:
        raise Nav2ImportError(f"map.yaml is {len(text)} bytes, more than the limit of {MAX_YAML_BYTES}", 413)
    loader: _MapYamlLoader | None = None
    try:
        # Made inside the `try`: it decodes the start of `text` (4 KB) at once, and raises its
        # ReaderError there for bytes that are not UTF-8 (or UTF-16) or for a control character,
        # which was an HTTP 500.
        loader = _MapYamlLoader(text)  # a SafeLoader: no Python objects
        # The first document only, as map_server's `YAML::LoadFile` reads it: `yaml.load` refused a
        # file ending in `---` (another document), which map_server loads.
        doc = loader.get_data() if loader.check_data() else None
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise Nav2ImportError(f"map.yaml is not valid YAML: {exc}") from None
    except ValueError as exc:  # PyYAML's int() of more than 4300 digits
        raise Nav2ImportError(f"map.yaml holds a number Python does not read: {exc}") from None
    finally:
        if loader is not None:
            loader.dispose()
    if doc is None:  # no document at all: an empty file, or only comments
        raise Nav2ImportError("map.yaml is empty: it must hold a mapping of fields (image, resolution, ...)")
    if not isinstance(doc, dict):
        raise Nav2ImportError(f"map.yaml must hold a mapping of fields, not a {type(doc).__name__}")
    image = doc.get("image")
    if not isinstance(image, str) or not image:
        raise Nav2ImportError(f"map.yaml 'image' must name the image file, got {_shown(image)}")
    resolution = _published_resolution(_number(doc, "resolution"))
    if resolution <= 0:
        raise Nav2ImportError(f"map.yaml 'resolution' must be positive, got {resolution!r}")
    origin = doc.get("origin")
    if not isinstance(origin, list) or len(origin) != 3:
        raise Nav2ImportError(
            f"map.yaml 'origin' must be a list of 3 numbers [x, y, yaw], got {_shown(origin)}"
        )
    x, y, yaw = (_number({"origin": v}, "origin") for v in origin)
    occupied, free = _number(doc, "occupied_thresh"), _number(doc, "free_thresh")
    if "negate" not in doc:
        raise Nav2ImportError("map.yaml has no 'negate'")
    negate = _negate(doc["negate"])
    mode = doc.get("mode", "trinary")
    if not isinstance(mode, str) or mode.lower() not in NAV2_MODES:
        raise Nav2ImportError(f"map.yaml 'mode' must be trinary, scale or raw, got {_shown(mode)}")
    lowered = NAV2_MODES[NAV2_MODES.index(mode.lower())]
    # map_server reads any thresholds; map_saver refuses these (checkSaveParameters), and scale
    # mode divides by their difference. Raw mode reads them (they must be there) but uses neither:
    # a raw map saved with both 0, which map_server loads, was refused.
    if lowered != "raw" and not 0.0 <= free < occupied <= 1.0:
        raise Nav2ImportError(
            f"map.yaml thresholds must satisfy 0 <= free_thresh < occupied_thresh <= 1, got free_thresh "
            f"{free!r}, occupied_thresh {occupied!r}"
        )
    return Nav2Meta(image, resolution, (x, y, yaw), occupied, free, bool(negate), lowered)


def occupancy_grid_values(meta: Nav2Meta, with_alpha: bool) -> np.ndarray:
    """map_server's OccupancyGrid value (int8: -1 unknown, else 0..100) of every pixel: indexed
    `[value]`, or `[value, alpha]` for an image with an alpha channel (`with_alpha`)."""
    levels = np.arange(256, dtype=np.float64)
    v, alpha = np.meshgrid(levels, levels if with_alpha else [255.0], indexing="ij")
    if not with_alpha:
        v, alpha = v[:, 0], alpha[:, 0]
    # The mean of r, g, b (and in trinary mode alpha) as a fraction of 255: 3 v + alpha over 4 x 255.
    shade = (3.0 * v + alpha) / 1020.0 if meta.mode == "trinary" and with_alpha else v / 255.0
    occ = shade if meta.negate else 1.0 - shade
    out = np.full(v.shape, OCC_GRID_UNKNOWN, dtype=np.int8)
    if meta.mode == "raw":
        percent = np.round(shade * 255.0)
        in_range = (percent >= OCC_GRID_FREE) & (percent <= OCC_GRID_OCCUPIED)
        out[in_range] = percent[in_range].astype(np.int8)
        return out
    occupied = meta.occupied_thresh < occ
    free = ~occupied & (occ < meta.free_thresh)
    out[occupied] = OCC_GRID_OCCUPIED
    out[free] = OCC_GRID_FREE
    if meta.mode == "scale":
        between = ~occupied & ~free
        scaled = np.rint((occ - meta.free_thresh) / (meta.occupied_thresh - meta.free_thresh) * 100.0)
        out[between] = scaled[between].astype(np.int8)
        out[alpha != 255.0] = OCC_GRID_UNKNOWN
    return out


def log_odds_of_values(values: np.ndarray, l_min: float, l_max: float) -> np.ndarray:
    """float32 log-odds of OccupancyGrid values: `logit(m / 100)` clamped to `[l_min, l_max]`, NaN
    for unknown (-1)."""
    p = np.clip(values, OCC_GRID_FREE, OCC_GRID_OCCUPIED).astype(np.float64) / 100.0  # unknown: below
    with np.errstate(divide="ignore"):
        lo = np.log(p) - np.log1p(-p)  # -inf at 0, +inf at 1: the clamp makes them l_min, l_max
    lo = np.clip(lo, l_min, l_max)
    lo[values == OCC_GRID_UNKNOWN] = np.nan
    return lo.astype(np.float32)


def image_values(data: bytes, name: str, meta: Nav2Meta) -> np.ndarray:
    """map_server's OccupancyGrid value (int8: -1 unknown, else 0..100, `occupancy_grid_values`)
    of every pixel of a PGM or PNG image read by `meta`'s mode and thresholds, row 0 the image's
    top; `Nav2ImportError` saying what it is when it is not 8-bit grey, or too big. Decoded whole
    by Pillow, then read a strip of `STRIP_ROWS` rows at a time: the numpy copy of a whole image
    with alpha (4 bytes a pixel) and its planes and masks doubled what decoding takes."""
    try:
        im = Image.open(io.BytesIO(data), formats=["PNG", "PPM"])  # reads the header only
    except Image.DecompressionBombError as exc:
        raise Nav2ImportError(f"{name} is too large: {exc}", 413) from None
    except UnidentifiedImageError:  # its message names the in-memory buffer object, not the file
        raise Nav2ImportError(f"{name} is not a PGM or PNG image") from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise Nav2ImportError(f"{name} is not a PGM or PNG image ({exc})") from None
    with im:
        w, h = im.size
        if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
            raise Nav2ImportError(
                f"{name} is {w} x {h} pixels: at most {MAX_IMAGE_SIDE} on a side and {MAX_IMAGE_PIXELS} "
                "in all are imported", 413,
            )  # fmt: skip
        if w == 0 or h == 0:
            raise Nav2ImportError(f"{name} is empty ({w} x {h} pixels)")
        mode = _PNG_READ_AS.get(im.mode, im.mode) if im.format == "PNG" else im.mode
        if mode not in ("L", "LA", "RGB", "RGBA"):
            kind = _MODE_WORDS.get(im.mode, "an unsupported")
            raise Nav2ImportError(f"{name} is {kind} image (mode {im.mode}): only 8-bit grey images are read")
        if _png_bit_depth(im, data) == 16:
            raise Nav2ImportError(
                f"{name} is a 16-bit PNG (mode {im.mode} as Pillow reads it, 8 bits of each 16): map_server "
                "reads all 16 bits, which 8 bits do not hold; only 8-bit grey images are read"
            )
        maxval = _pnm_maxval(im)
        if maxval != 255:
            raise Nav2ImportError(
                f"{name} is a {'PGM' if im.mode == 'L' else 'PPM'} whose maxval is {maxval}, not 255: its "
                f"grey levels are value / {maxval}, which map_server reads at 16 bits and 8 bits do not "
                "hold; only 8-bit grey images (maxval 255) are read"
            )
        if "transparency" in im.info:
            raise Nav2ImportError(
                f"{name} marks a transparent colour (a tRNS chunk): save it with an alpha channel instead"
            )
        try:
            im.load()
        except (OSError, ValueError, SyntaxError, zlib.error) as exc:
            raise Nav2ImportError(f"{name} cannot be decoded (the file is corrupt): {exc}") from None
        table = occupancy_grid_values(meta, mode in ("LA", "RGBA"))
        values = np.empty((h, w), dtype=np.int8)
        for top in range(0, h, STRIP_ROWS):
            part = im.crop((0, top, w, min(h, top + STRIP_ROWS)))
            strip = np.asarray(part if mode == im.mode else part.convert(mode))
            values[top : top + len(strip)] = table[_grey_and_alpha(strip, mode, meta, name, top, im.mode)]
    return values


def _grey_and_alpha(
    pixels: np.ndarray, mode: str, meta: Nav2Meta, name: str, top: int, image_mode: str
) -> tuple[np.ndarray, ...]:
    """The grey values, and the alpha channel where the image has one, of `pixels` (rows `top` on
    of an image of Pillow's `mode` L, LA, RGB or RGBA, read so from one of `image_mode`, which the
    message names), to index `occupancy_grid_values`'s table;
    `Nav2ImportError` naming the first pixel whose channels differ, where they must not: anywhere,
    or in scale mode only where it is opaque (map_server's scale mode reads every pixel not opaque
    as unknown, whatever its colour: an editor that keeps the colour of transparent pixels, GIMP's
    "save colour values from transparent pixels", made such a map refused as a colour image)."""
    if mode == "L":
        return (pixels,)
    grey = pixels[:, :, 0]
    if mode == "LA":
        return grey, pixels[:, :, 1]
    colour = (pixels[:, :, 1] != grey) | (pixels[:, :, 2] != grey)
    if meta.mode == "scale" and mode == "RGBA":
        colour &= pixels[:, :, 3] == 255
    if colour.any():
        y, x = (int(k) for k in np.argwhere(colour)[0])
        channels = tuple(int(c) for c in pixels[y, x])
        raise Nav2ImportError(
            f"{name} is a colour image (mode {image_mode}): pixel ({x}, {top + y}) is {channels}; only 8-bit "
            "grey images are read"
        )
    return (grey,) if mode == "RGB" else (grey, pixels[:, :, 3])


#: Where a PNG's bit depth is: after its 8-byte signature, the IHDR chunk's length and type (4 bytes
#: each), width and height (4 bytes each). Pillow has checked that IHDR comes first when it opened it.
_PNG_BIT_DEPTH_AT = 24


def _png_bit_depth(im: ImageFile.ImageFile, data: bytes) -> int | None:
    """The bit depth of a PNG's samples (1, 2, 4, 8 or 16) from its IHDR chunk, None for any other
    image. Pillow opens a 16-bit grey PNG as mode I;16, but a 16-bit RGB, RGBA or grey-with-alpha
    one as plain RGB / RGBA keeping the high byte of each sample: such a map was read at 8 bits
    without a word, where map_server's 16 bits put pixels near a threshold in another class (a grey
    of 52700 / 65535 is free with free_thresh 0.196, its high byte 205 unknown) and scale mode's
    percentages elsewhere."""
    if im.format != "PNG" or len(data) <= _PNG_BIT_DEPTH_AT:
        return None
    return data[_PNG_BIT_DEPTH_AT]


def _pnm_maxval(im: ImageFile.ImageFile) -> int:
    """The maxval of a PGM / PPM header (its white), 255 for any other image. Pillow decodes a maxval
    other than 255 rounded onto 0..255 (50 of 100 becomes 128, 0.502 where map_server's 16-bit
    GraphicsMagick has 0.5): a scale map's percentages and pixels at a threshold came out otherwise
    than map_server publishes them. Pillow keeps the maxval as the last argument of the image's
    decoder ("ppm" and "ppm_plain"; the raw decoder it uses for 255 and 65535 has none)."""
    if im.format != "PPM" or not im.tile:
        return 255
    args = im.tile[0].args
    return args[-1] if isinstance(args, tuple) and isinstance(args[-1], int) else 255


def _grid_index(value: float, resolutions: tuple[float, ...], what: str, snap: bool = False) -> int:
    """The cell edge index of origin coordinate `value` on a map of resolution `resolutions[0]`: the
    edge it lies on (within GRID_TOLERANCE cells) on the grid of one of `resolutions` (those that
    are the map's, `_grid_resolutions`), or with `snap` the nearest one of the map's own grid (half
    a cell off: the one above)."""
    for resolution in resolutions:
        cells = value / resolution
        nearest = math.floor(cells + 0.5)
        if abs(cells - nearest) <= GRID_TOLERANCE:
            return int(nearest)
    resolution = resolutions[0]
    cells = value / resolution
    nearest = math.floor(cells + 0.5)
    if not snap:
        raise Nav2ImportError(
            f"map.yaml origin {what} {value!r} is not on the map's cell grid: it is {cells:.9g} cells of "
            f"{resolution!r} m from 0, {abs(cells - nearest):.3g} cells off the nearest cell edge "
            f"({nearest * resolution:.9g} m); only maps whose origin is on the grid are imported, unless "
            "snap_origin moves it to the nearest edge"
        )
    return int(nearest)


def _grid_resolutions(meta: Nav2Meta, config: MapConfig) -> tuple[float, ...]:
    """The resolutions whose cell grid a map.yaml's origin may lie on to be on the grid of a map of
    `config` (whose resolution `_map_config` took for the YAML's): the map's, the YAML's as read
    (`_published_resolution`), and that as map_server publishes it, a float32. 0.05 and
    0.05000000074505806 are one resolution, but their grids drift apart by 1.5e-8 cells a cell: the
    export of a map configured at the float32, its origin 400 of its cells from 0, was 6e-06 cells
    off the grid of a new map made at 0.05, and refused (as was a 0.05 map's export by a map
    configured at the float32)."""
    return config.resolution, meta.resolution, float(np.float32(meta.resolution))


def _map_config(meta: Nav2Meta, config: MapConfig | None, defaults: MapConfig | None) -> MapConfig:
    """The configuration of the map made of `meta`: `config` (the map's), else `defaults` (the
    server's `--config`) with the YAML's resolution. Nav2ImportError if the resolutions differ or
    it keeps no occupancy layer, naming which configuration it is."""
    whose, how = "the map's configuration", ""
    if config is not None:
        # Also as map_server publishes both, a float32: a map configured at 0.05000000074505806 m
        # (copied from a published map) writes that into its export, which reads as 0.05.
        if not any(
            math.isclose(meta.resolution, resolution, rel_tol=RESOLUTION_TOLERANCE)
            for resolution in (config.resolution, _published_resolution(config.resolution))
        ):
            raise Nav2ImportError(
                f"map.yaml resolution {meta.resolution!r} m differs from the map configuration's "
                f"{config.resolution!r} m"
            )
    else:
        base = (defaults or MapConfig()).model_dump()
        # Said so: "the map configuration" was read as that of a map, where there is none yet.
        whose = "the server's default configuration (--config), which a map imported under a new id takes,"
        try:
            config = MapConfig.model_validate({**base, "resolution": meta.resolution})
        except ValidationError as exc:
            problems = "; ".join(
                e["msg"].removeprefix("Value error, ") for e in exc.errors(include_url=False)
            )
            raise Nav2ImportError(
                f"map.yaml resolution {meta.resolution!r} does not suit {whose[:-1]}: {problems}"
            ) from None
        how = "; make the map with a configuration that keeps it first (PUT /maps/{map_id})"
    if not config.has("occupancy"):
        raise Nav2ImportError(
            f"{whose} keeps no occupancy layer (layers {', '.join(config.layers)}): a nav2 map seeds it{how}"
        )
    return config


def map_from_nav2(
    yaml_text: str | bytes, image: bytes, config: MapConfig | None = None, defaults: MapConfig | None = None,
    reservation: UploadReservation | None = None, image_name: str | None = None, snap_origin: bool = False,
    stop: threading.Event | None = None,
) -> GridMap:  # fmt: skip
    """A new map holding a nav2 map_server map (the YAML text and the image file's bytes), read
    as map_server reads it (see the module's docstring).

    `config`: the new map's configuration, whose resolution must be the YAML's (the same float32,
    as map_server publishes it: 0.05 and 0.05000000074505806 are one resolution); without it,
    `defaults` (or the default configuration) with the YAML's resolution. The occupancy layer gets
    the map; the configuration's other layers stay unknown. With `reservation` (an upload's room in
    the memory budget), the map's tiles are reserved before anything is allocated, and refused (507)
    if the budget has no room for them. An origin off the map's cell grid is
    refused, or with `snap_origin` moved to the nearest cell edge (by at most half a cell on each
    axis). One image is read at a time in the process: a call waits for the others' (the module's
    docstring says why), raising `UploadStopped` if `stop` is set while it waits. Raises
    `Nav2ImportError`."""
    meta = parse_nav2_yaml(yaml_text)
    with _decoding_turn(stop):
        return _map_from_meta(meta, image, config, defaults, reservation, image_name, snap_origin)


@contextlib.contextmanager
def _decoding_turn(stop: threading.Event | None) -> Iterator[None]:
    """The block runs while this thread holds the process's one turn to read an image into a map
    (`_DECODING`), waiting for it as long as it takes: each read is bounded (MAX_IMAGE_PIXELS), a
    few seconds at most. `UploadStopped` if `stop` is set meanwhile (the upload's request ended: a
    waiting reader would otherwise hold the process's exit until its turn came and went)."""
    while not _DECODING.acquire(timeout=_TURN_POLL_S):
        check_stop(stop)
    try:
        yield
    finally:
        _DECODING.release()


def _map_from_meta(
    meta: Nav2Meta, image: bytes, config: MapConfig | None, defaults: MapConfig | None,
    reservation: UploadReservation | None, image_name: str | None, snap_origin: bool,
) -> GridMap:  # fmt: skip
    """`map_from_nav2` of a parsed map.yaml; the caller holds the decoding turn."""
    ox, oy, yaw = meta.origin
    if yaw != 0.0:
        raise Nav2ImportError(
            f"map.yaml origin yaw is {yaw!r} rad: only maps with yaw 0 (an image aligned with the map's "
            "axes) are imported"
        )
    config = _map_config(meta, config, defaults)
    res = config.resolution
    beyond = f"the map reaches beyond the +-{MAX_COORDINATE:g} m the service accepts (origin {ox!r}, {oy!r})"
    # Before it is counted in cells: 1.7e308 m, finite, is an infinite number of cells, which
    # `_grid_index` cannot round (OverflowError, an HTTP 500).
    if max(abs(ox), abs(oy)) > MAX_COORDINATE:
        raise Nav2ImportError(beyond)
    grid = _grid_resolutions(meta, config)
    i0, j0 = _grid_index(ox, grid, "x", snap_origin), _grid_index(oy, grid, "y", snap_origin)
    values = image_values(image, image_name or meta.image, meta)
    h, w = values.shape
    if max(abs(i0), abs(i0 + w), abs(j0), abs(j0 + h)) * res > MAX_COORDINATE:
        raise Nav2ImportError(beyond)
    _, _, l_min, l_max = config.occupancy.resolved()
    # The log-odds of every value, indexed by its byte: -1 (unknown) is 255, NaN.
    lut = log_odds_of_values(np.arange(256, dtype=np.uint8).view(np.int8), l_min, l_max)
    # Row 0 of the image is its top (the highest y): flipped, row 0 is j0, as the map's arrays are.
    flipped = values[::-1]
    index = flipped.view(np.uint8)
    t, s = config.tile_size, config.tile_size.bit_length() - 1
    windows: list[tuple[TileKey, slice, slice, slice, slice]] = []
    for tj in range(j0 >> s, ((j0 + h - 1) >> s) + 1):
        gj0, gj1 = max(j0, tj * t), min(j0 + h, (tj + 1) * t)
        rows = slice(gj0 - j0, gj1 - j0)
        for ti in range(i0 >> s, ((i0 + w - 1) >> s) + 1):
            gi0, gi1 = max(i0, ti * t), min(i0 + w, (ti + 1) * t)
            cols = slice(gi0 - i0, gi1 - i0)
            if (flipped[rows, cols] != OCC_GRID_UNKNOWN).any():  # a tile only where a cell is known
                local = (slice(gj0 - tj * t, gj1 - tj * t), slice(gi0 - ti * t, gi1 - ti * t))
                windows.append(((ti, tj), rows, cols, *local))
    if len(windows) > config.max_tiles:
        raise Nav2ImportError(
            f"the map needs {len(windows)} tiles of {t} x {t} cells, more than the configuration's "
            f"max_tiles {config.max_tiles}"
        )
    gmap = GridMap(config)
    if reservation is not None:
        try:
            reservation.charge(gmap.store, len(windows))
        except TileLimitError as exc:  # the budget's MemoryBudgetError
            raise Nav2ImportError(f"the map's {len(windows)} tiles {exc}", 507) from None
    gmap.store.create([key for key, *_ in windows])  # every cell of every layer unknown, versioned
    pool = gmap.store.pools["log_odds"]
    for key, rows, cols, local_rows, local_cols in windows:
        pool[gmap.store.slots[key], local_rows, local_cols] = lut[index[rows, cols]]
    return gmap


def _zip_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> bytes:
    if info.file_size > limit:
        raise Nav2ImportError(
            f"{info.filename} is {info.file_size} bytes decompressed, more than the limit of {limit}", 413
        )
    if info.flag_bits & 0x1:
        raise Nav2ImportError(f"{info.filename} in the zip is encrypted")
    try:
        with zf.open(info) as fp:
            data = fp.read(limit + 1)
    except _ZIP_ERRORS as exc:
        raise Nav2ImportError(f"{info.filename} cannot be read from the zip (it is corrupt): {exc}") from None
    if len(data) > limit:
        raise Nav2ImportError(f"{info.filename} holds more than the limit of {limit} bytes", 413)
    return data


#: A zip entry's flag saying that its name is UTF-8 (bit 11 of the general purpose flags, APPNOTE).
_ZIP_UTF8_FLAG = 0x800
#: The host systems of a zip entry made on Windows or DOS (APPNOTE's "version made by").
_WINDOWS_ZIP_SYSTEMS = (0, 6, 11, 14)


def _entry_name(info: zipfile.ZipInfo) -> str:
    """The name of a zip entry as unzip hands it to map_server on Linux: zipfile's, or for a name
    stored without the UTF-8 flag, which zipfile reads as code page 437, its bytes read as UTF-8
    when they are UTF-8, and with '/' for a backslash in a zip made on Windows. Info-ZIP's `zip`,
    Linux's usual one, stores a name so: `image: Büro.pgm` was not found in its zip, whose entry
    zipfile calls 'B├╝ro.pgm'."""
    name = info.filename
    if not info.flag_bits & _ZIP_UTF8_FLAG:
        with contextlib.suppress(UnicodeError):  # else a name in code page 437 indeed (old Windows tools)
            name = name.encode("cp437").decode("utf-8")
    # Windows PowerShell's Compress-Archive separates folders with a backslash, which unzip reads as
    # a '/' in a zip made on Windows (its host system MS-DOS / FAT, HPFS, NTFS or VFAT).
    return name.replace("\\", "/") if info.create_system in _WINDOWS_ZIP_SYSTEMS else name


def map_from_nav2_zip(
    data: bytes | IO[bytes], config: MapConfig | None = None, defaults: MapConfig | None = None,
    reservation: UploadReservation | None = None, snap_origin: bool = False,
    stop: threading.Event | None = None,
) -> GridMap:  # fmt: skip
    """`map_from_nav2` of a zip holding exactly one YAML file (`*.yaml` / `*.yml`) and, once, the image
    it names, which must be a plain file name beside it in the zip, maybe written `./name` (no folder,
    no `..`, no absolute path): what `GET /maps/{id}/export?format=ros` gives. Entries under
    `__MACOSX/` are not read. `data` is the zip's bytes, or a binary file open for reading that can
    seek (an upload spooled to disk: `fleetmap.upload_spool`), which is left open. The image is read
    from the zip in its turn, as `map_from_nav2` reads it (`stop` as there). Raises
    `Nav2ImportError`."""
    try:
        zf = upload_zip(data)
    except (*_ZIP_ERRORS, ValueError) as exc:
        raise Nav2ImportError(f"the body is not a zip file ({exc})", 415) from None
    with zf:
        # macOS's Finder (Compress) adds, for a file with extended attributes, an AppleDouble
        # `__MACOSX/<folder>/._<name>`: `._map.yaml` is no second YAML file.
        # A folder's name ends in '/' (`ZipInfo.is_dir`, which raised IndexError, a 500, for an entry
        # with an empty name: such an entry is neither the YAML nor its image, and is not read).
        infos = [
            i
            for i in zf.infolist()
            if not i.filename.endswith("/") and not i.filename.startswith("__MACOSX/")
        ]
        yamls = [i for i in infos if i.filename.lower().endswith((".yaml", ".yml"))]
        if len(yamls) != 1:
            named = ", ".join(i.filename for i in yamls) or "none"
            raise Nav2ImportError(
                f"the zip must hold exactly one .yaml file, it holds {len(yamls)} ({named})"
            )
        meta = parse_nav2_yaml(_zip_member(zf, yamls[0], MAX_YAML_BYTES))
        name = meta.image
        # `./map.pgm` is map.pgm beside the YAML to map_server too (it joins the YAML's folder and
        # the name), and hand-written map.yaml files often say so.
        while name.startswith("./"):
            name = name[2:]
        if name in ("", ".", "..") or "/" in name or "\\" in name or "\0" in name:
            raise Nav2ImportError(
                f"map.yaml 'image' {meta.image!r} is not a plain file name: the image must lie beside the "
                "YAML file in the zip"
            )
        path = posixpath.join(posixpath.dirname(_entry_name(yamls[0])), name)
        found = [i for i in infos if _entry_name(i) == path]
        if not found:
            raise Nav2ImportError(f"map.yaml names the image {name!r}, which is not in the zip")
        # zipfile appending a file of a name already there adds a second entry: which one is the
        # image depends on the tool (unzip and zipfile read the last), and the first was read here.
        if len(found) > 1:
            raise Nav2ImportError(
                f"the zip holds the image {name!r} {len(found)} times: which one is the map is not clear "
                "(unzip reads the last); zip it again with one"
            )
        # In its turn from here: the image's bytes (up to MAX_IMAGE_FILE_BYTES from a zip of a few
        # KB) are the first of what reading it takes.
        with _decoding_turn(stop):
            image = _zip_member(zf, found[0], MAX_IMAGE_FILE_BYTES)
            return _map_from_meta(meta, image, config, defaults, reservation, name, snap_origin)
