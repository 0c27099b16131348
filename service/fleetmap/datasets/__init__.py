"""Readers for recorded 2D laser logs with known poses: CARMEN text logs and Coursera .mat files.

    from fleetmap.datasets import load_dataset
    ds = load_dataset("../shared/datasets/intel-corrected.log.gz")
    len(ds)              # 910 scans, counted when the file was loaded
    for scan in ds:      # fleetmap.scan.Scan objects in log order, sensor poses in the map frame
        ...

`load_dataset` picks the reader: MATLAB for a `.mat` name or a file starting with a MAT-file header,
CARMEN for everything else (plain or gzip, detected from the content). Every reader parses the whole
file up front, so a malformed file raises `DatasetError` from `load_dataset`, never mid-iteration.
"""

from __future__ import annotations

from pathlib import Path

from .base import DEFAULT_RANGE_MIN, UNBOUNDED_RANGE_MAX, Dataset, DatasetError, open_log
from .carmen import read_carmen
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
        if path.suffix.lower() == ".mat" or head.startswith(_MAT_HEADER) or head == HDF5_MAGIC:
            return read_matlab(path, range_min=range_min, range_max=range_max, stream=stream)
        return read_carmen(path, range_min=range_min, range_max=range_max, stream=stream)
