"""The change feed of a map (`fleetmap.change_feed.ChangeFeed`): bounded, and exact within its bound."""

from __future__ import annotations

import gc
import tracemalloc

from fleetmap.change_feed import ChangeFeed


def _scan_tiles(scan: int, count: int) -> list[tuple[int, int]]:
    """`count` distinct tile keys for one scan, as `GridMap.apply` makes them (fresh tuples of ints past
    the small-int cache, as a map of small tiles has)."""
    return [(1000 + scan, 1000 + k) for k in range(count)]


def test_the_feed_is_bounded_in_tiles_not_only_in_scans() -> None:
    """The feed kept its last 4096 scans whatever their size: with tiles of 16 cells a Freiburg campus
    scan changes ~450 tiles, and 4096 such scans held 1.8 million tile keys, ~250 MB per map outside
    the memory budget (`--max-memory`), in a service whose budget was 256 MiB. It holds at most
    `MAX_TILES` keys now; a stream behind what it holds is told to reload (a reset)."""
    feed = ChangeFeed(start=100)
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for scan in range(4096):
            feed.record(_scan_tiles(scan, 450))
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert held < 16 << 20, held
    from fleetmap.change_feed import MAX_TILES

    # About 130 bytes a key (a tuple of two ints and its place in the scan's tuple).
    assert held < MAX_TILES * 200, held
    # The newest scans are all there, exactly; a stream from before them is reset.
    kept = MAX_TILES // 450
    recent = feed.since(feed.version - kept)
    assert not recent.reset
    assert recent.tiles == frozenset(k for scan in range(4096 - kept, 4096) for k in _scan_tiles(scan, 450))
    assert feed.since(100).reset
    assert feed.since(feed.version - 4000).reset


def test_a_scan_larger_than_the_bound_resets_the_streams_behind_it() -> None:
    """One change of more tiles than the feed holds is not kept; a stream behind it reloads, and
    one that saw it hears of what comes after."""
    from fleetmap.change_feed import MAX_TILES

    feed = ChangeFeed(start=7)
    feed.record([(0, 0)])
    before = feed.version
    feed.record([(1, k) for k in range(MAX_TILES + 1)])
    assert feed.since(before).reset
    after = feed.version
    feed.record([(2, 2)])
    assert feed.since(after) == feed.since(after).__class__(feed.version, frozenset({(2, 2)}))


def test_changes_within_the_bound_are_listed_exactly() -> None:
    """A scan that changes nothing is not logged, and does not make a stream reset: the versions
    around it are still exact (the old rule reset only a full log whose oldest entry was newer)."""
    feed = ChangeFeed(capacity=3, start=0)
    feed.record([(0, 0)])
    feed.record([])
    feed.record([(1, 1)])
    assert feed.since(0).tiles == {(0, 0), (1, 1)}
    feed.record([(2, 2)])
    feed.record([(3, 3)])  # (0, 0) is dropped: the log holds 3 changes
    assert feed.since(0).reset and feed.since(1).tiles == {(1, 1), (2, 2), (3, 3)}
    assert feed.since(2).tiles == {(1, 1), (2, 2), (3, 3)}
