"""The reader-independent part of the dataset package: `Dataset`, `DatasetError` and the builder.

A reader parses its whole file up front into a few flat arrays (poses, all ranges back to back, the
distinct beam-angle sets) through `DatasetBuilder`; `Dataset` then hands out one freshly built
`Scan` per log entry. Parsing up front means every malformed line is reported by `load_dataset`
itself, with its line number, and never halfway through a map build; the arrays are small (the
largest real log, 2008 scans of 360 beams, is under 6 MB).
"""

from __future__ import annotations

import io
import math
import operator
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, SupportsIndex, overload

import numpy as np

from ..cell_queries import real_number
from ..scan import Pose2D, Scan

#: Default `range_min` of every reader. The logs have no minimum range, but a reading of exactly 0
#: is a sensor's "no measurement" code, not an obstacle at the sensor, so it must be ignored: the
#: engine ignores readings below `range_min`, and 1 mm is below anything a 2D lidar can measure.
DEFAULT_RANGE_MIN = 1e-3

#: The `range_max` readers give for "no limit" (a caller's `range_max=math.inf`, and every scan of a
#: .mat file, which has none), and the largest they accept: a million metres, past any laser. (A
#: `Scan` itself takes +inf as well.)
UNBOUNDED_RANGE_MAX = 1e6


class DatasetError(ValueError):
    """A dataset file that cannot be read: unknown format, or a malformed line or field.

    The message names the file and, for text formats, the 1-based line number.
    """


@contextmanager
def open_log(path: Path) -> Iterator[BinaryIO]:
    """The file at `path`, opened once, as a binary stream that can seek back to its start: the file
    itself, or for a pipe (`fleetmap build <(zcat log.gz)`, /dev/stdin), which can be read only
    once, all of its bytes in memory (a log is a few MB). The readers look at a file's first bytes
    to tell its format and then read it from the start: opened again, a pipe had lost those bytes
    and all its first read had buffered, so a small log read as empty, the Intel log lost its first
    scan without a word, and a gzipped one was 'not UTF-8 text'. Raises `OSError` as `open` does."""
    with open(path, "rb") as file:
        yield file if file.seekable() else io.BytesIO(file.read())


def check_range_window(
    range_min: float | None, range_max: float | None, names: tuple[str, str] = ("range_min", "range_max")
) -> tuple[float, float | None]:
    """Validate caller overrides; return `(range_min, range_max)` with defaults filled in.

    `range_min` defaults to `DEFAULT_RANGE_MIN`; `range_max` stays None ("use the file's value") when
    not given, and +inf becomes `UNBOUNDED_RANGE_MAX`. Raises `DatasetError` for a window no `Scan`
    would accept, so a bad override fails at load time rather than on the first scan; its message
    calls the two `names` (`fleetmap build` passes its options', `--range-min` and `--range-max`).
    """
    min_name, max_name = names
    rmin = DEFAULT_RANGE_MIN if range_min is None else _number(min_name, range_min)
    # Below UNBOUNDED_RANGE_MAX too: no scan of any reader has a larger range_max (a .mat file's all
    # have it), so a larger range_min was taken here and every scan failed as it was built, mid-build.
    if not (math.isfinite(rmin) and 0.0 <= rmin < UNBOUNDED_RANGE_MAX):
        raise DatasetError(
            f"{min_name} must be finite, >= 0 and below {UNBOUNDED_RANGE_MAX:g} m (the largest range_max "
            f"a scan of a log may have), got {range_min!r}"
        )
    if range_max is None:
        return rmin, None
    rmax = _number(max_name, range_max)
    if rmax == math.inf:
        rmax = UNBOUNDED_RANGE_MAX
    if not (rmax > rmin and rmax <= UNBOUNDED_RANGE_MAX):
        raise DatasetError(
            f"{max_name} must be greater than {min_name} ({rmin}) and at most {UNBOUNDED_RANGE_MAX:g} m "
            f"(or inf), got {range_max!r}"
        )
    return rmin, rmax


def _number(name: str, value: object) -> float:
    """`value` as a float, or `DatasetError` naming `name`: text ("20") is no number here, as it is
    none to a `Scan` (`real_number`); float() parsed it, or raised its bare ValueError."""
    try:
        return real_number(value)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{name} must be a number, got {value!r:.40}") from None


