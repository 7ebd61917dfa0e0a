"""The deployment checks' parts without processes: the kernel's socket tables parsed
from sample input, the ``route_localnet`` settings judged, the per-port cache, the
refusal lines, the instance lock, the node environment (``cryptoros env``)."""

from __future__ import annotations

import os
from ipaddress import ip_address
import socket
import stat

import pytest

from cryptoros.errors import ConfigError, PolicyDenied
from cryptoros.exposure import (
    ExposureError,
    Listener,
    exposed_addresses,
    is_loopback_host,
    localnet_routed,
    parse_proc_net_tcp,
    parse_sock_diag,
    read_listeners,
    read_route_localnet,
    route_localnet_fix,
)
from cryptoros.ros1.xmlrpc import Request
from interceptor.exposure import NodeGuard, PortExposure, localnet_problem, master_problem, run_hint

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
        #: /proc/sys/net/ipv4/conf/*/route_localnet as a fresh host has them
        self.conf = {"all": "0\n", "default": "0\n", "lo": "0\n", "eth0": "0\n"}

    def read(self, port: int) -> list[Listener]:
        return [one for one in self.listeners if one.port == port]

    def read_localnet(self) -> dict[str, str]:
        return dict(self.conf)

    def exposure(self) -> PortExposure:
        return PortExposure(read=self.read, clock=lambda: self.now, read_localnet=self.read_localnet)


def test_a_port_seen_listening_keeps_its_answer_until_the_ttl_and_a_port_not_listening_is_asked_again():
    table = FakeTable()
    exposure = PortExposure(read=table.read, clock=lambda: table.now, ttl=1.0, read_localnet=table.read_localnet)
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
    guard = NodeGuard(table.exposure())
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
    guard = NodeGuard(table.exposure())
    roscpp = Request(method="registerPublisher", params=("/cpp", "/chatter", "std_msgs/String", "http://127.0.0.1:41234/"))
    with pytest.raises(PolicyDenied, match="roscpp binds its XML-RPC API.*firewall.*allow_exposed_nodes"):
        guard.check_registrations([roscpp], allow=("/other*",), config=None)
    warnings = guard.check_registrations([roscpp], allow=("/c*",), config=None)
    assert len(warnings) == 1 and "/cpp" in warnings[0] and "41234" in warnings[0]
    assert guard.check_registrations([roscpp], allow=("/c*",), config=None) == []  # said once
    assert "/cpp (0.0.0.0 port 41234)" in guard.warnings()[0]


def test_the_exposed_apis_of_refused_registrations_are_named_once_each_and_allowed_ones_never():
    """The nodes a robot's interceptor asks to shut down: an exposed XML-RPC API (not a
    service port alone, not a loopback one, not an allowed node), once within
    ASK_AGAIN_AFTER however many of its registrations are refused."""
    table = FakeTable()
    now = [0.0]
    guard = NodeGuard(table.exposure(), clock=lambda: now[0])
    exposed = Request(method="registerSubscriber", params=("/echo", "/chatter", "*", "http://robot-a:41234/"))
    service = Request(method="registerService", params=("/srv", "/add", "rosrpc://robot-a:41234", "http://127.0.0.1:11311/"))
    private = Request(method="registerPublisher", params=("/ok", "/chatter", "std_msgs/String", "http://127.0.0.1:11311/"))
    assert guard.exposed_apis([private, service, exposed, exposed], allow=()) == [("/echo", 41234, "robot-a", False)]
    assert guard.exposed_apis([exposed], allow=()) == []  # its next registration, refused too
    now[0] = NodeGuard.ASK_AGAIN_AFTER
    assert guard.exposed_apis([exposed], allow=()) == [("/echo", 41234, "robot-a", True)]  # still there: asked again
    assert guard.exposed_apis([exposed], allow=("/e*",)) == []
    # an IPv6 API as rospy writes it (no brackets) is read, not skipped as a bad URI
    table.listeners.append(Listener(address=ip_address("::"), port=41255))
    v6 = Request(method="registerSubscriber", params=("/v6", "/chatter", "*", "http://fd06::3:41255/"))
    with pytest.raises(PolicyDenied, match="exposed_endpoint|/v6"):
        guard.check_registrations([v6], allow=(), config=None)
    assert guard.exposed_apis([v6], allow=()) == [("/v6", 41255, "fd06::3", False)]
    # a port an allowed node was served on is never named for another node's refusal
    allowed = Request(method="registerPublisher", params=("/rec", "/chatter", "std_msgs/String", "http://h:5555/"))
    table.listeners.append(Listener(address=ip_address("0.0.0.0"), port=5555))
    assert guard.check_registrations([allowed], allow=("/rec",), config=None)
    deputy = Request(method="registerSubscriber", params=("/evil", "/chatter", "*", "http://127.0.0.1:5555/"))
    assert guard.exposed_apis([deputy], allow=("/rec",)) == []


