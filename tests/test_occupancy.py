"""Tests of the occupancy and counts layers: parameters, the ray and beam sensor models, and the
per-scan / per-ray update rules.

Most scenes use a resolution of 0.25 m and a sensor at the centre of cell (0, 0), (0.125, 0.125):
every coordinate is then exact in binary, so the cells a beam along an axis visits are known by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from fleetmap.cell_queries import RAY_OCCUPIED, STATE_FREE, STATE_OCCUPIED
from fleetmap.config import OCCUPANCY_PRESETS, STORED_CONFIG, MapConfig, OccupancyParams, logit, probability
from fleetmap.grid_map import GridMap
from fleetmap.kernels.traversal import BRESENHAM, EXACT, segment_cells
from fleetmap.scan import Scan

RES = 0.25
#: The centre of cell (0, 0) at RES.
SENSOR = (0.125, 0.125)


def make_map(**config: object) -> GridMap:
    """A map at RES keeping the occupancy and counts layers unless told otherwise."""
    config.setdefault("resolution", RES)
    config.setdefault("layers", ["occupancy", "counts"])
    return GridMap(MapConfig(**config))  # type: ignore[arg-type]


def beams(
    angles: list[float],
    ranges: list[float | None],
    pose: tuple[float, float, float] = (*SENSOR, 0.0),
    range_min: float = 0.0,
    range_max: float = math.inf,
) -> Scan:
    return Scan.from_angles(pose, angles, ranges, range_min=range_min, range_max=range_max)


def lo(m: GridMap, i: int, j: int) -> float:
    """Stored log-odds of cell (i, j) (NaN when unknown)."""
    return float(m.region("log_odds", i, j, i + 1, j + 1)[0, 0])


def known_cells(m: GridMap, window: int = 64) -> dict[tuple[int, int], float]:
    """Every known cell in [-window, window)^2 and its log-odds."""
    a = m.region("log_odds", -window, -window, window, window)
    jj, ii = np.nonzero(~np.isnan(a))
    return {(int(i) - window, int(j) - window): float(a[j, i]) for i, j in zip(ii, jj, strict=True)}


# -- parameters --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("preset", "expected"),
    [
        # log(p / (1 - p)) of the documented probabilities, written out.
        ("octomap", (0.8472978603872037, -0.4054651081081643, -1.9924301646902063, 3.4760986898352733)),
        ("cartographer", (0.2006706954621511, -0.04000533461369913, -2.1972245773362196, 2.1972245773362196)),
        ("coursera", (1.0, -0.5, -100.0, 100.0)),
        ("int8", (9.0, -9.0, -128.0, 127.0)),
    ],
)
def test_preset_values(preset: str, expected: tuple[float, float, float, float]) -> None:
    """Each preset resolves to the documented (l_hit, l_miss, l_min, l_max)."""
    p = OccupancyParams(preset=preset)  # type: ignore[arg-type]
    assert (p.l_hit, p.l_miss, p.l_min, p.l_max) == pytest.approx(expected, abs=1e-12)
    assert pytest.approx(expected, abs=1e-12) == OCCUPANCY_PRESETS[preset]


def test_default_preset_is_octomap() -> None:
    """A map configured with nothing uses OctoMap's 0.7 / 0.4 with clamping 0.12 / 0.97."""
    occ = MapConfig().occupancy
    assert occ.preset == "octomap"
    assert probability(occ.l_hit) == pytest.approx(0.7)
    assert probability(occ.l_miss) == pytest.approx(0.4)
    assert probability(occ.l_min) == pytest.approx(0.12)
    assert probability(occ.l_max) == pytest.approx(0.97)


def test_probability_and_logit() -> None:
    """p = 1 - 1/(1 + exp(l)), the inverse of logit, finite and in [0, 1] for huge |l|."""
    for l_val in (-30.0, -2.0, -0.1, 0.0, 0.3, 5.0, 40.0):
        e = math.exp(l_val)
        assert probability(l_val) == pytest.approx(e / (1.0 + e), rel=1e-12)
        assert 1.0 - 1.0 / (1.0 + e) == pytest.approx(probability(l_val), rel=1e-9, abs=1e-15)
    for p in (0.01, 0.3, 0.5, 0.77, 0.999):
        assert probability(logit(p)) == pytest.approx(p, rel=1e-12)
    assert probability(0.0) == 0.5
    assert probability(-1000.0) == 0.0
    assert probability(1000.0) == 1.0


def test_probability_parameters_equal_log_odds() -> None:
    """Parameters given as probabilities resolve to the same log-odds as the equivalent l_* values;
    explicit values override only their own field of the preset."""
    by_p = OccupancyParams(p_hit=0.7, p_miss=0.4, p_min=0.12, p_max=0.97, preset="coursera")
    assert (by_p.l_hit, by_p.l_miss, by_p.l_min, by_p.l_max) == pytest.approx(OCCUPANCY_PRESETS["octomap"])
    by_l = OccupancyParams(l_hit=logit(0.6), l_miss=logit(0.45))
    by_p2 = OccupancyParams(p_hit=0.6, p_miss=0.45)
    assert (by_l.l_hit, by_l.l_miss) == pytest.approx((by_p2.l_hit, by_p2.l_miss), abs=1e-15)
    mixed = OccupancyParams(preset="cartographer", l_hit=1.5)
    assert mixed.l_hit == 1.5
    assert (mixed.l_miss, mixed.l_min, mixed.l_max) == pytest.approx(OCCUPANCY_PRESETS["cartographer"][1:])


