"""Throwaway PKI fixtures, loaded by tests/conftest.py as a pytest plugin.

``pki`` is a fresh CA per test (ec-p256, unencrypted keys: tests only), ``other_pki``
an unrelated second CA for "certificate of another CA" tests::

    def test_x(pki, other_pki):
        mng = pki.issue("mng1")                       # manager, SANs IP:127.0.0.1 + DNS:localhost
        icp = pki.issue("icp1", kind="interceptor", sans=("IP:127.0.0.2",))
        crl = pki.revoke("mng1")                      # revoked and crl.pem rewritten
        bad = other_pki.issue("mng1")                 # same name, wrong CA
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from certs.pki import PKI, Issued


class TestPKIFactory:
    """A throwaway CA for tests. Keys it issues are not encrypted."""

    __test__ = False  # not a test class

    def __init__(self, directory: Path, *, trust_domain: str = "cryptoros.local", pki: PKI | None = None) -> None:
        self.pki: PKI = pki or PKI.init(directory, trust_domain=trust_domain, unsafe_no_passphrase=True)
        self.directory: Path = self.pki.directory
        self.ca_cert: Path = self.pki.ca_cert_path
        self.crl: Path = self.pki.crl_path
        self.trust_domain: str = self.pki.trust_domain

    def issue(
        self,
        name: str,
        kind: str = "manager",
        sans: Sequence[str] = ("IP:127.0.0.1", "DNS:localhost"),
        key_type: str = "ec-p256",
        *,
        days: int = 365,
        force: bool = False,
    ) -> Issued:
        return self.pki.issue(
            name, kind=kind, sans=sans, key_type=key_type, days=days, unsafe_no_passphrase=True, force=force
        )

    def renew_keeping_old(self, name: str, old_as: str) -> tuple[Path, Issued]:
        """A second certificate for ``name`` (its identity unchanged, as ``cryptoros-certs
        renew`` makes one), the first pair kept under the file name ``old_as``; returns
        the old certificate's new path and the new certificate."""
        import shutil

        shutil.copy2(self.pki.cert_path_for(name), self.pki.cert_path_for(old_as))
        shutil.copy2(self.pki.key_path_for(name), self.pki.key_path_for(old_as))
        return self.pki.cert_path_for(old_as), self.issue(name, force=True)

    def revoke(self, name: str, reason: str = "unspecified") -> Path:
        """Revoke ``name`` (or a serial) and rewrite the CRL; returns the CRL path."""
        self.pki.revoke(name, reason=reason)
        return self.pki.write_crl()

    def expired_crl(self, path: Path, *serials: int, due_days: float = -3) -> Path:
        """Write a CRL of this CA listing ``serials``, issued ten days ago and due for
        re-signing ``due_days`` from now (by default three days ago: older than any
        ``revoke`` wrote, and out of date)."""
        import datetime as dt

        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization

        from cryptoros.pemfiles import load_certificate, load_private_key

        ca, key = load_certificate(self.ca_cert), load_private_key(self.pki.ca_key_path, None)
        now = dt.datetime.now(dt.timezone.utc)
        builder = (x509.CertificateRevocationListBuilder().issuer_name(ca.subject)
                   .last_update(now - dt.timedelta(days=10)).next_update(now + dt.timedelta(days=due_days)))
        for serial in serials:
            builder = builder.add_revoked_certificate(x509.RevokedCertificateBuilder().serial_number(serial)
                                                      .revocation_date(now - dt.timedelta(days=9)).build())
        path.write_bytes(builder.sign(key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM))
        return path


# The brief names the class TestPKI; keep that name importable too.
TestPKI = TestPKIFactory


@pytest.fixture
def pki(tmp_path: Path) -> TestPKIFactory:
    """A fresh throwaway CA in tmp_path/"pki" (ec-p256, unencrypted keys)."""
    return TestPKIFactory(tmp_path / "pki")


@pytest.fixture
def other_pki(tmp_path: Path) -> TestPKIFactory:
    """A second CA, unrelated to ``pki``, in tmp_path/"other-pki"."""
    return TestPKIFactory(tmp_path / "other-pki", trust_domain="other.local")
