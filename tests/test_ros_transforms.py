"""The TF buffer (fleetmap.ros.transforms) against transforms computed independently with scipy's
rotations and 4x4 matrices: chains in both directions, interpolation, static edges, extrapolation,
the 3D -> 2D projection of level, upside-down and tilted lasers, and the limits."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from fleetmap.ros.tf_message import TransformStamped
from fleetmap.ros.transforms import (
    TfBuffer,
    TfError,
    TfPending,
    Transform,
    normalize_frame,
    sensor_pose_2d,
)


def ts(
    stamp: float, parent: str, child: str, xyz: tuple[float, float, float], rot: Rotation
) -> TransformStamped:
    q = rot.as_quat()
    return TransformStamped(stamp, parent, child, xyz, (q[0], q[1], q[2], q[3]))


def matrix(xyz: tuple[float, float, float], rot: Rotation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot.as_matrix()
    m[:3, 3] = xyz
    return m


def as_matrix(t: Transform) -> np.ndarray:
    return matrix(t.translation, Rotation.from_quat(t.rotation))


YAW = Rotation.from_euler


def robot_tree() -> tuple[TfBuffer, dict[str, np.ndarray]]:
    """map -> odom (static), odom -> base_link (dynamic, two samples), base_link -> laser and
    base_link -> camera (static)."""
    buf = TfBuffer()
    parts = {
        "map_odom": ((1.0, -2.0, 0.0), YAW("z", 30, degrees=True)),
        "base_laser": ((0.2, 0.05, 0.3), YAW("z", -10, degrees=True)),
        "base_camera": ((0.1, 0.0, 0.5), Rotation.from_euler("xyz", [5, 10, 20], degrees=True)),
    }
    buf.add(ts(0.0, "map", "odom", *parts["map_odom"]), static=True)
    buf.add(ts(0.0, "base_link", "laser", *parts["base_laser"]), static=True)
    buf.add(ts(0.0, "/base_link", "camera", *parts["base_camera"]), static=True)  # tf2 drops the '/'
    buf.add(ts(100.0, "odom", "base_link", (0.0, 0.0, 0.0), YAW("z", 0, degrees=True)), static=False)
    buf.add(ts(101.0, "odom", "base_link", (2.0, 1.0, 0.0), YAW("z", 90, degrees=True)), static=False)
    mats = {k: matrix(*v) for k, v in parts.items()}
    return buf, mats


def odom_base_at(f: float) -> np.ndarray:
    rot = Slerp([0, 1], Rotation.from_euler("z", [[0.0], [90.0]], degrees=True))([f])[0]
    return matrix((2.0 * f, 1.0 * f, 0.0), rot)


def test_chain_up_and_down_with_interpolation() -> None:
    buf, m = robot_tree()
    want = m["map_odom"] @ odom_base_at(0.25) @ m["base_laser"]
    np.testing.assert_allclose(as_matrix(buf.lookup("map", "laser", 100.25)), want, atol=1e-12)
    # The other direction, and between two children of base_link (up to base_link, then down).
    np.testing.assert_allclose(as_matrix(buf.lookup("laser", "map", 100.25)), np.linalg.inv(want), atol=1e-12)
    np.testing.assert_allclose(
        as_matrix(buf.lookup("camera", "laser", 100.7)),
        np.linalg.inv(m["base_camera"]) @ m["base_laser"],
        atol=1e-12,
    )
    # At the samples themselves, exactly them.
    np.testing.assert_allclose(
        as_matrix(buf.lookup("odom", "base_link", 101.0)), odom_base_at(1.0), atol=1e-12
    )


def test_interpolation_is_linear_in_translation_and_slerp_in_rotation() -> None:
    buf, _ = robot_tree()
    t = buf.lookup("odom", "base_link", 100.5)
    assert t.translation == pytest.approx((1.0, 0.5, 0.0), abs=1e-12)
    assert sensor_pose_2d(t).theta == pytest.approx(math.radians(45), abs=1e-12)


def test_static_edges_hold_at_all_times() -> None:
    buf, m = robot_tree()
    for stamp in (-1e9, 0.0, 5e9):
        np.testing.assert_allclose(as_matrix(buf.lookup("map", "odom", stamp)), m["map_odom"], atol=1e-12)


def test_extrapolation_into_the_future_waits_and_into_the_past_is_refused() -> None:
    buf, _ = robot_tree()
    with pytest.raises(TfPending, match="yet"):
        buf.lookup("map", "laser", 101.001)
    with pytest.raises(TfError) as info:
        buf.lookup("map", "laser", 99.999)
    assert not isinstance(info.value, TfPending)
    with pytest.raises(TfPending, match="not in the TF tree"):
        buf.lookup("map", "lidar", 100.5)
    buf.add(ts(0.0, "world", "other", (0.0, 0.0, 0.0), Rotation.identity()), static=True)
    with pytest.raises(TfPending, match="not connected"):
        buf.lookup("map", "other", 100.5)
    # TF arriving later resolves what was pending.
    buf.add(ts(102.0, "odom", "base_link", (2.0, 1.0, 0.0), YAW("z", 90, degrees=True)), static=False)
    buf.lookup("map", "laser", 101.001)


def test_samples_arriving_out_of_order_are_sorted() -> None:
    buf = TfBuffer()
    for stamp in (3.0, 1.0, 2.0):
        buf.add(ts(stamp, "odom", "base", (stamp, 0.0, 0.0), Rotation.identity()), static=False)
    assert buf.lookup("odom", "base", 1.5).translation[0] == pytest.approx(1.5)
    assert buf.lookup("odom", "base", 2.5).translation[0] == pytest.approx(2.5)


def beam_end_in_map(t: Transform, bearing: float, r: float) -> tuple[float, float]:
    x, y, _ = t.apply((r * math.cos(bearing), r * math.sin(bearing), 0.0))
    return x, y


def test_level_laser_pose_2d() -> None:
    t = Transform((1.0, 2.0, 0.4), tuple(Rotation.from_euler("xyz", [1, -2, 70], degrees=True).as_quat()))  # type: ignore[arg-type]
    pose = sensor_pose_2d(t)
    assert not pose.mirrored
    assert (pose.x, pose.y) == (1.0, 2.0)
    assert pose.theta == pytest.approx(math.radians(70), abs=0.002)


def test_upside_down_laser_mirrors_its_beams() -> None:
    """A laser mounted upside down (rolled 180 degrees about its x axis): beam angle a in the laser
    points at heading theta - a in the map. Checked by transforming the beam's end point in 3D."""
    rot = Rotation.from_euler("z", 40, degrees=True) * Rotation.from_euler("x", 180, degrees=True)
    t = Transform((3.0, -1.0, 0.2), tuple(rot.as_quat()))  # type: ignore[arg-type]
    pose = sensor_pose_2d(t)
    assert pose.mirrored
    assert pose.theta == pytest.approx(math.radians(40), abs=1e-12)
    for a in (-2.0, -0.3, 0.0, 0.8, 1.9):
        x, y = beam_end_in_map(t, a, 5.0)
        bearing = pose.theta - a  # Scan.from_fan(pose, -angle_min, -angle_increment): angle -> -angle
        assert (x, y) == pytest.approx(
            (pose.x + 5 * math.cos(bearing), pose.y + 5 * math.sin(bearing)), abs=1e-9
        )


