"""The soak's watched-stream figures (cryptoros.bench.soak.stream_figures): received and
lost count the same span as expected, so they add up to it; messages sent after the
talker's last report in time are counted apart."""

from __future__ import annotations

from cryptoros.bench.soak import stream_figures


def test_received_and_lost_add_up_to_expected_when_newer_messages_arrive():
    # 20 Hz for 10 s, every message delivered 10 ms after it was sent; the talker reports
    # its sequence number every 0.5 s
    published = [(i / 20, i) for i in range(0, 200, 10)]
    received = [(i / 20 + 0.01, i) for i in range(200) if i != 57]
    fig = stream_figures(received, published, start=0.0, end=10.0)
    assert fig["expected"] == 181  # 0 .. 180, the last report 1 s (in flight) before the end
    assert fig["lost"] == 1 and fig["first_lost"] == 57
    assert fig["received"] + fig["lost"] == fig["expected"]
    assert fig["newer"] == 19  # 181 .. 199: not judged, they may still be on their way
    assert fig["duplicates"] == 0
