"""Tests of the simulator: exact lidar, floor-plan generator and simulated robot."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from fleetmap.scan import Pose2D
from fleetmap.sim import (
    DEFAULT_NUM_BEAMS,
    MIN_DOOR_WIDTH,
    FloorPlan,
    SimulatedRobot,
    cast_rays,
    generate_floorplan,
    simulate_scan,
)
from fleetmap.sim.floorplan import FloorPlanError, passage_clearance
from fleetmap.sim.lidar import _cast_one

# --------------------------------------------------------------------------------------------------
# Reference ray caster: exact ray/box intersection against every occupied cell, no traversal at all.
# --------------------------------------------------------------------------------------------------


def reference_ranges(
    plan: FloorPlan, x: float, y: float, world_angles: np.ndarray, grow: float = 0.0
) -> np.ndarray:
    """Smallest t >= 0 at which the ray touches a closed occupied cell grown by `grow` metres on every
    side (shrunk if negative), +inf if none. Slab method, vectorised over all occupied cells."""
    j, i = np.nonzero(plan.occupied)
    ox, oy = plan.origin
    res = plan.resolution
    x0, x1 = ox + i * res - grow, ox + (i + 1) * res + grow
    y0, y1 = oy + j * res - grow, oy + (j + 1) * res + grow
    keep = (x0 <= x1) & (y0 <= y1)
    x0, x1, y0, y1 = x0[keep], x1[keep], y0[keep], y1[keep]
    out = np.full(len(world_angles), np.inf)
    for k, a in enumerate(world_angles):
        t_lo = np.zeros(x0.size)
        t_hi = np.full(x0.size, np.inf)
        for p, d, lo, hi in ((x, math.cos(a), x0, x1), (y, math.sin(a), y0, y1)):
            if d == 0.0:
                t_hi = np.where((lo <= p) & (p <= hi), t_hi, -np.inf)
            else:
                with np.errstate(over="ignore"):  # huge t for near-parallel rays: harmless
                    ta, tb = (lo - p) / d, (hi - p) / d
                t_lo = np.maximum(t_lo, np.minimum(ta, tb))
                t_hi = np.minimum(t_hi, np.maximum(ta, tb))
        hit = t_lo <= t_hi
        if hit.any():
            out[k] = t_lo[hit].min()
    return out


def wall_plan() -> FloorPlan:
    """Empty 4 x 6 m grid (x in [-1, 3), y in [-3, 3)) with one 0.2 m wall whose face is at x = 2.0."""
    occ = np.zeros((60, 40), dtype=bool)
    occ[:, 30:32] = True
    return FloorPlan(occ, 0.1, (-1.0, -3.0))


def grid_from_ascii(rows: list[str], resolution: float = 1.0) -> FloorPlan:
    """Plan from a picture: '#' occupied, top line = highest y (flipped into the map's row order)."""
    occ = np.array([[c == "#" for c in row] for row in rows[::-1]], dtype=bool)
    return FloorPlan(occ, resolution, (0.0, 0.0))


# --------------------------------------------------------------------------------------------------
# Lidar
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "x, y, theta",
    [
        (0.0, 0.0, 0.0),
        (1.234, -0.77, 0.3),
        (1.99, 0.5, -0.2),
        (-0.95, 2.1, 0.05),
        (-4.0, 0.3, 0.0),  # outside the grid: rays see nothing until they enter it at x = -1
        (1.0, -2.95, 0.6),
    ],
)
def test_single_wall_exact_range(x: float, y: float, theta: float) -> None:
    plan = wall_plan()
    angle_min, inc = -1.1, 0.01
    scan = simulate_scan(
        plan,
        Pose2D(x, y, theta),
        num_beams=221,
        range_max=30.0,
        range_min=0.0,
        angle_min=angle_min,
        angle_increment=inc,
    )
    world = theta + scan.angles
    hit_y = y + (2.0 - x) * np.tan(world)
    expected = (2.0 - x) / np.cos(world)
    # The ray reaches x = 2 inside the grid only if it has not left through the top or bottom first.
    # (Sensor outside: it must also be inside the grid's y range where it crosses x = -1.)
    entry_y = y + (-1.0 - x) * np.tan(world) if x < -1.0 else np.full_like(world, y)
    toward = np.cos(world) > 0.0
    sees_wall = toward & (np.abs(hit_y) < 2.999) & (np.abs(entry_y) < 2.999)
    assert sees_wall.sum() >= 50
    np.testing.assert_allclose(scan.ranges[sees_wall], expected[sees_wall], rtol=0, atol=1e-9)
    misses = ~toward | (np.abs(hit_y) > 3.001) | (np.abs(entry_y) > 3.001)
    assert np.all(np.isposinf(scan.ranges[misses]))


