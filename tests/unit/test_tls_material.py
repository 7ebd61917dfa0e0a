"""What an interceptor or the authorization server says when its TLS files do not load:
the file and the reason, where OpenSSL says ``PEM lib`` or ``KEY_VALUES_MISMATCH``."""

from __future__ import annotations

import pytest

from cryptoros.errors import ConfigError
from cryptoros.tls import TLSConfig, client_context, server_context


@pytest.mark.parametrize("make", [server_context, client_context])
def test_each_unloadable_file_is_named_with_the_reason(pki, tmp_path, make):
    """Operator audit: an empty certificate file read ``[SSL] PEM lib (_ssl.c:3905)`` and the
    CA's certificate given as the robot's ``KEY_VALUES_MISMATCH``."""
    issued = pki.issue("robot_a", kind="interceptor")
    empty = tmp_path / "empty.pem"
    empty.write_bytes(b"")
    good = {"ca_file": pki.ca_cert, "cert_file": issued.cert_path, "key_file": issued.key_path}
    cases = [
        ({"cert_file": empty}, f"TLS certificate: {empty} is not an X.509 certificate"),
        ({"ca_file": empty}, f"TLS CA: {empty} holds no readable certificate"),
        ({"key_file": empty}, f"TLS key: {empty} is not a private key"),
        ({"cert_file": pki.ca_cert}, f"TLS key {issued.key_path} does not belong to the certificate {pki.ca_cert}"),
    ]
    for change, message in cases:
        with pytest.raises(ConfigError) as info:
            make(TLSConfig(**{**good, **change}))
        assert str(info.value).startswith(message) and "\n" not in str(info.value), (change, str(info.value))
    make(TLSConfig(**good))
