"""glibc's malloc arenas, limited for a long-running service.

glibc gives each thread that allocates an arena of its own, up to 8 a core. The service's Zenoh,
HTTP, integration and journal threads each got one, and after minutes of churn those held about a
tenth more resident memory than 2 arenas do, at no measured cost in speed (`make bench-service`,
docs/benchmark-history.md, "Long-life memory"). `MALLOC_ARENA_MAX=2` in the environment does this,
but only for processes started with it: `limit_malloc_arenas` does it from inside, with
`mallopt(M_ARENA_MAX)`, for every deployment.

glibc fixes its arena limit when a process first needs more than 8 arenas, so the call takes effect
when made before that: `fleetmap serve` makes it first thing, before its threads exist.

`fix_mmap_threshold` keeps glibc from moving the size from which a block gets a mapping of its own
(given back to the system as soon as it is freed). glibc raises that threshold to the size of each
mapped block freed, up to 32 MiB: once a map's first tile pools (up to 32 MiB) or a snapshot's
buffers had been freed, numpy arrays up to that size came from the arenas, whose freed holes the
heap could not give back. Fixed at 1 MiB (`MALLOC_MMAP_THRESHOLD_=1048576` does the same for a
process started with it), the service held about 30 MB less under the long-life soak's churn, 40
minutes side by side (docs/benchmark-history.md, "Thirtieth session"), at no measured cost.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
from typing import Any

#: The service's arenas: the main one and one more shared by its threads.
SERVICE_ARENAS = 2
#: glibc's `mallopt` parameter number for the arena limit (malloc.h: `#define M_ARENA_MAX -8`).
M_ARENA_MAX = -8


#: Bytes from which the service's blocks get a mapping of their own (`fix_mmap_threshold`).
SERVICE_MMAP_THRESHOLD = 1 << 20
#: glibc's `mallopt` parameter number for the mmap threshold (malloc.h: `#define M_MMAP_THRESHOLD -3`).
M_MMAP_THRESHOLD = -3


def limit_malloc_arenas(arenas: int = SERVICE_ARENAS) -> bool:
    """Limit glibc's malloc to `arenas` arenas for this process; returns whether it did.

    Does nothing (False) where `MALLOC_ARENA_MAX` is set in the environment (glibc applied the
    operator's choice at start; it wins), off Linux, or where the C library is not glibc (musl has
    no arenas to limit) or refuses."""
    return _mallopt("MALLOC_ARENA_MAX", M_ARENA_MAX, arenas)


def fix_mmap_threshold(threshold: int = SERVICE_MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at `threshold` bytes for this process (glibc then never moves it);
    returns whether it did. Does nothing (False) where `MALLOC_MMAP_THRESHOLD_` is set in the
    environment, off Linux, or where the C library is not glibc or refuses."""
    return _mallopt("MALLOC_MMAP_THRESHOLD_", M_MMAP_THRESHOLD, threshold)


def _mallopt(variable: str, parameter: int, value: int) -> bool:
    """glibc's `mallopt(parameter, value)`, unless the environment sets `variable` (the operator's
    choice, which glibc applied at start, wins); whether it was made and succeeded."""
    if os.environ.get(variable) or not sys.platform.startswith("linux"):
        return False
    mallopt = _libc_mallopt()
    return mallopt is not None and bool(mallopt(parameter, value))  # 1 on success


@functools.cache
def _libc_mallopt() -> Any:
    """glibc's `mallopt`, or None where the C library has none (musl) or cannot be found. glibc by
    its soname first: `ctypes.util.find_library` runs `ldconfig -p` in a child process, one at each
    call, which a start-up need not spawn (a test that waits for the service's compile child found
    ldconfig instead)."""
    for find in (lambda: "libc.so.6", lambda: ctypes.util.find_library("c")):
        name = find()
        if name is None:
            continue
        try:
            mallopt = ctypes.CDLL(name).mallopt
        except (OSError, AttributeError):  # not found, or a C library without mallopt
            continue
        mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        mallopt.restype = ctypes.c_int
        return mallopt
    return None
