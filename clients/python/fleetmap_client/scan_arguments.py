"""The checks of a scan's `seq` and `stamp` arguments that both clients make before sending
anything (`ScanPublisher.publish`, `FleetmapClient.post_scan`): one rule, one error for the same
mistake, whichever way the robot sends its scans."""

from __future__ import annotations

import math
import numbers

from fleetmap.wire import SEQ_LIMIT


def checked_seq(seq: object) -> int:
    """`seq` as a Python int: TypeError unless it is an integer (a NumPy one too; not a bool),
    ValueError outside [0, 2**63), the seqs the wire carries."""
    if isinstance(seq, bool) or not isinstance(seq, numbers.Integral):
        raise TypeError(f"seq must be an integer, got {seq!r}")
    value = int(seq)
    if not 0 <= value < SEQ_LIMIT:
        raise ValueError(f"seq must be in [0, 2**63), got {value}")
    return value


def checked_stamp(stamp: object) -> float:
    """`stamp` (seconds) as a float: TypeError unless it is a number (not a bool), ValueError for
    one that is not finite."""
    if isinstance(stamp, bool) or not isinstance(stamp, numbers.Real):
        raise TypeError(f"stamp must be a number (seconds), got {stamp!r}")
    value = float(stamp)
    if not math.isfinite(value):
        raise ValueError(f"stamp must be finite, got {value}")
    return value


__all__ = ["checked_seq", "checked_stamp"]
