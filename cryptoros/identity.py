"""Whom a certificate names, and whether it may act as a given manager.

Every certificate ``cryptoros-certs`` issues carries its holder in a URI SAN,
``spiffe://<trust-domain>/<kind>/<name>`` (:func:`certs.pki.identity_uri`). A manager's
client presents one of :data:`CLIENT_KINDS`. The registry binds a manager to a
certificate by fingerprint; the CLI checks the name when a certificate file is bound,
and the authorization server checks it again on every token it issues, so a
fingerprint bound without the file (``import``, ``set-cert --fingerprint``) to the
wrong manager is refused rather than obeyed. A certificate naming no identity (made by
another tool) passes: its fingerprint is all there is.
"""

from __future__ import annotations

from cryptography import x509

#: The certificate kinds (cryptoros-certs issue --kind) a manager's client presents.
CLIENT_KINDS = ("manager", "interceptor", "master")


def named_holders(cert: x509.Certificate) -> list[tuple[str, str]]:
    """The (kind, name) pairs of the client identities ``cert``'s URI SANs name."""
    try:
        uris = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value \
            .get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        return []
    named = []
    for uri in uris:
        if not uri.startswith("spiffe://"):
            continue
        parts = uri[len("spiffe://"):].split("/")
        if len(parts) == 3 and parts[1] in CLIENT_KINDS:
            named.append((parts[1], parts[2]))
    return named


def identity_mismatch(named: list[tuple[str, str]], name: str) -> str | None:
    """Why a certificate naming ``named`` (:func:`named_holders`) may not act as manager
    ``name``, or None.

    A certificate naming another manager, robot (interceptor) or master would let that
    holder act as ``name``, and lock ``name``'s own client out: the runbook issues every
    robot's certificate as kind interceptor, so checking only the manager kind would
    protect no robot."""
    if not named or any(holder == name for _kind, holder in named):
        return None
    kind, holder = named[0]
    return (f"identifies {kind} {holder!r}, not manager {name!r}: give {name}'s own certificate "
            f"(cryptoros-certs issue {name} --kind {kind}), or bind this one to manager {holder!r}")


__all__ = ["CLIENT_KINDS", "identity_mismatch", "named_holders"]
