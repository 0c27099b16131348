"""Ground-truth floor plans for the simulator: a boolean occupancy grid plus a synthetic generator.

A `FloorPlan` uses the same cell convention as the maps the engine builds: element ``[j, i]`` of
`occupied` covers ``x in [ox + i*res, ox + (i+1)*res)`` and ``y in [oy + j*res, oy + (j+1)*res)``,
so row 0 is the LOWEST y. Everything outside the grid is unknown to the plan: `is_free` says False
there and the lidar sees nothing there.

`generate_floorplan` builds indoor-looking plans (outer walls, corridors, rooms split by walls with
doors, furniture and pillars) that are deterministic per seed and whose free space is one connected
region, also for a disc-shaped robot of a given radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy import ndimage

#: Doors narrower than this would not let a typical indoor robot through.
MIN_DOOR_WIDTH = 0.9

_SIDES = ("left", "right", "bottom", "top")


class FloorPlanError(ValueError):
    """Invalid floor plan or generator parameters. The message says what is wrong."""


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """A ground-truth occupancy grid: `occupied[j, i]` is True where cell (i, j) is solid.

    `occupied` has shape (ny, nx), row 0 at the lowest y; `resolution` is the cell edge in metres and
    `origin` the (x, y) of the lower-left corner of cell [0, 0]. The array is stored read-only so a plan
    can be shared by many simulated robots and lidars without anyone changing the ground truth.
    """

    occupied: np.ndarray
    resolution: float
    origin: tuple[float, float] = field(default=(0.0, 0.0))

    def __post_init__(self) -> None:
        occ = np.array(self.occupied, dtype=np.bool_, copy=True, order="C")
        if occ.ndim != 2 or occ.shape[0] == 0 or occ.shape[1] == 0:
            raise FloorPlanError(f"occupied must be a non-empty 2D array, got shape {occ.shape}")
        occ.setflags(write=False)
        object.__setattr__(self, "occupied", occ)
        res = float(self.resolution)
        if not (math.isfinite(res) and res > 0.0):
            raise FloorPlanError(f"resolution must be finite and > 0, got {self.resolution}")
        object.__setattr__(self, "resolution", res)
        ox, oy = (float(v) for v in self.origin)
        if not (math.isfinite(ox) and math.isfinite(oy)):
            raise FloorPlanError(f"origin must be finite, got {self.origin}")
        object.__setattr__(self, "origin", (ox, oy))

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) of the grid."""
        return self.occupied.shape

    def world_bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the area the grid covers, in metres."""
        ny, nx = self.occupied.shape
        ox, oy = self.origin
        return ox, oy, ox + nx * self.resolution, oy + ny * self.resolution

    def cell_of(self, x: float, y: float) -> tuple[int, int] | None:
        """Index (i, j) of the cell containing (x, y), or None outside the grid (or for NaN)."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return None
        ox, oy = self.origin
        i = math.floor((x - ox) / self.resolution)
        j = math.floor((y - oy) / self.resolution)
        ny, nx = self.occupied.shape
        if 0 <= i < nx and 0 <= j < ny:
            return i, j
        return None

    def is_free(self, x: float, y: float) -> bool:
        """True iff (x, y) is inside the grid and its cell is not occupied."""
        cell = self.cell_of(x, y)
        return cell is not None and not bool(self.occupied[cell[1], cell[0]])

    @cached_property
    def clearance_map(self) -> np.ndarray:
        """Per cell, a lower bound (metres) on the distance from ANY point of the cell to the nearest
        occupied cell or to the outside of the grid; 0 for occupied cells. Read-only, computed once.

        The Euclidean distance transform gives centre-to-centre distances D; a point of this cell is
        within res/sqrt(2) of its centre and an occupied cell extends res/sqrt(2) from its own, hence
        the bound D - sqrt(2)*res. Conservative by at most ~1.4 cells, which is what lets the robot
        check a single cell instead of a disc of cells.
        """
        # Pad with solid cells so the grid's edge counts as an obstacle: robots must stay inside.
        padded = np.pad(self.occupied, 1, mode="constant", constant_values=True)
        centre_dist = ndimage.distance_transform_edt(~padded)[1:-1, 1:-1] * self.resolution
        bound = np.maximum(centre_dist - math.sqrt(2.0) * self.resolution, 0.0)
        bound[self.occupied] = 0.0
        bound.setflags(write=False)
        return bound

    def clearance_at(self, x: float, y: float) -> float:
        """Lower bound on the distance from (x, y) to the nearest obstacle (see `clearance_map`);
        0.0 outside the grid or inside an occupied cell."""
        cell = self.cell_of(x, y)
        if cell is None:
            return 0.0
        return float(self.clearance_map[cell[1], cell[0]])

    def random_free_point(self, rng: np.random.Generator, clearance: float = 0.0) -> tuple[float, float]:
        """A random point whose cell is free and at least `clearance` metres (by `clearance_map`'s
        lower bound) from every obstacle: a uniformly chosen qualifying cell, uniformly inside it.

        Raises FloorPlanError if no cell qualifies.
        """
        mask = ~self.occupied if clearance <= 0.0 else self.clearance_map >= clearance
        candidates = np.flatnonzero(mask)
        if candidates.size == 0:
            raise FloorPlanError(f"no free cell with clearance >= {clearance} m")
        j, i = np.unravel_index(candidates[rng.integers(candidates.size)], mask.shape)
        u, v = rng.random(2)
        ox, oy = self.origin
        return ox + (int(i) + u) * self.resolution, oy + (int(j) + v) * self.resolution

    def free_components(self, clearance: float = 0.0) -> int:
        """Number of 4-connected regions of free cells (with `clearance_map >= clearance` if > 0)."""
        mask = ~self.occupied if clearance <= 0.0 else self.clearance_map >= clearance
        return int(ndimage.label(mask)[1])


