"""Every stream between interceptors ends with its authority, on ROS 1 too.

Real rosmaster, a rospy talker on robot A, a rospy listener on robot B, real
interceptors and a real ``cryptoros-authz`` daemon.

- The daemon issues 10 s tokens and is killed: nobody gets a fresh token, and the
  listener stops receiving (the stream cut, logged with its reason, counted) within a
  token lifetime + ``token_grace`` + one check interval of the kill.
- A removed grant cuts the stream where it is judged, and that interceptor counts the
  cut under ``grant_removed``.
"""

from __future__ import annotations

import re
import subprocess
import time
import urllib.request

import pytest

from cryptoros.lab.network import clean_env, stop, wait_port
from tests.interceptor_harness import got, read_lines, robot_network
from tests.stream_support import talker_a_to_listener_b

pytestmark = [pytest.mark.ros1]

LIFETIME = 10  # the daemon's shortest token lifetime (authz_server.config.MIN_LIFETIME)
GRACE = 3.0
POLL = 0.5  # the harness's revocation_poll_interval


def short_token_daemon(net, lifetime: int = LIFETIME) -> subprocess.Popen:
    """Replace the lab's authorization daemon by the same one issuing ``lifetime``-second
    tokens (same port, registry and PKI)."""
    args = [*net.authz_proc.args, "--token-lifetime", str(lifetime)]
    stop(net.authz_proc, timeout=10)
    log = (net.workdir / "authz-short.log").open("w")
    proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=clean_env())
    net.net.procs.append(proc)
    net.net.authz_proc = proc
    host, port = net.authz_url[len("https://"):].rsplit(":", 1)
    wait_port(host, int(port), 30, proc, "cryptoros-authz", net.workdir / "authz-short.log")
    return proc


def with_authz_settings(net, name: str, **settings: float) -> None:
    config = net.hosts[name].config
    lines = "".join(f"{key} = {value}\n" for key, value in settings.items())
    config.write_text(config.read_text().replace("[authz]\n", "[authz]\n" + lines, 1))


def cutoffs(net, name: str) -> dict[str, float]:
    """``cryptoros_interceptor_revocation_cutoffs_total`` of host ``name``, by reason."""
    port = net.hosts[name].metrics_port
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {m[1]: float(m[2]) for m in re.finditer(
        r'^cryptoros_interceptor_revocation_cutoffs_total\{reason="([^"]+)"\} (\S+)$', text, re.M)}


def test_with_the_authorization_server_down_a_topic_stream_is_cut_once_the_tokens_expired_plus_grace(tmp_path):
    with robot_network(tmp_path, start=()) as net:
        daemon = short_token_daemon(net)
        for name in ("master", "robot_a", "robot_b"):
            with_authz_settings(net, name, token_grace=GRACE, refresh_margin=3)
            net.start(name)
        with talker_a_to_listener_b(net) as sub:
            stop(daemon, timeout=10)
            killed = time.monotonic()
            # every token any interceptor holds was issued before the kill: all expired
            # LIFETIME s after it at the latest; the cut follows within GRACE + a sweep
            bound = LIFETIME + GRACE + POLL
            deadline = killed + bound + 5  # + slack for a loaded machine
            while not any("token_expired" in net.hosts[n].logs() for n in ("robot_a", "robot_b")):
                assert time.monotonic() < deadline, (
                    f"no token_expired cut within {bound + 5:.1f} s of the daemon's kill; logs:\n"
                    + net.hosts["robot_a"].logs()[-3000:] + net.hosts["robot_b"].logs()[-3000:])
                time.sleep(0.1)
            cut_after = time.monotonic() - killed
            read_lines(sub, None, 0.5)  # what was in flight at the cut
            late = got(read_lines(sub, None, 3.0))
            assert not late, f"the listener still received {len(late)} messages after the cut"
        cuts = {}
        for name in ("robot_a", "robot_b"):
            found = re.findall(r"cutting off stream of manager=robot_[ab] jti=\w+: ((?:own_)?token_expired)",
                               net.hosts[name].logs())
            counted = cutoffs(net, name)
            for reason in set(found):  # each cut logged is counted with its reason
                assert counted.get(reason, 0) >= 1, (name, reason, counted)
            cuts[name] = found
        assert any(cuts.values()), cuts
        assert cut_after > GRACE  # not before the tokens expired and the grace ran out


def test_a_cut_by_a_removed_grant_is_counted_with_its_reason_where_it_happens(tmp_path):
    """The publisher's grant is removed: the subscriber's interceptor (its relay judged
    the publisher's side) cuts the stream, logs ``grant_removed`` and counts it."""
    with robot_network(tmp_path) as net:
        with talker_a_to_listener_b(net) as sub:
            result = net.cli("revoke", "robot_a", "publish", "/talker_a", "/chatter")
            assert result.returncode == 0, result.stderr
            deadline = time.monotonic() + 10
            while "grant_removed" not in net.hosts["robot_b"].logs():
                assert time.monotonic() < deadline, "robot B did not cut the stream within 10 s"
                time.sleep(0.1)
            read_lines(sub, None, 0.5)
            assert not got(read_lines(sub, None, 2.0)), "the listener still receives after the cut"
        assert cutoffs(net, "robot_b").get("grant_removed", 0) >= 1, cutoffs(net, "robot_b")
