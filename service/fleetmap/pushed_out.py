"""The publisher sessions a robot's bookkeeping pushed out of its recent ones, kept compactly
(`PushedOutRows`): each as one row of machine numbers in a byte buffer, not as Python objects, so
that a robot remembers many of them in little memory. More robots under one robot id than the
recent sessions (a fleet started from one image with its default id) each push the others out
before they come back; a session not remembered then was taken for a new one with each scan (a
restart, its seqs before it lost), and its copies (its cache fetched again after a restart of the
service) for new scans, integrated twice. `fleetmap.robot_state.RobotState` says what the numbers
of a row are; this module only keeps them."""

from __future__ import annotations

import math
import struct
from array import array
from collections.abc import Iterator, Sequence
from operator import itemgetter
from typing import Any

#: A row's value: an integer in [0, 2**63), a float, a bool, or None (not known).
Value = int | float | bool | None
#: What stands for None in an integer column (`PushedOutRows.columns` reads it as stored).
STORED_NONE = -1


class PushedOutRows:
    """Rows of numbers keyed by an integer (a session key), least recently put first.

    `layout` gives each column's kind as a `struct` format character: `q` an integer in
    [0, 2**63) or None (stored as -1), `d` a float or None (stored as NaN), `?` a bool. A pushed-out
    session's row (13 numbers) takes 97 bytes and its key 8, where a `SessionSeqs` with its ledger
    took about 1.6 kB (tracemalloc). Finding a key scans the keys, an array searched at C speed:
    rows are few (`fleetmap.robot_state.MAX_SESSIONS_PUSHED_OUT` per robot at most)."""

    __slots__ = ("_format", "_keys", "_data", "_nones", "_int_columns", "_float_columns")

    def __init__(self, layout: str) -> None:
        self._format = struct.Struct("<" + layout)
        self._keys = array("q")
        self._data = bytearray()
        #: Per column: what stands for None in it (None: the column holds no None, a bool).
        self._nones: tuple[int | float | None, ...] = tuple(
            STORED_NONE if kind == "q" else math.nan if kind == "d" else None for kind in layout
        )
        self._int_columns = tuple(column for column, kind in enumerate(layout) if kind == "q")
        self._float_columns = tuple(column for column, kind in enumerate(layout) if kind == "d")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PushedOutRows):
            return NotImplemented
        return list(self.items()) == list(other.items()) and self._format.format == other._format.format

    __hash__ = None  # type: ignore[assignment]  # (mutable)

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: int) -> bool:
        return key in self._keys

    def keys(self) -> list[int]:
        """The keys, least recently put first."""
        return self._keys.tolist()

    def get(self, key: int) -> tuple[Value, ...] | None:
        """The row of `key`, None if there is none."""
        index = self._index(key)
        return None if index is None else self._row(index)

    def pop(self, key: int) -> tuple[Value, ...] | None:
        """The row of `key`, removed; None if there is none."""
        index = self._index(key)
        if index is None:
            return None
        row = self._row(index)
        self._remove(index)
        return row

    def put(self, key: int, row: Sequence[Value]) -> None:
        """Keep `row` for `key`: in place of its row if it has one (its place kept), else last."""
        # A list, not a generator unpacked into `pack`: that made a reference cycle per row put,
        # holding its packed bytes until the next collection.
        stored = [none if value is None else value for value, none in zip(row, self._nones, strict=True)]
        packed = self._format.pack(*stored)
        index = self._index(key)
        if index is None:
            self._keys.append(key)
            self._data += packed
        else:
            size = self._format.size
            self._data[index * size : (index + 1) * size] = packed

    def items(self) -> Iterator[tuple[int, tuple[Value, ...]]]:
        """(key, row) of each, least recently put first."""
        for key, row in zip(self._keys, self._format.iter_unpack(self._data), strict=True):
            yield key, self._decoded(row)

    def columns(self, *columns: int) -> list[Any]:
        """Columns `columns` of every row (a tuple of them, or the value of one), in the rows'
        order, as stored (None as `STORED_NONE` or NaN): read at C speed, without decoding whole
        rows (`items`), which took 5 µs a row when a robot's 128 were read with each of its scans."""
        return list(map(itemgetter(*columns), self._format.iter_unpack(self._data)))

    def drop_first(self, count: int = 1) -> None:
        """Forget the `count` rows put least recently."""
        del self._keys[:count]
        del self._data[: count * self._format.size]

    def _index(self, key: int) -> int | None:
        try:
            return self._keys.index(key)  # one scan of the keys (`in`, then `index`, made two)
        except ValueError:
            return None

    def _row(self, index: int) -> tuple[Value, ...]:
        return self._decoded(self._format.unpack_from(self._data, index * self._format.size))

    def _decoded(self, row: tuple[Any, ...]) -> tuple[Value, ...]:
        """`row` as stored with None for what stands for it: column by column, four times as fast
        as a test of each value against its column's None (a snapshot saves every row)."""
        values = list(row)
        for column in self._int_columns:
            if values[column] == STORED_NONE:
                values[column] = None
        for column in self._float_columns:
            if math.isnan(values[column]):
                values[column] = None
        return tuple(values)

    def _remove(self, index: int) -> None:
        size = self._format.size
        del self._keys[index]
        del self._data[index * size : (index + 1) * size]


__all__ = ["STORED_NONE", "PushedOutRows", "Value"]
