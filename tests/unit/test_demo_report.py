"""The demo's printed table and Markdown report (cryptoros.demo.report), from a result
made by hand: piped output keeps whole lines and whole cells, and the random seed is
not mistaken for a source paper's seed (000, 001, ...)."""

from __future__ import annotations

import io

from rich.console import Console

from cryptoros.demo import report as rep

REASON = "peer_did_not_return_a_certificate"


def _mode(denials: dict[str, int]) -> dict:
    return {"coverage": 0.94, "coverage_target": 0.9, "target_reached": True, "mission_time_sim_s": 92.0,
            "mission_time_wall_s": 11.8, "end_reason": "target", "setup_s": 2.9, "denials": denials,
            "messages": {"tx": 1629, "rx": 880, "tx_bytes": 254000, "rx_bytes": 246000},
            "interceptors": {"cpu_s": {"r0": 0.9}, "cpu_s_total": 0.9, "cpu_share_of_one_core": 0.08,
                             "bytes_relayed": 509000},
            "timeline": [[0, 0, 0.0], [92, 92, 0.94]]}


def _result(tmp_path) -> dict:
    attack = {"seed": "001", "what": "spoofed position", "protected_attacker": "insider",
              "plain": {"succeeded": True, "evidence": "2804 spoofed poses"},
              "protected": {"succeeded": False, "evidence": "0 spoofed poses"}}
    return {"config": {"modes": ["plain", "protected"], "robots": 3, "ros": 2, "seed": 1, "width": 40, "height": 40,
                       "scale": 8.0, "coverage_target": 0.9},
            "attacks": {"spoof-pose": attack},
            "modes": {"plain": _mode({}), "protected": _mode({"not_granted": 1, REASON: 12})},
            "workdir": str(tmp_path)}


def test_piped_output_keeps_every_denial_reason_whole(tmp_path, monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)
    out = io.StringIO()
    console = rep.LiveView(Console(file=out)).console  # a file: no terminal, as when piped
    console.print(rep.table(_result(tmp_path)))
    console.print("  cryptoros    5.0/30 s  sim   36.3 s  coverage  26.5%  " + " ".join(f"r{i}:explore" for i in range(12)))
    text = out.getvalue()
    assert f"{REASON} 12" in text, text
    assert "…" not in text
    assert " ".join(f"r{i}:explore" for i in range(12)) in text  # one line, not wrapped at 80 columns


def test_a_narrow_terminal_folds_a_reason_rather_than_cut_it(tmp_path):
    out = io.StringIO()
    Console(file=out, width=60).print(rep.table(_result(tmp_path)))
    assert "…" not in out.getvalue()


def test_the_report_calls_the_mission_seed_random(tmp_path):
    text = rep.write_report(_result(tmp_path), tmp_path).read_text()
    assert "(random seed 1, " in text
    assert "(seed 1," not in text
