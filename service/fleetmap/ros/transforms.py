"""A robot's TF tree and lookups in it, as tf2 does them: `TfBuffer`, `Transform`, `sensor_pose_2d`.

Pure Python, no Zenoh, no ROS. Each frame has at most one parent (the tree's edges point from
parent to child, as TF messages say them); a lookup walks from both frames up to their common
ancestor and composes the edges on the way, in either direction. A static edge (from `/tf_static`)
holds at all times; a dynamic one (from `/tf`) is interpolated between its two samples around the
stamp: linearly in translation, by slerp in rotation. A stamp past a dynamic edge's newest sample
is `TfPending` (its TF may still come: the caller waits, as tf2's MessageFilter does), and so is one
more than the history window before it (time may have gone back, and that time's TF restart the
edge); one before its oldest kept sample but within the window is a `TfError` (it never will).

Bounded against hostile input: frames per tree, samples per edge, samples per tree, and a history
window per edge (older samples dropped as newer ones arrive; a sample older than the window means
time went back, and the edge starts again from it; at the samples-per-tree limit the fullest
dynamic edge gives up its oldest). What does not fit is refused with a `TfError` whose message says
which limit.
"""

from __future__ import annotations

import bisect
import math
from array import array
from dataclasses import dataclass

from fleetmap.ros.tf_message import TransformStamped

#: Seconds of samples kept per dynamic edge, counted back from its newest one.
HISTORY_SECONDS = 10.0
MAX_FRAMES = 256
MAX_SAMPLES_PER_EDGE = 2000
MAX_SAMPLES = 20_000
MAX_FRAME_ID = 256
#: How far from unit length a quaternion may be (|q|^2) and be taken, normalised: tf2's own bound
#: (`QUATERNION_NORMALIZATION_TOLERANCE`, 10e-3, in `BufferCore::setTransform`), past which tf2 too
#: refuses it. A tighter one refused transforms written by hand to two digits (`--qz 0.71 --qw 0.71`,
#: |q|^2 = 1.0082), which tf2 takes: every scan of such a robot went without TF.
QUATERNION_TOLERANCE = 10e-3
#: A laser counts as level (or upside down) when its z axis is within this of the map's +z (or -z).
LEVEL_TOLERANCE_DEG = 5.0

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # x, y, z, w


class TfError(Exception):
    """No transform can be given, and none will be for this stamp; the message says why."""


class TfPending(TfError):
    """No transform yet: a frame is unknown or unconnected, or the stamp is newer than an edge's
    newest sample. More TF may resolve it."""


def _qmul(a: Quat, b: Quat) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def _rotate(q: Quat, v: Vec3) -> Vec3:
    # v' = v + 2w (u x v) + 2 u x (u x v), u = (x, y, z)
    x, y, z, w = q
    vx, vy, vz = v
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    ccx, ccy, ccz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return (vx + 2 * (w * cx + ccx), vy + 2 * (w * cy + ccy), vz + 2 * (w * cz + ccz))


@dataclass(frozen=True)
class Transform:
    """A rigid transform: `apply(p) = rotation * p + translation`. As a lookup's result, the pose
    of the source frame in the target frame."""

    translation: Vec3
    rotation: Quat

    @staticmethod
    def identity() -> Transform:
        return Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def __mul__(self, other: Transform) -> Transform:
        t = _rotate(self.rotation, other.translation)
        return Transform(
            (self.translation[0] + t[0], self.translation[1] + t[1], self.translation[2] + t[2]),
            _qmul(self.rotation, other.rotation),
        )

    def inverse(self) -> Transform:
        x, y, z, w = self.rotation
        q = (-x, -y, -z, w)
        t = _rotate(q, self.translation)
        return Transform((-t[0], -t[1], -t[2]), q)

    def apply(self, p: Vec3) -> Vec3:
        r = _rotate(self.rotation, p)
        return (r[0] + self.translation[0], r[1] + self.translation[1], r[2] + self.translation[2])

    def axis(self, i: int) -> Vec3:
        """Column i of the rotation matrix: the frame's x (0), y (1) or z (2) axis in the parent."""
        unit = [0.0, 0.0, 0.0]
        unit[i] = 1.0
        return _rotate(self.rotation, (unit[0], unit[1], unit[2]))