def _exposed_listener(port: int = 0) -> socket.socket:
    """A socket listening on every address (as roscpp's XML-RPC API does), on ``port``."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("0.0.0.0", port))
    sock.listen()
    return sock


def _served_then_exited(guard: NodeGuard) -> int:
    """``/record_1795`` (allowed) served exposed on a real socket, which then closes: its port."""
    with _exposed_listener() as record:
        port = record.getsockname()[1]
        allowed = Request(method="registerPublisher", params=("/record_1795", "/chatter", "std_msgs/String",
                                                              f"http://127.0.0.1:{port}/"))
        assert guard.check_registrations([allowed], allow=("/record_*",), config=None)
        assert f"/record_1795 (0.0.0.0 port {port})" in guard.warnings()[-1]
    return port


def test_an_allowed_exposed_node_that_exited_is_no_longer_named_in_the_status():
    """Operator audit: ``rosbag record`` and ``play`` (allowed exposed) exited, and the
    status named them for good (every anonymous run one more name)."""
    guard = NodeGuard()
    _served_then_exited(guard)
    assert not any("/record_1795" in line for line in guard.warnings())


def test_the_port_of_an_allowed_node_that_exited_is_judged_afresh():
    """Operator audit: a node not allowed that took the ephemeral port of an allowed one
    that had exited was refused but never asked to shut down. The host's real listening
    sockets: the allowed node's, closed, then another on the same port."""
    guard = NodeGuard()
    port = _served_then_exited(guard)
    with _exposed_listener(port):  # the ephemeral port taken again, by a node not allowed
        other = Request(method="registerSubscriber", params=("/echo", "/chatter", "*", f"http://127.0.0.1:{port}/"))
        with pytest.raises(PolicyDenied, match="exposed_endpoint"):
            guard.check_registrations([other], allow=("/record_*",), config=None)
        assert guard.exposed_apis([other], allow=("/record_*",)) == [("/echo", port, "127.0.0.1", False)]


def test_a_node_respawned_exposed_is_a_repeat_named_in_the_status_until_it_stops():
    """Stranger audit: roslaunch's respawn="true" started a refused exposed node again
    each time it was shut down, and a stranger reached it half of the time, with
    status saying nothing. The same node name found exposed again (any port) within
    REPEAT_WINDOW is a repeat (asked to shut down at once) and named in the status."""
    table = FakeTable()
    now = [0.0]
    guard = NodeGuard(table.exposure(), clock=lambda: now[0])

    def respawned(port: int) -> Request:
        table.listeners.append(Listener(address=ip_address("0.0.0.0"), port=port))
        return Request(method="registerSubscriber", params=("/echo", "/chatter", "*", f"http://robot-a:{port}/"))

    assert guard.exposed_apis([respawned(41300)], allow=()) == [("/echo", 41300, "robot-a", False)]
    assert not any("again and again" in w for w in guard.warnings())  # once is not a pattern
    now[0] = 1.5
    assert guard.exposed_apis([respawned(41301)], allow=()) == [("/echo", 41301, "robot-a", True)]
    now[0] = 3.0
    assert guard.exposed_apis([respawned(41302)], allow=()) == [("/echo", 41302, "robot-a", True)]
    line = next(w for w in guard.warnings() if "again and again" in w)
    assert "/echo (3 times)" in line and "respawn" in line and "cryptoros run" in line
    now[0] = 3.0 + NodeGuard.REPEAT_WINDOW  # quiet since: no longer named, and a new start is a first again
    assert not any("again and again" in w for w in guard.warnings())
    assert guard.exposed_apis([respawned(41303)], allow=()) == [("/echo", 41303, "robot-a", False)]


def test_master_problem_names_the_fix_and_the_override():
    table = FakeTable()
    exposure = table.exposure()
    assert master_problem("http://127.0.0.1:11311", exposure, None) is None
    table.listeners[1] = Listener(address=ip_address("0.0.0.0"), port=11311)
    table.now = 5
    line = master_problem("http://127.0.0.1:11311", exposure, None)
    assert "0.0.0.0" in line and "ROS_IP=127.0.0.1 rosmaster --core -p 11311" in line
    assert "allow_exposed_master = true" in line and "\n" not in line
    assert "non-loopback" in master_problem("http://10.77.0.1:11311", exposure, None)


