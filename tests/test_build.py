"""`fleetmap build`, run as the installed command in a subprocess, as a user runs it.

The expected maps come from the issue's definitions (cell boundaries, the octomap preset's
log-odds, nav2's trinary thresholds and row order), not from the engine's own helpers; on the real
Intel log the outputs are compared cell by cell with a map the library builds from the same file.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import yaml
from PIL import Image
from service_process import REPO_DIR, fleetmap_command, wait_for
from test_compiled_cache import LOADED_KERNELS

from fleetmap import cli, export, server
from fleetmap.config import MapConfig
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import GridMap

RES = 0.05
L_HIT, L_MISS = math.log(0.7 / 0.3), math.log(0.4 / 0.6)  # the default (octomap) preset

# The test scene: a sensor at (X, Y) facing +y, with FLASER's two beams of a 2-beam scan at -90 deg
# (so along +x, 1 m) and 0 deg (along +y, 2 m). X and Y are chosen so that the exported window's
# corner, cell -404 x cell -469, is a product with rounding noise: -404 * 0.05 = -20.200000000000003.
X, Y = -20.09, -23.34
I_S, J_S = -402, -467  # the sensor's cell: floor(X / RES), floor(Y / RES)
I_HIT, J_HIT = -382, -427  # floor((X + 1) / RES) and floor((Y + 2) / RES)
SCANS = 4  # four misses take a cell below nav2's free threshold (p = 0.165 < 0.196)


def flaser(ranges: list[float], x: float, y: float, theta: float) -> str:
    """A FLASER line (the corrected pose twice, as in the real logs)."""
    pose = f"{x!r} {y!r} {theta!r}"
    return f"FLASER {len(ranges)} {' '.join(f'{r:g}' for r in ranges)} {pose} {pose} 1.0 testhost 1.0"


def scene_log(path: Path, scans: int = SCANS, extra: tuple[str, ...] = ()) -> Path:
    path.write_text("\n".join([flaser([1.0, 2.0], X, Y, math.pi / 2)] * scans + list(extra)) + "\n")
    return path


def build(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*fleetmap_command(), "build", *map(str, args)],
        capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONWARNINGS": "default"},
    )  # fmt: skip


def read_pgm(path: Path) -> np.ndarray:
    magic, size, maxval, data = path.read_bytes().split(b"\n", 3)
    width, height = map(int, size.split())
    assert (magic, maxval) == (b"P5", b"255")
    return np.frombuffer(data, dtype=np.uint8).reshape(height, width)


def test_build_writes_the_nav2_map_image_layers_and_meta(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = build(scene_log(tmp_path / "scene.log"), "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    assert f"{SCANS} scans integrated (0 skipped)" in done.stdout
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted(
        ["map.yaml", "map.pgm", "map.png", "meta.json", "log_odds.npy", "hits.npy", "misses.npy",
         "tsdf.npy", "tsdf_weight.npy"]
    )  # fmt: skip
    assert all(f"wrote {out / name}" in done.stdout for name in written)

    # The window: every cell observed in any layer plus a margin of 2 cells. The TSDF band reaches
    # past the returns (by its truncation, 0.2 m), so the far edges come from tsdf.npy.
    info = json.loads((out / "meta.json").read_text())
    i0, j0, i1, j1 = info["cell_window"]
    tsdf_j, tsdf_i = np.nonzero(~np.isnan(np.load(out / "tsdf.npy")))
    assert (i0, j0) == (I_S - 2, J_S - 2)
    assert (i1, j1) == (i0 + tsdf_i.max() + 3, j0 + tsdf_j.max() + 3)
    assert I_HIT + 3 < i1 <= I_HIT + 3 + 0.2 / RES + 1 and J_HIT + 3 < j1 <= J_HIT + 3 + 0.2 / RES + 1
    ny, nx = j1 - j0, i1 - i0
    occupied = {(I_HIT, J_S), (I_S, J_HIT)}
    free = {(i, J_S) for i in range(I_S, I_HIT)} | {(I_S, j) for j in range(J_S, J_HIT)}

    meta = yaml.safe_load((out / "map.yaml").read_text())
    assert meta == {
        "image": "map.pgm", "mode": "trinary", "resolution": RES, "origin": [-20.2, -23.45, 0.0],
        "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196,
    }  # fmt: skip
    assert "origin: [-20.2, -23.45, 0.0]" in (out / "map.yaml").read_text()  # no rounding noise
    assert meta["origin"][:2] == pytest.approx([i0 * RES, j0 * RES], abs=1e-9)

    # map.pgm: trinary, top row = highest y.
    pgm = read_pgm(out / "map.pgm")
    want = np.full((ny, nx), 205, dtype=np.uint8)
    for cells, value in ((free, 254), (occupied, 0)):
        for i, j in cells:
            want[ny - 1 - (j - j0), i - i0] = value
    np.testing.assert_array_equal(pgm, want)

    # log_odds.npy: float32, (ny, nx), row 0 = lowest y, NaN where unknown.
    log_odds = np.load(out / "log_odds.npy")
    assert log_odds.dtype == np.float32 and log_odds.shape == (ny, nx)
    expected = np.full((ny, nx), np.nan)
    for cells, value in ((free, SCANS * L_MISS), (occupied, SCANS * L_HIT)):
        for i, j in cells:
            expected[j - j0, i - i0] = value
    np.testing.assert_allclose(log_odds, expected, rtol=1e-6)

    # The count layers, in the same window.
    hits, misses = np.load(out / "hits.npy"), np.load(out / "misses.npy")
    assert hits[J_S - j0, I_HIT - i0] == SCANS and misses[J_S - j0, I_HIT - i0] == 0
    assert misses[J_S - j0, I_S - i0] == SCANS and hits.sum() == 2 * SCANS
    assert np.load(out / "tsdf.npy").shape == (ny, nx)

    # map.png: grayscale, darker = more likely occupied, top row = highest y, unknown mid-gray.
    with Image.open(out / "map.png") as image:
        assert image.mode == "L" and image.size == (nx, ny)
        png = np.asarray(image)
    hit_px = png[ny - 1 - (J_HIT - j0), I_S - i0]
    free_px = png[ny - 1 - (J_S - j0), I_S + 5 - i0]
    unknown_px = png[0, 0]
    assert hit_px < unknown_px < free_px and unknown_px == 128

    assert info["resolution"] == RES and info["origin"] == [-20.2, -23.45]
    assert info["cell_window"] == [i0, j0, i1, j1] and info["shape"] == [ny, nx]
    assert info["layers"] == ["log_odds", "hits", "misses", "tsdf", "tsdf_weight"]
    assert MapConfig.model_validate(info["config"]) == MapConfig()


def test_build_options_change_the_map(tmp_path: Path) -> None:
    log = scene_log(tmp_path / "scene.log")
    (tmp_path / "occ.json").write_text(json.dumps({"layers": ["occupancy"], "resolution": 0.2}))

    # --config, with --resolution given on the command line winning over the file's.
    config = tmp_path / "occ.json"
    done = build(log, "--out", tmp_path / "a", "--config", config, "--resolution", "0.1", "--quiet")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [
        "log_odds.npy", "map.pgm", "map.png", "map.yaml", "meta.json",
    ]  # fmt: skip
    info = json.loads((tmp_path / "a" / "meta.json").read_text())
    assert info["resolution"] == 0.1 and info["layers"] == ["log_odds"]
    assert "M cell updates/s" in done.stdout and "TSDF" not in done.stdout
    # A TSDF-only map says how fast its TSDF was fused (it said "0.0 M cell updates/s").
    (tmp_path / "tsdf.json").write_text(json.dumps({"layers": ["tsdf"]}))
    tsdf = build(log, "--out", tmp_path / "t", "--config", tmp_path / "tsdf.json", "--quiet")
    assert tsdf.returncode == 0 and "M TSDF updates/s" in tsdf.stdout, tsdf.stdout + tsdf.stderr
    assert "cell updates" not in tsdf.stdout
    # At 0.1 m the sensor is in cell (-201, -234); the beams end in column -191 and row -214.
    assert info["cell_window"] == [-201 - 2, -234 - 2, -191 + 3, -214 + 3]

    def known(out: Path) -> set[tuple[int, int]]:
        info = json.loads((out / "meta.json").read_text())
        i0, j0 = info["cell_window"][:2]
        lo = np.load(out / "log_odds.npy")
        return {(int(i) + i0, int(j) + j0) for j, i in zip(*np.nonzero(~np.isnan(lo)), strict=True)}

    def hits(out: Path) -> set[tuple[int, int]]:
        info = json.loads((out / "meta.json").read_text())
        i0, j0 = info["cell_window"][:2]
        lo = np.load(out / "log_odds.npy")
        return {(int(i) + i0, int(j) + j0) for j, i in zip(*np.nonzero(lo > 0), strict=True)}

    beam_x = {(i, J_S) for i in range(I_S, I_HIT + 1)}
    beam_y = {(I_S, j) for j in range(J_S, J_HIT + 1)}

    # --range-max 1.5: the 2 m beam is "no return", ignored by default.
    done = build(log, "--out", tmp_path / "b", "--range-max", "1.5", "--quiet")
    assert done.returncode == 0, done.stderr
    assert known(tmp_path / "b") == beam_x and hits(tmp_path / "b") == {(I_HIT, J_S)}

    # ... and with --no-return-range 1: its first metre cleared, with no hit.
    done = build(log, "--out", tmp_path / "c", "--range-max", "1.5", "--no-return-range", "1", "--quiet")
    assert done.returncode == 0, done.stderr
    first_metre = {(I_S, j) for j in range(J_S, math.floor((Y + 1.0) / RES) + 1)}
    assert known(tmp_path / "c") == beam_x | first_metre and hits(tmp_path / "c") == {(I_HIT, J_S)}

    # --range-min 1.5: the 1 m reading is ignored.
    done = build(log, "--out", tmp_path / "d", "--range-min", "1.5", "--quiet")
    assert done.returncode == 0, done.stderr
    assert known(tmp_path / "d") == beam_y and hits(tmp_path / "d") == {(I_S, J_HIT)}


def test_a_counts_only_build_maps_the_count_models_occupancy(tmp_path: Path) -> None:
    """Without the occupancy layer, map.pgm and map.png show hits / (hits + misses), the count
    model's maximum-likelihood occupancy, by the same thresholds; meta.json says so."""
    log = scene_log(tmp_path / "scene.log")
    (tmp_path / "counts.json").write_text(json.dumps({"layers": ["counts"]}))
    counts = build(log, "--out", tmp_path / "counts", "--config", tmp_path / "counts.json", "--quiet")
    both = build(log, "--out", tmp_path / "both", "--quiet")
    assert counts.returncode == both.returncode == 0, counts.stderr
    assert sorted(p.name for p in (tmp_path / "counts").iterdir()) == [
        "hits.npy", "map.pgm", "map.png", "map.yaml", "meta.json", "misses.npy",
    ]  # fmt: skip
    info = json.loads((tmp_path / "counts" / "meta.json").read_text())
    assert info["map_source"] == "counts" and info["layers"] == ["hits", "misses"]
    assert json.loads((tmp_path / "both" / "meta.json").read_text())["map_source"] == "occupancy"
    # Each cell was hit 4 times or missed 4 times: p = 1 or 0, the same trinary map as the
    # occupancy layer's, in the window of the cells the counts know (no TSDF band here).
    i0, j0, i1, j1 = info["cell_window"]
    assert (i0, j0, i1, j1) == (I_S - 2, J_S - 2, I_HIT + 3, J_HIT + 3)
    pgm = read_pgm(tmp_path / "counts" / "map.pgm")
    ny, nx = j1 - j0, i1 - i0
    assert pgm.shape == (ny, nx)
    assert pgm[ny - 1 - (J_HIT - j0), I_S - i0] == 0 and pgm[ny - 1 - (J_S - j0), I_S + 5 - i0] == 254
    assert (pgm == 0).sum() == 2 and (pgm == 254).sum() == (I_HIT - I_S) + (J_HIT - J_S) - 1  # one shared
    with Image.open(tmp_path / "counts" / "map.png") as image:
        png = np.asarray(image)
    assert png[ny - 1 - (J_HIT - j0), I_S - i0] == 0 and png[0, 0] == 128
    assert png[ny - 1 - (J_S - j0), I_S + 5 - i0] == 255


