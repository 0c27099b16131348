"""A simulated robot that wanders a `FloorPlan` and produces lidar scans from its true pose.

The explorer is deliberately simple: pick a random free goal, plan a grid route to it (breadth-first
search over the cells where the robot fits), drive along the route at constant speed, repeat. If no
route is found (e.g. a hand-made plan with unreachable pockets) it picks a random heading with the
longest clear run and drives that way instead.

Safety does not depend on the planner: every sub-step of motion is checked against the plan's
`clearance_map`, and a sub-step that would bring the robot closer than `clearance` to an obstacle is
refused. Sub-steps are at most half the clearance long, so the straight segment between two accepted
positions stays more than `clearance/2` from every obstacle: the robot never enters an occupied cell.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit

from fleetmap.cell_queries import is_whole_number
from fleetmap.scan import MAX_BEAMS, Pose2D, Scan

from .floorplan import FloorPlan
from .lidar import DEFAULT_FOV, DEFAULT_NUM_BEAMS, simulate_scan

# Per plan and clearance, the cells the robot's centre may occupy. Shared by all robots on one plan,
# since load tests run many robots on the same plan and the mask is as large as the grid.
_PASSABLE: weakref.WeakKeyDictionary[FloorPlan, dict[float, np.ndarray]] = weakref.WeakKeyDictionary()


def _passable(plan: FloorPlan, clearance: float) -> np.ndarray:
    by_clearance = _PASSABLE.setdefault(plan, {})
    mask = by_clearance.get(clearance)
    if mask is None:
        mask = np.ascontiguousarray(plan.clearance_map >= clearance)
        mask.setflags(write=False)
        by_clearance[clearance] = mask
    return mask


@njit(cache=True, nogil=True)
def _bfs_path(passable: np.ndarray, si: int, sj: int, gi: int, gj: int) -> np.ndarray:
    """Cells (i, j) of a shortest 8-connected route from (si, sj) to (gi, gj) through `passable`,
    both ends included; shape (0, 2) if there is none. Diagonal moves need both orthogonal
    neighbours passable, so the straight segment between consecutive cell centres stays inside
    passable cells."""
    ny, nx = passable.shape
    parent = np.full(ny * nx, -1, dtype=np.int64)
    queue = np.empty(ny * nx, dtype=np.int64)
    start = sj * nx + si
    goal = gj * nx + gi
    parent[start] = start
    queue[0] = start
    head = 0
    tail = 1
    found = start == goal
    while head < tail and not found:
        cur = queue[head]
        head += 1
        cj = cur // nx
        ci = cur - cj * nx
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                i = ci + di
                j = cj + dj
                if (di == 0 and dj == 0) or i < 0 or i >= nx or j < 0 or j >= ny:
                    continue
                if not passable[j, i]:
                    continue
                if di != 0 and dj != 0 and not (passable[cj, i] and passable[j, ci]):
                    continue
                k = j * nx + i
                if parent[k] >= 0:
                    continue
                parent[k] = cur
                if k == goal:
                    found = True
                queue[tail] = k
                tail += 1
    if not found:
        return np.empty((0, 2), dtype=np.int64)
    length = 1
    k = goal
    while k != start:
        k = parent[k]
        length += 1
    path = np.empty((length, 2), dtype=np.int64)
    k = goal
    for n in range(length - 1, -1, -1):
        path[n, 0] = k % nx
        path[n, 1] = k // nx
        k = parent[k]
    return path


def _wrap(angle: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class SimulatedRobot:
    """A disc robot driving around `plan` at `speed` m/s, scanning at `scan_rate` Hz.

    Contract:

    * The robot's centre always stays where `plan.clearance_map >= clearance`, so its true distance
      to every occupied cell is at least `clearance` at every reported pose, and more than
      `clearance/2` in between. It never enters an occupied cell.
    * Motion and noise come from `seed` only: two robots built with the same arguments produce the same
      poses and scans for the same sequence of calls. Scanning does not change the motion.
    * `step(dt)` moves at most `speed * dt` metres along the current route (less only when the robot
      is boxed in) and turns the heading toward the direction of travel at up to `turn_rate` rad/s.
      The lidar sits at the robot's centre, looking along its heading.

    Raises ValueError for bad parameters or a `start` without `clearance` to the nearest obstacle.
    """

    def __init__(
        self,
        plan: FloorPlan,
        seed: int,
        *,
        speed: float = 1.0,
        scan_rate: float = 10.0,
        clearance: float = 0.3,
        turn_rate: float = 2.0,
        start: Pose2D | None = None,
        num_beams: int = DEFAULT_NUM_BEAMS,
        fov: float = DEFAULT_FOV,
        range_max: float = 30.0,
        range_min: float = 0.05,
        noise_std: float = 0.0,
    ) -> None:
        if not (math.isfinite(speed) and speed >= 0.0):
            raise ValueError(f"speed must be finite and >= 0, got {speed}")
        if not (math.isfinite(scan_rate) and scan_rate > 0.0):
            raise ValueError(f"scan_rate must be finite and > 0, got {scan_rate}")
        if not (math.isfinite(clearance) and clearance > 0.0):
            raise ValueError(f"clearance must be finite and > 0, got {clearance}")
        if not (math.isfinite(turn_rate) and turn_rate > 0.0):
            raise ValueError(f"turn_rate must be finite and > 0, got {turn_rate}")
        # Else the first scan fails, in the caller's loop (`simulate_scan` takes a whole number).
        if not is_whole_number(num_beams) or not 1 <= num_beams <= MAX_BEAMS:
            raise ValueError(f"num_beams must be a whole number, 1 to {MAX_BEAMS}, got {num_beams!r}")
        self.plan = plan
        self.speed = float(speed)
        self.scan_rate = float(scan_rate)
        self.clearance = float(clearance)
        self.turn_rate = float(turn_rate)
        self.num_beams = num_beams
        self.fov = fov
        self.range_max = range_max
        self.range_min = range_min
        self.noise_std = noise_std
        motion_seq, noise_seq = np.random.SeedSequence(seed).spawn(2)
        self._rng = np.random.default_rng(motion_seq)
        self._noise_rng = np.random.default_rng(noise_seq)
        self._passable = _passable(plan, self.clearance)
        # Half the clearance keeps the segment between accepted positions clear (see module doc);
        # one cell keeps the heading smooth along routes.
        self._max_substep = min(0.5 * self.clearance, plan.resolution)
        self._lookahead = max(1, round(0.5 / plan.resolution))  # route cells ahead the sensor faces

        if start is None:
            x, y = plan.random_free_point(self._rng, self.clearance)
            theta = float(self._rng.uniform(-math.pi, math.pi))
        else:
            x, y, theta = float(start.x), float(start.y), float(start.theta)
            if plan.clearance_at(x, y) < self.clearance:
                raise ValueError(f"start ({x}, {y}) is closer than {self.clearance} m to an obstacle")
        self._x, self._y, self._theta = x, y, _wrap(theta)
        self._route: list[tuple[float, float]] = []
        self._next = 0  # index into _route of the point being driven to
        self.time = 0.0
        self.odometer = 0.0  # metres driven

    @property
    def pose(self) -> Pose2D:
        """Current true pose (sensor pose) in the map frame."""
        return Pose2D(self._x, self._y, self._theta)

    @property
    def scan_period(self) -> float:
        return 1.0 / self.scan_rate

    def step(self, dt: float) -> Pose2D:
        """Advance the simulation by `dt` seconds (>= 0) and return the new pose."""
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"dt must be finite and >= 0, got {dt}")
        remaining = self.speed * dt
        refusals = 0
        # Bounded loop: routes are finite and refusals are capped, but never spin forever on a bug.
        for _ in range(100_000):
            if remaining <= 1e-12 or refusals > 8:
                break
            if self._next >= len(self._route):
                self._new_route()
                if not self._route:
                    refusals += 1
                    continue
            tx, ty = self._route[self._next]
            dist = math.hypot(tx - self._x, ty - self._y)
            if dist <= 1e-12:
                self._next += 1
                continue
            move = min(remaining, dist, self._max_substep)
            nx_ = self._x + (tx - self._x) * (move / dist)
            ny_ = self._y + (ty - self._y) * (move / dist)
            if self.plan.clearance_at(nx_, ny_) < self.clearance:
                # Not expected on a planned route; possible on an escape run or a changed plan.
                refusals += 1
                self._escape()
                continue
            self._x, self._y = nx_, ny_
            remaining -= move
            self.odometer += move
            if move >= dist:
                self._next += 1
        self._turn(dt)
        self.time += dt
        return self.pose

    def scan(self) -> Scan:
        """A lidar scan from the current pose (noise drawn from the robot's own noise stream)."""
        return simulate_scan(
            self.plan,
            self.pose,
            num_beams=self.num_beams,
            fov=self.fov,
            range_max=self.range_max,
            range_min=self.range_min,
            noise_std=self.noise_std,
            rng=self._noise_rng,
        )

    def tick(self) -> Scan:
        """Advance by one scan period and return the scan taken there."""
        self.step(self.scan_period)
        return self.scan()

    # --- internals ------------------------------------------------------------------------------

    def _new_route(self) -> None:
        """Route to a random reachable goal; an escape run if a few goals are all unreachable."""
        cell = self.plan.cell_of(self._x, self._y)
        if cell is not None:
            res = self.plan.resolution
            ox, oy = self.plan.origin
            for _ in range(5):
                gx, gy = self.plan.random_free_point(self._rng, self.clearance)
                goal = self.plan.cell_of(gx, gy)
                if goal is None:
                    continue
                cells = _bfs_path(self._passable, cell[0], cell[1], goal[0], goal[1])
                if cells.shape[0] >= 2:
                    self._route = [(ox + (i + 0.5) * res, oy + (j + 0.5) * res) for i, j in cells.tolist()]
                    self._next = 0
                    return
        self._escape()

    def _escape(self) -> None:
        """Replace the route by a straight run along the random heading with the longest clear run
        (up to 2 m); an empty route if every sampled heading is blocked at once."""
        best_len, best = 0.0, (self._x, self._y)
        step = self._max_substep
        for heading in self._rng.uniform(-math.pi, math.pi, size=16):
            c, s = math.cos(heading), math.sin(heading)
            run = 0.0
            while (
                run + step <= 2.0
                and self.plan.clearance_at(self._x + (run + step) * c, self._y + (run + step) * s)
                >= self.clearance
            ):
                run += step
            if run > best_len:
                best_len, best = run, (self._x + run * c, self._y + run * s)
        self._route = [best] if best_len > 0.0 else []
        self._next = 0

    def _turn(self, dt: float) -> None:
        """Turn the heading toward a point a little ahead on the route, at most turn_rate * dt."""
        if self._next >= len(self._route):
            return
        tx, ty = self._route[min(self._next + self._lookahead, len(self._route) - 1)]
        if math.hypot(tx - self._x, ty - self._y) < 1e-9:
            return
        error = _wrap(math.atan2(ty - self._y, tx - self._x) - self._theta)
        limit = self.turn_rate * dt
        self._theta = _wrap(self._theta + max(-limit, min(limit, error)))


__all__ = ["SimulatedRobot"]
