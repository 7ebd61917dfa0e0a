"""docs/runbook.md, executed: every fenced ``sh`` block runs as written, in order, in a
fresh ``bash -e`` in one temporary directory, with the placeholders (shell variables)
the runbook documents at its top; after each block the effect of its step is checked.

Part 1 (``# step: master-*``) builds a master host on an empty machine; part 2 runs
the day-2 steps against a lab network (real authz daemon, rosmaster, interceptors)
while a rospy talker on robot A streams to a listener on robot B.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import threading
import time
import urllib.request
import xmlrpc.client
from pathlib import Path

import pytest

from cryptoros.lab.network import clean_env, free_port
from tests.interceptor_harness import NODE, SYS_PY, got, read_lines, robot_network, wait_registered
from tests.support import REPO, VENV_BIN, require, running

pytestmark = [pytest.mark.ros1]

RUNBOOK = REPO / "docs" / "runbook.md"
BLOCK = re.compile(r"^```sh\n(.*?)^```", re.S | re.M)


def steps() -> list[tuple[str, str]]:
    """(step name, script) of every ``sh`` block, in order."""
    out = []
    for script in BLOCK.findall(RUNBOOK.read_text()):
        first = script.splitlines()[0]
        assert first.startswith("# step: "), f"a runbook block without '# step: NAME': {first!r}"
        out.append((first[len("# step: "):].strip(), script))
    return out


def run_block(name: str, script: str, cwd: Path, env: dict[str, str], timeout: float = 180) -> str:
    result = subprocess.run(["bash", "-e", "-c", script], cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=timeout, stdin=subprocess.DEVNULL)
    assert result.returncode == 0, f"runbook step {name} failed ({result.returncode}):\n{result.stdout[-3000:]}\n" \
                                   f"{result.stderr[-3000:]}"
    return result.stdout


def base_env(**extra: str) -> dict[str, str]:
    return clean_env(PATH=f"{VENV_BIN}:{os.environ.get('PATH', '/usr/bin:/bin')}", **extra)


def stop_pid(pid: int, timeout: float = 15) -> None:
    """Stop a daemon the runbook started (by its pid file), bounded."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def pid_of(path: Path) -> int:
    return int(path.read_text().split()[0])


def until(check, within: float, what: str):
    deadline = time.monotonic() + within
    while True:
        value = check()
        if value:
            return value
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def test_runbook_has_both_parts_and_every_step_a_check():
    names = [name for name, _ in steps()]
    assert names[:6] == ["master-pki", "master-registry", "master-authz", "master-rosmaster", "master-interceptor",
                         "master-processes"]
    assert set(names[6:]) == set(DAY2_CHECKS), names
    assert "## Part 1: the master host" in RUNBOOK.read_text() and "## Part 2: day-2 operations" in RUNBOOK.read_text()


# ------------------------------------------------------------------ part 1: the master host

def test_master_host_walkthrough(tmp_path):
    require("rosmaster", "curl")
    ports: set[int] = set()
    addr = "127.0.0.14"
    env = base_env(MASTER_ADDR=addr, PUBLIC_PORT=str(free_port(addr, ports)), ROS_PORT=str(free_port(taken=ports)),
                   AUTHZ_PORT=str(free_port(addr, ports)), PROBE_PORT=str(free_port(taken=ports)),
                   METRICS_PORT=str(free_port(taken=ports)))
    work = tmp_path / "master-host"
    work.mkdir()
    try:
        for name, script in steps():
            if not name.startswith("master-"):
                continue
            out = run_block(name, script, work, env)
            if name == "master-pki":
                assert all((work / "pki" / p).exists() for p in ("ca.crt", "crl.pem", "issued/authz.crt",
                                                                 "issued/master.crt", "private/master.key"))
            elif name == "master-registry":
                assert len(subprocess.run([str(VENV_BIN / "cryptoros-authz"), "--db", f"sqlite:///{work}/registry.db",
                                           "list-keys"], capture_output=True, text=True, timeout=60,
                                          env=env).stdout.splitlines()) == 1
            elif name == "master-authz":
                with urllib.request.urlopen(f"http://127.0.0.1:{env['PROBE_PORT']}/healthz", timeout=5) as reply:
                    assert reply.status == 200
            elif name == "master-rosmaster":
                code, _msg, _state = xmlrpc.client.ServerProxy(f"http://127.0.0.1:{env['ROS_PORT']}/").getSystemState("/t")
                assert code == 1
            elif name == "master-interceptor":
                assert "manager master" in out and "token     subject master" in out, out
            elif name == "master-processes":
                lines = out.strip().splitlines()
                assert len(lines) == 3, out
                assert any("cryptoros-authz serve" in line for line in lines)
                assert any("rosmaster --core" in line for line in lines)
                assert any("cryptoros-interceptor --config master.toml" in line for line in lines), out
    finally:
        for pidfile in ("interceptor.pid", "rosmaster.pid", "authz.pid"):
            if (work / pidfile).exists():
                stop_pid(pid_of(work / pidfile))


