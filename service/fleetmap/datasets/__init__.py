"""Readers for recorded 2D laser logs with known poses: CARMEN text logs and Coursera .mat files.

    from fleetmap.datasets import load_dataset
    ds = load_dataset("../shared/datasets/intel-corrected.log.gz")
    len(ds)              # 910 scans, counted when the file was loaded
    for scan in ds:      # fleetmap.scan.Scan objects in log order, sensor poses in the map frame
        ...

`load_dataset` picks the reader: MATLAB for a `.mat` name (`.mat.gz` gzipped) or a file starting
with a MAT-file header (plain or gzip), CARMEN for everything else (plain or gzip, detected from the
content). Every reader
parses the whole file up front, so a malformed file raises `DatasetError` from `load_dataset`, never
mid-iteration.
"""

from __future__ import annotations

import gzip
import io
import zlib
from pathlib import Path
from typing import BinaryIO

from .base import DEFAULT_RANGE_MIN, UNBOUNDED_RANGE_MAX, Dataset, DatasetError, open_log
from .carmen import GZIP_MAGIC, read_carmen
from .matlab import HDF5_MAGIC, read_matlab

__all__ = [
    "DEFAULT_RANGE_MIN",
    "UNBOUNDED_RANGE_MAX",
    "Dataset",
    "DatasetError",
    "load_dataset",
    "read_carmen",
    "read_matlab",
]

# A MATLAB v5+ file starts with a 116-byte text header beginning with this.
_MAT_HEADER = b"MATLAB"


def load_dataset(
    path: str | Path, *, range_min: float | None = None, range_max: float | None = None
) -> Dataset:
    """Read the laser log at `path` into a `Dataset` of `Scan`s.

    `range_min` / `range_max`, when given, replace the file's values for every scan
    (`range_max=math.inf` means no limit). Defaults: `range_min` 1e-3 (so zero readings are
    ignored); `range_max` from the log (CARMEN) or no limit (.mat).

    Raises `DatasetError` (a `ValueError`) naming the file, and the line for text formats, when the
    format is unknown or the content is malformed; `FileNotFoundError` / `OSError` when the file
    can't be opened.
    """
    path = Path(path)
    # Opened once (`open_log`): a pipe's first bytes, read here to tell the format, are gone from
    # it when it is opened again.
    with open_log(path) as stream:
        head = stream.read(8)
        stream.seek(0)
        named_mat = _named_mat(path)
        unpacked = _gunzipped_mat(stream, path, named_mat) if head.startswith(GZIP_MAGIC) else None
        if unpacked is not None:
            return read_matlab(path, range_min=range_min, range_max=range_max, stream=unpacked)
        if named_mat or _is_mat(head):
            return read_matlab(path, range_min=range_min, range_max=range_max, stream=stream)
        return read_carmen(path, range_min=range_min, range_max=range_max, stream=stream)


def _is_mat(head: bytes) -> bool:
    """Whether a file's first 8 bytes are those of a MAT-file (v4 to v7.2, or v7.3's HDF5)."""
    return head.startswith(_MAT_HEADER) or head == HDF5_MAGIC


def _named_mat(path: Path) -> bool:
    """Whether `path`'s name says a MAT-file: `.mat`, or `.mat.gz` gzipped (any case). A MATLAB v4
    file has no text header: its name is all that tells it."""
    name = path.name.lower()
    return name.endswith((".mat", ".mat.gz"))


def _gunzipped_mat(stream: BinaryIO, path: Path, named_mat: bool) -> BinaryIO | None:
    """A gzip `stream`'s content, in memory (a course's file is a few MB), when it is a MAT-file:
    one starting with a MAT-file header, or any when `named_mat` (`_named_mat`: a v4 file has no
    header, and gzipped was read as a CARMEN log, or handed to scipy still compressed); else None,
    the stream at its start again: a gzipped CARMEN log, or data too corrupt to tell, which the
    CARMEN reader reports. A gzipped .mat was read as a CARMEN log, and refused as 'not UTF-8 text:
    not a CARMEN log'. `DatasetError` for a MAT-file whose gzip data is corrupt."""
    head = b""
    try:
        with gzip.GzipFile(fileobj=stream, mode="rb") as file:
            head = file.read(8)
            if named_mat or _is_mat(head):
                return io.BytesIO(head + file.read())
    except (OSError, EOFError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        if named_mat or _is_mat(head):
            raise DatasetError(f"{path}: a gzipped .mat file whose gzip data is corrupt: {exc}") from None
    stream.seek(0)
    return None
