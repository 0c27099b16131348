"""CDR (XCDR1), the byte layout of ROS 2 messages: `CdrReader` and `CdrWriter`.

A payload is a 4-byte encapsulation header, then the message's fields in declaration order, each
primitive aligned to its own size (1, 2, 4 or 8 bytes) counted from the end of the header, padding
bytes in between. The header's second byte says the byte order: `00 01 00 00` little-endian (what
every ROS 2 machine of today writes), `00 00 00 00` big-endian. Both are read; XCDR2 and other
representations are refused. A string is a uint32 length that counts its terminating NUL, the
bytes, then the NUL; a sequence a uint32 element count, then the elements. Nested messages add no
alignment of their own.

The reader never trusts a length: a string or sequence longer than the bytes left is a `CdrError`
before anything is allocated, so a hostile 4 GB length costs nothing.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

#: Encapsulation headers: (byte 0, byte 1) -> little-endian?
_REPRESENTATIONS = {(0, 1): True, (0, 0): False}
HEADER_LE = b"\x00\x01\x00\x00"


class CdrError(ValueError):
    """A payload is not a valid CDR message of the expected type (truncated, bad header, bad length)."""


class CdrReader:
    """Reads one CDR payload field by field. Each method aligns, reads and advances; any shortfall
    raises `CdrError`. `remaining` says how many bytes are left (a decoder may insist on 0)."""

    def __init__(self, payload: bytes) -> None:
        if len(payload) < 4:
            raise CdrError(f"a CDR payload needs a 4-byte encapsulation header, got {len(payload)} bytes")
        little = _REPRESENTATIONS.get((payload[0], payload[1]))
        if little is None:
            raise CdrError(
                f"unsupported CDR representation {payload[:2].hex(' ')} (plain CDR, 00 01 or 00 00, expected)"
            )
        self._buf = memoryview(payload)
        self._pos = 4
        self.little_endian = little
        self._e: Literal["<", ">"] = "<" if little else ">"

    @property
    def remaining(self) -> int:
        return len(self._buf) - self._pos

    def _align(self, size: int) -> None:
        offset = (self._pos - 4) % size
        if offset:
            self._pos += size - offset
        if self._pos > len(self._buf):
            raise CdrError("truncated CDR payload (in alignment padding)")

    def _take(self, n: int) -> memoryview:
        end = self._pos + n
        if end > len(self._buf):
            raise CdrError(
                f"truncated CDR payload: needs {n} bytes at offset {self._pos}, has {self.remaining}"
            )
        view = self._buf[self._pos : end]
        self._pos = end
        return view

    def _prim(self, fmt: str, size: int) -> int | float:
        self._align(size)
        value: int | float = struct.unpack(self._e + fmt, self._take(size))[0]
        return value

    def uint8(self) -> int:
        return int(self._prim("B", 1))

    def int8(self) -> int:
        return int(self._prim("b", 1))

    def uint16(self) -> int:
        return int(self._prim("H", 2))

    def int16(self) -> int:
        return int(self._prim("h", 2))

    def uint32(self) -> int:
        return int(self._prim("I", 4))

    def int32(self) -> int:
        return int(self._prim("i", 4))

    def uint64(self) -> int:
        return int(self._prim("Q", 8))

    def int64(self) -> int:
        return int(self._prim("q", 8))

    def float32(self) -> float:
        return float(self._prim("f", 4))

    def float64(self) -> float:
        return float(self._prim("d", 8))

    def string(self) -> str:
        """A string: length (with the NUL), bytes, NUL. A length of 0 (some writers) is ''."""
        n = self.uint32()
        if n == 0:
            return ""
        if n > self.remaining:
            raise CdrError(f"string of {n} bytes but only {self.remaining} left")
        raw = bytes(self._take(n))
        if raw[-1] != 0:
            raise CdrError("string not terminated by NUL")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CdrError(f"string is not UTF-8: {exc}") from None

    def _array(self, dtype: str, size: int, n: int) -> np.ndarray:
        if n < 0:
            raise CdrError(f"negative array length {n}")
        if n == 0:
            return np.empty(0, dtype=dtype)
        self._align(size)
        if n * size > self.remaining:
            raise CdrError(f"array of {n} x {size} bytes but only {self.remaining} left")
        raw = self._take(n * size)
        return np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder(self._e)).astype(dtype)

    def float32_array(self, n: int) -> npt.NDArray[np.float32]:
        """A fixed-size array of n float32 (no length on the wire)."""
        return self._array("float32", 4, n)

    def float64_array(self, n: int) -> npt.NDArray[np.float64]:
        """A fixed-size array of n float64 (no length on the wire)."""
        return self._array("float64", 8, n)

    def _length(self, size: int) -> int:
        n = self.uint32()
        if n * size > self.remaining:
            raise CdrError(f"sequence of {n} elements of {size} bytes but only {self.remaining} bytes left")
        return n

    def sequence_float32(self) -> npt.NDArray[np.float32]:
        return self._array("float32", 4, self._length(4))

    def sequence_int8(self) -> npt.NDArray[np.int8]:
        return self._array("int8", 1, self._length(1))

    def sequence_uint8(self) -> bytes:
        return bytes(self._take(self._length(1)))

    def sequence_length(self, min_element_size: int = 1) -> int:
        """The element count of a sequence of structs, checked against the bytes left assuming each
        element takes at least `min_element_size` bytes (so a hostile count cannot make the caller
        loop for long)."""
        return self._length(max(1, min_element_size))


class CdrWriter:
    """Writes one little-endian CDR payload (header `00 01 00 00`); `getvalue()` returns it."""

    def __init__(self) -> None:
        self._buf = bytearray(HEADER_LE)

    def getvalue(self) -> bytes:
        return bytes(self._buf)

    def _align(self, size: int) -> None:
        offset = (len(self._buf) - 4) % size
        if offset:
            self._buf.extend(b"\x00" * (size - offset))

    def _prim(self, fmt: str, size: int, value: float) -> None:
        self._align(size)
        try:
            self._buf.extend(struct.pack("<" + fmt, value))
        except struct.error as exc:
            raise CdrError(f"cannot write {value!r} as {fmt}: {exc}") from None

    def write_uint8(self, v: int) -> None:
        self._prim("B", 1, v)

    def write_int8(self, v: int) -> None:
        self._prim("b", 1, v)

    def write_uint16(self, v: int) -> None:
        self._prim("H", 2, v)

    def write_int16(self, v: int) -> None:
        self._prim("h", 2, v)

    def write_uint32(self, v: int) -> None:
        self._prim("I", 4, v)

    def write_int32(self, v: int) -> None:
        self._prim("i", 4, v)

    def write_uint64(self, v: int) -> None:
        self._prim("Q", 8, v)

    def write_int64(self, v: int) -> None:
        self._prim("q", 8, v)

    def write_float32(self, v: float) -> None:
        self._prim("f", 4, v)

    def write_float64(self, v: float) -> None:
        self._prim("d", 8, v)

    def write_string(self, s: str) -> None:
        raw = s.encode("utf-8")
        self.write_uint32(len(raw) + 1)
        self._buf.extend(raw)
        self._buf.append(0)

    def _array(self, dtype: str, size: int, values: Sequence[float] | np.ndarray) -> None:
        arr = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder("<"))
        if arr.ndim != 1:
            raise CdrError(f"expected a 1-D array, got shape {arr.shape}")
        if arr.size:
            self._align(size)
            self._buf.extend(arr.tobytes())

    def write_float32_array(self, values: Sequence[float] | np.ndarray) -> None:
        self._array("float32", 4, values)

    def write_float64_array(self, values: Sequence[float] | np.ndarray) -> None:
        self._array("float64", 8, values)

    def write_sequence_float32(self, values: Sequence[float] | np.ndarray) -> None:
        self.write_uint32(len(values))
        self._array("float32", 4, values)

    def write_sequence_int8(self, values: Sequence[int] | np.ndarray) -> None:
        self.write_uint32(len(values))
        self._array("int8", 1, values)

    def write_sequence_uint8(self, values: bytes | bytearray | memoryview) -> None:
        raw = bytes(values)
        self.write_uint32(len(raw))
        self._buf.extend(raw)

    def write_sequence_length(self, n: int) -> None:
        """The count before a sequence of structs (the caller writes the elements)."""
        self.write_uint32(n)


__all__ = ["HEADER_LE", "CdrError", "CdrReader", "CdrWriter"]
