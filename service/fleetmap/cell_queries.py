"""The vocabulary of a map's cell and ray queries, without the engine that answers them.

What `GridMap.cells` and `GridMap.cast_rays` take (`Points`, `as_points`, the ray limits,
`UnknownCells`), what their answers' codes mean (`STATE_NAMES`, `RAY_STATUS_NAMES`), and where a
cell begins (`cell_edge`).
The REST edge needs these and not the engine: `fleetmap.api_models` writes answers with them and
`fleetmap_client.rest` checks requests with them. So this module imports numpy only, never
`fleetmap.kernels` (whose import loads numba) nor anything that does: importing the REST client
must not load numba and the engine. `fleetmap.grid_map` imports every name here and re-exports it
under the same name, so `from fleetmap.grid_map import MAX_RAYS` means what it always has.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

#: Map points as `GridMap.cells` (and the REST client's `cells`) take them: (x, y) pairs, shape
#: (n, 2), or one pair alone (one point).
Points = Sequence[Sequence[float]] | Sequence[float] | np.ndarray

#: Codes of the `state` layer.
STATE_UNKNOWN, STATE_FREE, STATE_OCCUPIED = 0, 1, 2
STATE_NAMES = {STATE_UNKNOWN: "unknown", STATE_FREE: "free", STATE_OCCUPIED: "occupied"}

#: Codes of a ray's `RaycastResult.status` (why it stopped), and their names (as the REST API
#: answers them). `kernels.raycast` writes them: numba compiles them into its cached machine code as
#: constants, and its cache notices edits of `@njit` files only, so a change here goes with an edit
#: of `kernels/raycast.py` (which drops the cache).
RAY_OCCUPIED, RAY_UNKNOWN, RAY_MAX_RANGE = 0, 1, 2
RAY_STATUS_NAMES = {RAY_OCCUPIED: "occupied", RAY_UNKNOWN: "unknown", RAY_MAX_RANGE: "max_range"}
#: What a cast ray does at a never-observed cell: stops there (status unknown), or walks through it.
UnknownCells = Literal["stop", "pass"]

#: Bounds of one `GridMap.cast_rays` call, which holds the map's lock (integration needs it) for its
#: whole walk: rays, the longest ray in cells (`max_range / resolution`), and rays x that length. The
#: walk takes about 2 ns a cell (1.4 cells per cell of length on a diagonal), so 2**24 cells, as many
#: as a region read copies, hold the lock for at most about 50 ms; 10,000 rays of 20,000 cells each
#: held it 0.5 s where nothing stopped them early. A scan of 360 rays may still look 20,000 cells
#: (1 km at 0.05 m) far, and 10,000 rays 1,677 cells (84 m).
MAX_RAYS = 10_000
MAX_RAY_CELLS = 20_000
MAX_RAY_WALK = 2**24


#: The decimals of a metre `cell_edge` rounds to: the nanometre.
EDGE_DIGITS = 9


def cell_edge(index: int, resolution: float) -> float:
    """The map coordinate where cell `index` begins (`index * resolution`), rounded to the nanometre
    (EDGE_DIGITS) so that exports say -20.2 rather than the product's -20.200000000000003. The
    rounding moves the edge by far less than any resolution a map may have, but by more than a
    billionth of a cell at a resolution of more than nine decimals (see `api.routes_data._edge`)."""
    return round(index * resolution, EDGE_DIGITS)


#: An integer as the engine and the clients take one (`is_whole_number`): Python's or NumPy's. A
#: NumPy integer (a seq from `np.arange`, an index read from an array) is no `int` to a type checker.
Integer = int | np.integer[Any]
#: A number as the engine and the clients take one (`real_number`): Python's or NumPy's, an integer
#: too. A NumPy float32 or integer (a coordinate read from an array) is no `float` to a type checker.
Real = float | np.floating[Any] | np.integer[Any]


def is_whole_number(value: object) -> bool:
    """Whether `value` is an integer, Python's or NumPy's: not a bool (an int to Python, none to
    NumPy), nor a float, whole or not (a count, a size or an index given as 2.5 is a mistake)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def real_number(value: object) -> float:
    """`float(value)`, but TypeError for a string or bytes, which `float` (and numpy) would read
    ("1.5", b"inf"): the engine takes numbers, as the wire's JSON does, not text that looks like one;
    and TypeError for a bool (`float(True)` is 1.0: a pose's x given as True was 1 m) and for a NumPy
    date or duration (`float` gives its count of days or seconds since some epoch)."""
    if isinstance(value, str | bytes | bytearray | bool | np.bool_ | np.datetime64 | np.timedelta64):
        raise TypeError(f"got {type(value).__name__} {value!r}, not a number")
    return float(value)  # type: ignore[arg-type]  # TypeError for what is no number


