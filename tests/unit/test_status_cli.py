"""``cryptoros status`` / ``denials`` when nothing answers at the interceptor's status
endpoint: one line that says what to try."""

from __future__ import annotations

import socket

from click.testing import CliRunner

from interceptor.status import status


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_refused_status_read_asks_whether_the_interceptor_runs(tmp_path, monkeypatch):
    config = tmp_path / "robot_a.toml"  # its [listen] metrics endpoint: a port nobody listens on
    url = f"http://127.0.0.1:{_closed_port()}/status"
    monkeypatch.setattr("interceptor.status._url_from_config", lambda path: (url, "robot_a"))
    r = CliRunner().invoke(status, ["--config", str(config)])
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "Connection refused" in lines[0]
    assert f"is the interceptor running? start it with cryptoros-interceptor --config {config}" in lines[0]


def test_without_a_config_the_hint_names_a_placeholder():
    r = CliRunner().invoke(status, ["--url", f"http://127.0.0.1:{_closed_port()}/status"])
    assert r.exit_code == 2
    assert r.stderr.strip().endswith("(is the interceptor running? start it with cryptoros-interceptor --config FILE)")
