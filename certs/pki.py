"""A small file-based certificate authority for cryptoros.

Layout of a PKI directory::

    ca.crt              the root CA certificate (PEM)
    private/ca.key      the CA key (PKCS#8 PEM, AES-256 encrypted unless unsafe)
    issued/<name>.crt   issued certificates
    private/<name>.key  keys made by ``issue`` (mode 0600)
    csr/<name>.csr      copies of CSRs signed by ``sign_csr``
    crl.pem             the current signed CRL (an empty one is written by ``init``)
    index.json          trust domain, CRL number and one record per certificate

How its files are written (whole or not at all, under the directory's lock, the CA
replaced so that a stop leaves the old one or the new one) is :mod:`certs.files`.
``revoke`` writes the CRL before the index (a crash leaves a certificate refused, never
one accepted that the index calls revoked). Every failure the caller can cause raises
:class:`PKIError`.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import ipaddress
import json
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from certs.files import INIT_READY, FileSet, finish_init, pki_lock, refuse_existing_ca, replace_ca, write_file
from cryptoros import pemfiles
from cryptoros.errors import PKIError
from cryptoros.pemfiles import key_is_encrypted, load_certificate, load_crl, load_csr, load_private_key

KEY_TYPES = ("ec-p256", "rsa2048", "rsa3072")
KINDS = ("manager", "interceptor", "server", "master")  # server = authz server
REASONS = (
    "unspecified",
    "key_compromise",
    "ca_compromise",
    "affiliation_changed",
    "superseded",
    "cessation_of_operation",
    "certificate_hold",
    "privilege_withdrawn",
)

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_TRUST_DOMAIN_RE = re.compile(r"^[a-z0-9]([a-z0-9._-]{0,253}[a-z0-9])?$")
_DNS_RE = re.compile(r"^(\*\.)?([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
_RESERVED_NAMES = frozenset({"ca", "crl", "index"})
_BACKDATE = dt.timedelta(minutes=5)  # tolerate small clock skew between hosts
_ORG = "cryptoros"


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, kw_only=True)
class Issued:
    """What ``issue`` / ``sign_csr`` produced. ``key_path`` is None for a signed CSR."""

    name: str
    cert_path: Path
    key_path: Path | None
    serial: int
    fingerprint_sha256: str  # lowercase hex of SHA-256 over the DER certificate


@dataclass(frozen=True, kw_only=True)
class CertRecord:
    """One line of ``index.json``."""

    serial: int
    name: str
    kind: str
    fingerprint_sha256: str
    not_after: dt.datetime
    status: str  # "valid" or "revoked"
    revoked_at: dt.datetime | None = None
    reason: str | None = None

    @property
    def expired(self) -> bool:
        return self.not_after <= _now()

    def to_json(self) -> dict:
        return {
            "serial": self.serial,
            "name": self.name,
            "kind": self.kind,
            "fingerprint": self.fingerprint_sha256,
            "not_after": self.not_after.isoformat(),
            "status": self.status,
            "revoked_at": self.revoked_at.isoformat() if self.revoked_at else None,
            "reason": self.reason,
        }

    @classmethod
    def from_json(cls, d: dict) -> CertRecord:
        try:
            return cls(
                serial=int(d["serial"]),
                name=str(d["name"]),
                kind=str(d["kind"]),
                fingerprint_sha256=str(d["fingerprint"]),
                not_after=dt.datetime.fromisoformat(d["not_after"]),
                status=str(d["status"]),
                revoked_at=dt.datetime.fromisoformat(d["revoked_at"]) if d.get("revoked_at") else None,
                reason=d.get("reason"),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise PKIError(f"corrupt index.json record: {d!r}") from err


# --------------------------------------------------------------------------- helpers


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc).replace(microsecond=0)


def manager_identity_uri(trust_domain: str, name: str) -> str:
    """The identity URI SAN of a manager: ``spiffe://<trust-domain>/manager/<name>``."""
    return identity_uri(trust_domain, "manager", name)


def identity_uri(trust_domain: str, kind: str, name: str) -> str:
    """The identity URI SAN every certificate carries: ``spiffe://<td>/<kind>/<name>``."""
    return f"spiffe://{trust_domain}/{kind}/{name}"


