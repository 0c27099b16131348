"""The engine as a library, as its documentation presents it: the public names of `fleetmap`, the
README's example run as written, and clear errors for the wrong inputs a new user gives."""

from __future__ import annotations

import importlib
import json
import math
import os
import re
import subprocess
import sys
import textwrap
import threading
import warnings
from dataclasses import astuple
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ConfigDict, ValidationError

import fleetmap
from fleetmap import export
from fleetmap.config import MapConfig, OccupancyParams
from fleetmap.export import write_build_outputs
from fleetmap.grid_map import GridMap
from fleetmap.scan import Pose2D, Scan, ScanError

REPO = Path(__file__).resolve().parent.parent


def _fan(pose: tuple[float, float, float] = (0.5, 0.5, 0.0), n: int = 90) -> Scan:
    return Scan.from_fan(pose, -math.pi / 2, math.pi / n, np.full(n, 2.0), 0.05, 10.0)


# -- the public import surface ---------------------------------------------------------------------


def test_every_public_name_comes_from_its_module() -> None:
    """`from fleetmap import X` gives the object its module defines, for every name in `__all__`."""
    assert fleetmap.__all__ == sorted(fleetmap.__all__)
    for name in fleetmap.__all__:
        defining = importlib.import_module(fleetmap._EXPORTS[name])
        assert getattr(fleetmap, name) is getattr(defining, name), name
    with pytest.raises(AttributeError, match="no attribute 'Gridmap'"):
        fleetmap.Gridmap  # noqa: B018


def test_fleetmap_is_a_regular_typed_package() -> None:
    """A package with an `__init__.py` and `py.typed` beside it, in both distributions' packages:
    a namespace package's `py.typed` does not mark its modules typed (PEP 561)."""
    import fleetmap_client

    for package in (fleetmap, fleetmap_client):
        assert package.__file__ is not None, f"{package.__name__} is a namespace package"
        assert (Path(package.__file__).parent / "py.typed").is_file(), package.__name__


def test_a_program_using_the_python_client_type_checks_strictly(tmp_path: Path, mypy_cache: Path) -> None:
    """`mypy --strict` of a program using the client as docs/clients.md does. The package's own
    names (`from fleetmap_client import FleetmapClient`) were Any to a type checker (its lazy
    `__getattr__`), so nothing of their use was checked; a NumPy `origin` of `raycast` and one
    (x, y) pair to `cells`, both documented, were type errors. A `type: ignore` marks each line that
    must be an error: `--strict` reports an ignore that is not needed, so a name that became Any
    again fails this test too."""
    pytest.importorskip("mypy")
    program = tmp_path / "uses_client.py"
    program.write_text(
        textwrap.dedent(
            """\
            from __future__ import annotations

            import numpy as np

            from fleetmap_client import FleetmapClient, FleetmapError, PublisherClosed, ScanPublisher


            def plan(fm: FleetmapClient) -> float:
                rays = fm.raycast("m", np.array([1.0, 2.0]), np.linspace(-1.0, 1.0, 5), max_range=10.0)
                one = fm.cells("m", [0.5, 0.5])
                many = fm.cells("m", np.zeros((3, 2)))
                maps: int = fm.list_maps()  # type: ignore[assignment]
                return float(rays["range"].sum() + one["probability"][0] + many["known"].sum() + maps)


            def drive(pub: ScanPublisher) -> bool:
                try:
                    return pub.wait_connected(timeout="soon")  # type: ignore[arg-type]
                except PublisherClosed:
                    return False


            def status(exc: FleetmapError) -> str:
                return exc.status  # type: ignore[return-value]
            """
        )
    )
    _assert_strictly_typed(program, mypy_cache)


