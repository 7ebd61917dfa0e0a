"""The README quickstart, end to end: scripts/quickstart with the venv's console
scripts and curl (PKI, registry, daemon, token over mutual TLS, verification)."""

from __future__ import annotations

import os

from tests.support import REPO, VENV_BIN, require, run


def test_quickstart_script_runs_end_to_end():
    require("curl", "bash")
    env = {**os.environ, "VENV_BIN": str(VENV_BIN)}
    env.pop("CRYPTOROS_AUTHZ_DB", None)
    r = run(["bash", str(REPO / "scripts" / "quickstart")], timeout=120, env=env)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    out = r.stdout
    for step in ("1. PKI", "2. Registry", "3. Signing key", "4. A token for alice", "5. Verify", "6. Audit"):
        assert f"==> {step}" in out
    assert '"sub": "alice"' in out and '"x5t#S256"' in out
    assert "token valid: subject alice" in out and "3 grant(s)" in out
    assert "refused during the TLS handshake" in out
    assert "issued manager=alice" in out
    assert out.rstrip().endswith("==> quickstart: OK")
