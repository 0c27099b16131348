"""`fleetmap serve`'s ROS 2 side (docs/ros.md): what the ROS options mean together (the domain id, the
frames of published maps, the checks of `--ros-*` given without what they need), and the ROS scan
ingest (`--ros-scans`) and map publisher (`--ros-publish-map`) started on the service's Zenoh
session, whose status `GET /healthz` shows with the session's (`zenoh_status`)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from fleetmap.api_models import ZENOH_ROS_MAPS, ZENOH_ROS_SCANS
from fleetmap.cli import CliError

if TYPE_CHECKING:
    from fleetmap.registry import MapRegistry
    from fleetmap.ros.ingest import RosScanIngest
    from fleetmap.zenoh_ingest import ZenohIngest


def ros_map_frame(args: argparse.Namespace, map_id: str) -> str:
    """The frame id of map `map_id`'s published grids: `--ros-map-frame`, else, for the map of
    `--ros-scans`, `--ros-fixed-frame` (the frame it builds that map in: a grid labelled `map` while
    its cells are in `world` would put it in the wrong place for nav2), else `map`. Another map
    (native robots') is not in that frame, so it is not labelled with it."""
    if args.ros_map_frame:
        return str(args.ros_map_frame)
    if map_id == args.ros_scans and args.ros_fixed_frame:
        return str(args.ros_fixed_frame)
    return "map"


def ros_domain(args: argparse.Namespace, environ: dict[str, str] | None = None) -> int:
    """The ROS domain id of `--ros-scans` and `--ros-publish-map`: `--ros-domain` (or
    FLEETMAP_ROS_DOMAIN), else ROS's own $ROS_DOMAIN_ID, else 0. Raises CliError for an unusable
    $ROS_DOMAIN_ID."""
    if args.ros_domain is not None:
        return int(args.ros_domain)
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    # ASCII digits only: str.isdigit() is also true of '²', which int() refuses, and of other
    # scripts' digits, which ROS's own strtoul reads as no number.
    if not (text.isascii() and text.isdigit()) or int(text) >= 2**32:
        raise CliError(f"$ROS_DOMAIN_ID={text!r}: expected a whole number (or give --ros-domain N)")
    return int(text)


def ros_options(args: argparse.Namespace, environ: dict[str, str] | None = None) -> tuple[int, str] | None:
    """(domain id, fixed frame) of `--ros-scans`, None without it (`ros_domain`). Raises CliError
    for an unusable $ROS_DOMAIN_ID, --ros-fixed-frame without --ros-scans, or --ros-domain with
    neither --ros-scans nor --ros-publish-map."""
    if args.ros_scans is None:
        if args.ros_fixed_frame is not None:
            raise CliError("--ros-fixed-frame needs --ros-scans MAP_ID")
        if args.ros_domain is not None and not args.ros_publish_map:
            raise CliError("--ros-domain needs --ros-scans MAP_ID or --ros-publish-map MAP_ID")
        return None
    return ros_domain(args, environ), args.ros_fixed_frame or "map"


def start_ros_scans(
    args: argparse.Namespace, options: tuple[int, str] | None, registry: MapRegistry, ingest: ZenohIngest
) -> RosScanIngest | None:
    """The ROS 2 scan ingest on the service's Zenoh session (`--ros-scans`; `options`: `ros_options`'),
    started; None without."""
    if options is None:
        return None
    from fleetmap.ros.ingest import RosScanIngest

    assert ingest.session is not None  # started
    domain, frame = options
    ros = RosScanIngest(registry, ingest.session, args.ros_scans, domain_id=domain, fixed_frame=frame)
    try:
        ros.start()
    except zenoh.ZError as exc:
        raise CliError(f"cannot subscribe to ROS 2 topics: {exc}") from None
    return ros


def start_ros_maps(args: argparse.Namespace, registry: Any, ingest: ZenohIngest) -> Any:
    """The `RosMapPublisher` of the `--ros-publish-map` maps on the ingest's session, started; None
    when no map is published to ROS 2."""
    if not args.ros_publish_map:
        return None
    from fleetmap.ros.map_publisher import RosMapOptions, RosMapPublisher

    assert ingest.session is not None  # started
    options = RosMapOptions(
        topics=tuple(args.ros_publish_map),
        domain_id=ros_domain(args),
        frame_id=args.ros_map_frame or "map",
        map_frames=tuple((spec.map_id, ros_map_frame(args, spec.map_id)) for spec in args.ros_publish_map),
        period=args.ros_map_period,
        distro=args.ros_distro,
    )
    publisher = RosMapPublisher(registry, ingest.session, options)
    publisher.start()
    return publisher


def zenoh_status(
    ingest: ZenohIngest, ros: RosScanIngest | None, ros_maps: Any
) -> Callable[[], dict[str, Any]]:
    """`GET /healthz`'s `zenoh`: the session's status, with the ROS ingest's under `ros` and the ROS
    map publisher's under `ros_maps` (`api_models.ZENOH_ROS_SCANS`, `ZENOH_ROS_MAPS`: withheld from a
    client that may not read)."""
    if ros is None and ros_maps is None:
        return ingest.status

    def status() -> dict[str, Any]:
        parts = ingest.status()
        if ros is not None:
            parts[ZENOH_ROS_SCANS] = ros.status()
        if ros_maps is not None:
            parts[ZENOH_ROS_MAPS] = ros_maps.status()
        return parts

    return status
