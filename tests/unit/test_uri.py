"""cryptoros.ros1.uri: one ROS URI parser (whole URIs, IPv6 brackets, clear errors)."""

from __future__ import annotations

import pytest

from cryptoros.errors import CryptorosError, RemoteProtocolError
from cryptoros.ros1.uri import RosUri, UriError, host_port, make_uri, split_uri


@pytest.mark.parametrize(
    ("uri", "expected"),
    [
        ("http://127.0.0.1:11311/", ("127.0.0.1", 11311)),
        ("http://robot-a.local:40000", ("robot-a.local", 40000)),
        ("http://[::1]:11311/", ("::1", 11311)),
        ("http://[fe80::1]:1/RPC2", ("fe80::1", 1)),
        ("rosrpc://10.0.0.2:5000", ("10.0.0.2", 5000)),
    ],
)
def test_host_and_port(uri, expected):
    assert host_port(uri) == expected


def test_split_keeps_scheme_and_path():
    assert split_uri("http://h:1/RPC2") == RosUri(scheme="http", host="h", port=1, path="/RPC2")
    assert split_uri("rosrpc://h:2", ("rosrpc",)).path == "/"


@pytest.mark.parametrize(
    ("uri", "why"),
    [
        (None, "not a non-empty string"),
        ("", "not a non-empty string"),
        (42, "not a non-empty string"),
        ("ftp://h:1/", "scheme"),
        ("h:1", "scheme"),
        ("http://:11311/", "no host"),
        ("http://h/", "no port"),
        ("http://h:0/", "no port"),
        ("http://h:65536/", "out of range"),
        ("http://h:port/", "bad URI"),
        ("http://[::1/", "bad URI"),
        ("http://user:pw@h:1/", "user information"),
    ],
)
def test_bad_uris_are_a_clear_remote_error(uri, why):
    with pytest.raises(UriError, match=why) as info:
        host_port(uri)
    assert isinstance(info.value, RemoteProtocolError) and isinstance(info.value, CryptorosError)


def test_schemes_are_the_callers():
    with pytest.raises(UriError, match="scheme is not https"):
        host_port("http://h:1/", ("https",))
    assert host_port("https://h:1", ("https",)) == ("h", 1)


def test_make_uri_round_trips_and_brackets_ipv6():
    for host in ("127.0.0.1", "robot", "::1"):
        uri = make_uri(host, 11311)
        assert host_port(uri) == (host, 11311)
    assert make_uri("::1", 5, "rosrpc", "") == "rosrpc://[::1]:5"
