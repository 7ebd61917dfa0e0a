"""Output files named on the command line: their directories are made, and a write that
still fails is one line (cryptoros.outputs, used by ``sim``, ``attack``, ``monitor`` and
the benches)."""

from __future__ import annotations

import json

from click.testing import CliRunner

from cryptoros.sim.cli import sim

SMALL = ["run", "--robots", "2", "--size", "20x20", "--max-time", "5", "--crypto-cost", "nominal", "--quiet"]


def test_sim_run_makes_the_directories_of_its_output_files(tmp_path):
    out = tmp_path / "sim-out" / "deeper"
    r = CliRunner().invoke(sim, [*SMALL, "--json", str(out / "r.json"), "--map-png", str(out / "r.png"),
                                 "--trace", str(out / "t.jsonl")])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "r.json").read_text())["outcome"]
    assert (out / "r.png").stat().st_size > 0
    assert (out / "t.jsonl").exists()


def test_a_write_that_cannot_happen_is_one_line(tmp_path):
    (tmp_path / "blocker").write_text("a file where a directory should be")
    r = CliRunner().invoke(sim, [*SMALL, "--json", str(tmp_path / "blocker" / "r.json")])
    assert r.exit_code == 1
    assert r.exception is None or isinstance(r.exception, SystemExit)
    last = r.output.strip().splitlines()[-1]
    assert last.startswith(f"Error: cannot write {tmp_path / 'blocker' / 'r.json'}: "), r.output
    assert "Traceback" not in r.output
