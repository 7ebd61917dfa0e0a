"""``cryptoros bench soak``: day-2 churn for minutes, with one stream watched throughout.

Builds the interceptor test bed (real Debian ``rosmaster`` behind the master's
interceptor, robot A's and robot B's interceptors, a real ``cryptoros-authz serve``;
every interceptor with a ``state_dir``) and runs, for ``--seconds``:

- the watched stream: a rospy talker on robot A (``/soak_talker``) publishes
  ``/chatter`` at ``--hz`` with a sequence number, a rospy listener on robot B
  (``/soak_listener``) receives it; its grants never change;
- nodes come and go: rospy publishers ``/churn_pub_<i>`` on robot A and subscribers
  ``/churn_sub_<i>`` on robot B (granted by the node patterns ``/churn_pub_*`` and
  ``/churn_sub_*``), each living a few seconds, stopped with SIGTERM;
- grants flip: ``cryptoros-authz revoke`` / ``grant`` of robot B's unrelated grant
  ``/flip_listener subscribe /flip`` (each revoke revokes robot B's live tokens: the
  watched stream must survive it);
- one interceptor restarts (``--restart``, default the master's: the watched stream
  does not pass through it) a third of the way in;
- the authorization server restarts two thirds of the way in.

Every event runs: one that falls due while an earlier one is still running (a restart
on a loaded host) runs late, and the soak ends after the last of them.

It prints progress lines while it runs, then per process (the three interceptors and
the authorization server) open fds (``/proc/PID/fd``) and RSS at start and end (and
the TCP sockets among the fds at the end, listening and established), the messages
lost on the watched stream and its longest gap, and how many stopped churn nodes
rosmaster still lists; ``--json`` prints one JSON object instead (progress goes to
stderr). Nothing is asserted.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import click

from cryptoros.lab.policy import policy_yaml
from cryptoros.ros1.uri import host_port

POLICY = policy_yaml({
    "master": {},
    "robot_a": {"publish": [("/soak_talker", "/chatter", "std_msgs/String"),
                            ("/churn_pub_*", "/churn", "std_msgs/String")]},
    "robot_b": {"subscribe": [("/soak_listener", "/chatter", "std_msgs/String"),
                              ("/churn_sub_*", "/churn", "std_msgs/String"),
                              ("/flip_listener", "/flip", "std_msgs/String")]},
})
HOSTS = {"master": "127.0.0.4", "robot_a": "127.0.0.2", "robot_b": "127.0.0.3"}
FLIP = ("robot_b", "subscribe", "/flip_listener", "/flip")
ROS_PYTHON = "/usr/bin/python3"

#: The rospy node every process of the soak runs (Debian's python3, written to the
#: work directory): ``pub NODE TOPIC HZ`` publishes sequence numbers and prints
#: ``AT <seq>`` twice a second; ``sub NODE TOPIC`` prints ``GOT <data>``. SIGTERM
#: shuts rospy down cleanly (unregistering at the master).
NODE_SCRIPT = r'''
import signal, sys, time
import rospy
from std_msgs.msg import String
mode, node, topic = sys.argv[1], sys.argv[2], sys.argv[3]
rospy.init_node(node.lstrip("/"), disable_signals=True)
signal.signal(signal.SIGTERM, lambda *_: rospy.signal_shutdown("SIGTERM"))
if mode == "pub":
    hz = float(sys.argv[4])
    pub = rospy.Publisher(topic, String, queue_size=1000, tcp_nodelay=True)
    print("READY", flush=True)
    seq, last_at = 0, 0.0
    while not rospy.is_shutdown():
        pub.publish(String(data=str(seq)))
        now = time.monotonic()
        if now - last_at >= 0.5:
            print("AT", seq, flush=True)
            last_at = now
        seq += 1
        time.sleep(1.0 / hz)
else:
    rospy.Subscriber(topic, String, lambda m: print("GOT", m.data, flush=True), tcp_nodelay=True)
    print("READY", flush=True)
    while not rospy.is_shutdown():
        time.sleep(0.1)
'''


def usage(pid: int) -> tuple[int, int]:
    """(open fds, RSS in KiB) of a live process; (-1, -1) if it is gone."""
    try:
        fds = len(os.listdir(f"/proc/{pid}/fd"))
        rss = 0
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1])
        return fds, rss
    except OSError:
        return -1, -1


def socket_states(pid: int) -> dict[str, int]:
    """The TCP sockets among a process's fds, by state (listen, established, other)."""
    names = {"0A": "listen", "01": "established"}
    try:
        inodes = set()
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        counts = {"listen": 0, "established": 0, "other": 0}
        for table in ("tcp", "tcp6"):
            with contextlib.suppress(OSError):
                for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
                    fields = line.split()
                    if len(fields) > 9 and fields[9] in inodes:
                        counts[names.get(fields[3], "other")] += 1
        return counts
    except OSError:
        return {}


