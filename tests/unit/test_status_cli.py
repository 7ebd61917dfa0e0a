"""``cryptoros status`` / ``denials`` when the status endpoint cannot be asked or answers
as something else than an interceptor's ``/status``, or the configuration file names it
badly: one line that says what to try, exit 2."""

from __future__ import annotations

import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from click.testing import CliRunner

from interceptor.status import denials, status


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def answering():
    """A real HTTP server on loopback answering every GET with the body it is given."""
    servers = []

    def serve(body: bytes, content_type: str = "application/json", code: int = 200) -> str:
        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                self.send_response(code)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}/healthz"

    yield serve
    for server in servers:
        server.shutdown()
        server.server_close()


def test_a_refused_status_read_asks_whether_the_interceptor_runs_on_this_host(tmp_path, monkeypatch):
    config = tmp_path / "robot_a.toml"  # its [listen] metrics endpoint: a port nobody listens on
    url = f"http://127.0.0.1:{_closed_port()}/status"
    monkeypatch.setattr("interceptor.status._url_from_config", lambda path: (url, "robot_a"))
    r = CliRunner().invoke(status, ["--config", str(config)])
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "Connection refused" in lines[0]
    assert (f"(is robot_a's interceptor running on this host? start it with cryptoros-interceptor "
            f"--config {config})") in lines[0]


def test_without_a_config_the_hint_names_a_placeholder():
    r = CliRunner().invoke(status, ["--url", f"http://127.0.0.1:{_closed_port()}/status"])
    assert r.exit_code == 2
    assert r.stderr.strip().endswith(
        "(is the interceptor running on this host? start it with cryptoros-interceptor --config FILE)")


INTERCEPTOR_HEALTHZ = json.dumps({"status": "ok", "open_streams": 0, "feed_age": 0.5}).encode()
AUTHZ_PROBE = json.dumps({"status": "ok", "database": "ok", "kid": "k1", "certificate": "ok"}).encode()


@pytest.mark.parametrize("command", [status, denials], ids=["status", "denials"])
@pytest.mark.parametrize(("body", "missing"), [
    (INTERCEPTOR_HEALTHZ, "no manager, roles, public, health, certificate, feed, denials"),
    (AUTHZ_PROBE, "no manager, roles, public, health, feed, open_streams, denials; "
                  "certificate is not an object"),
    (b"[1, 2]", "not a JSON object"),
    (b"# HELP cryptoros_streams\n", "not JSON"),
], ids=["interceptor-healthz", "authz-probe", "json-list", "prometheus-text"])
def test_an_answer_that_is_not_an_interceptors_status_is_one_line(answering, command, body, missing):
    url = answering(body)
    r = CliRunner().invoke(command, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stdout == ""  # denials: no false "no refusals recorded"
    assert r.stderr.strip() == (f"cryptoros {command.name}: error: {url} did not answer as an interceptor's "
                                f"/status ({missing}): give its [listen] metrics endpoint's /status")


@pytest.mark.parametrize("command", [status, denials], ids=["status", "denials"])
def test_an_http_error_answer_is_not_an_interceptors_status(answering, command):
    url = answering(json.dumps({"status": "token_expired", "detail": "expired"}).encode(), code=503)
    r = CliRunner().invoke(command, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (f"cryptoros {command.name}: error: {url} did not answer as an interceptor's "
                                "/status (HTTP 503 Service Unavailable): give its [listen] metrics endpoint's /status")


def test_an_answer_with_a_field_render_cannot_read_is_one_line(answering):
    body = {"manager": "robot_a", "roles": ["node"], "public": "127.0.0.1:11411", "health": "ok",
            "certificate": {"serial": "1f"}, "feed": {"age": 1.0, "revoked_tokens": 0, "disabled_managers": []},
            "open_streams": 0, "denials": []}
    url = answering(json.dumps(body).encode())
    r = CliRunner().invoke(status, ["--url", url])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (f"cryptoros status: error: {url} did not answer as an interceptor's /status "
                                "(certificate has no not_after, days_left): give its [listen] metrics "
                                "endpoint's /status")


ROS2_CONFIG = """\
manager = "robot_c"
roles = ["ros2"]
[tls]
ca = "ca.pem"
cert = "robot_c.pem"
key = "robot_c.key"
[authz]
url = "https://127.0.0.1:8443"
[listen]
public = "127.0.0.1:11400"
{metrics}
[ros2]
domain_id = 11
python = "no-such-venv/bin/python"
"""


@pytest.mark.parametrize("command", [status, denials], ids=["status", "denials"])
def test_a_ros2_configuration_without_the_bridges_python_here_still_finds_the_status(tmp_path, monkeypatch, command):
    monkeypatch.delenv("CRYPTOROS_ROS2_PYTHON", raising=False)
    port = _closed_port()
    for name in ("ca.pem", "robot_c.pem", "robot_c.key"):  # present: only the bridge's Python is not
        (tmp_path / name).write_text("")
    config = tmp_path / "robot_c.toml"
    config.write_text(ROS2_CONFIG.format(metrics=f'metrics = "127.0.0.1:{port}"'))
    r = CliRunner().invoke(command, ["--config", str(config)])
    assert r.exit_code == 2, r.output
    url = f"http://127.0.0.1:{port}/status"
    line = f"cryptoros {command.name}: error: cannot read {url}: [Errno 111] Connection refused"
    assert r.stderr.startswith(line) and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.parametrize(("metrics", "message"), [
    ("", "{config} has no [listen] metrics endpoint: status is served there"),
    ('metrics = "127.0.0.1"', "[listen] metrics: expected host:port, got '127.0.0.1'"),
    ('metrics = 9102', "[listen] metrics: expected host:port, got 9102"),
    ('metrics = "10.0.0.5:9102"', "[listen] metrics must be a loopback address"),
], ids=["none", "no-port", "not-a-string", "not-loopback"])
def test_a_configuration_without_a_usable_metrics_endpoint_is_one_line(tmp_path, metrics, message):
    config = tmp_path / "robot_c.toml"
    config.write_text(ROS2_CONFIG.format(metrics=metrics))
    r = CliRunner().invoke(status, ["--config", str(config)])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == f"cryptoros status: error: {message.format(config=config)}"


@pytest.mark.parametrize(("text", "message"), [
    ('[listen]\nmetrics = "127.0.0.1:9102"\n', "manager is required: the name of the manager whose token "
                                               "this interceptor holds"),
    ('manager = "robot_c"\nlisten = 3\n', "[listen] must be a table"),
    ("manager = \n", "invalid TOML"),
], ids=["no-manager", "listen-not-a-table", "bad-toml"])
def test_a_configuration_without_a_manager_or_readable_listen_is_one_line(tmp_path, text, message):
    config = tmp_path / "robot_c.toml"
    config.write_text(text)
    r = CliRunner().invoke(denials, ["--config", str(config)])
    assert r.exit_code == 2, r.output
    assert r.stderr.startswith("cryptoros denials: error: ") and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_a_missing_configuration_file_is_one_line(tmp_path):
    r = CliRunner().invoke(status, ["--config", str(tmp_path / "nowhere.toml")])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == f"cryptoros status: error: configuration file not found: {tmp_path / 'nowhere.toml'}"