def check_name(name: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise PKIError(f"invalid name {name!r}: use 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit")
    if name.lower() in _RESERVED_NAMES:
        raise PKIError(f"name {name!r} is reserved")
    return name


def _check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise PKIError(f"unknown kind {kind!r}: choose one of {', '.join(KINDS)}")
    return kind


def _check_days(days: int) -> int:
    if not isinstance(days, int) or days < 1:
        raise PKIError(f"days must be a positive integer, not {days!r}")
    return days


def _check_trust_domain(td: str) -> str:
    if not isinstance(td, str) or not _TRUST_DOMAIN_RE.match(td):
        raise PKIError(f"invalid trust domain {td!r}: use lowercase letters, digits, '.', '-', '_'")
    return td


def parse_san(spec: str | x509.GeneralName) -> x509.GeneralName:
    """Parse ``DNS:name``, ``IP:addr`` or ``URI:uri`` (the ``--san`` syntax)."""
    if isinstance(spec, x509.GeneralName):
        return spec
    if not isinstance(spec, str) or ":" not in spec:
        raise PKIError(f"bad SAN {spec!r}: expected DNS:<name>, IP:<address> or URI:<uri>")
    typ, _, value = spec.partition(":")
    typ = typ.strip().upper()
    value = value.strip()
    if not value:
        raise PKIError(f"bad SAN {spec!r}: empty value")
    if typ == "DNS":
        if not _DNS_RE.match(value) or len(value) > 253:
            raise PKIError(f"bad SAN {spec!r}: not a DNS name")
        return x509.DNSName(value)
    if typ in ("IP", "IP ADDRESS"):
        try:
            return x509.IPAddress(ipaddress.ip_address(value))
        except ValueError as err:
            raise PKIError(f"bad SAN {spec!r}: not an IP address") from err
    if typ == "URI":
        if not re.match(r"^[A-Za-z][A-Za-z0-9+.-]*://\S+$", value):
            raise PKIError(f"bad SAN {spec!r}: not an absolute URI")
        return x509.UniformResourceIdentifier(value)
    raise PKIError(f"bad SAN {spec!r}: type must be DNS, IP or URI")


def parse_sans(specs: Iterable[str | x509.GeneralName]) -> list[x509.GeneralName]:
    if isinstance(specs, str):
        specs = [specs]
    out: list[x509.GeneralName] = []
    for spec in specs:
        san = parse_san(spec)
        if san not in out:
            out.append(san)
    return out


def generate_key(key_type: str):
    if key_type == "ec-p256":
        return ec.generate_private_key(ec.SECP256R1())
    if key_type == "rsa2048":
        return rsa.generate_private_key(public_exponent=65537, key_size=2048)
    if key_type == "rsa3072":
        return rsa.generate_private_key(public_exponent=65537, key_size=3072)
    raise PKIError(f"unknown key type {key_type!r}: choose one of {', '.join(KEY_TYPES)}")


def _key_type_of(public_key) -> str:
    """The KEY_TYPES name of a public key (renewal keeps the type)."""
    if isinstance(public_key, ec.EllipticCurvePublicKey) and isinstance(public_key.curve, ec.SECP256R1):
        return "ec-p256"
    if isinstance(public_key, rsa.RSAPublicKey) and public_key.key_size in (2048, 3072):
        return f"rsa{public_key.key_size}"
    raise PKIError(f"cannot renew a {type(public_key).__name__} key: choose a key type")


def _key_encryption(passphrase: bytes | None, unsafe_no_passphrase: bool) -> serialization.KeySerializationEncryption:
    if unsafe_no_passphrase:
        if passphrase is not None:
            raise PKIError("give either a passphrase or unsafe_no_passphrase, not both")
        return serialization.NoEncryption()
    if passphrase is None:
        raise PKIError("a passphrase is required to encrypt the private key (or use unsafe_no_passphrase for throwaway setups)")
    if isinstance(passphrase, str):
        passphrase = passphrase.encode()
    if not passphrase:
        raise PKIError("the passphrase is empty")
    if len(passphrase) > 1023:
        raise PKIError("the passphrase is longer than 1023 bytes")
    # PKCS#8 with PBES2, AES-256-CBC: `openssl pkey -passin` opens it.
    return serialization.BestAvailableEncryption(passphrase)


def _key_pem(key, passphrase: bytes | None, unsafe_no_passphrase: bool) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        _key_encryption(passphrase, unsafe_no_passphrase),
    )


def cert_fingerprint_sha256(cert_or_path: x509.Certificate | str | os.PathLike) -> str:
    """Lowercase hex SHA-256 over the DER encoding of a certificate (or a cert file)."""
    cert = cert_or_path if isinstance(cert_or_path, x509.Certificate) else load_certificate(cert_or_path)
    return pemfiles.cert_fingerprint_sha256(cert.public_bytes(serialization.Encoding.DER))


