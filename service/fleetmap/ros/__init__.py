"""ROS 2 over rmw_zenoh: message encodings and key expressions, no ROS installation needed.

`cdr` reads and writes CDR (the byte layout of every ROS 2 message), `rmw_zenoh` the key expressions
and attachments rmw_zenoh puts around them. The rest of the package decodes the messages fleetmap
reads and turns a robot's TF into sensor poses; `fleetmap.ros.ingest` is the Zenoh edge.
"""