class DatasetBuilder:
    """Accumulates parsed scans, then freezes them into a `Dataset`.

    Readers pass each scan's SENSOR pose, its beam angles and ranges, and its `range_max`. Angle
    arrays are stored once per distinct array object, so a reader that reuses one array for every
    scan with the same beam layout (all real logs have one layout) stores it once.
    """

    def __init__(self) -> None:
        self._poses: list[tuple[float, float, float]] = []
        self._ranges: list[np.ndarray] = []
        self._range_max: list[float] = []
        self._angle_sets: list[np.ndarray] = []
        self._angle_set_ids: dict[int, int] = {}
        self._angle_set_of_scan: list[int] = []

    def __len__(self) -> int:
        return len(self._poses)

    def add(
        self, pose: tuple[float, float, float], angles: np.ndarray, ranges: np.ndarray, range_max: float
    ) -> None:
        """Append one scan. The caller has checked that the pose is finite and the lengths match."""
        key = id(angles)
        index = self._angle_set_ids.get(key)
        if index is None:
            index = len(self._angle_sets)
            self._angle_sets.append(angles)  # keeping a reference also keeps id(angles) unique
            self._angle_set_ids[key] = index
        self._angle_set_of_scan.append(index)
        self._poses.append(pose)
        self._ranges.append(ranges)
        self._range_max.append(range_max)

    def build(self, *, name: str, path: Path, format: str, range_min: float) -> Dataset:
        """Freeze the scans added so far into a `Dataset` (copying the ranges into one array)."""
        n = len(self._poses)
        lengths = np.fromiter((r.size for r in self._ranges), dtype=np.int64, count=n)
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(lengths, out=offsets[1:])
        # (Negative readings, error codes in some drivers, stay as they are: `Scan` ignores them, as
        # it ignores every reading below range_min.)
        ranges = np.concatenate(self._ranges).astype(np.float64, copy=False) if n else np.zeros(0, np.float64)
        return Dataset(
            name=name,
            path=path,
            format=format,
            poses=np.array(self._poses, dtype=np.float64).reshape(n, 3),
            ranges=ranges,
            offsets=offsets,
            angle_sets=[np.asarray(a, dtype=np.float64) for a in self._angle_sets],
            angle_set_of_scan=np.array(self._angle_set_of_scan, dtype=np.int32),
            range_max_of_scan=np.array(self._range_max, dtype=np.float64),
            range_min=range_min,
        )


class Dataset:
    """A recorded laser log: a fixed sequence of `Scan`s with known sensor poses, in log order.

    Attributes:
        name: the file name without its extensions (`intel-corrected` for `intel-corrected.log.gz`).
        path: the file it was read from.
        format: `"carmen"` or `"matlab"`.
        range_min: the `range_min` of every scan.
        range_max: the largest `range_max` of any scan (every scan of the real logs has the same
            one; a CARMEN log whose `robot_front_laser_max` changes mid-log could differ per scan).

    `len(ds)` is the number of scans, known without building any. `iter(ds)` can be called any
    number of times and yields new `Scan` objects whose arrays are private copies, so a consumer may
    modify them. `ds[i]` builds scan i alone, `ds[a:b]` the list of those scans.
    """

    def __init__(
        self,
        *,
        name: str,
        path: Path,
        format: str,
        poses: np.ndarray,
        ranges: np.ndarray,
        offsets: np.ndarray,
        angle_sets: list[np.ndarray],
        angle_set_of_scan: np.ndarray,
        range_max_of_scan: np.ndarray,
        range_min: float,
    ) -> None:
        self.name = name
        self.path = path
        self.format = format
        self.range_min = float(range_min)
        self.range_max = float(range_max_of_scan.max()) if range_max_of_scan.size else math.nan
        self._poses = poses
        self._ranges = ranges
        self._offsets = offsets
        self._angle_sets = angle_sets
        self._angle_set_of_scan = angle_set_of_scan
        self._range_max_of_scan = range_max_of_scan

    def __len__(self) -> int:
        return int(self._poses.shape[0])

    def __iter__(self) -> Iterator[Scan]:
        for i in range(len(self)):
            yield self._scan(i)

    @overload
    def __getitem__(self, index: SupportsIndex) -> Scan: ...

    @overload
    def __getitem__(self, index: slice) -> list[Scan]: ...

    def __getitem__(self, index: SupportsIndex | slice) -> Scan | list[Scan]:
        """Scan `index` (from the end if negative; NumPy integers too), or the list of a slice's
        scans, as a list indexes: `IndexError` past the end, `TypeError` for any other index."""
        n = len(self)
        if isinstance(index, slice):
            return [self._scan(i) for i in range(*index.indices(n))]
        try:
            i = operator.index(index)
        except TypeError:
            kind = type(index).__name__
            raise TypeError(f"dataset indices must be integers or slices, not {kind}") from None
        if not -n <= i < n:
            raise IndexError(f"scan index {i} out of range for {n} scans")
        return self._scan(i % n)

    def __repr__(self) -> str:
        return f"Dataset(name={self.name!r}, format={self.format!r}, scans={len(self)}, path='{self.path}')"

    @property
    def poses(self) -> np.ndarray:
        """The sensor poses of all scans as a (len, 3) array of x, y, theta (a copy)."""
        return self._poses.copy()

    def _scan(self, i: int) -> Scan:
        x, y, theta = self._poses[i]
        return Scan(
            pose=Pose2D(float(x), float(y), float(theta)),
            angles=self._angle_sets[self._angle_set_of_scan[i]].copy(),
            ranges=self._ranges[self._offsets[i] : self._offsets[i + 1]].copy(),
            range_min=self.range_min,
            range_max=float(self._range_max_of_scan[i]),
        )


def dataset_name(path: Path) -> str:
    """The file name without `.gz` and then without one more extension."""
    name = path.name
    if name.lower().endswith(".gz"):
        name = name[:-3]
    stem, dot, _ = name.rpartition(".")
    return stem if dot and stem else name
