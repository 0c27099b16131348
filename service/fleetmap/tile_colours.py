"""The colours of map tiles (tile_render's docstring, "Colours", says what each layer shows): a
lookup table per layer and the index of each value in it (`colour_index`), so that a tile's RGBA
pixels are `lut[index]`."""

from __future__ import annotations

import math

import numpy as np

from fleetmap.cell_queries import STATE_FREE, STATE_OCCUPIED
from fleetmap.config import log_odds_to_probability
from fleetmap.export import probability_grey
from fleetmap.grid_map import GridMap

#: A hit / miss count at or above this is the top of the colour ramp (log scale below it).
COUNT_SCALE = 1000


def _ramp_lut(anchors: list[tuple[int, int, int]]) -> np.ndarray:
    """256 RGBA entries: 0 transparent, 1..255 interpolated through `anchors`, opaque."""
    lut = np.zeros((256, 4), dtype=np.uint8)
    pos = np.linspace(0.0, 1.0, len(anchors))
    t = np.linspace(0.0, 1.0, 255)
    for c in range(3):
        lut[1:, c] = np.round(np.interp(t, pos, [a[c] for a in anchors]))
    lut[1:, 3] = 255
    return lut


#: Viridis sampled at 0, 0.1, ..., 1 (perceptually uniform, colour-blind safe).
_VIRIDIS = _ramp_lut([
    (68, 1, 84), (72, 36, 117), (65, 68, 135), (53, 95, 141), (42, 120, 142), (33, 145, 140),
    (34, 168, 132), (68, 191, 112), (122, 209, 81), (189, 223, 38), (253, 231, 37),
])  # fmt: skip
#: Blue - white - red (ColorBrewer RdBu ends).
_DIVERGING = _ramp_lut([(33, 102, 172), (247, 247, 247), (178, 24, 43)])
#: Index = `export.probability_grey` -> that grey; index 256 = unknown (transparent).
_GREY = np.zeros((257, 4), dtype=np.uint8)
_GREY[:256, :3] = np.arange(256, dtype=np.uint8)[:, None]
_GREY[:256, 3] = 255
#: By state code: unknown transparent, free near-white, occupied near-black.
_STATE = np.zeros((3, 4), dtype=np.uint8)
_STATE[STATE_FREE] = (245, 245, 245, 255)
_STATE[STATE_OCCUPIED] = (20, 20, 20, 255)


def _ramp_index(values: np.ndarray, scale: float) -> np.ndarray:
    """Ramp LUT indices for non-negative values on a log scale: 0 -> 0 (transparent), else 1..255,
    at `log1p(value) / log1p(scale)` of the ramp (the top for values at or past `scale`)."""
    v = values.astype(np.float32)
    # Divided in float64: a `tsdf.max_weight` below ~3e-39 (allowed down to float32's smallest
    # weight) made the float32 reciprocal of log1p(scale) infinite, so numpy warned on every render
    # and every weight under the cap took the top colour.
    t = np.minimum(np.log1p(v, dtype=np.float64) / math.log1p(scale), 1.0)
    idx = (1.0 + np.rint(t * 254.0)).astype(np.uint8)
    idx[~(v > 0)] = 0
    return idx


def colour_index(gmap: GridMap, layer: str, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """`(index, lut, transparent_index)`: RGBA = lut[index]."""
    if layer in ("probability", "log_odds"):
        # The probability the map reports for the cell (`/cells`), so the tile shows its grey.
        grey = probability_grey(log_odds_to_probability(grid))
        return np.nan_to_num(grey, nan=256).astype(np.uint16), _GREY, 256
    if layer == "state":
        return gmap.classify(grid), _STATE, 0
    if layer in ("hits", "misses"):
        return _ramp_index(grid, COUNT_SCALE), _VIRIDIS, 0
    if layer == "tsdf_weight":
        return _ramp_index(grid, gmap.config.tsdf.max_weight), _VIRIDIS, 0
    # tsdf in [-1, 1] -> 1..255; NaN (unobserved) -> 0.
    t = (np.clip(np.nan_to_num(grid, nan=0.0), -1.0, 1.0) + 1.0) * 127.0
    idx = (1.0 + np.rint(t)).astype(np.uint8)
    idx[np.isnan(grid)] = 0
    return idx, _DIVERGING, 0