# --------------------------------------------------------------------------------------------------
# Generator. All layout happens in integer cell units so walls, doors and junctions line up exactly.
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Rect:
    """Free rectangle [x0, x1) x [y0, y1) in cells, with door intervals already cut in its sides."""

    x0: int
    x1: int
    y0: int
    y1: int
    doors: dict[str, tuple[tuple[int, int], ...]]
    corridor_sides: frozenset[str]


@dataclass(frozen=True)
class _Layout:
    """Cell-unit generator parameters, derived once from the metric ones."""

    tw: int  # wall thickness
    dw_min: int  # door width range
    dw_max: int
    margin: int  # gap between a door and any wall meeting the wall it is in
    min_room: int
    max_room: int


def generate_floorplan(
    seed: int,
    width_m: float = 40.0,
    height_m: float = 30.0,
    resolution: float = 0.05,
    *,
    wall_thickness: float = 0.15,
    door_width: float = 1.0,
    corridor_width: float = 2.0,
    min_room_size: float = 3.0,
    max_room_size: float = 9.0,
    n_obstacles: int = 12,
    obstacle_gap: float = 1.0,
    robot_radius: float = 0.3,
    origin: tuple[float, float] = (0.0, 0.0),
) -> FloorPlan:
    """A synthetic indoor floor plan, identical for identical arguments.

    Layout: solid outer walls; 0-2 corridors each way crossing the whole plan (fewer on small plans);
    the blocks between corridors split recursively into rooms of `min_room_size`..`max_room_size`
    metres by walls of `wall_thickness`, every split wall with a door of `door_width`..1.2x metres,
    every block with at least one door onto each corridor it borders; then up to `n_obstacles`
    rectangles (furniture, 0.4-1.6 m) and discs (pillars, r 0.15-0.4 m) inside rooms, each at least
    `obstacle_gap` metres from anything solid.

    Guarantees (checked by a flood fill before returning): the free cells form one 4-connected
    region, and so do the cells with `clearance_map >= robot_radius`, so a disc robot of that radius
    can reach every room. A draw that misses them is made again from seeds derived from `seed`, at
    most `PLAN_ATTEMPTS` draws in all. Raises `FloorPlanError` for parameters it cannot meet that
    for, such as a robot too wide for the doors or corridors (`passage_clearance`), or when no draw
    met it.
    """
    if not (door_width >= MIN_DOOR_WIDTH):
        raise FloorPlanError(f"door_width must be >= {MIN_DOOR_WIDTH} m, got {door_width}")
    if not (math.isfinite(resolution) and 0.0 < resolution <= door_width / 4):
        raise FloorPlanError(f"resolution must be in (0, door_width/4], got {resolution}")
    if not (0.0 < wall_thickness <= 1.0):
        # Walls are at least one cell thick whatever this says, so coarse grids still get walls.
        raise FloorPlanError(f"wall_thickness must be in (0, 1 m], got {wall_thickness}")
    if not (corridor_width >= door_width and min_room_size >= door_width + 1.0):
        raise FloorPlanError("corridors must be at least a door wide, rooms a door plus 1 m")
    if not (max_room_size >= min_room_size):
        raise FloorPlanError("max_room_size must be >= min_room_size")
    if not (obstacle_gap >= 2.0 * robot_radius + 2.0 * resolution):
        # Closer obstacles could leave gaps the robot of `robot_radius` cannot pass.
        raise FloorPlanError("obstacle_gap must be at least the robot's diameter plus two cells")
    if n_obstacles < 0:
        raise FloorPlanError("n_obstacles must be >= 0")
    lay = _Layout(
        tw=max(1, round(wall_thickness / resolution)),
        dw_min=math.ceil(door_width / resolution - 1e-9),
        dw_max=math.ceil(1.2 * door_width / resolution - 1e-9),
        margin=max(2, round(0.25 / resolution)),
        min_room=math.ceil(min_room_size / resolution),
        max_room=math.ceil(max_room_size / resolution),
    )
    cw = max(1, round(corridor_width / resolution))
    # The robot must fit through the narrowest passage, by the bound the guarantee is checked with:
    # a robot too wide for the doors failed that check, as "generator bug: ... unreachable free space".
    narrowest, passage = min((lay.dw_min, "a door"), (int(cw * _CORRIDOR_SCALE[0]), "the narrowest corridor"))
    if passage_clearance(narrowest, resolution) < robot_radius:
        raise FloorPlanError(
            f"a robot of radius {robot_radius:g} m does not fit through {passage} ({narrowest} cells "
            f"of {resolution:g} m, where clearance_map keeps "
            f"{max(passage_clearance(narrowest, resolution), 0.0):.3g} m): give a smaller robot_radius, "
            "a wider door_width or corridor_width, or a finer resolution"
        )
    nx, ny = round(width_m / resolution), round(height_m / resolution)
    if min(nx, ny) < lay.min_room + 2 * lay.tw:
        raise FloorPlanError(f"a {width_m} x {height_m} m plan cannot hold one {min_room_size} m room")

    # A draw may leave a pocket of clearance the robot cannot reach, or a split wall too short for
    # its door, mostly on coarse grids (0.2 m cells: about one parameter set in three): the draw is
    # made again from seeds derived from `seed`, so the plan is still the same for the same
    # arguments, and the first draw's plan is the one it always was.
    for attempt in range(PLAN_ATTEMPTS):
        rng = np.random.default_rng(seed if attempt == 0 else [seed, attempt])
        try:
            plan = _draw_plan(
                rng, nx, ny, cw, lay, width_m, height_m, n_obstacles, obstacle_gap, resolution, origin
            )
        except _DrawFailed:
            continue
        if plan.free_components() == 1 and plan.free_components(robot_radius) == 1:
            return plan
    raise FloorPlanError(
        f"no floor plan of seed {seed} in {PLAN_ATTEMPTS} draws has all its free space reachable by a "
        f"robot of radius {robot_radius:g} m: give a finer resolution, a smaller robot_radius or wider "
        "doors"
    )


