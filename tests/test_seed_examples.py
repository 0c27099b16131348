"""The seed examples re-run through the engine, checked against independent computations."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fleetmap.examples import seed002, seed004


def seed_inverse_scanner(x: float, y: float, theta: float, meas_r: np.ndarray) -> np.ndarray:
    """The seed's `inverse_scanner`, vectorised over cells but with its exact formulas and its
    `m = zeros` start: a cell none of the three cases claims keeps 0 (see seed004's docstring)."""
    i, j = np.meshgrid(np.arange(seed004.M), np.arange(seed004.N), indexing="ij")
    r = np.sqrt((i - x) ** 2 + (j - y) ** 2)
    phi = (np.arctan2(j - y, i - x) - theta + math.pi) % (2 * math.pi) - math.pi
    diff = np.abs(phi[..., None] - seed004.MEAS_PHI)
    k = np.argmin(diff, axis=-1)
    zk = meas_r[k]
    dk = np.take_along_axis(diff, k[..., None], axis=-1)[..., 0]
    m = np.zeros((seed004.M, seed004.N))
    no_info = (r > np.minimum(seed004.R_MAX, zk + seed004.ALPHA / 2)) | (dk > seed004.BETA / 2)
    occ = ~no_info & (zk < seed004.R_MAX) & (np.abs(r - zk) < seed004.ALPHA / 2)
    free = ~no_info & ~occ & (r < zk)
    m[no_info] = 0.5
    m[occ] = seed004.P_OCC
    m[free] = seed004.P_FREE
    return m


def seed_belief() -> tuple[np.ndarray, np.ndarray]:
    """The seed's own m_f, and the mask of cells its fall-through case ever pinned to 0."""
    truth = seed004.true_map()
    poses = seed004.trajectory(truth)
    L = np.zeros((seed004.M, seed004.N))
    pinned = np.zeros_like(L, dtype=bool)
    for t in range(1, seed004.T_MAX):
        meas_r = seed004.get_ranges(truth, poses[:, t], seed004.MEAS_PHI, seed004.R_MAX)
        invmod = seed_inverse_scanner(*poses[:, t], meas_r)
        pinned |= invmod == 0
        with np.errstate(divide="ignore"):
            L = np.log(invmod / (1 - invmod)) + L
    return np.exp(L) / (1 + np.exp(L)), pinned


def test_seed004_matches_the_seed_computation() -> None:
    """Every cell's final belief equals the seed's, except cells the seed's fall-through pinned."""
    ours = seed004.run()
    theirs, pinned = seed_belief()
    assert ours.shape == (50, 60)
    np.testing.assert_allclose(ours[~pinned], theirs[~pinned], atol=1e-5)
    # The seed's quirk: pinned cells are exactly 0 there; the engine has real beliefs for them.
    assert np.all(theirs[pinned] == 0)
    # The map is informative: cells believed occupied are obstacles or the map's border (the
    # seed's lidar stops at the border as at a wall), give or take the obstacle thickness alpha.
    from scipy.ndimage import binary_dilation

    walls = seed004.true_map() == 1
    walls[[0, -1], :] = walls[:, [0, -1]] = True
    walls[[1, -2], :] = walls[:, [1, -2]] = True  # the seed's lidar stops at i <= 0 or i >= M - 1
    near_walls = binary_dilation(walls, iterations=1)
    believed = ours > 0.9
    assert believed.sum() > 30
    assert near_walls[believed].mean() > 0.95


def test_seed004_command_writes_the_belief(tmp_path: Path) -> None:
    out = tmp_path / "m_f.npy"
    subprocess.run([sys.executable, "-m", "fleetmap.examples.seed004", "--out", str(out)], check=True)
    saved = np.load(out)
    np.testing.assert_allclose(saved, seed004.run())


def test_seed004_saves_at_the_name_given_or_says_why_not(tmp_path: Path) -> None:
    """`--out` is the file written, whatever its name: np.save of a path without `.npy` added it,
    so `--out DIR` wrote DIR.npy beside the folder and `--out m_f` wrote m_f.npy, each saying
    'saved' the name given; an --out that cannot be written was a traceback after the run."""
    command = [sys.executable, "-m", "fleetmap.examples.seed004", "--out"]
    out = tmp_path / "m_f"
    done = subprocess.run([*command, str(out)], capture_output=True, text=True, check=True)
    assert done.stdout.splitlines()[-1] == f"saved {out}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m_f"]
    np.testing.assert_allclose(np.load(out), seed004.run())
    folder = tmp_path / "folder"
    folder.mkdir()
    for bad, reason in ((folder, "Is a directory"), (tmp_path / "none" / "m.npy", "No such file")):
        failed = subprocess.run([*command, str(bad)], capture_output=True, text=True)
        assert failed.returncode == 2 and failed.stdout == ""
        assert f"error: cannot write --out {bad}: {reason}" in failed.stderr
        assert "Traceback" not in failed.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "m_f"]


def hand_fused(distance: float) -> tuple[float, int]:
    """The seed002 fusion done by hand: mean of (z - d)/t over the measurements whose band holds d."""
    values = [(z - distance) / seed002.TRUNCATION for z in seed002.MEASUREMENTS]
    inside = [v for v in values if abs(v) <= 1.0]
    return sum(inside) / len(inside), len(inside)


def test_seed002_fused_values_and_surface() -> None:
    cells, surface = seed002.run()
    for distance, value, weight in cells:
        expected, count = hand_fused(distance)
        assert weight == count
        assert value == pytest.approx(expected, abs=1e-5)
    # Unclamped linear data: the zero crossing is the mean of the measurements.
    assert surface == pytest.approx(np.mean(seed002.MEASUREMENTS), abs=1e-5)


def test_seed002_prints_surface_last() -> None:
    out = (
        subprocess.run(
            [sys.executable, "-m", "fleetmap.examples.seed002"], check=True, capture_output=True, text=True
        )
        .stdout.strip()
        .splitlines()
    )
    assert len(out) == 6
    assert out[-1].startswith("surface ")
    assert float(out[-1].split()[1]) == pytest.approx(9.98298, abs=1e-5)
