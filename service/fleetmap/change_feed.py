"""What changed in a map's cells, for live viewers: a bounded log of the storage tiles each scan
changed. (Robots' poses and trails reach viewers another way: `MapEntry.live_version` and
`api/robots_feed.py`.)

Integration workers `record` the tiles each scan changed; event streams ask `since(version)` for
everything newer than what they last sent. The log is bounded: a client too far behind is told to
reload everything instead of replaying history.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

from fleetmap.tiles import TileKey


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

    def __init__(self, capacity: int = 4096, start: int = 0) -> None:
        self._log: deque[tuple[int, tuple[TileKey, ...]]] = deque(maxlen=capacity)
        self._start = start
        self._version = start
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
            return self._version

    def since(self, version: int) -> ChangeBatch:
        """Everything after `version`. A version older than the log reaches, or from before this
        feed began, gives `reset`."""
        with self._lock:
            current = self._version
            if version >= current:
                return ChangeBatch(current)
            if version < self._start:
                return ChangeBatch(current, reset=True)
            if self._log and self._log[0][0] > version + 1 and len(self._log) == self._log.maxlen:
                return ChangeBatch(current, reset=True)
            tiles: set[TileKey] = set()
            for v, keys in reversed(self._log):
                if v <= version:
                    break
                tiles.update(keys)
            return ChangeBatch(current, frozenset(tiles))