def test_a_build_into_an_earlier_builds_folder_leaves_none_of_its_files(tmp_path: Path) -> None:
    """Building again into the same --out with other layers removes the earlier build's files this
    map has none of, and says so: a TSDF-only build left the earlier map.yaml, map.pgm, map.png,
    log_odds.npy, hits.npy and misses.npy beside its new meta.json, so nav2 loaded the earlier map
    and a script loading hits.npy read another window (here another resolution) as this one. Other
    files in the folder are left alone."""
    log = scene_log(tmp_path / "scene.log")
    out = tmp_path / "out"
    first = build(log, "--out", out, "--resolution", "0.1", "--quiet")
    assert first.returncode == 0, first.stderr
    (out / "notes.txt").write_text("mine")
    (tmp_path / "tsdf.json").write_text(json.dumps({"layers": ["tsdf"]}))
    second = build(log, "--out", out, "--config", tmp_path / "tsdf.json", "--quiet")
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in out.iterdir()) == ["meta.json", "notes.txt", "tsdf.npy", "tsdf_weight.npy"]
    for name in ("map.yaml", "map.pgm", "map.png", "log_odds.npy", "hits.npy", "misses.npy"):
        assert f"removed {out / name}, an earlier build's: this map has no such layer" in second.stdout
    assert "removed" not in first.stdout and second.stdout.count("removed") == 6
    info = json.loads((out / "meta.json").read_text())
    assert info["layers"] == ["tsdf", "tsdf_weight"] and info["resolution"] == RES
    assert np.load(out / "tsdf.npy").shape == tuple(info["shape"])


