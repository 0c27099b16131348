"""Python clients of the fleetmap service.

* `fleetmap_client.publisher.ScanPublisher`: the robot side, publishing scans over Zenoh, and
  confirming they are in the map (`flush`: a `DeliveryReport`).
* `fleetmap_client.rest.FleetmapClient`: a typed client of the REST API, for programs.
* `fleetmap_client.cli`: the `fleetmap replay` and `fleetmap sim` commands, which run
  `fleetmap_client.replay.replay` and `fleetmap_client.sim.run_sim`.

Submodules are imported lazily so that a robot that only publishes does not import httpx, and a
program that only reads maps does not start Zenoh.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what type checkers and IDEs see; at run time `__getattr__` imports on demand
    from fleetmap_client.delivery import DeliveryReport
    from fleetmap_client.publisher import DeliveryUnsupported, PublisherClosed, ScanPublisher
    from fleetmap_client.rest import FleetmapClient, FleetmapError, MapChanged

_EXPORTS = {
    "ScanPublisher": "fleetmap_client.publisher",
    "DeliveryReport": "fleetmap_client.delivery",
    "DeliveryUnsupported": "fleetmap_client.publisher",
    "PublisherClosed": "fleetmap_client.publisher",
    "FleetmapClient": "fleetmap_client.rest",
    "FleetmapError": "fleetmap_client.rest",
    "MapChanged": "fleetmap_client.rest",
}

__all__ = [
    "DeliveryReport",
    "DeliveryUnsupported",
    "FleetmapClient",
    "FleetmapError",
    "MapChanged",
    "PublisherClosed",
    "ScanPublisher",
]
assert set(__all__) == set(_EXPORTS), "one list of public names"


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'fleetmap_client' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