def test_ray_that_misses_everything_is_inf() -> None:
    plan = wall_plan()
    # Away from the wall: leaves the grid at x = -1 with no hit.
    assert np.all(np.isposinf(cast_rays(plan, 0.0, 0.0, np.array([math.pi, 2.5, -2.5]))))
    # Toward the wall but range_max short of it: no return, not a clipped range.
    r = cast_rays(plan, 0.0, 0.0, np.array([0.0, 0.1]), range_max=1.9)
    assert np.all(np.isposinf(r))
    # A hit at exactly range_max counts as "no return" too; just inside it is a hit.
    assert np.isposinf(cast_rays(plan, 0.0, 0.0, np.array([0.0]), range_max=2.0)[0])
    assert cast_rays(plan, 0.0, 0.0, np.array([0.0]), range_max=2.0 + 1e-9)[0] == pytest.approx(
        2.0, abs=1e-12
    )
    # Outside the grid, pointing away from it.
    assert np.all(np.isposinf(cast_rays(plan, -5.0, 0.0, np.array([math.pi, math.pi / 2]))))
    # An empty grid sees nothing in any direction.
    empty = FloorPlan(np.zeros((10, 10), dtype=bool), 0.5)
    assert np.all(np.isposinf(cast_rays(empty, 2.5, 2.5, np.linspace(-3, 3, 50))))


def test_diagonal_ray_through_corner_joint() -> None:
    # Two cells touching only at their corner (1, 1): a 45 degree ray aimed at the joint must stop
    # there, at distance sqrt(2)/2, not slip through.
    joint = grid_from_ascii(
        [
            "....",
            "....",
            "#...",
            ".#..",
        ]
    )
    r = cast_rays(joint, 0.5, 0.5, np.array([math.pi / 4]))[0]
    assert r == pytest.approx(math.sqrt(0.5), abs=1e-9)

    # One side cell only: just below the diagonal the ray enters it at x = 1; just above it passes
    # the corner and the rest of the diagonal is empty, so it leaves the grid.
    side = grid_from_ascii(["....", "....", "....", ".#.."])
    eps = 1e-9  # the ray passes ~1e-9 m from the vertex: the traversal order must be exact
    below = cast_rays(side, 0.5, 0.5, np.array([math.pi / 4 - eps]))[0]
    assert below == pytest.approx(0.5 / math.cos(math.pi / 4 - eps), abs=1e-9)
    assert np.isposinf(cast_rays(side, 0.5, 0.5, np.array([math.pi / 4 + eps]))[0])
    upper = grid_from_ascii(["....", "....", "#...", "...."])  # the mirror image
    above = cast_rays(upper, 0.5, 0.5, np.array([math.pi / 4 + eps]))[0]
    assert above == pytest.approx(0.5 / math.sin(math.pi / 4 + eps), abs=1e-9)
    assert np.isposinf(cast_rays(upper, 0.5, 0.5, np.array([math.pi / 4 - eps]))[0])

    # Only a cell further along the diagonal, [2, 3) x [2, 3): the ray enters it at its corner (2, 2).
    diag = grid_from_ascii(["....", "..#.", "....", "...."])
    assert cast_rays(diag, 0.5, 0.5, np.array([math.pi / 4]))[0] == pytest.approx(
        1.5 * math.sqrt(2), abs=1e-9
    )


