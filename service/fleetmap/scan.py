"""One laser scan taken from a known sensor pose: the engine's input type.

A `Scan` is validated when it is built, so everything downstream (sensor models, kernels) can assume
finite poses, matching array lengths and a sane range window. Invalid input raises `ScanError` and
builds nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmap.cell_queries import float_array, real_number

#: Beams per scan accepted by the engine; far above any real 2D scanner (a 0.1 degree 360 degree
#: scanner has 3600). Protects the kernels from absurd allocations.
MAX_BEAMS = 100_000


class ScanError(ValueError):
    """A scan that cannot be integrated. The message says what is wrong with it."""


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A pose in the map frame: metres, and radians counter-clockwise from the +x axis."""

    x: float
    y: float
    theta: float

    def is_finite(self) -> bool:
        """Whether x, y and theta are all finite (no NaN or infinity): `Scan` requires it."""
        return math.isfinite(self.x) and math.isfinite(self.y) and math.isfinite(self.theta)


@dataclass(frozen=True, eq=False)
class Scan:
    """A 2D range scan taken from `pose`, the SENSOR pose in the map frame.

    `angles[i]` is beam i's bearing relative to the sensor heading, in radians. `ranges[i]` is its
    measured range in metres, NaN for an invalid reading and +inf (or anything >= `range_max`) for
    "no return". Readings below `range_min` (negative ones included: some drivers report errors so)
    or NaN are ignored by every sensor model, and the scan's other beams are integrated.

    Build one with `from_fan` (ROS LaserScan style) or `from_angles`, or directly, which takes the
    same inputs: a `Pose2D` or an (x, y, theta) sequence, sequences or arrays of numbers (not a
    generator or a set: the beams' order is theirs; stored as contiguous float64; None in `ranges`
    means "no return", as in JSON, and a masked element of a masked array of ranges an invalid
    reading, NaN; masked angles are refused), and numbers for the range window. Anything invalid
    (non-finite pose or angles, mismatched lengths, a range window that is not
    `0 <= range_min < range_max`, inputs that are not numbers) raises `ScanError`, a ValueError.
    Arrays that are contiguous float64 already are kept, not copied (every decoded scan comes so):
    the checks hold for them as they were when the scan was built, so do not write into an array a
    scan holds (a NaN angle written later is no longer refused, and fails the integration).
    """

    pose: Pose2D
    angles: np.ndarray  # float64, shape (n,)
    ranges: np.ndarray  # float64, shape (n,)
    range_min: float
    range_max: float

    def __post_init__(self) -> None:
        # The constructor takes what `from_fan` / `from_angles` take (a pose tuple, lists, None for
        # "no return"), so that building a Scan directly means the same as through them.
        # The checks of types already right are skipped: every decoded and replayed scan comes here.
        pose = self.pose
        if type(pose) is not Pose2D or not type(pose.x) is type(pose.y) is type(pose.theta) is float:
            object.__setattr__(self, "pose", _as_pose(pose))
        angles, ranges = self.angles, self.ranges
        if type(angles) is not np.ndarray or angles.dtype != np.float64:
            angles = _as_floats("angles", angles)
        if type(ranges) is not np.ndarray or ranges.dtype != np.float64:
            ranges = ranges_to_array(ranges)
        object.__setattr__(self, "angles", np.ascontiguousarray(angles))
        object.__setattr__(self, "ranges", np.ascontiguousarray(ranges))
        if type(self.range_min) is not float:
            object.__setattr__(self, "range_min", _as_number("range_min", self.range_min))
        if type(self.range_max) is not float:
            object.__setattr__(self, "range_max", _as_number("range_max", self.range_max))
        if not self.pose.is_finite():
            raise ScanError(f"pose must be finite, got {self.pose}")
        if angles.ndim != 1 or ranges.ndim != 1:
            raise ScanError("angles and ranges must be one-dimensional")
        if angles.shape != ranges.shape:
            raise ScanError(f"{angles.size} angles but {ranges.size} ranges: they must match")
        if angles.size > MAX_BEAMS:
            raise ScanError(f"{angles.size} beams is more than the limit of {MAX_BEAMS}")
        if not np.all(np.isfinite(angles)):
            raise ScanError("beam angles must be finite")
        if angles.size and not directions_finite(self.pose.theta, angles):
            raise ScanError(
                f"the sensor heading plus its beam angles must be finite: heading {self.pose.theta:g} with "
                f"angles from {angles.min():g} to {angles.max():g} overflows"
            )
        if not (math.isfinite(self.range_min) and self.range_min >= 0.0):
            raise ScanError(f"range_min must be finite and >= 0, got {self.range_min}")
        if not self.range_max > self.range_min:  # inf is allowed: "no maximum"
            raise ScanError(f"range_max {self.range_max:g} must be greater than range_min {self.range_min:g}")

    @classmethod
    def from_fan(
        cls,
        pose: Pose2D | tuple[float, float, float],
        angle_min: float,
        angle_increment: float,
        ranges: Sequence[float | None] | np.ndarray,
        range_min: float = 0.0,
        range_max: float = math.inf,
    ) -> Scan:
        """Build a scan whose beam i points at `angle_min + i * angle_increment` (ROS LaserScan style)."""
        r = ranges_to_array(ranges)
        angle_min = _as_number("angle_min", angle_min)
        angle_increment = _as_number("angle_increment", angle_increment)
        if not (math.isfinite(angle_min) and math.isfinite(angle_increment)):
            raise ScanError("angle_min and angle_increment must be finite")
        with np.errstate(over="ignore"):  # an overflow makes an infinite angle, which Scan refuses
            angles = angle_min + angle_increment * np.arange(r.size, dtype=np.float64)
        return cls(_as_pose(pose), angles, r, range_min, range_max)

    @classmethod
    def from_angles(
        cls,
        pose: Pose2D | tuple[float, float, float],
        angles: Sequence[float] | np.ndarray,
        ranges: Sequence[float | None] | np.ndarray,
        range_min: float = 0.0,
        range_max: float = math.inf,
    ) -> Scan:
        """Build a scan from an explicit list of beam bearings (radians, relative to the heading),
        one per range; both a sequence or an array (see the class doc)."""
        angles_array = _as_floats("angles", angles)
        return cls(_as_pose(pose), angles_array, ranges_to_array(ranges), range_min, range_max)

    @property
    def num_beams(self) -> int:
        """The number of beams (of angles, and of ranges)."""
        return int(self.ranges.size)

    def returns_mask(self) -> np.ndarray:
        """Beams with a usable return: `range_min <= r < range_max`."""
        r = self.ranges
        return (r >= self.range_min) & (r < self.range_max)  # NaN compares False, without a warning

    def no_return_mask(self) -> np.ndarray:
        """Beams that saw nothing: `r >= range_max` (inf included). NaN is invalid, not "no return"."""
        with np.errstate(invalid="ignore"):
            return self.ranges >= self.range_max

    def world_angles(self) -> np.ndarray:
        """Beam directions in the map frame."""
        return self.pose.theta + self.angles

    def endpoints(self, ranges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame end points of every beam at `ranges` (default: the measured ones)."""
        r = self.ranges if ranges is None else ranges
        a = self.world_angles()
        return self.pose.x + r * np.cos(a), self.pose.y + r * np.sin(a)


def ranges_to_array(ranges: Sequence[float | None] | np.ndarray) -> np.ndarray:
    """Ranges as float64; None (a JSON null) becomes +inf, i.e. "no return", in a list and in an
    object array alike (numpy alone would make it NaN, an invalid reading). Raises `ScanError` for
    anything that is not a sequence of numbers and None (a string is not one). A masked element of a
    NumPy masked array is an invalid reading: NaN."""
    if isinstance(ranges, np.ma.MaskedArray):
        # `np.asarray` drops the mask: the value under a masked reading (0, a fill value) was
        # integrated as a return, a wall where the sensor saw nothing valid.
        return np.where(np.ma.getmaskarray(ranges), np.nan, ranges_to_array(ranges.data))
    if isinstance(ranges, np.ndarray) and ranges.dtype != object:
        return _as_floats("ranges", ranges)
    _check_beam_values("ranges", ranges, "numbers or None")
    try:
        return np.array([math.inf if v is None else real_number(v) for v in ranges], dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: an int past float's range
        raise ScanError(f"ranges must be numbers or None: {exc}") from None


def _as_floats(name: str, values: Sequence[float] | np.ndarray) -> np.ndarray:
    """`values` as a float64 array, or `ScanError` naming `name` (not numpy's bare ValueError):
    `float_array`'s rules (no complex numbers, no text), and no mask."""
    _check_beam_values(name, values, "numbers")
    if np.ma.is_masked(values):  # numpy would read the values under the mask, dropping it
        raise ScanError(f"{name} must not be masked: give every beam its value, or mask its range instead")
    if np.iscomplexobj(values):  # numpy would drop the imaginary parts, with a warning only
        raise ScanError(f"{name} must be real numbers, got complex ones")
    try:
        return float_array(values)
    except (TypeError, ValueError) as exc:
        raise ScanError(f"{name} must be numbers: {exc}") from None


def _check_beam_values(name: str, values: object, what: str) -> None:
    """`ScanError` unless `values` (one value per beam, `what` they may be) is a sequence or an
    array: the beams' order is theirs. A generator of ranges was taken where one of angles was
    refused (as numpy's "not 'generator'"), and a set's order, which is not the beams', was read as
    theirs; text is refused, whose characters are no beams."""
    if isinstance(values, str | bytes | bytearray) or not (
        isinstance(values, Sequence | np.ndarray) or hasattr(values, "__array__")
    ):
        raise ScanError(
            f"{name} must be a sequence or an array of {what}, got {type(values).__name__}: give a list "
            "or an array"
        )


def directions_finite(theta: float, angles: np.ndarray) -> bool:
    """Whether every beam's direction in the map frame, `theta + angle`, is finite (both finite, their
    sum can overflow: 1e308 + 1e308). The sum rises with the angle, so its two ends tell. Such a
    direction was integrated as a streak of cells where no beam points (its cosine is NaN). `Scan`
    refuses such a scan; the dataset readers refuse such a line when they load it."""
    return math.isfinite(theta + float(angles.min())) and math.isfinite(theta + float(angles.max()))


def _as_number(name: str, value: float) -> float:
    try:
        return real_number(value)
    except (TypeError, ValueError):
        raise ScanError(f"{name} must be a number, got {value!r}") from None
    except OverflowError:  # an int past float's range (its repr may be thousands of digits)
        raise ScanError(f"{name} must be a finite number, got an integer beyond float range") from None


def _as_pose(pose: Pose2D | tuple[float, float, float]) -> Pose2D:
    """A `Pose2D` of floats, made of a `Pose2D` or an (x, y, theta) sequence; `ScanError` for anything
    else. A `Pose2D` checks nothing when built: one of a string (`Pose2D("1", 0, 0)`) raised
    TypeError from the finiteness check, and one of an int past int64 an OverflowError in the
    kernel, where `Scan` promises ScanError."""
    if isinstance(pose, Pose2D):
        if type(pose.x) is type(pose.y) is type(pose.theta) is float:
            return pose
        pose = (pose.x, pose.y, pose.theta)
    try:
        x, y, theta = (real_number(v) for v in pose)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int past float's range
        raise ScanError(
            f"pose must be a Pose2D or an (x, y, theta) sequence of numbers, got {pose!r}"
        ) from None
    return Pose2D(x, y, theta)
