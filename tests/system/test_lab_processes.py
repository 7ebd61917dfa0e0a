"""cryptoros.lab.processes: the one free-port picker and process stopper."""

from __future__ import annotations

import socket
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