@pytest.mark.parametrize(("conf", "routed"), [
    ({"all": "0", "default": "0", "lo": "0", "eth0": "0"}, []),
    ({"all": "0", "default": "0", "lo": "1", "eth0": "0"}, []),  # lo carries nothing from other hosts
    ({"all": "0", "default": "1", "lo": "0", "eth0": "0"}, []),  # only what interfaces made later start with
    ({"all": "1\n", "default": "0", "lo": "0", "eth0": "0"}, ["all"]),  # all OR the interface: every interface
    ({"all": "0", "default": "0", "lo": "0", "eth0": "1\n", "docker0": "0"}, ["eth0"]),
    ({"all": "1", "default": "1", "lo": "1", "eth0": "2", "br-lan": "1"}, ["all", "br-lan", "eth0"]),
])
def test_route_localnet_on_all_or_any_interface_but_lo_makes_loopback_reachable(conf, routed):
    assert localnet_routed(conf) == routed
    assert (localnet_problem(conf) is None) == (not routed)


def test_the_route_localnet_fix_sets_each_setting_to_zero_default_too_and_names_a_vlan_as_sysctl_does():
    conf = {"all": "1", "default": "1", "lo": "1", "eth0.100": "1", "eth0": "0"}
    assert route_localnet_fix(conf) == ("sysctl -w net.ipv4.conf.all.route_localnet=0 "
                                        "net.ipv4.conf.default.route_localnet=0 net.ipv4.conf.eth0/100.route_localnet=0")
    assert route_localnet_fix({"all": "0", "default": "0", "wlan0": "1"}) == \
        "sysctl -w net.ipv4.conf.wlan0.route_localnet=0"


@pytest.mark.parametrize("conf", [{"default": "0", "eth0": "0"}, {"all": "0", "eth0": "yes"}, {"all": ""}])
def test_route_localnet_settings_that_do_not_parse_are_an_error_never_a_private_loopback(conf):
    with pytest.raises(ExposureError):
        localnet_routed(conf)


def test_route_localnet_is_read_from_each_interface_and_unreadable_settings_are_an_error(tmp_path):
    for name, value in {"all": "0", "default": "1", "lo": "0", "eth0": "1"}.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "route_localnet").write_text(value + "\n")
    (tmp_path / "gone0").mkdir()  # an interface deleted while it is read: left out
    assert read_route_localnet(tmp_path) == {"all": "0\n", "default": "1\n", "lo": "0\n", "eth0": "1\n"}
    (tmp_path / "all" / "route_localnet").unlink()
    with pytest.raises(ExposureError, match="all"):
        read_route_localnet(tmp_path)
    with pytest.raises(ExposureError, match="cannot read"):
        read_route_localnet(tmp_path / "missing")
    real = read_route_localnet()  # this namespace's
    assert {"all", "default", "lo"} <= set(real) and all(value.strip().isdigit() for value in real.values())


def test_route_localnet_refuses_every_local_master_call_and_the_rosmaster_and_warns_in_status(tmp_path):
    table = FakeTable()
    exposure = table.exposure()
    guard = NodeGuard(exposure)
    config = tmp_path / "robot_a.toml"
    private = Request(method="registerPublisher", params=("/ok", "/chatter", "std_msgs/String", "http://127.0.0.1:11311/"))
    state = Request(method="getSystemState", params=("/stranger",))
    assert guard.check_registrations([private], allow=("*",), config=config) == []
    assert guard.check_registrations([state], allow=(), config=config) == []
    assert master_problem("http://127.0.0.1:11311", exposure, None) is None and guard.warnings() == []

    table.conf["eth0"] = "1\n"  # as kube-proxy or Docker (--userland-proxy=false) leave it
    table.now = 1.5
    fix = "sysctl -w net.ipv4.conf.eth0.route_localnet=0"
    for calls, allow in (([private], ("*",)), ([state], ()), ([state, private], ())):
        with pytest.raises(PolicyDenied) as err:  # the node's own patterns do not cover the local master
            guard.check_registrations(calls, allow=allow, config=config)
        text = str(err.value)
        assert err.value.reason == "exposed_endpoint" and "\n" not in text
        assert "local master" in text and "net.ipv4.conf.eth0.route_localnet=1" in text and fix in text
    with pytest.raises(PolicyDenied, match=r"node /cpp's TCPROS port \(port 11311\) is on loopback.*route_localnet"):
        guard.check_port("/cpp", 11311, "TCPROS port", allow=("*",), config=config)
    line = master_problem("http://127.0.0.1:11311", exposure, None)
    assert "net.ipv4.conf.eth0.route_localnet=1" in line and fix in line and "\n" not in line
    assert "allow_exposed_master = true" in line
    assert master_problem("http://127.0.0.1:4444", exposure, None) is not None  # not listening yet: all the same
    [warning] = guard.warnings()
    assert warning.startswith("this host's loopback answers other hosts: net.ipv4.conf.eth0.route_localnet=1")
    reads = exposure.localnet_reads
    assert guard.warnings() == [warning] and exposure.localnet_reads == reads  # kept for the TTL

    table.conf["all"], table.conf["eth0"] = "1", "0"  # all alone opens every interface
    table.now = 3.0
    assert "net.ipv4.conf.all.route_localnet=1" in guard.warnings()[0]
    table.conf["all"] = "0"
    table.now = 4.5
    assert guard.check_registrations([state], allow=(), config=config) == [] and guard.warnings() == []


