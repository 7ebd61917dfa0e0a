"""Scenario tests: whole missions, assertions on outcomes (nominal crypto costs, so
every result is a function of the seed)."""

from __future__ import annotations

import json
from functools import cache


from cryptoros.sim.robot import DEAD
from cryptoros.sim.scenario import Mission, SimConfig, deterministic, run
from cryptoros.sim.security import SecurityConfig
from tests.support import VENV_BIN, run as run_cmd


@cache
def mission(attacks: str = "", security: str = "none", robots: int = 4, seed: int = 1, **kw) -> dict:
    cfg = SimConfig(robots=robots, seed=seed, attacks=tuple(a for a in attacks.split(",") if a), security=SecurityConfig.parse(security), **kw)
    return run(cfg)


def task_time(r: dict) -> float:
    o = r["outcome"]
    return o["task_time_s"] if o["completed"] else o["end_time_s"]


def test_no_attack_reaches_the_coverage_target_with_a_correct_map():
    r = mission()
    assert r["outcome"]["completed"] and r["outcome"]["coverage"] >= 0.95
    assert r["outcome"]["mean_map_accuracy"] == 1.0
    assert r["packets"]["sent"] > 0 and r["packets"]["rejected"] == 0
    # sharing maps: every robot believes it knows far more than it saw itself
    assert all(v["map"]["believed_coverage"] > 1.3 * v["map"]["own_coverage"] for v in r["robots"].values())


def test_attack1_impersonation_leaves_the_map_incomplete_without_authentication():
    r = mission("impersonate")
    o = r["outcome"]
    assert not o["completed"]
    assert o["end_reason"] == "robots_believe_done"
    assert o["coverage"] < 0.5
    assert o["mean_map_accuracy"] < 0.95  # beliefs say "free" where there are walls
    assert r["packets"]["sent_by_honest"] < mission()["packets"]["sent_by_honest"]  # paper Fig. 4: fewer packets


def test_attack1_is_stopped_by_authentication():
    r = mission("impersonate", "ecdsa")
    assert r["outcome"]["completed"] and r["outcome"]["mean_map_accuracy"] == 1.0
    assert r["packets"]["rejected_by_reason"].get("unsigned", 0) > 0


def test_attack1_by_an_insider_passes_authentication_but_not_the_plausibility_check():
    insider = mission("impersonate-insider", "ecdsa")
    assert not insider["outcome"]["completed"]  # a valid key: authentication cannot tell
    checked = mission("impersonate-insider", "ecdsa", plausibility=True)
    assert checked["outcome"]["completed"]
    assert checked["packets"]["rejected_by_reason"].get("implausible_map", 0) > 0


def test_attack2_mitm_raises_task_time_without_integrity_and_not_with_a_keyed_mac():
    seeds = (1, 2, 3)  # the effect is on a mean: single missions vary with the map

    def mean(attacks, security):
        return sum(task_time(mission(attacks, security, seed=s)) for s in seeds) / len(seeds)

    legacy = mean("", "none")
    attacked = mean("mitm", "none")
    bare = mean("mitm", "sha256")
    keyed = mean("mitm", "hmac")
    assert attacked > 1.25 * legacy
    assert bare > 1.25 * legacy  # a bare SHA-256 digest is recomputed by the attacker
    assert keyed < 1.1 * legacy
    assert all(mission("mitm", "hmac", seed=s)["outcome"]["completed"] for s in seeds)
    assert mission("mitm", "hmac")["packets"]["rejected_by_reason"].get("bad_mac", 0) > 0


def test_attack3_eavesdropper_reconstructs_the_map_unless_encrypted():
    plain = mission("eavesdrop")
    spy = next(iter(plain["attack"].values()))
    assert spy["map_share"] > 0.9 and spy["positions_share"] > 0.9
    enc = mission("eavesdrop", "aes")
    spy = next(iter(enc["attack"].values()))
    assert spy["frames_heard"] > 100
    assert spy["map_share"] == 0.0 and spy["positions_share"] == 0.0 and spy["frames_read"] == 0
    assert enc["outcome"]["completed"]


