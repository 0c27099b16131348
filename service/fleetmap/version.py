"""The version of fleetmap that runs: `fleetmap --version` and `/metrics`' `fleetmap_build_info`."""

from __future__ import annotations

from importlib import metadata


def installed_version() -> str:
    """The installed package's version ("0.0.0" for a source tree run without being installed)."""
    try:
        return metadata.version("fleetmap")
    except metadata.PackageNotFoundError:
        return "0.0.0"
