"""A path to a device where a file is expected (a typo, a symlink left behind) is one
line and exit 2 from every tool, at once (CLI audit: /dev/zero given as a certificate,
passphrase or configuration hung each tool while it grew to gigabytes)."""

from __future__ import annotations

import subprocess

from tests.support import script


def _one_line(args: list[str], tool: str) -> str:
    r = subprocess.run(args, capture_output=True, text=True, timeout=30)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (r.returncode, r.stderr)
    assert lines[0].startswith(f"{tool}: error: "), lines
    return lines[0]


def test_a_device_given_as_a_file_is_refused_in_one_line(tmp_path):
    zero = tmp_path / "zero.pem"
    zero.symlink_to("/dev/zero")
    line = _one_line([script("cryptoros-certs"), "init", "--dir", str(tmp_path / "pki"), "--passphrase-file",
                      str(zero)], "cryptoros-certs")
    assert "not a regular file" in line and not (tmp_path / "pki" / "ca.key").exists()
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    subprocess.run([script("cryptoros-authz"), "--db", db, "db", "upgrade"], check=True, capture_output=True,
                   timeout=60)
    line = _one_line([script("cryptoros-authz"), "--db", db, "add-manager", "zz", "--cert", str(zero)],
                     "cryptoros-authz")
    assert "not a regular file" in line
    line = _one_line([script("cryptoros-authz"), "--db", db, "import", "--dry-run", str(zero)], "cryptoros-authz")
    assert "not a regular file" in line
    line = _one_line([script("cryptoros-interceptor"), "--config", str(zero), "--check"], "cryptoros-interceptor")
    assert "not a regular file" in line
