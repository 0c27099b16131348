"""The seed's occupancy grid simulation, with this engine's `beam` sensor model doing the mapping.

The seed (a robotics course notebook) moves a robot on a 50 x 60 grid with a few rectangular
obstacles for T_MAX = 150 steps from (30, 30, 0): each step it tries the current motion command
(cycling through (0, 3), (-3, 0), (0, -3), (3, 0) from the second one on), stays put and switches
to the next command when the move would leave the map or enter an obstacle, and turns its sensor
by 0.3 rad. Its lidar has beams at `arange(-0.4, 0.4, 0.05)`, r_max 30, and casts rays by unit
steps, rounding to the nearest cell. Each step after the first is integrated with the inverse range
sensor model (alpha 1, beta 0.05, p_occ 0.7, p_free 0.3, prior 0.5) into a log-odds grid.

The simulation is reproduced here as the seed wrote it; the mapping is the engine's: a map at
resolution 1 with `sensor_model: beam`, l_hit = logit(0.7), l_miss = logit(0.3), no clamping that
matters (+-1e6), and no-return beams clearing to r_max (the seed treats a beam with no hit as a
measurement of r_max: free up to it, never occupied). The seed evaluates cell (i, j) at the point
(i, j), the engine at the cell centre (i + 0.5, j + 0.5), so the sensor pose is shifted by half a
cell. The output `m_f[i, j]` is the final belief of cell (i, j), indexed as in the seed.

One difference, on purpose: the seed leaves a cell at 0 (not 0.5) when none of its three cases
applies, which happens only for a cell exactly at r = r_max in a beam with no return; log(0) then
pins that cell to probability 0 forever. The engine treats such a cell as "no information".
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from fleetmap.config import BeamModelParams, MapConfig, OccupancyParams
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan

M, N = 50, 60
T_MAX = 150
START = (30.0, 30.0, 0.0)
MOTIONS = np.array([[3, 0, -3, 0], [0, 3, 0, -3]])
FIRST_MOTION = 1
TURN = 0.3
MEAS_PHI = np.arange(-0.4, 0.4, 0.05)
R_MAX = 30
ALPHA = 1.0
BETA = 0.05
P_OCC, P_FREE = 0.7, 0.3


def true_map() -> np.ndarray:
    """The seed's ground truth, indexed [i, j] (i along x)."""
    m = np.zeros((M, N))
    m[0:10, 0:10] = 1
    m[30:35, 40:45] = 1
    m[3:6, 40:60] = 1
    m[20:30, 25:29] = 1
    m[40:50, 5:25] = 1
    return m


def get_ranges(truth: np.ndarray, pose: np.ndarray, meas_phi: np.ndarray, rmax: int) -> np.ndarray:
    """The seed's lidar: unit steps along each beam, rounding to the nearest cell; leaving the map or
    meeting an obstacle ends the beam at that step's range; no hit within r_max gives r_max."""
    x, y, theta = pose
    meas_r = rmax * np.ones(meas_phi.shape)
    for k in range(len(meas_phi)):
        for r in range(1, rmax + 1):
            xi = int(round(x + r * math.cos(theta + meas_phi[k])))
            yi = int(round(y + r * math.sin(theta + meas_phi[k])))
            if xi <= 0 or xi >= M - 1 or yi <= 0 or yi >= N - 1:
                meas_r[k] = r
                break
            if truth[xi, yi] == 1:
                meas_r[k] = r
                break
    return meas_r


def trajectory(truth: np.ndarray) -> np.ndarray:
    """The seed's poses, shape (3, T_MAX)."""
    x = np.zeros((3, T_MAX))
    x[:, 0] = START
    u_i = FIRST_MOTION
    for t in range(1, T_MAX):
        move = x[0:2, t - 1] + MOTIONS[:, u_i]
        if (
            move[0] >= M - 1
            or move[1] >= N - 1
            or move[0] <= 0
            or move[1] <= 0
            or truth[int(round(move[0])), int(round(move[1]))] == 1
        ):
            x[:, t] = x[:, t - 1]
            u_i = (u_i + 1) % 4
        else:
            x[0:2, t] = move
        x[2, t] = (x[2, t - 1] + TURN) % (2 * math.pi)
    return x


def engine_config() -> MapConfig:
    return MapConfig(
        resolution=1.0,
        layers=["occupancy"],
        sensor_model="beam",
        beam=BeamModelParams(alpha=ALPHA, beta=BETA),
        occupancy=OccupancyParams(p_hit=P_OCC, p_miss=P_FREE, l_min=-1e6, l_max=1e6),
        no_return_range=float(R_MAX),
    )


def run() -> np.ndarray:
    """The final belief m_f, shape (M, N), indexed [i, j]."""
    truth = true_map()
    poses = trajectory(truth)
    gmap = GridMap(engine_config())
    for t in range(1, T_MAX):  # the seed integrates every step after the initial one
        x, y, theta = poses[:, t]
        meas_r = get_ranges(truth, poses[:, t], MEAS_PHI, R_MAX)
        # Half a cell shift: the seed's point (i, j) is the engine's centre of cell (i, j).
        scan = Scan.from_angles((x + 0.5, y + 0.5, theta), MEAS_PHI, meas_r, 0.0, float(R_MAX))
        gmap.integrate(scan)
    p = gmap.region("probability", 0, 0, M, N)  # (N, M), [j, i]
    return np.nan_to_num(p, nan=0.5).T.astype(np.float64)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="the .npy file to save m_f in")
    args = parser.parse_args(argv)
    # The file is opened first, so that an --out that cannot be written is one line, not a traceback
    # after the run; and written through its handle, at the name given: np.save of a path adds
    # ".npy" to a name without it, so `--out /tmp` wrote /tmp.npy and `--out m_f` m_f.npy, and the
    # command said "saved /tmp", "saved m_f".
    try:
        with open(args.out, "wb") as file:
            m_f = run()
            np.save(file, m_f)
    except OSError as exc:
        parser.error(f"cannot write --out {args.out}: {exc.strerror}")
    for i, j in ((40, 10), (30, 40), (35, 40), (0, 50), (10, 5), (20, 15), (25, 50)):
        print(f"m_f[{i}, {j}] = {m_f[i, j]:.6f}")
    print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