@dataclass
class Lines:
    """A child's output lines with the (monotonic) time each was read, by a thread."""

    proc: subprocess.Popen
    lines: list[tuple[float, str]] = field(default_factory=list)
    ready: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))
            if line.startswith("READY"):
                self.ready.set()

    def numbers(self, prefix: str) -> list[tuple[float, int]]:
        out = []
        for at, line in list(self.lines):
            if line.startswith(prefix + " "):
                with contextlib.suppress(ValueError):
                    out.append((at, int(line.split()[1])))
        return out


def stream_figures(received: list[tuple[float, int]], published: list[tuple[float, int]], start: float, end: float,
                   in_flight: float = 1.0) -> dict:
    """Loss and longest gap of the watched stream over [start, end]: the messages from
    the first received after ``start`` up to the last the talker reported ``in_flight``
    seconds before ``end`` (``expected``; ``received`` and ``lost`` count the same span,
    so they add up to it), and the longest time without a message in the window.
    Messages sent after that report may still be on their way at ``end``: they are
    counted apart (``newer``), neither received nor lost."""
    window = [(at, seq) for at, seq in received if start <= at <= end]
    times = [start] + [at for at, _ in window] + [end]
    longest, gap_at = max(((b - a, a) for a, b in zip(times, times[1:])), default=(end - start, start))
    gap = {"longest_gap_s": round(longest, 3), "longest_gap_at_s": round(gap_at - start, 1)}
    if not window:
        return {"received": 0, "expected": None, "lost": None, "duplicates": 0, "newer": 0, **gap}
    first = window[0][1]
    upper = max((seq for at, seq in published if at <= end - in_flight), default=first)
    seqs = [seq for _, seq in window]
    got = set(seqs)
    expected = max(0, upper - first + 1)
    missing = [s for s in range(first, upper + 1) if s not in got]
    return {"received": sum(1 for s in got if s <= upper), "expected": expected, "lost": len(missing),
            "duplicates": len(seqs) - len(got), "newer": sum(1 for s in got if s > upper),
            "first_lost": missing[0] if missing else None, **gap}


