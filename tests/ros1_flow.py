"""A legitimate ROS 1 flow held around an attack, for the ROS 1 insider and stranger
tests (no tests here): no attack outlives itself.

An unmodified rospy talker (tests/interceptor_nodes/node.py ``pub``) on one robot
publishes ``/flow`` at 20 Hz to an unmodified rospy listener (``sub``) on another,
through both robots' interceptors and the master's. The listener's lines are read by a
thread and timed as they leave its pipe. :meth:`Flow.held` wraps an attack: during it
the flow is never silent :data:`BACK_WITHIN` seconds, and after it the flow is back
within :data:`BACK_WITHIN` and never that silent again, with the same nodes and
interceptors (no restart). Its node names and topic are its own (rosmaster shuts a node
down when another registers its name), and name the host (the master's interceptor holds
a released name for its manager a while: ``name_hold_seconds``).
"""

from __future__ import annotations

import contextlib
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

from tests.interceptor_harness import DEFAULT_POLICY, NODE, SYS_PY
from tests.support import on_host, stop

TOPIC = "/flow"


def talker_name(host: str) -> str:
    return f"/flow_talker_{host}"


def listener_name(host: str) -> str:
    return f"/flow_listener_{host}"


HZ = 20
#: every legitimate flow is back within this long after an attack ends, and is never
#: silent this long during one
BACK_WITHIN = 5.0
#: messages the flow must deliver after an attack before it is judged (3 s at 20 Hz)
AFTER = 60


def flow_policy(policy: str = DEFAULT_POLICY, *, talker: str = "robot_a", listener: str = "robot_c") -> str:
    """``policy`` (the harness's default layout) with the flow's grants: ``talker`` may
    publish ``/flow`` from its flow talker, ``listener`` subscribe to it from its flow
    listener; nothing else changes."""
    pub = f"    - {{{{node: {talker_name(talker)}, topic: {TOPIC}, type: std_msgs/String}}}}\n"
    sub = f"    - {{{{node: {listener_name(listener)}, topic: {TOPIC}, type: std_msgs/String}}}}\n"
    return _add_grant(_add_grant(policy, talker, "publish", pub), listener, "subscribe", sub)


def _add_grant(policy: str, manager: str, kind: str, line: str) -> str:
    head = f"- name: {manager}\n  fingerprint_sha256: {{{manager}}}\n"
    start = policy.index(head) + len(head)
    end = policy.find("\n- name:", start)
    end = len(policy) if end < 0 else end + 1
    section = policy[start:end]
    if "  grants:\n" not in section:
        section = "  grants:\n" + section
    if f"    {kind}:\n" in section:
        section = section.replace(f"    {kind}:\n", f"    {kind}:\n{line}", 1)
    else:
        section = section.replace("  grants:\n", f"  grants:\n    {kind}:\n{line}", 1)
    return policy[:start] + section + policy[end:]


