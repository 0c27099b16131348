"""A memory budget shared by maps: the bytes all their tile pools may hold together.

`MapConfig.max_tiles` bounds one map; a service holding many maps also needs a bound on all of them,
or robots mapping new ground make it grow until the operating system kills it. Each `TileStore`
charged to a budget (`TileStore.charge`) reserves the bytes of every pool growth before it
allocates; when the budget cannot cover the tiles a scan needs, the scan is refused whole with a
`MemoryBudgetError` and its map is unchanged. A store's bytes return to the budget when its map is
deleted or replaced (`TileStore.uncharge`, even while a reader still holds it), or else when the
store is freed.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path

from fleetmap.tiles import TileLimitError


class MemoryBudgetError(TileLimitError):
    """The shared memory budget cannot hold the tiles a scan needs. The map was not changed."""


class MemoryBudget:
    """Bytes reserved against a limit (None: no limit, only counted). Thread-safe."""

    def __init__(self, limit: int | None) -> None:
        if limit is not None and limit <= 0:
            raise ValueError(f"a memory budget must be positive, got {limit}")
        self.limit = limit
        self.used = 0
        # Reentrant: a store's finalizer (`release`) may run from a garbage collection that an
        # allocation inside `reserve` set off, on the same thread.
        self._lock = threading.RLock()

    def reserve(self, wanted: int, needed: int, unit: int) -> int:
        """Reserve between `needed` and `wanted` units of `unit` bytes, as many as fit; return how
        many. Raises `MemoryBudgetError` (reserving nothing) when even `needed` do not fit."""
        with self._lock:
            free = None if self.limit is None else max(0, self.limit - self.used)
            granted = wanted if free is None else min(wanted, free // unit)
            if granted < needed:
                raise MemoryBudgetError(
                    f"the service's memory budget of {_mib(self.limit)} is used up ({_mib(self.used)} held "
                    f"by all maps' tiles; this scan needs {_mib(needed * unit)} more): the scan was not "
                    "integrated (the budget is `fleetmap serve --max-memory`)"
                )
            self.used += granted * unit
            return granted

    def free(self) -> int | None:
        """Bytes the limit leaves (None: no limit)."""
        with self._lock:
            return None if self.limit is None else max(0, self.limit - self.used)

    def reserve_anyway(self, size: int) -> None:
        """Count `size` bytes even past the limit: memory that exists already (a map restored at
        start or installed from a snapshot file) is counted, never refused."""
        with self._lock:
            self.used += size

    def release(self, held: list[int]) -> None:
        """Return the bytes `held[0]` of a store being freed (see `TileStore.charge`)."""
        with self._lock:
            self.used -= held[0]
            held[0] = 0


def _mib(size: int | None) -> str:
    return "unlimited" if size is None else f"{size / 2**20:.1f} MiB"


#: `--max-memory`'s default: this share of the memory the service may use (its cgroup's limit, or the
#: machine's RAM), leaving room for Python, the tile cache and the operating system.
DEFAULT_SHARE = 0.75

_SIZE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(|k|m|g|t|kib|mib|gib|tib|kb|mb|gb|tb)\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_size(text: str) -> int | None:
    """A size such as `512MiB`, `2G` or `1073741824` (bytes; k, M, G, T are powers of 1024, with or
    without `iB` / `B`), `none` for no limit, or `auto` for `DEFAULT_SHARE` of `available_memory()`.
    Raises ValueError with the reason."""
    word = text.strip().lower()
    if word == "none":
        return None
    if word == "auto":
        return int(available_memory() * DEFAULT_SHARE)
    match = _SIZE.match(text)
    if match is None:
        raise ValueError(f"expected a size such as 512MiB, 2GiB, none or auto, got {text!r}")
    value = float(match.group(1)) * _UNITS[match.group(2).lower()[:1]]
    if value < 2**20:
        raise ValueError(f"a memory budget below 1 MiB holds no tile, got {text!r}")
    return int(value)


def available_memory() -> int:
    """Bytes this process may use: its cgroup's memory limit (v2 or v1) when one is set, else the
    machine's physical memory."""
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < physical:
            return int(text)
    return physical
