"""Tests of `fleetmap.datasets`: the CARMEN and .mat readers, on synthetic files and the real logs.

The real logs live beside the repository in `../shared/datasets/` (never copied into it); the tests
that need them are skipped, with the path in the reason, when that directory is absent.
"""

from __future__ import annotations

import codecs
import gzip
import math
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fleetmap.datasets import (
    DEFAULT_RANGE_MIN,
    UNBOUNDED_RANGE_MAX,
    Dataset,
    DatasetError,
    load_dataset,
)
from fleetmap.datasets.carmen import DEFAULT_FLASER_RANGE_MAX, flaser_angles
from fleetmap.scan import Scan

SHARED_DATASETS = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"

# ---------------------------------------------------------------------------------------------------
# Helpers writing synthetic CARMEN lines


def flaser(ranges: list[float], x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> str:
    """A well-formed FLASER line (odometry = corrected pose, as in the real logs)."""
    r = " ".join(f"{v:g}" for v in ranges)
    pose = f"{x!r} {y!r} {theta!r}"
    return f"FLASER {len(ranges)} {r} {pose} {pose} 12.5 testhost 12.6"


def robotlaser1(
    ranges: list[float],
    laser_pose: tuple[float, float, float],
    robot_pose: tuple[float, float, float] = (100.0, 200.0, 3.0),
    start: float = -1.5,
    res: float = 0.25,
    max_range: float = 30.0,
    remissions: tuple[float, ...] = (),
) -> str:
    fov = res * len(ranges)
    head = f"ROBOTLASER1 0 {start!r} {fov!r} {res!r} {max_range!r} 0.01 0 {len(ranges)}"
    r = " ".join(f"{v:g}" for v in ranges)
    rem = " ".join([str(len(remissions)), *(f"{v:g}" for v in remissions)])
    lp = " ".join(repr(v) for v in laser_pose)
    rp = " ".join(repr(v) for v in robot_pose)
    return f"{head} {r} {rem} {lp} {rp} 0.1 0.2 0.3 0.4 0.5 1000.5 testhost 1.5"


def write_log(path: Path, lines: list[str], *, compress: bool = False) -> Path:
    data = ("\n".join(lines) + "\n").encode()
    path.write_bytes(gzip.compress(data) if compress else data)
    return path


def real_log(name: str) -> Path:
    path = SHARED_DATASETS / name
    if not path.exists():
        pytest.skip(f"../shared/datasets not found: {path} does not exist")
    return path


# ---------------------------------------------------------------------------------------------------
# The real logs


REAL_LOGS = [
    # file, scans, beams, range_max, first beam angle, last beam angle
    ("intel-corrected.log.gz", 910, 180, 80.0, -math.pi / 2, math.pi / 2 - math.pi / 180),
    ("freiburg-campus-corrected.log.gz", 2008, 360, 80.99, -math.pi / 2, math.pi / 2 - math.pi / 360),
    ("csail-robotlaser.log.gz", 686, 361, 80.0, -1.570796, -1.570796 + 360 * 0.008727),
]


@pytest.fixture(scope="module")
def real_datasets() -> dict[str, Dataset]:
    """Each real log loaded once for the whole module (about 0.2 s in all)."""
    return {name: load_dataset(real_log(name)) for name, *_ in REAL_LOGS}


@pytest.mark.parametrize(("name", "scans", "beams", "range_max", "first", "last"), REAL_LOGS)
def test_real_log_counts_and_angles(
    real_datasets: dict[str, Dataset],
    name: str,
    scans: int,
    beams: int,
    range_max: float,
    first: float,
    last: float,
) -> None:
    ds = real_datasets[name]
    assert ds.format == "carmen"
    assert ds.name == name.removesuffix(".log.gz")
    assert len(ds) == scans
    assert ds.range_max == pytest.approx(range_max)
    assert ds.range_min == DEFAULT_RANGE_MIN
    seen = 0
    for scan in ds:
        seen += 1
        assert scan.num_beams == beams
        assert scan.range_max == pytest.approx(range_max)
    assert seen == scans  # len() agrees with what iteration yields
    scan = ds[0]
    assert scan.angles[0] == pytest.approx(first, abs=1e-9)
    assert scan.angles[-1] == pytest.approx(last, abs=1e-9)
    # Readings past the laser's maximum are in the logs and must come out as "no return".
    assert any(s.no_return_mask().any() for s in ds)


def test_real_log_poses(real_datasets: dict[str, Dataset]) -> None:
    """First poses as found in the files, with freiburg's -4 cm front-laser offset applied."""
    intel = real_datasets["intel-corrected.log.gz"].poses
    np.testing.assert_allclose(intel[0], [0.600266, -0.0320327, -0.354665])
    # freiburg: robot pose (0, 0, 0) and PARAM robot_frontlaser_offset -0.04.
    freiburg = real_datasets["freiburg-campus-corrected.log.gz"].poses
    np.testing.assert_allclose(freiburg[0], [-0.04, 0.0, 0.0], atol=1e-12)
    # Second freiburg line: robot (-0.0446373, 0.000922514, -0.130961), laser 4 cm behind it.
    th = -0.130961
    np.testing.assert_allclose(
        freiburg[1], [-0.0446373 - 0.04 * math.cos(th), 0.000922514 - 0.04 * math.sin(th), th]
    )
    csail = real_datasets["csail-robotlaser.log.gz"].poses
    np.testing.assert_allclose(csail[1], [0.319678, 0.110037, 0.994330])
    for poses in (intel, freiburg, csail):
        assert np.all(np.isfinite(poses))
        # A continuous trajectory: no jump of more than 2 m between consecutive scans.
        assert np.max(np.hypot(*np.diff(poses[:, :2], axis=0).T)) < 2.0


# ---------------------------------------------------------------------------------------------------
# CARMEN: synthetic logs


@pytest.mark.parametrize(
    ("n", "step"),
    [(180, math.pi / 180), (360, math.pi / 360), (181, math.pi / 180), (361, math.pi / 360), (5, math.pi / 4),
     (4, math.pi / 4)],
)  # fmt: skip
def test_flaser_angle_rule(n: int, step: float) -> None:
    a = flaser_angles(n)
    assert a.shape == (n,)
    assert a[0] == pytest.approx(-math.pi / 2)
    np.testing.assert_allclose(np.diff(a), step)
    # Odd counts include both ends of the half circle, even counts stop one step short of +90 deg.
    assert a[-1] == pytest.approx(math.pi / 2 if n % 2 else math.pi / 2 - step)


def test_flaser_synthetic_values(tmp_path: Path) -> None:
    path = write_log(
        tmp_path / "one.log",
        ["# a comment", "ODOM 0 0 0 0 0 0 1 h 1", "NEFF 1 2 3", flaser([1.0, 2.0, 0.0, 95.0], 1.0, 2.0, 0.5)],
    )
    ds = load_dataset(path)
    assert len(ds) == 1 and ds.name == "one"
    scan = next(iter(ds))
    assert isinstance(scan, Scan)
    assert (scan.pose.x, scan.pose.y, scan.pose.theta) == (1.0, 2.0, 0.5)
    np.testing.assert_array_equal(scan.ranges, [1.0, 2.0, 0.0, 95.0])
    np.testing.assert_allclose(scan.angles, -math.pi / 2 + np.arange(4) * math.pi / 4)
    assert scan.range_max == DEFAULT_FLASER_RANGE_MAX
    # The zero reading is ignored (below range_min), 95 m is "no return".
    np.testing.assert_array_equal(scan.returns_mask(), [True, True, False, False])
    np.testing.assert_array_equal(scan.no_return_mask(), [False, False, False, True])


def test_front_laser_offset_in_force_at_each_line(tmp_path: Path) -> None:
    lines = [
        flaser([1.0, 1.0], 1.0, 2.0, math.pi / 2),  # before any PARAM: offset 0
        "PARAM robot_frontlaser_offset 0.5 1.0 host 1.0",
        flaser([1.0, 1.0], 1.0, 2.0, math.pi / 2),  # 0.5 m ahead along +y
        flaser([1.0, 1.0], 0.0, 0.0, math.pi),  # 0.5 m ahead along -x
        "PARAM robot_frontlaser_offset -0.25 2.0 host 2.0",
        flaser([1.0, 1.0], 0.0, 0.0, 0.0),
    ]
    poses = load_dataset(write_log(tmp_path / "off.log", lines)).poses
    expected = [[1.0, 2.0, math.pi / 2], [1.0, 2.5, math.pi / 2], [-0.5, 0.0, math.pi], [-0.25, 0.0, 0.0]]
    np.testing.assert_allclose(poses, expected, atol=1e-12)


@pytest.mark.parametrize("compress", [False, True])
def test_a_byte_order_mark_does_not_hide_the_first_line(tmp_path: Path, compress: bool) -> None:
    """A log saved with a UTF-8 byte order mark (as Notepad saves) reads as without one: its first
    line's tag was read as '\\ufeffPARAM', an unknown message skipped silently, so the laser offset
    it set was lost and every scan lay 0.5 m off (a first FLASER line was lost the same way)."""
    lines = ["PARAM robot_frontlaser_offset 0.5 1.0 host 1.0", flaser([1.0, 1.0], 1.0, 2.0, 0.0)]
    plain = load_dataset(write_log(tmp_path / "plain.log", lines))
    path = write_log(tmp_path / "bom.log", lines)
    data = b"\xef\xbb\xbf" + path.read_bytes()
    path.write_bytes(gzip.compress(data) if compress else data)
    np.testing.assert_array_equal(load_dataset(path).poses, plain.poses)
    np.testing.assert_allclose(plain.poses, [[1.5, 2.0, 0.0]])
    path.write_bytes(b"\xef\xbb\xbf" + write_log(tmp_path / "scan.log", lines[1:]).read_bytes())
    assert len(load_dataset(path)) == 1


@pytest.mark.parametrize("compress", [False, True])
def test_a_comment_in_another_encoding_does_not_refuse_the_log(tmp_path: Path, compress: bool) -> None:
    """A comment is free text, skipped unread, whatever encoding its writer used: a log whose
    header comment says 'Universität' in Latin-1 (or Windows-1252) was refused whole, 'not UTF-8
    text: not a CARMEN log', though every message in it is. A message line that is not UTF-8 is
    still refused, naming its line."""
    lines = [flaser([1.0, 2.0], 1.0, 2.0, 0.0), flaser([3.0, 4.0], -1.0, 0.5, 1.0)]
    expected = load_dataset(write_log(tmp_path / "utf8.log", lines))
    comment = "# Universität Freiburg, Jürgen's robot".encode("latin-1")
    for first in (True, False):
        data = b"\n".join([comment, lines[0].encode(), comment, lines[1].encode()] if first else
                          [lines[0].encode(), b"  " + comment, lines[1].encode()]) + b"\n"  # fmt: skip
        path = tmp_path / "latin1.log"
        path.write_bytes(gzip.compress(data) if compress else data)
        np.testing.assert_array_equal(load_dataset(path).poses, expected.poses)
    path.write_bytes(b"\n".join([lines[0].encode(), b"FLASER 1 1.0 0 0 0 0 0 0 1.0 J\xfcrgen 1.0"]) + b"\n")
    with pytest.raises(DatasetError, match=r"latin1\.log:2: not UTF-8 text"):
        load_dataset(path)


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("ending", ["\r", "\r\n", "mixed"])
def test_lines_may_end_in_cr_lf_or_a_lone_cr(tmp_path: Path, ending: str, compress: bool) -> None:
    """A log with Windows (CR LF) or classic Mac (CR alone) line endings, or both, reads as with LF:
    with CR alone the whole log was one line and was refused as 'not a CARMEN laser log'. A
    malformed line is still named by its number, counted at every line end."""
    lines = [
        "# a comment",
        "PARAM robot_frontlaser_offset 0.5 1.0 host 1.0",
        flaser([1.0, 2.0], 1.0, 2.0, 0.0),
        robotlaser1([4.0, 5.0], (1.0, 1.0, 1.0)),
        flaser([3.0, 4.0], -1.0, 0.5, 1.0),
    ]
    expected = load_dataset(write_log(tmp_path / "lf.log", lines))
    assert len(expected) == 3

    def write(name: str, lines: list[str]) -> Path:
        ends = ["\r", "\r\n", "\n", "\r"] * len(lines) if ending == "mixed" else [ending] * len(lines)
        data = "".join(line + end for line, end in zip(lines, ends, strict=False)).encode()
        path = tmp_path / name
        path.write_bytes(gzip.compress(data) if compress else data)
        return path

    ds = load_dataset(write("odd.log", lines))
    assert len(ds) == len(expected)
    np.testing.assert_array_equal(ds.poses, expected.poses)
    for got, want in zip(ds, expected, strict=True):
        np.testing.assert_array_equal(got.ranges, want.ranges)
        np.testing.assert_array_equal(got.angles, want.angles)
    with pytest.raises(DatasetError, match=r"bad\.log:4: FLASER range 0"):
        load_dataset(write("bad.log", [*lines[:3], "FLASER 1 x 0 0 0 0 0 0 0 h 0", lines[4]]))


BYTE_ORDER_MARKS = {
    "utf-16-le": codecs.BOM_UTF16_LE,
    "utf-16-be": codecs.BOM_UTF16_BE,
    "utf-32-le": codecs.BOM_UTF32_LE,
    "utf-32-be": codecs.BOM_UTF32_BE,
}


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("encoding", list(BYTE_ORDER_MARKS))
def test_a_utf16_or_utf32_log_reads_as_its_utf8_text(tmp_path: Path, encoding: str, compress: bool) -> None:
    """A log saved as UTF-16 with its byte order mark (Windows PowerShell 5's `>` writes so, CR LF
    line ends included) reads as the same text in UTF-8: it was refused as 'not UTF-8 text: not a
    CARMEN log'. So does one saved as UTF-32 with its mark (`Out-File -Encoding utf32`), which,
    its little-endian mark starting as UTF-16's does, was read as UTF-16 and refused as 'no FLASER
    or ROBOTLASER1 message: not a CARMEN laser log'. Its malformed lines are named by their
    numbers, and text that does not decode is one clear error."""
    lines = ["PARAM robot_frontlaser_offset 0.5 1.0 host 1.0", flaser([1.0, 2.0], 1.0, 2.0, 0.0)]
    lines.append(robotlaser1([4.0, 5.0], (1.0, 1.0, 1.0)))
    expected = load_dataset(write_log(tmp_path / "utf8.log", lines))

    def write(name: str, text: str) -> Path:
        data = BYTE_ORDER_MARKS[encoding] + text.encode(encoding)
        path = tmp_path / name
        path.write_bytes(gzip.compress(data) if compress else data)
        return path

    ds = load_dataset(write("utf16.log", "\r\n".join(lines) + "\r\n"))
    assert len(ds) == len(expected) == 2
    np.testing.assert_array_equal(ds.poses, expected.poses)
    for got, want in zip(ds, expected, strict=True):
        np.testing.assert_array_equal(got.ranges, want.ranges)
        np.testing.assert_array_equal(got.angles, want.angles)
    with pytest.raises(DatasetError, match=r"bad\.log:3: FLASER range 0"):
        load_dataset(write("bad.log", "\n".join([*lines[:2], "FLASER 1 x 0 0 0 0 0 0 0 h 0"])))
    broken = write("broken.log", "\n".join(lines))
    data = gzip.decompress(broken.read_bytes()) if compress else broken.read_bytes()
    broken.write_bytes(data[:-1])  # half a character at its end
    with pytest.raises(DatasetError, match=f"not UTF-{encoding[4:6]} text"):
        load_dataset(broken)


def test_front_laser_max_param_in_force(tmp_path: Path) -> None:
    lines = [
        flaser([1.0, 50.0]),
        "PARAM robot_front_laser_max 40.0 1.0 host 1.0",
        flaser([1.0, 50.0]),
    ]
    ds = load_dataset(write_log(tmp_path / "max.log", lines))
    first, second = ds
    assert first.range_max == DEFAULT_FLASER_RANGE_MAX and not first.no_return_mask()[1]
    assert second.range_max == 40.0 and second.no_return_mask()[1]
    assert ds.range_max == DEFAULT_FLASER_RANGE_MAX  # the largest of the two


def test_a_range_min_past_the_logs_range_max_names_where_that_came_from(tmp_path: Path) -> None:
    """`fleetmap build intel.log.gz --range-min 90` is refused (no reading could be a return), and
    the error says where the range_max it compares with comes from. The Intel log has no PARAM
    robot_front_laser_max, yet the error said 'PARAM robot_front_laser_max = 80.0 is not a usable
    range_max', a line the user could not find in the log, and told them to 'pass range_max=', a
    Python keyword, not the command's --range-max."""
    lines = [flaser([1.0, 50.0]), "PARAM robot_front_laser_max 40.0 1.0 host 1.0", flaser([1.0, 50.0])]
    path = write_log(tmp_path / "max.log", lines)
    with pytest.raises(DatasetError) as default:
        load_dataset(path, range_min=90.0)
    message = str(default.value)
    assert f"{path}:1: FLASER's default range_max (no PARAM robot_front_laser_max" in message
    assert "= 80.0" in message and "--range-max" in message and "range_max=" not in message
    with pytest.raises(DatasetError, match=r"max.log:3: PARAM robot_front_laser_max = 40.0 is not"):
        load_dataset(path, range_min=50.0)


def test_robotlaser1_uses_laser_pose_and_own_angles(tmp_path: Path) -> None:
    lines = [
        "ROBOTLASER2 this rear laser message and unknown types are skipped",
        "SOMETHING_NEW 1 2 3",
        robotlaser1([1.0, 2.0, 31.0], (4.0, 5.0, 0.25), remissions=(0.5, 0.7, 0.9)),
    ]
    ds = load_dataset(write_log(tmp_path / "rl.log", lines))
    assert len(ds) == 1
    scan = ds[0]
    assert (scan.pose.x, scan.pose.y, scan.pose.theta) == (4.0, 5.0, 0.25)  # not the robot pose
    np.testing.assert_allclose(scan.angles, [-1.5, -1.25, -1.0])
    assert scan.range_max == 30.0
    np.testing.assert_array_equal(scan.no_return_mask(), [False, False, True])


def test_gzip_and_plain_text_give_the_same_scans(tmp_path: Path) -> None:
    lines = ["PARAM robot_frontlaser_offset 0.1 0 h 0", flaser([1.0, 2.0, 3.0], 1.0, 2.0, 0.3)]
    lines.append(robotlaser1([4.0, 5.0], (1.0, 1.0, 1.0)))
    plain = load_dataset(write_log(tmp_path / "a.log", lines))
    gz = load_dataset(write_log(tmp_path / "a.log.gz", lines, compress=True))
    # gzip is recognised by its magic bytes, not by the name.
    disguised = load_dataset(write_log(tmp_path / "b.log", lines, compress=True))
    assert plain.name == gz.name == "a"
    for ds in (gz, disguised):
        assert len(ds) == len(plain) == 2
        for s, t in zip(plain, ds, strict=True):
            assert s.pose == t.pose
            np.testing.assert_array_equal(s.ranges, t.ranges)
            np.testing.assert_array_equal(s.angles, t.angles)


@contextmanager
def piped(data: bytes) -> Iterator[Path]:
    """A path that reads `data` from a pipe, as `fleetmap build <(zcat log.gz)` or /dev/stdin does:
    it can be read once only, and not seeked."""
    read_end, write_end = os.pipe()

    def feed() -> None:
        with open(write_end, "wb") as pipe:
            pipe.write(data)

    writer = threading.Thread(target=feed)
    writer.start()
    try:
        yield Path(f"/dev/fd/{read_end}")
    finally:
        writer.join()
        os.close(read_end)


def test_a_log_read_from_a_pipe_loses_nothing(tmp_path: Path) -> None:
    """A log given as a pipe reads as the file does. The readers opened it twice (once for its
    first bytes, to tell the format, then to read it), and a pipe's second opening had lost what the
    first read: a small log was 'no FLASER or ROBOTLASER1 message in 0 lines', a big one lost its
    first scan without a word (909 scans of the Intel log's 910), a gzipped one was 'not UTF-8'."""
    lines = [flaser([1.0 + k, 2.0], float(k), 0.0, 0.0) for k in range(300)]  # 90 KB: past any buffer
    plain = write_log(tmp_path / "a.log", lines)
    expected = load_dataset(plain).poses
    mat = write_mat(tmp_path / "a.mat", np.ones((2, 3)), np.array([[0.0], [0.5]]), np.zeros((3, 3)))
    for data, scans in (
        (plain.read_bytes(), expected),
        (gzip.compress(plain.read_bytes()), expected),
        (mat.read_bytes(), load_dataset(mat).poses),
    ):
        with piped(data) as path:
            np.testing.assert_array_equal(load_dataset(path).poses, scans)


def test_negative_and_nan_readings_are_ignored(tmp_path: Path) -> None:
    scan = load_dataset(write_log(tmp_path / "neg.log", [flaser([-1.0, math.nan, 2.0, math.inf])]))[0]
    assert scan.ranges[0] == -1.0  # kept as read: below range_min, so ignored like NaN
    np.testing.assert_array_equal(scan.returns_mask(), [False, False, True, False])
    np.testing.assert_array_equal(scan.no_return_mask(), [False, False, False, True])


MALFORMED = [
    # (bad line, words expected in the message)
    (flaser([1.0, 2.0]).replace(" 2 ", " 3 ", 1), "fields"),  # n says 3, two readings present
    (flaser([1.0, 2.0]).replace("FLASER 2 1", "FLASER 2 one"), "range 0"),
    (flaser([1.0, 2.0]).replace("FLASER 2", "FLASER two"), "integer"),
    (flaser([1.0, 2.0]).replace("FLASER 2", "FLASER -2"), "out of range"),
    ("FLASER", "beam count"),
    (flaser([1.0, 2.0], x=math.nan), "finite"),
    (flaser([1.0, 2.0], theta=math.inf), "finite"),
    (flaser([1.0, 2.0]) + " extra", "fields"),
    ("PARAM robot_frontlaser_offset ahead 0 h 0", "robot_frontlaser_offset"),
    ("PARAM robot_front_laser_max", "robot_front_laser_max"),
    (robotlaser1([1.0, 2.0], (0.0, 0.0, 0.0)).rsplit(" ", 1)[0], "fields"),  # last field lost
    # n=2, ranges 1 2, then the remission count 1 replaced by "x"
    (robotlaser1([1.0, 2.0], (0.0, 0.0, 0.0), remissions=(1.0,)).replace(" 2 1 2 1 1 ", " 2 1 2 x 1 "),
     "remission count"),
    (robotlaser1([1.0, 2.0], (0.0, 0.0, 0.0), max_range=0.0), "max_range"),
    (robotlaser1([1.0, 2.0], (0.0, 0.0, 0.0), start=math.nan), "start_angle"),
]  # fmt: skip


@pytest.mark.parametrize(("bad", "words"), MALFORMED)
def test_malformed_line_names_file_and_line(tmp_path: Path, bad: str, words: str) -> None:
    path = write_log(tmp_path / "bad.log", ["# header", flaser([1.0, 2.0]), "", bad, flaser([1.0, 2.0])])
    with pytest.raises(DatasetError) as info:
        load_dataset(path)
    message = str(info.value)
    assert f"{path}:4:" in message
    assert words in message
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    ("lines", "words"),
    [
        # start_angle + 2 * angular_res overflows: every field is finite, the third bearing is not.
        ([robotlaser1([1.0, 2.0, 3.0], (0.0, 0.0, 0.0), res=1e308)], "ROBOTLASER1 beam angles"),
        # x and the offset are finite, the sensor's x (x + offset * cos(theta)) is not.
        (["PARAM robot_frontlaser_offset 1e308 0 h 0", flaser([1.0, 2.0], x=1.7e308)], "FLASER sensor pose"),
        # Every bearing (1e308) and the heading (1e308) are finite, a beam's direction, their sum, is not.
        ([robotlaser1([1.0, 2.0], (0.0, 0.0, 1e308), start=1e308, res=0.0)], "ROBOTLASER1 beam directions"),
    ],
    ids=["robotlaser1-angles", "flaser-sensor-pose", "robotlaser1-directions"],
)
def test_a_line_whose_scan_would_not_be_finite_is_malformed_at_load(
    tmp_path: Path, lines: list[str], words: str
) -> None:
    """Finite fields that make an infinite bearing or sensor pose are refused by `load_dataset`,
    naming the line: they were loaded, and building that scan raised ScanError mid-iteration,
    which stopped `fleetmap build` with a traceback."""
    path = write_log(tmp_path / "overflow.log", [flaser([1.0, 2.0]), *lines])
    with pytest.raises(DatasetError, match=words) as info:
        load_dataset(path)
    assert f"{path}:{1 + len(lines)}:" in str(info.value)


