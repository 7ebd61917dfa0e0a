"""The deployment checks' parts without processes: the kernel's socket tables parsed
from sample input, the per-port cache, the refusal lines, the instance lock, the node
environment (``cryptoros env``)."""

from __future__ import annotations

import os
from ipaddress import ip_address
import socket
import stat

import pytest

from cryptoros.errors import PolicyDenied
from cryptoros.exposure import (
    ExposureError,
    Listener,
    exposed_addresses,
    is_loopback_host,
    parse_proc_net_tcp,
    parse_sock_diag,
    read_listeners,
)
from cryptoros.ros1.xmlrpc import Request
from interceptor.exposure import NodeGuard, PortExposure, master_problem

HEADER = ("  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n")
TAIL = " 00000000:00000000 00:00000000 00000000     0        0 1563 1 0000000087f7565e 100 0 0 10 0\n"
#: a little-endian machine's /proc/net/tcp: 0.0.0.0:2024 and 127.0.0.1:11311 and
#: 10.77.0.2:41234 listening, one established connection (skipped)
PROC_TCP = (HEADER
            + "   0: 00000000:07E8 00000000:0000 0A" + TAIL
            + "   1: 0100007F:2C2F 00000000:0000 0A" + TAIL
            + "   2: 02004D0A:A112 00000000:0000 0A" + TAIL
            + "   3: 020200C0:CD5E 507100CB:01BB 01" + TAIL)
#: /proc/net/tcp6: :: port 80, ::1 port 81, ::ffff:127.0.0.1 port 82, 2001:db8::1 port 83
PROC_TCP6 = (HEADER
             + "   0: 00000000000000000000000000000000:0050 00000000000000000000000000000000:0000 0A" + TAIL
             + "   1: 00000000000000000000000001000000:0051 00000000000000000000000000000000:0000 0A" + TAIL
             + "   2: 0000000000000000FFFF00000100007F:0052 00000000000000000000000000000000:0000 0A" + TAIL
             + "   3: B80D0120000000000000000001000000:0053 00000000000000000000000000000000:0000 0A" + TAIL)
#: one sock_diag datagram captured here (three IPv4 sockets in LISTEN: 127.0.0.1:21312,
#: 0.0.0.0:21311, 0.0.0.0:2024), and the NLMSG_DONE that ended the dump
SOCK_DIAG = bytes.fromhex(
    "7c0000001400020001000000de290000020a0000534000007f000001000000000000000000000000000000000000000000000000"
    "000000000000000003100000000000000000000000000000050000000000000062490000050008000000000008000f0000000000"
    "0c001500010000000000000006001600520000007c0000001400020001000000de290000020a0000533f00000000000000000000"
    "00000000000000000000000000000000000000000000000000000000041000000000000000000000000000008000000000000000"
    "61490000050008000000000008000f00000000000c001500010000000000000006001600520000007c0000001400020001000000"
    "de290000020a000007e8000000000000000000000000000000000000000000000000000000000000000000000000000009000000"
    "00000000000000000000000080000000000000001b060000050008000000000008000f00000000000c0015000100000000000000"
    "0600160052000000")
DONE = bytes.fromhex("140000000300020001000000de29000000000000")


def _seen(listeners: list[Listener]) -> set[tuple[str, int, bool]]:
    return {(str(one.address), one.port, one.exposed) for one in listeners}


def test_proc_net_tcp_gives_the_listening_sockets_and_which_answer_other_hosts():
    assert _seen(parse_proc_net_tcp(PROC_TCP, byteorder="little")) == {
        ("0.0.0.0", 2024, True), ("127.0.0.1", 11311, False), ("10.77.0.2", 41234, True)}
    assert _seen(parse_proc_net_tcp(PROC_TCP6, byteorder="little")) == {
        ("::", 80, True), ("::1", 81, False), (str(ip_address("::ffff:127.0.0.1")), 82, False), ("2001:db8::1", 83, True)}


def test_a_big_endian_machine_prints_the_words_the_other_way_round():
    text = HEADER + "   0: 7F000001:2C2F 00000000:0000 0A" + TAIL
    assert _seen(parse_proc_net_tcp(text, byteorder="big")) == {("127.0.0.1", 11311, False)}


