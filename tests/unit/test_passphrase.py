"""cryptoros.passphrase: one rule for every passphrase file and variable."""

from __future__ import annotations

from pathlib import Path

import pytest

from cryptoros.errors import ConfigError, CryptorosError
from cryptoros.passphrase import PassphraseError, from_env, read_file, read_passphrase


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"s3cret", b"s3cret"),
        (b"s3cret\n", b"s3cret"),
        (b"s3cret\r\n", b"s3cret"),
        (b"s3cret\n\n", b"s3cret\n"),  # one newline only
        (b" spaced out \n", b" spaced out "),
    ],
)
def test_a_file_loses_one_trailing_newline_only(tmp_path: Path, content: bytes, expected: bytes):
    (tmp_path / "p").write_bytes(content)
    assert read_file(tmp_path / "p") == expected
    assert read_passphrase(tmp_path / "p", "UNUSED_VAR", environ={"UNUSED_VAR": "x"}) == expected


@pytest.mark.parametrize("content", [b"", b"\n", b"\r\n"])
def test_an_empty_file_is_an_error(tmp_path: Path, content: bytes):
    (tmp_path / "p").write_bytes(content)
    with pytest.raises(PassphraseError, match="empty"):
        read_file(tmp_path / "p")


def test_a_missing_file_is_an_error_naming_it(tmp_path: Path):
    with pytest.raises(PassphraseError, match="cannot read passphrase file .*nope"):
        read_file(tmp_path / "nope")
    assert issubclass(PassphraseError, ConfigError) and issubclass(PassphraseError, CryptorosError)


def test_environment_variable():
    assert from_env("P", {"P": "from env\n"}) == b"from env\n"  # as is
    assert from_env("P", {}) is None
    with pytest.raises(PassphraseError, match=r"\$P is set but empty"):
        from_env("P", {"P": ""})
    assert read_passphrase(None, "P", environ={"P": "x"}) == b"x"
    assert read_passphrase(None, None) is None
