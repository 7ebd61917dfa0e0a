"""``cryptoros bench interceptor``'s Targets table: a ``--quick`` run gives no verdict
(too short to judge), the full run keeps its yes/NO column."""

from __future__ import annotations

import io

from rich.console import Console

from cryptoros.bench.interceptor import targets_table

TARGETS = [{"target": "small messages throughput >= 1.3x stunnel (rospy)", "measured": 0.59, "unit": "x", "met": False},
           {"target": "bring-up of 50 subscribers at once <= 1.5x stunnel's", "measured": 1.2, "limit": 1.5, "unit": "x",
            "met": True}]


def _printed(report: dict) -> str:
    out = io.StringIO()
    Console(file=out, width=200).print(targets_table(report))
    return out.getvalue()


def test_a_quick_run_says_it_is_too_short_and_gives_no_verdict():
    text = _printed({"targets": TARGETS, "quick": True})
    assert "a --quick run is too short to judge them" in text
    assert "NO" not in text and "yes" not in text
    assert "0.59x" in text


def test_a_full_run_keeps_its_verdicts_and_names_where_the_targets_come_from():
    text = _printed({"targets": TARGETS, "quick": False})
    assert "issues 16 and 35" in text
    assert "NO" in text and "yes" in text
