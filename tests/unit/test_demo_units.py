"""The demo without processes: when a mission counts as stalled, and what an attack's evidence counts."""

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


def test_an_attacks_evidence_counts_only_what_its_own_sender_did():
    """Newcomer audit: the stranger's blocked flood read "r0 received 0 foreign stop
    commands, halted 26.7 s" (the held flood's halt) and the blocked false map "1 believed
    the map explored" (a robot done for another reason)."""
    from cryptoros.demo.run import judge

    def robot(state: str, held_stops: int = 0) -> dict:
        table = {"/teleop": {"n": held_stops, "first": 0.0, "last": 0.0, "effect": held_stops}}
        return {"state": state, "halted_s": 26.7 if held_stops else 0.0, "received": {},
                "stats": {"map_from_non_team": 0, "by_publisher": {"cmd_vel": table}}}

    mode = {"_final": {"r0": robot("done", held_stops=40), "r1": robot("explore"), "r2": robot("explore")},
            "attack_reports": {}}
    judged = judge(mode, ("cmd-flood", "false-map"), 3)
    assert judged["cmd-flood"] == {"succeeded": False, "evidence": "r0 received 0 foreign stop commands"}
    assert judged["false-map"] == {"succeeded": False,
                                   "evidence": "robots received 0 false map claims; 0 of them believed the map explored"}


def test_map_erase_is_judged_by_the_attackers_own_updates_not_by_unlisted_digests():
    """fresh85: behind the interceptors, where the attacker's registration was refused, the
    judge counted one team map update whose digest no robot listed as sent ("robots received
    1 altered team map updates"). Only updates of a team member sent by the attacker's node
    count now, and only the erased ones."""
    from cryptoros.demo.run import judge

    def robot(relayed: dict) -> dict:
        return {"state": "done", "halted_s": 0.0, "received": {"map": ["an-unlisted-digest"]},
                "stats": {"map_from_non_team": 0, "by_publisher": {"map_relayed": relayed}}}

    refused = {"_final": {r: robot({}) for r in ("r0", "r1", "r2")}, "attack_reports": {}}
    assert judge(refused, ("map-erase",), 3)["map-erase"] == {
        "succeeded": False, "evidence": "robots received 0 erased team map updates from /mitm"}
    relayed = {"/mitm": {"n": 7, "first": 0.0, "last": 0.0, "effect": 5.0},
               "/someone_else": {"n": 3, "first": 0.0, "last": 0.0, "effect": 3.0}}
    plain = {"_final": {"r0": robot(relayed), "r1": robot({}), "r2": robot({})}, "attack_reports": {}}
    assert judge(plain, ("map-erase",), 3)["map-erase"] == {
        "succeeded": True, "evidence": "robots received 5 erased team map updates from /mitm"}
