"""The ledger of local registrations (interceptor/registrations.py): what is made again
when our grants change, and its bounds."""

from __future__ import annotations

from cryptoros.grants import Grant, Grants
from interceptor.registrations import LocalRegistrations, covers

STRING = "std_msgs/String"
API = "http://127.0.0.1:40001/"
SUB = ("registerSubscriber", ("/listener", "/secret", STRING, API))
PUB = ("registerPublisher", ("/talker", "/chatter", STRING, "http://127.0.0.1:40002/"))
SRV = ("registerService", ("/adder", "/add", "rosrpc://127.0.0.1:40003", "http://127.0.0.1:40004/"))

NONE = Grants()
SUBSCRIBE = Grants([Grant(node="/listener", action="subscribe", name="/secret", type=STRING)])
ALL = Grants([
    Grant(node="/listener", action="subscribe", name="/secret", type=STRING),
    Grant(node="/talker", action="publish", name="/chatter", type=STRING),
    Grant(node="/adder", action="serve", name="/add", type="rospy_tutorials/AddTwoInts"),
])


def judged(ledger: LocalRegistrations, now: Grants, before: Grants | None) -> list[tuple[str, tuple]]:
    out = ledger.to_resend(lambda r: covers(now, "robot", r.method, r.params),
                           None if before is None else lambda r: covers(before, "robot", r.method, r.params))
    return [(r.method, r.params) for r in out]


def test_a_refused_registration_is_made_once_a_grant_covers_it():
    ledger = LocalRegistrations()
    ledger.refused(*SUB)
    assert judged(ledger, NONE, NONE) == []
    assert judged(ledger, SUBSCRIBE, NONE) == [SUB]
    assert judged(ledger, SUBSCRIBE, None) == [SUB]  # old grants unknown: refused ones still go
    ledger.made(*SUB)
    assert judged(ledger, SUBSCRIBE, SUBSCRIBE) == []  # made: nothing to do while the grant stays


def test_a_made_registration_goes_again_when_its_grant_comes_back():
    ledger = LocalRegistrations()
    ledger.made(*SUB)
    assert judged(ledger, NONE, SUBSCRIBE) == []  # removed: nothing to make
    assert judged(ledger, SUBSCRIBE, NONE) == [SUB]  # added back: made again (the node is told)
    assert judged(ledger, SUBSCRIBE, None) == []  # not known to have been missing


def test_released_registrations_are_forgotten_and_services_go_first():
    ledger = LocalRegistrations()
    for method, params in (SUB, PUB, SRV):
        ledger.refused(method, params)
    assert [m for m, _ in judged(ledger, ALL, NONE)] == ["registerService", "registerPublisher", "registerSubscriber"]
    ledger.released("unregisterPublisher", ("/talker", "/chatter", "http://127.0.0.1:40002/"))
    assert [m for m, _ in judged(ledger, ALL, NONE)] == ["registerService", "registerSubscriber"]
    assert ledger.get(*PUB) is None and ledger.get(*SUB).node_api == API


def test_the_ledger_is_bounded_and_drops_the_oldest_refused_first():
    ledger = LocalRegistrations(max_entries=4, max_refused=2)
    ledger.made(*PUB)
    for i in range(3):
        ledger.refused("registerSubscriber", ("/listener", f"/t{i}", STRING, API))
    assert ledger.refused_count == 2 and len(ledger) == 3 and ledger.dropped == 1
    assert ledger.get("registerSubscriber", ("/listener", "/t0", STRING, API)) is None
    ledger.made(*SRV)
    ledger.made("registerSubscriber", ("/listener", "/x", STRING, API))  # full: a refused one makes no room for it
    assert len(ledger) == 4 and ledger.dropped == 2
    ledger.refused("registerSubscriber", ("/listener", "/t9", STRING, API))  # full: the oldest refused goes
    assert len(ledger) == 4 and ledger.refused_count == 2


def test_not_a_registration_is_ignored():
    ledger = LocalRegistrations()
    ledger.refused("setParam", ("/n", "/k", 1))
    ledger.made("registerSubscriber", ("/n",))
    assert len(ledger) == 0


def test_a_repeated_refusal_changes_nothing_and_the_refused_are_listed_oldest_first():
    ledger = LocalRegistrations()
    assert ledger.refused(*SUB) is True
    assert ledger.refused(*SUB) is False  # the same again: no state to write
    assert ledger.refused(*PUB) is True
    assert ledger.refused_items() == [SUB, PUB]
    ledger.made(*SUB)
    assert ledger.refused_items() == [PUB]
    assert ledger.refused("setParam", ("/n", "/k", 1)) is False