# ------------------------------------------------------------------ part 2: day 2

def _registers(net, node: str) -> int:
    uri = "http://127.0.0.1:9/"
    local = xmlrpc.client.ServerProxy(net.hosts["robot_b"].master_uri)
    code = local.registerSubscriber(node, "/secret", "std_msgs/String", uri)[0]
    if code == 1:
        local.unregisterSubscriber(node, "/secret", uri)
    return code


def _receives(ctx, within: float = 10) -> None:
    read_lines(ctx["sub"], None, 0.2)
    assert got(read_lines(ctx["sub"], "GOT", within)), "the listener on robot B stopped receiving"


def check_add_grant(net, ctx, out):
    until(lambda: _registers(net, "/listener_new") == 1, 10, "the new grant did not work within 10 s")


def check_remove_grant(net, ctx, out):
    until(lambda: _registers(net, "/listener_new") == -1, 10, "the removed grant still works after 10 s")
    _receives(ctx)


def check_stock_tools(net, ctx, out):
    lines = out.splitlines()
    assert "1" in lines, out  # rosparam get /runbook/x
    assert any(line.startswith('data: "secret-') for line in lines), out  # rostopic echo
    assert "/talker_a" in lines, out  # rosnode list


def check_renew(net, ctx, out):
    status = json.loads(subprocess.run([str(VENV_BIN / "cryptoros"), "status", "--config", str(net.hosts["robot_b"].config),
                                        "--json"], capture_output=True, text=True, timeout=30).stdout)
    new = re.search(r"^serial:\s+(\S+)", out, re.M).group(1)
    assert status["certificate"]["serial"] == new
    assert "revoked serial" in out
    _receives(ctx)


def check_rotate_key(net, ctx, out):
    keys = [line for line in out.splitlines() if "created" in line]
    assert len(keys) == 2 and sum(" active" in line for line in keys) == 1, out
    active = next(line.split()[0] for line in keys if " active" in line)

    def new_kid() -> bool:
        import jwt

        status, body = net.daemon.token("robot_a")
        return status == 200 and jwt.get_unverified_header(body["access_token"])["kid"] == active

    until(new_kid, 30, "tokens are not signed with the new key 30 s after rotate-key")
    _receives(ctx)


def check_restart_interceptor(net, ctx, out):
    pid = pid_of(Path(ctx["run"]) / "robot_b.pid")
    assert pid != net.hosts["robot_b"].proc.pid and Path(f"/proc/{pid}").exists()
    ctx["started"].append(pid)
    _receives(ctx)


def check_restart_master_interceptor(net, ctx, out):
    pid = pid_of(Path(ctx["run"]) / "master.pid")
    assert pid != net.hosts["master"].proc.pid
    ctx["started"].append(pid)
    assert "/talker_a" in out.split(), out
    _receives(ctx)