def test_tilted_laser_is_refused_and_the_tolerance_is_a_few_degrees() -> None:
    for degrees, ok in ((4.0, True), (6.0, False), (90.0, False), (176.0, True), (174.0, False)):
        t = Transform((0.0, 0.0, 0.0), tuple(Rotation.from_euler("y", degrees, degrees=True).as_quat()))  # type: ignore[arg-type]
        if ok:
            sensor_pose_2d(t)
        else:
            with pytest.raises(TfError, match="tilted"):
                sensor_pose_2d(t)


def test_bad_samples_are_refused() -> None:
    buf = TfBuffer()
    good = (0.0, 0.0, 0.0, 1.0)
    with pytest.raises(TfError, match="finite"):
        buf.add(TransformStamped(0.0, "a", "b", (math.nan, 0.0, 0.0), good), static=False)
    with pytest.raises(TfError, match="unit quaternion"):
        buf.add(TransformStamped(0.0, "a", "b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)), static=False)
    with pytest.raises(TfError, match="itself"):
        buf.add(TransformStamped(0.0, "a", "/a", (0.0, 0.0, 0.0), good), static=False)
    with pytest.raises(TfError, match="frame id"):
        buf.add(TransformStamped(0.0, "", "b", (0.0, 0.0, 0.0), good), static=False)
    assert buf.frames == 0 and buf.samples == 0


def test_a_quaternion_tf2_takes_is_taken_normalised_and_one_it_refuses_is_refused() -> None:
    """tf2 (`BufferCore::setTransform`) takes a rotation whose |q|^2 is within 0.01 of 1
    (`QUATERNION_NORMALIZATION_TOLERANCE`, 10e-3) and refuses the others: a static transform written
    by hand to two digits, `static_transform_publisher --qz 0.71 --qw 0.71` (|q|^2 = 1.0082), poses
    the robot's laser in tf2, and was refused here (a tolerance of 0.001), leaving every scan of the
    robot without TF. Taken, it is normalised: a quarter turn exactly."""
    buf = TfBuffer()
    buf.add(TransformStamped(0.0, "base_link", "laser", (1.0, 0.0, 0.0), (0.0, 0.0, 0.71, 0.71)), static=True)
    t = buf.lookup("base_link", "laser", 0.0)
    assert t.rotation == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)), abs=1e-12)
    assert sensor_pose_2d(t).theta == pytest.approx(math.pi / 2, abs=1e-12)
    for q in ((0.0, 0.0, 0.7, 0.7), (0.0, 0.0, 0.714, 0.714)):  # |q|^2 0.98 and 1.0196: tf2 refuses
        with pytest.raises(TfError, match="unit quaternion"):
            buf.add(TransformStamped(0.0, "base_link", "other", (0.0, 0.0, 0.0), q), static=True)


