"""The one bounded-table helper: most recent last, the oldest dropped past the cap."""

from __future__ import annotations

from collections import OrderedDict

from cryptoros.lru import remember


def test_a_stored_key_becomes_the_most_recent_and_the_oldest_go_past_the_cap():
    table: dict[str, int] = {}
    assert [remember(table, k, i, 3) for i, k in enumerate("abc")] == [[], [], []]
    assert remember(table, "a", 10, 3) == []  # stored anew: now the most recent
    assert list(table.items()) == [("b", 1), ("c", 2), ("a", 10)]
    assert remember(table, "d", 3, 3) == [("b", 1)]
    assert list(table) == ["c", "a", "d"]


def test_a_lowered_cap_drops_every_entry_over_it_oldest_first():
    table = OrderedDict((k, i) for i, k in enumerate("abcde"))
    assert remember(table, "f", 5, 2) == [("a", 0), ("b", 1), ("c", 2), ("d", 3)]
    assert list(table.items()) == [("e", 4), ("f", 5)]
