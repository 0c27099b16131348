"""Map exports: the ROS nav2 map_server format, grayscale PNG, and numpy arrays.

Each export is a function of a `GridMap` and a cell window, returning bytes, so the command line
writes them to files and the service sends them over HTTP from the same code.

Conventions: arrays are (ny, nx) with row 0 = lowest y; images are the same data flipped so the top
row is the highest y, as image viewers and map_server expect. The origin of an export is the map
point of the lower-left corner of its cell window.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import json
import math
import os
import shutil
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from fleetmap.cell_queries import STATE_FREE, STATE_OCCUPIED, cell_edge, is_whole_number
from fleetmap.grid_map import GridMap

#: map_server's trinary pixel values and the thresholds that read them back unchanged.
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
NAV2_OCCUPIED_THRESH, NAV2_FREE_THRESH = 0.65, 0.196


@dataclass(frozen=True)
class Window:
    """Cells `[i0, i1) x [j0, j1)` of a map."""

    i0: int
    j0: int
    i1: int
    j1: int

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) = (j1 - j0, i1 - i0), the shape of the window's arrays."""
        return self.j1 - self.j0, self.i1 - self.i0

    @property
    def cells(self) -> int:
        """How many cells the window holds."""
        ny, nx = self.shape
        return nx * ny

    def origin(self, resolution: float) -> tuple[float, float]:
        """Map point of the window's lower-left corner."""
        return cell_edge(self.i0, resolution), cell_edge(self.j0, resolution)

    def aligned(self, scale: int) -> Window:
        """The smallest window holding this one whose edges lie on multiples of `scale` cells: one
        made of whole blocks of `scale` x `scale` cells, as an export at `scale` times the map's
        resolution reads it (`most_occupied`)."""
        return Window(
            self.i0 // scale * scale, self.j0 // scale * scale, -(-self.i1 // scale) * scale,
            -(-self.j1 // scale) * scale,
        )  # fmt: skip


def known_window(gmap: GridMap, margin: int = 0) -> Window | None:
    """The smallest window holding every observed cell, grown by `margin` cells; None if empty.
    ValueError unless `margin` is a whole number >= 0 (a Python or NumPy integer): a negative one cut
    observed cells off the exports without a word (or left none: Pillow's 'cannot write empty
    image'). The window's edges are Python ints."""
    if not is_whole_number(margin) or margin < 0:
        raise ValueError(f"margin must be a whole number of cells >= 0, got {margin!r}")
    # A Python int: with a NumPy one the window's edges were NumPy integers (which json, meta.json's
    # writer, refuses), and a negative edge minus an unsigned one overflowed.
    margin = int(margin)
    bounds = gmap.known_bounds()
    if bounds is None:
        return None
    i0, j0, i1, j1 = bounds
    return Window(i0 - margin, j0 - margin, i1 + margin, j1 + margin)


def bounding_window(windows: list[Window]) -> Window:
    """The smallest window holding every one of `windows` (at least one)."""
    return Window(
        min(w.i0 for w in windows), min(w.j0 for w in windows), max(w.i1 for w in windows),
        max(w.j1 for w in windows),
    )  # fmt: skip


def changed_windows(gmap: GridMap, since: int, window: Window) -> list[Window]:
    """The parts of `window` that may have changed after the map's tile clock was `since`, as
    disjoint rectangles: the storage tiles whose version is above `since`, those side by side in a
    row of tiles as one, each clipped to `window` (none that misses it), ordered by row then column.
    Every cell of `window` outside them is as it was at `since`. Apart, not as their bounding box:
    two robots at opposite corners of a map change two tiles, whose bounding box is the whole map.
    One hold of the map's lock, one pass over the tile versions (the keys of the changed tiles only
    are read)."""
    store = gmap.store
    with gmap.lock:
        changed = store.changed_since(since)
        keys = sorted((int(tj), int(ti)) for ti, tj in (store.keys[slot] for slot in changed.tolist()))
    t = store.tile_size
    runs: list[list[int]] = []  # [tj, first ti, last ti] of each run of tiles side by side
    for tj, ti in keys:
        if runs and runs[-1][0] == tj and runs[-1][2] == ti - 1:
            runs[-1][2] = ti
        else:
            runs.append([tj, ti, ti])
    parts = []
    for tj, ti0, ti1 in runs:
        part = Window(
            max(window.i0, ti0 * t), max(window.j0, tj * t), min(window.i1, (ti1 + 1) * t),
            min(window.j1, (tj + 1) * t),
        )  # fmt: skip
        if part.i0 < part.i1 and part.j0 < part.j1:
            parts.append(part)
    return parts


def state_to_pgm(state: np.ndarray) -> np.ndarray:
    """Trinary map_server pixels (top row = highest y) from `state` codes (row 0 = lowest y)."""
    pixels = np.full(state.shape, PGM_UNKNOWN, dtype=np.uint8)
    pixels[state == STATE_OCCUPIED] = PGM_OCCUPIED
    pixels[state == STATE_FREE] = PGM_FREE
    return pixels[::-1]


def pgm_bytes(pixels: np.ndarray) -> bytes:
    """A binary (P5) 8-bit PGM image."""
    h, w = pixels.shape
    return f"P5\n{w} {h}\n255\n".encode("ascii") + np.ascontiguousarray(pixels, dtype=np.uint8).tobytes()


def nav2_yaml(image: str, resolution: float, origin: tuple[float, float]) -> str:
    """The map_server YAML for a trinary image whose lower-left corner is at `origin`."""
    return (
        f"image: {image}\n"
        "mode: trinary\n"
        f"resolution: {resolution!r}\n"
        f"origin: [{origin[0]!r}, {origin[1]!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {NAV2_OCCUPIED_THRESH}\n"
        f"free_thresh: {NAV2_FREE_THRESH}\n"
    )


def map_source(gmap: GridMap) -> str | None:
    """The layer a map's images (nav2 files, PNG) show: `occupancy`, or for a map without it
    `counts` (their maximum-likelihood occupancy); None for a map that keeps only the TSDF."""
    for layer in ("occupancy", "counts"):
        if gmap.config.has(layer):
            return layer
    return None


def most_occupied(probability: np.ndarray, scale: int) -> np.ndarray:
    """Each block of `scale` x `scale` cells of `probability` (whose sides are multiples of `scale`)
    as one cell: its most occupied known cell, NaN (unknown) only where every cell is unknown. The
    rule of the viewer's zoomed-out tiles: an obstacle seen in a block is never averaged away, and a
    block seen free stays free."""
    if scale == 1:
        return probability
    ny, nx = probability.shape
    blocks = probability.reshape(ny // scale, scale, nx // scale, scale)
    return np.fmax.reduce(np.fmax.reduce(blocks, axis=3), axis=1)  # fmax ignores NaN


def map_probability(gmap: GridMap, window: Window) -> np.ndarray:
    """The occupancy probability its images show over a window (row 0 = lowest y), NaN where
    unknown: from the log-odds, or the count model's `hits / (hits + misses)` (see `map_source`).
    Raises LayerUnavailableError for a TSDF-only map."""
    i0, j0, i1, j1 = window.i0, window.j0, window.i1, window.j1
    if map_source(gmap) != "counts":
        return gmap.region("probability", i0, j0, i1, j1)
    with gmap.lock:  # both counts of one moment: read apart, a scan between them tore cells
        hits = gmap.region("hits", i0, j0, i1, j1).astype(np.float64)
        misses = gmap.region("misses", i0, j0, i1, j1)
    total = hits + misses
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, hits / total, np.nan)


def map_image(
    gmap: GridMap, window: Window, pixels: Callable[[np.ndarray], np.ndarray], scale: int = 1
) -> np.ndarray:
    """An 8-bit image of a window (top row = highest y): `pixels` (elementwise, each the same shape
    as its input) of `map_probability`, read as `by_blocks` reads it; with `scale` > 1 (a window
    `aligned` to it), a pixel per block of `scale` x `scale` cells (`most_occupied`)."""
    return by_blocks(gmap, window, scale, pixels)[::-1]


def tile_blocks(window: Window, tile_size: int) -> Iterator[Window]:
    """The parts of `window` in each storage tile it meets (tiles of `tile_size` cells, aligned on
    multiples of it), row of tiles by row of tiles from the lowest y."""
    for tj in range(window.j0 // tile_size, (window.j1 - 1) // tile_size + 1):
        for ti in range(window.i0 // tile_size, (window.i1 - 1) // tile_size + 1):
            yield _block(window, tile_size, ti, tj)


def _block(window: Window, size: int, bi: int, bj: int) -> Window:
    """The part of `window` in block (bi, bj) of a grid of `size` x `size` cells aligned on
    multiples of `size`: one of `tile_blocks`."""
    return Window(
        max(window.i0, bi * size),
        max(window.j0, bj * size),
        min(window.i1, (bi + 1) * size),
        min(window.j1, (bj + 1) * size),
    )


def _blocks_changed(gmap: GridMap, window: Window, size: int, since: int) -> list[Window]:
    """The blocks of `tile_blocks(window, size)` that meet a storage tile changed (or created) since
    the store's `clock` was `since`, in grid order. The caller holds the map's lock."""
    store = gmap.store
    t = store.tile_size
    grid: set[tuple[int, int]] = set()
    for slot in store.changed_since(since).tolist():
        ti, tj = store.keys[slot]
        # The tile's cells, within the window, and the blocks they fall in.
        i0, i1 = max(window.i0, ti * t), min(window.i1, (ti + 1) * t)
        j0, j1 = max(window.j0, tj * t), min(window.j1, (tj + 1) * t)
        if i0 < i1 and j0 < j1:
            grid.update(
                (bi, bj)
                for bj in range(j0 // size, (j1 - 1) // size + 1)
                for bi in range(i0 // size, (i1 - 1) // size + 1)
            )
    return [_block(window, size, bi, bj) for bj, bi in sorted((bj, bi) for bi, bj in grid)]


#: `by_blocks` reads again the blocks changed while it read them, block by block, at most this many
#: times before it reads those changed during the last such pass under one hold of the map's lock.
#: Each pass is shorter than the one before (it reads only what changed during it), so the last
#: hold is short: some tiles around the robots.
CATCH_UP_PASSES = 2


def by_blocks(
    gmap: GridMap, window: Window, scale: int, convert: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray:
    """`convert` (elementwise, to uint8) of `map_probability` over a window (row 0 = lowest y), a
    cell per block of `scale` x `scale` of the map's (`most_occupied`; the window `aligned` to
    `scale`). Read about one storage tile at a time (`tile_blocks`): the map's lock is held for one
    tile's copy at a time, so integration never waits longer for it (a whole window in one read
    held it for milliseconds), and only a tile's probabilities are held. A part of the window with
    no stored tile is `convert` of unknown without a read: a sparse map's window is mostly such
    parts (a window of 2^30 cells around two scans took 15 s a state export when they were read).
    Yet the image is of one moment of the map, the end of the read: a scan integrated while it reads
    changes tiles read before it, and the blocks of those tiles are read again, the last of them
    under one hold of the lock (`CATCH_UP_PASSES`; read once each, an export of a map robots wrote
    showed cells of several moments, which the map never held at once). Every cell is of that
    moment, within the window the caller chose before it (a map that grew meanwhile shows within
    it). Raises LayerUnavailableError for a TSDF-only map, ValueError for a `scale` that is not a
    whole number >= 1 or a window not `aligned` to it."""
    # Checked here, where every export of a window reads it: 0 was a ZeroDivisionError, -1 and 2.5
    # numpy's and range()'s errors, and an unaligned window numpy's "cannot reshape array".
    if not is_whole_number(scale) or scale < 1:
        raise ValueError(f"scale must be a whole number of cells >= 1, got {scale!r}")
    if window != window.aligned(scale):
        raise ValueError(
            f"the window {window} is not aligned to blocks of {scale} cells: pass window.aligned({scale})"
        )
    ny, nx = window.shape
    out = np.empty((max(ny, 0) // scale, max(nx, 0) // scale), dtype=np.uint8)
    out.fill(convert(np.full((1, 1), np.nan))[0, 0])

    def write(block: Window, probability: np.ndarray) -> None:
        rows = slice((block.j0 - window.j0) // scale, (block.j1 - window.j0) // scale)
        cols = slice((block.i0 - window.i0) // scale, (block.i1 - window.i0) // scale)
        out[rows, cols] = convert(most_occupied(probability, scale))

    size = max(1, gmap.store.tile_size // scale) * scale
    with gmap.lock:
        since = pass_began = gmap.store.clock
    blocks: Iterable[Window] = tile_blocks(window, size)
    for _ in range(CATCH_UP_PASSES):
        for block in blocks:
            if gmap.store.any_tile_in(block.i0, block.j0, block.i1, block.j1):
                write(block, map_probability(gmap, block))
        with gmap.lock:
            blocks = _blocks_changed(gmap, window, size, since)
            if not blocks:  # every block is as it is now
                return out
            pass_began, since = since, gmap.store.clock
    # The last: every block changed since the last pass began (during it, or since), read at one moment.
    with gmap.lock:
        last = [
            (block, map_probability(gmap, block)) for block in _blocks_changed(gmap, window, size, pass_began)
        ]
    for block, probability in last:
        write(block, probability)
    return out


def map_state(gmap: GridMap, window: Window, scale: int = 1) -> np.ndarray:
    """The trinary `state` codes (`STATE_UNKNOWN` / `STATE_FREE` / `STATE_OCCUPIED`, uint8, row 0 =
    lowest y) of `map_probability` by the map's thresholds, the classification the nav2 files show,
    read as `by_blocks` reads it; with `scale` > 1 (a window `aligned` to it), a code per block of
    `scale` x `scale` cells, of its `most_occupied` cell."""
    return by_blocks(gmap, window, scale, gmap.classify_probability)


def nav2_files(gmap: GridMap, window: Window, name: str = "map", scale: int = 1) -> dict[str, bytes]:
    """`{name}.yaml` and `{name}.pgm` in the nav2 map_server format, of `map_state` (a cell per
    `scale` x `scale` of the map's, the window `aligned` to `scale`)."""
    image = state_to_pgm(map_state(gmap, window, scale))
    yaml_text = nav2_yaml(
        f"{name}.pgm", export_resolution(gmap.resolution, scale), window.origin(gmap.resolution)
    )
    return {f"{name}.yaml": yaml_text.encode(), f"{name}.pgm": pgm_bytes(image)}


#: The time every entry of an export's zip carries (zip's earliest): the archive is then the same
#: bytes for the same map, where each entry carried the time of the request, so two downloads of an
#: unchanged map differed (a backup's checksum, a sync tool, a cache compared them in vain).
ZIP_ENTRY_TIME = (1980, 1, 1, 0, 0, 0)


def nav2_zip(gmap: GridMap, window: Window, name: str = "map", scale: int = 1) -> bytes:
    """The nav2 files in one zip archive, the same bytes for the same map (`ZIP_ENTRY_TIME`)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for filename, data in nav2_files(gmap, window, name, scale).items():
            entry = zipfile.ZipInfo(filename, date_time=ZIP_ENTRY_TIME)
            entry.external_attr = 0o644 << 16  # rw-r--r-- when unzipped, as writestr gives a name
            zf.writestr(entry, data, compress_type=zipfile.ZIP_DEFLATED)
    return buf.getvalue()


#: The coarsest export: a pixel per block of at most this many cells a side.
MAX_EXPORT_SCALE = 256


def export_scale(map_resolution: float, resolution: float) -> int:
    """How many of a map's cells a side one cell of an export at `resolution` holds: `resolution`
    must be a whole multiple of the map's, from 1 to MAX_EXPORT_SCALE times (to a part in 10^9,
    so that 0.15 is 3 x 0.05); ValueError saying why otherwise."""
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"an export's resolution must be a positive number of metres, got {resolution!r}")
    ratio = resolution / map_resolution  # inf for 1e308 m: refused before it is rounded (OverflowError)
    scale = round(ratio) if ratio < 2 * MAX_EXPORT_SCALE else 0
    if not 1 <= scale <= MAX_EXPORT_SCALE or abs(scale * map_resolution - resolution) > 1e-9 * resolution:
        raise ValueError(
            f"an export's resolution must be the map's ({map_resolution!r} m) times a whole number from 1 "
            f"to {MAX_EXPORT_SCALE}, got {resolution!r}"
        )
    return scale


#: The significant digits an export's resolution is stated to (`export_resolution`).
RESOLUTION_DIGITS = 15


def export_resolution(map_resolution: float, scale: int) -> float:
    """The resolution of an export at `scale` (`export_scale`), as its files state it: the map's
    exactly when `scale` is 1, else the product to RESOLUTION_DIGITS significant digits, which drops
    a float's rounding (0.15 for 3 x 0.05, where the float product is 0.15000000000000002) and
    nothing else. Rounded to the nanometre as the origins are, 3 x 0.05000000074505806 (a float32's
    0.05) was stated 0.150000002, whose grid parts from the exported cells' by 1.5e-9 cells a cell:
    the map's export 200 m from the origin was off the grid of its own YAML, and did not import."""
    return map_resolution if scale == 1 else float(f"{scale * map_resolution:.{RESOLUTION_DIGITS}g}")


def probability_grey(probability: np.ndarray) -> np.ndarray:
    """The grey of each probability, `255 (1 - p)` to the nearest integer (half to even), as float64;
    NaN stays NaN. The one rule of every grey image of a map: tiles, region PNGs, exports.

    Computed in double precision from the float32 `p` the map reports, where `1 - p` and the product
    are exact: in float32 both were rounded, and a cell hit once (p = 0.699999988, 76.500003) was
    drawn 76, not 77."""
    return np.rint(255.0 * (1.0 - np.asarray(probability, dtype=np.float64)))


def probability_to_gray(probability: np.ndarray) -> np.ndarray:
    """Grayscale pixels, darker = more likely occupied (`probability_grey`); unknown as p = 0.5.
    Rows stay in the order given (`map_image` turns the image top row = highest y)."""
    return probability_grey(np.nan_to_num(probability, nan=0.5)).astype(np.uint8)


def png_bytes(pixels: np.ndarray) -> bytes:
    """A PNG of a 2D uint8 (grayscale) or 3D uint8 (RGB / RGBA) array."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels)).save(buf, format="PNG", optimize=False, compress_level=1)
    return buf.getvalue()


def map_png(gmap: GridMap, window: Window, scale: int = 1) -> bytes:
    """`map_probability` of a window as a grayscale PNG (a pixel per `scale` x `scale` cells)."""
    return png_bytes(map_image(gmap, window, probability_to_gray, scale))


def npy_bytes(array: np.ndarray) -> bytes:
    """`array` in numpy's .npy format (no pickled objects), as `np.load` reads it back."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


#: Bytes a cell takes in the largest arrays `write_build_outputs` makes over its window (a layer's,
#: float32 or uint32).
BUILD_CELL_BYTES = 4

#: Every file `write_build_outputs` may write: map.yaml, map.pgm and map.png (not for a TSDF-only
#: map), one .npy per stored layer array, and meta.json.
BUILD_FILES = (
    "map.yaml", "map.pgm", "map.png", "log_odds.npy", "hits.npy", "misses.npy", "tsdf.npy",
    "tsdf_weight.npy", "meta.json",
)  # fmt: skip


def write_build_outputs(gmap: GridMap, out_dir: str | os.PathLike[str], margin: int = 2) -> list[Path]:
    """Everything `fleetmap build` writes into `out_dir` (created if missing): map.yaml, map.pgm,
    map.png, one .npy per stored layer, and meta.json, over the observed cells plus `margin` unknown
    cells around them (ValueError unless `margin` >= 0, see `known_window`). The map files show the
    occupancy layer, or for a map that keeps only counts (and maybe the TSDF) the count model's
    `hits / (hits + misses)`, which meta.json's `map_source` names. A file an earlier build into the
    same folder wrote (`earlier_build_files`) that this map has none of (of other layers) is
    removed: it described another map (another window, resolution or data), and a reader of the
    folder, nav2 loading map.yaml or a script loading hits.npy, took it for this one's. Returns the
    paths written; raises ValueError for a map with no observed cell, and MemoryError for one whose
    window does not fit in memory (nothing written).

    Each file is written beside its final name (`.NAME.partial`) and all take their names only once
    every one is written: a build that fails on the way (a full disk, a file-size limit) leaves the
    folder as it was, where it left a truncated map.pgm beside a new map.yaml, and an earlier
    build's other files, for nav2 to load.

    The files are of one state of the map: it holds the map's lock while it writes them, so a scan
    integrated by another thread meanwhile waits (one that went in between two files was in some
    of them and not the others: a map.pgm with a wall that log_odds.npy did not hold)."""
    out_dir = Path(out_dir)
    with gmap.lock:  # held to the end, below: the files are of one state of the map
        return _write_build_outputs(gmap, out_dir, margin)


def _write_build_outputs(gmap: GridMap, out_dir: Path, margin: int) -> list[Path]:
    """`write_build_outputs`, under the map's lock."""
    window = known_window(gmap, margin)
    if window is None:
        raise ValueError("the map has no observed cell: nothing to export")
    if window.cells * BUILD_CELL_BYTES > np.iinfo(np.intp).max:
        # numpy refuses an array past the address space with a ValueError ('array is too big'), not
        # the MemoryError of any other allocation that does not fit: fleetmap build passed its words
        # on, where a map a little smaller got the build's own error, naming the far pose.
        raise MemoryError(f"the map's window of {window.cells:,} cells is past this machine's address space")
    written: list[Path] = []
    earlier: list[Path] = []
    made_dir = not out_dir.exists()
    with contextlib.ExitStack() as holding:

        def write(filename: str, data: bytes | np.ndarray) -> None:
            # Each file as soon as it is made, the layers one at a time: a dense window spans the
            # whole map, and holding every file at once took several times the tiles' memory. The
            # folder is made with the first file, so that a map too large to export leaves none
            # behind, and held from then on (`_hold_folder`); what an earlier build left in it is
            # read once it is held, as another build may have just written it.
            if not written:
                holding.enter_context(_hold_folder(out_dir))
                earlier.extend(earlier_build_files(out_dir))
            path = out_dir / filename
            written.append(path)
            with open(_partial(path), "wb") as file:
                if isinstance(data, np.ndarray):
                    np.save(file, data, allow_pickle=False)
                else:
                    file.write(data)

        try:
            _write_build_files(gmap, window, write)
            _install(written)
        except BaseException:
            for path in written:
                _partial(path).unlink(missing_ok=True)
            if made_dir and out_dir.is_dir() and not any(out_dir.iterdir()):
                out_dir.rmdir()
            raise
        for path in earlier:
            if path not in written:
                path.unlink(missing_ok=True)
    return written


@contextlib.contextmanager
def _hold_folder(out_dir: Path) -> Iterator[None]:
    """Make `out_dir` if missing and hold it while one `write_build_outputs` writes into it: an
    exclusive `flock` of the folder itself, which another one into the same folder waits for (the
    kernel drops it when the process ends, however it ends). Two builds at once (a `make -j`, a
    build started again in another terminal) wrote the same `.NAME.partial` files and renamed each
    other's: the folder was left with map.yaml and map.pgm of one map beside meta.json and the
    arrays of the other. A folder removed while this waited (the other build failed, and removed
    the folder it had made) is made again. Where the file system takes no such lock (some network
    file systems), the folder is written unheld."""
    while True:
        out_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(out_dir, os.O_RDONLY | os.O_DIRECTORY)
        try:
            with contextlib.suppress(OSError):  # no flock there (ENOLCK, EOPNOTSUPP)
                fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                held = os.path.samestat(os.fstat(fd), os.stat(out_dir))
            except FileNotFoundError:
                held = False
            if held:
                yield
                return
        finally:
            os.close(fd)


def earlier_build_files(out_dir: str | os.PathLike[str]) -> list[Path]:
    """The files an earlier `write_build_outputs` left in `out_dir`, as its meta.json names them
    (its `layers`' .npy files, the map files unless its `map_source` was None, and itself), in
    `BUILD_FILES` order; none without a meta.json of a build. Only those are an earlier build's:
    every file of a `BUILD_FILES` name was taken for one, so a build into a folder holding the
    user's own map.png or hits.npy (`--out .`, an unset variable's `--out ""`) deleted it."""
    out_dir = Path(out_dir)
    try:
        meta = json.loads((out_dir / "meta.json").read_bytes())
    # None, or not a build's (ValueError: JSON's and UTF-8's errors; RecursionError: JSON nested
    # thousands deep, which json's parser recurses into).
    except (OSError, ValueError, RecursionError):
        return []
    layers = meta.get("layers") if isinstance(meta, dict) else None
    if not isinstance(layers, list) or "map_source" not in meta:
        return []
    names = {"meta.json", *(f"{layer}.npy" for layer in layers if isinstance(layer, str))}
    if meta["map_source"] is not None:
        names.update(("map.yaml", "map.pgm", "map.png"))
    return [out_dir / name for name in BUILD_FILES if name in names and (out_dir / name).is_file()]


def _partial(path: Path) -> Path:
    """Where `write_build_outputs` writes `path` until every file is written."""
    return path.with_name(f".{path.name}.partial")


def _install(paths: list[Path]) -> None:
    """Give each written file (`_partial`) its name, all or none: when one cannot take it (its name
    is a folder; in a sticky folder such as /tmp, another user's file), the files already renamed
    get their earlier contents back, kept meanwhile as hard links, and the error is raised. Renamed
    one by one without that, a failure left the new map.yaml beside the earlier map.pgm.

    A name that is a folder is refused before anything is renamed (a folder is not a file to
    replace). On a file system without hard links (FAT) the earlier files are kept as copies; one
    that cannot be kept stops it before any rename."""
    for path in paths:
        if path.is_dir() and not path.is_symlink():
            raise IsADirectoryError(errno.EISDIR, "a folder has the name of an output", str(path))
    kept: dict[Path, Path] = {}  # earlier file -> where it is kept (registered first: always removed)
    renamed: list[Path] = []
    try:
        for path in paths:
            if os.path.lexists(path):
                kept[path] = _previous(path)
                kept[path].unlink(missing_ok=True)
                try:
                    os.link(path, kept[path], follow_symlinks=False)
                except OSError:
                    shutil.copy2(path, kept[path], follow_symlinks=False)
        for path in paths:
            os.replace(_partial(path), path)
            renamed.append(path)
    except BaseException:
        for path in renamed:
            if path in kept:
                os.replace(kept.pop(path), path)
            else:
                path.unlink(missing_ok=True)
        raise
    finally:
        for link in kept.values():
            link.unlink(missing_ok=True)


def _previous(path: Path) -> Path:
    """Where `_install` keeps the earlier file of `path` until every new one has its name."""
    return path.with_name(f".{path.name}.previous")


def _write_build_files(
    gmap: GridMap, window: Window, write: Callable[[str, bytes | np.ndarray], None]
) -> None:
    """`write_build_outputs`' files, each given to `write(filename, data)` as soon as it is made."""
    source = map_source(gmap)
    if source is not None:
        for filename, data in nav2_files(gmap, window).items():
            write(filename, data)
        write("map.png", map_png(gmap, window))
    layers: list[str] = []
    if gmap.config.has("occupancy"):
        layers.append("log_odds")
    if gmap.config.has("counts"):
        layers += ["hits", "misses"]
    if gmap.config.has("tsdf"):
        layers += ["tsdf", "tsdf_weight"]
    for layer in layers:
        write(f"{layer}.npy", gmap.region(layer, window.i0, window.j0, window.i1, window.j1))
    meta = {
        "resolution": gmap.resolution,
        "origin": list(window.origin(gmap.resolution)),
        "shape": list(window.shape),
        "cell_window": [window.i0, window.j0, window.i1, window.j1],
        "layers": layers,
        "map_source": source,  # what map.pgm and map.png show (None: a TSDF-only map has none)
        "config": gmap.config.model_dump(mode="json"),
    }
    write("meta.json", (json.dumps(meta, indent=2) + "\n").encode())
