"""The demo's mission-end rule without processes: when a mission counts as stalled."""

from __future__ import annotations

from cryptoros.demo.run import ATTACKS_SETTLED_S, STALL_WINDOW_S, stalled


def timeline(coverages: list[float], step: float = 0.25) -> list[list[float]]:
    return [[i * step * 8, i * step, c] for i, c in enumerate(coverages)]


def test_a_flat_coverage_after_the_attacks_settle_is_a_stall():
    rows = timeline([0.1] * 100)  # 25 s of wall time, no progress
    assert stalled(rows, since_attacks=ATTACKS_SETTLED_S + STALL_WINDOW_S)


def test_no_stall_while_the_attacks_are_still_settling():
    rows = timeline([0.1] * 100)
    assert not stalled(rows, since_attacks=ATTACKS_SETTLED_S + STALL_WINDOW_S - 0.5)


def test_slow_but_real_progress_is_no_stall():
    rows = timeline([0.1 + 0.0008 * i for i in range(100)])  # 0.8 points per second of wall
    assert not stalled(rows, since_attacks=60)


def test_a_short_timeline_is_no_stall():
    assert not stalled(timeline([0.1] * 10), since_attacks=60)  # 2.5 s: no row 8 s back
    assert not stalled([], since_attacks=60)
