"""What changed in a map's cells, for live viewers: a bounded log of the storage tiles each scan
changed. (Robots' poses and trails reach viewers another way: `MapEntry.live_version` and
`api/robots_feed.py`.)

Integration workers `record` the tiles each scan changed; event streams ask `since(version)` for
everything newer than what they last sent. The log is bounded, in changes and in tiles: a client too
far behind is told to reload everything instead of replaying history.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

from fleetmap.tiles import TileKey

#: The most tile keys a feed holds, summed over its changes: about 130 bytes each (a tuple of two ints
#: and its place in its change's tuple), so 8.5 MiB per map at most. Bounded in changes alone (4096),
#: a feed of small tiles held 1.8 million keys (a Freiburg campus scan changes ~450 tiles of 16 cells),
#: ~240 MB per map outside the memory budget (`--max-memory`), which counts tiles.
MAX_TILES = 65536


@dataclass(frozen=True)
class ChangeBatch:
    """Changes after some version: the storage tiles touched (or `reset`: reload everything)."""

    version: int
    tiles: frozenset[TileKey] = field(default_factory=frozenset)
    reset: bool = False


class ChangeFeed:
    """The change log of one map. Its versions count from `start`: a feed made later (by a later
    process, or for a later map of the same id) starts above every version an earlier one gave, so
    a version below `start` (an event stream resumed with an id from before) is told apart from one
    of this feed and answered with a reset."""

    def __init__(self, capacity: int = 4096, start: int = 0, max_tiles: int = MAX_TILES) -> None:
        """`capacity`: the most changes it holds; `max_tiles`: the most tile keys, all together."""
        self._log: deque[tuple[int, tuple[TileKey, ...]]] = deque()
        self._capacity = capacity
        self._max_tiles = max_tiles
        self._tiles = 0  # keys in `_log`
        self._version = start
        #: The newest version whose change the log no longer holds (`start`: none yet, and no version
        #: before this feed's is one of its own): a stream at a version below it has missed changes.
        self._forgotten = start
        self._lock = threading.Lock()

    @property
    def version(self) -> int:
        return self._version

    def record(self, tiles: list[TileKey]) -> int:
        """Log one change; returns the new version."""
        with self._lock:
            self._version += 1
            if tiles:
                self._log.append((self._version, tuple(tiles)))
                self._tiles += len(tiles)
                while self._log and (len(self._log) > self._capacity or self._tiles > self._max_tiles):
                    self._forgotten, dropped = self._log.popleft()
                    self._tiles -= len(dropped)
            return self._version

    def since(self, version: int) -> ChangeBatch:
        """Everything after `version`. A version older than the log reaches, or from before this
        feed began, gives `reset`."""
        with self._lock:
            current = self._version
            if version >= current:
                return ChangeBatch(current)
            # Below `_forgotten` a change is missing. (Reading the log's oldest version instead, a
            # stream was reset for a version just before a change of no tiles, which is not logged.)
            if version < self._forgotten:
                return ChangeBatch(current, reset=True)
            tiles: set[TileKey] = set()
            for v, keys in reversed(self._log):
                if v <= version:
                    break
                tiles.update(keys)
            return ChangeBatch(current, frozenset(tiles))
