"""``cryptoros bench ciphers``: seed 002's cipher-cost study, our figures beside the paper's.

Seed 002 (Rodriguez-Lera et al., "Message Encryption in Robot Operating System")
encrypted ROS 1 LaserScan (4,152 B, 10 Hz) and Image (79,737 B on average, 30 fps)
messages with 3DES, AES and Blowfish in CBC mode (PyCrypto, one 24-byte key, IV 8 B or
16 B) on an Intel i7-3612QM and an Atom D525, and measured bytes on the network, CPU,
power, battery time and messages processed. This benchmark measures the same costs for
real ROS 1 wire bytes (serialized with :mod:`cryptoros.ros1.msgs`, rosbags):

* messages (:data:`MESSAGES`): std_msgs/String, geometry_msgs/PoseStamped,
  sensor_msgs/LaserScan (683 ranges, the paper's Hokuyo), the paper's image as a
  sensor_msgs/CompressedImage of 640x480 whose wire size is the paper's mean 79,737 B
  (random bytes stand in for the JPEG: a cipher's cost depends on the length only), a
  raw 640x480 rgb8 sensor_msgs/Image (921,600 B of pixels), and a sensor_msgs/PointCloud2
  of 65,536 points x 16 B (about 1 MB), each at a stated real rate;
* ciphers (:data:`PRIMITIVES`, all from ``cryptography``): 3DES-CBC and Blowfish-CBC
  (``hazmat.decrepit``), the paper's AES (24-byte key: AES-192-CBC, no MAC), AES-128/256-CBC
  with HMAC-SHA256 (encrypt-then-MAC), AES-128-GCM, ChaCha20-Poly1305; and the TLS suites
  the interceptor allows (:mod:`cryptoros.tls`), one TLS record stream per message
  through a client/server pair of ``ssl`` objects built by the interceptor's own context
  factory (TLS 1.3 suites narrowed per run with an ``OPENSSL_CONF`` in the child, TLS 1.2
  by narrowing the interceptor's cipher list on the pinned-1.2 context);
* per message and cipher: encrypt and decrypt microseconds (the median over a timed
  window, fresh IV/nonce every message), bytes added (measured, and checked against IV +
  padding + MAC/tag for the primitives), the CPU share of one core at the message's
  real rate, messages per second one core sustains, whether that keeps up;
  ``decrypt(encrypt(m)) == m`` is checked for every timed message (a mismatch aborts);
* the same on the Atom stand-in (the mean there: the quota's stalls count): each
  measuring child runs under its own CPU quota (cgroup v2 ``cpu.max``, else cgroup v1
  ``cpu.cfs_quota_us``, else a SIGSTOP/SIGCONT duty cycle; which one is printed) of
  :data:`ATOM_QUOTA` of one core, with AES-NI, PCLMULQDQ and AVX masked off in OpenSSL
  (``OPENSSL_ia32cap``): the D525 has none of them. A child the quota never stopped
  (the cgroup's ``nr_throttled``, or the duty cycle's stops) is measured again, and a
  second such run aborts; so is each row whose window ran the child for more than
  :data:`MAX_SHARE_OVER_QUOTA` times its quota (CPU time over wall time: a window that
  fell between two stalls), with a window twice as long, up to
  :data:`ROW_ATTEMPTS` times. Unthrottled figures are never reported as the stand-in's;
* an energy estimate (:func:`energy_model`: busy core-seconds x watts per busy core from
  the CPU's TDP; battery time from the paper's battery, its plain battery time and an
  assumed 11.1 V pack) and the paper's Table 2 rebuilt from our figures;
* ``--relay``: the interceptor pair itself (:mod:`cryptoros.bench.interceptor`'s
  machinery): LaserScan- and image-sized frames relayed through two interceptors for
  each allowed TLS 1.3 suite and TLS 1.2: messages per second, MB/s and the two
  interceptors' CPU per message (unthrottled: ``[limits] max_messages_per_second = 0``).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import click

from cryptoros.consoles import for_logs
from cryptoros.errors import CryptorosError
from cryptoros.outputs import write_output

# ============================================================ what is measured


@dataclass(frozen=True, kw_only=True)
class MessageSpec:
    key: str
    label: str
    typename: str
    rate_hz: float
    category: str  # the paper's Table 2 columns, simple / complex (its own messages), or extended (ours)
    note: str


MESSAGES: tuple[MessageSpec, ...] = (
    MessageSpec(key="string", label="String", typename="std_msgs/String", rate_hz=10, category="simple",
                note="std_msgs/String of 32 characters, 10 Hz"),
    MessageSpec(key="pose", label="Pose", typename="geometry_msgs/PoseStamped", rate_hz=50, category="simple",
                note="geometry_msgs/PoseStamped, 50 Hz (odometry-like)"),
    MessageSpec(key="laser", label="LaserScan", typename="sensor_msgs/LaserScan", rate_hz=10, category="simple",
                note="sensor_msgs/LaserScan, 683 ranges, no intensities (Hokuyo URG-04LX), 10 Hz as in the paper"),
    MessageSpec(key="image", label="Image", typename="sensor_msgs/CompressedImage", rate_hz=30, category="complex",
                note="sensor_msgs/CompressedImage 640x480, wire size = the paper's mean 79,737 B, 30 fps"),
    MessageSpec(key="image_raw", label="Image raw", typename="sensor_msgs/Image", rate_hz=30, category="extended",
                note="sensor_msgs/Image 640x480 rgb8 (921,600 B of pixels), 30 fps"),
    MessageSpec(key="cloud", label="PointCloud2", typename="sensor_msgs/PointCloud2", rate_hz=10, category="extended",
                note="sensor_msgs/PointCloud2, 65,536 points x 16 B (x, y, z, intensity), 10 Hz"),
)

#: (key, label, kind, block or nonce bytes, key bytes, mac/tag bytes)
PRIMITIVES: tuple[tuple[str, str, str, int, int, int], ...] = (
    ("3des-cbc", "3DES-CBC", "cbc", 8, 24, 0),
    ("blowfish-cbc", "Blowfish-CBC", "cbc", 8, 24, 0),
    ("aes192-cbc", "AES-192-CBC (paper's AES)", "cbc", 16, 24, 0),
    ("aes128-cbc-hmac", "AES-128-CBC+HMAC-SHA256", "cbc", 16, 16, 32),
    ("aes256-cbc-hmac", "AES-256-CBC+HMAC-SHA256", "cbc", 16, 32, 32),
    ("aes128-gcm", "AES-128-GCM", "aead", 12, 16, 16),
    ("chacha20-poly1305", "ChaCha20-Poly1305", "aead", 12, 32, 16),
)
TLS13_SUITES = ("TLS_AES_128_GCM_SHA256", "TLS_AES_256_GCM_SHA384", "TLS_CHACHA20_POLY1305_SHA256")
#: the paper's three ciphers -> our rows that implement them as the paper did
PAPER_CIPHERS = {"3DES": "3des-cbc", "AES": "aes192-cbc", "Blowfish": "blowfish-cbc"}

#: The Atom stand-in: one core's share. Assumption: an Atom D525 core (1.8 GHz, in-order
#: Bonnell, 2010) runs single-threaded code about 8 times slower than one vCPU of this
#: machine, an AMD EPYC (our reading of published single-thread ratings: roughly 300 to
#: 400 for the D525, 2,000 to 3,000 for a recent EPYC core), so 1/8 of a core.
ATOM_QUOTA = 0.125
#: cgroup / duty-cycle period (a short one, so a measuring window spans many periods)
THROTTLE_PERIOD_US = 10_000
# A throttled row's window may take at most this multiple of the quota's CPU share: a
# window of a few periods can start and end inside the child's run slices (measured: a
# 60-byte Pose row, 50 ms, ran unthrottled at 3.8 us while its child was throttled).
MAX_SHARE_OVER_QUOTA = 2.0
ROW_ATTEMPTS = 4
#: CPUID bits OpenSSL must not use on the stand-in (the D525 has SSSE3 at most):
#: AES-NI (bit 57), PCLMULQDQ (33) and AVX (60) of the first word; AVX2 (5) and
#: AVX-512F (16) of the second.
ATOM_IA32CAP = "~0x1200000200000000:~0x10020"

#: Energy model inputs (stated, not measured): watts per busy core = TDP / cores.
MACHINES = {
    "powerful": {"label": "Powerful CU (i7-3612QM stand-in: one core here, unthrottled)", "cpu": "i7-3612QM",
                 "tdp_w": 35.0, "cores": 4, "battery_mah": 4400, "plain_battery_h": 3.0, "paper_cu": "CU A"},
    "atom": {"label": "Medium CU (Atom D525 stand-in: 1/8 core, no AES-NI/AVX)", "cpu": "Atom D525",
             "tdp_w": 13.0, "cores": 2, "battery_mah": 5200, "plain_battery_h": 3 + 13 / 60, "paper_cu": "CU B"},
}
PACK_VOLTS = 11.1  # assumed 3S Li-ion pack: the paper gives only mAh

#: The paper's figures, quoted (seed 002), never computed here.
PAPER = {
    "laser_bytes": 4152,
    "image_bytes_mean": 79737,
    "atom_images_per_s_of_30": {"3DES": 5, "AES": 15, "Blowfish": 11},
    "atom_laser_kept_up": {"3DES": True, "AES": True, "Blowfish": True},
    "battery": {"CU A": {"plain": "3:00", "3DES": "2:20", "AES": "2:33", "Blowfish": "2:40"},
                "CU B": {"plain": "3:13", "3DES": "2:15", "AES": "2:28", "Blowfish": "2:34"}},
    "network": "AES delivered the most data: 1.5 MB plain, almost 5 MB with the images encrypted",
    # Table 2: machine -> category -> cipher -> symbol (custom messages as the paper has them)
    "table2": {
        "powerful": {"simple": {"3DES": "✓", "AES": "✓", "Blowfish": "✓"},
                     "complex": {"3DES": "✓", "AES": "✓", "Blowfish": "✓"},
                     "custom": {"3DES": "✓", "AES": "✓", "Blowfish": "✓"}},
        "atom": {"simple": {"3DES": "✓", "AES": "✓", "Blowfish": "✓"},
                 "complex": {"3DES": "⇌", "AES": "✓", "Blowfish": "✓"},
                 "custom": {"3DES": "∅", "AES": "✓", "Blowfish": "∅"}},
    },
}
#: Our Table 2 rule: the CPU share of one core that encrypting + decrypting the stream at
#: its real rate takes. <= 25 %: ✓; <= 100 %: ∅ (it fits, but takes a big share: study
#: the case); > 100 %: ⇌ (one core cannot keep up).
SUITABLE_SHARE = 0.25


# ============================================================ messages


def build_messages() -> dict[str, bytes]:
    """ROS 1 wire bytes of every :data:`MESSAGES` entry (checked by deserializing)."""
    import numpy as np

    from cryptoros.ros1 import msgs

    rng = np.random.default_rng(2)
    store = msgs.typestore()
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = msgs.msg_class("std_msgs/Header")

    def header(frame: str) -> object:
        return Header(seq=1, stamp=Time(sec=1_700_000_000, nanosec=0), frame_id=frame)

    out: dict[str, bytes] = {}
    out["string"] = msgs.serialize(msgs.msg_class("std_msgs/String")(data="x" * 32), "std_msgs/String")
    P = {t: msgs.msg_class(f"geometry_msgs/{t}") for t in ("PoseStamped", "Pose", "Point", "Quaternion")}
    pose = P["PoseStamped"](header=header("map"), pose=P["Pose"](
        position=P["Point"](x=1.5, y=-2.25, z=0.0), orientation=P["Quaternion"](x=0.0, y=0.0, z=0.38, w=0.92)))
    out["pose"] = msgs.serialize(pose, "geometry_msgs/PoseStamped")
    scan = msgs.msg_class("sensor_msgs/LaserScan")(
        header=header("laser"), angle_min=-2.0944, angle_max=2.0944, angle_increment=4.1888 / 682,
        time_increment=0.0001, scan_time=0.1, range_min=0.02, range_max=5.6,
        ranges=rng.uniform(0.02, 5.6, 683).astype(np.float32), intensities=np.zeros(0, dtype=np.float32))
    out["laser"] = msgs.serialize(scan, "sensor_msgs/LaserScan")
    Compressed = msgs.msg_class("sensor_msgs/CompressedImage")

    def compressed(n: int) -> bytes:
        return msgs.serialize(Compressed(header=header("camera"), format="rgb8; jpeg compressed bgr8",
                                         data=rng.integers(0, 256, n, dtype=np.uint8)), "sensor_msgs/CompressedImage")

    empty = len(compressed(0))
    out["image"] = compressed(PAPER["image_bytes_mean"] - empty)
    out["image_raw"] = msgs.serialize(msgs.msg_class("sensor_msgs/Image")(
        header=header("camera"), height=480, width=640, encoding="rgb8", is_bigendian=0, step=640 * 3,
        data=rng.integers(0, 256, 640 * 480 * 3, dtype=np.uint8)), "sensor_msgs/Image")
    Field = msgs.msg_class("sensor_msgs/PointField")
    fields = [Field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(("x", "y", "z", "intensity"))]
    points = 65_536
    out["cloud"] = msgs.serialize(msgs.msg_class("sensor_msgs/PointCloud2")(
        header=header("lidar"), height=64, width=points // 64, fields=fields, is_bigendian=False, point_step=16,
        row_step=16 * points // 64, data=rng.integers(0, 256, 16 * points, dtype=np.uint8), is_dense=True),
        "sensor_msgs/PointCloud2")
    for spec in MESSAGES:
        msgs.deserialize(out[spec.key], spec.typename)  # every byte consumed, or it raises
    return out


# ============================================================ ciphers (in the worker)


def primitive(key: str):
    """(encrypt, decrypt) for one of :data:`PRIMITIVES`: ``encrypt(m) -> bytes`` with a
    fresh IV/nonce in front (and the MAC behind); ``decrypt`` checks the MAC/tag."""
    from cryptography.hazmat.primitives import hashes, hmac, padding
    from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
    from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305

    try:
        from cryptography.hazmat.decrepit.ciphers.algorithms import Blowfish, TripleDES
    except ImportError:  # cryptography < 43
        Blowfish, TripleDES = algorithms.Blowfish, algorithms.TripleDES  # type: ignore[attr-defined]

    _, _, kind, size, key_len, mac_len = next(p for p in PRIMITIVES if p[0] == key)
    secret = bytes(range(1, 1 + key_len))  # one fixed key per cipher, as the paper's one 24-byte key
    urandom = os.urandom
    if kind == "aead":
        aead = AESGCM(secret) if key.startswith("aes") else ChaCha20Poly1305(secret)

        def enc_aead(m: bytes) -> bytes:
            nonce = urandom(size)
            return nonce + aead.encrypt(nonce, m, None)

        def dec_aead(c: bytes) -> bytes:
            return aead.decrypt(c[:size], c[size:], None)

        return enc_aead, dec_aead
    algo = {"3des-cbc": TripleDES, "blowfish-cbc": Blowfish}.get(key, algorithms.AES)
    mac_key = bytes(range(100, 132))

    def enc_cbc(m: bytes) -> bytes:
        iv = urandom(size)
        padder = padding.PKCS7(size * 8).padder()
        e = Cipher(algo(secret), modes.CBC(iv)).encryptor()
        c = iv + e.update(padder.update(m) + padder.finalize()) + e.finalize()
        if mac_len:
            h = hmac.HMAC(mac_key, hashes.SHA256())
            h.update(c)
            c += h.finalize()
        return c

    def dec_cbc(c: bytes) -> bytes:
        if mac_len:
            h = hmac.HMAC(mac_key, hashes.SHA256())
            h.update(c[:-mac_len])
            h.verify(c[-mac_len:])
            c = c[:-mac_len]
        d = Cipher(algo(secret), modes.CBC(c[:size])).decryptor()
        unpadder = padding.PKCS7(size * 8).unpadder()
        return unpadder.update(d.update(c[size:]) + d.finalize()) + unpadder.finalize()

    return enc_cbc, dec_cbc


def expected_added(key: str, n: int) -> int:
    """IV/nonce + PKCS7 padding (1 to a block) + MAC/tag, for a message of ``n`` bytes."""
    _, _, kind, size, _, mac_len = next(p for p in PRIMITIVES if p[0] == key)
    if kind == "aead":
        return size + mac_len
    return size + (size - n % size) + mac_len


def tls_pair(pki: dict, tls12_suite: str | None):
    """(encrypt, decrypt, negotiated) over a client/server pair of in-memory TLS objects
    made by :mod:`cryptoros.tls` (the interceptor's contexts, mutual certificates).
    ``tls12_suite``: pin TLS 1.2 and narrow the allowed list to that suite; None: TLS 1.3
    with what OpenSSL's configuration leaves (``OPENSSL_CONF`` narrows it)."""
    import ssl

    from cryptoros import tls

    def cfg(name: str) -> tls.TLSConfig:
        return tls.TLSConfig(ca_file=Path(pki["ca"]), cert_file=Path(pki[name][0]), key_file=Path(pki[name][1]),
                             pin_tls12=tls12_suite is not None)

    sctx, cctx = tls.server_context(cfg("server")), tls.client_context(cfg("client"), check_hostname=False)
    if tls12_suite is not None:
        for ctx in (sctx, cctx):
            ctx.set_ciphers(tls12_suite)
    c_in, c_out, s_in, s_out = (ssl.MemoryBIO() for _ in range(4))
    client = cctx.wrap_bio(c_in, c_out, server_side=False)
    server = sctx.wrap_bio(s_in, s_out, server_side=True)
    done = {"c": False, "s": False}
    for _ in range(50):
        for name, obj in (("c", client), ("s", server)):
            if not done[name]:
                try:
                    obj.do_handshake()
                    done[name] = True
                except ssl.SSLWantReadError:
                    pass
        if c_out.pending:
            s_in.write(c_out.read())
        if s_out.pending:
            c_in.write(s_out.read())
        if all(done.values()) and not c_out.pending and not s_out.pending:
            break
    if not all(done.values()):
        raise RuntimeError("TLS handshake did not complete")
    name, version, _bits = server.cipher()

    def enc_tls(m: bytes) -> bytes:
        client.write(m)
        return c_out.read()

    def dec_tls(c: bytes) -> bytes:
        s_in.write(c)
        parts = []
        while s_in.pending:
            parts.append(server.read(16384))  # one record at most: no 1 MB buffer per read
        return b"".join(parts)

    return enc_tls, dec_tls, f"{version} {name}"


def measure(enc, dec, m: bytes, min_time: float, min_ops: int, max_ops: int, estimator: str = "median") -> dict:
    """Encrypt and decrypt microseconds per message over a timed window (``estimator``:
    the median, robust to a shared machine's preemptions, or the mean, which counts the
    throttle's stalls); every round trip checked."""
    clock = time.perf_counter_ns
    warm_until, warm = clock() + 5_000_000, 0
    while warm < 3 or (warm < 50 and clock() < warm_until):  # one-time costs out of the window
        c = enc(m)
        if dec(c) != m:
            raise RuntimeError("decrypt(encrypt(m)) != m")
        warm += 1
    added = len(c) - len(m)
    enc_ns: list[int] = []
    dec_ns: list[int] = []
    start, cpu0 = clock(), time.process_time_ns()
    while len(enc_ns) < max_ops and (len(enc_ns) < min_ops or clock() - start < min_time * 1e9):
        t0 = clock()
        c = enc(m)
        t1 = clock()
        p = dec(c)
        t2 = clock()
        if p != m:
            raise RuntimeError("decrypt(encrypt(m)) != m")
        enc_ns.append(t1 - t0)
        dec_ns.append(t2 - t1)
    ops = len(enc_ns)
    cpu_share = (time.process_time_ns() - cpu0) / max(1, clock() - start)
    out = {"cpu_share": cpu_share, "enc_us_mean": sum(enc_ns) / ops / 1e3, "dec_us_mean": sum(dec_ns) / ops / 1e3,
           "enc_us_median": statistics.median(enc_ns) / 1e3, "dec_us_median": statistics.median(dec_ns) / 1e3,
           "ops": ops, "added": added, "roundtrip_checked": ops + warm}
    out["enc_us"], out["dec_us"] = out[f"enc_us_{estimator}"], out[f"dec_us_{estimator}"]
    return out


def measure_within(spec: dict, enc, dec, m: bytes) -> dict:
    """:func:`measure` for the spec's profile. Under a quota (``spec["quota"]``) a window
    whose CPU share exceeds :data:`MAX_SHARE_OVER_QUOTA` times the quota was not
    throttled: it is measured again with a window twice as long; after
    :data:`ROW_ATTEMPTS` such windows the row fails the run."""
    min_time, quota = spec["min_time"], spec.get("quota")
    for _ in range(ROW_ATTEMPTS if quota else 1):
        row = measure(enc, dec, m, min_time, spec["min_ops"], spec["max_ops"], spec["estimator"])
        if not quota or row["cpu_share"] <= MAX_SHARE_OVER_QUOTA * quota:
            return row
        min_time *= 2
    raise RuntimeError(f"{ROW_ATTEMPTS} windows up to {min_time / 2:g} s ran at {row['cpu_share']:.0%} of a core, "
                       f"over {MAX_SHARE_OVER_QUOTA:g}x the quota's {quota:.1%}: not the stand-in's figures")


def _worker() -> None:
    """The measuring child: imports, says ``READY`` (the parent then puts it under its
    throttle), reads a JSON spec on stdin, writes one JSON result per line on stdout."""
    import importlib

    for module in ("cryptography.hazmat.primitives.ciphers.aead", "cryptoros.tls"):  # before the throttle
        importlib.import_module(module)

    sys.stdout.write("READY\n")
    sys.stdout.flush()
    spec = json.loads(sys.stdin.read())
    blobs = {k: Path(p).read_bytes() for k, p in spec["messages"].items()}
    jobs: list[tuple[str, object]] = []
    for key in spec.get("primitives", []):
        jobs.append((key, lambda key=key: (*primitive(key), None)))
    for suite in spec.get("tls12", []):
        jobs.append((f"tls12:{suite}", lambda suite=suite: tls_pair(spec["pki"], suite)))
    if spec.get("tls13"):
        jobs.append((f"tls13:{spec['tls13']}", lambda: tls_pair(spec["pki"], None)))
    for cipher, make in jobs:
        enc, dec, negotiated = make()  # one key (TLS: one session) for every message, as on a stream
        for msg_key, m in blobs.items():
            try:
                row = measure_within(spec, enc, dec, m)
            except Exception as exc:  # reported to the parent, which fails the run
                row = {"error": f"{type(exc).__name__}: {exc}"}
            row.update(cipher=cipher, message=msg_key, bytes=len(m), negotiated=negotiated)
            sys.stdout.write(json.dumps(row) + "\n")
            sys.stdout.flush()
        sys.stderr.write(f"  [{spec['profile']}] {cipher_label(cipher)} done\n")
        sys.stderr.flush()


# ============================================================ the Atom stand-in's throttle


def _mounts() -> list[tuple[str, str, str]]:
    out = []
    with contextlib.suppress(OSError):
        for line in Path("/proc/mounts").read_text().splitlines():
            parts = line.split()
            if len(parts) >= 4:
                out.append((parts[1], parts[2], parts[3]))
    return out


class Throttle:
    """Limits each attached child process to ``quota`` of one core (a cgroup of its own
    per child): cgroup v2, cgroup v1 or a SIGSTOP/SIGCONT duty cycle, in that order."""

    def __init__(self, quota: float, period_us: int = THROTTLE_PERIOD_US) -> None:
        self.quota, self.period_us = quota, period_us
        self.prefix = f"cryptoros-bench-ciphers-{os.getpid()}"
        self.method, self.root = self._pick()
        self._paths: list[Path] = []
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._stops: dict[int, int] = {}  # the duty cycle's stops per child

    def _pick(self) -> tuple[str, Path | None]:
        if os.environ.get("CRYPTOROS_BENCH_THROTTLE") == "dutycycle":
            return "dutycycle", None
        for mount, fstype, _opts in _mounts():
            if fstype == "cgroup2":
                root = Path(mount)
                with contextlib.suppress(OSError):
                    if "cpu" not in (root / "cgroup.controllers").read_text().split():
                        continue
                    if "cpu" not in (root / "cgroup.subtree_control").read_text().split():
                        (root / "cgroup.subtree_control").write_text("+cpu")
                    self._limit("cgroup v2 cpu.max", root / f"{self.prefix}-probe").rmdir()
                    return "cgroup v2 cpu.max", root
        for mount, fstype, opts in _mounts():
            if fstype == "cgroup" and "cpu" in opts.split(","):
                root = Path(mount)
                with contextlib.suppress(OSError):
                    self._limit("cgroup v1 cpu.cfs_quota_us", root / f"{self.prefix}-probe").rmdir()
                    return "cgroup v1 cpu.cfs_quota_us", root
        return "dutycycle", None

    def _limit(self, method: str, path: Path) -> Path:
        path.mkdir(exist_ok=True)
        quota = int(self.quota * self.period_us)
        if method.startswith("cgroup v2"):
            (path / "cpu.max").write_text(f"{quota} {self.period_us}")
        else:
            (path / "cpu.cfs_period_us").write_text(str(self.period_us))
            (path / "cpu.cfs_quota_us").write_text(str(quota))
        return path

    def describe(self) -> str:
        q = int(self.quota * self.period_us)
        if self.method == "dutycycle":
            return f"SIGSTOP/SIGCONT duty cycle: each child runs {q} us of every {self.period_us} us"
        return f"{self.method}: {q} us of every {self.period_us} us, one cgroup per child under {self.root}"

    def attach(self, pid: int) -> None:
        if self.root is not None:
            path = self._limit(self.method, self.root / f"{self.prefix}-{pid}")
            self._paths.append(path)
            (path / "cgroup.procs").write_text(str(pid))
            return
        run_s, off_s = self.quota * self.period_us / 1e6, (1 - self.quota) * self.period_us / 1e6

        def cycle() -> None:
            while not self._stop.is_set():
                try:
                    time.sleep(run_s)
                    os.kill(pid, signal.SIGSTOP)
                    self._stops[pid] = self._stops.get(pid, 0) + 1
                    time.sleep(off_s)
                    os.kill(pid, signal.SIGCONT)
                except ProcessLookupError:
                    return
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)

        t = threading.Thread(target=cycle, daemon=True)
        t.start()
        self._threads.append(t)

    def stalls(self, pid: int) -> int:
        """How many times the quota stopped child ``pid`` (the cgroup's ``nr_throttled``,
        or the duty cycle's stops): 0 means its figures are this machine's, unthrottled.
        Read after the child exited (its cgroup stays until :meth:`close`)."""
        if self.root is None:
            return self._stops.get(pid, 0)
        with contextlib.suppress(OSError, ValueError):
            for line in (self.root / f"{self.prefix}-{pid}" / "cpu.stat").read_text().splitlines():
                key, _, value = line.partition(" ")
                if key == "nr_throttled":
                    return int(value)
        return 0

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)
        for path in self._paths:
            with contextlib.suppress(OSError):
                path.rmdir()


