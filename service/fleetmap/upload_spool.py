"""Uploads kept on disk rather than in memory while they are read: the body of a snapshot or nav2
upload (as big as the memory budget for a snapshot) goes to a `SpooledTemporaryFile`
(`spooled_file`), in memory up to SPOOL_MEMORY_BYTES, then in a file of the temporary directory
(`tempfile.gettempdir()`: `TMPDIR`, else /tmp), unlinked as soon as it is made (so a crash leaves
nothing behind) and closed, its room given back, when the upload is done with (`close_spool`). Held
whole in memory, it sat beside the map it builds and outside the memory budget (`--max-memory`).
The readers (`map_from_snapshot_file`, `map_from_nav2_zip`) take such a file as well as bytes
(`as_file`), and open a zip only through `upload_zip`, which checks its directory first. Snapshot
downloads are written to such a spool too, then sent from it. A spool leaves SPOOL_DISK_RESERVE of
its disk free.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable
from typing import IO, Any

#: Bytes of an upload kept in memory before it goes to a file: every upload the routes' tests and
#: clients make of a small map stays in memory (no disk), and a big one costs no more than this.
SPOOL_MEMORY_BYTES = 16 << 20

#: Bytes a spool leaves free on its disk: past that it stops growing, as on a full disk (507). The
#: temporary directory may share its disk with the data directory, whose journal must always find
#: room; and since a snapshot upload may be as big as the memory budget (and a compressed tiles.npz
#: in it is spooled again, decompressed, up to that), a few uploads at once could fill a disk.
SPOOL_DISK_RESERVE = 1 << 30
#: Bytes a spool on disk writes between two looks at its disk's free space.
SPOOL_CHECK_EVERY = 8 << 20

#: The most bytes of central directory (the list of its entries) an uploaded zip may have: about
#: 20,000 entries, where a snapshot has 2, its tiles.npz 6 and a nav2 zip a few. zipfile reads the
#: directory whole and makes an object of every entry before anything else can be checked: 1 million
#: entries (a 51 MiB body) took 434 MiB and 4.8 s, so a 4 GiB snapshot body would take some 35 GiB.
MAX_ZIP_DIRECTORY_BYTES = 1 << 20

#: The errors of a write that say the disk (or the user's quota of it) is full.
_NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class SpoolFailed(Exception):
    """An upload (or a download, `purpose`) could not be written to, or read back from, the temporary
    directory: `status` 507
    (Insufficient Storage) when it has no room, else 503 (an I/O error of its disk, unwritable, out
    of descriptors: the server's fault, not the body's; retry later). Nothing was changed. Not an
    OSError, so that the readers' handling of a corrupt zip (which includes OSError) never takes it
    for the client's fault: an EIO reading a spool back was answered 422, "the body is not a zip
    file"."""

    def __init__(self, exc: OSError, action: str = "written to", purpose: str = "upload") -> None:
        directory = tempfile.gettempdir()
        reason = exc.strerror or str(exc)
        self.directory, self.reason = directory, reason
        if exc.errno in _NO_ROOM:
            self.status = 507
            message = (
                f"the temporary directory {directory} has no room for the {purpose} ({reason}): it is "
                f"kept there while it is {'read' if purpose == 'upload' else 'sent'}, and needs free disk "
                "of its size (set TMPDIR to move it)"
            )
        else:
            self.status = 503
            message = f"the {purpose} could not be {action} the temporary directory {directory} ({reason})"
        super().__init__(message)


class UploadStopped(Exception):
    """The upload's request ended (cancelled at the shutdown's cutoff, or otherwise gone) while its
    reader still ran on a worker thread: the reader stops at its next chunk (a download's writer
    likewise, at its next write: `routes_snapshot.get_snapshot`). It ran on to the end, a
    compressed tiles.npz decompressed into the temporary directory up to its limit, and the
    process's exit waited for it (the event loop's executor joins its threads): 13 s more for a
    3.4 MB snapshot of 3.3 GiB of zeros."""


def check_stop(stop: threading.Event | None) -> None:
    """Raise `UploadStopped` if `stop` is set: what a reader calls between its chunks."""
    if stop is not None and stop.is_set():
        raise UploadStopped("the upload's request ended while it was being read")


