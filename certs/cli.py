"""``cryptoros-certs``: provision the certificates of a cryptoros deployment.

One-step flow on the CA host::

    cryptoros-certs init --dir pki
    cryptoros-certs issue mng1 --dir pki --kind manager
    cryptoros-certs issue icp1 --dir pki --kind interceptor --san IP:127.0.0.2

The paper's two-step flow (key and CSR made on the robot, signed on the CA host)::

    cryptoros-certs request mng1 --out-dir .          # on the robot
    cryptoros-certs sign mng1.csr --dir pki           # on the CA host

Passphrases for new keys come from ``--passphrase-file``, ``$CRYPTOROS_PASSPHRASE`` or a
prompt; the CA key's from ``--ca-passphrase-file``, ``$CRYPTOROS_CA_PASSPHRASE`` or a
prompt. Bad input gives one line on stderr and exit status 2; ``verify`` exits 1 when a
certificate is refused.
"""

from __future__ import annotations

import datetime as dt
import json
import sys
from pathlib import Path

import click
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed448, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID

from cryptoros import passphrase as passphrases
from cryptoros.errors import CryptorosError, PKIError

from . import pki as pkimod
from .pki import KEY_TYPES, KINDS, PKI, REASONS

#: the longest validity asked of a certificate, a CA or a CRL (100 years): a larger one
#: is past the dates the encodings hold (an OverflowError traceback, CLI audit)
MAX_DAYS = 36_500

PROG = "cryptoros-certs"
ENV_PASSPHRASE = "CRYPTOROS_PASSPHRASE"
ENV_CA_PASSPHRASE = "CRYPTOROS_CA_PASSPHRASE"
ENV_DIR = "CRYPTOROS_PKI_DIR"


class BadInput(click.ClickException, CryptorosError):
    """Bad input from the user: one line on stderr, exit status 2."""

    exit_code = 2


class Refused(click.ClickException, CryptorosError):
    """``verify`` refused a certificate: exit status 1."""

    exit_code = 1


# --------------------------------------------------------------------------- passphrases


def _read_passphrase(path: str | None, env: str) -> bytes | None:
    """:func:`cryptoros.passphrase.read_passphrase` (the one rule), as a usage error."""
    try:
        return passphrases.read_passphrase(path, env)
    except passphrases.PassphraseError as err:
        raise BadInput(str(err)) from err


def _prompt(label: str, *, confirm: bool) -> bytes:
    """Prompt on the terminal without echo; read plain lines when stdin is not a tty
    (so scripts and tests can pipe the passphrase in)."""
    if sys.stdin is not None and sys.stdin.isatty():
        try:
            value = click.prompt(label, hide_input=True, confirmation_prompt=confirm, err=True)
        except click.Abort as err:
            raise BadInput("no passphrase given") from err
        return value.encode()

    def line() -> bytes:
        click.echo(f"{label}: ", err=True, nl=False)
        text = sys.stdin.readline() if sys.stdin is not None else ""
        if not text:
            click.echo("", err=True)  # end the prompt line: the error gets a line of its own
            raise BadInput(
                f"no passphrase: use --passphrase-file, set ${ENV_PASSPHRASE}/${ENV_CA_PASSPHRASE}, or run interactively"
            )
        click.echo("", err=True)
        return text.rstrip("\r\n").encode()

    value = line()
    if confirm:
        label = f"Repeat for confirmation ({label.lower()})"
        if line() != value:
            raise BadInput("the two passphrases do not match")
    if not value:
        raise BadInput("the passphrase is empty")
    return value


def new_key_passphrase(passphrase_file: str | None, unsafe_no_passphrase: bool, what: str) -> bytes | None:
    if unsafe_no_passphrase:
        if passphrase_file:
            raise BadInput("--passphrase-file and --unsafe-no-passphrase exclude each other")
        return None
    value = _read_passphrase(passphrase_file, ENV_PASSPHRASE)
    if value is not None:
        return value
    return _prompt(f"Passphrase for the new {what} key", confirm=True)