# ============================================================ running the workers


def _openssl_conf(workdir: Path, suite: str) -> Path:
    path = workdir / f"openssl-{suite}.cnf"
    path.write_text("openssl_conf = openssl_init\n[openssl_init]\nssl_conf = ssl_sect\n[ssl_sect]\n"
                    "system_default = system_default_sect\n[system_default_sect]\n"
                    f"Ciphersuites = {suite}\n")
    return path


def run_worker(spec: dict, env_extra: dict[str, str], throttle: Throttle | None, timeout: float) -> list[dict]:
    env = {**os.environ, **env_extra}
    proc = subprocess.Popen([sys.executable, "-c", "from cryptoros.bench.ciphers import _worker; _worker()"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()
        if ready.strip() != "READY":
            proc.kill()
            proc.wait()
            raise click.ClickException(f"a measuring child ({spec['profile']}) did not start: {ready!r}")
        if throttle is not None:
            throttle.attach(proc.pid)
        out, _ = proc.communicate(json.dumps(spec), timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise click.ClickException(f"a measuring child ({spec['profile']}) did not finish within {timeout:.0f} s") from None
    if proc.returncode != 0:
        raise click.ClickException(f"a measuring child ({spec['profile']}) failed with exit code {proc.returncode}")
    rows = [json.loads(line) for line in out.splitlines() if line.strip()]
    bad = [r for r in rows if "error" in r]
    if bad:
        raise click.ClickException(f"{bad[0]['cipher']} on {bad[0]['message']}: {bad[0]['error']}")
    if throttle is not None and throttle.stalls(proc.pid) == 0:
        raise Unthrottled(f"the quota never stopped the measuring child of {', '.join(sorted({r['cipher'] for r in rows}))}")
    return rows


class Unthrottled(CryptorosError):
    """A throttled child that the quota never stopped: its figures would be this
    machine's, not the stand-in's. It is measured again; twice in a row aborts the run."""


def _make_pki(workdir: Path) -> dict:
    from certs.pki import PKI

    pki = PKI.init(workdir / "pki", unsafe_no_passphrase=True)
    out: dict = {"ca": str(pki.ca_cert_path)}
    for name in ("server", "client"):
        issued = pki.issue(name, kind="interceptor", sans=("IP:127.0.0.1",), unsafe_no_passphrase=True)
        out[name] = (str(issued.cert_path), str(issued.key_path))
    return out


def _tls12_suites() -> list[str]:
    """The TLS 1.2 suites the interceptor allows that an EC certificate can use."""
    import ssl

    from cryptoros.tls import STRICT_TLS12_CIPHERS

    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.set_ciphers(STRICT_TLS12_CIPHERS)
    return [c["name"] for c in ctx.get_ciphers() if c["protocol"] == "TLSv1.2" and c.get("auth") == "auth-ecdsa"]


def measure_all(profile: str, files: dict[str, str], pki: dict, windows: tuple[float, int, int],
                throttle: Throttle | None, workdir: Path, progress) -> list[dict]:
    """Every message x cipher in one profile (``normal`` or ``atom``). Unthrottled, the
    children run one after the other (one core each, nothing else of ours running);
    throttled, each child has its own quota, so they run side by side (8 x 1/8 of a core
    at most: within the machine's 2 cores)."""
    min_time, min_ops, max_ops = windows
    base = {"profile": profile, "messages": files, "pki": pki, "min_time": min_time, "min_ops": min_ops,
            "max_ops": max_ops, "estimator": "median" if throttle is None else "mean",
            "quota": None if throttle is None else throttle.quota}
    env = {"OPENSSL_ia32cap": ATOM_IA32CAP} if profile == "atom" else {}
    groups: list[tuple[dict, dict]] = [
        ({"primitives": ["3des-cbc"]}, env), ({"primitives": ["blowfish-cbc"]}, env),
        ({"primitives": ["aes192-cbc", "aes128-cbc-hmac", "aes256-cbc-hmac"]}, env),
        ({"primitives": ["aes128-gcm", "chacha20-poly1305"]}, env), ({"tls12": _tls12_suites()}, env),
        *(({"tls13": suite}, {**env, "OPENSSL_CONF": str(_openssl_conf(workdir, suite))}) for suite in TLS13_SUITES),
    ]
    results: list[list[dict] | BaseException] = [[] for _ in groups]

    def one(i: int) -> None:
        try:
            try:
                results[i] = run_worker({**base, **groups[i][0]}, groups[i][1], throttle, timeout=1800)
            except Unthrottled as exc:
                progress(f"{exc}: measured again")
                try:
                    results[i] = run_worker({**base, **groups[i][0]}, groups[i][1], throttle, timeout=1800)
                except Unthrottled as again:
                    raise click.ClickException(f"{again} twice: its figures would be this machine's, not the "
                                               "Atom stand-in's") from None
        except BaseException as exc:  # re-raised in the caller's thread
            results[i] = exc

    if throttle is None:
        for i in range(len(groups)):
            one(i)
    else:
        threads = [threading.Thread(target=one, args=(i,)) for i in range(len(groups))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    rows: list[dict] = []
    for got in results:
        if isinstance(got, BaseException):
            raise got
        rows += got
    for r in rows:
        suite = r["cipher"].partition(":")[2]
        if r["cipher"].startswith("tls") and not r["negotiated"].endswith(suite):
            raise click.ClickException(f"asked for {suite}, negotiated {r['negotiated']}")
    order = {name: i for i, name in enumerate([p[0] for p in PRIMITIVES])}
    rows.sort(key=lambda r: (order.get(r["cipher"], len(order)), r["cipher"]))
    return rows


# ============================================================ report


def cipher_label(key: str) -> str:
    for p in PRIMITIVES:
        if p[0] == key:
            return p[1]
    proto, _, suite = key.partition(":")
    if proto == "tls13":
        return "TLS1.3 " + suite.removeprefix("TLS_").rsplit("_", 1)[0]
    return "TLS1.2 " + suite.removeprefix("ECDHE-ECDSA-").removesuffix("-SHA384").removesuffix("-SHA256")


def symbol(share: float) -> str:
    return "✓" if share <= SUITABLE_SHARE else "∅" if share <= 1.0 else "⇌"


def energy_model(machine: str, busy_s_per_s: float) -> dict:
    """Battery time with an added CPU load of ``busy_s_per_s`` core-seconds per second
    (capped at the machine's cores: beyond that, messages are dropped, not burnt).

    P_added = min(load, cores) x TDP / cores; the battery holds mAh x 11.1 V; the base
    load is what drains it in the paper's plain battery time; T = E / (P_base + P_added).
    """
    m = MACHINES[machine]
    w_core = m["tdp_w"] / m["cores"]
    energy_wh = m["battery_mah"] / 1000 * PACK_VOLTS
    p_base = energy_wh / m["plain_battery_h"]
    p_added = min(busy_s_per_s, m["cores"]) * w_core
    return {"added_w": p_added, "base_w": p_base, "battery_h": energy_wh / (p_base + p_added), "w_per_core": w_core}


def hms(hours: float) -> str:
    minutes = round(hours * 60)
    return f"{minutes // 60}:{minutes % 60:02d}"


def build_report(raw: dict, messages: dict[str, bytes]) -> dict:
    """Rows per message x cipher (both profiles side by side), Table 2, the paper's
    headlines beside ours, energy. Checks bytes added against the formulas."""
    by = {(r["message"], r["cipher"], prof): r for prof, rows in raw.items() for r in rows}
    ciphers = list(dict.fromkeys(r["cipher"] for r in raw["normal"]))
    rows = []
    for spec in MESSAGES:
        n = len(messages[spec.key])
        for cipher in ciphers:
            row: dict = {"message": spec.key, "label": spec.label, "cipher": cipher, "cipher_label": cipher_label(cipher),
                         "bytes": n, "rate_hz": spec.rate_hz}
            for prof in raw:
                r = by[(spec.key, cipher, prof)]
                total = r["enc_us"] + r["dec_us"]
                share = total * spec.rate_hz / 1e6
                machine = "powerful" if prof == "normal" else "atom"
                w = MACHINES[machine]["tdp_w"] / MACHINES[machine]["cores"]
                row[prof] = {
                    "enc_us": r["enc_us"], "dec_us": r["dec_us"], "enc_dec_us": total, "ops": r["ops"],
                    "cpu_pct_at_rate": share * 100, "msgs_per_s_one_core": 1e6 / total,
                    "msgs_per_s_two_nodes": 1e6 / max(r["enc_us"], r["dec_us"]),
                    "keeps_up": 1e6 / total >= spec.rate_hz, "suitability": symbol(share),
                    "energy_mj_per_msg": total / 1e6 * w * 1e3, "roundtrip_checked": r["roundtrip_checked"],
                    "negotiated": r.get("negotiated"), "cpu_share": r["cpu_share"],
                }
            added = by[(spec.key, cipher, "normal")]["added"]
            row["bytes_added"] = added
            row["bytes_added_pct"] = added / n * 100
            if not cipher.startswith("tls"):
                row["bytes_added_expected"] = expected_added(cipher, n)
                if added != row["bytes_added_expected"]:
                    raise click.ClickException(f"{cipher} on {spec.key}: {added} B added, expected "
                                               f"{row['bytes_added_expected']} B")
            rows.append(row)
    report: dict = {"rows": rows, "ciphers": ciphers}
    # Table 2 rebuilt: machine -> category -> cipher -> worst symbol over the category's messages
    order = {"✓": 0, "∅": 1, "⇌": 2}
    table2: dict = {}
    for prof, machine in (("normal", "powerful"), ("atom", "atom")):
        if prof not in raw:
            continue
        for cat in ("simple", "complex", "extended"):
            for cipher in ciphers:
                syms = [r[prof]["suitability"] for r in rows if r["cipher"] == cipher
                        and next(s for s in MESSAGES if s.key == r["message"]).category == cat]
                table2.setdefault(machine, {}).setdefault(cat, {})[cipher] = max(syms, key=order.__getitem__)
    report["table2"] = table2
    report["table2_by_message"] = {
        machine: {spec.key: {r["cipher"]: r[prof]["suitability"] for r in rows if r["message"] == spec.key}
                  for spec in MESSAGES}
        for prof, machine in (("normal", "powerful"), ("atom", "atom")) if prof in raw
    }
    # the paper's workload (laser 10 Hz + image 30 fps, encrypt and decrypt on board): images
    # processed per second and battery time, per machine and cipher
    workload = {}
    for prof, machine in (("normal", "powerful"), ("atom", "atom")):
        if prof not in raw:
            continue
        for cipher in ciphers:
            get = {r["message"]: r[prof] for r in rows if r["cipher"] == cipher}
            load = sum(get[k]["enc_dec_us"] / 1e6 * rate for k, rate in (("laser", 10), ("image", 30)))
            e = energy_model(machine, load)
            workload.setdefault(machine, {})[cipher] = {
                "cpu_cores_busy": load,
                "images_per_s_two_nodes": min(30.0, get["image"]["msgs_per_s_two_nodes"]),
                "images_per_s_one_core": min(30.0, get["image"]["msgs_per_s_one_core"]),
                "laser_per_s_one_core": min(10.0, get["laser"]["msgs_per_s_one_core"]),
                **e,
            }
        plain = energy_model(machine, 0.0)
        workload[machine]["plain"] = {"battery_h": plain["battery_h"], "base_w": plain["base_w"]}
    report["paper_workload"] = workload
    report["paper"] = PAPER
    return report


def _num(v: float, digits: int = 3) -> str:
    if v >= 100:
        return f"{v:,.0f}"
    if v >= 10:
        return f"{v:.1f}"
    return f"{v:.{digits - 1}f}"


def _pct(v: float) -> str:
    return f"{v:,.0f} %" if v >= 10 else f"{v:.2g} %"


TABLE_HEADERS = ["message (B, Hz)", "cipher", "enc+dec us", "bytes added", "CPU % at rate", "msgs/s 1 core",
                 "keeps up", "Atom enc+dec us", "Atom msgs/s", "Atom keeps up", "mJ/msg (i7 / Atom)"]


def table_rows(report: dict) -> list[list[str]]:
    out = []
    for r in report["rows"]:
        n, a = r["normal"], r.get("atom")
        cells = [f"{r['label']} ({r['bytes']:,}, {r['rate_hz']:g})", r["cipher_label"], _num(n["enc_dec_us"]),
                 f"{r['bytes_added']:,} ({_pct(r['bytes_added_pct'])})", _num(n["cpu_pct_at_rate"]),
                 _num(n["msgs_per_s_one_core"]), "yes" if n["keeps_up"] else "NO"]
        if a:
            cells += [_num(a["enc_dec_us"]), _num(a["msgs_per_s_one_core"]), "yes" if a["keeps_up"] else "NO",
                      f"{_num(n['energy_mj_per_msg'])} / {_num(a['energy_mj_per_msg'])}"]
        else:
            cells += ["-", "-", "-", _num(n["energy_mj_per_msg"])]
        out.append(cells)
    return out


def table2_rows(report: dict) -> list[list[str]]:
    """machine | category | then per cipher: ours (paper's, for the paper's three)."""
    out = []
    paper_of = {v: k for k, v in PAPER_CIPHERS.items()}
    for machine, cats in report["table2"].items():
        for cat, cells in cats.items():
            if cat == "extended":
                continue
            row = [machine, cat]
            for cipher in report["ciphers"]:
                ours = cells[cipher]
                p = paper_of.get(cipher)
                row.append(f"{ours} (paper {PAPER['table2'][machine][cat][p]})" if p else ours)
            out.append(row)
        p_custom = PAPER["table2"][machine]["custom"]
        out.append([machine, "custom", *(f"not measured (paper {p_custom[paper_of[c]]})" if c in paper_of else "-"
                                         for c in report["ciphers"])])
    return out


def table2_extended_rows(report: dict) -> list[list[str]]:
    """The categories the paper did not have: raw camera images and point clouds."""
    return [[machine, "raw image + point cloud", *(cats["extended"][c] for c in report["ciphers"])]
            for machine, cats in report["table2"].items() if "extended" in cats]


def table2_message_rows(report: dict) -> list[list[str]]:
    labels = {s.key: s.label for s in MESSAGES}
    return [[machine, f"{labels[key]} ({report['messages'][key]['rate_hz']:g} Hz)",
             *(cells[c] for c in report["ciphers"])]
            for machine, by in report.get("table2_by_message", {}).items() for key, cells in by.items()]


def headline_rows(report: dict) -> list[list[str]]:
    """The paper's headlines beside ours: images/s on the Atom, battery time."""
    out = []
    wl = report["paper_workload"]
    atom = wl.get("atom", {})
    for name, key in PAPER_CIPHERS.items():
        if key in atom:
            a = atom[key]
            out.append([f"Atom: images processed per s of 30 ({name})", str(PAPER["atom_images_per_s_of_30"][name]),
                        f"{a['images_per_s_two_nodes']:.1f} (enc, dec on own cores) / {a['images_per_s_one_core']:.1f} (one core)"])
    for name, key in PAPER_CIPHERS.items():
        if key in atom:
            out.append([f"Atom: laser scans per s of 10 ({name})", "10 (kept up)", f"{atom[key]['laser_per_s_one_core']:.1f}"])
    for machine, cu in (("powerful", "CU A"), ("atom", "CU B")):
        if machine not in wl:
            continue
        out.append([f"{cu} battery time, plain", PAPER["battery"][cu]["plain"], hms(wl[machine]["plain"]["battery_h"]) + " (model input)"])
        for name, key in PAPER_CIPHERS.items():
            w = wl[machine][key]
            out.append([f"{cu} battery time, {name}", PAPER["battery"][cu][name],
                        f"{hms(w['battery_h'])} (+{w['added_w']:.2f} W, {w['cpu_cores_busy'] * 100:.1f} % of a core)"])
    rows = {r["cipher"]: r for r in report["rows"] if r["message"] == "image"}
    added = ", ".join(f"{name} {rows[key]['bytes_added']} B" for name, key in PAPER_CIPHERS.items() if key in rows)
    out.append(["bytes added per image (AES the most in the paper)", PAPER["network"], added])
    return out


def relay_rows(report: dict) -> list[list[str]]:
    out = []
    for run_label, modes in report["relay"].items():
        for key, r in modes.items():
            if isinstance(r, dict):
                cpu = r.get("interceptors_cpu_us_per_msg")
                out.append([run_label, modes.get("negotiated", "-"), f"{key} ({report['messages'][key]['bytes']:,} B)",
                            f"{r.get('msg_per_s', 0):,.0f}", f"{r.get('mb_per_s', 0):,.1f}",
                            "-" if cpu is None else f"{cpu:,.1f}", f"{r.get('received')}/{r.get('sent')}"])
    return out


def echo_markdown_table(title: str, headers: list[str], rows: list[list[str]]) -> None:
    """One titled Markdown table on standard output (the benches' --markdown)."""
    click.echo(f"\n**{title}**\n")
    click.echo("| " + " | ".join(headers) + " |")
    click.echo("|" + "---|" * len(headers))
    for row in rows:
        click.echo("| " + " | ".join(row) + " |")


def render(report: dict, markdown: bool) -> None:
    blocks = [
        ("Per message: encrypt + decrypt, one core, this machine and the Atom stand-in", TABLE_HEADERS, table_rows(report)),
        ("Table 2 rebuilt in the paper's categories (simple: String, Pose, LaserScan; complex: the paper's 80 KB "
         "camera image) (✓ <= 25 % of a core at the real rate, ∅ <= 100 %, ⇌ cannot keep up); paper's in brackets",
         ["machine", "messages", *(cipher_label(c) for c in report["ciphers"])], table2_rows(report)),
        ("Extended categories, not the paper's (raw 640x480 rgb8 image at 30 fps, 1 MB point cloud at 10 Hz): "
         "the same rule", ["machine", "messages", *(cipher_label(c) for c in report["ciphers"])],
         table2_extended_rows(report)),
        ("The same verdicts per message type (the categories above take the worst of theirs)",
         ["machine", "message", *(cipher_label(c) for c in report["ciphers"])], table2_message_rows(report)),
        ("The paper's headlines beside ours (paper's workload: LaserScan 10 Hz + image 30 fps)",
         ["figure", "paper (seed 002)", "ours"], headline_rows(report)),
    ]
    if report.get("relay"):
        blocks.append(("Relayed through the interceptor pair (our node client, loopback; frames of the message's size; "
                       "interceptors unthrottled, [limits] max_messages_per_second = 0)",
                       ["run", "negotiated", "frames", "msgs/s", "MB/s", "CPU us/msg, both interceptors", "received"], relay_rows(report)))
    if markdown:
        for title, headers, rows in blocks:
            echo_markdown_table(title, headers, rows)
    else:
        from rich.console import Console
        from rich.table import Table

        console = for_logs(Console())
        for title, headers, rows in blocks:
            table = Table(title=title)
            for i, h in enumerate(headers):
                table.add_column(h, justify="left" if i < 2 else "right")
            for row in rows:
                table.add_row(*row)
            console.print(table)


def plots(report: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    ciphers = report["ciphers"]
    fig, axes = plt.subplots(1, 2, figsize=(14, 6.2), gridspec_kw={"width_ratios": [3, 1.3]})
    ax = axes[0]
    width = 0.8 / len(ciphers)
    cmap = plt.get_cmap("tab20")
    for i, cipher in enumerate(ciphers):
        xs, ys, ya = [], [], []
        for j, spec in enumerate(MESSAGES):
            r = next(r for r in report["rows"] if r["message"] == spec.key and r["cipher"] == cipher)
            xs.append(j + (i - len(ciphers) / 2) * width + width / 2)
            ys.append(r["normal"]["msgs_per_s_one_core"])
            ya.append(r["atom"]["msgs_per_s_one_core"] if "atom" in r else float("nan"))
        ax.bar(xs, ys, width, color=cmap(i % 20), label=cipher_label(cipher))
        ax.scatter(xs, ya, s=10, color="black", zorder=3, marker="_")
    for j, spec in enumerate(MESSAGES):
        ax.hlines(spec.rate_hz, j - 0.45, j + 0.45, colors="red", linestyles="dashed", linewidth=1)
    ax.set_yscale("log")
    ax.set_xticks(range(len(MESSAGES)), [f"{s.label}\n{len_b(report, s.key):,} B" for s in MESSAGES])
    ax.set_ylabel("messages/s, encrypt + decrypt on one core")
    ax.set_title("bars: this machine; black ticks: Atom stand-in; red dashes: the message's real rate", fontsize=9)
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    ax = axes[1]
    names = list(PAPER_CIPHERS)
    atom = report["paper_workload"].get("atom", {})
    x = range(len(names))
    ax.bar([i - 0.27 for i in x], [PAPER["atom_images_per_s_of_30"][n] for n in names], 0.27, color="grey",
           label="paper, Atom D525 (2 cores)")
    ax.bar(list(x), [atom[PAPER_CIPHERS[n]]["images_per_s_two_nodes"] if atom else 0 for n in names], 0.27,
           color="tab:blue", label="ours: encrypt, decrypt on a stand-in core each")
    ax.bar([i + 0.27 for i in x], [atom[PAPER_CIPHERS[n]]["images_per_s_one_core"] if atom else 0 for n in names], 0.27,
           color="tab:cyan", label="ours: both on one stand-in core")
    ax.axhline(30, color="red", linestyle="dashed", linewidth=1)
    ax.set_xticks(list(x), [f"{n}\n({cipher_label(PAPER_CIPHERS[n]).split(' ')[0]})" for n in names])
    ax.set_ylim(0, 36)
    ax.set_ylabel("images processed per second (of 30)")
    ax.set_title("the paper's headline: images on the Atom", fontsize=9)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    fig.suptitle("cryptoros bench ciphers: seed 002's cipher costs on real ROS 1 messages")
    fig.tight_layout()
    path = out / "ciphers.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def len_b(report: dict, key: str) -> int:
    return next(r["bytes"] for r in report["rows"] if r["message"] == key)


# ============================================================ the interceptor pair


def relay_throughput(sizes: dict[str, int], n: int, workdir: Path, progress) -> dict:
    """Frames of each size relayed talker -> A's interceptor == TLS ==> B's -> listener,
    once per allowed TLS 1.3 suite (OPENSSL_CONF in the interceptors' environment) and
    once with TLS 1.2 pinned (the suite the interceptors negotiate), plus plain ROS. The
    interceptors run unthrottled (``[limits] max_messages_per_second = 0``)."""
    from cryptoros.bench.interceptor import BENCH_HOSTS, Mode, _policy, run_pair
    from cryptoros.lab.network import UNTHROTTLED, NetworkError, cpu_seconds, lab_network

    # small frames: 10 times as many, so a run lasts long enough to time
    modes = [Mode(key, f"{key} {size} B", "image", n * 10 if size < 16384 else n, size) for key, size in sizes.items()]

    def interceptors_cpu(net) -> float:
        return sum(cpu_seconds(net.hosts[h].proc.pid) or 0.0 for h in ("robot_a", "robot_b"))

    def timed(net, transport: str, sub: Path) -> dict:
        got = {}
        for mode in modes:
            before = interceptors_cpu(net)
            got[mode.key] = run_pair(net, "ours", transport, [mode], sub, progress)[mode.key]
            if transport == "interceptor" and got[mode.key].get("received"):
                got[mode.key]["interceptors_cpu_us_per_msg"] = (interceptors_cpu(net) - before) / got[mode.key]["received"] * 1e6
        return got

    out: dict = {}
    runs = [(f"TLS 1.3 {s}", s, False) for s in TLS13_SUITES] + [("TLS 1.2 (negotiated)", None, True)]
    for label, suite, pin12 in runs:
        progress(f"relay: {label}")
        old = os.environ.get("OPENSSL_CONF")
        if suite:
            os.environ["OPENSSL_CONF"] = str(_openssl_conf(workdir, suite))
        try:
            sub = workdir / label.replace(" ", "_")
            with lab_network(sub, _policy(), hosts=BENCH_HOSTS, start=[] if pin12 else None,
                             limits=UNTHROTTLED) as net:
                if pin12:
                    for name, host in net.hosts.items():
                        host.config.write_text(host.config.read_text().replace("[tls]\n", "[tls]\npin_tls12 = true\n"))
                    for name in net.hosts:
                        net.start(name)
                negotiated = _negotiated(net)
                progress(f"relay: the interceptors negotiate {negotiated}")
                out[label] = timed(net, "interceptor", sub)
                out[label]["negotiated"] = negotiated
                if not out.get("plain"):
                    out["plain"] = timed(net, "plain", sub)
        except NetworkError as exc:
            raise click.ClickException(f"relay {label}: {exc}") from None
        finally:
            if suite:
                if old is None:
                    os.environ.pop("OPENSSL_CONF", None)
                else:
                    os.environ["OPENSSL_CONF"] = old
    for modes_out in out.values():
        for key, r in modes_out.items():
            if isinstance(r, dict) and r.get("mb_per_s"):
                r["msg_per_s"] = r["mb_per_s"] * 1e6 / sizes[key]
                r["frames"] = next(m.n for m in modes if m.key == key)
    return out


def _negotiated(net) -> str:
    """The suite robot_a's interceptor negotiates with a client offering everything the
    interceptor's own contexts offer (a TLS handshake to its public port, no preamble)."""
    import socket

    from cryptoros import tls

    cert, key = net.cert("robot_b")
    ctx = tls.client_context(tls.TLSConfig(ca_file=net.ca, cert_file=cert, key_file=key), check_hostname=False)
    host = net.hosts["robot_a"]
    with socket.create_connection((host.address, host.public_port), 5) as raw, ctx.wrap_socket(raw) as conn:
        name, version, _bits = conn.cipher()
    return f"{version} {name}"


# ============================================================ command


@click.command()
@click.option("--quick", is_flag=True, help="Short timing windows (for tests): figures are noisier.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write every figure as JSON.")
@click.option("--plots", "plots_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also draw ciphers.png into this directory.")
@click.option("--atom-quota", type=click.FloatRange(0.01, 1.0), default=ATOM_QUOTA, show_default=True,
              help="Share of one core the Atom stand-in gets.")
@click.option("--no-atom", is_flag=True, help="Skip the throttled run.")
@click.option("--relay/--no-relay", default=None,
              help="Also relay frames through the interceptor pair per TLS suite (default: on, off with --quick).")
@click.option("--relay-messages", type=int, default=2000, show_default=True,
              help="Image-sized frames per relay row (LaserScan-sized: 10 times as many).")
@click.option("--markdown", is_flag=True, help="Print the tables as Markdown (for docs/ciphers.md).")
@click.option("--report", "report_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Measure nothing: print (and --plots) the figures of an earlier run's --json file.")
def ciphers(quick: bool, json_path: Path | None, plots_dir: Path | None, atom_quota: float, no_atom: bool,
            relay: bool | None, relay_messages: int, markdown: bool, report_path: Path | None) -> None:
    """Seed 002's cipher costs (3DES, Blowfish, AES, GCM, ChaCha20, TLS suites) on real ROS 1 messages."""
    started = time.monotonic()
    if report_path is not None:
        saved = json.loads(report_path.read_text())
        if plots_dir:
            plots(saved, plots_dir)
        render(saved, markdown)
        _footer(saved)
        return

    def progress(message: str) -> None:
        click.echo(f"[{time.monotonic() - started:6.1f} s] {message}", err=True)

    windows = {"normal": (0.02, 3, 10_000) if quick else (0.3, 5, 100_000),
               "atom": (0.05, 1, 10_000) if quick else (1.0, 3, 100_000)}
    if relay is None:
        relay = not quick
    workdir = Path(tempfile.mkdtemp(prefix="cryptoros-bench-ciphers-"))
    throttle = None
    try:
        progress("serializing messages")
        messages = build_messages()
        files = {}
        for key, blob in messages.items():
            files[key] = str(workdir / f"{key}.bin")
            Path(files[key]).write_bytes(blob)
        pki = _make_pki(workdir)
        raw: dict = {}
        progress("this machine, one core, unthrottled")
        raw["normal"] = measure_all("normal", files, pki, windows["normal"], None, workdir, progress)
        config: dict = {"cpus": os.cpu_count(), "quick": quick, "windows": windows}
        if not no_atom:
            throttle = Throttle(atom_quota)
            progress(f"Atom stand-in: {throttle.describe()}; OPENSSL_ia32cap={ATOM_IA32CAP}")
            config["throttle"] = {"method": throttle.method, "description": throttle.describe(), "quota": atom_quota,
                                  "period_us": THROTTLE_PERIOD_US, "openssl_ia32cap": ATOM_IA32CAP}
            raw["atom"] = measure_all("atom", files, pki, windows["atom"], throttle, workdir, progress)
        report = build_report(raw, messages)
        report["config"] = config
        report["messages"] = {s.key: {"type": s.typename, "bytes": len(messages[s.key]), "rate_hz": s.rate_hz,
                                      "note": s.note} for s in MESSAGES}
        report["energy_model"] = (
            f"energy per message = busy core-seconds x TDP/cores (i7-3612QM 35 W / 4, Atom D525 13 W / 2); "
            f"battery = mAh x {PACK_VOLTS} V (assumed 3S pack; the paper's 4,400 mAh on CU A, 5,200 mAh on CU B); "
            f"base load = battery / the paper's plain time (3:00, 3:13); battery time = battery / (base + added), "
            f"added capped at the machine's cores")
        if relay:
            sizes = {"laser": len(messages["laser"]), "image": len(messages["image"])}
            report["relay"] = relay_throughput(sizes, relay_messages, workdir, progress)
        report["elapsed_s"] = time.monotonic() - started
    finally:
        if throttle is not None:
            throttle.close()
        shutil.rmtree(workdir, ignore_errors=True)
    if json_path:
        write_output(json_path, json.dumps(report, indent=2, ensure_ascii=False))
    if plots_dir:
        for p in plots(report, plots_dir):
            progress(f"wrote {p}")
    render(report, markdown)
    _footer(report)


def _footer(report: dict) -> None:
    throttle = report["config"].get("throttle", {})
    click.echo(f"\nAtom stand-in: {throttle.get('description', 'not run')}; OpenSSL without AES-NI, PCLMULQDQ, "
               f"AVX ({throttle.get('openssl_ia32cap', ATOM_IA32CAP)}).\nEnergy model: {report['energy_model']}.")


__all__ = ["ciphers", "build_messages", "build_report", "primitive", "expected_added", "energy_model"]