def test_the_python_clients_numbers_may_be_numpys_to_a_type_checker(tmp_path: Path, mypy_cache: Path) -> None:
    """`mypy --strict` of a program that passes the client NumPy numbers where docs/clients.md says
    it takes them (a seq from `np.arange`, a tile index, a change version, a coordinate or a stamp
    read from an array): each was a type error ("incompatible type "signedinteger[_64Bit]";
    expected "int""), though the call works and the documentation names NumPy's integers. A string
    is still an error where a number is meant."""
    pytest.importorskip("mypy")
    program = tmp_path / "numpy_numbers.py"
    program.write_text(
        textwrap.dedent(
            """\
            from __future__ import annotations

            import numpy as np

            from fleetmap.scan import Scan
            from fleetmap_client import FleetmapClient, ScanPublisher


            def read(fm: FleetmapClient, scan: Scan, pub: ScanPublisher) -> None:
                for seq in np.arange(3, dtype=np.int64):
                    fm.post_scan("m", "r", scan, seq=seq, stamp=np.float32(1.5))
                    pub.publish(scan, seq=seq, stamp=np.float32(1.5))
                pub.flush_ended(np.int64(7), np.int64(0), np.int64(2), timeout=np.float32(1.0))
                fm.tile("m", np.int64(0), np.int32(-1), np.int64(2))
                fm.events("m", since=np.uint32(4))
                fm.cell("m", np.float32(1.5), np.int64(2))
                fm.region("m", np.float32(0), np.int64(0), np.float32(1.5), np.float64(2))
                fm.region_window("m", np.float32(0), np.int64(0), np.float32(1.5), np.float64(2))
                fm.region_png("m", np.float32(0), np.int64(0), np.float32(1.5), np.float64(2))
                fm.surface("m", np.float32(0), np.int64(0), np.float32(1.5), np.float64(2))
                fm.clear_region("m", np.float32(0), np.int64(0), np.float32(1.5), np.float64(2))
                fm.raycast("m", (0.0, 0.0), np.float32(0.5), max_range=np.float32(5.0))
                fm.export("m", margin=np.int64(3), resolution=np.float32(0.1))
                pub.wait_connected(timeout=np.float32(1.0))
                pub.flush(timeout=np.int64(1))
                FleetmapClient(timeout=np.float32(5.0), scan_timeout=np.int64(20)).close()
                fm.tile("m", "0", 0, 0)  # type: ignore[arg-type]
                fm.cell("m", "1.5", 2.0)  # type: ignore[arg-type]
            """
        )
    )
    _assert_strictly_typed(program, mypy_cache)


@pytest.fixture(scope="session")
def mypy_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One mypy cache for this process's strict checks: the first reads NumPy, pydantic and fleetmap
    (some 6 s of CPU), the others find them there (1 s)."""
    return tmp_path_factory.mktemp("mypy-cache")


def _assert_strictly_typed(program: Path, cache: Path) -> None:
    """`mypy --strict` of `program` as a user runs it: no project configuration (so no pydantic
    plugin), the packages checked as installed ones are (`--follow-imports silent`: their own
    errors are not reported; `make lint` checks them with the project's settings). `cache` is
    mypy's cache directory."""
    env = {**os.environ, "MYPYPATH": f"{REPO / 'service'}{os.pathsep}{REPO / 'clients' / 'python'}"}
    result = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--follow-imports", "silent", "--no-error-summary",
         "--config-file", "", "--cache-dir", str(cache), str(program)],
        capture_output=True, text=True, cwd=program.parent, env=env,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr


def test_a_program_using_the_engine_type_checks_strictly(tmp_path: Path, mypy_cache: Path) -> None:
    """`mypy --strict` of a program using the engine as the README does, by a user without pydantic's
    mypy plugin: `MapConfig()` and `MapConfig(resolution=0.05)` were errors ("Missing named argument
    'tile_size'" and three more), because the models gave their defaults positionally
    (`Field(256, ...)`), which type checkers do not read as a default (PEP 681 names it `default=`)."""
    pytest.importorskip("mypy")
    program = tmp_path / "uses_engine.py"
    program.write_text(
        textwrap.dedent(
            """\
            from __future__ import annotations

            from fleetmap import GridMap, MapConfig, OccupancyParams, Scan
            from fleetmap.wire import PoseMessage, ScanMessage


            def build() -> float:
                gmap = GridMap(MapConfig(resolution=0.05, occupancy=OccupancyParams(preset="cartographer")))
                other = GridMap(MapConfig())
                scan = Scan.from_fan((1.0, 2.0, 0.3), -1.0, 0.01, [2.0] * 200, 0.05, 30.0)
                result = gmap.integrate(scan)
                other.integrate(scan)
                message = ScanMessage(seq=1, pose=PoseMessage(x=0.0, y=0.0, theta=0.0), ranges=[1.0])
                updates: str = result.cell_updates  # type: ignore[assignment]
                return float(gmap.cells([[2.0, 2.5]])["probability"][0]) + message.seq + len(updates)
            """
        )
    )
    _assert_strictly_typed(program, mypy_cache)