@pytest.mark.parametrize(
    "kwargs",
    [
        {"l_hit": -0.5},
        {"l_hit": 0.0},
        {"p_hit": 0.4},
        {"l_miss": 0.3},
        {"p_miss": 0.6},
        {"l_hit": 1.0, "p_hit": 0.7},
        {"l_miss": -1.0, "p_miss": 0.4},
        {"l_min": 0.5},
        {"l_max": -0.5},
        {"p_min": 0.6},
        {"p_hit": 1.2},
        {"p_hit": 0.0},
        {"p_max": 1.0},
        {"l_hit": math.nan},
        {"l_max": math.inf},
        {"free_thresh": 0.7, "occupied_thresh": 0.6},
        {"preset": "nope"},
        {"bogus": 1},
    ],
)
def test_invalid_parameters_rejected(kwargs: dict[str, object]) -> None:
    """Invalid occupancy parameters raise pydantic's ValidationError."""
    with pytest.raises(ValidationError):
        OccupancyParams(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"p_max": 0.6}, r"p_max 0\.6 .* not above occupied_thresh 0\.65: no cell could ever be occupied"),
        ({"preset": "cartographer", "occupied_thresh": 0.9}, "no cell could ever be occupied"),
        ({"l_max": 0.5}, r"p_max 0\.622459 \(l_max 0\.5\)"),
        ({"p_min": 0.25}, r"p_min 0\.25 .* not below free_thresh 0\.196: no cell could ever be free"),
        ({"preset": "cartographer", "free_thresh": 0.099}, "no cell could ever be free"),
    ],
)
def test_a_clamp_that_makes_a_state_unreachable_is_refused(kwargs: dict[str, object], words: str) -> None:
    """A clamp that keeps every cell's probability at or below occupied_thresh (or at or above
    free_thresh) is refused, saying which state no cell could reach: with p_max 0.6 a build of the
    Intel log exported a nav2 map with no wall at all, silently. The same clamp with thresholds
    that it can cross is fine, and a stored map keeps its configuration."""
    with pytest.raises(ValidationError, match=words):
        MapConfig.model_validate({"occupancy": kwargs})
    stored = MapConfig.model_validate({"occupancy": kwargs}, context={STORED_CONFIG: True})
    assert (
        stored.occupancy.model_dump(exclude_none=True).items()
        >= {k: v for k, v in kwargs.items() if not k.startswith("p_")}.items()
    )
    MapConfig(occupancy=OccupancyParams(p_max=0.6, p_min=0.25, occupied_thresh=0.55, free_thresh=0.3))


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"l_hit": 1e-46}, r"l_hit 1e-46 is 0 as a cell stores log-odds \(float32\)"),
        ({"l_miss": -5e-324}, r"l_miss -4\.94066e-324 is 0 as a cell stores log-odds \(float32\)"),
    ],
)
def test_a_log_odds_step_that_float32_cells_round_to_zero_is_refused(
    kwargs: dict[str, object], words: str
) -> None:
    """Cells hold float32 log-odds: an l_hit of 1e-46 (positive, so accepted) added to an unknown
    cell's 0 is 0 again, so a hit cell stayed at p 0.5 whatever the scans (an l_miss likewise):
    refused now, naming the field. A stored map keeps its configuration."""
    stored = MapConfig.model_validate(
        {"resolution": RES, "layers": ["occupancy"], "occupancy": kwargs}, context={STORED_CONFIG: True}
    )
    m = GridMap(stored)
    for _ in range(5):
        m.integrate(beams([0.0], [1.0]))
    assert lo(m, 4, 0) == 0.0 if "l_hit" in kwargs else lo(m, 0, 0) == 0.0  # what the refusal prevents
    with pytest.raises(ValidationError, match=words):
        MapConfig.model_validate({"occupancy": kwargs})
    MapConfig.model_validate({"occupancy": {"l_hit": 1e-44, "l_miss": -1e-44}})  # a float32 holds these


@pytest.mark.parametrize("layers", [["counts"], ["tsdf"], ["counts", "tsdf"]])
def test_a_map_without_the_occupancy_layer_takes_thresholds_past_the_clamp(layers: list[str]) -> None:
    """The clamp bounds the occupancy layer's log-odds only. A counts map classifies by the count
    model's p = hits / (hits + misses), which reaches 0 and 1 (rays, exports), and a TSDF map by
    no p at all: a counts map with occupied_thresh 0.99 was refused, saying no cell could ever be
    occupied (by OctoMap's clamp, p 0.97, which it does not use), though a cell hit every time is.
    With the occupancy layer the same thresholds are refused, located at `occupancy`."""
    occupancy = {"occupied_thresh": 0.99, "free_thresh": 0.01}
    config = MapConfig.model_validate({"resolution": RES, "layers": layers, "occupancy": occupancy})
    with pytest.raises(ValidationError, match=r"occupancy\n.*no cell could ever be occupied") as refused:
        MapConfig.model_validate(
            {"resolution": RES, "layers": [*layers, "occupancy"], "occupancy": occupancy}
        )
    assert [e["loc"] for e in refused.value.errors()] == [("occupancy",)]
    if "counts" in layers:
        m = GridMap(config)
        m.integrate(beams([0.0], [1.0]))  # cells 0..3 missed (p 0), cell 4 hit (p 1)
        ray = m.cast_rays(SENSOR, [0.0], 3.0)
        assert (int(ray.status[0]), int(ray.i[0])) == (RAY_OCCUPIED, 4)