def ca_passphrase(pki: PKI, ca_passphrase_file: str | None) -> bytes | None:
    if ca_passphrase_file:
        return _read_passphrase(ca_passphrase_file, ENV_CA_PASSPHRASE)
    if not pki.ca_key_path.exists():
        raise BadInput(f"{pki.ca_key_path} is missing: this PKI directory cannot sign")
    if not pki.ca_key_encrypted:
        return None
    value = _read_passphrase(None, ENV_CA_PASSPHRASE)
    if value is not None:
        return value
    return _prompt("CA key passphrase", confirm=False)


def open_for_signing(directory: str, ca_passphrase_file: str | None) -> PKI:
    pki = PKI.open(directory)
    pki = PKI.open(directory, passphrase=ca_passphrase(pki, ca_passphrase_file))
    pki.unlock()  # a wrong CA passphrase fails here, before anything is written
    return pki


# --------------------------------------------------------------------------- options


def dir_option(f):
    return click.option(
        "--dir",
        "directory",
        envvar=ENV_DIR,
        default="pki",
        show_default=True,
        type=click.Path(file_okay=False),
        help=f"PKI directory (or ${ENV_DIR}).",
    )(f)


def ca_pass_option(f):
    return click.option(
        "--ca-passphrase-file",
        type=click.Path(dir_okay=False),
        help=f"File holding the CA key passphrase (one trailing newline dropped) (else ${ENV_CA_PASSPHRASE}, else a prompt).",
    )(f)


def new_pass_options(f):
    f = click.option(
        "--unsafe-no-passphrase",
        is_flag=True,
        help="Write the new private key unencrypted (throwaway setups only).",
    )(f)
    return click.option(
        "--passphrase-file",
        type=click.Path(dir_okay=False),
        help=f"File holding the new key's passphrase (one trailing newline dropped) (else ${ENV_PASSPHRASE}, else a prompt).",
    )(f)


def san_option(f):
    return click.option(
        "--san",
        "sans",
        multiple=True,
        metavar="TYPE:VALUE",
        help="Subject alternative name, repeatable: DNS:host, IP:127.0.0.2, URI:scheme://...",
    )(f)


key_type_option = click.option(
    "--key-type", type=click.Choice(KEY_TYPES), default="ec-p256", show_default=True, help="Key algorithm."
)
kind_option = click.option(
    "--kind",
    type=click.Choice(KINDS),
    default="manager",
    show_default=True,
    help="What the certificate is for (server = authorization server).",
)
force_option = click.option("--force", is_flag=True, help="Overwrite existing files.")


def _sans(sans: tuple[str, ...]) -> list[x509.GeneralName]:
    return pkimod.parse_sans(sans)  # PKIError on bad syntax -> one line, exit 2


# --------------------------------------------------------------------------- commands


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="cryptoros", prog_name=PROG)
def cli() -> None:
    """Certificate provisioning for cryptoros: root CA, keys, CSRs, CRL."""


@cli.command()
@dir_option
@click.option("--trust-domain", default="cryptoros.local", show_default=True, help="Trust domain of the identity URIs.")
@key_type_option
@click.option("--days", type=click.IntRange(min=1, max=MAX_DAYS), default=3650, show_default=True, help="CA validity.")
@new_pass_options
@force_option
def init(directory, trust_domain, key_type, days, passphrase_file, unsafe_no_passphrase, force):
    """Create a root CA (and an empty CRL) in --dir."""
    pkimod._check_trust_domain(trust_domain)
    if not force:
        for p in (Path(directory) / "ca.crt", Path(directory) / "private" / "ca.key", Path(directory) / "index.json"):
            if p.exists():
                raise BadInput(f"{p} exists: use --force to overwrite")
    passphrase = new_key_passphrase(passphrase_file, unsafe_no_passphrase, "CA")
    pki = PKI.init(
        directory,
        trust_domain=trust_domain,
        key_type=key_type,
        days=days,
        passphrase=passphrase,
        unsafe_no_passphrase=unsafe_no_passphrase,
        force=force,
    )
    click.echo(f"CA certificate: {pki.ca_cert_path}")
    click.echo(f"CA key:         {pki.ca_key_path}{'' if passphrase else ' (UNENCRYPTED)'}")
    click.echo(f"CRL:            {pki.crl_path}")
    click.echo(f"SHA-256:        {pkimod.cert_fingerprint_sha256(pki.ca_cert)}")