def test_importing_the_wire_schema_loads_no_compiler() -> None:
    """The names are lazy: a robot that imports `fleetmap.wire` and `fleetmap.codec` (through the
    package's `__init__`) neither imports numba nor the engine's kernels."""
    code = (
        "import sys, fleetmap, fleetmap.wire, fleetmap.codec\n"
        "from fleetmap import MapConfig, Scan\n"
        "print(sorted(m for m in ('numba', 'fleetmap.grid_map', 'fleetmap.kernels') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_readme_library_example_runs_as_written() -> None:
    """The README's "Use the engine as a library" block, with its free names (`ranges`, the window)
    given values, runs and reads back what it integrated."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Use the engine as a library", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S)
    assert code is not None
    namespace: dict[str, object] = {"ranges": np.full(1081, 3.0), "i0": 0, "j0": 0, "i1": 60, "j1": 80}
    exec(compile(textwrap.dedent(code.group(1)), "README.md", "exec"), namespace)
    gmap = namespace["gmap"]
    assert isinstance(gmap, GridMap)
    assert gmap.cells([[2.0, 2.5]])["known"].tolist() == [True]


# -- Scan: one meaning for each input, clear errors ------------------------------------------------


def test_scan_built_directly_means_what_from_angles_means() -> None:
    """`Scan(...)` takes a pose tuple and lists as `from_angles` does, and None is "no return"
    (+inf) in both: it was NaN, an invalid reading, when the constructor was called directly."""
    direct = Scan((1, 2, 0.5), [0.0, 0.1], [1.0, None], 0, 10)  # type: ignore[arg-type]
    built = Scan.from_angles((1, 2, 0.5), [0.0, 0.1], [1.0, None], 0, 10)
    assert direct.pose == built.pose == Pose2D(1.0, 2.0, 0.5)
    np.testing.assert_array_equal(direct.ranges, [1.0, math.inf])
    np.testing.assert_array_equal(direct.ranges, built.ranges)
    assert direct.ranges.dtype == direct.angles.dtype == np.float64
    assert isinstance(direct.range_min, float) and isinstance(direct.range_max, float)
    assert direct.no_return_mask().tolist() == [False, True]
    # A Pose2D of ints or numpy scalars is held as floats, as a tuple of them is.
    assert Scan(Pose2D(1, 2, np.float32(0.5)), [0.0], [1.0], 0, 10).pose == direct.pose  # type: ignore[arg-type]
    assert all(type(v) is float for v in (direct.pose.x, direct.pose.y, direct.pose.theta))


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Scan.from_fan((0, 0), 0, 0.1, [1.0]), r"pose must be a Pose2D or an \(x, y, theta\)"),
        (lambda: Scan.from_fan({"x": 0, "y": 0, "theta": 0}, 0, 0.1, [1.0]), "pose must be a Pose2D"),
        (lambda: Scan.from_fan(("a", 0, 0), 0, 0.1, [1.0]), "pose must be a Pose2D"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, "123"), "ranges must be a sequence.*, got str"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, 3.0), "ranges must be a sequence.*, got float"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array(["1", "x"])), "ranges must be numbers"),
        (lambda: Scan.from_angles((0, 0, 0), ["a"], [1.0]), "angles must be numbers"),
        (lambda: Scan.from_fan((0, 0, 0), "a", 0.1, [1.0]), "angle_min must be a number, got 'a'"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [1.0], range_max=None), "range_max must be a number"),
        (lambda: Scan(Pose2D(0, 0, 0), [0.0], [1.0], "x", 5.0), "range_min must be a number, got 'x'"),  # type: ignore[arg-type]
        (lambda: Scan((0, 0), [0.0], [1.0], 0.0, 5.0), "pose must be a Pose2D"),  # type: ignore[arg-type]
        (lambda: Scan(Pose2D("a", 0, 0), [0.0], [1.0], 0.0, 5.0), r"sequence of numbers, got \('a', 0, 0\)"),  # type: ignore[arg-type]
        (lambda: Scan.from_fan(Pose2D(None, 0, 0), 0, 0.1, [1.0]), "pose must be a Pose2D"),  # type: ignore[arg-type]
        (lambda: Scan.from_fan(Pose2D(10**400, 0, 0), 0, 0.1, [1.0]), "pose must be a Pose2D"),
        # Strings (and bytes) that read as numbers were read so: README.md says a string raises.
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, ["1.5", "2"]), "ranges must be numbers"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [1.0, b"2"]), "ranges must be numbers"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array(["1.5", "2"])), "ranges must be numbers"),
        (lambda: Scan.from_angles((0, 0, 0), ["0", "0.1"], [1.0, 2.0]), "angles must be numbers"),
        (lambda: Scan.from_angles((0, 0, 0), np.array([0, "1"], object), [1, 2]), "angles must be numbers"),
        (lambda: Scan.from_fan(("1", "2", "0"), 0, 0.1, [1.0]), "pose must be a Pose2D"),
        (lambda: Scan(Pose2D("1", 0, 0), [0.0], [1.0], 0.0, 5.0), "pose must be a Pose2D"),  # type: ignore[arg-type]
        (lambda: Scan.from_fan((0, 0, 0), "0.1", 0.1, [1.0]), "angle_min must be a number, got '0.1'"),
        (lambda: Scan(Pose2D(0, 0, 0), [0.0], [1.0], "0", 5.0), "range_min must be a number, got '0'"),  # type: ignore[arg-type]
        (lambda: Scan(Pose2D(0, 0, 0), [0.0], [1.0], 0.0, "inf"), "range_max must be a number, got 'inf'"),  # type: ignore[arg-type]
        # Bools, dates and durations were numbers to numpy and float(): ranges of True were walls
        # 1 m away, a date a wall some 20,000 m away (days since 1970), an x of True 1 m.
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array([True, False])), "numbers: got bool"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [True, 2.0]), "ranges must be numbers or None: got bool"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array(["2024-01-01"], "M8[D]")), "got datetime64"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array([3], "timedelta64[s]")), "got timedelta64"),
        (lambda: Scan.from_angles((0, 0, 0), np.array([False, True]), [1.0, 2.0]), "angles must be numbers"),
        (lambda: Scan.from_fan((True, 0, 0), 0, 0.1, [1.0]), "pose must be a Pose2D"),
        (lambda: Scan.from_fan((0, 0, 0), np.bool_(True), 0.1, [1.0]), "angle_min must be a number"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [np.timedelta64(2, "s")]), "ranges must be numbers or"),
        # Beams in an order of their own: a generator of ranges was taken where one of angles was
        # refused ("not 'generator'"), and a set of ranges in the set's order, not the beams'.
        (
            lambda: Scan.from_angles((0, 0, 0), (a for a in [0.0, 0.1]), [1.0, 2.0]),
            "angles must be a sequence or an array of numbers, got generator: give a list or an array",
        ),
        (
            lambda: Scan.from_angles((0, 0, 0), [0.0, 0.1], (r for r in [1.0, 2.0])),
            "ranges must be a sequence or an array of numbers or None, got generator: give a list",
        ),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, {3.0, 1.0}), "ranges must be a sequence.*, got set"),
        (lambda: Scan((0, 0, 0), {0.0, 0.1}, [1.0, 2.0], 0.0, 5.0), "angles must be a sequence.*, got set"),  # type: ignore[arg-type]
    ],
)  # fmt: skip
def test_scan_inputs_that_are_not_numbers_raise_scan_error(build: object, message: str) -> None:
    """Each raised numpy's bare ValueError, a TypeError or an AttributeError ('tuple' object has no
    attribute 'is_finite'), or, for a string of digits, built a scan of its characters. A `Pose2D`
    (which checks nothing) of a string or None raised TypeError from the finiteness check, and one
    of an int past float's range OverflowError."""
    with pytest.raises(ScanError, match=message):
        build()  # type: ignore[operator]


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [10**400]), "ranges must be numbers.*int too large"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array([10**400])), "ranges must be numbers.*too large"),
        (lambda: Scan.from_angles((0, 0, 0), [10**400], [1.0]), "angles must be numbers: got an integer"),
        (lambda: Scan.from_fan((10**400, 0, 0), 0, 0.1, [1.0]), "pose must be a Pose2D"),
        (lambda: Scan.from_fan((0, 0, 0), 10**400, 0.1, [1.0]), "angle_min must be a finite number, got an"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, [1.0], 0, 10**400), "range_max must be a finite number"),
        (lambda: Scan.from_angles((0, 0, 0), np.array([0.5j, 1 + 0.5j]), [1, 2]), "angles must be real"),
        (lambda: Scan.from_angles((0, 0, 0), [0.5j], [1.0]), "angles must be real numbers"),
        (lambda: Scan.from_fan((0, 0, 0), 0, 0.1, np.array([2 + 1j])), "ranges must be real numbers"),
    ],
)  # fmt: skip
def test_scan_inputs_beyond_real_floats_raise_scan_error(build: object, message: str) -> None:
    """A Python int beyond float's range raised OverflowError, not the documented ScanError (a
    ValueError) a caller catches; a complex array was taken with its imaginary parts dropped (angles
    [0.5j, 1 + 0.5j] became [0, 1]), with numpy's ComplexWarning only."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ScanError, match=message):
            build()  # type: ignore[operator]


def test_a_fan_whose_angles_overflow_is_refused_without_a_numpy_warning() -> None:
    """A finite increment can still make infinite angles (1e308 x 2): refused as such, quietly (the
    schema fuzzer found numpy's overflow warning on the REST path)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ScanError, match="beam angles must be finite"):
            Scan.from_fan((0, 0, 0), 1.0, 1e308, [1.0, 2.0, 3.0], 0.0, 10.0)


@pytest.mark.parametrize(("theta", "angle"), [(1e308, 1e308), (-1e308, -1.7e308), (1.7e308, 1.7e308)])
def test_a_scan_whose_heading_plus_bearing_overflows_is_refused(theta: float, angle: float) -> None:
    """A finite heading and finite bearings can still add up to an infinite direction in the map
    frame (1e308 + 1e308): such a scan was taken, and integrated as a streak of hits and free cells
    in a direction it never gave (57 cells of a map changed by 3 beams that point nowhere)."""
    gmap = GridMap()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ScanError, match="heading plus its beam angles must be finite"):
            gmap.integrate(Scan.from_angles((1.0, 2.0, theta), [angle, angle], [1.0, 0.5], 0.05, 30.0))
    assert gmap.known_bounds() is None