def _saturated_states(occupancy: dict[str, object]) -> list[int]:
    """The states of a beam's cells, driven to the clamp (the hit cell to l_max, the cells before it
    to l_min), in a map of `occupancy` (loaded as a stored configuration: not refused)."""
    config = MapConfig.model_validate(
        {"resolution": RES, "layers": ["occupancy"], "occupancy": occupancy}, context={STORED_CONFIG: True}
    )
    m = GridMap(config)
    for _ in range(60):  # Cartographer's miss takes 55 to reach its clamp
        m.integrate(beams([0.0], [1.0]))
    assert lo(m, 4, 0) == np.float32(config.occupancy.l_max)
    assert lo(m, 0, 0) == np.float32(config.occupancy.l_min)
    return [int(v) for v in m.region("state", 0, 0, 5, 1)[0]]


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        (
            {"p_max": 0.7, "occupied_thresh": 0.69999999999},
            r"p_max 0\.7 \(l_max 0\.847298; p 0\.699999988 as a cell stores it, in float32\) is not above "
            r"occupied_thresh 0\.69999999999: no cell could ever be occupied",
        ),
        ({"p_max": 0.9000000001, "occupied_thresh": 0.9}, r"p 0\.899999976 as a cell stores it"),
        (
            {"p_min": 0.249999999, "free_thresh": 0.25},
            r"p_min 0\.25 \(l_min -1\.09861; p 0\.25 as a cell stores it, in float32\) is not below "
            r"free_thresh 0\.25: no cell could ever be free",
        ),
    ],
)
def test_a_clamp_past_a_threshold_only_in_double_precision_is_refused(
    kwargs: dict[str, object], words: str
) -> None:
    """Cells hold float32 log-odds, and their probability is rounded to float32 before the
    thresholds classify it: a clamp a hair past a threshold in double precision (p_min 0.249999999
    against free_thresh 0.25) can land on it, or short of it, as stored. Such a clamp was accepted,
    and then no cell of the map was ever free (or occupied), as with the clamps refused for that."""
    states = _saturated_states(kwargs)
    assert STATE_OCCUPIED not in states or STATE_FREE not in states  # what the refusal prevents
    with pytest.raises(ValidationError, match=words):
        MapConfig.model_validate({"occupancy": kwargs})


@pytest.mark.parametrize(
    "kwargs",
    [
        {"preset": "cartographer", "free_thresh": 0.1},  # p_min 0.1: 0.09999999 as stored
        {"occupied_thresh": 0.97},  # OctoMap's p_max 0.97: 0.97000003 as stored
        {"p_min": 0.19599999999},  # 0.19599999487 as stored
        {"p_max": 0.7000001, "p_min": 0.2499999, "occupied_thresh": 0.7, "free_thresh": 0.25},
    ],
)
def test_a_clamp_past_a_threshold_as_stored_is_accepted(kwargs: dict[str, object]) -> None:
    """A clamp on a threshold in double precision that cells, as stored, do cross is accepted (it
    was refused, saying no cell could ever be free, of a map whose cells would have been): the
    rule is the one the map classifies its cells by."""
    MapConfig.model_validate({"occupancy": kwargs})
    assert STATE_OCCUPIED in _saturated_states(kwargs)
    assert STATE_FREE in _saturated_states(kwargs)


def test_invalid_map_config_rejected() -> None:
    """MapConfig rejects a tile size that is not a power of two, no layers and repeated layers."""
    for kwargs in ({"tile_size": 100}, {"layers": []}, {"layers": ["tsdf", "tsdf"]}, {"update": "sometimes"}):
        with pytest.raises(ValidationError):
            MapConfig(**kwargs)  # type: ignore[arg-type]


def test_band_widths_are_finite_and_at_most_256_cells() -> None:
    """`tsdf.truncation` and `beam.alpha` must be finite and at most MAX_BAND_CELLS cells: an infinite
    one made every scan 'beyond the map's coordinate range', 10 km took 8 s for a 3-beam scan, and
    1e9 m failed every scan with a MemoryError. The limit scales with the resolution. A stored
    configuration (validated with the STORED_CONFIG context) still loads past it."""
    from fleetmap.config import MAX_BAND_CELLS, STORED_CONFIG

    assert MAX_BAND_CELLS == 256
    MapConfig(resolution=0.01, tsdf={"truncation": 2.56}, beam={"alpha": 2.56})  # exactly the limit
    MapConfig(resolution=1.0, tsdf={"truncation": 200.0}, beam={"alpha": 256.0})
    for kwargs, message in (
        ({"resolution": 0.01, "tsdf": {"truncation": 2.57}}, "tsdf.truncation 2.57 m is more than 256 cells"),
        ({"tsdf": {"truncation": 1e9}}, "at most 12.8 m"),
        ({"beam": {"alpha": 13.0}}, "beam.alpha 13 m is more than 256 cells at resolution 0.05 m"),
        # A hair past the limit is said as given, not rounded to the limit ("12.8 m ... at most 12.8 m").
        ({"tsdf": {"truncation": 12.8000001}}, r"truncation 12.8000001 m is more .*\(at most 12.8 m\)"),
        ({"tsdf": {"truncation": math.inf}}, "finite"),
        ({"beam": {"alpha": math.nan}}, "finite"),
    ):
        with pytest.raises(ValidationError, match=message):
            MapConfig.model_validate(kwargs)
    stored = MapConfig.model_validate({"tsdf": {"truncation": 20.0}}, context={STORED_CONFIG: True})
    assert stored.tsdf.truncation == 20.0


@pytest.mark.parametrize(
    "config",
    [
        {"tsdf": {"max_weight": math.inf}},  # stored as null, which then failed to load: no restart
        {"resolution": math.nan},
        {"no_return_range": math.nan},
        {"beam": {"beta": math.nan}},
        {"occupancy": {"occupied_thresh": math.nan}},
        {"occupancy": {"free_thresh": math.inf}},
    ],
)
def test_every_number_in_a_configuration_is_finite(config: dict[str, object]) -> None:
    """NaN and infinity are refused by name (before, NaN got "should be less than or equal to 100",
    and an infinite weight cap was accepted, stored as null and then refused on restart)."""
    with pytest.raises(ValidationError, match="finite number"):
        MapConfig.model_validate(config)


