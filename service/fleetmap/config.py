"""Map configuration: resolution, tiling, layers and the parameters of each sensor and update model.

These pydantic models are the one definition of a map's configuration: the engine reads them, the
CLI loads them from JSON, and the REST API uses them as its request and response schema. Every field
is optional; defaults are chosen to be right for a typical indoor 2D lidar.

The models are frozen, and hold nothing that could be changed in place (`layers` is a tuple): a field
assigned after validation was not validated (resolution 0 made every scan a ZeroDivisionError, and
p_hit set on a validated configuration was ignored, its l_hit being the value in use). Other values
make another configuration.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

LayerName = Literal["occupancy", "counts", "tsdf"]
ALL_LAYERS: tuple[LayerName, ...] = ("occupancy", "counts", "tsdf")

#: `tsdf.truncation` and `beam.alpha` are at most this many cells. Each beam updates about
#: 2.8 cells per cell of truncation, so a wider band makes every scan slow for no mapping purpose
#: (Voxblox truncates at a few voxels), and past about 10**8 cells a scan cannot be held in memory.
MAX_BAND_CELLS = 256

#: Map coordinates the service accepts, metres (`+-10 000 km`: queries, request bodies, the tiles of
#: an uploaded snapshot): far beyond any real map, and small enough that cell indices stay exact
#: integers at any allowed resolution.
MAX_COORDINATE = 1.0e7

#: The `model_validate` context under which a configuration that was stored before a limit existed
#: still loads (`{STORED_CONFIG: True}`): a map must survive an upgrade.
STORED_CONFIG = "stored"

#: The `model_validate` context under which a configuration is read from a service's answer
#: (`{ANSWERED_CONFIG: True}`: the REST client reads `MapInfo` so): the fields this version does not
#: know, a newer service's, are left out, as the answers' other models leave them out
#: (`fleetmap.api_models`), instead of refusing the whole answer. A request's configuration (a `PUT`
#: body) and a stored one keep refusing them: there an unknown field is a mistake, or a map this
#: version cannot make as it was meant.
ANSWERED_CONFIG = "answered"

#: With STORED_CONFIG, in the context of a configuration only tried as a stored one, not loaded
#: (a `PUT` body refused as a new configuration: `fleetmap.api.config_body`): nothing is loaded,
#: so no warning says a stored map was.
TRIED_AS_STORED = "tried_as_stored"

log = logging.getLogger("fleetmap.config")

#: The band widths limited to MAX_BAND_CELLS cells: (section, field).
_BAND_WIDTHS = (("tsdf", "truncation"), ("beam", "alpha"))

#: Bound on every log-odds parameter's magnitude. Cells hold float32 log-odds, which overflow to
#: infinity past 3.4e38: with l_hit = 1e300 every hit cell read as "known" with no log-odds. Clamps
#: far beyond any probability (1e6, "unclamped") stay possible.
MAX_LOG_ODDS = 1e30
#: Bound on `tsdf.max_weight` (weights are float32; the default is 1000).
MAX_TSDF_WEIGHT = 1e30


def logit(p: float) -> float:
    """Log-odds of probability `p`, which must lie strictly between 0 and 1 (ValueError otherwise:
    it was math's 'math domain error' for 0 and 1.5, and ZeroDivisionError for 1)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"a probability for log-odds must lie strictly between 0 and 1, got {p!r}")
    return math.log(p / (1.0 - p))


def probability(log_odds: float) -> float:
    """Probability from log-odds: `1 - 1/(1 + exp(l))`, written to not overflow."""
    if log_odds >= 0:
        return 1.0 / (1.0 + math.exp(-log_odds))
    e = math.exp(log_odds)
    return e / (1.0 + e)


#: The smallest positive float32 (a subnormal): cells and weights are stored as float32, and a
#: positive parameter below about half of it is stored as 0.
_FLOAT32_TINIEST = float(np.nextafter(np.float32(0), np.float32(1)))


def _vanishes_in_float32(value: float) -> bool:
    """Whether `value`, not 0, is 0 once stored as a float32."""
    return value != 0 and np.float32(value) == 0


def log_odds_to_probability(log_odds: np.ndarray) -> np.ndarray:
    """`p = 1 - 1/(1 + exp(l))` elementwise, NaN stays NaN; float32 out: the probability a map
    reports (`probability` layer, `/cells`) and classifies by its thresholds (`GridMap.classify`)."""
    lo = np.asarray(log_odds, dtype=np.float64)
    with np.errstate(over="ignore"):
        return (1.0 - 1.0 / (1.0 + np.exp(lo))).astype(np.float32)


def stored_probability(log_odds: float) -> float:
    """The probability a map reports, and classifies by its thresholds, for a cell at `log_odds`:
    cells hold float32 log-odds, and `log_odds_to_probability` rounds the probability to float32."""
    return float(log_odds_to_probability(np.array([log_odds], dtype=np.float32))[0])


#: Named occupancy parameter sets, as log-odds (l_hit, l_miss, l_min, l_max).
OCCUPANCY_PRESETS: dict[str, tuple[float, float, float, float]] = {
    # OctoMap's defaults: hit 0.7, miss 0.4, clamping 0.12 / 0.97.
    "octomap": (logit(0.7), logit(0.4), logit(0.12), logit(0.97)),
    # Cartographer's 2D probability grid: hit 0.55, miss 0.49, probabilities clamped to [0.1, 0.9].
    "cartographer": (logit(0.55), logit(0.49), logit(0.1), logit(0.9)),
    # The Coursera robotics course: l_occ 1, l_free 0.5, clamped to +-100.
    "coursera": (1.0, -0.5, -100.0, 100.0),
    # The seed notes' int8 accumulator: +-9 per update, saturating on [-128, 127]. The values are
    # integers, so float32 storage reproduces the int8 arithmetic exactly.
    "int8": (9.0, -9.0, -128.0, 127.0),
}

#: The preset names as a type (pydantic and the OpenAPI spec need a Literal): `OCCUPANCY_PRESETS`' keys.
OccupancyPreset = Literal["octomap", "cartographer", "coursera", "int8"]
assert set(get_args(OccupancyPreset)) == set(OCCUPANCY_PRESETS)  # a new preset goes in both


class OccupancyParams(BaseModel):
    """Log-odds update parameters. Give a preset, log-odds values, or probabilities.

    Explicit values override the preset's. A value may be given as log-odds (`l_hit`) or as a
    probability (`p_hit`), not both. After validation the `l_*` fields always hold the values in use.
    The thresholds also classify a counts map's cells (by hits / (hits + misses)); a `MapConfig`
    that keeps the occupancy layer needs the clamp to reach past them (`unreachable_state`).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    preset: OccupancyPreset = "octomap"
    l_hit: float | None = Field(strict=True, default=None, description="log-odds added for a hit (> 0)")
    l_miss: float | None = Field(strict=True, default=None, description="log-odds added for a miss (< 0)")
    l_min: float | None = Field(strict=True, default=None, description="lower clamp of a cell's log-odds")
    l_max: float | None = Field(strict=True, default=None, description="upper clamp of a cell's log-odds")
    p_hit: float | None = Field(
        strict=True, default=None, gt=0, lt=1, description="hit probability, instead of l_hit"
    )
    p_miss: float | None = Field(
        strict=True, default=None, gt=0, lt=1, description="miss probability, instead of l_miss"
    )
    p_min: float | None = Field(
        strict=True, default=None, gt=0, lt=1, description="lower clamp as a probability"
    )
    p_max: float | None = Field(
        strict=True, default=None, gt=0, lt=1, description="upper clamp as a probability"
    )
    occupied_thresh: float = Field(
        strict=True, default=0.65, gt=0, lt=1, description="p above this is `occupied`"
    )
    free_thresh: float = Field(strict=True, default=0.196, gt=0, lt=1, description="p below this is `free`")

    @model_validator(mode="after")
    def _resolve(self, info: ValidationInfo) -> OccupancyParams:
        hit, miss, lo, hi = OCCUPANCY_PRESETS[self.preset]
        resolved = []
        for name, default in (("hit", hit), ("miss", miss), ("min", lo), ("max", hi)):
            l_val = getattr(self, f"l_{name}")
            p_val = getattr(self, f"p_{name}")
            if l_val is not None and p_val is not None:
                raise ValueError(f"give l_{name} or p_{name}, not both")
            if p_val is not None:
                l_val = logit(p_val)
            resolved.append(default if l_val is None else float(l_val))
        hit, miss, lo, hi = resolved
        if not all(math.isfinite(v) for v in resolved):
            raise ValueError("occupancy parameters must be finite")
        # A map stored before the bound existed still loads (its cells are what they are).
        if not (info.context or {}).get(STORED_CONFIG) and any(abs(v) > MAX_LOG_ODDS for v in resolved):
            raise ValueError(f"occupancy log-odds must lie within +-{MAX_LOG_ODDS:g}")
        if hit <= 0:
            raise ValueError(f"l_hit must be positive (p_hit > 0.5), got {hit}")
        if miss >= 0:
            raise ValueError(f"l_miss must be negative (p_miss < 0.5), got {miss}")
        if not (info.context or {}).get(STORED_CONFIG):
            for name, step in (("l_hit", hit), ("l_miss", miss)):
                # Added to an unknown cell's 0 and stored, such a step is 0 again: no cell would move.
                if _vanishes_in_float32(step):
                    raise ValueError(
                        f"{name} {step:g} is 0 as a cell stores log-odds (float32): it would change "
                        f"no cell (|{name}| must be at least {_FLOAT32_TINIEST:g})"
                    )
        if not lo < 0 < hi:
            # Said both ways: a clamp given as p_min / p_max is refused in the terms it was given in.
            raise ValueError(
                f"the clamp must satisfy l_min < 0 < l_max (p_min < 0.5 < p_max), got l_min {lo:g}, "
                f"l_max {hi:g} (p_min {probability(lo):.6g}, p_max {probability(hi):.6g})"
            )
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError("free_thresh must be below occupied_thresh")
        # Store the resolved values; probabilities are derived, so drop them to keep one truth.
        object.__setattr__(self, "l_hit", hit)
        object.__setattr__(self, "l_miss", miss)
        object.__setattr__(self, "l_min", lo)
        object.__setattr__(self, "l_max", hi)
        for name in ("p_hit", "p_miss", "p_min", "p_max"):
            object.__setattr__(self, name, None)
        return self

    def unreachable_state(self) -> str | None:
        """Why no cell of a map's occupancy layer could ever be occupied, or free, under these
        parameters (its clamp stops at or short of a threshold), else None.

        A clamp that keeps every cell on one side of a threshold makes that state unreachable: with
        p_max 0.6 and occupied_thresh 0.65 the nav2 export of a building had no wall, and nothing
        said why. Judged by the p a cell at the clamp has as stored (`stored_probability`), as
        `GridMap.classify_probability` judges it: in double precision a clamp a hair past a
        threshold may be on it, or short of it, in float32 (p_max 0.9000000001 against 0.9 made a
        map with no occupied cell), and one on it may be past it (Cartographer's p_min 0.1 with
        free_thresh 0.1 was refused, though its cells become free). Only the occupancy layer's
        log-odds are clamped: `MapConfig` asks this of a map that keeps it."""
        _, _, lo, hi = self.resolved()
        p_max, p_min = stored_probability(hi), stored_probability(lo)
        if p_max <= self.occupied_thresh:
            stored = _as_stored(probability(hi) > self.occupied_thresh, p_max)
            return (
                f"the clamp p_max {probability(hi):.6g} (l_max {hi:g}{stored}) is not above "
                f"occupied_thresh {self.occupied_thresh:.12g}: no cell could ever be occupied (raise "
                "the clamp or lower occupied_thresh)"
            )
        if p_min >= self.free_thresh:
            stored = _as_stored(probability(lo) < self.free_thresh, p_min)
            return (
                f"the clamp p_min {probability(lo):.6g} (l_min {lo:g}{stored}) is not below "
                f"free_thresh {self.free_thresh:.12g}: no cell could ever be free (lower the clamp "
                "or raise free_thresh)"
            )
        return None

    def same_params_as(self, other: OccupancyParams) -> bool:
        """Whether `other` updates and classifies cells as these parameters do: every value in use
        equal. The `preset` only names where the values not given explicitly came from: once they
        are resolved (`l_*`), it changes no cell, so `{"preset": "int8"}` is the same as int8's four
        values written out under any preset name."""
        return not _differences("", self, other)

    def resolved(self) -> tuple[float, float, float, float]:
        """(l_hit, l_miss, l_min, l_max) in use: validation resolved all four (never None after it)."""
        hit, miss, lo, hi = self.l_hit, self.l_miss, self.l_min, self.l_max
        if hit is None or miss is None or lo is None or hi is None:  # made by model_construct
            raise ValueError("occupancy parameters that were not validated have no log-odds")
        return hit, miss, lo, hi


#: Fields of a configuration's sections that make no other map: an occupancy `preset` only names
#: where the values not given came from (`OccupancyParams.same_params_as`).
_NAMING_FIELDS = frozenset({"preset"})


def _differences(prefix: str, mine: BaseModel, theirs: BaseModel) -> list[str]:
    """`mine`'s fields whose value `theirs` does not share, but those in _NAMING_FIELDS, each as
    `<prefix><field> <mine>, not <theirs>`."""
    return [
        f"{prefix}{name} {getattr(mine, name)!r}, not {getattr(theirs, name)!r}"
        for name in type(mine).model_fields
        if name not in _NAMING_FIELDS and getattr(mine, name) != getattr(theirs, name)
    ]


def _as_stored(past_in_double: bool, stored: float) -> str:
    """For a clamp that is past its threshold in double precision, refused as cells store it: what
    its probability is there (else nothing: the probability in double precision says it all)."""
    return f"; p {stored:.9g} as a cell stores it, in float32" if past_in_double else ""


class BeamModelParams(BaseModel):
    """The inverse range sensor model of Probabilistic Robotics (table 9.2), used when
    `sensor_model` is `beam`. Occupied and free cells get the occupancy layer's l_hit / l_miss."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    alpha: float = Field(
        strict=True,
        default=0.1,
        gt=0,
        allow_inf_nan=False,
        description=f"obstacle thickness in metres; at most {MAX_BAND_CELLS} cells",
    )
    beta: float = Field(strict=True, default=0.0175, gt=0, lt=math.pi, description="beam width in radians")


