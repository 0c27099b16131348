"""Replay a recorded laser log to a fleetmap service over Zenoh, as one robot.

    fleetmap replay ../shared/datasets/intel-corrected.log.gz --map intel --robot r1 --rate 2

The dataset is read with `fleetmap.datasets.load_dataset` (CARMEN FLASER / ROBOTLASER1 logs, plain
or gzip, and Coursera .mat files); scan k is published with seq k through a `ScanPublisher`.

Pacing. The dataset readers expose poses and scans but no timestamps (and the freiburg log's are all
0), so a replay runs at a nominal `NOMINAL_SCAN_RATE` = 10 scans per second of "real time": `rate`
X publishes 10 * X scans per second (X = 1: 10 scans/s, X = 0.5: 5 scans/s); `rate` 0 publishes as
fast as the link takes them (congestion control BLOCK: nothing is lost on the way), but the service's
ingest queue holds 1024 scans per robot and drops the scans it cannot hold (counted as `dropped` on
the robot; with a queue of 64, 2695 of a 3000-scan log of 1081 beams replayed at rate 0 over
loopback were). Use a finite rate for a lossless replay. Each scan's stamp is the wall-clock time it
was published.

Delivery. The replay first waits until the service is reachable and its subscriber matches (see
`ScanPublisher.wait_connected`), so no scan is published into the void. The publisher keeps its last
scans for re-delivery (`ScanPublisher`'s `backlog`), so the scans in flight when a link dies reach the
service once it is back. If the connection is lost midway, the replay pauses until it is back rather
than publishing on into the backlog: a log replayed faster than real time would otherwise push the
oldest scans out of it before the service could fetch them.

Confirmation. After the last scan the replay asks the service until it has settled every scan
(`ScanPublisher.flush`, for at most `confirm_timeout`: by default the `wait_timeout`, else
`DEFAULT_CONFIRM_TIMEOUT`) and reports what it confirmed (`ReplayResult.delivery`): a link that died
silently near the end, which `close()` would give up with the scans it did not deliver, shows as
scans unconfirmed rather than a replay that looks complete.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetmap.datasets import Dataset, load_dataset
from fleetmap.scan import Scan

from .delivery import DeliveryReport
from .publisher import DeliveryUnsupported, Encoding, ScanPublisher, check_period, check_timeouts

#: Scans per second of a replay at rate 1 (the dataset readers expose no timestamps; see above).
NOMINAL_SCAN_RATE = 10.0
#: Seconds a replay waits for the service to confirm its scans when neither `confirm_timeout` nor
#: `wait_timeout` says: a replay must end, and a whole backlog integrates in well under a second.
DEFAULT_CONFIRM_TIMEOUT = 60.0


class ReplayError(RuntimeError):
    """The replay could not run: no service reachable in time, or the publisher was closed."""


@dataclass
class ReplayResult:
    scans: int  # scans published (handed to a connected session, or kept for re-delivery)
    pauses: int  # times the replay paused for a lost connection to come back
    seconds: float  # from the first scan to the last
    #: What the service confirmed of them (`ScanPublisher.flush`); None when not asked (`confirm`
    #: False), when the service does not answer delivery queries (`unconfirmable` says why), or
    #: when its answer was an error or not a fleetmap one (`confirm_error` says which).
    delivery: DeliveryReport | None = None
    unconfirmable: str | None = None
    confirm_error: str | None = None

    @property
    def confirmed(self) -> bool:
        """Whether the service confirmed every scan integrated."""
        return self.delivery is not None and self.delivery.confirmed


def check_replay(
    rate: float,
    limit: int | None,
    wait_timeout: float | None,
    confirm_timeout: float | None,
    names: Mapping[str, str] | None = None,
) -> float:
    """The seconds between two scans at `rate` (0: as fast as possible); ValueError unless `replay`
    takes these arguments: a finite `rate` not negative whose period a thread can wait
    (`check_period`), a `limit` not negative, timeouts not negative nor NaN (`check_timeouts`). The
    message calls each value by its name in `names` (`fleetmap replay` passes its options',
    `REPLAY_OPTIONS`), else by its parameter's."""

    def name(parameter: str) -> str:
        return (names or {}).get(parameter, parameter)

    if not (rate >= 0.0 and rate != float("inf")):
        raise ValueError(f"{name('rate')} must be a finite number >= 0, got {rate}")
    period = 0.0 if rate == 0.0 else 1.0 / (NOMINAL_SCAN_RATE * rate)
    check_period(period, f"{name('rate')} {rate:g}")
    if limit is not None and limit < 0:
        raise ValueError(f"{name('limit')} must be >= 0, got {limit}")
    check_timeouts(**{name("wait_timeout"): wait_timeout, name("confirm_timeout"): confirm_timeout})
    return period