def test_log_odds_parameters_are_bounded_to_what_float32_cells_hold() -> None:
    """l_hit = 1e300 made every hit cell +inf in the float32 pools: "known" with no log-odds."""
    from fleetmap.config import MAX_LOG_ODDS, STORED_CONFIG

    MapConfig(occupancy={"l_min": -MAX_LOG_ODDS, "l_max": MAX_LOG_ODDS})
    MapConfig(occupancy={"l_min": -1e6, "l_max": 1e6})  # "unclamped"
    for name, value in (("l_hit", 1e300), ("l_miss", -1e31), ("l_min", -1e39), ("l_max", 2e30)):
        with pytest.raises(ValidationError, match="within"):
            MapConfig(occupancy={name: value})
    stored = MapConfig.model_validate({"occupancy": {"l_max": 1e300}}, context={STORED_CONFIG: True})
    assert stored.occupancy.l_max == 1e300  # a map stored before the bound still loads


# -- the ray sensor model ----------------------------------------------------------------------------


@pytest.mark.parametrize(("traversal", "method"), [("exact", EXACT), ("bresenham", BRESENHAM)])
def test_ray_marks_traversed_cells_miss_and_end_cell_hit(traversal: str, method: int) -> None:
    """One return: exactly the cells of the configured traversal become known, the end cell with
    l_hit and every other one with l_miss; nothing else is touched."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        pose = (float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), float(rng.uniform(-math.pi, math.pi)))
        a, r = float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(0.1, 5.0))
        m = make_map(occupancy={"preset": "coursera"}, traversal=traversal)
        m.integrate(beams([a], [r], pose=pose))
        x0, y0 = pose[0] / RES, pose[1] / RES
        x1 = (pose[0] + r * math.cos(pose[2] + a)) / RES
        y1 = (pose[1] + r * math.sin(pose[2] + a)) / RES
        path = [(int(i), int(j)) for i, j in segment_cells(x0, y0, x1, y1, method)]
        expected = dict.fromkeys(path[:-1], -0.5)
        expected[path[-1]] = 1.0
        assert known_cells(m) == expected


def test_per_scan_updates_each_cell_once() -> None:
    """per_scan (the default): 10 beams fanning out from the sensor all cross the sensor cell, which
    gets ONE miss; three beams ending in the same cell give it ONE hit."""
    m = make_map(occupancy={"preset": "coursera"})
    assert m.config.update == "per_scan"
    angles = [0.05 * k for k in range(10)]
    m.integrate(beams(angles, [3.0] * 10))
    assert lo(m, 0, 0) == -0.5
    assert lo(m, 1, 0) == -0.5
    m2 = make_map(occupancy={"preset": "coursera"})
    m2.integrate(beams([0.0, 0.01, -0.01], [1.0, 1.0, 1.0]))
    assert lo(m2, 4, 0) == 1.0
    assert m2.cells(np.array([[1.125, 0.125]]))["hits"][0] == 1


def test_per_ray_updates_every_ray() -> None:
    """per_ray: every ray updates the cells it crosses, so the sensor cell crossed by 10 rays gets 10
    misses, and a cell three rays end in gets three hits (the cells before it three misses each)."""
    m = make_map(occupancy={"preset": "coursera"}, update="per_ray")
    angles = [0.05 * k for k in range(10)]
    m.integrate(beams(angles, [3.0] * 10))
    assert lo(m, 0, 0) == pytest.approx(-5.0)
    assert m.cells(np.array([SENSOR]))["misses"].tolist() == [10]
    m2 = make_map(occupancy={"preset": "coursera"}, update="per_ray")
    m2.integrate(beams([0.0, 0.01, -0.01], [1.0, 1.0, 1.0]))
    assert lo(m2, 4, 0) == pytest.approx(3.0)
    assert lo(m2, 2, 0) == pytest.approx(-1.5)
    got = m2.cells(np.array([[0.125, 0.125], [1.125, 0.125]]))
    assert got["misses"].tolist() == [3, 0]
    assert got["hits"].tolist() == [0, 3]


def test_per_ray_clamps_after_every_update() -> None:
    """per_ray with OctoMap clamping: 20 misses drive the sensor cell to l_min, then a hit in the same
    scan (a later beam ending in the sensor cell) gives l_min + l_hit. Clamping only at the end would
    give l_min; likewise 20 hits then a miss give l_max + l_miss."""
    occ = OccupancyParams()
    m = make_map(update="per_ray")
    m.integrate(beams([0.02 * k for k in range(20)] + [0.0], [3.0] * 20 + [0.05]))
    assert lo(m, 0, 0) == pytest.approx(occ.l_min + occ.l_hit, abs=1e-6)
    m2 = make_map(update="per_ray")
    m2.integrate(beams([0.0] * 20 + [0.0], [0.05] * 20 + [3.0]))
    assert lo(m2, 0, 0) == pytest.approx(occ.l_max + occ.l_miss, abs=1e-6)


@pytest.mark.parametrize("heading", [-math.pi / 4, math.pi / 4, 3 * math.pi / 4])
def test_per_ray_and_per_scan_trace_the_same_cells_of_a_beam(heading: float) -> None:
    """A scan of one beam updates the same cells per ray as per scan: both walk the beam's end
    point as `scan_rays` computes it. The per-ray plan computed its own end points
    (`pose + r * cos(theta + a)`), an ulp off the per-scan ones, which moved the side cells of
    diagonal beams through cell corners (and end points on cell edges) to the other side."""
    differ = []
    for origin in [(0.0, 0.0), (1.0, 0.5), (-3.75, 2.75), (0.25, -1.0)]:
        for k in range(1, 12):
            # A beam at map bearing pi/4 ending on a cell corner, through every corner on the way.
            scan = beams([math.pi / 4 - heading], [k * RES * math.sqrt(2)], pose=(*origin, heading))
            per_scan, per_ray = (
                make_map(layers=["occupancy"]),
                make_map(layers=["occupancy"], update="per_ray"),
            )
            per_scan.integrate(scan)
            per_ray.integrate(scan)
            if known_cells(per_scan) != known_cells(per_ray):
                differ.append((origin, k))
    assert differ == []


def test_clamping_across_scans() -> None:
    """per_scan clamps after every scan's update: 30 scans of misses sit at l_min, and one hit
    afterwards lands exactly at l_min + l_hit; the int8 preset saturates at 127 and -128."""
    occ = OccupancyParams()
    m = make_map()
    for _ in range(30):
        m.integrate(beams([0.0], [3.0]))
        assert lo(m, 0, 0) >= occ.l_min - 1e-6
    assert lo(m, 0, 0) == pytest.approx(occ.l_min, abs=1e-6)
    m.integrate(beams([0.0], [0.05]))
    assert lo(m, 0, 0) == pytest.approx(occ.l_min + occ.l_hit, abs=1e-6)

    m8 = make_map(occupancy={"preset": "int8"})
    values = []
    for _ in range(16):
        m8.integrate(beams([0.0], [0.05]))
        values.append(lo(m8, 0, 0))
    assert values[:3] == [9.0, 18.0, 27.0]
    assert values[-1] == 127.0
    m8.integrate(beams([0.0], [3.0]))
    assert lo(m8, 0, 0) == 118.0
    for _ in range(40):
        m8.integrate(beams([0.0], [3.0]))
    assert lo(m8, 0, 0) == -128.0


@pytest.mark.parametrize("order", ["hit_first", "miss_first"])
def test_hit_beats_miss_within_a_scan(order: str) -> None:
    """per_scan: a cell that one beam ends in and another passes through is a hit only, whatever the
    beam order: l_hit in the occupancy layer, one hit and no miss in the counts."""
    through, ending = (0.0, 3.0), (0.0, 1.0)  # both along +x: cell 4 is crossed by one, the end of the other
    pair = [ending, through] if order == "hit_first" else [through, ending]
    m = make_map()
    m.integrate(beams([a for a, _ in pair], [r for _, r in pair]))
    assert lo(m, 4, 0) == pytest.approx(OccupancyParams().l_hit)
    got = m.cells(np.array([[4.5 * RES, 0.5 * RES]]))
    assert (int(got["hits"][0]), int(got["misses"][0])) == (1, 0)
    assert lo(m, 3, 0) == pytest.approx(OccupancyParams().l_miss)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=60))
def test_cartographer_matches_probability_space(events: list[bool]) -> None:
    """Cartographer multiplies odds and clamps probabilities to [0.1, 0.9]. Doing exactly that in
    probability space over a random hit / miss sequence of one cell matches the engine's log-space
    result to 1e-5 after every event."""
    p_hit, p_miss = 0.55, 0.49
    m = make_map(occupancy={"preset": "cartographer"}, layers=["occupancy"])
    p: float | None = None  # unknown

    def odds(q: float) -> float:
        return q / (1.0 - q)

    for hit in events:
        # Cell (4, 0): a beam ending there (hit) or passing through it to cell 8 (miss).
        m.integrate(beams([0.0], [1.0 if hit else 2.0]))
        o = (1.0 if p is None else odds(p)) * odds(p_hit if hit else p_miss)
        p = min(max(o / (1.0 + o), 0.1), 0.9)
        got = float(m.region("probability", 4, 0, 5, 1)[0, 0])
        assert got == pytest.approx(p, abs=1e-5)


def test_counts_maximum_likelihood() -> None:
    """Counts layer: scans of one beam along +x with known ranges. Cell k is hit by every scan whose
    beam ends in it and missed by every scan whose beam goes past it; the stored hits / misses and
    the ML occupancy hits / (hits + misses) match those exact numbers."""
    ranges = [1.0, 1.5, 1.0, 2.0, 0.5, 1.5, 1.5, 2.0, 0.25, 1.0]
    end_cells = [math.floor((SENSOR[0] + r) / RES) for r in ranges]  # 4, 6, 4, 8, 2, ...
    m = make_map(layers=["counts"])
    for r in ranges:
        m.integrate(beams([0.0], [r]))
    hits = m.region("hits", 0, 0, 10, 1)[0].astype(int)
    misses = m.region("misses", 0, 0, 10, 1)[0].astype(int)
    exp_hits = [sum(e == k for e in end_cells) for k in range(10)]
    exp_misses = [sum(e > k for e in end_cells) for k in range(10)]
    assert hits.tolist() == exp_hits
    assert misses.tolist() == exp_misses
    # By hand: cell 4 is the end of 3 beams and crossed by the 5 that end at 6 or 8.
    assert (exp_hits[4], exp_misses[4]) == (3, 5)
    total = hits + misses
    with np.errstate(invalid="ignore"):
        ml = np.where(total > 0, hits / np.maximum(total, 1), np.nan)
    assert ml[4] == pytest.approx(3 / 8)
    assert ml[0] == 0.0
    assert ml[8] == 1.0
    assert np.isnan(ml[9])
    assert m.region("hits", 0, 1, 10, 2).sum() == 0


def test_no_return_range_clears_without_hit() -> None:
    """No-return beams (inf, None, or exactly range_max) are ignored by default; with
    no_return_range R they clear their first R metres as misses and mark no hit."""
    for ranges, kwargs in (([math.inf], {}), ([None], {}), ([5.0], {"range_max": 5.0})):
        m0 = make_map()
        result = m0.integrate(beams([0.0], ranges, **kwargs))  # type: ignore[arg-type]
        assert result.cell_updates == 0
        assert len(m0.store) == 0
        assert m0.known_bounds() is None

        m = make_map(no_return_range=1.0, occupancy={"preset": "coursera"})
        m.integrate(beams([0.0], ranges, **kwargs))  # type: ignore[arg-type]
        # 1 m from x = 0.125 ends at x = 1.125, in cell 4: cells 0..4 cleared.
        assert known_cells(m) == {(k, 0): -0.5 for k in range(5)}
        assert m.region("hits", -8, -8, 8, 8).sum() == 0


@pytest.mark.parametrize("model", [{}, {"update": "per_ray"}, {"traversal": "bresenham"}])
def test_no_return_range_clears_its_metres_even_past_range_max(model: dict[str, object]) -> None:
    """The first R metres of a no-return beam are cleared, whatever the sensor's range_max: a
    configuration asking for 2 m with a 0.5 m sensor used to clear 0.5 m."""
    for planned in (False, True):
        m = make_map(no_return_range=2.0, occupancy={"preset": "coursera"}, **model)
        scan = beams([0.0], [math.inf], range_max=0.5)
        if planned:  # the service's path: plan, then apply
            m.apply(m.plan(scan))
        else:
            m.integrate(scan)
        # 2 m from x = 0.125 ends at x = 2.125, in cell 8: cells 0..8 cleared, none hit.
        assert known_cells(m) == {(k, 0): -0.5 for k in range(9)}
        assert m.region("hits", -8, -8, 16, 16).sum() == 0


def test_return_just_below_range_max_is_a_hit() -> None:
    """A return at range_max - epsilon is a hit; at range_max it is a no-return and ignored."""
    m = make_map(occupancy={"preset": "coursera"})
    m.integrate(beams([0.0], [0.999], range_max=1.0))
    assert lo(m, 4, 0) == 1.0
    m.integrate(beams([math.pi / 2], [1.0], range_max=1.0))
    assert math.isnan(lo(m, 0, 4))


def test_nan_and_below_range_min_are_ignored() -> None:
    """NaN readings and readings below range_min change nothing: the map equals the map of the
    valid beams alone, and a scan of only such readings creates no tile."""
    m = make_map()
    m.integrate(beams([0.5, 1.0], [math.nan, 0.05], range_min=0.1))
    assert len(m.store) == 0
    mixed = make_map()
    mixed.integrate(beams([0.5, 1.0, -0.7], [math.nan, 0.05, 2.0], range_min=0.1))
    valid = make_map()
    valid.integrate(beams([-0.7], [2.0], range_min=0.1))
    for layer in ("log_odds", "hits", "misses"):
        np.testing.assert_array_equal(
            mixed.region(layer, -16, -16, 16, 16), valid.region(layer, -16, -16, 16, 16)
        )
    # NaN is not a no-return: clearing does not apply to it either.
    cleared = make_map(no_return_range=1.0)
    cleared.integrate(beams([0.5], [math.nan]))
    assert len(cleared.store) == 0
    # A reading exactly at range_min is used.
    at_min = make_map()
    at_min.integrate(beams([0.0], [1.0], range_min=1.0))
    assert lo(at_min, 4, 0) > 0


@pytest.mark.parametrize(
    "model",
    [
        {},
        {"update": "per_ray"},
        {"traversal": "bresenham"},
        {"sensor_model": "beam"},
        {"no_return_range": 1.0},
    ],
    ids=["per-scan", "per-ray", "bresenham", "beam", "clearing"],
)
def test_negative_readings_are_ignored_and_the_other_beams_integrated(model: dict[str, object]) -> None:
    """A negative reading is below range_min, so it is ignored like NaN (some drivers report errors
    so); before, it made the whole scan an error and its good beams were lost."""
    angles = [-0.7, -0.2, 0.4, 1.1]
    layers = ["occupancy", "counts", "tsdf"]
    negative, invalid = make_map(layers=layers, **model), make_map(layers=layers, **model)
    negative.integrate(beams(angles, [2.0, -1.0, 1.5, -1e-9], range_max=5.0))
    invalid.integrate(beams(angles, [2.0, math.nan, 1.5, math.nan], range_max=5.0))
    bounds = invalid.known_bounds()
    assert bounds is not None and negative.known_bounds() == bounds
    for layer in ("log_odds", "hits", "misses", "tsdf", "tsdf_weight"):
        np.testing.assert_array_equal(negative.region(layer, *bounds), invalid.region(layer, *bounds))


def test_a_null_range_is_no_return_in_a_list_and_in_an_object_array() -> None:
    """None is "no return" (as JSON null is); numpy alone turns it into NaN, an invalid reading, so
    an object array used to clear nothing where the same list cleared its beam."""
    as_list = make_map(no_return_range=1.0)
    as_list.integrate(beams([0.3], [None]))
    as_array = make_map(no_return_range=1.0)
    as_array.integrate(beams([0.3], np.array([None], dtype=object)))  # type: ignore[arg-type]
    bounds = as_list.known_bounds()
    assert bounds is not None and as_array.known_bounds() == bounds
    np.testing.assert_array_equal(as_array.region("misses", *bounds), as_list.region("misses", *bounds))


def test_unknown_is_not_log_odds_zero() -> None:
    """With l_hit == -l_miss, a cell hit once and then missed once is KNOWN with log-odds 0 and
    p = 0.5, while a never-observed cell is unknown (NaN), also read as p = 0.5."""
    m = make_map(occupancy={"l_hit": 1.0, "l_miss": -1.0})
    m.integrate(beams([0.0], [1.0]))  # hit in cell 4
    m.integrate(beams([0.0], [2.0]))  # miss in cell 4
    got = m.cells(np.array([[4.5 * RES, 0.5 * RES], [4.5 * RES, 5.5 * RES]]))
    assert got["known"].tolist() == [True, False]
    assert got["log_odds"][0] == 0.0
    assert math.isnan(got["log_odds"][1])
    assert got["probability"].tolist() == [0.5, 0.5]
    region = m.region("log_odds", 4, 0, 5, 6)[:, 0]
    assert region[0] == 0.0
    assert np.isnan(region[5])
    assert m.region("probability", 4, 0, 5, 1)[0, 0] == 0.5
    assert np.isnan(m.region("probability", 4, 5, 5, 6)[0, 0])


# -- the beam (cone) model ---------------------------------------------------------------------------


def test_beam_model_single_beam_by_hand() -> None:
    """Probabilistic Robotics' inverse sensor model, one beam straight ahead at 2 m from the centre
    of cell (0, 0), alpha 0.1 m (0.4 cells), beta 1 degree: cells 0..7 of the row are free, cell 8
    (at exactly 2 m) is occupied, cells beyond and every cell off the beam are untouched. (The
    sensor's own cell, at range 0, has no defined bearing and is left out.)"""
    occ = OccupancyParams()
    m = make_map(sensor_model="beam", layers=["occupancy"])
    m.integrate(beams([0.0], [2.0]))
    expected = {(k, 0): occ.l_miss for k in range(1, 8)}
    expected[(8, 0)] = occ.l_hit
    got = known_cells(m)
    got.pop((0, 0), None)
    assert got == pytest.approx(expected)


def test_beam_model_thick_obstacle_and_heading() -> None:
    """alpha 0.6 m (2.4 cells) makes the cells with |r - z| < 1.2 cells occupied (7, 8, 9), cells
    nearer free and farther unknown; the sensor heading (pi/2) turns the beam to +y."""
    occ = OccupancyParams()
    m = make_map(sensor_model="beam", layers=["occupancy"], beam={"alpha": 0.6})
    m.integrate(beams([0.0], [2.0], pose=(*SENSOR, math.pi / 2)))
    expected = {(0, k): occ.l_miss for k in range(1, 7)}
    expected.update({(0, k): occ.l_hit for k in (7, 8, 9)})
    got = known_cells(m)
    got.pop((0, 0), None)
    assert got == pytest.approx(expected)


def test_beam_model_no_return_is_free_only() -> None:
    """Beam model: a no-return beam is ignored by default and, with no_return_range 1 m, clears the
    cells whose centres are closer than 1 m (cells 1..3, and the sensor's own) without any occupied
    cell."""
    occ = OccupancyParams()
    m = make_map(sensor_model="beam", layers=["occupancy"])
    m.integrate(beams([0.0], [math.inf]))
    assert known_cells(m) == {}
    m2 = make_map(sensor_model="beam", layers=["occupancy"], no_return_range=1.0)
    m2.integrate(beams([0.0], [math.inf]))
    got = known_cells(m2)
    got.pop((0, 0), None)
    assert got == pytest.approx({(k, 0): occ.l_miss for k in range(1, 4)})


def test_beam_model_nearest_beam_decides() -> None:
    """With a wide cone (beta 1 rad) and two beams at -0.3 rad (2 m) and +0.3 rad (0.5 m), each cell
    takes the beam nearest in bearing: (4, -1) lies nearer the long beam and is free, its mirror
    (4, 1) nearer the short beam and beyond its range, so untouched; (1, 0) (bearing 0, a tie
    between the beams, in range of both) is free; cells outside both cones stay unknown."""
    occ = OccupancyParams()
    m = make_map(sensor_model="beam", layers=["occupancy"], beam={"beta": 1.0})
    m.integrate(beams([-0.3, 0.3], [2.0, 0.5]))
    assert lo(m, 4, -1) == pytest.approx(occ.l_miss)
    assert math.isnan(lo(m, 4, 1))
    assert lo(m, 1, 0) == pytest.approx(occ.l_miss)
    assert math.isnan(lo(m, 1, 3))  # bearing 1.25 rad: outside both cones
    assert math.isnan(lo(m, -2, 0))  # behind the sensor


@pytest.mark.parametrize("ranges", [[0.5, 2.0], [2.0, 0.5]])
@pytest.mark.parametrize("bearing", [0.0, math.pi])
def test_beam_model_beams_at_one_bearing_the_first_decides(ranges: list[float], bearing: float) -> None:
    """Two beams at one bearing (an explicit angle list may repeat one; pi and -pi are one too) tie
    for every cell of their cone: the first in the scan decides, on both sides of the bearing. The
    nearest-beam search took the last of them for cells on the higher-bearing side, so the cone was
    split down its middle between the two ranges."""
    m = make_map(sensor_model="beam", layers=["occupancy"], beam={"beta": 0.6, "alpha": 0.25})
    second = -math.pi if bearing == math.pi else bearing
    m.integrate(beams([bearing, second], ranges))
    # Cells at 1.25 m and bearings -0.15 / +0.15 rad (centres in cell units: 5 * (cos, sin) off the
    # sensor cell's centre): free with the long beam first, beyond the short beam's reach (unknown)
    # with the short one first.
    for side in (-0.15, 0.15):
        a = bearing + side
        i, j = round(5 * math.cos(a)), round(5 * math.sin(a))
        got = lo(m, i, j)
        if ranges[0] == 2.0:
            assert got == pytest.approx(OccupancyParams().l_miss), (side, i, j)
        else:
            assert math.isnan(got), (side, i, j)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("heading", [0.0, 1e15])
def test_beam_model_matches_table_9_2(heading: float) -> None:
    """Random scans (partial and 360-degree fans, no-returns, finite and infinite range_max, with and
    without no-return clearing): the cells the beam model marks, and how, equal a direct evaluation
    of Probabilistic Robotics' table 9.2 at every cell centre of the window (the sensor's own cell,
    whose bearing is undefined, left out). Also with headings of 1e15 rad, legal but rounded to
    0.125 rad, where the model's cull by bearing would no longer be exact."""
    rng = np.random.default_rng(21)
    res, w = 0.1, 40
    jj, ii = np.mgrid[-w:w, -w:w]
    cx, cy = (ii + 0.5) * res, (jj + 0.5) * res
    marked = 0
    for _ in range(40):
        n = int(rng.integers(1, 40))
        span = math.pi if rng.random() < 0.5 else 1.5
        angles = np.sort(rng.uniform(-span, span, n))
        ranges = rng.uniform(0.2, 2.5, n)
        ranges[rng.random(n) < 0.2] = math.inf
        alpha, beta = float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.01, 0.6))
        clear = float(rng.choice([0.0, 1.0]))
        r_max = float(rng.choice([math.inf, 2.0]))
        pose = (float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), heading + float(rng.uniform(-4, 4)))
        m = make_map(
            resolution=res, sensor_model="beam", layers=["occupancy"],
            beam={"alpha": alpha, "beta": beta}, no_return_range=clear,
        )  # fmt: skip
        scan = beams(list(angles), list(ranges), pose=pose, range_max=r_max)
        m.integrate(scan)
        got = m.region("log_odds", -w, -w, w, w)

        has = scan.returns_mask()
        use = has | (scan.no_return_mask() if clear > 0 else False)
        expected = np.full(got.shape, np.nan)
        if use.any():
            z = np.where(has, ranges, min(clear, r_max))[use]
            phi_k = angles[use]
            r = np.hypot(cx - pose[0], cy - pose[1])
            phi = _wrap(np.arctan2(cy - pose[1], cx - pose[0]) - pose[2])
            diff = np.abs(_wrap(phi[..., None] - phi_k))
            k = np.argmin(diff, axis=-1)
            zk, dk, hk = z[k], np.take_along_axis(diff, k[..., None], -1)[..., 0], has[use][k]
            info = (r <= np.minimum(r_max, zk + alpha / 2)) & (dk <= beta / 2)
            occupied = info & hk & (zk < r_max) & (np.abs(r - zk) < alpha / 2)
            free = info & ~occupied & (r < zk)
            expected[free] = OccupancyParams().l_miss
            expected[occupied] = OccupancyParams().l_hit
        sensor = (math.floor(pose[1] / res) + w, math.floor(pose[0] / res) + w)
        got[sensor] = expected[sensor] = np.nan
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
        np.testing.assert_allclose(got, expected, atol=1e-6)
        marked += int((~np.isnan(got)).sum())
    assert marked > 1000