def test_false_recruit_lures_robots_unless_authenticated():
    lured = mission("false-recruit")
    assert lured["recruit"]["recruited"] >= 1
    assert task_time(lured) > task_time(mission())
    safe = mission("false-recruit", "ecdsa")
    assert safe["recruit"]["recruited"] == 0


def test_replay_is_rejected_with_authentication():
    r = mission("replay", "ecdsa")
    rej = r["packets"]["rejected_by_reason"]
    assert rej.get("stale", 0) + rej.get("replay", 0) > 100
    assert r["outcome"]["completed"]


def test_curves_differ_in_crypto_time_and_energy():
    res = {}
    for curve in ("secp192r1", "secp384r1"):
        res[curve] = run(SimConfig(robots=3, seed=2, security=SecurityConfig.parse("ecdsa", curve=curve)))
    assert res["secp384r1"]["crypto"]["cpu_s_total"] > 3 * res["secp192r1"]["crypto"]["cpu_s_total"]
    e = {c: sum(v["energy_by_kind_j"]["crypto"] for v in r["robots"].values()) for c, r in res.items()}
    assert e["secp384r1"] > e["secp192r1"]


def test_robot_returns_home_before_its_battery_runs_out_and_recruits_a_replacement():
    m = Mission(SimConfig(robots=2, idle=1, seed=3, battery_j=1500.0, max_time=900.0))
    r = m.run()
    explorer = r["robots"]["r0"]
    assert explorer["counters"]["returns_home"] >= 1
    assert explorer["counters"]["charges"] >= 1
    assert all(rb.state != DEAD for rb in m.robots.values())
    assert r["recruit"]["requests"] >= 1 and r["recruit"]["recruited"] >= 1


def test_same_seed_same_results():
    cfg = dict(robots=3, seed=5, attacks=("mitm",), security=SecurityConfig.parse("full"))
    a = deterministic(run(SimConfig(**cfg)))
    b = deterministic(run(SimConfig(**cfg)))
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    c = deterministic(run(SimConfig(**{**cfg, "seed": 6})))
    assert json.dumps(a, sort_keys=True) != json.dumps(c, sort_keys=True)


def test_cli_run_writes_json_and_map(tmp_path):
    out = tmp_path / "r.json"
    png = tmp_path / "m.png"
    res = run_cmd([str(VENV_BIN / "cryptoros"), "sim", "run", "--robots", "2", "--seed", "2", "--security", "hmac", "--attack", "mitm",
                   "--crypto-cost", "nominal", "--json", str(out), "--map-png", str(png), "--quiet"], timeout=120, check=True)
    assert "task completed" in res.stdout
    data = json.loads(out.read_text())
    assert data["config"]["robots"] == 2 and data["config"]["security"]["label"] == "hmac"
    assert png.stat().st_size > 1000 and png.read_bytes()[:4] == b"\x89PNG"
    bad = run_cmd([str(VENV_BIN / "cryptoros"), "sim", "run", "--attack", "nonsense"], timeout=60)
    assert bad.returncode != 0


def test_battery_sweep_scenario_reports_returns_and_recruits_in_the_csv(tmp_path):
    import csv

    from cryptoros.sim.sweep import sweep

    sweep([3], ["legacy", "battery"], ["secp256k1"], [1, 2], tmp_path, workers=1, extra={"max_time": 600.0})
    rows = list(csv.DictReader(open(tmp_path / "sweep.csv")))
    battery = [r for r in rows if r["scenario"] == "battery"]
    assert len(battery) == 2
    for r in battery:
        assert int(r["returns_home"]) > 0 and int(r["charges"]) > 0
        assert int(r["recruit_requests"]) > 0
    assert sum(int(r["recruit_successes"]) for r in battery) > 0
    assert all(int(r["returns_home"]) == 0 for r in rows if r["scenario"] == "legacy")
    paired = list(csv.DictReader(open(tmp_path / "paired.csv")))
    assert any(p["baseline"] == "legacy" and p["treatment"] == "battery" and p["metric"] == "coverage" and p["n"] == "2" for p in paired)
    assert (tmp_path / "maps" / "map-battery-3robots-seed1.png").read_bytes()[:4] == b"\x89PNG"