def test_a_build_removes_only_what_an_earlier_build_wrote(tmp_path: Path) -> None:
    """Every file of an output's name that this map has none of was removed as 'an earlier
    build's', whoever wrote it: a TSDF-only build into a folder holding the user's own map.png and
    hits.npy (`--out .`) deleted both. Only the files an earlier build's meta.json names are its
    own now. An empty --out (`--out "$OUT"` with OUT unset) built into the current folder."""
    log = scene_log(tmp_path / "scene.log")
    (tmp_path / "tsdf.json").write_text(json.dumps({"layers": ["tsdf"]}))
    out = tmp_path / "out"
    out.mkdir()
    mine = {"map.png": b"my drawing", "hits.npy": b"my counts", "notes.txt": b"mine"}
    for name, data in mine.items():
        (out / name).write_bytes(data)
    done = build(log, "--out", out, "--config", tmp_path / "tsdf.json", "--quiet")
    assert done.returncode == 0, done.stderr
    assert "removed" not in done.stdout
    assert {name: (out / name).read_bytes() for name in mine} == mine
    names = sorted([*mine, "meta.json", "tsdf.npy", "tsdf_weight.npy"])
    assert sorted(p.name for p in out.iterdir()) == names
    # Run in `out`, with a PYTHONPATH that still finds this checkout's packages from there.
    paths = os.environ.get("PYTHONPATH", "").split(os.pathsep)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(Path(p).resolve()) for p in paths if p)}
    empty = subprocess.run(
        [*fleetmap_command(), "build", str(log), "--out", "", "--quiet"],
        capture_output=True, text=True, timeout=300, cwd=out, env=env,
    )  # fmt: skip
    assert empty.returncode == 2
    assert empty.stderr == "fleetmap build: error: --out is empty: give the folder to write the map into\n"
    assert sorted(p.name for p in out.iterdir()) == names


