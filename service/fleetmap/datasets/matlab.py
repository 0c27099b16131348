"""Reader for the .mat logs of the Coursera course "Robotics: Estimation and Learning" (UPenn).

A file (MATLAB v4 to v7.2; v7.3 is HDF5, which `scipy.io.loadmat` can't read) holds:

* `ranges`: N x K, the range of beam n in scan k (metres),
* `scanAngles`: N x 1 (or 1 x N), the beam bearings relative to the robot heading (radians),
* `pose`: 3 x K, the robot pose (x, y, theta) of scan k, which is also the sensor pose,
* optionally `param` and `t`, ignored. Other variables are ignored too.

The course's frame has y pointing DOWN (y is the row index of its map image): its mapping code
puts the end point of a beam at

    x_occ = r*cos(a + theta) + x,    y_occ = -r*sin(a + theta) + y.

fleetmap's frame has y up. Flipping y (Y = -y) turns that end point into
`(x + r*cos(theta + a), -y + r*sin(theta + a))`, which is exactly the end point of a fleetmap
`Scan` with sensor pose `(x, -y, theta)` and the beam angles `a` unchanged. So that is what this
reader produces, and the map comes out as the course's image seen the right way up (not mirrored).
Either way a positive angle turns counter-clockwise as drawn (the course's image, fleetmap's y-up map).

`range_min` defaults to 1e-3 (zero readings are ignored) and `range_max` to "no limit" (1e6, the
largest a `Scan` accepts): the files carry no maximum range. Negative and NaN readings are ignored.
To be forgiving about how a file was saved, `ranges` may also be K x N and `pose` K x 3 when that is
unambiguous (the other orientation doesn't fit).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import scipy.io

from ..scan import MAX_BEAMS, directions_finite
from .base import (
    UNBOUNDED_RANGE_MAX,
    Dataset,
    DatasetBuilder,
    DatasetError,
    check_range_window,
    dataset_name,
    open_log,
)

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def read_matlab(
    path: str | Path,
    *,
    range_min: float | None = None,
    range_max: float | None = None,
    stream: BinaryIO | None = None,
) -> Dataset:
    """Read a course-style .mat file into a `Dataset` (see the module docstring for the frames).

    `range_min` (default 1e-3) and `range_max` (default no limit; `math.inf` also means no limit)
    apply to every scan. `stream`, when given, is the file already open (`open_log`, at its
    start), read instead of opening `path`, which then names it only. Raises `DatasetError` for a
    file scipy can't read, a missing variable, no scan, inconsistent shapes, non-numeric data, a
    non-finite pose or angle, or a heading plus beam angle that is not finite (overflows).
    """
    path = Path(path)
    rmin, rmax = check_range_window(range_min, range_max)
    if rmax is None:
        rmax = UNBOUNDED_RANGE_MAX
    if stream is None:
        with open_log(path) as opened:
            data = _load(opened, path)
    else:
        data = _load(stream, path)

    angles = _numeric(path, data, "scanAngles").ravel()
    n = angles.size
    if n == 0 or n > MAX_BEAMS:
        raise DatasetError(f"{path}: scanAngles has {n} beams; expected 1 to {MAX_BEAMS}")
    if not np.all(np.isfinite(angles)):
        raise DatasetError(f"{path}: scanAngles contains non-finite values")

    ranges = _numeric(path, data, "ranges")
    if ranges.ndim != 2:
        raise DatasetError(f"{path}: ranges must be a 2-D N x K array, got shape {ranges.shape}")
    if ranges.shape[0] != n:
        if ranges.shape[1] != n:
            raise DatasetError(
                f"{path}: ranges has shape {ranges.shape} but scanAngles has {n} beams; "
                "expected N x K with N = number of beams"
            )
        ranges = ranges.T  # saved as K x N
    k = ranges.shape[1]
    if k == 0:  # as a CARMEN log without a laser message is refused (`fleetmap build` said only
        # that the map had no observed cell)
        raise DatasetError(f"{path}: no scan: ranges holds 0 scans of {n} readings")

    pose = _numeric(path, data, "pose")
    if pose.shape != (3, k):
        if pose.shape != (k, 3):
            raise DatasetError(f"{path}: pose has shape {pose.shape}; expected 3 x K with K = {k} scans")
        pose = pose.T  # saved as K x 3
    bad = np.flatnonzero(~np.all(np.isfinite(pose), axis=0))
    if bad.size:
        raise DatasetError(f"{path}: scan {bad[0]} (0-based) has a non-finite pose {pose[:, bad[0]]}")

    # A scan whose beam directions overflow (finite heading plus finite bearings) is one `Scan`
    # refuses: refused here, where it was built mid-build and stopped `fleetmap build` with a traceback.
    for j in range(k):
        if not directions_finite(float(pose[2, j]), angles):
            raise DatasetError(
                f"{path}: scan {j} (0-based): heading {pose[2, j]:g} plus its beam angles overflows"
            )

    builder = DatasetBuilder()
    cols = np.ascontiguousarray(ranges.T, dtype=np.float64)  # one row per scan
    for j in range(k):
        # The y flip: see the module docstring.
        builder.add((float(pose[0, j]), -float(pose[1, j]), float(pose[2, j])), angles, cols[j], rmax)
    return builder.build(name=dataset_name(path), path=path, format="matlab", range_min=rmin)


def _load(stream: BinaryIO, path: Path) -> dict[str, Any]:
    head = stream.read(520)
    stream.seek(0)
    # MATLAB writes v7.3 files as HDF5 with a 512-byte text header ("MATLAB 7.3 MAT-file...") in
    # front, so the HDF5 signature sits at byte 512; other HDF5 writers put it at byte 0.
    if head.startswith(b"MATLAB 7.3") or HDF5_MAGIC in (head[:8], head[512:520]):
        raise DatasetError(
            f"{path}: a MATLAB v7.3 (HDF5) file, which is not supported; re-save it with save(..., '-v7')"
        )
    try:
        return scipy.io.loadmat(stream)  # type: ignore[arg-type]  # it reads a file object too (its docs)
    except Exception as exc:
        # scipy's reader fails on a non-MAT or truncated file with whatever its parsing step hits
        # (MatReadError, ValueError, IndexError on a short header, zlib.error, ...): all mean the
        # same thing to the caller.
        raise DatasetError(f"{path}: not a readable .mat file: {type(exc).__name__}: {exc}") from None


def _numeric(path: Path, data: dict[str, Any], key: str) -> np.ndarray:
    if key not in data:
        found = sorted(k for k in data if not k.startswith("__"))
        raise DatasetError(f"{path}: no variable {key!r} (found: {', '.join(found) or 'none'})")
    arr = np.asarray(data[key])
    if arr.dtype.kind not in "biuf":
        raise DatasetError(f"{path}: {key!r} must be a real numeric array, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)
