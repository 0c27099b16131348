"""glibc's malloc arenas, limited for a long-running service.

glibc gives each thread that allocates an arena of its own, up to 8 a core. The service's Zenoh,
HTTP, integration and journal threads each got one, and after minutes of churn those held about a
tenth more resident memory than 2 arenas do, at no measured cost in speed (`make bench-service`,
docs/benchmark-history.md, "Long-life memory"). `MALLOC_ARENA_MAX=2` in the environment does this,
but only for processes started with it: `limit_malloc_arenas` does it from inside, with
`mallopt(M_ARENA_MAX)`, for every deployment.

glibc fixes its arena limit when a process first needs more than 8 arenas, so the call takes effect
when made before that: `fleetmap serve` makes it first thing, before its threads exist.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: The service's arenas: the main one and one more shared by its threads.
SERVICE_ARENAS = 2
#: glibc's `mallopt` parameter number for the arena limit (malloc.h: `#define M_ARENA_MAX -8`).
M_ARENA_MAX = -8


def limit_malloc_arenas(arenas: int = SERVICE_ARENAS) -> bool:
    """Limit glibc's malloc to `arenas` arenas for this process; returns whether it did.

    Does nothing (False) where `MALLOC_ARENA_MAX` is set in the environment (glibc applied the
    operator's choice at start; it wins), off Linux, or where the C library is not glibc (musl has
    no arenas to limit) or refuses."""
    if os.environ.get("MALLOC_ARENA_MAX") or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not found, or a C library without mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, arenas))  # 1 on success
