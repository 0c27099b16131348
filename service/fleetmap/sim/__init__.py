"""Simulator: ground-truth floor plans, an exact lidar and simulated robots.

Tests use it for ground truth; the service's demo uses it to drive simulated robots.
"""

import fleetmap.kernels  # noqa: F401  (first: it drops numba's cache when compiled sources changed)

from .floorplan import MIN_DOOR_WIDTH, FloorPlan, FloorPlanError, generate_floorplan
from .lidar import DEFAULT_FOV, DEFAULT_NUM_BEAMS, cast_rays, simulate_scan
from .robot import SimulatedRobot

__all__ = [
    "DEFAULT_FOV",
    "DEFAULT_NUM_BEAMS",
    "MIN_DOOR_WIDTH",
    "FloorPlan",
    "FloorPlanError",
    "SimulatedRobot",
    "cast_rays",
    "generate_floorplan",
    "simulate_scan",
]
