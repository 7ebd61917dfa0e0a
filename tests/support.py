"""Helpers shared by the test suite: system parts, free ports, processes.

A test that needs a real system part (openssl, PostgreSQL, ROS 1, stunnel...) calls
:func:`require`. Where the part is missing the test is skipped with the reason; with
``CI=true`` in the environment it fails instead, so CI can never go green by
skipping what it was meant to check.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

# one port picker and one process stopper for tests, demo and bench alike
from cryptoros.lab.capture import Capture  # noqa: F401
from cryptoros.lab.processes import free_port, stop  # noqa: F401

REPO = Path(__file__).resolve().parent.parent
VENV_BIN = Path(sys.executable).parent
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def missing(reason: str) -> None:
    """Skip (locally) or fail (under CI=true) because a system part is missing."""
    if IN_CI:
        pytest.fail(f"CI=true and a required system part is missing: {reason}")
    pytest.skip(reason)


def require(*binaries: str) -> dict[str, str]:
    """Return absolute paths of the named executables, or skip/fail if one is missing."""
    found = {}
    for name in binaries:
        path = shutil.which(name)
        if path is None:
            missing(f"'{name}' is not installed (scripts/install-system-parts installs it as root)")
        found[name] = path
    return found


def script(name: str) -> str:
    """Path of one of this package's console scripts in the running venv."""
    path = VENV_BIN / name
    if not path.exists():
        pytest.fail(f"console script {name} is not installed in {VENV_BIN}: run 'pip install -e .'")
    return str(path)


def wait_for_port(host: str, port: int, timeout: float = 10.0, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read() if proc.stdout else ""
            raise AssertionError(f"process exited with {proc.returncode} before listening: {out}")
        with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
            return
        time.sleep(0.05)
    raise AssertionError(f"nothing listened on {host}:{port} within {timeout}s")


def on_host(args: Sequence[str], env: dict[str, str] | None) -> list[str]:
    """``args`` run on the host ``env`` belongs to: in its network namespace when the
    network is built with namespaces (``CRYPTOROS_NETNS``, set by ``Network.ros_env``)."""
    ns = (env or {}).get("CRYPTOROS_NETNS")
    return ["ip", "netns", "exec", ns, *args] if ns else list(args)


def run(args: Sequence[str], *, timeout: float = 60, check: bool = False, **kw) -> subprocess.CompletedProcess:
    """Run a command with a bounded wait, capturing text output (on the host of ``env``)."""
    result = subprocess.run(on_host(args, kw.get("env")), capture_output=True, text=True, timeout=timeout, **kw)
    if check and result.returncode != 0:
        raise AssertionError(f"{args} exited {result.returncode}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}")
    return result


@contextlib.contextmanager
def running(args: Sequence[str], **kw) -> Iterator[subprocess.Popen]:
    """A process with its output piped, stopped in a finally (on the host of ``env``)."""
    proc = subprocess.Popen(on_host(args, kw.get("env")), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            **kw)
    try:
        yield proc
    finally:
        stop(proc)


def client_hello(version: int, suites: list[int]) -> bytes:
    """A minimal, well-formed TLS ClientHello offering exactly ``suites``.

    Debian's OpenSSL can no longer offer 3DES or RC4 at all, so the test speaks the
    offer itself, byte for byte, the way an old or hostile client would.
    """
    import os
    import struct

    def ext(kind: int, body: bytes) -> bytes:
        return struct.pack("!HH", kind, len(body)) + body

    groups = struct.pack("!H", 4) + struct.pack("!HH", 0x0017, 0x001D)  # secp256r1, x25519
    sigalgs = struct.pack("!H", 6) + struct.pack("!HHH", 0x0403, 0x0804, 0x0401)
    extensions = ext(0x000A, groups) + ext(0x000B, b"\x01\x00") + ext(0x000D, sigalgs)
    cipher_bytes = b"".join(struct.pack("!H", c) for c in suites)
    body = (
        struct.pack("!H", version) + os.urandom(32) + b"\x00"
        + struct.pack("!H", len(cipher_bytes)) + cipher_bytes + b"\x01\x00"
        + struct.pack("!H", len(extensions)) + extensions
    )
    handshake = b"\x01" + len(body).to_bytes(3, "big") + body
    return b"\x16\x03\x01" + struct.pack("!H", len(handshake)) + handshake


def processes_using(path: Path) -> list[str]:
    """Processes whose command line names ``path`` (what a run left behind)."""
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(path) in cmd:
            found.append(f"{pid}: {cmd[:200]}")
    return found


def until(condition, timeout: float, what: str, every: float = 0.1):
    """Poll ``condition`` until it returns something true (returned), at most ``timeout``
    seconds; the assertion names ``what`` did not happen."""
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(every)
    return value


def ros_package(root: Path, name: str, scripts: dict[str, str]) -> Path:
    """A catkin package ``name`` under ``root`` (for ROS_PACKAGE_PATH) holding executable
    ``scripts`` (file name -> text), as roslaunch's ``<node pkg= type=>`` finds them."""
    pkg = root / name
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "package.xml").write_text(
        f'<?xml version="1.0"?><package format="2"><name>{name}</name><version>0.0.1</version>'
        '<description>t</description><maintainer email="t@t.t">t</maintainer><license>BSD</license></package>')
    for file_name, text in scripts.items():
        (pkg / file_name).write_text(text)
        (pkg / file_name).chmod(0o755)
    return pkg


class Clock:
    """A clock for code that takes one (``clock=``): it stands still until the test
    moves ``t``."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def expired_certificate(directory: Path, name: str = "expired", ip: str | None = None) -> tuple[Path, Path]:
    """A self-signed certificate (with an IP SAN ``ip``) that expired yesterday, and its
    key: what a deployment check must name before anything connects with it."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.UTC)
    builder = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
               .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=30))
               .not_valid_after(now - datetime.timedelta(days=1)))
    if ip is not None:
        builder = builder.add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address(ip))]),
                                        critical=False)
    cert_path, key_path = directory / f"{name}.crt", directory / f"{name}.key"
    cert_path.write_bytes(builder.sign(key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    key_path.chmod(0o600)
    return cert_path, key_path
