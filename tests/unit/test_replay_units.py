"""Seed 002's replay without processes: the bag's messages and the rules that turn
measurements into the paper's tables."""

from __future__ import annotations

import pytest

from cryptoros.bench import replay_report as rr
from cryptoros.bench.replay import _interp, summarize
from cryptoros.bench.replay_bag import write_bag
from cryptoros.bench.standin import PERIOD_US, SINGLE_THREAD, ratio


def test_the_bag_holds_the_papers_rates_and_sizes_and_1024_floats_make_its_4152_byte_scan(tmp_path):
    info = write_bag(tmp_path / "a.bag", 4, laser_ranges=683)
    assert (info["laser"]["messages"], info["image"]["messages"]) == (40, 120)
    assert info["laser"]["bytes_min"] == info["laser"]["bytes_max"] == 2789
    assert 78_000 < info["image"]["bytes_mean"] < 81_500 and info["image"]["bytes_sd"] > 300
    info = write_bag(tmp_path / "b.bag", 4, laser_ranges=1024)
    assert info["laser"]["bytes_min"] == info["laser"]["bytes_max"] == 4152  # the paper's size
    raw = write_bag(tmp_path / "c.bag", 4, image="raw")
    assert raw["image"]["bytes_mean"] == 921_647 and raw["image"]["type"] == "sensor_msgs/Image"

    from rosbags.rosbag1 import Reader

    with Reader(tmp_path / "a.bag") as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            "/scan": "sensor_msgs/msg/LaserScan", "/camera/image": "sensor_msgs/msg/CompressedImage"}
        assert reader.duration == pytest.approx(4e9 - 1e9 / 30, rel=0.02)


def test_the_rules_of_the_tables_and_their_verdicts_on_the_papers_own_figures():
    assert [rr.share_symbol(d, 30) for d in (30, 27, 26.9, 15, 12, 11, 5)] == ["✓", "✓", "∅", "∅", "∅", "⇌", "⇌"]
    assert [rr.table4_symbol(d, 10) for d in (10, 9, 8.9, 4, 3.9)] == ["✓", "✓", "○", "○", "▼"]
    assert [rr.score(v, (0.05, 0.25, 0.60)) for v in (0.0, 0.05, 0.3, 0.9)] == [0, 1, 2, 3]
    # the paper's Table 2 rates AES and Blowfish ✓ on the Atom for images it delivered at
    # 15 and 11 of 30 a second: no one threshold on the delivered share gives its table
    assert rr.share_symbol(rr.PAPER["atom_images_per_s"]["aes"], 30) != rr.PAPER["table2"]["atom"]["complex"]["aes"]


def test_the_summary_spreads_repetitions_and_counters_are_read_between_samples():
    samples = [[10.0, 1.0, 0, 0, 0], [11.0, 1.5, 100, 0, 3], [12.0, 2.5, 300, 0, 6]]
    assert _interp(samples, 10.5, 1) == pytest.approx(1.25) and _interp(samples, 11.5, 2) == pytest.approx(200)
    assert _interp(samples, 9.0, 2) == 0 and _interp(samples, 13.0, 2) == 300

    def one(d: float) -> dict:
        sensor = {"delivered_per_s": d, "enc_cpu_pct": 1.0, "enc_stage_us": {"cipher_s": 5.0}}
        return {"machine": "atom", "cipher": "aes", "window_s": 10, "loadavg_1min_before": 1.0,
                "laser": sensor, "image": sensor}

    s = summarize([one(10), one(14), one(12)])["atom"]["aes"]
    assert s["image.delivered_per_s"]["mean"] == 12 and (s["image.delivered_per_s"]["min"],
                                                         s["image.delivered_per_s"]["max"]) == (10, 14)
    assert s["image.enc_stage_us.cipher_s"]["sd"] == 0


def test_the_stand_ins_come_from_published_single_thread_ratings():
    assert ratio("Atom D525") == SINGLE_THREAD["Atom D525"]["rating"] / SINGLE_THREAD["this CPU"]["rating"]
    assert 0.08 < ratio("Atom D525") < 0.2 and 0.4 < ratio("i7-3612QM") < 0.8
    assert ratio("Atom D525") / ratio("i7-3612QM") == pytest.approx(330 / 1600)
    assert PERIOD_US == 100_000
