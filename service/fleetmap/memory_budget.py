"""A memory budget shared by maps: the bytes all their tiles may hold together (their pools, versions
and bookkeeping: `tiles.slot_bytes`).

`MapConfig.max_tiles` bounds one map; a service holding many maps also needs a bound on all of them,
or robots mapping new ground make it grow until the operating system kills it. Each `TileStore`
charged to a budget (`TileStore.charge`) reserves the bytes of every pool growth before it
allocates; when the budget cannot cover the tiles a scan needs, the scan is refused whole with a
`MemoryBudgetError` and its map is unchanged. A store's bytes return to the budget when its map is
deleted or replaced (`TileStore.uncharge`, even while a reader still holds it), or else when the
store is freed.

An upload's map (a snapshot, a nav2 import) is built beside the maps being served, for seconds, and
up to 4 are built at once: each reserves its tiles' bytes (`UploadReservation`) before it allocates
them, atomically, and holds them until the map is installed or the upload ends, so that uploads
together, and scans meanwhile, cannot take the service past the limit.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from fleetmap.tiles import TileLimitError

if TYPE_CHECKING:
    from fleetmap.tiles import TileStore


class MemoryBudgetError(TileLimitError):
    """The shared memory budget cannot hold the tiles a scan (or an upload) needs. The map was not
    changed."""


class Charge:
    """The bytes counted against one `MemoryBudget` for one holder: a tile store's pools
    (`TileStore.charge`), or an upload's reservation for the map it builds, which becomes that map's
    store's charge as it is (`UploadReservation`): so the bytes are never counted twice, nor, between
    the two, not at all. Its fields change under the budget's lock only."""

    __slots__ = ("borrowed", "borrowers", "bytes", "source")

    def __init__(self) -> None:
        self.bytes = 0
        #: Of a reservation for a map that replaces another: that map's charge, and how many of its
        #: bytes the budget counts as free for this reservation (a loan; see `reserve_replacing`).
        self.source: Charge | None = None
        self.borrowed = 0
        #: Of a map's charge: the reservations with a loan of its bytes.
        self.borrowers: list[Charge] = []