#: Draws `generate_floorplan` makes before it gives up on its parameters.
PLAN_ATTEMPTS = 20


class _DrawFailed(Exception):
    """A draw of `_draw_plan` that cannot be completed (a split wall too short for its door)."""


def _draw_plan(
    rng: np.random.Generator, nx: int, ny: int, cw: int, lay: _Layout, width_m: float, height_m: float,
    n_obstacles: int, obstacle_gap: float, resolution: float, origin: tuple[float, float],
) -> FloorPlan:  # fmt: skip
    """One draw of `generate_floorplan`'s plan from `rng`, its reachability not yet checked."""
    occ = np.ones((ny, nx), dtype=np.bool_)  # carve free space out of solid: walls are what is left
    xs_blocks, xs_corr = _split_axis(rng, lay.tw, nx - lay.tw, cw, lay, int(width_m // 15))
    ys_blocks, ys_corr = _split_axis(rng, lay.tw, ny - lay.tw, cw, lay, int(height_m // 16))
    for c0, c1 in xs_corr:
        occ[lay.tw : ny - lay.tw, c0:c1] = False
    for r0, r1 in ys_corr:
        occ[r0:r1, lay.tw : nx - lay.tw] = False

    leaves: list[_Rect] = []
    for bi, (x0, x1) in enumerate(xs_blocks):
        for bj, (y0, y1) in enumerate(ys_blocks):
            corridor_sides = frozenset(
                side
                for side, has in (
                    ("left", bi > 0),
                    ("right", bi < len(xs_corr)),
                    ("bottom", bj > 0),
                    ("top", bj < len(ys_corr)),
                )
                if has
            )
            doors: dict[str, tuple[tuple[int, int], ...]] = {s: () for s in _SIDES}
            block = _Rect(x0, x1, y0, y1, doors, corridor_sides)
            # One door onto every bordering corridor before splitting, so the block is reachable;
            # the splits then keep clear of these doors.
            for side in sorted(corridor_sides):
                block = _add_side_door(rng, occ, block, side, lay)
            _split_rooms(rng, occ, block, lay, leaves)

    # More doors from rooms onto corridors, for realism: most corridor-side rooms get their own.
    for k, leaf in enumerate(leaves):
        for side in sorted(leaf.corridor_sides):
            if not leaf.doors[side] and rng.random() < 0.6:
                leaves[k] = leaf = _add_side_door(rng, occ, leaf, side, lay)

    _place_obstacles(rng, occ, leaves, n_obstacles, obstacle_gap, resolution)
    return FloorPlan(occ, resolution, origin)


def passage_clearance(width: int, resolution: float) -> float:
    """`FloorPlan.clearance_map`'s value (metres) along the middle of a straight passage `width`
    cells wide between solid cells, such as a door or a corridor: the centre distance to the nearer
    side, `(width + 1) // 2` cells, less the map's margin of sqrt(2) cells (negative: none)."""
    return (width + 1) // 2 * resolution - math.sqrt(2.0) * resolution


#: Each corridor's width is the `corridor_width` (in cells) times a factor drawn from this range.
_CORRIDOR_SCALE = (0.85, 1.2)


def _split_axis(
    rng: np.random.Generator, lo: int, hi: int, cw: int, lay: _Layout, n_corridors: int
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Cut [lo, hi) into blocks separated by corridors (each with a wall on both sides).

    Returns (blocks, corridors) as half-open cell intervals. Uses fewer corridors if the blocks would
    otherwise be smaller than one room.
    """
    n = max(0, min(2, n_corridors))
    while True:
        widths = [int(cw * rng.uniform(*_CORRIDOR_SCALE)) for _ in range(n)]
        spare = (hi - lo) - sum(w + 2 * lay.tw for w in widths) - (n + 1) * lay.min_room
        if spare >= 0 or n == 0:
            break
        n -= 1
    # Blocks get a minimum room plus a random share of what is left, so corridors move per seed.
    shares = rng.uniform(0.5, 1.5, size=n + 1)
    extra = np.floor(max(spare, 0) * shares / shares.sum()).astype(int)
    extra[-1] += max(spare, 0) - int(extra.sum())
    blocks: list[tuple[int, int]] = []
    corridors: list[tuple[int, int]] = []
    pos = lo
    for k in range(n + 1):
        size = lay.min_room + int(extra[k])
        blocks.append((pos, pos + size))
        pos += size
        if k < n:
            pos += lay.tw
            corridors.append((pos, pos + widths[k]))
            pos += widths[k] + lay.tw
    # The last block absorbs rounding so it ends exactly at the outer wall.
    blocks[-1] = (blocks[-1][0], hi)
    return blocks, corridors


def _door_span(rect: _Rect, side: str) -> tuple[int, int]:
    """Cell interval along `side` of the rect: x for bottom/top, y for left/right."""
    return (rect.x0, rect.x1) if side in ("bottom", "top") else (rect.y0, rect.y1)


def _carve_door(occ: np.ndarray, rect: _Rect, side: str, d0: int, d1: int, tw: int) -> None:
    """Open [d0, d1) of the wall of thickness `tw` just outside `side` of the rect."""
    if side == "left":
        occ[d0:d1, rect.x0 - tw : rect.x0] = False
    elif side == "right":
        occ[d0:d1, rect.x1 : rect.x1 + tw] = False
    elif side == "bottom":
        occ[rect.y0 - tw : rect.y0, d0:d1] = False
    else:
        occ[rect.y1 : rect.y1 + tw, d0:d1] = False


def _add_side_door(rng: np.random.Generator, occ: np.ndarray, rect: _Rect, side: str, lay: _Layout) -> _Rect:
    """Cut a door in the wall outside `side` (kept `margin` cells from the rect's corners); returns
    the rect with the door recorded. Does nothing if the side is too short."""
    s0, s1 = _door_span(rect, side)
    dw = int(rng.integers(lay.dw_min, lay.dw_max + 1))
    hi = s1 - lay.margin - dw
    if hi < s0 + lay.margin:
        return rect
    d0 = int(rng.integers(s0 + lay.margin, hi + 1))
    _carve_door(occ, rect, side, d0, d0 + dw, lay.tw)
    doors = dict(rect.doors)
    doors[side] = (*doors[side], (d0, d0 + dw))
    return _Rect(rect.x0, rect.x1, rect.y0, rect.y1, doors, rect.corridor_sides)


def _wall_positions(lo: int, hi: int, blockers: tuple[tuple[int, int], ...], lay: _Layout) -> np.ndarray:
    """Allowed first cells c of a new wall [c, c+tw) splitting [lo, hi) into two rooms of at least
    `min_room`, not touching any door in `blockers` (the walls it will meet) within `margin`."""
    cand = np.arange(lo + lay.min_room, hi - lay.min_room - lay.tw + 1)
    ok = np.ones(cand.size, dtype=np.bool_)
    for d0, d1 in blockers:
        ok &= (cand + lay.tw <= d0 - lay.margin) | (cand >= d1 + lay.margin)
    return cand[ok]


def _split_rooms(
    rng: np.random.Generator, occ: np.ndarray, rect: _Rect, lay: _Layout, leaves: list[_Rect]
) -> None:
    """Recursively split `rect` by walls with one door each (binary space partition).

    Every split wall gets a door and later splits never block it, so by induction every leaf room is
    reachable from every other through the doors of the walls between them.
    """
    w, h = rect.x1 - rect.x0, rect.y1 - rect.y0
    small = max(w, h) <= lay.max_room
    if small and rng.random() < 0.5:
        _carve_leaf(occ, rect, leaves)
        return
    vertical_first = w > h if rng.random() < 0.8 else w <= h
    for vertical in (vertical_first, not vertical_first):
        if vertical:
            cand = _wall_positions(rect.x0, rect.x1, rect.doors["bottom"] + rect.doors["top"], lay)
        else:
            cand = _wall_positions(rect.y0, rect.y1, rect.doors["left"] + rect.doors["right"], lay)
        if cand.size:
            break
    else:
        _carve_leaf(occ, rect, leaves)
        return
    c = int(cand[rng.integers(cand.size)])
    e = c + lay.tw
    if vertical:
        first = _child(rect, rect.x0, c, rect.y0, rect.y1, cut_side="right")
        second = _child(rect, e, rect.x1, rect.y0, rect.y1, cut_side="left")
        wall_side = "right"  # the new wall lies just outside `first`'s right side
    else:
        first = _child(rect, rect.x0, rect.x1, rect.y0, c, cut_side="top")
        second = _child(rect, rect.x0, rect.x1, e, rect.y1, cut_side="bottom")
        wall_side = "top"
    with_door = _add_side_door(rng, occ, first, wall_side, lay)
    if not with_door.doors[wall_side]:
        raise _DrawFailed("a split wall too short for a door")
    door = with_door.doors[wall_side][-1]
    opposite = "left" if vertical else "bottom"
    second_doors = dict(second.doors)
    second_doors[opposite] = (door,)
    second = _Rect(second.x0, second.x1, second.y0, second.y1, second_doors, second.corridor_sides)
    _split_rooms(rng, occ, with_door, lay, leaves)
    _split_rooms(rng, occ, second, lay, leaves)


def _child(rect: _Rect, x0: int, x1: int, y0: int, y1: int, cut_side: str) -> _Rect:
    """Sub-rectangle of `rect`: inherits the doors on its outer sides (clipped to its extent) and the
    corridor flags; the `cut_side` is the new interior wall, with no doors yet."""
    doors: dict[str, tuple[tuple[int, int], ...]] = {}
    for side in _SIDES:
        if side == cut_side:
            doors[side] = ()
            continue
        lo, hi = (x0, x1) if side in ("bottom", "top") else (y0, y1)
        doors[side] = tuple(d for d in rect.doors[side] if d[0] < hi and d[1] > lo)
    return _Rect(x0, x1, y0, y1, doors, rect.corridor_sides - {cut_side})


def _carve_leaf(occ: np.ndarray, rect: _Rect, leaves: list[_Rect]) -> None:
    occ[rect.y0 : rect.y1, rect.x0 : rect.x1] = False
    leaves.append(rect)


def _place_obstacles(
    rng: np.random.Generator,
    occ: np.ndarray,
    leaves: list[_Rect],
    n_obstacles: int,
    gap_m: float,
    res: float,
) -> None:
    """Put up to `n_obstacles` boxes and discs in rooms, each `gap_m` clear of anything solid.

    The gap is what keeps connectivity: an obstacle surrounded by a free ring wider than the robot can
    always be walked around, so it can neither cut a room in two nor block a door.
    """
    if not leaves or n_obstacles == 0:
        return
    gap = math.ceil(gap_m / res)
    ny, nx = occ.shape
    placed = 0
    for _ in range(50 * n_obstacles):
        if placed == n_obstacles:
            break
        room = leaves[int(rng.integers(len(leaves)))]
        round_ = rng.random() < 0.4
        if round_:
            r = rng.uniform(0.15, 0.4) / res
            half_w = half_h = r
        else:
            half_w, half_h = rng.uniform(0.2, 0.8) / res, rng.uniform(0.2, 0.5) / res
            if rng.random() < 0.5:
                half_w, half_h = half_h, half_w
        cx = rng.uniform(room.x0, room.x1)
        cy = rng.uniform(room.y0, room.y1)
        i0, i1 = math.floor(cx - half_w), math.ceil(cx + half_w)
        j0, j1 = math.floor(cy - half_h), math.ceil(cy + half_h)
        if i0 - gap < 0 or j0 - gap < 0 or i1 + gap > nx or j1 + gap > ny:
            continue
        if occ[j0 - gap : j1 + gap, i0 - gap : i1 + gap].any():
            continue
        if round_:
            jj, ii = np.mgrid[j0:j1, i0:i1]
            disc = (ii + 0.5 - cx) ** 2 + (jj + 0.5 - cy) ** 2 <= half_w**2
            occ[j0:j1, i0:i1] |= disc
        else:
            occ[j0:j1, i0:i1] = True
        placed += 1
