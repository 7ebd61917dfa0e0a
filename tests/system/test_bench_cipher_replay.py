"""``cryptoros bench cipher-replay --quick`` as a real subprocess: a bag written with
rosbags, replayed by Debian's ``rosbag play`` through real encrypting and decrypting
rospy nodes (pycryptodome) on this machine and in the Atom stand-in's cgroups. Speed is
never asserted: what is checked is that every figure was measured (messages got
through and were counted, the nodes used CPU, bytes crossed the wire) and that the
ciphertext topic carries what CBC adds."""

from __future__ import annotations

import json

import pytest

from tests.support import run, script

pytestmark = [pytest.mark.slow, pytest.mark.ros1]


@pytest.mark.timeout(420)
def test_bench_cipher_replay_quick(tmp_path):
    out = tmp_path / "replay.json"
    plots = tmp_path / "plots"
    result = run([script("cryptoros"), "bench", "cipher-replay", "--quick", "--json", str(out), "--plots", str(plots)],
                 timeout=400)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "repetition 1/1" in result.stderr and "Atom D525 stand-in" in result.stderr  # progress
    report = json.loads(out.read_text())

    bag = report["bag"]
    assert bag["laser"]["messages"] == 60 and bag["image"]["messages"] == 180  # 6 s at 10 Hz and 30 fps
    assert bag["laser"]["bytes_mean"] == 2789  # 683 float32 ranges
    assert abs(bag["image"]["bytes_mean"] - 79_736.9) < 3 * 818.5 / 180 ** 0.5 * 2  # the paper's mean and SD
    assert 400 < bag["image"]["bytes_sd"] < 1300

    runs = {(r["machine"], r["cipher"]): r for r in report["runs"]}
    assert set(runs) == {(m, c) for m in ("full", "atom") for c in ("plain", "aes")}
    for (machine, cipher), r in runs.items():
        assert r["window_s"] > 2 and r["loadavg_1min_before"] >= 0
        for sensor, rate in (("laser", 10), ("image", 30)):
            s = r[sensor]
            assert s["decrypt_errors"] == 0
            assert 0 < s["delivered_per_s"] <= rate * 1.2, (machine, cipher, sensor, s)
            assert s["delivered_total"] <= s["published_total"]
            assert s["enc_cpu_pct"] > 0 and s["dec_cpu_pct"] > 0, (machine, cipher, sensor, s)
            assert s["plain_wire_bytes_per_s"] > 0 and s["cipher_wire_bytes_per_s"] > 0
            assert s["enc_stage_us"]["cipher_s"] > 0
    # what crossed the wire per message: the encrypted LaserScan is its 2,789 B + IV (16) +
    # PKCS7 padding (11) + UInt8MultiArray's framing, more than the plain one
    full = runs[("full", "aes")]["laser"]
    per_msg_plain = full["plain_wire_bytes_per_s"] / full["encrypted_per_s"]
    per_msg_cipher = full["cipher_wire_bytes_per_s"] / full["delivered_per_s"]
    assert per_msg_cipher > per_msg_plain * 0.95

    check = report["check"]["atom"]
    assert 0 < check["effective_ratio"] <= check["intended_ratio"] * 1.5, check  # the quota holds
    derived = report["derived"]
    assert set(derived["table2"]["atom"]["aes"].values()) <= {"✓", "∅", "⇌"}
    assert derived["energy"]["atom"]["aes"]["battery_h"] <= derived["energy"]["atom"]["plain"]["battery_h"] + 0.05
    assert set(derived["fig9"]["full"]["aes"]) >= {"security", "performance", "autonomy", "network"}
    for name in ("replay-delivered.png", "replay-cpu.png", "replay-bytes.png", "replay-fig9.png"):
        assert (plots / name).stat().st_size > 10_000
    assert "Table 2 in the paper's categories" in result.stdout and "MODEL, not measured" in result.stdout

    again = run([script("cryptoros"), "bench", "cipher-replay", "--report", str(out)], timeout=60)
    assert again.returncode == 0 and "Table 4" in again.stdout
