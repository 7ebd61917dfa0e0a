"""cryptoros.lab.processes: the one free-port picker and process stopper."""

from __future__ import annotations

import os
import socket
import time
import subprocess
import sys

import pytest

from cryptoros.errors import CryptorosError
from cryptoros.lab import network
from cryptoros.lab.processes import NetworkError, free_port, stop, wait_port


def test_free_port_never_hands_out_a_port_twice():
    taken: set[int] = set()
    ports = [free_port(taken=taken) for _ in range(5)]
    assert len(set(ports)) == 5 and set(ports) == taken
    with socket.socket() as s:
        s.bind(("127.0.0.1", free_port()))  # free now


def test_stop_is_bounded_and_idempotent():
    proc = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"])
    try:
        stop(proc, timeout=0.5)  # SIGTERM ignored: SIGKILL after the timeout
        assert proc.returncode is not None
        stop(proc)
        stop(None)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_wait_port_says_who_exited_first():
    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    proc.wait()
    with pytest.raises(NetworkError, match="exited with 3") as info:
        wait_port("127.0.0.1", free_port(), 5, proc, "child")
    assert isinstance(info.value, CryptorosError)


def test_the_network_module_uses_the_same_helpers():
    assert network.free_port is free_port and network.stop is stop and network.NetworkError is NetworkError


def test_capture_holds_the_last_packets_sent_before_stop(tmp_path):
    """A short exchange, then a stop once its last bytes reached the file: every payload
    byte is in it (the capture reads packets as they come, not in one-second blocks that
    SIGINT can cut, and the stop waits for tcpdump to catch up rather than cut its ring)."""
    from cryptoros.lab.capture import Capture, flows
    from tests.support import require

    require("tcpdump")
    if os.geteuid() != 0:
        pytest.skip("tcpdump on lo needs root")
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    probe = socket.create_server(("127.0.0.1", 0))
    probe_port = probe.getsockname()[1]
    capture = Capture(tmp_path / "c.pcap", f"tcp and (port {port} or port {probe_port})")
    try:
        # packets reach the file a moment after tcpdump says "listening on": a probe
        # connection first, until its bytes are seen there (readiness seen, not assumed)
        deadline = time.monotonic() + 15
        with socket.create_connection(("127.0.0.1", probe_port), timeout=5) as prober:
            probed = probe.accept()[0]
            while b"probe;" not in (capture.path.read_bytes() if capture.path.exists() else b""):
                assert time.monotonic() < deadline, "tcpdump wrote no probe packet within 15 s"
                prober.sendall(b"probe;")
                probed.recv(4096)
                time.sleep(0.05)
            probed.close()
        probe.close()
        with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
            peer = server.accept()[0]
            for i in range(5):
                client.sendall(f"payload-{i};".encode())
            peer.recv(4096)
            peer.close()
    finally:
        server.close()
        data = capture.stop(until=b"payload-4;")
    assert all(f"payload-{i};".encode() in data for i in range(5)), capture.dropped
    flow = flows(capture.path)[-1]  # in order of their first packet: the probe's, then ours
    assert flow["payload_bytes"] == len(b"payload-0;") * 5 and flow["frames"] >= 4
