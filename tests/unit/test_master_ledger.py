"""The master role's ledger, without processes: owners and holds, identical repeats,
relays counted per registration and released with the last one, a node restarted from
another API, the state file's round trip."""

from __future__ import annotations

from interceptor.name_holds import NameHolds
from interceptor.ros1.ledger import MasterLedger

RELAY_A, RELAY_S = "http://127.0.0.1:4001/", "rosrpc://127.0.0.1:4002"
RELAYS = {("127.0.0.1", 4001), ("127.0.0.1", 4002), ("127.0.0.1", 4003)}


class Clock:
    now = 100.0

    def __call__(self) -> float:
        return self.now


def ledger(clock=None):
    return MasterLedger(NameHolds(8, clock=clock or Clock()), lambda endpoint: endpoint in RELAYS)


def note(led, method, params, manager="robot_a", ok=True, released=1, exact=True):
    return led.note(method, params, ok=ok, released=released, manager=manager, exact=exact, hold_seconds=30)


PUB = ("/talker", "/chatter", "std_msgs/String", RELAY_A)
SRV = ("/talker", "/srv", RELAY_S, RELAY_A)


def test_a_registration_owns_the_name_and_counts_behind_its_relays_once():
    led = ledger()
    assert note(led, "registerPublisher", PUB).changed
    assert note(led, "registerService", SRV).changed
    assert led.owner_of("/talker") == "robot_a" and led.nodes_of("robot_a") == 1
    assert led.relay_refs == {("127.0.0.1", 4001): 2, ("127.0.0.1", 4002): 1}
    assert not note(led, "registerPublisher", PUB).changed  # an identical repeat changes nothing
    assert led.relay_refs[("127.0.0.1", 4001)] == 2
    assert note(led, "registerPublisher", PUB, ok=False).changed is False  # rosmaster refused it


def test_the_last_unregistration_releases_the_relays_and_holds_the_name_for_its_owner():
    clock = Clock()
    led = ledger(clock)
    note(led, "registerPublisher", PUB)
    note(led, "registerService", SRV)
    out = note(led, "unregisterService", ("/talker", "/srv", RELAY_S))
    assert out.released == [("127.0.0.1", 4002)] and led.owner_of("/talker") == "robot_a"
    out = note(led, "unregisterPublisher", ("/talker", "/chatter", RELAY_A))
    assert out.released == [("127.0.0.1", 4001)] and led.relay_refs == {}
    assert led.owner_of("/talker") == "robot_a"  # held for its owner...
    assert led.owner_of("/talker", names_exactly=True) is None  # ...not against a manager granted that very name
    clock.now += 31
    assert led.owner_of("/talker") is None


def test_a_name_taken_through_a_pattern_yields_to_a_manager_granted_it_exactly():
    led = ledger()
    note(led, "registerPublisher", PUB, manager="robot_b", exact=False)
    assert led.owner_of("/talker") == "robot_b"
    assert led.owner_of("/talker", names_exactly=True) is None


def test_a_node_registered_from_another_api_loses_what_the_old_one_had():
    led = ledger()
    note(led, "registerPublisher", PUB)
    out = note(led, "registerPublisher", ("/talker", "/other", "std_msgs/String", "http://127.0.0.1:4003/"))
    assert out.replaced == "robot_a"
    assert ("127.0.0.1", 4001) in out.released and led.relay_refs == {("127.0.0.1", 4003): 1}
    assert list(led.registrations) == [("pub", "/talker", "/other")]


def test_the_state_files_tables_round_trip():
    led = ledger()
    note(led, "registerPublisher", PUB)
    note(led, "registerService", SRV, manager="robot_a", exact=False)
    again = ledger()
    again.restore(led.snapshot())
    assert again.snapshot() == led.snapshot()
    assert again.relay_refs == led.relay_refs and again.owner_of("/talker") == "robot_a"


def test_registrations_past_the_bound_are_counted_not_kept():
    led = MasterLedger(NameHolds(8, clock=Clock()), lambda endpoint: False, max_registrations=2)
    for i in range(4):
        note(led, "registerPublisher", (f"/n{i}", "/t", "std_msgs/String", "http://127.0.0.1:9/"))
    assert len(led.registrations) == 2 and led.not_kept == 2