def test_malformed_line_in_gzip_file_has_line_number(tmp_path: Path) -> None:
    lines = [flaser([1.0])] * 6 + ["FLASER 1 x 0 0 0 0 0 0 0 h 0"]
    with pytest.raises(DatasetError, match=r"bad\.log\.gz:7: FLASER range 0"):
        load_dataset(write_log(tmp_path / "bad.log.gz", lines, compress=True))


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "no FLASER or ROBOTLASER1"),
        (b"hello world\nthis is not a log\n", "no FLASER or ROBOTLASER1"),
        (b"PARAM robot_frontlaser_offset 0.1 0 h 0\nODOM 0 0 0 0 0 0 0 h 0\n", "no FLASER or ROBOTLASER1"),
        (bytes(range(256)) * 4, "not UTF-8"),
        (gzip.compress(("\n".join([flaser([1.0, 2.0])] * 50)).encode(), mtime=0)[:-30], "corrupt gzip"),
    ],
)
def test_unknown_or_broken_format(tmp_path: Path, content: bytes, words: str) -> None:
    path = tmp_path / "mystery.dat"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=words):
        load_dataset(path)


def test_range_overrides(tmp_path: Path) -> None:
    lines = [flaser([0.2, 5.0, 20.0]), robotlaser1([0.2, 5.0, 20.0], (0.0, 0.0, 0.0), max_range=30.0)]
    path = write_log(tmp_path / "r.log", lines)
    ds = load_dataset(path, range_min=0.5, range_max=10.0)
    assert (ds.range_min, ds.range_max) == (0.5, 10.0)
    for scan in ds:
        assert (scan.range_min, scan.range_max) == (0.5, 10.0)
        np.testing.assert_array_equal(scan.returns_mask(), [False, True, False])
    # Only range_min: the per-message range_max stays.
    assert [s.range_max for s in load_dataset(path, range_min=0.0)] == [DEFAULT_FLASER_RANGE_MAX, 30.0]
    # inf means "no limit", stored as the readers' UNBOUNDED_RANGE_MAX.
    assert load_dataset(path, range_max=math.inf).range_max == UNBOUNDED_RANGE_MAX


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"range_min": -1.0}, "range_min"),
        ({"range_min": math.nan}, "range_min"),
        ({"range_max": 0.5, "range_min": 1.0}, "range_max"),
        ({"range_max": 2e6}, "range_max"),
        ({"range_max": math.nan}, "range_max"),
        # Text was parsed ("20" taken as 20 m, as no Scan would), or raised float()'s bare ValueError.
        ({"range_max": "20"}, "range_max must be a number, got '20'"),
        ({"range_min": "0.1"}, "range_min must be a number, got '0.1'"),
        ({"range_max": "far"}, "range_max must be a number"),
        ({"range_min": [1.0]}, "range_min must be a number"),
    ],
)
def test_invalid_range_overrides(tmp_path: Path, kwargs: dict[str, object], words: str) -> None:
    path = write_log(tmp_path / "r.log", [flaser([1.0])])
    with pytest.raises(DatasetError, match=words):
        load_dataset(path, **kwargs)


