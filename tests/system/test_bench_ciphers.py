"""``cryptoros bench ciphers --quick`` as a real subprocess: every message type x cipher
measured on this machine and on the throttled Atom stand-in, bytes added as the formulas
say, round trips checked, the paper's Table 2 rebuilt. Speed is never asserted: the
stand-in's rows are checked to have run under their 1/8 CPU quota (CPU time over wall
time), not to be slower."""

from __future__ import annotations

import json

import pytest

from cryptoros.bench.ciphers import MAX_SHARE_OVER_QUOTA
from tests.support import run, script

pytestmark = [pytest.mark.slow]

MESSAGES = {"string", "pose", "laser", "image", "image_raw", "cloud"}
PRIMITIVES = {"3des-cbc", "blowfish-cbc", "aes192-cbc", "aes128-cbc-hmac", "aes256-cbc-hmac", "aes128-gcm",
              "chacha20-poly1305"}
TLS13 = {"tls13:TLS_AES_128_GCM_SHA256", "tls13:TLS_AES_256_GCM_SHA384", "tls13:TLS_CHACHA20_POLY1305_SHA256"}


@pytest.mark.timeout(90)
def test_bench_ciphers_quick(tmp_path):
    out = tmp_path / "ciphers.json"
    plots = tmp_path / "plots"
    result = run([script("cryptoros"), "bench", "ciphers", "--quick", "--json", str(out), "--plots", str(plots)],
                 timeout=85)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    report = json.loads(out.read_text())
    rows = {(r["message"], r["cipher"]): r for r in report["rows"]}

    ciphers = set(report["ciphers"])
    assert PRIMITIVES | TLS13 <= ciphers
    assert any(c.startswith("tls12:") for c in ciphers)
    assert {(m, c) for m in MESSAGES for c in ciphers} == set(rows)

    # the wire sizes: the paper's image mean exactly, LaserScan of 683 float32 ranges, ~1 MB cloud
    assert report["messages"]["image"]["bytes"] == 79_737
    assert 683 * 4 < report["messages"]["laser"]["bytes"] < 683 * 4 + 200
    assert 1_000_000 < report["messages"]["cloud"]["bytes"] < 1_100_000

    for (message, cipher), r in rows.items():
        n = r["bytes"]
        for profile in ("normal", "atom"):
            p = r[profile]
            assert p["enc_us"] > 0 and p["dec_us"] > 0 and p["msgs_per_s_one_core"] > 0, (message, cipher, profile)
            assert p["roundtrip_checked"] >= p["ops"] + 1 >= 2, (message, cipher, profile)
        # every stand-in row was measured under its quota: its window's CPU time over wall time
        # (an unthrottled window runs near a whole core)
        assert r["atom"]["cpu_share"] <= MAX_SHARE_OVER_QUOTA * report["config"]["throttle"]["quota"], r["atom"]
        added = r["bytes_added"]
        if cipher in ("aes128-gcm", "chacha20-poly1305"):
            assert added == 12 + 16  # nonce + tag
        elif cipher.endswith("-cbc") or cipher.endswith("-cbc-hmac"):
            block = 8 if cipher in ("3des-cbc", "blowfish-cbc") else 16
            mac = 32 if cipher.endswith("hmac") else 0
            assert added == block + (block - n % block) + mac, (message, cipher, n, added)  # IV + PKCS7 + MAC
        else:  # TLS records: header and tag per 16 KiB record (TLS 1.2 GCM: + explicit nonce)
            records = -(-n // 16384)
            assert 21 * records <= added <= 29 * records, (message, cipher, n, added)
            assert r["normal"]["negotiated"].endswith(cipher.partition(":")[2])

    # the paper's Table 2, rebuilt for both machines and both message categories
    for machine in ("powerful", "atom"):
        for category in ("simple", "complex"):
            assert set(report["table2"][machine][category]) == ciphers
            assert set(report["table2"][machine][category].values()) <= {"✓", "∅", "⇌"}
            assert set(report["table2_by_message"][machine]) == MESSAGES
    workload = report["paper_workload"]
    for machine in ("powerful", "atom"):
        assert 0 < workload[machine]["3des-cbc"]["battery_h"] <= workload[machine]["plain"]["battery_h"]
    assert report["config"]["throttle"]["method"] in ("cgroup v2 cpu.max", "cgroup v1 cpu.cfs_quota_us", "dutycycle")
    assert (plots / "ciphers.png").stat().st_size > 10_000
    assert "Table 2 rebuilt" in result.stdout and "Energy model" in result.stdout


@pytest.mark.parametrize("method", ["picked", "dutycycle"])
def test_the_throttle_stops_a_busy_child_and_counts_it(monkeypatch, method):
    """The Atom stand-in's quota: a child that needs 50 ms of CPU (about 0.4 s under 1/8
    of a core) is stopped, and :meth:`Throttle.stalls` says so (a child it is 0 for is
    measured again, then the bench aborts: its figures would be this machine's)."""
    import subprocess
    import sys

    from cryptoros.bench.ciphers import Throttle

    if method == "dutycycle":
        monkeypatch.setenv("CRYPTOROS_BENCH_THROTTLE", "dutycycle")
    throttle = Throttle(0.125)
    try:
        child = subprocess.Popen([sys.executable, "-c", "import time\nend = time.process_time() + 0.05\n"
                                  "while time.process_time() < end: pass"])
        throttle.attach(child.pid)
        assert child.wait(timeout=30) == 0
        assert throttle.stalls(child.pid) > 0, throttle.describe()
        assert throttle.stalls(child.pid + 10**7) == 0  # a child it never had
    finally:
        throttle.close()