def float_array(values: npt.ArrayLike) -> np.ndarray:
    """`values` as a float64 array, as `np.asarray(values, dtype=np.float64)`, but ValueError for
    complex numbers: numpy drops their imaginary parts with a warning only, so two points written
    x + yj, an array of shape (2,), were read as the one point (x1, x2), and directions as unit
    complex numbers as angles equal to their cosines; ValueError for text, which numpy parses
    ("0.5"), as `real_number` refuses it; ValueError for an array of bools, dates or durations, which
    numpy converts to 0 / 1, days or seconds (ranges of True were walls 1 m away; `real_number`
    refuses them one by one); and ValueError, not OverflowError (no ValueError, so past
    the callers' documented errors), for an int beyond float's range. Raises what `np.asarray`
    raises otherwise."""
    if np.iscomplexobj(values):
        raise ValueError("got complex numbers, whose imaginary parts would be dropped: give real ones")
    try:
        array = np.asarray(values)
        if array.dtype.kind in "SUV" or (
            array.dtype == object and any(isinstance(v, str | bytes | bytearray) for v in array.flat)
        ):
            raise ValueError(f"got text ({array.dtype}), not numbers")
        if array.dtype.kind in "bmM":
            raise ValueError(f"got {array.dtype} values, not numbers")
        return array.astype(np.float64, copy=False)
    except OverflowError:
        raise ValueError("got an integer beyond the range of a float") from None


def as_points(points: Points) -> np.ndarray:
    """Map points as a float64 array of shape (n, 2); one (x, y) pair alone is one point, an empty
    sequence (or an array of shape (0, 2)) none. Raises ValueError for any other shape (an (n, 3)
    array is not read as 3n/2 points, nor `[[]]` or an (n, 0) array as no points), for values that
    are not numbers (complex ones too: two points x + yj are not the pair of their real parts), and
    for a coordinate that is not finite."""
    try:
        pts = float_array(points)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"points must be (x, y) pairs of numbers: {exc}") from None
    # Only these are "no points": `[[]]` is one point without coordinates, and an (n, 0) array n of
    # them; read as none, the answer had 0 entries where the caller counted on n.
    if pts.shape in ((0,), (0, 2)):
        return pts.reshape(0, 2)
    if pts.shape == (2,):
        pts = pts.reshape(1, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be (x, y) pairs, an array of shape (n, 2); got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points must be finite numbers")
    return pts


__all__ = [
    "EDGE_DIGITS",
    "MAX_RAYS",
    "MAX_RAY_CELLS",
    "MAX_RAY_WALK",
    "RAY_MAX_RANGE",
    "RAY_OCCUPIED",
    "RAY_STATUS_NAMES",
    "RAY_UNKNOWN",
    "STATE_FREE",
    "STATE_NAMES",
    "STATE_OCCUPIED",
    "STATE_UNKNOWN",
    "Integer",
    "Points",
    "Real",
    "UnknownCells",
    "as_points",
    "cell_edge",
    "float_array",
    "is_whole_number",
    "real_number",
]
