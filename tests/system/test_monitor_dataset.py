"""``cryptoros monitor dataset``: labelled runs of the demo's robots (real processes: the
embedded master, the robots, ``cryptoros monitor record``), a model trained on the
clean run, and every run scored by ``cryptoros monitor eval``. Robot r0 is compromised in
the attacked runs: it republishes old poses (``replay``), or its laser scans turn to
noise (``scan-noise``), through the grants it holds."""

from __future__ import annotations

import json

import pytest

from tests.support import run, script

pytestmark = [pytest.mark.timeout(240)]


def test_a_small_dataset_trains_a_model_that_flags_the_attacked_runs_and_not_the_clean_one(tmp_path):
    out = tmp_path / "ds"
    built = run([script("cryptoros"), "monitor", "dataset", "-o", str(out), "--seeds", "1", "--kinds",
                 "replay,scan-noise", "--seconds", "6", "--onset", "2"], timeout=200)
    assert built.returncode == 0, built.stdout + built.stderr
    assert "[3/3] seed 1, scan-noise" in built.stderr  # progress
    labels = {p.parent.name: json.loads(p.read_text()) for p in out.glob("*/run.bag.labels.json")}
    assert labels["seed1-clean"]["attacks"] == []
    (replay,) = labels["seed1-replay"]["attacks"]
    assert replay["publisher"] == "/r0_base" and replay["topic"] == "/r0/pose"
    assert replay["onset"] == pytest.approx(labels["seed1-replay"]["t0"] + 2)

    model = tmp_path / "model.json"
    trained = run([script("cryptoros"), "monitor", "train", str(out / "seed1-clean" / "run.bag"), "-o", str(model)])
    assert trained.returncode == 0, trained.stderr
    bags = [str(out / name / "run.bag") for name in ("seed1-clean", "seed1-replay", "seed1-scan-noise")]
    scored = run([script("cryptoros"), "monitor", "eval", *bags, "--model", str(model), "--json"])
    assert scored.returncode == 0, scored.stderr
    figures = json.loads(scored.stdout)
    print(json.dumps(figures, indent=1))
    assert figures["runs"] == 3 and figures["run_accuracy"] == 1.0, figures  # clean quiet, both attacks caught
    # The clean run raises no alert. In an attacked run a bystander's link-state updates
    # may: robots forward their team's updates in bursts (four 6 to 22 ms apart, 90 Hz over
    # three intervals), which 6 s of one clean run (18 of r1's updates, none so close) did
    # not show the model. How many bursts an attack's disruption sets off varies (one to
    # three of the replay's and scan noise's bystanders in fresh-clone runs): any other
    # bystander stream alerted fails, and the false-positive rate below bounds them all.
    assert figures["attack_streams_detected"] == "2 of 2", figures
    assert not [s for s in figures["clean_streams_alerted"] if s.startswith("seed1-clean/")], figures
    assert all(s.endswith(" on /team/lsu") for s in figures["clean_streams_alerted"]), figures
    assert figures["false_positive_rate"] <= 0.005 and figures["median_delay_s"] < 1.0, figures

    # seed 001's LSTM beside ours, on the same runs (tiny: the figures are the bench's job)
    bench = run([script("cryptoros"), "bench", "monitor", str(out), "--train-seeds", "1", "--eval-seeds", "1",
                 "--epochs", "3", "--window", "20", "--json", str(tmp_path / "bench.json"),
                 "--plots", str(tmp_path / "plots")], timeout=200)
    assert bench.returncode == 0, bench.stdout + bench.stderr
    assert "cryptoros monitor" in bench.stdout and "seed 001 LSTM" in bench.stdout
    side = json.loads((tmp_path / "bench.json").read_text())
    # the same robot's messages: the LSTM's rows are its pose, scan and cmd_vel (the paper's);
    # ours also reads its team packets (the false-map claims, the beacons)
    from rosbags.rosbag1 import Reader

    own = team = 0
    for bag in sorted(out.glob("seed1-*/run.bag")):
        with Reader(bag) as reader:
            for conn, _t, _raw in reader.messages():
                own += conn.topic.startswith("/r0/")
                team += conn.topic.startswith("/team/") and conn.ext.callerid == "/r0"
    assert side["lstm"]["messages"] == own > 0 and side["ours"]["messages"] == own + team and team > 0
    assert side["lstm"]["cpu_us_per_message"] > 0 and side["ours"]["cpu_us_per_message"] > 0
    assert (tmp_path / "plots" / "roc.png").stat().st_size > 1000 and (tmp_path / "plots" / "delays.png").exists()