@cli.command()
@click.argument("name")
@dir_option
@kind_option
@san_option
@key_type_option
@click.option("--days", type=click.IntRange(min=1, max=MAX_DAYS), default=365, show_default=True, help="Validity.")
@new_pass_options
@ca_pass_option
@force_option
def issue(name, directory, kind, sans, key_type, days, passphrase_file, unsafe_no_passphrase, ca_passphrase_file, force):
    """Make a key and a certificate for NAME in one step."""
    pkimod.check_name(name)
    san_list = _sans(sans)
    pki = PKI.open(directory)
    if not force:
        for p in (pki.cert_path_for(name), pki.key_path_for(name)):
            if p.exists():
                raise BadInput(f"{p} exists: use --force to overwrite")
    pki = open_for_signing(directory, ca_passphrase_file)
    passphrase = new_key_passphrase(passphrase_file, unsafe_no_passphrase, name)
    out = pki.issue(
        name,
        kind=kind,
        sans=san_list,
        key_type=key_type,
        days=days,
        passphrase=passphrase,
        unsafe_no_passphrase=unsafe_no_passphrase,
        force=force,
    )
    _print_issued(out, encrypted=passphrase is not None, days=days)


@cli.command()
@click.argument("name")
@dir_option
@click.option("--same-key", is_flag=True, help="Keep the current key pair: only the certificate is new.")
@click.option("--key-type", type=click.Choice(KEY_TYPES), default=None,
              help="Type of the new key (default: the type of the current one).")
@click.option("--days", type=click.IntRange(min=1, max=MAX_DAYS), default=365, show_default=True, help="Validity.")
@new_pass_options
@ca_pass_option
def renew(name, directory, same_key, key_type, days, passphrase_file, unsafe_no_passphrase, ca_passphrase_file):
    """A new certificate for NAME with the kind and DNS/IP names of its current one.

    A new key by default (--same-key keeps it). The current certificate stays valid, so
    the robot keeps running: bind the registry to the new one (cryptoros-authz set-cert),
    send the interceptor SIGHUP, then revoke the old serial; the lines printed say how."""
    pkimod.check_name(name)
    pki = PKI.open(directory)
    if not pki.cert_path_for(name).exists():
        raise BadInput(f"no certificate for {name!r} in {directory}: issue one first")
    pki = open_for_signing(directory, ca_passphrase_file)
    if same_key:
        if key_type or passphrase_file or unsafe_no_passphrase:
            raise BadInput("--same-key keeps the key: --key-type and passphrase options do not apply")
        passphrase = None
    else:
        passphrase = new_key_passphrase(passphrase_file, unsafe_no_passphrase, name)
    out, old_serial = pki.renew(name, new_key=not same_key, key_type=key_type, days=days, passphrase=passphrase,
                                unsafe_no_passphrase=unsafe_no_passphrase and not same_key)
    _print_issued(out, encrypted=passphrase is not None if not same_key else None, days=days)
    if any(r.serial == old_serial and r.status == "revoked" for r in pki.list()):
        click.echo(f"previous:    serial {old_serial:x} (revoked)")
        click.echo("next:        cryptoros-authz set-cert " + f"{name} --fingerprint {out.fingerprint_sha256}")
        click.echo("             then SIGHUP the interceptor using it (it reloads the new files)")
        return
    click.echo(f"previous:    serial {old_serial:x} (still valid)")
    click.echo("next:        cryptoros-authz set-cert " + f"{name} --fingerprint {out.fingerprint_sha256} --overlap 600")
    click.echo("             then SIGHUP the interceptor using it (it reloads the new files), then")
    click.echo(f"             cryptoros-certs revoke {name} --serial {old_serial:x} --dir {directory}")


