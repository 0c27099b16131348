"""What became of a robot's scans: the answer to the Zenoh delivery query.

`delivery_status` reads, under the registry's lock, a robot's counters and the ledger of each of
its publisher sessions (`robot_state.SessionLedger`), the sessions that went with a deleted or
replaced map (`Tombstones`), and the scans refused for want of the map or of room on it
(`UnmappedRefusals`): all a robot without its map has, and the first scans of a robot that is on it
now; it builds the `DeliveryStatus` after the lock, from copies. `ScanPublisher.flush`
asks for it (docs/protocol.md, "Delivery confirmation"); `ZenohIngest._on_delivery_query` answers.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable
from typing import TYPE_CHECKING

from fleetmap.robot_state import LEDGER_HISTORY, MAX_SESSIONS, SessionSeqs, pairs
from fleetmap.tombstones import Tombstone
from fleetmap.wire import BuriedSession, DeliveryStatus, SessionDelivery

if TYPE_CHECKING:
    from fleetmap.registry import MapRegistry


def delivery_status(
    registry: MapRegistry, map_id: str, robot_id: str, session: int | None = None
) -> DeliveryStatus:
    """What became of robot `robot_id`'s scans on map `map_id` (the Zenoh delivery query's
    answer): its counters and, per recent publisher session (only `session` if given: its
    session id, 0 for scans without one, which may also be one pushed out of the recent ones),
    its ledger; and the sessions whose scans went with
    a deleted or replaced map of this id (`Tombstones`), so that a robot stops waiting for them.
    Not those of a robot the map merely forgot (`Tombstone.forgotten`): its scans are in the map.
    Its scans refused before it was on the map (for want of the map, or of room on it) are in its
    sessions too (`_with_refusals_before`). Holds the registry's lock briefly."""
    with registry.lock:
        entry = registry.maps.get(map_id)
        robot = None if entry is None else entry.robots.get(robot_id)
        stone = registry.tombstones.get(map_id, robot_id)
        buried = [] if stone is None or stone.forgotten else _buried(stone, session)
        if robot is None:
            # Without its map, or room on it: the sessions whose scans were refused so, if any.
            refused, last_refusal = registry.unmapped.deliveries(map_id, robot_id, session)
            return DeliveryStatus(
                map_id=map_id, robot_id=robot_id, status="no_map" if entry is None else "no_robot",
                buried=buried, sessions=refused, last_error=last_refusal,
            )  # fmt: skip
        # Asked for by its id, a session pushed out of the recent ones (more robots under one id
        # than they hold) is answered too: else its robot's flush found none of its scans counted.
        sessions: Iterable[tuple[int, SessionSeqs]] = robot.sessions.items()
        if session is not None and session not in robot.sessions:
            pushed_out = robot.session_seqs(session)
            sessions = [] if pushed_out is None else [(session, pushed_out)]
        rows = [
            _session_row(key, seqs)
            for key, seqs in sessions
            if seqs.ledger.first_seq is not None and (session is None or key == session)
        ]
        counters = (robot.unsettled, robot.scans_integrated, robot.lost, robot.dropped, robot.duplicates)
        # Remembered until the map goes or forgets the robot, but its ledgers begin at its first scan
        # on the map: without them, its flush called the scans refused before "unconfirmed", why unsaid.
        before, refusal = registry.unmapped.deliveries(map_id, robot_id, session)
        last_error = robot.last_error or refusal
    # The reply is made after the lock from copies (`_session_row`): with 8 sessions' lists of
    # refused seqs and gaps full, made under it the lock was held 45 µs, and 80 with the lists
    # as arrays (boxing their ints); 2 µs now (the reply takes 80 µs).
    unsettled, scans_integrated, lost, dropped, duplicates = counters
    return DeliveryStatus(
        map_id=map_id, robot_id=robot_id, status="ok", unsettled=unsettled,
        scans_integrated=scans_integrated, lost=lost, dropped=dropped, duplicates=duplicates,
        sessions=_with_refusals_before([_session_delivery(*row) for row in rows], before), buried=buried,
        last_error=last_error,
    )  # fmt: skip