def replay(
    dataset: Dataset | str | Path,
    map_id: str,
    robot_id: str,
    *,
    rate: float = 1.0,
    connect: Sequence[str] | None = None,
    zenoh_config: str | None = None,
    encoding: Encoding = "binary",
    limit: int | None = None,
    wait_timeout: float | None = None,
    progress: bool = True,
    on_waiting: Callable[[ScanPublisher], None] | None = None,
    confirm: bool = True,
    confirm_timeout: float | None = None,
) -> ReplayResult:
    """Publish the first `limit` scans (all when None) of `dataset` as robot `robot_id` of `map_id`.

    `rate`: multiple of the nominal 10 scans/s (see the module docstring); 0 = as fast as possible.
    `wait_timeout`: seconds to wait for the service at the start and after a lost connection (None:
    forever); raises `ReplayError` when it passes. `on_waiting(publisher)` is called once when the
    service is not reachable within a second (the CLI prints a line). A tqdm progress bar goes to
    stderr unless `progress` is False. With `confirm` (default), the replay then waits up to
    `confirm_timeout` seconds (None: `wait_timeout`, else `DEFAULT_CONFIRM_TIMEOUT`) for the service
    to settle every scan, and `ReplayResult.delivery` says what it confirmed (`confirm_error`: the
    service's answer was an error, or not a fleetmap one). Raises ValueError for
    bad arguments, `DatasetError` / `OSError` for an unreadable dataset path.
    """
    period = check_replay(rate, limit, wait_timeout, confirm_timeout)
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    count = len(ds) if limit is None else min(limit, len(ds))
    with ScanPublisher(
        map_id, robot_id, connect=connect, encoding=encoding, zenoh_config=zenoh_config
    ) as pub:
        _wait(pub, wait_timeout, on_waiting)
        result = _publish_all(pub, (ds[k] for k in range(count)), count, period, wait_timeout, progress)
        if confirm:
            if confirm_timeout is None:
                confirm_timeout = DEFAULT_CONFIRM_TIMEOUT if wait_timeout is None else wait_timeout
            try:
                result.delivery = pub.flush(confirm_timeout)
            except DeliveryUnsupported as exc:
                result.unconfirmable = str(exc)
            except RuntimeError as exc:  # an error reply, or an answer not fleetmap's: not confirmed
                result.confirm_error = str(exc)
        return result


def _wait(
    pub: ScanPublisher, timeout: float | None, on_waiting: Callable[[ScanPublisher], None] | None
) -> None:
    if pub.wait_connected(min(1.0, timeout) if timeout is not None else 1.0):
        return
    if on_waiting is not None:
        on_waiting(pub)
    remaining = None if timeout is None else max(0.0, timeout - 1.0)
    if not pub.wait_connected(remaining):
        if pub.closed:
            raise ReplayError("the publisher was closed")
        reason = f" ({pub.last_connect_error})" if pub.last_connect_error else ""
        raise ReplayError(
            f"no fleetmap service reachable at {', '.join(pub.shown_endpoints)} within {timeout:g} s{reason}"
        )


def _publish_all(
    pub: ScanPublisher,
    scans: Iterable[Scan],
    count: int,
    period: float,
    wait_timeout: float | None,
    progress: bool,
) -> ReplayResult:
    from tqdm import tqdm

    pauses = 0
    started = time.monotonic()
    resumed = started  # when scan 0 was due, as far as the pacing goes: moved on by each pause
    with tqdm(total=count, unit="scan", disable=not progress, file=sys.stderr, desc=pub.robot_id) as bar:
        for k, scan in enumerate(scans):
            if period:
                delay = resumed + k * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if not pub.connected:
                pauses += 1
                paused = time.monotonic()
                try:
                    _wait(pub, wait_timeout, None)
                except ReplayError as exc:
                    # Midway, "no service reachable" alone read as if none had ever been.
                    raise ReplayError(
                        f"lost the fleetmap service after publishing {k} of {count} scans, and it did not "
                        f"come back: {exc}; the scans not delivered were given up, the others are in the "
                        "map or not as the service says (GET /maps/{id})"
                    ) from None
                # The schedule goes on from where it stopped: kept, every scan due during the pause
                # went out at once after it (2760 in a second after 12 s away at --rate 20), past
                # the service's ingest queue (1024 per robot), which dropped hundreds.
                resumed += time.monotonic() - paused
            pub.publish(scan, seq=k)  # kept for re-delivery if the link dies meanwhile
            bar.update(1)
    return ReplayResult(scans=count, pauses=pauses, seconds=time.monotonic() - started)


__all__ = ["DEFAULT_CONFIRM_TIMEOUT", "NOMINAL_SCAN_RATE", "ReplayError", "ReplayResult", "replay"]