def test_dataset_is_reiterable_and_yields_private_arrays(tmp_path: Path) -> None:
    ds = load_dataset(write_log(tmp_path / "it.log", [flaser([1.0, 2.0], x=float(i)) for i in range(3)]))
    first = list(ds)
    first[0].ranges[:] = 99.0  # a consumer scribbling on its scan must not change the dataset
    first[0].angles[:] = 0.0
    second = list(ds)
    assert [s.pose.x for s in second] == [0.0, 1.0, 2.0]
    np.testing.assert_array_equal(second[0].ranges, [1.0, 2.0])
    assert second[0].angles[0] == pytest.approx(-math.pi / 2)
    assert ds[-1].pose.x == 2.0
    with pytest.raises(IndexError):
        ds[3]


def test_dataset_takes_slices_and_numpy_integers_and_names_any_other_index(tmp_path: Path) -> None:
    """A dataset indexes as a list does: `ds[1:3]` (the scans to replay a part of a log) raised
    "'<=' not supported between 'int' and 'slice'", and `ds[1.5]` NumPy's IndexError about its
    arrays, naming nothing of the dataset."""
    ds = load_dataset(write_log(tmp_path / "sl.log", [flaser([1.0, 2.0], x=float(i)) for i in range(5)]))
    assert [s.pose.x for s in ds[1:3]] == [1.0, 2.0]
    assert [s.pose.x for s in ds[::-2]] == [4.0, 2.0, 0.0]
    assert ds[7:9] == []
    assert ds[np.int64(3)].pose.x == 3.0
    with pytest.raises(TypeError, match="dataset indices must be integers or slices, not float"):
        ds[1.5]  # type: ignore[call-overload]


