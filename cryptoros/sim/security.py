"""Security manager: authentication, integrity and confidentiality, each switchable.

Operations are real (``cryptography``): frames are really signed, hashed, MACed and
encrypted, and an attacker's change really fails verification. What each operation
*costs* is not the wall time of this run: it comes from a :class:`CostTable`, either
``nominal`` (fixed figures, the default for tests: results depend on the seed only)
or ``measured`` (timed once per process on this machine, rounded to two significant
digits, so a run is reproducible on one machine but not across machines). Either way
the cost is multiplied by ``cpu_scale`` (a TurtleBot3's Raspberry Pi is ~8x slower
than a desktop core) and charged to the robot's clock (its next step waits) and
battery (at the CPU's power draw).

Scheme (team roster provisioned in advance, as cryptoros' PKI does for real robots):

* every robot has a static ECDSA key on the chosen curve (secp192r1, secp256k1,
  secp384r1); the roster maps names to public keys. Keys derive from the run seed.
* **key agreement**: each robot has an outgoing *sender key* (AES-128) per epoch,
  rotated every ``key_period`` s (ephemeral keys, paper section 4.2). It is sent to
  each neighbour wrapped under a pairwise key from ECDH (a fresh ephemeral key of the
  sender with the receiver's static key, HKDF with the direction ``A->B`` in the info),
  or, as in the paper, under the receiver's RSA key (``auth="rsa"``: RSA-OAEP key
  transport). Outgoing and incoming traffic use different keys (A's key for A->*,
  B's key for B->*), so a reflected frame never decrypts or verifies.
* **authentication**: every frame is signed (ECDSA, SHA-256, fixed-width r||s) and
  checked against the roster; with it, frames carry a sequence number and timestamp
  that are checked for freshness (replays are rejected).
* **integrity**: ``sha256`` appends the paper's bare digest (anyone can recompute it:
  it stops accidents, not a man in the middle); ``hmac`` appends HMAC-SHA256 under a
  key derived from the sender key (stops an outsider; any holder of the key can forge).
* **confidentiality**: AES-128-CTR under the sender key, nonce from (epoch, seq).

Interface used by the robot (no I/O, ``now`` passed in): ``start``, ``tick``,
``expire``, ``on_neighbour`` return messages to send; ``seal`` turns a message into
``(typename, bytes)`` for the radio; ``open`` turns a received frame into
``(message, typename, reject_reason, replies)``; ``take_cpu`` returns the CPU seconds
spent since the last call.
"""

from __future__ import annotations

import hashlib
import hmac as hmac_mod
import math
import struct
import time
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature, encode_dss_signature
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from cryptography.hazmat.primitives.ciphers.aead import AESGCM
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat
from cryptography.exceptions import InvalidSignature, InvalidTag

from cryptoros.errors import ConfigError
from cryptoros.sim import packets as P

CURVES = {"secp192r1": ec.SECP192R1, "secp256k1": ec.SECP256K1, "secp384r1": ec.SECP384R1}
F_ENC, F_DIGEST, F_MAC, F_SIGNED = 1, 2, 4, 8


