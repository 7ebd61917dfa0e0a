"""Packet captures on loopback for tests and benchmarks: tcpdump into a pcap file, and
the TCP flows read back out of it.

Why ``--immediate-mode``: without it, Linux's tcpdump reads the capture ring in blocks
that are handed over when full or after the buffer timeout (one second); packets still
in an unfinished block when SIGINT arrives never reach the file. A short exchange
followed by a stop (a test's control capture) could lose exactly the packets it was
meant to show.
"""

from __future__ import annotations

import re
import shutil
import signal
import socket
import struct
import subprocess
import time
from pathlib import Path

from cryptoros.errors import CryptorosError
from cryptoros.lab.processes import stop

MARKER = b"cryptoros-capture-marker"


class CaptureError(CryptorosError):
    """tcpdump is missing, did not start, or never saw a packet it should have."""


class Capture:
    """tcpdump on ``lo`` writing ``path``; started and stopped with bounded waits.

    ``prove_loopback=True`` sends marker packets over ``marker_host`` (a loopback
    address, 127.0.0.1 unless given) until one shows up in the file (the filter must
    admit them): "listening on" is printed before packets
    really flow into the file. ``dropped`` is what tcpdump reported as dropped by the
    kernel once stopped (None while running)."""

    def __init__(self, path: Path, bpf: str, *, snaplen: int = 0, prove_loopback: bool = False,
                 marker_host: str = "127.0.0.1", start_timeout: float = 10.0) -> None:
        binary = shutil.which("tcpdump")
        if binary is None:
            raise CaptureError("tcpdump is not installed")
        self.path = Path(path)
        self.err = self.path.with_suffix(".err")
        self.dropped: int | None = None
        self.proc = subprocess.Popen([binary, "-i", "lo", "-n", "-U", "--immediate-mode", "-B", "16384",
                                      "-s", str(snaplen), "-w", str(self.path), bpf],
                                     stdout=subprocess.DEVNULL, stderr=self.err.open("w"))
        deadline = time.monotonic() + start_timeout
        while "listening on" not in self.err.read_text():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                stop(self.proc)
                raise CaptureError(f"tcpdump did not start: {self.err.read_text()[-300:]}")
            time.sleep(0.02)
        if prove_loopback:
            self._wait_for_marker(deadline, marker_host)

    def _wait_for_marker(self, deadline: float, host: str) -> None:
        server = socket.create_server((host, 0))
        port = server.getsockname()[1]
        try:
            while time.monotonic() < deadline:
                with socket.create_connection((host, port), timeout=2) as client:
                    client.sendall(MARKER)
                server.accept()[0].close()
                time.sleep(0.05)
                if self.path.exists() and MARKER in self.path.read_bytes():
                    return
        finally:
            server.close()
        self.stop()
        raise CaptureError(f"tcpdump never wrote a marker packet sent over {host}")

    def stop(self, settle: float = 0.0, *, until: bytes | None = None, timeout: float = 10.0) -> bytes:
        """After ``settle`` seconds (for the last ACKs in flight), SIGINT: tcpdump flushes
        and reports its counts; bounded. The pcap's bytes. ``until``: the last bytes the
        caller sent, waited for in the file first (up to ``timeout``): SIGINT ends
        tcpdump without reading what is still in the kernel's ring, which on a busy
        machine held a whole short exchange."""
        time.sleep(settle)
        deadline = time.monotonic() + timeout
        while (until is not None and self.proc.poll() is None and time.monotonic() < deadline
               and until not in (self.path.read_bytes() if self.path.exists() else b"")):
            time.sleep(0.02)
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        stop(self.proc)
        found = re.search(r"(\d+) packets? dropped by kernel", self.err.read_text())
        self.dropped = int(found.group(1)) if found else None
        return self.path.read_bytes() if self.path.exists() else b""


def flows(path: Path) -> list[dict]:
    """TCP flows of a pcap (Ethernet, Linux SLL or raw IPv4), in order of their first
    packet: frame bytes (as Wireshark counts them), IP bytes and TCP payload bytes."""
    data = path.read_bytes() if path.exists() else b""
    if len(data) < 24:
        return []
    magic = data[:4]
    endian = "<" if magic in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1") else ">"
    linktype = struct.unpack(endian + "I", data[20:24])[0]
    offset_link = {1: 14, 113: 16, 276: 20, 101: 0, 228: 0}.get(linktype)
    if offset_link is None:
        raise CaptureError(f"pcap link type {linktype} not understood")
    table: dict[tuple, dict] = {}
    pos = 24
    while pos + 16 <= len(data):
        _sec, _frac, incl, orig = struct.unpack(endian + "IIII", data[pos:pos + 16])
        pkt = data[pos + 16: pos + 16 + incl]
        pos += 16 + incl
        ip = pkt[offset_link:]
        if len(ip) < 20 or ip[0] >> 4 != 4 or ip[9] != 6:
            continue
        ihl = (ip[0] & 15) * 4
        total = struct.unpack("!H", ip[2:4])[0]
        tcp = ip[ihl:]
        if len(tcp) < 20:
            continue
        sport, dport = struct.unpack("!HH", tcp[:4])
        thl = (tcp[12] >> 4) * 4
        src, dst = ip[12:16], ip[16:20]
        key = tuple(sorted([(src, sport), (dst, dport)]))
        flow = table.setdefault(key, {"frames": 0, "frame_bytes": 0, "ip_bytes": 0, "payload_bytes": 0,
                                      "order": len(table)})
        flow["frames"] += 1
        flow["frame_bytes"] += orig
        flow["ip_bytes"] += total
        flow["payload_bytes"] += max(0, total - ihl - thl)
    return sorted(table.values(), key=lambda f: f["order"])