# ---------------------------------------------------------------------------------------------------
# MATLAB (.mat) files in the Coursera course's convention


def write_mat(path: Path, ranges: np.ndarray, angles: np.ndarray, pose: np.ndarray, **extra: object) -> Path:
    scipy.io.savemat(path, {"ranges": ranges, "scanAngles": angles, "pose": pose, **extra})
    return path


def course_endpoints(pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """End points as the course's occupancy-mapping code computes them (y pointing down)."""
    x, y, theta = pose
    return np.stack([ranges * np.cos(angles + theta) + x, -ranges * np.sin(angles + theta) + y], axis=-1)


def test_mat_worked_example(tmp_path: Path) -> None:
    """Robot at (1, 2) facing +x; a 3 m beam at +90 degrees.

    The course puts its end point at (1, 2 - 3) = (1, -1): three rows ABOVE the robot in its image
    (y grows downwards). In fleetmap's y-up frame that same picture has the point three metres
    above the robot, which sits at (1, -2): the point is at (1, 1) = (P.x, -P.y).
    """
    angles = np.array([[math.pi / 2]])
    path = write_mat(tmp_path / "ex.mat", np.array([[3.0]]), angles, np.array([[1.0], [2.0], [0.0]]))
    scan = load_dataset(path)[0]
    assert (scan.pose.x, scan.pose.y, scan.pose.theta) == (1.0, -2.0, 0.0)
    ex, ey = scan.endpoints()
    np.testing.assert_allclose([ex[0], ey[0]], [1.0, 1.0], atol=1e-12)
    p = course_endpoints(np.array([1.0, 2.0, 0.0]), angles.ravel(), np.array([3.0]))[0]
    np.testing.assert_allclose(p, [1.0, -1.0], atol=1e-12)


def test_mat_reader_flips_y(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    n_beams, n_scans = 11, 6
    angles = np.linspace(-2.0, 2.0, n_beams).reshape(-1, 1)  # N x 1, as in the course files
    ranges = rng.uniform(0.5, 20.0, size=(n_beams, n_scans))
    ranges[3, 2] = 0.0  # a zero reading: ignored by range_min
    pose = np.vstack(
        [rng.uniform(-10, 10, n_scans), rng.uniform(-10, 10, n_scans), rng.uniform(-3, 3, n_scans)]
    )
    path = write_mat(tmp_path / "course.mat", ranges, angles, pose, param={"resol": 25, "size": [900, 900]})
    ds = load_dataset(path)
    assert ds.format == "matlab" and ds.name == "course" and len(ds) == n_scans
    assert (ds.range_min, ds.range_max) == (DEFAULT_RANGE_MIN, UNBOUNDED_RANGE_MAX)
    for k, scan in enumerate(ds):
        np.testing.assert_allclose(scan.angles, angles.ravel())  # angles unchanged
        np.testing.assert_allclose([scan.pose.x, scan.pose.y, scan.pose.theta], pose[:, k] * [1, -1, 1])
        p = course_endpoints(pose[:, k], angles.ravel(), ranges[:, k])
        ex, ey = scan.endpoints()
        np.testing.assert_allclose(ex, p[:, 0], atol=1e-9)
        np.testing.assert_allclose(ey, -p[:, 1], atol=1e-9)
    assert not ds[2].returns_mask()[3]


def test_mat_transposed_layouts_and_detection_by_content(tmp_path: Path) -> None:
    angles = np.array([-0.5, 0.0, 0.5])
    ranges = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])  # K x N: 2 scans of 3 beams
    pose = np.array([[1.0, 2.0, 0.1], [3.0, 4.0, 0.2]])  # K x 3
    # No .mat extension: recognised by the MAT-file header.
    path = tmp_path / "course_copy.bin"
    scipy.io.savemat(path, {"ranges": ranges, "scanAngles": angles, "pose": pose})
    ds = load_dataset(path)
    assert ds.format == "matlab" and len(ds) == 2
    np.testing.assert_array_equal(ds[1].ranges, [4.0, 5.0, 6.0])
    np.testing.assert_allclose(ds.poses, [[1.0, -2.0, 0.1], [3.0, -4.0, 0.2]])