def check_restart_authz(net, ctx, out):
    pid = pid_of(Path(ctx["run"]) / "authz.pid")
    assert pid != net.authz_proc.pid
    ctx["started"].append(pid)
    assert net.daemon.token("robot_a")[0] == 200
    _receives(ctx)


def check_restart_rosmaster(net, ctx, out):
    pid = pid_of(Path(ctx["run"]) / "rosmaster.pid")
    ctx["started"].append(pid)
    # the new rosmaster holds the talker again: the master's interceptor replayed it
    wait_registered(net, "/talker_a", timeout=15)
    _receives(ctx)


def check_revoke_cert(net, ctx, out):
    def refused() -> bool:
        try:
            return net.daemon.token("robot_c")[0] != 200
        except OSError:  # the handshake itself is refused (the CRL lists it)
            return True

    until(refused, 5, "robot C still gets tokens 5 s after its revocation")
    assert "revoked" in out


DAY2_CHECKS = {
    "add-grant": check_add_grant,
    "remove-grant": check_remove_grant,
    "stock-tools": check_stock_tools,
    "renew": check_renew,
    "rotate-key": check_rotate_key,
    "restart-interceptor": check_restart_interceptor,
    "restart-master-interceptor": check_restart_master_interceptor,
    "restart-authz": check_restart_authz,
    "restart-rosmaster": check_restart_rosmaster,
    "revoke-cert": check_revoke_cert,
}


def _write_authz_toml(net, path: Path) -> None:
    """The lab daemon's command line as the ``authz.toml`` the runbook restarts it with."""
    args = list(net.authz_proc.args)
    flags = {args[i]: args[i + 1] for i in range(len(args) - 1) if args[i].startswith("--")}
    values = {"db": flags["--db"], "host": flags["--host"], "port": int(flags["--port"]), "ca": flags["--ca"],
              "cert": flags["--cert"], "key": flags["--key"], "crl": flags["--crl"],
              "signing_key_passphrase_file": flags["--key-passphrase-file"]}
    path.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items()))


def test_day2_runbook(tmp_path):
    require("rosmaster", "rostopic", "rosparam", "rosnode")
    state = {name: f'state_dir = "{tmp_path / "state" / name}"' for name in ("master", "robot_a", "robot_b")}
    with robot_network(tmp_path / "lab", start=("master", "robot_a", "robot_b"), extra=state) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "1000000", "20", "600"],
                    env=net.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(net, "/talker_a")
        run = net.workdir
        rosmaster = next(p for p in net.procs if "rosmaster" in str(p.args[0]))
        for name, proc in (("master", net.hosts["master"].proc), ("robot_b", net.hosts["robot_b"].proc),
                           ("rosmaster", rosmaster), ("authz", net.authz_proc)):
            (run / f"{name}.pid").write_text(f"{proc.pid}\n")
            # reaped as soon as the runbook stops it (as a service manager would): no zombie
            # for the runbook's ``tail --pid`` to wait on
            threading.Thread(target=proc.wait, daemon=True).start()
        _write_authz_toml(net, run / "authz.toml")
        env = base_env(CRYPTOROS_PKI_DIR=str(net.pki.pki.directory), CRYPTOROS_AUTHZ_DB=net.db, RUN=str(run),
                       ROS_MASTER_URI=net.hosts["robot_b"].master_uri, ROS_IP="127.0.0.1",
                       ROS_HOME=str(tmp_path / "ros_home"), ROSMASTER_PORT=net.rosmaster_uri.rstrip("/").rsplit(":", 1)[1])
        work = tmp_path / "runbook"
        work.mkdir()
        ctx = {"run": str(run), "started": []}
        try:
            with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "600"], env=net.ros_env("robot_b")) as sub:
                ctx["sub"] = sub
                read_lines(sub, "READY", 20)
                assert got(read_lines(sub, "GOT", 20))
                for name, script in steps():
                    if name.startswith("master-"):
                        continue
                    out = run_block(name, script, work, env)
                    DAY2_CHECKS[name](net, ctx, out)
        finally:
            for pid in ctx["started"]:
                stop_pid(pid)