def _check_public_key(key) -> None:
    if isinstance(key, rsa.RSAPublicKey):
        if key.key_size < 2048:
            raise PKIError(f"RSA key of {key.key_size} bits is too weak: at least 2048 are required")
    elif isinstance(key, ec.EllipticCurvePublicKey):
        if key.curve.name not in ("secp256r1", "secp384r1", "secp521r1"):
            raise PKIError(f"unsupported elliptic curve {key.curve.name}")
    else:
        raise PKIError(f"unsupported public key type {type(key).__name__}: use RSA or ECDSA")


def _sign_hash(key):
    return hashes.SHA256()


def _check_index(index: object, path: Path) -> dict:
    """The index as read, if it has the shape we write; PKIError naming the file if not."""
    problem = None
    if not isinstance(index, dict):
        problem = f"a JSON {type(index).__name__} instead of an object"
    elif not isinstance(index.setdefault("certificates", []), list):
        problem = "'certificates' is not a list"
    elif not all(isinstance(d, dict) for d in index["certificates"]):
        problem = "a certificate record is not an object"
    elif not isinstance(index.get("trust_domain", ""), str):
        problem = "'trust_domain' is not a string"
    elif not isinstance(index.get("crl_number", 0), int) or isinstance(index.get("crl_number"), bool):
        problem = "'crl_number' is not an integer"
    if problem:
        raise PKIError(f"{path} is not a cryptoros index ({problem}): restore it from a backup")
    return index


def _csr_common_name(csr: x509.CertificateSigningRequest, csr_path: Path) -> str:
    """The one common name of a CSR's subject; PKIError if it has none, several, or
    sits in a multi-valued RDN (``CN=a1+CN=a2``): which one was meant is a guess."""
    if any(len(rdn) > 1 for rdn in csr.subject.rdns):
        raise PKIError(f"CSR {csr_path} has a multi-valued RDN in its subject ({csr.subject.rfc4514_string()}): "
                       "ask for a CSR with one common name, or give the name explicitly")
    cns = csr.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not cns:
        raise PKIError(f"CSR {csr_path} has no common name: give the name explicitly")
    if len(cns) > 1:
        raise PKIError(f"CSR {csr_path} has {len(cns)} common names ({csr.subject.rfc4514_string()}): "
                       "ask for a CSR with one, or give the name explicitly")
    return str(cns[0].value)


def _entry_reason(entry: x509.RevokedCertificate) -> str:
    try:
        flag = entry.extensions.get_extension_for_class(x509.CRLReason).value.reason
    except x509.ExtensionNotFound:
        return "unspecified"
    return flag.name if flag.name in REASONS else "unspecified"


# --------------------------------------------------------------------------- building


def _ku(*, ca: bool, rsa_key: bool) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=(rsa_key and not ca),
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _ski_of(cert: x509.Certificate) -> x509.SubjectKeyIdentifier:
    try:
        return cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    except x509.ExtensionNotFound:
        return x509.SubjectKeyIdentifier.from_public_key(cert.public_key())


def _record_time(value: dt.datetime) -> dt.datetime:
    return value if value.tzinfo else value.replace(tzinfo=dt.timezone.utc)


# --------------------------------------------------------------------------- the CA