class TsdfParams(BaseModel):
    """Truncated signed distance fusion along each beam."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    truncation: float = Field(
        strict=True,
        default=0.2,
        gt=0,
        allow_inf_nan=False,
        description=f"truncation distance t in metres; at most {MAX_BAND_CELLS} cells",
    )
    max_weight: float = Field(
        strict=True,
        default=1000.0,
        gt=0,
        le=MAX_TSDF_WEIGHT,
        description="cap on a cell's accumulated weight",
    )

    @field_validator("max_weight")
    @classmethod
    def _weight_holds_in_float32(cls, max_weight: float, info: ValidationInfo) -> float:
        """A cap that a float32 weight rounds to 0 makes every fused cell's weight 0, which is never
        observed: the TSDF layer would observe nothing. A stored map keeps its configuration."""
        if _vanishes_in_float32(max_weight) and not (info.context or {}).get(STORED_CONFIG):
            raise ValueError(
                f"max_weight {max_weight:g} is 0 as a cell's weight is stored (float32): no cell would "
                f"ever be observed (it must be at least {_FLOAT32_TINIEST:g})"
            )
        return max_weight


class MapConfig(BaseModel):
    """Everything that defines how a map stores and integrates scans."""

    # Its numbers, and its parameters' (`OccupancyParams`, `BeamModelParams`, `TsdfParams`), are
    # `strict`: a JSON boolean or string is refused, as in every other body of the API, where lax
    # validation took `{"max_tiles": true}` as a map of 1 tile and `"0.1"` as a number. An integer
    # still counts as a number for a float.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    resolution: float = Field(strict=True, default=0.05, gt=0.001, le=100.0, description="metres per cell")
    tile_size: int = Field(
        strict=True, default=256, ge=16, le=4096, description="cells per tile side, a power of two"
    )
    max_tiles: int = Field(
        strict=True,
        default=4096,
        ge=1,
        le=1_000_000,
        description="cap on tiles per map; a scan that needs more is rejected",
    )
    # A tuple, not a list: the model is frozen, but a list's contents could still be changed in
    # place past validation (emptied, a layer twice, a name of no layer), and a map made of it kept
    # nothing or failed with a KeyError. A JSON array or a list is taken, and read back as a tuple.
    # Its rules (`_layers_are_a_set`) in the spec too, where a generated client or form reads them.
    layers: tuple[LayerName, ...] = Field(
        default=ALL_LAYERS, json_schema_extra={"minItems": 1, "uniqueItems": True}
    )
    occupancy: OccupancyParams = Field(default_factory=OccupancyParams)
    sensor_model: Literal["ray", "beam"] = "ray"
    traversal: Literal["exact", "bresenham"] = "exact"
    update: Literal["per_scan", "per_ray"] = "per_scan"
    no_return_range: float = Field(
        strict=True,
        default=0.0,
        ge=0,
        le=1000.0,
        description="metres of a no-return beam to clear as free; 0 = ignore",
    )
    # Their defaults validated too: the band limit depends on the resolution.
    beam: BeamModelParams = Field(default_factory=BeamModelParams, validate_default=True)
    tsdf: TsdfParams = Field(default_factory=TsdfParams, validate_default=True)

    @model_validator(mode="before")
    @classmethod
    def _newer_services_fields_left_out(cls, data: Any, info: ValidationInfo) -> Any:
        """Read from a service's answer (`ANSWERED_CONFIG`), the configuration without the fields,
        its own or its sections', that this version does not know: a newer service's new setting
        made every answer holding a map's configuration (`get_map`, `create_map`, an upload's) fail
        in an older client ("config.new_field: Extra inputs are not permitted")."""
        if not ((info.context or {}).get(ANSWERED_CONFIG) and isinstance(data, dict)):
            return data
        known = {name: value for name, value in data.items() if name in cls.model_fields}
        for name, value in known.items():
            section = cls.model_fields[name].annotation
            if isinstance(value, dict) and isinstance(section, type) and issubclass(section, BaseModel):
                known[name] = {key: v for key, v in value.items() if key in section.model_fields}
        return known

    @model_validator(mode="before")
    @classmethod
    def _stored_infinite_band(cls, data: Any, info: ValidationInfo) -> Any:
        """A stored configuration from before these fields had to be finite may hold an infinite
        `tsdf.truncation`, `beam.alpha` or `tsdf.max_weight`, which JSON stores as null. A map with
        an infinite band could not integrate any scan (its reach was infinite), so it holds nothing
        a finite width would change: it loads with the width at today's limit. An infinite weight
        cap loads as MAX_TSDF_WEIGHT, which no float32 weight reaches by fusing. A warning says so,
        unless the configuration is only tried as a stored one (`TRIED_AS_STORED`)."""
        if not ((info.context or {}).get(STORED_CONFIG) and isinstance(data, dict)):
            return data
        data = dict(data)
        resolution = data.get("resolution", cls.model_fields["resolution"].default)
        # Not a number (null, a string, a container: the resolution's own validation refuses it),
        # there is no band limit to load the widths at: a PUT's body of {"resolution": null},
        # tried as a stored configuration once refused as a new one, was a TypeError, a 500.
        if isinstance(resolution, bool) or not isinstance(resolution, (int, float)):
            return data
        limits = [(section, name, MAX_BAND_CELLS * resolution) for section, name in _BAND_WIDTHS]
        for section, name, limit in [*limits, ("tsdf", "max_weight", MAX_TSDF_WEIGHT)]:
            params = data.get(section)
            if isinstance(params, dict) and name in params and params[name] is None:
                # A refused PUT body tried as stored logged this for every request, where no map
                # was loaded.
                if not (info.context or {}).get(TRIED_AS_STORED):
                    log.warning(
                        "stored map configuration: %s.%s was infinite (stored as null); loaded as %g, "
                        "today's limit", section, name, limit,
                    )  # fmt: skip
                data[section] = {**params, name: limit}
        return data

    @field_validator("occupancy")
    @classmethod
    def _clamp_reaches_the_thresholds(
        cls, occupancy: OccupancyParams, info: ValidationInfo
    ) -> OccupancyParams:
        """A map that keeps the occupancy layer needs a clamp past both thresholds
        (`OccupancyParams.unreachable_state`); one without it classifies by the count model's
        p = hits / (hits + misses), which reaches 0 and 1, or not at all (TSDF), whatever the clamp.
        (`layers` is validated before `occupancy`: absent here only when it was invalid.) A stored
        map keeps its configuration."""
        if "occupancy" in info.data.get("layers", ()) and not (info.context or {}).get(STORED_CONFIG):
            reason = occupancy.unreachable_state()
            if reason is not None:
                raise ValueError(reason)
        return occupancy

    # Each rule below is a validator of the field it is about, so that a refusal is located there
    # (`errors[].loc` of a 422: `["body", "tile_size"]`), and listed beside every other problem: as
    # checks of the whole model, they were located at the body and ran only once all else was valid.

    @field_validator("tile_size", "max_tiles", mode="before")
    @classmethod
    def _numpy_integer_is_an_int(cls, value: Any) -> Any:
        """A NumPy integer counts as the int it holds (a tile size computed as an `np.int64`), as a
        NumPy float counts as a number for the float fields: strict validation refused it, where
        the REST client sends it. A NumPy bool is no integer to NumPy either: still refused."""
        return int(value) if isinstance(value, np.integer) else value

    @field_validator("tile_size")
    @classmethod
    def _tile_size_is_a_power_of_two(cls, tile_size: int) -> int:
        if tile_size & (tile_size - 1):
            raise ValueError(f"tile_size must be a power of two, got {tile_size}")
        return tile_size

    @field_validator("layers")
    @classmethod
    def _layers_are_a_set(cls, layers: tuple[LayerName, ...]) -> tuple[LayerName, ...]:
        if not layers:
            raise ValueError("a map needs at least one layer")
        if len(set(layers)) != len(layers):
            raise ValueError("layers must not repeat")
        return layers

    @field_validator("tsdf", "beam")
    @classmethod
    def _band_within_its_cells(
        cls, params: TsdfParams | BeamModelParams, info: ValidationInfo
    ) -> TsdfParams | BeamModelParams:
        """`tsdf.truncation` and `beam.alpha` are at most MAX_BAND_CELLS cells of the map's resolution
        (validated before them: absent here only when it was invalid), and the truncation is more
        than 0 cells. A stored map keeps its own."""
        resolution = info.data.get("resolution")
        if resolution is None or (info.context or {}).get(STORED_CONFIG):
            return params
        limit = MAX_BAND_CELLS * resolution
        for section, name in _BAND_WIDTHS:
            value = getattr(params, name, None)
            if section == info.field_name and value is not None and value > limit:
                # To 15 digits, not :g's 6: 12.8000001 m at 0.05 m was "12.8 m is more than 256
                # cells ... (at most 12.8 m)". 15 leave out a float's rounding (17.92 for 256 x 0.07).
                raise ValueError(
                    f"{section}.{name} {value:.15g} m is more than {MAX_BAND_CELLS} cells at resolution "
                    f"{resolution:.15g} m (at most {limit:.15g} m)"
                )
        # Scans divide each band cell's distance by the truncation in cells: one so small that
        # `truncation / resolution` underflows to 0 made every scan with a return fail with
        # "division by zero".
        if isinstance(params, TsdfParams) and params.truncation / resolution == 0:
            raise ValueError(
                f"tsdf.truncation {params.truncation:g} m is 0 cells at resolution {resolution:g} m (the "
                "division underflows): no scan could be fused; give a positive number of cells"
            )
        return params

    def has(self, layer: LayerName) -> bool:
        """Whether the map keeps `layer` (`occupancy`, `counts` or `tsdf`)."""
        return layer in self.layers

    def same_map_as(self, other: MapConfig) -> bool:
        """Whether `other` configures the same map: every field equal, `layers` as a set and
        `occupancy` by the values in use (`OccupancyParams.same_params_as`). The order of the layers
        is only the order a map lists and stores them in (`["tsdf", "occupancy"]` keeps the same
        cells as `["occupancy", "tsdf"]`), and a list built from a set has any order; a preset's
        name only says where values came from (a map of the `int8` preset is the map of its values
        written out: compared by the name too, a `PUT` of them was a 409)."""
        return not self.differences(other)

    def differences(self, other: MapConfig) -> list[str]:
        """How `other` configures another map than this one (`same_map_as`): for each field that
        differs, `<field> <this value>, not <other's>`, a section's fields dotted
        (`occupancy.l_hit 9.0, not 8.0`); none for the same map. A 409 for another configuration
        said only that it differed, where the difference may not be in the body sent (`{}` against
        a map a robot's scan made with the server's `--config`)."""
        found: list[str] = []
        for name in type(self).model_fields:
            mine, theirs = getattr(self, name), getattr(other, name)
            if isinstance(mine, BaseModel) and isinstance(theirs, BaseModel):
                found += _differences(f"{name}.", mine, theirs)
            elif name == "layers":
                if set(mine) != set(theirs):  # a set: the order is only the one a map lists them in
                    found.append(f"layers {list(mine)!r}, not {list(theirs)!r}")
            elif mine != theirs:
                found.append(f"{name} {mine!r}, not {theirs!r}")
        return found

    @property
    def has_cell_layers(self) -> bool:
        """Whether the map keeps a layer that scans update with hits and misses (occupancy or
        counts), as opposed to the TSDF alone."""
        return self.has("occupancy") or self.has("counts")

    @property
    def traces_rays(self) -> bool:
        """Whether scans are traced beam by beam into hits and misses: the ray model with a cell
        layer. (The TSDF band and the beam model visit only a few cells around each return.)"""
        return self.sensor_model == "ray" and self.has_cell_layers


def is_immutable(config: MapConfig) -> bool:
    """Whether nothing can change `config`: it and its parameters are of this module's frozen
    classes, not of subclasses, which may not be frozen. Such a configuration can be shared."""
    return (
        type(config) is MapConfig
        and type(config.occupancy) is OccupancyParams
        and type(config.beam) is BeamModelParams
        and type(config.tsdf) is TsdfParams
    )