class Soak:
    def __init__(self, net, work: Path, say) -> None:
        self.net, self.work, self.say = net, work, say
        self.script = work / "soak_node.py"
        self.script.write_text(NODE_SCRIPT)
        self.children: list[subprocess.Popen] = []
        self.churn: list[tuple[float, subprocess.Popen]] = []
        self.counts = {"nodes_started": 0, "nodes_stopped": 0, "grant_flips": 0, "interceptor_restarts": 0,
                       "authz_restarts": 0}
        self.flip_granted = True
        self.t0 = time.monotonic()
        #: (seconds since the soak started, what happened)
        self.timeline: list[tuple[float, str]] = []

    def note(self, what: str) -> None:
        self.timeline.append((round(time.monotonic() - self.t0, 1), what))
        self.say(what)

    def node(self, host: str, *argv: str, read: bool = True) -> subprocess.Popen:
        from cryptoros.lab.network import NETNS_ENV

        env = self.net.ros_env(host)
        cmd = [ROS_PYTHON, str(self.script), *argv]
        ns = env.get(NETNS_ENV)
        proc = subprocess.Popen(["ip", "netns", "exec", ns, *cmd] if ns else cmd, env=env,
                                stdout=subprocess.PIPE if read else subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                text=True)
        self.children.append(proc)
        return proc

    def churn_node(self, i: int, now: float, life: float) -> None:
        if i % 2 == 0:
            proc = self.node("robot_a", "pub", f"/churn_pub_{i}", "/churn", "5", read=False)
        else:
            proc = self.node("robot_b", "sub", f"/churn_sub_{i}", "/churn", read=False)
        self.churn.append((now + life, proc))
        self.counts["nodes_started"] += 1
        self.timeline.append((round(now - self.t0, 1), f"node {proc.args[-3 if i % 2 == 0 else -2]} started"))

    def reap(self, now: float, *, all_: bool = False) -> None:
        from cryptoros.lab.network import stop

        keep = []
        for until, proc in self.churn:
            if all_ or now >= until:
                stop(proc, timeout=5)
                self.counts["nodes_stopped"] += 1
            else:
                keep.append((until, proc))
        self.churn = keep

    def authz_cli(self, *args: str) -> subprocess.CompletedProcess:
        from cryptoros.lab.network import clean_env, tool

        return subprocess.run([tool("cryptoros-authz"), "--db", self.net.db, *args], capture_output=True, text=True,
                              timeout=60, env=clean_env())

    def flip(self) -> None:
        verb = "revoke" if self.flip_granted else "grant"
        result = self.authz_cli(verb, *FLIP, *(["std_msgs/String"] if verb == "grant" else []))
        if result.returncode != 0:
            raise click.ClickException(f"cryptoros-authz {verb} failed: {result.stderr.strip()}")
        self.flip_granted = not self.flip_granted
        self.counts["grant_flips"] += 1
        self.note(f"grant flip: {verb} {' '.join(FLIP)}")

    def restart_interceptor(self, name: str) -> float:
        t = time.monotonic()
        self.net.stop(name)
        self.net.start(name)
        self.counts["interceptor_restarts"] += 1
        took = time.monotonic() - t
        self.note(f"interceptor {name} restarted (listening again after {took:.1f} s)")
        return took

    def restart_authz(self) -> float:
        from cryptoros.lab.network import clean_env, stop, wait_port

        t = time.monotonic()
        old = self.net.authz_proc
        stop(old, timeout=10)
        host, port = host_port(self.net.authz_url, ("https",))
        log = (self.work / "authz.log").open("a")
        proc = subprocess.Popen(old.args, stdout=log, stderr=subprocess.STDOUT, env=clean_env(), **self.net.popen_extra)
        self.net.authz_proc = proc
        self.net.procs.append(proc)
        wait_port(host, int(port), 30, proc, "cryptoros-authz", self.work / "authz.log")
        self.counts["authz_restarts"] += 1
        took = time.monotonic() - t
        self.note(f"authorization server restarted (listening again after {took:.1f} s)")
        return took

    def stale_churn_nodes(self, within: float) -> list[str]:
        """Churn nodes rosmaster still lists (all were stopped with SIGTERM, which
        unregisters them), after waiting up to ``within`` seconds for them to go."""
        import xmlrpc.client

        deadline = time.monotonic() + within
        while True:
            with self.net.inside("master"):
                state = xmlrpc.client.ServerProxy(self.net.rosmaster_uri).getSystemState("/soak")[2]
            nodes = sorted({n for section in state for _name, ns in section for n in ns if n.startswith("/churn_")})
            if not nodes or time.monotonic() > deadline:
                return nodes
            time.sleep(0.5)

    def processes(self) -> dict[str, int]:
        pids = {name: h.proc.pid for name, h in self.net.hosts.items() if h.proc is not None}
        pids["authz"] = self.net.authz_proc.pid
        return pids