def test_a_build_into_a_folder_whose_meta_json_nests_deep_is_not_stopped_by_it(tmp_path: Path) -> None:
    """A meta.json that json's parser cannot read for its depth (arrays 100,000 deep) is not an
    earlier build's, as one that is not JSON is not: the build replaces it. Its RecursionError
    ended the build in a traceback, exit 1, after the scans were integrated."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "meta.json").write_text("[" * 100_000 + "]" * 100_000)
    done = build(scene_log(tmp_path / "scene.log"), "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    meta = json.loads((out / "meta.json").read_text())
    assert meta["layers"] == ["log_odds", "hits", "misses", "tsdf", "tsdf_weight"]


def test_a_build_that_cannot_write_all_its_files_leaves_the_folder_as_it_was(tmp_path: Path) -> None:
    """A disk that fills up while the build writes (here a file-size limit of 1000 bytes: map.yaml
    fits, map.pgm does not): the build said it could not write, and left a new map.yaml beside a
    truncated map.pgm and the earlier build's other files, a folder nav2 loaded as a map. Now no
    file takes its name until every one is written: the earlier build is there as it was, and
    nothing half-written is left."""
    resource = pytest.importorskip("resource")
    log = scene_log(tmp_path / "scene.log")
    out = tmp_path / "out"
    first = build(log, "--out", out, "--resolution", "0.1", "--quiet")
    assert first.returncode == 0, first.stderr
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    limited = subprocess.run(
        [*fleetmap_command(), "build", str(log), "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=300,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000)),
    )  # fmt: skip
    assert limited.returncode == 2, limited.stderr
    assert limited.stderr.startswith(f"fleetmap build: error: cannot write the outputs to {out}:"), (
        limited.stderr
    )
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before


def test_a_build_whose_files_cannot_all_take_their_names_leaves_the_folder_as_it_was(tmp_path: Path) -> None:
    """The files were renamed one by one once all were written, and a rename that failed (here
    map.pgm is a folder) left the new map.yaml beside the earlier files and eight .partial files.
    Now such a name is refused before any rename, and a rename that fails anyway (a file written
    meanwhile vanished; in a sticky folder, another user's file) puts back what was renamed."""
    log = scene_log(tmp_path / "scene.log")
    out = tmp_path / "out"
    first = build(log, "--out", out, "--resolution", "0.1", "--quiet")
    assert first.returncode == 0, first.stderr
    (out / "map.pgm").unlink()
    (out / "map.pgm").mkdir()
    before = {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()}
    refused = build(log, "--out", out, "--quiet")
    assert refused.returncode == 2
    assert refused.stderr == (
        f"fleetmap build: error: cannot write the outputs to {out}: [Errno 21] a folder has the name "
        f"of an output: '{out / 'map.pgm'}'\n"
    )
    assert {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()} == before
    assert sorted(path.name for path in out.iterdir()) == sorted([*before, "map.pgm"])
    # A rename that fails after others were made: map.yaml and map.png had new files, map.pgm's
    # is gone; the earlier map.yaml is back, the new map.png (no earlier one) removed.
    (out / "map.pgm").rmdir()
    (out / "map.png").unlink()
    names = ("map.yaml", "map.png", "map.pgm")
    for name in names:
        (out / f".{name}.partial").write_bytes(b"new")
    (out / ".map.pgm.partial").unlink()
    with pytest.raises(FileNotFoundError):
        export._install([out / name for name in names])
    del before["map.png"]
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before


def waiting_for_a_flock(pid: int) -> bool:
    """Whether a thread of process `pid` waits for a `flock` (a `->` line of /proc/locks)."""
    return any(
        line.split()[1:3] == ["->", "FLOCK"] and line.split()[5] == str(pid)
        for line in Path("/proc/locks").read_text().splitlines()
    )


@pytest.mark.skipif(not Path("/proc/locks").exists(), reason="needs Linux's /proc/locks")
def test_two_builds_into_one_folder_at_once_leave_one_whole_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two builds writing into one folder at once (a `make -j`, a build started again in another
    terminal) wrote the same `.NAME.partial` files: one took the other's files for its own, its
    rename of a file the other had already renamed failed, and the folder was left with map.yaml
    and map.pgm of one map beside meta.json and the arrays of the other, one build saying it had
    written them. Now a build holds the folder while it writes: the second waits for the
    first, and the folder holds the second's whole map."""
    fine, coarse = GridMap(MapConfig(resolution=RES)), GridMap(MapConfig(resolution=2 * RES))
    for gmap in (fine, coarse):
        for scan in load_dataset(scene_log(tmp_path / "scene.log")):
            gmap.integrate(scan)
    out = tmp_path / "out"
    errors: list[BaseException] = []

    def write_coarse() -> None:
        try:
            export.write_build_outputs(coarse, out)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    second = threading.Thread(target=write_coarse)
    real = export._write_build_files

    Write = Callable[[str, bytes | np.ndarray], None]

    def pausing(gmap: GridMap, window: export.Window, write: Write) -> None:
        def write_then_let_the_second_in(name: str, data: bytes | np.ndarray) -> None:
            write(name, data)
            if name == "map.yaml":  # the first build is writing: the second starts, and gets in or waits
                second.start()
                wait_for(lambda: not second.is_alive() or waiting_for_a_flock(os.getpid()), timeout=120,
                         what="the second build done or waiting")  # fmt: skip

        real(gmap, window, write_then_let_the_second_in if gmap is fine else write)

    monkeypatch.setattr(export, "_write_build_files", pausing)
    try:
        export.write_build_outputs(fine, out)
    finally:
        second.join(timeout=120)
    assert not errors, errors
    meta = json.loads((out / "meta.json").read_text())
    assert meta["resolution"] == yaml.safe_load((out / "map.yaml").read_text())["resolution"] == 2 * RES
    assert list(read_pgm(out / "map.pgm").shape) == meta["shape"] == list(np.load(out / "log_odds.npy").shape)
    assert sorted(path.name for path in out.iterdir()) == sorted(export.BUILD_FILES)


def test_a_build_keeps_the_earlier_files_as_copies_where_hard_links_fail(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a file system without hard links (FAT: a USB stick) `_install` keeps the earlier files as
    copies while the new ones take their names, so a rebuild there works and a failed rename still
    puts them back. os.link is made to fail as FAT's does (EPERM) because no FAT file system can
    be mounted here."""

    def no_links(*_: object, **__: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    names = ("map.yaml", "map.png", "map.pgm")
    for name in names:
        (tmp_path / name).write_bytes(b"earlier " + name.encode())
        (tmp_path / f".{name}.partial").write_bytes(b"new")
    export._install([tmp_path / name for name in names])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == dict.fromkeys(names, b"new")
    # The third rename fails: the two files renamed get their earlier contents back from the copies.
    for name in names:
        (tmp_path / name).write_bytes(b"earlier " + name.encode())
        (tmp_path / f".{name}.partial").write_bytes(b"new")
    (tmp_path / ".map.pgm.partial").unlink()
    with pytest.raises(FileNotFoundError):
        export._install([tmp_path / name for name in names])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if not p.name.endswith(".partial")} == {
        name: b"earlier " + name.encode() for name in names
    }
    assert not any(p.name.endswith(".previous") for p in tmp_path.iterdir())


def test_build_reads_the_seed_matlab_convention(tmp_path: Path) -> None:
    """The .mat of the course: robot at (1, 2) in its y-down frame, a 3 m beam at +90 degrees. Its
    end point lies three metres "up" the image, at map point (1, 1) once y points up."""
    path = tmp_path / "course.mat"
    scipy.io.savemat(path, {"ranges": [[3.0]], "scanAngles": [[math.pi / 2]], "pose": [[1.0], [2.0], [0.0]]})
    done = build(path, "--out", tmp_path / "out", "--quiet", "--range-max", "10")
    assert done.returncode == 0, done.stderr
    info = json.loads((tmp_path / "out" / "meta.json").read_text())
    i0, j0 = info["cell_window"][:2]
    lo = np.load(tmp_path / "out" / "log_odds.npy")
    (j,), (i,) = np.nonzero(lo > 0)
    assert (i + i0, j + j0) == (20, 20) and lo[j, i] == pytest.approx(L_HIT)
    # The sensor's cell, (1, -2) in map coordinates, is a miss.
    assert lo[-40 - j0, 20 - i0] == pytest.approx(L_MISS)


def test_build_shows_progress_unless_quiet(tmp_path: Path) -> None:
    log = scene_log(tmp_path / "long.log", scans=300)
    loud = build(log, "--out", tmp_path / "a")
    assert loud.returncode == 0 and "300/300" in loud.stderr and "scan" in loud.stderr
    quiet = build(log, "--out", tmp_path / "b", "--quiet")
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_a_build_of_one_scan_says_scan(tmp_path: Path) -> None:
    """The summary counts as `counted` does: a log of one scan said '1 scans integrated'."""
    done = build(scene_log(tmp_path / "one.log", scans=1), "--out", tmp_path / "out", "--quiet")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("1 scan integrated (0 skipped) in "), done.stdout


def test_build_skips_scans_it_cannot_integrate_and_says_so(tmp_path: Path) -> None:
    """Each scan skipped is named by its place in the log, so that it can be found there: the
    message was 'skipped a scan: ...', which of a log's thousands of scans it did not say."""
    far = flaser([1.0, 2.0], 1e13, 0.0, 0.0)  # beyond the map's cell index range
    done = build(scene_log(tmp_path / "scene.log", extra=(far,)), "--out", tmp_path / "out", "--quiet")
    assert done.returncode == 0, done.stderr
    assert f"{SCANS} scans integrated (1 skipped)" in done.stdout
    assert done.stderr == (
        f"skipped scan {SCANS + 1} of {SCANS + 1}: the scan's pose or ranges lie beyond the map's "
        "coordinate range\n"
    )


def test_a_build_whose_every_scan_is_skipped_says_so(tmp_path: Path) -> None:
    """Every scan skipped (here: each beyond the map's coordinate range): the error says so, not
    only that the map has no observed cell, which read as if the log held no usable reading."""
    far = [flaser([1.0, 2.0], 1e13, 0.0, 0.0) for _ in range(3)]
    log = tmp_path / "far.log"
    log.write_text("\n".join(far) + "\n")
    done = build(log, "--out", tmp_path / "out", "--quiet")
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines()[-1] == (
        "fleetmap build: error: the map has no observed cell: nothing to export"
        " (3 of 3 scans skipped, see above)"
    )
    assert not (tmp_path / "out").exists()


def bad_config(directory: Path) -> Path:
    path = directory / "bad.json"
    path.write_text('{"resolution": 0, "tsdf": {"max_weight": Infinity}}')
    return path


def deep_config(directory: Path) -> Path:
    """A configuration of arrays nested 100,000 deep: json's parser recurses into them."""
    path = directory / "deep.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    return path


def twice_config(directory: Path) -> Path:
    """A configuration holding a key twice: it was read as the last value, silently."""
    path = directory / "twice.json"
    path.write_text('{"resolution": 0.05, "occupancy": {"p_hit": 0.7, "p_hit": 0.9}}')
    return path


@pytest.mark.parametrize(
    ("make_args", "words"),
    [
        (lambda d: [d / "missing.log"], "missing.log"),
        # The option the user gave is named, not the configuration's field.
        (
            lambda d: [scene_log(d / "s.log"), "--resolution", "0"],
            "invalid map configuration: --resolution: Input should be greater than 0.001",
        ),
        (lambda d: [scene_log(d / "s.log"), "--config", d / "nope.json"], "cannot read config"),
        # The file's fields are named with the file, an option given with it as the option.
        (
            lambda d: [scene_log(d / "s.log"), "--config", bad_config(d), "--no-return-range", "-1"],
            "bad.json: Input should be greater than 0.001; --no-return-range: Input should be greater "
            "than or equal to 0; tsdf.max_weight in ",
        ),
        (
            lambda d: [scene_log(d / "s.log"), "--config", twice_config(d)],
            "twice.json: the key 'p_hit' appears twice in an object",
        ),
        # A RecursionError's traceback, exit 1.
        (
            lambda d: [scene_log(d / "s.log"), "--config", deep_config(d)],
            "deep.json: its JSON nests too deeply",
        ),
        (
            lambda d: [scene_log(d / "s.log"), "--range-min", "3", "--range-max", "2"],
            "error: --range-max must be greater than --range-min (3.0)",
        ),
        (lambda d: [scene_log(d / "s.log"), "--range-min", "-1"], "error: --range-min must be finite, >= 0"),
        # Every reading below range_min: no observed cell, nothing to export.
        (lambda d: [scene_log(d / "s.log"), "--range-min", "5"], "no observed cell"),
        # One pose 2,000 km from the others: the sparse map holds it, its dense exports cannot (a
        # uint8 image alone would be 1.4 PiB), which ended in numpy's MemoryError traceback.
        (
            lambda d: [scene_log(d / "s.log", extra=(flaser([1.0, 2.0], 2e6, 2e6, 0.0),))],
            " cells (2.00002e+06 x 2.00002e+06 m at 0.05 m), too many for its images and arrays "
            "(map.pgm alone would be 1,490,1",
        ),
    ],
    ids=[
        "missing-dataset",
        "bad-resolution",
        "missing-config",
        "bad-config",
        "a-key-twice",
        "a-deep-config",
        "inverted-ranges",
        "negative-range-min",
        "nothing-observed",
        "a-far-pose",
    ],  # fmt: skip
)
def test_build_errors_are_clear_and_write_nothing(
    tmp_path: Path, make_args: Callable[[Path], list[str | Path]], words: str
) -> None:
    out = tmp_path / "out"
    done = build(*make_args(tmp_path), "--out", out, "--quiet")
    assert done.returncode == 2, done.stdout
    assert done.stderr.startswith("fleetmap build: error:") and words in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and "pydantic.dev" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1  # one line, every problem in it
    assert not out.exists()


@pytest.mark.parametrize("big_first", [False, True], ids=["grows-later", "grows-at-once"])
def test_a_build_out_of_memory_is_one_clear_line(tmp_path: Path, big_first: bool) -> None:
    """A map whose tiles outgrow the memory the process may have (here a `ulimit -v` of 2 GiB, as
    shared machines set; elsewhere a fine resolution on a small machine) ends the build with one
    line saying so and what to change, exit 2, nothing written: it ended in numpy's traceback
    ('Unable to allocate 2.50 GiB for an array with shape (40, 4096, 4096)'), exit 1. The far
    scan's 900 m beams reach 40 tiles of 4096 cells at once, 2.5 GiB for the occupancy layer
    alone; the near scan's 2 tiles (128 MiB) fit, as does the rest of the command (about 700 MB
    of address space, numba's included). With the far scan first, the kernels' load, which
    integrates the first scan into a throwaway map, ran out of memory and ended in the traceback."""
    resource = pytest.importorskip("resource")  # POSIX: the limit is real, not a simulated failure
    log = tmp_path / "far.log"
    scans = [flaser([1.0] * 180, 0.0, 0.0, 0.0), flaser([900.0] * 180, 0.0, 0.0, 0.0)]
    log.write_text("\n".join(["PARAM robot_front_laser_max 2000 0 h 0", *scans[:: -1 if big_first else 1]]))
    config = tmp_path / "big_tiles.json"
    config.write_text('{"tile_size": 4096, "layers": ["occupancy"]}')
    out = tmp_path / "out"

    def limit_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    done = subprocess.run(
        [*fleetmap_command(), "build", str(log), "--out", str(out), "--config", str(config), "--quiet"],
        capture_output=True, text=True, timeout=300, preexec_fn=limit_memory,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    scan = 1 if big_first else 2
    assert done.stderr.startswith(f"fleetmap build: error: out of memory at scan {scan} of 2, growing")
    assert "tiles of 4096 x 4096 cells" in done.stderr and "coarser --resolution" in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("command", ["build", "replay"])
def test_a_missing_dataset_says_what_to_give_and_where_to_find_one(tmp_path: Path, command: str) -> None:
    """The README's examples name `../shared/datasets/...`, which a fresh clone does not have: the
    error says what the command reads and where the README says to find a log, not a bare errno."""
    missing = "../shared/datasets/intel-corrected.log.gz"
    extra = ["--out", str(tmp_path / "out")] if command == "build" else ["--map", "m", "--robot", "r"]
    done = subprocess.run(
        [*fleetmap_command(), command, missing, *extra, "--quiet"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith(f"fleetmap {command}: error: no such file: {missing} "), done.stderr
    assert "CARMEN" in done.stderr and 'README.md, "Build a map from a recorded dataset"' in done.stderr
    assert "Errno" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    readme = (REPO_DIR / "README.md").read_text(encoding="utf-8")
    section = readme.split("\n## Build a map from a recorded dataset\n", 1)[1].split("\n## ", 1)[0]
    assert "a fresh\nclone has no such folder" in section


def test_the_raycast_benchmark_without_its_dataset_says_what_to_give(tmp_path: Path) -> None:
    """docs/benchmarks.md runs `benchmarks/raycast_speed.py` as it is, which reads the Intel log of
    `../shared/datasets/`: in a fresh clone it ended in a FileNotFoundError traceback. It now says
    what it reads and how to give it, as `bench_engine.py` skips that workload with a note."""
    missing = tmp_path / "intel-corrected.log.gz"
    done = subprocess.run(
        [sys.executable, str(REPO_DIR / "benchmarks" / "raycast_speed.py"), "--dataset", str(missing)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert f"no dataset at {missing}" in done.stderr and "--dataset PATH" in done.stderr, done.stderr


@pytest.mark.parametrize("command", ["build", "replay"])
def test_a_folder_given_as_the_dataset_is_one_clear_line(tmp_path: Path, command: str) -> None:
    """`fleetmap build logs/ --out o` said `fleetmap build: error: [Errno 21] Is a directory: 'logs/'`."""
    logs = tmp_path / "logs"
    logs.mkdir()
    extra = ["--out", str(tmp_path / "out")] if command == "build" else ["--map", "m", "--robot", "r"]
    done = subprocess.run(
        [*fleetmap_command(), command, str(logs), *extra, "--quiet"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr == (
        f"fleetmap {command}: error: cannot read {logs}: Is a directory (give a recorded laser log: "
        "CARMEN, plain or .gz, or .mat)\n"
    )


@pytest.mark.parametrize("where", ["under-a-file", "is-a-file"])
def test_build_to_an_output_path_that_is_not_a_directory_is_a_clear_error(tmp_path: Path, where: str) -> None:
    """An `--out` that cannot be a directory (a file, or a path under one) is refused in one line
    before any scan is integrated; it was found only after the whole build, with a traceback."""
    log = scene_log(tmp_path / "s.log")
    out = log / "out" if where == "under-a-file" else log
    done = build(log, "--out", out, "--quiet")
    assert done.returncode == 2, done.stdout
    assert done.stderr.startswith(f"fleetmap build: error: cannot write the outputs to {out}: "), done.stderr
    assert f"{log} is not a directory" in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert "integrated" not in done.stdout


def test_build_to_an_output_name_too_long_for_the_file_system_is_a_clear_error(tmp_path: Path) -> None:
    """An `--out` whose name the file system cannot hold (a component over 255 bytes, as a name
    made from a configuration can be) is refused in one line before any scan is integrated: looking
    for it raised ENAMETOOLONG, which ended in a traceback, exit 1. (A folder the user may not look
    into, EACCES, raised there too; not tested here, where the tests run as root.)"""
    log = scene_log(tmp_path / "s.log")
    out = tmp_path / ("m" * 300)
    done = build(log, "--out", out, "--quiet")
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr == f"fleetmap build: error: cannot write the outputs to {out}: File name too long\n"
    assert "integrated" not in done.stdout


def test_build_of_the_intel_log_equals_the_library_map(datasets_dir: Path, tmp_path: Path) -> None:
    log = datasets_dir / "intel-corrected.log.gz"
    done = build(log, "--out", tmp_path, "--quiet")
    assert done.returncode == 0, done.stderr
    assert "910 scans integrated (0 skipped)" in done.stdout

    gmap = GridMap(MapConfig())
    for scan in load_dataset(log):
        gmap.integrate(scan)
    info = json.loads((tmp_path / "meta.json").read_text())
    i0, j0, i1, j1 = info["cell_window"]
    b = gmap.known_bounds()
    assert b is not None and (i0, j0, i1, j1) == (b[0] - 2, b[1] - 2, b[2] + 2, b[3] + 2)
    log_odds = np.load(tmp_path / "log_odds.npy")
    np.testing.assert_array_equal(log_odds, gmap.region("log_odds", i0, j0, i1, j1))
    np.testing.assert_array_equal(np.load(tmp_path / "hits.npy"), gmap.region("hits", i0, j0, i1, j1))

    # The nav2 image follows from the log-odds by the thresholds map.yaml states.
    p = 1.0 - 1.0 / (1.0 + np.exp(log_odds.astype(np.float64)))
    want = np.full(log_odds.shape, 205, dtype=np.uint8)
    want[p < 0.196] = 254
    want[p > 0.65] = 0
    np.testing.assert_array_equal(read_pgm(tmp_path / "map.pgm"), want[::-1])
    assert (want == 0).sum() > 10_000 and (want == 254).sum() > 100_000  # a real map, walls and floor
    # map.png the same way, from the float32 probabilities the map gives (unknown as p = 0.5). The
    # images are made a storage tile at a time: this window spans several tiles and ends inside one.
    # 255 (1 - p) is rounded exactly, not in float32 (which drew a cell hit once, 76.500003, as 76).
    reported = np.nan_to_num(p.astype(np.float32), nan=0.5).astype(np.float64)
    gray = np.round(255.0 * (1.0 - reported)).astype(np.uint8)
    with Image.open(tmp_path / "map.png") as image:
        np.testing.assert_array_equal(np.asarray(image), gray[::-1])
    tile = MapConfig().tile_size
    assert log_odds.shape[0] > 2 * tile and log_odds.shape[0] % tile


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["serve", "--data_dir", "x"],
         "fleetmap serve: error: unrecognized arguments: --data_dir x (--data_dir: did you mean "
         "--data-dir?) (see fleetmap serve --help)"),
        (["build", "log", "--out", "o", "--resolutoin", "0.1"],
         "fleetmap build: error: unrecognized arguments: --resolutoin 0.1 (--resolutoin: did you mean "
         "--resolution?)"),
        (["demo", "--htp=127.0.0.1:8001"],
         "fleetmap demo: error: unrecognized arguments: --htp=127.0.0.1:8001 (--htp: did you mean --http?)"),
        (["replay", "log", "--map", "m", "--robot", "r", "--bogus"],
         "fleetmap replay: error: unrecognized arguments: --bogus"),
    ],
)  # fmt: skip
def test_an_unknown_option_is_refused_by_its_command_naming_the_one_meant(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`fleetmap serve --data_dir x` said `fleetmap: error: unrecognized arguments: --data_dir x` under
    the usage `fleetmap [-h] COMMAND ...`: neither the command nor its options. The command's own
    parser refuses it now (`serve`'s in one line), with the option a mistyped one resembles."""
    runs = [cli.main] + ([server.main] if argv[0] == "serve" else [])
    for main in runs:
        with pytest.raises(SystemExit) as stopped:
            main(argv if main is cli.main else argv[1:])
        assert stopped.value.code == 2
        err = capsys.readouterr().err
        assert err.rstrip().splitlines()[-1] == says, err
        assert "usage: fleetmap [-h] COMMAND" not in err and "Traceback" not in err, err


def test_the_command_says_its_version(capsys: pytest.CaptureFixture[str]) -> None:
    """`fleetmap --version` said "the following arguments are required: COMMAND", exit 2: the version
    that runs was in /metrics only. It prints the installed package's version, exit 0."""
    with pytest.raises(SystemExit) as stopped:
        cli.main(["--version"])
    assert stopped.value.code == 0
    assert capsys.readouterr().out == f"fleetmap {importlib.metadata.version('fleetmap')}\n"


@pytest.mark.parametrize("module", ["fleetmap", "fleetmap.cli"])
def test_the_command_run_as_a_module_gives_the_same_clean_error(tmp_path: Path, module: str) -> None:
    # `python -m fleetmap.cli` runs cli.py as `__main__`, a second copy of the module whose
    # CliError the command modules do not raise: it printed a traceback instead of one line.
    done = subprocess.run(
        [sys.executable, "-m", module, "serve", "--http", "127.0.0.1:0", "--data-dir", str(tmp_path / "d"),
         "--config", str(tmp_path / "missing.json")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith("fleetmap serve: error: cannot read config"), done.stderr


_BUILD_AFTER_LOADING_KERNELS = (
    LOADED_KERNELS
    + """
import numpy as np
from fleetmap.cli import _load_kernels
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan

rng = np.random.default_rng(0)
late = {}
for overrides in ({}, {"sensor_model": "beam"}, {"update": "per_ray"}, {"traversal": "bresenham"},
                  {"layers": ["tsdf"]}, {"layers": ["counts"]}, {"no_return_range": 5.0}):
    config = MapConfig(**overrides)
    scans = []
    for k in range(20):  # 3 m apart: new tiles, and tiles already there
        ranges = rng.uniform(0.5, 25.0, 361)
        ranges[::40] = np.inf
        pose = (3.0 * k, 0.5 * k, 0.3 * k)
        scans.append(Scan.from_fan(pose, -1.57, 3.14 / 360, ranges.tolist(), 0.1, 30.0))
    _load_kernels(config, scans[0], quiet=True)
    before = loaded()
    gmap = GridMap(config)
    for scan in scans:
        gmap.integrate(scan)
    new = sorted(k for k, n in loaded().items() if n > before.get(k, 0))
    if new:
        late[str(overrides)] = new
print(late)
"""
)


def test_the_build_loads_its_kernels_before_it_times_the_scans() -> None:
    """The first run after an install compiles the kernels (15-30 s), and the build put that time
    into the rate it printed, without a word (0.3 M cell updates/s where the map took 19). They are
    loaded on a throwaway map first: checked in a fresh interpreter, for each sensor model, update,
    traversal and layer choice, that integrating a dataset loads no kernel the loading left out."""
    out = subprocess.run(
        [sys.executable, "-c", _BUILD_AFTER_LOADING_KERNELS], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "{}", f"kernels loaded only by the timed scans: {out.stdout.strip()}"


def test_the_build_help_says_what_each_option_is_when_not_given(tmp_path: Path) -> None:
    """`--resolution` said "(default 0.05)", but a --config file's resolution is what a build
    without the option uses; --range-min and --range-max said nothing of theirs."""
    config = tmp_path / "config.json"
    config.write_text('{"resolution": 0.1}')
    assert cli.load_config(str(config), resolution=None).resolution == 0.1
    parser = argparse.ArgumentParser(prog="fleetmap")
    sub = parser.add_subparsers()
    cli._add_build(sub)
    build = sub.choices["build"]
    helps = {a.dest: " ".join((a.help or "").split()) for a in build._actions}
    assert "the --config file's" in helps["resolution"]
    assert "default 0.001" in helps["range_min"] and "the log's own" in helps["range_max"]
