"""What a robot learns of its scans' delivery: `DeliveryReport`, built from the service's answer to
the delivery query (`fleetmap.wire.DeliveryStatus`, docs/protocol.md, "Delivery confirmation") by
`delivery_report` and, for a session that ended, `ended_session_report`. `ScanPublisher.flush` and
`flush_ended` (`publisher.py`) ask the service and return it."""

from __future__ import annotations

from dataclasses import dataclass, replace

from fleetmap.wire import DeliveryStatus


@dataclass(frozen=True)
class DeliveryReport:
    """What `ScanPublisher.flush` learned of the scans of the publisher's session: seqs `first_seq`
    to `last_seq` (`published` scans), as the service counted them. True (`confirmed`) when every
    one of them is integrated into the map (with durable storage: committed to its journal).

    `integrated`, `refused` (settled without being integrated: refused, dropped by the service's full
    queue, applied but not made durable) and `lost` (seqs that never reached the service) are the
    service's counts of this session (`flush` adds to `lost` the session's first seqs that the publisher
    gave up before it sent any, which the service never heard of); `unsettled` the rest: in flight,
    waiting in the backlog, or whose fate the service does not know (it restarted during the session and
    counts from the first scan it accepted afterwards: `counted_from`). `gone`: scans the service had
    when the map was deleted or replaced by an upload (it remembers the map's robots:
    `DeliveryStatus.buried`), which are in no map now. `settled`: the service settled every scan through
    `last_seq`. `answered`: whether the service answered at all (False: it was unreachable until the
    timeout). `last_error`: when scans were refused, the service's reason for the robot's last refused
    (or dropped) scan, as `GET /maps/{id}` shows it (None from a service older than this field)."""

    published: int
    first_seq: int | None = None
    last_seq: int | None = None
    integrated: int = 0
    refused: int = 0
    lost: int = 0
    settled: bool = False
    answered: bool = False
    counted_from: int | None = None
    gone: int = 0
    last_error: str | None = None

    @property
    def unsettled(self) -> int:
        """Scans neither integrated, refused, lost nor gone as far as the service says."""
        return max(0, self.published - self.integrated - self.refused - self.lost - self.gone)

    @property
    def confirmed(self) -> bool:
        """Whether every scan published is integrated: the service settled them all, counted them
        from the first, and refused or lost none."""
        if self.published == 0:
            return True
        counted = (
            self.counted_from is not None
            and self.first_seq is not None
            and self.counted_from <= self.first_seq
        )
        return self.settled and counted and self.refused == 0 and self.lost == 0 and self.gone == 0

    def __bool__(self) -> bool:
        return self.confirmed

    def summary(self) -> str:
        """One line: `N scans published, N integrated`, and what became of the others."""
        scans = "scan" if self.published == 1 else "scans"
        text = f"{self.published} {scans} published, {self.integrated} integrated"
        if self.confirmed:
            return text
        if not self.answered:
            return f"{text}: the service did not answer, {self.published - self.integrated} unconfirmed"
        refused = "refused or dropped by the service"
        if self.last_error:
            refused += f" (the last: {self.last_error})"
        parts = [f"{count} {what}" for count, what in (
            (self.lost, "lost"), (self.refused, refused),
            (self.gone, "went with a deleted or replaced map"), (self.unsettled, "unconfirmed"),
        ) if count]  # fmt: skip
        return f"{text}: {', '.join(parts) or 'not settled'}"


def ended_session_report(
    status: DeliveryStatus, session_id: int | None, report: DeliveryReport
) -> DeliveryReport | None:
    """The final `report` of an ended session (`ScanPublisher.flush_ended`), None while the service
    still has scans of it to settle: the seqs after the last it accepted are lost (they went with
    the publisher's backlog). `report` as it is when the service counts nothing of the session."""
    entry = status.session(session_id)
    if entry is None:
        return report
    assert report.last_seq is not None
    if entry.settled is None or entry.settled < entry.last_accepted:
        return None
    never = max(0, report.last_seq - entry.last_accepted)
    return replace(report, lost=report.lost + never, settled=True)


def delivery_report(status: DeliveryStatus, session_id: int | None, first: int, last: int) -> DeliveryReport:
    """The `DeliveryReport` of the scans `first` .. `last` of session `session_id` from the service's
    `status`."""
    published = last - first + 1
    # Listed also without the map (`no_map`): the scans the service refused for want of it.
    entry = status.session(session_id)
    # Scans `first` .. `gone_through` went with a deleted or replaced map, unless the counts of the
    # map there now include them (a session the service counts from before the map went).
    buried = status.buried_session(session_id) if session_id is not None else None
    gone_through = first - 1 if buried is None else min(buried.last_seq, last)
    if entry is not None and entry.first_seq <= gone_through:
        gone_through = first - 1
    gone = gone_through - first + 1
    if entry is None:  # nothing of this session accepted (yet) by the map there is now
        return DeliveryReport(
            published=published, first_seq=first, last_seq=last, answered=True, gone=gone,
            settled=gone == published,
        )  # fmt: skip
    integrated, refused, lost = min(entry.integrated, published), entry.refused, entry.lost
    if entry.last_accepted > last:
        # The service's counts take in scans published after `flush` began (a robot that goes on
        # publishing, or whose backlog came in all at once): only those through `last` are asked
        # about. A scan refused after it made "10 scans published, 10 integrated: 1 refused".
        if entry.refused_seqs is not None and entry.lost_gaps is not None:
            refused = sum(1 for seq in entry.refused_seqs if seq <= last)
            lost = sum(max(0, min(n, last - (seq - n) + 1)) for seq, n in entry.lost_gaps)
            counted = last - max(first, entry.first_seq) + 1
            integrated = min(integrated, max(0, counted - refused - lost))
        else:  # counted, not listed (an older service, or too many): at most what was asked about
            refused = min(refused, published)
            lost = min(lost, published - refused)
            integrated = min(integrated, published - refused - lost)
    return DeliveryReport(
        published=published, first_seq=first, last_seq=last, integrated=integrated, refused=refused,
        lost=lost, settled=entry.settled is not None and entry.settled >= last, answered=True,
        counted_from=entry.first_seq, gone=gone, last_error=status.last_error if refused else None,
    )  # fmt: skip


__all__ = ["DeliveryReport", "delivery_report", "ended_session_report"]