def test_mat_range_overrides(tmp_path: Path) -> None:
    path = write_mat(tmp_path / "o.mat", np.array([[0.3], [4.0], [12.0]]), np.zeros((3, 1)), np.zeros((3, 1)))
    scan = load_dataset(path, range_min=0.5, range_max=10.0)[0]
    assert (scan.range_min, scan.range_max) == (0.5, 10.0)
    np.testing.assert_array_equal(scan.returns_mask(), [False, True, False])
    np.testing.assert_array_equal(scan.no_return_mask(), [False, False, True])


@pytest.mark.parametrize("range_min", [UNBOUNDED_RANGE_MAX, 2e6])
def test_a_range_min_no_scan_could_reach_past_is_refused_at_load(tmp_path: Path, range_min: float) -> None:
    """A .mat file has no maximum range: its scans get UNBOUNDED_RANGE_MAX, the largest any reader
    gives. A range_min at or past it was taken by load_dataset, and every scan then failed as it was
    built (ScanError in the middle of iterating, where the readers promise DatasetError at load:
    fleetmap build --range-min 2000000 ended in a traceback); a CARMEN log's scans cannot have a
    larger range_max either."""
    mat = write_mat(tmp_path / "far.mat", np.array([[1.0]]), np.zeros((1, 1)), np.zeros((3, 1)))
    log = write_log(tmp_path / "far.log", [flaser([1.0])])
    for path in (mat, log):
        with pytest.raises(DatasetError, match="range_min must be .* below 1e\\+06 m"):
            load_dataset(path, range_min=range_min)


