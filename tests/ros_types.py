"""rosbags' ROS 2 Jazzy message definitions, with map_msgs added: the independent decoder the ROS
tests check fleetmap's CDR and type hashes against.

rosbags ships the common interfaces (nav_msgs, sensor_msgs, ...) but not map_msgs, whose
`OccupancyGridUpdate` fleetmap publishes on `<map topic>_updates`; it is registered here from its
definition (map_msgs/msg/OccupancyGridUpdate.msg of ros-planning/navigation_msgs, the package ROS 2
distributions ship), so that rosbags decodes it and computes its RIHS01 type hash as rosidl does.
"""

from __future__ import annotations

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

GRID = "nav_msgs/msg/OccupancyGrid"
GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
GRID_UPDATE_MSG = """std_msgs/Header header
int32 x
int32 y
uint32 width
uint32 height
int8[] data
"""

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
TYPESTORE.register(get_types_from_msg(GRID_UPDATE_MSG, GRID_UPDATE))