@dataclass(frozen=True)
class SecurityConfig:
    auth: str = "none"  # none | ecdsa | rsa
    integrity: str = "none"  # none | sha256 | hmac
    encrypt: bool = False
    curve: str = "secp256k1"
    key_period: float = 60.0
    freshness: float = 5.0
    beacon_period: float = 2.0
    crypto_cost: str = "nominal"  # nominal | measured
    cpu_scale: float = 8.0

    def __post_init__(self) -> None:
        if self.auth not in ("none", "ecdsa", "rsa"):
            raise ConfigError(f"auth must be none, ecdsa or rsa, not {self.auth!r}")
        if self.integrity not in ("none", "sha256", "hmac"):
            raise ConfigError(f"integrity must be none, sha256 or hmac, not {self.integrity!r}")
        if self.curve not in CURVES:
            raise ConfigError(f"curve must be one of {sorted(CURVES)}, not {self.curve!r}")
        if self.crypto_cost not in ("nominal", "measured"):
            raise ConfigError("crypto_cost must be nominal or measured")

    @property
    def enabled(self) -> bool:
        return self.auth != "none" or self.integrity != "none" or self.encrypt

    @property
    def needs_keys(self) -> bool:
        return self.encrypt or self.integrity == "hmac"

    @property
    def label(self) -> str:
        parts = []
        if self.auth != "none":
            parts.append(f"{self.auth}-{self.curve}")
        if self.integrity != "none":
            parts.append(self.integrity)
        if self.encrypt:
            parts.append("aes128")
        return "+".join(parts) or "none"

    @classmethod
    def parse(cls, spec: str, **kw: Any) -> "SecurityConfig":
        """``none`` | comma list of ``auth``/``ecdsa``, ``rsa``, ``sha256``, ``hmac``,
        ``aes``/``encrypt``, ``full`` (= ecdsa,hmac,aes)."""
        auth, integ, enc = "none", "none", False
        for tok in [t.strip() for t in spec.split(",") if t.strip()]:
            if tok == "none":
                continue
            if tok in ("auth", "ecdsa"):
                auth = "ecdsa"
            elif tok == "rsa":
                auth = "rsa"
            elif tok in ("sha256", "hmac"):
                integ = tok
            elif tok in ("aes", "aes128", "encrypt"):
                enc = True
            elif tok == "full":
                auth, integ, enc = "ecdsa", "hmac", True
            else:
                raise ConfigError(f"unknown security option {tok!r}")
        return cls(auth=auth, integrity=integ, encrypt=enc, **kw)


# ---------------------------------------------------------------- costs

# Nominal per-operation costs in seconds on a desktop core (rounded from OpenSSL 3 on
# x86-64); multiplied by cpu_scale. Per-byte costs for symmetric primitives.
NOMINAL = {
    "secp192r1": {"sign": 120e-6, "verify": 150e-6, "ecdh": 250e-6},
    "secp256k1": {"sign": 150e-6, "verify": 200e-6, "ecdh": 320e-6},
    "secp384r1": {"sign": 900e-6, "verify": 800e-6, "ecdh": 1600e-6},
    "rsa": {"wrap": 30e-6, "unwrap": 900e-6},
    "sym": {"aes_op": 1.5e-6, "aes_byte": 1.0e-9, "hash_op": 0.6e-6, "hash_byte": 2.0e-9, "hmac_op": 1.5e-6},
}


