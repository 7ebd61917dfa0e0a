"""The export and relay tables of interceptor/translate.py: pure, no sockets."""

from __future__ import annotations

import pytest

from cryptoros.errors import PolicyDenied
from interceptor.translate import Translator


#: the id of http://127.0.0.1:5000/ (address, port and kind in one number)
ID_5000 = ((1 << 16 | 5000) << 1)


def _translator(**kw) -> Translator:
    opened: list[tuple[str, int]] = []

    def open_relay(target, port):
        opened.append((target.host, port))
        return "127.0.0.1", 40000 + len(opened)

    return Translator(public_host="127.0.0.2", public_port=11400, local_master_uri="http://127.0.0.1:11311/",
                      open_relay=open_relay, **kw)


def test_exports_are_stable_loopback_only_and_bounded(monkeypatch):
    t = _translator()
    first = t.to_canonical("http://127.0.0.1:5000/")
    assert t.to_canonical("http://127.0.0.1:5000/") == first == f"cryptoros://127.0.0.2:11400/x/{ID_5000}"
    assert t.to_local(first) == "http://127.0.0.1:5000/"
    with pytest.raises(PolicyDenied) as foreign:
        t.to_canonical("http://10.1.2.3:5000/")
    assert foreign.value.reason == "foreign_uri"
    monkeypatch.setattr(Translator, "MAX_EXPORTS", 3)
    t.to_canonical("http://127.0.0.1:5001/")
    t.to_canonical("http://127.0.0.1:5002/")
    with pytest.raises(PolicyDenied) as full:  # a local process registering endless fake URIs
        t.to_canonical("http://127.0.0.1:5003/")
    assert full.value.reason == "export_limit"
    assert t.to_canonical("http://127.0.0.1:5001/").endswith(f"/x/{ID_5000 + 2}")  # known ones still resolve


def test_relays_toward_one_peer_are_capped():
    t = _translator(max_relays_per_host=2)
    t.to_local("cryptoros://127.0.0.3:11400/x/1")
    t.to_local("cryptoros://127.0.0.3:11400/x/2")
    assert t.to_local("cryptoros://127.0.0.3:11400/x/1").startswith("http://127.0.0.1:")  # the same relay again
    with pytest.raises(PolicyDenied) as capped:
        t.to_local("cryptoros://127.0.0.3:11400/x/3")
    assert capped.value.reason == "relay_limit"
    assert t.to_local("cryptoros://127.0.0.4:11400/x/1")  # another peer is not affected


def test_released_exports_free_their_slot_and_their_id_names_only_their_endpoint(monkeypatch):
    monkeypatch.setattr(Translator, "MAX_EXPORTS", 2)
    t = _translator()
    old = t.to_canonical("http://127.0.0.1:5000/")
    t.to_canonical("http://127.0.0.1:5001/")
    assert t.release(t.own_id(old)) and not t.release(t.own_id(old))
    new = t.to_canonical("http://127.0.0.1:5002/")  # the freed slot, the new endpoint's own id
    assert new.endswith(f"/x/{ID_5000 + 4}") and t.export_count == 2
    with pytest.raises(PolicyDenied) as gone:  # a peer holding the old name reaches nothing
        t.to_local(old)
    assert gone.value.reason == "unknown_target"
    monkeypatch.setattr(Translator, "MAX_EXPORTS", 4)
    counted = t.to_canonical("http://localhost:5003/")  # no IPv4 address: a counted id, never reused
    assert counted.endswith("/x/1")
    restored = _translator()
    restored.restore(t.snapshot())
    assert restored.to_canonical("http://localhost:5004/").endswith("/x/2")  # counted ids keep counting after a restart
    assert restored.own_id("cryptoros://127.0.0.9:11400/x/1") is None  # another interceptor's name


def test_a_released_endpoint_is_named_again_without_taking_an_export_slot():
    """An ``unregister*`` a replaced process sends late names its released endpoint by
    the name it had; nothing is exported for it, and it is not a live export."""
    t = _translator()
    old = t.to_canonical("http://127.0.0.1:5000/")
    assert t.name_of("http://127.0.0.1:5000/") == old and t.exported(old)
    t.release(t.own_id(old))
    assert t.name_of("http://127.0.0.1:5000/") == old  # the name rosmaster held, if any
    assert not t.exported(old) and t.export_count == 0
    counted = t.name_of("http://localhost:5003/")  # no IPv4 address: an id never handed out
    assert counted.endswith("/x/0") and not t.exported(counted) and t.export_count == 0
    t.add_master_uri("http://127.0.0.1:11311/")
    assert t.name_of("http://127.0.0.1:11311/") == "cryptoros://master"
    with pytest.raises(PolicyDenied) as foreign:
        t.name_of("http://10.1.2.3:5000/")
    assert foreign.value.reason == "foreign_uri"
    assert not t.exported("cryptoros://127.0.0.9:11400/x/1") and not t.exported(None)