class _Spool(tempfile.SpooledTemporaryFile[bytes]):
    """A `SpooledTemporaryFile` whose every failure of its own I/O is a `SpoolFailed`: its file is
    the server's, so an error reading or writing it (EIO from a failing disk, ENOSPC) is never the
    upload's fault, whichever reader (zipfile, numpy, the nav2 reader) meets it. A seek before the
    start (EINVAL) stays an OSError: its position comes from the upload (a corrupt zip's offsets),
    and zipfile expects an OSError there."""

    def __init__(self, purpose: str) -> None:
        super().__init__(max_size=SPOOL_MEMORY_BYTES, prefix=f"fleetmap-{purpose}-")
        self.purpose = purpose  # what `SpoolFailed` calls the file: an upload, or a download
        self._unchecked = SPOOL_CHECK_EVERY  # bytes written since the disk's room was checked

    def _io(self, action: str, call: Callable[..., Any], *args: Any) -> Any:
        try:
            return call(*args)
        except OSError as exc:
            raise SpoolFailed(exc, action, self.purpose) from None

    def write(self, s: Any) -> int:
        if self._rolled:  # type: ignore[attr-defined]  # on disk: leave its disk SPOOL_DISK_RESERVE
            self._unchecked += len(memoryview(s))
            if self._unchecked >= SPOOL_CHECK_EVERY:
                self._check_room()
        return int(self._io("written to", super().write, s))

    def _check_room(self) -> None:
        """Raise `SpoolFailed` (507) if the next SPOOL_CHECK_EVERY bytes would leave less than
        SPOOL_DISK_RESERVE free on the spool's disk."""
        self._unchecked = 0
        disk = self._io("written to", os.fstatvfs, self.fileno())
        if disk.f_bavail * disk.f_frsize < SPOOL_DISK_RESERVE + SPOOL_CHECK_EVERY:
            reason = (
                f"it would leave less than {SPOOL_DISK_RESERVE >> 20} MiB of its disk free, kept for "
                "the maps' storage"
            )
            raise SpoolFailed(OSError(errno.ENOSPC, reason), "written to", self.purpose)

    def writelines(self, iterable: Any) -> None:
        self._io("written to", super().writelines, iterable)

    def flush(self) -> None:
        self._io("written to", super().flush)

    def truncate(self, size: int | None = None) -> int:
        return int(self._io("written to", super().truncate, size))

    def rollover(self) -> None:
        self._io("written to", super().rollover)

    def read(self, *args: Any) -> bytes:
        return bytes(self._io("read back from", super().read, *args))

    def read1(self, *args: Any) -> bytes:
        return bytes(self._io("read back from", super().read1, *args))

    def readinto(self, b: Any) -> int:
        return int(self._io("read back from", super().readinto, b))

    def readinto1(self, b: Any) -> int:
        return int(self._io("read back from", super().readinto1, b))

    def readline(self, *args: Any) -> bytes:
        return bytes(self._io("read back from", super().readline, *args))

    def readlines(self, *args: Any) -> list[bytes]:
        return list(self._io("read back from", super().readlines, *args))

    def seek(self, *args: Any) -> int:
        try:
            return int(super().seek(*args))
        except OSError as exc:
            if exc.errno == errno.EINVAL:  # a position before the start: the upload's, not the disk's
                raise
            raise SpoolFailed(exc, "read back from", self.purpose) from None


def spooled_file(purpose: str = "upload") -> tempfile.SpooledTemporaryFile[bytes]:
    """A new empty spool (binary, readable and seekable); close it when done (that removes its file).
    Its reads, writes and seeks raise `SpoolFailed` for an error of the temporary directory's disk,
    which names the file by `purpose`: an "upload" being read, or a "download" being sent."""
    return _Spool(purpose)


def close_spool(spool: IO[bytes]) -> None:
    """Close `spool`, and so remove its file, never raising: closing flushes what its buffer still
    holds, which fails as the write before it did when the disk is full, and that error (raised in a
    `finally`) would replace the `SpoolFailed` being answered with a 500. The descriptor is closed
    whether the flush fails or not."""
    with contextlib.suppress(OSError, SpoolFailed):
        spool.close()


def as_file(data: bytes | IO[bytes]) -> IO[bytes]:
    """An upload as a binary file open for reading that can seek, as `zipfile` reads it: `data` itself
    if it is one (a spool), else the bytes in a `BytesIO` (no copy is made of them)."""
    return io.BytesIO(data) if isinstance(data, (bytes, bytearray, memoryview)) else data


def upload_zip(data: bytes | IO[bytes]) -> zipfile.ZipFile:
    """An upload (`as_file`) opened as a zip to read, whose central directory is at most
    MAX_ZIP_DIRECTORY_BYTES (checked before zipfile reads it) and whose every entry's local header
    lies within the file: raises `zipfile.BadZipFile` otherwise, as for any other corrupt zip, and
    whatever `zipfile.ZipFile` raises for one that is not a zip.

    zipfile takes the offsets of the central directory as they are, shifted by the bytes found
    before the archive (a self-extracting prefix; negative when the end record claims a directory
    further on than it is), and only seeks to them when a member is opened: an offset before the
    file's start (ValueError, or OSError from a real file) or past what a seek takes (zip64 gives 64
    bits: OverflowError) escaped the readers' handling of a corrupt zip as a 500."""
    fp = as_file(data)
    # zipfile's own reading of the end record (a zip64 one included), so that the bound is on the
    # very size it goes on to read; None (no end record) is left to ZipFile to refuse.
    end = zipfile._EndRecData(fp)  # type: ignore[attr-defined]
    if end and end[5] > MAX_ZIP_DIRECTORY_BYTES:  # _ECD_SIZE
        raise zipfile.BadZipFile(
            f"its central directory is {end[5]} bytes, more than the {MAX_ZIP_DIRECTORY_BYTES} an upload's "
            "may have (its list of entries: a fleetmap or nav2 zip holds a few)"
        )
    zf = zipfile.ZipFile(fp)
    size = fp.seek(0, io.SEEK_END)
    for info in zf.infolist():
        if not 0 <= info.header_offset < size:
            zf.close()
            raise zipfile.BadZipFile(
                f"entry {info.filename!r} says its header is at byte {info.header_offset}, outside the "
                f"file's {size} bytes"
            )
    return zf
