"""Smoke test of ``cryptoros bench scale --quick``: a real network (rosmaster, the
master's interceptor, robot A's interceptor restarted per point, a publisher of our node
client, streams opened with real mutual TLS and genuine tokens), 10 and 100 streams and
topics, the authorization replicas on PostgreSQL where it is installed. Checks the
report's structure and that its numbers are sane; speed is never asserted."""

from __future__ import annotations

import json

import pytest

from cryptoros.bench.scale import fit
from tests.support import require, run, script

pytestmark = [pytest.mark.ros1, pytest.mark.slow]


def test_fit_is_a_least_squares_line_and_flags_a_last_step_dearer_than_the_first():
    line = fit([10, 100, 1000], [5 + 2 * x for x in (10, 100, 1000)])
    assert line["slope"] == pytest.approx(2) and line["intercept"] == pytest.approx(5)
    assert line["superlinear"] is False
    quadratic = fit([10, 100, 1000], [x * x for x in (10, 100, 1000)])
    assert quadratic["superlinear"] is True and quadratic["step_ratio"] == pytest.approx(10)
    assert fit([10], [1.0])["slope"] is None


@pytest.mark.timeout(400)
def test_bench_scale_quick(tmp_path):
    require("rosmaster")
    out, plots = tmp_path / "scale.json", tmp_path / "plots"
    result = run([script("cryptoros"), "bench", "scale", "--quick", "--json", str(out), "--plots", str(plots)],
                 timeout=380)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]
    report = json.loads(out.read_text())
    assert "[scale]" in result.stderr  # progress lines
    assert "Unclosed" not in result.stderr  # aiohttp's warning for a token client's session left open
    assert report["limits"]["max_connections_per_peer"] >= 100

    for curve in ("streams", "topics"):
        points = report["curves"][curve]
        assert [p["count"] for p in points] == [10, 100]
        for p in points:
            assert p["failed"] == 0 and p["streams_open"] == p["count"], p
            assert p["messages"] > 0 and p["cpu_us_per_message"] > 0, p
            assert p["rss_before_kib"] > 0 and p["rss_open_kib"] > 0, p
            assert p["open_s"] > 0
        # every stream holds buffers and TLS state: ten times the streams, more memory
        assert points[1]["rss_open_kib"] > points[0]["rss_open_kib"], points
        assert points[1]["rss_added_kib"] > points[0]["rss_added_kib"], points
        fits = report["fits"][curve]
        assert fits["rss_kib"]["slope"] > 0
        assert fits["cpu_us_per_message"]["intercept"] is not None
        assert (plots / f"scale-{curve}.png").stat().st_size > 1000
        assert f"cost per {'stream' if curve == 'streams' else 'topic'}" in result.stdout

    authz = report["authz"]
    if "skipped" in authz:
        assert "PostgreSQL" in authz["skipped"]
    else:
        assert [r["replicas"] for r in authz["rows"]] == [1, 2]
        for r in authz["rows"]:
            assert r["tokens"] > 0 and r["tokens_per_s"] > 0 and r["errors"] == 0, r
            assert 0 < r["p50_ms"] <= r["p99_ms"], r
        assert (plots / "scale-authz.png").stat().st_size > 1000
