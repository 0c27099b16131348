"""fleetmap: occupancy, count and TSDF maps built from 2D laser scans with known poses.

The engine is usable on its own as a library; its public names are importable from here:

    from fleetmap import GridMap, MapConfig, Scan

    gmap = GridMap(MapConfig(resolution=0.05))
    gmap.integrate(Scan.from_fan((x, y, theta), angle_min, angle_increment, ranges, 0.05, 30.0))
    gmap.cells([[2.0, 2.5]])["probability"]

The names are imported lazily, on first use: `import fleetmap.wire` (what a robot's publisher
needs) must not load numba and compile the engine's kernels, and a program that only reads
configurations should not either. The submodules (`fleetmap.grid_map`, `fleetmap.export`,
`fleetmap.datasets`, `fleetmap.sim`, ...) hold everything else.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what type checkers and IDEs see; at run time `__getattr__` imports on demand
    from fleetmap.cell_queries import (
        MAX_RAY_CELLS,
        MAX_RAY_WALK,
        MAX_RAYS,
        RAY_MAX_RANGE,
        RAY_OCCUPIED,
        RAY_STATUS_NAMES,
        RAY_UNKNOWN,
        STATE_FREE,
        STATE_NAMES,
        STATE_OCCUPIED,
        STATE_UNKNOWN,
    )
    from fleetmap.config import (
        OCCUPANCY_PRESETS,
        BeamModelParams,
        LayerName,
        MapConfig,
        OccupancyParams,
        TsdfParams,
        logit,
        probability,
    )
    from fleetmap.datasets import Dataset, DatasetError, load_dataset
    from fleetmap.export import Window, known_window, write_build_outputs
    from fleetmap.grid_map import (
        REGION_LAYERS,
        GridMap,
        IntegrationResult,
        LayerUnavailableError,
        RaycastResult,
        RayLimitError,
        WindowCleared,
    )
    from fleetmap.scan import Pose2D, Scan, ScanError
    from fleetmap.tiles import TileLimitError

#: Public name -> the module that defines it.
_EXPORTS = {
    "Scan": "fleetmap.scan",
    "Pose2D": "fleetmap.scan",
    "ScanError": "fleetmap.scan",
    "MapConfig": "fleetmap.config",
    "OccupancyParams": "fleetmap.config",
    "BeamModelParams": "fleetmap.config",
    "TsdfParams": "fleetmap.config",
    "LayerName": "fleetmap.config",
    "OCCUPANCY_PRESETS": "fleetmap.config",
    "logit": "fleetmap.config",
    "probability": "fleetmap.config",
    "GridMap": "fleetmap.grid_map",
    "IntegrationResult": "fleetmap.grid_map",
    "LayerUnavailableError": "fleetmap.grid_map",
    "REGION_LAYERS": "fleetmap.grid_map",
    "STATE_UNKNOWN": "fleetmap.cell_queries",
    "STATE_FREE": "fleetmap.cell_queries",
    "STATE_OCCUPIED": "fleetmap.cell_queries",
    "STATE_NAMES": "fleetmap.cell_queries",
    "MAX_RAYS": "fleetmap.cell_queries",
    "MAX_RAY_CELLS": "fleetmap.cell_queries",
    "MAX_RAY_WALK": "fleetmap.cell_queries",
    "RAY_MAX_RANGE": "fleetmap.cell_queries",
    "RAY_OCCUPIED": "fleetmap.cell_queries",
    "RAY_STATUS_NAMES": "fleetmap.cell_queries",
    "RAY_UNKNOWN": "fleetmap.cell_queries",
    "RaycastResult": "fleetmap.grid_map",
    "RayLimitError": "fleetmap.grid_map",
    "TileLimitError": "fleetmap.tiles",
    "Window": "fleetmap.export",
    "WindowCleared": "fleetmap.grid_map",
    "known_window": "fleetmap.export",
    "write_build_outputs": "fleetmap.export",
    "Dataset": "fleetmap.datasets",
    "DatasetError": "fleetmap.datasets",
    "load_dataset": "fleetmap.datasets",
}

__all__ = [
    "BeamModelParams",
    "Dataset",
    "DatasetError",
    "GridMap",
    "IntegrationResult",
    "LayerName",
    "LayerUnavailableError",
    "MAX_RAYS",
    "MAX_RAY_CELLS",
    "MAX_RAY_WALK",
    "MapConfig",
    "OCCUPANCY_PRESETS",
    "OccupancyParams",
    "Pose2D",
    "RAY_MAX_RANGE",
    "RAY_OCCUPIED",
    "RAY_STATUS_NAMES",
    "RAY_UNKNOWN",
    "REGION_LAYERS",
    "RayLimitError",
    "RaycastResult",
    "STATE_FREE",
    "STATE_NAMES",
    "STATE_OCCUPIED",
    "STATE_UNKNOWN",
    "Scan",
    "ScanError",
    "TileLimitError",
    "TsdfParams",
    "Window",
    "WindowCleared",
    "known_window",
    "load_dataset",
    "logit",
    "probability",
    "write_build_outputs",
]
assert set(__all__) == set(_EXPORTS), "one list of public names"


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'fleetmap' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups find it without coming here
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