# -- GridMap: its inputs ---------------------------------------------------------------------------


def test_grid_map_takes_a_configuration_dict_and_refuses_other_things() -> None:
    assert GridMap({"resolution": 0.1, "layers": ["occupancy"]}).config.layers == ("occupancy",)  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="tile_size must be a power of two"):
        GridMap({"tile_size": 100})  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="config must be a MapConfig, .* not float"):
        GridMap(0.05)  # type: ignore[arg-type]


def test_a_configuration_takes_numpy_integers_as_the_numbers_they_hold() -> None:
    """A computed tile size or tile cap (`2 ** np.arange(...)`, `np.int64`) was refused, "Input
    should be a valid integer", where a NumPy float resolution was taken and the REST client sends
    both; a NumPy bool stays refused, as a Python one is."""
    config = MapConfig(tile_size=np.int64(64), max_tiles=np.uint16(300), resolution=np.float32(0.125))  # type: ignore[arg-type]
    assert config == MapConfig(tile_size=64, max_tiles=300, resolution=0.125)
    assert type(config.tile_size) is int and type(config.max_tiles) is int
    assert GridMap({"tile_size": np.int32(32)}).config.tile_size == 32
    for wrong in (np.True_, True):
        with pytest.raises(ValidationError, match="max_tiles"):
            MapConfig(max_tiles=wrong)  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="tile_size must be a power of two"):
        MapConfig(tile_size=np.int64(100))  # type: ignore[arg-type]