def _timeit(fn, reps: int = 15) -> float:
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    return ts[len(ts) // 2]


def _round2(x: float) -> float:
    if x <= 0:
        return 0.0
    e = math.floor(math.log10(x))
    return round(x, -e + 1)


@cache
def measured_costs(curve: str) -> dict[str, dict[str, float]]:
    """Time each primitive once per process (median of 15), rounded to 2 digits."""
    key = ec.generate_private_key(CURVES[curve]())
    peer = ec.generate_private_key(CURVES[curve]()).public_key()
    data = b"x" * 256
    sig = key.sign(data, ec.ECDSA(hashes.SHA256()))
    pub = key.public_key()
    rk = _rsa_key("cost")
    wrapped = rk.public_key().encrypt(b"k" * 16, _OAEP)
    aes = b"k" * 16
    big = b"y" * 4096

    def aes_once(buf: bytes) -> None:
        c = Cipher(algorithms.AES(aes), modes.CTR(b"\0" * 16)).encryptor()
        c.update(buf)
        c.finalize()

    out = {
        curve: {
            "sign": _timeit(lambda: key.sign(data, ec.ECDSA(hashes.SHA256()))),
            "verify": _timeit(lambda: pub.verify(sig, data, ec.ECDSA(hashes.SHA256()))),
            "ecdh": _timeit(lambda: ec.generate_private_key(CURVES[curve]()).exchange(ec.ECDH(), peer)),
        },
        "rsa": {"wrap": _timeit(lambda: rk.public_key().encrypt(b"k" * 16, _OAEP)), "unwrap": _timeit(lambda: rk.decrypt(wrapped, _OAEP))},
    }
    t_small = _timeit(lambda: aes_once(b"z" * 16), 50)
    t_big = _timeit(lambda: aes_once(big), 50)
    h_small = _timeit(lambda: hashlib.sha256(b"z").digest(), 50)
    h_big = _timeit(lambda: hashlib.sha256(big).digest(), 50)
    out["sym"] = {
        "aes_op": t_small, "aes_byte": max(0.0, (t_big - t_small) / 4096), "hash_op": h_small,
        "hash_byte": max(0.0, (h_big - h_small) / 4096), "hmac_op": _timeit(lambda: hmac_mod.new(aes, b"z", "sha256").digest(), 50),
    }
    return {k: {kk: _round2(vv) for kk, vv in v.items()} for k, v in out.items()}


@dataclass
class CostTable:
    curve: str
    mode: str = "nominal"
    cpu_scale: float = 8.0
    table: dict[str, dict[str, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.table = NOMINAL if self.mode == "nominal" else measured_costs(self.curve)

    def op(self, name: str) -> float:
        if name in ("sign", "verify", "ecdh"):
            return self.table[self.curve][name] * self.cpu_scale
        if name in ("wrap", "unwrap"):
            return self.table["rsa"][name] * self.cpu_scale
        raise KeyError(name)

    def sym(self, kind: str, nbytes: int) -> float:
        s = self.table["sym"]
        if kind == "aes":
            return (s["aes_op"] + s["aes_byte"] * nbytes) * self.cpu_scale
        if kind == "hash":
            return (s["hash_op"] + s["hash_byte"] * nbytes) * self.cpu_scale
        return (s["hmac_op"] + s["hash_byte"] * nbytes) * self.cpu_scale

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "cpu_scale": self.cpu_scale, "curve": self.table[self.curve], "rsa": self.table["rsa"], "sym": self.table["sym"]}


# ---------------------------------------------------------------- keys and roster

_OAEP = padding.OAEP(mgf=padding.MGF1(hashes.SHA256()), algorithm=hashes.SHA256(), label=None)


def derive_ec_key(seed: int, name: str, curve: str) -> ec.EllipticCurvePrivateKey:
    c = CURVES[curve]()
    h = int.from_bytes(hashlib.sha512(f"cryptoros-sim|{seed}|{name}|{curve}".encode()).digest(), "big")
    value = (h >> (512 - (c.key_size - 1))) | 1
    return ec.derive_private_key(value, c)


@cache
def _rsa_key(name: str) -> rsa.RSAPrivateKey:
    # RSA key generation cannot be seeded; results never depend on the key bytes
    # (OAEP output length is fixed), so one cached key per name and process is enough.
    return rsa.generate_private_key(public_exponent=65537, key_size=2048)


@dataclass
class Roster:
    """Who is in the team: name -> public keys (what the PKI would provision)."""

    seed: int
    curve: str
    ec_private: dict[str, ec.EllipticCurvePrivateKey] = field(default_factory=dict)
    ec_public: dict[str, ec.EllipticCurvePublicKey] = field(default_factory=dict)

    def enrol(self, name: str) -> None:
        k = derive_ec_key(self.seed, name, self.curve)
        self.ec_private[name] = k
        self.ec_public[name] = k.public_key()

    def rsa_private(self, name: str) -> rsa.RSAPrivateKey:
        return _rsa_key(name)


def _sig_bytes(der: bytes, key_size: int) -> bytes:
    r, s = decode_dss_signature(der)
    n = (key_size + 7) // 8
    return r.to_bytes(n, "big") + s.to_bytes(n, "big")


def _sig_der(raw: bytes) -> bytes:
    n = len(raw) // 2
    return encode_dss_signature(int.from_bytes(raw[:n], "big"), int.from_bytes(raw[n:], "big"))


def _hkdf(secret: bytes, info: str) -> bytes:
    return HKDF(algorithm=hashes.SHA256(), length=16, salt=None, info=info.encode()).derive(secret)


def _ctr(key: bytes, epoch: int, seq: int, data: bytes) -> bytes:
    nonce = struct.pack(">IIQ", epoch, 0, seq)
    c = Cipher(algorithms.AES(key), modes.CTR(nonce)).encryptor()
    return c.update(data) + c.finalize()


def header_bytes(sender: str, seq: int, stamp: float, epoch: int, inner: str, flags: int) -> bytes:
    return f"{sender}|{seq}|{stamp!r}|{epoch}|{inner}|{flags}".encode()


def _u8(b: bytes) -> np.ndarray:
    return np.frombuffer(b, dtype=np.uint8)


# ---------------------------------------------------------------- the manager


class SecurityManager:
    def __init__(self, name: str, config: SecurityConfig, roster: Roster, costs: CostTable, rng: np.random.Generator) -> None:
        self.name = name
        self.cfg = config
        self.roster = roster
        self.costs = costs
        self.rng = rng
        self.seq = 0
        self.cpu = 0.0
        self.cpu_total = 0.0
        self.ops: dict[str, int] = {}
        self.epoch = 0
        self.my_key = b""
        self.key_started = 0.0
        self.peer_keys: dict[str, dict[int, bytes]] = {}  # sender -> epoch -> key
        self.sent_key_to: dict[str, int] = {}  # peer -> epoch last sent
        self.peers_seen: dict[str, float] = {}
        self.last_seq: dict[str, int] = {}
        self.last_beacon = -1e9
        self._priv = roster.ec_private.get(name)

    # -- accounting --------------------------------------------------------------------

    def _spend(self, op: str, seconds: float) -> None:
        self.cpu += seconds
        self.cpu_total += seconds
        self.ops[op] = self.ops.get(op, 0) + 1

    def take_cpu(self) -> float:
        c, self.cpu = self.cpu, 0.0
        return c

    # -- keys --------------------------------------------------------------------------

    def _new_epoch(self, now: float) -> None:
        self.epoch += 1
        self.my_key = bytes(self.rng.integers(0, 256, 16, dtype=np.uint8))
        self.key_started = now
        self.peer_keys.setdefault(self.name, {})[self.epoch] = self.my_key

    def start(self, now: float) -> list[tuple[Any, str]]:
        if not self.cfg.enabled:
            return []
        if self.cfg.needs_keys:
            self._new_epoch(now)
            return [self._beacon(now)]
        return []

    def _beacon(self, now: float) -> tuple[Any, str]:
        self.last_beacon = now
        have = sorted(f"{p}:{max(k)}" for p, k in self.peer_keys.items() if p != self.name and k)
        msg = P.make(P.KEYX, source=self.name, destination="", kind=1, epoch=self.epoch, timestamp=now,
                     public_key=_u8(b""), wrapped_key=_u8(b""), signature=_u8(b""), have=have)
        return self._sign_keyx(msg), P.KEYX

    def _keyx_bytes(self, m: Any) -> bytes:
        return f"{m.source}|{m.destination}|{m.kind}|{m.epoch}|{m.timestamp!r}|{','.join(m.have)}|".encode() + bytes(m.public_key) + bytes(m.wrapped_key)

    def _sign_keyx(self, msg: Any) -> Any:
        if self.cfg.auth == "none" or self._priv is None:
            return msg
        der = self._priv.sign(self._keyx_bytes(msg), ec.ECDSA(hashes.SHA256()))
        self._spend("sign", self.costs.op("sign"))
        return P.replace(msg, signature=_u8(_sig_bytes(der, self._priv.curve.key_size)))

    def _sender_key_for(self, peer: str, now: float) -> tuple[Any, str] | None:
        if self.cfg.auth == "rsa":
            wrapped = self.roster.rsa_private(peer).public_key().encrypt(self.my_key, _OAEP)
            self._spend("rsa_wrap", self.costs.op("wrap"))
            eph_pub = b""
        else:
            pub = self.roster.ec_public.get(peer)
            if pub is None:
                return None
            eph = ec.generate_private_key(CURVES[self.cfg.curve]())
            k = _hkdf(eph.exchange(ec.ECDH(), pub), f"{self.name}->{peer}|{self.epoch}")
            self._spend("ecdh", self.costs.op("ecdh"))
            wrapped = AESGCM(k).encrypt(struct.pack(">I", self.epoch) + b"\0" * 8, self.my_key, self.name.encode())
            eph_pub = eph.public_key().public_bytes(Encoding.X962, PublicFormat.CompressedPoint)
        self.sent_key_to[peer] = self.epoch
        msg = P.make(P.KEYX, source=self.name, destination=peer, kind=3, epoch=self.epoch, timestamp=now,
                     public_key=_u8(eph_pub), wrapped_key=_u8(wrapped), signature=_u8(b""), have=[])
        return self._sign_keyx(msg), P.KEYX

    def _on_keyx(self, m: Any, now: float) -> tuple[str, list[tuple[Any, str]]]:
        if m.source == self.name:
            return "", []
        if self.cfg.auth != "none":
            pub = self.roster.ec_public.get(m.source)
            if pub is None:
                return "unknown_signer", []
            self._spend("verify", self.costs.op("verify"))
            try:
                pub.verify(_sig_der(bytes(m.signature)), self._keyx_bytes(m), ec.ECDSA(hashes.SHA256()))
            except (InvalidSignature, ValueError):
                return "bad_signature", []
            if now - m.timestamp > self.cfg.freshness:
                return "stale", []
        replies = []
        self.peers_seen[m.source] = now
        if m.kind == 1 and f"{self.name}:{self.epoch}" not in m.have:
            self.sent_key_to.pop(m.source, None)  # the peer says it lacks our key: send again
        if self.sent_key_to.get(m.source) != self.epoch and self.my_key:
            r = self._sender_key_for(m.source, now)
            if r:
                replies.append(r)
        if m.kind == 3 and m.destination == self.name:
            try:
                if self.cfg.auth == "rsa":
                    key = self.roster.rsa_private(self.name).decrypt(bytes(m.wrapped_key), _OAEP)
                    self._spend("rsa_unwrap", self.costs.op("unwrap"))
                else:
                    eph = ec.EllipticCurvePublicKey.from_encoded_point(CURVES[self.cfg.curve](), bytes(m.public_key))
                    k = _hkdf(self.roster.ec_private[self.name].exchange(ec.ECDH(), eph), f"{m.source}->{self.name}|{m.epoch}")
                    self._spend("ecdh", self.costs.op("ecdh"))
                    key = AESGCM(k).decrypt(struct.pack(">I", m.epoch) + b"\0" * 8, bytes(m.wrapped_key), m.source.encode())
            except (InvalidTag, ValueError, KeyError):
                return "bad_key", replies
            keys = self.peer_keys.setdefault(m.source, {})
            keys[int(m.epoch)] = key
            for old in [e for e in keys if e < m.epoch - 1]:
                del keys[old]
        return "", replies

    def tick(self, now: float) -> list[tuple[Any, str]]:
        out: list[tuple[Any, str]] = []
        if not self.cfg.needs_keys:
            return out
        if now - self.key_started >= self.cfg.key_period:
            self._new_epoch(now)
            for peer in sorted(self.peers_seen):
                r = self._sender_key_for(peer, now)
                if r:
                    out.append(r)
        if now - self.last_beacon >= self.cfg.beacon_period:
            out.append(self._beacon(now))
        return out

    def expire(self, neighbours: set[str], now: float) -> None:
        for p in [p for p, t in self.peers_seen.items() if now - t > 10.0]:
            del self.peers_seen[p]
            self.sent_key_to.pop(p, None)

    def on_neighbour(self, peer: str, now: float) -> list[tuple[Any, str]]:
        return []

    # -- frames ------------------------------------------------------------------------

    def seal(self, msg: Any, typename: str, now: float) -> tuple[str, bytes]:
        inner = P.encode(msg, typename)
        if not self.cfg.enabled or typename == P.KEYX:
            return typename, inner
        self.seq += 1
        flags = 0
        payload = inner
        if self.cfg.encrypt:
            payload = _ctr(self.my_key, self.epoch, self.seq, inner)
            self._spend("aes", self.costs.sym("aes", len(inner)))
            flags |= F_ENC
        digest = b""
        if self.cfg.integrity == "sha256":
            flags |= F_DIGEST
        elif self.cfg.integrity == "hmac":
            flags |= F_MAC
        if self.cfg.auth != "none" and self._priv is not None:
            flags |= F_SIGNED
        hdr = header_bytes(self.name, self.seq, now, self.epoch, typename, flags)
        if flags & F_DIGEST:
            digest = hashlib.sha256(hdr + payload).digest()
            self._spend("sha256", self.costs.sym("hash", len(payload)))
        elif flags & F_MAC:
            digest = hmac_mod.new(_mac_key(self.my_key), hdr + payload, "sha256").digest()[:16]
            self._spend("hmac", self.costs.sym("hmac", len(payload)))
        sig = b""
        if flags & F_SIGNED:
            der = self._priv.sign(hdr + payload + digest, ec.ECDSA(hashes.SHA256()))
            sig = _sig_bytes(der, self._priv.curve.key_size)
            self._spend("sign", self.costs.op("sign"))
        frame = P.make(P.SECURE, sender=self.name, signer=self.name if sig else "", seq=self.seq, timestamp=now, key_epoch=self.epoch,
                       inner_type=typename, flags=flags, payload=_u8(payload), digest=_u8(digest), signature=_u8(sig))
        return P.SECURE, P.encode(frame, P.SECURE)

    def open(self, frame: P.Frame, now: float) -> tuple[Any, str, str, list[tuple[Any, str]]]:
        if frame.typename == P.KEYX:
            m = frame.decode()
            if m is None:
                return None, "", "malformed", []
            if not self.cfg.needs_keys:
                return None, "", "", []
            why, replies = self._on_keyx(m, now)
            return None, "", why, replies
        if not self.cfg.enabled:
            if frame.typename == P.SECURE:
                return None, "", "no_key", []
            msg = frame.decode()
            return (msg, frame.typename, "", []) if msg is not None else (None, "", "malformed", [])
        if frame.typename != P.SECURE:
            return None, "", "not_secured", []
        f = frame.decode()
        if f is None:
            return None, "", "malformed", []
        payload = bytes(f.payload)
        hdr = header_bytes(f.sender, int(f.seq), float(f.timestamp), int(f.key_epoch), f.inner_type, int(f.flags))
        digest = bytes(f.digest)
        cache = frame.cache
        if self.cfg.auth != "none":
            if not f.flags & F_SIGNED:
                return None, "", "unsigned", []
            pub = self.roster.ec_public.get(f.signer)
            if pub is None or f.signer != f.sender:
                return None, "", "unknown_signer", []
            self._spend("verify", self.costs.op("verify"))
            ok = cache.get("sig")
            if ok is None:
                try:
                    pub.verify(_sig_der(bytes(f.signature)), hdr + payload + digest, ec.ECDSA(hashes.SHA256()))
                    ok = True
                except (InvalidSignature, ValueError):
                    ok = False
                cache["sig"] = ok
            if not ok:
                return None, "", "bad_signature", []
        key = self.peer_keys.get(f.sender, {}).get(int(f.key_epoch)) if self.cfg.needs_keys else None
        if self.cfg.integrity == "sha256":
            if not f.flags & F_DIGEST:
                return None, "", "no_digest", []
            self._spend("sha256", self.costs.sym("hash", len(payload)))
            if not hmac_mod.compare_digest(hashlib.sha256(hdr + payload).digest(), digest):
                return None, "", "bad_digest", []
        elif self.cfg.integrity == "hmac":
            if not f.flags & F_MAC:
                return None, "", "no_mac", []
            if key is None:
                return None, "", "no_key", []
            self._spend("hmac", self.costs.sym("hmac", len(payload)))
            if not hmac_mod.compare_digest(hmac_mod.new(_mac_key(key), hdr + payload, "sha256").digest()[:16], digest):
                return None, "", "bad_mac", []
        if self.cfg.auth != "none" or self.cfg.integrity == "hmac":
            if now - f.timestamp > self.cfg.freshness or f.timestamp - now > self.cfg.freshness:
                return None, "", "stale", []
            if int(f.seq) <= self.last_seq.get(f.sender, 0):
                return None, "", "replay", []
            self.last_seq[f.sender] = int(f.seq)
        if f.flags & F_ENC:
            if key is None:
                return None, "", "no_key", []
            self._spend("aes", self.costs.sym("aes", len(payload)))
            plain = _ctr(key, int(f.key_epoch), int(f.seq), payload)
        elif self.cfg.encrypt:
            return None, "", "not_encrypted", []
        else:
            plain = payload
        ck = ("inner", plain)
        msg = cache.get(ck)
        if msg is None:
            try:
                msg = P.decode(plain, f.inner_type)
            except Exception:
                return None, "", "malformed", []
            cache[ck] = msg
        return msg, f.inner_type, "", []


@cache
def _mac_key(key: bytes) -> bytes:
    return _hkdf(key, "mac")


def make_managers(names: list[str], config: SecurityConfig, seed: int, rngs: dict[str, np.random.Generator], *, insiders: list[str] = ()) -> tuple[dict[str, SecurityManager], Roster, CostTable]:
    roster = Roster(seed, config.curve)
    if config.enabled:
        for n in list(names) + list(insiders):
            roster.enrol(n)
    costs = CostTable(config.curve, config.crypto_cost, config.cpu_scale)
    return {n: SecurityManager(n, config, roster, costs, rngs[n]) for n in names}, roster, costs