@dataclass
class Flow:
    """The running flow: its two nodes and the arrivals (monotonic time, sequence
    number) of the listener's messages, appended by a reader thread."""

    talker_host: str
    listener_host: str
    talker: subprocess.Popen
    listener: subprocess.Popen
    interceptors: dict[str, int]
    network: object
    arrivals: list[tuple[float, int]] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)
    ended: bool = False
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def _read(self) -> None:
        for raw in self.listener.stdout:
            at = time.monotonic()  # as the line leaves the listener's pipe
            line = raw.rstrip("\n")
            with self._cond:
                if line.startswith("GOT secret-"):
                    self.arrivals.append((at, int(line.rsplit("-", 1)[1])))
                else:
                    self.lines = [*self.lines[-9:], line]
                self._cond.notify_all()
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def until(self, done, timeout: float, what: str) -> None:
        """Wait (bounded) until ``done()`` holds, woken by each line of the listener."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not done():
                left = deadline - time.monotonic()
                assert left > 0 and not self.ended, (
                    f"{what} within {timeout} s ({len(self.arrivals)} messages of the flow "
                    f"{self.talker_host} -> {self.listener_host}; listener's last other lines {self.lines[-5:]}"
                    f"{'; the listener ended' if self.ended else ''})")
                self._cond.wait(min(left, 0.5))

    def since(self, moment: float) -> int:
        return sum(1 for t, _ in self.arrivals if t > moment)

    def silence(self, start: float, stop: float | None = None) -> float:
        """The longest silence of the flow from ``start`` to ``stop`` (None: to its last
        message), both ends counted."""
        with self._cond:
            times = [start] + [t for t, _ in self.arrivals if t > start and (stop is None or t < stop)]
        times += [stop] if stop is not None else []
        return max((b - a for a, b in zip(times, times[1:])), default=float("inf"))

    def alive(self) -> None:
        """The flow's nodes and the interceptors it goes through run as they were started."""
        assert self.talker.poll() is None, "the flow's talker exited"
        assert self.listener.poll() is None, "the flow's listener exited"
        for name, pid in self.interceptors.items():
            proc = self.network.hosts[name].proc
            assert proc is not None and proc.pid == pid and proc.poll() is None, f"{name}'s interceptor was restarted"

    @contextlib.contextmanager
    def held(self, what: str = "the attack") -> Iterator[None]:
        """Wrap an attack: the flow delivers before it, is never silent BACK_WITHIN
        seconds during it, and is back within BACK_WITHIN after it (judged on AFTER
        messages), with no node or interceptor restarted."""
        self.alive()
        before = time.monotonic()
        self.until(lambda: self.since(before) >= 2, 30, f"the flow did not deliver before {what}")
        start = time.monotonic()
        yield
        end = time.monotonic()
        self.until(lambda: self.since(end) >= AFTER, 40, f"the flow did not come back after {what}")
        during, after = self.silence(start, end), self.silence(end)
        with self._cond:
            seqs = [seq for t, seq in self.arrivals if t > start]
        lost = seqs[-1] - seqs[0] + 1 - len(seqs)
        print(f"the flow's longest silence: {during:.2f} s during {what} ({end - start:.1f} s), {after:.2f} s after it"
              f" ({len(seqs)} messages since it began, {lost} missing from their sequence)")
        assert during < BACK_WITHIN, f"the flow was silent {during:.1f} s during {what}"
        assert after < BACK_WITHIN, f"the flow was silent {after:.1f} s after {what}"
        self.alive()


@contextlib.contextmanager
def legit_flow(network, talker: str = "robot_a", listener: str = "robot_c") -> Iterator[Flow]:
    """The flow from ``talker``'s host to ``listener``'s (the policy from
    :func:`flow_policy`), delivering before this yields; stopped after, with the
    interceptors this started for it."""
    started: list[str] = []
    procs: list[subprocess.Popen] = []
    try:
        for name in (talker, listener):
            if network.hosts[name].proc is None or network.hosts[name].proc.poll() is not None:
                network.start(name)
                started.append(name)
        sub = subprocess.Popen(on_host([SYS_PY, NODE, "sub", listener_name(listener), TOPIC, "86400"],
                                       network.ros_env(listener)),
                               env=network.ros_env(listener), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
        procs.append(sub)
        pub = subprocess.Popen(on_host([SYS_PY, NODE, "pub", talker_name(talker), TOPIC, "100000000", str(HZ)],
                                       network.ros_env(talker)),
                               env=network.ros_env(talker), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               text=True)
        procs.append(pub)
        threading.Thread(target=_drain, args=(pub,), daemon=True).start()
        flow = Flow(talker, listener, pub, sub, network=network,
                    interceptors={n: network.hosts[n].proc.pid for n in ("master", talker, listener)})
        threading.Thread(target=flow._read, daemon=True).start()
        flow.until(lambda: len(flow.arrivals) >= 5, 60, "the flow never started")
        yield flow
    finally:
        for proc in reversed(procs):
            stop(proc, timeout=5)
        for name in started:
            network.stop(name)


def _drain(proc: subprocess.Popen) -> None:
    for _ in proc.stdout:
        pass
