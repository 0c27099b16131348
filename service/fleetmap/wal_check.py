"""Damage in SQLite's write-ahead log (`fleetmap.db-wal`) that would lose committed transactions.

SQLite reads a WAL from its start and stops at the first frame whose checksum (cumulative over every
frame before it) or salts do not match: everything after it is dropped without an error, as the torn
tail of a transaction a crash interrupted. So one changed byte (bit rot, a bad copy, a hand edit) in
an early frame silently dropped every commit after it, acknowledged scans of every map among them,
and the service started "fine" on what was left. A crash cannot leave that: with `synchronous=FULL`
each commit is on disk before the next one is written, so at most the LAST transaction is torn. Two
or more commit frames of the log's current generation (its salts) after the last valid commit mean
damage, which `damaged_commits` counts before any connection opens the database (the last connection
to close checkpoints what SQLite recovered and deletes the log, the damage and its evidence with it).

The WAL format (https://www.sqlite.org/fileformat2.html#walformat): a 32-byte header (magic, version,
page size, checkpoint sequence, salt-1, salt-2, checksum-1, checksum-2, big-endian), then frames of
a 24-byte header (page number, database size after a commit (0: not a commit), salt-1, salt-2,
checksum-1, checksum-2) and one page. The checksums run over 32-bit words (big-endian if the magic's
low bit is set, else little-endian) in pairs: `s1 += x0 + s2; s2 += x1 + s1`, mod 2**32, from the
header's checksum through each frame's first 8 bytes and its page.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

_MAGIC = (0x377F0682, 0x377F0683)
_HEADER = 32
_FRAME_HEADER = 24
#: Frames checksummed per numpy step: about 32 KB of temporaries per frame.
_CHUNK_FRAMES = 512


class _Checksummer:
    """SQLite's WAL checksum of one frame (its first 8 bytes and its page) from the previous one's,
    vectorised: the state after n pairs is `A**n s + sum_i A**(n-1-i) b_i`, `b_i = (x0, x0 + x1)`,
    where `A = [[1, 1], [1, 2]]` takes the state (s1, s2) through one pair of zero words."""

    def __init__(self, page_size: int, big_endian: bool) -> None:
        self.dtype = np.dtype(">u4" if big_endian else "<u4")
        self.pairs = 1 + page_size // 8
        # powers[i] = A ** (pairs - 1 - i): what pair i adds to the state at the frame's end. uint64
        # wraps, which keeps every product and sum exact mod 2**32.
        powers = np.empty((self.pairs, 2, 2), dtype=np.uint64)
        current = np.eye(2, dtype=np.uint64)
        step = np.array([[1, 1], [1, 2]], dtype=np.uint64)  # A
        for i in range(self.pairs - 1, -1, -1):
            powers[i] = current
            current = current @ step
        self.powers = powers
        self.whole = current  # A ** pairs: what the frame does to the state it starts from

    def added(self, words: np.ndarray) -> np.ndarray:
        """Per frame (rows of `words`, each its 2 header words and its page's), what its pairs add to
        the state: shape (frames, 2), uint64 (exact mod 2**32)."""
        x = words.astype(np.uint64).reshape(len(words), self.pairs, 2)
        b = np.stack([x[..., 0], x[..., 0] + x[..., 1]], axis=-1)  # (frames, pairs, 2)
        return np.einsum("pij,fpj->fi", self.powers, b)

    def next(self, state: np.ndarray, added: np.ndarray) -> np.ndarray:
        return (self.whole @ state + added) & np.uint64(0xFFFFFFFF)


def _checksum_pairs(data: bytes, big_endian: bool) -> tuple[int, int]:
    """SQLite's checksum of a few bytes (the WAL header's first 24), from (0, 0)."""
    words = struct.unpack(f"{'>' if big_endian else '<'}{len(data) // 4}I", data)
    s1 = s2 = 0
    for k in range(0, len(words), 2):
        s1 = (s1 + words[k] + s2) & 0xFFFFFFFF
        s2 = (s2 + words[k + 1] + s1) & 0xFFFFFFFF
    return s1, s2


def _valid_page_size(size: int) -> bool:
    return 512 <= size <= 65536 and not size & (size - 1)


def _database_page_size(wal: Path) -> int | None:
    """The page size in the header of the database beside `wal` (None: unreadable or invalid)."""
    try:
        with open(wal.with_name(wal.name.removesuffix("-wal")), "rb") as f:
            f.seek(16)
            raw = f.read(2)
    except OSError:
        return None
    if len(raw) < 2:
        return None
    size = 65536 if raw == b"\x00\x01" else struct.unpack(">H", raw)[0]
    return size if _valid_page_size(size) else None


def damaged_commits(wal: Path) -> int:
    """How many commit frames of the log's current generation lie after its last valid commit,
    beyond the one a crash may tear: 0 for a log SQLite reads whole (or none, or one too short to
    hold a frame), more when damage drops committed transactions. Reads the file once, a chunk of
    frames at a time. Raises `OSError` if it cannot be read."""
    with open(wal, "rb") as f:
        header = f.read(_HEADER)
        if len(header) < _HEADER:
            return 0
        magic, _version, page_size, _seq, salt1, salt2, check1, check2 = struct.unpack(">8I", header)
        big_endian = bool(magic & 1)
        header_ok = magic in _MAGIC and _checksum_pairs(header[:24], big_endian) == (check1, check2)
        if not _valid_page_size(page_size):
            # Damaged where SQLite reads it (so it ignores the whole log): the database's is the
            # log's. Whether commits were lost shows in the frames, under the first frame's salts.
            header_ok, page_size = False, _database_page_size(wal)
            if page_size is None:
                return 0  # (no frame size to walk the frames by)
        frame_size = _FRAME_HEADER + page_size
        summer = _Checksummer(page_size, big_endian)
        state = np.array([check1, check2], dtype=np.uint64)
        valid = header_ok  # still in the prefix SQLite reads
        salts: tuple[int, int] | None = (salt1, salt2) if header_ok else None
        beyond = 0  # commit frames of the current generation after the last valid commit
        while chunk := f.read(frame_size * _CHUNK_FRAMES):
            frames = len(chunk) // frame_size
            if frames == 0:
                break
            raw = np.frombuffer(chunk, dtype=np.uint8, count=frames * frame_size).reshape(frames, frame_size)
            heads = raw[:, :_FRAME_HEADER].copy().view(">u4")  # (frames, 6), always big-endian
            if salts is None:  # a damaged header: the first frame's salts name the generation
                salts = (int(heads[0, 2]), int(heads[0, 3]))
            ours = (heads[:, 2] == salts[0]) & (heads[:, 3] == salts[1])
            commits = heads[:, 1] != 0
            if valid:
                words = np.concatenate([raw[:, :8], raw[:, _FRAME_HEADER:]], axis=1).copy().view(summer.dtype)
                added = summer.added(words)
                for k in range(frames):
                    state = summer.next(state, added[k])
                    if not ours[k] or (int(state[0]), int(state[1])) != (int(heads[k, 4]), int(heads[k, 5])):
                        valid = False
                        beyond += int(np.count_nonzero(ours[k:] & commits[k:]))
                        break
                    if commits[k]:
                        beyond = 0
                    # (a valid frame that is not a commit: part of a transaction that may yet end)
            else:
                beyond += int(np.count_nonzero(ours & commits))
        return max(0, beyond - 1)