def test_a_loop_is_an_error_not_a_hang() -> None:
    buf = TfBuffer()
    buf.add(TransformStamped(0.0, "a", "b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), static=True)
    buf.add(TransformStamped(0.0, "b", "a", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), static=True)
    with pytest.raises(TfError, match="loop"):
        buf.lookup("a", "b", 0.0)


def test_memory_is_bounded() -> None:
    buf = TfBuffer(history=10.0, max_frames=8, max_samples_per_edge=50, max_samples=120)
    q = (0.0, 0.0, 0.0, 1.0)
    for i in range(1000):  # 100 Hz for 10 s: the cap per edge, not the history, bounds it
        buf.add(TransformStamped(i * 0.01, "odom", "base", (0.0, 0.0, 0.0), q), static=False)
    assert buf.samples == 50
    for i in range(100):  # 1 Hz: the history window bounds it
        buf.add(TransformStamped(1000.0 + i, "odom", "other", (0.0, 0.0, 0.0), q), static=False)
    assert buf.samples == 50 + 11
    with pytest.raises(TfError, match="frames"):
        for i in range(10):
            buf.add(TransformStamped(0.0, "odom", f"f{i}", (0.0, 0.0, 0.0), q), static=True)
    assert buf.frames == 8
    # At the tree's limit the fullest edge's oldest sample makes room: the tree stays bounded and
    # keeps up with time, rather than refusing every later sample for good.
    small = TfBuffer(max_samples=10)
    for i in range(15):
        small.add(TransformStamped(float(i), "odom", "base", (float(i), 0.0, 0.0), q), static=False)
    assert small.samples == 10
    assert small.lookup("odom", "base", 13.5).translation[0] == pytest.approx(13.5)
    for i in range(8):
        small.add(TransformStamped(float(i), "odom", "arm", (0.0, 0.0, 0.0), q), static=False)
    assert small.samples == 10  # the fullest edge gave its oldest each time ("base" keeps 11 ... 14)
    assert small.lookup("odom", "base", 14.0).translation[0] == pytest.approx(14.0)
    full = TfBuffer(max_samples=4)  # every edge down to the two samples it interpolates between
    for child in ("a", "b"):
        for i in range(2):
            full.add(TransformStamped(float(i), "odom", child, (0.0, 0.0, 0.0), q), static=False)
    with pytest.raises(TfError, match="samples"):
        full.add(TransformStamped(0.0, "odom", "c", (0.0, 0.0, 0.0), q), static=False)
    assert full.samples == 4


def test_a_full_tree_forgets_the_frames_of_robots_gone_quiet() -> None:
    """Robots that come and go under frame prefixes of their own on one shared tree: once it is
    full, the frames below edges with no sample within the history kept are forgotten to make room,
    and robots still publishing keep theirs. Every new frame was refused until a restart."""
    q = (0.0, 0.0, 0.0, 1.0)
    buf = TfBuffer(history=10.0, max_frames=10)

    def robot(name: str, stamp: float) -> None:  # map -> odom -> base_link (dynamic) -> laser (static)
        buf.add(TransformStamped(stamp, "map", f"{name}/odom", (1.0, 0.0, 0.0), q), static=False)
        buf.add(
            TransformStamped(stamp, f"{name}/odom", f"{name}/base_link", (0.0, 1.0, 0.0), q), static=False
        )
        buf.add(TransformStamped(0.0, f"{name}/base_link", f"{name}/laser", (0.5, 0.0, 0.0), q), static=True)

    for name in ("r1", "r2", "r3"):
        robot(name, 100.0)  # 10 frames: full
    robot("r3", 125.0)  # r3 keeps publishing; r1 and r2 went quiet 25 s ago
    robot("r4", 125.0)
    assert buf.frames == 7  # map, r3's and r4's
    assert buf.lookup("map", "r4/laser", 125.0).translation == pytest.approx((1.5, 1.0, 0.0))
    assert buf.lookup("map", "r3/laser", 125.0).translation == pytest.approx((1.5, 1.0, 0.0))
    with pytest.raises(TfPending, match="not in the TF tree"):
        buf.lookup("map", "r1/laser", 100.0)
    # Within the history nothing is forgotten: a full tree of robots publishing refuses new frames.
    for name in ("r5", "r6"):
        with pytest.raises(TfError, match="frames") if name == "r6" else contextlib.nullcontext():
            robot(name, 126.0)
    assert buf.lookup("map", "r3/laser", 125.0).translation == pytest.approx((1.5, 1.0, 0.0))


def test_normalize_frame() -> None:
    assert normalize_frame("/map") == "map" and normalize_frame("base_link") == "base_link"
    for bad in ("", "/", "a\x00b", "x" * 300):
        with pytest.raises(TfError):
            normalize_frame(bad)


def test_time_going_back_restarts_an_edge() -> None:
    """A dynamic sample more than the history older than its edge's newest (a simulation restarted
    under use_sim_time) restarts the edge: it is kept and looked up, not dropped as too old."""
    buf = TfBuffer(history=10.0)
    for stamp in (300.0, 300.1):
        buf.add(TransformStamped(stamp, "map", "base", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), static=False)
    for stamp in (2.0, 2.1):
        buf.add(TransformStamped(stamp, "map", "base", (5.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), static=False)
    assert buf.samples == 2
    assert buf.lookup("map", "base", 2.05).translation == pytest.approx((5.0, 0.0, 0.0))
    # Before the new time's TF came: a stamp more than the history before the newest waits (the TF
    # of its time may come), one before the oldest but within the history never will.
    again = TfBuffer(history=10.0)
    for stamp in (300.0, 300.1):
        again.add(TransformStamped(stamp, "map", "base", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), static=False)
    with pytest.raises(TfPending):
        again.lookup("map", "base", 2.0)
    with pytest.raises(TfError) as info:
        again.lookup("map", "base", 299.0)
    assert not isinstance(info.value, TfPending)
    with pytest.raises(TfPending):
        buf.lookup("map", "base", 300.05)  # the old time's samples are gone