def _print_issued(out: pkimod.Issued, *, encrypted: bool | None, days: int) -> None:
    click.echo(f"certificate: {out.cert_path}")
    if out.key_path is not None:
        click.echo(f"key:         {out.key_path}{'' if encrypted else ' (UNENCRYPTED)'}")
    click.echo(f"serial:      {out.serial:x}")
    click.echo(f"SHA-256:     {out.fingerprint_sha256}")
    until = pkimod.load_certificate(out.cert_path).not_valid_after_utc
    asked = dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=days)
    if until < asked - dt.timedelta(hours=1):  # a leaf never outlives its CA
        click.echo(f"valid until: {until:%Y-%m-%d %H:%M} UTC, not {days} days: the CA itself ends then (renew the CA "
                   "before it, or every certificate it issued stops working)", err=True)
    else:
        click.echo(f"valid until: {until:%Y-%m-%d %H:%M} UTC")


@cli.command()
@click.argument("name")
@click.option(
    "--out-dir", type=click.Path(file_okay=False), default=".", show_default=True, help="Where NAME.key and NAME.csr go."
)
@san_option
@key_type_option
@new_pass_options
@force_option
def request(name, out_dir, sans, key_type, passphrase_file, unsafe_no_passphrase, force):
    """Make a key and a CSR for NAME (on the robot; sign the CSR on the CA host)."""
    pkimod.check_name(name)
    san_list = _sans(sans)
    if not force:
        for p in (Path(out_dir) / f"{name}.key", Path(out_dir) / f"{name}.csr"):
            if p.exists():
                raise BadInput(f"{p} exists: use --force to overwrite")
    passphrase = new_key_passphrase(passphrase_file, unsafe_no_passphrase, name)
    key_path, csr_path = pkimod.request(
        name,
        out_dir,
        key_type=key_type,
        passphrase=passphrase,
        unsafe_no_passphrase=unsafe_no_passphrase,
        sans=san_list,
        force=force,
    )
    click.echo(f"key: {key_path}{'' if passphrase else ' (UNENCRYPTED)'}")
    click.echo(f"CSR: {csr_path}")


@cli.command()
@click.argument("csr", type=click.Path(dir_okay=False))
@dir_option
@kind_option
@click.option("--name", help="Name of the certificate (default: the CSR's common name).")
@san_option
@click.option("--days", type=click.IntRange(min=1, max=MAX_DAYS), default=365, show_default=True, help="Validity.")
@ca_pass_option
@force_option
def sign(csr, directory, kind, name, sans, days, ca_passphrase_file, force):
    """Sign a CSR (ours, or one made by 'openssl req -new')."""
    san_list = _sans(sans)
    pkimod.load_csr(csr)  # not a CSR: fail before asking for a passphrase
    if name is not None:
        pkimod.check_name(name)
    pki = open_for_signing(directory, ca_passphrase_file)
    out = pki.sign_csr(csr, kind=kind, name=name, sans=san_list, days=days, force=force)
    _print_issued(out, encrypted=None, days=days)


@cli.command()
@click.argument("name_or_serial")
@dir_option
@click.option("--reason", type=click.Choice(REASONS), default="unspecified", show_default=True)
@click.option("--crl-days", type=click.IntRange(min=1, max=MAX_DAYS), default=7, show_default=True,
              help="Validity of the new CRL.")