@pytest.mark.parametrize("name", ["course.mat.gz", "course.gz", "course.bin"])
def test_a_gzipped_mat_file_reads_as_the_mat_file(tmp_path: Path, name: str) -> None:
    """A .mat file compressed with gzip (as logs are, and as a course's files are shared) reads as
    the file itself: it was taken for a gzipped CARMEN log and refused as 'not UTF-8 text: not a
    CARMEN log', naming a line of a file that has none."""
    path = write_mat(tmp_path / "course.mat", np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([-0.5, 0.5]),
                     np.array([[1.0, 2.0], [3.0, 4.0], [0.1, 0.2]]))  # fmt: skip
    expected = load_dataset(path)
    packed = tmp_path / name
    packed.write_bytes(gzip.compress(path.read_bytes()))
    ds = load_dataset(packed)
    assert (ds.format, ds.name, len(ds)) == ("matlab", "course", 2)
    np.testing.assert_array_equal(ds.poses, expected.poses)
    for got, want in zip(ds, expected, strict=True):
        np.testing.assert_array_equal(got.ranges, want.ranges)


@pytest.mark.parametrize("name", ["course.mat.gz", "course.MAT"])
def test_a_gzipped_mat_v4_file_named_so_reads_as_the_mat_file(tmp_path: Path, name: str) -> None:
    """A MATLAB v4 file has no text header, so only its `.mat` name tells it (the reader takes v4 to
    v7.2): gzipped, it was taken for a gzipped CARMEN log, refused as 'not UTF-8 text: not a CARMEN
    log' (the uncompressed file reads), or, gzipped under its own name, handed to scipy still
    compressed ('not a readable .mat file')."""
    path = tmp_path / "v4.mat"
    scipy.io.savemat(path, {"ranges": np.array([[1.0], [2.0]]), "scanAngles": np.array([[-0.5], [0.5]]),
                            "pose": np.array([[1.0], [2.0], [0.1]])}, format="4")  # fmt: skip
    assert not path.read_bytes().startswith(b"MATLAB")  # no header: the name is all there is
    expected = load_dataset(path)
    packed = tmp_path / name
    packed.write_bytes(gzip.compress(path.read_bytes()))
    ds = load_dataset(packed)
    assert (ds.format, len(ds)) == ("matlab", 1)
    np.testing.assert_array_equal(ds.poses, expected.poses)
    np.testing.assert_array_equal(ds[0].ranges, expected[0].ranges)


