"""A log that stays readable under a flood: `RateLimitedLog`.

Used where strangers can make the service log: Zenoh and ROS messages refused by the ingests (one
robot can send thousands a second), liveliness tokens coming and going, robot id conflicts, maps
that scans create and lose again, and HTTP connections refused when the process is out of
descriptors; where a failing disk would: every journal commit, and every map's snapshot, fails
while it is full; where a map the ROS publisher cannot publish would, at every change; and where a
bug would: an integration that raises for every scan would write a traceback per scan.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter

#: At most one log line per category (e.g. "decode error on map/robot") this often, in seconds.
LOG_INTERVAL = 5.0


class RateLimitedLog:
    """Logs at most one line per category per `interval` seconds, and at most `max_lines` lines in
    all per interval, and says how many it held back.

    A misbehaving robot can send thousands of bad messages per second, each under another robot id
    (so another category): the log must stay readable, the callback cheap and the memory bounded, so
    repeated lines are counted instead of written."""

    def __init__(self, logger: logging.Logger, interval: float = LOG_INTERVAL, max_lines: int = 20) -> None:
        self.logger = logger
        self.interval = interval
        self.max_lines = max_lines
        self._last: dict[str, float] = {}
        self._held: Counter[str] = Counter()
        self._window = -math.inf  # when the current interval of the overall line budget began
        self._lines = 0  # lines written in it
        self._other = 0  # lines held back by the overall budget, or of categories since forgotten
        self._lock = threading.Lock()

    def warning(self, category: str, message: str, **fields: object) -> bool:
        """`log` at WARNING."""
        return self.log(logging.WARNING, category, message, None, **fields)

    def error(
        self, category: str, message: str, exc_info: BaseException | None = None, **fields: object
    ) -> bool:
        """`log` at ERROR."""
        return self.log(logging.ERROR, category, message, exc_info, **fields)

    def log(
        self, level: int, category: str, message: str, exc_info: BaseException | None = None, **fields: object
    ) -> bool:
        """Log `message` at `level` unless `category` was logged less than `interval` ago, or
        `max_lines` lines were logged in the current interval. Returns whether it was logged.
        `exc_info`: an exception whose traceback the line carries (when it is logged). `fields`
        (map_id, robot_id, ...) are the line's structured fields (`extra=`; see
        fleetmap.log_format)."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(category)
            if last is not None and now - last < self.interval:
                self._held[category] += 1
                return False
            if now - self._window >= self.interval:
                self._window, self._lines = now, 0
            if self._lines >= self.max_lines:
                self._other += 1
                return False
            self._lines += 1
            self._last[category] = now
            held = self._held.pop(category, 0)
            other, self._other = self._other, 0
            # Bound memory under a flood of distinct categories (e.g. random robot ids): forget the
            # quiet ones, and count what they held back with the others.
            if len(self._last) > 10_000:
                self._last = {k: v for k, v in self._last.items() if now - v < self.interval}
                for key in [k for k in self._held if k not in self._last]:
                    self._other += self._held.pop(key)
        suffix = f" ({held} similar messages suppressed)" if held else ""
        if other:
            suffix += f" ({other} other messages suppressed)"
        self.logger.log(level, "%s%s", message, suffix, exc_info=exc_info, extra=fields)
        return True

    def log_held(self, level: int, message: str) -> int:
        """Log one line counting every message held back since its category's last line (and those
        the overall budget held), `message` with `%d` for their number, and forget them; return how
        many (no line for none). For a caller about to end: the next line of a category says what
        it held back, and at a stop no next line comes."""
        with self._lock:
            held = sum(self._held.values()) + self._other
            self._held.clear()
            self._other = 0
        if held:
            self.logger.log(level, message, held)
        return held