class _LooseConfig(MapConfig):
    """A MapConfig subclass that is not frozen: its fields can be assigned."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=False)


def test_a_map_keeps_its_configuration_when_the_one_given_changes() -> None:
    """A MapConfig reused for a second map, changed in between, changed the first map too (the map
    held the caller's object): with the TSDF layer taken out of the list, the first map, which
    keeps and integrates it, said it had none. (Only a subclass that is not frozen can change.)"""
    config = _LooseConfig(resolution=0.05)
    first = GridMap(config)
    first.integrate(Scan.from_angles((0.025, 0.025, 0.0), [0.0], [0.5], 0.0, 10.0))
    hit = [[0.525, 0.025]]
    config.layers = ("occupancy", "counts")
    second = GridMap(config)
    assert second.config.layers == ("occupancy", "counts")
    assert first.config.model_dump() == MapConfig(resolution=0.05).model_dump()
    assert first.cells(hit)["state"].tolist() == [fleetmap.STATE_OCCUPIED]
    assert first.cells(hit)["tsdf"].tolist() == [0.0]  # the return lies at its centre


def test_a_map_shares_a_frozen_configuration() -> None:
    """A MapConfig cannot change, so a map shares it: a deep copy per map took a second of a start
    that restores 5,000 maps. Its parameters of subclasses that are not frozen are copied."""
    config = MapConfig(resolution=0.05)
    assert GridMap(config).config is config
    loose = MapConfig(occupancy=_LooseOccupancy())
    assert GridMap(loose).config is not loose
    assert GridMap(loose).config == loose


class _LooseOccupancy(OccupancyParams):
    """Occupancy parameters of a subclass that is not frozen."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=False)


@pytest.mark.parametrize(
    ("part", "field", "value"),
    [
        ("", "resolution", 0.0),
        ("", "tile_size", 100),
        ("occupancy", "p_hit", 0.8),
        ("tsdf", "truncation", -1.0),
    ],
)
def test_a_configuration_cannot_be_changed_past_its_validation(part: str, field: str, value: float) -> None:
    """A MapConfig's fields could be assigned, unvalidated: resolution 0 made every scan a
    ZeroDivisionError, resolution -1 a map of nonsense, tile_size 100 broke the tiling, and p_hit on
    a validated configuration was ignored (its l_hit, resolved, is the value in use). A
    configuration is made whole and validated: MapConfig(...), MapConfig.model_validate(...)."""
    config = MapConfig()
    with pytest.raises(ValidationError, match="Instance is frozen"):
        setattr(getattr(config, part) if part else config, field, value)
    assert config == MapConfig()


def test_integrate_refuses_what_is_not_a_scan() -> None:
    gmap = GridMap()
    for wrong in ([1.0, 2.0], {"pose": (0, 0, 0)}):
        with pytest.raises(TypeError, match="expected a fleetmap Scan"):
            gmap.integrate(wrong)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="expected a fleetmap Scan"):
            gmap.plan(wrong)  # type: ignore[arg-type]
    assert len(gmap.store) == 0