def _slerp(a: Quat, b: Quat, f: float) -> Quat:
    dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
    if dot < 0.0:  # the shorter way round
        b = (-b[0], -b[1], -b[2], -b[3])
        dot = -dot
    if dot > 0.9995:  # nearly equal: linear, then normalised (slerp's formula divides by ~0)
        q = tuple(a[i] + f * (b[i] - a[i]) for i in range(4))
    else:
        theta = math.acos(min(dot, 1.0))
        s = math.sin(theta)
        wa, wb = math.sin((1 - f) * theta) / s, math.sin(f * theta) / s
        q = tuple(wa * a[i] + wb * b[i] for i in range(4))
    n = math.sqrt(sum(c * c for c in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def normalize_frame(frame_id: str) -> str:
    """tf2's frame id: without a leading `/`. Raises TfError for an empty, overlong or odd id."""
    frame = frame_id[1:] if frame_id.startswith("/") else frame_id
    if not frame or len(frame) > MAX_FRAME_ID or any(ord(c) < 32 for c in frame):
        raise TfError(f"invalid frame id {frame_id[:80]!r}")
    return frame


class _Edge:
    """The samples of one parent -> child edge: stamps ascending, 7 floats per sample (t, q)."""

    __slots__ = ("parent", "static", "stamps", "values")

    def __init__(self, parent: str, static: bool) -> None:
        self.parent = parent
        self.static = static
        self.stamps: array[float] = array("d")
        self.values: array[float] = array("d")

    def sample(self, i: int) -> Transform:
        v = self.values[7 * i : 7 * i + 7]
        return Transform((v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def at(self, stamp: float, child: str, history: float) -> Transform:
        """The edge's transform at `stamp`: TfPending past its newest sample, and more than `history`
        before it (time went back: a restarted simulation's TF, which restarts the edge, may still
        come); TfError between those and its oldest sample (never to be covered)."""
        if self.static:
            return self.sample(0)
        stamps = self.stamps
        if stamp > stamps[-1]:
            raise TfPending(f"no TF {self.parent} -> {child} at {stamp:.6f} yet (newest {stamps[-1]:.6f})")
        if stamp < stamps[-1] - history:
            raise TfPending(
                f"no TF {self.parent} -> {child} at {stamp:.6f}, more than {history:g} s before its newest "
                f"({stamps[-1]:.6f}): waiting in case time went back"
            )
        if stamp < stamps[0]:
            raise TfError(
                f"stamp {stamp:.6f} is older than the TF {self.parent} -> {child} kept (from {stamps[0]:.6f})"
            )
        i = bisect.bisect_left(stamps, stamp)
        if stamps[i] == stamp:
            return self.sample(i)
        t0, t1 = stamps[i - 1], stamps[i]
        a, b = self.sample(i - 1), self.sample(i)
        f = (stamp - t0) / (t1 - t0)
        ta, tb = a.translation, b.translation
        return Transform(
            (ta[0] + f * (tb[0] - ta[0]), ta[1] + f * (tb[1] - ta[1]), ta[2] + f * (tb[2] - ta[2])),
            _slerp(a.rotation, b.rotation, f),
        )


class TfBuffer:
    """One TF tree (a robot's, or a namespace's): `add` samples, `lookup` transforms. Not
    thread-safe: the caller holds a lock around both."""

    def __init__(
        self,
        history: float = HISTORY_SECONDS,
        max_frames: int = MAX_FRAMES,
        max_samples_per_edge: int = MAX_SAMPLES_PER_EDGE,
        max_samples: int = MAX_SAMPLES,
    ) -> None:
        self.history = history
        self.max_frames = max_frames
        self.max_samples_per_edge = max_samples_per_edge
        self.max_samples = max_samples
        self._edges: dict[str, _Edge] = {}  # by child frame
        self._frames: set[str] = set()
        self._samples = 0

    @property
    def frames(self) -> int:
        return len(self._frames)

    @property
    def samples(self) -> int:
        return self._samples

    def add(self, t: TransformStamped, static: bool) -> None:
        """Add one sample of the edge `t.parent -> t.child` (static: valid at all times, replacing
        the edge's samples). A child given a new parent is re-parented, as tf2 does. A dynamic sample
        older than the history kept before the edge's newest restarts the edge (time went back, see
        the comment in the code). Raises TfError
        for a bad sample (non-finite, not a rotation, bad frame ids) or one past a limit."""
        parent, child = normalize_frame(t.parent), normalize_frame(t.child)
        if parent == child:
            raise TfError(f"TF from frame {parent!r} to itself")
        values = (*t.translation, *t.rotation)
        if not all(math.isfinite(v) for v in (*values, t.stamp)):
            raise TfError(f"TF {parent} -> {child} is not finite")
        qx, qy, qz, qw = t.rotation
        n2 = qx * qx + qy * qy + qz * qz + qw * qw
        if not abs(n2 - 1.0) < QUATERNION_TOLERANCE:  # as tf2: taken strictly within the bound
            raise TfError(f"TF {parent} -> {child} rotation is not a unit quaternion (|q|^2 = {n2:.6g})")
        n = math.sqrt(n2)
        values = (*t.translation, qx / n, qy / n, qz / n, qw / n)
        new = {parent, child} - self._frames
        if len(self._frames) + len(new) > self.max_frames:
            self._forget_stale(now=t.stamp)
            new = {parent, child} - self._frames
            if len(self._frames) + len(new) > self.max_frames:
                raise TfError(f"TF tree already has {len(self._frames)} frames, the most it may have")
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent or edge.static != static:
            if edge is None and self._samples >= self.max_samples:
                self._make_room()
            if edge is not None:
                self._samples -= len(edge.stamps)
            edge = self._edges[child] = _Edge(parent, static)
        self._frames |= new
        if static:
            self._samples -= len(edge.stamps)
            edge.stamps = array("d", [t.stamp])
            edge.values = array("d", values)
            self._samples += 1
            return
        stamps = edge.stamps
        if stamps and t.stamp < stamps[-1] - self.history:
            # Time went back by more than the history kept: a simulation or a bag replay restarted
            # (use_sim_time), a robot's clock stepped back. The edge's samples belong to a time that
            # will not be asked for again, and kept they would make every new sample look too old
            # to keep, leaving the robot without TF for good. tf2 clears its buffer on a jump back
            # in time; this edge starts again from this sample.
            self._samples -= len(stamps)
            edge.stamps = stamps = array("d")
            edge.values = array("d")
        i = bisect.bisect_left(stamps, t.stamp)
        if i < len(stamps) and stamps[i] == t.stamp:
            edge.values[7 * i : 7 * i + 7] = array("d", values)  # the same stamp again: the newer wins
            return
        if self._samples >= self.max_samples:
            self._make_room()
            i = bisect.bisect_left(stamps, t.stamp)  # the room may have been made on this edge
        stamps.insert(i, t.stamp)
        edge.values[7 * i : 7 * i] = array("d", values)
        self._samples += 1
        # Drop what fell out of the history window, and the oldest past the per-edge cap.
        drop = bisect.bisect_left(stamps, stamps[-1] - self.history)
        drop = max(drop, len(stamps) - self.max_samples_per_edge)
        if drop > 0:
            del stamps[:drop]
            del edge.values[: 7 * drop]
            self._samples -= drop

    def _forget_stale(self, now: float) -> None:
        """At the tree's frame limit: forget each dynamic edge with no sample within the history
        kept (before `now`, or the tree's newest sample if later), and every frame below it. Those
        frames can serve no lookup until their edge gets samples again (a lookup needs a sample
        within the history), and robots that came and went under frame prefixes of their own on
        one shared tree (`robot7/odom`, ...) would otherwise fill it for good: every new frame,
        every new robot's, was refused until the service restarted. A static edge below a
        forgotten one goes too: its robot, back, publishes it again when it restarts (tf_static
        is latched); one that only lost its link for longer than the history needs it again."""
        newest = max(
            (edge.stamps[-1] for edge in self._edges.values() if not edge.static and edge.stamps),
            default=now,
        )
        horizon = max(now, newest) - self.history
        stale = [
            child
            for child, edge in self._edges.items()
            if not edge.static and (not edge.stamps or edge.stamps[-1] < horizon)
        ]
        if not stale:
            return
        below: dict[str, list[str]] = {}
        for child, edge in self._edges.items():
            below.setdefault(edge.parent, []).append(child)
        gone: set[str] = set()
        todo = list(stale)
        while todo:
            frame = todo.pop()
            if frame not in gone:
                gone.add(frame)
                todo.extend(below.get(frame, ()))
        for frame in gone:  # each the child of an edge: a stale one, or one below it
            self._samples -= len(self._edges.pop(frame).stamps)
        self._frames = set(self._edges) | {edge.parent for edge in self._edges.values()}

    def _make_room(self) -> None:
        """At the tree's sample limit: drop the oldest sample of the dynamic edge holding the most.
        Many fast edges (a robot's moving joints at the joint_states rate, a fleet's frames in one
        tree) can fill the tree before their history window; refusing new samples then would freeze
        every edge for good (an edge drops its old samples only as it takes new ones), so the
        fullest edges' histories get shorter instead. Each edge keeps two samples to interpolate
        between; raises TfError when no edge has more."""
        fullest = max(
            (edge for edge in self._edges.values() if not edge.static),
            key=lambda e: len(e.stamps),
            default=None,
        )
        if fullest is None or len(fullest.stamps) <= 2:
            raise TfError(f"TF tree already holds {self._samples} samples, the most it may hold")
        del fullest.stamps[0]
        del fullest.values[:7]
        self._samples -= 1

    def _chain(self, frame: str) -> list[str]:
        """`frame` and its ancestors up to its root."""
        chain = [frame]
        seen = {frame}
        edge = self._edges.get(frame)
        while edge is not None:
            if edge.parent in seen:
                raise TfError(f"TF has a loop through frame {edge.parent!r}")
            chain.append(edge.parent)
            seen.add(edge.parent)
            edge = self._edges.get(edge.parent)
        return chain

    def lookup(self, target: str, source: str, stamp: float) -> Transform:
        """The pose of frame `source` in frame `target` at `stamp` (seconds). Raises TfPending when
        more TF could answer it (unknown or unconnected frames, a stamp past the newest sample of a
        dynamic edge on the way), TfError when none will. A frame in itself is the identity at any
        stamp, in the tree or not, and a `stamp` of 0 means the latest time every dynamic edge on the
        way has a sample for (as tf2's `lookupTransform` and its `TimePointZero`)."""
        target, source = normalize_frame(target), normalize_frame(source)
        if target == source:
            return Transform.identity()
        for frame in (target, source):
            if frame not in self._frames:
                raise TfPending(f"frame {frame!r} is not in the TF tree")
        up_source = self._chain(source)
        up_target = self._chain(target)
        common = set(up_target)
        ancestor = next((f for f in up_source if f in common), None)
        if ancestor is None:
            raise TfPending(f"frames {target!r} and {source!r} are not connected in the TF tree")
        if stamp == 0.0:
            stamp = self._latest_common_time(up_target, up_source, ancestor)
        return self._to_ancestor(up_target, ancestor, stamp).inverse() * self._to_ancestor(
            up_source, ancestor, stamp
        )

    def _latest_common_time(self, up_target: list[str], up_source: list[str], ancestor: str) -> float:
        """tf2's latest common time of a lookup: the oldest of the newest samples of the dynamic edges
        between both frames and their common `ancestor` (0 when all are static: any stamp does)."""
        newest = [
            edge.stamps[-1]
            for chain in (up_target, up_source)
            for frame in chain[: chain.index(ancestor)]
            if not (edge := self._edges[frame]).static
        ]
        return min(newest, default=0.0)

    def _to_ancestor(self, chain: list[str], ancestor: str, stamp: float) -> Transform:
        """The pose of chain[0] in `ancestor`, composed edge by edge up the chain."""
        result = Transform.identity()
        for frame in chain:
            if frame == ancestor:
                return result
            result = self._edges[frame].at(stamp, frame, self.history) * result
        return result


@dataclass(frozen=True)
class Pose2DResult:
    """A sensor's 2D pose in the fixed frame; `mirrored`: the laser is upside down, so its beam
    angles turn the other way (angle -> -angle)."""

    x: float
    y: float
    theta: float
    mirrored: bool


def sensor_pose_2d(t: Transform, tolerance_deg: float = LEVEL_TOLERANCE_DEG) -> Pose2DResult:
    """Project the 3D pose of a laser in the fixed frame onto the map's plane. The laser's z axis
    must be within `tolerance_deg` of the map's +z (level) or -z (upside down: mirrored); theta is
    the heading of its x axis. A tilted laser raises TfError: its beams do not lie in the plane."""
    x_axis, z_axis = t.axis(0), t.axis(2)
    cos_tol = math.cos(math.radians(tolerance_deg))
    if z_axis[2] >= cos_tol:
        mirrored = False
    elif z_axis[2] <= -cos_tol:
        mirrored = True
    else:
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, z_axis[2]))))
        raise TfError(
            f"the laser is tilted {tilt:.1f} degrees from the map's vertical (at most {tolerance_deg:g} "
            "from level or upside down is integrated)"
        )
    theta = math.atan2(x_axis[1], x_axis[0])
    return Pose2DResult(t.translation[0], t.translation[1], theta, mirrored)


__all__ = [
    "HISTORY_SECONDS",
    "LEVEL_TOLERANCE_DEG",
    "Pose2DResult",
    "TfBuffer",
    "TfError",
    "TfPending",
    "Transform",
    "normalize_frame",
    "sensor_pose_2d",
]
