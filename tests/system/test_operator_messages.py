"""Messages an operator can act on, from the real daemons (``cryptoros-interceptor``,
``cryptoros-authz serve``) on a real lab network (rosmaster, rospy nodes, PKI, registry).

- a TLS key whose passphrase is wrong: one line naming the key file, in both daemons;
  the TOML key is ``tls_key_passphrase_file``, ``key_passphrase_file`` still accepted;
- a listener that cannot bind: one line naming it and its address;
- SIGTERM with rospy nodes and a peer stream connected: exit 0, no traceback;
- the revocation feed's "answers again" line within a poll of the server's return;
- the authorization server down past ``max_feed_age``: a robot's own stock tool that
  needs a new stream is told why (``feed_stale``), and ``cryptoros denials`` lists it
  with what to do.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import time
import urllib.request

import pytest
from cryptography.hazmat.primitives import serialization

from cryptoros import pemfiles
from cryptoros.lab.network import clean_env, stop, tool, wait_port
from tests.interceptor_harness import SYS_PY, robot_network, run_on
from tests.support import free_port, on_host, require, until
from tests.stream_support import talker_a_to_listener_b

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def net(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("operator"), start=("master",)) as network:
        yield network


def encrypted_copy(key_file, to, passphrase: bytes):
    key = pemfiles.load_private_key(key_file, None)
    to.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                     serialization.BestAvailableEncryption(passphrase)))
    return to


def interceptor(config, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([tool("cryptoros-interceptor"), "--config", str(config), *args], capture_output=True,
                          text=True, timeout=timeout, env=clean_env())


def one_line(result: subprocess.CompletedProcess, prog: str, status: int) -> str:
    assert result.returncode == status, (result.returncode, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), result.stderr
    return lines[0]


def with_tls_lines(config, tmp_path, name: str, **tls: str):
    """A copy of ``config`` with ``[tls]`` keys replaced or added."""
    text = config.read_text()
    for key, value in tls.items():
        text = re.sub(rf"^{key} = .*\n", "", text, flags=re.M)
        text = text.replace("[tls]\n", f'[tls]\n{key} = "{value}"\n', 1)
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_wrong_tls_key_passphrase_names_the_key_file_in_the_interceptor(net, tmp_path):
    config = net.hosts["robot_a"].config
    key = encrypted_copy(net.pki.pki.key_path_for("robot_a"), tmp_path / "robot_a.key", b"right passphrase")
    (tmp_path / "wrong.pass").write_text("wrong passphrase\n")
    (tmp_path / "right.pass").write_text("right passphrase\n")
    wrong = with_tls_lines(config, tmp_path, "wrong.toml", key=str(key),
                           tls_key_passphrase_file=str(tmp_path / "wrong.pass"))
    line = one_line(interceptor(wrong, "--check"), "cryptoros-interceptor", 2)
    assert f"TLS key {key}: the passphrase given does not open it" in line and "PEM lib" not in line
    none = with_tls_lines(config, tmp_path, "none.toml", key=str(key))
    line = one_line(interceptor(none, "--check"), "cryptoros-interceptor", 2)
    assert f"TLS key {key} is encrypted and no passphrase was given" in line
    # the right passphrase under the new name and under the old one: the file is good
    for name in ("tls_key_passphrase_file", "key_passphrase_file"):
        right = with_tls_lines(config, tmp_path, f"{name}.toml", key=str(key), **{name: str(tmp_path / "right.pass")})
        result = interceptor(right, "--check")
        assert result.returncode == 0 and "configuration ok" in result.stdout, result.stderr
    both = with_tls_lines(config, tmp_path, "both.toml", key=str(key), tls_key_passphrase_file=str(tmp_path / "right.pass"),
                          key_passphrase_file=str(tmp_path / "right.pass"))
    line = one_line(interceptor(both, "--check"), "cryptoros-interceptor", 2)
    assert "tls_key_passphrase_file and key_passphrase_file (its old name) are both given" in line


def test_a_wrong_tls_key_passphrase_names_the_key_file_in_the_authorization_server(net, tmp_path):
    server = net.pki.issue("authz2", kind="server", sans=("IP:127.0.0.1",))
    key = encrypted_copy(server.key_path, tmp_path / "authz2.key", b"right passphrase")
    (tmp_path / "wrong.pass").write_text("wrong passphrase\n")
    (tmp_path / "right.pass").write_text("right passphrase\n")

    def serve(passphrase_key: str, passphrase_file: str, port: int) -> subprocess.Popen:
        toml = tmp_path / f"serve-{passphrase_key}-{port}.toml"
        toml.write_text(f'host = "127.0.0.1"\nport = {port}\nca = "{net.pki.ca_cert}"\ncert = "{server.cert_path}"\n'
                        f'key = "{key}"\n{passphrase_key} = "{passphrase_file}"\n'
                        f'signing_key_passphrase_file = "{net.workdir / "signing.pass"}"\n')
        return subprocess.Popen([tool("cryptoros-authz"), "--db", net.db, "serve", "--config", str(toml)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=clean_env())

    proc = serve("tls_key_passphrase_file", str(tmp_path / "wrong.pass"), free_port())
    out, err = proc.communicate(timeout=60)
    line = one_line(subprocess.CompletedProcess(proc.args, proc.returncode, out, err), "cryptoros-authz", 2)
    assert f"TLS key {key}: the passphrase given does not open it" in line and "PEM lib" not in line
    port = free_port()
    proc = serve("key_passphrase_file", str(tmp_path / "right.pass"), port)  # the old name still works
    try:
        wait_port("127.0.0.1", port, 30, proc, "cryptoros-authz")
    finally:
        stop(proc)


@pytest.mark.parametrize("listener", ["public", "metrics", "local master"])
def test_a_listener_that_cannot_bind_is_named_with_its_address(net, listener):
    host = net.hosts["robot_a"]
    address = {"public": (host.address, host.public_port), "metrics": ("127.0.0.1", host.metrics_port),
               "local master": ("127.0.0.1", host.local_master_port)}[listener]
    with socket.socket() as squatter:
        squatter.bind(address)
        squatter.listen(1)
        result = interceptor(host.config, "--log-level", "error")  # the log goes to stderr too
    line = one_line(result, "cryptoros-interceptor", 1)
    assert line.endswith(f"cannot listen on {address[0]}:{address[1]} ({listener}): Address already in use"), line
    assert "Traceback" not in result.stdout + result.stderr


def test_sigterm_with_rospy_nodes_and_a_peer_stream_connected_exits_0_without_a_traceback(tmp_path):
    with robot_network(tmp_path) as network:
        with talker_a_to_listener_b(network):  # both nodes on their local masters, a stream A -> B
            for name in ("robot_b", "robot_a"):
                proc = network.hosts[name].proc
                proc.terminate()
                assert proc.wait(timeout=30) == 0
        for name in ("robot_a", "robot_b"):
            log = network.hosts[name].logs()
            assert "stopping" in log
            assert "Traceback" not in log and "CancelledError" not in log, log[-4000:]


def test_the_feed_says_it_answers_again_within_a_poll_of_the_servers_return(tmp_path):
    """The interceptor holds its feed long-polls (heartbeats every 15 s): the line comes
    with the first sign of life of the returned server, not when its first held poll
    ends (up to max_feed_age later)."""
    with robot_network(tmp_path, start=("master", "robot_a")) as network:
        host = network.hosts["robot_a"]
        args = list(network.authz_proc.args)
        stop(network.authz_proc, timeout=10)
        deadline = time.monotonic() + 15
        while "cannot poll the revocation feed" not in host.logs():
            assert time.monotonic() < deadline, "the interceptor did not notice the server was gone"
            time.sleep(0.1)
        with (network.workdir / "authz-again.log").open("w") as log:
            proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=clean_env())
        network.net.procs.append(proc)
        authz_host, port = network.authz_url[len("https://"):].rsplit(":", 1)
        wait_port(authz_host, int(port), 30, proc, "cryptoros-authz")
        back = time.monotonic()
        while "the revocation feed answers again" not in host.logs():
            # one poll interval (0.5 s here) and a request; 5 s of slack for a loaded machine
            assert time.monotonic() - back < 5.5, "no 'answers again' line within a poll of the server's return"
            time.sleep(0.1)


def test_a_stale_feed_tells_an_own_tool_why_its_new_stream_is_refused(tmp_path):
    """The authorization server down past ``max_feed_age`` (3 s here, on both ends):
    ``rostopic echo`` on the robot, which needs a new master stream (pooled ones close
    after 1 s unused), prints one error line naming ``feed_stale``; the robot's
    ``cryptoros denials`` lists it with what to do."""
    limits = "[limits]\nmax_feed_age = 3.0\ntunnel_idle_timeout = 1.0\n"
    with robot_network(tmp_path, start=("master", "robot_b"), extra={"master": limits, "robot_b": limits}) as network:
        host = network.hosts["robot_b"]

        def status() -> dict:
            with network.inside("robot_b"), urllib.request.urlopen(
                    f"http://127.0.0.1:{host.metrics_port}/status", timeout=5) as reply:
                return json.loads(reply.read())

        stop(network.authz_proc, timeout=10)
        until(lambda: (now := status())["health"].startswith("feed_stale") and now["open_streams"] == 0, 30,
              "robot_b's feed stale and its pooled streams closed")
        env = network.ros_env("robot_b")
        echo = subprocess.run(on_host([SYS_PY, require("rostopic")["rostopic"], "echo", "-n1", "/chatter"], env),
                              env=env, capture_output=True, text=True, timeout=60)
        assert echo.returncode == 1, (echo.stdout, echo.stderr)
        assert echo.stderr.strip().splitlines() == ["ERROR: denied by cryptoros: feed_stale"], echo.stderr
        listed = run_on(network, "robot_b", [tool("cryptoros"), "denials", "--config", str(host.config)]).stdout
        assert "feed_stale: revocation feed" in listed, listed
        assert "bring the authorization server back" in listed, listed
