"""What a beam is and what an update does to a cell: the codes the kernels hand each other.

Beam kinds come from `scan_geometry.scan_rays` and steer every trace; cell kinds come out of the
sensor models and the traces and tell the apply (`update`) whether a cell is a hit or a miss.
"""

from __future__ import annotations

#: Per-beam kinds (from `scan_geometry.scan_rays`, given to the traces).
BEAM_SKIP = 0
BEAM_HIT = 1
BEAM_CLEAR = 2

#: Per-cell update kinds produced by the sensor models. They are bit flags so that per-scan marking
#: can OR them in without a branch: a cell marked `CELL_HIT` (alone or with a miss) is a hit.
CELL_MISS = 1
CELL_HIT = 2