@pytest.mark.parametrize(
    "rows, expect_hit",
    [
        (["....", "....", "....", ".#.."], True),  # only the right-hand side cell
        (["....", "....", "#...", "...."], True),  # only the upper side cell
        (["....", "....", ".#..", "...."], True),  # only the diagonal cell
        (["....", "....", "....", "...."], False),
    ],
)
def test_exact_vertex_tie_touches_all_cells_at_the_vertex(rows: list[str], expect_hit: bool) -> None:
    # dx == dy exactly, so the crossings of x = 1 and y = 1 tie exactly: the kernel's tie branch.
    d = math.sqrt(0.5)
    plan = grid_from_ascii(rows)
    r = _cast_one(plan.occupied, 0.0, 0.0, 1.0, 0.5, 0.5, d, d, 100.0)
    if expect_hit:
        assert r == 0.5 / d
    else:
        assert np.isposinf(r)


def test_sensor_inside_occupied_cell_returns_zero() -> None:
    plan = wall_plan()
    scan = simulate_scan(plan, (2.1, 0.0, 0.0), num_beams=37)
    assert np.all(scan.ranges == 0.0)
    # 0.0 is below range_min, so the engine's sensor models ignore every beam of this scan.
    assert not scan.returns_mask().any()


def test_sensor_outside_grid_sees_first_occupied_cell_at_grid_edge() -> None:
    occ = np.zeros((5, 5), dtype=bool)
    occ[2, 0] = True  # left edge cell, y in [1, 1.5) with res 0.5
    plan = FloorPlan(occ, 0.5, (0.0, 0.0))
    r = cast_rays(plan, -3.0, 1.25, np.array([0.0, math.pi]))
    assert r[0] == pytest.approx(3.0, abs=1e-12)
    assert np.isposinf(r[1])