def test_a_restart_with_no_state_adopts_only_its_own_names_that_rosmaster_holds():
    t = _translator()
    tcpros = t.tcpros_to_canonical("127.0.0.5", 6000)[0]
    names = [t.to_canonical("http://127.0.0.1:5000/"), tcpros]
    fresh = _translator()
    with pytest.raises(PolicyDenied):  # nothing resolves until adopted
        fresh.to_local(names[0])
    assert [fresh.adopt(n).uri for n in names] == ["http://127.0.0.1:5000/", "rosrpc://127.0.0.5:6000"]
    assert fresh.to_local(names[0]) == "http://127.0.0.1:5000/"
    assert fresh.tcpros_to_local(tcpros, 1) == ("127.0.0.5", 6000)
    assert fresh.adopt("cryptoros://127.0.0.9:11400/x/" + names[0].rsplit("/", 1)[1]) is None  # not ours
    assert fresh.adopt("cryptoros://127.0.0.2:11400/x/7") is None  # a counted id says no endpoint
    assert fresh.adopt(names[0].replace("/x/", "/t/")) is None  # the kind is part of the id


def test_relays_handed_to_rosmaster_are_named_and_come_back_after_a_restart():
    t = _translator()
    named = t.to_local("cryptoros://127.0.0.3:11400/x/7", named=True)
    assert named == "http://127.0.0.1:40001/cryptoros/127.0.0.3/11400/x/7"
    assert t.from_master(named) == "cryptoros://127.0.0.3:11400/x/7"
    assert t.existing_local("cryptoros://127.0.0.3:11400/x/7", named=True) == named
    service = t.to_local("cryptoros://127.0.0.3:11400/t/9", named=True)
    assert service == "rosrpc://127.0.0.1:40002/cryptoros/127.0.0.3/11400/t/9"
    opened: list[tuple[str, int]] = []
    fresh = Translator(public_host="127.0.0.4", public_port=11400, local_master_uri=None,
                       open_relay=lambda target, port: opened.append((str(target), port)) or ("127.0.0.1", port))
    assert fresh.from_master(named) == "cryptoros://127.0.0.3:11400/x/7"
    assert fresh.from_master(service) == "cryptoros://127.0.0.3:11400/t/9"
    assert opened == [("cryptoros://127.0.0.3:11400/x/7", 40001), ("cryptoros://127.0.0.3:11400/t/9", 40002)]
    assert fresh.from_master(named) == "cryptoros://127.0.0.3:11400/x/7" and len(opened) == 2  # open already
    # the name says which target, even where another relay took its old port
    stale = named.replace("/x/7", "/x/11")  # port 40001 is x/7's relay now
    assert fresh.from_master(stale) == "cryptoros://127.0.0.3:11400/x/11"
    # a name of the wrong kind for its scheme is not taken as a name
    assert fresh.from_master("http://127.0.0.1:40009/cryptoros/127.0.0.3/11400/t/9").startswith(
        "cryptoros://127.0.0.4:11400/x/")


def test_a_requesttopic_reply_may_name_only_the_interceptor_that_answered():
    """A peer answering requestTopic for its node names its own public address; naming
    another (made-up) interceptor would have us open a listening relay per name."""
    opened: list = []
    t = Translator(public_host="127.0.0.2", public_port=11400, local_master_uri=None,
                   open_relay=lambda target, port: opened.append(target) or ("127.0.0.1", 40000 + len(opened)))
    peer = ("10.0.0.7", 11400)
    assert t.tcpros_to_local("cryptoros://10.0.0.7:11400/t/3", 1, via=peer) == ("127.0.0.1", 40001)
    for made_up in ("cryptoros://10.0.0.8:11400/t/3", "cryptoros://10.0.0.7:11401/t/3",
                    "cryptoros://203.0.113.9:443/t/1"):
        with pytest.raises(PolicyDenied) as elsewhere:
            t.tcpros_to_local(made_up, 1, via=peer)
        assert elsewhere.value.reason == "endpoint_not_peer"
    assert [(o.host, o.port) for o in opened] == [peer]  # no relay was opened for the others


def test_an_unknown_target_says_which_endpoint_it_named_and_why_it_is_not_here():
    """Operator audit: after a restart of robot A's interceptor a peer's stream to an
    endpoint named before it was refused as ``no exported x endpoint '210398'`` and
    nothing more (transient: the peer retried with the endpoint the master named then)."""
    t = _translator()
    with pytest.raises(PolicyDenied) as made:  # an id made of an endpoint: which one it names
        t.resolve("x", "210398")
    text = str(made.value)
    assert made.value.reason == "unknown_target" and "\n" not in text
    assert "(127.0.0.1 port 39663)" in text and "restart" in text and "retries" in text, text
    with pytest.raises(PolicyDenied) as counted:  # a counted id names no endpoint: the reasons still said
        t.resolve("t", "7")
    assert "restart" in str(counted.value) and " port " not in str(counted.value), str(counted.value)