@pytest.mark.parametrize("line", ["   0: 0100007F 00000000:0000 0A", "   0: 0100ZZ7F:2C2F 00000000:0000 0A",
                                  "   0: 01007F:2C2F 00000000:0000 0A"])
def test_a_listening_line_that_does_not_parse_is_an_error_never_a_private_port(line):
    with pytest.raises(ExposureError, match="does not parse"):
        parse_proc_net_tcp(HEADER + line + TAIL)


def test_sock_diag_dump_gives_the_same_listeners_and_its_end():
    listeners, done = parse_sock_diag(SOCK_DIAG)
    assert not done
    assert _seen(listeners) == {("127.0.0.1", 21312, False), ("0.0.0.0", 21311, True), ("0.0.0.0", 2024, True)}
    assert parse_sock_diag(DONE) == ([], True)
    assert _seen(parse_sock_diag(SOCK_DIAG + DONE)[0]) == _seen(listeners)


def test_a_sock_diag_error_or_a_truncated_message_is_an_error():
    error = bytes.fromhex("24000000020000000100000000000000") + (-13).to_bytes(4, "little", signed=True) + bytes(16)
    with pytest.raises(ExposureError, match="refused"):
        parse_sock_diag(error)
    for cut in (SOCK_DIAG[:10], SOCK_DIAG[:100]):
        with pytest.raises(ExposureError):
            parse_sock_diag(cut)


def test_the_kernel_of_this_namespace_tells_a_loopback_socket_from_a_wildcard_one():
    with socket.socket() as private, socket.socket() as public:
        private.bind(("127.0.0.1", 0))
        public.bind(("0.0.0.0", 0))
        private.listen()
        public.listen()
        listeners = read_listeners()
        assert exposed_addresses(listeners, private.getsockname()[1]) == []
        assert exposed_addresses(listeners, public.getsockname()[1]) == ["0.0.0.0"]


def test_loopback_hosts():
    assert all(map(is_loopback_host, ["localhost", "127.0.0.1", "127.3.2.1", "::1"]))
    assert not any(map(is_loopback_host, ["0.0.0.0", "", "::", "10.77.0.2", "robot-a"]))


class FakeTable:
    def __init__(self) -> None:
        self.listeners = [Listener(address=ip_address("0.0.0.0"), port=41234),
                          Listener(address=ip_address("127.0.0.1"), port=11311)]
        self.now = 0.0

    def read(self, port: int) -> list[Listener]:
        return [one for one in self.listeners if one.port == port]


def test_a_port_seen_listening_keeps_its_answer_until_the_ttl_and_a_port_not_listening_is_asked_again():
    table = FakeTable()
    exposure = PortExposure(read=table.read, clock=lambda: table.now, ttl=1.0)
    assert exposure.exposed(41234) == ["0.0.0.0"] and exposure.reads == 1
    assert exposure.exposed(11311) == [] and exposure.reads == 2
    assert exposure.exposed(41234) == ["0.0.0.0"] and exposure.exposed(11311) == [] and exposure.reads == 2
    assert exposure.exposed(5555) == [] and exposure.reads == 3  # not listening: not kept
    table.listeners.append(Listener(address=ip_address("::"), port=5555))
    assert exposure.exposed(5555) == ["::"] and exposure.reads == 4
    table.now = 1.5
    table.listeners = []
    assert exposure.exposed(41234) == [] and exposure.reads == 5


def test_the_kernel_filters_by_port():
    with socket.socket() as one, socket.socket() as other:
        one.bind(("0.0.0.0", 0))
        other.bind(("0.0.0.0", 0))
        one.listen()
        other.listen()
        port = one.getsockname()[1]
        assert {(str(x.address), x.port) for x in read_listeners(port)} == {("0.0.0.0", port)}


def test_a_registration_of_an_exposed_node_is_refused_in_one_line_naming_node_port_and_fix(tmp_path):
    table = FakeTable()
    guard = NodeGuard(PortExposure(read=table.read, clock=lambda: table.now))
    config = tmp_path / "robot_a.toml"
    private = Request(method="registerPublisher", params=("/ok", "/chatter", "std_msgs/String", "http://127.0.0.1:11311/"))
    assert guard.check_registrations([private], allow=(), config=config) == []
    exposed = Request(method="registerService", params=("/talker", "/add", "rosrpc://robot-a:41234", "http://127.0.0.1:11311/"))
    with pytest.raises(PolicyDenied) as err:
        guard.check_registrations([private, exposed], allow=(), config=config)
    text = str(err.value)
    assert err.value.reason == "exposed_endpoint" and "\n" not in text
    assert "/talker" in text and "41234" in text and "ROS_IP=127.0.0.1" in text and f"--config {config}" in text
    assert guard.warnings() == []