class MemoryBudget:
    """Bytes reserved against a limit (None: no limit, only counted). Thread-safe.

    `used` is every byte counted: stores' pools and uploads' reservations. It stays within `limit`,
    except for memory that exists already (`reserve_anyway`: maps restored at start) and for
    `lent`: the bytes of maps being replaced that uploads replacing them count as free
    (`reserve_replacing`), which the old map and the new one both hold until the new one is
    installed (the old one's bytes then go back) or given up. So `used <= limit + lent` holds
    whenever every map counted was counted within the limit."""

    def __init__(self, limit: int | None) -> None:
        if limit is not None and limit <= 0:
            raise ValueError(f"a memory budget must be positive, got {limit}")
        self.limit = limit
        self.used = 0
        self.lent = 0
        # Reentrant: a store's finalizer (`release`) may run from a garbage collection that an
        # allocation inside `reserve` set off, on the same thread.
        self._lock = threading.RLock()

    def reserve(self, wanted: int, needed: int, unit: int, charge: Charge) -> int:
        """Reserve for `charge` between `needed` and `wanted` units of `unit` bytes, as many as fit;
        return how many. Raises `MemoryBudgetError` (reserving nothing) when even `needed` do not fit."""
        with self._lock:
            free = self._free()
            granted = wanted if free is None else min(wanted, free // unit)
            if granted < needed:
                raise MemoryBudgetError(
                    f"the scan needs {format_size(needed * unit)} more for its new tiles, and the service's "
                    f"memory budget for all maps' tiles, {format_size(self.limit)} (`fleetmap serve "
                    f"--max-memory`), has {format_size(free)} free ({format_size(self.used)} held): the scan "
                    "was not integrated"
                )
            self.used += granted * unit
            charge.bytes += granted * unit
            return granted

    def check_tile(self, tile: int, what: str) -> None:
        """Raise `MemoryBudgetError` if one tile of `tile` bytes (`tiles.slot_bytes`) is more than the
        whole limit: no map of such tiles could ever hold one, whatever other maps gave back, so
        making it (`what`) would only have every scan of it refused, each told to try again once
        memory is freed."""
        if self.limit is not None and tile > self.limit:
            raise MemoryBudgetError(
                f"{what}: one of its tiles needs {format_size(tile)}, more than the service's whole memory "
                f"budget for all maps' tiles, {format_size(self.limit)} (`fleetmap serve --max-memory`), "
                "so no scan could ever be integrated into it; give it smaller tiles or fewer layers"
            )

    def reserve_replacing(self, size: int, charge: Charge, replacing: Charge | None) -> None:
        """Reserve `size` bytes for `charge`, an upload's reservation for a map that replaces the map
        charged `replacing` (None: a new map), counting that map's bytes as free: they go back when
        the new map is installed. Raises `MemoryBudgetError` (reserving nothing) when they do not fit.

        What is counted as free beyond the budget's free bytes is a loan of `replacing`'s bytes,
        recorded on both charges and in `lent` until it ends (`repay`): when the reservation is
        installed or released, or when `replacing` is released (its map deleted, or replaced by
        another upload: its bytes are then free for everyone, and no longer this upload's to
        borrow). A map's bytes are lent once: two uploads replacing the same map at once share them,
        and the second is refused what the first borrowed, though each alone would fit (only one of
        them can be installed in the old map's place; the other replaces the first). A scan growing
        the old map meanwhile reserves its growth from the free bytes as any scan does; the loan is
        of what the map held when it was taken. So the bytes counted past the limit are always
        bytes about to go back, never more than the old map holds."""
        with self._lock:
            free = self._free()
            borrowed = 0
            if free is not None and size > free:
                borrowed = size - free
                lendable = (
                    0 if replacing is None else replacing.bytes - sum(b.borrowed for b in replacing.borrowers)
                )
                if borrowed > lendable:
                    beside = (
                        "" if replacing is None else f" (and {format_size(lendable)} of the map it replaces)"
                    )
                    raise MemoryBudgetError(
                        f"need {format_size(size)}, and the service's memory budget for all maps' tiles has "
                        f"{format_size(free)} free{beside} (`fleetmap serve --max-memory`)"
                    )
            if borrowed:
                assert replacing is not None
                charge.source, charge.borrowed = replacing, borrowed
                replacing.borrowers.append(charge)
                self.lent += borrowed
            self.used += size
            charge.bytes += size

    def _free(self) -> int | None:
        """Bytes the limit leaves (None: no limit); call under `_lock`."""
        # `used` holds lent bytes twice, in the old map's charge and in the reservation that borrowed
        # them, and the limit bounds the rest. A borrower took every free byte first, so a loan makes
        # room for no one else; when it ends, the bytes that go back are what it no longer excuses.
        return None if self.limit is None else max(0, self.limit + self.lent - self.used)

    def reserve_anyway(self, size: int, charge: Charge | None = None) -> Charge:
        """Count `size` bytes for `charge` (a new one if None, which is returned) even past the limit:
        memory that exists already (a map restored at start, charged after its journal's scans were
        replayed) is counted, never refused."""
        charge = Charge() if charge is None else charge
        with self._lock:
            self.used += size
            charge.bytes += size
        return charge

    def repay(self, charge: Charge) -> None:
        """End `charge`'s loan, if it has one (see `reserve_replacing`): its bytes stay counted."""
        with self._lock:
            self._repay(charge)

    def _repay(self, charge: Charge) -> None:
        source = charge.source
        if source is not None:
            source.borrowers.remove(charge)
            self.lent -= charge.borrowed
            charge.source, charge.borrowed = None, 0

    def release(self, charge: Charge) -> None:
        """Return the bytes of `charge` (a store being freed or retired, a reservation given up), and
        end its loan and the loans of its bytes (see `reserve_replacing`)."""
        with self._lock:
            self._repay(charge)
            for borrower in list(charge.borrowers):
                self._repay(borrower)
            self.used -= charge.bytes
            charge.bytes = 0


class UploadReservation:
    """The room an upload (`PUT /maps/{id}/snapshot`, `.../import`) holds in a budget for the map it
    builds, so that uploads in progress together, and scans meanwhile, stay within the limit.

    The reader takes it (`charge`) as soon as it knows the map's tiles, before it allocates them; it
    is held while the map is read and stored, and then either becomes the installed map's own
    charge (`install`, under the registry's lock) or goes back (`release`, whatever ended the
    upload: a refusal, a failure, a cancelled request). `install` and `release` decide once, under
    this reservation's lock: a request cancelled while its map was being installed on a worker
    thread either releases first (and the install is refused) or finds it installed (and keeps it)."""

    def __init__(self, budget: MemoryBudget, replacing: TileStore | None) -> None:
        """`replacing`: the store of the map the upload replaces (None: a new map id), whose bytes
        count as free for it (`MemoryBudget.reserve_replacing`)."""
        self.budget = budget
        self._replacing = None if replacing is None else replacing.charged
        self._store: TileStore | None = None
        self._state = "open"  # then "installed" or "released", for good
        self._lock = threading.Lock()

    def charge(self, store: TileStore, tiles: int) -> None:
        """Reserve the bytes `tiles` tiles of `store` take (a new, empty store that is charged to no
        budget) and charge `store` with them, so that its growth to those tiles takes nothing more
        from the budget. Raises `MemoryBudgetError` (a `TileLimitError`; nothing reserved) if they do
        not fit, or if the upload already ended."""
        with self._lock:
            if self._state != "open" or self._store is not None:
                raise MemoryBudgetError(
                    f"the upload's reservation is {self._state}, its map cannot be charged"
                )
            charge = Charge()
            self.budget.reserve_replacing(store.bytes_for(tiles), charge, self._replacing)
            store.charge(self.budget, charge)
            self._store = store

    def install(self, store: TileStore) -> None:
        """`store`'s map is being installed (under the registry's lock): what it holds stays charged,
        as its own (a store the reader did not `charge` is charged as any map is). The loan of the
        replaced map's bytes ends here, before that map is retired: until then its bytes are counted
        twice and free to no one. Raises `MemoryBudgetError` if the reservation was released (the
        upload ended): nothing is then to be installed."""
        with self._lock:
            if self._state == "released":
                raise MemoryBudgetError("the upload ended before its map was installed")
            self._state = "installed"
            if store.budget is None:
                store.charge(self.budget)
            assert store.charged is not None
            self.budget.repay(store.charged)

    def release(self) -> None:
        """The upload ended: unless its map was installed, its bytes go back to the budget now, loan
        and all. Idempotent. A reader still running on its worker thread after a cancelled request
        charges what it still allocates to the budget as any growth, until its map is freed."""
        with self._lock:
            if self._state != "open":
                return
            self._state = "released"
            if self._store is not None:
                self._store.uncharge()


def format_size(size: int | None) -> str:
    """`size` bytes for a person: in the largest binary unit it holds one of, to a tenth (whole
    bytes below 1 KiB). In MiB alone, tiles of 16 cells (a kilobyte each) made "this scan needs
    0.0 MiB more" and "0.0 MiB free" of a refusal, which said nothing of what was missing."""
    if size is None:
        return "unlimited"
    if size < 1 << 10:
        return f"{size} bytes"
    unit = next(u for u in ("TiB", "GiB", "MiB", "KiB") if size >= 1 << _SHIFTS[u])
    return f"{size / (1 << _SHIFTS[unit]):.1f} {unit}"


_SHIFTS = {"KiB": 10, "MiB": 20, "GiB": 30, "TiB": 40}


#: `--max-memory`'s default (`auto_budget`): this share of the memory the service may use (its cgroup's
#: limit, or the machine's RAM), leaving room for Python, the tile cache and the operating system...
DEFAULT_SHARE = 0.75
#: ... and at least this much: what the service holds beside its maps' tiles (250-400 MB, README), the
#: rendered tiles' caches (up to 384 MiB) and the maps' change feeds. A share alone left 256 MiB of
#: a 1 GiB container, where the service was killed before its budget refused a scan.
RESERVED = 1 << 30
#: ... except in less than 4 / 3 GiB, where the budget keeps this share of it (the service is then
#: short of memory whatever its budget).
SMALLEST_SHARE = 0.25


def auto_budget(available: int) -> int:
    """`--max-memory auto`: the budget for a service that may use `available` bytes."""
    return int(max(available * SMALLEST_SHARE, min(available * DEFAULT_SHARE, available - RESERVED)))


_SIZE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(|k|m|g|t|kib|mib|gib|tib|kb|mb|gb|tb)\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_size(text: str) -> int | None:
    """A size such as `512MiB`, `2G` or `1073741824` (bytes; k, M, G, T are powers of 1024, with or
    without `iB` / `B`), `none` for no limit, or `auto` for `auto_budget(available_memory())`.
    Raises ValueError with the reason."""
    word = text.strip().lower()
    if word == "none":
        return None
    if word == "auto":
        return auto_budget(available_memory())
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