def test_route_localnet_that_cannot_be_read_fails_closed():
    table = FakeTable()

    def unreadable() -> dict[str, str]:
        raise ExposureError("cannot read /proc/sys/net/ipv4/conf: Permission denied")

    exposure = PortExposure(read=table.read, clock=lambda: table.now, read_localnet=unreadable)
    guard = NodeGuard(exposure)
    with pytest.raises(PolicyDenied, match="cannot tell.*Permission denied"):
        guard.check_registrations([Request(method="getSystemState", params=("/n",))], allow=(), config=None)
    assert "cannot tell" in master_problem("http://127.0.0.1:11311", exposure, None)
    assert "cannot tell" in guard.warnings()[0]


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
    from interceptor.runenv import TOOL_HOOK, node_environment, python_path, shell_lines

    node = tmp_path / "robot.toml"
    node.write_text('manager = "a"\n[listen]\npublic = "10.0.0.2:1"\nlocal_master = "127.0.0.1:11411"\n')
    env, unset = node_environment(node)
    assert env == {"ROS_MASTER_URI": "http://127.0.0.1:11411/", "ROS_IP": "127.0.0.1", "PYTHONPATH": str(TOOL_HOOK)}
    assert unset == ("ROS_HOSTNAME",) and (TOOL_HOOK / "sitecustomize.py").is_file()
    assert python_path("/h", None) == "/h" and python_path("/h", "/a:/b") == "/h:/a:/b"
    assert shell_lines({"PYTHONPATH": "/h"}, ()) == ['export PYTHONPATH=/h"${PYTHONPATH:+:$PYTHONPATH}"']
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


def test_node_environment_refuses_a_key_no_section_knows(tmp_path):
    """CLI audit: `cryptoros env` and `cryptoros run` took a typo ("managre") silently,
    where the interceptor refuses it: the operator learnt of it only at its start."""
    from interceptor.runenv import node_environment

    typo = tmp_path / "robot.toml"
    typo.write_text('managre = "a"\n[listen]\nlocal_master = "127.0.0.1:11411"\n')
    with pytest.raises(ConfigError, match=f"{typo}: unknown key 'managre' in top level"):
        node_environment(typo)
    typo.write_text('manager = "a"\n[listen]\nlocal_mastr = "127.0.0.1:11411"\n')
    with pytest.raises(ConfigError, match=r"unknown key 'local_mastr' in \[listen\]"):
        node_environment(typo)


def test_a_refused_node_that_could_not_be_shut_down_is_named_in_status_while_it_listens():
    """Deployment re-audit: a node the interceptor could not ask to shut down left robot
    B's status at ok."""
    table = FakeTable()
    guard = NodeGuard(table.exposure())
    guard.still_running("/lan_only", 41234)
    assert any("/lan_only (port 41234)" in line and "stop them" in line for line in guard.warnings())
    table.listeners = [one for one in table.listeners if one.port != 41234]  # it stopped
    table.now += 2  # past the kept answer
    assert not any("/lan_only" in line for line in guard.warnings())


def test_a_configuration_loaded_by_a_relative_path_names_itself_absolute(tmp_path, monkeypatch):
    """Stranger audit: the fix a refusal names (`cryptoros run --config robot.toml`) was
    the path as the interceptor was started with it; from the runbook's directory the
    right one was robot_a/robot.toml."""
    from interceptor.config import load

    (tmp_path / "robot_a").mkdir()
    for name in ("ca.crt", "me.crt", "me.key"):
        (tmp_path / "robot_a" / name).write_text("x")
    (tmp_path / "robot_a" / "robot.toml").write_text(
        'manager = "robot_a"\nroles = ["node"]\n[tls]\nca = "ca.crt"\ncert = "me.crt"\nkey = "me.key"\n'
        '[authz]\nurl = "https://127.0.0.1:8443"\n[listen]\npublic = "127.0.0.2:7400"\n'
        'local_master = "127.0.0.1:11311"\n[master]\ninterceptor = "127.0.0.4:7400"\n')
    monkeypatch.chdir(tmp_path / "robot_a")
    cfg = load("robot.toml")
    assert cfg.source == tmp_path / "robot_a" / "robot.toml"
    assert f"--config {tmp_path / 'robot_a' / 'robot.toml'} --" in run_hint(cfg.source, "CMD")