def _buried(stone: Tombstone, session: int | None) -> list[BuriedSession]:
    """The delivery query's `buried` of a deleted or replaced map's robot: the `MAX_SESSIONS` of
    its sessions heard most recently (only `session` if given, which may be an older one), as the
    query lists a robot's sessions on a live map. A tombstone remembers more (those its robot's
    bookkeeping pushed out: `Tombstones.bury`), and its robot's flush asks for its own."""
    if session is None:
        listed = stone.sessions.pairs()[-MAX_SESSIONS:]
    else:
        seq = stone.sessions.get(session)
        listed = [] if seq is None else [(session, seq)]
    return [BuriedSession(session=key, last_seq=seq, deleted_at=stone.deleted_at) for key, seq in listed]


def _with_refusals_before(
    sessions: list[SessionDelivery], before: list[SessionDelivery]
) -> list[SessionDelivery]:
    """The robot's `sessions` on its map, each begun at the first of its scans refused before the
    robot was on the map (`before`: `UnmappedRefusals.deliveries`) when those came before its first
    scan counted there: they count as refused, the seqs between that never came as lost. A session
    of `before` alone (a publisher that ended before the robot was on the map) is listed as it is,
    first, with at most `MAX_SESSIONS` sessions listed in all (the robot's own last)."""
    if not before:
        return sessions
    earlier = {entry.session: entry for entry in before}
    joined = []
    for entry in sessions:
        first = earlier.pop(entry.session, None)
        if first is not None and first.last_accepted < entry.first_seq:
            entry = _joined(first, entry)
        joined.append(entry)
    return [*earlier.values(), *joined][-MAX_SESSIONS:]


def _joined(first: SessionDelivery, then: SessionDelivery) -> SessionDelivery:
    """Session `then`, as the map counts it, preceded by `first`, its scans refused before the robot
    was on the map (all seqs below `then.first_seq`)."""
    gap = then.first_seq - first.last_accepted - 1  # seqs between the two that never came: lost
    refused_seqs = lost_gaps = None
    # Listed one by one only when every seq of `first` was refused (`UnmappedRefusals` counts them,
    # and lists none), and as many as a ledger lists.
    listed = first.last_accepted - first.first_seq + 1
    if (
        first.lost == 0
        and then.refused_seqs is not None
        and then.lost_gaps is not None
        and listed + len(then.refused_seqs) <= LEDGER_HISTORY
    ):
        refused_seqs = [*range(first.first_seq, first.last_accepted + 1), *then.refused_seqs]
        lost_gaps = [*([(then.first_seq, gap)] if gap else []), *then.lost_gaps]
    return then.model_copy(
        update={
            "first_seq": first.first_seq,
            "refused": first.refused + then.refused,
            "lost": first.lost + gap + then.lost,
            "refused_seqs": refused_seqs,
            "lost_gaps": lost_gaps,
        }
    )


def _session_row(key: int, seqs: SessionSeqs) -> tuple:
    """What the delivery query answers of the session `key` of a robot (one with a scan in its
    ledger), copied under the registry's lock for `_session_delivery` to read after it: its seqs
    and counts, and its lists as they are (arrays: a copy is a memcpy)."""
    ledger = seqs.ledger
    refused = None if ledger.refused_seqs is None else ledger.refused_seqs[:]
    gaps = None if ledger.lost_gaps is None else ledger.lost_gaps[:]
    return (
        key, ledger.first_seq, seqs.last_seq, ledger.settled, ledger.integrated, ledger.refused,
        ledger.lost, ledger.duplicates, refused, gaps,
    )  # fmt: skip


def _session_delivery(
    key: int, first_seq: int, last_accepted: int, settled: int | None, integrated: int, refused: int,
    lost: int, duplicates: int, refused_seqs: array[int] | None, lost_gaps: array[int] | None,
) -> SessionDelivery:  # fmt: skip
    """The delivery query's entry of a session from its copy (`_session_row`)."""
    return SessionDelivery(
        session=key, first_seq=first_seq, last_accepted=last_accepted, settled=settled,
        integrated=integrated, refused=refused, lost=lost, duplicates=duplicates,
        refused_seqs=None if refused_seqs is None else list(refused_seqs), lost_gaps=pairs(lost_gaps),
    )  # fmt: skip


__all__ = ["delivery_status"]
