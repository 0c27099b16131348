"""A bounded work queue that is fair between sources and keeps each source's items in order.

Each source (a robot on a map) has its own bounded FIFO. Consumers take from sources round-robin,
and never from a source that already has an item in flight, so one source's items are processed one
at a time in arrival order while different sources proceed in parallel. A source that floods fills
only its own FIFO: `put` refuses its surplus at once (the caller counts it) and never blocks.
Sources may belong to groups (a map's robots), each of which holds at most `per_group` items, so
many sources of one group (a sender under many robot ids) cannot fill the whole queue and starve
the other groups. With a size per item, the items queued also hold at most `max_bytes` together.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import Generic, TypeVar

T = TypeVar("T")
#: A source: a robot on a map, (map_id, robot_id), for the registry.
S = TypeVar("S", bound=Hashable)


class QueueClosed(Exception):
    """`get` on a closed, drained queue."""


#: Why `offer` refused an item: its source's FIFO, its group's share, the whole queue or its bytes
#: were full, or the queue is closed.
FULL_SOURCE, FULL_GROUP, FULL_TOTAL, FULL_BYTES, CLOSED = "source", "group", "total", "bytes", "closed"


class FairQueue(Generic[S, T]):
    """Bounded FIFOs per source, served round-robin, one item of a source in flight at a time (see
    the module docstring). `put` never blocks; `get` blocks until an item is ready or the queue is
    closed and drained."""

    def __init__(
        self,
        per_source: int,
        total: int,
        group: Callable[[S], Hashable] | None = None,
        per_group: int | None = None,
        size_of: Callable[[T], int] | None = None,
        max_bytes: int | None = None,
    ) -> None:
        """At most `per_source` items per source and `total` in all (the registry's sizes:
        `registry.QUEUE_PER_ROBOT`, `QUEUE_TOTAL`). `group(source)` names a source's group (default:
        none); `per_group` (default `total`) bounds the items of one group. With `size_of(item)`
        (bytes), the items queued hold at most `max_bytes` together."""
        self.per_source = per_source
        self.total = total
        self._size_of = size_of
        self.max_bytes = max_bytes
        self._bytes = 0
        self._group = group
        self.per_group = total if per_group is None else per_group
        self._group_size: dict[Hashable, int] = {}
        self._fifos: dict[S, deque[T]] = {}
        self._ready: deque[S] = deque()  # sources with items and nothing in flight
        self._busy: set[S] = set()
        self._size = 0
        self._closed = False
        self._cond = threading.Condition()

    def put(self, source: S, item: T) -> bool:
        """Enqueue without blocking. False, and nothing queued, when the source's FIFO is full
        (`per_source`), its group's share is (`per_group`), the whole queue is (`total`), the item
        would pass `max_bytes`, or the queue is closed."""
        return self.offer(source, item) is None

    def offer(self, source: S, item: T) -> str | None:
        """`put`, saying why an item is refused: None when it is queued, else which bound refused it
        (`FULL_SOURCE`, `FULL_GROUP`, `FULL_TOTAL`, `FULL_BYTES`, or `CLOSED`), the first that
        applies in that order, so that a sender is told whether its own FIFO is full or others
        fill the queue."""
        with self._cond:
            full = self._refusal(source, item)
            if full is not None:
                return full
            fifo = self._fifos.get(source)
            if fifo is None:
                fifo = self._fifos[source] = deque()
            group = self._group(source) if self._group is not None else None
            in_group = self._group_size.get(group, 0)
            weight = self._size_of(item) if self._size_of is not None else 0
            fifo.append(item)
            self._size += 1
            self._bytes += weight
            self._group_size[group] = in_group + 1
            if len(fifo) == 1 and source not in self._busy:
                self._ready.append(source)
                self._cond.notify()
            return None

    def refusal(self, source: S, item: T) -> str | None:
        """Which bound `offer` would refuse `item` of `source` by now (None: it would queue it),
        queuing nothing: a caller that holds a refused item back to offer it again later asks
        first, before it records the item as taken. Items only leave meanwhile (`get`), unless
        another thread offers some: the caller serialises its offers with its question."""
        with self._cond:
            return self._refusal(source, item)

    def room(self, source: S, promised: Mapping[S, int] | None = None) -> int:
        """How many more items of `source` the queue takes now by their counts (`per_source`, its
        group's `per_group`, `total`; not `max_bytes`, which depends on the items), counting
        `promised[s]` more items of each source `s` as queued: items a caller has asked for and
        will offer (fetches in flight), which the room it tells another source leaves to them."""
        promised = promised or {}
        with self._cond:
            fifo = self._fifos.get(source)
            group = self._group(source) if self._group is not None else None
            in_group = self._group_size.get(group, 0) + sum(
                count
                for other, count in promised.items()
                if self._group is None or self._group(other) == group
            )
            return max(
                0,
                min(
                    self.per_source - (len(fifo) if fifo else 0) - promised.get(source, 0),
                    self.per_group - in_group,
                    self.total - self._size - sum(promised.values()),
                ),
            )

    def _refusal(self, source: S, item: T) -> str | None:
        """`refusal`, under the lock."""
        if self._closed:
            return CLOSED
        fifo = self._fifos.get(source)
        group = self._group(source) if self._group is not None else None
        weight = self._size_of(item) if self._size_of is not None else 0
        return (
            FULL_SOURCE if fifo is not None and len(fifo) >= self.per_source
            else FULL_GROUP if self._group_size.get(group, 0) >= self.per_group
            else FULL_TOTAL if self._size >= self.total
            else FULL_BYTES if self.max_bytes is not None and self._bytes + weight > self.max_bytes
            else None
        )  # fmt: skip

    def get(self, timeout: float | None = None) -> tuple[S, T] | None:
        """The next item of the next ready source, marking that source busy until `done(source)`.
        Returns None on timeout; raises QueueClosed once closed and drained."""
        with self._cond:
            while not self._ready:
                if self._closed and self._size == 0:
                    raise QueueClosed
                if not self._cond.wait(timeout):
                    return None
            source = self._ready.popleft()
            item = self._fifos[source].popleft()
            self._size -= 1
            self._left(source, [item])
            self._busy.add(source)
            return source, item

    def done(self, source: S) -> None:
        """The consumer finished the item it took from `source`."""
        with self._cond:
            self._busy.discard(source)
            fifo = self._fifos.get(source)
            if fifo:
                self._ready.append(source)
                self._cond.notify()
            elif fifo is not None:
                del self._fifos[source]

    def drop_source(self, predicate: Callable[[S], bool]) -> list[T]:
        """Discard every queued item of the sources for which `predicate(source)` holds and return
        them, oldest first per source, so the caller can answer whoever waits for them (items in
        flight are not affected)."""
        with self._cond:
            dropped: list[T] = []
            for source in [s for s in self._fifos if predicate(s)]:
                dropped += self._fifos[source]
                self._size -= len(self._fifos[source])
                self._left(source, self._fifos[source])
                if source in self._busy:  # `done` deletes it
                    self._fifos[source].clear()
                else:
                    del self._fifos[source]
            self._ready = deque(s for s in self._ready if self._fifos.get(s))
            return dropped

    def _left(self, source: S, items: Iterable[T]) -> None:
        """`items` of `source` left the queue: its group and the bytes held shrink (call under the
        lock; `_size` is the caller's)."""
        items = list(items)
        if self._size_of is not None:
            self._bytes -= sum(self._size_of(item) for item in items)
        group = self._group(source) if self._group is not None else None
        left = self._group_size.get(group, 0) - len(items)
        if left > 0:
            self._group_size[group] = left
        else:
            self._group_size.pop(group, None)

    def idle(self) -> bool:
        """Nothing queued and nothing in flight."""
        with self._cond:
            return self._size == 0 and not self._busy

    def depth(self) -> int:
        with self._cond:
            return self._size

    def heads(self) -> tuple[int, list[T]]:
        """(items queued, the first queued item of every source): each source's oldest item, so the
        oldest of all is among them. In no particular order."""
        with self._cond:
            return self._size, [fifo[0] for fifo in self._fifos.values() if fifo]

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