class PKI:
    """A certificate authority kept in one directory (see the module docstring)."""

    def __init__(self, directory: Path, *, passphrase: bytes | None = None) -> None:
        # Use PKI.init / PKI.open.
        self.directory = Path(directory)
        self.ca_cert_path = self.directory / "ca.crt"
        self.ca_key_path = self.directory / "private" / "ca.key"
        self.crl_path = self.directory / "crl.pem"
        self.index_path = self.directory / "index.json"
        self._passphrase = passphrase.encode() if isinstance(passphrase, str) else passphrase
        self._ca_key_cache = None
        index = self._read_index()
        self.trust_domain: str = _check_trust_domain(index.get("trust_domain", "cryptoros.local"))
        self.ca_cert: x509.Certificate = load_certificate(self.ca_cert_path)

    # ---- creation / opening

    @classmethod
    def init(
        cls,
        directory: str | os.PathLike,
        *,
        trust_domain: str = "cryptoros.local",
        key_type: str = "ec-p256",
        days: int = 3650,
        passphrase: bytes | None = None,
        unsafe_no_passphrase: bool = False,
        force: bool = False,
    ) -> PKI:
        directory = Path(directory)
        _check_trust_domain(trust_domain)
        _check_days(days)
        if isinstance(passphrase, str):
            passphrase = passphrase.encode()
        key_pem_encryption = _key_encryption(passphrase, unsafe_no_passphrase)
        if not force:
            refuse_existing_ca(directory)  # before the (slow) key generation; again under the lock
        key = generate_key(key_type)
        now = _now()
        subject = x509.Name(
            [
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG),
                x509.NameAttribute(NameOID.COMMON_NAME, f"cryptoros root CA ({trust_domain})"[:64]),
            ]
        )
        ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
        cert = (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _BACKDATE)
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(_ku(ca=True, rsa_key=False), critical=True)
            .add_extension(ski, critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski), critical=False)
            .sign(key, _sign_hash(key))
        )
        key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, key_pem_encryption)
        index = {"version": 1, "trust_domain": trust_domain, "crl_number": 1, "certificates": []}
        crl = cls._build_crl(cert, key, [], number=1, days=7)
        files = {
            "ca.crt": (cert.public_bytes(serialization.Encoding.PEM), 0o644),
            "private/ca.key": (key_pem, 0o600),
            "index.json": ((json.dumps(index, indent=2) + "\n").encode(), 0o644),
            "crl.pem": (crl.public_bytes(serialization.Encoding.PEM), 0o644),
        }
        for sub in ("private", "issued", "csr"):
            (directory / sub).mkdir(parents=True, exist_ok=True)
        os.chmod(directory / "private", 0o700)
        with pki_lock(directory):
            finish_init(directory)  # an earlier init stopped past its point of no return
            if not force:
                refuse_existing_ca(directory)
            replace_ca(directory, files)
        pki = cls(directory, passphrase=passphrase)
        pki._ca_key_cache = key
        return pki

    @classmethod
    def open(cls, directory: str | os.PathLike, *, passphrase: bytes | None = None) -> PKI:
        """Open an existing PKI. ``passphrase`` unlocks the CA key; it is only needed
        (and checked) by the operations that sign: issue, sign_csr, write_crl."""
        directory = Path(directory)
        if (directory / INIT_READY).is_dir():
            with pki_lock(directory):
                finish_init(directory)
        if not (directory / "ca.crt").is_file() or not (directory / "index.json").is_file():
            raise PKIError(f"{directory} is not a PKI directory (run 'cryptoros-certs init --dir {directory}')")
        return cls(directory, passphrase=passphrase)

    @property
    def ca_key_encrypted(self) -> bool:
        return key_is_encrypted(self.ca_key_path)

    def _ca_key(self):
        if self._ca_key_cache is None:
            key = load_private_key(self.ca_key_path, self._passphrase)
            if key.public_key().public_bytes(
                serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
            ) != self.ca_cert.public_key().public_bytes(
                serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
            ):
                raise PKIError(
                    f"{self.ca_key_path} does not belong to {self.ca_cert_path}: put back a matching pair ('init "
                    f"--force' keeps the CA it replaced as ca.crt.old and private/ca.key.old) or make a new CA "
                    f"with 'cryptoros-certs init --force --dir {self.directory}' (then issue every certificate again)"
                )
            self._ca_key_cache = key
        return self._ca_key_cache

    def unlock(self) -> None:
        """Load the CA key now (raises PKIError on a wrong passphrase)."""
        self._ca_key()

    # ---- index

    def _read_index(self) -> dict:
        try:
            index = json.loads(self.index_path.read_text())
        except FileNotFoundError as err:
            raise PKIError(f"{self.directory} is not a PKI directory (no index.json)") from err
        except (OSError, ValueError) as err:
            raise PKIError(f"cannot read {self.index_path}: {err}") from err
        return _check_index(index, self.index_path)

    def _index_bytes(self, index: dict) -> bytes:
        return (json.dumps(index, indent=2) + "\n").encode()

    @contextlib.contextmanager
    def _locked(self) -> Iterator[dict]:
        """Hold an exclusive lock on the PKI while reading and changing the index."""
        with pki_lock(self.directory):
            yield self._read_index()

    def list(self) -> list[CertRecord]:
        return [CertRecord.from_json(d) for d in self._read_index()["certificates"]]

    def find(self, name_or_serial: str | int) -> list[CertRecord]:
        """Records matching a name, or a serial (decimal, or hex with 0x / colons)."""
        records = self.list()
        if isinstance(name_or_serial, int):
            return [r for r in records if r.serial == name_or_serial]
        by_name = [r for r in records if r.name == name_or_serial]
        if by_name:
            return by_name
        serial = parse_serial(name_or_serial)
        if serial is None:
            return []
        return [r for r in records if r.serial == serial]

    def cert_path_for(self, name: str) -> Path:
        return self.directory / "issued" / f"{check_name(name)}.crt"

    def key_path_for(self, name: str) -> Path:
        return self.directory / "private" / f"{check_name(name)}.key"

    # ---- issuing

    def _build_cert(
        self,
        *,
        name: str,
        kind: str,
        public_key,
        sans: Sequence[x509.GeneralName],
        days: int,
    ) -> x509.Certificate:
        ca_key = self._ca_key()
        now = _now()
        not_after = now + dt.timedelta(days=days)
        ca_not_after = _record_time(self.ca_cert.not_valid_after_utc)
        if not_after > ca_not_after:
            not_after = ca_not_after  # a leaf never outlives its CA
        if not_after <= now:
            raise PKIError("the CA certificate has expired")
        uri = x509.UniformResourceIdentifier(identity_uri(self.trust_domain, kind, name))
        names: list[x509.GeneralName] = [uri]
        extra = list(sans)
        if not extra and _DNS_RE.match(name) and "_" not in name:
            extra = [x509.DNSName(name)]
        names += [s for s in extra if s != uri]
        subject = x509.Name(
            [
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG),
                x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, kind),
                x509.NameAttribute(NameOID.COMMON_NAME, name),
            ]
        )
        return (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(self.ca_cert.subject)
            .public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _BACKDATE)
            .not_valid_after(not_after)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(_ku(ca=False, rsa_key=isinstance(public_key, rsa.RSAPublicKey)), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(public_key), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(_ski_of(self.ca_cert)),
                critical=False,
            )
            .sign(ca_key, _sign_hash(ca_key))
        )

    def _record(self, index: dict, cert: x509.Certificate, name: str, kind: str) -> None:
        rec = CertRecord(
            serial=cert.serial_number,
            name=name,
            kind=kind,
            fingerprint_sha256=cert_fingerprint_sha256(cert),
            not_after=_record_time(cert.not_valid_after_utc),
            status="valid",
        )
        index.setdefault("certificates", []).append(rec.to_json())

    def issue(
        self,
        name: str,
        *,
        kind: str = "manager",
        sans: Iterable[str | x509.GeneralName] = (),
        key_type: str = "ec-p256",
        days: int = 365,
        passphrase: bytes | None = None,
        unsafe_no_passphrase: bool = False,
        force: bool = False,
    ) -> Issued:
        """Make a key and a certificate for ``name`` in one step."""
        check_name(name)
        _check_kind(kind)
        _check_days(days)
        san_list = parse_sans(sans)
        encryption = _key_encryption(passphrase, unsafe_no_passphrase)
        cert_path, key_path = self.cert_path_for(name), self.key_path_for(name)
        with self._locked() as index:
            fs = FileSet(force=force)
            fs.check(cert_path)
            fs.check(key_path)
            self._ca_key()  # wrong CA passphrase: fail before the (slow) key generation
            if key_type not in KEY_TYPES:
                raise PKIError(f"unknown key type {key_type!r}: choose one of {', '.join(KEY_TYPES)}")
            key = generate_key(key_type)
            cert = self._build_cert(name=name, kind=kind, public_key=key.public_key(), sans=san_list, days=days)
            self._record(index, cert, name, kind)
            key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, encryption)
            # the index first: a certificate the CA signed is always listed (revocable by
            # its serial), whatever stops this before its file is in place
            write_file(self.index_path, self._index_bytes(index), force=True)
            with fs:
                fs.add(key_path, key_pem, 0o600)
                fs.add(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
        return Issued(
            name=name,
            cert_path=cert_path,
            key_path=key_path,
            serial=cert.serial_number,
            fingerprint_sha256=cert_fingerprint_sha256(cert),
        )

    def renew(
        self,
        name: str,
        *,
        new_key: bool = True,
        key_type: str | None = None,
        days: int = 365,
        passphrase: bytes | None = None,
        unsafe_no_passphrase: bool = False,
    ) -> tuple[Issued, int]:
        """A new certificate for ``name`` with the kind and DNS/IP names of its current
        one, for a new key (of the same type unless ``key_type``) or the same public
        key (``new_key=False``: no private key is read or written). The current
        certificate stays valid: revoke it once the registry (``set-cert``) and the
        interceptor (SIGHUP) use the new one. Returns the new one and the old serial."""
        check_name(name)
        _check_days(days)
        cert_path, key_path = self.cert_path_for(name), self.key_path_for(name)
        if not cert_path.exists():
            raise PKIError(f"no certificate for {name} in {self.directory}: issue one first")
        old = load_certificate(cert_path)
        records = [r for r in self.list() if r.serial == old.serial_number]
        if not records:
            raise PKIError(f"{cert_path} (serial {old.serial_number:x}) was not issued by this CA directory")
        kind = records[0].kind
        try:
            present = old.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        except x509.ExtensionNotFound:
            present = []
        sans = [g for g in present if isinstance(g, (x509.DNSName, x509.IPAddress))]
        key_pem = None
        if new_key:
            encryption = _key_encryption(passphrase, unsafe_no_passphrase)
            key_type = key_type or _key_type_of(old.public_key())
            self._ca_key()  # wrong CA passphrase: fail before the (slow) key generation
            key = generate_key(key_type)
            public_key = key.public_key()
            key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, encryption)
        else:
            if key_type is not None or passphrase is not None or unsafe_no_passphrase:
                raise PKIError("the same key is kept: no key type or passphrase applies")
            if records[0].status == "revoked":  # the key it certifies may be in other hands
                raise PKIError(f"{cert_path} (serial {old.serial_number:x}) was revoked"
                               f"{f' ({records[0].reason})' if records[0].reason else ''}: its key is not "
                               "certified again; renew without --same-key (a new key)")
            public_key = old.public_key()
            _check_public_key(public_key)
        with self._locked() as index:
            fs = FileSet(force=True)
            cert = self._build_cert(name=name, kind=kind, public_key=public_key, sans=sans, days=days)
            self._record(index, cert, name, kind)
            write_file(self.index_path, self._index_bytes(index), force=True)  # first: as in issue
            with fs:
                if key_pem is not None:
                    fs.add(key_path, key_pem, 0o600)
                fs.add(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
        issued = Issued(name=name, cert_path=cert_path, key_path=key_path if key_pem is not None else None,
                        serial=cert.serial_number, fingerprint_sha256=cert_fingerprint_sha256(cert))
        return issued, old.serial_number

    def sign_csr(
        self,
        csr_path: str | os.PathLike,
        *,
        kind: str = "manager",
        name: str | None = None,
        sans: Iterable[str | x509.GeneralName] = (),
        days: int = 365,
        force: bool = False,
    ) -> Issued:
        """Sign a CSR made elsewhere (the paper's two-step flow).

        The name defaults to the CSR's common name. The CA decides the identity URI;
        DNS and IP names requested in the CSR are kept when ``sans`` is empty."""
        _check_kind(kind)
        _check_days(days)
        san_list = parse_sans(sans)
        csr_path = Path(csr_path)
        csr = load_csr(csr_path)
        if name is None:
            name = _csr_common_name(csr, csr_path)
        check_name(name)
        public_key = csr.public_key()
        _check_public_key(public_key)
        if not san_list:
            try:
                requested = csr.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            except x509.ExtensionNotFound:
                requested = []
            except ValueError as err:
                raise PKIError(f"CSR {csr_path} has malformed extensions") from err
            san_list = [g for g in requested if isinstance(g, (x509.DNSName, x509.IPAddress))]
        cert_path = self.cert_path_for(name)
        with self._locked() as index:
            fs = FileSet(force=force)
            fs.check(cert_path)
            cert = self._build_cert(name=name, kind=kind, public_key=public_key, sans=san_list, days=days)
            self._record(index, cert, name, kind)
            write_file(self.index_path, self._index_bytes(index), force=True)  # first: as in issue
            with fs:
                fs.add(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
            write_file(
                self.directory / "csr" / f"{name}.csr", csr.public_bytes(serialization.Encoding.PEM), force=True
            )
        return Issued(
            name=name,
            cert_path=cert_path,
            key_path=None,
            serial=cert.serial_number,
            fingerprint_sha256=cert_fingerprint_sha256(cert),
        )

    # ---- revocation

    def revoke(self, name_or_serial: str | int, *, reason: str = "unspecified", crl_days: int = 7) -> int:
        """Revoke certificates, publish a CRL listing them, and return the serial.

        A name revokes every still-valid certificate of that name (the newest serial
        is returned). The CRL is written before the index, under the same lock: a
        failure or a kill in between leaves the certificate refused (in the CRL) with
        the index still saying valid, and repeating the revoke finishes it. Revoking
        what the index calls revoked but the CRL lacks (an earlier failure) re-signs
        the CRL; what both already list raises PKIError."""
        if reason not in REASONS:
            raise PKIError(f"unknown reason {reason!r}: choose one of {', '.join(REASONS)}")
        _check_days(crl_days)
        ca_key = self._ca_key()
        with self._locked() as index:
            targets = self._targets(index, name_or_serial)
            live = [r for r in targets if r.status != "revoked"]
            if not live:
                listed = self._crl_entries()
                unpublished = [r for r in targets if listed is None or r.serial not in listed]
                if not unpublished:
                    raise PKIError(f"{name_or_serial!r} is already revoked")
                self._publish(index, ca_key, days=crl_days)
                return unpublished[-1].serial
            now = _now()
            serials = {r.serial for r in live}
            for d in index["certificates"]:
                if int(d["serial"]) in serials:
                    d["status"] = "revoked"
                    d["revoked_at"] = now.isoformat()
                    d["reason"] = reason
            self._publish(index, ca_key, days=crl_days)
        return live[-1].serial

    @staticmethod
    def _targets(index: dict, name_or_serial: str | int) -> list[CertRecord]:
        records = [CertRecord.from_json(d) for d in index["certificates"]]
        if isinstance(name_or_serial, int):
            targets = [r for r in records if r.serial == name_or_serial]
        else:
            targets = [r for r in records if r.name == name_or_serial]
            if not targets:
                serial = parse_serial(name_or_serial)
                targets = [r for r in records if serial is not None and r.serial == serial]
        if not targets:
            raise PKIError(f"no certificate with name or serial {name_or_serial!r}")
        return targets

    @staticmethod
    def _build_crl(ca_cert, ca_key, records: Sequence[CertRecord], *, number: int, days: int):
        now = _now()
        builder = (
            x509.CertificateRevocationListBuilder()
            .issuer_name(ca_cert.subject)
            .last_update(now - _BACKDATE)
            .next_update(now + dt.timedelta(days=days))
            .add_extension(x509.CRLNumber(number), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(_ski_of(ca_cert)), critical=False
            )
        )
        for rec in records:
            entry = (
                x509.RevokedCertificateBuilder()
                .serial_number(rec.serial)
                .revocation_date(rec.revoked_at or now)
            )
            if rec.reason and rec.reason != "unspecified":
                entry = entry.add_extension(x509.CRLReason(x509.ReasonFlags[rec.reason]), critical=False)
            builder = builder.add_revoked_certificate(entry.build())
        return builder.sign(ca_key, _sign_hash(ca_key))

    def write_crl(self, *, days: int = 7) -> Path:
        """Sign and write ``crl.pem`` listing every revoked certificate."""
        _check_days(days)
        ca_key = self._ca_key()
        with self._locked() as index:
            self._publish(index, ca_key, days=days)
        return self.crl_path

    def _crl_entries(self) -> dict[int, x509.RevokedCertificate] | None:
        """The entries of ``crl.pem`` by serial, or None when it is missing, unreadable
        or not signed by this CA (then it revokes nothing an interceptor would apply)."""
        try:
            crl = load_crl(self.crl_path)
        except (PKIError, OSError, ValueError):
            return None
        if crl.issuer != self.ca_cert.subject or not crl.is_signature_valid(self.ca_cert.public_key()):
            return None
        return {entry.serial_number: entry for entry in crl}

    def _publish(self, index: dict, ca_key, *, days: int) -> None:
        """Sign a CRL of every revoked record and write it, then the index (under the
        caller's lock). A serial the current CRL lists that the index calls valid is a
        revoke stopped between the two writes: it is recorded revoked, never dropped."""
        listed = self._crl_entries() or {}
        for d in index["certificates"]:
            entry = listed.get(int(d["serial"]))
            if entry is not None and d.get("status") != "revoked":
                d["status"] = "revoked"
                d["revoked_at"] = _record_time(entry.revocation_date_utc).isoformat()
                d["reason"] = _entry_reason(entry)
        number = int(index.get("crl_number", 0)) + 1
        revoked = [r for r in (CertRecord.from_json(d) for d in index["certificates"]) if r.status == "revoked"]
        crl = self._build_crl(self.ca_cert, ca_key, revoked, number=number, days=days)
        index["crl_number"] = number
        # the CRL first: a failure before the index is written leaves a certificate refused
        write_file(self.crl_path, crl.public_bytes(serialization.Encoding.PEM), force=True)
        write_file(self.index_path, self._index_bytes(index), force=True)

    def crl_disagreements(self) -> list[str]:
        """What the index and ``crl.pem`` disagree about, one line each naming the fix
        (a cheap check for ``list`` and ``verify``; nothing is changed)."""
        records = self.list()
        listed = self._crl_entries()
        fix = f"cryptoros-certs crl --dir {self.directory}"
        if listed is None:
            return [f"{self.crl_path} is missing, unreadable or not signed by {self.ca_cert_path}, so no "
                    f"revocation is applied: run '{fix}'"]
        out = []
        for r in records:
            if r.status == "revoked" and r.serial not in listed:
                out.append(f"serial {r.serial:x} ({r.name}) is revoked in {self.index_path} but not in "
                           f"{self.crl_path}, so it is still accepted: run '{fix}'")
            elif r.status != "revoked" and r.serial in listed:
                out.append(f"serial {r.serial:x} ({r.name}) is in {self.crl_path} but valid in {self.index_path} "
                           f"(a revoke that stopped half-way): run 'cryptoros-certs revoke 0x{r.serial:x} "
                           f"--dir {self.directory}' to finish it")
        return out

    # ---- verification

    def verify(self, cert_or_path: x509.Certificate | str | os.PathLike, *, at: dt.datetime | None = None) -> x509.Certificate:
        """Check a certificate against this CA and its CRL; PKIError says why it fails."""
        cert = cert_or_path if isinstance(cert_or_path, x509.Certificate) else load_certificate(cert_or_path)
        verify_certificate(cert, self.ca_cert, crl=load_crl(self.crl_path) if self.crl_path.exists() else None, at=at)
        return cert


def parse_serial(text: str) -> int | None:
    """A serial as decimal, ``0x``-hex or colon-separated hex; None if it is neither."""
    t = text.strip()
    try:
        if t.lower().startswith("0x"):
            return int(t[2:], 16)
        if ":" in t:
            return int(t.replace(":", ""), 16)
        if t.isdigit():
            return int(t)
        if re.fullmatch(r"[0-9A-Fa-f]{16,}", t):
            return int(t, 16)
    except ValueError:
        return None
    return None


def verify_certificate(
    cert: x509.Certificate,
    ca_cert: x509.Certificate,
    *,
    crl: x509.CertificateRevocationList | None = None,
    at: dt.datetime | None = None,
) -> None:
    """Verify issuer, signature, validity, leaf profile and revocation; PKIError if not."""
    at = at or _now()
    if cert.issuer != ca_cert.subject:
        raise PKIError("not issued by this CA (issuer name differs)")
    try:
        cert.verify_directly_issued_by(ca_cert)
    except (ValueError, TypeError, InvalidSignature) as err:
        raise PKIError("not issued by this CA (bad signature)") from err
    if at < _record_time(cert.not_valid_before_utc):
        raise PKIError("certificate is not yet valid")
    if at > _record_time(cert.not_valid_after_utc):
        raise PKIError("certificate has expired")
    if at > _record_time(ca_cert.not_valid_after_utc):
        raise PKIError("CA certificate has expired")
    try:
        bc = cert.extensions.get_extension_for_class(x509.BasicConstraints).value
        if bc.ca:
            raise PKIError("certificate is a CA certificate, not an end-entity one")
    except x509.ExtensionNotFound:
        pass
    if crl is not None:
        if crl.issuer != ca_cert.subject or not crl.is_signature_valid(ca_cert.public_key()):
            raise PKIError("the CRL is not signed by this CA")
        next_update = crl.next_update_utc
        if next_update is not None and at > _record_time(next_update):
            raise PKIError("the CRL is out of date (run 'cryptoros-certs crl')")
        entry = crl.get_revoked_certificate_by_serial_number(cert.serial_number)
        if entry is not None:
            raise PKIError(f"certificate is revoked (since {entry.revocation_date_utc.isoformat()})")


# --------------------------------------------------------------------------- two-step flow


def request(
    name: str,
    out_dir: str | os.PathLike,
    *,
    key_type: str = "ec-p256",
    passphrase: bytes | None = None,
    unsafe_no_passphrase: bool = False,
    sans: Iterable[str | x509.GeneralName] = (),
    force: bool = False,
) -> tuple[Path, Path]:
    """Make a key and a CSR on the robot; returns ``(key_path, csr_path)``."""
    check_name(name)
    san_list = parse_sans(sans)
    encryption = _key_encryption(passphrase, unsafe_no_passphrase)
    out_dir = Path(out_dir)
    key_path, csr_path = out_dir / f"{name}.key", out_dir / f"{name}.csr"
    fs = FileSet(force=force)
    fs.check(key_path)
    fs.check(csr_path)
    key = generate_key(key_type)
    builder = x509.CertificateSigningRequestBuilder().subject_name(
        x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG), x509.NameAttribute(NameOID.COMMON_NAME, name)])
    )
    if san_list:
        builder = builder.add_extension(x509.SubjectAlternativeName(san_list), critical=False)
    csr = builder.sign(key, hashes.SHA256())
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, encryption)
    with fs:
        fs.add(key_path, key_pem, 0o600)
        fs.add(csr_path, csr.public_bytes(serialization.Encoding.PEM), 0o644)
    return key_path, csr_path


__all__ = [
    "KEY_TYPES",
    "KINDS",
    "REASONS",
    "PKI",
    "Issued",
    "CertRecord",
    "request",
    "load_private_key",
    "load_certificate",
    "load_csr",
    "load_crl",
    "key_is_encrypted",
    "cert_fingerprint_sha256",
    "manager_identity_uri",
    "identity_uri",
    "parse_san",
    "parse_sans",
    "parse_serial",
    "verify_certificate",
    "check_name",
]
