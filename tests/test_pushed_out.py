"""The compact rows of a robot's sessions pushed out of its recent ones (`fleetmap.pushed_out`):
each value comes back as it was put, None included, and rows keep their places."""

from __future__ import annotations

import math

import pytest

from fleetmap.pushed_out import STORED_NONE, PushedOutRows


def test_rows_give_back_what_was_put_none_included_in_their_places() -> None:
    rows = PushedOutRows("qd?q")
    first, second = (2**63 - 1, -2.5e300, True, None), (0, None, False, 7)
    rows.put(5, first)
    rows.put(2**53 - 1, second)
    assert rows.get(5) == first and rows.get(2**53 - 1) == second and rows.get(6) is None
    assert list(rows.items()) == [(5, first), (2**53 - 1, second)] and len(rows) == 2 and 5 in rows
    assert rows.columns(3) == [STORED_NONE, 7] and math.isnan(rows.columns(0, 1)[1][1])
    rows.put(5, (1, 1.0, False, 1))  # in place: its place kept
    assert rows.keys() == [5, 2**53 - 1] and rows.get(5) == (1, 1.0, False, 1)
    assert rows.pop(5) == (1, 1.0, False, 1) and rows.pop(5) is None and rows.keys() == [2**53 - 1]
    rows.put(9, first)
    rows.drop_first()
    assert list(rows.items()) == [(9, first)]
    other = PushedOutRows("qd?q")
    other.put(9, first)
    assert other == rows
    with pytest.raises(ValueError):  # (a row of another length)
        rows.put(3, (1, 1.0, True))