GOOD_MAT = {"ranges": np.ones((3, 2)), "scanAngles": np.zeros(3), "pose": np.zeros((3, 2))}


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"pose": None}, "no variable 'pose'"),
        ({"scanAngles": np.zeros(4)}, "scanAngles has 4"),
        ({"pose": np.zeros((3, 5))}, "pose has shape"),
        ({"pose": np.full((3, 2), np.nan)}, "non-finite"),
        ({"scanAngles": ["a", "b", "c"]}, "numeric"),
        ({"ranges": np.ones(6)}, "ranges has shape"),
        # As a CARMEN log without a laser message is refused: `fleetmap build` said only that the
        # map had no observed cell, and `fleetmap replay` published nothing.
        ({"ranges": np.ones((3, 0)), "pose": np.zeros((3, 0))}, "no scan: ranges holds 0 scans of 3"),
        # Finite bearings and a finite heading whose sum, a beam's direction, is not: building that
        # scan mid-build raised ScanError, a traceback from `fleetmap build`.
        ({"scanAngles": np.full(3, 1e308), "pose": np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 1e308]])},
         "scan 1 \\(0-based\\): heading 1e\\+308 plus its beam angles"),
    ],
)  # fmt: skip
def test_mat_malformed(tmp_path: Path, changes: dict[str, object], words: str) -> None:
    variables = {k: v for k, v in (GOOD_MAT | changes).items() if v is not None}
    path = tmp_path / "bad.mat"
    scipy.io.savemat(path, variables)
    with pytest.raises(DatasetError, match=words):
        load_dataset(path)


V73_HEADER = b"MATLAB 7.3 MAT-file, Platform: GLNXA64".ljust(512)
HDF5 = b"\x89HDF\r\n\x1a\n"


@pytest.mark.parametrize(
    ("name", "content", "words"),
    [
        ("x.mat", HDF5 + bytes(100), "v7.3"),
        # What MATLAB's save -v7.3 writes: a 512-byte text header, then the HDF5 signature. It is
        # recognised as MATLAB by its header even without the .mat extension.
        ("x.mat", V73_HEADER + HDF5 + bytes(100), "v7.3"),
        ("x.dat", V73_HEADER + HDF5 + bytes(100), "v7.3"),
        ("x.mat", b"definitely not a mat file", "not a readable .mat"),
    ],
)
def test_mat_unreadable(tmp_path: Path, name: str, content: bytes, words: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=words):
        load_dataset(path)