def run_soak(seconds: float, hz: float, restart: str, say, keep: bool = False) -> dict:
    from cryptoros.lab.network import lab_network, stop

    if shutil.which("rosmaster") is None:
        raise click.ClickException("rosmaster is not installed (scripts/install-system-parts installs it as root)")
    if not Path(ROS_PYTHON).exists():
        raise click.ClickException(f"{ROS_PYTHON} (Debian's, with rospy) is missing")
    work = Path(tempfile.mkdtemp(prefix="cryptoros-bench-soak-"))
    extra = {name: f'state_dir = "{work / "state" / name}"' for name in HOSTS}
    try:
        with lab_network(work, POLICY, hosts=HOSTS, master="rosmaster", progress=say, extra=extra,
                         poll_interval=0.5) as net:
            soak = Soak(net, work, say)
            try:
                return _run(soak, seconds, hz, restart, say)
            finally:
                soak.reap(time.monotonic(), all_=True)
                for proc in soak.children:
                    stop(proc, timeout=5)
    finally:
        if keep:
            say(f"work directory (logs) kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


def _run(soak: Soak, seconds: float, hz: float, restart: str, say) -> dict:
    say("watched stream: /soak_talker on robot_a -> /soak_listener on robot_b, /chatter")
    talker = Lines(soak.node("robot_a", "pub", "/soak_talker", "/chatter", str(hz)))
    listener = Lines(soak.node("robot_b", "sub", "/soak_listener", "/chatter"))
    deadline = time.monotonic() + 40
    while not listener.numbers("GOT"):
        if time.monotonic() > deadline or talker.proc.poll() is not None or listener.proc.poll() is not None:
            raise click.ClickException("the watched stream never delivered a message within 40 s")
        time.sleep(0.1)
    pids_start = soak.processes()
    start_usage = {name: usage(pid) for name, pid in pids_start.items()}
    start = soak.t0 = time.monotonic()
    end = start + seconds
    churn_every = max(2.0, min(5.0, seconds / 12))
    flip_every = max(3.0, min(10.0, seconds / 8))
    events = sorted([(start + seconds / 3, "restart"), (start + 2 * seconds / 3, "authz")]
                    + [(start + t * churn_every, "churn") for t in range(1, int(seconds / churn_every))]
                    + [(start + t * flip_every, "flip") for t in range(1, int(seconds / flip_every))])
    say(f"soak for {seconds:.0f} s: a node every {churn_every:.0f} s, a grant flip every {flip_every:.0f} s, "
        f"{restart}'s interceptor restarts at {seconds / 3:.0f} s, the authorization server at {2 * seconds / 3:.0f} s")
    restarts: dict[str, float] = {}
    next_progress = start + 10
    i = 0
    while (now := time.monotonic()) < end or events:  # every event runs, late if need be
        while events and events[0][0] <= now:
            _, kind = events.pop(0)
            if kind == "churn":
                soak.churn_node(i, now, life=min(8.0, 2 * churn_every))
                i += 1
            elif kind == "flip":
                soak.flip()
            elif kind == "restart":
                restarts["interceptor_s"] = round(soak.restart_interceptor(restart), 2)
            else:
                restarts["authz_s"] = round(soak.restart_authz(), 2)
        soak.reap(now)
        if now >= next_progress:
            fig = stream_figures(listener.numbers("GOT"), talker.numbers("AT"), start, now)
            say(f"t={now - start:4.0f} s: watched stream received {fig['received']}, lost {fig['lost']}, "
                f"longest gap {fig['longest_gap_s']:.2f} s; churn nodes alive {len(soak.churn)}")
            next_progress += 10
        time.sleep(0.1)  # the scheduler's tick
    end = time.monotonic()
    soak.reap(end, all_=True)
    if not soak.flip_granted:
        soak.flip()  # leave the registry as it was
    stale = soak.stale_churn_nodes(within=10)
    if stale:
        say(f"rosmaster still lists {len(stale)} stopped churn nodes 10 s after the last stopped: {', '.join(stale[:5])}")
    pids_end = soak.processes()
    end_usage = {name: usage(pid) for name, pid in pids_end.items()}
    end_sockets = {name: socket_states(pid) for name, pid in pids_end.items()}
    figures = stream_figures(listener.numbers("GOT"), talker.numbers("AT"), start, end)
    alive = talker.proc.poll() is None and listener.proc.poll() is None
    return {
        "seconds": round(end - start, 1),
        "hz": hz,
        "restarted_interceptor": restart,
        "events": soak.counts,
        "restart_times": restarts,
        "timeline": sorted(soak.timeline),
        "watched_stream": {**figures, "nodes_alive_at_end": alive},
        "stale_churn_registrations": len(stale),
        "processes": {
            name: {"pid_start": pids_start[name], "pid_end": pids_end[name],
                   "fds_start": start_usage[name][0], "fds_end": end_usage[name][0],
                   "rss_kib_start": start_usage[name][1], "rss_kib_end": end_usage[name][1],
                   "tcp_end": end_sockets[name]}
            for name in pids_start
        },
    }


@click.command("soak")
@click.option("--seconds", type=click.FloatRange(10, 24 * 3600), default=120, show_default=True,
              help="How long the churn runs.")
@click.option("--hz", type=click.FloatRange(1, 500), default=20, show_default=True,
              help="Rate of the watched talker.")
@click.option("--restart", type=click.Choice(["master", "robot_a", "robot_b"]), default="master", show_default=True,
              help="The interceptor that restarts (robot_a or robot_b: the watched stream passes through it).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (progress goes to stderr).")
@click.option("--keep", is_flag=True, help="Keep the work directory (interceptor and authz logs).")
def soak(seconds: float, hz: float, restart: str, as_json: bool, keep: bool) -> None:
    """Day-2 churn for minutes: nodes come and go, grants flip, an interceptor and the
    authorization server restart; fds, RSS, loss and the longest gap of a stream that
    stays granted."""

    def say(message: str) -> None:
        click.echo(f"... {message}", err=as_json)
        if as_json:
            sys.stderr.flush()

    result = run_soak(seconds, hz, restart, say, keep)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    s, e = result["watched_stream"], result["events"]
    click.echo("")
    click.echo(f"soak: {result['seconds']:.0f} s; {e['nodes_started']} nodes started, {e['nodes_stopped']} stopped, "
               f"{e['grant_flips']} grant flips, {e['interceptor_restarts']} interceptor restart ({restart}), "
               f"{e['authz_restarts']} authorization server restart")
    click.echo(f"watched stream (granted throughout, {hz:g} Hz): received {s['received']}, expected {s['expected']}, "
               f"lost {s['lost']}, duplicates {s['duplicates']}, longest gap {s['longest_gap_s']:.2f} s "
               f"(at {s['longest_gap_at_s']:.0f} s); {s.get('newer', 0)} newer, sent in the last second, not counted")
    click.echo(f"stopped churn nodes rosmaster still lists: {result['stale_churn_registrations']}")
    click.echo("")
    click.echo(f"{'process':12} {'fds start':>9} {'fds end':>8} {'RSS start MiB':>14} {'RSS end MiB':>12} "
               f"{'TCP listen/estab end':>21}  pid")
    for name, p in result["processes"].items():
        pid = f"{p['pid_start']}" + (f" -> {p['pid_end']} (restarted)" if p["pid_end"] != p["pid_start"] else "")
        tcp = p["tcp_end"]
        click.echo(f"{name:12} {p['fds_start']:>9} {p['fds_end']:>8} {p['rss_kib_start'] / 1024:>14.1f} "
                   f"{p['rss_kib_end'] / 1024:>12.1f} {tcp.get('listen', 0):>10}/{tcp.get('established', 0):<10}  {pid}")


__all__ = ["run_soak", "soak", "stream_figures"]