@click.option("--serial", "pick", help="With a NAME that has several valid certificates: revoke only this serial.")
@click.option("--all", "all_", is_flag=True, help="With a NAME that has several valid certificates: revoke every one.")
@ca_pass_option
def revoke(name_or_serial, directory, reason, crl_days, pick, all_, ca_passphrase_file):
    """Revoke a certificate by NAME or SERIAL and publish a new CRL.

    A NAME with several valid certificates (a renewal in progress, say) is refused
    unless --serial picks one or --all says every one: revoking the one in use by
    mistake cuts a robot off."""
    pki = PKI.open(directory)
    found = pki.find(name_or_serial)
    if not found:
        raise BadInput(f"no certificate with name or serial {name_or_serial!r} in {directory}")
    live = [r for r in found if r.status != "revoked"]
    targets: list[int | str] = [name_or_serial]
    if pick is not None:
        serial = pkimod.parse_serial(pick)
        chosen = [r for r in live if r.serial == serial]
        if not chosen:
            raise BadInput(f"{name_or_serial!r} has no valid certificate with serial {pick}")
        targets = [chosen[0].serial]
    elif len(live) > 1:
        if not all_:
            serials = ", ".join(f"{r.serial:x}" for r in live)
            raise BadInput(f"{name_or_serial!r} has {len(live)} valid certificates (serials {serials}): "
                           "give --serial SERIAL for one, or --all for every one")
        targets = [r.serial for r in live]
    pki = open_for_signing(directory, ca_passphrase_file)
    serials = [pki.revoke(t, reason=reason, crl_days=crl_days) for t in targets]
    for serial in serials:
        if live:
            click.echo(f"revoked serial {serial:x}")
        else:  # PKI.revoke refuses what the CRL lists already: this one it lacked
            click.echo(f"serial {serial:x} was revoked in {pki.index_path} but missing from {pki.crl_path} "
                       "(an earlier revoke failed half-way): CRL re-signed with it")
    click.echo(f"CRL: {pki.crl_path}")


@cli.command()
@dir_option
@click.option("--days", type=click.IntRange(min=1, max=MAX_DAYS), default=7, show_default=True, help="Validity of the CRL.")
@ca_pass_option
def crl(directory, days, ca_passphrase_file):
    """Sign a fresh CRL listing every revoked certificate."""
    pki = open_for_signing(directory, ca_passphrase_file)
    path = pki.write_crl(days=days)
    c = pkimod.load_crl(path)
    click.echo(f"CRL: {path}")
    click.echo(f"revoked: {len(list(c))}  next update: {c.next_update_utc.isoformat() if c.next_update_utc else '-'}")


