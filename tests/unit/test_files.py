"""read_bounded: a file an operator named is read only if it is a regular file of a
bounded size (CLI audit: /dev/zero given as a certificate grew a tool to 9.6 GB)."""

import os

import pytest

from cryptoros.files import read_bounded


def test_a_regular_file_within_the_limit_is_read_whole(tmp_path):
    f = tmp_path / "ok.pem"
    f.write_bytes(b"x" * 100)
    assert read_bounded(f, 100) == b"x" * 100


def test_a_larger_file_is_refused_saying_so(tmp_path):
    f = tmp_path / "big.pem"
    f.write_bytes(b"x" * 101)
    with pytest.raises(OSError, match="larger than"):
        read_bounded(f, 100)


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom"])
def test_devices_are_refused_at_once(device, tmp_path):
    link = tmp_path / "cert.pem"
    link.symlink_to(device)
    with pytest.raises(OSError, match="not a regular file") as err:
        read_bounded(link, 1 << 30)
    assert err.value.strerror.startswith("not a regular file")


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    fifo = tmp_path / "pass"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="not a regular file"):
        read_bounded(fifo, 100)


def test_a_directory_and_a_missing_file_are_os_errors(tmp_path):
    with pytest.raises(OSError):
        read_bounded(tmp_path, 100)
    with pytest.raises(FileNotFoundError):
        read_bounded(tmp_path / "missing", 100)


def _tls_files(tmp_path):
    for name in ("ca.crt", "me.crt", "me.key"):
        (tmp_path / name).write_bytes(b"-----BEGIN CERTIFICATE-----\n")
    return {"ca_file": tmp_path / "ca.crt", "cert_file": tmp_path / "me.crt", "key_file": tmp_path / "me.key"}


def test_tls_files_that_openssl_reads_itself_are_held_to_the_same_rule(tmp_path):
    """The CA, certificate, key and CRL of a TLS context are read by OpenSSL, not by
    read_bounded: a device or an oversized file is refused by name before OpenSSL sees it
    (a 200 MB file had been read whole, a device reported as "not found")."""
    from cryptoros.errors import ConfigError
    from cryptoros.tls import TLSConfig

    files = _tls_files(tmp_path)
    TLSConfig(**files)  # the files as they are: accepted
    zero = tmp_path / "zero.pem"
    zero.symlink_to("/dev/zero")
    with pytest.raises(ConfigError, match=r"TLS crl file .*zero\.pem is not a regular file"):
        TLSConfig(**files, crl_file=zero)
    big = tmp_path / "big.crt"
    with open(big, "wb") as f:
        f.truncate((16 << 20) + 1)  # sparse: no 16 MiB written
    with pytest.raises(ConfigError, match=r"TLS ca file .*big\.crt is larger than 16 MiB"):
        TLSConfig(**{**files, "ca_file": big})
    with pytest.raises(ConfigError, match=r"TLS cert file not found: .*missing\.crt"):
        TLSConfig(**{**files, "cert_file": tmp_path / "missing.crt"})


def test_a_secret_file_open_to_group_or_others_is_one_line_naming_file_mode_and_fix(tmp_path):
    from cryptoros.files import open_to_others

    closed, group, world = (tmp_path / name for name in ("closed.key", "group.pass", "world.key"))
    for path, mode in ((closed, 0o600), (group, 0o640), (world, 0o604)):
        path.write_text("secret")
        path.chmod(mode)
    assert open_to_others([("the TLS key", closed), ("no file", None), ("missing", tmp_path / "nothing")]) == []
    assert open_to_others([("the passphrase file", group), ("the TLS key", world)]) == [
        f"the passphrase file {group} has mode 0640, open to its group on this host: chmod 600 {group}",
        f"the TLS key {world} has mode 0604, open to other users on this host: chmod 600 {world}",
    ]
