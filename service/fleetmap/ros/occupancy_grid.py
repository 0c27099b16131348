"""A map window as a ROS 2 `nav_msgs/msg/OccupancyGrid` message, and a part of it as the
`map_msgs/msg/OccupancyGridUpdate` that brings a grid up to date, CDR-encoded. Pure: no Zenoh.

The cells are what nav2's map_server publishes for a trinary map: 100 occupied, 0 free, -1 unknown,
by the same classification as fleetmap's nav2 export (`export.map_state`, the map's thresholds), so
`GET /maps/{id}/export?format=ros` loaded by map_server and this grid carry the same cells.

Layout (nav_msgs/msg/OccupancyGrid): `header` (stamp, frame_id), `info` (map_load_time, resolution,
width, height, origin pose), then `int8[] data` row-major starting at the origin cell: row 0 is the
lowest y, the same order as fleetmap's arrays (images are the ones flipped). `info.origin` is the
map point of the window's lower-left corner, z 0, identity orientation.

An update (map_msgs/msg/OccupancyGridUpdate: `header`, `int32 x`, `int32 y`, `uint32 width`,
`uint32 height`, `int8[] data`) carries the cells of a rectangle of the last grid's window: `x`,
`y` the column and row of its lower-left cell in that grid, `data` row-major from there, the cells
made by the same `grid_cells` as the grid's. A subscriber (RViz's Map display, nav2's static layer)
writes them over its copy of the grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetmap.cell_queries import STATE_FREE, STATE_OCCUPIED, STATE_UNKNOWN
from fleetmap.export import Window, map_state
from fleetmap.grid_map import GridMap
from fleetmap.ros.cdr import CdrWriter

ROS_TYPE = "nav_msgs/msg/OccupancyGrid"
UPDATE_ROS_TYPE = "map_msgs/msg/OccupancyGridUpdate"

#: OccupancyGrid's cell values: nav2 map_server's for a trinary map.
GRID_OCCUPIED, GRID_FREE, GRID_UNKNOWN = 100, 0, -1

#: `state` code -> cell value, indexed by the code.
_STATE_TO_GRID = np.zeros(max(STATE_UNKNOWN, STATE_FREE, STATE_OCCUPIED) + 1, dtype=np.int8)
_STATE_TO_GRID[[STATE_UNKNOWN, STATE_FREE, STATE_OCCUPIED]] = [GRID_UNKNOWN, GRID_FREE, GRID_OCCUPIED]


def grid_cells(gmap: GridMap, window: Window) -> np.ndarray:
    """The OccupancyGrid cell values (int8, shape (ny, nx), row 0 = lowest y) of a window: the nav2
    export's trinary classification (`map_state`) as 100 / 0 / -1. Reads the map one storage tile
    at a time, each under the map's lock for its copy only. Raises LayerUnavailableError for a
    TSDF-only map."""
    return _STATE_TO_GRID[map_state(gmap, window)]


@dataclass(frozen=True)
class GridInfo:
    """What an OccupancyGrid says besides its cells."""

    frame_id: str
    stamp_ns: int  # header.stamp and info.map_load_time, nanoseconds since the epoch
    resolution: float
    origin: tuple[float, float]  # the map point of the lower-left corner of cell (0, 0)


def encode_occupancy_grid(cells: np.ndarray, info: GridInfo) -> bytes:
    """The CDR bytes (XCDR1 little-endian, encapsulation header `00 01 00 00`) of an OccupancyGrid
    of `cells` (int8 values, shape (height, width), row 0 = lowest y)."""
    height, width = cells.shape
    w = CdrWriter()
    sec, nanosec = _write_header(w, info.frame_id, info.stamp_ns)
    w.write_int32(sec)  # info.map_load_time
    w.write_uint32(nanosec)
    w.write_float32(info.resolution)
    w.write_uint32(width)
    w.write_uint32(height)
    for value in (info.origin[0], info.origin[1], 0.0, 0.0, 0.0, 0.0, 1.0):  # position, orientation
        w.write_float64(value)
    w.write_sequence_int8(np.ascontiguousarray(cells, dtype=np.int8).reshape(-1))
    return w.getvalue()


def occupancy_grid(gmap: GridMap, window: Window, frame_id: str, stamp_ns: int) -> bytes:
    """The CDR bytes of the OccupancyGrid of `window` of `gmap` (see `grid_cells`)."""
    info = GridInfo(frame_id, stamp_ns, gmap.resolution, window.origin(gmap.resolution))
    return encode_occupancy_grid(grid_cells(gmap, window), info)


def encode_occupancy_grid_update(cells: np.ndarray, x: int, y: int, frame_id: str, stamp_ns: int) -> bytes:
    """The CDR bytes (as `encode_occupancy_grid`'s) of an OccupancyGridUpdate of `cells` (int8 values,
    shape (height, width), row 0 = lowest y) whose lower-left cell is column `x`, row `y` of the grid
    it updates."""
    height, width = cells.shape
    w = CdrWriter()
    _write_header(w, frame_id, stamp_ns)
    w.write_int32(x)
    w.write_int32(y)
    w.write_uint32(width)
    w.write_uint32(height)
    w.write_sequence_int8(np.ascontiguousarray(cells, dtype=np.int8).reshape(-1))
    return w.getvalue()


def occupancy_grid_update(gmap: GridMap, window: Window, part: Window, frame_id: str, stamp_ns: int) -> bytes:
    """The CDR bytes of the OccupancyGridUpdate that brings the cells of `part` (inside `window`) of
    the OccupancyGrid of `window` up to date: `grid_cells` of `part`, at its offset in `window`."""
    if not (window.i0 <= part.i0 <= part.i1 <= window.i1 and window.j0 <= part.j0 <= part.j1 <= window.j1):
        raise ValueError(f"the update's cells {part} are not inside the grid's {window}")
    cells = grid_cells(gmap, part)
    return encode_occupancy_grid_update(cells, part.i0 - window.i0, part.j0 - window.j0, frame_id, stamp_ns)


def _write_header(w: CdrWriter, frame_id: str, stamp_ns: int) -> tuple[int, int]:
    """Write a std_msgs/msg/Header (stamp, frame_id); returns the stamp as (sec, nanosec)."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    w.write_int32(sec)
    w.write_uint32(nanosec)
    w.write_string(frame_id)
    return sec, nanosec