@cli.command(name="list")
@dir_option
@click.option("--json", "as_json", is_flag=True, help="Print JSON records.")
def list_(directory, as_json):
    """List every certificate this CA issued."""
    pki = PKI.open(directory)
    records = pki.list()
    _warn_disagreements(pki)
    if as_json:
        click.echo(json.dumps([r.to_json() for r in records], indent=2))
        return
    if not records:
        click.echo("no certificates issued")
        return
    rows = [("SERIAL", "NAME", "KIND", "STATUS", "NOT AFTER", "SHA-256")]
    for r in records:
        status = r.status if r.status == "revoked" or not r.expired else "expired"
        rows.append((f"{r.serial:x}", r.name, r.kind, status, r.not_after.strftime("%Y-%m-%d"), r.fingerprint_sha256[:16]))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        click.echo("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())


@cli.command()
@click.argument("target")
@dir_option
@click.option("--pem", is_flag=True, help="Also print the PEM certificate.")
def show(target, directory, pem):
    """Print a certificate readably: TARGET is a name in --dir, 'ca', or a file."""
    path = _resolve_cert(target, directory)
    cert = pkimod.load_certificate(path)
    click.echo(describe(cert), nl=False)
    if Path(directory, "index.json").exists():
        rec = next((r for r in PKI.open(directory).list() if r.serial == cert.serial_number), None)
        if rec is not None:
            extra = f" since {rec.revoked_at.isoformat()} ({rec.reason})" if rec.status == "revoked" else ""
            click.echo(f"    Status: {rec.status}{extra}")
    if pem:
        click.echo(cert.public_bytes(serialization.Encoding.PEM).decode(), nl=False)


def _warn_disagreements(pki: PKI) -> None:
    """One stderr line per disagreement of the index and the CRL, each naming its fix."""
    for line in pki.crl_disagreements():
        click.echo(f"{PROG}: warning: {line}", err=True)


def _resolve_cert(target: str, directory: str) -> Path:
    p = Path(target)
    if p.is_file():
        return p
    if target == "ca":
        return Path(directory) / "ca.crt"
    if pkimod._NAME_RE.match(target):
        candidate = Path(directory) / "issued" / f"{target}.crt"
        if candidate.is_file():
            return candidate
        if candidate.exists() or candidate.is_symlink():
            what = ("a directory" if candidate.is_dir() else
                    "a dangling link" if not candidate.exists() else "not a regular file")
            raise BadInput(f"{candidate} is {what}, not a certificate: move it away and issue {target!r} again")
    raise BadInput(f"no certificate named {target!r} in {directory} and no such file")


@cli.command()
@click.argument("cert")
@dir_option
@click.option("--ca-file", type=click.Path(dir_okay=False), help="CA certificate (default: ca.crt of --dir).")
@click.option("--crl-file", type=click.Path(dir_okay=False), help="CRL (default: crl.pem of --dir; none with --ca-file).")
def verify(cert, directory, ca_file, crl_file):
    """Check CERT (a file or a name) against the CA and its CRL. Exit 1 if refused."""
    path = _resolve_cert(cert, directory)
    certificate = pkimod.load_certificate(path)
    if ca_file is None:
        ca_file = str(Path(directory) / "ca.crt")
        if crl_file is None and (Path(directory) / "crl.pem").exists():
            crl_file = str(Path(directory) / "crl.pem")
        if crl_file is not None and Path(directory, "index.json").exists():
            _warn_disagreements(PKI.open(directory))
    ca = pkimod.load_certificate(ca_file)
    crl_obj = pkimod.load_crl(crl_file) if crl_file else None
    try:
        pkimod.verify_certificate(certificate, ca, crl=crl_obj)
    except PKIError as err:
        raise Refused(f"{path}: verification failed: {err}") from err
    click.echo(f"{path}: OK{' (CRL checked)' if crl_obj is not None else ''}")


# --------------------------------------------------------------------------- show


_EKU_NAMES = {
    ExtendedKeyUsageOID.SERVER_AUTH: "TLS Web Server Authentication",
    ExtendedKeyUsageOID.CLIENT_AUTH: "TLS Web Client Authentication",
}
_KU_FIELDS = [
    ("digital_signature", "Digital Signature"),
    ("content_commitment", "Non Repudiation"),
    ("key_encipherment", "Key Encipherment"),
    ("data_encipherment", "Data Encipherment"),
    ("key_agreement", "Key Agreement"),
    ("key_cert_sign", "Certificate Sign"),
    ("crl_sign", "CRL Sign"),
]


def _hex(data: bytes) -> str:
    return ":".join(f"{b:02X}" for b in data)


def _name(name: x509.Name) -> str:
    return ", ".join(f"{a.rfc4514_attribute_name} = {a.value}" for a in name)


def _general_name(g: x509.GeneralName) -> str:
    if isinstance(g, x509.DNSName):
        return f"DNS:{g.value}"
    if isinstance(g, x509.IPAddress):
        return f"IP Address:{g.value}"
    if isinstance(g, x509.UniformResourceIdentifier):
        return f"URI:{g.value}"
    if isinstance(g, x509.RFC822Name):
        return f"email:{g.value}"
    return str(g)


def _ext_lines(ext: x509.Extension) -> tuple[str, list[str]]:
    v = ext.value
    if isinstance(v, x509.BasicConstraints):
        body = f"CA:{'TRUE' if v.ca else 'FALSE'}" + (f", pathlen:{v.path_length}" if v.path_length is not None else "")
        return "X509v3 Basic Constraints", [body]
    if isinstance(v, x509.KeyUsage):
        names = [label for attr, label in _KU_FIELDS if getattr(v, attr)]
        return "X509v3 Key Usage", [", ".join(names)]
    if isinstance(v, x509.ExtendedKeyUsage):
        return "X509v3 Extended Key Usage", [", ".join(_EKU_NAMES.get(o, o.dotted_string) for o in v)]
    if isinstance(v, x509.SubjectAlternativeName):
        return "X509v3 Subject Alternative Name", [", ".join(_general_name(g) for g in v)]
    if isinstance(v, x509.SubjectKeyIdentifier):
        return "X509v3 Subject Key Identifier", [_hex(v.digest)]
    if isinstance(v, x509.AuthorityKeyIdentifier):
        return "X509v3 Authority Key Identifier", [_hex(v.key_identifier) if v.key_identifier else "-"]
    return ext.oid._name if ext.oid._name != "Unknown OID" else ext.oid.dotted_string, [repr(v)]


def _key_lines(key) -> list[str]:
    if isinstance(key, rsa.RSAPublicKey):
        return ["Public Key Algorithm: rsaEncryption", f"    Public-Key: ({key.key_size} bit)"]
    if isinstance(key, ec.EllipticCurvePublicKey):
        nist = {"secp256r1": "P-256", "secp384r1": "P-384", "secp521r1": "P-521"}.get(key.curve.name, "")
        return [
            "Public Key Algorithm: id-ecPublicKey",
            f"    Public-Key: ({key.key_size} bit)",
            f"    ASN1 OID: {key.curve.name}" + (f"  NIST CURVE: {nist}" if nist else ""),
        ]
    if isinstance(key, (ed25519.Ed25519PublicKey, ed448.Ed448PublicKey)):
        return [f"Public Key Algorithm: {type(key).__name__.removesuffix('PublicKey')}"]
    return [f"Public Key Algorithm: {type(key).__name__}"]


def _time(t: dt.datetime) -> str:
    return t.strftime("%b %d %H:%M:%S %Y GMT")


def describe(cert: x509.Certificate) -> str:
    """A readable text form of a certificate, laid out like ``openssl x509 -text``."""
    serial_hex = f"{cert.serial_number:x}"
    serial_hex = serial_hex if len(serial_hex) % 2 == 0 else "0" + serial_hex
    lines = [
        "Certificate:",
        "    Data:",
        f"        Version: {cert.version.value + 1} (0x{cert.version.value:x})",
        "        Serial Number:",
        f"            {':'.join(serial_hex[i:i + 2] for i in range(0, len(serial_hex), 2))}",
        f"        Signature Algorithm: {cert.signature_algorithm_oid._name}",
        f"        Issuer: {_name(cert.issuer)}",
        "        Validity",
        f"            Not Before: {_time(cert.not_valid_before_utc)}",
        f"            Not After : {_time(cert.not_valid_after_utc)}",
        f"        Subject: {_name(cert.subject)}",
        "        Subject Public Key Info:",
        *[f"            {line}" for line in _key_lines(cert.public_key())],
        "        X509v3 extensions:",
    ]
    for ext in cert.extensions:
        title, body = _ext_lines(ext)
        lines.append(f"            {title}:{' critical' if ext.critical else ''}")
        lines += [f"                {b}" for b in body]
    lines.append(f"    SHA256 Fingerprint: {_hex(bytes.fromhex(pkimod.cert_fingerprint_sha256(cert)))}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- entry point


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def main(argv: list[str] | None = None) -> None:
    """Console script: one-line errors on stderr, exit 2 on bad input, never a traceback."""
    try:
        rv = cli.main(args=argv, prog_name=PROG, standalone_mode=False)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    except click.Abort:
        click.echo(f"{PROG}: error: aborted", err=True)
        sys.exit(2)
    except click.UsageError as e:
        click.echo(f"{PROG}: error: {_one_line(e.format_message())} (see '{PROG} --help')", err=True)
        sys.exit(2)
    except click.ClickException as e:
        click.echo(f"{PROG}: error: {_one_line(e.format_message())}", err=True)
        sys.exit(e.exit_code)
    except PKIError as e:
        click.echo(f"{PROG}: error: {_one_line(str(e))}", err=True)
        sys.exit(2)
    except OSError as e:
        where = f" {e.filename}" if e.filename else ""
        click.echo(f"{PROG}: error:{where} {_one_line(e.strerror or str(e))}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo(f"{PROG}: error: interrupted", err=True)
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":  # pragma: no cover
    main()