def test_a_node_that_announces_loopback_but_binds_every_address_is_told_about_roscpp_and_the_override():
    table = FakeTable()
    guard = NodeGuard(PortExposure(read=table.read, clock=lambda: table.now))
    roscpp = Request(method="registerPublisher", params=("/cpp", "/chatter", "std_msgs/String", "http://127.0.0.1:41234/"))
    with pytest.raises(PolicyDenied, match="roscpp binds its XML-RPC API.*firewall.*allow_exposed_nodes"):
        guard.check_registrations([roscpp], allow=("/other*",), config=None)
    warnings = guard.check_registrations([roscpp], allow=("/c*",), config=None)
    assert len(warnings) == 1 and "/cpp" in warnings[0] and "41234" in warnings[0]
    assert guard.check_registrations([roscpp], allow=("/c*",), config=None) == []  # said once
    assert "/cpp (0.0.0.0 port 41234)" in guard.warnings()[0]


def test_master_problem_names_the_fix_and_the_override():
    table = FakeTable()
    exposure = PortExposure(read=table.read, clock=lambda: table.now)
    assert master_problem("http://127.0.0.1:11311", exposure, None) is None
    table.listeners[1] = Listener(address=ip_address("0.0.0.0"), port=11311)
    table.now = 5
    line = master_problem("http://127.0.0.1:11311", exposure, None)
    assert "0.0.0.0" in line and "ROS_IP=127.0.0.1 rosmaster --core -p 11311" in line
    assert "allow_exposed_master = true" in line and "\n" not in line
    assert "non-loopback" in master_problem("http://10.77.0.1:11311", exposure, None)


def test_the_instance_lock_refuses_a_second_holder_naming_the_first(tmp_path):
    from interceptor.statefile import InstanceRunning, lock_instance

    state = tmp_path / "robot_a.state"
    first = lock_instance(state, "robot_a")
    try:
        assert stat.S_IMODE(state.stat().st_mode) == 0o700
        assert (state / "robot_a.lock").read_text().strip() == str(os.getpid())
        with pytest.raises(InstanceRunning, match=f"pid {os.getpid()}"):
            lock_instance(state, "robot_a")
        assert (state / "robot_a.lock").read_text().strip() == str(os.getpid())
    finally:
        first.close()
    lock_instance(state, "robot_a").close()  # released with its file


def test_state_dir_defaults_beside_the_config(tmp_path):
    from interceptor.config import default_state_dir

    assert default_state_dir(tmp_path / "robot_a.toml") == tmp_path / "robot_a.state"


def test_node_environment_for_each_role(tmp_path):
    from interceptor.runenv import node_environment, shell_lines

    node = tmp_path / "robot.toml"
    node.write_text('manager = "a"\n[listen]\npublic = "10.0.0.2:1"\nlocal_master = "127.0.0.1:11411"\n')
    env, unset = node_environment(node)
    assert env == {"ROS_MASTER_URI": "http://127.0.0.1:11411/", "ROS_IP": "127.0.0.1"} and unset == ("ROS_HOSTNAME",)
    master = tmp_path / "master.toml"
    master.write_text('manager = "m"\nroles = ["master"]\n[master]\nupstream = "http://127.0.0.1:11311"\n')
    assert node_environment(master)[0]["ROS_MASTER_URI"] == "http://127.0.0.1:11311"
    ros2 = tmp_path / "ros2.toml"
    ros2.write_text('manager = "a"\nroles = ["ros2"]\n[ros2]\ndomain_id = 11\n')
    env, unset = node_environment(ros2)
    assert env["ROS_DOMAIN_ID"] == "11" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("localhost_profile.xml") and "ROS_STATIC_PEERS" in unset
    assert "ROS_MASTER_URI" not in env
    assert shell_lines({"A": "x y"}, ("B",)) == ["export A='x y'", "unset B"]
