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
