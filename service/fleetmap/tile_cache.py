"""The cache of rendered map tiles (`TileCache`), which the REST API serves tiles from: each PNG kept
with the tile version it shows, rendered again only when that version moves, and rendered once for
concurrent requests."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fleetmap.tile_reduce import ReducedCache
from fleetmap.tile_render import check_layer, etag_for, render_tile_versioned, tile_version

if TYPE_CHECKING:
    from fleetmap.map_entry import MapEntry


@dataclass(frozen=True)
class _Cached:
    version: int
    png: bytes
    etag: str


class TileCache:
    """Thread-safe LRU of rendered tiles keyed by (map id, generation, layer, z, x, y), each stored
    with the tile version it shows. It holds at most `max_entries` tiles and `max_bytes` of PNG
    (more only while its one tile is larger), the least recently used going first; the zoomed-out
    reductions it renders from are cached apart, in `reduced` (a `ReducedCache` of `reduced_bytes`).

    `get_or_render` reads the current version first (cheap, lock-free), serves the cached PNG if it
    is that version (or newer), else renders, stores and returns it. Concurrent requests for the
    same missing tile render it once: the others wait for that render (and use it if it is at least
    the version they saw). A new map generation (a map deleted and re-created) never hits the old
    generation's entries; those age out, or `drop_map` removes them at once.
    """

    def __init__(
        self,
        max_entries: int = 4096,
        max_bytes: int = 256 << 20,
        reduced_bytes: int = 128 << 20,
        on_render: Callable[[str, int, float], None] | None = None,
    ) -> None:
        """`on_render(layer, z, seconds)` is called after each actual render (for metrics)."""
        if max_entries < 1:
            raise ValueError("max_entries must be at least 1")
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.reduced = ReducedCache(reduced_bytes)
        self.on_render = on_render
        self.hits = 0  # requests served without a render of their own (cached, or another's render)
        self.renders = 0  # tiles actually rendered: hits + renders = tiles served
        self._items: OrderedDict[tuple, _Cached] = OrderedDict()
        self._bytes = 0
        self._inflight: dict[tuple, Future[_Cached]] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def cached(self, entry: MapEntry, layer: str, z: int, x: int, y: int) -> tuple[bytes, str] | None:
        """`(png_bytes, etag)` if the cache holds the tile's current version, else None: never
        renders and never waits for a render, so an event loop may call it. Raises TileError for a
        bad zoom, tile index or layer."""
        gmap = entry.gmap
        version = tile_version(gmap, z, x, y)  # validates z, x, y
        check_layer(gmap, layer)
        key = (entry.id, entry.generation, layer, z, x, y)
        with self._lock:
            hit = self._items.get(key)
            if hit is None or hit.version < version:
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return hit.png, hit.etag

    def get_or_render(self, entry: MapEntry, layer: str, z: int, x: int, y: int) -> tuple[bytes, str]:
        """`(png_bytes, etag)` of tile (z, x, y) of `layer` of the registry entry's map.
        Raises TileError for a bad zoom, tile index or layer."""
        gmap = entry.gmap
        version = tile_version(gmap, z, x, y)  # validates z, x, y
        check_layer(gmap, layer)
        key = (entry.id, entry.generation, layer, z, x, y)
        while True:
            with self._lock:
                hit = self._items.get(key)
                if hit is not None and hit.version >= version:
                    self._items.move_to_end(key)
                    self.hits += 1
                    return hit.png, hit.etag
                pending = self._inflight.get(key)
                if pending is None:
                    pending = self._inflight[key] = Future()
                    owner = True
                else:
                    owner = False
            if owner:
                return self._render(entry, layer, z, x, y, key, pending)
            done = pending.result()  # re-raises the renderer's exception
            if done.version >= version:
                # Served without a render of its own: a hit, so that hits and renders add up to the
                # tiles served (the metrics' hit ratio counted none of these under load).
                with self._lock:
                    self.hits += 1
                return done.png, done.etag
            # That render began before the change we saw: go round (it has left _inflight by now).

    def _render(
        self, entry: MapEntry, layer: str, z: int, x: int, y: int, key: tuple, pending: Future[_Cached]
    ) -> tuple[bytes, str]:
        try:
            started = time.perf_counter()
            png, version = render_tile_versioned(entry.gmap, layer, z, x, y, self.reduced)
            seconds = time.perf_counter() - started
            done = _Cached(version, png, etag_for(entry.generation, layer, z, x, y, version))
        except BaseException as exc:
            with self._lock:
                self._inflight.pop(key, None)
            pending.set_exception(exc)
            raise
        with self._lock:
            self.renders += 1
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= len(old.png)
            keep = old if old is not None and old.version > done.version else done
            self._items[key] = keep
            self._bytes += len(keep.png)
            while len(self._items) > self.max_entries or (
                self._bytes > self.max_bytes and len(self._items) > 1
            ):
                _, evicted = self._items.popitem(last=False)
                self._bytes -= len(evicted.png)
            self._inflight.pop(key, None)
        pending.set_result(done)
        if self.on_render is not None:
            self.on_render(layer, z, seconds)
        return done.png, done.etag

    def drop_map(self, map_id: str) -> None:
        """Forget every cached tile of `map_id` (all generations), e.g. when the map is deleted."""
        with self._lock:
            for key in [k for k in self._items if k[0] == map_id]:
                self._bytes -= len(self._items.pop(key).png)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0