def test_simulate_scan_fan_and_noise() -> None:
    plan = generate_floorplan(3, 12.0, 9.0)
    pose = Pose2D(*plan.random_free_point(np.random.default_rng(0), 0.5), 0.4)
    scan = simulate_scan(plan, pose)
    assert scan.num_beams == DEFAULT_NUM_BEAMS
    assert scan.angles[0] == pytest.approx(-0.75 * math.pi) and scan.angles[-1] == pytest.approx(
        0.75 * math.pi
    )
    assert np.allclose(np.diff(scan.angles), math.radians(0.25))
    assert scan.range_max == 30.0 and scan.range_min == 0.05
    # Indoors within 30 m every beam hits something, and ranges agree with the reference caster.
    assert np.all(np.isfinite(scan.ranges)) and np.all(scan.ranges > 0.0)
    ref = reference_ranges(plan, pose.x, pose.y, scan.world_angles()[::20])
    np.testing.assert_allclose(scan.ranges[::20], ref, rtol=0, atol=1e-9)

    noisy_a = simulate_scan(plan, pose, noise_std=0.02, rng=np.random.default_rng(7))
    noisy_b = simulate_scan(plan, pose, noise_std=0.02, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(noisy_a.ranges, noisy_b.ranges)
    err = noisy_a.ranges - scan.ranges
    assert 0.015 < float(np.std(err)) < 0.025 and abs(float(np.mean(err))) < 0.005


@pytest.mark.parametrize("num_beams", [2.5, 3.0, "3", np.float64(3.0), True, 0, -1])
def test_simulate_scan_takes_a_whole_number_of_beams(num_beams: object) -> None:
    """num_beams 2.5 made 3 beams spaced for 2.5, the last one 90 degrees past the field of view;
    what is not a whole number >= 1 is refused, naming it."""
    plan = generate_floorplan(3, 12.0, 9.0)
    with pytest.raises(ValueError, match="num_beams must be a whole number >= 1"):
        simulate_scan(plan, (6.0, 4.5, 0.0), num_beams=num_beams)  # type: ignore[arg-type]
    assert simulate_scan(plan, (6.0, 4.5, 0.0), num_beams=np.int64(3)).angles.tolist() == pytest.approx(
        [-0.75 * math.pi, 0.0, 0.75 * math.pi]
    )


def test_simulate_scan_points_a_single_beam_at_the_heading() -> None:
    """The default fan is centred on the heading; one beam was put at its left edge, -135 degrees,
    a range of another wall than the one the sensor faces."""
    plan = generate_floorplan(3, 12.0, 9.0)
    pose = Pose2D(*plan.random_free_point(np.random.default_rng(0), 0.5), 0.4)
    scan = simulate_scan(plan, pose, num_beams=1)
    assert scan.angles.tolist() == [0.0]
    assert scan.ranges.tolist() == cast_rays(plan, pose.x, pose.y, np.array([0.4]), 30.0).tolist()


@st.composite
def ray_problems(draw: st.DrawFn) -> tuple[FloorPlan, float, float, np.ndarray, float]:
    nx, ny = draw(st.integers(1, 8)), draw(st.integers(1, 8))
    occ = np.array(draw(st.lists(st.booleans(), min_size=nx * ny, max_size=nx * ny)), dtype=bool)
    res = draw(st.sampled_from([0.05, 0.1, 0.3, 1.0, 1.7]))
    origin = (draw(st.floats(-3.0, 3.0)), draw(st.floats(-3.0, 3.0)))
    plan = FloorPlan(occ.reshape(ny, nx), res, origin)
    x_lo, y_lo, x_hi, y_hi = plan.world_bounds()
    # Sensor anywhere in or around the grid, so starts outside the grid and inside occupied cells occur.
    x = draw(st.floats(x_lo - 2.0, x_hi + 2.0))
    y = draw(st.floats(y_lo - 2.0, y_hi + 2.0))
    angles = np.array(draw(st.lists(st.floats(-math.pi, math.pi), min_size=1, max_size=16)))
    range_max = draw(st.floats(0.01, 40.0))
    return plan, x, y, angles, range_max


@settings(max_examples=300, deadline=None)
@given(ray_problems())
def test_raycaster_matches_exact_reference(
    problem: tuple[FloorPlan, float, float, np.ndarray, float],
) -> None:
    plan, x, y, angles, range_max = problem
    fast = cast_rays(plan, x, y, angles, range_max)
    # Bracket the exact answer by perturbing every cell boundary by eps: growing the cells can only
    # make hits earlier, shrinking them later. Away from degenerate rays (along a grid line, through
    # a vertex, from a boundary) the bracket is ~eps wide, so this demands the exact range.
    eps = 1e-9
    early = reference_ranges(plan, x, y, angles, grow=eps)
    late = reference_ranges(plan, x, y, angles, grow=-eps)
    tol = 1e-9
    for f, lo, hi in zip(fast, early, late, strict=True):
        if math.isinf(f):
            assert f > 0 and hi >= range_max - tol, (f, lo, hi)
        else:
            assert 0.0 <= f < range_max
            assert lo - tol <= f <= hi + tol, (f, lo, hi)


# --------------------------------------------------------------------------------------------------
# Floor plans
# --------------------------------------------------------------------------------------------------


def test_floorplan_deterministic_per_seed() -> None:
    a, b, c = generate_floorplan(11), generate_floorplan(11), generate_floorplan(12)
    np.testing.assert_array_equal(a.occupied, b.occupied)
    assert a.resolution == 0.05 and a.origin == (0.0, 0.0)
    assert a.occupied.shape == (600, 800) and a.world_bounds() == (0.0, 0.0, 40.0, 30.0)
    assert not np.array_equal(a.occupied, c.occupied)
    with pytest.raises(ValueError):
        a.occupied[0, 0] = False  # the ground truth is read-only


def _free_runs(occ: np.ndarray) -> np.ndarray:
    """Lengths (cells) of every maximal run of free cells along rows and columns that has an occupied
    cell at both ends: the widths of every gap an agent would have to pass."""
    lengths = []
    for grid in (occ, occ.T):
        for row in grid:
            edges = np.flatnonzero(np.diff(row.astype(np.int8)))
            # A free run between two occupied cells starts after a 1->0 edge and ends at a 0->1 edge.
            for start, end in zip(edges[:-1], edges[1:], strict=True):
                if row[start] and not row[start + 1]:
                    lengths.append(end - start)
    return np.array(lengths)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_floorplan_structure_and_reachability(seed: int) -> None:
    plan = generate_floorplan(seed)
    occ = plan.occupied
    res = plan.resolution
    # Closed outer walls, 0.1-0.2 m thick.
    assert occ[0].all() and occ[-1].all() and occ[:, 0].all() and occ[:, -1].all()
    assert occ[:2].all() and not occ[3].all()
    # Interior walls and obstacles exist, but most of the plan is free.
    interior = occ[5:-5, 5:-5]
    assert 0.03 < interior.mean() < 0.2
    # Flood fill from one free point reaches every free cell (4-connected).
    labels, n = ndimage.label(~occ)
    assert n == 1
    start = plan.random_free_point(np.random.default_rng(seed), 0.5)
    i, j = plan.cell_of(*start)
    assert (labels[j, i] == labels[~occ]).all()
    # A 0.3 m robot can reach every room, too.
    assert plan.free_components(0.3) == 1
    # Every gap between two solid cells, along rows and columns, is at least a door wide.
    runs = _free_runs(occ)
    assert runs.size > 100
    assert runs.min() * res >= MIN_DOOR_WIDTH - 1e-9


def test_floorplan_helpers() -> None:
    plan = wall_plan()
    assert plan.is_free(0.0, 0.0) and not plan.is_free(2.05, 0.0)
    assert not plan.is_free(-1.01, 0.0) and not plan.is_free(3.0, 0.0)  # outside the grid
    assert plan.is_free(-1.0, -3.0)  # the lower-left corner belongs to cell [0, 0]
    rng = np.random.default_rng(1)
    for _ in range(200):
        x, y = plan.random_free_point(rng, clearance=0.5)
        # Exact distance to the wall and to the grid's edges, which count as obstacles.
        assert min(2.0 - x, x + 1.0, 3.0 - y, y + 3.0) >= 0.5
        assert plan.clearance_at(x, y) >= 0.5
    # clearance_map is a lower bound on the true distance, and not a loose one.
    assert plan.clearance_at(1.0, 0.0) <= 1.0
    assert plan.clearance_at(1.0, 0.0) >= 1.0 - 2 * plan.resolution
    with pytest.raises(ValueError):
        plan.random_free_point(rng, clearance=10.0)
    with pytest.raises(ValueError):
        generate_floorplan(0, door_width=0.8)


def test_a_robot_too_wide_for_the_doors_is_a_parameter_error() -> None:
    """A robot_radius the doors cannot pass is refused as the parameter it is: a 0.45 m robot (an
    0.9 m wide AMR, under the 1 m door) raised RuntimeError 'generator bug: seed 1 produced a plan
    with unreachable free space'. The bound is the one the guarantee is checked with."""
    with pytest.raises(FloorPlanError, match=r"radius 0.45 m does not fit through a door \(20 cells"):
        generate_floorplan(1, robot_radius=0.45)
    with pytest.raises(FloorPlanError, match="radius 0.3 m does not fit through the narrowest corridor"):
        generate_floorplan(1, door_width=0.9, corridor_width=0.9, resolution=0.1)
    for width in range(1, 8):  # passage_clearance is clearance_map's value in such a passage
        occupied = np.ones((21, 12), dtype=bool)
        occupied[:, 2 : 2 + width] = False
        clearance = FloorPlan(occupied, 0.1).clearance_map[10, 2 : 2 + width].max()
        assert clearance == pytest.approx(max(passage_clearance(width, 0.1), 0.0))
    plan = generate_floorplan(1, robot_radius=0.42)  # 0.429 m of clearance in a door: fits
    assert plan.free_components(0.42) == 1


def test_a_draw_that_misses_the_guarantees_is_made_again_not_a_generator_bug() -> None:
    """On coarse grids a draw of valid parameters often left a pocket of clearance the robot could
    not reach (or a split wall too short for its door), and the generator raised RuntimeError
    'generator bug' (434 parameter sets in 150 s of random search). It draws again from seeds
    derived from the seed: the plan meets its guarantees and is still the same for the same
    arguments."""
    coarse = dict(
        width_m=35.75, height_m=28.81, resolution=0.2, wall_thickness=0.326, door_width=1.415,
        corridor_width=2.258, min_room_size=3.405, max_room_size=8.178, n_obstacles=12, obstacle_gap=0.745,
        robot_radius=0.132,
    )  # fmt: skip
    plan = generate_floorplan(564647, **coarse)
    assert plan.free_components() == 1 and plan.free_components(0.132) == 1
    np.testing.assert_array_equal(plan.occupied, generate_floorplan(564647, **coarse).occupied)


# --------------------------------------------------------------------------------------------------
# Robot
# --------------------------------------------------------------------------------------------------


def _assert_segment_free(plan: FloorPlan, a: Pose2D, b: Pose2D) -> None:
    for s in np.linspace(0.0, 1.0, 9):
        assert plan.is_free(a.x + s * (b.x - a.x), a.y + s * (b.y - a.y)), (a, b)


def test_robot_never_enters_occupied_cells_and_explores() -> None:
    plan = generate_floorplan(5, 20.0, 15.0)
    rng = np.random.default_rng(0)
    for seed in range(3):
        robot = SimulatedRobot(plan, seed, speed=1.5, clearance=0.3)
        prev = robot.pose
        visited = set()
        for _ in range(3000):
            dt = float(rng.uniform(0.02, 0.3))
            pose = robot.step(dt)
            assert plan.clearance_at(pose.x, pose.y) >= 0.3
            _assert_segment_free(plan, prev, pose)
            assert math.hypot(pose.x - prev.x, pose.y - prev.y) <= 1.5 * dt + 1e-9
            visited.add((int(pose.x), int(pose.y)))
            prev = pose
        # It keeps moving at its speed and covers a good part of the plan (~300 m of driving).
        assert robot.odometer >= 0.95 * 1.5 * robot.time
        assert len(visited) > 80


def test_robot_boxed_in_escapes_safely() -> None:
    # Two rooms with no door between them: routes to goals in the other room fail, so the robot falls
    # back to random-heading runs. It must stay in its own room and keep clear of the walls.
    occ = np.zeros((60, 120), dtype=bool)
    occ[:2], occ[-2:], occ[:, :2], occ[:, -2:] = True, True, True, True
    occ[:, 59:61] = True
    plan = FloorPlan(occ, 0.05)
    robot = SimulatedRobot(plan, 3, start=Pose2D(1.0, 1.5, 0.0), clearance=0.25)
    prev = robot.pose
    for _ in range(2000):
        pose = robot.step(0.1)
        assert pose.x < 2.95 and plan.clearance_at(pose.x, pose.y) >= 0.25
        _assert_segment_free(plan, prev, pose)
        prev = pose
    assert robot.odometer > 50.0
    with pytest.raises(ValueError):
        SimulatedRobot(plan, 0, start=Pose2D(0.15, 1.5, 0.0))  # too close to the wall
    for beams in (0, 100_001, 2.5):  # no scan could be made: refused here, not at the first scan
        with pytest.raises(ValueError, match=f"num_beams must be a whole number, 1 to 100000, got {beams}"):
            SimulatedRobot(plan, 0, num_beams=beams)


def test_robot_deterministic_and_scans() -> None:
    plan = generate_floorplan(2, 15.0, 12.0)
    a = SimulatedRobot(plan, 42, noise_std=0.01, num_beams=181)
    b = SimulatedRobot(plan, 42, noise_std=0.01, num_beams=181)
    c = SimulatedRobot(plan, 43, noise_std=0.01, num_beams=181)
    for _ in range(50):
        sa, sb = a.tick(), b.tick()
        assert sa.pose == sb.pose
        np.testing.assert_array_equal(sa.ranges, sb.ranges)
    assert a.time == pytest.approx(5.0)
    assert c.step(5.0) != a.pose
    # Scanning does not change the motion: a robot that never scans follows the same path.
    d = SimulatedRobot(plan, 42, noise_std=0.01, num_beams=181)
    for _ in range(50):
        d.step(0.1)
    assert d.pose == a.pose
    # The scan is taken from the robot's pose and sees the plan.
    scan = a.scan()
    assert scan.pose == a.pose and scan.num_beams == 181
    assert np.isfinite(scan.ranges).all() and (scan.ranges > 0.2).all()
