"""``cryptoros bench soak`` smoke test: a short soak runs every kind of churn (nodes
come and go, grant flips, the master's interceptor and the authorization server
restart) and prints its figures as JSON. Figures are printed, not asserted, except
that the watched stream delivered, its nodes survived, every process is still there and
no stopped node stays registered with rosmaster."""

from __future__ import annotations

import json

from tests.support import require, run, script


def test_bench_soak_quick():
    require("rosmaster")
    result = run([script("cryptoros"), "bench", "soak", "--seconds", "12", "--json"], timeout=180)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "... soak for 12 s" in result.stderr  # progress goes to stderr with --json
    figures = json.loads(result.stdout)
    events = figures["events"]
    assert events["interceptor_restarts"] == 1 and events["authz_restarts"] == 1
    assert events["nodes_started"] >= 2 and events["nodes_stopped"] == events["nodes_started"]
    assert events["grant_flips"] >= 2
    stream = figures["watched_stream"]
    assert stream["received"] > 0 and stream["nodes_alive_at_end"]
    assert stream["lost"] is not None and stream["longest_gap_s"] > 0
    procs = figures["processes"]
    assert set(procs) == {"master", "robot_a", "robot_b", "authz"}
    assert all(p["fds_start"] > 0 and p["fds_end"] > 0 and p["rss_kib_end"] > 0 for p in procs.values())
    assert procs["robot_b"]["tcp_end"]["listen"] >= 2
    # every churn node was stopped with SIGTERM, which unregisters it (the bench waits up to 10 s)
    assert figures["stale_churn_registrations"] == 0, figures
    assert procs["master"]["pid_end"] != procs["master"]["pid_start"]  # it was restarted
    assert procs["authz"]["pid_end"] != procs["authz"]["pid_start"]
    assert procs["robot_a"]["pid_end"] == procs["robot_a"]["pid_start"]