def test_counts_saturate_instead_of_wrapping() -> None:
    """The count model's apply, single cells and runs: a count at 2**32 - 1 stays there, the others
    go up by one (hits for hit cells, misses for the rest), and every tile with a cell is flagged."""
    from fleetmap.kernels.kinds import CELL_HIT, CELL_MISS
    from fleetmap.kernels.update import apply_cells

    top = np.uint32(0xFFFFFFFF)
    shift = 2  # 4 x 4 cells per tile; plane key = tile << 4 | local_j << 2 | local_i
    hits = np.zeros((3, 4, 4), dtype=np.uint32)
    misses = np.zeros((3, 4, 4), dtype=np.uint32)
    hits[1, 0, 0] = top
    misses[1, 0, 1] = top
    misses[2, 3, 1] = top  # inside the run below
    hits[2, 3, 2] = 7  # a run is misses only: its hits stay
    cell = np.array([0 << 4 | 0, 0 << 4 | 1, 0 << 4 | 2, 1 << 4 | 5], dtype=np.int64)
    kind = np.array([CELL_HIT, CELL_MISS, CELL_HIT | CELL_MISS, CELL_MISS], dtype=np.uint8)
    runs = np.array([[2 << 4 | 3 << 2 | 0], [4]], dtype=np.int64)  # plan tile 2, row 3, cells 0..3
    slots = np.array([1, 0, 2], dtype=np.int64)
    changed = np.zeros(3, dtype=np.uint8)
    none = np.empty((0, 0, 0), dtype=np.float32)
    assert apply_cells(cell, kind, runs, slots, shift, none, hits, misses, 0, 0, 0, 0, changed) == 8
    assert hits[1, 0, 0] == top and misses[1, 0, 0] == 0  # a hit at the top stays there
    assert misses[1, 0, 1] == top and hits[1, 0, 1] == 0  # a miss at the top
    assert hits[1, 0, 2] == 1 and misses[1, 0, 2] == 0  # a hit beats the miss
    assert misses[0, 1, 1] == 1 and hits[0, 1, 1] == 0
    assert misses[2, 3].tolist() == [1, top, 1, 1] and hits[2, 3].tolist() == [0, 0, 7, 0]
    assert changed.tolist() == [1, 1, 1]
    assert (
        int(hits.sum(dtype=np.uint64)) == int(top) + 8
        and int(misses.sum(dtype=np.uint64)) == 2 * int(top) + 4
    )