def test_cells_reads_only_x_y_pairs() -> None:
    """Two rows of (x, y, z) were read as three points, silently; now it is an error. One pair alone
    is one point, and a point beyond any cell a map can hold reads as unknown, without a warning."""
    gmap = GridMap()
    gmap.integrate(_fan())
    with pytest.raises(ValueError, match=r"shape \(n, 2\); got shape \(2, 3\)"):
        gmap.cells([[1.0, 0.5, 0.0], [2.0, 0.5, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        gmap.cells([[math.nan, 0.5]])
    with pytest.raises(ValueError, match="pairs of numbers"):
        gmap.cells([["a", 0.5]])
    one = gmap.cells([2.51, 0.5])
    assert one["known"].tolist() == [True] and one["hits"].tolist() == [1]
    assert gmap.cells(np.zeros((0, 2)))["known"].shape == (0,)
    assert gmap.cells([])["known"].shape == (0,)
    # An empty array of another shape is not "no points": [[]] is one point without coordinates, an
    # (n, 0) array n of them; read as none, the answer had 0 entries where the caller counted on n.
    for shape in [(1, 0), (5, 0), (0, 3), (0, 0), (0, 2, 2)]:
        with pytest.raises(ValueError, match=re.escape(f"shape (n, 2); got shape {shape}")):
            gmap.cells(np.zeros(shape))
    with pytest.raises(ValueError, match=r"got shape \(1, 0\)"):
        gmap.cells([[]])
    # Two points written x + yj were read as the one point (x1, x2), numpy dropping the imaginary
    # parts with a warning only; rays' angles given as unit complex directions, as their cosines.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for complex_points in (np.array([2.51 + 0.5j, 3.0 + 0.5j]), np.array([[2.51 + 0j, 0.5]])):
            with pytest.raises(ValueError, match="complex"):
                gmap.cells(complex_points)
        with pytest.raises(ValueError, match="angles must be numbers"):
            gmap.cast_rays((0.0, 0.0), np.exp(1j * np.array([0.0, 1.0])), 1.0)
        with pytest.raises(ValueError, match="origin must be an"):
            gmap.cast_rays(np.array([1.0 + 0j, 0.5]), [0.0], 1.0)
    # An int beyond float's range raised OverflowError, which is no ValueError: past the errors
    # these calls document.
    with pytest.raises(ValueError, match="pairs of numbers"):
        gmap.cells([[10**400, 0.5]])
    with pytest.raises(ValueError, match="angles must be numbers"):
        gmap.cast_rays((0.0, 0.0), [10**400], 1.0)
    with pytest.raises(ValueError, match="origin must be an"):
        gmap.cast_rays((10**400, 0.0), [0.0], 1.0)
    with pytest.raises(ValueError, match="max_range must be a positive finite number"):
        gmap.cast_rays((0.0, 0.0), [0.0], 10**400)
    # Text that reads as numbers was parsed, where a Scan refuses it: one rule for every input.
    with pytest.raises(ValueError, match="pairs of numbers: got text"):
        gmap.cells([["1", "2"]])
    with pytest.raises(ValueError, match="pairs of numbers: got text"):
        gmap.cells(np.array([[b"2.51", b"0.5"]]))
    with pytest.raises(ValueError, match="angles must be numbers"):
        gmap.cast_rays((0.0, 0.0), ["0.5"], 1.0)
    with pytest.raises(ValueError, match="origin must be an"):
        gmap.cast_rays(["0.5", 0.5], [0.0], 1.0)
    with pytest.raises(ValueError, match="max_range must be a positive finite number"):
        gmap.cast_rays((0.0, 0.0), [0.0], "10")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pairs of numbers: got bool"):
        gmap.cells(np.array([[True, False]]))
    with pytest.raises(ValueError, match="angles must be numbers"):
        gmap.cast_rays((0.0, 0.0), np.array([True]), 1.0)
    with pytest.raises(ValueError, match="max_range must be a positive finite number"):
        gmap.cast_rays((0.0, 0.0), [0.0], True)
    with np.errstate(all="raise"):
        far = gmap.cells([[1e300, -1e300], [2.51, 0.5]])
    assert far["known"].tolist() == [False, True]


def test_occupancy_clamp_error_names_the_probabilities_it_was_given_as() -> None:
    with pytest.raises(ValidationError, match=r"p_min < 0.5 < p_max.*p_min 0.9, p_max 0.2"):
        fleetmap.OccupancyParams(p_min=0.9, p_max=0.2)


def test_write_build_outputs_takes_a_string_path(tmp_path: Path) -> None:
    gmap = GridMap()
    gmap.integrate(_fan())
    written = write_build_outputs(gmap, str(tmp_path / "out"))
    assert {p.name for p in written} >= {"map.yaml", "map.pgm", "map.png", "meta.json", "log_odds.npy"}
    assert all(p.is_file() for p in written)


def test_write_build_outputs_writes_one_state_of_a_map_being_integrated(tmp_path: Path) -> None:
    """A scan integrated by another thread while the files were written went into some of them and
    not the others: map.pgm showed a wall that log_odds.npy and hits.npy did not hold, each file
    of another map. The files are of one state now: integration waits until they are written. The
    other thread integrates between two of the export's reads if it can do so without waiting."""
    gmap = GridMap()
    gmap.integrate(_fan())
    late = _fan((0.6, 0.4, 1.0))
    read = gmap.region
    integrated: list[bool] = []

    def integrate_if_free() -> None:
        if gmap.lock.acquire(blocking=False):
            try:
                gmap.integrate(late)
            finally:
                gmap.lock.release()
            integrated.append(True)

    def region_then_a_scan(*args: Any) -> np.ndarray:
        out = read(*args)
        if not integrated:
            writer = threading.Thread(target=integrate_if_free)
            writer.start()
            writer.join()
        return out

    gmap.region = region_then_a_scan  # type: ignore[method-assign]
    write_build_outputs(gmap, tmp_path, margin=0)
    gmap.region = read  # type: ignore[method-assign]
    log_odds = np.load(tmp_path / "log_odds.npy")
    hits, misses = np.load(tmp_path / "hits.npy"), np.load(tmp_path / "misses.npy")
    np.testing.assert_array_equal(~np.isnan(log_odds), (hits > 0) | (misses > 0))
    pgm = (tmp_path / "map.pgm").read_bytes()
    assert pgm.endswith(export.pgm_bytes(export.state_to_pgm(gmap.classify(log_odds))))
    assert not integrated  # it waited


def test_write_build_outputs_of_a_map_past_the_address_space_is_out_of_memory(tmp_path: Path) -> None:
    """A pose 5e10 m from the others (a log's glitch; the engine takes cells up to 2**40) spans a
    window of 10**24 cells: numpy refuses its arrays with a ValueError ('array is too big'), not the
    MemoryError of any other allocation that does not fit, and fleetmap build passed numpy's words
    on as its error, where a map a little smaller got its own, naming the far pose (cli._too_large)."""
    gmap = GridMap()
    gmap.integrate(_fan())
    gmap.integrate(_fan((5e10, 5e10, 0.0)))
    with pytest.raises(MemoryError, match="address space"):
        write_build_outputs(gmap, tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("margin", [-2, -1000, 2.5, True, "2"])
def test_write_build_outputs_refuses_a_margin_that_is_not_cells_around_the_map(
    tmp_path: Path, margin: object
) -> None:
    """`margin` is the unknown cells added around the observed ones: -2 cut two rows and columns of
    observed cells off every file without a word, -1000 failed in Pillow ('cannot write empty
    image') and 2.5 in range() ('float' object cannot be interpreted as an integer)."""
    gmap = GridMap()
    gmap.integrate(_fan())
    with pytest.raises(ValueError, match=f"margin must be a whole number of cells >= 0, got {margin!r}"):
        write_build_outputs(gmap, tmp_path / "out", margin=margin)  # type: ignore[arg-type]
    assert not (tmp_path / "out").exists()
    window = fleetmap.known_window(gmap, np.int64(3))
    assert window is not None and window == fleetmap.known_window(gmap, 3)


def test_write_build_outputs_takes_a_numpy_margin(tmp_path: Path) -> None:
    """`known_window` takes a NumPy integer margin, but its window then held NumPy integers, and
    `write_build_outputs` failed at its last file, meta.json ('Object of type int64 is not JSON
    serializable'), having written nothing. A window's edges are Python ints whatever the margin."""
    gmap = GridMap()
    gmap.integrate(_fan())
    window = fleetmap.known_window(gmap, np.int64(2))
    assert window is not None and all(type(edge) is int for edge in astuple(window))
    write_build_outputs(gmap, tmp_path / "numpy", margin=np.uint8(2))  # type: ignore[arg-type]
    write_build_outputs(gmap, tmp_path / "python", margin=2)
    for name in ("meta.json", "map.pgm", "hits.npy"):
        assert (tmp_path / "numpy" / name).read_bytes() == (tmp_path / "python" / name).read_bytes(), name
    assert json.loads((tmp_path / "numpy" / "meta.json").read_text())["cell_window"] == list(astuple(window))


@pytest.mark.parametrize("p", [0.0, 1.0, 1.5, -0.1, math.nan])
def test_logit_of_what_is_not_a_probability_says_so(p: float) -> None:
    """`fleetmap.logit(1.0)` raised ZeroDivisionError ('float division by zero'), 0 and 1.5 math's
    'math domain error', and NaN gave NaN log-odds."""
    with pytest.raises(ValueError, match=f"must lie strictly between 0 and 1, got {p!r}"):
        fleetmap.logit(p)
    assert fleetmap.probability(fleetmap.logit(0.7)) == pytest.approx(0.7)


@pytest.mark.parametrize("point", [(math.inf, 0.0), (0.0, -math.inf), (math.nan, 1.0), (0, -(10**400))])
def test_cell_index_of_a_point_that_is_not_finite_is_a_value_error(point: tuple[float, float]) -> None:
    """`cell_index(inf, 0)` raised math.floor's OverflowError ('cannot convert float infinity to
    integer'), not the ValueError `cells` raises for such a point; an int past float's range,
    math.isfinite's OverflowError ('int too large to convert to float')."""
    with pytest.raises(ValueError, match="a point must be finite numbers"):
        GridMap().cell_index(*point)
    assert GridMap().cell_index(-1e-12, 0.07) == (-1, 1)


@pytest.mark.parametrize(
    "change",
    [
        lambda layers: layers.clear(),
        lambda layers: layers.append("tsdf"),
        lambda layers: layers.__setitem__(0, "walls"),
    ],
    ids=["emptied", "repeated", "unknown"],
)
def test_a_configurations_layers_cannot_be_changed_past_its_validation(change: Any) -> None:
    """`layers` was a list inside a frozen configuration: changed in place, it held what validation
    refuses (no layer, one twice, one that does not exist), and a map made of it kept no layer and
    integrated every scan into nothing, kept the TSDF twice, or failed with a bare KeyError."""
    config = MapConfig()
    with pytest.raises((TypeError, AttributeError)):
        change(config.layers)
    assert config == MapConfig()
    assert set(GridMap(config).store.pools) == {"log_odds", "hits", "misses", "tsdf", "tsdf_weight"}


def test_masked_ranges_are_invalid_readings() -> None:
    """A NumPy masked array of ranges (a driver's or a file's way of marking bad readings) lost its
    mask: each masked reading was integrated as the value under it, a wall where the sensor saw
    nothing valid. A masked reading is an invalid one (NaN), ignored as such."""
    values = np.full(90, 2.0)
    bad = np.arange(90) % 3 == 0
    masked = np.ma.array(values, mask=bad)
    expected = np.where(bad, np.nan, values)
    for scan in (
        Scan.from_fan((0.5, 0.5, 0.0), -math.pi / 2, math.pi / 90, masked, 0.05, 10.0),
        Scan.from_angles((0.5, 0.5, 0.0), np.linspace(-1.5, 1.5, 90), masked, 0.05, 10.0),
        Scan((0.5, 0.5, 0.0), np.linspace(-1.5, 1.5, 90), masked, 0.05, 10.0),  # type: ignore[arg-type]
    ):
        assert type(scan.ranges) is np.ndarray
        np.testing.assert_array_equal(scan.ranges, expected)
    gmap, reference = GridMap(), GridMap()
    gmap.integrate(Scan.from_fan((0.5, 0.5, 0.0), -math.pi / 2, math.pi / 90, masked, 0.05, 10.0))
    reference.integrate(Scan.from_fan((0.5, 0.5, 0.0), -math.pi / 2, math.pi / 90, expected, 0.05, 10.0))
    bounds = reference.known_bounds()
    assert bounds is not None and gmap.known_bounds() == bounds
    np.testing.assert_array_equal(gmap.region("hits", *bounds), reference.region("hits", *bounds))


def test_masked_angles_are_refused() -> None:
    """A masked bearing is no bearing: refused, not read as the value under its mask."""
    angles = np.ma.array([0.0, 0.1, 0.2], mask=[False, True, False])
    with pytest.raises(ScanError, match="angles must not be masked"):
        Scan.from_angles((0.0, 0.0, 0.0), angles, [1.0, 1.0, 1.0])
    with pytest.raises(ScanError, match="angles must not be masked"):
        Scan((0.0, 0.0, 0.0), angles, [1.0, 1.0, 1.0], 0.0, 10.0)  # type: ignore[arg-type]
    unmasked = Scan.from_angles((0.0, 0.0, 0.0), np.ma.array([0.0, 0.1]), [1.0, 1.0])
    assert type(unmasked.angles) is np.ndarray and unmasked.angles.tolist() == [0.0, 0.1]


def test_cell_windows_take_integers_of_any_kind_and_name_what_is_not_one() -> None:
    """`region`, `surface` and `clear_window` take cell indices: NumPy integers mixed (int64 with
    uint64 made a float64 width, "'numpy.float64' object cannot be interpreted as an integer") work
    as the ints they hold, and a float said "unsupported operand type(s) for >>" (clear_window) or
    "'float' object cannot be interpreted as an integer", naming nothing; now a TypeError names it."""
    gmap = GridMap()
    gmap.integrate(_fan())
    window = (np.int64(0), np.int32(-5), np.uint64(30), np.int64(40))
    expected = gmap.region("hits", 0, -5, 30, 40)
    np.testing.assert_array_equal(gmap.region("hits", *window), expected)  # type: ignore[arg-type]
    np.testing.assert_array_equal(gmap.surface(*window), gmap.surface(0, -5, 30, 40))  # type: ignore[arg-type]
    for call in (
        lambda: gmap.region("hits", 0, -5, 30.0, 40),
        lambda: gmap.surface(0, -5, 30.0, 40),
        lambda: gmap.clear_window(0, -5, 30.0, 40),
    ):
        with pytest.raises(TypeError, match="i1 must be an integer cell index, got 30.0"):
            call()
    with pytest.raises(TypeError, match="j0 must be an integer cell index, got True"):
        gmap.clear_window(0, True, 30, 40)
    np.testing.assert_array_equal(gmap.region("hits", 0, -5, 30, 40), expected)
    assert gmap.clear_window(*window).cells > 0  # type: ignore[arg-type]
    assert not gmap.region("hits", 0, -5, 30, 40).any()
